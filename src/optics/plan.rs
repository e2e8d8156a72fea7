//! The automatic plan: model no more than a scene needs. Given the physical system, the DOE,
//! the colour channels (wavelengths or spectral [`Band`]s) and a tolerance on the relative L2
//! error of each channel, [`plan`] picks the method, pupil sampling, padding, pixel
//! sub-sampling, precision and number of spectral samples: the cheapest configuration whose
//! *estimated* error is within the tolerance, each choice with the condition that bounds it
//! ([`Plan::choices`]).
//!
//! Error estimates (relative L2 per channel, summed over the terms: a triangle inequality):
//!
//! * Pixel integration by `s x s` midpoint sub-samples of spacing `h = p / s`. A spatial
//!   frequency `f` of the intensity is integrated over the pixel with the factor
//!   `pi f h / sin(pi f h)` relative to the exact box integral. The intensity spectrum is the
//!   autocorrelation of the pupil, so for any phase-only DOE `|I^(f)| <= OTF_0(f)`, the
//!   aberration-free OTF of the circular aperture with cutoff `f_c = D / (lambda |B|)`
//!   (Goodman, Introduction to Fourier Optics, sec. 6.4). The estimate is the
//!   `OTF_0^2`-weighted RMS of `g(f_x h) g(f_y h) - 1` (a diffraction-limited spectrum). Where
//!   `f_c h >= 1` the sub-samples alias the intensity and the estimate is infinite.
//! * Precision: `f32` products carry about `u sqrt(n + M)` relative error (`u = 2^-24`,
//!   `n` pupil and `M` sensor samples per side; measured ten times below this in
//!   `benches/psf.rs`), `f64` none worth counting.
//! * Spectral samples: the composite midpoint rule over `N` sub-bands of a band of width `W`
//!   errs by `W delta^2 / 24 f''` for the weighted PSF `f(lambda) = R(lambda) I_lambda`,
//!   `delta = W / N`. A pilot run at the band's edges and centre measures the second
//!   difference `D2 = f(lo) - 2 f(mid) + f(hi) = (W/2)^2 f''`, so the relative error is
//!   `||D2|| / (6 N^2 ||f_mean||)`, `f_mean` Simpson's mean of the three. It sees the pattern's
//!   scaling with wavelength, the DOE's dispersion and the response's curvature together;
//!   variation finer than half the band (a response with narrow features) it cannot see.
//!   `bench spectral` measures it against the rule's converged result: on the bench scene
//!   with the paper's channels as 80 nm bands, too high by 4-18x from 9 sub-bands on, and up
//!   to 1.8x too low at 3 (before the rule's `N^-2` regime).
//!
//! Method: [`Method::MatrixDft`] at the DOE's own pitch (its samples, no interpolation) when
//! valid; otherwise at the DOE pitch divided by the smallest integer that satisfies its
//! sampling conditions; [`Method::AngularSpectrum`] (2x padding) where the paraxial method
//! is invalid or it costs less. Cost is counted in real multiply-adds.

use std::f64::consts::PI;
use std::ops::Bound;

use serde::{Deserialize, Serialize};

use super::propagate::{self, asm, matrix_dft, Method, Options, Precision, Violation};
use super::psf::{Channel, Psf};
use super::spectrum::{combine, Band};
use super::system::{sinc, OpticalSystem, PixelRule};
use crate::error::{Allowed, Condition, Error, Result};
use crate::grid::{Grid, Interpolation};

/// The default tolerance of `doefab psf`: relative L2 error per channel.
pub const DEFAULT_TOLERANCE: f64 = 1e-3;
/// The largest pixel sub-sampling and pupil refinement the plan considers.
const MAX_SUBSAMPLE: usize = 32;
const MAX_REFINE: usize = 8;
/// The most spectral samples per band the plan considers.
pub const MAX_SPECTRAL: usize = 64;
/// The largest pupil or FFT grid side the plan and `bench psf` run (memory: 16 bytes a
/// sample, a few such arrays at once: about 5 GB at this side).
pub const MAX_SIDE: usize = 8192;

/// One choice of the plan with the condition that bounds it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Choice {
    /// What was chosen ("method", "pupil pitch", "pixel integration", "padding",
    /// "precision", "spectral samples", "spectral check").
    pub what: String,
    /// The value taken, as text with its unit ("matrix_dft", "4.2900 um", "2x").
    pub value: String,
    /// The condition that bounds it, with the numbers.
    pub because: String,
}

/// Estimated relative L2 error of each term and their sum.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    /// Error of integrating each pixel by its sub-samples (module docs), relative L2.
    pub pixel_integration: f64,
    /// Rounding error of `f32` products, `u sqrt(n + M)`; 0 in `f64`.
    pub precision: f64,
    /// Error of the composite midpoint rule over the spectral samples of a band, from the
    /// pilot run or, once run, the run's own check; 0 for plain wavelengths.
    pub spectral: f64,
    /// The sum of the three (a triangle inequality), relative L2.
    pub total: f64,
}

/// A configuration the plan chose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    /// The tolerance planned for: relative L2 error per channel, in (0, 1).
    pub tolerance: f64,
    /// The propagation method chosen.
    pub method: Method,
    /// Precision of the matrix products (`f32` only for the matrix DFT).
    pub precision: Precision,
    /// The system with the chosen pupil pitch, sub-sampling and the wavelengths to simulate.
    pub system: OpticalSystem,
    /// Spectral samples per band (1 for plain wavelengths).
    pub spectral_samples: usize,
    /// FFT window over pupil window (1 = none, the matrix DFT needs none).
    pub padding: f64,
    /// Estimated relative L2 error of each term of the configuration.
    pub estimate: Estimate,
    /// Real multiply-adds of the run (all wavelengths).
    pub cost: f64,
    /// Each choice with the condition that bounds it, in the order made.
    pub choices: Vec<Choice>,
}

