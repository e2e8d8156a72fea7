//! Quantization of wrapped heights to N levels, the predicted diffraction efficiency of the
//! quantized profile, and the minimum-feature check against the writer.

use ndarray::{s, Array2, Zip};
use serde::{Deserialize, Serialize};

use crate::error::{Allowed, DataCause, Error, Result};
use crate::grid::{row_blocks, Grid, Unit};
use crate::rounding;

/// How heights are mapped onto levels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum QuantizeMethod {
    /// Nearest level.
    #[default]
    Round,
    /// Floyd-Steinberg error diffusion (Floyd & Steinberg 1976, Proc. SID 17(2)), serpentine
    /// scan: the local mean height follows the design more closely than rounding at the cost of
    /// high-frequency noise.
    FloydSteinberg,
}

/// Largest level count for 8-bit writers and the GDSII mask set.
pub const MAX_LEVELS_8BIT: usize = 256;
/// Level count of 16-bit writers.
pub const LEVELS_16BIT: usize = 65536;

/// Checks a level count: 2..=256, or 65536 for 16-bit writers.
pub fn check_level_count(n: usize) -> Result<()> {
    if (2..=MAX_LEVELS_8BIT).contains(&n) || n == LEVELS_16BIT {
        Ok(())
    } else {
        Err(Error::param(
            "level_count",
            format!("{n} is out of range: expected 2..=256, or 65536 for 16-bit writers"),
        ))
    }
}

/// A quantized map: levels `0..N-1` (the heights they stand for: [`Quantized::heights`]).
#[derive(Debug, Clone)]
pub struct Quantized {
    /// Level index per sample (`Unit::Level`).
    pub levels: Grid,
    /// Number of levels `N` per period.
    pub level_count: usize,
    /// Height of one full period (`p * h_2pi`), metres.
    pub period: f64,
    /// How the heights were mapped onto levels.
    pub method: QuantizeMethod,
    /// RMS of (quantized - design) over valid samples, phase-wrapped, metres.
    pub rms_error: f64,
}

impl Quantized {
    /// The heights the levels stand for, `level * period / N` metres (computed on each call).
    pub fn heights(&self) -> Result<Grid> {
        let n = self.level_count as f64;
        let period = self.period;
        let mut h = self.levels.values().clone();
        row_blocks::map_blocks_mut(&mut h, |_, mut b| b.mapv_inplace(|l| level_height(l, period, n)));
        self.levels.map_values(h, Unit::Metre)
    }
}

/// `l * period / n`. Where `n` is a power of two, dividing by it is an exact scaling, so the
/// product with `1 / n` has the same bits and spares a division.
#[inline]
fn level_height(l: f64, period: f64, n: f64) -> f64 {
    let x = l * period;
    if is_power_of_two(n) {
        x * (1.0 / n)
    } else {
        x / n
    }
}

/// Whether `n` (a level count) is a power of two.
#[inline]
fn is_power_of_two(n: f64) -> bool {
    n >= 1.0 && n.to_bits() & ((1u64 << 52) - 1) == 0
}

/// The level of a wrapped height by rounding: `round(h N / P) mod N`. The remainder is taken
/// only outside `[0, N)` (the top level `N` is phase-equivalent to 0), with the bits of `%`.
#[inline]
fn round_level(h: f64, period: f64, n: f64) -> f64 {
    let r = rounding::round(h / period * n);
    if r >= 0.0 && r < n {
        r
    } else if r == n {
        0.0
    } else {
        remainder(r, n)
    }
}

/// `r % n`, out of line: an inlined `%` may be evaluated on every sample even where its result
/// is not used (it is a library call).
#[cold]
#[inline(never)]
fn remainder(r: f64, n: f64) -> f64 {
    r % n
}

/// The squared phase-wrapped error `d^2` of quantized height `q` against height `h`:
/// `d = q - h` taken into `[-P/2, P/2]` by whole periods. Below a quarter period the wrap
/// cannot move `d` (`round(d / P)` is a signed zero) and is skipped.
#[inline]
fn wrapped_sq_error(q: f64, h: f64, period: f64) -> f64 {
    let d = q - h;
    let d = if d.abs() < 0.25 * period { d } else { d - rounding::round(d / period) * period };
    d * d
}

