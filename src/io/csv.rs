//! Text matrices: one row of the map per line, cells separated by commas, semicolons, tabs or
//! spaces (the separator is taken from the first data line: `;` if present, else `,`, else
//! whitespace). Blank lines and lines starting with `#` are skipped; one trailing separator per
//! line is tolerated. `nan`/`inf` cells are read as such (invalid samples downstream).
//!
//! Comment lines of the form `# key: value` (or `# key = value`) are metadata. Recognised keys:
//! ours, `pitch_x`, `pitch_y` (or `pitch`) in metres or with a unit, and `unit`; and those of
//! Gwyddion's "ASCII data matrix" export: `Width` and `Height` (field size with unit, so the
//! pitch is width / columns and height / rows) and `Value units`.
//!
//! Errors name the file, the line (1-based) and, for a bad cell, the column (1-based cell
//! index); ragged rows name both column counts.

use std::io::Write;
use std::path::Path;

use ndarray::Array2;

use crate::error::{Error, Result};
use crate::io::atomic::write_atomic;
use crate::io::raw_map::{pitch_unit_from_text, unit_from_text, Metadata, RawMap, SampleKind};
use crate::units::parse_length;

/// Reads a text matrix (see the module docs).
pub fn read_csv(path: &Path) -> Result<RawMap> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_csv(path, &bytes)
}

/// Decodes the bytes of a text matrix file (see [`read_csv`]); `path` names it in errors.
pub fn decode_csv(path: &Path, bytes: &[u8]) -> Result<RawMap> {
    let text = std::str::from_utf8(bytes).map_err(|e| {
        Error::malformed(path, format!("not UTF-8 text (invalid byte at offset {})", e.valid_up_to()))
    })?;
    parse_csv(path, text)
}

#[derive(Clone, Copy, PartialEq)]
enum Sep {
    Char(char),
    Space,
}

/// Parses the text of a matrix file (see [`read_csv`]); `path` names it in errors.
pub fn parse_csv(path: &Path, text: &str) -> Result<RawMap> {
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let mut metadata = Vec::new();
    let mut sep = None;
    let mut data: Vec<f64> = Vec::new();
    let mut cols = 0usize;
    let mut first_line = 0usize;
    let mut rows = 0usize;
    for (n, line) in text.lines().enumerate() {
        let lineno = n + 1;
        let t = line.trim();
        if t.is_empty() {
            continue;
        }
        if let Some(c) = t.strip_prefix('#') {
            let kv = c.split_once(':').or_else(|| c.split_once('='));
            if let Some((k, v)) = kv {
                metadata.push((k.trim().to_string(), v.trim().to_string()));
            }
            continue;
        }
        let s = *sep.get_or_insert(if t.contains(';') {
            Sep::Char(';')
        } else if t.contains(',') {
            Sep::Char(',')
        } else {
            Sep::Space
        });
        let mut cells: Vec<&str> = match s {
            Sep::Char(c) => t.split(c).map(str::trim).collect(),
            Sep::Space => t.split_whitespace().collect(),
        };
        if cells.len() > 1 && cells.last() == Some(&"") {
            cells.pop();
        }
        if rows == 0 {
            cols = cells.len();
            first_line = lineno;
        } else if cells.len() != cols {
            return Err(Error::malformed(
                path,
                format!(
                    "line {lineno} has {} columns but line {first_line} (the first data line) has {cols}",
                    cells.len()
                ),
            ));
        }
        for (k, cell) in cells.iter().enumerate() {
            let v: f64 = cell.parse().map_err(|_| {
                let shown = if cell.is_empty() { "an empty cell".to_string() } else { format!("'{cell}'") };
                Error::malformed(path, format!("line {lineno}, column {}: {shown} is not a number", k + 1))
            })?;
            data.push(v);
        }
        rows += 1;
    }
    if rows == 0 || cols == 0 {
        return Err(Error::malformed(path, "holds no data lines"));
    }
    let values = Array2::from_shape_vec((rows, cols), data)
        .map_err(|e| Error::malformed(path, format!("cannot form a {rows} x {cols} matrix: {e}")))?;

    let (mut pitch, mut unit) = pitch_unit_from_text(path, &metadata)?;
    let get = |k: &str| metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
    if pitch.is_none() {
        if let (Some(wt), Some(ht)) = (get("Width"), get("Height")) {
            let (wd, hd) = (parse_length(wt), parse_length(ht));
            match (wd, hd) {
                (Ok(wd), Ok(hd)) if wd > 0.0 && hd > 0.0 => {
                    pitch = Some([wd / cols as f64, hd / rows as f64])
                }
                _ => {
                    return Err(Error::malformed(
                        path,
                        format!("header 'Width: {wt}' / 'Height: {ht}' is not a pair of positive lengths"),
                    ))
                }
            }
        }
    }
    if unit.is_none() {
        if let Some(u) = get("Value units") {
            unit = Some(unit_from_text(path, "Value units", u)?);
        }
    }
    Ok(RawMap { values, kind: SampleKind::Float, pitch, unit, metadata, scale_hint: None })
}

