//! Keyence VK laser confocal microscope files: `.vk4`, and `.vk6` / `.vk7`, which carry the same
//! VK4 byte stream inside a zip archive.
//!
//! Layout of the VK4 byte stream (Keyence's VK4 description as followed by Gwyddion's `keyence`
//! module, SurfaceTopography's `VK` reader and surfalize's `vk.py`; little-endian, every number
//! a u32 unless said otherwise, every offset from the start of the stream):
//!
//! | offset | size | field |
//! |---|---|---|
//! | 0 | 4 | magic `VK4_` |
//! | 4 | 4 | DLL version (four bytes, the last the major number) |
//! | 8 | 4 | file type: 0 (all four bytes zero) |
//! | 12 | 72 | offset table: measurement conditions, colour peak image, colour + light image, light images 1-3, height images 1-3, four thumbnails, assembly, line measurement, line thickness, strings, reserved (0: absent) |
//! | conditions | `size` ≥ 304 | measurement conditions (below) |
//! | height image | 796 + data | width, height, bit depth (8, 16 or 32), compression, data byte size (= width × height × depth / 8), palette min and max, a 768-byte palette, then the counts (unsigned, row by row, the first row first) |
//! | strings | | title and lens name: each a u32 count of UTF-16LE code units, then the units |
//!
//! The measurement conditions read, by their offset in the block: 0 size, 4-24 year, month,
//! day, hour, minute, second, 28 difference from UTC in minutes (i32), 48 run mode, 52 peak
//! mode, 72 optical zoom (tenths), 96 lens magnification (tenths), 168 and 172 x and y length
//! per pixel (picometres: the pitch), 176 z length per digit (picometres per count: the height
//! unit), 224 numerical aperture (thousandths), 228 head type, 240 lens ID, 300 the height's
//! effective bit depth.
//!
//! The first height image present is read (the file's measured topography); further height
//! layers are skipped with a warning, and the light (intensity) and colour images, which every
//! file carries, are named in the metadata as not read. The description names no marker for
//! points not measured (every count is a height), so none is read as such.
//!
//! `.vk6` and `.vk7` (VK-X 3000 series software) start with `VK6` or `VK7`, a u32 length and a
//! BMP preview of that length, followed by a zip archive whose entry `Vk4File` is the VK4 byte
//! stream above (Gwyddion's `keyence` module; SurfaceTopography and surfalize read the entry
//! the same way). The other entries (settings XML, HDR images) are not read. The entry is
//! decompressed into memory no larger than deflate's largest expansion of the archive allows.

use std::io::{Cursor, Read};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, shape, Bin, ScanFormat, ScanRaw};

/// The magic of a VK4 byte stream.
pub const MAGIC: &[u8; 4] = b"VK4_";
const HEADER: usize = 12;
const TABLE: usize = 72;
/// The smallest measurement conditions block (Gwyddion's and SurfaceTopography's).
const CONDITIONS_MIN: usize = 304;
/// Header (28 bytes) and palette (768 bytes) of a false-colour image.
const IMAGE_HEADER: usize = 28 + 768;
/// Picometres, the unit of the pitch and of the height per count.
const PM: f64 = 1e-12;
/// The zip entry of a `.vk6` / `.vk7` file that holds the VK4 stream.
const VK4_ENTRY: &str = "Vk4File";
/// The most a `Vk4File` entry may expand to (a 2^28-point scan with its images fits).
const ENTRY_LIMIT: u64 = 1 << 32;
/// Deflate's largest expansion: an entry expands to at most this many times the archive.
const DEFLATE_RATIO: u64 = 1032;

/// The offset table's entries, in file order.
const TABLE_NAMES: [&str; 18] = [
    "measurement conditions",
    "colour peak image",
    "colour + light image",
    "light image 1",
    "light image 2",
    "light image 3",
    "height image 1",
    "height image 2",
    "height image 3",
    "colour peak thumbnail",
    "colour thumbnail",
    "light thumbnail",
    "height thumbnail",
    "assembly",
    "line measurement",
    "line thickness",
    "strings",
    "reserved",
];
const HEIGHT1: usize = 6;
const STRINGS: usize = 16;

