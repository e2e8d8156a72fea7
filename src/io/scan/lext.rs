//! Olympus LEXT laser confocal microscope files (`.lext`, OLS4000 and later): a multi-page TIFF
//! whose pages are the images of one measurement, with the scales in XML.
//!
//! Layout (Gwyddion's `lextfile` module, surfalize's `lext.py` and SurfaceTopography's `LEXT`
//! reader, which agree on it; TIFF 6.0 for the container):
//!
//! | where | what |
//! |---|---|
//! | bytes 0-7 | classic TIFF header: `II*\0` (little-endian, what the instruments write) or `MM\0*`, then the offset of the first IFD (u32) |
//! | each IFD | u16 entry count, 12-byte entries (tag u16, type u16, count u32, value or offset u32), offset of the next IFD (0: last) |
//! | page 0 ImageDescription (270) | the `<TiffTagDescData>` XML: `HeightInfo/HeightDataPerPixelX`, `...Y` (picometres a pixel: the pitch) and `...Z` (picometres a count: the height unit), `HeightDataUnitX/Y/Z`, and the acquisition settings |
//! | page 0 ExifIFD (34665) | an EXIF IFD whose DeviceSettingDescription (0xA40B, ASCII) is the `<ExifTagDescData>` XML: `ImageCommonSettingsInfo/MakerCalibrationValueX/Y/Z` (the calibration factors x 10^6), objective, zoom |
//! | page 0 Make (271), Model (272), Software (305), DateTime (306) | the instrument, its software, the date `YYYY:MM:DD HH:MM:SS` |
//! | pages 1.. ImageDescription | the page's title: `HEIGHT`, `INTENSITY`, `COLOR`, `THUMBNAIL`, `INVALID` (any case) |
//! | `HEIGHT` page | one sample a pixel, uncompressed strips (StripOffsets 273, RowsPerStrip 278, StripByteCounts 279), the counts row by row from the top of the image: unsigned (SampleFormat 1, the default), signed (2) or float (3), 8 to 64 bits |
//! | `INVALID` page | a 1-bit mask (photometric 4) of the same size: a set bit marks a point not measured (FillOrder 266: 1, the most significant bit first, or 2) |
//!
//! Page 0 carries no title of its own (its ImageDescription is the XML): as Gwyddion and
//! surfalize do, its kind is inferred from its size and bit depth (128 x 128 RGB: a thumbnail;
//! RGB: the colour image; 1-bit: the invalid mask; 16-bit: the intensity) when no other page has
//! that title. Neither ever takes page 0 as the height image, and nor does this reader.
//!
//! Heights are `count x HeightDataPerPixelZ x zcal` picometres and the pitch
//! `HeightDataPerPixelX x xcal`, `...Y x ycal` picometres, with each calibration factor
//! `MakerCalibrationValue x 10^-6` (1 when the EXIF block or the value is absent). Gwyddion
//! since 2.55 (2019), surfalize and SurfaceTopography all apply the factors (Gwyddion's first
//! reader, 2010, ignored them, reading pitch and heights off by the factor); they are the maker's
//! per-instrument calibration, so they are applied here too. A factor that is not a positive
//! number is not applied (warning), as Gwyddion does for x and y.
//!
//! The `INVALID` mask's set bits become non-measured points (NaN), as surfalize reads them;
//! Gwyddion and SurfaceTopography do not read the mask (the counts stored there are then
//! heights to them). The intensity, colour and thumbnail pages are named in the metadata as not
//! read; a second `HEIGHT` page is skipped with a warning. Every page's strips must lie within
//! the file (a cut file is refused, whatever page it cuts). Compressed or tiled pages, BigTIFF
//! and several samples a pixel in the height page are refused naming the field.
//!
//! The XML elements of both blocks are kept as metadata under their paths without the root
//! (`HeightInfo/HeightDataPerPixelZ`), in file order; `objective` and `magnification` come from
//! `ObjectiveLenseType` and `ObjectiveLenseMagnification` wherever they lie.

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, decode_text, shape, Bin, ScanFormat, ScanRaw};

/// Picometres, the unit of the pitch and of the height per count.
const PM: f64 = 1e-12;
/// The most pages read (a LEXT file has five or six).
const MAX_PAGES: usize = 256;
/// The start of the measurement XML in page 0's ImageDescription.
const TIFF_XML: &str = "<TiffTagDescData";
/// The start of the device settings XML in the EXIF DeviceSettingDescription.
const EXIF_XML: &str = "<ExifTagDescData";

const IMAGE_WIDTH: u16 = 256;
const IMAGE_LENGTH: u16 = 257;
const BITS_PER_SAMPLE: u16 = 258;
const COMPRESSION: u16 = 259;
const FILL_ORDER: u16 = 266;
const IMAGE_DESCRIPTION: u16 = 270;
const MAKE: u16 = 271;
const MODEL: u16 = 272;
const STRIP_OFFSETS: u16 = 273;
const SAMPLES_PER_PIXEL: u16 = 277;
const ROWS_PER_STRIP: u16 = 278;
const STRIP_BYTE_COUNTS: u16 = 279;
const SOFTWARE: u16 = 305;
const DATE_TIME: u16 = 306;
const TILE_WIDTH: u16 = 322;
const SAMPLE_FORMAT: u16 = 339;
const EXIF_IFD: u16 = 34665;
const DEVICE_SETTING_DESCRIPTION: u16 = 0xA40B;

