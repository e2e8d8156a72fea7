//! Stylus profiler exports (Bruker Dektak, KLA-Tencor Alpha-Step and P-series, and any two-column
//! text): header lines (`key, value` pairs or free text), a column-header line naming the units,
//! then rows of position and height.
//!
//! * Text is UTF-8, or Latin-1 where it is not valid UTF-8 (instrument software writes `µm` and
//!   `Å` either way); a byte-order mark is skipped.
//! * The delimiter is taken from the first data row: tab, else `;`, else `,`, else whitespace.
//!   A data row is one whose first two cells are numbers; the first two columns are the
//!   position and the height (further columns, such as Dektak's "Normal" data, are ignored).
//! * Units come from the last non-data line before the data that names a unit for each of the
//!   two columns (`Lateral(um)`, `Z [nm]`, `Height (Å)`, `x um`), else from header pairs
//!   `X units, um` / `Z units, A` (keys with `unit` and x, lateral, horizontal, scan or z, y,
//!   vertical, height); recognised: `m`, `mm`, `um`, `µm` (micro sign or Greek mu), `nm`,
//!   `pm`, `A`, `Å`, `Angstrom`. A unit the caller gives ([`ProfileReadOptions`]) is used where
//!   the file names none and refused where the file names another.
//! * A row whose first cell is not a number ends the data (instrument footers); after it, no
//!   further data rows are read. An empty, `nan` or `inf` height cell is a non-measured point.
//!   A data row with a single cell is an error (a truncated file), as is any other cell that is
//!   not a number.
//! * Positions must be strictly monotone; a decreasing column is reversed (with the heights).
//!   A step back or a repeated position is refused, naming its line.
//!
//! Errors name the file, the line (1-based) and what was expected there.

use std::io::Write;
use std::path::Path;

use crate::error::{Allowed, Error, Result};
use crate::grid::profile::Profile;
use crate::io::atomic::write_atomic;

/// What the caller states about a profile file (the command line's `--x-unit`, `--z-unit`).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ProfileReadOptions {
    /// Metres per stored position value.
    pub x_unit: Option<f64>,
    /// Metres per stored height value.
    pub z_unit: Option<f64>,
}

/// A profile read from a file, with what the file said about itself.
#[derive(Debug, Clone)]
pub struct ProfileFile {
    /// Positions and heights in metres.
    pub profile: Profile,
    /// Metres per stored position value.
    pub x_unit: f64,
    /// Metres per stored height value.
    pub z_unit: f64,
    /// Where the position unit came from, in words (the column header or a header pair with
    /// its line, or `x_unit` where the caller gave it).
    pub x_unit_source: String,
    /// Where the height unit came from, as for `x_unit_source` (`z_unit` where the caller gave
    /// it).
    pub z_unit_source: String,
    /// Header `key, value` pairs, in file order.
    pub metadata: Vec<(String, String)>,
    /// Lines after the data that were not read as data.
    pub footer_lines: usize,
    /// What the reader changed or found missing, one sentence each (a reversed profile, the
    /// count of non-measured points).
    pub warnings: Vec<String>,
}

/// Reads a stylus profile export (see the module docs).
pub fn read_profile(path: &Path, opts: &ProfileReadOptions) -> Result<ProfileFile> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    parse_profile(path, &bytes, opts)
}

/// The text of a file: UTF-8 where valid, else Latin-1.
fn decode(bytes: &[u8]) -> String {
    let bytes = bytes.strip_prefix(b"\xef\xbb\xbf").unwrap_or(bytes);
    match std::str::from_utf8(bytes) {
        Ok(s) => s.to_string(),
        Err(_) => bytes.iter().map(|&c| c as char).collect(),
    }
}

#[derive(Clone, Copy, PartialEq, Debug)]
enum Delim {
    Char(char),
    Space,
}

fn split(line: &str, d: Delim) -> Vec<&str> {
    let mut cells: Vec<&str> = match d {
        Delim::Char(c) => line.split(c).map(str::trim).collect(),
        Delim::Space => line.split_whitespace().collect(),
    };
    while cells.len() > 2 && cells.last() == Some(&"") {
        cells.pop();
    }
    cells
}

