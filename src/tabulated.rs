//! Two-column tables (CSV with the unit in the column name) and their monotone interpolation,
//! shared by resist contrast curves and measured refractive-index tables.
//!
//! Interpolation is the piecewise-cubic Hermite scheme of Fritsch & Carlson (SIAM J. Numer.
//! Anal. 17(2), 238-246, 1980) with the slopes of Fritsch & Butland (1984): the weighted
//! harmonic mean of the neighbouring secants where they agree in sign, else 0, and one-sided
//! three-point end slopes limited to keep the shape, as SciPy's `PchipInterpolator`. It never
//! overshoots the data: monotone data give a monotone curve.

use std::path::Path;

use crate::error::{Error, Result};
use crate::units::length_unit;

/// PCHIP slopes at the points `(x, y)`; `x` strictly increasing, at least 2 points.
pub fn pchip_slopes(x: &[f64], y: &[f64]) -> Vec<f64> {
    let n = x.len();
    let h: Vec<f64> = x.windows(2).map(|w| w[1] - w[0]).collect();
    let d: Vec<f64> = (0..n - 1).map(|k| (y[k + 1] - y[k]) / h[k]).collect();
    if n == 2 {
        return vec![d[0], d[0]];
    }
    let mut m = vec![0.0; n];
    for k in 1..n - 1 {
        if d[k - 1] * d[k] > 0.0 {
            let (w1, w2) = (2.0 * h[k] + h[k - 1], h[k] + 2.0 * h[k - 1]);
            m[k] = (w1 + w2) / (w1 / d[k - 1] + w2 / d[k]);
        }
    }
    let end = |h0: f64, h1: f64, d0: f64, d1: f64| {
        let s = ((2.0 * h0 + h1) * d0 - h0 * d1) / (h0 + h1);
        if s * d0 <= 0.0 {
            0.0
        } else if d0 * d1 < 0.0 && s.abs() > 3.0 * d0.abs() {
            3.0 * d0
        } else {
            s
        }
    };
    m[0] = end(h[0], h[1], d[0], d[1]);
    m[n - 1] = end(h[n - 2], h[n - 3], d[n - 2], d[n - 3]);
    m
}

/// The cubic Hermite interpolant through `(x, y)` with slopes `m`, at `t` clamped to the range.
pub fn hermite(x: &[f64], y: &[f64], m: &[f64], t: f64) -> f64 {
    let n = x.len();
    let t = t.clamp(x[0], x[n - 1]);
    let k = match x.partition_point(|&v| v <= t) {
        0 => 0,
        p => (p - 1).min(n - 2),
    };
    let h = x[k + 1] - x[k];
    let s = (t - x[k]) / h;
    let (s2, s3) = (s * s, s * s * s);
    (2.0 * s3 - 3.0 * s2 + 1.0) * y[k]
        + (s3 - 2.0 * s2 + s) * h * m[k]
        + (-2.0 * s3 + 3.0 * s2) * y[k + 1]
        + (s3 - s2) * h * m[k + 1]
}

/// A two-column CSV: the header's column names (lower case) and the numeric rows with their
/// 1-based line numbers.
pub struct TwoColumns {
    /// The two column names, trimmed and in lower case, as the header spells them.
    pub header: [String; 2],
    /// `(line, first, second)` per data row: the 1-based line number in the file and the two
    /// finite values, in the columns' own units.
    pub rows: Vec<(usize, f64, f64)>,
}

/// Reads a two-column CSV: blank lines and `#` comments skipped, then a header, then rows of two
/// numbers. `expected` describes the header in error messages (e.g. "dose,depth_nm").
pub fn read_two_columns(path: &Path, expected: &str) -> Result<TwoColumns> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    parse_two_columns(path, &text, expected)
}

/// Parses the text of a two-column CSV (see [`read_two_columns`]); `path` names it in errors.
pub fn parse_two_columns(path: &Path, text: &str, expected: &str) -> Result<TwoColumns> {
    let mut lines =
        text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    let Some((hl, header)) = lines.next() else {
        return Err(Error::malformed(path, format!("empty table (expected a header '{expected}')")));
    };
    let cols: Vec<String> = header.split(',').map(|c| c.trim().to_ascii_lowercase()).collect();
    if cols.len() != 2 {
        return Err(Error::malformed(
            path,
            format!("line {}: header must be '{expected}', got '{header}'", hl + 1),
        ));
    }
    let mut rows = Vec::new();
    for (ln, line) in lines {
        let f: Vec<&str> = line.split(',').map(str::trim).collect();
        if f.len() != 2 {
            return Err(Error::malformed(
                path,
                format!("line {}: expected 2 fields, got {}", ln + 1, f.len()),
            ));
        }
        let num = |s: &str, col: &str| {
            s.parse::<f64>().ok().filter(|v| v.is_finite()).ok_or_else(|| {
                Error::malformed(path, format!("line {}: {col} '{s}' is not a number", ln + 1))
            })
        };
        rows.push((ln + 1, num(f[0], &cols[0])?, num(f[1], &cols[1])?));
    }
    Ok(TwoColumns { header: [cols[0].clone(), cols[1].clone()], rows })
}

/// The length unit (metres) a column name carries after `base`: `depth_nm`, `wavelength (um)`,
/// `wavelength[m]`. A column without a unit is refused: a number without a unit is a guess.
pub fn column_unit(path: &Path, column: &str, base: &str) -> Result<f64> {
    if !column.starts_with(base) {
        return Err(Error::malformed(
            path,
            format!("header column '{column}' must be {base}_<unit>, e.g. {base}_nm"),
        ));
    }
    let unit = column.strip_prefix(base).map(|u| {
        u.trim_matches(|c: char| c == '_' || c.is_whitespace())
            .trim_start_matches(['(', '['])
            .trim_end_matches([')', ']'])
    });
    match unit {
        Some(u) if !u.is_empty() => length_unit(u).map_err(|_| {
            Error::malformed(path, format!("column '{column}': '{u}' is not a length unit (nm, um, m)"))
        }),
        _ => Err(Error::malformed(
            path,
            format!("column '{column}' names no unit: write {base}_nm, {base}_um or {base}_m"),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_on_lines_and_shape_preserving() {
        let x = [0.0, 0.25, 0.5, 1.0];
        let y = [1.0, 1.5, 2.0, 3.0];
        let m = pchip_slopes(&x, &y);
        for k in 0..=50 {
            let t = k as f64 / 50.0;
            assert!((hermite(&x, &y, &m, t) - (1.0 + 2.0 * t)).abs() < 1e-14);
        }
        // A local maximum keeps a zero slope there and no overshoot.
        let (x, y) = ([0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 0.5, 0.4]);
        let m = pchip_slopes(&x, &y);
        assert_eq!(m[1], 0.0);
        assert!((0..=300).all(|k| hermite(&x, &y, &m, k as f64 / 100.0) <= 1.0 + 1e-15));
        // Clamped outside the range.
        assert_eq!(hermite(&x, &y, &m, -1.0), 0.0);
    }

    #[test]
    fn columns_name_their_units() {
        let p = Path::new("t.csv");
        assert_eq!(column_unit(p, "depth_nm", "depth").unwrap(), 1e-9);
        assert_eq!(column_unit(p, "wavelength (um)", "wavelength").unwrap(), 1e-6);
        assert!(column_unit(p, "depth", "depth").unwrap_err().to_string().contains("names no unit"));
        assert!(column_unit(p, "depth_ft", "depth").is_err());
    }
}
