//! Wyko / Bruker Vision binary data files (`.opd`), the height map.
//!
//! Little-endian throughout. After two bytes `01 00` comes a directory of 24-byte entries:
//!
//! | bytes | field |
//! |---|---|
//! | 0..16 | name, padded with NUL or spaces |
//! | 16..18 | u16 type (below) |
//! | 18..22 | u32 size of the entry's data, bytes |
//! | 22..24 | u16 flags |
//!
//! The first entry is the directory itself (`Directory`, type 1, flags `0xffff`, size = 24 x
//! the number of entries). The entries' data follow the directory in the entries' order, each
//! `size` bytes long (empty entries take none). The types, as Gwyddion's `opdfile` module
//! (2.6x) and SurfaceTopography's `OPD.py` (1.27) read them:
//!
//! | type | data |
//! |---|---|
//! | 1 | directory: only the first entry (a nested one is refused) |
//! | 3 | array: three u16, columns, rows and bytes per element (4: f32, 2: i16, 1: u8), then the elements column by column, each column from the last row to the first |
//! | 5 | text, NUL-padded |
//! | 6 | short (i16); one of 4 bytes is a long |
//! | 7 | float (f32); one of 2 bytes is a short (Vision's `AdjustVSI_*` entries), one of more bytes holds the float in its first 4 (`ImageModificat~0` declares 40) |
//! | 8 | double (f64) |
//! | 12 | long (i32) |
//! | 15, others | serialised structures of later Vision versions (among them `ExtendedKeys`, the full names of entries whose names were cut to 16 bytes): skipped by their size |
//!
//! The height map is the first array, in directory order, named `OPD`, `SAMPLE_DATA`,
//! `RAW_DATA`, `RAW DATA` or `Raw` (later Vision versions); arrays named `Image`, `Intensity`
//! or `SecArr_0` are intensity images and are not read. `z = value * Wavelength (nm) / Mult`
//! (`Mult` absent: 1; either of any number type). Non-measured points are f32 values of 1e38
//! and above or not finite, and i16 values of 32766 and above (signed: negative heights are
//! measured ones); u8 arrays have no marker. `Pixel_size` (millimetres) is the x pitch, y is
//! `Aspect` times it.
//!
//! The two readers differ in one place: for a float `ImageModificat~0` that declares 40 bytes,
//! Gwyddion counts 4 bytes in the layout, SurfaceTopography the declared 40. The declared sizes
//! are taken unless the file ends exactly where Gwyddion's count puts the end and not where
//! the declared sizes do (a warning says so). The reader is checked against Gwyddion's and
//! SurfaceTopography's reading of a real file and SurfaceTopography's of files built from this
//! layout (`profilometry/make_opd_files.py`).

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, shape, Bin, ScanFormat, ScanRaw};

const ENTRY: usize = 24;
const T_DIRECTORY: u16 = 1;
const T_ARRAY: u16 = 3;
const T_TEXT: u16 = 5;
const T_SHORT: u16 = 6;
const T_FLOAT: u16 = 7;
const T_DOUBLE: u16 = 8;
const T_LONG: u16 = 12;
const HEIGHT_ARRAYS: [&str; 5] = ["OPD", "SAMPLE_DATA", "RAW_DATA", "RAW DATA", "Raw"];
const INTENSITY_ARRAYS: [&str; 3] = ["Image", "Intensity", "SecArr_0"];
const BAD_F32: f32 = 1e38;
const BAD_I16: i16 = 32766;

/// True when `head` starts as an OPD file does (`01 00 Directory`).
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(b"\x01\x00Directory")
}

/// One directory entry: where it is listed (`at`) and where its data are.
struct Entry {
    name: String,
    kind: u16,
    at: usize,
    offset: usize,
    size: usize,
}

/// The size Gwyddion counts for an entry's data: 4 bytes for a float `ImageModificat~0` that
/// declares 40, else the declared size.
fn gwyddion_size(name: &str, kind: u16, size: usize) -> usize {
    if kind == T_FLOAT && size == 40 && name == "ImageModificat~0" {
        4
    } else {
        size
    }
}

