//! Fine-tuning against time (the report's decoder section): how far a few minutes of CPU
//! fine-tuning move the decoder, as the held-out validation PSNR against training time.
//!
//! The run is [`Trainer`]'s, with the settings of `doefab finetune` (measured noise, 8-bit
//! captures, negative-output penalty, batches of 4 crops 256 px a side;
//! [`FinetuneConfig::recommended`]), so that its time per step is what a user's run costs. The
//! first step is timed, and the run then takes as many steps as the budget holds, in
//! `evaluations` equal legs (at least one step each), the
//! validation set (simulated once, from held-out seeds) scored after each leg. The time axis is
//! training time (the steps' wall clock on the machine's threads), validation excluded, as in
//! `bench decoder`'s fine-tuning chart.
//!
//! The scenes are the seeded procedural HDR scenes ([`procedural_scenes`]): a gain there is a
//! gain on simulated captures of simulated scenes, which the paper's real captures need not
//! show (README, Decoder).

use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use crate::decoder::finetune::{procedural_scenes, psnr_of_loss, FinetuneConfig, Trainer};
use crate::decoder::unet::UNet;
use crate::decoder::weights::{decoder_sha256, DecoderWeights};
use crate::error::{Allowed, DataCause, Error, Result};
use crate::optics::Psf;

/// What [`run`] runs.
#[derive(Debug, Clone, PartialEq)]
pub struct TimedOptions {
    /// The decoder to start from (a file or `built-in:NAME`).
    pub init: PathBuf,
    /// Wall-clock seconds for the whole run, validation included; the run takes at least
    /// `evaluations` steps even when they take longer.
    pub seconds: f64,
    /// Validations after the start (the legs of the run).
    pub evaluations: usize,
    /// Training settings (`steps` is set from the budget).
    pub config: FinetuneConfig,
}

impl TimedOptions {
    /// `doefab finetune`'s settings from the paper's simulated-PSF decoder, with 8 validation
    /// views, within `seconds`.
    pub fn new(seconds: f64) -> TimedOptions {
        TimedOptions {
            init: crate::decoder::default_init(),
            seconds,
            evaluations: 8,
            config: FinetuneConfig { validation: 8, ..FinetuneConfig::recommended() },
        }
    }
}

/// The validation score after a number of steps.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TimedPoint {
    /// Fine-tuning steps done at this validation (0: the starting decoder).
    pub step: usize,
    /// Training time up to this step (validation excluded), seconds.
    pub seconds: f64,
    /// Validation PSNR (the loss's sqrt domain), dB.
    pub val_psnr: f64,
}

/// What [`run`] measured.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TimedFinetune {
    /// The starting decoder and its SHA-256.
    pub init: String,
    /// The PSF the captures are simulated through: its file, or `built-in:paper-measured-psf`.
    pub psf: String,
    /// What it was trained on: the procedural scenes' name.
    pub training_data: String,
    /// Crops per training step.
    pub batch: usize,
    /// Side of each training crop, pixels.
    pub crop: usize,
    /// Views in the fixed validation set.
    pub validation_views: usize,
    /// Threads the steps ran on.
    pub threads: usize,
    /// Training steps run: the legs' steps, `evaluations` legs of equal length.
    pub steps: usize,
    /// Training time per step (validation excluded), seconds: the steps' training seconds over
    /// `steps`.
    pub seconds_per_step: f64,
    /// Wall-clock seconds of the whole run (validation and setup included).
    pub total_seconds: f64,
    /// Step 0 (the start) and every validation after it.
    pub points: Vec<TimedPoint>,
    /// What the numbers are in: PSNR in dB (validation loss's sqrt domain, peak = the clipping
    /// level), times in seconds.
    pub units: &'static str,
}

impl TimedFinetune {
    /// The start's validation PSNR and the best one, dB.
    pub fn start_and_best(&self) -> (f64, f64) {
        let start = self.points.first().map_or(f64::NAN, |p| p.val_psnr);
        (start, self.points.iter().map(|p| p.val_psnr).fold(start, f64::max))
    }

    /// Training seconds at the first validation that reached half of the best gain over the
    /// start (`None` without a gain).
    pub fn half_gain_seconds(&self) -> Option<f64> {
        let (start, best) = self.start_and_best();
        if !start.is_finite() || best <= start {
            return None;
        }
        self.points.iter().find(|p| p.val_psnr - start >= 0.5 * (best - start)).map(|p| p.seconds)
    }
}

/// How many progress ticks [`run`] gives: one per validation after the start.
pub fn steps(opts: &TimedOptions) -> usize {
    opts.evaluations
}

