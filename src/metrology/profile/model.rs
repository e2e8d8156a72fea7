//! The model a profile is fitted with: the design blurred on a crop around the line
//! ([`Blurred`]), the fit context ([`Ctx`]), the normal equations of `(s, v, a, b, c)`, the
//! damped Gauss-Newton refinement at a fixed blur, and the covariance of the fitted parameters
//! (step 2 and 3 of the [module docs](super)).

use crate::error::{DataCause, Error, Result};
use crate::grid::blur::gaussian_blur;
use crate::grid::Grid;
use crate::metrology::scan_registration::Sampler;

/// The design blurred on a crop around the line, and where the crop's centre lies.
pub(super) struct Blurred {
    sampler: Sampler<'static>,
    centre: [f64; 2],
    pitch: [f64; 2],
}

impl Blurred {
    /// `(H, dH/dx, dH/dy)` at design position `p` (metres from the design's centre).
    pub(super) fn at(&self, p: [f64; 2]) -> Option<(f64, f64, f64)> {
        let (fi, fj) = self.sampler.index_of([p[0] - self.centre[0], p[1] - self.centre[1]]);
        self.sampler.eval(fi, fj).map(|(h, di, dj)| (h, dj / self.pitch[0], di / self.pitch[1]))
    }
}

/// Fit context: the crop of the design, the points and the line frame.
pub(super) struct Ctx<'a> {
    pub(super) crop: &'a Grid,
    pub(super) crop_centre: [f64; 2],
    pub(super) pts: &'a [(f64, f64)],
    pub(super) u_mean: f64,
    pub(super) start: [f64; 2],
    pub(super) dir: [f64; 2],
    pub(super) nrm: [f64; 2],
}

impl Ctx<'_> {
    pub(super) fn pos(&self, u: f64, s: f64, v: f64) -> [f64; 2] {
        [
            self.start[0] + (u + s) * self.dir[0] + v * self.nrm[0],
            self.start[1] + (u + s) * self.dir[1] + v * self.nrm[1],
        ]
    }
    pub(super) fn blurred(&self, sigma: f64) -> Result<Blurred> {
        let g = gaussian_blur(self.crop, sigma)?;
        Ok(Blurred { sampler: Sampler::new_owned(&g), centre: self.crop_centre, pitch: self.crop.pitch() })
    }
}

/// Normal equations of the 5 parameters `(s, v, a, b, c)` at `p`.
pub(super) struct Normal {
    jtj: [[f64; 5]; 5],
    jtr: [f64; 5],
    sse: f64,
    n: usize,
    /// Squared norms of the `s` and `v` columns.
    pub(super) col2: [f64; 2],
}

pub(super) fn normal(ctx: &Ctx, b: &Blurred, p: &[f64; 5]) -> Normal {
    let mut nm = Normal { jtj: [[0.0; 5]; 5], jtr: [0.0; 5], sse: 0.0, n: 0, col2: [0.0; 2] };
    for &(u, z) in ctx.pts {
        let Some((h, hx, hy)) = b.at(ctx.pos(u, p[0], p[1])) else { continue };
        let du = u - ctx.u_mean;
        let r = z - (p[2] * h + p[3] + p[4] * du);
        let j = [
            p[2] * (hx * ctx.dir[0] + hy * ctx.dir[1]),
            p[2] * (hx * ctx.nrm[0] + hy * ctx.nrm[1]),
            h,
            1.0,
            du,
        ];
        for a in 0..5 {
            nm.jtr[a] += j[a] * r;
            for c in 0..5 {
                nm.jtj[a][c] += j[a] * j[c];
            }
        }
        nm.col2[0] += j[0] * j[0];
        nm.col2[1] += j[1] * j[1];
        nm.sse += r * r;
        nm.n += 1;
    }
    nm
}

/// Solves `(A + lambda diag A) x = r` over the `free` indices (scaled to unit diagonal).
fn damped_solve(a: &[[f64; 5]; 5], r: &[f64; 5], lambda: f64, free: &[usize]) -> Option<[f64; 5]> {
    let m = free.len();
    let d: Vec<f64> = free.iter().map(|&i| a[i][i].sqrt()).collect();
    if d.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return None;
    }
    let mut mat = vec![0.0; m * m];
    let mut rhs = vec![0.0; m];
    for (p, &i) in free.iter().enumerate() {
        rhs[p] = r[i] / d[p];
        for (q, &j) in free.iter().enumerate() {
            mat[p * m + q] = a[i][j] / (d[p] * d[q]) + if p == q { lambda } else { 0.0 };
        }
    }
    let x = crate::linalg::solve(mat, rhs, m).ok()?;
    let mut out = [0.0; 5];
    for (p, &i) in free.iter().enumerate() {
        out[i] = x[p] / d[p];
    }
    Some(out)
}