impl Plan {
    /// The choices as lines of text.
    pub fn explain(&self) -> String {
        let mut s = format!(
            "plan for tolerance {:.1e}: estimated error {:.2e} (pixels {:.1e}, precision {:.1e}, spectrum {:.1e}), {:.2e} multiply-adds\n",
            self.tolerance,
            self.estimate.total,
            self.estimate.pixel_integration,
            self.estimate.precision,
            self.estimate.spectral,
            self.cost
        );
        for c in &self.choices {
            s.push_str(&format!("  {:<18} {:<22} {}\n", c.what, c.value, c.because));
        }
        s
    }
}

/// The cost of the matrix DFT of `n x n` pupil samples onto `m x m` sensor samples, one
/// wavelength in f64, real multiply-adds: `n^2 m + n m^2` (its two products).
pub fn matrix_dft_cost(n: usize, m: usize) -> f64 {
    let (n, m) = (n as f64, m as f64);
    n * n * m + n * m * m
}

/// The cost of a transfer-function method on a `w x w` FFT window, one wavelength, real
/// multiply-adds: two steps of a forward and an inverse complex FFT, `5 N log2 N` flops each
/// (about `2.5 N log2 N` multiply-adds, `N = w^2`).
pub fn fft_cost(w: usize) -> f64 {
    let n = (w * w) as f64;
    4.0 * 2.5 * n * n.log2()
}

/// The estimated pixel-integration error of `s` sub-samples per axis by `rule` for pixels of
/// `pitch` and an intensity band-limited to `cutoff` cycles/m (see the module docs): the
/// `OTF_0^2`-weighted RMS of `b_s(f_x) b_s(f_y) - b(f_x) b(f_y)` over that of `b(f_x) b(f_y)`,
/// with `b(f) = sinc(f p)` the exact pixel integral of `exp(2 pi i f x)` and
/// `b_s(f) = sum_k w_k cos(2 pi f x_k)` the rule's.
pub fn pixel_error(rule: PixelRule, pitch: f64, s: usize, cutoff: f64) -> f64 {
    let probe = OpticalSystem {
        crop: 1,
        subsample: s,
        sensor_pitch: pitch,
        pixel_rule: rule,
        ..OpticalSystem::default()
    };
    let (xs, ws) = (probe.sensor_coords(), probe.pixel_weights());
    let rule_b = |f: f64| xs.iter().zip(&ws).map(|(x, w)| w * (2.0 * PI * f * x).cos()).sum::<f64>();
    let otf = |nu: f64| if nu >= 1.0 { 0.0 } else { 2.0 / PI * (nu.acos() - nu * (1.0 - nu * nu).sqrt()) };
    let k = 128;
    let f: Vec<f64> = (0..k).map(|a| (a as f64 + 0.5) / k as f64 * cutoff).collect();
    let exact: Vec<f64> = f.iter().map(|&f| sinc(f * pitch)).collect();
    let approx: Vec<f64> = f.iter().map(|&f| rule_b(f)).collect();
    let (mut num, mut den) = (0.0, 0.0);
    for a in 0..k {
        for b in 0..k {
            let w = otf((f[a] * f[a] + f[b] * f[b]).sqrt() / cutoff).powi(2);
            num += w * (approx[a] * approx[b] - exact[a] * exact[b]).powi(2);
            den += w * (exact[a] * exact[b]).powi(2);
        }
    }
    (num / den).sqrt()
}

/// The estimated error of `f32` products for `n` pupil and `m` sensor samples per side.
pub fn f32_error(n: usize, m: usize) -> f64 {
    2f64.powi(-24) * ((n + m) as f64).sqrt()
}

/// The estimated relative error of `n` midpoint sub-bands for a band whose pilot PSFs
/// (absolute intensities times the response) at its low edge, centre and high edge are
/// `f` (see the module docs).
pub fn spectral_error(f: [&ndarray::Array2<f64>; 3], n: usize) -> f64 {
    let d2 = f[0] - &(f[1] * 2.0) + f[2];
    let mean = (f[0] + &(f[1] * 4.0) + f[2]) / 6.0;
    let norm = |a: &ndarray::Array2<f64>| a.iter().map(|v| v * v).sum::<f64>().sqrt();
    norm(&d2) / (6.0 * (n * n) as f64 * norm(&mean))
}

/// The spectral count the plan starts a run with (see [`spectral_count`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SpectralCount {
    /// The smallest count whose estimate is within the budget, the largest over the bands.
    pub needed: usize,
    /// That band's estimate at `needed`.
    pub estimate: f64,
    /// That band's name.
    pub band: String,
    /// The nearest cheaper counts of that band with their estimates, as text.
    pub rejected: String,
}

impl SpectralCount {
    /// `needed` rounded up to a multiple of 3, so that [`run`] can check the result against
    /// its own middle thirds. (A multiple of 9, whose first check can also compare the middle
    /// thirds with theirs, was measured and left: on `built-in:paper` at 1e-3 it refused where
    /// this settles on 90; README, Spectral bands.)
    pub fn start(&self) -> usize {
        self.needed.div_ceil(3) * 3
    }
}