fn number(cell: &str) -> Option<f64> {
    cell.trim().parse::<f64>().ok().filter(|v| v.is_finite())
}

/// The delimiter under which `line` is a data row (its first two cells numbers).
fn data_delimiter(line: &str) -> Option<Delim> {
    [Delim::Char('\t'), Delim::Char(';'), Delim::Char(','), Delim::Space].into_iter().find(|&d| {
        let c = split(line, d);
        c.len() >= 2 && number(c[0]).is_some() && number(c[1]).is_some()
    })
}

/// A missing-height marker: empty, `nan` or `inf` in any case.
fn is_missing(cell: &str) -> bool {
    let t = cell.trim().to_ascii_lowercase();
    t.is_empty()
        || ["nan", "-nan", "+nan", "inf", "-inf", "+inf", "infinity", "-infinity"].contains(&t.as_str())
}

/// Metres per unit of a unit name as stylus software writes it.
pub fn profile_unit(name: &str) -> Option<f64> {
    let t = name.trim().trim_matches(|c: char| matches!(c, '(' | ')' | '[' | ']' | '{' | '}'));
    match t {
        "A" | "Å" | "\u{212b}" | "Angstrom" | "angstrom" | "Angstroms" | "angstroms" | "Ang" => Some(1e-10),
        "" => None,
        _ => crate::units::length_unit(t).ok(),
    }
}

/// Metres per unit of a unit the caller names (`--x-unit`, `--z-unit`): those of
/// [`profile_unit`], refused with the list otherwise.
pub fn profile_unit_arg(name: &str) -> Result<f64> {
    profile_unit(name).ok_or_else(|| {
        Error::param_in(
            "unit",
            Allowed::one_of(&["m", "mm", "um", "nm", "pm", "A"]),
            format!("'{name}' is not a length unit (expected one of m, mm, um, nm, pm, A)"),
        )
    })
}

/// The unit a column-header cell names: the text in parentheses or brackets, else its last
/// word (`Height (nm)`, `Z[um]`, `x um`, `um`).
fn cell_unit(cell: &str) -> Option<(f64, String)> {
    let c = cell.trim();
    for (open, close) in [('(', ')'), ('[', ']')] {
        if let (Some(a), Some(b)) = (c.rfind(open), c.rfind(close)) {
            if a < b {
                let u = &c[a + 1..b];
                return profile_unit(u).map(|s| (s, u.trim().to_string()));
            }
        }
    }
    let last = c.split_whitespace().last()?;
    profile_unit(last).map(|s| (s, last.to_string()))
}

/// Which column a header key's unit belongs to: 0 = position, 1 = height.
fn unit_key_column(key: &str) -> Option<usize> {
    let k = key.to_ascii_lowercase();
    if !k.contains("unit") {
        return None;
    }
    let words: Vec<&str> = k.split(|c: char| !c.is_alphanumeric()).filter(|w| !w.is_empty()).collect();
    let has =
        |w: &[&str]| words.iter().any(|x| w.contains(x) || w.iter().any(|p| x.starts_with(p) && p.len() > 1));
    if has(&["x", "lateral", "horizontal", "scan", "position", "distance"]) {
        Some(0)
    } else if has(&["z", "y", "vertical", "height", "data"]) {
        Some(1)
    } else {
        None
    }
}

/// A profile export's header (the lines before the data).
struct Header {
    /// Key/value pairs, in file order.
    metadata: Vec<(String, String)>,
    /// The last line naming two units (position, height): its line number and the units.
    header_units: Option<(usize, [(f64, String); 2])>,
    /// Units named by key/value pairs (`X units, um`), per column, with their line numbers.
    key_units: [Option<(f64, String, usize)>; 2],
}

