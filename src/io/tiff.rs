//! Grayscale TIFF height maps and masks (through the `tiff` crate).
//!
//! Reading: one single-channel (grayscale, BlackIsZero) image.
//! * 32-bit (or 64/16-bit) IEEE float samples are values in a length unit ([`SampleKind::Float`]);
//! * 8/16/32-bit integer samples are counts ([`SampleKind::Counts`]) that the caller scales with
//!   an explicit metres-per-count factor: TIFF has no standard field for a height scale, so a
//!   counts TIFF without one is refused rather than guessed (Gwyddion's 16-bit export is such a
//!   file).
//!
//! TIFF states neither pitch nor value unit in a standard way (X/YResolution are print
//! densities, often a default 72 dpi). Only files written by [`write_tiff_f32`] and its siblings
//! carry them: their `ImageDescription` starts with the line `doefab` followed by `key=value`
//! lines (`pitch_x`, `pitch_y` in metres, `unit`, then free text). Any other description is kept
//! as metadata and not interpreted.
//!
//! Writing: Deflate-compressed strips, no timestamps, deterministic bytes.

use std::io::Cursor;
use std::path::Path;

use ndarray::Array2;
use tiff::decoder::{Decoder, DecodingResult};
use tiff::encoder::colortype::{self, ColorType as EncColor};
use tiff::encoder::compression::DeflateLevel;
use tiff::encoder::{Compression, TiffEncoder, TiffValue};
use tiff::tags::{PhotometricInterpretation, Tag};
use tiff::ColorType;

use crate::error::{Error, Result};
use crate::io::atomic::write_bytes;
use crate::io::raw_map::{pitch_unit_from_text, Metadata, RawMap, SampleKind};

/// First line of the `ImageDescription` of TIFF files this module writes.
pub const DESCRIPTION_MARK: &str = "doefab";

/// Reads a grayscale TIFF height map (see the module docs).
pub fn read_tiff(path: &Path) -> Result<RawMap> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_tiff(path, &bytes)
}

