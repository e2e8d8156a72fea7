//! Form removal: mean subtraction, least-squares plane and polynomial levelling, each fitted
//! on the valid samples (optionally restricted by a region mask) and subtracted everywhere.
//!
//! Coordinates are pixel indices: the plane is `z = a + bx * j + by * i` (column j, row i), so
//! `bx`, `by` are heights per pixel and `a` is the plane's height at sample (0, 0) - the form
//! Gwyddion reports. The polynomial of order k is `sum c_pq u^p v^q` over `p + q <= k`, with
//! `u = (j - jc) / hj`, `v = (i - ic) / hi` the indices centred and scaled to [-1, 1] (for a
//! well-conditioned normal matrix). Fits solve the normal equations by Gaussian elimination with
//! partial pivoting; a singular system (too few or collinear points) is refused.

use ndarray::Array2;

use crate::error::{Error, Result};
use crate::grid::Grid;

/// A least-squares plane `z = a + bx * j + by * i` (heights per pixel).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Plane {
    pub a: f64,
    pub bx: f64,
    pub by: f64,
}

impl Plane {
    /// The plane's height at row `i`, column `j`.
    pub fn at(&self, i: f64, j: f64) -> f64 {
        self.a + self.bx * j + self.by * i
    }
}

/// A fitted polynomial surface of order `order` in centred, scaled coordinates (module docs).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Polynomial {
    pub order: usize,
    /// `((p, q), c_pq)`: the coefficient of `u^p v^q`.
    pub coefficients: Vec<((usize, usize), f64)>,
    /// `[jc, hj, ic, hi]`: `u = (j - jc) / hj`, `v = (i - ic) / hi`.
    pub frame: [f64; 4],
}

impl Polynomial {
    /// The polynomial's height at row `i`, column `j`.
    pub fn at(&self, i: f64, j: f64) -> f64 {
        let [jc, hj, ic, hi] = self.frame;
        let (u, v) = ((j - jc) / hj, (i - ic) / hi);
        self.coefficients.iter().map(|((p, q), c)| c * u.powi(*p as i32) * v.powi(*q as i32)).sum()
    }
}

/// The samples a fit uses: valid in the grid and (when given) true in `region`.
fn fit_points(g: &Grid, region: Option<&Array2<bool>>) -> Result<Vec<(usize, usize, f64)>> {
    if let Some(r) = region {
        if r.dim() != g.dim() {
            return Err(Error::param("region", format!("mask is {:?}, surface is {:?}", r.dim(), g.dim())));
        }
    }
    if let Some((count, (i, j))) = g.non_finite() {
        return Err(Error::Data(format!(
            "{count} valid heights are NaN or infinite (first at row {i}, column {j})"
        )));
    }
    Ok(g.values()
        .indexed_iter()
        .filter(|((i, j), _)| g.is_valid(*i, *j) && region.is_none_or(|r| r[[*i, *j]]))
        .map(|((i, j), &z)| (i, j, z))
        .collect())
}

/// Least squares for `z ~ sum_k c_k f_k(i, j)`: returns `c`.
fn lstsq(points: &[(usize, usize, f64)], m: usize, basis: impl Fn(f64, f64, &mut [f64])) -> Result<Vec<f64>> {
    if points.len() < m {
        return Err(Error::Data(format!("{} points cannot fix {m} fit coefficients", points.len())));
    }
    let mut a = vec![0.0; m * m];
    let mut b = vec![0.0; m];
    let mut f = vec![0.0; m];
    for &(i, j, z) in points {
        basis(i as f64, j as f64, &mut f);
        for r in 0..m {
            b[r] += f[r] * z;
            for c in r..m {
                a[r * m + c] += f[r] * f[c];
            }
        }
    }
    for r in 0..m {
        for c in 0..r {
            a[r * m + c] = a[c * m + r];
        }
    }
    solve(a, b, m)
}

