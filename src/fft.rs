//! FFTs through `rustfft`, planned once per shape and reused: the one place the crate plans
//! and runs them, for the optics (propagation, PSF comparison, image formation) and the
//! metrology (the coarse search of a scan's registration) alike.
//!
//! Conventions (those of `rustfft`, fixed here once): no normalisation in either direction
//! (a forward then inverse transform multiplies by the sample count) unless a method says
//! otherwise, DC at index 0, bin `k` is the frequency `k / (n dx)` for `k < n/2` and
//! `(k - n) / (n dx)` above ([`fft_freq`]).
//!
//! A [`Plan2d`] holds the 1-D transforms along its rows and along its columns (one plan where
//! the grid is square), in `f64` or `f32` (`rustfft::FftNum`). Its 2-D transforms are all
//! rows, transpose, rows:
//! * [`Plan2d::transform`] and [`Plan2d::convolve`] on an `Array2`, the rows in parallel with
//!   rayon (each task with its own scratch; every row is transformed alone, so the result does
//!   not depend on the thread count).
//!   [`Plan2d::convolve`] applies a transfer function `H(fx, fy)` that is symmetric under
//!   swapping its axes (true of every free-space propagator on a square grid with equal
//!   pitch): forward rows, transpose, rows gives the transposed spectrum; multiplying by `H`
//!   and running the same sequence inverse returns the result in the original orientation, so
//!   a convolution costs two transposes instead of four.
//! * [`Plan2d::transform_with`] on a row-major slice, on the calling thread with a
//!   [`Workspace`] it owns (for callers that run many small transforms in parallel).
//! * [`Plan2d::forward_transposed`] and [`Plan2d::inverse_transposed`]: one transpose each
//!   way, the spectrum column-major in between (for products with a spectrum of the same
//!   layout, as a linear convolution's).
//!
//! A [`Plan1d`] transforms single lanes (a profile, a row or column taken out of a grid).

use std::sync::Arc;

use ndarray::Array2;
use rayon::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::num_traits::NumAssign;
use rustfft::{Fft, FftNum, FftPlanner};

/// The zero of `Complex<T>`.
fn zero<T: FftNum>() -> Complex<T> {
    Complex::new(T::zero(), T::zero())
}

/// `x` in `T` (exact for `f64`; rounded to nearest for `f32`).
fn real<T: FftNum>(x: f64) -> T {
    T::from_f64(x).expect("a finite f64 converts to every FftNum")
}

/// A planned 2-D FFT of `rows x cols` samples (forward and inverse), square or rectangular.
#[derive(Clone)]
pub struct Plan2d<T: FftNum = f64> {
    rows: usize,
    cols: usize,
    /// Along each row (length `cols`): forward, inverse.
    along_rows: [Arc<dyn Fft<T>>; 2],
    /// Along each column (length `rows`): forward, inverse.
    along_cols: [Arc<dyn Fft<T>>; 2],
}

/// The buffers of [`Plan2d::transform_with`]: `rustfft`'s scratch and the transposed grid.
#[derive(Clone)]
pub struct Workspace<T: FftNum> {
    scratch: Vec<Complex<T>>,
    tmp: Vec<Complex<T>>,
}

impl<T: FftNum + NumAssign> Plan2d<T> {
    /// Plans the square transforms of side `n`.
    pub fn new(n: usize) -> Plan2d<T> {
        Plan2d::rect(n, n)
    }

    /// Plans the transforms of `rows x cols` samples.
    pub fn rect(rows: usize, cols: usize) -> Plan2d<T> {
        let mut planner = FftPlanner::new();
        let along_rows = [planner.plan_fft_forward(cols), planner.plan_fft_inverse(cols)];
        let along_cols = [planner.plan_fft_forward(rows), planner.plan_fft_inverse(rows)];
        Plan2d { rows, cols, along_rows, along_cols }
    }

    /// The side of a square plan (its row count).
    /// The number of rows (the side of a square plan).
    pub fn len(&self) -> usize {
        self.rows
    }

    /// Whether the plan has no samples.
    pub fn is_empty(&self) -> bool {
        self.rows == 0 || self.cols == 0
    }

