//! Square 2-D FFTs through `rustfft`, planned once per size and reused.
//!
//! Conventions (those of `rustfft`, fixed here once): no normalisation in either direction
//! (a forward then inverse transform multiplies by `n^2`), DC at index 0, bin `k` is the
//! frequency `k / (n dx)` for `k < n/2` and `(k - n) / (n dx)` above ([`fft_freq`]).
//! Rows are transformed in parallel with rayon, each task with its own scratch.
//!
//! [`Plan2d::convolve`] applies a transfer function `H(fx, fy)` that is symmetric under
//! swapping its axes (true of every free-space propagator on a square grid with equal pitch):
//! forward rows, transpose, rows gives the transposed spectrum; multiplying by `H` and running
//! the same sequence inverse returns the result in the original orientation, so a convolution
//! costs two transposes instead of four.

use std::sync::Arc;

use ndarray::Array2;
use rayon::prelude::*;
use rustfft::num_complex::Complex64;
use rustfft::{Fft, FftPlanner};

/// A planned square 2-D FFT of side `n` (forward and inverse).
pub struct Plan2d {
    n: usize,
    forward: Arc<dyn Fft<f64>>,
    inverse: Arc<dyn Fft<f64>>,
}

impl Plan2d {
    /// Plans the transforms of side `n` with `planner` (share one planner between plans).
    pub fn new(planner: &mut FftPlanner<f64>, n: usize) -> Plan2d {
        Plan2d { n, forward: planner.plan_fft_forward(n), inverse: planner.plan_fft_inverse(n) }
    }

    /// The side `n` of the transform, samples.
    pub fn len(&self) -> usize {
        self.n
    }

    /// Whether the side is 0.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Transforms every row of `data` (row-major, `n` columns) in place.
    fn rows(&self, data: &mut [Complex64], inverse: bool) {
        let fft = if inverse { &self.inverse } else { &self.forward };
        let n = self.n;
        let tasks = rayon::current_num_threads().max(1) * 2;
        let rows_per_task = n.div_ceil(tasks).max(1);
        data.par_chunks_mut(rows_per_task * n).for_each(|chunk| {
            let mut scratch = vec![Complex64::new(0.0, 0.0); fft.get_inplace_scratch_len()];
            fft.process_with_scratch(chunk, &mut scratch);
        });
    }

    /// The unnormalised 2-D DFT of `field` (side `n`) in place, forward or `inverse`
    /// (`exp(+2 pi i k x / n)`).
    ///
    /// # Panics
    /// If `field` is not `n x n` (a programming error, not user input).
    pub fn transform(&self, field: &mut Array2<Complex64>, inverse: bool) {
        let n = self.n;
        assert_eq!(field.dim(), (n, n), "field does not match the plan");
        let mut tmp = vec![Complex64::new(0.0, 0.0); n * n];
        let data = field.as_slice_mut().expect("standard layout");
        self.rows(data, inverse);
        transpose::transpose(data, &mut tmp, n, n);
        self.rows(&mut tmp, inverse);
        transpose::transpose(&tmp, data, n, n);
    }

    /// Multiplies the 2-D spectrum of `field` (side `n`) by `h` (in FFT order, symmetric in its
    /// two axes) and transforms back, normalised: the circular convolution of `field` with the
    /// kernel whose transfer function is `h`.
    ///
    /// # Panics
    /// If `field` or `h` is not `n x n` (a programming error, not user input).
    pub fn convolve(&self, field: &mut Array2<Complex64>, h: &Array2<Complex64>) {
        let n = self.n;
        assert_eq!(field.dim(), (n, n), "field does not match the plan");
        assert_eq!(h.dim(), (n, n), "transfer function does not match the plan");
        let mut tmp = vec![Complex64::new(0.0, 0.0); n * n];
        let data = field.as_slice_mut().expect("standard layout");
        self.rows(data, false);
        transpose::transpose(data, &mut tmp, n, n);
        self.rows(&mut tmp, false);
        let scale = 1.0 / (n as f64 * n as f64);
        let hs = h.as_slice().expect("standard layout");
        tmp.par_iter_mut().zip(hs.par_iter()).for_each(|(v, h)| *v *= h * scale);
        self.rows(&mut tmp, true);
        transpose::transpose(&tmp, data, n, n);
        self.rows(data, true);
    }
}

