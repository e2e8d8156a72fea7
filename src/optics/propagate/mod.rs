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
mod method;
pub mod rayleigh;

use ndarray::Array2;
use rayon::prelude::*;

use super::psf::{Channel, Psf};
use super::system::{OpticalSystem, PixelRule};
use crate::error::{Condition, DataCause, Error, Result};
use crate::grid::{Grid, Unit};
pub use method::{field_power, Method, Options, Precision, SensorIntensity, Violation};

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
        return Err(Error::validity(
            Condition::Propagation,
            format!(
                "method {method} is not valid for this system (run with allow_invalid to force):\n  {}",
                list.join("\n  ")
            ),
        ));
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
        return Err(Error::data(
            DataCause::Empty,
            format!("no light reaches the {c} x {c} sensor window (total {total})"),
        ));
    }
    px.mapv_inplace(|v| v / total);
    Ok((Grid::new(px, [system.sensor_pitch; 2], Unit::Dimensionless)?, captured))
}

#[cfg(test)]
mod tests {
    use std::f64::consts::PI;

    use super::method::*;
    use super::*;

    /// The phase changes of one row of phases (radians: `k = 1`).
    fn row(phase: &[f64]) -> PhaseChanges {
        let h = Array2::from_shape_vec((1, phase.len()), phase.to_vec()).unwrap();
        phase_changes(h.view(), &|_, _| true, 1.0)
    }

    /// A row spanning 8 rad (its last samples climb to 8 in resolved changes) with one jump of
    /// `jump` between flat flanks.
    fn jump_row(jump: f64) -> Vec<f64> {
        let mut v = vec![0.0, 0.0, jump, jump];
        while *v.last().unwrap() < 8.0 {
            v.push((v.last().unwrap() + 1.0).min(8.0));
        }
        v
    }

    #[test]
    fn a_step_is_the_span_less_a_resolved_change() {
        // Span 8 rad: a jump of 8 - 0.98 pi is a step, 8 - 1.02 pi a slope.
        let step = row(&jump_row(8.0 - 0.98 * PI));
        assert_eq!((step.steps, step.slopes), (1, 0), "{step:?}");
        assert!((step.steepest - 0.98 * PI).abs() < 1e-12, "{step:?}");
        let slope = row(&jump_row(8.0 - 1.02 * PI));
        assert_eq!((slope.steps, slope.slopes), (0, 1), "{slope:?}");
        assert_eq!(slope.worst.2, 1);
        // A change of exactly pi is resolved (a binary grating of pi steps).
        assert_eq!(row(&[0.0, PI, 0.0, PI]), PhaseChanges { steepest: PI, ..Default::default() });
    }

    #[test]
    fn a_slope_keeps_climbing_a_terrace_turns_back() {
        // Over a 7 rad span, a climb of 0.98 pi then a step of the rest (7 - 0.98 pi, within pi
        // of the span); a climb of 1.02 pi leaves a rest that is not: two slopes.
        let climb = |c: f64| row(&[0.0, c, 7.0, 7.0]);
        let r = climb(0.98 * PI);
        assert_eq!((r.steps, r.slopes), (1, 0), "{r:?}");
        let r = climb(1.02 * PI);
        assert_eq!((r.steps, r.slopes), (0, 2), "{r:?}");
        // A terrace one sample wide turns back: two steps, no slope.
        let terrace = row(&[0.0, 0.0, 7.0, 0.0, 0.0]);
        assert_eq!((terrace.steps, terrace.slopes), (2, 0));
        // A smooth slope of 4 rad per sample is a slope at every pair.
        let steep = row(&[0.0, 4.0, 8.0, 12.0, 16.0]);
        assert_eq!((steep.steps, steep.slopes), (0, 4));
        assert_eq!(steep.worst, (4.0, 0, 0));
    }

    /// A tilt of 0.3 pi per sample wrapped modulo 2 pi: steps at the design wavelength (2 pi
    /// less 0.3 pi), and scaled by 0.8 or 1.2 (another wavelength) still steps, one per zone,
    /// the slope across each (0.3 pi times the scale) the steepest change.
    #[test]
    fn a_wrapped_tilt_steps_at_every_wavelength() {
        let tau = 2.0 * PI;
        let wrapped: Vec<f64> = (0..60).map(|j| (0.3 * PI * j as f64).rem_euclid(tau)).collect();
        let zones = wrapped.windows(2).filter(|w| w[1] < w[0]).count();
        assert!(zones >= 8);
        for scale in [0.8, 1.0, 1.2] {
            let v: Vec<f64> = wrapped.iter().map(|p| p * scale).collect();
            let r = row(&v);
            assert_eq!((r.steps, r.slopes), (zones, 0), "scale {scale}: {r:?}");
            assert!((r.steepest - 0.3 * PI * scale).abs() < 1e-9, "scale {scale}: {r:?}");
        }
        // Steeper than pi per sample and not wrapped: all slopes.
        let steep: Vec<f64> = (0..10).map(|j| 1.1 * PI * j as f64).collect();
        assert_eq!(row(&steep).slopes, 9);
    }
}
