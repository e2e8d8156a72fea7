//! Fine-tuning the decoder for one fixed PSF, as the paper refines its pretrained network for
//! the measured PSF of the fabricated DOE (Metzler et al. 2020, Sec. 5).
//!
//! Each step draws `batch` scenes of `crop + PSF margins` from a [`SceneSource`], flips each at
//! random (left-right, up-down), simulates its capture with [`measurement::measure`](super::measurement::measure) and takes one
//! Adam step on the paper's gamma-corrected L2 loss over the batch:
//!
//! `L = sqrt(mean((sqrt(max(y_hat, 0) + 1/255) - sqrt(x + 1/255))^2))`.
//!
//! Adam as TensorFlow implements it (Kingma & Ba 2015, Sec. 2, with the bias corrections folded
//! into the step size): `m <- b1 m + (1 - b1) g`, `v <- b2 v + (1 - b2) g^2`,
//! `p <- p - lr sqrt(1 - b2^t) / (1 - b1^t) m / (sqrt(v) + eps)`; lr 1e-4, betas 0.9 / 0.999,
//! eps 1e-8. BatchNorm statistics stay frozen (see [`crate::decoder::unet`]).
//!
//! With `grad_clip` `c > 0` a gradient whose global norm `|g| = sqrt(sum g^2)` exceeds `c` is
//! scaled to `c g / |g|` before Adam sees it (Pascanu et al. 2013, Sec. 3.2, Algorithm 2).
//!
//! Every `checkpoint_every` steps the network is evaluated on a fixed validation set (simulated
//! once from its own seed); its PSNR in the loss's sqrt domain, `-20 log10 L` (peak = the
//! clipping level), is logged. A non-finite training loss, or a validation loss above
//! `divergence` times the best one so far, stops the run with an error before anything is
//! written, so the checkpoint on disk is the last good one. Otherwise the checkpoint (decoder
//! tensors, Adam moments, step, generator state, history) is written atomically; resuming from
//! it replays the same batches, so N steps equal N/2 steps plus N/2 resumed, bit for bit.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::decoder::dataset::{training_and_validation, HdrScenes};
use crate::decoder::measurement::{measure, Halo, Measurement, MeasurementModel};
use crate::decoder::scenes::{GeneratedScenes, SceneSource};
use crate::decoder::unet::{is_trainable, tensor_values, UNet};
use crate::decoder::weights::{encode_safetensors, read_safetensors, DecoderWeights, NamedTensor};
use crate::decoder::{to_tensor, weights};
use crate::error::{Allowed, Error, Result};
use crate::image::Image;
use crate::io::atomic::write_bytes;
use crate::optics::convolve::Convolver;
use crate::optics::psf::Psf;
use crate::rng::Lcg;

/// A scene generator `f(seed, rows, cols)`.
pub type SceneGenerator = fn(u64, usize, usize) -> Image<f32>;

/// The seeded procedural HDR scenes
/// ([`procedural_scene`](crate::decoder::scenes::procedural_scene)) as a scene source.
pub fn procedural_scenes() -> GeneratedScenes<SceneGenerator> {
    GeneratedScenes { name: "procedural HDR scenes", generate: crate::decoder::scenes::procedural_scene }
}

/// A run's scenes: real HDR images with their validation images, or procedural scenes (which
/// validate on held-out seeds of their own).
pub enum TrainingScenes {
    Real { training: HdrScenes, validation: HdrScenes },
    Procedural(GeneratedScenes<SceneGenerator>),
}

impl TrainingScenes {
    /// The images of `data` as `finetune` takes them ([`training_and_validation`]: validated on
    /// `validation` or on 1 in `holdout_every` of them, panoramas narrower than
    /// `min_panorama_width` left out, colour jitter up to `white_balance`); procedural scenes
    /// without `data`.
    pub fn new(
        data: Option<&Path>,
        validation: Option<&Path>,
        holdout_every: usize,
        min_panorama_width: usize,
        white_balance: f64,
    ) -> Result<TrainingScenes> {
        if !(white_balance >= 1.0 && white_balance.is_finite()) {
            return Err(Error::param_in(
                "white_balance",
                Allowed::at_least(1.0),
                format!("{white_balance} must be finite and >= 1"),
            ));
        }
        Ok(match data {
            Some(dir) => {
                let (mut training, validation) =
                    training_and_validation(dir, validation, holdout_every, min_panorama_width)?;
                training.white_balance = white_balance;
                TrainingScenes::Real { training, validation }
            }
            None => TrainingScenes::Procedural(procedural_scenes()),
        })
    }

    /// Warnings about the images that could not be read (and were skipped).
    pub fn warnings(&self) -> Vec<String> {
        match self {
            TrainingScenes::Real { training, validation } => {
                training.skipped.iter().chain(&validation.skipped).cloned().collect()
            }
            TrainingScenes::Procedural(_) => Vec::new(),
        }
    }

    /// The training source and, for real images, the validation source ([`Trainer::new`]'s).
    pub fn sources(&self) -> (&dyn SceneSource, Option<&dyn SceneSource>) {
        match self {
            TrainingScenes::Real { training, validation } => (training, Some(validation)),
            TrainingScenes::Procedural(p) => (p, None),
        }
    }
}

