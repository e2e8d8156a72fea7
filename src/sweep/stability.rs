//! Stability maps of the PSF methods (`doefab bench stability`): their error over
//! two-dimensional sweeps that cross their validity guards, with every run's guard verdict,
//! and the count of silent failures (the guard accepts, the error is over the tolerance). One
//! pair of maps per method: the two-step Fresnel method, the angular spectrum and the matrix
//! DFT (direct Rayleigh-Sommerfeld is the angular spectrum's truth).
//!
//! The scene is [`super::psf::scene`] (0.5 mm aperture, 3 um pixels, a 40 x 40 crop) with a DOE
//! that has one truth at every pupil pitch swept: the phase `3 (cos(2 pi x / 60 um) +
//! cos(2 pi y / 85 um))` rad at 550 nm, sampled at 0.8 um (0.25 rad per sample at most), so the
//! pupil samples of every pitch are read from a well-resolved surface. 0.8 um is none of the
//! swept pupil pitches `3 um / s`: every method then interpolates the same pupil samples (at a
//! pitch equal to the DOE's, the matrix DFT takes the DOE's own samples with the DOE's parity,
//! which can sit half a sample from the Fresnel method's grid: a different pupil, and a
//! 4.7e-3 difference that is not either method's error). The pupil pitch of the
//! transfer-function methods is `dx = sensor_pitch / s` for `s` sub-samples per pixel.
//!
//! **Truths.** Each method's truth takes the same pupil samples (pitch `dx`) to the same sensor
//! points (midpoint rule, `s` per pixel), so pupil sampling and pixel integration cancel and
//! what is left is the method's own error:
//! * the two-step Fresnel method (paraxial): the matrix DFT ([`crate::optics::propagate::matrix_dft`]),
//!   in focus the exact discrete transform of that pupil, with no window, replicas or chirp to
//!   sample;
//! * the angular spectrum (non-paraxial, hyperbolic lens): no paraxial result can be its truth
//!   (they differ by the paraxial model's own error, of order NA^2: 3e-2 at F/7 on this scene),
//!   so its truth is [`rayleigh::band_limited_intensity`], direct Rayleigh-Sommerfeld
//!   integration of the band-limited field of the same samples on a lattice finer than the
//!   wavelength (exact up to 2e-5 on this scene, its convergence tested). It costs 1 to 10 s a
//!   run, so its maps stop at `asm_subsamples` (1 to 4 by default: down to 0.19 lambda F# at
//!   550 nm and F/7, well inside every boundary);
//! * the matrix DFT: exact for its sampled pupil in focus, so its one approximation is the
//!   pupil's sampling of the surface; its pupil pitch is its own (`mdft_pitches`, 2 to 18 um,
//!   Gauss-Legendre pixels at 3 sub-samples in run and truth alike), and its truth is the same
//!   method on the surface between the DOE's samples, at a 0.4 um pupil pitch (which differs
//!   from 0.2 um by 4e-4: the truth's uncertainty, tested). Its maps found silent failures, now
//!   refused: see `pupil_resampling` in [`crate::optics::propagate`].
//! * the matrix DFT on a stepped DOE ([`stepped_doe`]: the same phase sampled at
//!   [`STEPPED_DOE_PITCH`], wrapped at 550 nm, and that quantized to [`MapOptions::levels`]
//!   levels, as `fab` makes a part): the part is piecewise constant per sample, so its truth is
//!   the same method on that piecewise-constant surface, point samples five per DOE sample and
//!   axis read by nearest interpolation (nested in the cells; against the cells' exact
//!   envelope, 4.8e-4 at 400 nm, less at longer wavelengths: its uncertainty, tested; the
//!   runs at the DOE's own pitch differ from it by 2.1e-3 at most, their aperture's edge
//!   sampled at 2 um against 0.4 um). Its
//!   runs read the pupil as the plan does for a stepped DOE, by nearest interpolation, at the
//!   DOE's pitch, at whole fractions of it (`stepped_pitches`) and coarser, in the model of
//!   such a part: cells of constant height ([`OpticalSystem::cells`]; the point samples the
//!   paper's model takes differ from the part by the cell envelope `sinc(f dx)`, which the
//!   maps found 1.1e-2 off at 400 nm at the DOE's own 2 um pitch, for any design, smooth or
//!   stepped, pixelated at that pitch). Away from 550 nm the wrap's steps are real steps of
//!   `(n(lambda) - 1) h_2pi k`, over pi in phase: the guard tells them from undersampled
//!   slopes ([`crate::optics::propagate`]'s `phase_changes`), and refuses the coarser pupils, which
//!   read across them (`step_resampling`).
//!
//! **Axes.** x: the pupil pitch over the lens-sampling limit, `dx / (lambda F#)` (the
//! transfer-function guards' `lens_sampling` boundary is x = 1 on every row; the matrix DFT's
//! `output_window` boundary, the replica period `lambda g / dx` equal to the crop, is x =
//! `D / (crop window)`). Map 1, y: the Fresnel number of the
//! aperture at the sensor, `N_F = (D/2)^2 / (lambda d_s)`, swept through the focal length
//! (`d_s = g`, in focus) at one wavelength. Map 2, y: the wavelength, at the scene's focal
//! length (the stepped DOEs have this map only: at 550 nm their steps vanish). The paper's own
//! sampling (4.29 um at F/7: x = 0.97, 1.16, 1.36 at 635, 530, 450 nm) is marked on map 2's x
//! axis.
//!
//! The error is the relative L2 of the PSF (normalised to sum 1 over the crop) against the
//! truth's, one wavelength per run.

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use super::psf::scene;
use crate::error::{Error, Result};
use crate::fabrication::quantize::{quantize, QuantizeMethod};
use crate::fabrication::wrap::{wrap, WrapSpec};
use crate::grid::{Grid, Interpolation, Unit};
use crate::material::Material;
use crate::optics::propagate::{asm, check, rayleigh, Method, Options, Precision};
use crate::optics::psf::relative_l2;
use crate::optics::simulate;
use crate::optics::system::{OpticalSystem, PixelRule};

