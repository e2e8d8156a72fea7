//! Method 4: direct Rayleigh-Sommerfeld integration, the slow ground truth on small grids.
//!
//! The first Rayleigh-Sommerfeld solution (Goodman, Introduction to Fourier Optics, eq. 3-74,
//! with the exact derivative of the Green function) is the sum
//!
//! `U2(x) = sum_u U1(u) h(x - u, z) dx^2`, `h(rho, z) = z / (2 pi R^2) (1/R - i k) exp(i k (R - z))`,
//! `R = sqrt(rho^2 + z^2)`
//!
//! (the constant `exp(i k z)` dropped). Two steps: the pupil (pitch `dx`, `n` samples) to the
//! lens plane on a window twice the pupil's (as the angular-spectrum method pads), the
//! hyperbolic lens `exp(-i k (sqrt(r^2 + g^2) - g))`, then the lens plane to each sensor
//! sub-sample directly. Non-paraxial and free of periodic replicas; the cost is
//! `n^2 (2n)^2 + (2n)^2 m^2` kernel products, so it is for small grids only.
//!
//! Validity: the kernel's phase sampled (`k dx rho_max / R <= pi`) on both steps; the lens phase
//! sampled; the lens window holding the light the DOE spreads; a cost limit ([`Error::Limit`]).

use std::f64::consts::PI;

use ndarray::Array2;
use rayon::prelude::*;
use rustfft::num_complex::Complex64;

use super::{check_lens_sampling, content_bandwidth, field_power, pupil_phase, SensorIntensity, Violation};
use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::optics::system::OpticalSystem;

/// Largest number of kernel products a run may take.
pub const MAX_WORK: f64 = 4e9;

/// `(n, dx, l)`: pupil samples, pitch and lens-plane samples (`2n`).
pub fn grid(system: &OpticalSystem) -> (usize, f64, usize) {
    let dx = system.sample_pitch();
    let n = system.pupil_samples(dx, system.samples() % 2);
    (n, dx, 2 * n)
}

fn kernel(rho2: f64, z: f64, k: f64) -> Complex64 {
    let r2 = rho2 + z * z;
    let r = r2.sqrt();
    // R - z without cancellation.
    let phase = k * rho2 / (r + z);
    Complex64::new(1.0 / r, -k) * Complex64::from_polar(z / (2.0 * PI * r2), phase)
}

/// The violated validity conditions at `wavelength` (see the module docs).
pub fn check(system: &OpticalSystem, doe: &Grid, wavelength: f64) -> Result<Vec<Violation>> {
    let (n, dx, l) = grid(system);
    let (f_doe, gradient) = pupil_phase(system, doe, n, dx, wavelength)?;
    let k = 2.0 * PI / wavelength;
    let mut out = Vec::new();
    if system.cells {
        out.push(Violation::new(
            "cells",
            wavelength,
            "direct integration models point samples only; set cells = false".into(),
        ));
    }
    out.extend(check_lens_sampling(system, dx, wavelength, true, f_doe));
    let half_lens = l as f64 * dx * 0.5;
    for (z, src, dst, what) in [
        (system.doe_to_lens, system.aperture * 0.5, half_lens, "DOE -> lens"),
        (system.lens_to_sensor, half_lens, system.sensor_window() * 0.5, "lens -> sensor"),
    ] {
        let rho = (src + dst) * std::f64::consts::SQRT_2;
        let step = k * dx * rho / (rho * rho + z * z).sqrt();
        if step > PI {
            out.push(Violation::new(
                "kernel_sampling",
                wavelength,
                format!(
                    "{what}: the Rayleigh-Sommerfeld kernel's phase changes by {step:.2} rad (> pi) per \
                     {:.3} um sample at the widest angle; sample finer or propagate further",
                    dx * 1e6
                ),
            ));
        }
    }
    let spread = system.aperture * 0.5
        + system.doe_to_lens * wavelength * content_bandwidth(system, f_doe, dx, wavelength, false);
    if spread > half_lens {
        out.push(Violation::new(
            "output_window",
            wavelength,
            format!(
                "light from the DOE spreads to {:.3} mm from the axis at the lens, beyond the {:.3} mm lens window",
                spread * 1e3,
                half_lens * 1e3
            ),
        ));
    }
    out.extend(gradient);
    Ok(out)
}

