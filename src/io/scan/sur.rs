//! Digital Surf / MountainsMap surface files (`.sur`), single-object surfaces.
//!
//! A 512-byte little-endian header (offsets in bytes, after Digital Surf's "SUR file format"
//! description as implemented by Gwyddion's `surffile.c` and surfalize's `sur.py`):
//!
//! | offset | field |
//! |---|---|
//! | 0 | signature `DIGITAL SURF` (12 bytes) |
//! | 12, 14, 16, 18 | format (u16, 0 = PC), object count, version, studiable type (u16) |
//! | 20, 50 | object name, operator name (30 bytes each) |
//! | 86 | non-measured points flag (u16; 1 = there are some) |
//! | 98 | bits per point (u16: 16 or 32) |
//! | 100, 104 | zmin, zmax (i32): the range of measured values |
//! | 108, 112, 116 | points per line, lines, total points (i32) |
//! | 120, 124, 128 | x, y, z spacing (f32), in the units below |
//! | 132, 148, 164 | axis names (16 bytes each) |
//! | 180, 196, 212 | x, y, z spacing units (16 bytes each; Latin-1 `µm` or UTF-8 `µm`, `pm`, ...) |
//! | 228, 244, 260 | x, y, z length units (16 bytes each) |
//! | 334, 336 | comment size, private zone size (u16) |
//! | 466, 470, 474 | x, y, z offset (f32, in the spacing units) |
//!
//! The data (i16 or i32 per point, row by row, first line first) follow the header, the comment
//! and the private zone. Heights: `z = raw * z_spacing + z_offset` in the z spacing unit
//! (Gwyddion writes picometres with an offset of -149000 pm; skipping the offset shifts every
//! height). With the non-measured flag set, raw values outside `zmin..=zmax` are non-measured
//! points (surfalize writes `i32::MIN`, the specification `zmin - 1`).

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, scan_length_unit, shape, Bin, ScanFormat, ScanRaw};

/// Size of the fixed header.
pub const HEADER: usize = 512;

/// Decodes a `.sur` file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    if b.take(0, 12, "the signature")? != b"DIGITAL SURF" {
        return Err(b.signature(0, "not a Digital Surf file: the signature is not 'DIGITAL SURF'"));
    }
    b.take(0, HEADER, "the 512-byte header")?;
    let nobjects = b.u16le(14, "the object count")?;
    if nobjects > 1 {
        return Err(b.bad(
            14,
            format!("{nobjects} objects (a series or a multi-layer study); one surface is supported"),
        ));
    }
    let nm_flag = b.u16le(86, "the non-measured points flag")?;
    let bits = b.u16le(98, "bits per point")?;
    let size = match bits {
        16 => 2,
        32 => 4,
        _ => return Err(b.bad(98, format!("{bits} bits per point (16 or 32 expected)"))),
    };
    let (zmin, zmax) = (b.i32le(100, "zmin")?, b.i32le(104, "zmax")?);
    let xres = b.i32le(108, "points per line")?;
    let yres = b.i32le(112, "number of lines")?;
    if xres <= 0 || yres <= 0 {
        return Err(b.bad(108, format!("{xres} points per line, {yres} lines: the map is empty")));
    }
    let (xres, yres) = (xres as usize, yres as usize);
    let total = b.i32le(116, "total points")?;
    if total as i64 != (xres * yres) as i64 {
        return Err(b.bad(116, format!("total points {total} is not {xres} x {yres}")));
    }
    let dx = b.f32le(120, "x spacing")? as f64;
    let dy = b.f32le(124, "y spacing")? as f64;
    let dz = b.f32le(128, "z spacing")? as f64;
    let names = ["x spacing unit", "y spacing unit", "z spacing unit"];
    let mut units = Vec::new();
    for (k, name) in names.iter().enumerate() {
        let off = 180 + 16 * k;
        let text = b.text(off, 16, name)?;
        let s = scan_length_unit(&text)
            .ok_or_else(|| b.bad(off, format!("{name} '{text}' is not a length unit")))?;
        units.push((text, s));
    }
    let comment = b.u16le(334, "the comment size")? as usize;
    let private = b.u16le(336, "the private zone size")? as usize;
    let zoff = b.f32le(474, "z offset")? as f64;
    let (xoff, yoff) = (b.f32le(466, "x offset")? as f64, b.f32le(470, "y offset")? as f64);
    if !(dx.is_finite() && dx > 0.0 && dy.is_finite() && dy > 0.0) {
        return Err(b.bad(120, format!("x/y spacing {dx}, {dy} must be positive")));
    }
    if !(dz.is_finite() && dz != 0.0 && zoff.is_finite()) {
        return Err(
            b.bad(128, format!("z spacing {dz} and z offset {zoff} must be finite, spacing non-zero"))
        );
    }
    let start = HEADER + comment + private;
    let n = data_len(path, yres, xres, size)?;
    let data = b.take(start, n, &format!("the {xres} x {yres} {bits}-bit data"))?;
    let zs = units[2].1;
    let values: Vec<f64> = data
        .chunks_exact(size)
        .map(|c| {
            let raw = if size == 2 {
                i16::from_le_bytes([c[0], c[1]]) as i32
            } else {
                i32::from_le_bytes([c[0], c[1], c[2], c[3]])
            };
            if nm_flag != 0 && (raw < zmin || raw > zmax) {
                f64::NAN
            } else {
                (raw as f64 * dz + zoff) * zs
            }
        })
        .collect();
    let values = shape(path, yres, xres, values)?;
    let pitch = [dx * units[0].1, dy * units[1].1];
    let comment_text = String::from_utf8_lossy(&bytes[HEADER..HEADER + comment]).trim().to_string();
    let mut metadata = vec![
        ("object".to_string(), b.text(20, 30, "the object name")?),
        ("operator".to_string(), b.text(50, 30, "the operator name")?),
        ("bits".to_string(), bits.to_string()),
        ("z_spacing".to_string(), format!("{dz:e} {}", units[2].0)),
        ("z_offset".to_string(), format!("{zoff:e} {}", units[2].0)),
        ("xy_unit".to_string(), units[0].0.clone()),
        ("non_measured_flag".to_string(), nm_flag.to_string()),
    ];
    if !comment_text.is_empty() {
        metadata.push(("comment".to_string(), comment_text));
    }
    let raw = RawMap {
        values,
        kind: SampleKind::Float,
        pitch: Some(pitch),
        unit: Some(1.0),
        metadata,
        scale_hint: None,
    };
    let mut sr = ScanRaw::new(raw, ScanFormat::Sur);
    sr.origin = Some([xoff * units[0].1, yoff * units[1].1]);
    Ok(sr)
}

