//! ISO 25178-2 areal height and hybrid parameters, over the valid samples only.
//!
//! With `z_k` the valid heights (N of them), `m` their mean and `d_k = z_k - m` (the mean plane
//! is the reference; level the surface first to refer to a fitted plane):
//!
//! * `Sa = mean |d|`, `Sq = sqrt(mean d^2)` (arithmetic mean and root mean square height),
//! * `Sp = max d`, `Sv = -min d` (both >= 0), `Sz = Sp + Sv`,
//! * `Ssk = mean d^3 / Sq^3` (skewness), `Sku = mean d^4 / Sq^4` (kurtosis, ISO definition:
//!   3 for a Gaussian height distribution; Gwyddion displays `Sku - 3`).
//!
//! Hybrid parameters, discretisation: the gradient is taken on each 2 x 2 cell of samples whose
//! four corners are valid, at the cell centre, by averaged forward differences
//! `gx = ((z[i][j+1] - z[i][j]) + (z[i+1][j+1] - z[i+1][j])) / (2 dx)`, `gy` likewise along rows,
//! with `dx`, `dy` the pitches. Then
//!
//! * `Sdq = sqrt(mean over cells of (gx^2 + gy^2))` (root mean square gradient),
//! * `Sdr = mean over cells of (sqrt(1 + gx^2 + gy^2) - 1)` (developed interfacial area ratio:
//!   each cell's area as that of its tangent plane; Gwyddion triangulates instead, so its Sdr
//!   differs at second order on curved surfaces).
//!
//! Both are exact for a plane: `Sdq = |grad z|`, `Sdr = sqrt(1 + |grad z|^2) - 1`.
//! Sums are accumulated in `f64`, the moments about the mean in a second pass.

use ndarray::{s, Array2, Zip};
use serde::Serialize;

use crate::error::{DataCause, Error, Result};
use crate::grid::{Grid, Unit};

/// ISO 25178 height parameters of a surface (heights in the grid's unit, metres for scans).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HeightParams {
    /// Number of valid samples used.
    pub n: usize,
    /// Mean height (the reference of the other parameters).
    pub mean: f64,
    /// Arithmetic mean height `Sa = mean |d|`, metres.
    pub sa: f64,
    /// Root mean square height `Sq = sqrt(mean d^2)`, metres.
    pub sq: f64,
    /// Maximum peak height `Sp = max d`, metres (>= 0).
    pub sp: f64,
    /// Maximum pit depth `Sv = -min d`, metres (>= 0).
    pub sv: f64,
    /// Maximum height `Sz = Sp + Sv`, metres.
    pub sz: f64,
    /// Skewness (0 for a flat surface).
    pub ssk: f64,
    /// Kurtosis, ISO (3 for a Gaussian; 0 for a flat surface).
    pub sku: f64,
    /// Root mean square gradient; `None` without a 2 x 2 cell of valid samples.
    pub sdq: Option<f64>,
    /// Developed interfacial area ratio (a fraction, not a percentage); `None` as for `sdq`.
    pub sdr: Option<f64>,
}

/// Computes the height parameters over the valid samples of `g` (see the module docs).
pub fn height_params(g: &Grid) -> Result<HeightParams> {
    if g.unit() != Unit::Metre {
        return Err(Error::param("surface", format!("expected heights in m, got {}", g.unit().symbol())));
    }
    let vals: Vec<f64> = match g.mask() {
        None => g.values().iter().copied().collect(),
        Some(m) => g.values().iter().zip(m).filter_map(|(v, ok)| ok.then_some(*v)).collect(),
    };
    if vals.iter().any(|v| !v.is_finite()) {
        if let Some((count, (i, j))) = g.non_finite() {
            return Err(Error::data(
                DataCause::NotFinite,
                format!("{count} valid heights are NaN or infinite (first at row {i}, column {j})"),
            ));
        }
    }
    let n = vals.len();
    if n == 0 {
        return Err(Error::data(DataCause::Empty, "no valid sample: the surface parameters are undefined"));
    }
    let nf = n as f64;
    let mean = vals.iter().sum::<f64>() / nf;
    let (mut s1, mut s2, mut s3, mut s4) = (0.0, 0.0, 0.0, 0.0);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for &v in &vals {
        let d = v - mean;
        s1 += d.abs();
        let d2 = d * d;
        s2 += d2;
        s3 += d2 * d;
        s4 += d2 * d2;
        lo = lo.min(d);
        hi = hi.max(d);
    }
    let sq = (s2 / nf).sqrt();
    let (ssk, sku) = if sq > 0.0 { (s3 / nf / sq.powi(3), s4 / nf / sq.powi(4)) } else { (0.0, 0.0) };
    let (sdq, sdr) = gradient_params(g);
    Ok(HeightParams { n, mean, sa: s1 / nf, sq, sp: hi, sv: -lo, sz: hi - lo, ssk, sku, sdq, sdr })
}

