//! Form removal: mean subtraction, least-squares plane and polynomial levelling, each fitted
//! on the valid samples (optionally restricted by a region mask) and subtracted everywhere;
//! facet levelling and substrate-only planes, which level a structured part (a quantized DOE)
//! by its flat terraces instead of by the average of its structure.
//!
//! Coordinates are pixel indices: the plane is `z = a + bx * j + by * i` (column j, row i), so
//! `bx`, `by` are heights per pixel and `a` is the plane's height at sample (0, 0) - the form
//! Gwyddion reports. The polynomial of order k is `sum c_pq u^p v^q` over `p + q <= k`, with
//! `u = (j - jc) / hj`, `v = (i - ic) / hi` the indices centred and scaled to [-1, 1] (for a
//! well-conditioned normal matrix). Fits solve the normal equations by LU with partial pivoting
//! ([`crate::linalg::solve`]); a singular system (too few or collinear points) is refused.
//!
//! **Facet levelling** (the scheme of Gwyddion's "Facet Level", `modules/process/facet-level.c`
//! with `libprocess/level.c`): on every 2 x 2 cell of valid samples the gradient `g = (gx, gy)`
//! is taken as in [`crate::metrology::stats`] (averaged forward differences over the pitch). With
//! `s2` a fraction (1/20 here) of the mean `|g|^2`, the cells are weighted by
//! `w = exp(-|g|^2 / s2)`, so that near-flat cells count and steps and spikes do not, and the
//! weighted mean of the unit normals `n = (-gx, -gy, 1) / sqrt(1 + |g|^2)` gives the dominant
//! facet's slope `(-Nx / Nz, -Ny / Nz)`. That slope is subtracted and the step repeated until it
//! is below 1e-9 of the weighting width `sqrt(s2)` plus the slope (at most 100 times; no
//! convergence is refused). Noise makes the steps shrink only geometrically (a mean shift with a
//! narrow kernel), so every other step jumps to the limit of the series (Aitken's
//! extrapolation). Only the tilt is fixed this way: the offset `a` is chosen so that the
//! levelled valid samples have zero mean.
//!
//! **Substrate plane**: the least-squares plane through the substrate only, either a region the
//! caller names (outside the aperture of the part) or the lowest level of a quantized surface.
//! The lowest level is found in the height histogram after facet levelling: the histogram of
//! the valid heights (256 bins over the 0.1 % to 99.9 % quantiles, smoothed over 3 bins) has a
//! peak per level; the lowest peak holding at least 1 % of the samples is the substrate, and
//! every sample between the histogram's valley above it and the same distance below it is fitted.
//! The fit and the selection are repeated until the selection no longer changes (at most 10
//! times). The levels must be resolved: a second peak must exist and the valley between the two
//! must fall below half the lower peak's height, else tilt or noise blur the levels into one
//! another and the fit is refused with the reason; and the substrate samples must lie within a
//! sixth of the step to the next level (rms about the plane), else the surface is not terraced
//! (a smooth relief's height histogram also has a lowest peak) and the fit is refused.

use ndarray::Array2;

use crate::error::{Allowed, DataCause, Error, Result};
use crate::grid::Grid;

/// A least-squares plane `z = a + bx * j + by * i` (heights per pixel).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Plane {
    /// Height at sample (0, 0), in the grid's unit (metres for a scan).
    pub a: f64,
    /// Slope along the columns, grid unit per pixel.
    pub bx: f64,
    /// Slope along the rows, grid unit per pixel.
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
    /// The highest total degree `p + q`.
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
        return Err(Error::data(
            DataCause::NotFinite,
            format!("{count} valid heights are NaN or infinite (first at row {i}, column {j})"),
        ));
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
        return Err(Error::data(
            DataCause::TooFew,
            format!("{} points cannot fix {m} fit coefficients", points.len()),
        ));
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
    crate::linalg::solve(a, b, m)
}

/// Fits the least-squares plane to the valid samples (within `region` when given).
pub fn fit_plane(g: &Grid, region: Option<&Array2<bool>>) -> Result<Plane> {
    fit_plane_rows(g, region, 1)
}