/// True when `head` starts as a VK4 byte stream does.
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(MAGIC)
}

/// Decodes a `.vk4`, `.vk6` or `.vk7` file (see the module docs), whichever its first bytes say.
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    if bytes.starts_with(b"VK6") || bytes.starts_with(b"VK7") {
        return decode_container(path, bytes);
    }
    if !bytes.starts_with(b"VK3_") && !bytes.starts_with(MAGIC) {
        return Err(Bin::new(path, bytes)
            .signature(0, "not a Keyence VK file: it does not start with 'VK4_', 'VK6' or 'VK7'"));
    }
    decode_vk4(path, bytes)
}

/// A `.vk6` / `.vk7` file: the VK4 stream from the zip archive after the BMP preview.
fn decode_container(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    let kind = String::from_utf8_lossy(&bytes[..3]).into_owned();
    // The zip follows the 7-byte header and the BMP preview whose length the header gives (and
    // the BMP's own header repeats); where they disagree the zip is looked for from the end.
    let preview = b.u32le(3, "the preview length")? as usize;
    let start = match (b.take(7, 2, "the preview"), b.u32le(9, "the preview's BMP size")) {
        (Ok(bm), Ok(size)) if bm == b"BM" && size as usize == preview && 7 + preview < bytes.len() => {
            7 + preview
        }
        _ => 0,
    };
    let zip_bytes = &bytes[start..];
    let mut zip = zip::ZipArchive::new(Cursor::new(zip_bytes)).map_err(|e| {
        b.bad(start, format!("{kind} file: no zip archive after the {preview}-byte preview: {e}"))
    })?;
    let mut f = match zip.by_name(VK4_ENTRY) {
        Ok(f) => f,
        Err(zip::result::ZipError::FileNotFound) => {
            return Err(b.bad(start, format!("{kind} file: its zip archive holds no '{VK4_ENTRY}' entry")))
        }
        Err(e) => return Err(b.bad(start, format!("{kind} file: zip entry '{VK4_ENTRY}': {e}"))),
    };
    let at = start as u64 + f.data_start();
    let limit = (zip_bytes.len() as u64).saturating_mul(DEFLATE_RATIO).min(ENTRY_LIMIT);
    if f.size() > limit {
        return Err(Error::malformed(
            path,
            format!(
                "byte offset {at}: zip entry '{VK4_ENTRY}' claims {} bytes, more than the {}-byte \
                 archive can hold (at most {limit})",
                f.size(),
                zip_bytes.len()
            ),
        )
        .at(at));
    }
    // Grown as the entry decompresses, never reserved from the size the archive claims.
    let mut inner = Vec::new();
    (&mut f).take(limit).read_to_end(&mut inner).map_err(|e| {
        Error::malformed(path, format!("byte offset {at}: zip entry '{VK4_ENTRY}' is corrupt: {e}")).at(at)
    })?;
    let inner_path = PathBuf::from(format!("{} (zip entry {VK4_ENTRY})", path.display()));
    let mut sr = decode_vk4(&inner_path, &inner).map_err(|e| match e {
        Error::Format { offset, cause, what, .. } => Error::Format {
            path: path.to_path_buf(),
            offset,
            cause,
            what: format!("zip entry '{VK4_ENTRY}': {what}"),
        },
        other => other,
    })?;
    sr.raw.metadata.insert(0, ("container".into(), format!("{kind} (zip entry {VK4_ENTRY})")));
    Ok(sr)
}

