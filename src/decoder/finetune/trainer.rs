//! The fine-tuning loop ([`Trainer`]): the captures simulated for each batch, one Adam step on
//! the batch, the validation that stops a diverging run, and the history of the steps.

use std::collections::BTreeMap;
use std::path::Path;

use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::decoder::measurement::{measure, Measurement, MeasurementModel};
use crate::decoder::runtime::to_tensor;
use crate::decoder::scenes::SceneSource;
use crate::decoder::unet::{is_trainable, tensor_values, UNet};
use crate::decoder::weights;
use crate::decoder::weights::{read_safetensors, DecoderWeights};
use crate::error::{DataCause, Error, Result};
use crate::image::Image;
use crate::optics::convolve::Convolver;
use crate::optics::psf::Psf;
use crate::rng::Lcg;

use super::config::FinetuneConfig;
use super::optimiser::{gamma_loss, psnr_of_loss, Adam};

/// One logged point of the training curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HistoryEntry {
    /// Steps taken (0: the start, before any step).
    pub step: usize,
    /// Training loss of this step's batch (before its update, with the negative-output penalty
    /// when set); none at step 0.
    pub loss: Option<f64>,
    /// Validation loss after this step (the paper's loss, sqrt domain, relative to the clipping
    /// level); `None` between evaluations.
    pub val_loss: Option<f64>,
    /// Validation PSNR after this step, dB (`-20 log10 val_loss`); `None` between evaluations.
    pub val_psnr: Option<f64>,
    /// The global norm of this step's gradient before clipping (recorded only with clipping on).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grad_norm: Option<f64>,
}

/// `count` simulated training captures of `crop x crop`, their scenes (the crop plus `conv`'s
/// margins) drawn from `source` with `rng`, flipped at random and simulated with
/// `measure` (seeds drawn in order, the simulations run in parallel, so the result does not
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
                return Err(Error::data(
                    DataCause::Shape,
                    format!("the scene source gave {:?}, not {rows} x {cols} x 3", scene.dim()),
                ));
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
    pub(super) cfg: FinetuneConfig,
    pub(super) net: UNet,
    pub(super) adam: Adam,
    pub(super) step: usize,
    pub(super) rng: Lcg,
    pub(super) history: Vec<HistoryEntry>,
    pub(super) best_val: f64,
    conv: Convolver,
    pub(super) source: &'a dyn SceneSource,
    validation: Vec<Measurement>,
    /// What the validation set was simulated from.
    pub(super) validation_data: String,
    pub(super) psf_sha256: String,
    pub(super) init: String,
    /// The start weights (the pull of L2-SP) and the best validated ones, with their step.
    pub(super) start: Vec<Tensor<1>>,
    pub(super) best: Vec<Tensor<1>>,
    pub(super) best_step: usize,
    /// Validations since the last new best.
    pub(super) stale: usize,
    /// The next step's batch, simulated while the current step ran, with the generator's
    /// state after it (see [`Trainer::train_step`]).
    prefetched: Option<(Lcg, Result<Vec<Measurement>>)>,
}

/// What one step reports to the caller (for a progress bar).
#[derive(Debug, Clone, PartialEq)]
pub struct StepStats {
    /// Steps taken, this one included.
    pub step: usize,
    /// Steps the run goes to ([`FinetuneConfig::steps`]).
    pub steps: usize,
    /// Training loss of this step's batch (before its update, with the negative-output penalty
    /// when set).
    pub loss: f64,
    /// Validation PSNR after this step, dB; `None` at a step without validation.
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

    /// Steps taken so far.
    pub fn step(&self) -> usize {
        self.step
    }

    /// The training curve so far: one entry per step, step 0 the start.
    pub fn history(&self) -> &[HistoryEntry] {
        &self.history
    }

    /// The run's settings.
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

    pub(super) fn validation_loss_of(&self, net: &UNet) -> Result<f64> {
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
            return Err(Error::data(
                DataCause::Diverged,
                format!("validation loss is {val} after step {}; stopped", self.step),
            ));
        }
        if val > self.cfg.divergence * self.best_val {
            let what = format!(
                "training diverged: validation loss {val:.4} after step {} exceeds {} x the best {:.4}; stopped",
                self.step, self.cfg.divergence, self.best_val
            );
            return Err(Error::data(DataCause::Diverged, what));
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
            e @ Error::Data { .. } => e.reworded(|m| format!("{m} at step {}; stopped", self.step + 1)),
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
}