/// `(Sdq, Sdr)` by the cell discretisation of the module docs.
fn gradient_params(g: &Grid) -> (Option<f64>, Option<f64>) {
    let (nr, nc) = g.dim();
    if nr < 2 || nc < 2 {
        return (None, None);
    }
    let [dx, dy] = g.pitch();
    let z = g.values();
    let (a, b, c, d) = (s![..-1, ..-1], s![..-1, 1..], s![1.., ..-1], s![1.., 1..]);
    // A cell counts when its four corners are valid.
    let cell_ok = match g.mask() {
        None => Array2::from_elem((nr - 1, nc - 1), true),
        Some(m) => {
            let mut ok = Array2::from_elem((nr - 1, nc - 1), false);
            Zip::from(&mut ok)
                .and(m.slice(a))
                .and(m.slice(b))
                .and(m.slice(c))
                .and(m.slice(d))
                .for_each(|o, &p, &q, &r, &s| *o = p && q && r && s);
            ok
        }
    };
    let (mut sg, mut sa, mut cells) = (0.0, 0.0, 0usize);
    Zip::from(&cell_ok).and(z.slice(a)).and(z.slice(b)).and(z.slice(c)).and(z.slice(d)).for_each(
        |&ok, &z00, &z01, &z10, &z11| {
            if ok {
                let gx = ((z01 - z00) + (z11 - z10)) / (2.0 * dx);
                let gy = ((z10 - z00) + (z11 - z01)) / (2.0 * dy);
                let g2 = gx * gx + gy * gy;
                sg += g2;
                // sqrt(1 + g2) - 1 without cancellation for small slopes.
                sa += g2 / ((1.0 + g2).sqrt() + 1.0);
                cells += 1;
            }
        },
    );
    if cells == 0 {
        return (None, None);
    }
    let c = cells as f64;
    (Some((sg / c).sqrt()), Some(sa / c))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_gradient_parameters_are_exact() {
        let (gx, gy) = (0.03, -0.04);
        let v = Array2::from_shape_fn((30, 40), |(i, j)| gx * j as f64 * 2e-6 + gy * i as f64 * 3e-6);
        let g = Grid::new(v, [2e-6, 3e-6], Unit::Metre).unwrap();
        let p = height_params(&g).unwrap();
        let slope = (gx * gx + gy * gy).sqrt();
        assert!((p.sdq.unwrap() - slope).abs() < 1e-12 * slope);
        let sdr = (1.0 + slope * slope).sqrt() - 1.0;
        assert!((p.sdr.unwrap() - sdr).abs() < 1e-9 * sdr);
    }

    #[test]
    fn two_level_surface_moments() {
        // Half the samples at 0, half at h: Sa = Sq = h/2, Ssk = 0, Sku = 1.
        let v = Array2::from_shape_fn((4, 6), |(_, j)| if j < 3 { 0.0 } else { 1e-6 });
        let p = height_params(&Grid::new(v, [1e-6; 2], Unit::Metre).unwrap()).unwrap();
        assert!((p.sa - 0.5e-6).abs() < 1e-18 && (p.sq - 0.5e-6).abs() < 1e-18);
        assert!(p.ssk.abs() < 1e-12 && (p.sku - 1.0).abs() < 1e-12);
        assert!((p.sz - 1e-6).abs() < 1e-18 && (p.sp - 0.5e-6).abs() < 1e-18);
        let flat = height_params(&Grid::new(Array2::zeros((2, 2)), [1e-6; 2], Unit::Metre).unwrap()).unwrap();
        assert_eq!((flat.sq, flat.ssk, flat.sku), (0.0, 0.0, 0.0));
    }
}
