//! Zygo Mx files (`.datx`): HDF5 containers of a measurement's surface map, its non-measured
//! marker, units and lateral calibration.
//!
//! Layout (as SurfaceTopography's `DATX.py`, prysm's `read_zygo_datx` and Gwyddion's DATX
//! module describe the files Zygo's Mx software writes; the HDF5 container itself is read with
//! the pure-Rust `hdf5-reader` crate):
//!
//! | object | what |
//! |---|---|
//! | `/MetaData` | table of (`Source`, `Link`, `Destination`) strings: `Root` -Measurement-> *m*, *m* -Surface-> *s*, *s* -Path-> the surface dataset's path |
//! | `/Measurement/Surface` (Mx 7 and later; older files: the dataset of `/Data/Surface`) | the heights, 2-D, rows along y with the first row first, any float or integer type, chunked and deflated or not |
//! | its attribute `Unit` | one string: `NanoMeters`, `MicroMeters`, `MilliMeters`, `Meters`, `Angstroms` (or a plain `nm`, `um`, ...), or `Fringes` |
//! | `No Data` | one number: the value of non-measured points (NaN and infinities are never measured) |
//! | `Wavelength`, `Interferometric Scale Factor`, `Obliquity Factor` | for `Fringes`: height = value x wavelength (m) x scale factor x obliquity |
//! | `X Converter`, `Y Converter` | compound (`Category`, `BaseUnit`, `Parameters`): `LateralCat`, `Pixels`, and `Parameters[1]` the pitch in metres |
//! | `Z Converter` | compound `HeightCat`, the height unit (agreeing with `Unit`), `Parameters` = (?, wavelength, scale factor, obliquity) |
//! | other datasets beside the surface (`Intensity`, ...) | other channels: skipped, with a warning naming them |
//! | attributes of the surface's groups and of `/Attributes/*` | instrument metadata (`... System Type`, `... System Serial Number`, objective, time stamp ...) |
//!
//! `Parameters` may be a variable-length sequence or a fixed array of f64; strings may be
//! variable-length or fixed. A file whose `Unit` and `Z Converter` disagree is refused (as
//! SurfaceTopography does); a unit other than a length or `Fringes` is refused naming it. Every
//! string or single-number attribute of the surface dataset, of the groups above it and of the
//! `/Attributes` groups is kept as metadata (first occurrence of a name wins).
//!
//! Limits: the decoded map may not exceed 2^28 samples nor 1100 bytes per byte of the file
//! (deflate cannot compress beyond 1032:1), so a small file never makes a large allocation.

use std::path::Path;

use hdf5_reader::{Attribute, Dataset, Datatype, Hdf5File, OpenOptions};

use crate::error::{Error, Result};
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, scan_length_unit, shape, ScanFormat, ScanRaw};

/// The HDF5 signature, at byte offset 0 (or 512, 1024, ... after a user block).
pub const MAGIC: &[u8; 8] = b"\x89HDF\r\n\x1a\n";
/// Decoded bytes allowed per byte of the file (deflate's limit is 1032).
const INFLATE: usize = 1100;

/// True when `head` starts with the HDF5 signature.
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(MAGIC)
}

/// Where the HDF5 signature is: 0, 512, 1024, 2048, ... (a user block before it).
fn signature_offset(bytes: &[u8]) -> Option<usize> {
    let mut off = 0usize;
    loop {
        let end = off.checked_add(MAGIC.len())?;
        if end > bytes.len() {
            return None;
        }
        if &bytes[off..end] == MAGIC {
            return Some(off);
        }
        off = if off == 0 { 512 } else { off.checked_mul(2)? };
    }
}

struct Ctx<'a> {
    path: &'a Path,
    len: usize,
}

impl Ctx<'_> {
    fn err(&self, what: impl std::fmt::Display) -> Error {
        Error::malformed(self.path, what.to_string())
    }
    /// An error of the HDF5 layer, while reading `what`.
    fn h5(&self, what: &str) -> impl Fn(hdf5_reader::error::Error) -> Error + '_ {
        let what = what.to_string();
        let len = self.len;
        move |e| {
            use hdf5_reader::error::Error as H5Error;
            let what = format!(
                "HDF5 structure damaged or cut short while reading {what} (the file ends at byte offset {len}): {e}"
            );
            match e {
                H5Error::UnexpectedEof { .. } | H5Error::OffsetOutOfBounds(_) => {
                    Error::truncated(self.path, len as u64, what)
                }
                _ => Error::malformed(self.path, what),
            }
        }
    }
}

