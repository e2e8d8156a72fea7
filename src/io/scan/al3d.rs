//! Alicona Imaging / Bruker Alicona files (`.al3d`): the depth image, its invalid points and its
//! repeatability filter as non-measured points.
//!
//! Layout (AL3D file format specification 1.0, as described by Gwyddion's `alicona` module and
//! surfalize's `al3d.py`; little-endian):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 17 | magic `AliconaImaging\0\r\n` |
//! | 17 | 52 | tag `Version` |
//! | 69 | 52 | tag `TagCount`: the number N of tags that follow |
//! | 121 | 52 N | the tags, in any order |
//! | 121 + 52 N | 256 | comment: text, NUL-padded, ending in CR LF |
//! | `DepthImageOffset` | | depth image: `Rows` rows of `Cols` f32, metres |
//! | `TextureImageOffset` | | `NumberOfPlanes` texture planes of `Rows` rows of `Cols` u8 |
//!
//! A tag is a 20-byte key and a 30-byte value, both ISO 8859-1 text ending at the first NUL,
//! then CR LF. Every number is a tag value written as decimal text. Each row of an image is
//! padded to a multiple of 8 bytes (the padding after the last row need not be present).
//!
//! Tags read: `Rows`, `Cols`, `PixelSizeXMeter`, `PixelSizeYMeter` (the pitch, metres),
//! `DepthImageOffset` (0: no depth image, refused), `InvalidPixelValue` (depths from this value
//! upwards are not measured; NaN and infinities never are), and the repeatability filter of the
//! Bruker Alicona software: when `DepthImageResPtr` names a texture plane and
//! `DepthResFilterVal` is set, a depth whose repeatability code `c` (that plane's byte) gives
//! `c * DepthResShiftVal + DepthResMinVal > DepthResFilterVal` is read as non-measured (the
//! software hides those points by default; a warning gives the count). Every tag and the
//! comment are kept as metadata.

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, decode_text, shape, Bin, ScanFormat, ScanRaw};

/// The magic at the start of every AL3D file.
pub const MAGIC: &[u8; 17] = b"AliconaImaging\0\r\n";
const KEY: usize = 20;
const VALUE: usize = 30;
const TAG: usize = KEY + VALUE + 2;
const COMMENT: usize = 256;
/// Image rows are padded to a multiple of this many bytes.
const ALIGN: usize = 8;

/// True when `head` starts as an AL3D file does.
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(MAGIC)
}

/// The header's tags in file order (`Version` and `TagCount` included) and what was parsed of
/// them, with the byte offset of each tag for errors.
struct Tags<'a> {
    b: &'a Bin<'a>,
    tags: Vec<(String, String, usize)>,
}

impl Tags<'_> {
    fn get(&self, key: &str) -> Option<(&str, usize)> {
        self.tags.iter().find(|(k, _, _)| k == key).map(|(_, v, off)| (v.as_str(), *off))
    }

    /// A required tag.
    fn need(&self, key: &str) -> Result<(&str, usize)> {
        self.get(key).ok_or_else(|| self.b.bad(17, format!("the header has no '{key}' tag")))
    }

    fn int(&self, key: &str, value: &str, off: usize) -> Result<i64> {
        value
            .trim()
            .parse::<i64>()
            .map_err(|_| self.b.bad(off + KEY, format!("tag '{key}' = '{value}' is not an integer")))
    }

    fn float(&self, key: &str, value: &str, off: usize) -> Result<f64> {
        value
            .trim()
            .parse::<f64>()
            .map_err(|_| self.b.bad(off + KEY, format!("tag '{key}' = '{value}' is not a number")))
    }

    /// A required count or offset (a non-negative integer that fits the address space).
    fn need_usize(&self, key: &str) -> Result<usize> {
        let (v, off) = self.need(key)?;
        let n = self.int(key, v, off)?;
        usize::try_from(n).map_err(|_| self.b.bad(off + KEY, format!("tag '{key}' = {n} is negative")))
    }

    /// An optional number; `None` when absent or empty.
    fn opt_float(&self, key: &str) -> Result<Option<f64>> {
        match self.get(key) {
            Some((v, off)) if !v.trim().is_empty() => Ok(Some(self.float(key, v, off)?)),
            _ => Ok(None),
        }
    }
}

