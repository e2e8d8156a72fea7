//! Per-level step heights along a profile: the design's distinct levels (at most
//! [`MAX_LEVELS`]), the crop of the design around the line with its terrace interiors
//! ([`DesignIndex`]), and the step heights and depth scales of each level ([`LevelSteps`]).

use serde::Serialize;

use crate::error::{DataCause, Error, Result};
use crate::grid::Grid;

use super::model::Ctx;

/// Most distinct design heights for which the reference counts as multi-level.
pub const MAX_LEVELS: usize = 256;

/// One design level's step on the line (see the module docs).
#[derive(Debug, Clone, Serialize)]
pub struct LevelStep {
    /// Index of the level among the design's distinct heights (0 = lowest).
    pub level: usize,
    /// The design's height of the level above the reference level, metres.
    pub design_step: f64,
    /// Terrace-interior points of the level on the line.
    pub points: usize,
    /// Mean `m_l` of their measured heights `y_k`, metres.
    pub mean: f64,
    /// Sample standard deviation `s_l` of their measured heights `y_k`, metres.
    pub std: f64,
    /// Step height `H_l = m_l - m_l0` above the reference level, metres; `None` for the
    /// reference level.
    pub step_height: Option<f64>,
    /// Standard error of `step_height`, `sqrt(s_l^2 / n_l + s_l0^2 / n_l0)`, metres; `None` for
    /// the reference level.
    pub step_height_sigma: Option<f64>,
    /// Depth scale `H_l / design_step` (1 = as designed); `None` for the reference level.
    pub depth_scale: Option<f64>,
    /// Standard error of `depth_scale`, `step_height_sigma / |design_step|`; `None` for the
    /// reference level.
    pub depth_scale_sigma: Option<f64>,
}

/// The per-level step heights on the line.
#[derive(Debug, Clone, Serialize)]
pub struct LevelSteps {
    /// The design's distinct heights, metres (levels are indices into it).
    pub design_levels: Vec<f64>,
    /// The lowest level with at least 3 interior points on the line, against which step heights
    /// are given (an index into `design_levels`).
    pub reference_level: usize,
    /// Interior radius `r = 2 sigma + 1.5 max(pitch)`, metres: a point is in a terrace interior
    /// when every design sample within `r` is on its level.
    pub interior_radius: f64,
    /// The levels with at least 3 interior points on the line, lowest first.
    pub levels: Vec<LevelStep>,
}

/// The design's distinct heights, sorted, over its valid samples; `None` when there are more
/// than [`MAX_LEVELS`] (not a multi-level design).
fn distinct_levels(design: &Grid) -> Option<Vec<f64>> {
    let nc = design.dim().1;
    let mut v: Vec<f64> = Vec::new();
    for (k, &h) in design.values().iter().enumerate() {
        let (i, j) = (k / nc, k % nc);
        if design.is_valid(i, j) && !v.contains(&h) {
            v.push(h);
            if v.len() > MAX_LEVELS {
                break;
            }
        }
    }
    (v.len() <= MAX_LEVELS).then(|| {
        v.sort_unstable_by(f64::total_cmp);
        v
    })
}

/// The design with its sample index of a position (metres from its centre: fractional index
/// `x / pitch + (n - 1) / 2` along each axis) and its levels ([`distinct_levels`]).
pub(super) struct DesignIndex<'a> {
    design: &'a Grid,
    /// `(n - 1) / 2` along x (columns) and y (rows).
    half: [f64; 2],
    pub(super) levels: Option<Vec<f64>>,
}

impl<'a> DesignIndex<'a> {
    pub(super) fn new(design: &'a Grid) -> Self {
        let (nr, nc) = design.dim();
        let half = [(nc as f64 - 1.0) * 0.5, (nr as f64 - 1.0) * 0.5];
        DesignIndex { design, half, levels: distinct_levels(design) }
    }

