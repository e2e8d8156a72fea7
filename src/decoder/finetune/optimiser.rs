//! The loss and the optimiser of a fine-tuning run: the paper's gamma-corrected L2 loss, its
//! PSNR, and Adam as TensorFlow implements it, with the global-norm gradient clipping (module
//! docs).

use burn::tensor::Tensor;

use crate::decoder::unet::{tensor_values, UNet};
use crate::error::{DataCause, Error, Result};

use super::config::FinetuneConfig;

/// The paper's loss on NCHW tensors: `sqrt(mean((sqrt(max(y,0) + 1/255) - sqrt(x + 1/255))^2))`.
pub fn gamma_loss(y_hat: Tensor<4>, x: Tensor<4>) -> Tensor<1> {
    let e = 1.0 / 255.0;
    let d = (y_hat.clamp_min(0.0) + e).sqrt() - (x + e).sqrt();
    (d.clone() * d).mean().sqrt()
}

/// PSNR of a loss value in the sqrt domain, peak 1: `-20 log10 L`.
pub fn psnr_of_loss(loss: f64) -> f64 {
    -20.0 * loss.log10()
}

/// Adam (TensorFlow's form, see the module docs) over a [`UNet`]'s trainable tensors.
pub struct Adam {
    /// Step size of the next step before the bias corrections (the trainer sets it from
    /// [`FinetuneConfig::lr_at`] each step).
    pub lr: f64,
    /// First-moment decay rate `b1`.
    pub beta1: f64,
    /// Second-moment decay rate `b2`.
    pub beta2: f64,
    /// `eps`, added to `sqrt(v)` in the update's denominator.
    pub epsilon: f64,
    /// Steps taken (`t` of the bias corrections).
    pub t: usize,
    /// Which of the network's tensors are updated.
    pub(super) updates: Vec<bool>,
    /// Weight of the penalty on negative outputs (see [`FinetuneConfig::negative_penalty`]).
    pub negative_penalty: f64,
    /// Largest gradient norm a step takes (see [`FinetuneConfig::grad_clip`]; 0 = no limit).
    pub grad_clip: f64,
    /// The global norm of the last step's gradient before clipping (computed only when
    /// clipping is on).
    pub last_grad_norm: Option<f64>,
    /// First and second moments per checkpoint entry (`None` for frozen or not yet updated).
    pub(super) m: Vec<Option<Tensor<1>>>,
    pub(super) v: Vec<Option<Tensor<1>>>,
}

impl Adam {
    /// Fresh moments for `net`, hyper-parameters from `cfg`.
    pub fn new(net: &UNet, cfg: &FinetuneConfig) -> Adam {
        let n = net.params().len();
        Adam {
            lr: cfg.lr,
            beta1: cfg.beta1,
            beta2: cfg.beta2,
            epsilon: cfg.epsilon,
            t: 0,
            updates: net.names().iter().map(|n| cfg.updates(n)).collect(),
            negative_penalty: cfg.negative_penalty,
            grad_clip: cfg.grad_clip,
            last_grad_norm: None,
            m: vec![None; n],
            v: vec![None; n],
        }
    }

    /// Forward, the paper's loss, backward and one update of `net` for the NCHW batch `x`
    /// with targets `target` (on the network's device). Returns the loss before the update;
    /// a non-finite loss is an error and leaves `net` and the moments unchanged.
    pub fn step(&mut self, net: &mut UNet, x: Tensor<4>, target: Tensor<4>) -> Result<f64> {
        let leaves: Vec<Tensor<1>> = self
            .updates
            .iter()
            .zip(net.params())
            .map(|(&update, p)| {
                let t = p.clone().autodiff();
                if update {
                    t.require_grad()
                } else {
                    t
                }
            })
            .collect();
        let mut tracked = net.clone();
        tracked.set_params(leaves.clone());
        let y_hat = tracked.forward(x.autodiff())?;
        let mut loss = gamma_loss(y_hat.clone(), target.autodiff());
        if self.negative_penalty > 0.0 {
            let neg = y_hat.clamp_max(0.0);
            loss = loss + (neg.clone() * neg).mean() * self.negative_penalty as f32;
        }
        let value = tensor_values(loss.clone().inner())?[0] as f64;
        if !value.is_finite() {
            return Err(Error::data(DataCause::Diverged, format!("training loss is {value}")));
        }
        let grads = loss.backward();
        let grads: Vec<Option<Tensor<1>>> = leaves.iter().map(|leaf| leaf.grad(&grads)).collect();
        let scale = self.clip(&grads)?;
        let t = (self.t + 1) as i32;
        let (b1, b2) = (self.beta1, self.beta2);
        let lr_t = (self.lr * (1.0 - b2.powi(t)).sqrt() / (1.0 - b1.powi(t))) as f32;
        let mut params = Vec::with_capacity(leaves.len());
        for (i, (g, p)) in grads.into_iter().zip(net.params()).enumerate() {
            let Some(g) = g else {
                params.push(p.clone());
                continue;
            };
            let g = if scale < 1.0 { g * scale } else { g };
            let m = match self.m[i].take() {
                Some(m) => m * b1 as f32 + g.clone() * (1.0 - b1) as f32,
                None => g.clone() * (1.0 - b1) as f32,
            };
            let v = match self.v[i].take() {
                Some(v) => v * b2 as f32 + g.clone() * g * (1.0 - b2) as f32,
                None => g.clone() * g * (1.0 - b2) as f32,
            };
            params.push(p.clone() - m.clone() * lr_t / (v.clone().sqrt() + self.epsilon as f32));
            self.m[i] = Some(m);
            self.v[i] = Some(v);
        }
        net.set_params(params);
        self.t += 1;
        Ok(value)
    }

    /// The factor (at most 1) this step's gradients are scaled by: `grad_clip / |g|` where the
    /// global norm `|g| = sqrt(sum g^2)` exceeds `grad_clip`, else 1. The sum runs on the host
    /// in f64, element by element in a fixed order, so it does not depend on the backend or
    /// the thread count.
    fn clip(&mut self, grads: &[Option<Tensor<1>>]) -> Result<f32> {
        if self.grad_clip == 0.0 {
            return Ok(1.0);
        }
        let mut sum_sq = 0.0f64;
        for g in grads.iter().flatten() {
            sum_sq += tensor_values(g.clone())?.iter().map(|&v| f64::from(v) * f64::from(v)).sum::<f64>();
        }
        let norm = sum_sq.sqrt();
        if !norm.is_finite() {
            return Err(Error::data(DataCause::Diverged, format!("the gradient's norm is {norm}")));
        }
        self.last_grad_norm = Some(norm);
        Ok(if norm > self.grad_clip { (self.grad_clip / norm) as f32 } else { 1.0 })
    }
}