/// True when `head` starts as a classic TIFF does (either byte order).
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(b"II*\0") || head.starts_with(b"MM\0*")
}

/// One IFD entry: tag, type, count and the offset of the entry itself.
#[derive(Debug, Clone, Copy)]
struct Entry {
    tag: u16,
    kind: u16,
    count: u32,
    at: usize,
}

/// A TIFF file's bytes with its byte order.
struct Tiff<'a> {
    b: Bin<'a>,
    big: bool,
}

/// The size of one value of a TIFF field type, `None` for an unknown type.
fn type_size(kind: u16) -> Option<usize> {
    match kind {
        1 | 2 | 6 | 7 => Some(1),
        3 | 8 => Some(2),
        4 | 9 | 11 | 13 => Some(4),
        5 | 10 | 12 => Some(8),
        _ => None,
    }
}

impl<'a> Tiff<'a> {
    fn u16(&self, off: usize, what: &str) -> Result<u16> {
        let s = self.b.take(off, 2, what)?;
        let a = [s[0], s[1]];
        Ok(if self.big { u16::from_be_bytes(a) } else { u16::from_le_bytes(a) })
    }

    fn u32(&self, off: usize, what: &str) -> Result<u32> {
        let s = self.b.take(off, 4, what)?;
        let a = [s[0], s[1], s[2], s[3]];
        Ok(if self.big { u32::from_be_bytes(a) } else { u32::from_le_bytes(a) })
    }

    /// The entries of the IFD at `off`, and the offset of the next IFD.
    fn ifd(&self, off: usize, what: &str) -> Result<(Vec<Entry>, usize)> {
        let n = self.u16(off, &format!("the {what}'s entry count"))? as usize;
        self.b.take(off + 2, 12 * n + 4, &format!("the {what}'s {n} entries"))?;
        let mut entries = Vec::with_capacity(n);
        for k in 0..n {
            let at = off + 2 + 12 * k;
            entries.push(Entry {
                tag: self.u16(at, what)?,
                kind: self.u16(at + 2, what)?,
                count: self.u32(at + 4, what)?,
                at,
            });
        }
        let next = self.u32(off + 2 + 12 * n, &format!("the {what}'s next-IFD offset"))? as usize;
        Ok((entries, next))
    }

    /// The bytes of an entry's value (in the entry when they fit in 4 bytes).
    fn value(&self, e: &Entry, what: &str) -> Result<&'a [u8]> {
        let size = type_size(e.kind)
            .ok_or_else(|| self.b.bad(e.at + 2, format!("{what}: unknown TIFF field type {}", e.kind)))?;
        let len = (e.count as usize)
            .checked_mul(size)
            .ok_or_else(|| self.b.bad(e.at + 4, format!("{what}: {} values overflow", e.count)))?;
        if len <= 4 {
            self.b.take(e.at + 8, len, what)
        } else {
            let off = self.u32(e.at + 8, what)? as usize;
            self.b.take(off, len, &format!("{what} ({len} bytes)"))
        }
    }

    /// An entry's values as unsigned integers (BYTE, SHORT, LONG or IFD).
    fn uints(&self, e: &Entry, what: &str) -> Result<Vec<u64>> {
        let v = self.value(e, what)?;
        let big = self.big;
        Ok(match e.kind {
            1 => v.iter().map(|&x| x as u64).collect(),
            3 => v
                .chunks_exact(2)
                .map(|c| {
                    (if big { u16::from_be_bytes([c[0], c[1]]) } else { u16::from_le_bytes([c[0], c[1]]) })
                        as u64
                })
                .collect(),
            4 | 13 => v
                .chunks_exact(4)
                .map(|c| {
                    let a = [c[0], c[1], c[2], c[3]];
                    (if big { u32::from_be_bytes(a) } else { u32::from_le_bytes(a) }) as u64
                })
                .collect(),
            k => {
                return Err(self
                    .b
                    .bad(e.at + 2, format!("{what}: field type {k} where an unsigned integer is expected")))
            }
        })
    }

    /// An entry's text (ASCII, or UNDEFINED bytes), up to the first NUL.
    fn text(&self, e: &Entry, what: &str) -> Result<String> {
        match e.kind {
            2 | 7 => Ok(decode_text(self.value(e, what)?)),
            k => Err(self.b.bad(e.at + 2, format!("{what}: field type {k} where text is expected"))),
        }
    }
}

/// One page: its IFD offset, entries and title.
struct Page {
    at: usize,
    entries: Vec<Entry>,
    /// The ImageDescription (page 0: the XML), if any.
    description: Option<String>,
}

impl Page {
    fn get(&self, tag: u16) -> Option<&Entry> {
        self.entries.iter().find(|e| e.tag == tag)
    }
}