/// Quantizes wrapped heights (in `[0, period)`) to `level_count` levels.
///
/// Level `l` stands for height `l * period / N`. Rounding maps `h` to `round(h N / period)`;
/// the top level `N` is phase-equivalent to 0 and becomes 0. Runs in parallel over fixed row
/// blocks; the RMS error's squares are summed in row-major order within each block and the
/// block sums in block order, so its bits do not depend on the number of threads.
pub fn quantize(
    heights: &Grid,
    period: f64,
    level_count: usize,
    method: QuantizeMethod,
) -> Result<Quantized> {
    quantize_owned(heights.clone(), period, level_count, method)
}

/// [`quantize`] in the heights' own storage: each height becomes its level. A non-finite
/// height stays non-finite in place (NaN), so the error names the same samples as for the
/// input.
pub fn quantize_owned(
    mut heights: Grid,
    period: f64,
    level_count: usize,
    method: QuantizeMethod,
) -> Result<Quantized> {
    check_level_count(level_count)?;
    if heights.unit() != Unit::Metre {
        return Err(Error::param("heights", "expected heights in metres"));
    }
    if !(period > 0.0 && period.is_finite()) {
        return Err(Error::param_in(
            "period",
            Allowed::positive(),
            format!("must be positive, got {period}"),
        ));
    }
    let n = level_count as f64;
    let check_range = |range: Option<(f64, f64)>| match range {
        Some((lo, hi)) if lo < -1e-12 * period || hi > period * (1.0 + 1e-9) => Err(Error::data(
            DataCause::OutOfRange,
            format!(
                "quantization needs heights wrapped into [0, {:.4} um); got {:.4}..{:.4} um: wrap first",
                period * 1e6,
                lo * 1e6,
                hi * 1e6
            ),
        )),
        _ => Ok(()),
    };
    let sq = match method {
        QuantizeMethod::Round => {
            // One pass: the range of the valid heights, their levels in place (invalid samples
            // at 0) and the squared errors.
            let (values, mask) = heights.values_mut_and_mask();
            let start = (0.0, f64::INFINITY, f64::NEG_INFINITY);
            // Carried through a fold, not captured by a closure, so that they stay in registers.
            let one = |(sq, lo, hi): (f64, f64, f64), h: &mut f64| {
                let v = *h;
                let l = round_level(v, period, n);
                *h = l;
                // Compare and select; NaN is skipped as `f64::min` and `max` skip it.
                (
                    sq + wrapped_sq_error(level_height(l, period, n), v, period),
                    if v < lo { v } else { lo },
                    if v > hi { v } else { hi },
                )
            };
            let parts = row_blocks::map_blocks_mut(values, |r0, mut block| {
                match mask.map(|m| m.slice(s![r0..r0 + block.nrows(), ..])) {
                    None => block.iter_mut().fold(start, one),
                    Some(valid) => Zip::from(&mut block).and(&valid).fold(start, |a, h, &ok| {
                        if ok {
                            one(a, h)
                        } else {
                            *h = 0.0;
                            a
                        }
                    }),
                }
            });
            let (sq, lo, hi) = parts.into_iter().fold(start, |a, b| (a.0 + b.0, a.1.min(b.1), a.2.max(b.2)));
            check_range((lo <= hi).then_some((lo, hi)))?;
            sq
        }
        QuantizeMethod::FloydSteinberg => {
            let (range, finite) = heights.min_max_finite();
            check_range(range)?;
            if !finite {
                // Diffusion would spread a NaN to its neighbours.
                crate::fabrication::wrap::check_finite(&heights)?;
            }
            let levels = floyd_steinberg(&heights, period, n);
            // The squared errors summed as the rounding pass sums them.
            let values = heights.values();
            let parts = row_blocks::map_blocks(&levels, |r0, block| {
                let mut sq = 0.0;
                for ((i, j), &l) in block.indexed_iter() {
                    if heights.is_valid(r0 + i, j) {
                        sq += wrapped_sq_error(level_height(l, period, n), values[[r0 + i, j]], period);
                    }
                }
                sq
            });
            *heights.values_mut() = levels;
            parts.into_iter().sum()
        }
    };
    // Non-finite heights became NaN levels at the same samples.
    crate::fabrication::wrap::check_finite(&heights)?;
    let rms_error = (sq / heights.valid_count().max(1) as f64).sqrt();
    Ok(Quantized { levels: heights.into_unit(Unit::Level), level_count, period, method, rms_error })
}

