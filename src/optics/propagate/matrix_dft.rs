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

use ndarray::{s, Array2, Axis, LinalgScalar};
use rayon::prelude::*;
use rustfft::num_complex::Complex64;

use super::method::{check_fresnel, field_power, pupil_phase, Precision, SensorIntensity, Violation};
use crate::error::{Condition, Error, Result};
use crate::grid::{Grid, Interpolation};
use crate::optics::system::{nested_parity, nested_refinement, sinc, OpticalSystem};

/// The pupil grid of this method: `(n, dx)` with `dx` the system's pupil pitch and `n` just
/// covering the aperture, with the DOE's parity when the DOE has that pitch (so the samples
/// coincide and no interpolation happens), and with nearest interpolation at a whole fraction
/// of the DOE's pitch the parity that nests the pupil samples in the DOE's cells
/// ([`nested_refinement`]).
pub fn pupil_grid(system: &OpticalSystem, doe: &Grid) -> (usize, f64) {
    let dx = system.pupil_pitch;
    let same = doe.pitch().iter().all(|p| (p / dx - 1.0).abs() < 1e-12);
    let nested = match system.interpolation {
        Interpolation::Nearest => nested_refinement(doe, dx),
        _ => None,
    };
    let parity = match nested {
        _ if same => doe.dim().1 % 2,
        Some(k) => nested_parity(doe, k),
        None => 0,
    };
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

/// The sensor intensity at `wavelength` on the sub-sample grid (see the module docs), with the
/// matrix products in `precision`.
pub fn sensor_intensity(
    system: &OpticalSystem,
    doe: &Grid,
    wavelength: f64,
    precision: Precision,
) -> Result<SensorIntensity> {
    let (n, dx) = pupil_grid(system, doe);
    let u1 = system.pupil_field(doe, n, dx, wavelength, true)?;
    let input_power = field_power(&u1, dx);
    let xs = system.sensor_coords();
    let intensity = match precision {
        Precision::F32 => transform::<f32>(system, &u1, dx, &xs, wavelength)?,
        Precision::F64 => transform::<f64>(system, &u1, dx, &xs, wavelength)?,
    };
    Ok(SensorIntensity { intensity, input_power })
}

/// A real type the matrix products run in (`f32` or `f64`); phases and trigonometry are
/// always evaluated in `f64` and rounded once.
pub trait Real: LinalgScalar + Send + Sync {
    /// `x` rounded to this type.
    fn of(x: f64) -> Self;
    /// The value widened to `f64`.
    fn wide(self) -> f64;
}

impl Real for f32 {
    fn of(x: f64) -> f32 {
        x as f32
    }
    fn wide(self) -> f64 {
        self as f64
    }
}

impl Real for f64 {
    fn of(x: f64) -> f64 {
        x
    }
    fn wide(self) -> f64 {
        self
    }
}

/// Collins' integral of the pupil field `u1` (pitch `dx`, centred) evaluated at the sensor
/// points `xs x xs` (metres, both axes, symmetric about the axis as
/// [`OpticalSystem::sensor_coords`]): the intensity `|U2|^2`.
///
/// Both coordinate sets are symmetric about 0 (`u_{n-1-j} = -u_j`, `x_{M-1-q} = -x_q`), so the
/// kernel `exp(-i a x u) = cos(a x u) - i sin(a x u)` (`a = 2 pi / (lambda B)`) folds: with
/// `G+-` the pupil columns at `+-u`, `sum_j G_j exp(-i a x u_j) = sum_{u > 0} (G+ + G-) cos -
/// i (G+ - G-) sin`, and the result at `-x` is the same with `+i`. Each of the two 1-D transforms
/// becomes two real matrix products over half the pupil for half the sensor, a quarter of the
/// arithmetic of the complex product (`2 n^2 M` real multiply-adds for the first, `n M^2 / 2`
/// for the second, n pupil and M sensor samples per side). The products run in `T` through
/// `matrixmultiply`'s GEMM, split over rayon's threads by rows.
pub fn transform<T: Real>(
    system: &OpticalSystem,
    u1: &Array2<Complex64>,
    dx: f64,
    xs: &[f64],
    wavelength: f64,
) -> Result<Array2<f64>> {
    let m = system.abcd();
    if m.b.abs() < 1e-9 * system.focal_length {
        return Err(Error::validity(Condition::Geometry, "B = 0: the sensor images the DOE plane"));
    }
    let n = u1.dim().0;
    let c = (n as f64 - 1.0) * 0.5;
    let u: Vec<f64> = (0..n).map(|j| (j as f64 - c) * dx).collect();
    let lb = wavelength * m.b;
    // Only the quadratic term of the pupil that the transform itself adds (A/B); the object's
    // spherical wave is already in u1.
    let ca = PI * m.a / lb;
    let g = |i: usize, j: usize| {
        let v = u1[[i, j]];
        if v == Complex64::new(0.0, 0.0) || ca == 0.0 {
            v
        } else {
            v * Complex64::from_polar(1.0, ca * (u[i] * u[i] + u[j] * u[j]))
        }
    };
    let big_m = xs.len();
    let span = xs.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    if (0..big_m).any(|q| (xs[q] + xs[big_m - 1 - q]).abs() > 1e-9 * span) {
        return Err(Error::param("xs", "the sensor points must lie symmetric about the axis"));
    }
    // Pupil pairs k = 0..h: columns (n-1-k, k) at +-w_k, w_k = u_{n-1-k} >= 0 (the centre
    // column of an odd n pairs with itself and counts once). Sensor pairs p = 0..mh likewise.
    let (h, mh) = (n.div_ceil(2), big_m.div_ceil(2));
    let a = 2.0 * PI / lb;
    // Cell envelope: sinc of the sensor position's spatial frequency x / (lambda B) times dx
    // (exact in focus, where the transform is a Fourier transform).
    let (cos, sin) = {
        let mut cm = Array2::<T>::zeros((mh, h));
        let mut sm = Array2::<T>::zeros((mh, h));
        for p in 0..mh {
            let y = xs[big_m - 1 - p];
            let env = if system.cells { sinc(y * dx / lb) } else { 1.0 };
            for k in 0..h {
                let (s, co) = (a * y * u[n - 1 - k]).sin_cos();
                cm[[p, k]] = T::of(env * co);
                sm[[p, k]] = T::of(env * s);
            }
        }
        (cm, sm)
    };
    // Sum and difference of the paired samples (`get(r, k)`, k along the folded axis of length
    // n), real and imaginary parts stacked: two `2 rows x h` real matrices.
    let fold = |get: &dyn Fn(usize, usize) -> Complex64, rows: usize| {
        let mut even = Array2::<T>::zeros((2 * rows, h));
        let mut odd = Array2::<T>::zeros((2 * rows, h));
        for r in 0..rows {
            for k in 0..h {
                let plus = get(r, n - 1 - k);
                let (e, o) = if n - 1 - k == k {
                    (plus, Complex64::new(0.0, 0.0))
                } else {
                    let minus = get(r, k);
                    (plus + minus, plus - minus)
                };
                even[[r, k]] = T::of(e.re);
                even[[rows + r, k]] = T::of(e.im);
                odd[[r, k]] = T::of(o.re);
                odd[[rows + r, k]] = T::of(o.im);
            }
        }
        (even, odd)
    };
    // The folded transform of `rows` stacked rows: value at row r and sensor sample q.
    // With P = even cos^T and Q = odd sin^T, the value at +x_p is P - i Q and at -x_p is P + i Q.
    let unfold = |pm: &Array2<T>, qm: &Array2<T>, rows: usize, r: usize, q: usize| {
        let plus = q >= big_m / 2;
        let p = if plus { big_m - 1 - q } else { q };
        let (pr, pi) = (pm[[r, p]].wide(), pm[[rows + r, p]].wide());
        let (qr, qi) = (qm[[r, p]].wide(), qm[[rows + r, p]].wide());
        if plus {
            Complex64::new(pr + qi, pi - qr)
        } else {
            Complex64::new(pr - qi, pi + qr)
        }
    };
    // Step 1, along the pupil's x (columns): rows are the pupil's y.
    let (ge, go) = fold(&|i, j| g(i, j), n);
    let (p1, q1) = (par_gemm(&ge, &cos), par_gemm(&go, &sin));
    drop((ge, go));
    // Step 2, along the pupil's y: rows are the sensor's x.
    let (te, to) = fold(&|q, i| unfold(&p1, &q1, n, i, q), big_m);
    let (p2, q2) = (par_gemm(&te, &cos), par_gemm(&to, &sin));
    let scale = (dx * dx / lb).powi(2);
    Ok(Array2::from_shape_fn((big_m, big_m), |(row, col)| {
        unfold(&p2, &q2, big_m, col, row).norm_sqr() * scale
    }))
}

/// `a b^T` by GEMM, the rows of `a` split into blocks over rayon's threads.
fn par_gemm<T: Real>(a: &Array2<T>, b: &Array2<T>) -> Array2<T> {
    let rows = a.nrows();
    let block = rows.div_ceil(2 * rayon::current_num_threads()).max(64);
    let parts: Vec<Array2<T>> = (0..rows)
        .step_by(block)
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|r0| a.slice(s![r0..(r0 + block).min(rows), ..]).dot(&b.t()))
        .collect();
    let views: Vec<_> = parts.iter().map(|p| p.view()).collect();
    ndarray::concatenate(Axis(0), &views).expect("blocks share their column count")
}