/// The image parameters of a page.
struct Image {
    /// The offset of the page's IFD (where its errors point).
    at: usize,
    cols: usize,
    rows: usize,
    spp: usize,
    bits: usize,
    format: u64,
    compression: u64,
    fill_order: u64,
    /// (offset, bytes) of each strip.
    strips: Vec<(usize, usize)>,
    rows_per_strip: usize,
}

/// Reads the image parameters of page `p` (number `index`) and checks its strips lie in the file.
fn image(t: &Tiff, p: &Page, index: usize) -> Result<Image> {
    let what = |name: &str| format!("page {index}'s {name}");
    let one = |tag: u16, name: &str, default: Option<u64>| -> Result<u64> {
        match p.get(tag) {
            Some(e) => t
                .uints(e, &what(name))?
                .first()
                .copied()
                .ok_or_else(|| t.b.bad(e.at, format!("{} has no value", what(name)))),
            None => default.ok_or_else(|| t.b.bad(p.at, format!("{} (tag {tag}) is missing", what(name)))),
        }
    };
    let cols = one(IMAGE_WIDTH, "ImageWidth", None)? as usize;
    let rows = one(IMAGE_LENGTH, "ImageLength", None)? as usize;
    let spp = one(SAMPLES_PER_PIXEL, "SamplesPerPixel", Some(1))? as usize;
    let bits = one(BITS_PER_SAMPLE, "BitsPerSample", Some(1))? as usize;
    let format = one(SAMPLE_FORMAT, "SampleFormat", Some(1))?;
    let compression = one(COMPRESSION, "Compression", Some(1))?;
    let fill_order = one(FILL_ORDER, "FillOrder", Some(1))?;
    if p.get(TILE_WIDTH).is_some() {
        return Err(t.b.bad(p.at, format!("page {index} is tiled: LEXT pages are strips")));
    }
    let rps = one(ROWS_PER_STRIP, "RowsPerStrip", Some(u32::MAX as u64))? as usize;
    let offsets = match p.get(STRIP_OFFSETS) {
        Some(e) => t.uints(e, &what("StripOffsets"))?,
        None => return Err(t.b.bad(p.at, format!("{} (tag 273) is missing", what("StripOffsets")))),
    };
    let counts = match p.get(STRIP_BYTE_COUNTS) {
        Some(e) => t.uints(e, &what("StripByteCounts"))?,
        None => return Err(t.b.bad(p.at, format!("{} (tag 279) is missing", what("StripByteCounts")))),
    };
    if counts.len() != offsets.len() {
        return Err(t.b.bad(
            p.at,
            format!(
                "page {index} has {} strip offsets but {} strip byte counts",
                offsets.len(),
                counts.len()
            ),
        ));
    }
    let rows_per_strip = if rps == 0 { rows } else { rps }.min(rows).max(1);
    // The bytes an uncompressed strip needs (some writers state more in StripByteCounts:
    // Gwyddion's TIFF export gives bits): what must lie in the file.
    let row_bytes = cols.checked_mul(spp).and_then(|n| n.checked_mul(bits)).map(|n| n.div_ceil(8));
    let mut strips = Vec::with_capacity(offsets.len());
    for (k, (&o, &n)) in offsets.iter().zip(&counts).enumerate() {
        let (o, n) = (o as usize, n as usize);
        let strip_rows = rows.saturating_sub(k.saturating_mul(rows_per_strip)).min(rows_per_strip);
        let need = match (compression, row_bytes) {
            (1, Some(rb)) => n.min(rb.saturating_mul(strip_rows)),
            _ => n,
        };
        t.b.take(o, need, &format!("page {index}'s strip {k}"))?;
        strips.push((o, n));
    }
    Ok(Image { at: p.at, cols, rows, spp, bits, format, compression, fill_order, strips, rows_per_strip })
}

/// The bytes of `rows` rows of `row_bytes` each of an uncompressed page, gathered from its strips.
fn rows_bytes(t: &Tiff, img: &Image, index: usize, row_bytes: usize) -> Result<Vec<u8>> {
    if img.rows == 0 || img.cols == 0 {
        return Err(t.b.bad(img.at, format!("page {index} is empty ({} x {} points)", img.cols, img.rows)));
    }
    let need = img.rows.checked_mul(row_bytes).ok_or_else(|| {
        Error::malformed(t.b.path, format!("page {index}: {} rows of {row_bytes} bytes overflow", img.rows))
    })?;
    let nstrips = img.rows.div_ceil(img.rows_per_strip);
    if img.strips.len() != nstrips {
        return Err(t.b.bad(
            img.at,
            format!(
                "page {index}: {} strips where {} rows of {} a strip need {nstrips}",
                img.strips.len(),
                img.rows,
                img.rows_per_strip
            ),
        ));
    }
    // Bounded by the strips, which lie in the file.
    let mut out = Vec::with_capacity(need.min(t.b.bytes.len()));
    for (k, &(off, len)) in img.strips.iter().enumerate() {
        let strip_rows = img.rows_per_strip.min(img.rows - k * img.rows_per_strip);
        let want = strip_rows * row_bytes;
        if len < want {
            return Err(t.b.bad(
                off,
                format!("page {index}'s strip {k} holds {len} bytes, {strip_rows} rows of {row_bytes} need {want}"),
            ));
        }
        out.extend_from_slice(t.b.take(off, want, &format!("page {index}'s strip {k}"))?);
    }
    Ok(out)
}