/// The plan's spectral rule for bands whose pilots (absolute intensities times the response at
/// each band's low edge, centre and high edge) are `pilots`, named: per band the smallest
/// number of midpoint sub-bands whose estimate ([`spectral_error`]) is within `budget`, up to
/// [`MAX_SPECTRAL`] (beyond, an error naming the band), and the largest of them.
pub fn spectral_count<'a>(
    pilots: impl IntoIterator<Item = (&'a str, [&'a ndarray::Array2<f64>; 3])>,
    budget: f64,
) -> Result<SpectralCount> {
    let mut worst = SpectralCount { needed: 0, estimate: 0.0, band: String::new(), rejected: String::new() };
    for (name, f) in pilots {
        let n = (1..=MAX_SPECTRAL).find(|&n| spectral_error(f, n) <= budget).ok_or_else(|| {
            Error::validity(Condition::Sampling, format!(
                "band '{name}' would need more than {MAX_SPECTRAL} spectral samples for an error within {budget:.1e}"
            ))
        })?;
        if n > worst.needed {
            let rejected = (n.saturating_sub(3).max(1)..n)
                .map(|m| format!("{m}: {:.1e}", spectral_error(f, m)))
                .collect::<Vec<_>>()
                .join(", ");
            worst = SpectralCount { needed: n, estimate: spectral_error(f, n), band: name.into(), rejected };
        }
    }
    Ok(worst)
}

/// The plan for `doe` in `system` (its aperture, distances, lens, sensor, material; its
/// `pupil_pitch` and `subsample` are chosen here) with the colour channels `bands` (each
/// simulated at its spectral samples) or, when `bands` is empty, the system's wavelengths.
pub fn plan(system: &OpticalSystem, doe: &Grid, bands: &[Band], tolerance: f64) -> Result<Plan> {
    if !(tolerance > 0.0 && tolerance < 1.0) {
        return Err(Error::param_in(
            "tolerance",
            Allowed::within(Bound::Excluded(0.0), Bound::Excluded(1.0)),
            format!("must lie in (0, 1), got {tolerance}"),
        ));
    }
    system.validate()?;
    let mut choices = Vec::new();
    // Shortest and longest wavelength: every validity condition is monotone in the wavelength.
    let (lmin, lmax) = wavelength_range(system, bands)?;
    let extremes = OpticalSystem { wavelengths: vec![lmin, lmax], ..system.clone() };
    let b = extremes.abcd().b.abs();
    let cutoff = system.aperture / (lmin * b);

    // Pixel sub-sampling: the smallest s per rule whose estimate takes at most half the
    // tolerance (Gauss-Legendre for the matrix DFT, the midpoint rule for the FFT methods).
    let subsample = |rule: PixelRule| least_subsample(rule, system.sensor_pitch, cutoff, tolerance);
    let (s_gl, s_mid) = (subsample(PixelRule::GaussLegendre)?, subsample(PixelRule::Midpoint));

    // Method and pupil sampling.
    let (matrix, mut refusals) = matrix_dft_candidate(&extremes, doe, s_gl)?;
    // The angular spectrum samples the pupil at the sensor sub-sample pitch, the midpoint rule.
    let s_mid = match s_mid {
        Ok(s) => s,
        Err(e) => {
            refusals.push(format!("angular_spectrum: {e}"));
            usize::MAX
        }
    };
    let (asm, asm_refusals) = angular_spectrum_candidate(&extremes, doe, s_mid)?;
    refusals.extend(asm_refusals);
    let mut candidates: Vec<Candidate> = matrix.into_iter().chain(asm).collect();
    candidates.sort_by(|a, b| a.2.total_cmp(&b.2));
    let Some((method, chosen, mut cost, why)) = candidates.first().cloned() else {
        return Err(Error::validity(
            Condition::Propagation,
            format!("no method is valid for this system:\n  {}", refusals.join("\n  ")),
        ));
    };
    let others: Vec<String> = candidates[1..]
        .iter()
        .map(|c| format!("{} costs {:.1e}", c.0, c.2))
        .chain(refusals.iter().cloned())
        .collect();
    choices.push(choice(
        "method",
        method.name().into(),
        format!(
            "cheapest valid ({:.1e} multiply-adds per wavelength){}",
            cost,
            if others.is_empty() { String::new() } else { format!("; {}", others.join("; ")) }
        ),
    ));
    choices.push(choice(
        "pupil pitch",
        format!(
            "{:.4} um",
            if method == Method::MatrixDft { chosen.pupil_pitch } else { chosen.sample_pitch() } * 1e6
        ),
        why,
    ));
    let (e_pix, pixels) = pixel_choice(&chosen, system.sensor_pitch, cutoff, lmin);
    choices.push(pixels);
    let padding = if method == Method::MatrixDft { 1.0 } else { 2.0 };
    choices.push(choice(
        "padding",
        if padding == 1.0 { "none".into() } else { "2x".into() },
        if padding == 1.0 {
            "the matrix DFT evaluates the sensor samples directly: no FFT window to wrap".into()
        } else {
            "band-limited angular spectrum: Q = 2 keeps the linear convolution (Matsushima and Shimobaba 2009)".into()
        },
    ));

    // Precision.
    let (n, m) = (matrix_dft::pupil_grid(&chosen, doe).0, chosen.samples());
    let (precision, e_prec, because) = choose_precision(method, n, m, tolerance);
    choices.push(choice("precision", precision.name().into(), because));
    if precision == Precision::F32 {
        cost *= 0.5;
    }

    // Spectral samples: what remains of the tolerance.
    let remaining = tolerance - e_pix - e_prec;
    let (samples, e_spec, wavelengths) = if bands.is_empty() {
        choices.push(choice("spectral samples", "1 per channel".into(), "monochromatic channels".into()));
        (1, 0.0, system.wavelengths.clone())
    } else {
        let (n, estimate, because) = spectral_choice(&chosen, doe, bands, method, precision, remaining)?;
        choices.push(choice("spectral samples", format!("{n} per band (to start)"), because));
        let wl = bands.iter().flat_map(|b| b.samples(n)).map(|s| s.0).collect();
        (n, estimate, wl)
    };
    cost *= wavelengths.len() as f64;
    let system = OpticalSystem { wavelengths, ..chosen };
    Ok(Plan {
        tolerance,
        method,
        precision,
        system,
        spectral_samples: samples,
        padding,
        estimate: Estimate {
            pixel_integration: e_pix,
            precision: e_prec,
            spectral: e_spec,
            total: e_pix + e_prec + e_spec,
        },
        cost,
        choices,
    })
}