/// One 52-byte tag at `off`: key and value text.
fn tag(b: &Bin, off: usize, index: usize) -> Result<(String, String)> {
    let raw = b.take(off, TAG, &format!("header tag {index}"))?;
    if &raw[KEY + VALUE..] != b"\r\n" {
        return Err(b.bad(off + KEY + VALUE, format!("header tag {index} does not end in CR LF")));
    }
    let key = decode_text(&raw[..KEY]);
    if key.is_empty() {
        return Err(b.bad(off, format!("header tag {index} has an empty key")));
    }
    Ok((key, decode_text(&raw[KEY..KEY + VALUE])))
}

/// The length of a padded row of `cols` samples of `size` bytes.
fn stride(cols: usize, size: usize) -> usize {
    (cols * size).div_ceil(ALIGN) * ALIGN
}

/// The bytes of an image of `rows` padded rows at `off` (the last row's padding may be absent),
/// and its row stride.
fn image<'a>(
    b: &Bin<'a>,
    off: usize,
    rows: usize,
    cols: usize,
    size: usize,
    what: &str,
) -> Result<(&'a [u8], usize)> {
    data_len(b.path, rows, cols, size)?;
    let st = stride(cols, size);
    let len = st * (rows - 1) + cols * size;
    Ok((b.take(off, len, &format!("the {cols} x {rows} {what}"))?, st))
}

/// Decodes an `.al3d` file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    let n = bytes.len().min(MAGIC.len());
    if bytes[..n] != MAGIC[..n] {
        return Err(b.signature(0, "not an Alicona AL3D file: it does not start with 'AliconaImaging'"));
    }
    b.take(0, MAGIC.len(), "the magic")?;
    let mut tags = Vec::new();
    for (index, want) in [(0, "Version"), (1, "TagCount")] {
        let off = MAGIC.len() + index * TAG;
        let (key, value) = tag(&b, off, index)?;
        if key != want {
            return Err(b.bad(off, format!("header tag {index} is '{key}', '{want}' expected")));
        }
        tags.push((key, value, off));
    }
    let count_off = MAGIC.len() + TAG;
    let count =
        tags[1].1.trim().parse::<usize>().map_err(|_| {
            b.bad(count_off + KEY, format!("tag 'TagCount' = '{}' is not a count", tags[1].1))
        })?;
    let first = MAGIC.len() + 2 * TAG;
    let header_end = count
        .checked_mul(TAG)
        .and_then(|l| l.checked_add(first + COMMENT))
        .ok_or_else(|| b.bad(count_off + KEY, format!("TagCount {count} is beyond any file")))?;
    b.take(0, header_end, &format!("the header of {count} tags and the comment"))?;
    for index in 0..count {
        let off = first + index * TAG;
        let (key, value) = tag(&b, off, index + 2)?;
        if tags.iter().any(|(k, _, _)| *k == key) {
            return Err(b.bad(off, format!("header tag '{key}' is given twice")));
        }
        tags.push((key, value, off));
    }
    let comment_off = header_end - COMMENT;
    let comment = b.take(comment_off, COMMENT, "the comment")?;
    if &comment[COMMENT - 2..] != b"\r\n" {
        return Err(b.bad(header_end - 2, "the 256-byte comment does not end in CR LF"));
    }
    let comment = decode_text(&comment[..COMMENT - 2]);
    let t = Tags { b: &b, tags };

    let rows = t.need_usize("Rows")?;
    let cols = t.need_usize("Cols")?;
    if rows == 0 || cols == 0 {
        return Err(b.bad(t.need("Rows")?.1, format!("the map is empty ({cols} x {rows} points)")));
    }
    let depth_off = t.need_usize("DepthImageOffset")?;
    if depth_off == 0 {
        return Err(b.unsupported(
            t.need("DepthImageOffset")?.1,
            "DepthImageOffset is 0: the file holds no depth image (a texture only)",
        ));
    }
    if depth_off < header_end {
        return Err(b.bad(
            t.need("DepthImageOffset")?.1 + KEY,
            format!("DepthImageOffset {depth_off} points into the header (which ends at {header_end})"),
        ));
    }
    let (depth, st) = image(&b, depth_off, rows, cols, 4, "f32 depth image")?;
    let marker = t.opt_float("InvalidPixelValue")?.map(|v| v as f32);
    let mut values = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        for c in depth[r * st..r * st + cols * 4].chunks_exact(4) {
            let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            let invalid = !v.is_finite() || marker.is_some_and(|m| v >= m);
            values.push(if invalid { f64::NAN } else { v as f64 });
        }
    }
    let mut warnings = Vec::new();
    let filtered = repeatability_filter(&t, rows, cols, &mut values)?;
    if filtered > 0 {
        warnings.push(format!(
            "{filtered} points whose repeatability exceeds DepthResFilterVal read as non-measured (the \
             instrument software's default filter)"
        ));
    }
    let values = shape(path, rows, cols, values)?;

    let dx = t.opt_float("PixelSizeXMeter")?.map(f64::abs);
    let dy = t.opt_float("PixelSizeYMeter")?.map(f64::abs);
    let pitch = match (dx, dy) {
        (Some(x), Some(y)) if x.is_finite() && x > 0.0 && y.is_finite() && y > 0.0 => Some([x, y]),
        _ => {
            warnings.push(format!(
                "PixelSizeXMeter / PixelSizeYMeter ({dx:?}, {dy:?}) give no usable pitch: pass `pitch`"
            ));
            None
        }
    };
    let mut metadata: Vec<(String, String)> = t.tags.into_iter().map(|(k, v, _)| (k, v)).collect();
    if !comment.is_empty() {
        metadata.push(("comment".into(), comment));
    }
    metadata.push(("height_unit".into(), "m (f32)".into()));
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Al3d);
    sr.warnings = warnings;
    Ok(sr)
}

