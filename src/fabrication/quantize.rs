//! Quantization of wrapped heights to N levels, the predicted diffraction efficiency of the
//! quantized profile, and the minimum-feature check against the writer.

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::grid::{Grid, Unit};

/// How heights are mapped onto levels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default, clap::ValueEnum)]
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

/// A quantized map: levels `0..N-1` and the heights they stand for.
#[derive(Debug, Clone)]
pub struct Quantized {
    /// Level index per sample (`Unit::Level`).
    pub levels: Grid,
    /// `level * period / N`, metres.
    pub heights: Grid,
    pub level_count: usize,
    /// Height of one full period (`p * h_2pi`), metres.
    pub period: f64,
    pub method: QuantizeMethod,
    /// RMS of (quantized - design) over valid samples, phase-wrapped, metres.
    pub rms_error: f64,
}

/// Quantizes wrapped heights (in `[0, period)`) to `level_count` levels.
///
/// Level `l` stands for height `l * period / N`. Rounding maps `h` to `round(h N / period)`;
/// the top level `N` is phase-equivalent to 0 and becomes 0.
pub fn quantize(
    heights: &Grid,
    period: f64,
    level_count: usize,
    method: QuantizeMethod,
) -> Result<Quantized> {
    check_level_count(level_count)?;
    if heights.unit() != Unit::Metre {
        return Err(Error::param("heights", "expected heights in metres"));
    }
    if !(period > 0.0 && period.is_finite()) {
        return Err(Error::param("period", format!("must be positive, got {period}")));
    }
    if let Some((lo, hi)) = heights.min_max() {
        if lo < -1e-12 * period || hi > period * (1.0 + 1e-9) {
            return Err(Error::Data(format!(
                "quantization needs heights wrapped into [0, {:.4} um); got {:.4}..{:.4} um: wrap first",
                period * 1e6,
                lo * 1e6,
                hi * 1e6
            )));
        }
    }
    crate::fabrication::wrap::check_finite(heights)?;
    let n = level_count as f64;
    let (nr, nc) = heights.dim();
    let mut levels = Array2::<f64>::zeros((nr, nc));
    match method {
        QuantizeMethod::Round => {
            for ((i, j), l) in levels.indexed_iter_mut() {
                if heights.is_valid(i, j) {
                    *l = (heights.values()[[i, j]] / period * n).round() % n;
                }
            }
        }
        QuantizeMethod::FloydSteinberg => {
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
        }
    }
    let qh = levels.mapv(|l| l * period / n);
    let mut sq = 0.0;
    for ((i, j), &q) in qh.indexed_iter() {
        if heights.is_valid(i, j) {
            let d = q - heights.values()[[i, j]];
            let d = d - (d / period).round() * period;
            sq += d * d;
        }
    }
    let rms_error = (sq / heights.valid_count().max(1) as f64).sqrt();
    Ok(Quantized {
        levels: heights.map_values(levels, Unit::Level)?,
        heights: heights.map_values(qh, Unit::Metre)?,
        level_count,
        period,
        method,
        rms_error,
    })
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
pub struct FeatureReport {
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
pub fn feature_check(heights: &Grid, period: f64, level_count: usize, min_feature: f64) -> FeatureReport {
    let steps_per_zone = if level_count == LEVELS_16BIT { 1 } else { level_count } as f64;
    let (nr, nc) = heights.dim();
    let v = heights.values();
    let [px, py] = heights.pitch();
    let wrapd = |d: f64| d - (d / period).round() * period;
    let limit = UNDERSAMPLED_STEP * period;
    // Per row: smallest zone period, samples below the feature, steps, samples counted. The
    // minimum and the counts do not depend on how rows are split among threads.
    use rayon::prelude::*;
    let rows: Vec<(f64, usize, usize, usize)> = (0..nr)
        .into_par_iter()
        .map(|i| {
            let (mut min_period, mut below, mut steps, mut counted) = (f64::INFINITY, 0, 0, 0);
            // The wrapped difference from sample `a` to `b` when both are valid.
            let diff = |a: (usize, usize), b: (usize, usize)| -> Option<f64> {
                (heights.is_valid(a.0, a.1) && heights.is_valid(b.0, b.1)).then(|| wrapd(v[b] - v[a]))
            };
            for j in 0..nc {
                if !heights.is_valid(i, j) {
                    continue;
                }
                // One-sided differences at the border, central inside.
                let gx = [
                    (j > 0).then(|| diff((i, j - 1), (i, j))).flatten(),
                    (j + 1 < nc).then(|| diff((i, j), (i, j + 1))).flatten(),
                ];
                let gy = [
                    (i > 0).then(|| diff((i - 1, j), (i, j))).flatten(),
                    (i + 1 < nr).then(|| diff((i, j), (i + 1, j))).flatten(),
                ];
                counted += 1;
                if gx.iter().chain(&gy).flatten().any(|d| d.abs() > limit) {
                    steps += 1;
                    continue;
                }
                let mean = |g: &[Option<f64>; 2], step: f64| {
                    let n = g.iter().flatten().count();
                    if n == 0 {
                        0.0
                    } else {
                        g.iter().flatten().sum::<f64>() / (n as f64 * step)
                    }
                };
                let grad = mean(&gx, px).hypot(mean(&gy, py));
                if grad > 0.0 {
                    let lam = period / grad;
                    min_period = min_period.min(lam);
                    if lam / steps_per_zone <= min_feature {
                        below += 1;
                    }
                }
            }
            (min_period, below, steps, counted)
        })
        .collect();
    let (min_period, below, steps, counted) =
        rows.iter().fold((f64::INFINITY, 0, 0, 0), |a, r| (a.0.min(r.0), a.1 + r.1, a.2 + r.2, a.3 + r.3));
    FeatureReport {
        min_zone_period: min_period,
        min_terrace_width: min_period / steps_per_zone,
        min_feature,
        fraction_below: below as f64 / counted.max(1) as f64,
        step_samples: steps,
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
        assert!(quantize(&g, 1e-6, 4, QuantizeMethod::Round).unwrap_err().to_string().contains("wrap first"));
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
