//! Wyko / Bruker Vision binary data files (`.opd`), the height map.
//!
//! Little-endian throughout. After two bytes `01 00` comes a directory of 24-byte entries:
//!
//! | bytes | field |
//! |---|---|
//! | 0..16 | name, padded with NUL or spaces |
//! | 16..18 | u16 type: 1 directory, 3 array, 5 text, 6 short (i16), 7 float (f32), 8 double (f64), 12 long (i32) |
//! | 18..22 | u32 size of the entry's data, bytes |
//! | 22..24 | u16 flags |
//!
//! The first entry is the directory itself (`Directory`, type 1, flags `0xffff`, size = 24 x
//! the number of entries). The entries' data follow the directory in the entries' order, each
//! `size` bytes long (empty entries take none). An array starts with three u16, columns, rows
//! and bytes per element (4: f32, 2: i16, 1: u8), then its elements column by column, each
//! column from the last row to the first. The height map is the array named `OPD`,
//! `SAMPLE_DATA`, `RAW_DATA` or `RAW DATA`: `z = value * Wavelength (nm) / Mult` (`Mult`
//! absent: 1); non-measured points are f32 values of 1e38 and above, i16 values of 32766 and
//! above (signed: negative heights are measured ones). `Pixel_size` (f32, millimetres) is the x pitch, y is `Aspect`
//! times it. This is the layout Gwyddion's `opdfile` module reads; the reader is checked
//! against Gwyddion's and SurfaceTopography's reading of a real file.

use std::path::Path;

use crate::error::Result;
use crate::io::heightmap::{RawMap, SampleKind};
use crate::io::scan::{data_len, shape, Bin, ScanFormat, ScanRaw};

const ENTRY: usize = 24;
const T_DIRECTORY: u16 = 1;
const T_ARRAY: u16 = 3;
const T_TEXT: u16 = 5;
const T_SHORT: u16 = 6;
const T_FLOAT: u16 = 7;
const T_DOUBLE: u16 = 8;
const T_LONG: u16 = 12;
const HEIGHT_ARRAYS: [&str; 4] = ["OPD", "SAMPLE_DATA", "RAW_DATA", "RAW DATA"];
const BAD_F32: f32 = 1e38;
const BAD_I16: i16 = 32766;

/// True when `head` starts as an OPD file does (`01 00 Directory`).
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(b"\x01\x00Directory")
}

/// One directory entry and where its data are.
struct Entry {
    name: String,
    kind: u16,
    offset: usize,
    size: usize,
}