/// True when `e` says an object is absent (rather than damaged).
fn is_absent(e: &hdf5_reader::error::Error) -> bool {
    use hdf5_reader::error::Error as H;
    match e {
        H::GroupNotFound(_) | H::DatasetNotFound(_) => true,
        H::Context { source, .. } => is_absent(source),
        _ => false,
    }
}

/// The dataset at `p`: `None` when absent, an error when the structure is damaged.
fn find_dataset(ctx: &Ctx, file: &Hdf5File, p: &str) -> Result<Option<Dataset>> {
    match file.dataset(p) {
        Ok(d) => Ok(Some(d)),
        Err(e) if is_absent(&e) => Ok(None),
        Err(e) => Err(ctx.h5(p)(e)),
    }
}

/// The group at `p`: `None` when absent, an error when the structure is damaged.
fn find_group(ctx: &Ctx, file: &Hdf5File, p: &str) -> Result<Option<hdf5_reader::group::Group>> {
    match file.group(p) {
        Ok(g) => Ok(Some(g)),
        Err(e) if is_absent(&e) => Ok(None),
        Err(e) => Err(ctx.h5(p)(e)),
    }
}

/// One decoded attribute value: text, numbers, or a compound's fields.
#[derive(Debug, Clone, PartialEq)]
enum Value {
    Text(String),
    Numbers(Vec<f64>),
    Fields(Vec<(String, Value)>),
    Other,
}

impl Value {
    fn text(&self) -> Option<&str> {
        match self {
            Value::Text(s) => Some(s),
            _ => None,
        }
    }
    fn first(&self) -> Option<f64> {
        match self {
            Value::Numbers(v) => v.first().copied(),
            _ => None,
        }
    }
    fn field(&self, name: &str) -> Option<&Value> {
        match self {
            Value::Fields(f) => f.iter().find(|(n, _)| n == name).map(|(_, v)| v),
            _ => None,
        }
    }
    /// The value as metadata text, `None` for what has no short text form.
    fn display(&self) -> Option<String> {
        match self {
            Value::Text(s) => Some(s.clone()),
            Value::Numbers(v) if !v.is_empty() && v.len() <= 16 => {
                Some(v.iter().map(|&x| num_text(x)).collect::<Vec<_>>().join(", "))
            }
            Value::Fields(f) => {
                let parts: Vec<String> = f
                    .iter()
                    .filter_map(|(n, v)| {
                        let d = match v {
                            Value::Numbers(x) => {
                                format!("[{}]", x.iter().map(|&x| num_text(x)).collect::<Vec<_>>().join(", "))
                            }
                            other => other.display()?,
                        };
                        Some(format!("{n}: {d}"))
                    })
                    .collect();
                (!parts.is_empty()).then(|| parts.join("; "))
            }
            _ => None,
        }
    }
}

/// Resolves variable-length references (`(count u32, heap address, index u32)`) of the file.
trait Vlen {
    fn vlen(&self, reference: &[u8], elem: usize) -> Option<Vec<u8>>;
}

impl Vlen for Dataset {
    fn vlen(&self, reference: &[u8], elem: usize) -> Option<Vec<u8>> {
        self.resolve_vlen_reference_bytes(reference, elem).ok()
    }
}

impl Vlen for hdf5_reader::group::Group {
    fn vlen(&self, reference: &[u8], elem: usize) -> Option<Vec<u8>> {
        self.resolve_vlen_reference_bytes(reference, elem).ok()
    }
}