/// Frequency of FFT bin `k` of an `n`-point transform at sample pitch `dx`, cycles per metre.
pub fn fft_freq(k: usize, n: usize, dx: f64) -> f64 {
    let k = k as f64;
    let n_f = n as f64;
    if k < n_f / 2.0 {
        k / (n_f * dx)
    } else {
        (k - n_f) / (n_f * dx)
    }
}

/// The smallest length `>= n` whose prime factors are 2, 3 and 5 (fast FFT sizes) and whose
/// parity is `parity` (0 even, 1 odd; odd lengths are products of 3 and 5 only).
pub fn good_size(n: usize, parity: usize) -> usize {
    let mut m = n.max(1);
    loop {
        if m % 2 == parity % 2 {
            let mut r = m;
            for p in [2, 3, 5] {
                while r.is_multiple_of(p) {
                    r /= p;
                }
            }
            if r == 1 {
                return m;
            }
        }
        m += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The naive 2-D DFT as oracle.
    fn naive_convolve(field: &Array2<Complex64>, h: &Array2<Complex64>) -> Array2<Complex64> {
        let n = field.dim().0;
        let w = |a: usize, b: usize, sign: f64| {
            Complex64::from_polar(1.0, sign * 2.0 * std::f64::consts::PI * (a * b % n) as f64 / n as f64)
        };
        let mut spec = Array2::<Complex64>::zeros((n, n));
        for ((p, q), s) in spec.indexed_iter_mut() {
            for ((i, j), v) in field.indexed_iter() {
                *s += v * w(p, i, -1.0) * w(q, j, -1.0);
            }
            *s *= h[[p, q]];
        }
        let mut out = Array2::<Complex64>::zeros((n, n));
        for ((i, j), o) in out.indexed_iter_mut() {
            for ((p, q), s) in spec.indexed_iter() {
                *o += s * w(p, i, 1.0) * w(q, j, 1.0);
            }
            *o /= (n * n) as f64;
        }
        out
    }

    #[test]
    fn convolve_matches_the_naive_dft() {
        for n in [6usize, 9] {
            let field = Array2::from_shape_fn((n, n), |(i, j)| {
                Complex64::new((i as f64 * 0.7 + j as f64 * 1.3).sin(), (i * j) as f64 * 0.1)
            });
            let h = Array2::from_shape_fn((n, n), |(p, q)| {
                let f2 = fft_freq(p, n, 1.0).powi(2) + fft_freq(q, n, 1.0).powi(2);
                Complex64::from_polar(1.0 / (1.0 + f2), 3.0 * f2)
            });
            let mut planner = FftPlanner::new();
            let plan = Plan2d::new(&mut planner, n);
            let mut got = field.clone();
            plan.convolve(&mut got, &h);
            let want = naive_convolve(&field, &h);
            for (a, b) in got.iter().zip(want.iter()) {
                assert!((a - b).norm() < 1e-12, "{a} vs {b}");
            }
        }
    }

    #[test]
    fn transform_matches_the_naive_dft() {
        let n = 10usize;
        let field = Array2::from_shape_fn((n, n), |(i, j)| {
            Complex64::new((i as f64 - 2.0 * j as f64).cos(), j as f64)
        });
        let mut planner = FftPlanner::new();
        let plan = Plan2d::new(&mut planner, n);
        for inverse in [false, true] {
            let sign = if inverse { 1.0 } else { -1.0 };
            let mut got = field.clone();
            plan.transform(&mut got, inverse);
            for ((p, q), g) in got.indexed_iter() {
                let mut want = Complex64::new(0.0, 0.0);
                for ((i, j), v) in field.indexed_iter() {
                    let t = ((p * i + q * j) % n) as f64 / n as f64;
                    want += v * Complex64::from_polar(1.0, sign * 2.0 * std::f64::consts::PI * t);
                }
                assert!((g - want).norm() < 1e-10, "{g} vs {want}");
            }
        }
    }

    #[test]
    fn good_sizes() {
        assert_eq!(good_size(1959, 0), 2000);
        assert_eq!(good_size(1306, 0), 1350);
        assert_eq!(good_size(7, 1), 9);
        assert_eq!(fft_freq(3, 4, 0.5), -0.5);
    }
}