/// The value of a number entry as both readers take it (the type-size pairs in the module
/// docs); `None` for text, arrays, other types and sizes that hold no number of the type.
fn number(bytes: &[u8], e: &Entry) -> Option<f64> {
    let d = &bytes[e.offset..e.offset + e.size];
    let short = || f64::from(i16::from_le_bytes([d[0], d[1]]));
    let long = || f64::from(i32::from_le_bytes([d[0], d[1], d[2], d[3]]));
    match (e.kind, e.size) {
        (T_SHORT | T_FLOAT, 2) => Some(short()),
        (T_SHORT, 4) | (T_LONG, 4..) => Some(long()),
        (T_FLOAT, 4..) => Some(f64::from(f32::from_le_bytes([d[0], d[1], d[2], d[3]]))),
        (T_DOUBLE, 8..) => Some(f64::from_le_bytes([d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]])),
        _ => None,
    }
}

/// Decodes an OPD file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    b.take(0, 2 + ENTRY, "the directory entry")?;
    if !has_magic(bytes) {
        return Err(b.signature(0, "not a Wyko OPD file: it does not start with 01 00 'Directory'"));
    }
    let mut warnings = Vec::new();
    let entries = read_directory(&b, &mut warnings)?;
    let find = |name: &str| entries.iter().find(|e| e.name == name);
    // A scale entry's value; `None` when absent, an error when it holds no number.
    let scale = |name: &str| -> Result<Option<f64>> {
        find(name)
            .map(|e| {
                number(bytes, e).ok_or_else(|| {
                    b.bad(
                        e.at + 16,
                        format!("entry '{name}' of type {} and {} bytes is not a number", e.kind, e.size),
                    )
                })
            })
            .transpose()
    };
    let wavelength = scale("Wavelength")?.ok_or_else(|| {
        b.bad(2, "the entry 'Wavelength' (nm, the height of one count with Mult) is missing")
    })?;
    if !(wavelength.is_finite() && wavelength > 0.0 && wavelength < 1e5) {
        return Err(b.bad(find("Wavelength").map_or(2, |e| e.offset), format!("Wavelength {wavelength} nm")));
    }
    let mult = scale("Mult")?.unwrap_or(1.0);
    if !(mult.is_finite() && mult != 0.0) {
        return Err(b.bad(find("Mult").map_or(2, |e| e.offset), format!("Mult {mult}")));
    }
    let pixel = scale("Pixel_size")?;
    let aspect = scale("Aspect")?.unwrap_or(1.0);
    let heights: Vec<&Entry> =
        entries.iter().filter(|e| e.kind == T_ARRAY && HEIGHT_ARRAYS.contains(&e.name.as_str())).collect();
    let Some(&data) = heights.first() else {
        let held: Vec<String> = entries
            .iter()
            .filter(|e| e.kind == T_ARRAY || HEIGHT_ARRAYS.contains(&e.name.as_str()))
            .map(|e| match e.kind {
                T_ARRAY if INTENSITY_ARRAYS.contains(&e.name.as_str()) => format!("'{}' (intensity)", e.name),
                T_ARRAY => format!("'{}'", e.name),
                k => format!("'{}' (of type {k}, not an array)", e.name),
            })
            .collect();
        let held = if held.is_empty() { "none".to_string() } else { held.join(", ") };
        return Err(b.bad(
            2,
            format!(
                "no height array in the directory: expected an array entry (type 3) named OPD, SAMPLE_DATA, \
                 RAW_DATA, RAW DATA or Raw; its arrays: {held}"
            ),
        ));
    };
    if heights.len() > 1 {
        let rest: Vec<&str> = heights[1..].iter().map(|e| e.name.as_str()).collect();
        warnings.push(format!(
            "the height array '{}' is read; further height arrays skipped: {}",
            data.name,
            rest.join(", ")
        ));
    }
    let cols = b.u16le(data.offset, "the array's columns")? as usize;
    let rows = b.u16le(data.offset + 2, "the array's rows")? as usize;
    let elem = b.u16le(data.offset + 4, "the array's element size")? as usize;
    if !matches!(elem, 1 | 2 | 4) {
        return Err(b.bad(data.offset + 4, format!("array element of {elem} bytes (1, 2 or 4 expected)")));
    }
    let need = data_len(path, rows, cols, elem)?;
    if data.size < 6 + need {
        return Err(b.bad(
            data.offset,
            format!(
                "array '{}' of {cols} x {rows} x {elem} bytes does not fit its {} bytes",
                data.name, data.size
            ),
        ));
    }
    let raw = b.take(data.offset + 6, need, "the array's elements")?;
    let z = wavelength * 1e-9 / mult;
    let mut values = vec![f64::NAN; rows * cols];
    for (k, v) in raw.chunks_exact(elem).enumerate() {
        // Column k / rows, stored from the last row up.
        let (col, r) = (k / rows, k % rows);
        let row = rows - 1 - r;
        values[row * cols + col] = match elem {
            4 => {
                let f = f32::from_le_bytes([v[0], v[1], v[2], v[3]]);
                if f.is_finite() && f < BAD_F32 {
                    f as f64 * z
                } else {
                    f64::NAN
                }
            }
            2 => {
                let s = i16::from_le_bytes([v[0], v[1]]);
                if s < BAD_I16 {
                    s as f64 * z
                } else {
                    f64::NAN
                }
            }
            _ => v[0] as f64 * z,
        };
    }
    let values = shape(path, rows, cols, values)?;
    let pitch = match pixel {
        Some(p) if p.is_finite() && p > 0.0 && aspect.is_finite() && aspect > 0.0 => {
            Some([p * 1e-3, aspect * p * 1e-3])
        }
        _ => None,
    };
    let mut metadata = Vec::new();
    for e in &entries {
        let text = match e.kind {
            T_TEXT => Some(crate::io::scan::raw::decode_text(&bytes[e.offset..e.offset + e.size])),
            T_SHORT | T_LONG | T_FLOAT | T_DOUBLE => {
                let v = number(bytes, e);
                if v.is_none() {
                    warnings.push(format!(
                        "entry '{}' of type {} holds {} bytes, no number of that type: left out",
                        e.name, e.kind, e.size
                    ));
                }
                v.map(|v| format!("{v}"))
            }
            _ => None,
        };
        if let Some(t) = text.filter(|t| !t.is_empty()) {
            metadata.push((e.name.clone(), t));
        }
    }
    if pitch.is_none() {
        warnings.push("the file states no usable Pixel_size: pass `pitch`".to_string());
    }
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Opd);
    sr.warnings = warnings;
    Ok(sr)
}

