//! Where the PSF calibration fails (`doefab bench calibration`): the error of the PSF that
//! `calibrate-psf` recovers from a simulated pinhole bracket of a known PSF, over one axis of
//! trouble at a time.
//!
//! The truth is a PSF (by default the paper's measured one, 319 x 319 x RGB). Its pinhole
//! bracket is simulated as the demo does ([`simulate_pinhole_bracket`]: 8-bit frames one stop
//! apart, the brightest pixel at half full scale in the shortest frame, a black level and
//! Gaussian read noise, 40 px of background around the PSF), then merged without dark frames
//! and without trusting the listed times (the black level and the effective times estimated
//! from the pixels, [`merge`]'s defaults) and calibrated ([`calibrate_psf`], the crop at the
//! brightest pixel as the paper's file has it). The baseline bracket: 12 frames, read noise
//! 0.2 % and black level 1 % of full scale; each axis moves one of these: the frame count
//! (2-14: the bracket's dynamic range, `2^(frames - 1)` times the one of a single frame), the
//! read noise (0-5 %) and the black level (0-40 %), two seeds per value.
//!
//! The error is the relative L2 distance of each recovered channel from the truth
//! ([`Psf::relative_l2`]), the largest over the channels. A trial is **calibrated** when it is
//! within [`TOLERANCE`], **refused** when the calibration returns an error, **warned** when it
//! is over the tolerance and the calibration said so (its estimated error over the
//! tolerance, see [`PsfCalibration::estimated_error`]), and **silent** when it is over the
//! tolerance and nothing said so: the count that must be zero.

use std::path::PathBuf;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::SweepAxis;
use crate::calibration::capture::Capture;
use crate::calibration::hdr_merge::{merge, MergeOptions};
use crate::calibration::psf_extract::{
    calibrate_psf, simulate_pinhole_bracket, Centre, PsfCalibration, PsfOptions,
};
use crate::error::Result;
use crate::optics::Psf;

/// The largest relative L2 error (per channel) of a usable calibrated PSF: the accuracy the
/// calibration tests hold it to (2 %).
pub const TOLERANCE: f64 = 0.02;

const SEEDS: [u64; 2] = [1, 2];
const MARGIN: usize = 40;
const BASE_FRAMES: usize = 12;
const BASE_NOISE: f64 = 0.002;
const BASE_BLACK: f64 = 0.01;

/// The axes swept (module docs), in their units.
pub fn axes() -> Vec<SweepAxis> {
    let a = SweepAxis::new;
    vec![
        a("frames", "count", &[2.0, 3.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0]),
        a("read noise", "% of full scale", &[0.0, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0]),
        a("black level", "% of full scale", &[0.0, 1.0, 3.0, 10.0, 20.0, 40.0]),
    ]
}

/// One calibration trial.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Trial {
    /// The axis this trial moves ([`SweepAxis::name`]: "frames", "read noise" or "black
    /// level"); the others stay at the baseline bracket (12 frames, read noise 0.2 %, black
    /// level 1 %).
    pub axis: String,
    /// The axis's value, in its unit ([`SweepAxis::unit`]: frame count or % of full scale).
    pub value: f64,
    /// Seed of the simulated bracket's read noise.
    pub seed: u64,
    /// `calibrated`, `warned`, `refused` or `silent`.
    pub outcome: String,
    /// Relative L2 error of each channel against the truth (empty if refused).
    pub error: Vec<f64>,
    /// The largest of them (NaN if refused).
    pub worst: f64,
    /// The calibration's own estimate of its error, the largest over the channels (NaN if
    /// refused).
    pub estimated: f64,
    /// Wall-clock seconds of the merge and the calibration.
    pub seconds: f64,
    /// The calibration's warnings, or why it was refused.
    pub messages: Vec<String>,
}