/// Writes a matrix as comma-separated text with `# key: value` header lines, atomically.
/// Numbers are written in the shortest form that reads back to the same `f64`.
pub fn write_csv(path: &Path, values: &Array2<f64>, meta: &Metadata) -> Result<()> {
    let kv = meta.key_values(path)?;
    for (k, v) in &kv {
        if k.contains([':', '=', '\n', '\r']) || v.contains(['\n', '\r']) {
            return Err(Error::param(
                "metadata",
                format!("'{k}' = '{v}' cannot be a one-line '# key: value' header"),
            ));
        }
    }
    write_atomic(path, |w: &mut dyn Write| {
        let io = |e| Error::io(path, e);
        for (k, v) in &kv {
            writeln!(w, "# {k}: {v}").map_err(io)?;
        }
        for row in values.rows() {
            let line: Vec<String> = row.iter().map(|v| format!("{v:e}")).collect();
            writeln!(w, "{}", line.join(",")).map_err(io)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p() -> &'static Path {
        Path::new("m.csv")
    }

    #[test]
    fn separators_comments_and_trailing_separator() {
        for text in [
            "1,2,3\n4,5,6\n",
            "# c\n1; 2; 3\n\n4;5;6;\n",
            "1\t2\t3\n4\t5\t6\t\n",
            "  1  2 3\n4 5    6\n# end\n",
            "\u{feff}1, 2, 3\r\n4, 5, 6\r\n",
        ] {
            let r = parse_csv(p(), text).unwrap();
            assert_eq!(r.values, ndarray::array![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], "{text:?}");
        }
        let r = parse_csv(p(), "nan 1\n-inf 2e-3\n").unwrap();
        assert!(r.values[[0, 0]].is_nan() && r.values[[1, 0]] == f64::NEG_INFINITY);
    }

    #[test]
    fn errors_name_line_and_column() {
        let e = parse_csv(p(), "# h\n1,2,3\n4,5\n").unwrap_err().to_string();
        assert!(
            e.contains("m.csv")
                && e.contains("line 3 has 2 columns")
                && e.contains("line 2")
                && e.contains("has 3"),
            "{e}"
        );
        let e = parse_csv(p(), "1,2\n3,x4\n").unwrap_err().to_string();
        assert!(e.contains("line 2, column 2: 'x4' is not a number"), "{e}");
        let e = parse_csv(p(), "1,,2\n").unwrap_err().to_string();
        assert!(e.contains("column 2: an empty cell"), "{e}");
        assert!(parse_csv(p(), "# only\n\n").unwrap_err().to_string().contains("no data"));
    }

    #[test]
    fn header_metadata_ours_and_gwyddions() {
        let r = parse_csv(p(), "# pitch_x: 2 um\n# pitch_y: 3e-6\n# unit: nm\n1 2\n").unwrap();
        assert_eq!((r.pitch, r.unit), (Some([2e-6, 3e-6]), Some(1e-9)));
        let r = parse_csv(p(), "# Width: 20.0 µm\n# Height: 10.0 µm\n# Value units: m\n1 2\n3 4\n").unwrap();
        let pitch = r.pitch.unwrap();
        assert!((pitch[0] - 10e-6).abs() < 1e-18 && (pitch[1] - 5e-6).abs() < 1e-18);
        assert_eq!(r.unit, Some(1.0));
        assert!(parse_csv(p(), "# Value units: V\n1\n")
            .unwrap_err()
            .to_string()
            .contains("not a length unit"));
    }

    #[test]
    fn round_trip_is_exact() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("m.csv");
        let a = Array2::from_shape_fn((4, 3), |(i, j)| (i as f64 + 0.1) / 3.0 * 1e-7 - j as f64 * 1e-9);
        write_csv(&f, &a, &Metadata::heights([1e-6, 2e-6]).with("source", "test")).unwrap();
        let r = read_csv(&f).unwrap();
        assert_eq!(r.values, a);
        assert_eq!((r.pitch, r.unit), (Some([1e-6, 2e-6]), Some(1.0)));
        assert!(r.metadata.contains(&("source".into(), "test".into())));
    }
}
