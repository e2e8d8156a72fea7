//! What the propagation methods share: their names and precisions, the validity violation a
//! check reports, the sensor intensity a method returns, and the pupil field's phase, power and
//! the sampling checks every method runs on it.

use std::f64::consts::PI;
use std::fmt;

use ndarray::{Array2, ArrayView2};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::grid::{Grid, Interpolation};
use crate::optics::system::{nested_parity, nested_refinement, takes_doe_samples, OpticalSystem};

/// The propagation methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Single transform pupil -> sensor by matrix DFT ([`matrix_dft`](super::matrix_dft)).
    MatrixDft,
    /// Two-step Fresnel transfer function with a thin-lens phase ([`fresnel`](super::fresnel)).
    Fresnel,
    /// Band-limited angular spectrum with a hyperbolic lens phase ([`asm`](super::asm)).
    AngularSpectrum,
    /// Direct Rayleigh-Sommerfeld integration ([`rayleigh`](super::rayleigh)).
    RayleighSommerfeld,
}

impl Method {
    /// Every method, in the order of the enum.
    pub const ALL: [Method; 4] =
        [Method::MatrixDft, Method::Fresnel, Method::AngularSpectrum, Method::RayleighSommerfeld];

    /// The name used on the command line and in metadata.
    pub fn name(self) -> &'static str {
        match self {
            Method::MatrixDft => "matrix_dft",
            Method::Fresnel => "fresnel",
            Method::AngularSpectrum => "angular_spectrum",
            Method::RayleighSommerfeld => "rayleigh_sommerfeld",
        }
    }

    /// The FFT window over the pupil samples' side a transfer-function method takes when the
    /// system sets no `padding` (nominal: the Fresnel method pads `n / 4` a side, the angular
    /// spectrum to `2 n`, each then rounded up to a fast FFT size); `None` for the methods
    /// without an FFT window.
    pub fn default_padding(self) -> Option<f64> {
        match self {
            Method::Fresnel => Some(1.5),
            Method::AngularSpectrum => Some(2.0),
            Method::MatrixDft | Method::RayleighSommerfeld => None,
        }
    }

    /// Parses a method name (as [`Method::name`] writes it; `-` and `_` alike).
    pub fn from_name(name: &str) -> Result<Method> {
        let n = name.trim().to_ascii_lowercase().replace('-', "_");
        Method::ALL.into_iter().find(|m| m.name() == n || (n == "asm" && *m == Method::AngularSpectrum)).ok_or_else(
            || {
                Error::param(
                    "method",
                    format!("unknown method '{name}' (known: matrix_dft, fresnel, angular_spectrum, rayleigh_sommerfeld)"),
                )
            },
        )
    }
}

impl fmt::Display for Method {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Floating-point precision of the matrix products of [`matrix_dft`](super::matrix_dft); the
/// FFT methods and every phase are computed in `f64`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// Single precision: half the memory traffic and twice the SIMD width of `f64`. Its
    /// rounding error (unit roundoff `6e-8` accumulated over sums of ~n/2 terms) stays near
    /// `1e-6` relative L2 on the PSF (measured by the tests and `benches/psf.rs`).
    F32,
    /// Double precision, the default.
    #[default]
    F64,
}

impl Precision {
    /// The name used on the command line and in metadata (`f32`, `f64`).
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::F64 => "f64",
        }
    }

    /// Parses `f32` or `f64`.
    pub fn from_name(name: &str) -> Result<Precision> {
        match name.trim().to_ascii_lowercase().as_str() {
            "f32" | "single" => Ok(Precision::F32),
            "f64" | "double" => Ok(Precision::F64),
            _ => Err(Error::param("precision", format!("unknown precision '{name}' (known: f32, f64)"))),
        }
    }
}

/// Options shared by the methods.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Options {
    /// Run even where a validity condition fails; the violations become warnings.
    pub allow_invalid: bool,
    /// Precision of the matrix products; `f32` is for [`Method::MatrixDft`] only.
    pub precision: Precision,
}