/// Pitch of the stability DOE's samples, metres.
pub const DOE_PITCH: f64 = 0.8e-6;
/// Pitch of the stepped (wrapped, quantized) DOEs' samples, metres: 0.63 rad per sample at
/// most at 550 nm, every slope resolved.
pub const STEPPED_DOE_PITCH: f64 = 2e-6;
/// Pupil samples per DOE sample and axis of the stepped DOEs' truth (a 0.4 um pupil).
pub const STEPPED_TRUTH_REFINEMENT: usize = 5;
/// The wavelength the stepped DOEs are wrapped at, metres.
pub const STEPPED_WRAP_WAVELENGTH: f64 = 550e-9;

/// The paper's DOE pitch and F-number, and its three wavelengths (metres).
const PAPER_PITCH: f64 = 4.29e-6;
const PAPER_F_NUMBER: f64 = 7.0;
const PAPER_WAVELENGTHS: [f64; 3] = [635e-9, 530e-9, 450e-9];

/// What the maps sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapOptions {
    /// Error above which a run the guard accepts is a silent failure.
    pub tolerance: f64,
    /// Sub-samples per pixel (pupil pitch `3 um / s`) of the Fresnel method's maps.
    pub subsamples: Vec<usize>,
    /// Sub-samples per pixel of the angular spectrum's maps (its truth is the costly part).
    pub asm_subsamples: Vec<usize>,
    /// Pupil pitches of the matrix DFT's maps, metres (its pupil pitch is its own, free of the
    /// sensor's).
    pub mdft_pitches: Vec<f64>,
    /// Focal lengths of map 1 (metres; the sensor at `d_s = g`).
    pub focal_lengths: Vec<f64>,
    /// Wavelength of map 1, metres.
    pub wavelength: f64,
    /// Wavelengths of map 2, metres (at the scene's 3.5 mm focal length).
    pub wavelengths: Vec<f64>,
    /// Pupil pitches of the matrix DFT's maps on the stepped DOEs, metres (nearest
    /// interpolation: whole fractions of [`STEPPED_DOE_PITCH`] nest in its cells).
    pub stepped_pitches: Vec<f64>,
    /// Level count of the quantized DOE.
    pub levels: usize,
}