    /// `(rows, cols)`.
    pub fn dim(&self) -> (usize, usize) {
        (self.rows, self.cols)
    }

    /// Transforms every lane of `data` (row-major lanes of `fft.len()` samples) in place, the
    /// lanes split into blocks of about `lanes / (2 threads)`, one task each.
    fn lanes(fft: &Arc<dyn Fft<T>>, data: &mut [Complex<T>]) {
        let n = fft.len();
        let lanes = data.len() / n.max(1);
        let tasks = rayon::current_num_threads().max(1) * 2;
        let lanes_per_task = lanes.div_ceil(tasks).max(1);
        data.par_chunks_mut(lanes_per_task * n).for_each(|chunk| {
            let mut scratch = vec![zero::<T>(); fft.get_inplace_scratch_len()];
            fft.process_with_scratch(chunk, &mut scratch);
        });
    }

    /// The unnormalised 2-D DFT of `field` in place, forward or `inverse`
    /// (`exp(+2 pi i k x / n)`).
    ///
    /// # Panics
    /// If `field` is not `rows x cols` (a programming error, not user input).
    pub fn transform(&self, field: &mut Array2<Complex<T>>, inverse: bool) {
        let (r, c) = (self.rows, self.cols);
        assert_eq!(field.dim(), (r, c), "field does not match the plan");
        let k = usize::from(inverse);
        let mut tmp = vec![zero::<T>(); r * c];
        let data = field.as_slice_mut().expect("standard layout");
        Self::lanes(&self.along_rows[k], data);
        transpose::transpose(data, &mut tmp, c, r);
        Self::lanes(&self.along_cols[k], &mut tmp);
        transpose::transpose(&tmp, data, r, c);
    }

    /// Multiplies the 2-D spectrum of `field` by `h` (in FFT order, symmetric in its two axes)
    /// and transforms back, normalised: the circular convolution of `field` with the kernel
    /// whose transfer function is `h`. Square plans only.
    ///
    /// # Panics
    /// If the plan is not square, or `field` or `h` is not `n x n` (a programming error, not
    /// user input).
    pub fn convolve(&self, field: &mut Array2<Complex<T>>, h: &Array2<Complex<T>>) {
        let n = self.rows;
        assert_eq!(self.cols, n, "convolve needs a square plan");
        assert_eq!(field.dim(), (n, n), "field does not match the plan");
        assert_eq!(h.dim(), (n, n), "transfer function does not match the plan");
        let [forward, inverse] = &self.along_rows;
        let mut tmp = vec![zero::<T>(); n * n];
        let data = field.as_slice_mut().expect("standard layout");
        Self::lanes(forward, data);
        transpose::transpose(data, &mut tmp, n, n);
        Self::lanes(forward, &mut tmp);
        let scale = real::<T>(1.0 / (n as f64 * n as f64));
        let hs = h.as_slice().expect("standard layout");
        tmp.par_iter_mut().zip(hs.par_iter()).for_each(|(v, h)| *v *= h * scale);
        Self::lanes(inverse, &mut tmp);
        transpose::transpose(&tmp, data, n, n);
        Self::lanes(inverse, data);
    }

    /// The buffers [`Plan2d::transform_with`] needs (one per thread that runs it).
    pub fn workspace(&self) -> Workspace<T> {
        let plans = self.along_rows.iter().chain(&self.along_cols);
        let n = plans.map(|f| f.get_inplace_scratch_len()).max().unwrap_or(0);
        Workspace { scratch: vec![zero::<T>(); n], tmp: vec![zero::<T>(); self.rows * self.cols] }
    }

    /// The unnormalised 2-D DFT of the row-major `rows x cols` samples `buf` in place, forward
    /// or `inverse`, on the calling thread: rows, transpose, rows, transpose back.
    ///
    /// # Panics
    /// If `buf` or `work` does not match the plan (a programming error, not user input).
    pub fn transform_with(&self, buf: &mut [Complex<T>], inverse: bool, work: &mut Workspace<T>) {
        let (r, c) = (self.rows, self.cols);
        assert_eq!(buf.len(), r * c, "buffer does not match the plan");
        assert_eq!(work.tmp.len(), r * c, "workspace does not match the plan");
        let k = usize::from(inverse);
        let (row, col) = (&self.along_rows[k], &self.along_cols[k]);
        row.process_with_scratch(buf, &mut work.scratch);
        for i in 0..r {
            for j in 0..c {
                work.tmp[j * r + i] = buf[i * c + j];
            }
        }
        col.process_with_scratch(&mut work.tmp, &mut work.scratch);
        for j in 0..c {
            for i in 0..r {
                buf[i * c + j] = work.tmp[j * r + i];
            }
        }
    }