/// Marks the depths the repeatability plane filters out (see the module docs); the count.
fn repeatability_filter(t: &Tags, rows: usize, cols: usize, values: &mut [f64]) -> Result<usize> {
    let plane = match t.get("DepthImageResPtr") {
        Some((v, off)) if !v.trim().is_empty() => (t.int("DepthImageResPtr", v, off)?, off),
        _ => return Ok(0),
    };
    let Some(filter) = t.opt_float("DepthResFilterVal")? else { return Ok(0) };
    let texture = match t.get("TextureImageOffset") {
        Some((v, off)) if !v.trim().is_empty() => t.int("TextureImageOffset", v, off)?,
        _ => 0,
    };
    if texture <= 0 {
        return Ok(0);
    }
    let b = t.b;
    let (index, off) = plane;
    let planes = match t.get("NumberOfPlanes") {
        Some((v, o)) => Some(t.int("NumberOfPlanes", v, o)?),
        None => None,
    };
    if index < 0 || planes.is_some_and(|p| index >= p) {
        return Err(b.bad(
            off + KEY,
            format!("DepthImageResPtr {index} is not one of the {} texture planes", planes.unwrap_or(0)),
        ));
    }
    let plane_len = stride(cols, 1).checked_mul(rows);
    let start = plane_len
        .and_then(|l| l.checked_mul(index as usize))
        .and_then(|l| l.checked_add(texture as usize))
        .ok_or_else(|| b.bad(off + KEY, format!("texture plane {index} lies beyond any file")))?;
    let (codes, st) = image(b, start, rows, cols, 1, "repeatability plane")?;
    let shift = t.opt_float("DepthResShiftVal")?.unwrap_or(0.0);
    let min = t.opt_float("DepthResMinVal")?.unwrap_or(0.0);
    let mut count = 0;
    for r in 0..rows {
        for (c, &code) in codes[r * st..r * st + cols].iter().enumerate() {
            let v = &mut values[r * cols + c];
            if code as f64 * shift + min > filter && !v.is_nan() {
                *v = f64::NAN;
                count += 1;
            }
        }
    }
    Ok(count)
}