/// Solves the `m x m` system `a x = b` (row-major `a`) by Gaussian elimination with partial
/// pivoting; refuses pivots below 1e-12 of the largest diagonal entry.
pub(crate) fn solve(mut a: Vec<f64>, mut b: Vec<f64>, m: usize) -> Result<Vec<f64>> {
    let scale = (0..m).map(|k| a[k * m + k]).fold(0.0f64, f64::max);
    // Gaussian elimination with partial pivoting.
    for col in 0..m {
        let piv =
            (col..m).max_by(|&x, &y| a[x * m + col].abs().total_cmp(&a[y * m + col].abs())).unwrap_or(col);
        if a[piv * m + col].abs() <= 1e-12 * scale {
            return Err(Error::Data(
                "the fit is singular: the points do not determine the surface (too few or collinear)".into(),
            ));
        }
        if piv != col {
            for k in 0..m {
                a.swap(piv * m + k, col * m + k);
            }
            b.swap(piv, col);
        }
        for r in col + 1..m {
            let fct = a[r * m + col] / a[col * m + col];
            for k in col..m {
                a[r * m + k] -= fct * a[col * m + k];
            }
            b[r] -= fct * b[col];
        }
    }
    let mut x = vec![0.0; m];
    for r in (0..m).rev() {
        let s: f64 = (r + 1..m).map(|k| a[r * m + k] * x[k]).sum();
        x[r] = (b[r] - s) / a[r * m + r];
    }
    Ok(x)
}

