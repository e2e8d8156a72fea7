//! Built-in example designs, generated in code so that every command runs without input.
//!
//! * [`paper_example`]: the paper's geometry (5 mm aperture on a 5.6 mm grid at 4.29 um,
//!   1306 x 1306 samples, heights within 0..1.55 um in PDMS) with a grating-like profile:
//!   three sinusoidal phase gratings at 0, 60 and 120 degrees make a central peak plus six
//!   weaker shifted copies (thin sinusoidal grating of modulation m: order q carries
//!   J_q(m)^2; Goodman, Introduction to Fourier Optics, 4.4.2), on a gentle tilt that pushes
//!   the heights beyond one 2 pi period at 530 nm so that wrapping has work to do.
//! * [`fresnel_lens`]: a wrapped Fresnel lens, `phi(r) = -pi r^2 / (lambda f)` modulo 2 pi,
//!   whose zone radii `r_m = sqrt(2 m lambda f)` make analytic tests possible.

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::grid::{Grid, Unit};
use crate::material::Material;

/// Sample pitch of the paper's DOE, metres (Metzler et al. 2020, Sec. 5).
pub const PAPER_PITCH: f64 = 4.29e-6;
/// Samples per side: 5.6 mm / 4.29 um.
pub const PAPER_SAMPLES: usize = 1306;
/// Clear aperture diameter, metres.
pub const PAPER_APERTURE: f64 = 5e-3;
/// Largest height of the paper's DOE, metres.
pub const PAPER_MAX_HEIGHT: f64 = 1.55e-6;

/// Parameters of the grating-like example.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ExampleParams {
    /// Samples per side.
    pub samples: usize,
    /// Sample pitch, metres.
    pub pitch: f64,
    /// Clear aperture diameter, metres; outside it the height is 0.
    pub aperture: f64,
    /// Wavelength the phase values refer to, metres.
    pub wavelength: f64,
    /// Grating period, metres (copies land at lambda g / period from the centre).
    pub grating_period: f64,
    /// Phase modulation amplitude of each of the three gratings, radians.
    pub modulation: f64,
    /// Tilt across the aperture, in waves at `wavelength`.
    pub tilt_waves: f64,
}

impl Default for ExampleParams {
    fn default() -> Self {
        ExampleParams {
            samples: PAPER_SAMPLES,
            pitch: PAPER_PITCH,
            aperture: PAPER_APERTURE,
            wavelength: 530e-9,
            grating_period: 24.0 * PAPER_PITCH,
            modulation: 0.55,
            tilt_waves: 0.75,
        }
    }
}

/// The built-in grating-like example design (heights in metres, PDMS), see the module docs.
pub fn paper_example(p: &ExampleParams) -> Result<Grid> {
    let material = Material::pdms();
    let h2pi = material.height_2pi(p.wavelength)?;
    let n = p.samples;
    let c = (n as f64 - 1.0) * 0.5;
    let radius = p.aperture * 0.5;
    let dirs = [0.0f64, 60.0, 120.0].map(f64::to_radians);
    let tilt_dir = 45f64.to_radians();
    let phase = |x: f64, y: f64| {
        let gratings: f64 = dirs
            .iter()
            .map(|t| {
                p.modulation
                    * (2.0 * std::f64::consts::PI * (x * t.cos() + y * t.sin()) / p.grating_period).cos()
            })
            .sum();
        // Tilt of `tilt_waves` across the aperture diameter along the diagonal.
        let tilt = 2.0 * std::f64::consts::PI * p.tilt_waves * (x * tilt_dir.cos() + y * tilt_dir.sin())
            / p.aperture;
        gratings + tilt
    };
    let mut values = Array2::<f64>::zeros((n, n));
    let mut lo = f64::INFINITY;
    for ((i, j), v) in values.indexed_iter_mut() {
        let (x, y) = ((j as f64 - c) * p.pitch, (i as f64 - c) * p.pitch);
        if x * x + y * y <= radius * radius {
            *v = phase(x, y) / (2.0 * std::f64::consts::PI) * h2pi;
            lo = lo.min(*v);
        } else {
            *v = f64::NAN;
        }
    }
    if !lo.is_finite() {
        return Err(Error::param("aperture", "no sample lies inside the aperture"));
    }
    values.mapv_inplace(|v| if v.is_nan() { 0.0 } else { v - lo });
    Grid::new(values, [p.pitch, p.pitch], Unit::Metre)
}

