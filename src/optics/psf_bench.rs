//! Speed against accuracy of the PSF methods on a small scene (`doefab bench psf`).
//!
//! The scene: F/7 at 635 and 450 nm (0.5 mm aperture, g = d_s = 3.5 mm, 3 um pixels, a 40 x 40
//! crop) with a smooth, grating-like DOE phase sampled at 5 um. Each method (matrix DFT in f64
//! and f32, two-step Fresnel, angular spectrum) runs at `s` = 1..=5 sub-samples per pixel and
//! axis (Gauss-Legendre nodes for the matrix DFT; the transfer-function methods sample the
//! pupil and the sensor uniformly at `pitch / s`, the midpoint rule, so `s` is also their
//! pupil grid), forced past its validity guard so that the error where it
//! refuses is seen; the guard's verdict is recorded with each run.
//! The error is the worst channel's relative L2 against a converged reference: the matrix DFT
//! with the midpoint rule at 16 and 32 sub-samples, Richardson-extrapolated
//! (`(4 I_32 - I_16) / 3`, the rule's error being even in the spacing), as the plan's tests use.
//! Times are the fastest of three wall-clock runs after a warm-up run of the same
//! configuration.

use std::time::Instant;

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use super::propagate::check;
use super::system::{OpticalSystem, PixelRule};
use super::{simulate, Method, Options, Precision, Psf};
use crate::error::Result;
use crate::grid::{Grid, Unit};
use crate::material::Material;

/// Samples across the bench scene's DOE grid.
pub const N: usize = 112;
/// Pitch of the bench scene's DOE grid, metres.
pub const PITCH: f64 = 5e-6;

/// Sub-samples per pixel and axis swept, 1 to this.
const SUBSAMPLES: usize = 5;

/// Method and precision pairs run.
const CONFIGS: [(Method, Precision); 4] = [
    (Method::MatrixDft, Precision::F64),
    (Method::MatrixDft, Precision::F32),
    (Method::Fresnel, Precision::F64),
    (Method::AngularSpectrum, Precision::F64),
];

/// Configurations [`run_bench`] runs (for a progress bar).
pub const RUNS: usize = CONFIGS.len() * SUBSAMPLES;

/// Timed runs per configuration (the fastest counts), after one warm-up run.
const REPEATS: usize = 3;

/// One timed run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BenchPoint {
    pub method: String,
    pub precision: String,
    /// Sub-samples per pixel and axis.
    pub subsample: usize,
    /// Their quadrature rule (`gauss_legendre`, or `midpoint` for the FFT methods, whose
    /// sensor grid is uniform).
    pub pixel_rule: String,
    /// Pupil sample pitch the method used, metres.
    pub pupil_pitch: f64,
    pub seconds: f64,
    /// Worst channel's relative L2 against the converged reference.
    pub error: f64,
    /// The validity conditions its guard refuses on, with the wavelength (empty: valid).
    pub violations: Vec<String>,
    /// On the Pareto front of (seconds, error) among the valid runs.
    pub pareto: bool,
}

/// The bench scene's system (see the module docs).
pub fn scene() -> OpticalSystem {
    OpticalSystem {
        aperture: 0.5e-3,
        doe_to_lens: 1e-3,
        focal_length: 3.5e-3,
        lens_to_sensor: 3.5e-3,
        sensor_pitch: 3e-6,
        crop: 40,
        pupil_pitch: PITCH,
        pupil_window: N as f64 * PITCH,
        wavelengths: vec![635e-9, 450e-9],
        ..Default::default()
    }
}

/// The bench DOE: phase `3 (cos(2 pi x / 60 um) + cos(2 pi y / 85 um))` radians at 550 nm in
/// PDMS, as heights.
pub fn doe() -> Result<Grid> {
    let tau = 2.0 * std::f64::consts::PI;
    heights(|x, y| 3.0 * ((tau * x / 60e-6).cos() + (tau * y / 85e-6).cos()))
}

/// The heights on the bench scene's `N x N` grid (centred, pitch `PITCH`) of a DOE whose phase
/// at 550 nm in PDMS is `phase(x, y)` radians: `h = phase / (2 pi (n - 1) / lambda)`.
pub fn heights(phase: impl Fn(f64, f64) -> f64) -> Result<Grid> {
    let l = 550e-9;
    let k = 2.0 * std::f64::consts::PI / l * (Material::pdms().index(l)? - 1.0);
    let c = (N as f64 - 1.0) * 0.5;
    let v = Array2::from_shape_fn((N, N), |(i, j)| phase((j as f64 - c) * PITCH, (i as f64 - c) * PITCH) / k);
    Grid::new(v, [PITCH; 2], Unit::Metre)
}