    /// The unnormalised forward 2-D DFT of the row-major `rows x cols` samples `data`, on the
    /// calling thread, returned column-major (rows, transpose, rows: the transpose back is
    /// left out).
    pub fn forward_transposed(&self, data: Vec<Complex<T>>) -> Vec<Complex<T>> {
        self.transposing(data, false)
    }

    /// The inverse of [`Plan2d::forward_transposed`], normalised (divided by `rows cols`): a
    /// column-major spectrum in, the row-major samples out.
    pub fn inverse_transposed(&self, spectrum: Vec<Complex<T>>) -> Vec<Complex<T>> {
        self.transposing(spectrum, true)
    }

    /// 2-D FFT of a row-major buffer with one transpose: the forward result is column-major;
    /// the inverse takes column-major and returns row-major, normalised.
    fn transposing(&self, data: Vec<Complex<T>>, inverse: bool) -> Vec<Complex<T>> {
        let (r, c) = (self.rows, self.cols);
        let k = usize::from(inverse);
        let (first, second, n1, n2) = if inverse {
            (&self.along_cols[k], &self.along_rows[k], r, c)
        } else {
            (&self.along_rows[k], &self.along_cols[k], c, r)
        };
        let mut data = data;
        let mut scratch =
            vec![zero::<T>(); first.get_inplace_scratch_len().max(second.get_inplace_scratch_len())];
        first.process_with_scratch(&mut data, &mut scratch[..first.get_inplace_scratch_len()]);
        let mut t = vec![zero::<T>(); r * c];
        transpose::transpose(&data, &mut t, n1, n2);
        second.process_with_scratch(&mut t, &mut scratch[..second.get_inplace_scratch_len()]);
        if inverse {
            let scale = real::<T>(1.0 / (r * c) as f64);
            t.iter_mut().for_each(|v| *v *= scale);
        }
        t
    }
}

/// A planned 1-D FFT of length `n` (forward and inverse, unnormalised).
pub struct Plan1d<T: FftNum = f64> {
    forward: Arc<dyn Fft<T>>,
    inverse: Arc<dyn Fft<T>>,
}

impl<T: FftNum> Plan1d<T> {
    /// Plans the transforms of length `n`.
    pub fn new(n: usize) -> Plan1d<T> {
        let mut planner = FftPlanner::new();
        Plan1d { forward: planner.plan_fft_forward(n), inverse: planner.plan_fft_inverse(n) }
    }

    /// The transform's length, samples.
    pub fn len(&self) -> usize {
        self.forward.len()
    }