/// Reads the header `lines` (from the file's first line): each line split at its first
/// delimiter among tab, `;`, `,`, `:`, `=` (else at spaces) into a key and value, and the units
/// it names.
fn read_header(lines: &[&str]) -> Header {
    let mut metadata = Vec::new();
    let mut header_units: Option<(usize, [(f64, String); 2])> = None;
    let mut key_units: [Option<(f64, String, usize)>; 2] = [None, None];
    for (n, line) in lines.iter().enumerate() {
        let t = line.trim().trim_start_matches('#').trim();
        if t.is_empty() {
            continue;
        }
        let d = if t.contains('\t') {
            Delim::Char('\t')
        } else if t.contains(';') {
            Delim::Char(';')
        } else if t.contains(',') {
            Delim::Char(',')
        } else if t.contains(':') {
            Delim::Char(':')
        } else if t.contains('=') {
            Delim::Char('=')
        } else {
            Delim::Space
        };
        let cells = split(t, d);
        if d == Delim::Space {
            // Words naming a unit: in parentheses or brackets, or a bare unit other than the
            // ambiguous "A" and "m" of free text.
            let units: Vec<(f64, String)> = cells
                .iter()
                .filter(|w| w.starts_with(['(', '[']) || !matches!(**w, "A" | "m"))
                .filter_map(|w| profile_unit(w).map(|s| (s, w.to_string())))
                .collect();
            if let [a, b] = units.as_slice() {
                header_units = Some((n + 1, [a.clone(), b.clone()]));
            }
        }
        if cells.len() >= 2 && d != Delim::Space {
            if let (Some(a), Some(b)) = (cell_unit(cells[0]), cell_unit(cells[1])) {
                header_units = Some((n + 1, [a, b]));
            }
            let (k, v) = (cells[0].to_string(), cells[1..].join(" ").trim().to_string());
            if let Some(col) = unit_key_column(&k) {
                if let Some(u) = cell_unit(&v) {
                    key_units[col] = Some((u.0, u.1, n + 1));
                }
            }
            metadata.push((k, v));
        }
    }
    Header { metadata, header_units, key_units }
}

/// The data rows of a profile export, as stored.
struct Rows {
    x: Vec<f64>,
    z: Vec<f64>,
    /// False where the height is missing (empty or NaN).
    valid: Vec<bool>,
    /// Each row's line number (from 1).
    lineno_of: Vec<usize>,
    /// Lines after the data that were not read as data.
    footer_lines: usize,
}

/// Reads the data rows from line index `first` (split at `delim`) until the first line that
/// does not start with a number (the footer); a row without a height, a height that is no
/// number, or fewer than 2 rows is refused naming the line.
fn read_rows(path: &Path, lines: &[&str], first: usize, delim: Delim) -> Result<Rows> {
    let mut x = Vec::new();
    let mut z = Vec::new();
    let mut valid = Vec::new();
    let mut lineno_of = Vec::new();
    let mut footer_lines = 0usize;
    let mut ended = false;
    for (n, line) in lines.iter().enumerate().skip(first) {
        let lineno = n + 1;
        let t = line.trim();
        if ended {
            if !t.is_empty() {
                footer_lines += 1;
            }
            continue;
        }
        if t.is_empty() {
            continue;
        }
        let cells = split(t, delim);
        let Some(pos) = number(cells[0]) else {
            ended = true;
            footer_lines += 1;
            continue;
        };
        if cells.len() < 2 {
            return Err(Error::malformed(
                path,
                format!(
                    "line {lineno}: one cell '{}' where a position and a height were expected (is the file \
                     truncated?)",
                    cells[0]
                ),
            ));
        }
        let (h, ok) = match number(cells[1]) {
            Some(v) => (v, true),
            None if is_missing(cells[1]) => (0.0, false),
            None => {
                return Err(Error::malformed(
                    path,
                    format!(
                        "line {lineno}, column 2: '{}' is not a height (a number, or empty/NaN)",
                        cells[1]
                    ),
                ))
            }
        };
        x.push(pos);
        z.push(h);
        valid.push(ok);
        lineno_of.push(lineno);
    }
    if x.len() < 2 {
        return Err(Error::malformed(
            path,
            format!("holds {} data row(s): a profile needs at least 2", x.len()),
        ));
    }
    Ok(Rows { x, z, valid, lineno_of, footer_lines })
}