/// The sensor intensity at `wavelength` (see the module docs).
pub fn sensor_intensity(system: &OpticalSystem, doe: &Grid, wavelength: f64) -> Result<SensorIntensity> {
    let (n, dx, l) = grid(system);
    let m = system.samples();
    let work = (n * n) as f64 * (l * l) as f64 + (l * l) as f64 * (m * m) as f64;
    if work > MAX_WORK {
        return Err(Error::Limit(format!(
            "direct Rayleigh-Sommerfeld integration would take {work:.2e} kernel products (limit {MAX_WORK:.0e}); \
             it is meant for small grids"
        )));
    }
    let u0 = system.pupil_field(doe, n, dx, wavelength, false)?;
    let input_power = field_power(&u0, dx);
    let k = 2.0 * PI / wavelength;
    // Step 1 on the lattice: offsets (p - q - (l - n)/2) dx, index t = p - q + n - 1.
    let dz = system.doe_to_lens;
    let off = |t: usize| (t as f64 - (n as f64 - 1.0) - (l as f64 - n as f64) * 0.5) * dx;
    let nt = l + n - 1;
    let table = Array2::from_shape_fn((nt, nt), |(a, b)| {
        let (y, x) = (off(a), off(b));
        kernel(x * x + y * y, dz, k) * (dx * dx)
    });
    let src: Vec<(usize, usize, Complex64)> =
        u0.indexed_iter().filter(|(_, v)| v.norm_sqr() > 0.0).map(|((i, j), v)| (i, j, *v)).collect();
    let cl = (l as f64 - 1.0) * 0.5;
    let g = system.focal_length;
    let mut lens_field = Array2::<Complex64>::zeros((l, l));
    lens_field.as_slice_mut().expect("standard layout").par_chunks_mut(l).enumerate().for_each(
        |(p1, row)| {
            for (p2, v) in row.iter_mut().enumerate() {
                let mut acc = Complex64::new(0.0, 0.0);
                for &(q1, q2, u) in &src {
                    acc += u * table[[p1 + n - 1 - q1, p2 + n - 1 - q2]];
                }
                let (x, y) = ((p2 as f64 - cl) * dx, (p1 as f64 - cl) * dx);
                let r2 = x * x + y * y;
                *v = acc * Complex64::from_polar(1.0, -k * r2 / ((r2 + g * g).sqrt() + g));
            }
        },
    );
    // Step 2 to each sensor sub-sample.
    let xs = system.sensor_coords();
    let lx: Vec<f64> = (0..l).map(|j| (j as f64 - cl) * dx).collect();
    let lens_src: Vec<(f64, f64, Complex64)> = lens_field
        .indexed_iter()
        .filter(|(_, v)| v.norm_sqr() > 0.0)
        .map(|((i, j), v)| (lx[j], lx[i], *v))
        .collect();
    let zs = system.lens_to_sensor;
    let mut intensity = Array2::<f64>::zeros((m, m));
    intensity.as_slice_mut().expect("standard layout").par_chunks_mut(m).enumerate().for_each(|(a, row)| {
        for (b, v) in row.iter_mut().enumerate() {
            let (x, y) = (xs[b], xs[a]);
            let mut acc = Complex64::new(0.0, 0.0);
            for &(sx, sy, u) in &lens_src {
                let (ddx, ddy) = (x - sx, y - sy);
                acc += u * kernel(ddx * ddx + ddy * ddy, zs, k);
            }
            *v = (acc * dx * dx).norm_sqr();
        }
    });
    Ok(SensorIntensity { intensity, input_power })
}
