//! A `doefab finetune` run from its job ([`FinetuneJob`]: the PSF, the data and the
//! configuration) to its outcome ([`FinetuneOutcome`]).

use std::path::PathBuf;

use serde::Serialize;

use crate::decoder::unet::UNet;
use crate::decoder::weights::DecoderWeights;
use crate::error::Result;
use crate::optics::psf::Psf;

use super::config::{short_run_warning, FinetuneConfig};
use super::optimiser::psnr_of_loss;
use super::outputs::{CHECKPOINT, DECODER};
use super::trainer::{HistoryEntry, StepStats, Trainer};
use super::training_scenes::TrainingScenes;

/// A `doefab finetune` run: the PSF, the data and the configuration.
#[derive(Debug, Clone)]
pub struct FinetuneJob {
    /// The PSF file (`.npz` with `psf_key`, or `.npy`) at pixel `pitch`, metres.
    pub psf: PathBuf,
    /// Name of the array inside a `.npz` holding several (`None`: its only array).
    pub psf_key: Option<String>,
    /// PSF pixel pitch (the sensor's), metres: used where the file states none, checked where
    /// it does.
    pub pitch: f64,
    /// The start decoder (`None`: [`crate::decoder::runtime::default_init`]).
    pub init: Option<PathBuf>,
    /// Real HDR training images (see `crate::decoder::dataset`); `None`: procedural scenes.
    pub data: Option<PathBuf>,
    /// Validation images (`None`: held out from `data` by name, 1 in `holdout_every`).
    pub validation_data: Option<PathBuf>,
    /// Without `validation_data`, 1 in this many of `data`'s images validate, chosen by the
    /// SHA-256 of their name ([`crate::decoder::dataset::is_validation`]).
    pub holdout_every: usize,
    /// Panoramas narrower than this are not used (see `crate::decoder::dataset`).
    pub min_panorama_width: usize,
    /// Largest white-balance gain of the training views' colour jitter
    /// ([`crate::decoder::dataset::HdrScenes::white_balance`]).
    pub white_balance: f64,
    /// Output folder: checkpoint, decoder and `training.json`.
    pub output: PathBuf,
    /// Continue the checkpoint in `output` (to `cfg.steps`, at `lr` when given).
    pub resume: bool,
    /// Adam step size (`None`: `cfg.lr` for a new run, the saved one on `resume`).
    pub lr: Option<f64>,
    /// The fine-tuning settings; on `resume` only `steps` and `blend` are taken, the rest come
    /// from the checkpoint.
    pub cfg: FinetuneConfig,
    /// Run on the GPU ([`crate::decoder::runtime::select_device`]); `false`: the CPU.
    pub gpu: bool,
}

/// What a finetune run did (the `--json` output of `doefab finetune`).
#[derive(Debug, Clone, Serialize)]
pub struct FinetuneOutcome {
    /// The output folder.
    pub output: PathBuf,
    /// The fine-tuned decoder written, [`DECODER`] in `output`.
    pub decoder: PathBuf,
    /// Steps the run took in all (a resumed run's included).
    pub steps: usize,
    /// `patience` validations passed without a new best, which stops the run
    /// ([`Trainer::stopped_early`]).
    pub stopped_early: bool,
    /// The step the written decoder comes from (0: no step validated better than the start).
    pub best_step: usize,
    /// Validation PSNR of the start decoder, dB (`-20 log10 L`, sqrt domain, peak = the
    /// clipping level); `None` when the history holds no step 0.
    pub start_validation_psnr: Option<f64>,
    /// Validation PSNR of the best validated weights, dB.
    pub best_validation_psnr: f64,
    /// The written decoder's blend with the start (see [`FinetuneConfig::blend`]; 1 = the best
    /// validated weights as they are).
    pub blend: f64,
    /// Validation PSNR of the written decoder, dB.
    pub written_validation_psnr: f64,
    /// What the training scenes were ([`crate::decoder::scenes::SceneSource::describe`]).
    pub data: String,
    /// What the validation set was simulated from.
    pub validation_data: String,
    /// The training curve: one entry per step (step 0 the start), validations at their steps.
    pub history: Vec<HistoryEntry>,
    /// Why the written decoder may be worse than its start: a run handed over before
    /// [`STEPS`](crate::decoder::STEPS) steps, which on the paper's real captures first fall
    /// below the start.
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
    let selected = crate::decoder::runtime::select_device(job.gpu)?;
    let device = selected.device;
    let mut trainer = if job.resume {
        let ckpt = job.output.join(CHECKPOINT);
        let mut t =
            Trainer::resume(&ckpt, &psf, &psf_sha, source, validation, job.cfg.steps, job.lr, &device)?;
        t.cfg.blend = job.cfg.blend;
        t
    } else {
        let init = job.init.clone().unwrap_or_else(crate::decoder::runtime::default_init);
        let weights = DecoderWeights::read(&init)?;
        let net = UNet::from_weights(&weights, &device);
        let desc = format!("{} (sha256 {})", init.display(), crate::decoder::weights::decoder_sha256(&init)?);
        let cfg = FinetuneConfig { lr: job.lr.unwrap_or(job.cfg.lr), ..job.cfg.clone() };
        Trainer::new(net, &psf, &psf_sha, source, validation, cfg, &desc)?
    };
    if let Err(e) = trainer.run(&job.output, on_step) {
        let ckpt = job.output.join(CHECKPOINT);
        return Err(match ckpt.exists() {
            true => e.reworded(|m| format!("{m}; the last good checkpoint is {}", ckpt.display())),
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
