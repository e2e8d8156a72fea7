//! Bruker Vision64 / Dektak files (`.opdx`, "VCA DATA"): the primary 2-D height channel.
//!
//! Layout (SurfaceTopography's `OPDx.py`, which follows Gwyddion's `dektakvca` module;
//! little-endian): the 12-byte magic `VCA DATA\x01\x00\x00\x55`, then items until a terminator
//! item. An item is a name (u32 byte count + UTF-8), a type byte and its payload. A *length* is
//! one byte giving its own size (1, 2 or 4) followed by the length in that many bytes.
//!
//! | type | payload |
//! |---|---|
//! | 0x7d container, 0x46 / 0x47 raw-data containers | length; the items; a terminator item; 2 bytes (the length covers all of it) |
//! | 0x7f terminator | none (its name is empty) |
//! | 0x01 bool, 0x04 / 0x05 i16 / u16, 0x06 / 0x07 i32 / u32, 0x0a / 0x0b i64 / u64, 0x0c f32, 0x0d f64 | the value |
//! | 0x12 string | length; UTF-8 |
//! | 0x13 quantity | length; f64 value, unit name, unit symbol (names), anything else to the length |
//! | 0x18 unit | length; unit name, symbol, f64 value, 12 bytes |
//! | 0x15 time stamp | 9 bytes |
//! | 0x0e type id | type name; length; bytes |
//! | 0x40 double array | type name; length; bytes |
//! | 0x42 string list | type name; length; names |
//! | 0x00 matrix | type name; u32; a name; length; u32 rows, u32 columns, rows x columns f32 row by row |
//! | 0x45 anonymous matrix | type name; length; u32 rows, u32 columns, the f32 values |
//! | 0x7c position data | type name; length; the bytes (skipped) |
//!
//! A map file (`/MetaData/DataKind` "Surface Height", or 2-D data present) holds channels
//! `/2D_Data/NAME` with `Matrix`, `Dimension1Points` (rows, along y), `Dimension2Points`
//! (columns, along x), `Dimension1Extent` / `Dimension2Extent` (quantities: the distance from the
//! first to the last point, so the pitch is extent / (points - 1)) and `DataScale` (a quantity:
//! height per stored value). The channel read is `/MetaData/PrimaryData2D`, else the first of the
//! `/MetaData/2D_Channels/Height` list; other 2-D channels are skipped with a warning. NaN and
//! infinities are non-measured (the description names no other marker). A profile file
//! ("Surface Profile", 1-D data only) is refused naming it. Every number, string and quantity
//! under `/MetaData` is kept as metadata, keyed by its path below `/MetaData`.

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, scan_length_unit, shape, Bin, ScanFormat, ScanRaw};

/// The 12-byte magic.
pub const MAGIC: &[u8; 12] = b"VCA DATA\x01\x00\x00\x55";
/// Containers nest no deeper than this (real files: 4 levels).
const MAX_DEPTH: usize = 32;

/// True when `head` starts as an `.opdx` file does.
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(MAGIC)
}

/// What an item holds (payloads not needed for the map are kept as `Other`).
#[derive(Debug, Clone, PartialEq)]
enum Item {
    Number(f64),
    Text(String),
    Quantity {
        value: f64,
        symbol: String,
    },
    List(Vec<String>),
    /// Rows, columns, the byte offset of the f32 values and the bytes the item holds for them.
    Matrix {
        rows: usize,
        cols: usize,
        offset: usize,
        len: usize,
    },
    Other,
}

struct Reader<'a> {
    b: Bin<'a>,
    items: Vec<(String, Item, usize)>,
}

