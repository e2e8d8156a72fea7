//! Propagation from the DOE to the sensor: one file per method, each with the same inputs
//! (an [`OpticalSystem`], a DOE height [`Grid`], [`Options`]) and its own validity checks.
//!
//! * [`matrix_dft`]: the single transform pupil -> sensor (Collins' ABCD integral) evaluated
//!   straight on the sensor sub-samples by a matrix DFT (paraxial).
//! * [`fresnel`]: two-step Fresnel transfer-function propagation with an explicit quadratic
//!   thin-lens phase, as the paper's code (pads N/4 each side; paraxial).
//! * [`asm`]: band-limited angular spectrum (Matsushima and Shimobaba 2009), 2x padding, with a
//!   hyperbolic (aberration-free) lens phase (non-paraxial).
//! * [`rayleigh`]: direct Rayleigh-Sommerfeld integration, slow ground truth on small grids.
//!
//! A configuration outside a method's validity is refused with [`Error::Validity`] naming every
//! violated condition; [`Options::allow_invalid`] runs it anyway and records the violations as
//! warnings in the resulting [`Psf`].
//!
//! Normalisation: each channel of the returned PSF sums to 1 over the crop (as the paper);
//! [`Channel::captured`](super::psf::Channel::captured) keeps the fraction of the power leaving
//! the DOE that lands in the crop, so absolute energies (order efficiencies, Strehl) survive.

pub mod asm;
pub mod fresnel;
pub mod matrix_dft;
pub mod rayleigh;

use std::f64::consts::PI;
use std::fmt;

use ndarray::Array2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::psf::{Channel, Psf};
use super::system::{OpticalSystem, PixelRule};
use crate::error::{Error, Result};
use crate::grid::{Grid, Unit};

/// The propagation methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Single transform pupil -> sensor by matrix DFT ([`matrix_dft`]).
    MatrixDft,
    /// Two-step Fresnel transfer function with a thin-lens phase ([`fresnel`]).
    Fresnel,
    /// Band-limited angular spectrum with a hyperbolic lens phase ([`asm`]).
    AngularSpectrum,
    /// Direct Rayleigh-Sommerfeld integration ([`rayleigh`]).
    RayleighSommerfeld,
}

impl Method {
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

/// Floating-point precision of the matrix products of [`matrix_dft`]; the FFT methods and
/// every phase are computed in `f64`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    /// Single precision: half the memory traffic and twice the SIMD width of `f64`. Its
    /// rounding error (unit roundoff `6e-8` accumulated over sums of ~n/2 terms) stays near
    /// `1e-6` relative L2 on the PSF (measured by the tests and `benches/psf.rs`).
    F32,
    #[default]
    F64,
}

impl Precision {
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
    pub intensity: Array2<f64>,
    pub input_power: f64,
}

/// Every violated validity condition of `method` for `system` and `doe`, all wavelengths.
pub fn check(method: Method, system: &OpticalSystem, doe: &Grid) -> Result<Vec<Violation>> {
    system.validate()?;
    let mut out = Vec::new();
    for &l in &system.wavelengths {
        out.extend(match method {
            Method::MatrixDft => matrix_dft::check(system, doe, l)?,
            Method::Fresnel => fresnel::check(system, doe, l)?,
            Method::AngularSpectrum => asm::check(system, doe, l)?,
            Method::RayleighSommerfeld => rayleigh::check(system, doe, l)?,
        });
    }
    Ok(out)
}

/// The PSF of `doe` in `system` by `method`: checks validity (see the module docs), propagates
/// each wavelength (in parallel), bins the sub-samples into pixels and normalises each channel
/// to sum 1 over the crop.
pub fn simulate(system: &OpticalSystem, doe: &Grid, method: Method, opts: &Options) -> Result<Psf> {
    let violations = check(method, system, doe)?;
    if !violations.is_empty() && !opts.allow_invalid {
        let list: Vec<String> = violations.iter().map(|v| v.to_string()).collect();
        return Err(Error::Validity(format!(
            "method {method} is not valid for this system (run with allow_invalid to force):\n  {}",
            list.join("\n  ")
        )));
    }
    if opts.precision == Precision::F32 && method != Method::MatrixDft {
        return Err(Error::param(
            "precision",
            format!("f32 is implemented for matrix_dft only; {method} computes in f64"),
        ));
    }
    if system.pixel_rule == PixelRule::GaussLegendre
        && matches!(method, Method::Fresnel | Method::AngularSpectrum)
    {
        return Err(Error::param(
            "pixel_rule",
            format!("{method} samples the sensor on its uniform FFT grid: Gauss-Legendre pixel integration needs matrix_dft or rayleigh_sommerfeld"),
        ));
    }
    let fields: Vec<Result<SensorIntensity>> = system
        .wavelengths
        .par_iter()
        .map(|&l| match method {
            Method::MatrixDft => matrix_dft::sensor_intensity(system, doe, l, opts.precision),
            Method::Fresnel => fresnel::sensor_intensity(system, doe, l),
            Method::AngularSpectrum => asm::sensor_intensity(system, doe, l),
            Method::RayleighSommerfeld => rayleigh::sensor_intensity(system, doe, l),
        })
        .collect();
    let mut channels = Vec::new();
    for (k, f) in fields.into_iter().enumerate() {
        let f = f?;
        let l = system.wavelengths[k];
        let (grid, captured) = bin_pixels(system, &f)?;
        channels.push(Channel {
            name: format!("{:.0}nm", l * 1e9),
            wavelength: Some(l),
            grid,
            captured: Some(captured),
        });
    }
    Ok(Psf {
        channels,
        method: method.name().to_string(),
        warnings: violations.iter().map(|v| v.to_string()).collect(),
    })
}

