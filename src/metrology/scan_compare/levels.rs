//! The quantization levels of a comparison: how the design's levels are given
//! ([`LevelSpec`]), the mean and spread of each level in the difference map ([`LevelStat`]), and
//! each level's height fitted as the blurred indicator of its footprint ([`LevelHeights`]).

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::grid::Grid;

/// NaN: a figure a file written before it existed does not hold.
pub(super) fn nan() -> f64 {
    f64::NAN
}

/// Reads a JSON `null` (how serde_json writes NaN and infinities) back as NaN.
pub(super) fn null_as_nan<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::NAN))
}

/// The quantization of the design: `count` levels of `step` metres (level `l` at `l step`).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct LevelSpec {
    /// Number of levels of the design (level `l` at `l step`, `l = 0..count`).
    pub count: usize,
    /// Height of one level step, metres.
    pub step: f64,
}

impl LevelSpec {
    /// The levels a surface of these levels whose highest height is `top` holds: `count`, and
    /// one more where `top` reaches `count step` (the cast of the master, whose level 0 lies at
    /// the full period: level `count`).
    pub fn indices(&self, top: f64) -> usize {
        let q = (top / self.step).round();
        if q.is_finite() && q >= self.count as f64 {
            self.count + 1
        } else {
            self.count
        }
    }

    /// The level of height `h` among `indices` levels: the nearest, within range.
    pub fn level_of(&self, h: f64, indices: usize) -> usize {
        (h / self.step).round().clamp(0.0, indices as f64 - 1.0) as usize
    }
}

/// Mean and spread of the part's height over one level's terraces.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LevelStat {
    /// Index of the level (0 = lowest; `count` for the cast's level at the full period).
    pub level: usize,
    /// Design height `l step`, metres.
    pub design_height: f64,
    /// Samples (terrace interiors: the sample and its four neighbours on this level, measured).
    pub samples: usize,
    /// Mean of the as-fabricated height over the samples, metres; `NaN` (`null` in JSON)
    /// without samples.
    #[serde(deserialize_with = "null_as_nan")]
    pub mean: f64,
    /// Sample standard deviation of the as-fabricated height over the samples, metres; `NaN`
    /// (`null` in JSON) with fewer than 2.
    #[serde(deserialize_with = "null_as_nan")]
    pub std: f64,
    /// The level's height fitted with the part's blur over the terrace interiors of the
    /// aperture, metres (see [`LevelHeights`]); `None` where the fit is singular.
    #[serde(default)]
    pub fitted_height: Option<f64>,
    /// Measured terrace-interior samples of this level inside the aperture (the fit's support).
    #[serde(default)]
    pub aperture_samples: usize,
}

/// The per-level statistics (`levels` has a level more than `count` for the cast of the
/// master: its level 0 lies at the full period, as level `count`, and level 0 is empty). The
/// means over terrace interiors are biased wherever the blur
/// reaches into the interiors (narrow terraces, and the level next to a phase wrap most of
/// all, whose neighbour is a full period higher); `fitted_height` is not: the surface over the
/// aperture's terrace interiors is fitted as `s(x) = sum_l h_l (G_sigma * chi_l)(x)`, with
/// `chi_l` the indicator of level `l` and `sigma` the fitted blur, by linear least squares in
/// the `h_l` (without blur, the fit is the interior mean).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct LevelHeights {
    /// Number of levels of the design ([`LevelSpec::count`]).
    pub count: usize,
    /// Nominal step, metres.
    pub step: f64,
    /// One per level index, lowest first: `count`, or `count + 1` for the cast of the master.
    pub levels: Vec<LevelStat>,
    /// Differences of consecutive level means `mean[l + 1] - mean[l]` (both with samples),
    /// metres.
    pub step_heights: Vec<f64>,
    /// Mean of `step_heights`, metres; `NaN` (`null` in JSON) when there is none.
    #[serde(deserialize_with = "null_as_nan")]
    pub mean_step: f64,
    /// Sample standard deviation of `step_heights`, metres; `NaN` (`null` in JSON) with fewer
    /// than 2.
    #[serde(deserialize_with = "null_as_nan")]
    pub step_std: f64,
    /// Largest distance of a design height from its level, in steps (0 for a quantized design).
    #[serde(deserialize_with = "null_as_nan")]
    pub design_off_level: f64,
}

