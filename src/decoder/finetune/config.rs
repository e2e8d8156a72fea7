//! The configuration of a fine-tuning run ([`FinetuneConfig`]): its defaults (the paper's
//! settings, each a named constant) and its checks.

use std::ops::Bound;

use serde::{Deserialize, Serialize};

use crate::decoder::measurement::{Halo, MeasurementModel};
use crate::decoder::unet::is_trainable;
use crate::error::{Allowed, Error, Result};

/// Fine-tuning settings (defaults: the paper's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinetuneConfig {
    /// Total steps of the run (a resumed run continues to this count).
    pub steps: usize,
    /// Scenes (simulated captures) per step.
    pub batch: usize,
    /// Crop side, pixels (a multiple of 16).
    pub crop: usize,
    /// Adam's step size `lr` before the bias corrections and the decay ([`Self::lr_at`]).
    pub lr: f64,
    /// Adam's first-moment decay rate `b1`, in `[0, 1)`.
    pub beta1: f64,
    /// Adam's second-moment decay rate `b2`, in `[0, 1)`.
    pub beta2: f64,
    /// Adam's `eps`, added to `sqrt(v)` in the update's denominator.
    pub epsilon: f64,
    /// Validate and checkpoint every this many steps (and at the end).
    pub checkpoint_every: usize,
    /// Size of the fixed validation set, simulated captures.
    pub validation: usize,
    /// Seed of the generator that draws the training batches; the validation set is simulated
    /// from a seed derived from it.
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

pub(super) fn one() -> f64 {
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

/// `doefab finetune`'s batch, scenes per step.
pub const BATCH: usize = 4;

/// `doefab finetune`'s crop side, pixels (well over the decoder's receptive radius; 128 px
/// crops, smaller than the 320 px PSF, lose on the real captures; README).
pub const CROP: usize = 256;

/// `doefab finetune`'s validation cadence, steps.
pub const CHECKPOINT_EVERY: usize = 20;

/// `doefab finetune`'s validation set size, views (simulated captures).
pub const VALIDATION: usize = 16;

/// Read noise of `doefab finetune`'s simulated captures, fraction of full scale: measured on
/// the paper's captures (README, fine-tuning table; the paper trained with 0.02).
pub const READ_NOISE: f64 = 0.001;

/// Shot-noise variance per unit signal of `doefab finetune`'s captures, measured as above.
pub const SHOT_NOISE: f64 = 8e-5;

/// Bit depth of `doefab finetune`'s captures (the paper's captures are 8-bit).
pub const BITS: u32 = 8;

/// Where each channel of `doefab finetune`'s captures clips: as the paper's camera, whose green
/// tops out at 231 of 255 in every frame of both scenes (`crate::calibration::clipping`).
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

    pub(super) fn check(&self) -> Result<()> {
        let bad = |n: &str, r: String| Err(Error::param(n, r));
        let out = |n: &str, allowed: Allowed, r: String| Err(Error::param_in(n, allowed, r));
        let (open_unit, at_least_0) =
            (Allowed::within(Bound::Excluded(0.0), Bound::Included(1.0)), Allowed::at_least(0.0));
        if self.crop == 0 || !self.crop.is_multiple_of(16) {
            return bad("crop", format!("{} is not a positive multiple of 16", self.crop));
        }
        if self.batch == 0 || self.checkpoint_every == 0 || self.validation == 0 {
            return bad("batch", "batch, checkpoint interval and validation size must be at least 1".into());
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            return out("lr", Allowed::positive(), format!("{} is not a positive step size", self.lr));
        }
        if !(0.0..1.0).contains(&self.beta1) || !(0.0..1.0).contains(&self.beta2) {
            return out(
                "betas",
                Allowed::within(Bound::Included(0.0), Bound::Excluded(1.0)),
                format!("{} / {} must lie in [0, 1)", self.beta1, self.beta2),
            );
        }
        if self.divergence <= 1.0 {
            return out(
                "divergence",
                Allowed::within(Bound::Excluded(1.0), Bound::Unbounded),
                format!("{} must exceed 1", self.divergence),
            );
        }
        if !(self.pull >= 0.0 && self.pull.is_finite()) {
            return out("pull", at_least_0.clone(), format!("{} must be finite and >= 0", self.pull));
        }
        if !(self.negative_penalty >= 0.0 && self.negative_penalty.is_finite()) {
            return out(
                "negative_penalty",
                at_least_0.clone(),
                format!("{} must be finite and >= 0", self.negative_penalty),
            );
        }
        if !(self.blend > 0.0 && self.blend <= 1.0) {
            return out("blend", open_unit.clone(), format!("{} must lie in (0, 1]", self.blend));
        }
        if !(self.lr_decay > 0.0 && self.lr_decay <= 1.0) {
            return out("lr_decay", open_unit.clone(), format!("{} must lie in (0, 1]", self.lr_decay));
        }
        if !(self.shot_noise >= 0.0 && self.noise_sigma >= 0.0) {
            return out(
                "noise",
                at_least_0,
                format!("read {} and shot {} must be >= 0", self.noise_sigma, self.shot_noise),
            );
        }
        if !self.channel_clipping.iter().all(|c| *c > 0.0 && *c <= 1.0) {
            return out(
                "channel_clipping",
                open_unit,
                format!("{:?}: each must lie in (0, 1]", self.channel_clipping),
            );
        }
        if let Some(h) = &self.halo {
            h.check()?;
        }
        if !(self.grad_clip >= 0.0 && self.grad_clip.is_finite()) {
            return out(
                "grad_clip",
                at_least_0.clone(),
                format!("{} must be finite and >= 0 (0: no clipping)", self.grad_clip),
            );
        }
        if self.bits.is_some_and(|b| !(1..=16).contains(&b)) {
            return out("bits", Allowed::between(1.0, 16.0), format!("{:?} must lie in 1..=16", self.bits));
        }
        Ok(())
    }

    pub(super) fn model(&self) -> MeasurementModel {
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
