//! Where scan registration fails (`doefab bench register`): its error and verdict over one axis
//! of trouble at a time, from a known truth.
//!
//! The part is the paper's DOE on 320 samples of 4.29 um, wrapped at 530 nm in PDMS and
//! quantized to 8 levels (the surface `compare` registers a scan to). A scan of it is
//! simulated (`crate::metrology::synthetic_scan`) at 2.7 um with a known pose, and
//! [`register`] must find that pose without being told
//! anything of it (it searches rotation, mirror and height sign). The baseline scan: 20 nm of
//! noise, a 2 um blur, 10 % of samples missing, a rotation of 0.3 deg, scale 1, a shift of
//! (3.2, -1.7) um; each axis then moves one of these (noise, blur, missing fraction, rotation,
//! scale, and the design's level count) across and past where registration can work, two
//! seeds per value.
//!
//! Each trial ends one of three ways: **registered** (the pose within [`WRONG_SHIFT`] design
//! samples and [`WRONG_ROTATION`] of the truth, mirror and height sign right), **refused** (an
//! error naming why), or **wrong**: accepted with a pose outside those bounds, a silent
//! failure. The count of wrong trials is the figure that must be zero.

use std::collections::BTreeMap;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::SweepAxis;
use crate::design::{paper_example, ExampleParams, PAPER_PITCH};
use crate::error::Result;
use crate::fabrication::quantize::{quantize, QuantizeMethod};
use crate::fabrication::wrap::{wrap, WrapSpec};
use crate::grid::Grid;
use crate::metrology::scan_registration::{register, Pose, RegisterOptions};
use crate::metrology::synthetic_scan::{simulate_scan, SimulateParams};

/// A pose further than this from the truth, in design samples, is wrong.
pub const WRONG_SHIFT: f64 = 0.5;
/// A rotation further than this from the truth, radians (0.1 deg), is wrong.
pub const WRONG_ROTATION: f64 = 0.1 * std::f64::consts::PI / 180.0;

const SAMPLES: usize = 320;
const SCAN_PITCH: f64 = 2.7e-6;
const SEEDS: [u64; 2] = [1, 2];

/// The axes swept (module docs), in their units.
pub fn axes() -> Vec<SweepAxis> {
    let a = SweepAxis::new;
    vec![
        a("noise", "nm", &[0.0, 100.0, 300.0, 600.0, 1000.0, 3000.0]),
        a("blur", "um", &[0.0, 5.0, 20.0, 40.0, 80.0]),
        a("missing", "fraction", &[0.0, 0.6, 0.9, 0.97, 0.99, 0.998]),
        a("rotation", "deg", &[0.0, 2.5, 8.0, 20.0, 45.0, 90.0]),
        a("scale", "1", &[0.8, 0.9, 0.97, 1.0, 1.03, 1.1, 1.25]),
        a("levels", "count", &[2.0, 4.0, 8.0, 64.0]),
    ]
}

/// One registration trial.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Trial {
    /// The axis this trial moves ([`SweepAxis::name`]); the others stay at the baseline scan.
    pub axis: String,
    /// The axis's value, in its unit ([`SweepAxis::unit`]).
    pub value: f64,
    /// Seed of the simulated scan (noise, missing samples).
    pub seed: u64,
    /// `registered`, `refused` or `wrong`.
    pub outcome: String,
    /// Distance of the found shift from the truth, design samples (NaN if refused).
    pub shift_error: f64,
    /// Found rotation minus the truth, degrees (NaN if refused).
    pub rotation_error_deg: f64,
    /// Correlation of the scan with the registered design (NaN if refused).
    pub correlation: f64,
    /// The registration's own formal standard error of the shift, design samples (the larger of
    /// x and y); NaN if refused.
    pub shift_sigma: f64,
    /// The registration's own formal standard error of the rotation, degrees; NaN if refused.
    pub rotation_sigma_deg: f64,
    /// Wall-clock seconds of the registration alone.
    pub seconds: f64,
    /// Why it was refused.
    pub reason: Option<String>,
}

/// Everything [`run`] measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RegistrationSweep {
    /// What the numbers are in: shift errors in design samples (4.29 um), rotation errors in
    /// degrees, times in seconds, axis values in their axis's unit.
    pub units: String,
    /// Samples of the square design along each side (320).
    pub design_samples: usize,
    /// The design's pitch, metres (4.29 um).
    pub design_pitch: f64,
    /// The simulated scan's pitch, metres (2.7 um).
    pub scan_pitch: f64,
    /// [`WRONG_SHIFT`]: the largest shift error of a registered trial, design samples.
    pub wrong_shift: f64,
    /// [`WRONG_ROTATION`] in degrees: the largest rotation error of a registered trial.
    pub wrong_rotation_deg: f64,
    /// The axes swept, in their units.
    pub axes: Vec<SweepAxis>,
    /// Every trial, axis by axis, value by value, seed by seed.
    pub trials: Vec<Trial>,
    /// Trials accepted with a wrong pose.
    pub silent_failures: usize,
    /// Trials whose registration returned an error.
    pub refused: usize,
}