pub(super) fn level_stats(
    design: &Grid,
    surface: &Grid,
    inside: &Array2<bool>,
    spec: LevelSpec,
    blur: f64,
) -> Result<LevelHeights> {
    if spec.count < 2 || !(spec.step.is_finite() && spec.step > 0.0) {
        return Err(Error::param(
            "levels",
            format!(
                "{} levels of {:e} m: expected at least 2 levels of a positive step",
                spec.count, spec.step
            ),
        ));
    }
    let (nr, nc) = design.dim();
    let count = spec.indices(design.min_max().map_or(0.0, |m| m.1));
    let mut off = 0.0f64;
    let level = Array2::from_shape_fn((nr, nc), |(i, j)| {
        let h = design.values()[[i, j]];
        let l = spec.level_of(h, count);
        if inside[[i, j]] {
            off = off.max((h / spec.step - l as f64).abs());
        }
        l
    });
    let mut acc = vec![(0usize, 0.0f64, 0.0f64); count];
    for i in 1..nr.saturating_sub(1) {
        for j in 1..nc.saturating_sub(1) {
            let l = level[[i, j]];
            let nb = [(i, j), (i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)];
            if nb.iter().all(|&(a, b)| level[[a, b]] == l && inside[[a, b]] && surface.is_valid(a, b)) {
                let z = surface.values()[[i, j]];
                acc[l].0 += 1;
                acc[l].1 += z;
                acc[l].2 += z * z;
            }
        }
    }
    let (fitted, area) = fit_level_heights(design, surface, inside, &level, count, blur)?;
    let levels: Vec<LevelStat> = acc
        .iter()
        .enumerate()
        .map(|(l, &(n, s, ss))| {
            let mean = if n > 0 { s / n as f64 } else { f64::NAN };
            let var = if n > 1 { (ss - s * s / n as f64) / (n as f64 - 1.0) } else { f64::NAN };
            LevelStat {
                level: l,
                design_height: l as f64 * spec.step,
                samples: n,
                mean,
                std: var.max(0.0).sqrt(),
                fitted_height: fitted[l],
                aperture_samples: area[l],
            }
        })
        .collect();
    let step_heights: Vec<f64> = levels
        .windows(2)
        .filter(|w| w[0].samples > 0 && w[1].samples > 0)
        .map(|w| w[1].mean - w[0].mean)
        .collect();
    let m = step_heights.len() as f64;
    let mean_step = step_heights.iter().sum::<f64>() / m;
    let step_std = (step_heights.iter().map(|d| (d - mean_step).powi(2)).sum::<f64>() / (m - 1.0)).sqrt();
    Ok(LevelHeights {
        count: spec.count,
        step: spec.step,
        levels,
        step_heights,
        mean_step,
        step_std,
        design_off_level: off,
    })
}

/// Most levels whose heights are fitted with the blur (a fit for the few levels of a
/// multi-level part, not for the 65,536 "levels" of a continuous 16-bit surface).
pub const MAX_FITTED_LEVELS: usize = 256;