/// The levels of Floyd-Steinberg error diffusion (serpentine scan, invalid samples skipped and
/// left at 0).
fn floyd_steinberg(heights: &Grid, period: f64, n: f64) -> Array2<f64> {
    let (nr, nc) = heights.dim();
    let mut levels = Array2::<f64>::zeros((nr, nc));
    let mut u = heights.values().mapv(|h| h / period * n);
    for i in 0..nr {
        let forward = i % 2 == 0;
        for k in 0..nc {
            let j = if forward { k } else { nc - 1 - k };
            if !heights.is_valid(i, j) {
                continue;
            }
            let q = u[[i, j]].round().clamp(0.0, n);
            let err = u[[i, j]] - q;
            levels[[i, j]] = q % n;
            let ahead = if forward { j + 1 } else { j.wrapping_sub(1) };
            let behind = if forward { j.wrapping_sub(1) } else { j + 1 };
            let mut push = |ii: usize, jj: usize, w: f64| {
                if ii < nr && jj < nc && heights.is_valid(ii, jj) {
                    u[[ii, jj]] += err * w;
                }
            };
            push(i, ahead, 7.0 / 16.0);
            push(i + 1, behind, 3.0 / 16.0);
            push(i + 1, j, 5.0 / 16.0);
            push(i + 1, ahead, 1.0 / 16.0);
        }
    }
    levels
}

/// Diffraction efficiency of order `m` of an N-level staircase approximation of a blazed
/// profile, illuminated with detuning `a` (Swanson 1989, MIT Lincoln Laboratory TR 854, eq. 8):
///
/// `eta_m = sinc^2(m / N) * [sin(pi (a - m)) / (N sin(pi (a - m) / N))]^2`, `sinc x = sin(pi x)/(pi x)`.
///
/// At `a = m = 1` this is `sinc^2(1/N)`: 0.405, 0.811, 0.950, 0.987 for N = 2, 4, 8, 16.
/// The bracket's removable singularities (where `(a - m)/N` is an integer) take their limit 1.
pub fn order_efficiency(level_count: usize, a: f64, m: i64) -> f64 {
    let n = level_count as f64;
    let m = m as f64;
    let sinc =
        |x: f64| if x == 0.0 { 1.0 } else { (std::f64::consts::PI * x).sin() / (std::f64::consts::PI * x) };
    let x = std::f64::consts::PI * (a - m) / n;
    let bracket = if x.sin().abs() < 1e-12 { 1.0 } else { (n * x).sin() / (n * x.sin()) };
    sinc(m / n).powi(2) * bracket * bracket
}

/// Diffraction efficiency of order `m` of the unquantized (continuous) blazed profile at
/// detuning `a`: `sinc^2(a - m)`, `sinc x = sin(pi x)/(pi x)`.
pub fn continuous_efficiency(a: f64, m: i64) -> f64 {
    let x = a - m as f64;
    if x == 0.0 {
        1.0
    } else {
        ((std::f64::consts::PI * x).sin() / (std::f64::consts::PI * x)).powi(2)
    }
}

/// Detuning of a wavelength relative to the design: `a = p lambda0 (n(lambda) - 1) / (lambda (n0 - 1))`.
pub fn detuning(order: u32, design_wavelength: f64, design_index: f64, wavelength: f64, index: f64) -> f64 {
    order as f64 * design_wavelength * (index - 1.0) / (wavelength * (design_index - 1.0))
}

/// Predicted efficiency of the design order at one wavelength.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct EfficiencyRow {
    /// Wavelength, metres.
    pub wavelength: f64,
    /// Refractive index there.
    pub index: f64,
    /// Detuning `a`.
    pub detuning: f64,
    /// Diffraction order evaluated (the design order p).
    pub order: i64,
    /// Efficiency of that order for the N-level profile.
    pub efficiency: f64,
    /// The same for the unquantized profile, `sinc^2(a - p)`, for comparison.
    pub continuous_efficiency: f64,
}

/// The efficiency table for `wavelengths` (the paper's RGB by default).
pub fn efficiency_table(
    spec: &crate::fabrication::wrap::WrapSpec,
    level_count: usize,
    wavelengths: &[f64],
) -> Result<Vec<EfficiencyRow>> {
    let n0 = spec.index()?;
    wavelengths
        .iter()
        .map(|&l| {
            let n = spec.material.index(l)?;
            let a = detuning(spec.order, spec.wavelength, n0, l, n);
            let m = spec.order as i64;
            Ok(EfficiencyRow {
                wavelength: l,
                index: n,
                detuning: a,
                order: m,
                efficiency: order_efficiency(level_count, a, m),
                continuous_efficiency: continuous_efficiency(a, m),
            })
        })
        .collect()
}