/// Encodes a minimal single-surface `.sur` (32-bit data, a z offset of 100 units, z step 0.5
/// unit, non-measured points as `zmin - 1`) with the unit strings in `unit_bytes` (e.g. Latin-1
/// `b"\xb5m"`) meaning `unit` metres, for tests. Heights in metres; NaN = non-measured.
pub fn encode(values: &ndarray::Array2<f64>, pitch_units: f64, unit_bytes: &[u8], unit: f64) -> Vec<u8> {
    encode_bits(values, pitch_units, unit_bytes, unit, 32)
}

/// As [`encode`], with 16- or 32-bit data (`bits`).
pub fn encode_bits(
    values: &ndarray::Array2<f64>,
    pitch_units: f64,
    unit_bytes: &[u8],
    unit: f64,
    bits: u16,
) -> Vec<u8> {
    let (r, c) = values.dim();
    let mut h = vec![0u8; HEADER];
    h[..12].copy_from_slice(b"DIGITAL SURF");
    h[14..16].copy_from_slice(&1u16.to_le_bytes());
    h[86..88].copy_from_slice(&1u16.to_le_bytes());
    h[98..100].copy_from_slice(&bits.to_le_bytes());
    let (zmin, zmax) = if bits == 16 { (-30000i32, 30000i32) } else { (-1_000_000i32, 1_000_000i32) };
    h[100..104].copy_from_slice(&zmin.to_le_bytes());
    h[104..108].copy_from_slice(&zmax.to_le_bytes());
    h[108..112].copy_from_slice(&(c as i32).to_le_bytes());
    h[112..116].copy_from_slice(&(r as i32).to_le_bytes());
    h[116..120].copy_from_slice(&((r * c) as i32).to_le_bytes());
    let dz = 0.5f32;
    for (off, v) in [(120, pitch_units as f32), (124, pitch_units as f32), (128, dz), (474, 100.0f32)] {
        h[off..off + 4].copy_from_slice(&v.to_le_bytes());
    }
    for k in 0..6 {
        h[180 + 16 * k..180 + 16 * k + unit_bytes.len()].copy_from_slice(unit_bytes);
    }
    for v in values {
        let raw = if v.is_nan() { zmin - 1 } else { ((v / unit - 100.0) / dz as f64).round() as i32 };
        if bits == 16 {
            h.extend_from_slice(&(raw as i16).to_le_bytes());
        } else {
            h.extend_from_slice(&raw.to_le_bytes());
        }
    }
    h
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latin1_and_utf8_micro_and_offset_and_cuts() {
        let mut v = ndarray::Array2::from_shape_fn((3, 4), |(i, j)| (i * 4 + j) as f64 * 1e-6);
        v[[2, 1]] = f64::NAN;
        for unit in [&b"\xb5m"[..], "µm".as_bytes()] {
            let b = encode(&v, 2.0, unit, 1e-6);
            let r = decode(Path::new("t.sur"), &b).unwrap();
            assert_eq!(r.raw.pitch, Some([2e-6, 2e-6]));
            for ((i, j), x) in v.indexed_iter() {
                let y = r.raw.values[[i, j]];
                assert!(x.is_nan() && y.is_nan() || (x - y).abs() < 1e-15, "{x} {y}");
            }
        }
        // 16-bit data in nanometres: heights 0..11 um would overflow; use 0..1.1 um.
        let small = v.mapv(|x| x * 0.1);
        let b16 = encode_bits(&small, 2.0, b"nm", 1e-9, 16);
        assert_eq!(b16.len(), HEADER + 2 * 12);
        let r = decode(Path::new("t16.sur"), &b16).unwrap();
        for ((i, j), x) in small.indexed_iter() {
            let y = r.raw.values[[i, j]];
            assert!(x.is_nan() && y.is_nan() || (x - y).abs() < 1e-18, "{x} {y}");
        }
        let b = encode(&v, 2.0, b"nm", 1e-9);
        for cut in 0..b.len() {
            let e = decode(Path::new("cut.sur"), &b[..cut]).unwrap_err().to_string();
            assert!(e.contains("cut.sur") && e.contains("byte offset"), "cut at {cut}: {e}");
        }
        let mut bad = b.clone();
        bad[98] = 8;
        assert!(decode(Path::new("x.sur"), &bad).unwrap_err().to_string().contains("byte offset 98"));
    }
}