/// Everything [`run`] measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationSweep {
    /// What the numbers are in: errors relative L2 against the truth (largest channel), times in
    /// seconds, axis values in their axis's unit.
    pub units: String,
    /// The truth PSF: its file's path, or `built-in:paper-measured-psf` for the paper's
    /// measured PSF.
    pub truth: String,
    /// [`TOLERANCE`]: the largest relative L2 error of a calibrated trial (0.02).
    pub tolerance: f64,
    /// The axes swept, in their units.
    pub axes: Vec<SweepAxis>,
    /// Every trial, axis by axis, value by value, seed by seed.
    pub trials: Vec<Trial>,
    /// Trials over the tolerance that nothing warned of.
    pub silent_failures: usize,
    /// Trials over the tolerance whose calibration said so (estimated error over the tolerance).
    pub warned: usize,
    /// Trials whose merge or calibration returned an error.
    pub refused: usize,
}

/// Trials [`run`] makes (for a progress bar).
pub fn steps() -> usize {
    axes().iter().map(|a| a.values.len() * SEEDS.len()).sum()
}

/// The bracket's `(frames, read noise, black level)` with `axis` set to `value`.
fn params(axis: &str, value: f64) -> (usize, f64, f64) {
    match axis {
        "frames" => (value as usize, BASE_NOISE, BASE_BLACK),
        "read noise" => (BASE_FRAMES, value / 100.0, BASE_BLACK),
        _ => (BASE_FRAMES, BASE_NOISE, value / 100.0),
    }
}

/// One trial: the bracket simulated, merged and calibrated, the result scored.
fn trial(truth: &Psf, axis: &SweepAxis, value: f64, seed: u64) -> Result<Trial> {
    let (frames, noise, black) = params(&axis.name, value);
    let (values, times, _) = simulate_pinhole_bracket(truth, MARGIN, frames, noise, black, seed);
    let captures: Vec<Capture> = values
        .into_iter()
        .enumerate()
        .map(|(k, image)| Capture { path: PathBuf::from(format!("pinhole{k:02}.png")), image, bits: 8 })
        .collect();
    let opts = PsfOptions { crop: truth.dim().0, centre: Centre::Peak, ..Default::default() };
    let t = Instant::now();
    let got = merge(&captures, &times, None, None, &MergeOptions::default())
        .and_then(|merged| calibrate_psf(&merged, &opts));
    let seconds = t.elapsed().as_secs_f64();
    let base = Trial {
        axis: axis.name.clone(),
        value,
        seed,
        outcome: String::new(),
        error: Vec::new(),
        worst: f64::NAN,
        estimated: f64::NAN,
        seconds,
        messages: Vec::new(),
    };
    Ok(match got {
        Ok((psf, report)) => {
            let error = psf.relative_l2(truth)?;
            let worst = error.iter().copied().fold(0.0, f64::max);
            let estimated = report.estimated_error.iter().copied().fold(0.0, f64::max);
            let outcome = if worst <= TOLERANCE {
                "calibrated"
            } else if estimated > TOLERANCE {
                "warned"
            } else {
                "silent"
            };
            Trial {
                outcome: outcome.into(),
                error,
                worst,
                estimated,
                messages: all_warnings(&report),
                ..base
            }
        }
        Err(e) => Trial { outcome: "refused".into(), messages: vec![e.to_string()], ..base },
    })
}

fn all_warnings(r: &PsfCalibration) -> Vec<String> {
    r.merge.warnings.iter().chain(&r.warnings).cloned().collect()
}

/// Runs every trial (module docs) on the PSF `truth` (named `name` in the report), calling
/// `tick` before each ([`steps`] in all).
pub fn run(truth: &Psf, name: &str, mut tick: impl FnMut(&str)) -> Result<CalibrationSweep> {
    let axes = axes();
    let mut trials = Vec::new();
    for axis in &axes {
        for &value in &axis.values {
            for seed in SEEDS {
                tick(&format!("{} = {value} {}, seed {seed}", axis.name, axis.unit));
                trials.push(trial(truth, axis, value, seed)?);
            }
        }
    }
    let count = |o: &str| trials.iter().filter(|t| t.outcome == o).count();
    Ok(CalibrationSweep {
        units:
            "errors: relative L2 against the truth (largest channel); times in s; axis values in their units"
                .into(),
        truth: name.into(),
        tolerance: TOLERANCE,
        silent_failures: count("silent"),
        warned: count("warned"),
        refused: count("refused"),
        axes,
        trials,
    })
}