/// A [`Choice`] from its parts.
fn choice(what: &str, value: String, because: String) -> Choice {
    Choice { what: what.into(), value, because }
}

/// A method the plan found valid: the method, the system it runs (pupil pitch, sub-sampling,
/// pixel rule at the extreme wavelengths), its cost per wavelength and why that sampling.
type Candidate = (Method, OpticalSystem, f64, String);

/// The shortest and longest wavelength the plan must hold: the bands' edges (each checked
/// against the material's dispersion formula), or the system's wavelengths without bands.
fn wavelength_range(system: &OpticalSystem, bands: &[Band]) -> Result<(f64, f64)> {
    let mut edges: Vec<f64> = system.wavelengths.clone();
    for b in bands {
        let (lo, hi) = b.range();
        for l in [lo, hi] {
            system.material.index(l).map_err(|e| Error::param("band", format!("band '{}': {e}", b.name)))?;
        }
        edges.extend([lo, hi]);
    }
    if !bands.is_empty() {
        edges.drain(..system.wavelengths.len());
    }
    let lmin = edges.iter().copied().fold(f64::INFINITY, f64::min);
    let lmax = edges.iter().copied().fold(0.0, f64::max);
    Ok((lmin, lmax))
}

/// The smallest pixel sub-sampling by `rule` whose estimated error ([`pixel_error`], pixels of
/// `pitch`, intensity band limit `cutoff`) takes at most half the `tolerance`, up to
/// [`MAX_SUBSAMPLE`].
fn least_subsample(rule: PixelRule, pitch: f64, cutoff: f64, tolerance: f64) -> Result<usize> {
    let share = 0.5 * tolerance;
    (1..=MAX_SUBSAMPLE).find(|&s| pixel_error(rule, pitch, s, cutoff) <= share).ok_or_else(|| {
        Error::validity(Condition::Sampling, format!(
            "pixel integration by {rule:?} would need more than {MAX_SUBSAMPLE} sub-samples per pixel for a tolerance of {tolerance:e}"
        ))
    })
}

/// The matrix DFT at the DOE's pitch divided by the smallest `k <= MAX_REFINE` at which every
/// sampling condition holds (a stepped DOE read by nearest interpolation), `s_gl`
/// Gauss-Legendre sub-samples per pixel; else the reasons it is refused.
fn matrix_dft_candidate(
    extremes: &OpticalSystem,
    doe: &Grid,
    s_gl: usize,
) -> Result<(Option<Candidate>, Vec<String>)> {
    let doe_pitch = doe.pitch()[0].min(doe.pitch()[1]);
    let base = OpticalSystem { subsample: s_gl, pixel_rule: PixelRule::GaussLegendre, ..extremes.clone() };
    let mut refusals: Vec<String> = Vec::new();
    let mut last: Vec<Violation> = Vec::new();
    for k in 1..=MAX_REFINE {
        let mut s = OpticalSystem { pupil_pitch: doe_pitch / k as f64, ..base.clone() };
        let n = matrix_dft::pupil_grid(&s, doe).0;
        if n > MAX_SIDE {
            refusals.push(format!(
                "matrix_dft: a {n} x {n} pupil (DOE pitch / {k}) exceeds {MAX_SIDE} x {MAX_SIDE}"
            ));
            break;
        }
        let mut v = propagate::check(Method::MatrixDft, &s, doe)?;
        // A stepped DOE is read by nearest interpolation, k x k pupil samples in each of its
        // samples: the piecewise-constant part, its steps kept.
        let stepped = v.iter().any(|v| v.condition == "step_resampling");
        if stepped && s.interpolation != Interpolation::Nearest {
            s.interpolation = Interpolation::Nearest;
            v = propagate::check(Method::MatrixDft, &s, doe)?;
        }
        if v.is_empty() {
            let (n, _) = matrix_dft::pupil_grid(&s, doe);
            let cost = matrix_dft_cost(n, s.samples());
            let why = if k == 1 {
                format!(
                    "the DOE's own {:.3} um samples: no interpolation, every condition holds",
                    doe_pitch * 1e6
                )
            } else {
                format!(
                    "DOE pitch / {k} ({}): at / {} {}",
                    if stepped {
                        "nearest, the DOE's steps kept: a pixelated part's surface".to_string()
                    } else {
                        format!("{:?}", s.interpolation).to_lowercase()
                    },
                    k - 1,
                    last.iter().map(|v| v.condition.as_str()).collect::<Vec<_>>().join(", ")
                )
            };
            return Ok((Some((Method::MatrixDft, s, cost, why)), refusals));
        }
        // Conditions no pupil refinement fixes.
        if v.iter().any(|v| v.condition == "fresnel_approximation" || v.condition == "imaging_condition") {
            refusals.push(format!("matrix_dft: {}", v[0]));
            break;
        }
        last = v;
    }
    if refusals.is_empty() {
        refusals.push(format!(
            "matrix_dft: still invalid at DOE pitch / {MAX_REFINE}: {}",
            last.first().map_or(String::new(), |v| v.to_string())
        ));
    }
    Ok((None, refusals))
}