/// The measurement conditions' fields that are kept, `(offset in the block, name)`.
const CONDITIONS: [(usize, &str); 8] = [
    (48, "run_mode"),
    (52, "peak_mode"),
    (56, "sharpening_level"),
    (64, "distance_nm"),
    (68, "pitch_nm"),
    (228, "head_type"),
    (240, "lens_id"),
    (300, "height_effective_bit_depth"),
];

/// A VK4 byte stream (see the module docs).
fn decode_vk4(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    let n = bytes.len().min(MAGIC.len());
    if bytes[..n] != MAGIC[..n] {
        if bytes.starts_with(b"VK3_") {
            return Err(
                b.unsupported(0, "a Keyence VK3 file (the older layout) is not read; VK4, VK6 and VK7 are")
            );
        }
        return Err(b.signature(0, "not a Keyence VK4 file: it does not start with 'VK4_'"));
    }
    let head = b.take(0, HEADER, "the 12-byte header")?;
    let kind = u32::from_le_bytes([head[8], head[9], head[10], head[11]]);
    if kind != 0 {
        return Err(b.bad(8, format!("file type {kind:#010x}: 0 expected after the magic and DLL version")));
    }
    let mut table = [0usize; 18];
    for (i, t) in table.iter_mut().enumerate() {
        *t = b.u32le(HEADER + 4 * i, &format!("the offset table's {} entry", TABLE_NAMES[i]))? as usize;
    }
    // Measurement conditions.
    let mc = table[0];
    if mc < HEADER + TABLE {
        return Err(b.bad(
            HEADER,
            format!("the measurement conditions' offset {mc} points into the header (which ends at 84)"),
        ));
    }
    let size = b.u32le(mc, "the measurement conditions' size")? as usize;
    if size < CONDITIONS_MIN {
        return Err(b.bad(
            mc,
            format!("the measurement conditions' size {size} is below the {CONDITIONS_MIN} bytes they hold"),
        ));
    }
    b.take(mc, size, "the measurement conditions")?;
    let u = |off: usize, what: &str| b.u32le(mc + off, what);
    let date: Vec<u32> =
        [(4, "year"), (8, "month"), (12, "day"), (16, "hour"), (20, "minute"), (24, "second")]
            .iter()
            .map(|&(o, w)| u(o, w))
            .collect::<Result<_>>()?;
    let utc = b.i32le(mc + 28, "the difference from UTC")?;
    let zoom = u(72, "the optical zoom")?;
    let lens = u(96, "the lens magnification")?;
    let px = u(168, "the x length per pixel")?;
    let py = u(172, "the y length per pixel")?;
    let pz = u(176, "the z length per digit")?;
    let na = u(224, "the numerical aperture")?;

    // The height image: the first present.
    let heights: Vec<(usize, usize)> =
        (0..3).map(|i| (i, table[HEIGHT1 + i])).filter(|&(_, off)| off != 0).collect();
    let Some(&(layer, off)) = heights.first() else {
        return Err(b.bad(
            HEADER + 4 * HEIGHT1,
            "the offset table names no height image (its three entries are 0): the file holds no topography",
        ));
    };
    let what = TABLE_NAMES[HEIGHT1 + layer];
    let cols = b.u32le(off, &format!("the {what}'s width"))? as usize;
    let rows = b.u32le(off + 4, &format!("the {what}'s height"))? as usize;
    let bits = b.u32le(off + 8, &format!("the {what}'s bit depth"))?;
    let compression = b.u32le(off + 12, &format!("the {what}'s compression"))?;
    let byte_size = b.u32le(off + 16, &format!("the {what}'s data size"))? as usize;
    b.take(off, IMAGE_HEADER, &format!("the {what}'s header and palette"))?;
    if rows == 0 || cols == 0 {
        return Err(b.bad(off, format!("the {what} is empty ({cols} x {rows} points)")));
    }
    let bytes_per = match bits {
        8 | 16 | 32 => bits as usize / 8,
        _ => return Err(b.bad(off + 8, format!("the {what}'s bit depth {bits} is not 8, 16 or 32"))),
    };
    let need = data_len(path, rows, cols, bytes_per)?;
    if byte_size != need {
        return Err(b.bad(
            off + 16,
            format!(
                "the {what}'s data size {byte_size} is not {cols} x {rows} x {bytes_per} = {need} bytes \
                 (compression {compression})"
            ),
        ));
    }
    let data =
        b.take(off + IMAGE_HEADER, need, &format!("the {what}'s {cols} x {rows} {bits}-bit counts"))?;
    let values: Vec<f64> = match bytes_per {
        1 => data.iter().map(|&v| v as f64).collect(),
        2 => data.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]]) as f64).collect(),
        _ => data.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64).collect(),
    };
    let values = shape(path, rows, cols, values)?;

    let mut warnings = Vec::new();
    if heights.len() > 1 {
        let skipped: Vec<&str> = heights[1..].iter().map(|&(i, _)| TABLE_NAMES[HEIGHT1 + i]).collect();
        warnings.push(format!("{what} read; {} skipped", skipped.join(" and ")));
    }
    let pitch = if px > 0 && py > 0 {
        Some([px as f64 * PM, py as f64 * PM])
    } else {
        warnings.push(format!("the length per pixel {px} x {py} pm gives no usable pitch: pass `pitch`"));
        None
    };
    let unit = if pz > 0 {
        Some(pz as f64 * PM)
    } else {
        warnings.push("the z length per digit is 0: pass `z_unit` (metres per count)".to_string());
        None
    };

    let mut metadata: Vec<(String, String)> = vec![("instrument".into(), "Keyence VK".into())];
    metadata.push(("dll_version".into(), format!("{}.{}.{}.{}", head[7], head[6], head[5], head[4])));
    let sign = if utc < 0 { '-' } else { '+' };
    let (h, m) = (utc.unsigned_abs() / 60, utc.unsigned_abs() % 60);
    metadata.push((
        "date".into(),
        format!(
            "{:04}-{:02}-{:02}T{:02}:{:02}:{:02}{sign}{h:02}:{m:02}",
            date[0], date[1], date[2], date[3], date[4], date[5]
        ),
    ));
    metadata.push(("lens_magnification".into(), format!("{}", lens as f64 / 10.0)));
    metadata.push(("optical_zoom".into(), format!("{}", zoom as f64 / 10.0)));
    metadata.push(("numerical_aperture".into(), format!("{}", na as f64 / 1000.0)));
    for (o, name) in CONDITIONS {
        metadata.push((name.into(), u(o, name)?.to_string()));
    }
    metadata.push(("x_length_per_pixel".into(), format!("{px} pm")));
    metadata.push(("y_length_per_pixel".into(), format!("{py} pm")));
    metadata.push(("z_length_per_digit".into(), format!("{pz} pm")));
    metadata.push(("height_layer".into(), format!("{} of {} ({bits}-bit counts)", layer + 1, heights.len())));
    let others: Vec<&str> = (1..=5).filter(|&i| table[i] != 0).map(|i| TABLE_NAMES[i]).collect();
    if !others.is_empty() {
        metadata.push(("images_not_read".into(), others.join(", ")));
    }
    if table[STRINGS] != 0 {
        let mut at = table[STRINGS];
        for name in ["title", "lens_name"] {
            let (text, next) = utf16(&b, at, name)?;
            metadata.push((name.into(), text));
            at = next;
        }
    }
    metadata.push(("height_unit".into(), format!("{pz} pm per count")));
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit, metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Vk);
    sr.warnings = warnings;
    Ok(sr)
}