/// Decodes the bytes of a TIFF file (see [`read_tiff`]); `path` names it in errors.
pub fn decode_tiff(path: &Path, bytes: &[u8]) -> Result<RawMap> {
    if bytes.len() < 4
        || !(bytes[..4] == *b"II*\0"
            || bytes[..4] == *b"MM\0*"
            || bytes[..4] == *b"II+\0"
            || bytes[..4] == *b"MM\0+")
    {
        return Err(Error::signature(path, "not a TIFF file: bad magic (expected II*\\0 or MM\\0*)"));
    }
    let run = || -> std::result::Result<RawMap, Error> {
        let fail = |what: &str, e: tiff::TiffError| Error::malformed(path, format!("TIFF: {what}: {e}"));
        let mut dec = Decoder::new(Cursor::new(bytes)).map_err(|e| fail("cannot read the header", e))?;
        let (w, h) = dec.dimensions().map_err(|e| fail("cannot read the dimensions", e))?;
        let color = dec.colortype().map_err(|e| fail("cannot read the colour type", e))?;
        let bits = match color {
            ColorType::Gray(b) => b,
            other => {
                return Err(Error::unsupported(
                    path,
                    format!("is a {other:?} image; a height map must be single-channel grayscale"),
                ))
            }
        };
        let photometric = dec.find_tag_unsigned::<u16>(Tag::PhotometricInterpretation).ok().flatten();
        if photometric == Some(PhotometricInterpretation::WhiteIsZero.to_u16()) {
            return Err(Error::unsupported(
                path,
                "is stored WhiteIsZero (inverted); a height map must be BlackIsZero",
            ));
        }
        let description = match dec.find_tag(Tag::ImageDescription) {
            Ok(Some(v)) => v.into_string().ok(),
            _ => None,
        };
        let data = dec.read_image().map_err(|e| fail("cannot read the image data", e))?;
        if dec.more_images() {
            return Err(Error::unsupported(path, "holds several images; a height map file holds one"));
        }
        let (kind, samples): (SampleKind, Vec<f64>) = match data {
            DecodingResult::F32(v) => (SampleKind::Float, v.into_iter().map(f64::from).collect()),
            DecodingResult::F64(v) => (SampleKind::Float, v),
            DecodingResult::F16(v) => (SampleKind::Float, v.into_iter().map(|x| x.to_f64()).collect()),
            DecodingResult::U8(v) => (SampleKind::Counts { bits }, v.into_iter().map(f64::from).collect()),
            DecodingResult::U16(v) => (SampleKind::Counts { bits }, v.into_iter().map(f64::from).collect()),
            DecodingResult::U32(v) => (SampleKind::Counts { bits }, v.into_iter().map(f64::from).collect()),
            DecodingResult::I8(v) => (SampleKind::Counts { bits }, v.into_iter().map(f64::from).collect()),
            DecodingResult::I16(v) => (SampleKind::Counts { bits }, v.into_iter().map(f64::from).collect()),
            DecodingResult::I32(v) => (SampleKind::Counts { bits }, v.into_iter().map(f64::from).collect()),
            DecodingResult::U64(_) | DecodingResult::I64(_) => {
                return Err(Error::unsupported(
                    path,
                    "64-bit integer samples are not supported for height maps",
                ))
            }
        };
        let (rows, cols) = (h as usize, w as usize);
        if rows == 0 || cols == 0 {
            return Err(Error::malformed(path, "the image is empty"));
        }
        let values = Array2::from_shape_vec((rows, cols), samples).map_err(|_| {
            Error::malformed(
                path,
                format!("the decoded samples do not fill {cols} x {rows} (bits per sample {bits})"),
            )
        })?;
        let (mut pitch, mut unit, mut metadata) = (None, None, Vec::new());
        match description {
            Some(d) if d.lines().next().map(str::trim) == Some(DESCRIPTION_MARK) => {
                for line in d.lines().skip(1).filter(|l| !l.trim().is_empty()) {
                    let (k, v) = line.split_once('=').ok_or_else(|| {
                        Error::malformed(path, format!("ImageDescription line '{line}' is not key=value"))
                    })?;
                    metadata.push((k.trim().to_string(), v.trim().to_string()));
                }
                (pitch, unit) = pitch_unit_from_text(path, &metadata)?;
            }
            Some(d) => metadata.push(("ImageDescription".to_string(), d)),
            None => {}
        }
        let scale_hint = matches!(kind, SampleKind::Counts { .. })
            .then(|| "TIFF has no standard height-scale field, so none is read from the file".to_string());
        Ok(RawMap { values, kind, pitch, unit, metadata, scale_hint })
    };
    // The decoder is third-party code fed with user bytes: a panic in it becomes an error.
    std::panic::catch_unwind(run)
        .unwrap_or_else(|_| Err(Error::malformed(path, "TIFF: the decoder failed on malformed data")))
}

/// The `ImageDescription` text for `meta`: the mark line, then `key=value` lines.
fn description(path: &Path, meta: &Metadata) -> Result<String> {
    let mut text = String::from(DESCRIPTION_MARK);
    for (k, v) in meta.key_values(path)? {
        let bad = |s: &str| !s.is_ascii() || s.contains(['\n', '\r', '\0']);
        if bad(&k) || bad(&v) || k.contains('=') || k.trim().is_empty() {
            return Err(Error::param(
                "metadata",
                format!("'{k}' = '{v}' cannot be stored in a TIFF description (ASCII, one line, no '=' in the key)"),
            ));
        }
        text.push('\n');
        text.push_str(&format!("{k}={v}"));
    }
    Ok(text)
}

fn encode<C>(path: &Path, dim: (usize, usize), data: &[C::Inner], meta: &Metadata) -> Result<Vec<u8>>
where
    C: EncColor,
    [C::Inner]: TiffValue,
{
    let (h, w) = dim;
    let (w32, h32) = match (u32::try_from(w), u32::try_from(h)) {
        (Ok(a), Ok(b)) if a > 0 && b > 0 => (a, b),
        _ => return Err(Error::param("image", format!("{h} x {w} cannot be stored as a TIFF image"))),
    };
    let desc = description(path, meta)?;
    let fail = |e: tiff::TiffError| Error::encoding(path, format!("TIFF encoding failed: {e}"));
    let mut buf = Cursor::new(Vec::new());
    {
        let mut enc = TiffEncoder::new(&mut buf)
            .map_err(fail)?
            .with_compression(Compression::Deflate(DeflateLevel::Balanced));
        let mut img = enc.new_image::<C>(w32, h32).map_err(fail)?;
        img.encoder().write_tag(Tag::ImageDescription, desc.as_str()).map_err(fail)?;
        img.write_data(data).map_err(fail)?;
    }
    Ok(buf.into_inner())
}

