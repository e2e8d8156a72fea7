//! Method 1: the single transform from the pupil to the sensor.
//!
//! The paraxial system DOE -> d_phi -> thin lens g -> d_s is one ABCD matrix
//! ([`crate::optics::system::Abcd`]); Collins' integral (Collins 1970, JOSA 60, 1168) maps the
//! field after the DOE straight to the sensor:
//!
//! `U2(x, y) = 1/(i lambda B) exp(i pi D (x^2 + y^2) / (lambda B))
//!   * sum_uv U1(u, v) exp(i pi A (u^2 + v^2) / (lambda B)) exp(-2 pi i (x u + y v) / (lambda B)) dx^2`.
//!
//! The sum is separable in x and y, so on the sensor sub-sample coordinates `x_q` it is two
//! dense matrix products, `U2 = F G F^T` with `F[q, j] = exp(-2 pi i x_q u_j / (lambda B))`
//! (a matrix DFT, as in Soummer et al. 2007, Opt. Express 15, 15935), evaluated by
//! `ndarray`'s GEMM. Every wavelength lands on the same sensor grid with no interpolation.
//! In focus (`d_s = g`) `A = 0` and `B = g`: the intensity does not depend on d_phi.
//! With [`OpticalSystem::cells`] the rows of `F` carry the cell envelope `sinc(x dx / (lambda B))`.
//!
//! Validity: the sensor window must fit within the replica period `lambda |B| / dx` of the
//! sampled pupil; the quadratic pupil phase `pi (A/B + B... )` left by defocus or a finite
//! object distance must be sampled (local frequency `<= 1/(2 dx)`); the DOE phase gradient;
//! the Fresnel approximation out of focus.

use std::f64::consts::PI;

use ndarray::Array2;
use rustfft::num_complex::Complex64;

use super::{check_fresnel, field_power, pupil_phase, SensorIntensity, Violation};
use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::optics::system::{sinc, OpticalSystem};

/// The pupil grid of this method: `(n, dx)` with `dx` the system's pupil pitch and `n` just
/// covering the aperture, with the DOE's parity when the DOE has that pitch (so the samples
/// coincide and no interpolation happens).
pub fn pupil_grid(system: &OpticalSystem, doe: &Grid) -> (usize, f64) {
    let dx = system.pupil_pitch;
    let same = doe.pitch().iter().all(|p| (p / dx - 1.0).abs() < 1e-12);
    let parity = if same { doe.dim().1 % 2 } else { 0 };
    let mut n = (system.aperture / dx).ceil() as usize + 2;
    if n % 2 != parity {
        n += 1;
    }
    (n, dx)
}

/// The curvature `c` (1/m) of the quadratic pupil phase `pi c r^2 / lambda` the transform
/// carries: `A / B` plus `1 / z_o` for a finite object.
fn pupil_curvature(system: &OpticalSystem) -> f64 {
    let m = system.abcd();
    m.a / m.b + system.object_distance.map_or(0.0, |z| 1.0 / z)
}

/// The violated validity conditions at `wavelength` (see the module docs).
pub fn check(system: &OpticalSystem, doe: &Grid, wavelength: f64) -> Result<Vec<Violation>> {
    let (n, dx) = pupil_grid(system, doe);
    let (f_doe, gradient) = pupil_phase(system, doe, n, dx, wavelength)?;
    let m = system.abcd();
    let mut out = Vec::new();
    if m.b.abs() < 1e-9 * system.focal_length {
        out.push(Violation::new(
            "imaging_condition",
            wavelength,
            "B = 0: the sensor images the DOE plane, the single transform is degenerate".into(),
        ));
        return Ok(out);
    }
    let period = wavelength * m.b.abs() / dx;
    if system.sensor_window() > period {
        out.push(Violation::new(
            "output_window",
            wavelength,
            format!(
                "the {:.3} mm sensor window exceeds the replica period lambda |B| / dx = {:.3} mm of the \
                 {:.3} um pupil sampling: sample the pupil finer",
                system.sensor_window() * 1e3,
                period * 1e3,
                dx * 1e6
            ),
        ));
    }
    let fmax = pupil_curvature(system).abs() * system.aperture * 0.5 / wavelength;
    if fmax > 1.0 / (2.0 * dx) {
        out.push(Violation::new(
            "defocus_sampling",
            wavelength,
            format!(
                "the quadratic pupil phase of defocus / object distance reaches {:.1} cycles/mm at the \
                 aperture edge, above the pupil's Nyquist frequency {:.1} cycles/mm",
                fmax * 1e-3,
                0.5e-3 / dx
            ),
        ));
    }
    out.extend(gradient);
    out.extend(check_fresnel(system, f_doe, dx, wavelength));
    Ok(out)
}

/// The sensor intensity at `wavelength` on the sub-sample grid (see the module docs).
pub fn sensor_intensity(system: &OpticalSystem, doe: &Grid, wavelength: f64) -> Result<SensorIntensity> {
    let (n, dx) = pupil_grid(system, doe);
    let u1 = system.pupil_field(doe, n, dx, wavelength, true)?;
    let input_power = field_power(&u1, dx);
    let xs = system.sensor_coords();
    let intensity = transform(system, &u1, dx, &xs, wavelength)?;
    Ok(SensorIntensity { intensity, input_power })
}

/// Collins' integral of the pupil field `u1` (pitch `dx`, centred) evaluated at the sensor
/// points `xs x xs` (metres, both axes): the intensity `|U2|^2`.
pub fn transform(
    system: &OpticalSystem,
    u1: &Array2<Complex64>,
    dx: f64,
    xs: &[f64],
    wavelength: f64,
) -> Result<Array2<f64>> {
    let m = system.abcd();
    if m.b.abs() < 1e-9 * system.focal_length {
        return Err(Error::Validity("B = 0: the sensor images the DOE plane".into()));
    }
    let n = u1.dim().0;
    let c = (n as f64 - 1.0) * 0.5;
    let u: Vec<f64> = (0..n).map(|j| (j as f64 - c) * dx).collect();
    let lb = wavelength * m.b;
    // Only the quadratic term of the pupil that the transform itself adds (A/B); the object's
    // spherical wave is already in u1.
    let ca = PI * m.a / lb;
    let g = Array2::from_shape_fn((n, n), |(i, j)| {
        let v = u1[[i, j]];
        if v == Complex64::new(0.0, 0.0) || ca == 0.0 {
            v
        } else {
            v * Complex64::from_polar(1.0, ca * (u[i] * u[i] + u[j] * u[j]))
        }
    });
    // Cell envelope: sinc of the sensor position's spatial frequency x / (lambda B) times dx
    // (exact in focus, where the transform is a Fourier transform).
    let env: Vec<f64> = xs.iter().map(|&x| if system.cells { sinc(x * dx / lb) } else { 1.0 }).collect();
    let f = Array2::from_shape_fn((xs.len(), n), |(q, j)| {
        Complex64::from_polar(env[q], -2.0 * PI * xs[q] * u[j] / lb)
    });
    let t = g.dot(&f.t());
    let u2 = f.dot(&t);
    let scale = (dx * dx / lb).powi(2);
    Ok(u2.mapv(|v| v.norm_sqr() * scale))
}