/// The height page's counts, row by row.
fn heights(t: &Tiff, img: &Image, index: usize) -> Result<Vec<f64>> {
    let at = img.at;
    if img.compression != 1 {
        return Err(t.b.bad(
            at,
            format!(
                "the HEIGHT page {index} is compressed (Compression {}): LEXT writes it uncompressed",
                img.compression
            ),
        ));
    }
    if img.spp != 1 {
        return Err(t.b.bad(at, format!("the HEIGHT page {index} has {} samples a pixel, not 1", img.spp)));
    }
    let size = match (img.format, img.bits) {
        (1 | 2, 8 | 16 | 32 | 64) | (3, 32 | 64) => img.bits / 8,
        (f, b) => {
            return Err(t.b.bad(
                at,
                format!(
                    "the HEIGHT page {index}'s {b}-bit samples of SampleFormat {f} are not read \
                     (unsigned or signed 8 to 64 bits, float 32 or 64)"
                ),
            ))
        }
    };
    data_len(t.b.path, img.rows, img.cols, size)?;
    let raw = rows_bytes(t, img, index, img.cols * size)?;
    let big = t.big;
    let v = raw
        .chunks_exact(size)
        .map(|c| {
            let mut a = [0u8; 8];
            if big {
                a[8 - size..].copy_from_slice(c);
            } else {
                a[..size].copy_from_slice(c);
            }
            let bits = if big { u64::from_be_bytes(a) } else { u64::from_le_bytes(a) };
            let shift = 64 - 8 * size as u32;
            match img.format {
                1 => bits as f64,
                2 => ((bits << shift) as i64 >> shift) as f64,
                _ if size == 4 => f32::from_bits(bits as u32) as f64,
                _ => f64::from_bits(bits),
            }
        })
        .map(|v| if v.is_finite() { v } else { f64::NAN })
        .collect();
    Ok(v)
}

/// The invalid mask page's bits, row by row (true: not measured).
fn mask(t: &Tiff, img: &Image, index: usize) -> Result<Vec<bool>> {
    let row_bytes = img.cols.div_ceil(8);
    data_len(t.b.path, img.rows, row_bytes, 1)?;
    let raw = rows_bytes(t, img, index, row_bytes)?;
    let lsb = img.fill_order == 2;
    let mut out = Vec::with_capacity(img.rows * img.cols);
    for row in raw.chunks_exact(row_bytes.max(1)) {
        for j in 0..img.cols {
            let byte = row[j / 8];
            let bit = if lsb { j % 8 } else { 7 - j % 8 };
            out.push((byte >> bit) & 1 == 1);
        }
    }
    Ok(out)
}

/// The elements of an XML block with text, as (path without the root, text), in file order.
fn flatten(xml: &str) -> std::result::Result<Vec<(String, String)>, String> {
    let doc = roxmltree::Document::parse(xml).map_err(|e| e.to_string())?;
    let mut out = Vec::new();
    // Depth-first in file order, without recursion; elements below MAX_DEPTH (the LEXT blocks
    // nest three deep) are not kept, which bounds the paths' length.
    const MAX_DEPTH: usize = 16;
    let mut stack: Vec<(roxmltree::Node, String, usize)> = vec![(doc.root_element(), String::new(), 0)];
    while let Some((n, path, depth)) = stack.pop() {
        let children: Vec<_> = n.children().filter(|c| c.is_element() && depth < MAX_DEPTH).collect();
        for c in children.into_iter().rev() {
            let name = c.tag_name().name();
            let p = if path.is_empty() { name.to_string() } else { format!("{path}/{name}") };
            stack.push((c, p, depth + 1));
        }
        if n != doc.root_element() {
            if let Some(t) = n.text().map(str::trim).filter(|t| !t.is_empty()) {
                out.push((path, t.to_string()));
            }
        }
    }
    Ok(out)
}

/// The last value of `key` (the readers keep the last of repeated elements).
fn lookup<'m>(m: &'m [(String, String)], key: &str) -> Option<&'m str> {
    m.iter().rev().find(|(k, _)| k == key).map(|(_, v)| v.as_str())
}

/// The kind of page 0 as its size and depth suggest, unless another page carries that title.
fn guess_page0(img: &Image, titles: &[String]) -> Option<&'static str> {
    let seen = |t: &str| titles.iter().any(|x| x == t);
    let g = match (img.cols, img.rows, img.spp, img.bits) {
        (128, 128, 3, 8) => "THUMBNAIL",
        (_, _, 3, 8) => "COLOR",
        (_, _, 1, 1) => "INVALID",
        (_, _, 1, 16) => "INTENSITY",
        _ => return None,
    };
    (!seen(g)).then_some(g)
}