/// The directory (module docs): its entries with their data's offsets, in file order, those
/// without data left out; where the declared sizes do not end at the file's end but
/// Gwyddion's count does, that count is used, with a warning per entry it changes.
fn read_directory(b: &Bin, warnings: &mut Vec<String>) -> Result<Vec<Entry>> {
    let bytes = b.bytes;
    let dir_type = b.u16le(18, "the directory's type")?;
    let dir_size = b.u32le(20, "the directory's size")? as usize;
    let flags = b.u16le(24, "the directory's flags")?;
    if dir_type != T_DIRECTORY || flags != 0xffff || dir_size < ENTRY || !dir_size.is_multiple_of(ENTRY) {
        return Err(b.bad(
            18,
            format!(
                "directory entry of type {dir_type}, size {dir_size}, flags {flags:#06x}: expected type 1, a \
                 multiple of 24 bytes, flags 0xffff"
            ),
        ));
    }
    b.take(2, dir_size, "the directory")?;
    let mut listed = Vec::with_capacity(dir_size / ENTRY - 1);
    for k in 1..dir_size / ENTRY {
        let at = 2 + k * ENTRY;
        let name = b.text(at, 16, "an entry's name")?;
        let kind = b.u16le(at + 16, "an entry's type")?;
        let size = b.u32le(at + 18, "an entry's size")? as usize;
        if kind == T_DIRECTORY && size > 0 {
            return Err(b.bad(at + 16, format!("entry '{name}' is a nested directory")));
        }
        listed.push((name, kind, at, size));
    }
    // Where the data end with the declared sizes and with Gwyddion's count (u64: no overflow).
    let end = |count: &dyn Fn(&str, u16, usize) -> usize| -> u64 {
        listed.iter().map(|(n, k, _, s)| count(n, *k, *s) as u64).sum::<u64>() + (2 + dir_size) as u64
    };
    let len = bytes.len() as u64;
    let gwyddion = end(&|_, _, s| s) != len && end(&gwyddion_size) == len;
    let mut entries = Vec::new();
    let mut offset = 2 + dir_size;
    for (name, kind, at, declared) in listed {
        let size = if gwyddion { gwyddion_size(&name, kind, declared) } else { declared };
        if size != declared {
            warnings.push(format!(
                "entry '{name}' declares {declared} bytes and holds {size}: the file ends where that count \
                 (Gwyddion's) puts its end"
            ));
        }
        b.take(offset, size, &format!("the data of entry '{name}'"))?;
        if size > 0 {
            entries.push(Entry { name, kind, at, offset, size });
        }
        offset += size;
    }
    Ok(entries)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An entry: name bytes, type, declared size, the data written.
    type E = (Vec<u8>, u16, usize, Vec<u8>);

    /// An entry declaring the size of its data.
    fn e(name: &str, kind: u16, data: impl Into<Vec<u8>>) -> E {
        let data = data.into();
        (name.as_bytes().to_vec(), kind, data.len(), data)
    }

    /// A file byte by byte: `01 00`, the directory (itself first), each entry's data in order.
    fn build(entries: &[E]) -> Vec<u8> {
        let mut out = vec![1u8, 0];
        let mut entry = |name: &[u8], kind: u16, size: usize, flags: u16| {
            let mut n = [0u8; 16];
            n[..name.len()].copy_from_slice(name);
            out.extend_from_slice(&n);
            out.extend_from_slice(&kind.to_le_bytes());
            out.extend_from_slice(&(size as u32).to_le_bytes());
            out.extend_from_slice(&flags.to_le_bytes());
        };
        entry(b"Directory", T_DIRECTORY, ENTRY * (entries.len() + 1), 0xffff);
        for (name, kind, size, _) in entries {
            entry(name, *kind, *size, 0);
        }
        for (_, _, _, data) in entries {
            out.extend_from_slice(data);
        }
        out
    }

    /// An array entry's data: `rows x cols` elements of `elem` bytes, element (i, j) (row i from
    /// the top) from `cell`, written column by column, each column from the last row up.
    fn array(rows: usize, cols: usize, elem: u16, cell: impl Fn(usize, usize) -> Vec<u8>) -> Vec<u8> {
        let mut out = Vec::new();
        for v in [cols as u16, rows as u16, elem] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for j in 0..cols {
            for i in (0..rows).rev() {
                let c = cell(i, j);
                assert_eq!(c.len(), elem as usize);
                out.extend_from_slice(&c);
            }
        }
        out
    }

    fn f32b(v: f32) -> Vec<u8> {
        v.to_le_bytes().to_vec()
    }

    fn p() -> &'static Path {
        Path::new("t.opd")
    }

    /// Equal to within the rounding of the scale's products (1e-15 relative).
    fn close(got: f64, want: f64) -> bool {
        (got - want).abs() <= 1e-15 * want.abs()
    }

    fn md<'a>(s: &'a ScanRaw, key: &str) -> Option<&'a str> {
        s.raw.metadata.iter().find(|(k, _)| k == key).map(|(_, v)| v.as_str())
    }

    /// Each height array name with each element size, behind an intensity image: the counts
    /// times Wavelength / Mult, the markers of each size as non-measured points (none for u8),
    /// the extremes that are measured read as such.
    #[test]
    fn every_height_array_name_and_element_size() {
        let (rows, cols) = (3, 4);
        // The count at (i, j) and whether the element is a non-measured marker.
        let cell = |elem: u16, i: usize, j: usize| -> (Vec<u8>, Option<f64>) {
            let c = (10 * i + j) as f64 - 5.0;
            match (elem, i, j) {
                (4, 0, 1) => (f32b(1e38), None),
                (4, 1, 1) => (f32b(f32::INFINITY), None),
                (4, 2, 1) => (f32b(f32::NAN), None),
                (4, 2, 3) => (f32b(3e38), None),
                (4, ..) => (f32b(c as f32 + 0.25), Some(c + 0.25)),
                (2, 0, 0) => (i16::MIN.to_le_bytes().to_vec(), Some(-32768.0)),
                (2, 0, 1) => (32765i16.to_le_bytes().to_vec(), Some(32765.0)),
                (2, 1, 1) => (32766i16.to_le_bytes().to_vec(), None),
                (2, 2, 1) => (i16::MAX.to_le_bytes().to_vec(), None),
                (2, ..) => ((c as i16).to_le_bytes().to_vec(), Some(c)),
                (_, 0, 1) => (vec![255], Some(255.0)),
                _ => (vec![(c + 100.0) as u8], Some(c + 100.0)),
            }
        };
        for name in HEIGHT_ARRAYS {
            for elem in [1u16, 2, 4] {
                let bytes = build(&[
                    e("Image", T_ARRAY, array(rows, cols, 1, |i, j| vec![(i * cols + j) as u8])),
                    e(name, T_ARRAY, array(rows, cols, elem, |i, j| cell(elem, i, j).0)),
                    e("Wavelength", T_FLOAT, f32b(600.0)),
                    e("Mult", T_SHORT, 4i16.to_le_bytes()),
                    e("Pixel_size", T_FLOAT, f32b(2e-3)),
                ]);
                let s = decode(p(), &bytes).unwrap();
                assert!(s.warnings.is_empty(), "{name} {elem}: {:?}", s.warnings);
                assert_eq!(s.raw.values.dim(), (rows, cols));
                let z = 600.0 * 1e-9 / 4.0;
                for ((i, j), v) in s.raw.values.indexed_iter() {
                    match cell(elem, i, j).1 {
                        None => assert!(v.is_nan(), "{name} {elem} ({i}, {j}): {v}"),
                        Some(c) => {
                            assert!((v - c * z).abs() <= 1e-15 * (c * z).abs(), "{name} ({i}, {j}): {v}")
                        }
                    }
                }
            }
        }
    }

    /// A later Vision version's directory, the layout surfalize stops on (a type-15 entry) and
    /// that this reader refused before: heights in `Raw` (i16), an `Image` array before it,
    /// type-15 entries among the numbers and at the end (`ExtendedKeys`, named in Latin-1), a
    /// float entry of 2 bytes (a short), a short entry of 4 bytes (a long), `ImageModificat~0`
    /// declaring and holding 40 bytes before the heights.
    #[test]
    fn later_vision_directory() {
        let (rows, cols) = (4, 5);
        let count = |i: usize, j: usize| -> Option<i16> {
            match (i, j) {
                (1, 2) | (3, 0) => None,
                _ => Some(100 * i as i16 - 7 * j as i16),
            }
        };
        let raw = array(rows, cols, 2, |i, j| {
            count(i, j).map_or(32766 + (i as i16 % 2), |c| c).to_le_bytes().to_vec()
        });
        let mut image_modification = f32b(2.5);
        image_modification.extend(1..=36u8);
        let bytes = build(&[
            e("Image", T_ARRAY, array(rows, cols, 1, |i, j| vec![(40 + i + j) as u8])),
            e("ImageModificat~0", T_FLOAT, image_modification),
            e("Raw", T_ARRAY, raw),
            e("Wavelength", T_FLOAT, f32b(632.8)),
            e("Mult", T_SHORT, 8i16.to_le_bytes()),
            e("StageState", 15, [2u8, 0, 0, 0, 9, 9, 9, 9, 9, 9, 9, 9, 9]),
            e("Pixel_size", T_FLOAT, f32b(2.5e-3)),
            e("Aspect", T_FLOAT, f32b(1.25)),
            e("AdjustVSI_Gain", T_FLOAT, 3i16.to_le_bytes()),
            e("NumFrames", T_SHORT, 70000i32.to_le_bytes()),
            e("Title", T_TEXT, b"later Vision\0\0\0\0".to_vec()),
            (b"\xcaxtendedKe\xfds".to_vec(), 15, 22, b"ImageModificat~0\0Image".to_vec()),
        ]);
        let s = decode(p(), &bytes).unwrap();
        assert!(s.warnings.is_empty(), "{:?}", s.warnings);
        let z = f64::from(632.8f32) * 1e-9 / 8.0;
        for ((i, j), v) in s.raw.values.indexed_iter() {
            match count(i, j) {
                None => assert!(v.is_nan(), "({i}, {j}): {v}"),
                Some(c) => assert!(close(*v, f64::from(c) * z), "({i}, {j}): {v}"),
            }
        }
        let px = f64::from(2.5e-3f32) * 1e-3;
        let [dx, dy] = s.raw.pitch.unwrap();
        assert!(close(dx, px) && close(dy, 1.25 * px), "{dx} {dy}");
        assert_eq!(md(&s, "AdjustVSI_Gain"), Some("3"));
        assert_eq!(md(&s, "NumFrames"), Some("70000"));
        assert_eq!(md(&s, "ImageModificat~0"), Some("2.5"));
        assert_eq!(md(&s, "Title"), Some("later Vision"));
        assert!(s.raw.metadata.iter().all(|(k, _)| k != "StageState" && !k.contains("xtended")));
    }

    /// Gwyddion's count for `ImageModificat~0`: declaring 40 bytes, holding 4, before the
    /// heights. The declared sizes end 36 bytes past the file; Gwyddion's end with it, so the
    /// heights are found where Gwyddion reads them, with a warning. The same entry holding its
    /// 40 bytes is read with the declared sizes (`later_vision_directory`).
    #[test]
    fn gwyddions_count_for_image_modification() {
        let mut entries = vec![
            (b"ImageModificat~0".to_vec(), T_FLOAT, 40, f32b(2.5)),
            e("RAW_DATA", T_ARRAY, array(2, 3, 4, |i, j| f32b((3 * i + j) as f32))),
            e("Wavelength", T_FLOAT, f32b(500.0)),
        ];
        let s = decode(p(), &build(&entries)).unwrap();
        assert_eq!(
            s.warnings,
            [
                "entry 'ImageModificat~0' declares 40 bytes and holds 4: the file ends where that count \
                 (Gwyddion's) puts its end",
                "the file states no usable Pixel_size: pass `pitch`"
            ]
        );
        for ((i, j), v) in s.raw.values.indexed_iter() {
            assert!(close(*v, (3 * i + j) as f64 * 500e-9), "({i}, {j}): {v}");
        }
        assert_eq!(md(&s, "ImageModificat~0"), Some("2.5"));
        // Ending where neither count puts the end: the declared sizes, which run past the file.
        entries[0].3.extend([0u8; 20]);
        let e = decode(p(), &build(&entries)).unwrap_err().to_string();
        assert!(e.contains("t.opd") && e.contains("the data of entry 'RAW_DATA'"), "{e}");
    }

    /// The scale entries in every number type: Wavelength as f32 or f64, Mult as short, long,
    /// a short of 4 bytes, float or absent, Pixel_size as f64; the height of one count and the
    /// pitch follow.
    #[test]
    fn scale_entries_of_every_number_type() {
        let mults = [
            (Some(e("Mult", T_SHORT, 3i16.to_le_bytes())), 3.0),
            (Some(e("Mult", T_LONG, 3i32.to_le_bytes())), 3.0),
            (Some(e("Mult", T_SHORT, 3i32.to_le_bytes())), 3.0),
            (Some(e("Mult", T_FLOAT, f32b(3.0))), 3.0),
            (None, 1.0),
        ];
        for wavelength in
            [e("Wavelength", T_FLOAT, f32b(600.0)), e("Wavelength", T_DOUBLE, 600f64.to_le_bytes())]
        {
            for (mult, m) in &mults {
                let mut entries = vec![
                    e(
                        "SAMPLE_DATA",
                        T_ARRAY,
                        array(2, 2, 2, |i, j| (7 * i as i16 + j as i16 + 1).to_le_bytes().to_vec()),
                    ),
                    wavelength.clone(),
                    e("Pixel_size", T_DOUBLE, 1.5e-3f64.to_le_bytes()),
                ];
                entries.extend(mult.iter().cloned());
                let s = decode(p(), &build(&entries)).unwrap();
                assert!(s.warnings.is_empty(), "{:?}", s.warnings);
                assert!(close(s.raw.values[[1, 1]], 9.0 * 600e-9 / m), "Mult {mult:?}");
                let [dx, dy] = s.raw.pitch.unwrap();
                assert!(close(dx, 1.5e-6) && close(dy, 1.5e-6), "{dx} {dy}");
            }
        }
    }

    /// Directories with no readable height map: an error naming the file, what was expected
    /// and what the directory holds.
    #[test]
    fn unreadable_directories_name_what_was_expected() {
        let err = |entries: &[E]| decode(p(), &build(entries)).unwrap_err().to_string();
        let wavelength = e("Wavelength", T_FLOAT, f32b(600.0));
        let heights = e("OPD", T_ARRAY, array(2, 2, 4, |_, _| f32b(1.0)));
        let expected =
            "no height array in the directory: expected an array entry (type 3) named OPD, SAMPLE_DATA, \
                        RAW_DATA, RAW DATA or Raw; its arrays: ";
        let e1 = err(&[
            e("Image", T_ARRAY, array(2, 2, 1, |_, _| vec![1])),
            e("OPD", T_TEXT, b"not heights".to_vec()),
            e("Phase", T_ARRAY, array(2, 2, 4, |_, _| f32b(1.0))),
            e("SecArr_0", T_ARRAY, array(2, 2, 2, |_, _| vec![1, 0])),
            wavelength.clone(),
        ]);
        assert!(e1.starts_with("t.opd"), "{e1}");
        assert!(
            e1.contains(&format!(
                "{expected}'Image' (intensity), 'OPD' (of type 5, not an array), 'Phase', 'SecArr_0' (intensity)"
            )),
            "{e1}"
        );
        let e2 = err(&[wavelength.clone(), e("Title", T_TEXT, b"x".to_vec())]);
        assert!(e2.contains(&format!("{expected}none")), "{e2}");
        for (entries, want) in [
            (
                vec![heights.clone()],
                "the entry 'Wavelength' (nm, the height of one count with Mult) is missing",
            ),
            (
                vec![heights.clone(), e("Wavelength", T_FLOAT, [0u8, 0, 0])],
                "entry 'Wavelength' of type 7 and 3 bytes is not a number",
            ),
            (vec![heights.clone(), e("Wavelength", T_TEXT, b"600".to_vec())], "entry 'Wavelength' of type 5"),
            (vec![heights.clone(), wavelength.clone(), e("Mult", T_SHORT, 0i16.to_le_bytes())], "Mult 0"),
            (
                vec![e("OPD", T_ARRAY, array(2, 2, 3, |_, _| vec![0; 3])), wavelength.clone()],
                "array element of 3 bytes",
            ),
            (vec![heights.clone(), e("Sub", T_DIRECTORY, [0u8; 24])], "entry 'Sub' is a nested directory"),
        ] {
            let e = err(&entries);
            assert!(e.starts_with("t.opd") && e.contains(want), "{want}: {e}");
        }
        let mut short = heights.clone();
        short.3.truncate(12);
        short.2 = 12;
        let e = err(&[short, wavelength]);
        assert!(e.contains("array 'OPD' of 2 x 2 x 4 bytes does not fit its 12 bytes"), "{e}");
    }

    /// A number entry whose size holds no number of its type is left out of the metadata with
    /// a warning; a second height array is named in a warning and the first one read.
    #[test]
    fn odd_entries_are_named_in_warnings() {
        let bytes = build(&[
            e("RAW DATA", T_ARRAY, array(2, 2, 2, |i, j| (i as i16 * 2 + j as i16).to_le_bytes().to_vec())),
            e("Raw", T_ARRAY, array(2, 2, 2, |_, _| 5i16.to_le_bytes().to_vec())),
            e("Wavelength", T_FLOAT, f32b(600.0)),
            e("Pixel_size", T_FLOAT, f32b(1e-3)),
            e("Odd", T_SHORT, [1u8, 2, 3]),
        ]);
        let s = decode(p(), &bytes).unwrap();
        assert_eq!(
            s.warnings,
            [
                "the height array 'RAW DATA' is read; further height arrays skipped: Raw",
                "entry 'Odd' of type 6 holds 3 bytes, no number of that type: left out"
            ]
        );
        assert!(close(s.raw.values[[1, 1]], 3.0 * 600e-9));
        assert_eq!(md(&s, "Odd"), None);
    }

    /// Every truncation of a file is an error naming the file and an offset; a file that does
    /// not start as an OPD file is named as such.
    #[test]
    fn truncation_and_magic() {
        let bytes = build(&[
            e("RAW_DATA", T_ARRAY, array(3, 4, 4, |i, j| f32b((10 * i + j) as f32))),
            e("Wavelength", T_FLOAT, f32b(632.8)),
            e("Mult", T_SHORT, 2i16.to_le_bytes()),
            e("Pixel_size", T_FLOAT, f32b(2e-3)),
            e("Title", T_TEXT, b"synthetic".to_vec()),
        ]);
        assert!(decode(p(), &bytes).is_ok());
        for cut in [1, 20, 30, 2 + 5 * 24 + 3, bytes.len() - 1] {
            let e = decode(p(), &bytes[..cut]).unwrap_err().to_string();
            assert!(e.contains("t.opd") && e.contains("offset"), "{cut}: {e}");
        }
        let mut bad = bytes.clone();
        bad[2] = b'X';
        assert!(decode(p(), &bad).unwrap_err().to_string().contains("not a Wyko OPD file"));
    }
}
