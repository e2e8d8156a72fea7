//! The least-squares refinement of a registration (module docs, step 3): the scan samples fitted,
//! the parameters, the normal equations accumulated in fixed chunks (the same sums on any
//! thread count) and the Levenberg-Marquardt steps.

use crate::error::{Condition, Error, Refusal, Result};
use crate::grid::Grid;

use super::sampler::Sampler;

/// Solves the `n x n` system `a x = r` ([`crate::linalg::solve`]); `None` where it
/// is singular or the solution is not finite.
pub(super) fn solve(a: &mut [f64], r: &mut [f64], n: usize) -> Option<Vec<f64>> {
    let x = crate::linalg::solve(a.to_vec(), r.to_vec(), n).ok()?;
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Scan samples for the fit: `[x, y, z]` (positions from the scan's centre, metres) with a
/// stride so that at most about `limit` remain.
pub(super) fn points(scan: &Grid, limit: usize) -> Vec<[f64; 3]> {
    let (nr, nc) = scan.dim();
    let n = scan.valid_count().max(1);
    let stride = ((n as f64 / limit.max(1) as f64).sqrt().ceil() as usize).max(1);
    let p = scan.pitch();
    let (ci, cj) = ((nr as f64 - 1.0) * 0.5, (nc as f64 - 1.0) * 0.5);
    let mut out = Vec::with_capacity(n / (stride * stride) + 1);
    for i in (0..nr).step_by(stride) {
        for j in (0..nc).step_by(stride) {
            if scan.is_valid(i, j) {
                out.push([(j as f64 - cj) * p[0], (i as f64 - ci) * p[1], scan.values()[[i, j]]]);
            }
        }
    }
    out
}

/// The parameters of the least-squares model: shift in design pixels, rotation, log scale and
/// the linear `(a, b, c_x, c_y)`.
#[derive(Debug, Clone, Copy)]
pub(super) struct Params {
    pub(super) t: [f64; 2],
    pub(super) theta: f64,
    pub(super) ln_s: f64,
    /// `(a, b, c_x, c_y, e)`: `e` weighs the design's Laplacian (first-order blur, `e = a sigma^2 / 2`).
    pub(super) lin: [f64; 5],
}

impl Params {
    fn vec(&self) -> [f64; NP] {
        let l = self.lin;
        [self.t[0], self.t[1], self.theta, self.ln_s, l[0], l[1], l[2], l[3], l[4]]
    }
    fn from_vec(v: &[f64; NP]) -> Params {
        Params { t: [v[0], v[1]], theta: v[2], ln_s: v[3], lin: [v[4], v[5], v[6], v[7], v[8]] }
    }
}

/// Parameters of the least-squares model.
const NP: usize = 9;

pub(super) struct Ctx<'a> {
    pub(super) sampler: &'a Sampler<'a>,
    pub(super) mirror: bool,
    /// Design pitch (shift unit).
    pub(super) pd: [f64; 2],
    /// Binning factor of the sampler's grid relative to the design.
    pub(super) g: f64,
}

/// Normal equations and moments over the points at one parameter set.
#[derive(Debug, Clone, Copy)]
pub(super) struct Normal {
    n: f64,
    sse: f64,
    a: [f64; NP * NP],
    r: [f64; NP],
    /// Moments of (z - plane) and h: sums of z', z'^2, h, h^2, z' h.
    m: [f64; 5],
}

impl Normal {
    fn zero() -> Normal {
        Normal { n: 0.0, sse: 0.0, a: [0.0; NP * NP], r: [0.0; NP], m: [0.0; 5] }
    }
    fn add(&mut self, o: &Normal) {
        self.n += o.n;
        self.sse += o.sse;
        self.a.iter_mut().zip(&o.a).for_each(|(x, y)| *x += y);
        self.r.iter_mut().zip(&o.r).for_each(|(x, y)| *x += y);
        self.m.iter_mut().zip(&o.m).for_each(|(x, y)| *x += y);
    }
    fn mse(&self) -> f64 {
        if self.n > 0.0 {
            self.sse / self.n
        } else {
            f64::INFINITY
        }
    }
}

/// Points per chunk of [`accumulate`]: fixed, so that the sums are added in the same order
/// whatever the number of threads (the result is bit-identical on 1 or 64 cores).
const ACCUMULATE_CHUNK: usize = 8192;

/// The normal equations over all points: fixed chunks accumulated in parallel, then added in
/// chunk order. A worker that panics is reported as an error, never taken as zeros.
fn accumulate(ctx: &Ctx, pts: &[[f64; 3]], p: &Params, half: [f64; 2]) -> Result<Normal> {
    use rayon::prelude::*;
    let parts = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        pts.par_chunks(ACCUMULATE_CHUNK).map(|c| accumulate_chunk(ctx, c, p, half)).collect::<Vec<_>>()
    }))
    .map_err(|e| {
        let why = e
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| e.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown cause".into());
        Error::internal(format!("registration: a worker accumulating the normal equations panicked ({why})"))
    })?;
    let mut total = Normal::zero();
    for q in &parts {
        total.add(q);
    }
    Ok(total)
}