/// One violated validity condition.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Violation {
    /// Short name of the condition (`lens_sampling`, `phase_gradient`, ...).
    pub condition: String,
    /// The wavelength it concerns, metres.
    pub wavelength: f64,
    /// What failed, with the numbers.
    pub message: String,
}

impl Violation {
    pub(crate) fn new(condition: &str, wavelength: f64, message: String) -> Violation {
        Violation { condition: condition.into(), wavelength, message }
    }
}

impl fmt::Display for Violation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "[{} at {:.1} nm] {}", self.condition, self.wavelength * 1e9, self.message)
    }
}

/// The sensor intensity of one wavelength on the sub-sample grid (`crop * subsample` per side,
/// W/m^2 for a unit-amplitude incident wave) with the power that left the DOE (W).
pub struct SensorIntensity {
    /// `|u|^2` on the sensor sub-samples, `crop * subsample` square, W/m^2.
    pub intensity: Array2<f64>,
    /// Power of the pupil field leaving the DOE, `sum |u|^2 dx^2` ([`field_power`]), W.
    pub input_power: f64,
}

/// Power carried by a sampled field, `sum |u|^2 dx^2`.
pub fn field_power(u: &Array2<rustfft::num_complex::Complex64>, dx: f64) -> f64 {
    u.iter().map(|v| v.norm_sqr()).sum::<f64>() * dx * dx
}

/// The phase changes between neighbouring samples of a height map at one wavelength, sorted
/// (see [`phase_changes`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct PhaseChanges {
    /// The steepest resolved change, rad per sample: a change within pi, or what a step leaves
    /// once its period is taken off (the slope across it).
    pub steepest: f64,
    /// Pairs that step by about the map's period (module docs of [`phase_changes`]).
    pub steps: usize,
    /// Pairs that change by more than pi along a slope, and the worst: (|change| in rad, row,
    /// column of its first sample).
    pub slopes: usize,
    pub worst: (f64, usize, usize),
}

/// Sorts the phase changes between neighbouring samples (along rows and columns) of heights
/// `h` (metres), of the samples where `read(i, j)` holds (the aperture), at `k = 2 pi (n - 1) /
/// lambda` radians per metre of height, into three kinds:
///
/// * resolved: `|d| <= pi`, the Nyquist limit of a sampled phase;
/// * a step: the jump of a wrapped or quantized surface from its top back to its bottom. Such
///   a surface spans about one period `P` of height (`[0, P)` once wrapped, `(N - 1) P / N` once
///   quantized to N levels), and a step jumps by that span less the change of the surface
///   across it, so the step is `|d| >= Phi - pi` with `Phi = k (max h - min h)`: its remainder
///   `Phi - |d|`, the slope across it, resolved as any change. Its flanks are resolved too: a
///   climb of more than pi beside it in the same direction would take the surface beyond its
///   span. At the wrap's design wavelength `Phi` is 2 pi and the step vanishes in `exp(i phi)`;
///   at another it is a real step of `(n(lambda) - 1) P k`. Either way the part is piecewise
///   constant per sample (a pixelated part is made so), which the transform of the samples
///   holds exactly: the jump is no slope to resolve;
/// * a slope: any other change over pi, a smooth surface steeper than the samples resolve.
pub(crate) fn phase_changes(h: ArrayView2<f64>, read: &dyn Fn(usize, usize) -> bool, k: f64) -> PhaseChanges {
    let (rows, cols) = h.dim();
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for ((i, j), &v) in h.indexed_iter() {
        if read(i, j) {
            lo = lo.min(v);
            hi = hi.max(v);
        }
    }
    let mut out = PhaseChanges::default();
    if hi < lo {
        return out;
    }
    let period = k * (hi - lo);
    // Tolerances keep exact changes (pi of a binary grating, a step of exactly the span less
    // pi) on the resolved side.
    let limit = PI * (1.0 + 1e-9);
    for i in 0..rows {
        for j in 0..cols {
            if !read(i, j) {
                continue;
            }
            for (di, dj) in [(1, 0), (0, 1)] {
                let (a, b) = ((i, j), (i + di, j + dj));
                if b.0 >= rows || b.1 >= cols || !read(b.0, b.1) {
                    continue;
                }
                let d = k * (h[b] - h[a]);
                if d.abs() <= limit {
                    out.steepest = out.steepest.max(d.abs());
                    continue;
                }
                let remainder = period - d.abs();
                if remainder <= limit {
                    out.steps += 1;
                    out.steepest = out.steepest.max(remainder.max(0.0));
                } else {
                    out.slopes += 1;
                    if d.abs() > out.worst.0 {
                        out.worst = (d.abs(), i, j);
                    }
                }
            }
        }
    }
    out
}