/// Parses the bytes of a profile export (see [`read_profile`]); `path` names it in errors.
pub fn parse_profile(path: &Path, bytes: &[u8], opts: &ProfileReadOptions) -> Result<ProfileFile> {
    let text = decode(bytes);
    let lines: Vec<&str> = text.lines().collect();
    let Some((first, delim)) =
        lines.iter().enumerate().find_map(|(n, l)| data_delimiter(l.trim()).map(|d| (n, d)))
    else {
        return Err(Error::malformed(
            path,
            "holds no data rows (expected rows of two numbers, position and height, after the header)",
        ));
    };
    // Header: key/value pairs and the column header (the last line naming two units).
    let Header { metadata, header_units, key_units } = read_header(&lines[..first]);
    let Rows { x, z, mut valid, lineno_of, footer_lines } = read_rows(path, &lines, first, delim)?;
    // Units: the caller's, the column header's, the header pairs'.
    let mut resolved: [(f64, String); 2] = Default::default();
    for (col, (name, given, flag)) in
        [("position", opts.x_unit, "x_unit"), ("height", opts.z_unit, "z_unit")].into_iter().enumerate()
    {
        let from_file = header_units
            .as_ref()
            .map(|(l, u)| (u[col].0, format!("'{}' in the column header, line {l}", u[col].1)))
            .or_else(|| {
                key_units[col].as_ref().map(|(s, u, l)| (*s, format!("'{u}' in the header, line {l}")))
            });
        resolved[col] = match (from_file, given) {
            (Some((s, src)), Some(g)) if (s / g - 1.0).abs() > 1e-9 => {
                return Err(Error::malformed(
                    path,
                    format!("the {name} unit is {src} ({s:e} m) but `{flag}` says {g:e} m"),
                ))
            }
            (Some(f), _) => f,
            (None, Some(g)) => (g, flag.to_string()),
            (None, None) => {
                return Err(Error::malformed(
                    path,
                    format!(
                        "no {name} unit found (expected a column header such as 'Lateral (um), Height (nm)' \
                         before the data on line {}, or a header pair such as '{} units, um'); pass `{flag}`",
                        first + 1,
                        if col == 0 { "X" } else { "Z" }
                    ),
                ))
            }
        };
    }
    let [(xu, xs), (zu, zs)] = resolved;
    // Monotone positions.
    let increasing = x[1] > x[0];
    for k in 1..x.len() {
        let ok = if increasing { x[k] > x[k - 1] } else { x[k] < x[k - 1] };
        if !ok {
            return Err(Error::malformed(
                path,
                format!(
                    "line {}: position {} does not {} the previous row's {} (line {}): the position column \
                     must be strictly monotone",
                    lineno_of[k],
                    x[k],
                    if increasing { "exceed" } else { "fall below" },
                    x[k - 1],
                    lineno_of[k - 1]
                ),
            ));
        }
    }
    let mut xm: Vec<f64> = x.iter().map(|v| v * xu).collect();
    let mut zm: Vec<f64> = z.iter().map(|v| v * zu).collect();
    let mut warnings = Vec::new();
    if !increasing {
        xm.reverse();
        zm.reverse();
        valid.reverse();
        warnings.push("the positions decrease: the profile was reversed".to_string());
    }
    let missing = valid.iter().filter(|v| !**v).count();
    if missing > 0 {
        warnings.push(format!("{missing} of {} points are not measured (empty or NaN heights)", valid.len()));
    }
    let profile = Profile::new(xm, zm, Some(valid)).map_err(|e| Error::malformed(path, e.to_string()))?;
    Ok(ProfileFile {
        profile,
        x_unit: xu,
        z_unit: zu,
        x_unit_source: xs,
        z_unit_source: zs,
        metadata,
        footer_lines,
        warnings,
    })
}