impl Default for MapOptions {
    fn default() -> MapOptions {
        MapOptions {
            tolerance: 1e-2,
            subsamples: vec![1, 2, 3, 4, 5, 6],
            asm_subsamples: vec![1, 2, 3, 4],
            mdft_pitches: vec![2e-6, 3e-6, 4.5e-6, 6.5e-6, 9e-6, 13e-6, 18e-6],
            focal_lengths: vec![1.0e-3, 1.4e-3, 2.0e-3, 2.8e-3, 4.0e-3, 5.6e-3, 8.0e-3],
            wavelength: 550e-9,
            wavelengths: vec![400e-9, 450e-9, 500e-9, 550e-9, 600e-9, 650e-9, 700e-9],
            stepped_pitches: vec![2e-6 / 3.0, 1e-6, 2e-6, 3e-6, 4.5e-6, 6.5e-6, 9e-6],
            levels: 4,
        }
    }
}

/// One run of a map.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MapCell {
    /// Sub-samples per pixel and axis (the transfer-function methods' pupil pitch is
    /// `sensor_pitch / subsample`; the matrix DFT's maps: 3 Gauss-Legendre nodes).
    pub subsample: usize,
    /// Pupil pitch, metres.
    pub pupil_pitch: f64,
    /// The run's wavelength, metres.
    pub wavelength: f64,
    /// The focal length `g`, metres (the sensor in focus, `d_s = g`).
    pub focal_length: f64,
    /// The x axis: `dx / (lambda F#)`.
    pub lens_sampling_ratio: f64,
    /// Map 1's y axis, the Fresnel number `N_F = (D/2)^2 / (lambda d_s)`.
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
    /// The method (`fresnel`, `angular_spectrum` or `matrix_dft`).
    pub method: String,
    /// The DOE: `smooth` (the stability DOE), `wrapped` or `quantized` ([`stepped_doe`]).
    pub design: String,
    /// `fresnel_number` or `wavelength`: the y axis.
    pub y_axis: String,
    /// The guard boundary drawn on the chart: its place on the x axis, `dx / (lambda F#)` (1
    /// for the transfer-function methods, `D / (crop window)` for the matrix DFT).
    pub limit_x: f64,
    /// The guard boundary's name.
    pub limit: String,
    /// Every run, row by row (focal length or wavelength), each row along the x axis.
    pub cells: Vec<MapCell>,
    /// Runs the guard accepts whose error is over the tolerance (NaN included).
    pub silent_failures: usize,
    /// Runs the guard refuses whose error is within the tolerance (the guard's caution).
    pub refused_within_tolerance: usize,
}

impl StabilityMap {
    /// The map's name in file names and tables: `<method>_<y axis>`, with the design between
    /// them for a stepped DOE (`matrix_dft_wrapped_wavelength`).
    pub fn name(&self) -> String {
        map_name(&self.method, &self.design, &self.y_axis)
    }
}

/// Where the paper's sampling sits on the x axis.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PaperMark {
    /// One of the paper's wavelengths, metres.
    pub wavelength: f64,
    /// The paper's sampling there, `dx / (lambda F#)` with 4.29 um at F/7: its place on the x axis.
    pub lens_sampling_ratio: f64,
}

/// Everything [`run_maps`] measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StabilitySweepResults {
    /// What the numbers are in: lengths in metres, errors relative L2, ratios and Fresnel numbers
    /// dimensionless.
    pub units: String,
    /// Error above which a run the guard accepts is a silent failure ([`MapOptions::tolerance`]).
    pub tolerance: f64,
    /// The truth and the scene, in words.
    pub truth: String,
    /// The scene's aperture diameter `D`, metres.
    pub aperture: f64,
    /// The scene's sensor pixel pitch, metres.
    pub sensor_pitch: f64,
    /// Sensor window, pixels per side.
    pub crop: usize,
    /// The maps run, in the order of [`MAPS`].
    pub maps: Vec<StabilityMap>,
    /// The maps a time budget left out ([`MapKind::name`]), with why.
    pub left_out: Vec<String>,
    /// Where the paper's sampling sits on the x axis, one mark per wavelength (635, 530, 450 nm).
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