/// A string of the strings block at `at`: a u32 count of UTF-16LE code units, then the units;
/// the text and the offset after it.
fn utf16(b: &Bin, at: usize, name: &str) -> Result<(String, usize)> {
    let n = b.u32le(at, &format!("the {name}'s length"))? as usize;
    let len =
        n.checked_mul(2).ok_or_else(|| b.bad(at, format!("the {name}'s length {n} is beyond any file")))?;
    let raw = b.take(at + 4, len, &format!("the {name}'s {n} UTF-16 code units"))?;
    let units: Vec<u16> = raw.chunks_exact(2).map(|c| u16::from_le_bytes([c[0], c[1]])).collect();
    let text =
        String::from_utf16(&units).map_err(|_| b.bad(at + 4, format!("the {name} is not valid UTF-16")))?;
    Ok((text.trim_end_matches('\0').trim().to_string(), at + 4 + len))
}

/// What [`encode`] writes besides the heights.
#[derive(Debug, Clone)]
pub struct Vk4Parts {
    /// `[x, y]` length per pixel and z length per digit, picometres.
    pub pm: [u32; 3],
    /// Bits per count of the height images: 8, 16 or 32.
    pub bits: u32,
    /// Further height layers (counts), written as height images 2 and 3.
    pub more_layers: Vec<ndarray::Array2<u32>>,
    /// A 16-bit light image of the same size.
    pub light: bool,
    /// Title and lens name (the strings block), when given.
    pub strings: Option<(String, String)>,
    /// Year, month, day, hour, minute, second and the difference from UTC in minutes.
    pub date: ([u32; 6], i32),
    /// Lens magnification in tenths.
    pub lens_mag: u32,
    /// Bytes of measurement conditions (304 or more).
    pub conditions: usize,
}

