//! Phase wrapping and replica inversion.
//!
//! A height `h` of material with index `n0` at the design wavelength `lambda0` delays the
//! phase by `phi = 2 pi / lambda0 * (n0 - 1) * h`. Wrapping `phi` modulo `p * 2 pi` (p = 1 for
//! an ordinary DOE, p > 1 for a multi-order DOE, Sweeney & Sommargren 1995) leaves the design
//! wavelength's field unchanged and gives heights in `[0, p * h_2pi)`, `h_2pi = lambda0 / (n0 - 1)`.
//!
//! The paper's DOE is a PDMS cast of a lithographic master, so the cast is the height
//! complement of the master, mirrored. [`to_master`] produces the master whose cast equals the
//! design: `master(x, y) = (P - design(-x, y)) mod P`, with `P = p * h_2pi`.

use serde::{Deserialize, Serialize};

use ndarray::{s, Zip};

use crate::error::{Allowed, DataCause, Error, Result};
use crate::grid::{row_blocks, Grid, Unit};
use crate::material::Material;
use crate::rounding;

/// Design wavelength, material and multi-order factor of the wrap.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct WrapSpec {
    /// Design wavelength, metres.
    pub wavelength: f64,
    /// Material of the part (its index sets `h_2pi`).
    pub material: Material,
    /// Multi-order factor p >= 1: wrap modulo p * 2 pi.
    pub order: u32,
}

impl Default for WrapSpec {
    /// The paper's green channel in PDMS, single order.
    fn default() -> Self {
        WrapSpec { wavelength: 530e-9, material: Material::pdms(), order: 1 }
    }
}

impl WrapSpec {
    /// Refractive index at the design wavelength.
    pub fn index(&self) -> Result<f64> {
        self.material.index(self.wavelength)
    }
    /// The wrap period `P = p * lambda0 / (n0 - 1)`, metres.
    pub fn period(&self) -> Result<f64> {
        if self.order == 0 {
            return Err(Error::param_in(
                "order",
                Allowed::at_least(1.0),
                "the multi-order factor p must be at least 1",
            ));
        }
        Ok(self.order as f64 * self.material.height_2pi(self.wavelength)?)
    }
}

/// What wrapping did.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct WrapStats {
    /// Wrap period `p * h_2pi`, metres.
    pub period: f64,
    /// Index at the design wavelength.
    pub index: f64,
    /// Samples whose height changed (moved down by one or more periods, or up from below 0).
    pub wrapped_samples: usize,
    /// The largest number of periods removed from any sample.
    pub max_wraps: i64,
    /// Largest input height, metres.
    pub input_max_height: f64,
    /// Largest output height, metres (< period).
    pub max_height: f64,
}

/// Wraps heights modulo the period of `spec`. The input must hold heights in metres with no
/// non-finite valid samples. Invalid samples stay invalid.
///
/// A valid height `h` becomes `w = h - k P` with `k = floor(h / P)`; rounding can put `w` at
/// exactly `P` (taken down to 0, phase-equivalent) or a hair below 0 (clamped to 0). Computed
/// in parallel over row blocks; every figure of the report is a count or an extremum, the same
/// however the rows are split.
pub fn wrap(heights: &Grid, spec: &WrapSpec) -> Result<(Grid, WrapStats)> {
    wrap_owned(heights.clone(), spec)
}

/// [`wrap`] computed in the heights' own storage. A non-finite height stays non-finite in
/// place (NaN), so the error names the same samples as for the input.
pub fn wrap_owned(heights: Grid, spec: &WrapSpec) -> Result<(Grid, WrapStats)> {
    wrap_in_place(heights, spec, false)
}

/// [`wrap`] then [`into_master`] in one pass over the heights' own storage: each block of rows
/// wrapped, complemented and reversed while it is in cache (the same bits as the two passes;
/// the wrapped heights lie in `[0, P)`, so the master's range check cannot fail).
pub fn wrap_to_master_owned(heights: Grid, spec: &WrapSpec) -> Result<(Grid, WrapStats)> {
    wrap_in_place(heights, spec, true)
}