    /// The crop of the design holding the line from `start` along `dir` over `u` in
    /// `reach[0]..reach[1]` and offsets across it in `reach[2]..reach[3]`, with `margin` metres
    /// around, and the position of the crop's centre; a line outside the design is refused.
    pub(super) fn crop_around_line(
        &self,
        start: [f64; 2],
        dir: [f64; 2],
        reach: [f64; 4],
        margin: f64,
    ) -> Result<(Grid, [f64; 2])> {
        let (design, half) = (self.design, self.half);
        let pd = design.pitch();
        let nrm = [-dir[1], dir[0]];
        let (nr, nc) = design.dim();
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for u in [reach[0], reach[1]] {
            for v in [reach[2], reach[3]] {
                let p = [start[0] + u * dir[0] + v * nrm[0], start[1] + u * dir[1] + v * nrm[1]];
                for a in 0..2 {
                    lo[a] = lo[a].min(p[a] - margin);
                    hi[a] = hi[a].max(p[a] + margin);
                }
            }
        }
        let idx = |x: f64, a: usize| x / pd[a] + half[a];
        let c0 = idx(lo[0], 0).floor().max(0.0) as usize;
        let c1 = (idx(hi[0], 0).ceil().max(0.0) as usize + 1).min(nc);
        let r0 = idx(lo[1], 1).floor().max(0.0) as usize;
        let r1 = (idx(hi[1], 1).ceil().max(0.0) as usize + 1).min(nr);
        if c0 + 4 > c1 || r0 + 4 > r1 {
            return Err(Error::data(DataCause::OutOfRange, format!(
                "the line from ({:.1}, {:.1}) um along ({:.3}, {:.3}) lies outside the {:.1} x {:.1} um design",
                start[0] * 1e6,
                start[1] * 1e6,
                dir[0],
                dir[1],
                design.extent()[0] * 1e6,
                design.extent()[1] * 1e6
            )));
        }
        let crop = design.crop(r0..r1, c0..c1)?;
        let crop_centre =
            [((c0 + c1 - 1) as f64 * 0.5 - half[0]) * pd[0], ((r0 + r1 - 1) as f64 * 0.5 - half[1]) * pd[1]];
        Ok((crop, crop_centre))
    }

    /// The level of the design sample nearest to `p` (metres from the centre); `None` off the
    /// design, on an invalid sample, or for a design that is not multi-level.
    fn level_at(&self, p: [f64; 2]) -> Option<usize> {
        let levels = self.levels.as_ref()?;
        let (design, half, pd) = (self.design, self.half, self.design.pitch());
        let (nr, nc) = design.dim();
        let j = (p[0] / pd[0] + half[0]).round();
        let i = (p[1] / pd[1] + half[1]).round();
        if i < 0.0 || j < 0.0 || i >= nr as f64 || j >= nc as f64 || !design.is_valid(i as usize, j as usize)
        {
            return None;
        }
        let h = design.values()[[i as usize, j as usize]];
        levels.iter().position(|l| *l == h)
    }

    /// Refuses a line (at zero shift and offset) that crosses fewer than 2 of the levels.
    pub(super) fn check_levels_on_line(&self, ctx: &Ctx) -> Result<()> {
        let mut seen: Vec<usize> =
            ctx.pts.iter().filter_map(|&(u, _)| self.level_at(ctx.pos(u, 0.0, 0.0))).collect();
        seen.sort_unstable();
        seen.dedup();
        if seen.len() < 2 {
            return Err(Error::data(DataCause::Featureless, format!(
                "the line crosses {} level(s) of the design ({}): step heights need at least 2; choose a line \
                 across the structure",
                seen.len(),
                seen.iter().map(|l| l.to_string()).collect::<Vec<_>>().join(", ")
            )));
        }
        Ok(())
    }