impl Reader<'_> {
    fn name(&self, off: usize, what: &str) -> Result<(String, usize)> {
        let n = self.b.u32le(off, what)? as usize;
        let s = self.b.take(off + 4, n, what)?;
        let s = std::str::from_utf8(s)
            .map(str::to_string)
            .unwrap_or_else(|_| s.iter().map(|&c| c as char).collect());
        Ok((s, off + 4 + n))
    }

    /// A length field at `off`: the length and the offset after it.
    fn length(&self, off: usize, what: &str) -> Result<(usize, usize)> {
        let size = self.b.take(off, 1, what)?[0];
        let len = match size {
            1 => self.b.take(off + 1, 1, what)?[0] as usize,
            2 => self.b.u16le(off + 1, what)? as usize,
            4 => self.b.u32le(off + 1, what)? as usize,
            other => {
                return Err(self
                    .b
                    .bad(off, format!("{what}: a length of {other} bytes (expected 1, 2 or 4)")))
            }
        };
        let start = off + 1 + size as usize;
        if start.checked_add(len).is_none_or(|end| end > self.b.bytes.len()) {
            return Err(self.b.bad(
                off,
                format!(
                    "{what}: {len} bytes from offset {start} run past the end of the file (truncated at byte offset {})",
                    self.b.bytes.len()
                ),
            ));
        }
        Ok((len, start))
    }

    /// Reads the items from `off` up to and including a terminator; returns the offset after it.
    fn items(&mut self, mut off: usize, prefix: &str, depth: usize) -> Result<usize> {
        if depth > MAX_DEPTH {
            return Err(self.b.bad(off, format!("containers nested deeper than {MAX_DEPTH} levels")));
        }
        loop {
            let (name, o) = self.name(off, "an item name")?;
            let typeid = self.b.take(o, 1, "an item type")?[0];
            let path = format!("{prefix}/{name}");
            let p = o + 1;
            let what = format!("item '{path}'");
            let (item, next) = match typeid {
                0x7f => return Ok(p),
                0x7d | 0x46 | 0x47 => {
                    let (len, start) = self.length(p, &what)?;
                    let end = self.items(start, &path, depth + 1)?;
                    self.b.take(end, 2, &format!("the end of container '{path}'"))?;
                    if end + 2 != start + len {
                        return Err(self.b.bad(
                            start,
                            format!(
                                "container '{path}' ends at byte offset {} but states {len} bytes",
                                end + 2
                            ),
                        ));
                    }
                    off = start + len;
                    continue;
                }
                0x01 => (Item::Number(self.b.take(p, 1, &what)?[0] as f64), p + 1),
                0x04 => (Item::Number(i16::from_le_bytes(self.arr(p, &what)?) as f64), p + 2),
                0x05 => (Item::Number(self.b.u16le(p, &what)? as f64), p + 2),
                0x06 => (Item::Number(self.b.i32le(p, &what)? as f64), p + 4),
                0x07 => (Item::Number(self.b.u32le(p, &what)? as f64), p + 4),
                0x0a => (Item::Number(i64::from_le_bytes(self.arr(p, &what)?) as f64), p + 8),
                0x0b => (Item::Number(u64::from_le_bytes(self.arr(p, &what)?) as f64), p + 8),
                0x0c => (Item::Number(self.b.f32le(p, &what)? as f64), p + 4),
                0x0d => (Item::Number(self.b.f64le(p, &what)?), p + 8),
                0x12 => {
                    let (len, start) = self.length(p, &what)?;
                    (
                        Item::Text(crate::io::scan::raw::decode_text(&self.b.bytes[start..start + len])),
                        start + len,
                    )
                }
                0x13 => {
                    let (len, start) = self.length(p, &what)?;
                    let end = start + len;
                    let value = self.b.f64le(start, &what)?;
                    let (_, o) = self.name(start + 8, &what)?;
                    let (symbol, o) = self.name(o, &what)?;
                    if o > end {
                        return Err(self
                            .b
                            .bad(start, format!("{what}: the quantity runs past its {len} bytes")));
                    }
                    (Item::Quantity { value, symbol }, end)
                }
                0x18 => {
                    let (len, start) = self.length(p, &what)?;
                    let end = start + len;
                    let (_, o) = self.name(start, &what)?;
                    let (symbol, o) = self.name(o, &what)?;
                    let value = self.b.f64le(o, &what)?;
                    if o + 8 > end {
                        return Err(self.b.bad(start, format!("{what}: the unit runs past its {len} bytes")));
                    }
                    (Item::Quantity { value, symbol }, end)
                }
                0x15 => {
                    self.b.take(p, 9, &what)?;
                    (Item::Other, p + 9)
                }
                0x0e | 0x40 | 0x7c => {
                    let (_, o) = self.name(p, &what)?;
                    let (len, start) = self.length(o, &what)?;
                    (Item::Other, start + len)
                }
                0x42 => {
                    let (_, o) = self.name(p, &what)?;
                    let (len, start) = self.length(o, &what)?;
                    let end = start + len;
                    let mut list = Vec::new();
                    let mut q = start;
                    while q < end {
                        let (s, n) = self.name(q, &what)?;
                        list.push(s);
                        q = n;
                    }
                    if q != end {
                        return Err(self
                            .b
                            .bad(start, format!("{what}: the string list overruns its {len} bytes")));
                    }
                    (Item::List(list), end)
                }
                0x00 | 0x45 => {
                    let (_, mut o) = self.name(p, &what)?;
                    if typeid == 0x00 {
                        self.b.u32le(o, &what)?;
                        o = self.name(o + 4, &what)?.1;
                    }
                    let (len, start) = self.length(o, &what)?;
                    let rows = self.b.u32le(start, &format!("{what}: the row count"))? as usize;
                    let cols = self.b.u32le(start + 4, &format!("{what}: the column count"))? as usize;
                    if len < 8 {
                        return Err(self.b.bad(
                            start,
                            format!("{what}: a matrix of {len} bytes has no room for its size"),
                        ));
                    }
                    (Item::Matrix { rows, cols, offset: start + 8, len: len - 8 }, start + len)
                }
                other => {
                    return Err(self.b.bad(o, format!("{what}: unknown item type 0x{other:02x}")));
                }
            };
            self.items.push((path, item, p));
            off = next;
        }
    }

    fn arr<const N: usize>(&self, off: usize, what: &str) -> Result<[u8; N]> {
        let s = self.b.take(off, N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }

    fn get(&self, path: &str) -> Option<(&Item, usize)> {
        self.items.iter().find(|(p, _, _)| p == path).map(|(_, i, o)| (i, *o))
    }
}

