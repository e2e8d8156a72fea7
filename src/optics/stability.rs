//! Stability maps of the transfer-function PSF method (`doefab bench stability`): its error over
//! two-dimensional sweeps that cross its validity guard, with every run's guard verdict, and the
//! count of silent failures (the guard accepts, the error is over the tolerance).
//!
//! The scene is [`super::psf_bench::scene`] (0.5 mm aperture, 3 um pixels, a 40 x 40 crop) with a DOE
//! that has one truth at every pupil pitch swept: the phase `3 (cos(2 pi x / 60 um) +
//! cos(2 pi y / 85 um))` rad at 550 nm, sampled at 0.8 um (0.25 rad per sample at most), so the
//! pupil samples of every pitch are read from a well-resolved surface. 0.8 um is none of the
//! swept pupil pitches `3 um / s`: every method then interpolates the same pupil samples (at a
//! pitch equal to the DOE's, the matrix DFT takes the DOE's own samples with the DOE's parity,
//! which can sit half a sample from the Fresnel method's grid: a different pupil, and a
//! 4.7e-3 difference that is not either method's error). The pupil pitch is the
//! transfer-function method's own, `dx = sensor_pitch / s` for `s` sub-samples per pixel.
//!
//! **Truth.** The matrix DFT ([`super::propagate::matrix_dft`]) on the same sampled pupil (pitch
//! `dx`, the same samples) at the same sensor points (midpoint rule, `s` per pixel): in focus it
//! is the exact discrete transform of that pupil, with no window, replicas or chirp to sample,
//! so the difference is the two-step Fresnel method's own error, and pupil sampling and pixel
//! integration cancel. Both are paraxial; the angular-spectrum method is not mapped against it,
//! because it differs from any paraxial result by the paraxial model's own error (of order
//! NA^2: 3e-2 at F/7 on this scene), which only a non-paraxial truth could separate.
//!
//! **Axes.** x: the pupil pitch over the lens-sampling limit, `dx / (lambda F#)` (the guard's
//! `lens_sampling` boundary is x = 1 on every row). Map 1, y: the Fresnel number of the
//! aperture at the sensor, `N_F = (D/2)^2 / (lambda d_s)`, swept through the focal length
//! (`d_s = g`, in focus) at one wavelength. Map 2, y: the wavelength, at the scene's focal
//! length. The paper's own sampling (4.29 um at F/7: x = 0.97, 1.16, 1.36 at 635, 530, 450 nm)
//! is marked on map 2's x axis.
//!
//! The error is the relative L2 of the PSF (normalised to sum 1 over the crop) against the
//! truth's, one wavelength per run.

use serde::{Deserialize, Serialize};

use super::propagate::{check, Method, Options, Precision};
use super::psf::relative_l2;
use super::psf_bench::scene;
use super::simulate;
use super::system::{OpticalSystem, PixelRule};
use crate::error::{Error, Result};
use crate::grid::{Grid, Unit};
use crate::material::Material;

/// Pitch of the stability DOE's samples, metres.
pub const DOE_PITCH: f64 = 0.8e-6;

/// The paper's DOE pitch and F-number, and its three wavelengths (metres).
const PAPER_PITCH: f64 = 4.29e-6;
const PAPER_F_NUMBER: f64 = 7.0;
const PAPER_WAVELENGTHS: [f64; 3] = [635e-9, 530e-9, 450e-9];

/// What the maps sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapOptions {
    /// Error above which a run the guard accepts is a silent failure.
    pub tolerance: f64,
    /// Sub-samples per pixel (pupil pitch `3 um / s`).
    pub subsamples: Vec<usize>,
    /// Focal lengths of map 1 (metres; the sensor at `d_s = g`).
    pub focal_lengths: Vec<f64>,
    /// Wavelength of map 1, metres.
    pub wavelength: f64,
    /// Wavelengths of map 2, metres (at the scene's 3.5 mm focal length).
    pub wavelengths: Vec<f64>,
}

impl Default for MapOptions {
    fn default() -> MapOptions {
        MapOptions {
            tolerance: 1e-2,
            subsamples: vec![1, 2, 3, 4, 5, 6],
            focal_lengths: vec![1.0e-3, 1.4e-3, 2.0e-3, 2.8e-3, 4.0e-3, 5.6e-3, 8.0e-3],
            wavelength: 550e-9,
            wavelengths: vec![400e-9, 450e-9, 500e-9, 550e-9, 600e-9, 650e-9, 700e-9],
        }
    }
}

/// One run of a map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapCell {
    pub subsample: usize,
    /// Pupil pitch, metres.
    pub pupil_pitch: f64,
    pub wavelength: f64,
    pub focal_length: f64,
    /// `dx / (lambda F#)`.
    pub lens_sampling_ratio: f64,
    /// `(D/2)^2 / (lambda d_s)`.
    pub fresnel_number: f64,
    /// Relative L2 against the truth.
    pub error: f64,
    /// The conditions the guard refuses (empty: it accepts).
    pub violations: Vec<String>,
    /// The guard accepts and the error is over the tolerance.
    pub silent: bool,
}

/// One map: a method over two axes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StabilityMap {
    pub method: String,
    /// `fresnel_number` or `wavelength`: the y axis.
    pub y_axis: String,
    pub cells: Vec<MapCell>,
    pub silent_failures: usize,
    /// Runs the guard refuses whose error is within the tolerance (the guard's caution).
    pub refused_within_tolerance: usize,
}

/// Where the paper's sampling sits on the x axis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PaperMark {
    pub wavelength: f64,
    pub lens_sampling_ratio: f64,
}