/// Fine-tuning settings (defaults: the paper's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinetuneConfig {
    /// Total steps of the run (a resumed run continues to this count).
    pub steps: usize,
    pub batch: usize,
    /// Crop side, pixels (a multiple of 16).
    pub crop: usize,
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub epsilon: f64,
    /// Validate and checkpoint every this many steps (and at the end).
    pub checkpoint_every: usize,
    /// Size of the fixed validation set.
    pub validation: usize,
    pub seed: u64,
    /// Stop when the validation loss exceeds this factor times the best so far.
    pub divergence: f64,
    /// Gaussian read noise, fraction of the clipping level.
    pub noise_sigma: f64,
    /// Shot noise: variance `shot_noise * y` added to the read noise's (units of the clipping
    /// level; 0 = none).
    #[serde(default)]
    pub shot_noise: f64,
    /// Bit depth the simulated captures are quantised to (`None`: not quantised).
    #[serde(default)]
    pub bits: Option<u32>,
    /// L2-SP (Li et al. 2018): after each Adam step, trainable weights move toward the start
    /// weights by `lr * pull * (w - w0)` (a decoupled pull, as AdamW decouples its decay).
    #[serde(default)]
    pub pull: f64,
    /// Keep the encoder (`enc*` tensors) at its start weights.
    #[serde(default)]
    pub freeze_encoder: bool,
    /// Exponential step-size decay: `lr_t = lr * lr_decay^(t / 1000)` (1 = constant).
    #[serde(default = "one")]
    pub lr_decay: f64,
    /// Stop after this many validations without a new best (0 = never stop early).
    #[serde(default)]
    pub patience: usize,
    /// Weight `mu` of a penalty on negative outputs added to the training loss,
    /// `mu mean(min(y_hat, 0)^2)`: the paper's loss sees `max(y_hat, 0)` only, so nothing holds
    /// dark outputs above zero (0 = the paper's loss alone). Validation keeps the paper's loss.
    #[serde(default)]
    pub negative_penalty: f64,
    /// Weight-space blend of the decoder written: `w = w0 + blend (w_best - w0)` between the
    /// start weights `w0` and the best validated ones (WiSE-FT, Wortsman et al. 2022, Eq. 1;
    /// 1 = the best validated weights as they are). Simulated validation favours the fine-tuned
    /// end; real captures, which the simulation does not fully model, are scored best in
    /// between (README, fine-tuning table).
    #[serde(default = "one")]
    pub blend: f64,
    /// Where each channel of the simulated captures clips, fraction of full scale (see
    /// [`MeasurementModel::channel_clipping`]).
    #[serde(default = "full_scale")]
    pub channel_clipping: [f64; 3],
    /// Light the element spreads beyond its measured PSF's crop (see
    /// [`MeasurementModel::halo`]); `None`: none.
    #[serde(default)]
    pub halo: Option<Halo>,
    /// Gradient-norm clipping (Pascanu et al. 2013, Sec. 3.2): a step's gradient whose global
    /// norm exceeds `grad_clip` is scaled down to that norm (0 = no clipping). On the paper's
    /// real captures some batches of the first steps have norms of 10^3-10^4 where the others
    /// have 0.5-2 (simulated captures on which the start decoder writes strongly negative
    /// outputs, which the negative penalty squares), and Adam's second moment then holds the
    /// later steps back (README, the seed table).
    #[serde(default)]
    pub grad_clip: f64,
}

fn one() -> f64 {
    1.0
}

fn full_scale() -> [f64; 3] {
    [1.0; 3]
}

impl Default for FinetuneConfig {
    fn default() -> Self {
        FinetuneConfig {
            steps: 1000,
            batch: 8,
            crop: 320,
            lr: 1e-4,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            checkpoint_every: 100,
            validation: 8,
            seed: 1,
            divergence: 10.0,
            noise_sigma: 0.02,
            shot_noise: 0.0,
            bits: None,
            pull: 0.0,
            freeze_encoder: false,
            lr_decay: 1.0,
            patience: 0,
            negative_penalty: 0.0,
            blend: 1.0,
            channel_clipping: full_scale(),
            halo: None,
            grad_clip: 0.0,
        }
    }
}

/// `doefab finetune`'s steps (on the paper's real captures, longer runs drift in colour; README).
pub const STEPS: usize = 80;
/// Why a run handed over before [`STEPS`] steps may be worse than its start: on the paper's
/// real captures the decoder first falls, then rises above its start (README, Fine-tuning
/// against time). `None` when `steps` is at least [`STEPS`] or the written decoder is the start
/// itself (`best_step` 0).
pub fn short_run_warning(steps: usize, best_step: usize) -> Option<String> {
    (steps < STEPS && best_step > 0).then(|| {
        format!(
            "the decoder comes from a run of {steps} steps, fewer than the {STEPS} measured to lift the paper's \
             simulated-PSF decoder above its start on the paper's real captures: after 20 steps two seeds wrote \
             decoders 0.2 to 0.7 dB below their start on both scenes while their simulated validation rose; score it \
             on real captures with the decoder benchmark, without fine-tuning, before use"
        )
    })
}