/// Fits the least-squares plane to the valid samples (within `region` when given).
pub fn fit_plane(g: &Grid, region: Option<&Array2<bool>>) -> Result<Plane> {
    if let Some(r) = region {
        if r.dim() != g.dim() {
            return Err(Error::param("region", format!("mask is {:?}, surface is {:?}", r.dim(), g.dim())));
        }
    }
    let (nr, nc) = g.dim();
    let (ic, jc) = ((nr as f64 - 1.0) * 0.5, (nc as f64 - 1.0) * 0.5);
    // Moments of the centred coordinates x = j - jc, y = i - ic, accumulated row by row.
    let (mut n, mut sx, mut sy, mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    let (mut sz, mut sxz, mut syz) = (0.0, 0.0, 0.0);
    let mask = g.mask();
    for (i, row) in g.values().outer_iter().enumerate() {
        let y = i as f64 - ic;
        for (j, &z) in row.iter().enumerate() {
            if !(mask.is_none_or(|m| m[[i, j]]) && region.is_none_or(|r| r[[i, j]])) {
                continue;
            }
            if !z.is_finite() {
                return Err(Error::Data(format!("a valid height is NaN or infinite (row {i}, column {j})")));
            }
            let x = j as f64 - jc;
            n += 1.0;
            sx += x;
            sy += y;
            sxx += x * x;
            sxy += x * y;
            syy += y * y;
            sz += z;
            sxz += x * z;
            syz += y * z;
        }
    }
    if n < 3.0 {
        return Err(Error::Data(format!("{n} points cannot fix 3 fit coefficients")));
    }
    let c = solve(vec![n, sx, sy, sx, sxx, sxy, sy, sxy, syy], vec![sz, sxz, syz], 3)?;
    Ok(Plane { a: c[0] - c[1] * jc - c[2] * ic, bx: c[1], by: c[2] })
}

/// Subtracts `f(i, j)` from every valid sample.
fn subtract(g: &Grid, f: impl Fn(f64, f64) -> f64) -> Result<Grid> {
    let mut v = g.values().clone();
    for ((i, j), z) in v.indexed_iter_mut() {
        if g.is_valid(i, j) {
            *z -= f(i as f64, j as f64);
        }
    }
    g.map_values(v, g.unit())
}

/// Fits a plane (see [`fit_plane`]) and subtracts it from the whole surface.
pub fn level_plane(g: &Grid, region: Option<&Array2<bool>>) -> Result<(Grid, Plane)> {
    let p = fit_plane(g, region)?;
    Ok((subtract(g, |i, j| p.at(i, j))?, p))
}

/// Fits a polynomial of order `order` (0..=10) to the valid samples (within `region`).
pub fn fit_polynomial(g: &Grid, order: usize, region: Option<&Array2<bool>>) -> Result<Polynomial> {
    if order > 10 {
        return Err(Error::param(
            "order",
            format!("{order} is above 10 (the normal equations lose all precision)"),
        ));
    }
    let pts = fit_points(g, region)?;
    let (nr, nc) = g.dim();
    let frame = [
        (nc as f64 - 1.0) * 0.5,
        ((nc as f64 - 1.0) * 0.5).max(0.5),
        (nr as f64 - 1.0) * 0.5,
        ((nr as f64 - 1.0) * 0.5).max(0.5),
    ];
    let terms: Vec<(usize, usize)> = (0..=order).flat_map(|t| (0..=t).map(move |q| (t - q, q))).collect();
    let [jc, hj, ic, hi] = frame;
    let c = lstsq(&pts, terms.len(), |i, j, f| {
        let (u, v) = ((j - jc) / hj, (i - ic) / hi);
        for (k, (p, q)) in terms.iter().enumerate() {
            f[k] = u.powi(*p as i32) * v.powi(*q as i32);
        }
    })?;
    Ok(Polynomial { order, coefficients: terms.into_iter().zip(c).collect(), frame })
}

/// Fits a polynomial (see [`fit_polynomial`]) and subtracts it from the whole surface.
pub fn level_polynomial(g: &Grid, order: usize, region: Option<&Array2<bool>>) -> Result<(Grid, Polynomial)> {
    let p = fit_polynomial(g, order, region)?;
    Ok((subtract(g, |i, j| p.at(i, j))?, p))
}

/// Subtracts the mean of the valid samples; returns the surface and the mean.
pub fn subtract_mean(g: &Grid) -> Result<(Grid, f64)> {
    let pts = fit_points(g, None)?;
    if pts.is_empty() {
        return Err(Error::Data("no valid sample: the mean is undefined".into()));
    }
    let m = pts.iter().map(|p| p.2).sum::<f64>() / pts.len() as f64;
    Ok((subtract(g, |_, _| m)?, m))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Unit;

    #[test]
    fn plane_and_polynomial_recover_their_coefficients() {
        let v = Array2::from_shape_fn((20, 30), |(i, j)| 5.0 + 0.3 * j as f64 - 0.7 * i as f64);
        let g = Grid::new(v, [1e-6; 2], Unit::Metre).unwrap();
        let p = fit_plane(&g, None).unwrap();
        assert!((p.a - 5.0).abs() < 1e-12 && (p.bx - 0.3).abs() < 1e-13 && (p.by + 0.7).abs() < 1e-13);
        let q = Array2::from_shape_fn((20, 30), |(i, j)| {
            let (x, y) = (j as f64, i as f64);
            1.0 + 0.1 * x - 0.2 * y + 0.01 * x * x + 0.02 * x * y - 0.003 * y * y * y
        });
        let g = Grid::new(q, [1e-6; 2], Unit::Metre).unwrap();
        let (flat, _) = level_polynomial(&g, 3, None).unwrap();
        assert!(flat.values().iter().all(|r| r.abs() < 1e-9), "cubic not removed");
        let (rest, _) = level_polynomial(&g, 2, None).unwrap();
        assert!(rest.values().iter().any(|r| r.abs() > 1e-3), "a quadratic cannot remove y^3");
        let mut region = Array2::from_elem((20, 30), false);
        region[[0, 0]] = true;
        region[[0, 1]] = true;
        assert!(fit_plane(&g, Some(&region)).unwrap_err().to_string().contains("cannot fix"));
        region[[0, 2]] = true;
        assert!(fit_plane(&g, Some(&region)).unwrap_err().to_string().contains("singular"));
        let (m, mean) = subtract_mean(&g).unwrap();
        assert!(m.values().sum().abs() < 1e-9 && mean > 0.0);
    }
}