/// The band-limited angular spectrum with the pupil at the sensor sub-sample pitch, `s_mid`
/// midpoint sub-samples per pixel (none: `usize::MAX`) times the smallest factor up to
/// [`MAX_REFINE`] at which its conditions hold; else the reasons it is refused.
fn angular_spectrum_candidate(
    extremes: &OpticalSystem,
    doe: &Grid,
    s_mid: usize,
) -> Result<(Option<Candidate>, Vec<String>)> {
    let mut refusals = Vec::new();
    for extra in (1..=MAX_REFINE).take_while(|_| s_mid != usize::MAX) {
        let s =
            OpticalSystem { subsample: s_mid * extra, pixel_rule: PixelRule::Midpoint, ..extremes.clone() };
        let w = asm::grid(&s).2;
        if w > MAX_SIDE {
            refusals.push(format!(
                "angular_spectrum: {s_mid} x {extra} sub-samples per pixel need a {w} x {w} FFT, over {MAX_SIDE} x {MAX_SIDE}"
            ));
            break;
        }
        let v = propagate::check(Method::AngularSpectrum, &s, doe)?;
        if v.is_empty() {
            let cost = fft_cost(asm::grid(&s).2);
            let why = format!(
                "pupil at the sensor sub-sample pitch {:.3} um{}, 2x padding",
                s.sample_pitch() * 1e6,
                if extra > 1 {
                    format!(" ({extra} x the pixel estimate's sub-samples, for its conditions)")
                } else {
                    String::new()
                }
            );
            return Ok((Some((Method::AngularSpectrum, s, cost, why)), refusals));
        }
        if extra == MAX_REFINE || v.iter().all(|v| v.condition == "phase_gradient" && extra > 4) {
            refusals.push(format!("angular_spectrum: {}", v[0]));
            break;
        }
    }
    Ok((None, refusals))
}

/// The pixel integration of the `chosen` system: its estimated error (pixels of `pitch`,
/// intensity band limit `cutoff` at the shortest wavelength `lmin`) and the choice, naming
/// every cheaper sub-sampling rejected with its estimate.
fn pixel_choice(chosen: &OpticalSystem, pitch: f64, cutoff: f64, lmin: f64) -> (f64, Choice) {
    let e_pix = pixel_error(chosen.pixel_rule, pitch, chosen.subsample, cutoff);
    // Every cheaper sub-sampling, rejected, with its estimate.
    let rejected: Vec<String> = (1..chosen.subsample)
        .map(|s| format!("{s} x {s}: {:.1e}", pixel_error(chosen.pixel_rule, pitch, s, cutoff)))
        .collect();
    let c = choice(
        "pixel integration",
        format!("{:?} {} x {}", chosen.pixel_rule, chosen.subsample, chosen.subsample),
        format!(
            "intensity band limit D / (lambda |B|) = {:.1} cycles/mm at {:.0} nm: estimate {:.1e} <= tolerance / 2{}",
            cutoff * 1e-3,
            lmin * 1e9,
            e_pix,
            if rejected.is_empty() {
                String::new()
            } else {
                format!("; cheaper, rejected: {}", rejected.join(", "))
            }
        ),
    );
    (e_pix, c)
}

/// The precision of a run by `method` with `n` pupil and `m` sensor samples per side: `f32`
/// for the matrix DFT when its rounding estimate ([`f32_error`]) is within a tenth of the
/// `tolerance`, else `f64` (whose error is not counted); with the estimate and why.
fn choose_precision(method: Method, n: usize, m: usize, tolerance: f64) -> (Precision, f64, String) {
    let e32 = f32_error(n, m);
    let (precision, e_prec) = if method == Method::MatrixDft && e32 <= 0.1 * tolerance {
        (Precision::F32, e32)
    } else {
        (Precision::F64, 0.0)
    };
    let because = if method != Method::MatrixDft {
        format!("{method} computes in f64")
    } else {
        format!(
            "f32 rounding estimate u sqrt(n + M) = {e32:.1e} {} tolerance / 10",
            if precision == Precision::F32 { "<=" } else { ">" }
        )
    };
    (precision, e_prec, because)
}

/// The spectral samples per band to start a run with: a pilot run of the `chosen` system at
/// each band's edges and centre, the count of [`spectral_count`] within the `remaining`
/// tolerance rounded up to a multiple of 3; the count, its estimate and why.
fn spectral_choice(
    chosen: &OpticalSystem,
    doe: &Grid,
    bands: &[Band],
    method: Method,
    precision: Precision,
    remaining: f64,
) -> Result<(usize, f64, String)> {
    let mut pilots = Vec::new();
    for b in bands {
        let (lo, hi) = b.range();
        let pilot_system = OpticalSystem { wavelengths: vec![lo, 0.5 * (lo + hi), hi], ..chosen.clone() };
        let opts = Options { allow_invalid: false, precision };
        let pilot = propagate::simulate(&pilot_system, doe, method, &opts)?;
        let f: Vec<ndarray::Array2<f64>> = pilot
            .channels
            .iter()
            .zip(&pilot_system.wavelengths)
            .map(|(c, &l)| c.grid.values() * (c.captured.unwrap_or(1.0) * b.response_at(l)))
            .collect();
        pilots.push(f);
    }
    let count = spectral_count(
        bands.iter().zip(&pilots).map(|(b, f)| (b.name.as_str(), [&f[0], &f[1], &f[2]])),
        remaining,
    )?;
    let because = format!(
        "midpoint rule, band '{}' (pilot at its edges and centre): estimate {:.1e} at {} <= the remaining {:.1e}{}; \
         rounded up to a multiple of 3, checked by the run against its own middle thirds and tripled until \
         they agree",
        count.band,
        count.estimate,
        count.needed,
        remaining,
        if count.rejected.is_empty() { String::new() } else { format!(" (cheaper, rejected: {})", count.rejected) }
    );
    Ok((count.start(), count.estimate, because))
}

/// The most spectral samples per band [`run`] refines to.
pub const MAX_SPECTRAL_CHECKED: usize = 243;