/// Sums `subsample x subsample` blocks of the sub-sample intensity, each sample times its
/// quadrature weight, into pixels and normalises
/// to sum 1; returns the pixel grid and the captured fraction of the input power.
fn bin_pixels(system: &OpticalSystem, f: &SensorIntensity) -> Result<(Grid, f64)> {
    let (c, s) = (system.crop, system.subsample);
    let w = system.pixel_weights();
    let mut px = Array2::<f64>::zeros((c, c));
    for ((i, j), v) in f.intensity.indexed_iter() {
        px[[i / s, j / s]] += w[i] * w[j] * v;
    }
    let total: f64 = px.sum();
    let p = system.sensor_pitch;
    let captured = total * p * p / f.input_power;
    if !(total > 0.0 && total.is_finite()) {
        return Err(Error::Data(format!("no light reaches the {c} x {c} sensor window (total {total})")));
    }
    px.mapv_inplace(|v| v / total);
    Ok((Grid::new(px, [system.sensor_pitch; 2], Unit::Dimensionless)?, captured))
}

/// Power carried by a sampled field, `sum |u|^2 dx^2`.
pub fn field_power(u: &Array2<rustfft::num_complex::Complex64>, dx: f64) -> f64 {
    u.iter().map(|v| v.norm_sqr()).sum::<f64>() * dx * dx
}

/// Phase-gradient check on pupil heights (metres) at `pitch`, with the DOE's bandwidth.
///
/// The phase step between neighbouring samples inside the aperture, `k (n - 1) dh`, must stay
/// within pi (Nyquist) unless it is a wrap step, i.e. at least 3 pi / 2 in size and within
/// pi / 2 of a multiple of 2 pi (a phase-wrapped DOE's zone edges, harmless in `exp(i phi)`).
/// The bandwidth is the largest local frequency of the phase, `|step mod 2 pi| / (2 pi dx)`.
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
    let mut bad = 0usize;
    let mut worst = (0.0f64, 0usize, 0usize);
    let mut steepest = 0.0f64;
    for i in 0..n {
        for j in 0..n {
            if !inside(i, j) {
                continue;
            }
            for (a, b) in [(i + 1, j), (i, j + 1)] {
                if a >= n || b >= n || !inside(a, b) {
                    continue;
                }
                let d = k * (h[[a, b]] - h[[i, j]]);
                let r = d - 2.0 * PI * (d / (2.0 * PI)).round();
                steepest = steepest.max(r.abs());
                // Tolerances keep exact steps (pi, 3 pi / 2 of a staircase) on the valid side.
                let ok = d.abs() <= PI * (1.0 + 1e-9)
                    || (d.abs() >= 1.5 * PI * (1.0 - 1e-9) && r.abs() <= 0.5 * PI * (1.0 + 1e-9));
                if !ok {
                    bad += 1;
                    if d.abs() > worst.0 {
                        worst = (d.abs(), i, j);
                    }
                }
            }
        }
    }
    let bandwidth = steepest / (2.0 * PI * pitch);
    let mut out = Vec::new();
    let coarser = doe.pitch().iter().any(|p| pitch > p * (1.0 + 1e-9));
    if coarser && bad == 0 && steepest > 0.5 * PI * (1.0 + 1e-9) {
        out.push(Violation::new(
            "pupil_resampling",
            wavelength,
            format!(
                "the {:.3} um pupil is coarser than the DOE's {:.3} um samples and its phase changes by up to \
                 {steepest:.2} rad (> pi/2) between neighbouring samples: the surface's spectrum aliases \
                 onto the sensor; sample the pupil at the DOE's pitch",
                pitch * 1e6,
                doe.pitch()[0].min(doe.pitch()[1]) * 1e6
            ),
        ));
    }
    out.extend((bad > 0).then(|| {
        Violation::new(
            "phase_gradient",
            wavelength,
            format!(
                "the DOE phase changes by more than pi between {bad} pairs of neighbouring pupil samples \
                 at {:.3} um pitch (worst {:.2} rad at row {}, column {}): the pupil is undersampled",
                pitch * 1e6,
                worst.0,
                worst.1,
                worst.2
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
