//! Grayscale PNG height maps and masks (through the `png` crate).
//!
//! Reading: an 8- or 16-bit grayscale PNG holds integer counts ([`SampleKind::Counts`]). A
//! height needs an explicit scale (metres per count, plus an optional offset) from the caller:
//! PNG's one calibration chunk, `pCAL`, is not applied because writers disagree on it (the PNG
//! specification's linear form is `p0 + p1 * X / (x1 - x0)`, but Gwyddion 2.62 stores the
//! per-count step as `p1`). What the file's metadata suggests is reported in the error that
//! asks for the scale.
//!
//! Pitch is read from text chunks when present: our keys `pitch_x`, `pitch_y` (or `pitch`), in
//! metres, else Gwyddion's `Gwy::XReal` / `Gwy::YReal` (the full field width and height, with
//! `Gwy::XYUnit` = `m`), divided by the number of columns / rows.
//!
//! Writing: 8/16-bit grayscale (and 8-bit RGB for pictures) with text chunks (`tEXt`, or `iTXt` for text beyond Latin-1) in
//! the order given, before the image data; no time chunk; deterministic bytes.

use std::io::Cursor;
use std::path::Path;

use ndarray::{Array2, Array3};

use crate::error::{Error, Result};
use crate::io::atomic::write_bytes;
use crate::io::raw_map::{pitch_unit_from_text, Metadata, RawMap, SampleKind};

const SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];

/// Reads a grayscale PNG height map (see the module docs).
pub fn read_png(path: &Path) -> Result<RawMap> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_png(path, &bytes)
}

/// Decodes the bytes of a PNG file (see [`read_png`]); `path` names it in errors.
pub fn decode_png(path: &Path, bytes: &[u8]) -> Result<RawMap> {
    if bytes.len() < 8 || bytes[..8] != SIGNATURE {
        return Err(Error::signature(path, "not a PNG file: bad signature"));
    }
    let run = || -> Result<RawMap> {
        let fail = |what: &str, e: png::DecodingError| Error::malformed(path, format!("PNG: {what}: {e}"));
        let mut dec = png::Decoder::new(Cursor::new(bytes));
        dec.set_transformations(png::Transformations::IDENTITY);
        let mut reader = dec.read_info().map_err(|e| fail("cannot read the header", e))?;
        let (w, h, color, depth) = {
            let info = reader.info();
            (info.width as usize, info.height as usize, info.color_type, info.bit_depth)
        };
        if color != png::ColorType::Grayscale {
            return Err(Error::unsupported(
                path,
                format!("is a {color:?} PNG; a height map must be single-channel grayscale"),
            ));
        }
        let bits: u8 = match depth {
            png::BitDepth::Eight => 8,
            png::BitDepth::Sixteen => 16,
            d => {
                return Err(Error::unsupported(
                    path,
                    format!("has {d:?} bit depth; a height map PNG must have 8 or 16 bits per sample"),
                ))
            }
        };
        // The header's size is a claim: deflate compresses at most 1032:1 (RFC 1951: a 258-byte
        // match in at most 2 bits), so a file cannot hold more raw image bytes than that.
        let raw = (w * bits as usize / 8 + 1) * h;
        if raw / 1032 > bytes.len() {
            return Err(Error::malformed(
                path,
                format!(
                    "byte offset 16: IHDR says {w} x {h} samples of {bits} bits ({raw} bytes), more than \
                     a {}-byte file can hold at deflate's best ratio (1032:1)",
                    bytes.len()
                ),
            )
            .at(16));
        }
        let size = reader.output_buffer_size().ok_or_else(|| {
            Error::malformed(
                path,
                format!("byte offset 16: IHDR says {w} x {h}, too large an image for this machine"),
            )
            .at(16)
        })?;
        let mut buf = vec![0u8; size];
        let frame = reader.next_frame(&mut buf).map_err(|e| fail("cannot read the image data", e))?;
        reader.finish().map_err(|e| fail("cannot read the chunks after the image data", e))?;
        let line = frame.line_size;
        let mut samples = Vec::with_capacity(w * h);
        for row in buf.chunks_exact(line).take(h) {
            if bits == 16 {
                samples.extend(row[..2 * w].chunks_exact(2).map(|b| u16::from_be_bytes([b[0], b[1]]) as f64));
            } else {
                samples.extend(row[..w].iter().map(|&b| b as f64));
            }
        }
        let values = Array2::from_shape_vec((h, w), samples)
            .map_err(|_| Error::malformed(path, format!("the image data does not fill {w} x {h}")))?;
        let mut metadata = Vec::new();
        let info = reader.info();
        for t in &info.uncompressed_latin1_text {
            metadata.push((t.keyword.clone(), t.text.clone()));
        }
        for t in &info.compressed_latin1_text {
            metadata.push((t.keyword.clone(), t.get_text().map_err(|e| fail("bad zTXt chunk", e))?));
        }
        for t in &info.utf8_text {
            metadata.push((t.keyword.clone(), t.get_text().map_err(|e| fail("bad iTXt chunk", e))?));
        }
        let (mut pitch, _) = pitch_unit_from_text(path, &metadata)?;
        let get = |k: &str| metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.trim());
        let num = |k: &str| get(k).and_then(|v| v.parse::<f64>().ok()).filter(|v| v.is_finite());
        if pitch.is_none() && get("Gwy::XYUnit") == Some("m") {
            if let (Some(xr), Some(yr)) = (num("Gwy::XReal"), num("Gwy::YReal")) {
                if xr > 0.0 && yr > 0.0 {
                    pitch = Some([xr / w as f64, yr / h as f64]);
                }
            }
        }
        let full = if bits == 16 { 65535.0 } else { 255.0 };
        let mut hints = Vec::new();
        if let (Some(lo), Some(hi), Some("m")) = (num("Gwy::ZMin"), num("Gwy::ZMax"), get("Gwy::ZUnit")) {
            hints.push(format!(
                "its Gwyddion text says ZMin = {lo:e} m, ZMax = {hi:e} m: if the counts span the full \
                 range, that is `z_scale` {:e}m, `z_offset` {lo:e}m",
                (hi - lo) / full
            ));
        }
        for key in ["z_scale", "z_offset"] {
            if let Some(v) = get(key) {
                hints.push(format!("its text says {key} = {v}"));
            }
        }
        let scale_hint = (!hints.is_empty()).then(|| hints.join("; "));
        Ok(RawMap { values, kind: SampleKind::Counts { bits }, pitch, unit: None, metadata, scale_hint })
    };
    // The decoder is third-party code fed with user bytes: a panic in it becomes an error.
    std::panic::catch_unwind(run)
        .unwrap_or_else(|_| Err(Error::malformed(path, "PNG: the decoder failed on malformed data")))
}