/// The cheaper pixel sub-samplings the plan rejected, measured rather than estimated.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheaperMeasured {
    /// The plan's tolerance, relative L2 error per channel.
    pub tolerance: f64,
    /// The plan's sub-samples per pixel and axis.
    pub chosen: usize,
    /// The plan's total estimated error ([`Estimate::total`]), relative L2.
    pub chosen_estimate: f64,
    /// Where they were compared, metres: the plan's wavelengths, or each band's centre.
    pub wavelengths: Vec<f64>,
    /// Each cheaper sub-sampling with its worst channel's relative L2 against the plan's run at
    /// the same wavelengths, and whether the method's guard accepts it.
    pub runs: Vec<CheaperRun>,
}

/// One cheaper run of [`measure_cheaper`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheaperRun {
    /// Sub-samples per pixel and axis of this run.
    pub subsample: usize,
    /// Relative L2 against the plan's run, the worst channel's.
    pub error: f64,
    /// The pixel integration error estimated for this sub-sampling, relative L2.
    pub estimate: f64,
    /// Whether the method's validity checks accept this sub-sampling (the run was forced).
    pub valid: bool,
}

impl CheaperMeasured {
    /// The measurement as lines of text, with what it says of the plan's choice.
    pub fn explain(&self) -> String {
        let mut s = format!(
            "measured: the cheaper pixel sub-samplings against the plan's {c} x {c} run (whose own estimate is {:.1e}) at {}
",
            self.chosen_estimate,
            self.wavelengths.iter().map(|l| format!("{:.0} nm", l * 1e9)).collect::<Vec<_>>().join(", "),
            c = self.chosen
        );
        for r in &self.runs {
            s.push_str(&format!(
                "  {s} x {s}: {:.1e} (estimated {:.1e}){}
",
                r.error,
                r.estimate,
                if r.valid { "" } else { ", refused by its guard" },
                s = r.subsample
            ));
        }
        let adequate = self.runs.iter().find(|r| r.valid && r.error + self.chosen_estimate <= self.tolerance);
        s.push_str(&match adequate {
            Some(r) => format!(
                "  {s} x {s} would have met the tolerance {:.1e} (measured {:.1e} plus the plan's own {:.1e}): the estimate is cautious here
",
                self.tolerance,
                r.error,
                self.chosen_estimate,
                s = r.subsample
            ),
            None => format!(
                "  every cheaper sub-sampling misses the tolerance {:.1e}: the plan took the cheapest adequate one
",
                self.tolerance
            ),
        });
        s
    }
}

/// Measures the plan's rejected pixel sub-samplings (up to three, the nearest below its
/// choice): each run by the plan's method and precision, forced past its guard (whose verdict
/// is kept), and compared with the plan's own sub-sampling at the same wavelengths (the plan's
/// wavelengths, or each band's centre: the pixel integration error hardly changes across a
/// band). The plan's run errs by its estimate at most, so a measured figure is the cheaper
/// run's error within that. Costs less than three plan runs at one wavelength per channel.
pub fn measure_cheaper(plan: &Plan, doe: &Grid, bands: &[Band]) -> Result<CheaperMeasured> {
    let wavelengths: Vec<f64> = if bands.is_empty() {
        plan.system.wavelengths.clone()
    } else {
        bands.iter().map(|b| b.range()).map(|(lo, hi)| 0.5 * (lo + hi)).collect()
    };
    let at = |subsample: usize| OpticalSystem {
        subsample,
        wavelengths: wavelengths.clone(),
        ..plan.system.clone()
    };
    let forced = Options { allow_invalid: true, precision: plan.precision };
    let chosen = plan.system.subsample;
    let reference = propagate::simulate(&at(chosen), doe, plan.method, &forced)?;
    let lmin = wavelengths.iter().copied().fold(f64::INFINITY, f64::min);
    let cutoff = plan.system.aperture / (lmin * plan.system.abcd().b.abs());
    let mut runs = Vec::new();
    for s in chosen.saturating_sub(3).max(1)..chosen {
        let sys = at(s);
        let valid = propagate::check(plan.method, &sys, doe)?.is_empty();
        let psf = propagate::simulate(&sys, doe, plan.method, &forced)?;
        let error = psf.relative_l2(&reference)?.into_iter().fold(0.0, f64::max);
        let estimate = pixel_error(sys.pixel_rule, sys.sensor_pitch, s, cutoff);
        runs.push(CheaperRun { subsample: s, error, estimate, valid });
    }
    Ok(CheaperMeasured {
        tolerance: plan.tolerance,
        chosen,
        chosen_estimate: plan.estimate.total,
        wavelengths,
        runs,
    })
}

/// Runs a plan: simulates every wavelength and, for bands, combines the spectral samples into
/// one channel per band. Returns the PSF and the plan as run.
///
/// With bands the pilot's estimate is checked a posteriori: the `N` sub-bands (a multiple of
/// 3) contain the midpoints of `N / 3` (the middle third of each), and when `N` is a multiple
/// of 9 those of `N / 9`, so their PSFs come from the same runs. The difference `d` between `N`
/// and `N / 3` bounds the error of `N / 3`'s and estimates `N`'s: `d / 8` (Richardson: the
/// midpoint rule's error falls 9x when `N` triples) once that regime is seen, the difference
/// having fallen at least 4x from the one between `N / 3` and `N / 9`; else `d` itself. While
/// that exceeds what the pixel and precision terms leave of the tolerance, `N` is tripled (the old samples are the new middle
/// thirds, so only the new two thirds are simulated), up to [`MAX_SPECTRAL_CHECKED`], beyond
/// which the run refuses with the figures. The plan as run carries the final `N`, the checked
/// estimate and a line saying how it was reached. (`bench spectral` measured why: at the
/// paper's geometry with 80 nm bands the pilot's three-point estimate asked for 10 sub-bands
/// at 1e-2, which erred by 0.12.)
pub fn run(plan: &Plan, doe: &Grid, bands: &[Band]) -> Result<(Psf, Plan)> {
    run_reporting(plan, doe, bands, &mut |_| {})
}

