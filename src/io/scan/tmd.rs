//! TrueMap / GelSight binary surface files (`.tmd`, "Binary TrueMap Data File v2.0").
//!
//! Layout (TrueGage TrueMap and GelSight's `readtmd` / `writetmd`; also SurfaceTopography's and
//! Gwyddion's readers; little-endian):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 32 | magic `Binary TrueMap Data File v2.0\r\n\0` |
//! | 32 | n + 1 | comment: ISO 8859-1 text ending at a NUL (TrueMap writes `Created by TrueMap v6\r\n\0`, GelSight a lone NUL) |
//! | 33 + n | 4, 4 | columns, rows (u32) |
//! | 41 + n | 4, 4 | x length, y length (f32, millimetres: the pitch is length / count) |
//! | 49 + n | 4, 4 | x offset, y offset (f32, millimetres: the position of this field in the full field of view) |
//! | 57 + n | 4 rows cols | heights (f32, millimetres), row by row, the first row first |
//!
//! The description names no marker for points not measured: NaN and infinities are read as
//! non-measured. Bytes after the heights are left unread with a warning. An older or other
//! "Binary TrueMap Data File" (Ambios `.amb`, a version other than 2.0) is refused naming it.

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, decode_text, shape, Bin, ScanFormat, ScanRaw};

/// The 32-byte magic of version 2.0.
pub const MAGIC: &[u8; 32] = b"Binary TrueMap Data File v2.0\r\n\0";
/// The part every TrueMap binary file starts with.
const FAMILY: &[u8] = b"Binary TrueMap Data File";
/// Millimetres, the unit of lengths, offsets and heights.
const MM: f64 = 1e-3;

/// True when `head` starts as a version 2.0 `.tmd` file does.
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(MAGIC)
}

/// Decodes a `.tmd` file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    let n = bytes.len().min(FAMILY.len());
    if bytes[..n] != FAMILY[..n] {
        return Err(b.signature(0, "not a TrueMap file: it does not start with 'Binary TrueMap Data File'"));
    }
    let n = bytes.len().min(MAGIC.len());
    if bytes[..n] != MAGIC[..n] {
        let line = bytes.split(|&c| c == b'\r' || c == b'\n' || c == 0).next().unwrap_or(&[]);
        let line = decode_text(&line[..line.len().min(64)]);
        return Err(b.unsupported(
            FAMILY.len(),
            format!("'{line}' is not a version 2.0 TrueMap file ('Binary TrueMap Data File v2.0' CR LF NUL)"),
        ));
    }
    b.take(0, MAGIC.len(), "the magic")?;
    let rest = &bytes[MAGIC.len()..];
    let Some(len) = rest.iter().position(|&c| c == 0) else {
        return Err(b.bad(MAGIC.len(), "the comment has no terminating NUL before the end of the file"));
    };
    let comment = decode_text(&rest[..len]);
    let h = MAGIC.len() + len + 1;
    let cols = b.u32le(h, "the number of columns")? as usize;
    let rows = b.u32le(h + 4, "the number of rows")? as usize;
    let lx = b.f32le(h + 8, "the x length")? as f64;
    let ly = b.f32le(h + 12, "the y length")? as f64;
    let ox = b.f32le(h + 16, "the x offset")? as f64;
    let oy = b.f32le(h + 20, "the y offset")? as f64;
    if rows == 0 || cols == 0 {
        return Err(b.bad(h, format!("the map is empty ({cols} x {rows} points)")));
    }
    let start = h + 24;
    let need = data_len(path, rows, cols, 4)?;
    let data = b.take(start, need, &format!("the {cols} x {rows} f32 heights"))?;
    let values: Vec<f64> = data
        .chunks_exact(4)
        .map(|c| {
            let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            if v.is_finite() {
                v as f64 * MM
            } else {
                f64::NAN
            }
        })
        .collect();
    let values = shape(path, rows, cols, values)?;
    let mut warnings = Vec::new();
    let pitch = if lx.is_finite() && lx > 0.0 && ly.is_finite() && ly > 0.0 {
        Some([lx / cols as f64 * MM, ly / rows as f64 * MM])
    } else {
        warnings.push(format!("the lengths {lx} x {ly} mm give no usable pitch: pass `pitch`"));
        None
    };
    let extra = bytes.len() - (start + need);
    if extra > 0 {
        warnings
            .push(format!("{extra} bytes after the heights (from byte offset {}) left unread", start + need));
    }
    let metadata = vec![
        ("comment".to_string(), comment),
        ("length_x".to_string(), format!("{lx} mm")),
        ("length_y".to_string(), format!("{ly} mm")),
        ("offset_x".to_string(), format!("{ox} mm")),
        ("offset_y".to_string(), format!("{oy} mm")),
        ("height_unit".to_string(), "mm (f32)".to_string()),
    ];
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Tmd);
    sr.origin = Some([ox * MM, oy * MM]);
    sr.warnings = warnings;
    Ok(sr)
}