/// Decodes an OPD file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    b.take(0, 2 + ENTRY, "the directory entry")?;
    if !has_magic(bytes) {
        return Err(b.bad(0, "not a Wyko OPD file: it does not start with 01 00 'Directory'"));
    }
    let dir_type = b.u16le(18, "the directory's type")?;
    let dir_size = b.u32le(20, "the directory's size")? as usize;
    let flags = b.u16le(24, "the directory's flags")?;
    if dir_type != T_DIRECTORY || flags != 0xffff || dir_size < ENTRY || !dir_size.is_multiple_of(ENTRY) {
        return Err(b.bad(
            18,
            format!(
                "directory entry of type {dir_type}, size {dir_size}, flags {flags:#06x}: expected type 1, a \
                 multiple of 24 bytes, flags 0xffff"
            ),
        ));
    }
    b.take(2, dir_size, "the directory")?;
    let mut entries = Vec::new();
    let mut offset = 2 + dir_size;
    for k in 1..dir_size / ENTRY {
        let at = 2 + k * ENTRY;
        let name = b.text(at, 16, "an entry's name")?;
        let kind = b.u16le(at + 16, "an entry's type")?;
        let size = b.u32le(at + 18, "an entry's size")? as usize;
        if kind == T_DIRECTORY && size > 0 {
            return Err(b.bad(at + 16, format!("entry '{name}' is a nested directory")));
        }
        b.take(offset, size, &format!("the data of entry '{name}'"))?;
        let expected = match kind {
            T_SHORT => Some(2),
            T_FLOAT | T_LONG => Some(4),
            T_DOUBLE => Some(8),
            _ => None,
        };
        if let Some(e) = expected.filter(|&e| size > 0 && size != e) {
            return Err(b.bad(at + 18, format!("entry '{name}' of type {kind} holds {size} bytes, not {e}")));
        }
        if size > 0 {
            entries.push(Entry { name, kind, offset, size });
        }
        offset += size;
    }
    let find = |name: &str| entries.iter().find(|e| e.name == name);
    // A number entry (short, long, float or double) as f64; by name, `None` when absent.
    let value = |e: &Entry| -> Result<f64> {
        let what = format!("entry '{}'", e.name);
        Ok(match e.kind {
            T_SHORT => i16::from_le_bytes([bytes[e.offset], bytes[e.offset + 1]]) as f64,
            T_LONG => b.i32le(e.offset, &what)? as f64,
            T_FLOAT => b.f32le(e.offset, &what)? as f64,
            T_DOUBLE => b.f64le(e.offset, &what)?,
            k => return Err(b.bad(e.offset, format!("{what} is of type {k}, not a number"))),
        })
    };
    let number = |name: &str| find(name).map(value).transpose();
    let wavelength = number("Wavelength")?.ok_or_else(|| b.bad(2, "the entry 'Wavelength' is missing"))?;
    if !(wavelength.is_finite() && wavelength > 0.0 && wavelength < 1e5) {
        return Err(b.bad(find("Wavelength").map_or(2, |e| e.offset), format!("Wavelength {wavelength} nm")));
    }
    let mult = number("Mult")?.unwrap_or(1.0);
    if !(mult.is_finite() && mult != 0.0) {
        return Err(b.bad(find("Mult").map_or(2, |e| e.offset), format!("Mult {mult}")));
    }
    let pixel = number("Pixel_size")?;
    let aspect = number("Aspect")?.unwrap_or(1.0);
    let data = entries.iter().find(|e| HEIGHT_ARRAYS.contains(&e.name.as_str())).ok_or_else(|| {
        b.bad(2, "no height array (OPD, SAMPLE_DATA, RAW_DATA or RAW DATA) in the directory")
    })?;
    if data.kind != T_ARRAY {
        return Err(
            b.bad(data.offset, format!("entry '{}' is of type {}, not an array", data.name, data.kind))
        );
    }
    let cols = b.u16le(data.offset, "the array's columns")? as usize;
    let rows = b.u16le(data.offset + 2, "the array's rows")? as usize;
    let elem = b.u16le(data.offset + 4, "the array's element size")? as usize;
    if !matches!(elem, 1 | 2 | 4) {
        return Err(b.bad(data.offset + 4, format!("array element of {elem} bytes (1, 2 or 4 expected)")));
    }
    let need = data_len(path, rows, cols, elem)?;
    if data.size < 6 + need {
        return Err(b.bad(
            data.offset,
            format!(
                "array '{}' of {cols} x {rows} x {elem} bytes does not fit its {} bytes",
                data.name, data.size
            ),
        ));
    }
    let raw = b.take(data.offset + 6, need, "the array's elements")?;
    let z = wavelength * 1e-9 / mult;
    let mut values = vec![f64::NAN; rows * cols];
    for (k, v) in raw.chunks_exact(elem).enumerate() {
        // Column k / rows, stored from the last row up.
        let (col, r) = (k / rows, k % rows);
        let row = rows - 1 - r;
        values[row * cols + col] = match elem {
            4 => {
                let f = f32::from_le_bytes([v[0], v[1], v[2], v[3]]);
                if f.is_finite() && f < BAD_F32 {
                    f as f64 * z
                } else {
                    f64::NAN
                }
            }
            2 => {
                let s = i16::from_le_bytes([v[0], v[1]]);
                if s < BAD_I16 {
                    s as f64 * z
                } else {
                    f64::NAN
                }
            }
            _ => v[0] as f64 * z,
        };
    }
    let values = shape(path, rows, cols, values)?;
    let pitch = match pixel {
        Some(p) if p.is_finite() && p > 0.0 && aspect.is_finite() && aspect > 0.0 => {
            Some([p * 1e-3, aspect * p * 1e-3])
        }
        _ => None,
    };
    let mut metadata = Vec::new();
    for e in &entries {
        let text = match e.kind {
            T_TEXT => Some(crate::io::scan::decode_text(&bytes[e.offset..e.offset + e.size])),
            T_SHORT | T_LONG | T_FLOAT | T_DOUBLE => Some(format!("{}", value(e)?)),
            _ => None,
        };
        if let Some(t) = text.filter(|t| !t.is_empty()) {
            metadata.push((e.name.clone(), t));
        }
    }
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Opd);
    if pitch.is_none() {
        sr.warnings.push("the file states no usable Pixel_size: pass --pitch".to_string());
    }
    Ok(sr)
}