/// A number of `dtype` from `b` (its full size), as f64.
fn number(dtype: &Datatype, b: &[u8]) -> Option<f64> {
    use hdf5_reader::ByteOrder;
    let (size, big) = match dtype {
        Datatype::FloatingPoint { size, byte_order } | Datatype::FixedPoint { size, byte_order, .. } => {
            (*size as usize, *byte_order == ByteOrder::BigEndian)
        }
        _ => return None,
    };
    let raw = b.get(..size)?;
    let mut a = [0u8; 8];
    if size > 8 {
        return None;
    }
    if big {
        for (k, &c) in raw.iter().rev().enumerate() {
            a[k] = c;
        }
    } else {
        a[..size].copy_from_slice(raw);
    }
    Some(match (dtype, size) {
        (Datatype::FloatingPoint { .. }, 4) => f32::from_le_bytes([a[0], a[1], a[2], a[3]]) as f64,
        (Datatype::FloatingPoint { .. }, 8) => f64::from_le_bytes(a),
        (Datatype::FixedPoint { signed: true, .. }, 1..=8) => {
            let shift = 64 - 8 * size as u32;
            ((i64::from_le_bytes(a) << shift) >> shift) as f64
        }
        (Datatype::FixedPoint { signed: false, .. }, 1..=8) => u64::from_le_bytes(a) as f64,
        _ => return None,
    })
}

/// A number as metadata text: shortest round-trip form, in exponent form when very large or small.
fn num_text(x: f64) -> String {
    if x != 0.0 && x.is_finite() && !(1e-3..1e9).contains(&x.abs()) {
        format!("{x:e}")
    } else {
        format!("{x}")
    }
}

/// Text from the bytes of a string (up to the first NUL, trimmed; Latin-1 when not UTF-8).
fn text(b: &[u8]) -> String {
    crate::io::scan::raw::decode_text(b)
}

/// The byte size of one element of `dtype` in its stored form (vlen references: 16 bytes with
/// 8-byte offsets), `None` where unknown.
fn stored_size(dtype: &Datatype, vref: usize) -> Option<usize> {
    use hdf5_reader::messages::datatype::StringSize;
    Some(match dtype {
        Datatype::FixedPoint { size, .. }
        | Datatype::FloatingPoint { size, .. }
        | Datatype::Bitfield { size, .. } => *size as usize,
        Datatype::String { size: StringSize::Fixed(n), .. } => *n as usize,
        Datatype::String { .. } | Datatype::VarLen { .. } => vref,
        Datatype::Compound { size, .. } | Datatype::Opaque { size, .. } => *size as usize,
        Datatype::Array { base, dims } => {
            let n = dims.iter().try_fold(1u64, |a, &d| a.checked_mul(d))?;
            stored_size(base, vref)?.checked_mul(usize::try_from(n).ok()?)?
        }
        Datatype::Enum { base, .. } => stored_size(base, vref)?,
        Datatype::Reference { size, .. } => *size as usize,
    })
}

/// Decodes one element of `dtype` stored in `b`.
fn decode_value(dtype: &Datatype, b: &[u8], vref: usize, heap: &dyn Vlen, depth: u32) -> Value {
    use hdf5_reader::messages::datatype::{StringSize, VarLenKind};
    if depth > 4 {
        return Value::Other;
    }
    match dtype {
        Datatype::FixedPoint { .. } | Datatype::FloatingPoint { .. } => {
            number(dtype, b).map(|x| Value::Numbers(vec![x])).unwrap_or(Value::Other)
        }
        Datatype::String { size: StringSize::Fixed(n), .. } => {
            b.get(..*n as usize).map(|s| Value::Text(text(s))).unwrap_or(Value::Other)
        }
        Datatype::VarLen { base, kind, .. } => {
            let Some(r) = b.get(..vref) else { return Value::Other };
            let is_text = *kind == VarLenKind::String || base.is_vlen_string_base();
            if is_text {
                return heap.vlen(r, 1).map(|s| Value::Text(text(&s))).unwrap_or(Value::Other);
            }
            let Some(es) = stored_size(base, vref).filter(|&s| s > 0) else { return Value::Other };
            let Some(data) = heap.vlen(r, es) else { return Value::Other };
            let v: Option<Vec<f64>> = data.chunks_exact(es).map(|c| number(base, c)).collect();
            v.map(Value::Numbers).unwrap_or(Value::Other)
        }
        Datatype::Array { base, .. } => {
            let Some(es) = stored_size(base, vref).filter(|&s| s > 0) else { return Value::Other };
            let Some(total) = stored_size(dtype, vref) else { return Value::Other };
            let Some(data) = b.get(..total) else { return Value::Other };
            let v: Option<Vec<f64>> = data.chunks_exact(es).map(|c| number(base, c)).collect();
            v.map(Value::Numbers).unwrap_or(Value::Other)
        }
        Datatype::Compound { fields, .. } => Value::Fields(
            fields
                .iter()
                .map(|f| {
                    let v = b
                        .get(f.byte_offset as usize..)
                        .map(|s| decode_value(&f.datatype, s, vref, heap, depth + 1))
                        .unwrap_or(Value::Other);
                    (f.name.clone(), v)
                })
                .collect(),
        ),
        _ => Value::Other,
    }
}