/// The stepped DOEs on a grid covering the scene's pupil window: the stability DOE's phase
/// sampled at [`STEPPED_DOE_PITCH`], wrapped at [`STEPPED_WRAP_WAVELENGTH`] in PDMS
/// ([`crate::fabrication::wrap`]), and that quantized to `levels` levels by rounding
/// ([`crate::fabrication::quantize`]), as `fab` makes them: `(wrapped, quantized)`.
pub fn stepped_doe(levels: usize) -> Result<(Grid, Grid)> {
    let l = 550e-9;
    let k = 2.0 * std::f64::consts::PI / l * (Material::pdms().index(l)? - 1.0);
    let tau = 2.0 * std::f64::consts::PI;
    let n = (scene().pupil_window / STEPPED_DOE_PITCH).ceil() as usize + 20;
    let c = (n as f64 - 1.0) * 0.5;
    let v = ndarray::Array2::from_shape_fn((n, n), |(i, j)| {
        let (x, y) = ((j as f64 - c) * STEPPED_DOE_PITCH, (i as f64 - c) * STEPPED_DOE_PITCH);
        (3.0 * ((tau * x / 60e-6).cos() + (tau * y / 85e-6).cos()) + 6.0) / k
    });
    let spec = WrapSpec { wavelength: STEPPED_WRAP_WAVELENGTH, material: Material::pdms(), order: 1 };
    let (wrapped, _) = wrap(&Grid::new(v, [STEPPED_DOE_PITCH; 2], Unit::Metre)?, &spec)?;
    let quantized = quantize(&wrapped, spec.period()?, levels, QuantizeMethod::Round)?.heights()?;
    Ok((wrapped, quantized))
}

/// How many runs [`run_maps`] makes (for a progress bar).
pub fn steps(opts: &MapOptions) -> usize {
    MAPS.iter().map(|&kind| map_steps(opts, kind)).sum()
}

/// `base` at focal length `g` with the sensor in focus, one wavelength, `subsample` sub-samples
/// per pixel by `pixel_rule`.
fn in_focus(
    base: &OpticalSystem,
    g: f64,
    wavelength: f64,
    subsample: usize,
    pixel_rule: PixelRule,
) -> OpticalSystem {
    OpticalSystem {
        focal_length: g,
        lens_to_sensor: g,
        subsample,
        pixel_rule,
        wavelengths: vec![wavelength],
        ..base.clone()
    }
}

/// `method` (the two-step Fresnel or the angular-spectrum method) and its truth at one
/// configuration (module docs).
fn cell(
    method: Method,
    base: &OpticalSystem,
    doe: &Grid,
    s: usize,
    g: f64,
    wavelength: f64,
    tolerance: f64,
) -> Result<MapCell> {
    let sys = in_focus(base, g, wavelength, s, PixelRule::Midpoint);
    let dx = sys.sample_pitch();
    let error = match method {
        Method::AngularSpectrum => {
            let (n, _, _) = asm::grid(&sys);
            let u0 = sys.pupil_field(doe, n, dx, wavelength, false)?;
            let truth = rayleigh::band_limited_intensity(&sys, &u0, dx, wavelength)?;
            let run = asm::sensor_intensity(&sys, doe, wavelength)?.intensity;
            relative_l2(&rayleigh::pixels(&run, s), &rayleigh::pixels(&truth, s))
        }
        _ => {
            // The Fresnel method against the matrix DFT of the same pupil.
            let forced = Options { allow_invalid: true, precision: Precision::F64 };
            let truth_system = OpticalSystem { pupil_pitch: dx, ..sys.clone() };
            let truth = simulate(&truth_system, doe, Method::MatrixDft, &Options::default())?;
            let run = simulate(&sys, doe, method, &forced)?;
            relative_l2(run.channels[0].grid.values(), truth.channels[0].grid.values())
        }
    };
    verdict(method, &sys, doe, dx, error, tolerance)
}

/// The cell of `method`'s run in `sys` (one wavelength) at pupil pitch `dx` with `error`: the
/// guard's verdict and the axes.
fn verdict(
    method: Method,
    sys: &OpticalSystem,
    doe: &Grid,
    dx: f64,
    error: f64,
    tolerance: f64,
) -> Result<MapCell> {
    let mut violations: Vec<String> = check(method, sys, doe)?.into_iter().map(|v| v.condition).collect();
    violations.dedup();
    let wavelength = sys.wavelengths[0];
    Ok(MapCell {
        subsample: sys.subsample,
        pupil_pitch: dx,
        wavelength,
        focal_length: sys.focal_length,
        lens_sampling_ratio: dx / (wavelength * sys.f_number()),
        fresnel_number: (0.5 * sys.aperture).powi(2) / (wavelength * sys.focal_length),
        error,
        // A NaN error is over any tolerance.
        silent: violations.is_empty() && (error > tolerance || error.is_nan()),
        violations,
    })
}