/// Writes an AL3D file from the layout in the module docs (for tests): `heights` in metres, NaN
/// written as the invalid pixel value 3e15, `pitch` `[x, y]` in metres, `extra` tags after the
/// required ones, each row padded to 8 bytes except the last when `pad_last` is false, and
/// `texture` (planes of `rows x cols` bytes) after the depth image.
pub fn encode(
    heights: &ndarray::Array2<f64>,
    pitch: [f64; 2],
    extra: &[(&str, &str)],
    comment: &str,
    texture: &[ndarray::Array2<u8>],
    pad_last: bool,
) -> Vec<u8> {
    let (rows, cols) = heights.dim();
    let put_tag = |out: &mut Vec<u8>, k: &str, v: &str| {
        let mut t = [0u8; TAG];
        t[..k.len()].copy_from_slice(k.as_bytes());
        t[KEY..KEY + v.len()].copy_from_slice(v.as_bytes());
        t[KEY + VALUE..].copy_from_slice(b"\r\n");
        out.extend_from_slice(&t);
    };
    let invalid = 3.0e15f32;
    let mut tags: Vec<(String, String)> = vec![
        ("Rows".into(), rows.to_string()),
        ("Cols".into(), cols.to_string()),
        ("PixelSizeXMeter".into(), format!("{:e}", pitch[0])),
        ("PixelSizeYMeter".into(), format!("{:e}", pitch[1])),
        ("InvalidPixelValue".into(), format!("{}", invalid as f64)),
        ("NumberOfPlanes".into(), texture.len().to_string()),
        ("DepthImageOffset".into(), String::new()),
        ("TextureImageOffset".into(), String::new()),
    ];
    tags.extend(extra.iter().map(|(k, v)| (k.to_string(), v.to_string())));
    let header = MAGIC.len() + TAG * (2 + tags.len()) + COMMENT;
    let depth = stride(cols, 4) * rows;
    for (k, v) in tags.iter_mut() {
        if k == "DepthImageOffset" {
            *v = header.to_string();
        } else if k == "TextureImageOffset" {
            *v = if texture.is_empty() { "0".into() } else { (header + depth).to_string() };
        }
    }
    let mut out = MAGIC.to_vec();
    put_tag(&mut out, "Version", "1");
    put_tag(&mut out, "TagCount", &tags.len().to_string());
    for (k, v) in &tags {
        put_tag(&mut out, k, v);
    }
    let mut c = comment.as_bytes().to_vec();
    c.resize(COMMENT - 2, 0);
    out.extend_from_slice(&c);
    out.extend_from_slice(b"\r\n");
    for row in heights.rows() {
        let start = out.len();
        for v in row {
            let f = if v.is_nan() { invalid } else { *v as f32 };
            out.extend_from_slice(&f.to_le_bytes());
        }
        out.resize(start + stride(cols, 4), 0);
    }
    for plane in texture {
        for row in plane.rows() {
            let start = out.len();
            out.extend(row.iter());
            out.resize(start + stride(cols, 1), 0);
        }
    }
    if !pad_last && texture.is_empty() {
        out.truncate(out.len() - (stride(cols, 4) - cols * 4));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    fn read(bytes: &[u8]) -> Result<ScanRaw> {
        decode(Path::new("t.al3d"), bytes)
    }

    fn heights(rows: usize, cols: usize) -> Array2<f64> {
        let mut h = Array2::from_shape_fn((rows, cols), |(i, j)| 1e-7 * (10 * i + j) as f64);
        h[[1, 2]] = f64::NAN;
        h
    }

    #[test]
    fn padded_rows_pitch_invalid_points_and_metadata() {
        // 5 columns of f32 = 20 bytes, padded to 24; without the last row's padding too.
        let h = heights(3, 5);
        for pad_last in [true, false] {
            let bytes = encode(&h, [2e-6, 3e-6], &[("Objective", "20x")], "stage 4", &[], pad_last);
            let r = read(&bytes).unwrap();
            assert_eq!(r.raw.values.dim(), (3, 5));
            assert_eq!(r.raw.pitch, Some([2e-6, 3e-6]));
            assert_eq!(r.raw.unit, Some(1.0));
            for ((i, j), v) in r.raw.values.indexed_iter() {
                let w = h[[i, j]];
                assert!(w.is_nan() && v.is_nan() || (v - (w as f32) as f64).abs() == 0.0, "({i}, {j}) {v}");
            }
            let meta = |k: &str| r.raw.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.clone());
            assert_eq!(meta("Objective").as_deref(), Some("20x"));
            assert_eq!(meta("comment").as_deref(), Some("stage 4"));
            assert_eq!(meta("Version").as_deref(), Some("1"));
            assert!(r.warnings.is_empty(), "{:?}", r.warnings);
        }
        // Depths above the marker are invalid too; without the tag only NaN is.
        let mut above = h.clone();
        above[[0, 0]] = 4e15;
        let r = read(&encode(&above, [1e-6; 2], &[], "", &[], true)).unwrap();
        assert!(r.raw.values[[0, 0]].is_nan());
    }

    #[test]
    fn the_repeatability_plane_filters_depths() {
        let h = heights(3, 5);
        let gray = Array2::from_elem((3, 5), 7u8);
        let mut codes = Array2::from_elem((3, 5), 10u8);
        codes[[0, 4]] = 200; // 200 * 1e-8 + 1e-7 > 1.5e-6
        codes[[2, 0]] = 140; // exactly at the filter value: kept
        codes[[1, 2]] = 255; // already invalid: not counted twice
        let extra = [
            ("DepthImageResPtr", "1"),
            ("DepthResMinVal", "1e-07"),
            ("DepthResShiftVal", "1e-08"),
            ("DepthResFilterVal", "1.5e-06"),
        ];
        let bytes = encode(&h, [1e-6; 2], &extra, "", &[gray, codes], true);
        let r = read(&bytes).unwrap();
        let nan: Vec<(usize, usize)> =
            r.raw.values.indexed_iter().filter(|(_, v)| v.is_nan()).map(|(ij, _)| ij).collect();
        assert_eq!(nan, vec![(0, 4), (1, 2)]);
        assert!(r.warnings.iter().any(|w| w.starts_with("1 points whose repeatability")), "{:?}", r.warnings);
        // A plane index past NumberOfPlanes is refused.
        let bad = [("DepthImageResPtr", "2"), ("DepthResFilterVal", "1e-6")];
        let e =
            read(&encode(&h, [1e-6; 2], &bad, "", &[Array2::zeros((3, 5))], true)).unwrap_err().to_string();
        assert!(e.contains("DepthImageResPtr 2 is not one of the 1 texture planes"), "{e}");
    }

    #[test]
    fn malformed_headers_are_refused_with_the_field() {
        let h = heights(2, 3);
        let good = encode(&h, [1e-6; 2], &[], "", &[], true);
        let err = |bytes: &[u8]| read(bytes).unwrap_err().to_string();
        assert!(err(b"GWYP").contains("not an Alicona AL3D file"));
        assert!(err(b"%PDF-1.4 and more bytes than the magic").contains("byte offset 0"));
        // Everything but the last row's padding (3 f32 = 12 bytes, padded to 16) is needed.
        for cut in 0..good.len() - 4 {
            let e = err(&good[..cut]);
            assert!(e.contains("t.al3d") && e.contains("byte offset"), "cut at {cut}: {e}");
        }
        let tag_at = |k: usize| MAGIC.len() + k * TAG;
        let mut crlf = good.clone();
        crlf[tag_at(3) + KEY + VALUE] = b' ';
        assert!(err(&crlf).contains("header tag 3 does not end in CR LF"), "{}", err(&crlf));
        let mut version = good.clone();
        version[MAGIC.len()] = b'X';
        assert!(err(&version).contains("'Version' expected"), "{}", err(&version));
        let mut twice = good.clone();
        let rows_tag = good[tag_at(2)..tag_at(3)].to_vec();
        twice[tag_at(3)..tag_at(4)].copy_from_slice(&rows_tag);
        assert!(err(&twice).contains("'Rows' is given twice"), "{}", err(&twice));
        let set = |k: &str, v: &str| encode(&h, [1e-6; 2], &[], "", &[], true).replace_tag(k, v);
        assert!(err(&set("Rows", "-3")).contains("'Rows' = -3 is negative"));
        assert!(err(&set("Cols", "abc")).contains("'Cols' = 'abc' is not an integer"));
        assert!(err(&set("Cols", "0")).contains("the map is empty"));
        assert!(err(&set("DepthImageOffset", "0")).contains("no depth image"));
        assert!(err(&set("DepthImageOffset", "12")).contains("points into the header"));
        assert!(err(&set("Rows", "99999999999")).contains("beyond any profilometer scan"));
        let r = read(&set("PixelSizeXMeter", "0")).unwrap();
        assert!(r.raw.pitch.is_none() && r.warnings[0].contains("pass `pitch`"), "{:?}", r.warnings);
        let mut comment = good;
        let end = tag_at(2 + 8) + COMMENT;
        comment[end - 1] = 0;
        assert!(err(&comment).contains("comment does not end in CR LF"));
    }

    /// Test helper: rewrites a tag's value in place.
    trait ReplaceTag {
        fn replace_tag(self, key: &str, value: &str) -> Vec<u8>;
    }

    impl ReplaceTag for Vec<u8> {
        fn replace_tag(mut self, key: &str, value: &str) -> Vec<u8> {
            let mut off = MAGIC.len();
            while decode_text(&self[off..off + KEY]) != key {
                off += TAG;
            }
            self[off + KEY..off + KEY + VALUE].fill(0);
            self[off + KEY..off + KEY + value.len()].copy_from_slice(value.as_bytes());
            self
        }
    }
}