/// `doefab finetune`'s batch and crop side, pixels (the crop well over the decoder's receptive
/// radius; 128 px crops, smaller than the 320 px PSF, lose on the real captures; README).
pub const BATCH: usize = 4;
pub const CROP: usize = 256;
/// `doefab finetune`'s validation cadence, steps, and validation set size, views.
pub const CHECKPOINT_EVERY: usize = 20;
pub const VALIDATION: usize = 16;
/// Read noise of `doefab finetune`'s simulated captures, fraction of full scale: measured on
/// the paper's captures (README, fine-tuning table; the paper trained with 0.02).
pub const READ_NOISE: f64 = 0.001;
/// Shot-noise variance per unit signal of `doefab finetune`'s captures, measured as above.
pub const SHOT_NOISE: f64 = 8e-5;
/// Bit depth of `doefab finetune`'s captures (the paper's captures are 8-bit).
pub const BITS: u32 = 8;
/// Where each channel of `doefab finetune`'s captures clips: as the paper's camera, whose green
/// tops out at 231 of 255 in every frame of both scenes ([`crate::calibration::clipping`]).
pub const CHANNEL_CLIPPING: [f64; 3] = [1.0, 231.0 / 255.0, 1.0];
/// `doefab finetune`'s halo: 5 % of the light in a Gaussian of 64 px beyond the measured PSF's
/// crop. `bench forward` finds 10-15 % at 64-128 px on the real captures; 0.05 at 64 px raised
/// the real-scene scores over the same seed without it on both scenes with each of three seeds
/// (saturated pixels +0.06 to +1.80 dB; README, the seed table).
pub const HALO: Halo = Halo { fraction: 0.05, radius_px: 64.0 };
/// `doefab finetune`'s negative-output penalty: with it the fine-tuned decoder scores above
/// its start on both of the paper's real scenes (README).
pub const NEGATIVE_PENALTY: f64 = 10.0;
/// `doefab finetune`'s weight-space blend: with [`GRAD_CLIP`], 0.25 keeps every channel's
/// balance within 5 % of the start's on the paper's real captures with each of three seeds,
/// where 0.5 moved it by 6-9 % with two of them (README, the seed table).
pub const BLEND: f64 = 0.25;
/// `doefab finetune`'s largest gradient norm: 2, above the usual 0.5-2 of a step and far below
/// the first steps' spikes (10^3-10^4). With it the real-scene scores rose over the run without
/// it with each of three seeds (README, the seed table).
pub const GRAD_CLIP: f64 = 2.0;

impl FinetuneConfig {
    /// `doefab finetune`'s settings, measured on the paper's real captures (README): the
    /// paper's optimiser with the captures' measured noise, bit depth, channel clipping and
    /// halo, the negative-output penalty, gradient clipping and the blend, 80 steps of 4
    /// crops 256 px a side,
    /// validated on 16 views every 20 steps.
    pub fn recommended() -> FinetuneConfig {
        FinetuneConfig {
            steps: STEPS,
            batch: BATCH,
            crop: CROP,
            checkpoint_every: CHECKPOINT_EVERY,
            validation: VALIDATION,
            noise_sigma: READ_NOISE,
            shot_noise: SHOT_NOISE,
            bits: Some(BITS),
            negative_penalty: NEGATIVE_PENALTY,
            blend: BLEND,
            channel_clipping: CHANNEL_CLIPPING,
            halo: Some(HALO),
            grad_clip: GRAD_CLIP,
            ..FinetuneConfig::default()
        }
    }

    fn check(&self) -> Result<()> {
        let bad = |n: &str, r: String| Err(Error::param(n, r));
        if self.crop == 0 || !self.crop.is_multiple_of(16) {
            return bad("crop", format!("{} is not a positive multiple of 16", self.crop));
        }
        if self.batch == 0 || self.checkpoint_every == 0 || self.validation == 0 {
            return bad("batch", "batch, checkpoint interval and validation size must be at least 1".into());
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            return bad("lr", format!("{} is not a positive step size", self.lr));
        }
        if !(0.0..1.0).contains(&self.beta1) || !(0.0..1.0).contains(&self.beta2) {
            return bad("betas", format!("{} / {} must lie in [0, 1)", self.beta1, self.beta2));
        }
        if self.divergence <= 1.0 {
            return bad("divergence", format!("{} must exceed 1", self.divergence));
        }
        if !(self.pull >= 0.0 && self.pull.is_finite()) {
            return bad("pull", format!("{} must be finite and >= 0", self.pull));
        }
        if !(self.negative_penalty >= 0.0 && self.negative_penalty.is_finite()) {
            return bad("negative_penalty", format!("{} must be finite and >= 0", self.negative_penalty));
        }
        if !(self.blend > 0.0 && self.blend <= 1.0) {
            return bad("blend", format!("{} must lie in (0, 1]", self.blend));
        }
        if !(self.lr_decay > 0.0 && self.lr_decay <= 1.0) {
            return bad("lr_decay", format!("{} must lie in (0, 1]", self.lr_decay));
        }
        if !(self.shot_noise >= 0.0 && self.noise_sigma >= 0.0) {
            return bad(
                "noise",
                format!("read {} and shot {} must be >= 0", self.noise_sigma, self.shot_noise),
            );
        }
        if !self.channel_clipping.iter().all(|c| *c > 0.0 && *c <= 1.0) {
            return bad("channel_clipping", format!("{:?}: each must lie in (0, 1]", self.channel_clipping));
        }
        if let Some(h) = &self.halo {
            h.check()?;
        }
        if !(self.grad_clip >= 0.0 && self.grad_clip.is_finite()) {
            return bad("grad_clip", format!("{} must be finite and >= 0 (0: no clipping)", self.grad_clip));
        }
        if self.bits.is_some_and(|b| !(1..=16).contains(&b)) {
            return bad("bits", format!("{:?} must lie in 1..=16", self.bits));
        }
        Ok(())
    }

    fn model(&self) -> MeasurementModel {
        MeasurementModel {
            noise_sigma: self.noise_sigma,
            shot_noise: self.shot_noise,
            bits: self.bits,
            channel_clipping: self.channel_clipping.map(|c| c as f32),
            halo: self.halo,
            ..MeasurementModel::default()
        }
    }

    /// The step size of step `t` (1-based): `lr * lr_decay^(t / 1000)`.
    pub fn lr_at(&self, t: usize) -> f64 {
        self.lr * self.lr_decay.powf(t as f64 / 1000.0)
    }

    /// Whether the tensor `name` is updated: not a BatchNorm statistic, not a frozen encoder.
    pub fn updates(&self, name: &str) -> bool {
        is_trainable(name) && !(self.freeze_encoder && name.starts_with("enc"))
    }
}