/// The phase changes ([`phase_changes`]) of the DOE's own samples inside the aperture (valid
/// and finite ones), at `k` radians per metre of height.
fn doe_phase_changes(system: &OpticalSystem, doe: &Grid, k: f64) -> PhaseChanges {
    let (rows, cols) = doe.dim();
    let [px, py] = doe.pitch();
    let r2 = (system.aperture * 0.5).powi(2);
    let (ci, cj) = ((rows as f64 - 1.0) * 0.5, (cols as f64 - 1.0) * 0.5);
    let h = doe.values();
    let read = |i: usize, j: usize| {
        let (x, y) = ((j as f64 - cj) * px, (i as f64 - ci) * py);
        x * x + y * y <= r2 && doe.is_valid(i, j) && h[[i, j]].is_finite()
    };
    phase_changes(h.view(), &read, k)
}

/// Phase checks on pupil heights (metres) at `pitch`, with the DOE's bandwidth.
///
/// The phase change between neighbouring samples inside the aperture, `k (n - 1) dh`, must
/// stay within pi (Nyquist) unless it is a step of a wrapped or quantized surface
/// ([`phase_changes`]): a slope over pi is refused (`phase_gradient`), a step is exact. The
/// bandwidth is the largest local frequency of the phase, its steepest resolved change (across
/// a step, the step less its period) over `2 pi dx`.
///
/// A stepped DOE is piecewise constant per sample, so a pupil that interpolates it (any pupil
/// but the DOE's own samples, or, with nearest interpolation, `k x k` samples nested in each of
/// them: [`crate::optics::system::nested_refinement`]) reads a surface the part does not have:
/// a ramp across each step, or a step moved by up to half a pupil sample (`step_resampling`).
///
/// A pupil coarser than the DOE's own samples reads the surface at fewer points than the
/// design holds, and `exp(i phi)` spreads beyond its local frequency (Carson's rule: by the
/// modulating frequency again), so that spread aliases onto the sensor: there the step must
/// stay within pi / 2 (`pupil_resampling`). `bench stability`'s matrix-DFT maps found pupils of
/// 6.5 and 9 um on a DOE sampled at 0.8 um (2 to 2.8 rad per sample), which the pi rule
/// accepted, 1.3e-2 to 8e-2 off their truth; within pi / 2 the worst was 9.7e-3. At the DOE's
/// own pitch the pupil is the design's samples and the pi rule holds.
pub(crate) fn pupil_phase(
    system: &OpticalSystem,
    doe: &Grid,
    n: usize,
    pitch: f64,
    wavelength: f64,
) -> Result<(f64, Vec<Violation>)> {
    let h = system.pupil_heights(doe, n, pitch)?;
    let k = 2.0 * PI / wavelength * (system.material.index(wavelength)? - 1.0);
    let r2 = (system.aperture * 0.5).powi(2);
    let c = (n as f64 - 1.0) * 0.5;
    let inside = |i: usize, j: usize| {
        let (x, y) = ((j as f64 - c) * pitch, (i as f64 - c) * pitch);
        x * x + y * y <= r2
    };
    let pupil = phase_changes(h.view(), &inside, k);
    let steepest = pupil.steepest;
    let bandwidth = steepest / (2.0 * PI * pitch);
    let mut out = Vec::new();
    let doe_pitch = doe.pitch()[0].min(doe.pitch()[1]);
    let nested = system.interpolation == Interpolation::Nearest
        && nested_refinement(doe, pitch).is_some_and(|k| nested_parity(doe, k) == n % 2);
    if !takes_doe_samples(doe, n, pitch) && !nested {
        let steps = doe_phase_changes(system, doe, k).steps;
        if steps > 0 {
            out.push(Violation::new(
                "step_resampling",
                wavelength,
                format!(
                    "the DOE steps by about its height span between {steps} pairs of neighbouring samples (a \
                     wrapped or quantized surface, piecewise constant per sample as the part is made): {} \
                     interpolation onto the {:.3} um pupil reads across its steps; sample the pupil at the \
                     DOE's {:.3} um pitch, or at a whole fraction of it with nearest interpolation",
                    format!("{:?}", system.interpolation).to_lowercase(),
                    pitch * 1e6,
                    doe_pitch * 1e6
                ),
            ));
        }
    }
    let coarser = doe.pitch().iter().any(|p| pitch > p * (1.0 + 1e-9));
    if coarser && pupil.slopes == 0 && steepest > 0.5 * PI * (1.0 + 1e-9) {
        out.push(Violation::new(
            "pupil_resampling",
            wavelength,
            format!(
                "the {:.3} um pupil is coarser than the DOE's {:.3} um samples and its phase changes by up to \
                 {steepest:.2} rad (> pi/2) between neighbouring samples: the surface's spectrum aliases \
                 onto the sensor; sample the pupil at the DOE's pitch",
                pitch * 1e6,
                doe_pitch * 1e6
            ),
        ));
    }
    out.extend((pupil.slopes > 0).then(|| {
        let (worst, i, j) = pupil.worst;
        Violation::new(
            "phase_gradient",
            wavelength,
            format!(
                "the DOE phase changes by more than pi between {} pairs of neighbouring pupil samples \
                 at {:.3} um pitch (worst {worst:.2} rad at row {i}, column {j}) along a slope, not by a step of \
                 about the surface's height span ({} such steps, which are exact): the slope is undersampled",
                pupil.slopes,
                pitch * 1e6,
                pupil.steps
            ),
        )
    }));
    Ok((bandwidth, out))
}

