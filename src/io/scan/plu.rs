//! Sensofar PLu binary files (`.plu`, the SensoSCAN format of 2000 and its later revisions),
//! the topography.
//!
//! Little-endian. A 500-byte header, then the measurement:
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | 128 chars | date, as text |
//! | 128 | u32 | date, seconds since 1970 |
//! | 132 | 256 chars | user comment |
//! | 388, 392 | u32 | rows, columns of the calibration |
//! | 404, 408 | f32 | x and y pitch, micrometres per pixel |
//! | 428 | u32 | measurement type: 0 image, 1 profile, 2 multi-profile, 3 topography, 4 coordinates, 5 thickness, 6 custom |
//! | 432 | u32 | algorithm (0, 1 confocal intensity / gradient; 2, 3 interferometric PSI / VSI; ...) |
//! | 440 | u32 | objective code |
//! | 464 | u32 | numerical aperture code |
//! | 490 | u8 | format version (0: 2000, 255: 2006; later revisions write others) |
//! | 500 | u32, u32 | rows, columns of the data |
//! | 508 | rows x columns f32 | heights in micrometres, row by row; 1000001 = not measured |
//!
//! Later revisions append more (an intensity image) after the heights, which is left unread.
//! This is the layout Gwyddion's `sensofar` module reads; the reader is checked against
//! Gwyddion's and SurfaceTopography's reading of a real file.

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, shape, Bin, ScanFormat, ScanRaw};

const HEADER: usize = 500;
const NOT_MEASURED: f32 = 1_000_001.0;
const TOPOGRAPHY: u32 = 3;

/// Decodes a PLu file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    b.take(0, HEADER + 8, "the header")?;
    let date = b.text(0, 128, "the date")?;
    if date.is_empty() || !date.chars().all(|c| !c.is_control()) {
        return Err(b.signature(0, "not a Sensofar PLu file: the header does not start with a date"));
    }
    let kind = b.u32le(428, "the measurement type")?;
    if kind != TOPOGRAPHY {
        let name = match kind {
            0 => "an image",
            1 => "a profile",
            2 => "a multi-profile",
            4 => "coordinates",
            5 => "a thickness map",
            6 => "a custom measurement",
            _ => "an unknown measurement",
        };
        return Err(b.unsupported(428, format!("measurement type {kind} is {name}, not a topography (3)")));
    }
    let rows = b.u32le(HEADER, "the rows")? as usize;
    let cols = b.u32le(HEADER + 4, "the columns")? as usize;
    let need = data_len(path, rows, cols, 4)?;
    let data = b.take(HEADER + 8, need, &format!("the {cols} x {rows} heights"))?;
    let values: Vec<f64> = data
        .chunks_exact(4)
        .map(|c| {
            let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            if v == NOT_MEASURED || !v.is_finite() {
                f64::NAN
            } else {
                v as f64 * 1e-6
            }
        })
        .collect();
    let values = shape(path, rows, cols, values)?;
    let (px, py) = (b.f32le(404, "the x pitch")?.abs() as f64, b.f32le(408, "the y pitch")?.abs() as f64);
    let pitch = (px.is_finite() && px > 0.0 && py.is_finite() && py > 0.0).then_some([px * 1e-6, py * 1e-6]);
    let mut metadata = vec![
        ("date".to_string(), date),
        ("comment".to_string(), b.text(132, 256, "the comment")?),
        ("algorithm".to_string(), b.u32le(432, "the algorithm")?.to_string()),
        ("objective".to_string(), b.u32le(440, "the objective")?.to_string()),
        ("numerical_aperture_code".to_string(), b.u32le(464, "the numerical aperture")?.to_string()),
        ("format_version".to_string(), b.take(490, 1, "the version")?[0].to_string()),
    ];
    metadata.retain(|(_, v)| !v.is_empty());
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Plu);
    if pitch.is_none() {
        sr.warnings.push("the file states no usable pitch: pass `pitch`".to_string());
    }
    Ok(sr)
}

/// Writes a PLu file from the layout in the module docs (for tests): `heights` in metres, NaN
/// written as the non-measured marker, `pitch` in metres.
pub fn encode(heights: &ndarray::Array2<f64>, pitch: f64) -> Vec<u8> {
    let (rows, cols) = heights.dim();
    let mut b = vec![0u8; HEADER];
    b[..24].copy_from_slice(b"Mon Apr 19 11:40:13 2021");
    let put = |b: &mut Vec<u8>, off: usize, v: &[u8]| b[off..off + v.len()].copy_from_slice(v);
    put(&mut b, 388, &(rows as u32).to_le_bytes());
    put(&mut b, 392, &(cols as u32).to_le_bytes());
    put(&mut b, 404, &((pitch * 1e6) as f32).to_le_bytes());
    put(&mut b, 408, &((pitch * 1e6) as f32).to_le_bytes());
    put(&mut b, 428, &TOPOGRAPHY.to_le_bytes());
    b.extend_from_slice(&(rows as u32).to_le_bytes());
    b.extend_from_slice(&(cols as u32).to_le_bytes());
    for v in heights {
        let f = if v.is_nan() { NOT_MEASURED } else { (v * 1e6) as f32 };
        b.extend_from_slice(&f.to_le_bytes());
    }
    b
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_truncation_and_other_measurements() {
        let mut h = ndarray::Array2::from_shape_fn((3, 4), |(i, j)| 1e-7 * (10 * i + j) as f64);
        h[[2, 1]] = f64::NAN;
        let bytes = encode(&h, 0.5e-6);
        let p = Path::new("t.plu");
        let s = decode(p, &bytes).unwrap();
        for ((i, j), v) in s.raw.values.indexed_iter() {
            if (i, j) == (2, 1) {
                assert!(v.is_nan());
            } else {
                assert!((v - h[[i, j]]).abs() < 1e-13, "({i}, {j}): {v}");
            }
        }
        assert_eq!(s.raw.pitch, Some([0.5e-6; 2]));
        for cut in [10, 400, HEADER + 4, bytes.len() - 1] {
            let e = decode(p, &bytes[..cut]).unwrap_err().to_string();
            assert!(e.contains("t.plu") && e.contains("offset"), "{cut}: {e}");
        }
        let mut profile = bytes.clone();
        profile[428] = 1;
        let e = decode(p, &profile).unwrap_err().to_string();
        assert!(e.contains("byte offset 428") && e.contains("a profile"), "{e}");
        let mut binary = bytes;
        binary[0] = 7;
        assert!(decode(p, &binary).unwrap_err().to_string().contains("not a Sensofar PLu file"));
    }
}