impl Default for Vk4Parts {
    fn default() -> Self {
        Vk4Parts {
            pm: [1_000_000, 1_000_000, 1_000],
            bits: 32,
            more_layers: Vec::new(),
            light: false,
            strings: None,
            date: ([2024, 5, 17, 13, 4, 59], 120),
            lens_mag: 200,
            conditions: CONDITIONS_MIN,
        }
    }
}

/// Writes a VK4 byte stream from the layout in the module docs (for tests): `counts` as height
/// image 1 (rows × columns), everything else from `parts`.
pub fn encode(counts: &ndarray::Array2<u32>, parts: &Vk4Parts) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[0, 0, 1, 2]);
    out.extend_from_slice(&[0; 4]);
    let table_at = out.len();
    out.resize(HEADER + TABLE, 0);
    let mut table = [0u32; 18];
    table[0] = out.len() as u32;
    let mut mc = vec![0u8; parts.conditions];
    let mut put = |o: usize, v: u32| mc[o..o + 4].copy_from_slice(&v.to_le_bytes());
    put(0, parts.conditions as u32);
    for (i, v) in parts.date.0.iter().enumerate() {
        put(4 + 4 * i, *v);
    }
    put(28, parts.date.1 as u32);
    put(72, 10);
    put(96, parts.lens_mag);
    put(168, parts.pm[0]);
    put(172, parts.pm[1]);
    put(176, parts.pm[2]);
    put(224, 950);
    put(300, parts.bits);
    out.extend_from_slice(&mc);
    let image = |out: &mut Vec<u8>, a: &ndarray::Array2<u32>, bits: u32| {
        let (rows, cols) = a.dim();
        let bytes = (bits / 8) as usize;
        for v in [cols as u32, rows as u32, bits, 0, (rows * cols * bytes) as u32, 0, 0] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&[0; 768]);
        for &v in a {
            out.extend_from_slice(&v.to_le_bytes()[..bytes]);
        }
    };
    if parts.light {
        table[3] = out.len() as u32;
        image(&mut out, &counts.mapv(|v| v % 65536), 16);
    }
    table[HEIGHT1] = out.len() as u32;
    image(&mut out, counts, parts.bits);
    for (i, a) in parts.more_layers.iter().enumerate().take(2) {
        table[HEIGHT1 + 1 + i] = out.len() as u32;
        image(&mut out, a, parts.bits);
    }
    if let Some((title, lens)) = &parts.strings {
        table[STRINGS] = out.len() as u32;
        for s in [title, lens] {
            let units: Vec<u16> = s.encode_utf16().collect();
            out.extend_from_slice(&(units.len() as u32).to_le_bytes());
            for u in units {
                out.extend_from_slice(&u.to_le_bytes());
            }
        }
    }
    for (i, v) in table.iter().enumerate() {
        out[table_at + 4 * i..table_at + 4 * i + 4].copy_from_slice(&v.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;
    use std::io::Write;

    fn read(bytes: &[u8]) -> Result<ScanRaw> {
        decode(Path::new("t.vk4"), bytes)
    }

    fn counts() -> Array2<u32> {
        Array2::from_shape_fn((3, 5), |(i, j)| (1000 * i + 7 * j) as u32)
    }

    #[test]
    fn depths_pitch_unit_layers_and_metadata() {
        for bits in [8u32, 16, 32] {
            let c = counts().mapv(|v| v % (1 << bits.min(16)));
            let parts = Vk4Parts {
                pm: [1_500_000, 2_000_000, 100],
                bits,
                light: true,
                strings: Some(("wafer 3".into(), "50x µ-lens".into())),
                conditions: 400,
                ..Default::default()
            };
            let r = read(&encode(&c, &parts)).unwrap();
            assert_eq!(r.format, ScanFormat::Vk);
            assert_eq!(r.raw.values.dim(), (3, 5));
            assert_eq!(r.raw.pitch, Some([1.5e-6, 2e-6]));
            assert_eq!(r.raw.unit, Some(100.0 * PM));
            for ((i, j), v) in r.raw.values.indexed_iter() {
                assert_eq!(*v, c[[i, j]] as f64);
            }
            assert!(r.warnings.is_empty(), "{:?}", r.warnings);
            let m = |k: &str| r.raw.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.clone());
            assert_eq!(m("date").as_deref(), Some("2024-05-17T13:04:59+02:00"));
            assert_eq!(m("lens_magnification").as_deref(), Some("20"));
            assert_eq!(m("title").as_deref(), Some("wafer 3"));
            assert_eq!(m("lens_name").as_deref(), Some("50x µ-lens"));
            assert_eq!(m("images_not_read").as_deref(), Some("light image 1"));
            assert_eq!(m("dll_version").as_deref(), Some("2.1.0.0"));
        }
        // A second and third height layer: the first is read, a warning names the others.
        let parts = Vk4Parts { more_layers: vec![counts() + 1, counts() + 2], ..Default::default() };
        let r = read(&encode(&counts(), &parts)).unwrap();
        assert_eq!(r.raw.values[[1, 1]], 1007.0);
        assert_eq!(r.warnings, ["height image 1 read; height image 2 and height image 3 skipped"]);
        // A zero pitch or unit: asked for, not guessed.
        let parts = Vk4Parts { pm: [0, 1, 0], date: ([2024, 1, 2, 3, 4, 5], -90), ..Default::default() };
        let r = read(&encode(&counts(), &parts)).unwrap();
        assert!(r.raw.pitch.is_none() && r.raw.unit.is_none());
        assert!(
            r.warnings[0].contains("pass `pitch`") && r.warnings[1].contains("pass `z_unit`"),
            "{:?}",
            r.warnings
        );
        assert!(r.raw.metadata.iter().any(|(k, v)| k == "date" && v == "2024-01-02T03:04:05-01:30"));
    }

    #[test]
    fn vk6_and_vk7_containers_read_their_vk4_entry() {
        let vk4 = encode(&counts(), &Vk4Parts { pm: [2_000_000, 3_000_000, 10], ..Default::default() });
        let zipped = |name: &str, data: &[u8]| {
            let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
            let o = zip::write::SimpleFileOptions::default();
            w.start_file("MeasureCondition", o).unwrap();
            w.write_all(b"<xml/>").unwrap();
            w.start_file(name, o).unwrap();
            w.write_all(data).unwrap();
            w.finish().unwrap().into_inner()
        };
        let mut bmp = b"BM".to_vec();
        bmp.extend_from_slice(&60u32.to_le_bytes());
        bmp.resize(60, 7);
        for (magic, bmp_ok) in [(b"VK6", true), (b"VK7", true), (b"VK6", false)] {
            let mut f = magic.to_vec();
            f.extend_from_slice(&60u32.to_le_bytes());
            let mut preview = bmp.clone();
            if !bmp_ok {
                // The BMP's own size disagrees: the zip is still found from the end.
                preview[2] = 61;
            }
            f.extend_from_slice(&preview);
            f.extend_from_slice(&zipped(VK4_ENTRY, &vk4));
            let r = decode(Path::new("t.vk6"), &f).unwrap();
            assert_eq!(r.raw.pitch, Some([2e-6, 3e-6]));
            assert_eq!(r.raw.values[[2, 4]], 2028.0);
            assert_eq!(r.raw.metadata[0].0, "container");
        }
        let mut f = b"VK6".to_vec();
        f.extend_from_slice(&60u32.to_le_bytes());
        f.extend_from_slice(&bmp);
        f.extend_from_slice(&zipped("Other", &vk4));
        let e = decode(Path::new("t.vk6"), &f).unwrap_err().to_string();
        assert!(
            e.contains("t.vk6") && e.contains("byte offset 67") && e.contains("no 'Vk4File' entry"),
            "{e}"
        );
        let mut cut = vk4.clone();
        cut.truncate(500);
        let mut f = b"VK7".to_vec();
        f.extend_from_slice(&60u32.to_le_bytes());
        f.extend_from_slice(&bmp);
        f.extend_from_slice(&zipped(VK4_ENTRY, &cut));
        let e = decode(Path::new("t.vk7"), &f).unwrap_err().to_string();
        assert!(
            e.contains("t.vk7") && e.contains("zip entry 'Vk4File': truncated at byte offset 500"),
            "{e}"
        );
        assert!(decode(Path::new("t.vk6"), b"VK6\x10\0\0\0BM")
            .unwrap_err()
            .to_string()
            .contains("no zip archive"));
    }

    #[test]
    fn other_files_cuts_and_bad_fields_are_refused() {
        let good =
            encode(&counts(), &Vk4Parts { strings: Some(("t".into(), "l".into())), ..Default::default() });
        let err = |bytes: &[u8]| read(bytes).unwrap_err().to_string();
        assert!(err(b"AliconaImaging\0\r\n").contains("not a Keyence VK file"));
        assert!(err(b"VK4").contains("not a Keyence VK file"));
        assert!(err(b"VK3_\0\0\0\0").contains("VK3"));
        for cut in 0..good.len() {
            let e = err(&good[..cut]);
            assert!(e.contains("t.vk4") && e.contains("byte offset"), "cut at {cut}: {e}");
        }
        let set = |off: usize, v: u32| {
            let mut b = good.clone();
            b[off..off + 4].copy_from_slice(&v.to_le_bytes());
            b
        };
        assert!(err(&set(8, 1)).contains("file type"));
        assert!(err(&set(12, 20)).contains("points into the header"));
        assert!(err(&set(84, 100)).contains("size 100 is below"));
        let h = HEADER + TABLE + CONDITIONS_MIN;
        assert!(err(&set(12 + 4 * HEIGHT1, 0)).contains("no height image"));
        assert!(err(&set(h + 8, 24)).contains("bit depth 24"));
        assert!(err(&set(h + 16, 7)).contains("data size 7 is not 5 x 3 x 4 = 60"));
        assert!(err(&set(h, 0)).contains("is empty"));
        let e = err(&set(h, 1 << 20));
        assert!(e.contains("beyond any profilometer scan") || e.contains("data size"), "{e}");
        let strings = good.len() - 12;
        assert!(err(&set(strings, u32::MAX)).contains("the title's"));
    }
}