/// Lens-phase sampling: the field just after the lens carries the lens phase's local
/// frequency at the aperture edge, `D / (2 lambda g)` paraxially (`r / (lambda sqrt(r^2 + g^2))`
/// at `r = D/2` for the hyperbolic lens), plus the DOE phase's own largest local frequency
/// `f_doe`; their sum must stay within the pupil's Nyquist frequency `1 / (2 dx)`. For a flat
/// DOE this is `dx <= lambda F#`. The DOE's share matters near the boundary: `bench stability`
/// found the two-step Fresnel method 1.3e-2 off its exact truth at `dx = 0.97 lambda F#`, where
/// the lens phase alone passes.
pub(crate) fn check_lens_sampling(
    system: &OpticalSystem,
    dx: f64,
    wavelength: f64,
    hyperbolic: bool,
    f_doe: f64,
) -> Option<Violation> {
    let r = system.aperture * 0.5;
    let g = system.focal_length;
    let f_lens = if hyperbolic { r / (wavelength * (r * r + g * g).sqrt()) } else { r / (wavelength * g) };
    let limit = 0.5 / (f_lens + f_doe);
    (dx > limit * (1.0 + 1e-12)).then(|| {
        let what = if f_doe > 0.0 {
            format!(
                "the lens phase's {:.1} cycles/mm at the aperture edge plus the DOE's own {:.1} cycles/mm need a \
                 pupil pitch of at most {:.3} um, not {:.3} um (lambda F# = {:.3} um at F/{:.2})",
                f_lens * 1e-3,
                f_doe * 1e-3,
                limit * 1e6,
                dx * 1e6,
                wavelength * system.f_number() * 1e6,
                system.f_number()
            )
        } else {
            format!(
                "pupil pitch {:.3} um exceeds lambda F# = {:.3} um (F/{:.2})",
                dx * 1e6,
                limit * 1e6,
                system.f_number()
            )
        };
        Violation::new(
            "lens_sampling",
            wavelength,
            format!("the lens phase is undersampled: {what}; sample the pupil finer (raise subsample) or use matrix_dft"),
        )
    })
}