fn accumulate_chunk(ctx: &Ctx, pts: &[[f64; 3]], p: &Params, half: [f64; 2]) -> Normal {
    let mut nm = Normal::zero();
    let s = p.ln_s.exp();
    let (sn, cs) = p.theta.sin_cos();
    let mx = if ctx.mirror { -1.0 } else { 1.0 };
    let t = [p.t[0] * ctx.pd[0], p.t[1] * ctx.pd[1]];
    let pitch = [ctx.pd[0] * ctx.g, ctx.pd[1] * ctx.g];
    let (ci, cj) = ((ctx.sampler.rows as f64 - 1.0) * 0.5, (ctx.sampler.cols as f64 - 1.0) * 0.5);
    let [a, b, cx, cy, e] = p.lin;
    let mut jac = [0.0; NP];
    for q in pts {
        let u = [(q[0] - t[0]) / s, (q[1] - t[1]) / s];
        let v = [cs * u[0] + sn * u[1], -sn * u[0] + cs * u[1]];
        let w = [mx * v[0], v[1]];
        let Some([h, hi, hj, l, li, lj]) = ctx.sampler.eval_lap(w[1] / pitch[1] + ci, w[0] / pitch[0] + cj)
        else {
            continue;
        };
        // Gradient (per metre) of the model's design term a h + e L.
        let (gx, gy) = ((a * hj + e * lj) / pitch[0], (a * hi + e * li) / pitch[1]);
        let (xn, yn) = (q[0] / half[0], q[1] / half[1]);
        let plane = b + cx * xn + cy * yn;
        let r = q[2] - a * h - e * l - plane;
        // d w / d t_x (per design pixel), d t_y, d theta, d ln s.
        let dtx = [-mx * cs / s * ctx.pd[0], sn / s * ctx.pd[0]];
        let dty = [-mx * sn / s * ctx.pd[1], -cs / s * ctx.pd[1]];
        let dth = [mx * v[1], -v[0]];
        let dls = [-w[0], -w[1]];
        jac[0] = gx * dtx[0] + gy * dtx[1];
        jac[1] = gx * dty[0] + gy * dty[1];
        jac[2] = gx * dth[0] + gy * dth[1];
        jac[3] = gx * dls[0] + gy * dls[1];
        jac[4] = h;
        jac[5] = 1.0;
        jac[6] = xn;
        jac[7] = yn;
        jac[8] = l;
        for k in 0..NP {
            nm.r[k] += jac[k] * r;
            for m in k..NP {
                nm.a[k * NP + m] += jac[k] * jac[m];
            }
        }
        nm.n += 1.0;
        nm.sse += r * r;
        let zp = q[2] - plane - e * l;
        nm.m[0] += zp;
        nm.m[1] += zp * zp;
        nm.m[2] += h;
        nm.m[3] += h * h;
        nm.m[4] += zp * h;
    }
    for k in 0..NP {
        for m in 0..k {
            nm.a[k * NP + m] = nm.a[m * NP + k];
        }
    }
    nm
}