fn wrap_in_place(mut heights: Grid, spec: &WrapSpec, master: bool) -> Result<(Grid, WrapStats)> {
    if heights.unit() != Unit::Metre {
        return Err(Error::param(
            "heights",
            format!("expected heights in m, got {}", heights.unit().symbol()),
        ));
    }
    let period = match spec.period() {
        Ok(p) => p,
        Err(e) => {
            check_finite(&heights)?;
            return Err(e);
        }
    };
    let (values, mask) = heights.values_mut_and_mask();
    // Per block: wrapped samples, most periods removed, largest output and input heights,
    // whether every valid height is finite.
    // The figures are carried through a fold, not captured by a closure, so that they stay
    // in registers.
    type Figures = (usize, i64, f64, f64, bool);
    let start: Figures = (0, 0, 0.0, f64::NEG_INFINITY, true);
    let one = |(mut wrapped, mut max_wraps, max_height, input_max, mut finite): Figures, h: &mut f64| {
        let v = *h;
        // Inside (0, P) the quotient v / P rounds below 1 (it is at most 1 - 2^-53), so k = 0
        // and w = v: the division is skipped. Zero takes the general path, which turns -0
        // into +0.
        let w = if v > 0.0 && v < period {
            v
        } else {
            let k = rounding::floor(v / period);
            let mut w = v - k * period;
            if w >= period {
                w -= period;
            }
            if w < 0.0 {
                w = 0.0;
            }
            if k != 0.0 {
                wrapped += 1;
                max_wraps = max_wraps.max(k.abs() as i64);
            }
            finite &= v.is_finite();
            w
        };
        *h = w;
        // Compare and select: NaN is skipped as `f64::max` skips it.
        (
            wrapped,
            max_wraps,
            if w > max_height { w } else { max_height },
            if v > input_max { v } else { input_max },
            finite,
        )
    };
    let parts = row_blocks::map_blocks_mut(values, |r0, mut block| {
        let figures = match mask.map(|m| m.slice(s![r0..r0 + block.nrows(), ..])) {
            None => block.iter_mut().fold(start, one),
            // Invalid samples keep their stored value (0).
            Some(valid) => {
                Zip::from(&mut block).and(&valid).fold(start, |a, h, &ok| if ok { one(a, h) } else { a })
            }
        };
        if master {
            for mut row in block.rows_mut() {
                row.mapv_inplace(|h| complement(h, period));
                reverse(row);
            }
        }
        figures
    });
    let (wrapped_samples, max_wraps, max_height, input_max, finite) = parts
        .into_iter()
        .fold(start, |a, b| (a.0 + b.0, a.1.max(b.1), a.2.max(b.2), a.3.max(b.3), a.4 && b.4));
    // The mask follows the mirrored values.
    let heights = if master { heights.into_mirrored_mask(true, false) } else { heights };
    if !finite {
        // Named where the input has them: the master's columns turned back.
        let input_order = if master { heights.into_mirrored(true, false) } else { heights };
        check_finite(&input_order)?;
        return Err(Error::data(DataCause::NotFinite, "non-finite heights"));
    }
    // No valid sample: the largest input height is reported as 0.
    let input_max_height = if input_max == f64::NEG_INFINITY { 0.0 } else { input_max };
    let report =
        WrapStats { period, index: spec.index()?, wrapped_samples, max_wraps, input_max_height, max_height };
    Ok((heights, report))
}

/// The master's height over a wrapped height `h`: `P - h`, or 0 where that is `P`.
#[inline]
fn complement(h: f64, period: f64) -> f64 {
    let c = period - h;
    if c >= period {
        c - period
    } else {
        c
    }
}

/// Reverses a row in place (the mirror in x).
fn reverse(mut row: ndarray::ArrayViewMut1<'_, f64>) {
    if let Some(r) = row.as_slice_mut() {
        r.reverse();
    } else {
        let n = row.len();
        for j in 0..n / 2 {
            row.swap(j, n - 1 - j);
        }
    }
}

/// The master whose PDMS cast equals `design`: complement modulo `period` and mirror in x.
/// `design` must already be wrapped into `[0, period)`.
pub fn to_master(design: &Grid, period: f64) -> Result<Grid> {
    into_master(design.clone(), period)
}