    /// The level of `q` when every design sample within `r` of it is on that level (the
    /// terrace interior of the module docs), else `None`.
    fn interior(&self, q: [f64; 2], r: f64) -> Option<usize> {
        let (design, half, pd) = (self.design, self.half, self.design.pitch());
        let (nr, nc) = design.dim();
        let dl = self.levels.as_ref()?;
        let l = self.level_at(q)?;
        let (fi, fj) = (q[1] / pd[1] + half[1], q[0] / pd[0] + half[0]);
        let (ri, rj) = ((r / pd[1]).ceil() as i64, (r / pd[0]).ceil() as i64);
        for di in -ri..=ri {
            for dj in -rj..=rj {
                let (i, j) = (fi.round() as i64 + di, fj.round() as i64 + dj);
                let dx = (j as f64 - fj) * pd[0];
                let dy = (i as f64 - fi) * pd[1];
                if dx * dx + dy * dy > r * r {
                    continue;
                }
                if i < 0
                    || j < 0
                    || i >= nr as i64
                    || j >= nc as i64
                    || !design.is_valid(i as usize, j as usize)
                {
                    return None;
                }
                if design.values()[[i as usize, j as usize]] != dl[l] {
                    return None;
                }
            }
        }
        Some(l)
    }

    /// Per level, the measured heights `y_k = sign(a) (z_k - b - c (u_k - u_mean))` of the
    /// points at their registered positions (parameters `p`) inside its terraces ([`Self::interior`]).
    pub(super) fn interior_heights(&self, ctx: &Ctx, p: &[f64; 5], r: f64) -> Vec<Vec<f64>> {
        let count = self.levels.as_ref().map_or(0, Vec::len);
        let sgn = p[2].signum();
        let mut heights: Vec<Vec<f64>> = vec![Vec::new(); count];
        for &(u, z) in ctx.pts {
            if let Some(l) = self.interior(ctx.pos(u, p[0], p[1]), r) {
                heights[l].push(sgn * (z - p[3] - p[4] * (u - ctx.u_mean)));
            }
        }
        heights
    }
}

/// The step heights of the module docs from each level's interior heights `heights[l]`
/// (`dl` the design's levels, `r` the interior radius): levels with at least 3 points, steps
/// against the lowest of them; fewer than two such levels are refused.
pub(super) fn step_heights(dl: &[f64], heights: &[Vec<f64>], r: f64) -> Result<LevelSteps> {
    let mut acc: Vec<(f64, f64, usize)> = vec![(0.0, 0.0, 0); dl.len()];
    for (l, hs) in heights.iter().enumerate() {
        if !hs.is_empty() {
            let m = hs.iter().sum::<f64>() / hs.len() as f64;
            let sd =
                (hs.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (hs.len() as f64 - 1.0).max(1.0)).sqrt();
            acc[l] = (m, sd, hs.len());
        }
    }
    let present: Vec<usize> = (0..dl.len()).filter(|&l| acc[l].2 >= 3).collect();
    if present.len() < 2 {
        let what = format!(
            "the line holds terrace interiors (points {:.1} um or more from any other level) of {} level(s): \
             step heights need at least 2",
            r * 1e6,
            present.len()
        );
        return Err(Error::data(DataCause::TooFew, what));
    }
    let l0 = present[0];
    let (m0, sd0, n0) = acc[l0];
    let se0 = sd0 * sd0 / n0 as f64;
    let steps = present
        .iter()
        .map(|&l| {
            let (m, sd, n) = acc[l];
            let design_step = dl[l] - dl[l0];
            let (sh, shs, ds, dss) = if l == l0 {
                (None, None, None, None)
            } else {
                let hgt = m - m0;
                let se = (sd * sd / n as f64 + se0).sqrt();
                (Some(hgt), Some(se), Some(hgt / design_step), Some(se / design_step.abs()))
            };
            LevelStep {
                level: l,
                design_step,
                points: n,
                mean: m,
                std: sd,
                step_height: sh,
                step_height_sigma: shs,
                depth_scale: ds,
                depth_scale_sigma: dss,
            }
        })
        .collect();
    Ok(LevelSteps { design_levels: dl.to_vec(), reference_level: l0, interior_radius: r, levels: steps })
}

#[cfg(test)]
mod tests {
    use ndarray::Array2;