/// The largest spatial frequency the field carries, cycles/m: the DOE phase's largest local
/// frequency `f_doe` plus eight diffraction orders of the aperture edge (`8 / D`), plus the
/// lens's `D / (2 lambda g)` after the lens, at most the pupil's Nyquist frequency `1/(2 dx)`.
pub(crate) fn content_bandwidth(
    system: &OpticalSystem,
    f_doe: f64,
    dx: f64,
    wavelength: f64,
    after_lens: bool,
) -> f64 {
    let mut f = f_doe + 8.0 / system.aperture;
    if after_lens {
        f += system.aperture / (2.0 * wavelength * system.focal_length);
    }
    f.min(1.0 / (2.0 * dx))
}

/// Fresnel-approximation condition for the DOE -> lens step (Goodman, Introduction to Fourier
/// Optics, eq. 4-18, written per plane-wave component): the dropped term of the propagator's
/// phase, `k d_phi theta^4 / 8` for the steepest angle `theta = lambda f_max` the DOE sends,
/// must stay below pi/2 (Rayleigh's quarter wave). Only checked out of focus or for a finite
/// object: at `d_s = g` with a plane wave the sensor records the angular spectrum at the lens,
/// whose intensity free-space propagation over d_phi leaves unchanged in any approximation.
pub(crate) fn check_fresnel(
    system: &OpticalSystem,
    f_doe: f64,
    dx: f64,
    wavelength: f64,
) -> Option<Violation> {
    let in_focus = system.abcd().a.abs() < 1e-9 && system.object_distance.is_none();
    if in_focus {
        return None;
    }
    let theta = wavelength * content_bandwidth(system, f_doe, dx, wavelength, false);
    let k = 2.0 * PI / wavelength;
    let err = k * system.doe_to_lens * theta.powi(4) / 8.0;
    (err > 0.5 * PI).then(|| {
        Violation::new(
            "fresnel_approximation",
            wavelength,
            format!(
                "the Fresnel approximation over d_phi = {:.3} mm drops a phase of {err:.2} rad (> pi/2) \
                 at the DOE's steepest angle {:.4} rad; use angular_spectrum",
                system.doe_to_lens * 1e3,
                theta
            ),
        )
    })
}

/// Output window vs replica period for the transfer-function methods, whose pupil sampled at
/// `dx` makes the focal pattern periodic with period `P = lambda d_s / dx` and whose FFT window
/// `w` wraps light around. The crop must not see a replica (`crop <= P`), and the light must not
/// wrap onto the crop: it reaches `lambda d_s f_c + (D/2) |1 - d_s/g|` from the axis (`f_c` the
/// DOE's bandwidth, the second term the defocused beam's half width), which must stay within
/// `w - crop/2`.
pub(crate) fn check_window(system: &OpticalSystem, dx: f64, w: f64, wavelength: f64) -> Option<Violation> {
    let ds = system.lens_to_sensor;
    let period = wavelength * ds / dx;
    let crop = system.sensor_window();
    let reach = wavelength * ds / (2.0 * dx) + 0.5 * system.aperture * (1.0 - ds / system.focal_length).abs();
    if crop > period || reach > w - 0.5 * crop {
        Some(Violation::new(
            "output_window",
            wavelength,
            format!(
                "the {:.3} mm sensor window does not fit: replica period lambda d_s / dx = {:.3} mm, light \
                 reaching {:.3} mm from the axis in a {:.3} mm FFT window",
                crop * 1e3,
                period * 1e3,
                reach * 1e3,
                w * 1e3
            ),
        ))
    } else {
        None
    }
}