/// The value of an attribute: its first element for compounds and strings, every element for
/// numbers (at most 64).
fn attr_value(a: &Attribute, vref: usize, heap: &dyn Vlen) -> Value {
    if let Some(s) = &a.decoded_strings {
        return s.first().map(|s| Value::Text(s.trim().to_string())).unwrap_or(Value::Other);
    }
    match &a.datatype {
        Datatype::FixedPoint { .. } | Datatype::FloatingPoint { .. } => {
            let Some(es) = stored_size(&a.datatype, vref).filter(|&s| s > 0) else { return Value::Other };
            let v: Option<Vec<f64>> =
                a.raw_data.chunks_exact(es).take(64).map(|c| number(&a.datatype, c)).collect();
            v.filter(|v| !v.is_empty()).map(Value::Numbers).unwrap_or(Value::Other)
        }
        // Scalar vlen strings come resolved in raw_data.
        Datatype::VarLen { .. } if a.shape.is_empty() && a.raw_data.len() != vref => {
            Value::Text(text(&a.raw_data))
        }
        dtype => decode_value(dtype, &a.raw_data, vref, heap, 0),
    }
}

/// Metres per stored unit for a Zygo unit name (`None` for `Fringes` and unknown names).
fn zygo_unit(name: &str) -> Option<f64> {
    match name.trim() {
        "Meters" => Some(1.0),
        "MilliMeters" => Some(1e-3),
        "MicroMeters" => Some(1e-6),
        "NanoMeters" => Some(1e-9),
        "PicoMeters" => Some(1e-12),
        "Angstroms" => Some(1e-10),
        other => scan_length_unit(other),
    }
}

/// The path of the surface dataset from the `/MetaData` link table, when there is one.
fn metadata_path(ctx: &Ctx, file: &Hdf5File, vref: usize) -> Result<Option<String>> {
    let Some(md) = find_dataset(ctx, file, "/MetaData")? else { return Ok(None) };
    let Datatype::Compound { fields, size } = md.dtype().clone() else {
        return Err(ctx.err("/MetaData is not a table of (Source, Link, Destination) strings"));
    };
    if fields.len() < 3 {
        return Err(
            ctx.err(format!("/MetaData has {} columns, expected Source, Link, Destination", fields.len()))
        );
    }
    let raw = md.read_raw_bytes().map_err(ctx.h5("the /MetaData table"))?;
    let size = size as usize;
    if size == 0 {
        return Err(ctx.err("/MetaData has an empty row type"));
    }
    let mut rows = Vec::new();
    for row in raw.chunks_exact(size) {
        let cell = |k: usize| {
            decode_value(&fields[k].datatype, row.get(fields[k].byte_offset as usize..)?, vref, &md, 0)
                .text()
                .map(str::to_string)
        };
        if let (Some(s), Some(l), Some(d)) = (cell(0), cell(1), cell(2)) {
            rows.push((s, l, d));
        }
    }
    let link = |src: &str, name: &str| {
        rows.iter().find(|(s, l, _)| s == src && l == name).map(|(_, _, d)| d.clone())
    };
    let Some(m) = link("Root", "Measurement") else { return Ok(None) };
    let Some(s) = link(&m, "Surface") else { return Ok(None) };
    Ok(link(&s, "Path"))
}