/// Decodes a `.lext` file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    let big = match bytes.get(..4) {
        Some(b"II*\0") => false,
        Some(b"MM\0*") => true,
        Some(b"II+\0") | Some(b"MM\0+") => {
            return Err(b.bad(0, "a BigTIFF file: Olympus LEXT files are classic TIFF"));
        }
        _ => {
            b.take(0, 4, "the TIFF header")?;
            return Err(b.signature(
                0,
                "not an Olympus LEXT file: it does not start as a TIFF file does (II*\\0 or MM\\0*)",
            ));
        }
    };
    let t = Tiff { b: Bin::new(path, bytes), big };
    let pages = read_pages(&t)?;
    let images: Vec<Image> = pages.iter().enumerate().map(|(i, p)| image(&t, p, i)).collect::<Result<_>>()?;

    // Page 0's measurement XML.
    let desc = pages[0].description.as_deref().unwrap_or("");
    let Some(start) = desc.find(TIFF_XML) else {
        return Err(t.b.signature(
            pages[0].at,
            "not an Olympus LEXT file: the first page's ImageDescription holds no <TiffTagDescData> XML",
        ));
    };
    let mut warnings = Vec::new();
    let mut xml = flatten(&desc[start..]).map_err(|e| {
        t.b.bad(pages[0].at, format!("the first page's <TiffTagDescData> XML does not parse: {e}"))
    })?;

    let (cal, cal_text, exif_read) = device_calibration(&t, &pages[0], &mut xml, &mut warnings)?;

    // The height page: the first titled HEIGHT after page 0.
    let titles: Vec<String> =
        pages.iter().map(|p| p.description.as_deref().unwrap_or("").trim().to_ascii_uppercase()).collect();
    let guessed = guess_page0(&images[0], &titles[1..]);
    let height_pages: Vec<usize> = (1..pages.len()).filter(|&i| titles[i] == "HEIGHT").collect();
    let Some(&hp) = height_pages.first() else {
        return Err(t.b.bad(
            pages[0].at,
            format!("no page titled HEIGHT among the {} pages: the file holds no topography", pages.len()),
        ));
    };
    let img = &images[hp];
    let values = heights(&t, img, hp)?;
    let (rows, cols) = (img.rows, img.cols);
    let mut values = shape(path, rows, cols, values)?;
    if height_pages.len() > 1 {
        let skipped: Vec<String> = height_pages[1..].iter().map(|i| format!("page {i}")).collect();
        warnings.push(format!("HEIGHT page {hp} read; further HEIGHT {} skipped", skipped.join(", ")));
    }

    // The invalid mask.
    let mask_page =
        (1..pages.len()).find(|&i| titles[i] == "INVALID").or((guessed == Some("INVALID")).then_some(0));
    let invalid = match mask_page {
        Some(mp) => apply_invalid_mask(&t, &images[mp], mp, &mut values, &mut warnings)?,
        None => 0,
    };

    let num = |key: &str| {
        lookup(&xml, key).and_then(|v| v.parse::<f64>().ok()).filter(|v| v.is_finite() && *v > 0.0)
    };
    let (px, py, pz) = (
        num("HeightInfo/HeightDataPerPixelX"),
        num("HeightInfo/HeightDataPerPixelY"),
        num("HeightInfo/HeightDataPerPixelZ"),
    );
    let pitch = match (px, py) {
        (Some(x), Some(y)) => Some([x * cal[0] * PM, y * cal[1] * PM]),
        _ => {
            warnings.push(
                "HeightInfo/HeightDataPerPixelX and Y are not both positive numbers: no pitch, pass `pitch`"
                    .into(),
            );
            None
        }
    };
    let unit = match pz {
        Some(z) => Some(z * cal[2] * PM),
        None => {
            warnings.push(
                "HeightInfo/HeightDataPerPixelZ is not a positive number: pass `z_unit` (metres per count)"
                    .into(),
            );
            None
        }
    };
    let units: Vec<&str> = ["X", "Y", "Z"]
        .iter()
        .filter_map(|a| lookup(&xml, &format!("HeightInfo/HeightDataUnit{a}")))
        .collect();
    if units.len() == 3 && (units[0] != units[2] || units[1] != units[2]) {
        warnings.push(format!(
            "HeightDataUnitX, Y, Z differ ({}, {}, {}): the lengths are read as picometres all the same",
            units[0], units[1], units[2]
        ));
    }

    // Metadata.
    let mut metadata = instrument_metadata(&t, &pages[0], &xml)?;
    metadata.push((
        "calibration".into(),
        if cal_text.is_empty() {
            if exif_read { "no MakerCalibrationValue" } else { "no EXIF device settings" }.to_string()
        } else {
            format!("MakerCalibrationValue x 1e-6 applied: {}", cal_text.join(", "))
        },
    ));
    metadata.push((
        "height_page".into(),
        format!(
            "page {hp} of {} ({}-bit {}, byte order {})",
            pages.len(),
            img.bits,
            sample_name(img.format),
            if big { "MM" } else { "II" }
        ),
    ));
    if let Some(mp) = mask_page {
        metadata.push(("invalid_page".into(), format!("page {mp}: {invalid} points not measured")));
    }
    let others: Vec<String> = (0..pages.len())
        .filter(|&i| i != hp && Some(i) != mask_page && !height_pages.contains(&i))
        .filter_map(|i| {
            if i == 0 {
                guessed.map(|g| format!("{g} (page 0, inferred)"))
            } else if titles[i].is_empty() {
                Some(format!("page {i} (untitled)"))
            } else {
                Some(format!("{} (page {i})", titles[i]))
            }
        })
        .collect();
    if !others.is_empty() {
        metadata.push(("images_not_read".into(), others.join(", ")));
    }
    metadata.push((
        "height_unit".into(),
        match pz {
            Some(z) => format!("{z} pm per count x {}", cal[2]),
            None => "none".into(),
        },
    ));
    metadata.extend(xml);
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit, metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Lext);
    sr.warnings = warnings;
    Ok(sr)
}