/// Trials [`run`] makes (for a progress bar).
pub fn steps() -> usize {
    axes().iter().map(|a| a.values.len() * SEEDS.len()).sum()
}

/// The part's surface at `levels` levels (module docs).
fn part(levels: usize) -> Result<Grid> {
    let p = ExampleParams {
        samples: SAMPLES,
        aperture: 0.9 * SAMPLES as f64 * PAPER_PITCH,
        ..Default::default()
    };
    let (w, r) = wrap(&paper_example(&p)?, &WrapSpec::default())?;
    quantize(&w, r.period, levels, QuantizeMethod::Round)?.heights()
}

/// The baseline scan's parameters with `axis` set to `value`; the design's level count.
fn params(axis: &str, value: f64, seed: u64) -> (SimulateParams, usize) {
    let mut p = SimulateParams {
        blur: 2e-6,
        noise: 20e-9,
        missing: 0.1,
        pose: Pose { mirror: false, rotation: 0.3f64.to_radians(), scale: 1.0, shift: [3.2e-6, -1.7e-6] },
        pitch: Some([SCAN_PITCH; 2]),
        seed,
        ..SimulateParams::default()
    };
    let mut levels = 8;
    match axis {
        "noise" => p.noise = value * 1e-9,
        "blur" => p.blur = value * 1e-6,
        "missing" => p.missing = value,
        "rotation" => p.pose.rotation = value.to_radians(),
        "scale" => p.pose.scale = value,
        _ => levels = value as usize,
    }
    (p, levels)
}

/// Runs every trial (module docs), calling `tick` before each ([`steps`] in all).
pub fn run(mut tick: impl FnMut(&str)) -> Result<RegistrationSweep> {
    let axes = axes();
    let opts = RegisterOptions::default();
    let mut trials = Vec::new();
    let mut parts: BTreeMap<usize, Grid> = BTreeMap::new();
    for axis in &axes {
        for &value in &axis.values {
            for seed in SEEDS {
                tick(&format!("{} = {value} {}, seed {seed}", axis.name, axis.unit));
                let (p, levels) = params(&axis.name, value, seed);
                let design = match parts.entry(levels) {
                    std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
                    std::collections::btree_map::Entry::Vacant(e) => e.insert(part(levels)?),
                };
                let scan = simulate_scan(design, &p)?;
                let t = Instant::now();
                let got = register(design, &scan, &opts);
                let seconds = t.elapsed().as_secs_f64();
                let trial = match got {
                    Ok(r) => {
                        let d = [r.pose.shift[0] - p.pose.shift[0], r.pose.shift[1] - p.pose.shift[1]];
                        let shift_error = d[0].hypot(d[1]) / PAPER_PITCH;
                        let rotation_error = r.pose.rotation - p.pose.rotation;
                        let right = shift_error <= WRONG_SHIFT
                            && rotation_error.abs() <= WRONG_ROTATION
                            && r.pose.mirror == p.pose.mirror
                            && r.complement == p.complement;
                        Trial {
                            axis: axis.name.clone(),
                            value,
                            seed,
                            outcome: if right { "registered" } else { "wrong" }.into(),
                            shift_error,
                            rotation_error_deg: rotation_error.to_degrees(),
                            correlation: r.correlation,
                            shift_sigma: r.shift_sigma[0].max(r.shift_sigma[1]) / PAPER_PITCH,
                            rotation_sigma_deg: r.rotation_sigma.to_degrees(),
                            seconds,
                            reason: None,
                        }
                    }
                    Err(e) => Trial {
                        axis: axis.name.clone(),
                        value,
                        seed,
                        outcome: "refused".into(),
                        shift_error: f64::NAN,
                        rotation_error_deg: f64::NAN,
                        correlation: f64::NAN,
                        shift_sigma: f64::NAN,
                        rotation_sigma_deg: f64::NAN,
                        seconds,
                        reason: Some(e.to_string()),
                    },
                };
                trials.push(trial);
            }
        }
    }
    let count = |o: &str| trials.iter().filter(|t| t.outcome == o).count();
    Ok(RegistrationSweep {
        units: "shift errors in design samples (4.29 um), rotation errors in degrees, times in s; axis values in their units".into(),
        design_samples: SAMPLES,
        design_pitch: PAPER_PITCH,
        scan_pitch: SCAN_PITCH,
        wrong_shift: WRONG_SHIFT,
        wrong_rotation_deg: WRONG_ROTATION.to_degrees(),
        silent_failures: count("wrong"),
        refused: count("refused"),
        axes,
        trials,
    })
}