/// Paths of the datasets of the group at `group` (`/`-joined), sorted by name; none when the
/// group is absent.
fn datasets_in(ctx: &Ctx, file: &Hdf5File, group: &str) -> Result<Vec<String>> {
    let Some(g) = find_group(ctx, file, group)? else { return Ok(Vec::new()) };
    let (_, mut names) = g.member_names().map_err(ctx.h5(group))?;
    names.sort();
    Ok(names.into_iter().map(|n| format!("{}/{n}", group.trim_end_matches('/'))).collect())
}

/// Where the surface is: the `/MetaData` link table's path, else `/Measurement/Surface`
/// (Mx 7), else the first dataset of `/Data/Surface` (older Mx; more than one warned about).
fn surface_path(ctx: &Ctx, file: &Hdf5File, vref: usize, warnings: &mut Vec<String>) -> Result<String> {
    let from_table = metadata_path(ctx, file, vref)?;
    Ok(match from_table {
        Some(p) => p,
        None => {
            if find_dataset(ctx, file, "/Measurement/Surface")?.is_some() {
                "/Measurement/Surface".to_string()
            } else {
                let found = datasets_in(ctx, file, "/Data/Surface")?;
                match found.as_slice() {
                    [] => return Err(Error::signature(
                        ctx.path,
                        "not a Zygo .datx file: an HDF5 file with no surface map (no /MetaData link to one, \
                             no /Measurement/Surface, no dataset in /Data/Surface)",
                    )),
                    [one] => one.clone(),
                    [first, rest @ ..] => {
                        warnings.push(format!(
                            "/Data/Surface holds {} maps; the first, {first}, is read ({} skipped)",
                            rest.len() + 1,
                            rest.join(", ")
                        ));
                        first.clone()
                    }
                }
            }
        }
    })
}

/// The surface's height unit (its `Unit` attribute or the Z Converter's base unit, which must
/// agree) and metres per stored value: the unit's length, or for fringes the wavelength times
/// the interferometric scale factor and the obliquity factor (attributes, else the Z
/// Converter's parameters).
fn height_scale(
    ctx: &Ctx,
    attrs: &[(String, Value)],
    surface_path: &str,
    warnings: &mut Vec<String>,
) -> Result<(String, f64)> {
    let attr = |name: &str| attrs.iter().find(|(n, _)| n == name).map(|(_, v)| v);
    let unit_attr = attr("Unit").and_then(Value::text).map(str::to_string).filter(|s| !s.is_empty());
    let zconv = attr("Z Converter");
    let zunit = zconv
        .and_then(|z| z.field("BaseUnit"))
        .and_then(Value::text)
        .map(str::to_string)
        .filter(|s| !s.is_empty());
    if let Some(cat) = zconv.and_then(|z| z.field("Category")).and_then(Value::text) {
        if cat != "HeightCat" {
            warnings.push(format!("the Z Converter's category is '{cat}', not HeightCat"));
        }
    }
    let unit = match (&unit_attr, &zunit) {
        (Some(u), Some(z)) if u != z => {
            return Err(ctx.err(format!(
                "{surface_path}: the height unit '{u}' (Unit) and '{z}' (Z Converter) disagree"
            )))
        }
        (Some(u), _) | (None, Some(u)) => u.clone(),
        (None, None) => {
            return Err(ctx.err(format!("{surface_path} states no height unit (no Unit, no Z Converter)")))
        }
    };
    let metres = if unit == "Fringes" {
        let zp = |k: usize| match zconv.and_then(|z| z.field("Parameters")) {
            Some(Value::Numbers(p)) => p.get(k).copied(),
            _ => None,
        };
        let w = attr("Wavelength").and_then(Value::first).or_else(|| zp(1));
        let s = attr("Interferometric Scale Factor").and_then(Value::first).or_else(|| zp(2));
        let o = attr("Obliquity Factor").and_then(Value::first).or_else(|| zp(3));
        match (w, s, o) {
            (Some(w), Some(s), Some(o)) if (w * s * o).is_finite() && w * s * o > 0.0 => w * s * o,
            _ => {
                return Err(ctx.err(format!(
                    "{surface_path} is in fringes but its wavelength {w:?}, interferometric scale factor {s:?} and \
                     obliquity {o:?} give no height scale"
                )))
            }
        }
    } else {
        zygo_unit(&unit).ok_or_else(|| {
            ctx.err(format!("{surface_path}: height unit '{unit}' is not a length nor Fringes"))
        })?
    };
    Ok((unit, metres))
}