/// [`fit_plane`] over every `row_step`-th row only (a cheaper estimate from a subset of rows;
/// the plane is still expressed in the grid's own indices).
pub fn fit_plane_rows(g: &Grid, region: Option<&Array2<bool>>, row_step: usize) -> Result<Plane> {
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
    for (i, row) in g.values().outer_iter().enumerate().step_by(row_step.max(1)) {
        let y = i as f64 - ic;
        for (j, &z) in row.iter().enumerate() {
            if !(mask.is_none_or(|m| m[[i, j]]) && region.is_none_or(|r| r[[i, j]])) {
                continue;
            }
            if !z.is_finite() {
                return Err(Error::data(
                    DataCause::NotFinite,
                    format!("a valid height is NaN or infinite (row {i}, column {j})"),
                ));
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
        return Err(Error::data(DataCause::TooFew, format!("{n} points cannot fix 3 fit coefficients")));
    }
    let c = crate::linalg::solve(vec![n, sx, sy, sx, sxx, sxy, sy, sxy, syy], vec![sz, sxz, syz], 3)?;
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

/// Fits a plane (see `fit_plane`) and subtracts it from the whole surface.
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
        return Err(Error::data(DataCause::Empty, "no valid sample: the mean is undefined"));
    }
    let m = pts.iter().map(|p| p.2).sum::<f64>() / pts.len() as f64;
    Ok((subtract(g, |_, _| m)?, m))
}

/// A levelling method for a whole scan (`doefab scan-info --level`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LevelMethod {
    /// Least-squares plane through every valid sample.
    Plane,
    /// Facet levelling: the dominant local facet made horizontal (module docs).
    Facet,
    /// Least-squares plane through the substrate: the samples outside a centred circular
    /// aperture of this diameter (metres) when given, else the lowest level (module docs).
    Substrate {
        /// Diameter of the centred circular aperture, metres; `None`: the lowest level is the
        /// substrate.
        aperture: Option<f64>,
    },
}

/// What a levelling did: the plane removed and, for a substrate fit, what the substrate was.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Levelling {
    /// The method applied.
    pub method: LevelMethod,
    /// The plane subtracted (heights per pixel, as [`Plane`]).
    pub plane: Plane,
    /// Samples the plane was fitted on.
    pub fitted_points: usize,
    /// Facet levelling: iterations to convergence.
    pub iterations: Option<usize>,
    /// Lowest-level substrate: the level found in the histogram.
    pub lowest_level: Option<LowestLevel>,
}

/// The substrate level found in the height histogram.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct LowestLevel {
    /// Height of the next level above the substrate, after levelling (the substrate is at 0).
    pub next_level: f64,
    /// Standard deviation of the substrate samples about the plane (noise and roughness).
    pub spread: f64,
}

/// Levels `g` by `method`; returns the levelled surface and what was removed.
pub fn level(g: &Grid, method: LevelMethod) -> Result<(Grid, Levelling)> {
    let (plane, fitted_points, iterations, lowest_level) = match method {
        LevelMethod::Plane => (fit_plane(g, None)?, g.valid_count(), None, None),
        LevelMethod::Facet => {
            let (p, it) = fit_facet(g)?;
            (p, g.valid_count(), Some(it), None)
        }
        LevelMethod::Substrate { aperture: Some(d) } => {
            let region = outside_aperture(g, d)?;
            let n = (0..g.dim().0)
                .flat_map(|i| (0..g.dim().1).map(move |j| (i, j)))
                .filter(|&(i, j)| region[[i, j]] && g.is_valid(i, j))
                .count();
            (fit_plane(g, Some(&region))?, n, None, None)
        }
        LevelMethod::Substrate { aperture: None } => {
            let (p, n, low) = fit_lowest_level(g)?;
            (p, n, None, Some(low))
        }
    };
    let levelled = subtract(g, |i, j| plane.at(i, j))?;
    Ok((levelled, Levelling { method, plane, fitted_points, iterations, lowest_level }))
}