/// The level heights of [`LevelHeights`]'s blurred-indicator fit, of the levels the design
/// holds (`None` for a level it does not hold, and for every level where the fit is singular:
/// a level held with no measured sample in the aperture), and each level's measured samples
/// there.
fn fit_level_heights(
    design: &Grid,
    surface: &Grid,
    inside: &Array2<bool>,
    level: &Array2<usize>,
    count: usize,
    blur: f64,
) -> Result<(Vec<Option<f64>>, Vec<usize>)> {
    // Terrace interiors, as for the means: a sample next to a level change also carries the
    // resampling of the scan onto the design grid, which no blur of the design models.
    let (nr, nc) = level.dim();
    let used = |i: usize, j: usize| {
        let l = level[[i, j]];
        i > 0
            && j > 0
            && i + 1 < nr
            && j + 1 < nc
            && [(i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)].iter().all(|&(a, b)| level[[a, b]] == l)
            && inside[[i, j]]
            && surface.is_valid(i, j)
    };
    let mut area = vec![0usize; count];
    let mut held = vec![false; count];
    for ((i, j), &l) in level.indexed_iter() {
        held[l] = true;
        if used(i, j) {
            area[l] += 1;
        }
    }
    // The unknowns: the levels the design holds (a level it does not hold has no indicator).
    let index: Vec<Option<usize>> =
        held.iter().scan(0, |k, &h| Some(h.then(|| std::mem::replace(k, *k + 1)))).collect();
    let unknowns = held.iter().filter(|h| **h).count();
    let singular = (0..count).any(|l| held[l] && area[l] == 0);
    if singular || unknowns > MAX_FITTED_LEVELS {
        return Ok((vec![None; count], area));
    }
    // The blurred indicators at each used sample, from the sample's window of the design's
    // levels (the blur reaches across the aperture's edge as it does on the part): the same
    // truncated, border-normalised separable kernel as [`gaussian_blur`]. Rows are summed in
    // fixed chunks, in order, so the sums do not depend on the thread count.
    use rayon::prelude::*;
    let kernel = |s: f64| -> Vec<f64> {
        if s <= 0.0 {
            return vec![1.0];
        }
        let r = (4.0 * s).ceil() as isize;
        (-r..=r).map(|k| (-0.5 * (k as f64 / s).powi(2)).exp()).collect()
    };
    let kx = kernel(blur / design.pitch()[0]);
    let ky = kernel(blur / design.pitch()[1]);
    let (rx, ry) = ((kx.len() / 2) as isize, (ky.len() / 2) as isize);
    let scale = 1e-6;
    const ROWS: usize = 16;
    let n = unknowns;
    let chunks: Vec<(Vec<f64>, Vec<f64>)> = (0..nr.div_ceil(ROWS))
        .into_par_iter()
        .map(|c| {
            let (mut a, mut r) = (vec![0.0; n * n], vec![0.0; n]);
            let mut f = vec![0.0; n];
            let mut seen = vec![false; n];
            let mut touched = Vec::with_capacity(n);
            for i in c * ROWS..((c + 1) * ROWS).min(nr) {
                for j in 0..nc {
                    if !used(i, j) {
                        continue;
                    }
                    let (i0, i1) = ((i as isize - ry).max(0), (i as isize + ry).min(nr as isize - 1));
                    let (j0, j1) = ((j as isize - rx).max(0), (j as isize + rx).min(nc as isize - 1));
                    let wy: f64 = (i0..=i1).map(|a| ky[(a - i as isize + ry) as usize]).sum();
                    let wx: f64 = (j0..=j1).map(|b| kx[(b - j as isize + rx) as usize]).sum();
                    for a in i0..=i1 {
                        let gy = ky[(a - i as isize + ry) as usize];
                        for b in j0..=j1 {
                            // Every level read here is held, so it has an index.
                            let Some(l) = index[level[[a as usize, b as usize]]] else { continue };
                            if !seen[l] {
                                seen[l] = true;
                                touched.push(l);
                            }
                            f[l] += gy * kx[(b - j as isize + rx) as usize];
                        }
                    }
                    let z = surface.values()[[i, j]] / scale;
                    for &p in &touched {
                        let fp = f[p] / (wx * wy);
                        r[p] += fp * z;
                        for &q in &touched {
                            a[p * n + q] += fp * f[q] / (wx * wy);
                        }
                    }
                    for &p in &touched {
                        f[p] = 0.0;
                        seen[p] = false;
                    }
                    touched.clear();
                }
            }
            (a, r)
        })
        .collect();
    let (mut a, mut r) = (vec![0.0; n * n], vec![0.0; n]);
    for (ca, cr) in &chunks {
        a.iter_mut().zip(ca).for_each(|(x, y)| *x += y);
        r.iter_mut().zip(cr).for_each(|(x, y)| *x += y);
    }
    match crate::linalg::solve(a, r, n) {
        Ok(h) => Ok((index.iter().map(|k| k.map(|k| h[k] * scale)).collect(), area)),
        Err(_) => Ok((vec![None; count], area)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::blur::gaussian_blur;
    use crate::grid::Unit;

    /// Level heights of a blurred staircase (8 levels of 5 samples, a bowed response, blur of
    /// two samples): the blurred-indicator fit recovers them to round-off, where the interior
    /// means are pulled towards the neighbours (level 0 most, next to the wrap).
    #[test]
    fn the_blurred_indicator_fit_recovers_level_heights_that_means_miss() {
        let (n, pitch) = (120, 4e-6);
        let level = Array2::from_shape_fn((n, n), |(_, j)| (j % 40) / 5);
        let h: Vec<f64> = (0..8).map(|l| l as f64 * 150e-9 * (1.0 + 0.04 * l as f64)).collect();
        let design = Grid::new(level.mapv(|l| l as f64 * 150e-9), [pitch; 2], Unit::Metre).unwrap();
        let made = Grid::new(level.mapv(|l| h[l]), [pitch; 2], Unit::Metre).unwrap();
        let part = gaussian_blur(&made, 2.0 * pitch).unwrap();
        let inside = Array2::from_elem((n, n), true);
        let (fit, area) = fit_level_heights(&design, &part, &inside, &level, 8, 2.0 * pitch).unwrap();
        let fit: Vec<f64> = fit.iter().map(|h| h.unwrap()).collect();
        assert!(area.iter().all(|&a| a > 1000), "{area:?}");
        for (l, (f, h)) in fit.iter().zip(&h).enumerate() {
            assert!((f - h).abs() < 1e-12, "level {l}: {f} vs {h}");
        }
        let spec = LevelSpec { count: 8, step: 150e-9 };
        let r = level_stats(&design, &part, &inside, spec, 2.0 * pitch).unwrap();
        assert!(r.levels[0].mean - h[0] > 50e-9, "{:?}", r.levels[0]);
        assert_eq!(r.levels[0].fitted_height, Some(fit[0]));
        // Without the blur in the fit the same samples give the means' bias back.
        let (plain, _) = fit_level_heights(&design, &part, &inside, &level, 8, 0.0).unwrap();
        assert!((plain[0].unwrap() - r.levels[0].mean).abs() < 1e-15);
        // The same staircase with level 0 lifted to the period (as the cast of a master holds
        // it): 9 level indices, level 0 held nowhere, the others fitted as before.
        let lifted = level.mapv(|l| if l == 0 { 8 } else { l });
        let hl = |l: usize| if l == 8 { h[0] + 8.0 * 150e-9 } else { h[l] };
        let made = Grid::new(lifted.mapv(hl), [pitch; 2], Unit::Metre).unwrap();
        let part = gaussian_blur(&made, 2.0 * pitch).unwrap();
        let (fit, area) = fit_level_heights(&design, &part, &inside, &lifted, 9, 2.0 * pitch).unwrap();
        assert_eq!((fit[0], area[0]), (None, 0));
        for (l, f) in fit.iter().enumerate().skip(1) {
            assert!((f.unwrap() - hl(l)).abs() < 1e-12, "level {l}: {f:?} vs {}", hl(l));
        }
    }
}