    use super::*;
    use crate::grid::Unit;
    use crate::metrology::profile::line::{line_length_warning, LineSpec};
    use crate::metrology::profile::simulate::tests::staircase;

    #[test]
    fn distinct_levels_are_sorted_and_capped() {
        assert_eq!(distinct_levels(&staircase()), Some(vec![0.0, 100e-9, 200e-9, 300e-9]));
        let ramp = |n: usize| {
            Grid::new(Array2::from_shape_fn((1, n), |(_, j)| (n - j) as f64 * 1e-9), [1e-6; 2], Unit::Metre)
                .unwrap()
        };
        let levels = distinct_levels(&ramp(MAX_LEVELS)).unwrap();
        assert_eq!(
            (levels.len(), levels[0], levels[MAX_LEVELS - 1]),
            (MAX_LEVELS, 1e-9, MAX_LEVELS as f64 * 1e-9)
        );
        assert_eq!(distinct_levels(&ramp(MAX_LEVELS + 1)), None);
    }

    /// `H_l = m_l - m_l0 +- sqrt(s_l^2 / n_l + s_l0^2 / n_l0)` on heights whose means and
    /// spreads are known: level 0 (1.0 +- 0.2, 3 points), level 1 too few points, level 2
    /// (3.0, spread sqrt(0.02 / 3), 4 points).
    #[test]
    fn step_heights_follow_the_module_docs() {
        let dl = [0.0, 0.5, 1.0];
        let heights = vec![vec![1.0, 1.2, 0.8], vec![2.0, 2.0], vec![3.0, 3.1, 2.9, 3.0]];
        let s = step_heights(&dl, &heights, 1e-6).unwrap();
        assert_eq!((s.reference_level, s.levels.len(), s.levels[1].level), (0, 2, 2));
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        let (l0, l2) = (&s.levels[0], &s.levels[1]);
        assert!(close(l0.mean, 1.0) && close(l0.std, 0.2) && l0.step_height.is_none(), "{l0:?}");
        let se = (0.04 / 3.0 + 0.02 / 3.0 / 4.0f64).sqrt();
        assert!(close(l2.step_height.unwrap(), 2.0) && close(l2.step_height_sigma.unwrap(), se), "{l2:?}");
        assert!(close(l2.depth_scale.unwrap(), 2.0) && close(l2.depth_scale_sigma.unwrap(), se), "{l2:?}");
        let e = step_heights(&dl, &heights[..2], 1e-6).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::TooFew, .. }), "{e:?}");
    }

    #[test]
    fn the_crop_holds_every_searched_position_of_the_line() {
        let d = staircase();
        let index = DesignIndex::new(&d);
        let (start, dir) = LineSpec::Angle { angle: 0.4 }.frame(300e-6);
        let reach = [-20e-6, 320e-6, -10e-6, 10e-6];
        let (crop, centre) = index.crop_around_line(start, dir, reach, 5e-6).unwrap();
        let half = [0.5 * crop.extent()[0], 0.5 * crop.extent()[1]];
        for u in [reach[0], reach[1]] {
            for v in [reach[2], reach[3]] {
                let p = [start[0] + u * dir[0] - v * dir[1], start[1] + u * dir[1] + v * dir[0]];
                for a in 0..2 {
                    assert!(
                        (p[a] - centre[a]).abs() + 5e-6 <= half[a],
                        "{p:?} outside {centre:?} +- {half:?}"
                    );
                }
            }
        }
        let far = index.crop_around_line([1e-3, 1e-3], [1.0, 0.0], reach, 5e-6).unwrap_err().to_string();
        assert!(far.contains("lies outside"), "{far}");
        assert!(line_length_warning(&LineSpec::Angle { angle: 0.0 }, 1e-4).is_none());
        let line = LineSpec::Points { start: [0.0, 0.0], end: [100e-6, 0.0] };
        assert!(line_length_warning(&line, 104e-6).is_none() && line_length_warning(&line, 200e-6).is_some());
    }
}