/// One logged point of the training curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HistoryEntry {
    pub step: usize,
    /// Training loss of this step's batch (before its update); none at step 0.
    pub loss: Option<f64>,
    /// Validation loss and PSNR (sqrt domain, dB) after this step, at evaluations.
    pub val_loss: Option<f64>,
    pub val_psnr: Option<f64>,
    /// The global norm of this step's gradient before clipping (recorded only with clipping on).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grad_norm: Option<f64>,
}

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
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub epsilon: f64,
    /// Steps taken (`t` of the bias corrections).
    pub t: usize,
    /// Which of the network's tensors are updated.
    updates: Vec<bool>,
    /// Weight of the penalty on negative outputs (see [`FinetuneConfig::negative_penalty`]).
    pub negative_penalty: f64,
    /// Largest gradient norm a step takes (see [`FinetuneConfig::grad_clip`]; 0 = no limit).
    pub grad_clip: f64,
    /// The global norm of the last step's gradient before clipping (computed only when
    /// clipping is on).
    pub last_grad_norm: Option<f64>,
    /// First and second moments per checkpoint entry (`None` for frozen or not yet updated).
    m: Vec<Option<Tensor<1>>>,
    v: Vec<Option<Tensor<1>>>,
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
            return Err(Error::Data(format!("training loss is {value}")));
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
            return Err(Error::Data(format!("the gradient's norm is {norm}")));
        }
        self.last_grad_norm = Some(norm);
        Ok(if norm > self.grad_clip { (self.grad_clip / norm) as f32 } else { 1.0 })
    }
}

/// `count` simulated training captures of `crop x crop`, their scenes (the crop plus `conv`'s
/// margins) drawn from `source` with `rng`, flipped at random and simulated with
/// [`measure`] (seeds drawn in order, the simulations run in parallel, so the result does not
/// depend on the thread count). All on the CPU.
pub fn simulate_captures(
    source: &dyn SceneSource,
    conv: &Convolver,
    model: &MeasurementModel,
    crop: usize,
    rng: &mut Lcg,
    count: usize,
) -> Result<Vec<Measurement>> {
    let (t, l, b, r) = conv.margins();
    let (rows, cols) = (crop + t + b, crop + l + r);
    let seeds: Vec<u64> = (0..count).map(|_| (rng.uniform() * (1u64 << 53) as f64) as u64).collect();
    seeds
        .par_iter()
        .map(|&seed| {
            let mut g = Lcg(seed);
            let mut scene = source.scene(&mut g, rows, cols)?.values;
            if scene.dim() != (rows, cols, 3) {
                return Err(Error::Data(format!(
                    "the scene source gave {:?}, not {rows} x {cols} x 3",
                    scene.dim()
                )));
            }
            if g.uniform() < 0.5 {
                scene.invert_axis(ndarray::Axis(1));
            }
            if g.uniform() < 0.5 {
                scene.invert_axis(ndarray::Axis(0));
            }
            measure(&Image::new(scene.as_standard_layout().to_owned()), conv, model, &mut g)
        })
        .collect()
}

/// A fine-tuning run in memory.
pub struct Trainer<'a> {
    cfg: FinetuneConfig,
    net: UNet,
    adam: Adam,
    step: usize,
    rng: Lcg,
    history: Vec<HistoryEntry>,
    best_val: f64,
    conv: Convolver,
    source: &'a dyn SceneSource,
    validation: Vec<Measurement>,
    /// What the validation set was simulated from.
    validation_data: String,
    psf_sha256: String,
    init: String,
    /// The start weights (the pull of L2-SP) and the best validated ones, with their step.
    start: Vec<Tensor<1>>,
    best: Vec<Tensor<1>>,
    best_step: usize,
    /// Validations since the last new best.
    stale: usize,
    /// The next step's batch, simulated while the current step ran, with the generator's
    /// state after it (see [`Trainer::train_step`]).
    prefetched: Option<(Lcg, Result<Vec<Measurement>>)>,
}

/// What one step reports to the caller (for a progress bar).
#[derive(Debug, Clone, PartialEq)]
pub struct StepStats {
    pub step: usize,
    pub steps: usize,
    pub loss: f64,
    pub val_psnr: Option<f64>,
}

