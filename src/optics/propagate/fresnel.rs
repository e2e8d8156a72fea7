//! Method 2: two-step Fresnel transfer-function propagation with an explicit thin-lens phase,
//! as the paper's code does (Metzler et al. 2020, "Modeling the Optical Point Spread Function").
//!
//! `U_sensor = P_ds{ t_l P_dphi{ t_phi } }` with the Fresnel transfer function
//! `H(fx, fy) = exp(-i pi lambda z (fx^2 + fy^2))` (Goodman, Introduction to Fourier Optics,
//! eq. 4-21, without the constant `exp(i k z)`) applied by FFT on the pupil grid zero-padded by
//! at least N/4 on each side (the paper's padding, rounded up to a fast FFT size), and the lens
//! `t_l = exp(-i k (x^2 + y^2) / (2 g))`. The pitch stays `dx = sensor_pitch / subsample`
//! throughout, so the output is already on the sensor sub-sample grid; the crop is its centre.
//! With [`OpticalSystem::cells`] the first transfer function carries the cell envelope.
//!
//! Validity: the lens phase sampled at `dx <= lambda F#` (the paper's own 4.29 um at F/7
//! violates it at 530 and 450 nm); the transfer function's chirp sampled over the pupil's band
//! (`lambda z <= W dx` for window `W`, Voelz and Roggemann 2009, Appl. Opt. 48, 6132); the output window vs the replica period; the DOE phase gradient; the
//! Fresnel approximation out of focus.

use std::f64::consts::PI;

use ndarray::{s, Array2};
use rayon::prelude::*;
use rustfft::num_complex::Complex64;

use super::method::{
    check_fresnel, check_lens_sampling, check_window, field_power, pupil_phase, SensorIntensity, Violation,
};
use crate::error::{Condition, Error, Result};
use crate::fft::{fft_freq, good_size, Plan2d};
use crate::grid::Grid;
use crate::optics::system::{sinc, OpticalSystem};

/// `(n, dx, w)`: pupil samples, pitch and padded FFT size of this method (`n / 4` a side, as
/// the paper's code, or `system.padding` times `n`).
pub fn grid(system: &OpticalSystem) -> (usize, f64, usize) {
    let dx = system.sample_pitch();
    let n = system.pupil_samples(dx, system.samples() % 2);
    let w = match system.padding {
        Some(p) => (p * n as f64).ceil() as usize,
        None => n + 2 * n.div_ceil(4),
    };
    (n, dx, good_size(w.max(n), n % 2))
}

/// The violated validity conditions at `wavelength` (see the module docs).
pub fn check(system: &OpticalSystem, doe: &Grid, wavelength: f64) -> Result<Vec<Violation>> {
    let (n, dx, w) = grid(system);
    let (f_doe, gradient) = pupil_phase(system, doe, n, dx, wavelength)?;
    let mut out = Vec::new();
    out.extend(check_lens_sampling(system, dx, wavelength, false, f_doe));
    out.extend(check_bandwidth(system, dx, w, wavelength));
    out.extend(check_window(system, dx, w as f64 * dx, wavelength));
    if system.samples() > w {
        out.push(crop_too_large(system, w, wavelength));
    }
    out.extend(gradient);
    out.extend(check_fresnel(system, f_doe, dx, wavelength));
    Ok(out)
}

pub(crate) fn crop_too_large(system: &OpticalSystem, w: usize, wavelength: f64) -> Violation {
    Violation::new(
        "crop",
        wavelength,
        format!(
            "the sensor crop needs {} samples per side but the propagation window has {w}",
            system.samples()
        ),
    )
}