/// Parameters of the Fresnel lens example.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FresnelParams {
    /// Samples per side.
    pub samples: usize,
    /// Sample pitch, metres.
    pub pitch: f64,
    /// Clear aperture diameter, metres; outside it the height is 0.
    pub aperture: f64,
    /// Focal length `f` of the lens, metres.
    pub focal_length: f64,
    /// Design wavelength `lambda`, metres; one zone is one 2 pi period (PDMS) at it.
    pub wavelength: f64,
}

impl Default for FresnelParams {
    fn default() -> Self {
        FresnelParams {
            samples: PAPER_SAMPLES,
            pitch: PAPER_PITCH,
            aperture: PAPER_APERTURE,
            focal_length: 100e-3,
            wavelength: 530e-9,
        }
    }
}

/// A wrapped PDMS Fresnel lens: `h = ((-r^2 / (2 lambda f)) mod 1) * lambda / (n - 1)`.
pub fn fresnel_lens(p: &FresnelParams) -> Result<Grid> {
    let h2pi = Material::pdms().height_2pi(p.wavelength)?;
    let n = p.samples;
    let c = (n as f64 - 1.0) * 0.5;
    let r2max = (p.aperture * 0.5).powi(2);
    let values = Array2::from_shape_fn((n, n), |(i, j)| {
        let r2 = ((j as f64 - c) * p.pitch).powi(2) + ((i as f64 - c) * p.pitch).powi(2);
        if r2 > r2max {
            0.0
        } else {
            (-r2 / (2.0 * p.wavelength * p.focal_length)).rem_euclid(1.0) * h2pi
        }
    });
    Grid::new(values, [p.pitch, p.pitch], Unit::Metre)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn example_has_the_paper_geometry() {
        let g = paper_example(&ExampleParams::default()).unwrap();
        assert_eq!(g.dim(), (1306, 1306));
        assert!((g.extent()[0] - 5.60274e-3).abs() < 1e-7);
        let (lo, hi) = g.min_max().unwrap();
        assert!(lo >= 0.0 && hi <= PAPER_MAX_HEIGHT, "{lo} {hi}");
        // It must exceed one 2 pi period at 530 nm, so that wrapping is exercised.
        assert!(hi > Material::pdms().height_2pi(530e-9).unwrap());
        // Flat (zero) outside the aperture.
        assert_eq!(g.values()[[0, 0]], 0.0);
    }

    #[test]
    fn fresnel_zone_boundaries_fall_on_the_analytic_radii() {
        let p = FresnelParams {
            samples: 801,
            pitch: 1e-6,
            aperture: 0.8e-3,
            focal_length: 20e-3,
            wavelength: 530e-9,
        };
        let g = fresnel_lens(&p).unwrap();
        // Along the central row, the height jumps up by about h_2pi at r_m = sqrt(2 m lambda f).
        let row = g.values().row(400);
        let h2pi = Material::pdms().height_2pi(530e-9).unwrap();
        for m in 1..4 {
            let rm = (2.0 * m as f64 * 530e-9 * 20e-3).sqrt();
            let j = 400 + (rm / 1e-6).round() as usize;
            let jump = (j - 2..j + 3).any(|k| row[k + 1] - row[k] > 0.8 * h2pi);
            assert!(jump, "no zone edge near r_{m} = {rm}");
        }
    }
}
