//! Gaussian blur of a sampled grid, below the stages that use it: the lateral resolution of a
//! fabrication process (metrology's simulated scans and fitted model, fabrication's
//! pre-compensation) and the registration's smoothing.

use ndarray::Array2;

use crate::error::{Allowed, Error, Result};
use crate::grid::Grid;

/// Separable Gaussian blur (standard deviation `sigma` metres) normalised over valid samples:
/// `sum w g v / sum w g` with `w` the validity (Knutsson & Westin's normalized convolution).
pub fn gaussian_blur(g: &Grid, sigma: f64) -> Result<Grid> {
    if !(sigma.is_finite() && sigma >= 0.0) {
        return Err(Error::param_in(
            "blur",
            Allowed::at_least(0.0),
            format!("must be finite and >= 0, got {sigma} m"),
        ));
    }
    if sigma == 0.0 {
        return Ok(g.clone());
    }
    let (nr, nc) = g.dim();
    let kx = gaussian_kernel(sigma / g.pitch()[0]);
    let ky = gaussian_kernel(sigma / g.pitch()[1]);
    if g.mask().is_none() {
        // Every sample valid: the weight sum factorises, so each axis normalises on its own.
        return g.map_values(blur_separable(g.values(), &kx, &ky)?, g.unit());
    }
    // Normalised convolution: both passes of the numerator and the weights share each
    // output's normalisation by the taps inside the grid, which cancels in their ratio.
    let w0 = Array2::from_shape_fn((nr, nc), |(i, j)| if g.is_valid(i, j) { 1.0 } else { 0.0 });
    let v0 = g.values() * &w0;
    let num = blur_separable(&v0, &kx, &ky)?;
    let den = blur_separable(&w0, &kx, &ky)?;
    let values = ndarray::Zip::from(&num).and(&den).map_collect(|&n, &d| if d > 0.0 { n / d } else { 0.0 });
    g.map_values(values, g.unit())
}

/// Separable Gaussian blur of plain samples, standard deviation `sigma` in samples, each axis
/// normalised by the weights of its taps inside the array (so a constant stays constant up to
/// the edges). `sigma` 0 returns the values.
pub fn blur_samples(values: &Array2<f64>, sigma: f64) -> Result<Array2<f64>> {
    if !(sigma.is_finite() && sigma >= 0.0) {
        return Err(Error::param_in(
            "blur",
            Allowed::at_least(0.0),
            format!("must be finite and >= 0, got {sigma} samples"),
        ));
    }
    if sigma == 0.0 {
        return Ok(values.clone());
    }
    let k = gaussian_kernel(sigma);
    blur_separable(values, &k, &k)
}

/// The taps `exp(-k^2 / 2 s^2)`, `|k| <= ceil(4 s)`, of a Gaussian of `s` samples.
fn gaussian_kernel(s: f64) -> Vec<f64> {
    let r = (4.0 * s).ceil() as isize;
    (-r..=r).map(|k| (-0.5 * (k as f64 / s).powi(2)).exp()).collect()
}

/// The values convolved with the odd kernels `kx` along rows and `ky` along columns (centres at
/// `len / 2`), each axis normalised by the weights of its taps inside the grid. One sweep over
/// the output rows in parallel: each row first combines its `ky` input rows, then runs `kx` along
/// the result; every output sample is summed in the same order whatever the thread count.
fn blur_separable(a: &Array2<f64>, kx: &[f64], ky: &[f64]) -> Result<Array2<f64>> {
    use rayon::prelude::*;
    let (nr, nc) = a.dim();
    let (rx, ry) = (kx.len() / 2, ky.len() / 2);
    let a = a.as_standard_layout();
    let src = a.as_slice().ok_or_else(|| Error::internal("blur: values not contiguous"))?;
    let span = |c: usize, n: usize, r: usize| (c.saturating_sub(r), (c + r).min(n - 1));
    let kx_sum: f64 = kx.iter().sum();
    let mut out = vec![0.0; nr * nc];
    out.par_chunks_mut(nc).enumerate().for_each_init(
        || vec![0.0; nc],
        |col, (i, o)| {
            let (lo, hi) = span(i, nr, ry);
            let taps = &ky[lo + ry - i..=hi + ry - i];
            let w: f64 = taps.iter().sum();
            col.iter_mut().for_each(|x| *x = 0.0);
            for (p, t) in (lo..=hi).zip(taps) {
                let t = t / w;
                for (x, y) in col.iter_mut().zip(&src[p * nc..(p + 1) * nc]) {
                    *x += t * y;
                }
            }
            for (j, oj) in o.iter_mut().enumerate() {
                if j >= rx && j + rx < nc {
                    let acc: f64 = kx.iter().zip(&col[j - rx..=j + rx]).map(|(t, v)| t * v).sum();
                    *oj = acc / kx_sum;
                } else {
                    let (lo, hi) = span(j, nc, rx);
                    let taps = &kx[lo + rx - j..=hi + rx - j];
                    let acc: f64 = taps.iter().zip(&col[lo..=hi]).map(|(t, v)| t * v).sum();
                    *oj = acc / taps.iter().sum::<f64>();
                }
            }
        },
    );
    Array2::from_shape_vec((nr, nc), out).map_err(|e| Error::internal(format!("blur: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Unit;

    /// A grid with a hole and a ramp, blurred against the direct two-dimensional sum
    /// `sum_kl w_kl g_kl v_kl / sum_kl w_kl g_kl` written out here.
    #[test]
    fn masked_blur_equals_the_direct_normalised_convolution() {
        let (nr, nc, pitch, sigma) = (23, 31, 2e-6, 3.1e-6);
        let v = Array2::from_shape_fn((nr, nc), |(i, j)| (0.3 * i as f64).sin() + 0.05 * j as f64);
        let mask = Array2::from_shape_fn((nr, nc), |(i, j)| {
            !((5..9).contains(&i) && (10..20).contains(&j)) && (i + j) % 7 != 0
        });
        let g = Grid::new(v.clone(), [pitch; 2], Unit::Metre).unwrap().with_mask(mask.clone()).unwrap();
        let b = gaussian_blur(&g, sigma).unwrap();
        let r = (4.0 * sigma / pitch).ceil() as isize;
        for i in 0..nr as isize {
            for j in 0..nc as isize {
                let (mut num, mut den) = (0.0, 0.0);
                for k in (i - r).max(0)..=(i + r).min(nr as isize - 1) {
                    for l in (j - r).max(0)..=(j + r).min(nc as isize - 1) {
                        let (k, l) = (k as usize, l as usize);
                        if mask[[k, l]] {
                            let d2 = ((k as f64 - i as f64).powi(2) + (l as f64 - j as f64).powi(2))
                                * pitch
                                * pitch;
                            let w = (-0.5 * d2 / (sigma * sigma)).exp();
                            num += w * v[[k, l]];
                            den += w;
                        }
                    }
                }
                let got = b.values()[[i as usize, j as usize]];
                assert!((got - num / den).abs() < 1e-12, "({i}, {j}): {got} vs {}", num / den);
            }
        }
    }
}