/// Metres per unit for a symbol as Vision64 writes it (`µm`, `um`, `nm`, `mm`, `m`, `Å`).
fn unit_metres(symbol: &str) -> Option<f64> {
    match symbol.trim() {
        "~m" => Some(1e-6),
        s => scan_length_unit(s),
    }
}

/// Decodes an `.opdx` file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    let n = bytes.len().min(8);
    if bytes[..n] != MAGIC[..n] {
        return Err(b.signature(0, "not a Bruker Vision64 .opdx file: it does not start with 'VCA DATA'"));
    }
    b.take(0, MAGIC.len(), "the magic")?;
    if bytes[..MAGIC.len()] != MAGIC[..] {
        return Err(b.unsupported(
            8,
            "a 'VCA DATA' file of another version (expected the bytes 01 00 00 55 after 'VCA DATA')",
        ));
    }
    let mut r = Reader { b: Bin::new(path, bytes), items: Vec::new() };
    let end = r.items(MAGIC.len(), "", 0)?;
    let mut warnings = Vec::new();
    if end < bytes.len() {
        warnings.push(format!(
            "{} bytes after the final terminator (from byte offset {end}) left unread",
            bytes.len() - end
        ));
    }

    let channel = height_channel(&r, &b, &mut warnings)?;
    let pre = format!("/2D_Data/{channel}");
    let Some((&Item::Matrix { rows, cols, offset, len: mlen }, moff)) = r.get(&format!("{pre}/Matrix"))
    else {
        return Err(b.bad(MAGIC.len(), format!("{pre}/Matrix is missing")));
    };
    let count = |k: &str| match r.get(&format!("{pre}/{k}")) {
        Some((Item::Number(v), _)) => Some(*v),
        _ => None,
    };
    for (k, n) in [("Dimension1Points", rows), ("Dimension2Points", cols)] {
        if let Some(v) = count(k) {
            if v != n as f64 {
                return Err(b.bad(moff, format!("{pre}: {k} = {v} but the matrix has {n}")));
            }
        }
    }
    if rows == 0 || cols == 0 {
        return Err(b.bad(moff, format!("the map is empty ({cols} x {rows} points)")));
    }
    let need = data_len(path, rows, cols, 4)?;
    let data = b.take(offset, need, &format!("the {cols} x {rows} f32 heights of {pre}"))?;
    if need > mlen {
        return Err(b.bad(
            offset,
            format!("{pre}/Matrix: {cols} x {rows} f32 values need {need} bytes but the matrix holds {mlen}"),
        ));
    }
    let quantity = |k: &str| match r.get(&format!("{pre}/{k}")) {
        Some((Item::Quantity { value, symbol }, o)) => Some((*value, symbol.clone(), o)),
        _ => None,
    };
    let (scale, zsym, zoff) = quantity("DataScale")
        .ok_or_else(|| b.bad(moff, format!("{pre} has no DataScale (the height per stored value)")))?;
    let zunit = unit_metres(&zsym)
        .ok_or_else(|| b.bad(zoff, format!("{pre}/DataScale: unit '{zsym}' is not a length unit")))?;
    let per_value = scale * zunit;
    if !per_value.is_finite() || per_value == 0.0 {
        return Err(b.bad(zoff, format!("{pre}/DataScale = {scale} {zsym} is no height scale")));
    }
    let step = |k: &str, n: usize, warnings: &mut Vec<String>| -> Result<Option<f64>> {
        let Some((v, sym, o)) = quantity(k) else {
            warnings.push(format!("{pre} has no {k}"));
            return Ok(None);
        };
        let u = unit_metres(&sym)
            .ok_or_else(|| b.bad(o, format!("{pre}/{k}: unit '{sym}' is not a length unit")))?;
        let p = v * u / (n.max(2) - 1) as f64;
        if n < 2 || !p.is_finite() || p <= 0.0 {
            warnings.push(format!("{pre}/{k} = {v} {sym} over {n} points gives no pitch"));
            return Ok(None);
        }
        Ok(Some(p))
    };
    let px = step("Dimension2Extent", cols, &mut warnings)?;
    let py = step("Dimension1Extent", rows, &mut warnings)?;
    let pitch = match (px, py) {
        (Some(x), Some(y)) => Some([x, y]),
        _ => {
            warnings.push("no usable pitch: pass `pitch`".to_string());
            None
        }
    };
    let values: Vec<f64> = data
        .chunks_exact(4)
        .map(|c| {
            let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            if v.is_finite() {
                v as f64 * per_value
            } else {
                f64::NAN
            }
        })
        .collect();
    let values = shape(path, rows, cols, values)?;

    let metadata = opdx_metadata(&r, &channel, scale, &zsym);
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Opdx);
    sr.warnings = warnings;
    Ok(sr)
}