/// Fine-tunes `opts.init` on `psf` (named `psf_name` in the outputs) for what `opts.seconds`
/// holds, scoring the validation set after each of `opts.evaluations` legs (see the module
/// docs). `tick` is called once per validation.
pub fn run(
    opts: &TimedOptions,
    psf: &Psf,
    psf_name: &str,
    mut tick: impl FnMut(&str),
) -> Result<TimedFinetune> {
    if !(opts.seconds > 0.0 && opts.seconds.is_finite()) {
        return Err(Error::param_in(
            "seconds",
            Allowed::positive(),
            format!("must be a positive time, got {} s", opts.seconds),
        ));
    }
    if opts.evaluations == 0 {
        return Err(Error::param_in("evaluations", Allowed::at_least(1.0), "must be at least 1"));
    }
    let clock = Instant::now();
    let device = crate::decoder::device(false)?;
    let start = DecoderWeights::read(&opts.init)?;
    let init = format!("{} (sha256 {})", opts.init.display(), decoder_sha256(&opts.init)?);
    let source = procedural_scenes();
    // The trainer records the PSF's hash in the decoders it writes; this run writes none, so
    // the PSF's name stands in for it.
    let mut trainer = Trainer::new(
        UNet::from_weights(&start, &device),
        psf,
        psf_name,
        &source,
        None,
        opts.config.clone(),
        &init,
    )?;
    let validation_seconds = clock.elapsed().as_secs_f64();
    let mut points = vec![TimedPoint { step: 0, seconds: 0.0, val_psnr: psnr_from(&trainer)? }];
    let step_clock = Instant::now();
    trainer.train_step()?;
    let first = step_clock.elapsed().as_secs_f64();
    // Steps the rest of the budget holds, with one validation per leg (a validation costs
    // at most what setting up the validation set and scoring it once did).
    let left = opts.seconds - clock.elapsed().as_secs_f64() - opts.evaluations as f64 * validation_seconds;
    let more = (left / first).floor().max(0.0) as usize;
    let every = ((1 + more) / opts.evaluations).max(1);
    let total = every * opts.evaluations;
    let mut seconds = first;
    loop {
        if trainer.step() % every == 0 {
            let psnr = trainer.evaluate()?;
            points.push(TimedPoint { step: trainer.step(), seconds, val_psnr: psnr });
            tick(&format!("fine-tuning: step {} of {total}, validation {psnr:.2} dB", trainer.step()));
        }
        if trainer.step() >= total {
            break;
        }
        let step_clock = Instant::now();
        trainer.train_step()?;
        seconds += step_clock.elapsed().as_secs_f64();
    }
    Ok(TimedFinetune {
        init,
        psf: psf_name.into(),
        training_data: source.name.into(),
        batch: opts.config.batch,
        crop: opts.config.crop,
        validation_views: opts.config.validation,
        threads: rayon::current_num_threads(),
        steps: total,
        seconds_per_step: seconds / total as f64,
        total_seconds: clock.elapsed().as_secs_f64(),
        points,
        units: "PSNR in dB (validation loss's sqrt domain, peak = the clipping level); seconds",
    })
}

/// The validation PSNR the trainer logged last.
fn psnr_from(trainer: &Trainer) -> Result<f64> {
    trainer
        .history()
        .iter()
        .rev()
        .find_map(|h| h.val_loss)
        .map(psnr_of_loss)
        .ok_or_else(|| Error::data(DataCause::Empty, "the fine-tuning run logged no validation"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decoder::finetune::Trainer;

    fn point(step: usize, seconds: f64, val_psnr: f64) -> TimedPoint {
        TimedPoint { step, seconds, val_psnr }
    }

    fn timed(points: Vec<TimedPoint>) -> TimedFinetune {
        TimedFinetune {
            init: "x".into(),
            psf: "p".into(),
            training_data: "d".into(),
            batch: 2,
            crop: 64,
            validation_views: 2,
            threads: 1,
            steps: points.last().map_or(0, |p| p.step),
            seconds_per_step: 1.0,
            total_seconds: 1.0,
            points,
            units: "",
        }
    }

    /// Half the gain: the first validation at least half-way from the start to the best.
    #[test]
    fn half_the_gain_is_the_first_point_half_way_to_the_best() {
        let r =
            timed(vec![point(0, 0.0, 10.0), point(1, 5.0, 10.9), point(2, 10.0, 11.0), point(3, 15.0, 12.0)]);
        assert_eq!(r.start_and_best(), (10.0, 12.0));
        assert_eq!(r.half_gain_seconds(), Some(10.0));
        let flat = timed(vec![point(0, 0.0, 10.0), point(1, 5.0, 9.0)]);
        assert_eq!(flat.start_and_best(), (10.0, 10.0));
        assert_eq!(flat.half_gain_seconds(), None);
    }

    /// A budget too small for a step still runs one step a leg; the start's PSNR is the
    /// starting decoder's validation PSNR as a trainer of its own scores it, each later point
    /// is a validation after its leg.
    #[test]
    fn a_timed_run_scores_its_legs_and_the_start_matches_an_independent_trainer() {
        let psf = Psf::paper_measured().unwrap();
        let config = FinetuneConfig { batch: 1, crop: 32, validation: 2, ..FinetuneConfig::recommended() };
        let opts =
            TimedOptions { seconds: 1e-3, evaluations: 2, config: config.clone(), ..TimedOptions::new(1.0) };
        let mut ticks = 0;
        let r = run(&opts, &psf, "built-in:paper-measured-psf", |_| ticks += 1).unwrap();
        assert_eq!(ticks, 2);
        assert_eq!(r.steps, 2);
        let steps: Vec<usize> = r.points.iter().map(|p| p.step).collect();
        assert_eq!(steps, [0, 1, 2]);
        assert!(r.points.windows(2).all(|w| w[1].seconds > w[0].seconds), "{:?}", r.points);
        // The same start, validated by a trainer of its own.
        let device = crate::decoder::device(false).unwrap();
        let net = UNet::from_weights(&DecoderWeights::read(&opts.init).unwrap(), &device);
        let source = procedural_scenes();
        let t = Trainer::new(net, &psf, "x", &source, None, config, "start").unwrap();
        assert_eq!(r.points[0].val_psnr, psnr_of_loss(t.validation_loss().unwrap()));
        let bad = TimedOptions { seconds: 0.0, ..opts };
        let e = run(&bad, &psf, "p", |_| {}).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name == "seconds"), "{e:?}");
    }
}