impl<'a> Trainer<'a> {
    /// Starts a run from `net`. `psf_sha256` and `init` (the initial decoder's description)
    /// are recorded in the outputs. The validation set is simulated from `validation`
    /// (held-out images) or, without it, from `source` with a seed of its own.
    pub fn new(
        net: UNet,
        psf: &Psf,
        psf_sha256: &str,
        source: &'a dyn SceneSource,
        validation: Option<&dyn SceneSource>,
        cfg: FinetuneConfig,
        init: &str,
    ) -> Result<Trainer<'a>> {
        let mut t = Trainer::prepared(net, psf, psf_sha256, source, validation, cfg, init)?;
        let v0 = t.validation_loss()?;
        t.check_validation(v0)?;
        t.history.push(HistoryEntry {
            step: 0,
            loss: None,
            val_loss: Some(v0),
            val_psnr: Some(psnr_of_loss(v0)),
            grad_norm: None,
        });
        Ok(t)
    }

    /// The run's state before any validation: network, optimiser and the validation set.
    fn prepared(
        net: UNet,
        psf: &Psf,
        psf_sha256: &str,
        source: &'a dyn SceneSource,
        validation: Option<&dyn SceneSource>,
        cfg: FinetuneConfig,
        init: &str,
    ) -> Result<Trainer<'a>> {
        cfg.check()?;
        if psf.channels.len() != 3 {
            return Err(Error::param(
                "psf",
                format!("has {} channels; the decoder needs RGB", psf.channels.len()),
            ));
        }
        let (kh, kw) = psf.dim();
        let conv = Convolver::new(psf, (cfg.crop + kh - 1, cfg.crop + kw - 1))?;
        let start = net.params().to_vec();
        let val_source = validation.unwrap_or(source);
        let mut t = Trainer {
            rng: Lcg(cfg.seed),
            adam: Adam::new(&net, &cfg),
            cfg,
            net,
            step: 0,
            history: Vec::new(),
            best_val: f64::INFINITY,
            conv,
            source,
            validation: Vec::new(),
            validation_data: val_source.describe(),
            psf_sha256: psf_sha256.into(),
            init: init.into(),
            best: start.clone(),
            start,
            best_step: 0,
            stale: 0,
            prefetched: None,
        };
        t.validation =
            t.simulate_batch(val_source, &mut Lcg(t.cfg.seed ^ 0x5eed_0000_7a11_da7e), t.cfg.validation)?;
        Ok(t)
    }

    /// Continues the run saved in `checkpoint`, to `steps` total steps, with step size `lr`
    /// (`None`: the saved one). The PSF and the data must be the ones the run started with.
    #[allow(clippy::too_many_arguments)]
    pub fn resume(
        checkpoint: &Path,
        psf: &Psf,
        psf_sha256: &str,
        source: &'a dyn SceneSource,
        validation: Option<&dyn SceneSource>,
        steps: usize,
        lr: Option<f64>,
        device: &burn::tensor::Device,
    ) -> Result<Trainer<'a>> {
        let (mut tensors, meta) = read_safetensors(checkpoint)?;
        let field = |k: &str| {
            meta.get(k)
                .ok_or_else(|| Error::signature(checkpoint, format!("not a checkpoint: no '{k}' metadata")))
        };
        let parse_err = |k: &str, e: String| Error::malformed(checkpoint, format!("metadata '{k}': {e}"));
        if field("psf_sha256")? != psf_sha256 {
            return Err(Error::param(
                "psf",
                format!(
                    "its SHA-256 {psf_sha256} differs from the one the checkpoint was trained with ({})",
                    field("psf_sha256")?
                ),
            ));
        }
        let mut cfg: FinetuneConfig =
            serde_json::from_str(field("config")?).map_err(|e| parse_err("config", e.to_string()))?;
        let step: usize = field("checkpoint_step")?
            .parse()
            .map_err(|e: std::num::ParseIntError| parse_err("checkpoint_step", e.to_string()))?;
        let rng: u64 = field("rng_state")?
            .parse()
            .map_err(|e: std::num::ParseIntError| parse_err("rng_state", e.to_string()))?;
        let history: Vec<HistoryEntry> =
            serde_json::from_str(field("history")?).map_err(|e| parse_err("history", e.to_string()))?;
        let best_val: f64 = field("best_val_loss")?
            .parse()
            .map_err(|e: std::num::ParseFloatError| parse_err("best_val_loss", e.to_string()))?;
        let init = field("init")?.clone();
        let best_step: usize = field("best_step")?
            .parse()
            .map_err(|e: std::num::ParseIntError| parse_err("best_step", e.to_string()))?;
        let stale: usize = field("stale")?
            .parse()
            .map_err(|e: std::num::ParseIntError| parse_err("stale", e.to_string()))?;
        let mut moments = BTreeMap::new();
        tensors.retain(|name, t| {
            if ["adam.", "best.", "start."].iter().any(|p| name.starts_with(p)) {
                moments.insert(name.clone(), t.clone());
                false
            } else {
                true
            }
        });
        let weights = DecoderWeights::from_map(checkpoint, tensors, BTreeMap::new())?;
        let net = UNet::from_weights(&weights, device);
        cfg.steps = steps;
        if let Some(lr) = lr {
            cfg.lr = lr;
        }
        let mut t = Trainer::prepared(net, psf, psf_sha256, source, validation, cfg, &init)?;
        let mut take = |key: String| {
            let mt = moments
                .remove(&key)
                .ok_or_else(|| Error::malformed(checkpoint, format!("checkpoint lacks tensor '{key}'")))?;
            let n = mt.values.len();
            Ok::<_, Error>(Tensor::<1>::from_data(TensorData::new(mt.values, [n]), device))
        };
        for (i, name) in weights::tensor_specs().iter().map(|(n, _)| n).enumerate() {
            t.best[i] = take(format!("best.{name}"))?;
            t.start[i] = take(format!("start.{name}"))?;
            if !is_trainable(name) {
                continue;
            }
            t.adam.m[i] = Some(take(format!("adam.m.{name}"))?);
            t.adam.v[i] = Some(take(format!("adam.v.{name}"))?);
        }
        t.best_step = best_step;
        t.stale = stale;
        t.step = step;
        t.adam.t = step;
        t.rng = Lcg(rng);
        t.history = history;
        t.best_val = best_val;
        Ok(t)
    }

    pub fn step(&self) -> usize {
        self.step
    }

    pub fn history(&self) -> &[HistoryEntry] {
        &self.history
    }

    pub fn config(&self) -> &FinetuneConfig {
        &self.cfg
    }

    /// `count` simulated captures of this run's crops ([`simulate_captures`]).
    fn simulate_batch(
        &self,
        source: &dyn SceneSource,
        rng: &mut Lcg,
        count: usize,
    ) -> Result<Vec<Measurement>> {
        simulate_captures(source, &self.conv, &self.cfg.model(), self.cfg.crop, rng, count)
    }

    fn tensors(&self, batch: &[Measurement], device: &burn::tensor::Device) -> (Tensor<4>, Tensor<4>) {
        let caps: Vec<&Image<f32>> = batch.iter().map(|m| &m.capture).collect();
        let tgts: Vec<&Image<f32>> = batch.iter().map(|m| &m.target).collect();
        (to_tensor(&caps, device), to_tensor(&tgts, device))
    }

    /// The loss over the validation set (evaluated in chunks of the batch size).
    pub fn validation_loss(&self) -> Result<f64> {
        self.validation_loss_of(&self.net)
    }

    fn validation_loss_of(&self, net: &UNet) -> Result<f64> {
        let mut sum_sq = 0.0;
        let mut count = 0usize;
        for chunk in self.validation.chunks(self.cfg.batch) {
            let (x, t) = self.tensors(chunk, net.device());
            let l = tensor_values(gamma_loss(net.forward(x)?, t))?[0] as f64;
            let n = chunk.len();
            sum_sq += l * l * n as f64;
            count += n;
        }
        Ok((sum_sq / count as f64).sqrt())
    }

    fn check_validation(&mut self, val: f64) -> Result<()> {
        if !val.is_finite() {
            return Err(Error::Data(format!("validation loss is {val} after step {}; stopped", self.step)));
        }
        if val > self.cfg.divergence * self.best_val {
            return Err(Error::Data(format!(
                "training diverged: validation loss {val:.4} after step {} exceeds {} x the best {:.4}; stopped",
                self.step, self.cfg.divergence, self.best_val
            )));
        }
        self.best_val = self.best_val.min(val);
        Ok(())
    }

    /// One Adam step on a fresh batch (then the L2-SP pull, when set); returns the batch's
    /// loss (before the update).
    ///
    /// The next step's batch is simulated on the CPU while this step runs (on a GPU the step
    /// would otherwise wait for it). It is drawn from the generator's state after this step's
    /// batch, exactly as the next step would draw it, so a run's batches, and with them its
    /// weights, do not depend on the prefetching (tested against steps without it).
    pub fn train_step(&mut self) -> Result<f64> {
        let (rng, batch) = match self.prefetched.take() {
            Some((rng, batch)) => (rng, batch?),
            None => {
                let mut rng = self.rng.clone();
                let batch = self.simulate_batch(self.source, &mut rng, self.cfg.batch)?;
                (rng, batch)
            }
        };
        let (x, target) = self.tensors(&batch, &self.net.device().clone());
        self.adam.lr = self.cfg.lr_at(self.step + 1);
        let (source, conv, model, crop, count) =
            (self.source, &self.conv, self.cfg.model(), self.cfg.crop, self.cfg.batch);
        let prefetch = self.step + 1 < self.cfg.steps;
        let (stepped, next) = std::thread::scope(|scope| {
            let next = prefetch.then(|| {
                let mut rng = rng.clone();
                scope.spawn(move || {
                    let batch = simulate_captures(source, conv, &model, crop, &mut rng, count);
                    (rng, batch)
                })
            });
            let stepped = self.adam.step(&mut self.net, x, target);
            (stepped, next.map(|handle| handle.join()))
        });
        self.prefetched = match next {
            Some(Ok(next)) => Some(next),
            Some(Err(panic)) => std::panic::resume_unwind(panic),
            None => None,
        };
        let value = stepped.map_err(|e| match e {
            Error::Data(m) => Error::Data(format!("{m} at step {}; stopped", self.step + 1)),
            other => other,
        })?;
        if self.cfg.pull > 0.0 {
            let k = (self.adam.lr * self.cfg.pull) as f32;
            let pulled = self
                .net
                .params()
                .iter()
                .zip(&self.start)
                .zip(&self.adam.updates)
                .map(
                    |((p, p0), &update)| {
                        if update {
                            p.clone() - (p.clone() - p0.clone()) * k
                        } else {
                            p.clone()
                        }
                    },
                )
                .collect();
            self.net.set_params(pulled);
        }
        self.step += 1;
        self.rng = rng;
        self.history.push(HistoryEntry {
            step: self.step,
            loss: Some(value),
            val_loss: None,
            val_psnr: None,
            grad_norm: self.adam.last_grad_norm,
        });
        Ok(value)
    }

    /// Evaluates on the validation set, logs it, checks for divergence and keeps the weights
    /// when they are the best validated so far.
    pub fn evaluate(&mut self) -> Result<f64> {
        let val = self.validation_loss()?;
        let improved = val < self.best_val;
        self.check_validation(val)?;
        if improved {
            self.best = self.net.params().to_vec();
            self.best_step = self.step;
            self.stale = 0;
        } else {
            self.stale += 1;
        }
        if let Some(last) = self.history.last_mut().filter(|h| h.step == self.step) {
            last.val_loss = Some(val);
            last.val_psnr = Some(psnr_of_loss(val));
        }
        Ok(psnr_of_loss(val))
    }

    /// The step whose weights validated best (0: the start) and its validation loss.
    pub fn best(&self) -> (usize, f64) {
        (self.best_step, self.best_val)
    }

    /// The decoder `write_outputs` writes (see [`Trainer::decoder`]): the best validated
    /// weights blended with the start's by `blend` (see [`FinetuneConfig::blend`]), and its
    /// validation loss. Should the blend validate worse than the start (it lies between the
    /// start and the best, so it seldom can), the best validated weights are written instead,
    /// so the decoder written never validates below its start.
    pub fn written_decoder(&self) -> Result<(DecoderWeights, Written)> {
        let mut net = self.net.clone();
        net.set_params(self.best.clone());
        let mut val = self.best_val;
        let mut blend = 1.0;
        if self.cfg.blend < 1.0 && self.best_step > 0 {
            let b = self.cfg.blend as f32;
            let mut blended = net.clone();
            blended.set_params(
                self.start
                    .iter()
                    .zip(&self.best)
                    .map(|(w0, w)| w0.clone() + (w.clone() - w0.clone()) * b)
                    .collect(),
            );
            let v = self.validation_loss_of(&blended)?;
            let start_val = self.history.iter().find(|h| h.step == 0).and_then(|h| h.val_loss);
            if start_val.is_none_or(|s| v <= s) {
                (net, val, blend) = (blended, v, self.cfg.blend);
            }
        }
        let mut w = self.decoder_of(&net)?;
        w.metadata.insert("best_step".into(), self.best_step.to_string());
        w.metadata.insert("best_validation_loss".into(), format!("{:e}", self.best_val));
        w.metadata.insert("blend".into(), blend.to_string());
        w.metadata.insert("validation_loss".into(), format!("{val:e}"));
        Ok((w, Written { blend, validation_loss: val }))
    }

    /// The current decoder with its training record in the metadata.
    pub fn decoder(&self) -> Result<DecoderWeights> {
        self.decoder_of(&self.net)
    }

    fn decoder_of(&self, net: &UNet) -> Result<DecoderWeights> {
        let mut w = net.to_weights()?;
        let last_loss = self.history.iter().rev().find_map(|h| h.loss);
        let last_val = self.history.iter().rev().find_map(|h| h.val_loss);
        w.metadata = BTreeMap::from([
            ("model".into(), "DeepOpticsHDR my_medium_model (is_training=False, log_domain=False)".into()),
            ("psf_sha256".into(), self.psf_sha256.clone()),
            ("init".into(), self.init.clone()),
            ("training_steps".into(), self.step.to_string()),
            ("training_data".into(), self.source.describe()),
            ("validation_data".into(), self.validation_data.clone()),
            ("final_loss".into(), last_loss.map_or("none".into(), |l| format!("{l:.6e}"))),
            ("final_validation_loss".into(), last_val.map_or("none".into(), |l| format!("{l:.6e}"))),
            (
                "loss".into(),
                "sqrt(mean((sqrt(max(y_hat,0)+1/255) - sqrt(x+1/255))^2)) per batch; values relative to the sensor \
                 clipping level"
                    .into(),
            ),
            ("config".into(), serde_json::to_string(&self.cfg).map_err(|e| Error::Data(e.to_string()))?),
        ]);
        Ok(w)
    }

    /// Writes the checkpoint (decoder, Adam moments, step, generator state, history) atomically.
    pub fn write_checkpoint(&self, path: &Path) -> Result<()> {
        let w = self.decoder()?;
        let mut meta = w.metadata.clone();
        meta.insert("checkpoint_step".into(), self.step.to_string());
        meta.insert("rng_state".into(), self.rng.0.to_string());
        meta.insert("best_val_loss".into(), format!("{:e}", self.best_val));
        meta.insert("best_step".into(), self.best_step.to_string());
        meta.insert("stale".into(), self.stale.to_string());
        meta.insert(
            "history".into(),
            serde_json::to_string(&self.history).map_err(|e| Error::Data(e.to_string()))?,
        );
        let mut owned: Vec<(String, NamedTensor)> = w.tensors.clone();
        for (i, name) in self.net.names().iter().enumerate() {
            for (which, t) in [("best", &self.best[i]), ("start", &self.start[i])] {
                let values = tensor_values(t.clone())?;
                owned.push((format!("{which}.{name}"), NamedTensor { shape: vec![values.len()], values }));
            }
            for (which, slot) in [("m", &self.adam.m[i]), ("v", &self.adam.v[i])] {
                if let Some(t) = slot {
                    let values = tensor_values(t.clone())?;
                    owned.push((
                        format!("adam.{which}.{name}"),
                        NamedTensor { shape: vec![values.len()], values },
                    ));
                } else if is_trainable(name) {
                    let n = self.net.params()[i].dims()[0];
                    owned.push((
                        format!("adam.{which}.{name}"),
                        NamedTensor { shape: vec![n], values: vec![0.0; n] },
                    ));
                }
            }
        }
        let refs: Vec<(&str, &NamedTensor)> = owned.iter().map(|(n, t)| (n.as_str(), t)).collect();
        write_bytes(path, &encode_safetensors(&refs, &meta))
    }

    /// Runs to the configured step count, validating and checkpointing into `out` every
    /// `checkpoint_every` steps and at the end; `on_step` sees every step. With `patience`
    /// set, stops early after that many validations without a new best.
    pub fn run(&mut self, out: &Path, on_step: &mut dyn FnMut(&StepStats)) -> Result<()> {
        std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
        while self.step < self.cfg.steps {
            let loss = self.train_step()?;
            let mut val_psnr = None;
            if self.step.is_multiple_of(self.cfg.checkpoint_every) || self.step == self.cfg.steps {
                val_psnr = Some(self.evaluate()?);
                self.write_checkpoint(&out.join(CHECKPOINT))?;
            }
            on_step(&StepStats { step: self.step, steps: self.cfg.steps, loss, val_psnr });
            if self.stopped_early() {
                break;
            }
        }
        Ok(())
    }

    /// Whether `patience` validations have passed without a new best.
    pub fn stopped_early(&self) -> bool {
        self.cfg.patience > 0 && self.stale >= self.cfg.patience
    }

    /// Writes the final outputs into `out`: [`DECODER`] (the blended best validated decoder,
    /// see [`Trainer::written_decoder`]; the start decoder itself when no step validated
    /// better, with its training record) and `training.json` (configuration and curve); the
    /// curve's chart, `training_curve.png`, is drawn by the commands
    /// ([`crate::charts::training::write_training_chart`]).
    pub fn write_outputs(&self, out: &Path) -> Result<Written> {
        let (decoder, written) = self.written_decoder()?;
        decoder.write(&out.join(DECODER))?;
        let record = serde_json::json!({
            "config": self.cfg,
            "steps": self.step,
            "stopped_early": self.stopped_early(),
            "best_step": self.best_step,
            "best_validation_loss": self.best_val,
            "best_validation_psnr": psnr_of_loss(self.best_val),
            "blend": written.blend,
            "written_validation_psnr": psnr_of_loss(written.validation_loss),
            "psf_sha256": self.psf_sha256,
            "init": self.init,
            "data": self.source.describe(),
            "validation_data": self.validation_data,
            "loss_units": "sqrt domain, relative to the sensor clipping level; PSNR in dB with peak 1",
            "history": self.history,
        });
        crate::io::atomic::write_json(&out.join("training.json"), &record)?;
        Ok(written)
    }
}