/// The height channel read: the primary 2-D data when it is a height channel with a matrix,
/// else the first listed height channel with one; a profile (1-D data) or a file without a
/// height matrix is refused, and the other 2-D channels are warned about as skipped.
fn height_channel(r: &Reader, b: &Bin, warnings: &mut Vec<String>) -> Result<String> {
    let text = |k: &str| match r.get(k) {
        Some((Item::Text(s), _)) => Some(s.clone()),
        _ => None,
    };
    let kind = text("/MetaData/DataKind");
    let has_2d =
        r.items.iter().any(|(p, i, _)| p.starts_with("/2D_Data/") && matches!(i, Item::Matrix { .. }));
    if !has_2d {
        let what = kind.as_deref().unwrap_or("no 2-D data");
        let profile = r.items.iter().any(|(p, _, _)| p.starts_with("/1D_Data/"));
        return Err(b.unsupported(
            MAGIC.len(),
            if profile {
                format!("a stylus profile ('{what}', 1-D data), not a surface map: profiles are not read by scan-info")
            } else {
                format!("no 2-D height map in the file (data kind '{what}')")
            },
        ));
    }
    let mut heights: Vec<String> = match r.get("/MetaData/2D_Channels/Height") {
        Some((Item::List(l), _)) => l.clone(),
        _ => Vec::new(),
    };
    if let Some(primary) = text("/MetaData/PrimaryData2D") {
        heights.retain(|h| *h != primary);
        heights.insert(0, primary);
    }
    let with_matrix: std::collections::HashSet<&str> = r
        .items
        .iter()
        .filter(|(_, i, _)| matches!(i, Item::Matrix { .. }))
        .filter_map(|(p, _, _)| p.strip_prefix("/2D_Data/")?.strip_suffix("/Matrix"))
        .collect();
    let channel = heights.iter().find(|h| with_matrix.contains(h.as_str())).cloned().ok_or_else(|| {
        b.bad(MAGIC.len(), format!("no height channel with a matrix (height channels listed: {heights:?})"))
    })?;
    let others: Vec<String> = r
        .items
        .iter()
        .filter_map(|(p, i, _)| {
            let name = p.strip_prefix("/2D_Data/")?.strip_suffix("/Matrix")?;
            (matches!(i, Item::Matrix { .. }) && name != channel).then(|| name.to_string())
        })
        .collect();
    if !others.is_empty() {
        warnings.push(format!(
            "the height channel '{channel}' is read; other 2-D channels skipped: {}",
            others.join(", ")
        ));
    }
    Ok(channel)
}