/// Writes a 32-bit float grayscale TIFF (row 0 at the top), atomically.
pub fn write_tiff_f32(path: &Path, values: &Array2<f32>, meta: &Metadata) -> Result<()> {
    let data: Vec<f32> = values.iter().copied().collect();
    write_bytes(path, &encode::<colortype::Gray32Float>(path, values.dim(), &data, meta)?)
}

/// Writes a 16-bit grayscale TIFF (e.g. a grayscale lithography mask), atomically.
pub fn write_tiff_u16(path: &Path, values: &Array2<u16>, meta: &Metadata) -> Result<()> {
    let data: Vec<u16> = values.iter().copied().collect();
    write_bytes(path, &encode::<colortype::Gray16>(path, values.dim(), &data, meta)?)
}

/// Writes an 8-bit grayscale TIFF, atomically.
pub fn write_tiff_u8(path: &Path, values: &Array2<u8>, meta: &Metadata) -> Result<()> {
    let data: Vec<u8> = values.iter().copied().collect();
    write_bytes(path, &encode::<colortype::Gray8>(path, values.dim(), &data, meta)?)
}

/// Encodes a 32-bit float grayscale TIFF in memory (what [`write_tiff_f32`] writes).
pub fn encode_tiff_f32(path: &Path, values: &Array2<f32>, meta: &Metadata) -> Result<Vec<u8>> {
    let data: Vec<f32> = values.iter().copied().collect();
    encode::<colortype::Gray32Float>(path, values.dim(), &data, meta)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn float_round_trip_keeps_pitch_unit_and_nan() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.tif");
        let mut a = Array2::from_shape_fn((5, 7), |(i, j)| (i as f32 - 2.0) * 0.1 + j as f32 * 0.01);
        a[[2, 3]] = f32::NAN;
        write_tiff_f32(&p, &a, &Metadata::heights([3e-6, 2e-6]).with("note", "x")).unwrap();
        let r = read_tiff(&p).unwrap();
        assert_eq!(r.kind, SampleKind::Float);
        assert!(r.values[[2, 3]].is_nan());
        for ((i, j), v) in a.indexed_iter() {
            if !v.is_nan() {
                assert_eq!(r.values[[i, j]], *v as f64);
            }
        }
        assert_eq!(r.pitch, Some([3e-6, 2e-6]));
        assert_eq!(r.unit, Some(1.0));
        assert!(r.metadata.contains(&("note".into(), "x".into())));
    }

    #[test]
    fn counts_round_trip_as_counts() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m16.tiff");
        let a = Array2::from_shape_fn((4, 9), |(i, j)| (i * 9000 + j * 7) as u16);
        write_tiff_u16(&p, &a, &Metadata::default()).unwrap();
        let r = read_tiff(&p).unwrap();
        assert_eq!(r.kind, SampleKind::Counts { bits: 16 });
        assert_eq!(r.values, a.mapv(f64::from));
        assert_eq!((r.pitch, r.unit), (None, None));
        let q = dir.path().join("m8.tif");
        let b = Array2::from_shape_fn((3, 2), |(i, j)| (i * 100 + j) as u8);
        write_tiff_u8(&q, &b, &Metadata::default()).unwrap();
        let r = read_tiff(&q).unwrap();
        assert_eq!(r.kind, SampleKind::Counts { bits: 8 });
        assert_eq!(r.values, b.mapv(f64::from));
    }

    #[test]
    fn deterministic_and_every_cut_is_an_error() {
        let a = Array2::from_shape_fn((6, 6), |(i, j)| (i * j) as f32);
        let x = encode_tiff_f32(Path::new("a.tif"), &a, &Metadata::heights([1e-6; 2])).unwrap();
        assert_eq!(x, encode_tiff_f32(Path::new("a.tif"), &a, &Metadata::heights([1e-6; 2])).unwrap());
        for cut in 0..x.len() {
            let e = decode_tiff(Path::new("cut.tif"), &x[..cut]);
            assert!(e.unwrap_err().to_string().contains("cut.tif"), "cut at {cut}");
        }
        let bad = Metadata::default().with("a=b", "c");
        assert!(encode_tiff_f32(Path::new("a.tif"), &a, &bad).is_err());
    }
}