/// The chain of pages (IFDs) from the header's first offset, each with its ImageDescription;
/// a loop, more than [`MAX_PAGES`] pages or none at all is refused.
fn read_pages(t: &Tiff) -> Result<Vec<Page>> {
    let mut pages: Vec<Page> = Vec::new();
    let mut next = t.u32(4, "the first IFD offset")? as usize;
    while next != 0 {
        if pages.len() == MAX_PAGES || pages.iter().any(|p| p.at == next) {
            return Err(t.b.bad(next, format!("the chain of IFDs loops or passes {MAX_PAGES} pages")));
        }
        let index = pages.len();
        let (entries, n) = t.ifd(next, &format!("page {index}'s IFD"))?;
        let mut p = Page { at: next, entries, description: None };
        if let Some(e) = p.get(IMAGE_DESCRIPTION).copied() {
            p.description = Some(t.text(&e, &format!("page {index}'s ImageDescription"))?);
        }
        pages.push(p);
        next = n;
    }
    if pages.is_empty() {
        return Err(t.b.bad(4, "the TIFF file has no page"));
    }
    Ok(pages)
}

/// The maker's calibration factors of x, y and z (`MakerCalibrationValue` times `1e-6`, 1 where
/// absent or unusable, with a warning), page 0's EXIF device settings XML added to `xml`:
/// the factors, their text and whether the EXIF settings were read.
fn device_calibration(
    t: &Tiff,
    page0: &Page,
    xml: &mut Vec<(String, String)>,
    warnings: &mut Vec<String>,
) -> Result<([f64; 3], Vec<String>, bool)> {
    let mut exif_read = false;
    if let Some(e) = page0.get(EXIF_IFD).copied() {
        let off = *t.uints(&e, "page 0's ExifIFD offset")?.first().unwrap_or(&0) as usize;
        if off != 0 {
            let (entries, _) = t.ifd(off, "EXIF IFD")?;
            if let Some(d) = entries.iter().find(|e| e.tag == DEVICE_SETTING_DESCRIPTION) {
                let text = t.text(d, "the EXIF DeviceSettingDescription")?;
                match text.find(EXIF_XML).map(|s| flatten(&text[s..])) {
                    Some(Ok(m)) => {
                        xml.extend(m);
                        exif_read = true;
                    }
                    Some(Err(err)) => warnings.push(format!(
                        "the EXIF <ExifTagDescData> XML does not parse ({err}): no calibration factors applied"
                    )),
                    None => {}
                }
            }
        }
    }
    let mut cal = [1.0f64; 3];
    let mut cal_text = Vec::new();
    for (k, axis) in ["X", "Y", "Z"].iter().enumerate() {
        let key = format!("ImageCommonSettingsInfo/MakerCalibrationValue{axis}");
        if let Some(v) = lookup(xml, &key) {
            match v.parse::<f64>().ok().map(|x| x * 1e-6).filter(|x| x.is_finite() && *x > 0.0) {
                Some(f) => {
                    cal[k] = f;
                    cal_text.push(format!("{axis} {f}"));
                }
                None => warnings
                    .push(format!("MakerCalibrationValue{axis} '{v}' is not a positive number: not applied")),
            }
        }
    }
    Ok((cal, cal_text, exif_read))
}

/// Applies the INVALID page `m` (page `mp`) to the heights `values`: NaN where its bit is set;
/// a mask that is not an uncompressed 1-bit page of the heights' size is not applied, with a
/// warning. Returns the points it marked.
fn apply_invalid_mask(
    t: &Tiff,
    m: &Image,
    mp: usize,
    values: &mut ndarray::Array2<f64>,
    warnings: &mut Vec<String>,
) -> Result<usize> {
    let (rows, cols) = values.dim();
    let mut invalid = 0usize;
    if m.bits != 1 || m.spp != 1 || m.compression != 1 {
        warnings.push(format!(
            "the INVALID page {mp} ({} samples of {} bits, Compression {}) is not an uncompressed \
             1-bit mask: not applied",
            m.spp, m.bits, m.compression
        ));
    } else if (m.rows, m.cols) != (rows, cols) {
        warnings.push(format!(
            "the INVALID page {mp} is {} x {}, the heights {cols} x {rows}: not applied",
            m.cols, m.rows
        ));
    } else {
        for (v, bad) in values.iter_mut().zip(mask(t, m, mp)?) {
            if bad && !v.is_nan() {
                *v = f64::NAN;
                invalid += 1;
            }
        }
    }
    Ok(invalid)
}