/// [`to_master`] computed in `design`'s own storage: each height `h` becomes `P - h`, or 0
/// where that is `P`, then the columns are reversed.
pub fn into_master(mut design: Grid, period: f64) -> Result<Grid> {
    // One pass over the rows: the range of the valid heights, the complement, the reversal.
    // On a range error the grid (consumed) is dropped half-changed.
    let mask = design.mask().cloned();
    let start = (f64::INFINITY, f64::NEG_INFINITY);
    let parts = row_blocks::map_blocks_mut(design.values_mut(), |r0, mut block| {
        let (mut lo, mut hi) = start;
        for (k, mut row) in block.rows_mut().into_iter().enumerate() {
            let valid = mask.as_ref().map(|m| m.row(r0 + k));
            for (j, h) in row.iter_mut().enumerate() {
                if valid.as_ref().is_none_or(|m| m[j]) {
                    lo = lo.min(*h);
                    hi = hi.max(*h);
                }
                *h = complement(*h, period);
            }
            reverse(row);
        }
        (lo, hi)
    });
    let (lo, hi) = parts.into_iter().fold(start, |a, b| (a.0.min(b.0), a.1.max(b.1)));
    if lo <= hi && (lo < 0.0 || hi >= period * (1.0 + 1e-12)) {
        return Err(Error::data(
            DataCause::OutOfRange,
            format!(
                "replica inversion needs wrapped heights in [0, {:.4} um), got {:.4}..{:.4} um",
                period * 1e6,
                lo * 1e6,
                hi * 1e6
            ),
        ));
    }
    Ok(design.into_mirrored_mask(true, false))
}

/// The cast of the master that [`to_master`] makes of wrapped heights `w`, in the design frame:
/// `P - master(-x, y)`, a cast being its master's plain complement, mirrored. It is `w` where
/// `w > 0` and the full period where `w = 0` (the master is 0 there, not `P`): heights in
/// `(0, P]`, phase-equivalent to `w` at the design wavelength but not linear in it.
pub fn cast_of_master(wrapped: &Grid, period: f64) -> Result<Grid> {
    let master = to_master(wrapped, period)?;
    let cast = master.values().mapv(|m| period - m);
    Ok(master.map_values(cast, Unit::Metre)?.mirror(true, false))
}

