//! ISO 25178-71 surface data files (`.sdf`, the "Surfstand" SDF of Stout & Blunt), ASCII and
//! binary.
//!
//! **ASCII** (version strings `aBCR-x.y`, `aISO-x.y`): the version line, `Key = Value` header
//! lines up to a line `*`, then `NumPoints * NumProfiles` numbers separated by white space (row
//! by row, first profile first), then `*` (Gwyddion omits it) and an optional trailer section
//! closed by `*`. The
//! token `BAD` marks a non-measured point. Numbers are as written (Gwyddion writes `%g`, six
//! significant digits).
//!
//! **Binary** (`bBCR-x.y`, `bISO-x.y`), little endian, header fields in this order:
//! version (8 bytes), ManufacID (10), CreateDate (12), ModDate (12), NumPoints, NumProfiles,
//! Xscale, Yscale, Zscale, Zresolution (f64 each), Compression, DataType, CheckType (u8 each),
//! then the data. NumPoints and NumProfiles are u16 in the original format (81-byte header;
//! Gwyddion, surfalize) but u32 in some ISO writers (85-byte header; sdfio 2.0): the layout
//! whose dimensions are non-zero and whose data fits the file is taken, the exact fit first.
//!
//! Both: `Xscale`, `Yscale` are metres per point (the pitch), `Zscale` metres per stored unit.
//! `DataType`: 0 u8, 1 u16, 2 u32, 3 f32, 4 i8, 5 i16, 6 i32, 7 f64. In binary float data a
//! non-measured point is NaN or the type's largest magnitude (sdfio and surfalize write
//! `-f64::MAX`). Dates are not validated (Gwyddion writes a 0-based month and year-1900).

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, decode_text, shape, Bin, ScanFormat, ScanRaw};

fn type_size(t: u8) -> Option<usize> {
    match t {
        0 | 4 => Some(1),
        1 | 5 => Some(2),
        2 | 3 | 6 => Some(4),
        7 => Some(8),
        _ => None,
    }
}

/// Decodes an ASCII or binary SDF file (by its first byte).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    match bytes.first() {
        Some(b'a') => {
            let text = std::str::from_utf8(bytes).map_err(|e| {
                let at = e.valid_up_to();
                Error::malformed(path, format!("byte offset {at}: ASCII SDF is not text")).at(at as u64)
            })?;
            decode_ascii(path, text)
        }
        Some(b'b') => decode_binary(path, bytes),
        _ => Err(Error::signature(path, "not an SDF file: the version string must start with 'a' or 'b'")),
    }
}

fn finish(
    path: &Path,
    metadata: Vec<(String, String)>,
    xres: usize,
    yres: usize,
    scales: [f64; 3],
    raw: Vec<f64>,
    format: ScanFormat,
) -> Result<ScanRaw> {
    let [xs, ys, zs] = scales;
    if !(xs.is_finite() && xs > 0.0 && ys.is_finite() && ys > 0.0) {
        return Err(Error::malformed(
            path,
            format!("Xscale = {xs}, Yscale = {ys}: the pitch must be positive"),
        ));
    }
    if !(zs.is_finite() && zs != 0.0) {
        return Err(Error::malformed(path, format!("Zscale = {zs}: must be finite and non-zero")));
    }
    let values = shape(path, yres, xres, raw.into_iter().map(|v| v * zs).collect())?;
    let raw = RawMap {
        values,
        kind: SampleKind::Float,
        pitch: Some([xs, ys]),
        unit: Some(1.0),
        metadata,
        scale_hint: None,
    };
    Ok(ScanRaw::new(raw, format))
}

