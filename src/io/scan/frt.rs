//! FRT MicroProf binary files (`.frt`, "FRTM_GLIDERV" versions 1.00 and 1.01): the topography.
//!
//! Layout (Gwyddion's `microprof` module and SurfaceTopography's `FRT` reader, which follow
//! FRT's description of the blocks; little-endian):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 16 | magic `FRTM_GLIDERV` and the version `1.00` or `1.01` |
//! | 16 | 2 | u16: the number of blocks |
//! | 18 | | blocks to the end of the file: u16 type, the payload size (u32 in 1.00, u64 in 1.01), the payload |
//!
//! Blocks read (any order; each at most once; others are skipped):
//!
//! | type | payload |
//! |---|---|
//! | 0x000b | the image of a single-image file: rows of u16 (16 bits) or i32 (32 bits) counts |
//! | 0x0065 | description (text) |
//! | 0x0066 | columns, rows, bits per count (16 or 32), u32 each |
//! | 0x0067 | x and y range (f64, metres: the scanned field; the pitch is range / count), x and y offset of the centre (f64, metres), y/x range factor (f64), scan direction (u32) |
//! | 0x006c | measuring range code (u32), z scale (f64, metres per count) |
//! | 0x0072 | measurement start and end (u32, seconds since 1970, UTC), duration (u32, s) |
//! | 0x0077 | parameter set name (text) |
//! | 0x007d | multi-image block: four u16 buffer ids, then images, each a u32 type, u32 columns, rows and bits per count, and the counts |
//!
//! The first stored row is the bottom of the image (both readers turn it over); the count 1
//! marks a point not measured. The image read is block 0x000b's when present (the topography;
//! a multi-image block repeats it), else the first image of block 0x007d whose type is
//! topography (flag 0x0004; types from 0x4000 up are fits, not heights), else the first
//! thickness, sample thickness or AFM image (flags 0x0080, 0x0800, 0x1000). The other images
//! (intensity, a second sensor) are skipped with a warning naming them. Heights are the counts
//! times the z scale.

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, shape, Bin, ScanFormat, ScanRaw};

/// The part of the magic before the version.
pub const MAGIC: &[u8; 12] = b"FRTM_GLIDERV";
/// The count that marks a point not measured.
const NOT_MEASURED: i64 = 1;

const TOPOGRAPHY: u32 = 0x0004;
const HEIGHT_LIKE: u32 = 0x0080 | 0x0800 | 0x1000;
const TYPE_MASK: u32 = 0x0000_ffdf;
const FIT: u32 = 0x4000;
const BOTTOM_SENSOR: u32 = 0x1000_0000;

/// True when `head` starts as an FRT binary file does.
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(MAGIC)
}

/// One image: its type, size, bits per count, and the byte offset of its counts.
#[derive(Debug, Clone, Copy)]
struct Image {
    kind: u32,
    cols: usize,
    rows: usize,
    bits: u32,
    at: usize,
}

/// A name for an image type, as the instrument software gives it.
fn type_name(kind: u32) -> String {
    let base = kind & TYPE_MASK;
    let name = if base >= FIT {
        "Fit"
    } else {
        [
            (0x0004, "Topography"),
            (0x0080, "Thickness"),
            (0x0800, "Sample thickness"),
            (0x1000, "AFM"),
            (0x0001, "Piezo"),
            (0x0002, "Intensity"),
            (0x0008, "Real part"),
            (0x0010, "Imaginary part"),
            (0x0040, "Camera"),
            (0x0200, "Absolute value"),
            (0x0400, "Phase"),
            (0x2000, "Quality"),
        ]
        .iter()
        .find(|(f, _)| base & f != 0)
        .map_or("Unknown", |(_, n)| n)
    };
    let sensor = if kind & BOTTOM_SENSOR != 0 { "bottom" } else { "top" };
    format!("{name} ({sensor} sensor) {}", ((kind & 0x0f00_0000) >> 24) + 1)
}