/// The samples outside a circle of diameter `d` (metres) centred on the field.
fn outside_aperture(g: &Grid, d: f64) -> Result<Array2<bool>> {
    if !(d.is_finite() && d > 0.0) {
        return Err(Error::param_in(
            "aperture",
            Allowed::positive(),
            format!("{d} m is not a positive diameter"),
        ));
    }
    let (nr, nc) = g.dim();
    let [px, py] = g.pitch();
    let (ic, jc) = ((nr as f64 - 1.0) * 0.5, (nc as f64 - 1.0) * 0.5);
    let r2 = 0.25 * d * d;
    let region = Array2::from_shape_fn((nr, nc), |(i, j)| {
        let (x, y) = ((j as f64 - jc) * px, (i as f64 - ic) * py);
        x * x + y * y > r2
    });
    let [ex, ey] = g.extent();
    if !region.iter().any(|&r| r) {
        return Err(Error::param(
            "aperture",
            format!(
                "a {:.4} mm aperture covers the whole {:.4} x {:.4} mm scan: no substrate is left to fit",
                d * 1e3,
                ex * 1e3,
                ey * 1e3
            ),
        ));
    }
    Ok(region)
}

/// The facet-levelling plane (module docs) and the number of iterations it took.
pub fn fit_facet(g: &Grid) -> Result<(Plane, usize)> {
    if let Some((count, (i, j))) = g.non_finite() {
        return Err(Error::data(
            DataCause::NotFinite,
            format!("{count} valid heights are NaN or infinite (first at row {i}, column {j})"),
        ));
    }
    let (nr, nc) = g.dim();
    let [px, py] = g.pitch();
    let v = g.values();
    // Cell gradients of the surface as given; levelling by a plane shifts each by the same.
    let mut cells = Vec::new();
    for i in 0..nr.saturating_sub(1) {
        for j in 0..nc.saturating_sub(1) {
            if g.is_valid(i, j) && g.is_valid(i, j + 1) && g.is_valid(i + 1, j) && g.is_valid(i + 1, j + 1) {
                let gx = (v[[i, j + 1]] - v[[i, j]] + v[[i + 1, j + 1]] - v[[i + 1, j]]) / (2.0 * px);
                let gy = (v[[i + 1, j]] - v[[i, j]] + v[[i + 1, j + 1]] - v[[i, j + 1]]) / (2.0 * py);
                cells.push((gx, gy));
            }
        }
    }
    if cells.len() < 3 {
        return Err(Error::data(
            DataCause::TooFew,
            format!("{} cells of 2 x 2 valid samples: facet levelling needs at least 3", cells.len()),
        ));
    }
    let (mut sx, mut sy) = (0.0, 0.0);
    let mut prev: Option<(f64, f64)> = None;
    for it in 1..=100 {
        let s2 = cells.iter().map(|&(gx, gy)| (gx - sx).powi(2) + (gy - sy).powi(2)).sum::<f64>()
            / cells.len() as f64
            / 20.0;
        if s2 == 0.0 {
            return Ok((facet_plane(g, sx * px, sy * py), it));
        }
        let (mut nx, mut ny, mut nz) = (0.0, 0.0, 0.0);
        for &(gx, gy) in &cells {
            let (ux, uy) = (gx - sx, gy - sy);
            let q2 = ux * ux + uy * uy;
            let w = (-q2 / s2).exp() / (1.0 + q2).sqrt();
            nx -= w * ux;
            ny -= w * uy;
            nz += w;
        }
        let (dx, dy) = (-nx / nz, -ny / nz);
        if !(dx.is_finite() && dy.is_finite()) {
            break;
        }
        if dx.hypot(dy) <= 1e-9 * (s2.sqrt() + sx.hypot(sy)) {
            return Ok((facet_plane(g, (sx + dx) * px, (sy + dy) * py), it));
        }
        // Aitken's extrapolation on every other step (module docs).
        let mut k = 1.0;
        if let Some((ox, oy)) = prev.take() {
            let rho = (dx * ox + dy * oy) / (ox * ox + oy * oy);
            if rho > 0.0 && rho < 0.95 {
                k = 1.0 / (1.0 - rho);
            }
        } else {
            prev = Some((dx, dy));
        }
        sx += k * dx;
        sy += k * dy;
    }
    Err(Error::data(
        DataCause::Diverged,
        "facet levelling did not converge in 100 iterations: the surface has no dominant facet",
    ))
}

/// The plane of slopes `bx`, `by` (per pixel) whose subtraction leaves zero mean.
fn facet_plane(g: &Grid, bx: f64, by: f64) -> Plane {
    let (mut n, mut sum) = (0.0, 0.0);
    for ((i, j), &z) in g.values().indexed_iter() {
        if g.is_valid(i, j) {
            n += 1.0;
            sum += z - bx * j as f64 - by * i as f64;
        }
    }
    Plane { a: sum / n, bx, by }
}