/// [`run`], telling `progress` what it simulates: the plan's wavelengths, then each tripling of
/// the sub-bands with the check that asked for it.
pub fn run_reporting(
    plan: &Plan,
    doe: &Grid,
    bands: &[Band],
    progress: &mut dyn FnMut(&str),
) -> Result<(Psf, Plan)> {
    let opts = Options { allow_invalid: false, precision: plan.precision };
    let label =
        |psf: &mut Psf| psf.method = format!("{} (plan, tolerance {:e})", plan.method, plan.tolerance);
    progress(&format!("PSF by {} ({} wavelengths)", plan.method, plan.system.wavelengths.len()));
    if bands.is_empty() {
        let mut psf = propagate::simulate(&plan.system, doe, plan.method, &opts)?;
        label(&mut psf);
        return Ok((psf, plan.clone()));
    }
    let mut n = plan.spectral_samples;
    if !n.is_multiple_of(3) {
        return Err(Error::param("spectral_samples", format!("the run checks multiples of 3, got {n}")));
    }
    let simulate_at = |wavelengths: Vec<f64>| -> Result<Vec<Channel>> {
        let system = OpticalSystem { wavelengths, ..plan.system.clone() };
        Ok(propagate::simulate(&system, doe, plan.method, &opts)?.channels)
    };
    // Channels per band, in the order of the band's samples.
    let mut channels: Vec<Vec<Channel>> = Vec::new();
    let mut all = simulate_at(bands.iter().flat_map(|b| b.samples(n)).map(|s| s.0).collect())?.into_iter();
    for _ in bands {
        channels.push(all.by_ref().take(n).collect());
    }
    let band_psf = |b: &Band, chans: Vec<Channel>, m: usize| -> Result<Psf> {
        combine(&Psf::new(chans, plan.method.name())?, std::slice::from_ref(b), &[b.samples(m)])
    };
    loop {
        // Per band: the differences between N and N / 3, and between N / 3 and N / 9 (0 when
        // N is not a multiple of 9).
        let mut diffs = Vec::new();
        let mut before = Vec::new();
        for (b, chans) in bands.iter().zip(&channels) {
            // The midpoints of m sub-bands among the n: the middle one of each run of n / m.
            let level = |m: usize| -> Result<Psf> {
                let k = n / m;
                band_psf(b, (0..m).map(|j| chans[k * j + k / 2].clone()).collect(), m)
            };
            let (fine, third) = (level(n)?, level(n / 3)?);
            diffs.push(third.relative_l2(&fine)?.into_iter().fold(0.0, f64::max));
            before.push(match n % 9 {
                0 => level(n / 9)?.relative_l2(&third)?.into_iter().fold(0.0, f64::max),
                _ => 0.0,
            });
        }
        let estimate = diffs
            .iter()
            .zip(&before)
            .map(|(&d, &prev)| if prev >= 4.0 * d { d / 8.0 } else { d })
            .fold(0.0, f64::max);
        let budget = plan.tolerance - plan.estimate.pixel_integration - plan.estimate.precision;
        if estimate <= budget {
            let mut ordered = Vec::new();
            for chans in channels {
                ordered.extend(chans);
            }
            let samples: Vec<Vec<(f64, f64)>> = bands.iter().map(|b| b.samples(n)).collect();
            let mut psf = combine(&Psf::new(ordered, plan.method.name())?, bands, &samples)?;
            label(&mut psf);
            let mut ran = plan.clone();
            ran.cost *= n as f64 / plan.spectral_samples as f64;
            ran.spectral_samples = n;
            ran.system.wavelengths = bands.iter().flat_map(|b| b.samples(n)).map(|s| s.0).collect();
            ran.estimate.spectral = estimate;
            ran.estimate.total = ran.estimate.pixel_integration + ran.estimate.precision + estimate;
            ran.choices.push(Choice {
                what: "spectral check".into(),
                value: format!("{n} per band"),
                because: format!(
                    "the {n} sub-bands against their middle thirds ({}): differ by {:.1e} at most, estimate {:.1e} <= {:.1e}{}",
                    n / 3,
                    diffs.iter().copied().fold(0.0, f64::max),
                    estimate,
                    budget,
                    if n > plan.spectral_samples {
                        format!(" (tripled from the plan's {})", plan.spectral_samples)
                    } else {
                        String::new()
                    }
                ),
            });
            return Ok((psf, ran));
        }
        if 3 * n > MAX_SPECTRAL_CHECKED {
            return Err(Error::validity(Condition::Sampling, format!(
                "spectral sampling does not converge within {MAX_SPECTRAL_CHECKED} sub-bands per band: {n} sub-bands \
                 differ from their middle thirds by {:.1e} (estimate {estimate:.1e}, allowed {budget:.1e}); \
                 narrow the bands or raise the tolerance",
                diffs.iter().copied().fold(0.0, f64::max)
            )));
        }
        // Triple: the old samples are the middle thirds of the new sub-bands.
        progress(&format!(
            "spectral check: {n} sub-bands against their middle thirds, estimate {estimate:.1e} > {budget:.1e}; \
             simulating {} per band",
            3 * n
        ));
        let fresh: Vec<f64> = bands
            .iter()
            .flat_map(|b| {
                b.samples(3 * n).into_iter().enumerate().filter(|(k, _)| k % 3 != 1).map(|(_, s)| s.0)
            })
            .collect();
        let mut fresh = simulate_at(fresh)?.into_iter();
        for chans in &mut channels {
            let old = std::mem::take(chans);
            for c in old {
                chans.extend(fresh.by_ref().take(1));
                chans.push(c);
                chans.extend(fresh.by_ref().take(1));
            }
        }
        n *= 3;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Unit;

    /// F/7 at 635 and 450 nm: 0.5 mm aperture, 3.5 mm to the sensor, 3 um pixels, 40 x 40.
    fn scene() -> OpticalSystem {
        OpticalSystem {
            aperture: 0.5e-3,
            doe_to_lens: 1e-3,
            focal_length: 3.5e-3,
            lens_to_sensor: 3.5e-3,
            sensor_pitch: 3e-6,
            crop: 40,
            pupil_pitch: 5e-6,
            pupil_window: 112.0 * 5e-6,
            wavelengths: vec![635e-9, 450e-9],
            ..Default::default()
        }
    }

    /// A flat DOE of 112 x 112 samples at 5 um.
    fn flat() -> Grid {
        Grid::new(ndarray::Array2::zeros((112, 112)), [5e-6; 2], Unit::Metre).unwrap()
    }

    #[test]
    fn the_wavelength_range_is_the_bands_edges_or_the_systems_wavelengths() {
        let s = scene();
        assert_eq!(wavelength_range(&s, &[]).unwrap(), (450e-9, 635e-9));
        let bands = [Band::flat("A", 500e-9, 520e-9).unwrap(), Band::flat("B", 600e-9, 690e-9).unwrap()];
        assert_eq!(wavelength_range(&s, &bands).unwrap(), (500e-9, 690e-9));
        let uv = Band::flat("UV", 350e-9, 450e-9).unwrap();
        let e = wavelength_range(&s, &[uv]).unwrap_err().to_string();
        assert!(e.contains("band 'UV'") && e.contains("400-700 nm"), "{e}");
    }

    /// The least sub-sampling meets half the tolerance and the one below it does not; a
    /// tolerance no sub-sampling meets (the midpoint rule's error falls as `s^-2`) is refused
    /// naming the rule.
    #[test]
    fn the_least_subsample_is_the_first_within_half_the_tolerance() {
        let (pitch, cutoff) = (3e-6, 0.5e-3 / (450e-9 * 3.5e-3));
        for (rule, tolerances) in
            [(PixelRule::GaussLegendre, [1e-2, 1e-3, 1e-4]), (PixelRule::Midpoint, [1e-1, 1e-2, 1e-3])]
        {
            for tolerance in tolerances {
                let s = least_subsample(rule, pitch, cutoff, tolerance).unwrap();
                assert!(pixel_error(rule, pitch, s, cutoff) <= 0.5 * tolerance, "{rule:?} {tolerance}");
                assert!(
                    s == 1 || pixel_error(rule, pitch, s - 1, cutoff) > 0.5 * tolerance,
                    "{rule:?} {tolerance}"
                );
            }
        }
        let e = least_subsample(PixelRule::Midpoint, pitch, cutoff, 1e-4).unwrap_err().to_string();
        assert!(e.contains("Midpoint") && e.contains("more than 32 sub-samples"), "{e}");
    }

    /// `f32` only for the matrix DFT, and only while `2^-24 sqrt(n + M)` is within a tenth of
    /// the tolerance: `sqrt(140) 2^-24 = 7.05e-7`.
    #[test]
    fn f32_is_chosen_for_the_matrix_dft_within_a_tenth_of_the_tolerance() {
        let e = 140f64.sqrt() / 16_777_216.0;
        let (p, err, why) = choose_precision(Method::MatrixDft, 100, 40, 1e-3);
        assert_eq!((p, err), (Precision::F32, e));
        assert!(why.contains("7.1e-7 <="), "{why}");
        let (p, err, why) = choose_precision(Method::MatrixDft, 100, 40, 1e-6);
        assert_eq!((p, err), (Precision::F64, 0.0));
        assert!(why.contains("7.1e-7 >"), "{why}");
        let (p, err, why) = choose_precision(Method::AngularSpectrum, 100, 40, 1e-3);
        assert_eq!((p, err), (Precision::F64, 0.0));
        assert!(why.contains("computes in f64"), "{why}");
    }

    /// The DOE's own 5 um samples suffice for a 40-pixel crop; a 183-pixel one (0.55 mm) exceeds
    /// the replica period `lambda |B| / dx` = 0.315 mm at 450 nm, which half the pitch lifts
    /// over it; a 1000-pixel one (3 mm) no refinement up to 8 reaches (2.5 mm at 450 nm).
    #[test]
    fn the_matrix_dft_refines_the_pupil_until_the_replicas_clear_the_crop() {
        let doe = flat();
        let at = |crop: usize| {
            let s = OpticalSystem { crop, wavelengths: vec![450e-9, 635e-9], ..scene() };
            matrix_dft_candidate(&s, &doe, 4).unwrap()
        };
        let (c, refusals) = at(40);
        let c = c.unwrap();
        assert_eq!((c.0, c.1.pupil_pitch, c.1.subsample, refusals.len()), (Method::MatrixDft, 5e-6, 4, 0));
        let n = matrix_dft::pupil_grid(&c.1, &doe).0;
        assert_eq!(c.2, matrix_dft_cost(n, 160));
        let (c, _) = at(183);
        let c = c.unwrap();
        assert!(c.1.pupil_pitch == 2.5e-6 && c.3.starts_with("DOE pitch / 2"), "{}", c.3);
        let (c, refusals) = at(1000);
        assert!(c.is_none() && refusals.len() == 1, "{refusals:?}");
        assert!(refusals[0].starts_with("matrix_dft: still invalid at DOE pitch / 8"), "{refusals:?}");
        assert_eq!(angular_spectrum_candidate(&scene(), &doe, usize::MAX).unwrap(), (None, Vec::new()));
    }
}