/// Gauss-Legendre sub-samples per pixel of the matrix DFT's maps (its pixel integration is the
/// same in the run and the truth, so it cancels).
const MDFT_SUBSAMPLE: usize = 3;

/// The pupil pitch of the matrix DFT's truth, metres: half the DOE's pitch, 5 to 45 times finer
/// than the runs (the truth at half this pitch differs from it by 3.7e-4; tested below 5e-4).
pub const MDFT_TRUTH_PITCH: f64 = 0.4e-6;

/// The matrix DFT's truth for `sys`: the same method on the surface between the DOE's samples,
/// at [`MDFT_TRUTH_PITCH`].
fn mdft_truth(sys: &OpticalSystem, doe: &Grid) -> Result<Array2<f64>> {
    let fine = OpticalSystem { pupil_pitch: MDFT_TRUTH_PITCH, ..sys.clone() };
    let psf = simulate(&fine, doe, Method::MatrixDft, &Options::default())?;
    Ok(psf.channels[0].grid.values().clone())
}

/// The matrix DFT at pupil pitch `dx` against `truth` ([`mdft_truth`] of `sys`).
fn mdft_cell(
    sys: &OpticalSystem,
    doe: &Grid,
    dx: f64,
    truth: &Array2<f64>,
    tolerance: f64,
) -> Result<MapCell> {
    let sys = OpticalSystem { pupil_pitch: dx, ..sys.clone() };
    let forced = Options { allow_invalid: true, precision: Precision::F64 };
    let run = simulate(&sys, doe, Method::MatrixDft, &forced)?;
    let error = relative_l2(run.channels[0].grid.values(), truth);
    verdict(Method::MatrixDft, &sys, doe, dx, error, tolerance)
}

fn map(
    (method, design): (Method, &str),
    y_axis: &str,
    cells: Vec<MapCell>,
    tolerance: f64,
    base: &OpticalSystem,
) -> StabilityMap {
    let silent_failures = cells.iter().filter(|c| c.silent).count();
    let refused_within_tolerance =
        cells.iter().filter(|c| !c.violations.is_empty() && c.error <= tolerance).count();
    let (limit_x, limit) = match method {
        // lambda |B| / dx = crop window in focus (|B| = g): dx / (lambda F#) = D / window.
        Method::MatrixDft => {
            (base.aperture / base.sensor_window(), "replica-period limit (a guard condition)")
        }
        _ => (1.0, "lens-sampling limit (a guard condition)"),
    };
    StabilityMap {
        method: method.name().into(),
        design: design.into(),
        y_axis: y_axis.into(),
        limit_x,
        limit: limit.into(),
        cells,
        silent_failures,
        refused_within_tolerance,
    }
}

/// One row of a map: every pupil sampling of `method` at focal length `g` (the sensor in
/// focus) and `wavelength`.
fn row(
    method: Method,
    opts: &MapOptions,
    (base, doe): (&OpticalSystem, &Grid),
    g: f64,
    wavelength: f64,
    tick: &mut dyn FnMut(&str),
) -> Result<Vec<MapCell>> {
    let what = |x: String| format!("{method}: g = {:.2} mm, {:.0} nm, {x}", g * 1e3, wavelength * 1e9);
    let mut cells = Vec::new();
    match method {
        Method::MatrixDft => {
            let sys = in_focus(base, g, wavelength, MDFT_SUBSAMPLE, PixelRule::GaussLegendre);
            let truth = mdft_truth(&sys, doe)?;
            for &dx in &opts.mdft_pitches {
                tick(&what(format!("pupil pitch {:.1} um", dx * 1e6)));
                cells.push(mdft_cell(&sys, doe, dx, &truth, opts.tolerance)?);
            }
        }
        _ => {
            let subsamples =
                if method == Method::AngularSpectrum { &opts.asm_subsamples } else { &opts.subsamples };
            for &s in subsamples {
                tick(&what(format!("s = {s}")));
                cells.push(cell(method, base, doe, s, g, wavelength, opts.tolerance)?);
            }
        }
    }
    Ok(cells)
}