/// Decodes an `.frt` file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    let n = bytes.len().min(MAGIC.len());
    if bytes[..n] != MAGIC[..n] {
        if bytes.starts_with(b"HeaderLines=") {
            return Err(
                b.bad(0, "a MicroProf text export, not the binary .frt format: read it as a text matrix")
            );
        }
        return Err(b.signature(0, "not an FRT MicroProf file: it does not start with 'FRTM_GLIDERV'"));
    }
    let version = b.text(12, 4, "the version")?;
    let wide = match version.as_str() {
        "1.00" => false,
        "1.01" => true,
        _ => return Err(b.unsupported(12, format!("version '{version}' is not read (1.00 and 1.01 are)"))),
    };
    let count = b.u16le(16, "the number of blocks")?;
    let mut warnings = Vec::new();
    let blocks = Blocks { b: &b, seen: read_blocks(&b, wide, &mut warnings)? };
    let seen = &blocks.seen;
    if seen.len() != count as usize {
        warnings.push(format!("the header announces {count} blocks, the file holds {}", seen.len()));
    }
    let block = |kind: u16| blocks.find(kind);
    let fixed = |kind: u16, need: usize, what: &str| blocks.fixed(kind, need, what);

    // The images the file holds.
    let images = list_images(&blocks, &mut warnings)?;
    let single = block(0x000b).is_some();
    let base = |i: &Image| i.kind & TYPE_MASK;
    let chosen = images
        .iter()
        .position(|i| base(i) < FIT && base(i) & TOPOGRAPHY != 0)
        .or_else(|| images.iter().position(|i| base(i) < FIT && base(i) & HEIGHT_LIKE != 0));
    let Some(chosen) = chosen else {
        let names: Vec<String> = images.iter().map(|i| type_name(i.kind)).collect();
        return Err(b.bad(
            18,
            if names.is_empty() {
                "the file holds no image (neither block 0x000b nor 0x007d)".to_string()
            } else {
                format!("the file holds no topography, only: {}", names.join(", "))
            },
        ));
    };
    let image = images[chosen];
    let counts = counts(&b, &image)?;
    // A multi-image block repeats the single image: only the others are skipped.
    let skipped: Vec<String> = images
        .iter()
        .enumerate()
        .filter(|&(k, i)| k != chosen && !(single && counts_equal(&b, i, &image)))
        .map(|(_, i)| type_name(i.kind))
        .collect();
    if !skipped.is_empty() {
        warnings.push(format!("{} read; skipped: {}", type_name(image.kind), skipped.join(", ")));
    }

    let mut metadata: Vec<(String, String)> = vec![
        ("instrument".into(), "FRT MicroProf".into()),
        ("version".into(), version),
        ("image".into(), type_name(image.kind)),
    ];
    for (kind, key) in [(0x0065, "description"), (0x0077, "parameter_set")] {
        if let Some((off, size)) = block(kind) {
            let t = b.text(off, size, key)?;
            if !t.is_empty() {
                metadata.push((key.into(), t));
            }
        }
    }
    let unit = match fixed(0x006c, 12, "the z scale")? {
        Some(z) => {
            let range = b.u32le(z, "the measuring range")?;
            let scale = b.f64le(z + 4, "the z scale")?;
            metadata.push(("measuring_range_code".into(), range.to_string()));
            metadata.push(("z_scale".into(), format!("{scale} m per count")));
            if scale.is_finite() && scale != 0.0 {
                Some(scale)
            } else {
                warnings.push(format!("the z scale {scale} m per count is not usable: pass `z_unit`"));
                None
            }
        }
        None => {
            warnings.push("no block 0x006c gives the z scale: pass `z_unit` (metres per count)".into());
            None
        }
    };
    let pitch = match fixed(0x0067, 44, "the scan ranges")? {
        Some(r) => {
            let xr = b.f64le(r, "the x range")?.abs();
            let yr = b.f64le(r + 8, "the y range")?.abs();
            let xo = b.f64le(r + 16, "the x offset")?;
            let yo = b.f64le(r + 24, "the y offset")?;
            let dir = b.u32le(r + 40, "the scan direction")?;
            metadata.push(("x_range".into(), format!("{xr} m")));
            metadata.push(("y_range".into(), format!("{yr} m")));
            metadata.push(("x_offset".into(), format!("{xo} m")));
            metadata.push(("y_offset".into(), format!("{yo} m")));
            metadata.push(("scan_direction".into(), dir.to_string()));
            if xr.is_finite() && xr > 0.0 && yr.is_finite() && yr > 0.0 {
                Some([xr / image.cols as f64, yr / image.rows as f64])
            } else {
                warnings.push(format!("the ranges {xr} x {yr} m give no usable pitch: pass `pitch`"));
                None
            }
        }
        None => {
            warnings.push("no block 0x0067 gives the scan ranges: pass `pitch`".into());
            None
        }
    };
    if let Some(t) = fixed(0x0072, 12, "the measurement time")? {
        let start = b.u32le(t, "the measurement start")?;
        let secs = b.u32le(t + 8, "the measurement duration")?;
        if start != 0 && start != u32::MAX {
            metadata.push(("date".into(), iso_utc(start as i64)));
            metadata.push(("duration".into(), format!("{secs} s")));
        }
    }
    metadata.push((
        "height_unit".into(),
        format!("z scale per {}-bit count; the count 1 not measured", image.bits),
    ));
    let raw = RawMap { values: counts, kind: SampleKind::Float, pitch, unit, metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Frt);
    sr.warnings = warnings;
    Ok(sr)
}