fn encode(
    path: &Path,
    dim: (usize, usize),
    depth: png::BitDepth,
    color: png::ColorType,
    data: &[u8],
    meta: &Metadata,
) -> Result<Vec<u8>> {
    let (h, w) = dim;
    let (w32, h32) = match (u32::try_from(w), u32::try_from(h)) {
        (Ok(a), Ok(b)) if a > 0 && b > 0 => (a, b),
        _ => return Err(Error::param("image", format!("{h} x {w} cannot be stored as a PNG image"))),
    };
    let fail = |e: png::EncodingError| Error::encoding(path, format!("PNG encoding failed: {e}"));
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, w32, h32);
        enc.set_color(color);
        enc.set_depth(depth);
        enc.set_compression(png::Compression::Fast);
        for (k, v) in meta.key_values(path)? {
            let latin1 = |s: &str| s.chars().all(|c| (c as u32) < 256);
            if k.is_empty() || k.len() > 79 || !latin1(&k) {
                return Err(Error::param(
                    "metadata",
                    format!("PNG text key '{k}' must be 1-79 Latin-1 characters"),
                ));
            }
            if latin1(&v) {
                enc.add_text_chunk(k, v).map_err(fail)?;
            } else {
                enc.add_itxt_chunk(k, v).map_err(fail)?;
            }
        }
        let mut writer = enc.write_header().map_err(fail)?;
        writer.write_image_data(data).map_err(fail)?;
        writer.finish().map_err(fail)?;
    }
    Ok(out)
}

/// Encodes a 16-bit grayscale PNG in memory (what [`write_png_u16`] writes).
pub fn encode_png_u16(path: &Path, values: &Array2<u16>, meta: &Metadata) -> Result<Vec<u8>> {
    // Samples to big-endian bytes, in parallel chunks.
    use rayon::prelude::*;
    const CHUNK: usize = 1 << 16;
    let src = values.as_standard_layout();
    let mut data = vec![0u8; 2 * values.len()];
    match src.as_slice() {
        Some(flat) => data.par_chunks_mut(2 * CHUNK).zip(flat.par_chunks(CHUNK)).for_each(|(out, vals)| {
            for (o, v) in out.chunks_exact_mut(2).zip(vals) {
                o.copy_from_slice(&v.to_be_bytes());
            }
        }),
        None => {
            for (o, v) in data.chunks_exact_mut(2).zip(src.iter()) {
                o.copy_from_slice(&v.to_be_bytes());
            }
        }
    }
    encode(path, values.dim(), png::BitDepth::Sixteen, png::ColorType::Grayscale, &data, meta)
}

/// Encodes an 8-bit grayscale PNG in memory (what [`write_png_u8`] writes).
pub fn encode_png_u8(path: &Path, values: &Array2<u8>, meta: &Metadata) -> Result<Vec<u8>> {
    let data: Vec<u8> = values.iter().copied().collect();
    encode(path, values.dim(), png::BitDepth::Eight, png::ColorType::Grayscale, &data, meta)
}

/// Writes a 16-bit grayscale PNG (row 0 at the top) with `meta` as text chunks, atomically.
pub fn write_png_u16(path: &Path, values: &Array2<u16>, meta: &Metadata) -> Result<()> {
    write_bytes(path, &encode_png_u16(path, values, meta)?)
}