/// One row of a stepped DOE's map: the matrix DFT of cells at every pupil pitch of
/// `opts.stepped_pitches` by nearest interpolation, at the scene's focal length and
/// `wavelength`, against the piecewise-constant part (module docs).
fn stepped_row(
    opts: &MapOptions,
    (base, doe, design): (&OpticalSystem, &Grid, &str),
    wavelength: f64,
    tick: &mut dyn FnMut(&str),
) -> Result<Vec<MapCell>> {
    let sys = OpticalSystem {
        interpolation: Interpolation::Nearest,
        cells: true,
        ..in_focus(base, base.focal_length, wavelength, MDFT_SUBSAMPLE, PixelRule::GaussLegendre)
    };
    let truth_system = OpticalSystem {
        pupil_pitch: STEPPED_DOE_PITCH / STEPPED_TRUTH_REFINEMENT as f64,
        cells: false,
        ..sys.clone()
    };
    let truth = simulate(&truth_system, doe, Method::MatrixDft, &Options::default())?;
    let truth = truth.channels[0].grid.values();
    let mut cells = Vec::new();
    for &dx in &opts.stepped_pitches {
        tick(&format!(
            "matrix_dft on the {design} DOE: {:.0} nm, pupil pitch {:.2} um",
            wavelength * 1e9,
            dx * 1e6
        ));
        cells.push(mdft_cell(&sys, doe, dx, truth, opts.tolerance)?);
    }
    Ok(cells)
}

/// One map of the stability report: the method, the DOE (`smooth`, `wrapped`, `quantized`)
/// and the y axis (`fresnel_number`, `wavelength`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MapKind {
    /// The method mapped.
    pub method: Method,
    /// The DOE: `smooth` (the stability DOE), `wrapped` or `quantized` ([`stepped_doe`]).
    pub design: &'static str,
    /// The y axis: `fresnel_number` (map 1) or `wavelength` (map 2).
    pub y_axis: &'static str,
}

impl MapKind {
    /// The map's name ([`StabilityMap::name`]).
    pub fn name(self) -> String {
        map_name(self.method.name(), self.design, self.y_axis)
    }
}

/// `<method>_<y axis>`, with the design between them for a stepped DOE.
fn map_name(method: &str, design: &str, y_axis: &str) -> String {
    if design == "smooth" {
        format!("{method}_{y_axis}")
    } else {
        format!("{method}_{design}_{y_axis}")
    }
}

/// The eight maps, in the order [`run_maps`] runs them: two per method on the smooth DOE, and
/// the matrix DFT's on the two stepped ones.
pub const MAPS: [MapKind; 8] = {
    const fn kind(method: Method, design: &'static str, y_axis: &'static str) -> MapKind {
        MapKind { method, design, y_axis }
    }
    [
        kind(Method::Fresnel, "smooth", "fresnel_number"),
        kind(Method::Fresnel, "smooth", "wavelength"),
        kind(Method::AngularSpectrum, "smooth", "fresnel_number"),
        kind(Method::AngularSpectrum, "smooth", "wavelength"),
        kind(Method::MatrixDft, "smooth", "fresnel_number"),
        kind(Method::MatrixDft, "smooth", "wavelength"),
        kind(Method::MatrixDft, "wrapped", "wavelength"),
        kind(Method::MatrixDft, "quantized", "wavelength"),
    ]
};

/// How many runs the map `kind` makes.
pub fn map_steps(opts: &MapOptions, kind: MapKind) -> usize {
    let per_row = match (kind.method, kind.design) {
        (_, "wrapped" | "quantized") => opts.stepped_pitches.len(),
        (Method::Fresnel, _) => opts.subsamples.len(),
        (Method::AngularSpectrum, _) => opts.asm_subsamples.len(),
        _ => opts.mdft_pitches.len(),
    };
    let rows =
        if kind.y_axis == "fresnel_number" { opts.focal_lengths.len() } else { opts.wavelengths.len() };
    per_row * rows
}

/// Checks the sweeps of `opts`.
fn check_options(opts: &MapOptions) -> Result<()> {
    let bad = |v: f64| !(v > 0.0 && v.is_finite());
    if bad(opts.tolerance)
        || opts.subsamples.is_empty()
        || opts.asm_subsamples.is_empty()
        || opts.subsamples.iter().chain(&opts.asm_subsamples).any(|&s| s == 0)
        || opts.mdft_pitches.is_empty()
        || opts.stepped_pitches.is_empty()
        || opts
            .focal_lengths
            .iter()
            .chain(&opts.wavelengths)
            .chain(&opts.mdft_pitches)
            .chain(&opts.stepped_pitches)
            .any(|v| bad(*v))
        || bad(opts.wavelength)
    {
        return Err(Error::param(
            "stability",
            "the tolerance, sub-samplings, pupil pitches, focal lengths and wavelengths must be positive and finite",
        ));
    }
    Ok(())
}