/// The transfer function's chirp must be sampled over the whole band of the pupil grid,
/// `1 / (2 dx) <= W / (2 lambda z)`, i.e. `lambda z <= W dx`: a sharp aperture edge fills the
/// band, so a smaller estimate of the field's bandwidth lets aliased light through.
fn check_bandwidth(system: &OpticalSystem, dx: f64, w: usize, wavelength: f64) -> Vec<Violation> {
    let win = w as f64 * dx;
    let mut out = Vec::new();
    for (z, what) in [(system.doe_to_lens, "DOE -> lens"), (system.lens_to_sensor, "lens -> sensor")] {
        let f = 1.0 / (2.0 * dx);
        let limit = win / (2.0 * wavelength * z);
        if f > limit {
            out.push(Violation::new(
                "transfer_function_bandwidth",
                wavelength,
                format!(
                    "{what}: the Fresnel transfer function's chirp is sampled only up to {:.1} cycles/mm, \
                     below the pupil's band {:.1} cycles/mm (lambda z = {:.3e} m^2 > window x pitch = {:.3e} m^2)",
                    limit * 1e-3,
                    f * 1e-3,
                    wavelength * z,
                    win * dx
                ),
            ));
        }
    }
    out
}

/// The sensor intensity at `wavelength` (see the module docs).
pub fn sensor_intensity(system: &OpticalSystem, doe: &Grid, wavelength: f64) -> Result<SensorIntensity> {
    let (n, dx, w) = grid(system);
    let u0 = system.pupil_field(doe, n, dx, wavelength, true)?;
    let input_power = field_power(&u0, dx);
    let transfer = |z: f64, cells: bool| {
        Array2::from_shape_fn((w, w), |(p, q)| {
            let (fy, fx) = (fft_freq(p, w, dx), fft_freq(q, w, dx));
            let env = if cells { sinc(fx * dx) * sinc(fy * dx) } else { 1.0 };
            Complex64::from_polar(env, -PI * wavelength * z * (fx * fx + fy * fy))
        })
    };
    let k = 2.0 * PI / wavelength;
    let g = system.focal_length;
    let lens = |r2: f64| Complex64::from_polar(1.0, -k * r2 / (2.0 * g));
    let u = two_step(
        system,
        &u0,
        dx,
        w,
        transfer(system.doe_to_lens, system.cells),
        transfer(system.lens_to_sensor, false),
        lens,
    )?;
    Ok(SensorIntensity { intensity: u.mapv(|v| v.norm_sqr()), input_power })
}

/// Shared by the transfer-function methods: embeds `u0` centred in a `w x w` window, applies
/// `h1`, the lens `lens(r^2)`, `h2`, and returns the centred `crop * subsample` field.
pub(crate) fn two_step(
    system: &OpticalSystem,
    u0: &Array2<Complex64>,
    dx: f64,
    w: usize,
    h1: Array2<Complex64>,
    h2: Array2<Complex64>,
    lens: impl Fn(f64) -> Complex64 + Sync,
) -> Result<Array2<Complex64>> {
    let n = u0.dim().0;
    let m = system.samples();
    if m > w || !(w - n).is_multiple_of(2) || !(w - m).is_multiple_of(2) {
        return Err(Error::validity(
            Condition::Geometry,
            format!(
                "the sensor crop ({m} samples) does not fit centred in the {w}-sample propagation window"
            ),
        ));
    }
    let plan = Plan2d::new(w);
    let mut u = Array2::<Complex64>::zeros((w, w));
    let o = (w - n) / 2;
    u.slice_mut(s![o..o + n, o..o + n]).assign(u0);
    plan.convolve(&mut u, &h1);
    let c = (w as f64 - 1.0) * 0.5;
    let x: Vec<f64> = (0..w).map(|j| (j as f64 - c) * dx).collect();
    u.as_slice_mut().expect("standard layout").par_chunks_mut(w).enumerate().for_each(|(i, row)| {
        for (j, v) in row.iter_mut().enumerate() {
            *v *= lens(x[i] * x[i] + x[j] * x[j]);
        }
    });
    plan.convolve(&mut u, &h2);
    let o = (w - m) / 2;
    Ok(u.slice(s![o..o + m, o..o + m]).to_owned())
}