/// Refuses non-finite valid samples with their count and first location.
pub fn check_finite(g: &Grid) -> Result<()> {
    match g.non_finite() {
        None => Ok(()),
        Some((count, (i, j))) => Err(Error::data(
            DataCause::NotFinite,
            format!(
                "{count} height values are NaN or infinite (first at row {i}, column {j}); \
             set `fill` to fill them from their neighbours"
            ),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn wrap_to_master_in_one_pass_equals_wrap_then_master() {
        let spec = WrapSpec::default();
        let p = spec.period().unwrap();
        // Heights over several periods, negative ones, exact multiples, dx != dy, and a mask.
        let v = Array2::from_shape_fn((37, 29), |(i, j)| {
            (i as f64 * 0.173 - j as f64 * 0.091) * p + (i * j % 3) as f64 * p
        });
        let valid = Array2::from_shape_fn((37, 29), |(i, j)| (i * 7 + j * 3) % 11 != 0);
        let plain = Grid::new(v, [1e-6, 2e-6], Unit::Metre).unwrap();
        for g in [plain.clone(), plain.with_mask(valid).unwrap()] {
            let (w, r) = wrap(&g, &spec).unwrap();
            let two = into_master(w, p).unwrap();
            let (one, r1) = wrap_to_master_owned(g.clone(), &spec).unwrap();
            assert_eq!(r1, r);
            assert_eq!(one.mask(), two.mask());
            assert!(one.values().iter().zip(two.values()).all(|(a, b)| a.to_bits() == b.to_bits()));
        }
        // A non-finite height is named where the input has it.
        let mut v = Array2::from_elem((3, 5), 0.5 * p);
        v[[1, 1]] = f64::NAN;
        let e = wrap_to_master_owned(Grid::new(v, [1e-6, 1e-6], Unit::Metre).unwrap(), &spec).unwrap_err();
        assert!(
            matches!(e, Error::Data { cause: DataCause::NotFinite, .. })
                && e.to_string().contains("row 1, column 1"),
            "{e:?}"
        );
    }

    fn grid(v: Array2<f64>) -> Grid {
        Grid::new(v, [1e-6, 1e-6], Unit::Metre).unwrap()
    }

    #[test]
    fn wrap_preserves_phase_and_counts_wraps() {
        let spec = WrapSpec::default();
        let p = spec.period().unwrap();
        // h_2pi = 530 nm / 0.4349.
        assert!((p - 530e-9 / 0.4349).abs() < 1e-15);
        let v = Array2::from_shape_fn((1, 50), |(_, j)| j as f64 * 0.1 * p - 0.3 * p);
        let (w, r) = wrap(&grid(v.clone()), &spec).unwrap();
        for (a, b) in v.iter().zip(w.values()) {
            assert!(*b >= 0.0 && *b < p);
            let k = (a - b) / p;
            assert!((k - k.round()).abs() < 1e-9, "wrap changed the phase");
        }
        assert_eq!(r.max_wraps, 4);
        // Samples below 0 (j = 0..3) and at or above one period (j = 13..50; j = 13 sits on the edge).
        assert!((39..=40).contains(&r.wrapped_samples), "{}", r.wrapped_samples);
        assert!(r.max_height < p);
    }

    #[test]
    fn multi_order_wrap_uses_p_periods() {
        let spec = WrapSpec { order: 3, ..Default::default() };
        let h2pi = WrapSpec::default().period().unwrap();
        let v = Array2::from_elem((2, 2), 2.5 * h2pi);
        let (w, r) = wrap(&grid(v), &spec).unwrap();
        assert_eq!(r.wrapped_samples, 0);
        assert!((w.values()[[0, 0]] - 2.5 * h2pi).abs() < 1e-18);
        assert!(wrap(&grid(Array2::zeros((1, 1))), &WrapSpec { order: 0, ..Default::default() }).is_err());
    }

    #[test]
    fn master_cast_gives_back_the_design() {
        let p = 1.2e-6;
        let v = Array2::from_shape_fn((3, 4), |(i, j)| ((i * 4 + j) as f64 * 0.09e-6) % p);
        let d = grid(v);
        let m = to_master(&d, p).unwrap();
        // Casting: complement and mirror again.
        let cast = to_master(&m, p).unwrap();
        for (a, b) in cast.values().iter().zip(d.values()) {
            assert!((a - b).abs() < 1e-15 || (a - b).abs() > p * 0.999, "{a} {b}");
        }
        assert_eq!(m.values()[[0, 2]], p - d.values()[[0, 1]]);
        assert_eq!(m.values()[[0, 3]], 0.0, "a zero height complements to a full period, i.e. 0");
        assert!(to_master(&grid(Array2::from_elem((1, 1), 2.0 * p)), p).is_err());
    }

    /// The cast of the master is the wrapped design where it is above 0 and the full period
    /// where it is 0: the master there is 0 (its complement modulo the period), and the cast is
    /// the master's plain complement.
    #[test]
    fn the_cast_of_the_master_lifts_zero_heights_to_the_period() {
        let p = 1.2e-6;
        let v = Array2::from_shape_fn((3, 5), |(i, j)| ((i * 5 + j) % 6) as f64 * 0.2e-6);
        let w = grid(v);
        let cast = cast_of_master(&w, p).unwrap();
        let master = to_master(&w, p).unwrap();
        for ((i, j), &h) in w.values().indexed_iter() {
            let c = cast.values()[[i, j]];
            let want = if h == 0.0 { p } else { h };
            assert!((c - want).abs() < 1e-18, "({i}, {j}): {c} vs {want}");
            // The master, mirrored back, plus the cast is the period everywhere.
            assert!((master.values()[[i, 4 - j]] + c - p).abs() < 1e-18);
        }
    }

    #[test]
    fn non_finite_heights_are_refused_with_location_or_filled() {
        let mut v = Array2::from_shape_fn((5, 5), |(i, j)| (i + j) as f64 * 1e-8);
        v[[2, 3]] = f64::NAN;
        v[[4, 1]] = f64::INFINITY;
        let g = grid(v);
        let e = wrap(&g, &WrapSpec::default()).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::NotFinite, .. }), "{e:?}");
        let e = e.to_string();
        assert!(e.contains("2 height values") && e.contains("row 2, column 3"), "{e}");
        let (f, n) = crate::grid::fill::fill_missing(&g).unwrap();
        assert_eq!(n, 2);
        // A linear field is harmonic: the Laplace fill restores it.
        assert!((f.values()[[2, 3]] - 5e-8).abs() < 1e-12);
        assert!(wrap(&f, &WrapSpec::default()).is_ok());
    }
}