/// The file's blocks, `(type, payload offset, payload size)` in file order.
struct Blocks<'a> {
    b: &'a Bin<'a>,
    seen: Vec<(u16, usize, usize)>,
}

impl Blocks<'_> {
    /// The payload offset and size of the block of type `kind`.
    fn find(&self, kind: u16) -> Option<(usize, usize)> {
        self.seen.iter().find(|&&(k, _, _)| k == kind).map(|&(_, off, size)| (off, size))
    }

    /// A fixed-size block: its payload offset, after checking it holds `need` bytes.
    fn fixed(&self, kind: u16, need: usize, what: &str) -> Result<Option<usize>> {
        match self.find(kind) {
            Some((off, size)) if size < need => Err(self
                .b
                .bad(off, format!("block {kind:#06x} ({what}) holds {size} bytes, {need} expected"))),
            Some((off, _)) => Ok(Some(off)),
            None => Ok(None),
        }
    }
}

/// The chain of blocks after the 18-byte header (headers of 6 bytes, or 10 with 64-bit sizes
/// in version 1.01 (`wide`)); a type given twice is refused, bytes too few for a block header
/// at the end are warned about.
fn read_blocks(b: &Bin, wide: bool, warnings: &mut Vec<String>) -> Result<Vec<(u16, usize, usize)>> {
    let bytes = b.bytes;
    let head = if wide { 10 } else { 6 };
    let mut at = 18;
    let mut seen: Vec<(u16, usize, usize)> = Vec::new(); // (type, payload offset, payload size)
    while at < bytes.len() {
        if bytes.len() - at < head {
            warnings.push(format!(
                "{} bytes after the last block (from byte offset {at}) left unread",
                bytes.len() - at
            ));
            break;
        }
        let kind = b.u16le(at, "a block's type")?;
        let size = if wide {
            let lo = b.u32le(at + 2, "a block's size")? as u64;
            let hi = b.u32le(at + 6, "a block's size")? as u64;
            usize::try_from(hi << 32 | lo).unwrap_or(usize::MAX)
        } else {
            b.u32le(at + 2, "a block's size")? as usize
        };
        let payload = at + head;
        b.take(payload, size, &format!("block {kind:#06x}"))?;
        if seen.iter().any(|&(k, _, _)| k == kind) {
            return Err(b.bad(at, format!("block {kind:#06x} is given twice")));
        }
        seen.push((kind, payload, size));
        at = payload + size;
    }
    Ok(seen)
}