/// The least-squares plane through the lowest level (module docs): the plane, the samples it
/// was fitted on and the level found.
pub fn fit_lowest_level(g: &Grid) -> Result<(Plane, usize, LowestLevel)> {
    let (mut plane, _) = fit_facet(g)?;
    let mut sel = lowest_band(g, &plane)?.0;
    for _ in 0..10 {
        plane = fit_plane(g, Some(&sel))?;
        let next = lowest_band(g, &plane)?.0;
        if next == sel {
            break;
        }
        sel = next;
    }
    plane = fit_plane(g, Some(&sel))?;
    let (sel, [_, _, next]) = lowest_band(g, &plane)?;
    let (mut n, mut ss) = (0usize, 0.0);
    for ((i, j), &z) in g.values().indexed_iter() {
        if sel[[i, j]] {
            n += 1;
            ss += (z - plane.at(i as f64, j as f64)).powi(2);
        }
    }
    let spread = (ss / n as f64).sqrt();
    if next < 6.0 * spread {
        return Err(Error::data(
            DataCause::Featureless,
            format!(
                "the lowest level spreads {spread:.4e} m (rms) about its plane, more than a sixth of the \
             {next:.4e} m step to the next level: the surface is not terraced (or too rough) for a \
             lowest-level substrate; name the substrate region (an aperture) or use facet levelling"
            ),
        ));
    }
    Ok((plane, n, LowestLevel { next_level: next, spread }))
}

/// The valid samples in the lowest level's band about `plane` (module docs), and the histogram
/// levels `[peak, valley, next peak]` of the heights above the plane.
fn lowest_band(g: &Grid, plane: &Plane) -> Result<(Array2<bool>, [f64; 3])> {
    let resid = |i: usize, j: usize| g.values()[[i, j]] - plane.at(i as f64, j as f64);
    let mut r: Vec<f64> = Vec::with_capacity(g.valid_count());
    for (i, j) in (0..g.dim().0).flat_map(|i| (0..g.dim().1).map(move |j| (i, j))) {
        if g.is_valid(i, j) {
            r.push(resid(i, j));
        }
    }
    let range = g.min_max().map_or(0.0, |(lo, hi)| hi - lo);
    let levels = histogram_levels(&mut r, range)?;
    let [peak, valley, _] = levels;
    let sel = Array2::from_shape_fn(g.dim(), |(i, j)| {
        g.is_valid(i, j) && (2.0 * peak - valley..=valley).contains(&resid(i, j))
    });
    Ok((sel, levels))
}

/// The smoothed 256-bin histogram of `r` over its 0.1 %..99.9 % quantiles: `(lo, bin width,
/// counts)`. Sorts `r`.
fn histogram(r: &mut [f64]) -> (f64, f64, Vec<f64>) {
    r.sort_unstable_by(f64::total_cmp);
    let q = |p: f64| r[((r.len() - 1) as f64 * p).round() as usize];
    let (lo, hi) = (q(0.001), q(0.999));
    const NB: usize = 256;
    let w = (hi - lo) / NB as f64;
    let mut c = vec![0.0; NB];
    if w > 0.0 {
        for &x in r.iter() {
            if (lo..=hi).contains(&x) {
                c[(((x - lo) / w) as usize).min(NB - 1)] += 1.0;
            }
        }
    }
    let s = (0..NB).map(|k| c[k.saturating_sub(1)..(k + 2).min(NB)].iter().sum::<f64>() / 3.0).collect();
    (lo, w, s)
}