/// The decoder a run wrote: its blend with the start (1 = the best validated weights) and its
/// validation loss.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Written {
    pub blend: f64,
    pub validation_loss: f64,
}

/// File name of the fine-tuned decoder inside the output folder.
pub const DECODER: &str = "decoder.safetensors";

/// File name of the checkpoint inside the output folder.
pub const CHECKPOINT: &str = "checkpoint.safetensors";

/// A `doefab finetune` run: the PSF, the data and the configuration.
#[derive(Debug, Clone)]
pub struct FinetuneJob {
    /// The PSF file (`.npz` with `psf_key`, or `.npy`) at pixel `pitch`, metres.
    pub psf: PathBuf,
    pub psf_key: Option<String>,
    pub pitch: f64,
    /// The start decoder (`None`: [`crate::decoder::default_init`]).
    pub init: Option<PathBuf>,
    /// Real HDR training images (see [`crate::decoder::dataset`]); `None`: procedural scenes.
    pub data: Option<PathBuf>,
    /// Validation images (`None`: held out from `data` by name, 1 in `holdout_every`).
    pub validation_data: Option<PathBuf>,
    pub holdout_every: usize,
    /// Panoramas narrower than this are not used (see [`crate::decoder::dataset`]).
    pub min_panorama_width: usize,
    /// Largest white-balance gain of the training views' colour jitter
    /// ([`crate::decoder::dataset::HdrScenes::white_balance`]).
    pub white_balance: f64,
    pub output: PathBuf,
    /// Continue the checkpoint in `output` (to `cfg.steps`, at `lr` when given).
    pub resume: bool,
    pub lr: Option<f64>,
    pub cfg: FinetuneConfig,
    pub gpu: bool,
}