    /// Whether the transform has no samples.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The unnormalised DFT of `buf` in place (every lane of `len()` samples, one after the
    /// other), forward or `inverse`.
    pub fn process(&self, buf: &mut [Complex<T>], inverse: bool) {
        if inverse { &self.inverse } else { &self.forward }.process(buf);
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

/// The smallest `n >= m` of the form `2^a 3^b 5^c` (fast for `rustfft`).
pub fn fast_len(m: usize) -> usize {
    let mut n = m.max(1);
    loop {
        let mut k = n;
        for f in [2, 3, 5] {
            while k.is_multiple_of(f) {
                k /= f;
            }
        }
        if k == 1 {
            return n;
        }
        n += 1;
    }
}

#[cfg(test)]
mod tests {
    use rustfft::num_complex::{Complex32, Complex64};

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
            let plan = Plan2d::new(n);
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
        let plan = Plan2d::new(n);
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

    /// A rectangular field's 2-D DFT against the direct sum, in both directions; the serial
    /// path ([`Plan2d::transform_with`]) and the one-transpose path give the same bits as the
    /// parallel one (the same 1-D plans on the same lanes).
    #[test]
    fn rectangular_transforms_match_the_naive_dft_and_each_other() {
        let (r, c) = (6usize, 10usize);
        let field = Array2::from_shape_fn((r, c), |(i, j)| {
            Complex64::new((i as f64 * 0.9 - j as f64 * 0.4).sin(), (i + 2 * j) as f64 * 0.05)
        });
        let plan = Plan2d::rect(r, c);
        assert_eq!((plan.dim(), plan.is_empty()), ((r, c), false));
        for inverse in [false, true] {
            let sign = if inverse { 1.0 } else { -1.0 };
            let mut got = field.clone();
            plan.transform(&mut got, inverse);
            for ((p, q), g) in got.indexed_iter() {
                let mut want = Complex64::new(0.0, 0.0);
                for ((i, j), v) in field.indexed_iter() {
                    let t = (p * i) as f64 / r as f64 + (q * j) as f64 / c as f64;
                    want += v * Complex64::from_polar(1.0, sign * 2.0 * std::f64::consts::PI * t);
                }
                assert!((g - want).norm() < 1e-10, "{g} vs {want}");
            }
            let mut serial = field.as_slice().unwrap().to_vec();
            plan.transform_with(&mut serial, inverse, &mut plan.workspace());
            assert!(serial
                .iter()
                .zip(got.iter())
                .all(|(a, b)| a.re.to_bits() == b.re.to_bits() && a.im.to_bits() == b.im.to_bits()));
        }
        let mut full = field.clone();
        plan.transform(&mut full, false);
        let spectrum = plan.forward_transposed(field.as_slice().unwrap().to_vec());
        for ((p, q), v) in full.indexed_iter() {
            assert_eq!(spectrum[q * r + p], *v);
        }
        let back = plan.inverse_transposed(spectrum);
        for (a, b) in back.iter().zip(field.iter()) {
            assert!((a - b).norm() < 1e-12, "{a} vs {b}");
        }
    }

    /// The single-precision plan against the double-precision one, and a lane of the 1-D plan
    /// against the naive sum.
    #[test]
    fn single_precision_and_one_dimensional_plans() {
        let (r, c) = (5usize, 8usize);
        let field: Vec<Complex64> =
            (0..r * c).map(|k| Complex64::new((k as f64 * 0.37).cos(), 0.0)).collect();
        let plan = Plan2d::<f64>::rect(r, c);
        let mut want = field.clone();
        plan.transform_with(&mut want, false, &mut plan.workspace());
        let plan32 = Plan2d::<f32>::rect(r, c);
        let mut got: Vec<Complex32> =
            field.iter().map(|v| Complex32::new(v.re as f32, v.im as f32)).collect();
        plan32.transform_with(&mut got, false, &mut plan32.workspace());
        for (g, w) in got.iter().zip(&want) {
            assert!(
                (f64::from(g.re) - w.re).abs() < 1e-4 && (f64::from(g.im) - w.im).abs() < 1e-4,
                "{g} vs {w}"
            );
        }
        let lane = Plan1d::new(c);
        assert_eq!((lane.len(), lane.is_empty()), (c, false));
        let mut row = field[..c].to_vec();
        lane.process(&mut row, false);
        for (k, v) in row.iter().enumerate() {
            let mut s = Complex64::new(0.0, 0.0);
            for (j, x) in field[..c].iter().enumerate() {
                s += x * Complex64::from_polar(1.0, -2.0 * std::f64::consts::PI * (k * j) as f64 / c as f64);
            }
            assert!((v - s).norm() < 1e-12, "{v} vs {s}");
        }
        lane.process(&mut row, true);
        assert!(row.iter().zip(&field[..c]).all(|(a, b)| (a / c as f64 - b).norm() < 1e-12));
    }

    #[test]
    fn good_sizes() {
        assert_eq!(good_size(1959, 0), 2000);
        assert_eq!(good_size(1306, 0), 1350);
        assert_eq!(good_size(7, 1), 9);
        assert_eq!(fft_freq(3, 4, 0.5), -0.5);
        assert_eq!((fast_len(0), fast_len(7), fast_len(97), fast_len(1001)), (1, 8, 100, 1024));
    }
}