/// The instrument (page 0's Make and Model, else "Olympus LEXT"), software, date and the
/// objective and its magnification from the XML, where given.
fn instrument_metadata(t: &Tiff, page0: &Page, xml: &[(String, String)]) -> Result<Vec<(String, String)>> {
    let tag_text = |tag: u16, name: &str| -> Result<Option<String>> {
        match page0.get(tag) {
            Some(e) => Ok(Some(t.text(e, &format!("page 0's {name}"))?).filter(|s| !s.is_empty())),
            None => Ok(None),
        }
    };
    let make = tag_text(MAKE, "Make")?;
    let model = tag_text(MODEL, "Model")?;
    let mut metadata: Vec<(String, String)> = Vec::new();
    let instrument = match (&make, &model) {
        (Some(a), Some(b)) => format!("{a} {b}"),
        (Some(a), None) | (None, Some(a)) => a.clone(),
        (None, None) => "Olympus LEXT".into(),
    };
    metadata.push(("instrument".into(), instrument));
    if let Some(s) = tag_text(SOFTWARE, "Software")? {
        metadata.push(("software".into(), s));
    }
    if let Some(d) = tag_text(DATE_TIME, "DateTime")? {
        metadata.push(("date".into(), tiff_date(&d).unwrap_or(d)));
    }
    let by_name =
        |name: &str| xml.iter().find(|(k, _)| k.rsplit('/').next() == Some(name)).map(|(_, v)| v.clone());
    if let Some(o) = by_name("ObjectiveLenseType") {
        metadata.push(("objective".into(), o));
    }
    if let Some(m) = by_name("ObjectiveLenseMagnification") {
        metadata.push(("magnification".into(), m));
    }
    Ok(metadata)
}

fn sample_name(format: u64) -> &'static str {
    match format {
        2 => "signed",
        3 => "float",
        _ => "unsigned",
    }
}