/// Solves the damped, diagonally scaled normal equations for the free parameters.
fn lm_step(nm: &Normal, lambda: f64, free: &[usize]) -> Option<[f64; NP]> {
    let n = free.len();
    let d: Vec<f64> = free.iter().map(|&k| nm.a[k * NP + k].sqrt().max(1e-300)).collect();
    let mut a = vec![0.0; n * n];
    let mut r = vec![0.0; n];
    for (x, &k) in free.iter().enumerate() {
        r[x] = nm.r[k] / d[x];
        for (y, &l) in free.iter().enumerate() {
            a[x * n + y] = nm.a[k * NP + l] / (d[x] * d[y]);
        }
        a[x * n + x] += lambda;
    }
    let x = solve(&mut a, &mut r, n)?;
    let mut out = [0.0; NP];
    for (i, &k) in free.iter().enumerate() {
        out[k] = x[i] / d[i];
    }
    Some(out)
}

pub(super) struct Fit {
    pub(super) correlation: f64,
    pub(super) rms: f64,
    pub(super) sigma: [f64; NP],
    pub(super) points: usize,
}

/// Levenberg-Marquardt on the eight parameters (step 4 of the module docs); `linear_first`: an
/// exact least-squares step of the linear parameters alone first (for a start whose heights are
/// not yet fitted).
pub(super) fn refine(
    ctx: &Ctx,
    pts: &[[f64; 3]],
    p: &mut Params,
    radius_px: f64,
    linear_first: bool,
) -> Result<Fit> {
    // Plane slopes are fitted per metre (the normal equations are diagonally scaled).
    let half = [1.0, 1.0];
    // The linear parameters first, with the geometry fixed (exact least squares).
    let mut nm = accumulate(ctx, pts, p, half)?;
    if nm.n < 16.0 {
        return Err(Error::validity(
            Condition::Registration(Refusal::NoOverlap),
            "the scan and the design barely overlap at the coarse placement: nothing to refine",
        ));
    }
    let all: Vec<usize> = (0..NP).collect();
    if let Some(d) = lm_step(&nm, 0.0, &[4, 5, 6, 7, 8]).filter(|_| linear_first) {
        let mut v = p.vec();
        v.iter_mut().zip(&d).for_each(|(x, y)| *x += y);
        *p = Params::from_vec(&v);
        nm = accumulate(ctx, pts, p, half)?;
    }
    let mut lambda = 1e-3;
    for _ in 0..50 {
        let Some(d) = lm_step(&nm, lambda, &all) else { break };
        let mut v = p.vec();
        v.iter_mut().zip(&d).for_each(|(x, y)| *x += y);
        let q = Params::from_vec(&v);
        let nq = accumulate(ctx, pts, &q, half)?;
        if nq.n >= 16.0 && nq.mse() <= nm.mse() {
            *p = q;
            nm = nq;
            lambda = (lambda * 0.1).max(1e-9);
            let geo = d[0].abs().max(d[1].abs()).max((d[2].abs() + d[3].abs()) * radius_px);
            if geo < 1e-5 {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    let n = nm.n;
    let [sz, szz, sh, shh, szh] = nm.m;
    let cov_zh = szh / n - sz * sh / (n * n);
    let var_z = szz / n - (sz / n).powi(2);
    let var_h = shh / n - (sh / n).powi(2);
    let correlation = (cov_zh / (var_z * var_h).sqrt()).abs();
    // Formal covariance sigma^2 (J^T J)^-1, column by column, solved on the diagonally scaled
    // matrix D^-1 (J^T J) D^-1 (the parameters' units differ by orders of magnitude) and scaled
    // back: (J^T J)^-1 = D^-1 (D^-1 J^T J D^-1)^-1 D^-1. NaN when the matrix is singular.
    let s2 = nm.sse / (n - NP as f64).max(1.0);
    let d: Vec<f64> = (0..NP).map(|k| nm.a[k * NP + k].sqrt().max(1e-300)).collect();
    let scaled: Vec<f64> = (0..NP * NP).map(|q| nm.a[q] / (d[q / NP] * d[q % NP])).collect();
    let mut sigma = [f64::NAN; NP];
    for (k, sk) in sigma.iter_mut().enumerate() {
        let mut a = scaled.clone();
        let mut e = vec![0.0; NP];
        e[k] = 1.0;
        if let Some(x) = solve(&mut a, &mut e, NP) {
            *sk = (s2 * x[k]).max(0.0).sqrt() / d[k];
        }
    }
    Ok(Fit {
        correlation: if correlation.is_finite() { correlation } else { 0.0 },
        rms: nm.mse().sqrt(),
        sigma,
        points: n as usize,
    })
}
