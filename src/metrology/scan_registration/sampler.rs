//! Reading a grid between its samples with its gradient ([`Sampler`]): Keys cubic convolution
//! where all 16 taps are measured.

use std::borrow::Cow;

use rayon::prelude::*;

use crate::grid::Grid;

/// Keys cubic convolution (a = -0.5) of a grid's values with its analytic gradient; positions
/// in metres from the grid's centre or fractional indices. Taps beyond the edge repeat the edge
/// sample; a point more than half a sample outside the grid, or touching an invalid sample,
/// has no value.
#[derive(Debug, Clone)]
pub struct Sampler<'a> {
    /// The values, row-major: borrowed from the grid when it stores them so.
    v: Cow<'a, [f64]>,
    /// Discrete Laplacian of the values (per square metre), when made by [`Sampler::with_laplacian`].
    lap: Option<Vec<f64>>,
    valid: Option<Vec<bool>>,
    pub(super) rows: usize,
    pub(super) cols: usize,
    pitch: [f64; 2],
}

impl<'a> Sampler<'a> {
    /// A sampler of `g`'s values (borrowed where the grid stores them row-major), without the
    /// Laplacian.
    pub fn new(g: &'a Grid) -> Sampler<'a> {
        let (rows, cols) = g.dim();
        Sampler {
            v: g.values()
                .as_slice()
                .map_or_else(|| Cow::Owned(g.values().iter().copied().collect()), Cow::Borrowed),
            lap: None,
            valid: g.mask().map(|m| m.iter().copied().collect()),
            rows,
            cols,
            pitch: g.pitch(),
        }
    }

    /// A sampler holding its own copy of the values (one that outlives the grid).
    pub fn new_owned(g: &Grid) -> Sampler<'static> {
        let s = Sampler::new(g);
        Sampler {
            v: Cow::Owned(s.v.into_owned()),
            lap: s.lap,
            valid: s.valid,
            rows: s.rows,
            cols: s.cols,
            pitch: s.pitch,
        }
    }

    /// Also samples the 5-point Laplacian `d2h/dx2 + d2h/dy2` of the values (0 next to an
    /// invalid sample; edges repeat the edge sample).
    pub fn with_laplacian(g: &'a Grid) -> Sampler<'a> {
        let mut s = Sampler::new(g);
        let (nr, nc) = (s.rows, s.cols);
        let (px2, py2) = (s.pitch[0] * s.pitch[0], s.pitch[1] * s.pitch[1]);
        let ok = |k: usize| s.valid.as_ref().is_none_or(|m| m[k]);
        let mut lap = vec![0.0; nr * nc];
        let v = &s.v;
        // Rows in parallel; each sample depends on its neighbours only.
        lap.par_chunks_mut(nc).enumerate().for_each(|(i, row)| {
            for (j, out) in row.iter_mut().enumerate() {
                let k = i * nc + j;
                let (u, d) = (i.saturating_sub(1) * nc + j, (i + 1).min(nr - 1) * nc + j);
                let (l, r) = (i * nc + j.saturating_sub(1), i * nc + (j + 1).min(nc - 1));
                if [k, u, d, l, r].iter().all(|&q| ok(q)) {
                    *out = (v[l] + v[r] - 2.0 * v[k]) / px2 + (v[u] + v[d] - 2.0 * v[k]) / py2;
                }
            }
        });
        s.lap = Some(lap);
        s
    }

    /// Fractional `(row, column)` index of a position (metres from the centre).
    pub fn index_of(&self, x: [f64; 2]) -> (f64, f64) {
        (
            x[1] / self.pitch[1] + (self.rows as f64 - 1.0) * 0.5,
            x[0] / self.pitch[0] + (self.cols as f64 - 1.0) * 0.5,
        )
    }

    /// Value at a position (metres from the centre).
    pub fn at_position(&self, x: [f64; 2]) -> Option<f64> {
        let (fi, fj) = self.index_of(x);
        self.eval(fi, fj).map(|r| r.0)
    }

    /// `(value, d value / d row, d value / d column)` at fractional index `(fi, fj)`.
    #[inline]
    pub fn eval(&self, fi: f64, fj: f64) -> Option<(f64, f64, f64)> {
        self.eval_lap(fi, fj).map(|r| (r[0], r[1], r[2]))
    }

    /// `[h, dh/di, dh/dj, L, dL/di, dL/dj]` with `L` the Laplacian (0 without one).
    #[inline]
    pub fn eval_lap(&self, fi: f64, fj: f64) -> Option<[f64; 6]> {
        let (nr, nc) = (self.rows as isize, self.cols as isize);
        if !(fi >= -0.5 && fj >= -0.5 && fi <= nr as f64 - 0.5 && fj <= nc as f64 - 0.5) {
            return None;
        }
        let (i0, j0) = (fi.floor(), fj.floor());
        let (wi, di) = keys(fi - i0);
        let (wj, dj) = keys(fj - j0);
        let (i0, j0) = (i0 as isize, j0 as isize);
        let mut out = [0.0; 6];
        for a in 0..4 {
            let r = (i0 + a as isize - 1).clamp(0, nr - 1) as usize * self.cols;
            let (mut row, mut drow, mut lrow, mut ldrow) = (0.0, 0.0, 0.0, 0.0);
            for b in 0..4 {
                let k = r + (j0 + b as isize - 1).clamp(0, nc - 1) as usize;
                if let Some(m) = &self.valid {
                    if !m[k] {
                        return None;
                    }
                }
                row += wj[b] * self.v[k];
                drow += dj[b] * self.v[k];
                if let Some(l) = &self.lap {
                    lrow += wj[b] * l[k];
                    ldrow += dj[b] * l[k];
                }
            }
            out[0] += wi[a] * row;
            out[1] += di[a] * row;
            out[2] += wi[a] * drow;
            out[3] += wi[a] * lrow;
            out[4] += di[a] * lrow;
            out[5] += wi[a] * ldrow;
        }
        Some(out)
    }
}

/// Keys weights for taps at -1, 0, 1, 2 from `t` in [0, 1), and their derivatives in `t`.
#[inline]
fn keys(t: f64) -> ([f64; 4], [f64; 4]) {
    let k1 = |x: f64| 1.5 * x * x * x - 2.5 * x * x + 1.0; // |x| <= 1
    let k2 = |x: f64| -0.5 * x * x * x + 2.5 * x * x - 4.0 * x + 2.0; // 1 < |x| < 2
    let d1 = |x: f64| 4.5 * x * x - 5.0 * x;
    let d2 = |x: f64| -1.5 * x * x + 5.0 * x - 4.0;
    ([k2(t + 1.0), k1(t), k1(1.0 - t), k2(2.0 - t)], [d2(t + 1.0), d1(t), -d1(1.0 - t), -d2(2.0 - t)])
}