/// Levenberg-Marquardt on `(s, v, a, b, c)` at a fixed blur; returns the SSE and point count.
pub(super) fn refine(ctx: &Ctx, b: &Blurred, p: &mut [f64; 5], free: &[usize]) -> (f64, usize) {
    let mut nm = normal(ctx, b, p);
    let mut lambda = 1e-3;
    for _ in 0..60 {
        let Some(step) = damped_solve(&nm.jtj, &nm.jtr, lambda, free) else { break };
        let mut q = *p;
        for i in 0..5 {
            q[i] += step[i];
        }
        let nq = normal(ctx, b, &q);
        let better = nq.n + 2 >= nm.n && nq.sse / nq.n.max(1) as f64 <= nm.sse / nm.n.max(1) as f64;
        if better {
            let gain = nm.sse - nq.sse;
            *p = q;
            nm = nq;
            lambda = (lambda * 0.1).max(1e-12);
            if gain.abs() <= 1e-12 * nm.sse.max(1e-300) {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    (nm.sse, nm.n)
}

/// The starting parameters: `p` (the coarse shift, offset and sign) with `a, b, c` moved to
/// their linear least-squares values on the sharp design (one undamped Gauss-Newton step over
/// them alone, exact for a model linear in them).
pub(super) fn linear_start(ctx: &Ctx, sharp: &Blurred, mut p: [f64; 5]) -> [f64; 5] {
    let nm = normal(ctx, sharp, &p);
    if let Some(x) = damped_solve(&nm.jtj, &nm.jtr, 0.0, &[2, 3, 4]) {
        for i in 2..5 {
            p[i] += x[i];
        }
    }
    p
}

/// The fit table: per point on the blurred design at its registered position (parameters
/// `p`), the position as in the file (`u + x0`), the measured height and the model's.
pub(super) fn fit_table(ctx: &Ctx, blurred: &Blurred, p: &[f64; 5], x0: f64) -> Vec<[f64; 3]> {
    let mut fit = Vec::with_capacity(ctx.pts.len());
    for &(u, z) in ctx.pts {
        if let Some((hh, _, _)) = blurred.at(ctx.pos(u, p[0], p[1])) {
            fit.push([u + x0, z, p[2] * hh + p[3] + p[4] * (u - ctx.u_mean)]);
        }
    }
    fit
}

/// Standard errors of `(s, v, a, b, c)` and of the blur: `s2 (J^T J)^-1` with the blur's
/// column by central differences; at fixed blur (and the blur's from the profile likelihood)
/// where that column is not determined.
#[allow(clippy::too_many_arguments)]
pub(super) fn covariance(
    ctx: &Ctx,
    b: &Blurred,
    p: &[f64; 5],
    free: &[usize],
    sigma: f64,
    h: f64,
    s2: f64,
    profile_blur_sigma: f64,
) -> Result<([f64; 5], f64)> {
    let with_blur = sigma > 2.0 * h;
    let (bp, bm) =
        if with_blur { (Some(ctx.blurred(sigma + h)?), Some(ctx.blurred(sigma - h)?)) } else { (None, None) };
    let m = free.len() + usize::from(with_blur);
    let mut jtj = vec![0.0; m * m];
    for &(u, _) in ctx.pts {
        let q = ctx.pos(u, p[0], p[1]);
        let Some((hh, hx, hy)) = b.at(q) else { continue };
        let full = [
            p[2] * (hx * ctx.dir[0] + hy * ctx.dir[1]),
            p[2] * (hx * ctx.nrm[0] + hy * ctx.nrm[1]),
            hh,
            1.0,
            u - ctx.u_mean,
        ];
        let mut j: Vec<f64> = free.iter().map(|&i| full[i]).collect();
        if let (Some(bp), Some(bm)) = (&bp, &bm) {
            match (bp.at(q), bm.at(q)) {
                (Some(a), Some(c)) => j.push(p[2] * (a.0 - c.0) / (2.0 * h)),
                _ => continue,
            }
        }
        for x in 0..m {
            for y in 0..m {
                jtj[x * m + y] += j[x] * j[y];
            }
        }
    }
    // Inverse by columns, on the matrix scaled to unit diagonal.
    let d: Vec<f64> = (0..m).map(|k| jtj[k * m + k].sqrt()).collect();
    if d.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(Error::data(
            DataCause::Singular,
            "the fit is singular: a parameter has no effect on the profile",
        ));
    }
    let scaled: Vec<f64> = (0..m * m).map(|k| jtj[k] / (d[k / m] * d[k % m])).collect();
    let mut diag = vec![0.0; m];
    let mut singular = false;
    for k in 0..m {
        let mut e = vec![0.0; m];
        e[k] = 1.0;
        match crate::linalg::solve(scaled.clone(), e, m) {
            Ok(x) => diag[k] = x[k] / (d[k] * d[k]),
            Err(_) => singular = true,
        }
    }
    if singular && with_blur {
        // The blur's column is degenerate with the others: errors at fixed blur.
        let (e, _) = covariance(ctx, b, p, free, 0.0, h, s2, profile_blur_sigma)?;
        return Ok((e, profile_blur_sigma));
    }
    if singular {
        return Err(Error::data(
            DataCause::Singular,
            "the fit is singular: the parameters are not determined by the profile",
        ));
    }
    let mut errors = [0.0; 5];
    for (k, &i) in free.iter().enumerate() {
        errors[i] = (s2 * diag[k]).sqrt();
    }
    let blur_sigma = if with_blur { (s2 * diag[m - 1]).sqrt() } else { profile_blur_sigma };
    Ok((errors, blur_sigma))
}