/// Decodes a `.datx` file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let ctx = Ctx { path, len: bytes.len() };
    if signature_offset(bytes).is_none() {
        return Err(Error::signature(
            path,
            format!(
            "byte offset 0: not a Zygo .datx file: no HDF5 signature (\\x89HDF\\r\\n\\x1a\\n) at byte offset 0, 512, 1024, ... \
             (the file is {} bytes)",
            bytes.len()
        ))
        .at(0));
    }
    let budget = bytes.len().saturating_mul(INFLATE).max(1 << 16);
    let opts = OpenOptions::default()
        .with_max_chunk_bytes(budget.min(1 << 28))
        .with_max_read_bytes(budget)
        .with_max_object_header_bytes(bytes.len().max(1 << 12))
        .with_chunk_cache_bytes(budget.min(1 << 26));
    let file = Hdf5File::from_bytes_with_options(bytes, opts).map_err(ctx.h5("the superblock"))?;
    let sb = file.superblock();
    let vref = 4 + sb.offset_size as usize + 4;
    let end = sb.base_address.saturating_add(sb.eof_address);
    if end > bytes.len() as u64 {
        return Err(Error::truncated(
            path,
            bytes.len() as u64,
            format!(
                "truncated at byte offset {}: the HDF5 superblock says the file ends at byte offset {end}",
                bytes.len()
            ),
        ));
    }
    let mut warnings = Vec::new();

    // Where the surface is: the link table, else the places Mx 7 and older Mx write it.
    let surface_path = surface_path(&ctx, &file, vref, &mut warnings)?;
    let ds = find_dataset(&ctx, &file, &surface_path)?.ok_or_else(|| {
        ctx.err(format!("/MetaData names the surface map {surface_path}, which is not in the file"))
    })?;
    let (rows, cols) = match ds.shape() {
        [r, c] => (
            usize::try_from(*r).map_err(|_| ctx.err("the surface map's row count overflows"))?,
            usize::try_from(*c).map_err(|_| ctx.err("the surface map's column count overflows"))?,
        ),
        other => return Err(ctx.err(format!("the surface map {surface_path} has shape {other:?}, not 2-D"))),
    };
    if rows == 0 || cols == 0 {
        return Err(ctx.err(format!("the surface map {surface_path} is empty ({cols} x {rows} points)")));
    }
    let dtype = ds.dtype().clone();
    let elem = match &dtype {
        Datatype::FloatingPoint { size: s @ (4 | 8), .. } => *s as usize,
        Datatype::FixedPoint { size: s @ (1 | 2 | 4 | 8), .. } => *s as usize,
        other => return Err(ctx.err(format!("the surface map {surface_path} holds {other:?}, not numbers"))),
    };
    let need = data_len(path, rows, cols, elem)?;
    if need > budget {
        return Err(ctx.err(format!(
            "the surface map {surface_path} claims {cols} x {rows} points ({need} bytes), more than a {} byte file can hold",
            bytes.len()
        )));
    }

    // Attributes of the surface.
    let attrs: Vec<(String, Value)> =
        ds.attributes().iter().map(|a| (a.name.clone(), attr_value(a, vref, &ds))).collect();
    let attr = |name: &str| attrs.iter().find(|(n, _)| n == name).map(|(_, v)| v);
    let (unit, metres) = height_scale(&ctx, &attrs, &surface_path, &mut warnings)?;
    let no_data = attr("No Data").and_then(Value::first);

    let pitch_of = |name: &str, warnings: &mut Vec<String>| -> Option<f64> {
        let c = attr(name)?;
        let cat = c.field("Category").and_then(Value::text).unwrap_or("");
        let base = c.field("BaseUnit").and_then(Value::text).unwrap_or("");
        let p = match c.field("Parameters") {
            Some(Value::Numbers(p)) => p.get(1).copied(),
            _ => None,
        };
        if cat != "LateralCat" || base != "Pixels" {
            warnings.push(format!(
                "the {name} is '{cat}' / '{base}', not LateralCat / Pixels: its pitch is not used"
            ));
            return None;
        }
        p.filter(|v| v.is_finite() && *v > 0.0)
    };
    let px = pitch_of("X Converter", &mut warnings);
    let py = pitch_of("Y Converter", &mut warnings);
    let pitch = match (px, py) {
        (Some(x), Some(y)) => Some([x, y]),
        _ => {
            warnings.push(format!(
                "no usable lateral pitch in the X / Y Converter (x {px:?}, y {py:?} m): pass `pitch`"
            ));
            None
        }
    };

    // The heights.
    let values = read_numbers(&ds, &dtype).map_err(ctx.h5(&format!("the surface map {surface_path}")))?;
    if values.len() != rows * cols {
        return Err(ctx.err(format!(
            "the surface map {surface_path} gave {} values for {cols} x {rows}",
            values.len()
        )));
    }
    let values: Vec<f64> = values
        .into_iter()
        .map(|v| if !v.is_finite() || Some(v) == no_data { f64::NAN } else { v * metres })
        .collect();
    let values = shape(path, rows, cols, values)?;

    // Other channels beside the surface.
    let others = other_channels(&ctx, &file, &surface_path)?;
    if !others.is_empty() {
        warnings.push(format!(
            "the height map {surface_path} is read; other channels skipped: {}",
            others.join(", ")
        ));
    }
    let metadata = datx_metadata(&ctx, &file, vref, &surface_path, &unit, metres, &attrs)?;

    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Datx);
    sr.warnings = warnings;
    Ok(sr)
}