/// Wrapped height step per sample (fraction of a period) above which a design counts as
/// undersampled.
pub const UNDERSAMPLED_STEP: f64 = 0.4;

/// Local zone periods against the writer's minimum feature.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct FeatureStats {
    /// Smallest local zone period over the valid samples, metres (infinite for a flat map).
    pub min_zone_period: f64,
    /// Smallest zone period divided by N (by 1 for continuous profiles): the narrowest
    /// feature, metres.
    pub min_terrace_width: f64,
    /// The writer's minimum feature size, metres.
    pub min_feature: f64,
    /// Fraction of valid samples whose terrace width (zone period / N) is below `min_feature`.
    pub fraction_below: f64,
    /// Samples where the wrapped height step to a neighbour exceeds 0.4 of a period (phase
    /// step above 0.8 pi per sample): a real step (the aperture edge) or a design at or beyond
    /// its sampling limit. A step beyond pi aliases into a smaller one and cannot be told apart
    /// from the samples, so the check flags the approach to the limit. These samples have no
    /// meaningful local zone period and are left out of the estimate.
    pub step_samples: usize,
}

/// Estimates the local zone period `Lambda = P / |grad h|` from phase-wrapped central
/// differences (a difference is taken modulo `P` into `[-P/2, P/2)`, so the estimate works on
/// wrapped and unwrapped maps alike), and compares `Lambda / N` to `min_feature`. A 16-bit
/// (continuous) profile has no terraces: its narrowest feature is a whole zone, so there the
/// zone period itself is compared.
pub fn feature_check(heights: &Grid, period: f64, level_count: usize, min_feature: f64) -> FeatureStats {
    let steps_per_zone = if level_count == LEVELS_16BIT { 1 } else { level_count } as f64;
    let (nr, nc) = heights.dim();
    let v = heights.values();
    let [px, py] = heights.pitch();
    // A difference taken modulo the period into [-P/2, P/2]. Below a quarter period the
    // correction `round(d / P) P` is a signed zero and is skipped (only the sign of a zero
    // difference could change, and no figure depends on it).
    let wrapd = |d: f64| if d.abs() < 0.25 * period { d } else { d - rounding::round(d / period) * period };
    let zones = ZoneTally::new(period, [px, py], UNDERSAMPLED_STEP * period, steps_per_zone, min_feature);
    // Per row: smallest zone period, samples below the feature, steps, samples counted. The
    // minimum and the counts do not depend on how rows are split among threads.
    use rayon::prelude::*;
    let plain = if heights.mask().is_none() { v.as_slice() } else { None };
    let rows: Vec<(f64, usize, usize, usize)> = (0..nr)
        .into_par_iter()
        .map(|i| {
            let mut row_tally = zones.row();
            let mut counted = 0;
            match plain {
                Some(flat) => {
                    // Every sample valid, rows contiguous: the differences straight from the
                    // rows, each horizontal one used for both of its samples.
                    let row_at = |k: usize| &flat[k * nc..(k + 1) * nc];
                    let (row, up, down) =
                        (row_at(i), (i > 0).then(|| row_at(i - 1)), (i + 1 < nr).then(|| row_at(i + 1)));
                    match (up, down) {
                        // An interior row: every sample but the first and last has all four
                        // differences, passed as `Some` so that the inlined tally drops its
                        // checks for missing ones.
                        (Some(up), Some(down)) if nc >= 2 => {
                            let vert = |j: usize| (wrapd(row[j] - up[j]), wrapd(down[j] - row[j]));
                            let mut left = wrapd(row[1] - row[0]);
                            let (u, d) = vert(0);
                            row_tally.add(&zones, [None, Some(left), Some(u), Some(d)]);
                            for j in 1..nc - 1 {
                                let right = wrapd(row[j + 1] - row[j]);
                                let (u, d) = vert(j);
                                row_tally.add(&zones, [Some(left), Some(right), Some(u), Some(d)]);
                                left = right;
                            }
                            let (u, d) = vert(nc - 1);
                            row_tally.add(&zones, [Some(left), None, Some(u), Some(d)]);
                        }
                        _ => {
                            let mut left = None;
                            for j in 0..nc {
                                let right = (j + 1 < nc).then(|| wrapd(row[j + 1] - row[j]));
                                let u = up.map(|r| wrapd(row[j] - r[j]));
                                let d = down.map(|r| wrapd(r[j] - row[j]));
                                row_tally.add(&zones, [left, right, u, d]);
                                left = right;
                            }
                        }
                    }
                    counted = nc;
                }
                None => {
                    // The wrapped difference from sample `a` to `b` when both are valid.
                    let valid = |(i, j): (usize, usize)| heights.is_valid(i, j);
                    let diff = |a: (usize, usize), b: (usize, usize)| -> Option<f64> {
                        (valid(a) && valid(b)).then(|| wrapd(v[b] - v[a]))
                    };
                    for j in (0..nc).filter(|&j| valid((i, j))) {
                        counted += 1;
                        row_tally.add(
                            &zones,
                            [
                                (j > 0).then(|| diff((i, j - 1), (i, j))).flatten(),
                                (j + 1 < nc).then(|| diff((i, j), (i, j + 1))).flatten(),
                                (i > 0).then(|| diff((i - 1, j), (i, j))).flatten(),
                                (i + 1 < nr).then(|| diff((i, j), (i + 1, j))).flatten(),
                            ],
                        );
                    }
                }
            }
            (row_tally.min_period, row_tally.below, row_tally.steps, counted)
        })
        .collect();
    let (min_period, below, steps, counted) =
        rows.iter().fold((f64::INFINITY, 0, 0, 0), |a, r| (a.0.min(r.0), a.1 + r.1, a.2 + r.2, a.3 + r.3));
    FeatureStats {
        min_zone_period: min_period,
        min_terrace_width: min_period / steps_per_zone,
        min_feature,
        fraction_below: below as f64 / counted.max(1) as f64,
        step_samples: steps,
    }
}