/// The heights of the lowest level's histogram peak, of the valley above it and of the next
/// level's peak (module docs); refuses a histogram whose lowest two levels are not resolved, and
/// heights `r` that vary by less than 1e-9 of `range` (the surface's range before levelling:
/// a plane, levelled down to rounding errors).
fn histogram_levels(r: &mut [f64], range: f64) -> Result<[f64; 3]> {
    if r.len() < 3 {
        return Err(Error::data(
            DataCause::TooFew,
            format!("{} valid samples: no height histogram", r.len()),
        ));
    }
    let n = r.len() as f64;
    let (lo, w, c) = histogram(r);
    if w * c.len() as f64 <= 1e-9 * range {
        return Err(Error::data(
            DataCause::Featureless,
            "the surface is flat: a single level, no substrate to tell apart",
        ));
    }
    let nb = c.len();
    // Local maxima (the first bin of a plateau) holding about 1 % of the samples.
    let peaks: Vec<usize> = (0..nb)
        .filter(|&k| {
            c[k.saturating_sub(3)..(k + 4).min(nb)].iter().all(|&x| x <= c[k])
                && (k == 0 || c[k - 1] < c[k])
                && 3.0 * c[k] >= 0.01 * n
        })
        .collect();
    let at = |k: usize| lo + (k as f64 + 0.5) * w;
    let [p0, p1, ..] = peaks[..] else {
        return Err(Error::data(
            DataCause::Featureless,
            "the height histogram shows a single level: no substrate to tell apart from the structure",
        ));
    };
    let v = (p0..=p1).min_by(|&a, &b| c[a].total_cmp(&c[b])).unwrap_or(p0);
    if c[v] > 0.5 * c[p0] {
        return Err(Error::data(
            DataCause::Featureless,
            format!(
                "the lowest levels at {:.4e} m and {:.4e} m are not resolved in the height histogram (the \
             valley between them holds {:.0} % of the lower peak): tilt or noise blur the levels, so \
             the substrate cannot be told apart",
                at(p0),
                at(p1),
                100.0 * c[v] / c[p0]
            ),
        ));
    }
    Ok([at(p0), at(v), at(p1)])
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
        let e = fit_plane(&g, Some(&region)).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::TooFew, .. }), "{e:?}");
        region[[0, 2]] = true;
        let e = fit_plane(&g, Some(&region)).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::Singular, .. }), "{e:?}");
        let (m, mean) = subtract_mean(&g).unwrap();
        assert!(m.values().sum().abs() < 1e-9 && mean > 0.0);
    }

    /// A 4-level quantized DOE-like surface (levels 0, 100, 200, 300 nm in random 12 x 12 pixel
    /// blocks, 240 x 240 samples at 1 um), plus a tilt of `bx`, `by` per pixel, an offset and
    /// Gaussian noise of `noise` metres.
    fn quantized(bx: f64, by: f64, noise: f64, seed: u64) -> Grid {
        let mut rng = crate::rng::Lcg(seed);
        let blocks = Array2::from_shape_fn((20, 20), |_| (rng.uniform() * 4.0).floor() * 100e-9);
        let v = Array2::from_shape_fn((240, 240), |(i, j)| {
            blocks[[i / 12, j / 12]] + 40e-9 + bx * j as f64 + by * i as f64 + noise * rng.normal()
        });
        Grid::new(v, [1e-6; 2], Unit::Metre).unwrap()
    }

    /// Slope error (per pixel) of `p` against the truth, as height across the 240-pixel field.
    fn tilt_error(p: &Plane, bx: f64, by: f64) -> f64 {
        240.0 * ((p.bx - bx).abs() + (p.by - by).abs())
    }

    #[test]
    fn facet_and_substrate_remove_a_tilt_to_the_noise_level() {
        // 2 nm/px is 480 nm across the field: more than the 100 nm step, so the raw histogram
        // has no levels and the least-squares plane is pulled by the random level pattern.
        let (bx, by, noise) = (2e-9, -1.2e-9, 2e-9);
        let g = quantized(bx, by, noise, 7);
        let ls = fit_plane(&g, None).unwrap();
        let (_, facet) = level(&g, LevelMethod::Facet).unwrap();
        let (flat, sub) = level(&g, LevelMethod::Substrate { aperture: None }).unwrap();
        // Tilt left across the field: below the noise for both; the plain fit is far off.
        assert!(tilt_error(&facet.plane, bx, by) < 0.5 * noise, "facet {:?}", facet.plane);
        assert!(tilt_error(&sub.plane, bx, by) < 0.2 * noise, "substrate {:?}", sub.plane);
        assert!(tilt_error(&ls, bx, by) > 5.0 * noise, "least squares {ls:?}");
        // The substrate is the 0 nm level (40 nm up): found at 0 after levelling, to noise / sqrt(N).
        let low = sub.lowest_level.unwrap();
        assert!((sub.plane.a - 40e-9).abs() < 0.1 * noise, "a = {}", sub.plane.a);
        assert!((low.spread - noise).abs() < 0.1 * noise, "spread {}", low.spread);
        assert!((low.next_level - 100e-9).abs() < 2e-9, "next level {}", low.next_level);
        assert!(sub.fitted_points > 240 * 240 / 8 && sub.fitted_points < 240 * 240 / 2);
        let lowest = flat.values().iter().filter(|z| z.abs() < 20e-9).count();
        assert_eq!(lowest, sub.fitted_points, "every substrate sample is at 0 +- 10 sigma");
    }

    #[test]
    fn substrate_refuses_levels_blurred_by_noise() {
        // Step 100 nm: noise 8 nm leaves the levels resolved, 40 nm merges them.
        assert!(level(&quantized(1e-9, 0.5e-9, 8e-9, 3), LevelMethod::Substrate { aperture: None }).is_ok());
        let e =
            level(&quantized(1e-9, 0.5e-9, 40e-9, 3), LevelMethod::Substrate { aperture: None }).unwrap_err();
        assert!(
            matches!(e, Error::Data { cause: DataCause::Featureless, .. })
                && e.to_string().contains("not resolved"),
            "{e:?}"
        );
        let flat =
            Grid::new(Array2::from_shape_fn((30, 30), |(i, _)| i as f64 * 1e-9), [1e-6; 2], Unit::Metre)
                .unwrap();
        let e = level(&flat, LevelMethod::Substrate { aperture: None }).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::Featureless, .. }), "{e:?}");
        // A smooth relief of concentric sinusoidal rings: its height histogram peaks at both
        // extremes, but the lower "level" is half the surface, not a terrace.
        let rings = Array2::from_shape_fn((200, 200), |(i, j)| {
            let (x, y) = (j as f64 - 100.0, i as f64 - 100.0);
            300e-9 * ((x * x + y * y).sqrt() * 0.2).sin() + 1e-9 * x
        });
        let e = level(
            &Grid::new(rings, [1e-6; 2], Unit::Metre).unwrap(),
            LevelMethod::Substrate { aperture: None },
        )
        .unwrap_err();
        assert!(
            matches!(e, Error::Data { cause: DataCause::Featureless, .. })
                && e.to_string().contains("not terraced"),
            "{e:?}"
        );
    }

    #[test]
    fn substrate_outside_an_aperture() {
        // A plane outside a 100 um disc, a raised disc inside it: the fit sees the plane only.
        let v = Array2::from_shape_fn((151, 151), |(i, j)| {
            let (x, y) = (j as f64 - 75.0, i as f64 - 75.0);
            3e-9 * j as f64 - 2e-9 * i as f64 + 7e-9 + if x * x + y * y <= 52.0 * 52.0 { 1e-6 } else { 0.0 }
        });
        let g = Grid::new(v, [1e-6; 2], Unit::Metre).unwrap();
        let (_, l) = level(&g, LevelMethod::Substrate { aperture: Some(110e-6) }).unwrap();
        assert!((l.plane.bx - 3e-9).abs() < 1e-18 && (l.plane.by + 2e-9).abs() < 1e-18, "{:?}", l.plane);
        assert!((l.plane.a - 7e-9).abs() < 1e-15);
        // Inside the raised disc the fit would see the step.
        let (_, l) = level(&g, LevelMethod::Substrate { aperture: Some(90e-6) }).unwrap();
        assert!((l.plane.a - 7e-9).abs() > 1e-9);
        let e = level(&g, LevelMethod::Substrate { aperture: Some(0.3e-3) }).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name == "aperture"), "{e:?}");
        assert!(level(&g, LevelMethod::Substrate { aperture: Some(-1.0) }).is_err());
    }

    #[test]
    fn facet_refuses_too_few_cells() {
        let g = Grid::new(Array2::from_shape_fn((2, 2), |(i, j)| (i + j) as f64), [1e-6; 2], Unit::Metre)
            .unwrap();
        let e = fit_facet(&g).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::TooFew, .. }), "{e:?}");
        let g = Grid::new(Array2::from_shape_fn((2, 4), |(i, j)| (i + j) as f64), [1e-6; 2], Unit::Metre)
            .unwrap();
        let (p, _) = fit_facet(&g).unwrap();
        assert!((p.bx - 1.0).abs() < 1e-9 && (p.by - 1.0).abs() < 1e-9, "{p:?}");
    }
}