/// The surface map's stored numbers as f64, row-major, whatever their integer or float type.
fn read_numbers(ds: &Dataset, dtype: &Datatype) -> std::result::Result<Vec<f64>, hdf5_reader::error::Error> {
    match dtype {
        Datatype::FloatingPoint { size: 4, .. } => {
            ds.read_array::<f32>().map(|a| a.iter().map(|&v| v as f64).collect())
        }
        Datatype::FloatingPoint { .. } => ds.read_array::<f64>().map(|a| a.iter().copied().collect()),
        Datatype::FixedPoint { size: 1, signed: true, .. } => {
            ds.read_array::<i8>().map(|a| a.iter().map(|&v| v as f64).collect())
        }
        Datatype::FixedPoint { size: 1, .. } => {
            ds.read_array::<u8>().map(|a| a.iter().map(|&v| v as f64).collect())
        }
        Datatype::FixedPoint { size: 2, signed: true, .. } => {
            ds.read_array::<i16>().map(|a| a.iter().map(|&v| v as f64).collect())
        }
        Datatype::FixedPoint { size: 2, .. } => {
            ds.read_array::<u16>().map(|a| a.iter().map(|&v| v as f64).collect())
        }
        Datatype::FixedPoint { size: 4, signed: true, .. } => {
            ds.read_array::<i32>().map(|a| a.iter().map(|&v| v as f64).collect())
        }
        Datatype::FixedPoint { size: 4, .. } => {
            ds.read_array::<u32>().map(|a| a.iter().map(|&v| v as f64).collect())
        }
        Datatype::FixedPoint { signed: true, .. } => {
            ds.read_array::<i64>().map(|a| a.iter().map(|&v| v as f64).collect())
        }
        _ => ds.read_array::<u64>().map(|a| a.iter().map(|&v| v as f64).collect()),
    }
}

/// The group holding `path` (`/` at the root).
fn parent_group(path: &str) -> &str {
    path.rsplit_once('/').map(|(p, _)| if p.is_empty() { "/" } else { p }).unwrap_or("/")
}