/// The fixed parameters of [`feature_check`]'s per-sample evaluation.
///
/// A sample's local zone period is `lam = P / hypot(gx, gy)` with the mean gradients
/// `g = sum / (count * pitch)` of its wrapped differences; the report needs the smallest `lam`
/// and the count of `lam / N <= min_feature`. `hypot` is a library call and the means take
/// divisions, so each sample is first judged by the estimate `s = ex^2 + ey^2` of `hypot^2`
/// (means as products with reciprocals: a few ulp off, when the square neither overflows nor
/// underflows). Only a sample whose estimate lies within a relative margin of 1e-9 of a
/// decision threshold is evaluated exactly, so the figures are those of the exact formula.
struct ZoneTally {
    period: f64,
    pitch: [f64; 2],
    /// `1 / (count * pitch)` for counts 0 (unused), 1, 2, per axis.
    inv: [[f64; 3]; 2],
    limit: f64,
    steps_per_zone: f64,
    min_feature: f64,
    /// `s` above this: certainly below the minimum feature; below `below_lo`: certainly not.
    /// `None` when the thresholds cannot be formed (no positive finite minimum feature).
    below_range: Option<(f64, f64)>,
}

/// Relative margin around a threshold inside which a sample is evaluated exactly.
const ZONE_MARGIN: f64 = 1e-9;

/// One row's running figures of [`feature_check`].
struct RowTally {
    min_period: f64,
    /// Estimates `s` at or above this may reach `min_period` and are evaluated exactly.
    min_threshold: f64,
    below: usize,
    steps: usize,
}

impl ZoneTally {
    fn new(period: f64, pitch: [f64; 2], limit: f64, steps_per_zone: f64, min_feature: f64) -> Self {
        let inv = pitch.map(|p| [0.0, 1.0 / p, 1.0 / (2.0 * p)]);
        // lam / N <= f  <=>  hypot^2 >= (P / (N f))^2.
        let b = (period / (steps_per_zone * min_feature)).powi(2);
        let below_range = (b.is_normal() && min_feature > 0.0 && b < 1e280 && b > 1e-280)
            .then_some((b * (1.0 + ZONE_MARGIN), b * (1.0 - ZONE_MARGIN)));
        ZoneTally { period, pitch, inv, limit, steps_per_zone, min_feature, below_range }
    }

    fn row(&self) -> RowTally {
        RowTally { min_period: f64::INFINITY, min_threshold: 0.0, below: 0, steps: 0 }
    }

    /// The exact zone period of a sample (infinite where the surface is flat).
    #[cold]
    fn exact(&self, [left, right, up, down]: [Option<f64>; 4]) -> f64 {
        let mean = |a: Option<f64>, b: Option<f64>, step: f64| {
            let (n, sum) = [a, b].iter().flatten().fold((0, 0.0), |(n, s), d| (n + 1, s + d));
            if n == 0 {
                0.0
            } else {
                sum / (n as f64 * step)
            }
        };
        let grad = mean(left, right, self.pitch[0]).hypot(mean(up, down, self.pitch[1]));
        if grad > 0.0 {
            self.period / grad
        } else {
            f64::INFINITY
        }
    }
}