/// What a finetune run did (the `--json` output of `doefab finetune`).
#[derive(Debug, Clone, Serialize)]
pub struct FinetuneOutcome {
    pub output: PathBuf,
    pub decoder: PathBuf,
    pub steps: usize,
    pub stopped_early: bool,
    /// The step the written decoder comes from (0: no step validated better than the start).
    pub best_step: usize,
    pub start_validation_psnr: Option<f64>,
    pub best_validation_psnr: f64,
    /// The written decoder's blend (see [`FinetuneConfig::blend`]) and validation PSNR.
    pub blend: f64,
    pub written_validation_psnr: f64,
    pub data: String,
    pub validation_data: String,
    pub history: Vec<HistoryEntry>,
    /// Why the written decoder may be worse than its start ([`short_run_warning`]).
    pub warnings: Vec<String>,
}

/// Runs a fine-tuning job into `job.output` (see the module docs): `on_step` sees every
/// step. A run that stops on an error leaves the last good checkpoint and says so.
pub fn run_job(job: &FinetuneJob, on_step: &mut dyn FnMut(&StepStats)) -> Result<FinetuneOutcome> {
    let psf = Psf::read(&job.psf, job.psf_key.as_deref(), Some(job.pitch))?;
    let psf_sha = crate::io::file_sha256(&job.psf)?;
    let scenes = TrainingScenes::new(
        job.data.as_deref(),
        job.validation_data.as_deref(),
        job.holdout_every,
        job.min_panorama_width,
        job.white_balance,
    )?;
    let (source, validation) = scenes.sources();
    let selected = crate::decoder::select_device(job.gpu)?;
    let device = selected.device;
    let mut trainer = if job.resume {
        let ckpt = job.output.join(CHECKPOINT);
        let mut t =
            Trainer::resume(&ckpt, &psf, &psf_sha, source, validation, job.cfg.steps, job.lr, &device)?;
        t.cfg.blend = job.cfg.blend;
        t
    } else {
        let init = job.init.clone().unwrap_or_else(crate::decoder::default_init);
        let weights = DecoderWeights::read(&init)?;
        let net = UNet::from_weights(&weights, &device);
        let desc = format!("{} (sha256 {})", init.display(), crate::decoder::weights::decoder_sha256(&init)?);
        let cfg = FinetuneConfig { lr: job.lr.unwrap_or(job.cfg.lr), ..job.cfg.clone() };
        Trainer::new(net, &psf, &psf_sha, source, validation, cfg, &desc)?
    };
    if let Err(e) = trainer.run(&job.output, on_step) {
        let ckpt = job.output.join(CHECKPOINT);
        return Err(match ckpt.exists() {
            true => Error::Data(format!("{e}; the last good checkpoint is {}", ckpt.display())),
            false => e,
        });
    }
    let written = trainer.write_outputs(&job.output)?;
    let (best_step, best_val) = trainer.best();
    Ok(FinetuneOutcome {
        output: job.output.clone(),
        decoder: job.output.join(DECODER),
        steps: trainer.step(),
        stopped_early: trainer.stopped_early(),
        best_step,
        start_validation_psnr: trainer.history().iter().find(|h| h.step == 0).and_then(|h| h.val_psnr),
        best_validation_psnr: psnr_of_loss(best_val),
        blend: written.blend,
        written_validation_psnr: psnr_of_loss(written.validation_loss),
        data: source.describe(),
        validation_data: trainer.validation_data.clone(),
        history: trainer.history().to_vec(),
        warnings: selected
            .warnings
            .into_iter()
            .chain(scenes.warnings())
            .chain(short_run_warning(trainer.step(), best_step))
            .collect(),
    })
}