/// Writes a `.tmd` file from the layout in the module docs (for tests): `heights` in metres (NaN
/// kept as NaN), `pitch` `[x, y]` and `offset` in metres, any `comment` (without its NUL).
pub fn encode(heights: &ndarray::Array2<f64>, pitch: [f64; 2], offset: [f64; 2], comment: &[u8]) -> Vec<u8> {
    let (rows, cols) = heights.dim();
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(comment);
    out.push(0);
    out.extend_from_slice(&(cols as u32).to_le_bytes());
    out.extend_from_slice(&(rows as u32).to_le_bytes());
    for v in [pitch[0] * cols as f64, pitch[1] * rows as f64, offset[0], offset[1]] {
        out.extend_from_slice(&((v / MM) as f32).to_le_bytes());
    }
    for v in heights {
        out.extend_from_slice(&((v / MM) as f32).to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    fn read(bytes: &[u8]) -> Result<ScanRaw> {
        decode(Path::new("t.tmd"), bytes)
    }

    #[test]
    fn any_comment_length_millimetres_and_offsets() {
        let mut h = Array2::from_shape_fn((3, 4), |(i, j)| 1e-7 * (10 * i + j) as f64);
        h[[2, 1]] = f64::NAN;
        // GelSight's lone NUL, TrueMap's 24 bytes with CR LF, and a Latin-1 comment.
        for comment in [&b""[..], b"Created by TrueMap v6\r\n", b"\xb5m scan, 50\xd7"] {
            let bytes = encode(&h, [0.5e-6, 2e-6], [1e-3, -2e-3], comment);
            let r = read(&bytes).unwrap();
            assert_eq!(r.raw.values.dim(), (3, 4));
            let [px, py] = r.raw.pitch.unwrap();
            // The lengths are f32 millimetres.
            assert!((px / 0.5e-6 - 1.0).abs() < 1e-7 && (py / 2e-6 - 1.0).abs() < 1e-7, "{px} {py}");
            let [ox, oy] = r.origin.unwrap();
            assert!((ox - 1e-3).abs() < 1e-10 && (oy + 2e-3).abs() < 1e-10);
            for ((i, j), v) in r.raw.values.indexed_iter() {
                let w = h[[i, j]];
                // f32 millimetres: within half an f32 step.
                assert!(w.is_nan() && v.is_nan() || (v - w).abs() <= 1e-7 * w.abs(), "({i}, {j}) {v} {w}");
            }
            assert!(r.warnings.is_empty(), "{:?}", r.warnings);
            let c = &r.raw.metadata[0];
            assert_eq!(c.0, "comment");
            assert_eq!(c.1, decode_text(comment));
        }
        assert_eq!(read(&encode(&h, [1e-6; 2], [0.0; 2], b"")).unwrap().raw.metadata[0].1, "");
        let mut longer = encode(&h, [1e-6; 2], [0.0; 2], b"x");
        longer.extend_from_slice(&[1, 2, 3]);
        let r = read(&longer).unwrap();
        assert!(r.warnings[0].starts_with("3 bytes after the heights"), "{:?}", r.warnings);
    }

    #[test]
    fn other_files_cuts_and_bad_sizes_are_refused() {
        let h = Array2::from_elem((2, 3), 1e-6);
        let good = encode(&h, [1e-6; 2], [0.0; 2], b"Created by TrueMap v6\r\n");
        let err = |bytes: &[u8]| read(bytes).unwrap_err().to_string();
        assert!(err(b"AliconaImaging\0\r\n").contains("not a TrueMap file"));
        let e = err(b"Binary TrueMap Data File \\ Ambios File Format\r\n");
        assert!(e.contains("'Binary TrueMap Data File \\ Ambios File Format' is not a version 2.0"), "{e}");
        assert!(err(b"Binary TrueMap Data File v1.0\r\n\0").contains("not a version 2.0"));
        for cut in 0..good.len() {
            let e = err(&good[..cut]);
            assert!(e.contains("t.tmd") && e.contains("byte offset"), "cut at {cut}: {e}");
        }
        let h0 = MAGIC.len() + 24;
        let mut empty = good.clone();
        empty[h0..h0 + 4].fill(0);
        assert!(err(&empty).contains("the map is empty"));
        let mut huge = good.clone();
        huge[h0..h0 + 8].fill(0xff);
        assert!(err(&huge).contains("beyond any profilometer scan"));
        let mut no_nul = MAGIC.to_vec();
        no_nul.extend_from_slice(b"comment without end");
        assert!(err(&no_nul).contains("byte offset 32: the comment has no terminating NUL"));
        let mut flat = good;
        flat[h0 + 8..h0 + 12].copy_from_slice(&0f32.to_le_bytes());
        let r = read(&flat).unwrap();
        assert!(r.raw.pitch.is_none() && r.warnings[0].contains("pass `pitch`"));
    }
}