impl RowTally {
    /// Adds a sample given its wrapped differences to the left, right, up and down neighbours
    /// (`None` at the border or next to an invalid sample).
    #[inline(always)]
    fn add(&mut self, z: &ZoneTally, diffs: [Option<f64>; 4]) {
        if diffs.iter().flatten().any(|d| d.abs() > z.limit) {
            self.steps += 1;
            return;
        }
        // Per axis the sum of the differences and its reciprocal weight.
        let axis = |a: Option<f64>, b: Option<f64>, inv: &[f64; 3]| match (a, b) {
            (Some(a), Some(b)) => (a + b, inv[2]),
            (Some(a), None) | (None, Some(a)) => (a, inv[1]),
            (None, None) => (0.0, 0.0),
        };
        let ((sx, wx), (sy, wy)) = (axis(diffs[0], diffs[1], &z.inv[0]), axis(diffs[2], diffs[3], &z.inv[1]));
        if sx == 0.0 && sy == 0.0 {
            // Flat: the exact means are zero too, no zone period.
            return;
        }
        let (ex, ey) = (sx * wx, sy * wy);
        let s = ex * ex + ey * ey;
        let Some((hi, lo)) = z.below_range.filter(|_| s > 1e-280 && s < 1e280) else {
            self.exact(z, diffs);
            return;
        };
        if s >= self.min_threshold {
            self.new_min(z, z.exact(diffs));
        }
        let below = s > hi || (s >= lo && z.exact(diffs) / z.steps_per_zone <= z.min_feature);
        self.below += below as usize;
    }

    /// The exact path for a sample the estimate cannot judge.
    #[cold]
    fn exact(&mut self, z: &ZoneTally, diffs: [Option<f64>; 4]) {
        let lam = z.exact(diffs);
        self.new_min(z, lam);
        if lam / z.steps_per_zone <= z.min_feature {
            self.below += 1;
        }
    }

