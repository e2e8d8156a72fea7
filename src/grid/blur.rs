//! Gaussian blur of a sampled grid, below the stages that use it: the lateral resolution of a
//! fabrication process (metrology's simulated scans and fitted model, fabrication's
//! pre-compensation) and the registration's smoothing.

use ndarray::Array2;

use crate::error::{Error, Result};
use crate::grid::Grid;

/// Separable Gaussian blur (standard deviation `sigma` metres) normalised over valid samples:
/// `sum w g v / sum w g` with `w` the validity (Knutsson & Westin's normalized convolution).
pub fn gaussian_blur(g: &Grid, sigma: f64) -> Result<Grid> {
    if !(sigma.is_finite() && sigma >= 0.0) {
        return Err(Error::param("blur", format!("must be finite and >= 0, got {sigma} m")));
    }
    if sigma == 0.0 {
        return Ok(g.clone());
    }
    let (nr, nc) = g.dim();
    let kernel = |s: f64| -> Vec<f64> {
        let r = (4.0 * s).ceil() as isize;
        (-r..=r).map(|k| (-0.5 * (k as f64 / s).powi(2)).exp()).collect()
    };
    let kx = kernel(sigma / g.pitch()[0]);
    let ky = kernel(sigma / g.pitch()[1]);
    if g.mask().is_none() {
        // Every sample valid: the weight sum factorises, so each axis normalises on its own.
        let rows = blur_axis(g.values(), &kx, 1)?;
        return g.map_values(blur_axis(&rows, &ky, 0)?, g.unit());
    }
    let w0 = Array2::from_shape_fn((nr, nc), |(i, j)| if g.is_valid(i, j) { 1.0 } else { 0.0 });
    let v0 = g.values() * &w0;
    let pass = |a: &Array2<f64>, k: &[f64], axis: usize| -> Array2<f64> {
        let r = (k.len() / 2) as isize;
        let n = if axis == 0 { nr } else { nc } as isize;
        Array2::from_shape_fn((nr, nc), |(i, j)| {
            let c = if axis == 0 { i } else { j } as isize;
            let mut acc = 0.0;
            for (t, w) in k.iter().enumerate() {
                let p = c + t as isize - r;
                if p >= 0 && p < n {
                    let p = p as usize;
                    acc += w * if axis == 0 { a[[p, j]] } else { a[[i, p]] };
                }
            }
            acc
        })
    };
    let num = pass(&pass(&v0, &kx, 1), &ky, 0);
    let den = pass(&pass(&w0, &kx, 1), &ky, 0);
    let values =
        Array2::from_shape_fn(
            (nr, nc),
            |(i, j)| {
                if den[[i, j]] > 0.0 {
                    num[[i, j]] / den[[i, j]]
                } else {
                    0.0
                }
            },
        );
    g.map_values(values, g.unit())
}

/// The values convolved along `axis` (1: along rows, 0: along columns) with the odd kernel
/// `k` (centre at `k.len() / 2`), normalised by the weights of the taps inside the grid; output
/// rows in parallel.
fn blur_axis(a: &Array2<f64>, k: &[f64], axis: usize) -> Result<Array2<f64>> {
    use rayon::prelude::*;
    let (nr, nc) = a.dim();
    let r = k.len() / 2;
    let a = a.as_standard_layout();
    let src = a.as_slice().ok_or_else(|| Error::Data("blur: values not contiguous".into()))?;
    let mut out = vec![0.0; nr * nc];
    let span = |c: usize, n: usize| (c.saturating_sub(r), (c + r).min(n - 1));
    out.par_chunks_mut(nc).enumerate().for_each(|(i, o)| {
        if axis == 1 {
            let row = &src[i * nc..(i + 1) * nc];
            for (j, oj) in o.iter_mut().enumerate() {
                let (lo, hi) = span(j, nc);
                let taps = &k[lo + r - j..=hi + r - j];
                let acc: f64 = taps.iter().zip(&row[lo..=hi]).map(|(t, v)| t * v).sum();
                *oj = acc / taps.iter().sum::<f64>();
            }
        } else {
            let (lo, hi) = span(i, nr);
            let taps = &k[lo + r - i..=hi + r - i];
            let w: f64 = taps.iter().sum();
            for (p, t) in (lo..=hi).zip(taps) {
                let t = t / w;
                for (x, y) in o.iter_mut().zip(&src[p * nc..(p + 1) * nc]) {
                    *x += t * y;
                }
            }
        }
    });
    Array2::from_shape_vec((nr, nc), out).map_err(|e| Error::Data(format!("blur: {e}")))
}