/// The images of block 0x000b (one topography, its size in block 0x0066) and of block 0x007d
/// (each with its own header), in that order; bytes left at the end of block 0x007d are warned
/// about.
fn list_images(blocks: &Blocks, warnings: &mut Vec<String>) -> Result<Vec<Image>> {
    let b = blocks.b;
    let mut images: Vec<Image> = Vec::new();
    if let Some((off, size)) = blocks.find(0x000b) {
        let Some(s) = blocks.fixed(0x0066, 12, "the image size")? else {
            return Err(b.bad(off, "block 0x000b holds an image but no block 0x0066 gives its size"));
        };
        let image = Image {
            kind: TOPOGRAPHY,
            cols: b.u32le(s, "the number of columns")? as usize,
            rows: b.u32le(s + 4, "the number of rows")? as usize,
            bits: b.u32le(s + 8, "the bits per count")?,
            at: off,
        };
        check(b, &image, size, s)?;
        images.push(image);
    }
    if let Some((off, size)) = blocks.find(0x007d) {
        if size < 8 {
            return Err(b.bad(off, format!("block 0x007d (images) holds {size} bytes, at least 8 expected")));
        }
        let end = off + size;
        let mut p = off + 8;
        while end - p > 16 {
            let image = Image {
                kind: b.u32le(p, "an image's type")?,
                cols: b.u32le(p + 4, "an image's columns")? as usize,
                rows: b.u32le(p + 8, "an image's rows")? as usize,
                bits: b.u32le(p + 12, "an image's bits per count")?,
                at: p + 16,
            };
            let len = check(b, &image, end - image.at, p)?;
            images.push(image);
            p = image.at + len;
        }
        if p != end {
            warnings.push(format!(
                "{} bytes at the end of block 0x007d (from byte offset {p}) left unread",
                end - p
            ));
        }
    }
    Ok(images)
}

/// Checks an image's size and bits against the `room` bytes after its header (`head`: where
/// its description is); the bytes of its counts.
fn check(b: &Bin, i: &Image, room: usize, head: usize) -> Result<usize> {
    if i.rows == 0 || i.cols == 0 {
        return Err(b.bad(head, format!("the map is empty ({} x {} points)", i.cols, i.rows)));
    }
    if i.bits != 16 && i.bits != 32 {
        return Err(b.bad(head, format!("{} bits per count: 16 or 32 expected", i.bits)));
    }
    let len = data_len(b.path, i.rows, i.cols, i.bits as usize / 8)?;
    if len > room {
        return Err(b.bad(
            i.at,
            format!(
                "the {} x {} image of {}-bit counts needs {len} bytes, its block holds {room}",
                i.cols, i.rows, i.bits
            ),
        ));
    }
    b.take(i.at, len, "the image")?;
    Ok(len)
}

/// The counts of an image, rows turned over (the file's first row is the bottom of the image),
/// the count 1 as NaN.
fn counts(b: &Bin, i: &Image) -> Result<ndarray::Array2<f64>> {
    let size = i.bits as usize / 8;
    let data = b.take(i.at, data_len(b.path, i.rows, i.cols, size)?, "the image")?;
    let mut values = Vec::with_capacity(i.rows * i.cols);
    for r in (0..i.rows).rev() {
        let row = &data[r * i.cols * size..(r + 1) * i.cols * size];
        values.extend(row.chunks_exact(size).map(|c| {
            let v = if size == 2 {
                u16::from_le_bytes([c[0], c[1]]) as i64
            } else {
                i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as i64
            };
            if v == NOT_MEASURED {
                f64::NAN
            } else {
                v as f64
            }
        }));
    }
    shape(b.path, i.rows, i.cols, values)
}