/// Writes an 8-bit grayscale PNG with `meta` as text chunks, atomically.
pub fn write_png_u8(path: &Path, values: &Array2<u8>, meta: &Metadata) -> Result<()> {
    write_bytes(path, &encode_png_u8(path, values, meta)?)
}

/// Encodes an 8-bit picture `(H, W, C)` in memory: grayscale for C = 1, RGB for C = 3.
pub fn encode_png_image_u8(path: &Path, values: &Array3<u8>, meta: &Metadata) -> Result<Vec<u8>> {
    let (h, w, c) = values.dim();
    let color = match c {
        1 => png::ColorType::Grayscale,
        3 => png::ColorType::Rgb,
        _ => {
            return Err(Error::param(
                "image",
                format!(
                    "{} has {c} channels; an 8-bit PNG picture is grayscale (1) or RGB (3)",
                    path.display()
                ),
            ))
        }
    };
    let data: Vec<u8> = values.iter().copied().collect();
    encode(path, (h, w), png::BitDepth::Eight, color, &data, meta)
}

/// Writes an 8-bit grayscale or RGB picture (what [`encode_png_image_u8`] encodes) with `meta`
/// as text chunks, atomically.
pub fn write_png_image_u8(path: &Path, values: &Array3<u8>, meta: &Metadata) -> Result<()> {
    write_bytes(path, &encode_png_image_u8(path, values, meta)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_16_and_8_bit_with_text() {
        let a = Array2::from_shape_fn((5, 9), |(i, j)| (i * 13000 + j * 511) as u16);
        let meta = Metadata::heights([2e-6, 3e-6]).with("z_scale", "1e-10 m").with("note", "µ-lens");
        let bytes = encode_png_u16(Path::new("a.png"), &a, &meta).unwrap();
        assert_eq!(bytes, encode_png_u16(Path::new("a.png"), &a, &meta).unwrap());
        let r = decode_png(Path::new("a.png"), &bytes).unwrap();
        assert_eq!(r.kind, SampleKind::Counts { bits: 16 });
        assert_eq!(r.values, a.mapv(f64::from));
        assert_eq!(r.pitch, Some([2e-6, 3e-6]));
        assert!(r.metadata.contains(&("note".into(), "µ-lens".into())));
        assert!(r.scale_hint.unwrap().contains("z_scale = 1e-10 m"));
        let b = Array2::from_shape_fn((3, 4), |(i, j)| (i * 80 + j) as u8);
        let bytes = encode_png_u8(Path::new("b.png"), &b, &Metadata::default()).unwrap();
        let r = decode_png(Path::new("b.png"), &bytes).unwrap();
        assert_eq!(r.kind, SampleKind::Counts { bits: 8 });
        assert_eq!(r.values, b.mapv(f64::from));
        assert_eq!(r.pitch, None);
    }

    #[test]
    fn rgb_and_gray_pictures_read_back_through_the_png_crate() {
        let rgb = Array3::from_shape_fn((2, 3, 3), |(i, j, c)| (i * 100 + j * 10 + c) as u8);
        let meta = Metadata::default().with("ev", "-2");
        let bytes = encode_png_image_u8(Path::new("p.png"), &rgb, &meta).unwrap();
        let mut reader = png::Decoder::new(Cursor::new(bytes)).read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let frame = reader.next_frame(&mut buf).unwrap();
        assert_eq!((frame.width, frame.height, frame.color_type), (3, 2, png::ColorType::Rgb));
        assert_eq!(&buf[..frame.buffer_size()], rgb.as_slice().unwrap());
        let text = &reader.info().uncompressed_latin1_text;
        assert_eq!((text[0].keyword.as_str(), text[0].text.as_str()), ("ev", "-2"));
        let gray = Array3::from_shape_fn((2, 3, 1), |(i, j, _)| (i * 3 + j) as u8);
        let r =
            decode_png(Path::new("g.png"), &encode_png_image_u8(Path::new("g.png"), &gray, &meta).unwrap());
        assert_eq!(r.unwrap().values, gray.index_axis(ndarray::Axis(2), 0).mapv(f64::from));
        let e = encode_png_image_u8(Path::new("two.png"), &Array3::zeros((2, 2, 2)), &meta).unwrap_err();
        assert!(e.to_string().contains("two.png") && e.to_string().contains("2 channels"), "{e}");
    }

    #[test]
    fn every_cut_is_an_error_naming_the_file() {
        let a = Array2::from_shape_fn((6, 7), |(i, j)| (i * 1000 + j) as u16);
        let bytes = encode_png_u16(Path::new("a.png"), &a, &Metadata::heights([1e-6; 2])).unwrap();
        for cut in 0..bytes.len() {
            let e = decode_png(Path::new("cut.png"), &bytes[..cut]);
            assert!(e.unwrap_err().to_string().contains("cut.png"), "cut at {cut}");
        }
    }
}