    /// Takes `lam` into the minimum and moves the threshold of estimates that may reach it:
    /// `lam <= m  <=>  hypot^2 >= (P / m)^2`.
    fn new_min(&mut self, z: &ZoneTally, lam: f64) {
        if lam < self.min_period {
            self.min_period = lam;
            let t = (z.period / lam).powi(2) * (1.0 - ZONE_MARGIN);
            // A threshold that cannot be formed sends every later sample to the exact path.
            self.min_threshold = if t.is_finite() { t } else { 0.0 };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn swanson_formula_gives_sinc_squared_at_the_design_wavelength() {
        let expect = [(2, 0.405), (4, 0.811), (8, 0.950), (16, 0.987)];
        for (n, e) in expect {
            let eta = order_efficiency(n, 1.0, 1);
            assert!((eta - e).abs() < 5e-4, "N={n}: {eta}");
            let s = (std::f64::consts::PI / n as f64).sin() / (std::f64::consts::PI / n as f64);
            assert!((eta - s * s).abs() < 1e-12);
        }
        // Binary 0/pi grating: orders +-1 carry 4/pi^2 each, order 0 and even orders nothing.
        let b = 4.0 / std::f64::consts::PI.powi(2);
        assert!((order_efficiency(2, 1.0, -1) - b).abs() < 1e-12);
        assert!(order_efficiency(2, 1.0, 0).abs() < 1e-12);
        assert!(order_efficiency(2, 1.0, 2).abs() < 1e-12);
    }

    /// Independent check: a direct Fourier series of one period of the N-level staircase
    /// with phase scaled by the detuning a.
    fn dft_efficiency(n: usize, a: f64, m: i64) -> f64 {
        let samples = n * 512;
        let (mut re, mut im) = (0.0, 0.0);
        for s in 0..samples {
            let x = (s as f64 + 0.5) / samples as f64;
            let level = (x * n as f64).floor();
            let phase =
                2.0 * std::f64::consts::PI * a * level / n as f64 - 2.0 * std::f64::consts::PI * m as f64 * x;
            re += phase.cos();
            im += phase.sin();
        }
        (re * re + im * im) / (samples as f64).powi(2)
    }

    #[test]
    fn swanson_formula_agrees_with_a_direct_fourier_series_under_detuning() {
        for n in [2, 3, 4, 8, 16] {
            for a in [0.83, 1.0, 1.17] {
                for m in [-1, 0, 1, 2] {
                    let f = order_efficiency(n, a, m);
                    let d = dft_efficiency(n, a, m);
                    assert!((f - d).abs() < 1e-4, "N={n} a={a} m={m}: {f} vs {d}");
                }
            }
        }
    }

    #[test]
    fn rounding_and_error_diffusion_keep_levels_in_range() {
        let p = 1.2e-6;
        let v = Array2::from_shape_fn((32, 40), |(i, j)| ((i * 40 + j) as f64 * 0.013e-6) % p);
        let g = Grid::new(v, [1e-6, 1e-6], Unit::Metre).unwrap();
        for method in [QuantizeMethod::Round, QuantizeMethod::FloydSteinberg] {
            let q = quantize(&g, p, 4, method).unwrap();
            assert!(q.levels.values().iter().all(|&l| l == l.round() && (0.0..4.0).contains(&l)));
            // Rounding error is at most half a step (wrapped), so rms <= step/2.
            assert!(q.rms_error <= p / 4.0 * 0.5 + 1e-15, "{method:?}: {}", q.rms_error);
        }
        // Rounding error of a uniform ramp is uniform in [-s/2, s/2]: rms = s / sqrt(12).
        let ramp = Array2::from_shape_fn((1, 100_000), |(_, j)| j as f64 / 100_000.0 * p);
        let q = quantize(&Grid::new(ramp, [1e-6, 1e-6], Unit::Metre).unwrap(), p, 8, QuantizeMethod::Round)
            .unwrap();
        let s = p / 8.0;
        assert!((q.rms_error - s / 12f64.sqrt()).abs() < 1e-3 * s);
    }

    #[test]
    fn error_diffusion_preserves_the_local_mean() {
        // A constant height between two levels: rounding puts everything on one level, error
        // diffusion mixes the two so that the mean is right.
        let p = 1.0e-6;
        let h = 0.3 * p / 4.0 + p / 4.0; // 1.3 steps
        let g = Grid::new(Array2::from_elem((64, 64), h), [1e-6, 1e-6], Unit::Metre).unwrap();
        let fs = quantize(&g, p, 4, QuantizeMethod::FloydSteinberg).unwrap();
        let mean = fs.levels.values().mean().unwrap();
        assert!((mean - 1.3).abs() < 0.01, "{mean}");
        let r = quantize(&g, p, 4, QuantizeMethod::Round).unwrap();
        assert_eq!(r.levels.values().mean().unwrap(), 1.0);
    }

    #[test]
    fn level_count_range_is_enforced() {
        for bad in [0, 1, 257, 1000, 65535] {
            assert!(check_level_count(bad).is_err(), "{bad}");
        }
        for good in [2, 3, 8, 256, 65536] {
            assert!(check_level_count(good).is_ok());
        }
        let g = Grid::new(Array2::from_elem((2, 2), 2e-6), [1e-6, 1e-6], Unit::Metre).unwrap();
        let e = quantize(&g, 1e-6, 4, QuantizeMethod::Round).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::OutOfRange, .. }), "{e:?}");
    }

    /// The feature check's figures straight from their definition (module docs of
    /// [`feature_check`]), every sample evaluated exactly.
    fn feature_reference(g: &Grid, period: f64, n: f64, min_feature: f64) -> (f64, usize, usize, usize) {
        let (nr, nc) = g.dim();
        let v = g.values();
        let wrapd = |d: f64| d - (d / period).round() * period;
        let diff = |a: (usize, usize), b: (usize, usize)| {
            (g.is_valid(a.0, a.1) && g.is_valid(b.0, b.1)).then(|| wrapd(v[b] - v[a]))
        };
        let (mut min, mut below, mut steps, mut counted) = (f64::INFINITY, 0, 0, 0);
        for i in (0..nr).filter(|&i| (0..nc).any(|j| g.is_valid(i, j))) {
            for j in (0..nc).filter(|&j| g.is_valid(i, j)) {
                counted += 1;
                let h = [
                    (j > 0).then(|| diff((i, j - 1), (i, j))),
                    (j + 1 < nc).then(|| diff((i, j), (i, j + 1))),
                ];
                let w = [
                    (i > 0).then(|| diff((i - 1, j), (i, j))),
                    (i + 1 < nr).then(|| diff((i, j), (i + 1, j))),
                ];
                let (h, w): (Vec<f64>, Vec<f64>) = (
                    h.into_iter().flatten().flatten().collect(),
                    w.into_iter().flatten().flatten().collect(),
                );
                if h.iter().chain(&w).any(|d| d.abs() > UNDERSAMPLED_STEP * period) {
                    steps += 1;
                    continue;
                }
                let mean = |d: &[f64], pitch: f64| {
                    if d.is_empty() {
                        0.0
                    } else {
                        d.iter().sum::<f64>() / (d.len() as f64 * pitch)
                    }
                };
                let grad = mean(&h, g.pitch()[0]).hypot(mean(&w, g.pitch()[1]));
                let lam = if grad > 0.0 { period / grad } else { f64::INFINITY };
                min = min.min(lam);
                below += (lam / n <= min_feature) as usize;
            }
        }
        (min, below, steps, counted)
    }

    #[test]
    fn feature_check_equals_its_definition_evaluated_at_every_sample() {
        // A wrapped diffractive lens (zone periods from 70 um at the centre to a few um at
        // the corners, where the steps pass 0.4 of a period), dx != dy, with and without a
        // mask of non-measured samples.
        let p = 1.2e-6;
        let (nr, nc) = (61, 83);
        let v = Array2::from_shape_fn((nr, nc), |(i, j)| {
            let (x, y) = ((j as f64 - 40.0) * 1.1e-6, (i as f64 - 30.0) * 0.9e-6);
            ((x * x + y * y) * 2.6e5 + 1e-9 * ((i * 7 + j * 3) % 5) as f64).rem_euclid(p)
        });
        let plain = Grid::new(v, [1.1e-6, 0.9e-6], Unit::Metre).unwrap();
        let valid = Array2::from_shape_fn((nr, nc), |(i, j)| (i * 13 + j * 7) % 17 != 0);
        let masked = plain.clone().with_mask(valid).unwrap();
        for g in [&plain, &masked] {
            for (n, f) in [(8usize, 0.8e-6), (8, 1.5e-6), (16, 0.3e-6), (LEVELS_16BIT, 5e-6)] {
                let per_zone = if n == LEVELS_16BIT { 1.0 } else { n as f64 };
                let r = feature_check(g, p, n, f);
                let (min, below, steps, counted) = feature_reference(g, p, per_zone, f);
                assert_eq!(r.min_zone_period, min, "N {n}, f {f}");
                assert_eq!(r.fraction_below, below as f64 / counted as f64, "N {n}, f {f}");
                assert_eq!(r.step_samples, steps, "N {n}, f {f}");
                assert!(
                    below > 0 && below < counted && steps > 0 || n == LEVELS_16BIT,
                    "N {n}: {below} {steps}"
                );
            }
        }
    }

    #[test]
    fn zone_period_of_a_linear_blazed_grating() {
        // Heights rising by one period every 20 um, wrapped: zone period 20 um everywhere.
        let p = 1.2e-6;
        let v = Array2::from_shape_fn((8, 100), |(_, j)| (j as f64 * 1e-6 / 20e-6 * p) % p);
        let g = Grid::new(v, [1e-6, 1e-6], Unit::Metre).unwrap();
        let r = feature_check(&g, p, 8, 2e-6);
        assert!((r.min_zone_period - 20e-6).abs() < 1e-9, "{}", r.min_zone_period);
        assert!((r.min_terrace_width - 2.5e-6).abs() < 1e-9);
        assert_eq!(r.fraction_below, 0.0);
        let r = feature_check(&g, p, 16, 2e-6);
        assert_eq!(r.fraction_below, 1.0);
        assert_eq!(r.step_samples, 0);
        // A continuous (16-bit) profile's narrowest feature is the whole 20 um zone.
        let r = feature_check(&g, p, LEVELS_16BIT, 2e-6);
        assert!((r.min_terrace_width - 20e-6).abs() < 1e-9 && r.fraction_below == 0.0);
        // Steps of 0.45 of a period per sample are flagged, 0.35 are not.
        for (step, flagged) in [(0.45, true), (0.35, false)] {
            let v = Array2::from_shape_fn((4, 50), |(_, j)| (j as f64 * step * p) % p);
            let r = feature_check(&Grid::new(v, [1e-6, 1e-6], Unit::Metre).unwrap(), p, 8, 1e-6);
            assert_eq!(r.step_samples > 0, flagged, "step {step}");
        }
    }
}