/// The datasets beside the surface at `surface_path` (in its group, and in the groups of
/// `/Data` but `Surface`), the link table left out.
fn other_channels(ctx: &Ctx, file: &Hdf5File, surface_path: &str) -> Result<Vec<String>> {
    let parent = parent_group(surface_path);
    let mut others: Vec<String> =
        datasets_in(ctx, file, parent)?.into_iter().filter(|p| *p != surface_path).collect();
    if let Some(data) = find_group(ctx, file, "/Data")? {
        let (groups, _) = data.member_names().map_err(ctx.h5("/Data"))?;
        for g in groups {
            if g != "Surface" {
                others.extend(datasets_in(ctx, file, &format!("/Data/{g}"))?);
            }
        }
    }
    others.retain(|p| p != "/MetaData");
    Ok(others)
}

/// The metadata: the surface's path and height unit (`unit`, `metres` per stored value), its
/// attributes `attrs`, its groups', then those of `/Attributes/*` (the first of a name kept).
fn datx_metadata(
    ctx: &Ctx,
    file: &Hdf5File,
    vref: usize,
    surface_path: &str,
    unit: &str,
    metres: f64,
    attrs: &[(String, Value)],
) -> Result<Vec<(String, String)>> {
    let parent = parent_group(surface_path);
    let mut metadata = vec![
        ("surface_path".to_string(), surface_path.to_string()),
        ("height_unit".to_string(), format!("{unit} ({} m per stored value)", num_text(metres))),
    ];
    let mut push = |k: &str, v: &Value| {
        if let Some(d) = v.display() {
            if !metadata.iter().any(|(key, _)| key == k) {
                metadata.push((k.to_string(), d));
            }
        }
    };
    for (k, v) in attrs {
        push(k, v);
    }
    let mut groups = Vec::new();
    let mut p = parent.to_string();
    while p != "/" && !p.is_empty() {
        groups.push(p.clone());
        p = p.rsplit_once('/').map(|(a, _)| a.to_string()).unwrap_or_default();
    }
    if let Some(attr_root) = find_group(ctx, file, "/Attributes")? {
        let (names, _) = attr_root.member_names().map_err(ctx.h5("/Attributes"))?;
        groups.extend(names.into_iter().map(|n| format!("/Attributes/{n}")));
    }
    for g in groups {
        if let Some(group) = find_group(ctx, file, &g)? {
            for a in &group.attributes().map_err(ctx.h5(&format!("the attributes of {g}")))? {
                push(&a.name, &attr_value(a, vref, &group));
            }
        }
    }
    Ok(metadata)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_of_every_width_and_byte_order() {
        use hdf5_reader::ByteOrder::{BigEndian, LittleEndian};
        let f32le = Datatype::FloatingPoint { size: 4, byte_order: LittleEndian };
        assert_eq!(number(&f32le, &1.5f32.to_le_bytes()), Some(1.5));
        let f64be = Datatype::FloatingPoint { size: 8, byte_order: BigEndian };
        assert_eq!(number(&f64be, &(-2.25f64).to_be_bytes()), Some(-2.25));
        let i16be = Datatype::FixedPoint { size: 2, signed: true, byte_order: BigEndian };
        assert_eq!(number(&i16be, &(-300i16).to_be_bytes()), Some(-300.0));
        let u32le = Datatype::FixedPoint { size: 4, signed: false, byte_order: LittleEndian };
        assert_eq!(number(&u32le, &4_000_000_000u32.to_le_bytes()), Some(4e9));
        assert_eq!(number(&u32le, &[1, 2]), None);
        assert_eq!(zygo_unit("NanoMeters"), Some(1e-9));
        assert_eq!(zygo_unit("MicroMeters"), Some(1e-6));
        assert_eq!(zygo_unit("µm"), Some(1e-6));
        assert_eq!(zygo_unit("Fringes"), None);
    }

    #[test]
    fn signature_after_a_user_block() {
        let mut b = vec![0u8; 1024 + 8];
        b[1024..].copy_from_slice(MAGIC);
        assert_eq!(signature_offset(&b), Some(1024));
        assert_eq!(signature_offset(MAGIC), Some(0));
        assert_eq!(signature_offset(b"\x89HDF"), None);
        let e = decode(Path::new("t.datx"), b"PK\x03\x04 zip").unwrap_err().to_string();
        assert!(e.contains("t.datx") && e.contains("no HDF5 signature"), "{e}");
    }
}