/// Everything [`run_maps`] measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StabilityReport {
    pub units: String,
    pub tolerance: f64,
    /// The truth and the scene, in words.
    pub truth: String,
    pub aperture: f64,
    pub sensor_pitch: f64,
    pub crop: usize,
    pub maps: Vec<StabilityMap>,
    pub paper: Vec<PaperMark>,
}

/// The stability DOE (module docs) on a grid covering the scene's pupil window.
pub fn doe() -> Result<Grid> {
    let l = 550e-9;
    let k = 2.0 * std::f64::consts::PI / l * (Material::pdms().index(l)? - 1.0);
    let tau = 2.0 * std::f64::consts::PI;
    let n = (scene().pupil_window / DOE_PITCH).ceil() as usize + 40;
    let c = (n as f64 - 1.0) * 0.5;
    let v = ndarray::Array2::from_shape_fn((n, n), |(i, j)| {
        let (x, y) = ((j as f64 - c) * DOE_PITCH, (i as f64 - c) * DOE_PITCH);
        3.0 * ((tau * x / 60e-6).cos() + (tau * y / 85e-6).cos()) / k
    });
    Grid::new(v, [DOE_PITCH; 2], Unit::Metre)
}

/// How many runs [`run_maps`] makes (for a progress bar).
pub fn steps(opts: &MapOptions) -> usize {
    opts.subsamples.len() * (opts.focal_lengths.len() + opts.wavelengths.len())
}

/// The two-step Fresnel method and its truth at one configuration.
fn cell(
    base: &OpticalSystem,
    doe: &Grid,
    s: usize,
    g: f64,
    wavelength: f64,
    tolerance: f64,
) -> Result<MapCell> {
    let sys = OpticalSystem {
        focal_length: g,
        lens_to_sensor: g,
        subsample: s,
        pixel_rule: PixelRule::Midpoint,
        wavelengths: vec![wavelength],
        ..base.clone()
    };
    let dx = sys.sample_pitch();
    let forced = Options { allow_invalid: true, precision: Precision::F64 };
    let truth_system = OpticalSystem { pupil_pitch: dx, ..sys.clone() };
    let truth = simulate(&truth_system, doe, Method::MatrixDft, &Options::default())?;
    let run = simulate(&sys, doe, Method::Fresnel, &forced)?;
    let error = relative_l2(run.channels[0].grid.values(), truth.channels[0].grid.values());
    let mut violations: Vec<String> =
        check(Method::Fresnel, &sys, doe)?.into_iter().map(|v| v.condition).collect();
    violations.dedup();
    Ok(MapCell {
        subsample: s,
        pupil_pitch: dx,
        wavelength,
        focal_length: g,
        lens_sampling_ratio: dx / (wavelength * sys.f_number()),
        fresnel_number: (0.5 * sys.aperture).powi(2) / (wavelength * g),
        error,
        // A NaN error is over any tolerance.
        silent: violations.is_empty() && (error > tolerance || error.is_nan()),
        violations,
    })
}

fn map(method: &str, y_axis: &str, cells: Vec<MapCell>, tolerance: f64) -> StabilityMap {
    let silent_failures = cells.iter().filter(|c| c.silent).count();
    let refused_within_tolerance =
        cells.iter().filter(|c| !c.violations.is_empty() && c.error <= tolerance).count();
    StabilityMap {
        method: method.into(),
        y_axis: y_axis.into(),
        cells,
        silent_failures,
        refused_within_tolerance,
    }
}

/// Runs both maps (module docs), calling `tick` before each run ([`steps`] in all).
pub fn run_maps(opts: &MapOptions, mut tick: impl FnMut(&str)) -> Result<StabilityReport> {
    let bad = |v: f64| !(v > 0.0 && v.is_finite());
    if bad(opts.tolerance)
        || opts.subsamples.is_empty()
        || opts.subsamples.contains(&0)
        || opts.focal_lengths.iter().chain(&opts.wavelengths).any(|v| bad(*v))
        || bad(opts.wavelength)
    {
        return Err(Error::param(
            "stability",
            "the tolerance, sub-samplings, focal lengths and wavelengths must be positive and finite",
        ));
    }
    let base = scene();
    let doe = doe()?;
    let mut by_fresnel = Vec::new();
    for &g in &opts.focal_lengths {
        for &s in &opts.subsamples {
            tick(&format!("map 1: g = {:.2} mm, s = {s}", g * 1e3));
            by_fresnel.push(cell(&base, &doe, s, g, opts.wavelength, opts.tolerance)?);
        }
    }
    let mut by_wavelength = Vec::new();
    for &l in &opts.wavelengths {
        for &s in &opts.subsamples {
            tick(&format!("map 2: {:.0} nm, s = {s}", l * 1e9));
            by_wavelength.push(cell(&base, &doe, s, base.focal_length, l, opts.tolerance)?);
        }
    }
    let paper = PAPER_WAVELENGTHS
        .iter()
        .map(|&l| PaperMark { wavelength: l, lens_sampling_ratio: PAPER_PITCH / (l * PAPER_F_NUMBER) })
        .collect();
    Ok(StabilityReport {
        units: "lengths in m; errors as relative L2; ratios and Fresnel numbers dimensionless".into(),
        tolerance: opts.tolerance,
        truth: "matrix DFT on the same sampled pupil at the same sensor points (exact discrete transform in focus)"
            .into(),
        aperture: base.aperture,
        sensor_pitch: base.sensor_pitch,
        crop: base.crop,
        maps: vec![
            map("fresnel", "fresnel_number", by_fresnel, opts.tolerance),
            map("fresnel", "wavelength", by_wavelength, opts.tolerance),
        ],
        paper,
    })
}