/// The metadata: the channel, the height unit (`scale` `zsym` per stored value) and every
/// item under `/MetaData/`.
fn opdx_metadata(r: &Reader, channel: &str, scale: f64, zsym: &str) -> Vec<(String, String)> {
    let mut metadata = vec![
        ("channel".to_string(), channel.to_string()),
        ("height_unit".to_string(), format!("{scale} {zsym} per stored value (f32)")),
    ];
    for (p, item, _) in &r.items {
        let Some(key) = p.strip_prefix("/MetaData/") else { continue };
        let v = match item {
            Item::Number(v) => format!("{v}"),
            Item::Text(s) => s.clone(),
            Item::Quantity { value, symbol } => format!("{value} {symbol}"),
            Item::List(l) => l.join(", "),
            _ => continue,
        };
        metadata.push((key.to_string(), v));
    }
    metadata
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(bytes: &[u8]) -> Result<ScanRaw> {
        decode(Path::new("t.opdx"), bytes)
    }

    fn name(s: &str) -> Vec<u8> {
        let mut v = (s.len() as u32).to_le_bytes().to_vec();
        v.extend_from_slice(s.as_bytes());
        v
    }

    #[test]
    fn other_files_versions_and_profiles_are_refused() {
        let err = |b: &[u8]| read(b).unwrap_err().to_string();
        assert!(err(b"PK\x03\x04").contains("not a Bruker Vision64 .opdx file"));
        assert!(err(b"VCA DATA\x02\x00\x00\x55").contains("another version"));
        // A profile: /1D_Data/Raw holding a u32, then the terminators.
        let mut f = MAGIC.to_vec();
        let mut inner = name("NumPoints");
        inner.push(0x07);
        inner.extend_from_slice(&5u32.to_le_bytes());
        inner.extend_from_slice(&name(""));
        inner.push(0x7f);
        inner.extend_from_slice(&[0, 0]);
        let mut raw = name("Raw");
        raw.push(0x7d);
        raw.push(1);
        raw.push(inner.len() as u8);
        raw.extend_from_slice(&inner);
        raw.extend_from_slice(&name(""));
        raw.push(0x7f);
        raw.extend_from_slice(&[0, 0]);
        f.extend_from_slice(&name("1D_Data"));
        f.push(0x7d);
        f.push(1);
        f.push(raw.len() as u8);
        f.extend_from_slice(&raw);
        f.extend_from_slice(&name(""));
        f.push(0x7f);
        let e = err(&f);
        assert!(e.contains("stylus profile"), "{e}");
        // An unknown type byte and a bad length size are named with their offsets.
        let mut bad = MAGIC.to_vec();
        bad.extend_from_slice(&name("X"));
        bad.push(0x99);
        assert!(err(&bad).contains("byte offset 17: item '/X': unknown item type 0x99"), "{}", err(&bad));
        let mut bad = MAGIC.to_vec();
        bad.extend_from_slice(&name("S"));
        bad.extend_from_slice(&[0x12, 3, 0, 0, 0]);
        assert!(err(&bad).contains("a length of 3 bytes"), "{}", err(&bad));
    }
}
