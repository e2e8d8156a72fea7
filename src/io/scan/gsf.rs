//! Gwyddion Simple Field (`.gsf`), after the format's description in the Gwyddion user guide
//! ("Gwyddion Simple Field", file format 1.0).
//!
//! Layout: the line `Gwyddion Simple Field 1.0`, then `Key = Value` lines (UTF-8), then 1 to 4
//! NUL bytes so that the data starts at a multiple of 4 bytes, then `XRes * YRes` IEEE single
//! floats, little endian, row by row (first row = top). Keys used: `XRes`, `YRes` (required),
//! `XReal`, `YReal` (field size; pitch = XReal / XRes), `XOffset`, `YOffset`, `XYUnits`,
//! `ZUnits`. NaN values are non-measured points. Without `XYUnits` (or `ZUnits`) the file states
//! no length unit for the field (or heights), and the caller must give one.

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, scan_length_unit, shape, Bin, ScanFormat, ScanRaw};

/// First line of a GSF file.
pub const MAGIC: &str = "Gwyddion Simple Field 1.0";

/// Decodes a GSF file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let head = format!("{MAGIC}\n");
    if !bytes.starts_with(head.as_bytes()) {
        if head.as_bytes().starts_with(bytes) {
            return Err(Error::truncated(
                path,
                bytes.len() as u64,
                format!("truncated at byte offset {} inside the '{MAGIC}' line", bytes.len()),
            ));
        }
        return Err(Error::signature(
            path,
            format!("byte offset 0: not a GSF file: it does not start with '{MAGIC}'"),
        )
        .at(0));
    }
    let nul = bytes.iter().position(|&b| b == 0).ok_or_else(|| {
        Error::truncated(
            path,
            bytes.len() as u64,
            format!("truncated at byte offset {}: the header never ends (no NUL padding)", bytes.len()),
        )
    })?;
    let header = std::str::from_utf8(&bytes[..nul]).map_err(|e| {
        let at = e.valid_up_to();
        Error::malformed(path, format!("byte offset {at}: header is not UTF-8")).at(at as u64)
    })?;
    let start = (nul / 4 + 1) * 4;
    let bin = Bin::new(path, bytes);
    let pad = bin.take(nul, start - nul, "the NUL padding after the header")?;
    if let Some(k) = pad.iter().position(|&b| b != 0) {
        return Err(bin.bad(nul + k, "expected NUL padding between the header and the data"));
    }
    let mut metadata = Vec::new();
    for (n, line) in header.lines().enumerate().skip(1) {
        if line.trim().is_empty() {
            continue;
        }
        let (k, v) = line.split_once('=').ok_or_else(|| {
            Error::malformed(path, format!("header line {}: '{line}' is not 'Key = Value'", n + 1))
        })?;
        if metadata.iter().any(|(key, _)| key == k.trim()) {
            return Err(Error::malformed(
                path,
                format!("header line {}: key '{}' is given twice", n + 1, k.trim()),
            ));
        }
        metadata.push((k.trim().to_string(), v.trim().to_string()));
    }
    let get = |k: &str| metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.as_str());
    let num =
        |k: &str| -> Result<Option<f64>> {
            match get(k) {
                None => Ok(None),
                Some(v) => v.parse::<f64>().ok().filter(|x| x.is_finite()).map(Some).ok_or_else(|| {
                    Error::malformed(path, format!("header '{k} = {v}' is not a finite number"))
                }),
            }
        };
    let res = |k: &str| -> Result<usize> {
        let v = get(k).ok_or_else(|| Error::malformed(path, format!("header lacks the required '{k}'")))?;
        v.parse::<usize>()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| Error::malformed(path, format!("header '{k} = {v}' is not a positive integer")))
    };
    let (xres, yres) = (res("XRes")?, res("YRes")?);
    let nbytes = data_len(path, yres, xres, 4)?;
    let data = bin.take(start, nbytes, &format!("the {xres} x {yres} float data"))?;
    if bytes.len() > start + nbytes {
        return Err(bin.bad(
            start + nbytes,
            format!("{} bytes follow the {xres} x {yres} float data", bytes.len() - start - nbytes),
        ));
    }
    let values: Vec<f64> =
        data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64).collect();
    let values = shape(path, yres, xres, values)?;
    let xy =
        match get("XYUnits") {
            Some(u) => Some(scan_length_unit(u).ok_or_else(|| {
                Error::malformed(path, format!("header 'XYUnits = {u}' is not a length unit"))
            })?),
            None => None,
        };
    let unit = match get("ZUnits") {
        Some(u) => Some(scan_length_unit(u).ok_or_else(|| {
            Error::malformed(
                path,
                format!("header 'ZUnits = {u}' is not a length unit (a height map needs one)"),
            )
        })?),
        None => None,
    };
    let (xreal, yreal) = (num("XReal")?, num("YReal")?);
    let pitch = match (xy, xreal, yreal) {
        (Some(s), Some(xr), Some(yr)) if xr > 0.0 && yr > 0.0 => {
            Some([xr * s / xres as f64, yr * s / yres as f64])
        }
        (Some(_), Some(_), Some(_)) => {
            return Err(Error::malformed(path, "header XReal/YReal must be positive"));
        }
        _ => None,
    };
    let (xo, yo) = (num("XOffset")?.unwrap_or(0.0), num("YOffset")?.unwrap_or(0.0));
    let mut sr = ScanRaw::new(
        RawMap { values, kind: SampleKind::Float, pitch, unit, metadata, scale_hint: None },
        ScanFormat::Gsf,
    );
    if let (Some(s), Some(p)) = (xy, pitch) {
        // Gwyddion's offset is the corner of the field; sample centres sit half a pitch in.
        sr.origin = Some([xo * s + 0.5 * p[0], yo * s + 0.5 * p[1]]);
    }
    Ok(sr)
}

/// Encodes a GSF file (tests and synthetic scans): heights in metres, NaN for non-measured.
pub fn encode(values: &ndarray::Array2<f64>, pitch: [f64; 2]) -> Vec<u8> {
    let (r, c) = values.dim();
    let mut out = format!(
        "{MAGIC}\nXRes = {c}\nYRes = {r}\nXReal = {:e}\nYReal = {:e}\nXYUnits = m\nZUnits = m\n",
        pitch[0] * c as f64,
        pitch[1] * r as f64
    )
    .into_bytes();
    let pad = 4 - out.len() % 4;
    out.extend(std::iter::repeat_n(0u8, pad));
    for v in values {
        out.extend_from_slice(&(*v as f32).to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_every_cut_fails() {
        let mut v = ndarray::Array2::from_shape_fn((3, 5), |(i, j)| (i * 5 + j) as f64 * 1e-8);
        v[[1, 2]] = f64::NAN;
        let b = encode(&v, [1e-6, 2e-6]);
        let r = decode(Path::new("t.gsf"), &b).unwrap();
        assert_eq!(r.raw.pitch, Some([1e-6, 2e-6]));
        assert_eq!(r.raw.unit, Some(1.0));
        assert!(r.raw.values[[1, 2]].is_nan());
        assert_eq!(r.raw.values[[2, 4]], (14.0e-8f64 as f32) as f64);
        for cut in 0..b.len() {
            let e = decode(Path::new("cut.gsf"), &b[..cut]).unwrap_err().to_string();
            assert!(e.contains("cut.gsf"), "cut at {cut}: {e}");
        }
        let cut = b.len() - 6;
        let e = decode(Path::new("cut.gsf"), &b[..cut]).unwrap_err().to_string();
        assert!(e.contains(&format!("byte offset {cut}")), "{e}");
    }
}