/// The converged reference (see the module docs), one array per channel.
pub fn reference(system: &OpticalSystem, doe: &Grid) -> Result<Vec<Array2<f64>>> {
    let at = |s: usize| {
        let sys = OpticalSystem { subsample: s, pixel_rule: PixelRule::Midpoint, ..system.clone() };
        simulate(&sys, doe, Method::MatrixDft, &Options::default())
    };
    let (a, b) = (at(16)?, at(32)?);
    Ok(a.channels
        .iter()
        .zip(&b.channels)
        .map(|(a, b)| (4.0 * b.grid.values() - a.grid.values()) / 3.0)
        .collect())
}

/// The indices of the points not dominated by another (one at most as slow and at most as
/// wrong, and better in one of the two), in increasing time.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut front: Vec<usize> = (0..points.len())
        .filter(|&i| {
            let (t, e) = points[i];
            !points.iter().any(|&(u, f)| u <= t && f <= e && (u < t || f < e))
        })
        .collect();
    front.sort_by(|&a, &b| points[a].0.total_cmp(&points[b].0));
    front
}

/// Runs every configuration (see the module docs), calling `tick` after each.
pub fn run_bench(mut tick: impl FnMut(&BenchPoint)) -> Result<Vec<BenchPoint>> {
    let (system, doe) = (scene(), doe()?);
    let reference = reference(&system, &doe)?;
    let mut points = Vec::new();
    for (method, precision) in CONFIGS {
        for s in 1..=SUBSAMPLES {
            // The FFT methods sample the sensor on their uniform grid: the midpoint rule.
            let (pixel_rule, rule) = if method == Method::MatrixDft {
                (PixelRule::GaussLegendre, "gauss_legendre")
            } else {
                (PixelRule::Midpoint, "midpoint")
            };
            let sys = OpticalSystem { subsample: s, pixel_rule, ..system.clone() };
            let violations: Vec<String> = check(method, &sys, &doe)?
                .iter()
                .map(|v| format!("{} at {:.0} nm", v.condition, v.wavelength * 1e9))
                .collect();
            let opts = Options { allow_invalid: true, precision };
            let timed = || -> Result<(Psf, f64)> {
                let t = Instant::now();
                let psf = simulate(&sys, &doe, method, &opts)?;
                Ok((psf, t.elapsed().as_secs_f64()))
            };
            timed()?;
            let (psf, mut seconds) = timed()?;
            for _ in 1..REPEATS {
                seconds = seconds.min(timed()?.1);
            }
            let error = psf
                .channels
                .iter()
                .zip(&reference)
                .map(|(c, r)| super::psf::relative_l2(c.grid.values(), r))
                .fold(0.0, f64::max);
            let pupil_pitch = if method == Method::MatrixDft { sys.pupil_pitch } else { sys.sample_pitch() };
            let p = BenchPoint {
                method: method.name().into(),
                precision: precision.name().into(),
                subsample: s,
                pixel_rule: rule.into(),
                pupil_pitch,
                seconds,
                error,
                violations,
                pareto: false,
            };
            tick(&p);
            points.push(p);
        }
    }
    let valid: Vec<usize> = (0..points.len()).filter(|&i| points[i].violations.is_empty()).collect();
    let pairs: Vec<(f64, f64)> = valid.iter().map(|&i| (points[i].seconds, points[i].error)).collect();
    for k in pareto_front(&pairs) {
        points[valid[k]].pareto = true;
    }
    Ok(points)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_pareto_front_of_a_hand_made_set() {
        // (time, error): 0 and 3 are each best in one respect, 1 trades between them, 2 is
        // dominated by 1, 4 ties 3 in time but is worse, 5 equals 1 (neither dominates).
        let pts = [(1.0, 1e-2), (2.0, 1e-4), (3.0, 1e-3), (5.0, 1e-8), (5.0, 1e-6), (2.0, 1e-4)];
        assert_eq!(pareto_front(&pts), vec![0, 1, 5, 3]);
        assert!(pareto_front(&[]).is_empty());
    }
}