/// Writes an OPD file from the layout in the module docs (for tests): `heights` in units of
/// `wavelength / mult` nanometres as f32 (NaN written as the non-measured marker), row 0 first.
pub fn encode(heights: &ndarray::Array2<f64>, pixel_size_mm: f32, wavelength_nm: f32, mult: i16) -> Vec<u8> {
    let (rows, cols) = heights.dim();
    let mut array = Vec::new();
    array.extend_from_slice(&(cols as u16).to_le_bytes());
    array.extend_from_slice(&(rows as u16).to_le_bytes());
    array.extend_from_slice(&4u16.to_le_bytes());
    for c in 0..cols {
        for r in (0..rows).rev() {
            let v = heights[[r, c]];
            let f = if v.is_nan() { BAD_F32 } else { v as f32 };
            array.extend_from_slice(&f.to_le_bytes());
        }
    }
    let entries: Vec<(&str, u16, Vec<u8>)> = vec![
        ("RAW_DATA", T_ARRAY, array),
        ("Wavelength", T_FLOAT, wavelength_nm.to_le_bytes().to_vec()),
        ("Mult", T_SHORT, mult.to_le_bytes().to_vec()),
        ("Pixel_size", T_FLOAT, pixel_size_mm.to_le_bytes().to_vec()),
        ("Aspect", T_FLOAT, 1f32.to_le_bytes().to_vec()),
        ("Title", T_TEXT, b"synthetic".to_vec()),
    ];
    let mut out = vec![1u8, 0];
    let entry = |out: &mut Vec<u8>, name: &str, kind: u16, size: usize, flags: u16| {
        let mut n = [0u8; 16];
        n[..name.len()].copy_from_slice(name.as_bytes());
        out.extend_from_slice(&n);
        out.extend_from_slice(&kind.to_le_bytes());
        out.extend_from_slice(&(size as u32).to_le_bytes());
        out.extend_from_slice(&flags.to_le_bytes());
    };
    entry(&mut out, "Directory", T_DIRECTORY, ENTRY * (entries.len() + 1), 0xffff);
    for (name, kind, data) in &entries {
        entry(&mut out, name, *kind, data.len(), 0);
    }
    for (_, _, data) in entries {
        out.extend_from_slice(&data);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3 x 4 map with one non-measured point through `encode` and back: values, orientation,
    /// pitch, the mask; every truncation is an error naming an offset.
    #[test]
    fn round_trip_and_truncation() {
        let mut h = ndarray::Array2::from_shape_fn((3, 4), |(i, j)| (10 * i + j) as f64);
        h[[1, 2]] = f64::NAN;
        let bytes = encode(&h, 2e-3, 632.8, 2);
        let p = Path::new("t.opd");
        let s = decode(p, &bytes).unwrap();
        let z = 632.8e-9 / 2.0;
        for ((i, j), v) in s.raw.values.indexed_iter() {
            if (i, j) == (1, 2) {
                assert!(v.is_nan());
            } else {
                assert!((v - h[[i, j]] * z).abs() < 1e-6 * z * 30.0, "({i}, {j}): {v}");
            }
        }
        let px = 2e-3f32 as f64 * 1e-3;
        assert_eq!(s.raw.pitch, Some([px, px]));
        assert!(s.raw.metadata.iter().any(|(k, v)| k == "Title" && v == "synthetic"));
        for cut in [1, 20, 30, 2 + 7 * 24 + 3, bytes.len() - 1] {
            let e = decode(p, &bytes[..cut]).unwrap_err().to_string();
            assert!(e.contains("t.opd") && e.contains("offset"), "{cut}: {e}");
        }
        let mut bad = bytes.clone();
        bad[2] = b'X';
        assert!(decode(p, &bad).unwrap_err().to_string().contains("not a Wyko OPD file"));
    }
}