/// Runs the map `kind` (module docs), calling `tick` before each run ([`map_steps`] in all).
pub fn run_map(opts: &MapOptions, kind: MapKind, mut tick: impl FnMut(&str)) -> Result<StabilityMap> {
    check_options(opts)?;
    let tick: &mut dyn FnMut(&str) = &mut tick;
    let base = scene();
    let mut cells = Vec::new();
    match kind.design {
        "smooth" => {
            let doe = doe()?;
            if kind.y_axis == "fresnel_number" {
                for &g in &opts.focal_lengths {
                    cells.extend(row(kind.method, opts, (&base, &doe), g, opts.wavelength, tick)?);
                }
            } else {
                for &l in &opts.wavelengths {
                    cells.extend(row(kind.method, opts, (&base, &doe), base.focal_length, l, tick)?);
                }
            }
        }
        design => {
            let (wrapped, quantized) = stepped_doe(opts.levels)?;
            let stepped = if design == "wrapped" { wrapped } else { quantized };
            for &l in &opts.wavelengths {
                cells.extend(stepped_row(opts, (&base, &stepped, design), l, tick)?);
            }
        }
    }
    Ok(map((kind.method, kind.design), kind.y_axis, cells, opts.tolerance, &base))
}

/// The report of `maps` run with `opts`, naming the maps `left_out` (by a time budget).
pub fn report(opts: &MapOptions, maps: Vec<StabilityMap>, left_out: Vec<String>) -> StabilitySweepResults {
    let base = scene();
    let paper = PAPER_WAVELENGTHS
        .iter()
        .map(|&l| PaperMark { wavelength: l, lens_sampling_ratio: PAPER_PITCH / (l * PAPER_F_NUMBER) })
        .collect();
    StabilitySweepResults {
        units: "lengths in m; errors as relative L2; ratios and Fresnel numbers dimensionless".into(),
        tolerance: opts.tolerance,
        truth: "the same pupil samples to the same sensor points: for fresnel the matrix DFT (exact discrete \
                transform in focus), for angular_spectrum direct Rayleigh-Sommerfeld integration of their \
                band-limited field on a lattice finer than the wavelength; for matrix_dft the matrix DFT of the \
                same surface at a 0.4 um pupil pitch, at the same Gauss-Legendre sensor points; on the wrapped \
                and quantized DOEs (2 um samples, wrapped at 550 nm; runs in cells of constant height) the \
                matrix DFT of the piecewise-constant part, 5 x 5 point samples nested in each DOE sample by \
                nearest interpolation"
            .into(),
        aperture: base.aperture,
        sensor_pitch: base.sensor_pitch,
        crop: base.crop,
        maps,
        left_out,
        paper,
    }
}

/// Runs the eight maps of [`MAPS`] (module docs), calling `tick` before each run ([`steps`] in
/// all).
pub fn run_maps(opts: &MapOptions, mut tick: impl FnMut(&str)) -> Result<StabilitySweepResults> {
    let maps = MAPS.iter().map(|&kind| run_map(opts, kind, &mut tick)).collect::<Result<Vec<_>>>()?;
    Ok(report(opts, maps, Vec::new()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The matrix DFT's truth at 0.4 um against the same at 0.2 um, at 550 nm and g = 3.5 mm:
    /// within 5e-4 (measured 3.7e-4), twenty times below the maps' tolerance.
    #[test]
    fn the_matrix_dft_truth_is_converged_to_its_stated_uncertainty() {
        let sys = OpticalSystem {
            subsample: MDFT_SUBSAMPLE,
            pixel_rule: PixelRule::GaussLegendre,
            wavelengths: vec![550e-9],
            ..scene()
        };
        let doe = doe().unwrap();
        let truth = mdft_truth(&sys, &doe).unwrap();
        let finer = OpticalSystem { pupil_pitch: 0.5 * MDFT_TRUTH_PITCH, ..sys };
        let psf = simulate(&finer, &doe, Method::MatrixDft, &Options::default()).unwrap();
        let e = relative_l2(&truth, psf.channels[0].grid.values());
        assert!(e < 5e-4, "{e}");
    }
}