/// `YYYY:MM:DD HH:MM:SS` (TIFF DateTime) as `YYYY-MM-DDTHH:MM:SS`; `None` for any other text.
fn tiff_date(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let digits = |r: std::ops::Range<usize>| b.get(r).is_some_and(|d| d.iter().all(u8::is_ascii_digit));
    let ok = b.len() == 19
        && digits(0..4)
        && b[4] == b':'
        && digits(5..7)
        && b[7] == b':'
        && digits(8..10)
        && b[10] == b' '
        && digits(11..13)
        && b[13] == b':'
        && digits(14..16)
        && b[16] == b':'
        && digits(17..19);
    ok.then(|| format!("{}-{}-{}T{}", &s[0..4], &s[5..7], &s[8..10], &s[11..19]))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One page for [`tiff`]: (description, width, height, bits, sample format, fill order,
    /// the strip's bytes).
    type PageSpec<'a> = (&'a str, u32, u32, u16, u16, u16, Vec<u8>);

    /// A classic TIFF of `pages`, one strip each, in the byte order `big` says (built from the
    /// TIFF 6.0 layout, for tests).
    fn tiff(big: bool, pages: &[PageSpec]) -> Vec<u8> {
        let u16b = |v: u16| if big { v.to_be_bytes() } else { v.to_le_bytes() };
        let u32b = |v: u32| if big { v.to_be_bytes() } else { v.to_le_bytes() };
        let mut out = if big { b"MM\0*".to_vec() } else { b"II*\0".to_vec() };
        out.extend_from_slice(&u32b(8));
        for (k, (desc, w, h, bits, format, fill, data)) in pages.iter().enumerate() {
            let mut text = desc.as_bytes().to_vec();
            text.push(0);
            let n = 10u16;
            let ifd = out.len();
            let text_at = ifd + 2 + 12 * n as usize + 4;
            let data_at = text_at + text.len();
            let next = if k + 1 == pages.len() { 0 } else { (data_at + data.len()) as u32 };
            out.extend_from_slice(&u16b(n));
            let mut entry = |tag: u16, kind: u16, count: u32, value: [u8; 4]| {
                out.extend_from_slice(&u16b(tag));
                out.extend_from_slice(&u16b(kind));
                out.extend_from_slice(&u32b(count));
                out.extend_from_slice(&value);
            };
            let short = |v: u16| {
                let mut a = [0u8; 4];
                a[..2].copy_from_slice(&u16b(v));
                a
            };
            entry(IMAGE_WIDTH, 4, 1, u32b(*w));
            entry(IMAGE_LENGTH, 4, 1, u32b(*h));
            entry(BITS_PER_SAMPLE, 3, 1, short(*bits));
            entry(FILL_ORDER, 3, 1, short(*fill));
            entry(IMAGE_DESCRIPTION, 2, text.len() as u32, u32b(text_at as u32));
            entry(STRIP_OFFSETS, 4, 1, u32b(data_at as u32));
            entry(SAMPLES_PER_PIXEL, 3, 1, short(1));
            entry(ROWS_PER_STRIP, 4, 1, u32b(*h));
            entry(STRIP_BYTE_COUNTS, 4, 1, u32b(data.len() as u32));
            entry(SAMPLE_FORMAT, 3, 1, short(*format));
            out.extend_from_slice(&u32b(next));
            out.extend_from_slice(&text);
            out.extend_from_slice(data);
        }
        out
    }

    const XML: &str = "<?xml version=\"1.0\"?><TiffTagDescData a=\"1\"><HeightInfo>\
        <HeightDataPerPixelX>1000000</HeightDataPerPixelX><HeightDataPerPixelY>2000000</HeightDataPerPixelY>\
        <HeightDataPerPixelZ>1000</HeightDataPerPixelZ></HeightInfo></TiffTagDescData>";

    #[test]
    fn float_heights_lsb_first_mask_and_both_byte_orders() {
        for big in [false, true] {
            // 3 x 2 f64 heights (one NaN), and 32-bit floats; a mask marking (0, 2) and (1, 0)
            // with the least significant bit first.
            let h = [1.0f64, 2.0, 3.0, f64::NAN, 5.0, 6.0];
            let f64s: Vec<u8> =
                h.iter().flat_map(|v| if big { v.to_be_bytes() } else { v.to_le_bytes() }).collect();
            let f32s: Vec<u8> = h
                .iter()
                .flat_map(|&v| if big { (v as f32).to_be_bytes() } else { (v as f32).to_le_bytes() })
                .collect();
            for (bits, data) in [(64, f64s), (32, f32s)] {
                let bytes = tiff(
                    big,
                    &[
                        (XML, 1, 1, 8, 1, 1, vec![0]),
                        ("Height", 3, 2, bits, 3, 1, data),
                        ("invalid", 3, 2, 1, 1, 2, vec![0b100, 0b001]),
                    ],
                );
                let r = decode(Path::new("t.lext"), &bytes).unwrap();
                let v: Vec<f64> = r.raw.values.iter().copied().collect();
                let want = [1.0, 2.0, f64::NAN, f64::NAN, 5.0, 6.0];
                assert!(
                    v.iter().zip(want).all(|(a, b)| a == &b || a.is_nan() && b.is_nan()),
                    "{big} {bits}: {v:?}"
                );
                assert_eq!(r.raw.pitch, Some([1e6 * PM, 2e6 * PM]));
                assert_eq!(r.raw.unit, Some(1000.0 * PM));
                let m = |k: &str| r.raw.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.clone());
                assert_eq!(m("invalid_page").as_deref(), Some("page 2: 1 points not measured"));
                assert_eq!(m("calibration").as_deref(), Some("no EXIF device settings"));
                assert_eq!(m("instrument").as_deref(), Some("Olympus LEXT"));
                assert!(r.warnings.is_empty(), "{:?}", r.warnings);
            }
        }
    }

    #[test]
    fn unsigned_bytes_signed_shorts_and_refusals() {
        let page0 = (XML, 1, 1, 8, 1, 1, vec![0]);
        let r = decode(
            Path::new("t.lext"),
            &tiff(false, &[page0.clone(), ("HEIGHT", 2, 1, 8, 1, 1, vec![7, 255])]),
        )
        .unwrap();
        assert_eq!(r.raw.values.iter().copied().collect::<Vec<_>>(), [7.0, 255.0]);
        let s: Vec<u8> = [-3i16, 4].iter().flat_map(|v| v.to_be_bytes()).collect();
        let r = decode(Path::new("t.lext"), &tiff(true, &[page0.clone(), ("HEIGHT", 2, 1, 16, 2, 1, s)]))
            .unwrap();
        assert_eq!(r.raw.values.iter().copied().collect::<Vec<_>>(), [-3.0, 4.0]);
        let err =
            |pages: &[PageSpec]| decode(Path::new("t.lext"), &tiff(false, pages)).unwrap_err().to_string();
        let e = err(&[page0.clone(), ("HEIGHT", 2, 1, 16, 3, 1, vec![0; 4])]);
        assert!(e.contains("16-bit samples of SampleFormat 3 are not read"), "{e}");
        let e = err(&[page0.clone(), ("HEIGHT", 2, 1, 16, 1, 1, vec![0; 3])]);
        assert!(e.contains("strip 0 holds 3 bytes"), "{e}");
        let e = err(&[page0.clone(), ("INTENSITY", 2, 1, 16, 1, 1, vec![0; 4])]);
        assert!(e.contains("no page titled HEIGHT"), "{e}");
        let e = err(&[("HEIGHT", 2, 1, 16, 1, 1, vec![0; 4])]);
        assert!(e.contains("no <TiffTagDescData>"), "{e}");
        let e = err(&[("<TiffTagDescData><a>", 1, 1, 8, 1, 1, vec![0])]);
        assert!(e.contains("XML does not parse"), "{e}");
        let e = decode(Path::new("t.lext"), b"II+\0\x08\0\0\0").unwrap_err().to_string();
        assert!(e.contains("BigTIFF"), "{e}");
        let mut looped = tiff(false, &[page0]);
        let n = looped.len();
        let ifd_next = 8 + 2 + 12 * 10;
        looped[ifd_next..ifd_next + 4].copy_from_slice(&8u32.to_le_bytes());
        assert!(n > ifd_next);
        let e = decode(Path::new("t.lext"), &looped).unwrap_err().to_string();
        assert!(e.contains("loops"), "{e}");
        assert_eq!(tiff_date("2024:03:05 14:22:31").as_deref(), Some("2024-03-05T14:22:31"));
        assert_eq!(tiff_date("5 March 2024"), None);
    }
}