/// Decodes an ASCII SDF (see the module docs).
pub fn decode_ascii(path: &Path, text: &str) -> Result<ScanRaw> {
    let mut lines = text.lines().enumerate();
    let version = lines.next().map(|(_, l)| l.trim()).unwrap_or_default();
    if !(version.starts_with("aBCR") || version.starts_with("aISO")) {
        return Err(Error::signature(
            path,
            format!("line 1: '{version}' is not an ASCII SDF version (aBCR/aISO)"),
        ));
    }
    let mut metadata = vec![("Version".to_string(), version.to_string())];
    let mut closed = false;
    for (n, line) in lines.by_ref() {
        let t = line.trim();
        if t == "*" {
            closed = true;
            break;
        }
        if t.is_empty() {
            continue;
        }
        let (k, v) = t
            .split_once('=')
            .ok_or_else(|| Error::malformed(path, format!("line {}: '{t}' is not 'Key = Value'", n + 1)))?;
        if metadata.iter().any(|(key, _)| key == k.trim()) {
            return Err(Error::malformed(
                path,
                format!("line {}: header key '{}' is given twice", n + 1, k.trim()),
            ));
        }
        metadata.push((k.trim().to_string(), v.trim().to_string()));
    }
    if !closed {
        return Err(Error::malformed(path, "the header is not closed by a '*' line"));
    }
    let get = |k: &str| metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
    let need = |k: &str| get(k).ok_or_else(|| Error::malformed(path, format!("header lacks '{k}'")));
    let count = |k: &str| -> Result<usize> {
        let v = need(k)?;
        v.parse::<usize>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| Error::malformed(path, format!("header '{k} = {v}' is not a positive integer")))
    };
    let float = |k: &str| -> Result<f64> {
        let v = need(k)?;
        v.parse::<f64>().map_err(|_| Error::malformed(path, format!("header '{k} = {v}' is not a number")))
    };
    let (xres, yres) = (count("NumPoints")?, count("NumProfiles")?);
    let scales = [float("Xscale")?, float("Yscale")?, float("Zscale")?];
    let n = data_len(path, yres, xres, 1)?;
    // The header's size is a claim: reserve no more than the text can hold (a number and a
    // separator take at least two bytes).
    let mut data = Vec::with_capacity(n.min(text.len() / 2 + 1));
    let mut ended = false;
    'lines: for (ln, line) in lines {
        for tok in line.split_whitespace() {
            if tok == "*" {
                ended = true;
                break 'lines;
            }
            if data.len() == n {
                return Err(Error::malformed(
                    path,
                    format!(
                        "line {}: more than NumPoints x NumProfiles = {n} values before the closing '*'",
                        ln + 1
                    ),
                ));
            }
            let v = if tok == "BAD" {
                f64::NAN
            } else {
                tok.parse::<f64>().map_err(|_| {
                    Error::malformed(path, format!("line {}: '{tok}' is neither a number nor BAD", ln + 1))
                })?
            };
            data.push(v);
        }
    }
    if data.len() != n {
        return Err(Error::malformed(
            path,
            format!("holds {} values, NumPoints x NumProfiles = {xres} x {yres} = {n} expected", data.len()),
        ));
    }
    // Gwyddion ends the file after the last value without the closing '*': accepted.
    let _ = ended;
    finish(path, metadata, xres, yres, scales, data, ScanFormat::SdfAscii)
}