fn counts_equal(b: &Bin, x: &Image, y: &Image) -> bool {
    let len = |i: &Image| i.rows * i.cols * (i.bits as usize / 8);
    x.rows == y.rows
        && x.cols == y.cols
        && x.bits == y.bits
        && b.take(x.at, len(x), "").ok() == b.take(y.at, len(y), "").ok()
}

/// `YYYY-MM-DDThh:mm:ssZ` of a count of seconds since 1970 (proleptic Gregorian, UTC).
fn iso_utc(t: i64) -> String {
    let (days, secs) = (t.div_euclid(86400), t.rem_euclid(86400));
    // Days to a civil date (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!("{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z", secs / 3600, secs / 60 % 60, secs % 60)
}

/// Writes an FRT file from the layout in the module docs (for tests): `counts` (rows from the
/// top of the image) as block 0x000b (`multi` false) or as the second image of block 0x007d
/// after an intensity image (`multi` true); version 1.01 (u64 sizes) when `wide`.
pub fn encode(
    counts: &ndarray::Array2<i32>,
    bits: u32,
    pitch: [f64; 2],
    zscale: f64,
    wide: bool,
    multi: bool,
) -> Vec<u8> {
    let (rows, cols) = counts.dim();
    let block = |out: &mut Vec<u8>, kind: u16, payload: &[u8]| {
        out.extend_from_slice(&kind.to_le_bytes());
        if wide {
            out.extend_from_slice(&(payload.len() as u64).to_le_bytes());
        } else {
            out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
        }
        out.extend_from_slice(payload);
    };
    let image = |a: &ndarray::Array2<i32>| -> Vec<u8> {
        let mut v = Vec::new();
        for r in (0..rows).rev() {
            for c in 0..cols {
                let x = a[[r, c]];
                if bits == 16 {
                    v.extend_from_slice(&(x as u16).to_le_bytes());
                } else {
                    v.extend_from_slice(&x.to_le_bytes());
                }
            }
        }
        v
    };
    let mut out = MAGIC.to_vec();
    out.extend_from_slice(if wide { b"1.01" } else { b"1.00" });
    out.extend_from_slice(&(6u16).to_le_bytes());
    block(&mut out, 0x0065, b"test surface");
    let mut p = Vec::new();
    for v in [cols as u32, rows as u32, bits] {
        p.extend_from_slice(&v.to_le_bytes());
    }
    block(&mut out, 0x0066, &p);
    let mut p = Vec::new();
    for v in [pitch[0] * cols as f64, pitch[1] * rows as f64, 0.0, 0.0, 1.0] {
        p.extend_from_slice(&v.to_le_bytes());
    }
    p.extend_from_slice(&1u32.to_le_bytes());
    block(&mut out, 0x0067, &p);
    let mut p = 2u32.to_le_bytes().to_vec();
    p.extend_from_slice(&zscale.to_le_bytes());
    block(&mut out, 0x006c, &p);
    let mut p = Vec::new();
    for v in [1_700_000_000u32, 1_700_000_060, 60] {
        p.extend_from_slice(&v.to_le_bytes());
    }
    block(&mut out, 0x0072, &p);
    if multi {
        let mut p = vec![0u8; 8];
        for (kind, a) in [(0x0002u32, counts.mapv(|v| v.rem_euclid(1000) + 2)), (TOPOGRAPHY, counts.clone())]
        {
            for v in [kind, cols as u32, rows as u32, bits] {
                p.extend_from_slice(&v.to_le_bytes());
            }
            p.extend_from_slice(&image(&a));
        }
        block(&mut out, 0x007d, &p);
    } else {
        block(&mut out, 0x000b, &image(counts));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    fn read(bytes: &[u8]) -> Result<ScanRaw> {
        decode(Path::new("t.frt"), bytes)
    }

    fn counts() -> Array2<i32> {
        let mut a = Array2::from_shape_fn((3, 4), |(i, j)| 100 * i as i32 + 3 * j as i32 + 5);
        a[[2, 1]] = 1;
        a
    }

    #[test]
    fn both_versions_both_image_blocks_rows_turned_over() {
        for (bits, wide, multi) in
            [(32, false, false), (16, true, false), (32, true, true), (16, false, true)]
        {
            let r = read(&encode(&counts(), bits, [2e-6, 3e-6], 1e-9, wide, multi)).unwrap();
            assert_eq!(r.format, ScanFormat::Frt);
            let v = &r.raw.values;
            assert_eq!(v.dim(), (3, 4));
            assert_eq!(v[[0, 0]], 5.0, "row 0 is the top of the image (stored last)");
            assert_eq!(v[[2, 3]], 214.0);
            assert!(v[[2, 1]].is_nan());
            assert_eq!(v.iter().filter(|x| x.is_nan()).count(), 1);
            assert_eq!(r.raw.unit, Some(1e-9));
            let [px, py] = r.raw.pitch.unwrap();
            assert!((px - 2e-6).abs() < 1e-18 && (py - 3e-6).abs() < 1e-18);
            let m = |k: &str| r.raw.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.clone());
            assert_eq!(m("date").as_deref(), Some("2023-11-14T22:13:20Z"));
            assert_eq!(m("description").as_deref(), Some("test surface"));
            if multi {
                assert_eq!(r.warnings, ["Topography (top sensor) 1 read; skipped: Intensity (top sensor) 1"]);
            } else {
                assert!(r.warnings.is_empty(), "{:?}", r.warnings);
            }
        }
        assert_eq!(iso_utc(0), "1970-01-01T00:00:00Z");
        assert_eq!(iso_utc(951_782_400), "2000-02-29T00:00:00Z");
    }

    #[test]
    fn other_files_cuts_and_bad_blocks_are_refused() {
        let good = encode(&counts(), 32, [1e-6; 2], 1e-9, false, false);
        let err = |bytes: &[u8]| read(bytes).unwrap_err().to_string();
        assert!(err(b"AliconaImaging\0\r\n").contains("not an FRT MicroProf file"));
        assert!(err(b"HeaderLines=12\r\n").contains("text export"));
        assert!(err(b"FRTM_GLIDERV2.00\0\0").contains("version '2.00'"));
        // Cut anywhere in a block: an error naming the offset (a cut between blocks leaves a
        // file without its image).
        for cut in 0..good.len() {
            let e = err(&good[..cut]);
            assert!(e.contains("t.frt") && e.contains("byte offset"), "cut at {cut}: {e}");
        }
        let data_size_at = good.len() - 48 - 4;
        let mut bad = good.clone();
        bad[data_size_at..data_size_at + 4].copy_from_slice(&40u32.to_le_bytes());
        bad.truncate(bad.len() - 8);
        assert!(err(&bad).contains("needs 48 bytes, its block holds 40"), "{}", err(&bad));
        let size_at = 18 + 6 + 12 + 6;
        let mut bad = good.clone();
        bad[size_at + 8..size_at + 12].copy_from_slice(&24u32.to_le_bytes());
        assert!(err(&bad).contains("24 bits per count"));
        let mut twice = good.clone();
        twice.extend_from_slice(&good[18..18 + 6 + 12]);
        assert!(err(&twice).contains("block 0x0065 is given twice"));
        // Only an intensity image.
        let mut only = MAGIC.to_vec();
        only.extend_from_slice(b"1.00\x01\x00");
        let mut p = vec![0u8; 8];
        for v in [2u32, 1, 1, 16] {
            p.extend_from_slice(&v.to_le_bytes());
        }
        p.extend_from_slice(&[9, 0]);
        only.extend_from_slice(&0x7du16.to_le_bytes());
        only.extend_from_slice(&(p.len() as u32).to_le_bytes());
        only.extend_from_slice(&p);
        assert!(err(&only).contains("no topography, only: Intensity (top sensor) 1"), "{}", err(&only));
    }
}