/// Writes a profile as comma-separated text, Dektak-like: `key, value` header lines, a column
/// header `Lateral (um), Height (nm)`, then one row per point (positions in um, heights in nm,
/// non-measured points as `NaN`), atomically. Numbers are written in the shortest form that
/// reads back to the same `f64` after the unit conversion's rounding.
pub fn write_profile_csv(path: &Path, profile: &Profile, header: &[(&str, &str)]) -> Result<()> {
    write_atomic(path, |w: &mut dyn Write| {
        let io = |e| Error::io(path, e);
        for (k, v) in header {
            writeln!(w, "{k},{v}").map_err(io)?;
        }
        writeln!(w, "Lateral (um),Height (nm)").map_err(io)?;
        for k in 0..profile.len() {
            let z = if profile.is_valid(k) { format!("{}", profile.z()[k] * 1e9) } else { "NaN".into() };
            writeln!(w, "{},{z}", profile.x()[k] * 1e6).map_err(io)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p() -> &'static Path {
        Path::new("scan01.csv")
    }

    fn read(text: &[u8]) -> Result<ProfileFile> {
        parse_profile(p(), text, &ProfileReadOptions::default())
    }

    #[test]
    fn a_dektak_like_csv_with_its_header() {
        let t = "Meta Data\nRecipe,step 2um\nScan Length,2000.0,um\nStylus Force,3.0,mg\n\nScan Data\n\
                 Lateral(um),Raw(A),Normal(A)\n0.0,12.5,0.0\n0.5,13.0,0.5\n1.0,NaN,\n1.5,1012.5,1000.0\n\
                 End of data\nTotal points,4\n";
        let f = read(t.as_bytes()).unwrap();
        assert_eq!(f.profile.x(), &[0.0, 0.5e-6, 1.0e-6, 1.5e-6]);
        assert!((f.profile.z()[3] - 1012.5e-10).abs() < 1e-20 && (f.profile.z()[0] - 12.5e-10).abs() < 1e-22);
        assert_eq!(f.profile.valid(), &[true, true, false, true]);
        assert_eq!((f.x_unit, f.z_unit), (1e-6, 1e-10));
        assert!(f.z_unit_source.contains("line 7"), "{}", f.z_unit_source);
        assert_eq!(f.footer_lines, 2);
        assert!(f.metadata.contains(&("Scan Length".into(), "2000.0 um".into())));
        assert!(f.warnings.iter().any(|w| w.contains("1 of 4")));
    }

    #[test]
    fn tab_semicolon_and_whitespace_text() {
        for t in [
            "X (µm)\tZ (nm)\n0\t1\n2\t3\n",
            "x [um]; height [nm]\n0;1\n2;3\n",
            "# Alpha-Step export\nX units, um\nZ units, nm\n  0   1\n  2   3\n",
            "Lateral um  Height nm\n0 1\n2 3\n",
        ] {
            let f = read(t.as_bytes()).unwrap_or_else(|e| panic!("{t:?}: {e}"));
            assert_eq!(f.profile.x(), &[0.0, 2e-6], "{t:?}");
            assert!((f.profile.z()[1] - 3e-9).abs() < 1e-22, "{t:?}");
        }
    }

    #[test]
    fn units_angstrom_and_micro_in_utf8_and_latin1() {
        let f = read("Position (mm),Height (Å)\n0,10\n0.001,20\n".as_bytes()).unwrap();
        assert_eq!((f.x_unit, f.z_unit), (1e-3, 1e-10));
        let f = read("Position (\u{212b}),Height (A)\n0,10\n1,20\n".as_bytes()).unwrap();
        assert_eq!((f.x_unit, f.z_unit), (1e-10, 1e-10));
        // The micro sign in UTF-8 (C2 B5), Greek mu (CE BC) and Latin-1 (B5); angstrom in Latin-1 (C5).
        for bytes in [
            b"X (\xc2\xb5m),Z (\xc3\x85)\n0,1\n1,2\n".to_vec(),
            b"X (\xce\xbcm),Z (\xc3\x85)\n0,1\n1,2\n".to_vec(),
            b"X (\xb5m),Z (\xc5)\n0,1\n1,2\n".to_vec(),
        ] {
            let f = read(&bytes).unwrap();
            assert_eq!((f.x_unit, f.z_unit), (1e-6, 1e-10), "{bytes:?}");
        }
    }

    #[test]
    fn missing_units_need_the_callers_and_conflicts_are_refused() {
        let t = b"0,1\n1,2\n";
        let e = read(t).unwrap_err().to_string();
        assert!(
            e.contains("scan01.csv") && e.contains("no position unit") && e.contains("pass `x_unit`"),
            "{e}"
        );
        let o = ProfileReadOptions { x_unit: Some(1e-6), z_unit: None };
        let e = parse_profile(p(), t, &o).unwrap_err().to_string();
        assert!(e.contains("no height unit") && e.contains("pass `z_unit`"), "{e}");
        let o = ProfileReadOptions { x_unit: Some(1e-6), z_unit: Some(1e-9) };
        let f = parse_profile(p(), t, &o).unwrap();
        assert_eq!((f.profile.x()[1], f.z_unit_source.as_str()), (1e-6, "z_unit"));
        let e = parse_profile(p(), b"x (um),z (nm)\n0,1\n1,2\n", &o.clone())
            .map(|_| ())
            .and_then(|_| parse_profile(p(), b"x (mm),z (nm)\n0,1\n1,2\n", &o).map(|_| ()))
            .unwrap_err()
            .to_string();
        assert!(e.contains("position unit") && e.contains("but `x_unit` says"), "{e}");
    }

    #[test]
    fn non_monotone_positions_name_the_line() {
        let e = read(b"x (um),z (nm)\n0,1\n1,2\n3,2\n2.5,1\n").unwrap_err().to_string();
        assert!(e.contains("line 5") && e.contains("monotone") && e.contains("line 4"), "{e}");
        let e = read(b"x (um),z (nm)\n0,1\n1,2\n1,2\n").unwrap_err().to_string();
        assert!(e.contains("line 4"), "{e}");
        let f = read(b"x (um),z (nm)\n2,1\n1,2\n0,3\n").unwrap();
        assert_eq!(f.profile.x(), &[0.0, 1e-6, 2e-6]);
        assert!((f.profile.z()[0] - 3e-9).abs() < 1e-22);
    }

    #[test]
    fn truncated_and_broken_files() {
        let full = "Lateral(um),Raw(A)\n0.0,12.5\n0.5,13.0\n1.0,14.0\n";
        let cut = &full[..full.len() - 6];
        assert!(cut.ends_with("\n1.0"));
        let e = read(cut.as_bytes()).unwrap_err().to_string();
        assert!(e.contains("scan01.csv") && e.contains("line 4") && e.contains("truncated"), "{e}");
        let e = read(b"x (um),z (nm)\n0,1\n1,abc\n").unwrap_err().to_string();
        assert!(e.contains("line 3, column 2") && e.contains("'abc'"), "{e}");
        let e = read(b"Meta Data\nScan Length,2000\n").unwrap_err().to_string();
        assert!(e.contains("no data rows"), "{e}");
        let e = read(b"x (um),z (nm)\n0,1\n").unwrap_err().to_string();
        assert!(e.contains("1 data row"), "{e}");
    }

    #[test]
    fn written_profiles_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("p.csv");
        let prof = Profile::new(
            vec![0.0, 0.5e-6, 1.0e-6, 1.5e-6],
            vec![1e-9, 2.5e-9, 0.0, 3.25e-7],
            Some(vec![true, true, false, true]),
        )
        .unwrap();
        write_profile_csv(&f, &prof, &[("Instrument", "simulated")]).unwrap();
        let r = read_profile(&f, &ProfileReadOptions::default()).unwrap();
        assert_eq!(r.profile.valid(), prof.valid());
        for k in 0..4 {
            assert!((r.profile.x()[k] - prof.x()[k]).abs() < 1e-18);
            if prof.is_valid(k) {
                assert!((r.profile.z()[k] - prof.z()[k]).abs() < 1e-18);
            }
        }
    }
}