/// Decodes a binary SDF (see the module docs).
pub fn decode_binary(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    let version = b.text(0, 8, "the version string")?;
    if !(version.starts_with("bBCR") || version.starts_with("bISO")) {
        return Err(b.signature(0, format!("'{version}' is not a binary SDF version (bBCR/bISO)")));
    }
    // Try both layouts of NumPoints/NumProfiles (u16: 81-byte header; u32: 85-byte header).
    let mut candidates = Vec::new();
    for wide in [false, true] {
        let (xres, yres, hsize) = if wide {
            (b.u32le(42, "NumPoints")? as usize, b.u32le(46, "NumProfiles")? as usize, 85usize)
        } else {
            (b.u16le(42, "NumPoints")? as usize, b.u16le(44, "NumProfiles")? as usize, 81usize)
        };
        let d = hsize - 3;
        if bytes.len() < hsize || xres == 0 || yres == 0 {
            continue;
        }
        let Some(size) = type_size(bytes[d + 1]) else { continue };
        let Ok(n) = data_len(path, yres, xres, size) else { continue };
        if hsize + n <= bytes.len() {
            candidates.push((hsize + n == bytes.len(), wide, xres, yres, hsize));
        }
    }
    candidates.sort_by_key(|c| !c.0);
    let Some(&(_, wide, xres, yres, hsize)) = candidates.first() else {
        // Report against the classic layout, field by field.
        let (xres, yres) = (b.u16le(42, "NumPoints")? as usize, b.u16le(44, "NumProfiles")? as usize);
        if xres == 0 || yres == 0 {
            return Err(b.bad(42, format!("NumPoints = {xres}, NumProfiles = {yres}: the map is empty")));
        }
        let dt = b.take(79, 1, "DataType")?[0];
        let size = type_size(dt).ok_or_else(|| b.bad(79, format!("DataType {dt} is not 0..7")))?;
        b.take(81, data_len(path, yres, xres, size)?, &format!("the {xres} x {yres} data of type {dt}"))?;
        return Err(b.bad(42, "the header does not describe the data that follows"));
    };
    let f = if wide { 50 } else { 46 };
    let scales = [b.f64le(f, "Xscale")?, b.f64le(f + 8, "Yscale")?, b.f64le(f + 16, "Zscale")?];
    let zres = b.f64le(f + 24, "Zresolution")?;
    let d = hsize - 3;
    let (compression, dtype, check) = (bytes[d], bytes[d + 1], bytes[d + 2]);
    if compression != 0 {
        return Err(
            b.unsupported(d, format!("Compression = {compression}: only uncompressed data is supported"))
        );
    }
    let size = type_size(dtype).ok_or_else(|| b.bad(d + 1, format!("DataType {dtype} is not 0..7")))?;
    let data = b.take(hsize, xres * yres * size, "the data")?;
    let raw: Vec<f64> = data
        .chunks_exact(size)
        .map(|c| match dtype {
            0 => c[0] as f64,
            4 => c[0] as i8 as f64,
            1 => u16::from_le_bytes([c[0], c[1]]) as f64,
            5 => i16::from_le_bytes([c[0], c[1]]) as f64,
            2 => u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
            6 => i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
            3 => {
                let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
                if v.abs() == f32::MAX {
                    f64::NAN
                } else {
                    v as f64
                }
            }
            _ => {
                let v = f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]);
                if v.abs() == f64::MAX {
                    f64::NAN
                } else {
                    v
                }
            }
        })
        .collect();
    let metadata = vec![
        ("Version".to_string(), version),
        ("ManufacID".to_string(), b.text(8, 10, "ManufacID")?),
        ("CreateDate".to_string(), decode_text(&bytes[18..30])),
        ("ModDate".to_string(), decode_text(&bytes[30..42])),
        ("NumPoints".to_string(), xres.to_string()),
        ("NumProfiles".to_string(), yres.to_string()),
        ("Zresolution".to_string(), format!("{zres:e}")),
        ("DataType".to_string(), dtype.to_string()),
        ("CheckType".to_string(), check.to_string()),
        ("HeaderBytes".to_string(), hsize.to_string()),
    ];
    finish(path, metadata, xres, yres, scales, raw, ScanFormat::SdfBinary)
}

/// Encodes a classic binary SDF (`bBCR-1.0`, u16 dimensions, f64 data in metres) for tests.
pub fn encode_binary(values: &ndarray::Array2<f64>, pitch: [f64; 2]) -> Vec<u8> {
    let (r, c) = values.dim();
    let mut out = b"bBCR-1.0doefab    000000000000000000000000".to_vec();
    out.extend_from_slice(&(c as u16).to_le_bytes());
    out.extend_from_slice(&(r as u16).to_le_bytes());
    for v in [pitch[0], pitch[1], 1.0, -1.0] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&[0, 7, 0]);
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ascii_with_bad_and_binary_round_trip() {
        let t = "aBCR-0.0\nNumPoints = 3\nNumProfiles = 2\nXscale = 1e-6\nYscale = 2e-6\nZscale = 1e-9\n*\n\
                 1 2 BAD\n4 5 6\n*\n";
        let r = decode(Path::new("a.sdf"), t.as_bytes()).unwrap();
        assert_eq!(r.raw.pitch, Some([1e-6, 2e-6]));
        assert!(r.raw.values[[0, 2]].is_nan());
        assert!((r.raw.values[[1, 0]] - 4e-9).abs() < 1e-24);
        let e = decode(Path::new("a.sdf"), t.replace("BAD", "x").as_bytes()).unwrap_err().to_string();
        assert!(e.contains("line 8") && e.contains("'x'"), "{e}");
        let e = decode(Path::new("a.sdf"), t.replace(" 6\n", "\n").as_bytes()).unwrap_err().to_string();
        assert!(e.contains("holds 5 values"), "{e}");

        let v = ndarray::Array2::from_shape_fn((2, 3), |(i, j)| (i * 3 + j) as f64 * 1e-7);
        let b = encode_binary(&v, [1e-6, 1e-6]);
        assert_eq!(b.len(), 81 + 48);
        let r = decode(Path::new("b.sdf"), &b).unwrap();
        assert_eq!(r.raw.values, v);
        for cut in 0..b.len() {
            let e = decode(Path::new("cut.sdf"), &b[..cut]).unwrap_err().to_string();
            assert!(e.contains("cut.sdf") && (cut == 0 || e.contains("byte offset")), "cut at {cut}: {e}");
        }
    }
}
