//! Outlier detection: spikes and dropouts of a scan, returned as a mask (`true` = outlier) to
//! be removed from the validity mask ([`without_outliers`]) and, if wanted, filled
//! ([`crate::grid::fill::fill_missing`]).
//!
//! * [`nsigma_outliers`]: residuals from a least-squares polynomial of order k (1 = plane) fitted
//!   on the valid samples; a sample is an outlier where `|residual| > n * sigma`, sigma the
//!   residuals' RMS. The test repeats on the remaining samples (refit, new sigma) until no new
//!   outlier appears or `max_iterations` passes are done.
//! * [`median_outliers`]: residuals from a `size x size` median of the valid neighbours; a
//!   sample is an outlier where `|residual| > max(n * 1.4826 * MAD, min_step)`, MAD the median
//!   absolute residual (1.4826 MAD estimates sigma for Gaussian noise without being pulled by the
//!   outliers). `min_step` keeps a noise-free scan (MAD = 0) from flagging every edge: on a
//!   stepped surface the median filter leaves the corners of each step as residuals of one step
//!   height, so `min_step` should exceed the design's largest step.

use ndarray::Array2;
use serde::Serialize;

use crate::error::{Allowed, DataCause, Error, Result};
use crate::grid::Grid;
use crate::metrology::level::{level_plane, level_polynomial};

/// What an outlier test found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Outliers {
    /// `true` at each outlier.
    #[serde(skip)]
    pub mask: Array2<bool>,
    /// `(row, column)` of each outlier, row-major order.
    pub positions: Vec<(usize, usize)>,
    /// The final threshold on |residual| (grid units).
    pub threshold: f64,
    /// Passes run (n-sigma test) or 1.
    pub iterations: usize,
}

fn collect(mask: Array2<bool>, threshold: f64, iterations: usize) -> Outliers {
    let positions = mask.indexed_iter().filter(|(_, &m)| m).map(|(p, _)| p).collect();
    Outliers { mask, positions, threshold, iterations }
}

/// The n-sigma test on residuals from a polynomial of order `order` (see the module docs).
pub fn nsigma_outliers(g: &Grid, n: f64, order: usize, max_iterations: usize) -> Result<Outliers> {
    if !(n.is_finite() && n > 0.0) {
        return Err(Error::param_in("n-sigma", Allowed::positive(), format!("must be positive, got {n}")));
    }
    let mut out = Array2::from_elem(g.dim(), false);
    let mut threshold = f64::INFINITY;
    let mut passes = 0;
    for _ in 0..max_iterations.max(1) {
        passes += 1;
        let valid = g.values().indexed_iter().map(|((i, j), _)| g.is_valid(i, j) && !out[[i, j]]);
        let valid =
            Array2::from_shape_vec(g.dim(), valid.collect()).map_err(|e| Error::internal(e.to_string()))?;
        let masked = g.clone().with_mask(valid.clone())?;
        let res = if order == 1 {
            level_plane(&masked, None)?.0
        } else {
            level_polynomial(&masked, order, None)?.0
        };
        let vals: Vec<f64> =
            res.values().indexed_iter().filter(|(p, _)| valid[*p]).map(|(_, &v)| v).collect();
        let sigma = (vals.iter().map(|v| v * v).sum::<f64>() / vals.len() as f64).sqrt();
        threshold = n * sigma;
        let mut new = 0;
        for (p, &r) in res.values().indexed_iter() {
            if valid[p] && r.abs() > threshold {
                out[p] = true;
                new += 1;
            }
        }
        if new == 0 {
            break;
        }
    }
    Ok(collect(out, threshold, passes))
}

/// The median-filter test (see the module docs); `size` is odd, >= 3.
pub fn median_outliers(g: &Grid, size: usize, n: f64, min_step: f64) -> Result<Outliers> {
    if size < 3 || size.is_multiple_of(2) {
        return Err(Error::param("median size", format!("must be odd and at least 3, got {size}")));
    }
    let (nr, nc) = g.dim();
    let h = size / 2;
    let z = g.values();
    let mut res = Array2::from_elem((nr, nc), f64::NAN);
    let mut win = Vec::with_capacity(size * size);
    for i in 0..nr {
        for j in 0..nc {
            if !g.is_valid(i, j) {
                continue;
            }
            win.clear();
            for a in i.saturating_sub(h)..(i + h + 1).min(nr) {
                for b in j.saturating_sub(h)..(j + h + 1).min(nc) {
                    if g.is_valid(a, b) {
                        win.push(z[[a, b]]);
                    }
                }
            }
            win.sort_by(f64::total_cmp);
            let m = win.len();
            let med = if m % 2 == 1 { win[m / 2] } else { 0.5 * (win[m / 2 - 1] + win[m / 2]) };
            res[[i, j]] = z[[i, j]] - med;
        }
    }
    let mut abs: Vec<f64> = res.iter().filter(|v| v.is_finite()).map(|v| v.abs()).collect();
    if abs.is_empty() {
        return Err(Error::data(DataCause::Empty, "no valid sample to test"));
    }
    abs.sort_by(f64::total_cmp);
    let mad = abs[abs.len() / 2];
    let threshold = (n * 1.4826 * mad).max(min_step);
    let mask = res.mapv(|r| r.is_finite() && r.abs() > threshold);
    Ok(collect(mask, threshold, 1))
}

/// The surface with `outliers` marked invalid (non-measured).
pub fn without_outliers(g: &Grid, outliers: &Outliers) -> Result<Grid> {
    let valid = Array2::from_shape_fn(g.dim(), |(i, j)| g.is_valid(i, j) && !outliers.mask[[i, j]]);
    g.clone().with_mask(valid)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Unit;

    #[test]
    fn spikes_on_a_tilted_ramp() {
        let mut v = Array2::from_shape_fn((30, 30), |(i, j)| {
            1e-9 * (j as f64 - 0.5 * i as f64) + 1e-8 * ((i * 7 + j * 3) % 5) as f64
        });
        v[[4, 5]] += 1e-6;
        v[[20, 21]] -= 1e-6;
        let g = Grid::new(v, [1e-6; 2], Unit::Metre).unwrap();
        let o = nsigma_outliers(&g, 3.0, 1, 10).unwrap();
        assert_eq!(o.positions, vec![(4, 5), (20, 21)]);
        let m = median_outliers(&g, 3, 5.0, 0.0).unwrap();
        assert_eq!(m.positions, vec![(4, 5), (20, 21)]);
        let clean = without_outliers(&g, &o).unwrap();
        assert_eq!(clean.valid_count(), 898);
    }
}
