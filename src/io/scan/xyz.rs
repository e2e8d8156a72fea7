//! Point lists (`.xyz`): one point per line, `x y z` (separated by white space, commas or
//! semicolons), on a regular grid in any order; lines starting with `#` are comments, and
//! `# unit: um` states the length unit shared by the three columns.
//!
//! The coordinates are sample centres (Gwyddion writes 0.5, 1.5, ... 199.5 um for a 200-point,
//! 200 um wide field), so the pitch is `(max - min) / (n - 1)` for `n` distinct values, not
//! `range / n`. Each point goes to column `round((x - min_x) / pitch_x)` and row
//! `round((y - min_y) / pitch_y)`, row 0 at the smallest y; a point further than 1% of a pitch
//! from its grid node, or a node given twice, is an error. Nodes with no point are non-measured.
//! A file without a `# unit:` line needs the unit from the caller (`--z-unit`).

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::raw_map::{unit_from_text, RawMap, SampleKind};
use crate::io::scan::raw::{data_len, ScanFormat, ScanRaw};

/// Distinct values of a sorted list, merging those closer than `tol`.
fn distinct(sorted: &[f64], tol: f64) -> usize {
    let mut n = 0;
    let mut last = f64::NEG_INFINITY;
    for &v in sorted {
        if v - last > tol {
            n += 1;
            last = v;
        }
    }
    n
}

/// Parses the text of an `.xyz` file; `unit` is the caller's length unit (metres per unit).
pub fn parse(path: &Path, text: &str, unit: Option<f64>) -> Result<ScanRaw> {
    let mut metadata = Vec::new();
    let mut pts: Vec<[f64; 3]> = Vec::new();
    let mut lines = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let t = line.trim();
        if t.is_empty() {
            continue;
        }
        if let Some(c) = t.strip_prefix('#') {
            if let Some((k, v)) = c.split_once(':').or_else(|| c.split_once('=')) {
                metadata.push((k.trim().to_string(), v.trim().to_string()));
            }
            continue;
        }
        let cells: Vec<&str> =
            t.split(|c: char| c.is_whitespace() || c == ',' || c == ';').filter(|c| !c.is_empty()).collect();
        if cells.len() != 3 {
            return Err(Error::malformed(
                path,
                format!("line {}: {} columns, x y z expected", n + 1, cells.len()),
            ));
        }
        let mut p = [0.0f64; 3];
        for (k, c) in cells.iter().enumerate() {
            p[k] = c.parse().map_err(|_| {
                Error::malformed(path, format!("line {}, column {}: '{c}' is not a number", n + 1, k + 1))
            })?;
        }
        if !(p[0].is_finite() && p[1].is_finite()) {
            return Err(Error::malformed(path, format!("line {}: x and y must be finite", n + 1)));
        }
        pts.push(p);
        lines.push(n + 1);
    }
    if pts.is_empty() {
        return Err(Error::malformed(path, "holds no points"));
    }
    let file_unit = match metadata.iter().find(|(k, _)| k == "unit") {
        Some((_, u)) => Some(unit_from_text(path, "unit", u)?),
        None => None,
    };
    let s = file_unit.or(unit).ok_or_else(|| {
        Error::param(
            "z_unit",
            format!(
                "{} states no length unit for its x, y, z columns: pass `z_unit` (e.g. m; \
                 the three columns share it)",
                path.display()
            ),
        )
    })?;
    let axis = |k: usize| -> Result<(f64, f64, usize)> {
        let mut v: Vec<f64> = pts.iter().map(|p| p[k]).collect();
        v.sort_by(f64::total_cmp);
        let (lo, hi) = (v[0], v[v.len() - 1]);
        let n = distinct(&v, 1e-6 * (hi - lo));
        let name = if k == 0 { "x" } else { "y" };
        if n < 2 {
            return Err(Error::malformed(
                path,
                format!("all points share one {name} value: the {name} pitch cannot be derived"),
            ));
        }
        Ok((lo, (hi - lo) / (n - 1) as f64, n))
    };
    let (x0, px, nx) = axis(0)?;
    let (y0, py, ny) = axis(1)?;
    let total = data_len(path, ny, nx, 1)?;
    let mut values = ndarray::Array2::from_elem((ny, nx), f64::NAN);
    let mut seen = ndarray::Array2::from_elem((ny, nx), false);
    for (p, line) in pts.iter().zip(&lines) {
        let fj = (p[0] - x0) / px;
        let fi = (p[1] - y0) / py;
        let (j, i) = (fj.round(), fi.round());
        if (fj - j).abs() > 0.01 || (fi - i).abs() > 0.01 {
            return Err(Error::malformed(
                path,
                format!(
                    "line {line}: ({}, {}) is off the regular grid (pitch {px:e} x {py:e}, origin {x0:e}, {y0:e})",
                    p[0], p[1]
                ),
            ));
        }
        let (i, j) = (i as usize, j as usize);
        if seen[[i, j]] {
            return Err(Error::malformed(path, format!("line {line}: grid node ({i}, {j}) is given twice")));
        }
        seen[[i, j]] = true;
        values[[i, j]] = p[2];
    }
    let _ = total;
    let raw = RawMap {
        values,
        kind: SampleKind::Float,
        pitch: Some([px * s, py * s]),
        unit: Some(s),
        metadata,
        scale_hint: None,
    };
    let mut sr = ScanRaw::new(raw, ScanFormat::Xyz);
    sr.origin = Some([x0 * s, y0 * s]);
    Ok(sr)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centres_missing_nodes_and_errors() {
        let t = "# unit: um\n0.5 0.5 1\n1.5 0.5 2\n2.5 0.5 3\n0.5 2.5 4\n2.5 2.5 6\n";
        let r = parse(Path::new("p.xyz"), t, None).unwrap();
        assert_eq!(r.raw.values.dim(), (2, 3));
        let p = r.raw.pitch.unwrap();
        assert!((p[0] - 1e-6).abs() < 1e-18 && (p[1] - 2e-6).abs() < 1e-18);
        assert!(r.raw.values[[1, 1]].is_nan());
        assert_eq!(r.raw.values[[1, 2]], 6.0);
        let e = parse(Path::new("p.xyz"), "0 0 1\n1 0 1\n", None).unwrap_err().to_string();
        assert!(e.contains("pass `z_unit`"), "{e}");
        let e = parse(Path::new("p.xyz"), "0 0 1\n1 0 1\n1 0 2\n0 1 1\n", Some(1.0)).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("twice"), "{e}");
        let e =
            parse(Path::new("p.xyz"), "0 0 1\n1 0 1\n0.3 1 1\n2 1 1\n", Some(1.0)).unwrap_err().to_string();
        assert!(e.contains("off the regular grid"), "{e}");
    }
}
