//! The multi-level binary mask set as one GDSII stream file, plus a PNG preview per layer.
//!
//! # Mask set
//!
//! A level map with `N = 2^M` levels (level `l` has height `l * period / N`, period
//! `= p * h_2pi`) is made by `M` binary etch steps. Mask `k` (`k = 1..M`, GDSII layer `k`,
//! datatype 0) opens the pixels whose level has bit `M - k` set and etches `period / 2^k`, so
//! that a pixel's total depth is `sum_k bit_(M-k)(l) * period / 2^k = l * period / N`
//! (the binary-optics decomposition of Swanson, "Binary optics technology: the theory and
//! design of multi-level diffractive optical elements", MIT Lincoln Laboratory TR 854, 1989).
//!
//! # Geometry
//!
//! Units: user unit 1 um, database unit 1 nm. Sample `(i, j)` of the grid owns the cell
//! `x in [x_j - px/2, x_j + px/2]`, `y in [y_i - py/2, y_i + py/2]`; GDSII `X = x`,
//! `Y = -y` (rows run downward as in images, so the layout looks like the PNG previews).
//! The pitch must be a whole number of nanometres; the grid's left and top edges are
//! rounded to the nearest nanometre once, so every cell is exactly one pitch wide.
//!
//! Each layer's open region is traced by [`crate::fabrication::trace::trace`] into simple,
//! hole-free, merged rectilinear polygons written as BOUNDARY elements, counter-clockwise in
//! GDSII coordinates.
//!
//! Vertex limit: a record's length is an unsigned 16-bit byte count that includes its 4-byte
//! header, so an XY record holds at most `(65535 - 4) / 8 = 8191` coordinate pairs. A
//! BOUNDARY repeats its first point as its last, so it has at most 8190 distinct vertices
//! ([`MAX_BOUNDARY_VERTICES`]). (The original Calma format allowed 200 points; 8191 is the
//! limit of current readers such as KLayout.) Readers that take the length as a signed
//! 16-bit number stop at 32767 bytes, i.e. 4095 pairs or 4094 vertices
//! ([`SIGNED_LENGTH_MAX_VERTICES`]); KLayout reads longer records correctly but warns about
//! each ("Record length larger than 0x8000"). The default limit is therefore 4094, which
//! every reader takes without a word; [`MaskSetOptions::max_vertices`] (a recipe's
//! `gds.max_vertices`, `doefab gds --max-vertices`) sets any limit in 4..=8190.
//!
//! Alignment crosses (two bars of `cross_width` by `cross_arm`) sit outside the four corners
//! of the design extent, `cross_margin` away from it in x and y, identical on every layer so
//! that the masks register to each other.
//!
//! # Stream format
//!
//! Records `HEADER (600) BGNLIB LIBNAME UNITS BGNSTR STRNAME {BOUNDARY LAYER DATATYPE XY
//! ENDEL}* ENDSTR ENDLIB`, big-endian (Calma GDSII Stream Format Manual, release 6.0, 1987).
//! Time stamps are fixed at 1970-01-01 00:00:00 so that the output is deterministic.
//! Reals are the 8-byte excess-64 base-16 format ([`encode_real8`]).

use std::path::{Path, PathBuf};

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use crate::error::{Allowed, DataCause, Error, Resource, Result};
use crate::fabrication::trace::{trace, Polygon};
use crate::grid::{Grid, Unit};
use crate::io::atomic::write_bytes;

/// Most distinct vertices of a GDSII BOUNDARY (8191 XY pairs including the closing one).
pub const MAX_BOUNDARY_VERTICES: usize = 8190;
/// Most distinct vertices of a BOUNDARY whose XY record stays below 32 KiB (for readers
/// that take record lengths as signed).
pub const SIGNED_LENGTH_MAX_VERTICES: usize = 4094;
/// The database unit, metres.
pub const DATABASE_UNIT: f64 = 1e-9;
/// The user unit, metres.
pub const USER_UNIT: f64 = 1e-6;
/// Library name written into LIBNAME.
pub const LIBRARY_NAME: &str = "DOEFAB";
/// Name of the one structure holding every layer.
pub const STRUCTURE_NAME: &str = "DOEFAB";

/// GDSII record types (record type byte << 8 | data type byte).
mod rec {
    pub const HEADER: u16 = 0x0002;
    pub const BGNLIB: u16 = 0x0102;
    pub const LIBNAME: u16 = 0x0206;
    pub const UNITS: u16 = 0x0305;
    pub const ENDLIB: u16 = 0x0400;
    pub const BGNSTR: u16 = 0x0502;
    pub const STRNAME: u16 = 0x0606;
    pub const ENDSTR: u16 = 0x0700;
    pub const BOUNDARY: u16 = 0x0800;
    pub const LAYER: u16 = 0x0D02;
    pub const DATATYPE: u16 = 0x0E02;
    pub const XY: u16 = 0x1003;
    pub const ENDEL: u16 = 0x1100;
}

/// Fixed modification and access time stamps: 1970-01-01 00:00:00, twice.
const TIMESTAMPS: [i16; 12] = [1970, 1, 1, 0, 0, 0, 1970, 1, 1, 0, 0, 0];

/// Encodes `v` as a GDSII 8-byte real: sign bit, 7-bit exponent `E` (excess 64, base 16) and a
/// 56-bit mantissa `M`, value `(-1)^s * M / 2^56 * 16^(E - 64)`, with `1/16 <= M / 2^56 < 1`.
///
/// Every finite `f64` in range converts exactly (its 53-bit significand fits the 56-bit
/// mantissa after a shift of at most 3 bits), so decoding gives back the same `f64`. This is
/// what KLayout writes, e.g. `1e-3 -> 3E4189374BC6A7F0`, `1e-9 -> 3944B82FA09B5A54`; the often
/// quoted `3E4189374BC6A7EF` is the decimal 0.001 truncated to 56 bits. Values below `16^-65`
/// lose precision (the exponent cannot go lower) and may become 0.
pub fn encode_real8(v: f64) -> Result<[u8; 8]> {
    if !v.is_finite() {
        return Err(Error::param("GDSII real", format!("{v} is not finite")));
    }
    if v == 0.0 {
        return Ok([0; 8]);
    }
    let sign = if v < 0.0 { 0x80u8 } else { 0 };
    let bits = v.abs().to_bits();
    let biased = ((bits >> 52) & 0x7ff) as i64;
    let frac = bits & ((1u64 << 52) - 1);
    // |v| = m * 2^k with an integer m < 2^53.
    let (m, k) = if biased == 0 { (frac, -1074) } else { (frac | (1u64 << 52), biased - 1075) };
    let t = 64 - m.leading_zeros() as i64;
    // M = m * 2^s must have 53..=56 bits, and k - s + 56 must be a multiple of 4.
    let s = (53 - t..=56 - t).find(|s| (k - s + 56).rem_euclid(4) == 0).unwrap_or(56 - t);
    let mut mant = m << s;
    let mut e = (k - s + 56) / 4 + 64;
    if e > 127 {
        return Err(Error::param("GDSII real", format!("{v} is too large for the GDSII real format")));
    }
    if e < 0 {
        // Below the smallest exponent: shift the mantissa right, rounding to nearest.
        let shift = 4 * (-e) as u32;
        mant = if shift >= 60 { 0 } else { (mant + (1u64 << (shift - 1))) >> shift };
        e = 0;
        if mant == 0 {
            return Ok([0; 8]);
        }
    }
    let mut out = [0u8; 8];
    out[0] = sign | e as u8;
    out[1..].copy_from_slice(&mant.to_be_bytes()[1..]);
    Ok(out)
}

/// Decodes a GDSII 8-byte real (see [`encode_real8`]).
pub fn decode_real8(b: [u8; 8]) -> f64 {
    let e = (b[0] & 0x7f) as i32;
    let mut m = [0u8; 8];
    m[1..].copy_from_slice(&b[1..]);
    let mant = u64::from_be_bytes(m) as f64;
    // Scale in two steps so that intermediate powers of two stay in range.
    let p = 4 * (e - 64) - 56;
    let v = mant * 2f64.powi(p / 2) * 2f64.powi(p - p / 2);
    if b[0] & 0x80 != 0 {
        -v
    } else {
        v
    }
}

/// A GDSII stream assembled in memory.
#[derive(Debug, Default, Clone)]
pub struct GdsStream {
    buf: Vec<u8>,
}

impl GdsStream {
    /// An empty stream.
    pub fn new() -> Self {
        GdsStream::default()
    }

    fn head(&mut self, record: u16, data_len: usize) -> Result<()> {
        let len = data_len + 4;
        if len > u16::MAX as usize {
            let what = format!("a GDSII record of {len} bytes exceeds the 65535-byte limit");
            return Err(Error::limit(Resource::RecordBytes, len as f64, f64::from(u16::MAX), what));
        }
        self.buf.extend_from_slice(&(len as u16).to_be_bytes());
        self.buf.extend_from_slice(&record.to_be_bytes());
        Ok(())
    }

    fn shorts(&mut self, record: u16, values: &[i16]) -> Result<()> {
        self.head(record, 2 * values.len())?;
        for v in values {
            self.buf.extend_from_slice(&v.to_be_bytes());
        }
        Ok(())
    }

    fn string(&mut self, record: u16, s: &str) -> Result<()> {
        if !s.bytes().all(|b| b.is_ascii_graphic() || b == b' ') || s.is_empty() {
            return Err(Error::param("GDSII name", format!("'{s}' must be non-empty printable ASCII")));
        }
        let padded = s.len() + s.len() % 2;
        self.head(record, padded)?;
        self.buf.extend_from_slice(s.as_bytes());
        if s.len() % 2 == 1 {
            self.buf.push(0);
        }
        Ok(())
    }

    /// HEADER (version 600), BGNLIB, LIBNAME and UNITS (database unit in user units, database
    /// unit in metres).
    pub fn begin_library(&mut self, name: &str, user_unit: f64, database_unit: f64) -> Result<()> {
        self.shorts(rec::HEADER, &[600])?;
        self.shorts(rec::BGNLIB, &TIMESTAMPS)?;
        self.string(rec::LIBNAME, name)?;
        self.head(rec::UNITS, 16)?;
        let a = encode_real8(database_unit / user_unit)?;
        let b = encode_real8(database_unit)?;
        self.buf.extend_from_slice(&a);
        self.buf.extend_from_slice(&b);
        Ok(())
    }

    /// BGNSTR and STRNAME.
    pub fn begin_structure(&mut self, name: &str) -> Result<()> {
        self.shorts(rec::BGNSTR, &TIMESTAMPS)?;
        self.string(rec::STRNAME, name)
    }

    /// A BOUNDARY element with the given distinct vertices (the closing point is added).
    pub fn boundary(&mut self, layer: u16, datatype: u16, points: &[[i32; 2]]) -> Result<()> {
        self.boundary_from(layer, datatype, points.len(), |k| points[k])
    }

    /// A BOUNDARY of `n` distinct vertices given by `point(k)`, `k < n`.
    fn boundary_from(
        &mut self,
        layer: u16,
        datatype: u16,
        n: usize,
        point: impl Fn(usize) -> [i32; 2],
    ) -> Result<()> {
        if !(3..=MAX_BOUNDARY_VERTICES).contains(&n) {
            let what = format!("a GDSII boundary needs 3..={MAX_BOUNDARY_VERTICES} vertices, got {n}");
            return Err(match n {
                0..3 => Error::data(DataCause::TooFew, what),
                _ => Error::limit(Resource::Vertices, n as f64, MAX_BOUNDARY_VERTICES as f64, what),
            });
        }
        let (layer, datatype) = (gds_short("layer", layer)?, gds_short("datatype", datatype)?);
        self.head(rec::BOUNDARY, 0)?;
        self.shorts(rec::LAYER, &[layer])?;
        self.shorts(rec::DATATYPE, &[datatype])?;
        self.head(rec::XY, 8 * (n + 1))?;
        self.buf.reserve(8 * (n + 1) + 4);
        for k in (0..n).chain([0]) {
            let p = point(k);
            self.buf.extend_from_slice(&p[0].to_be_bytes());
            self.buf.extend_from_slice(&p[1].to_be_bytes());
        }
        self.head(rec::ENDEL, 0)
    }

    /// ENDSTR.
    pub fn end_structure(&mut self) -> Result<()> {
        self.head(rec::ENDSTR, 0)
    }

    /// ENDLIB.
    pub fn end_library(&mut self) -> Result<()> {
        self.head(rec::ENDLIB, 0)
    }

    /// Appends another stream's records (elements built separately).
    pub fn append(&mut self, other: GdsStream) {
        self.buf.extend_from_slice(&other.buf);
    }

    /// Length of the stream so far, bytes.
    pub fn len(&self) -> usize {
        self.buf.len()
    }

    /// Whether no record has been written.
    pub fn is_empty(&self) -> bool {
        self.buf.is_empty()
    }

    /// The stream's bytes, as a GDSII file holds them.
    pub fn into_bytes(self) -> Vec<u8> {
        self.buf
    }
}

fn gds_short(name: &str, v: u16) -> Result<i16> {
    i16::try_from(v).map_err(|_| Error::param(name, format!("{v} exceeds the GDSII limit of 32767")))
}

/// Options of the mask set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MaskSetOptions {
    /// Most vertices per polygon, 4..=8190 (default 4094, see the module docs).
    pub max_vertices: usize,
    /// Length of each bar of the alignment crosses (tip to tip), metres.
    pub cross_arm: f64,
    /// Width of the bars of the alignment crosses, metres.
    pub cross_width: f64,
    /// Gap between the design extent and the nearest tips of each cross, metres.
    pub cross_margin: f64,
}

impl Default for MaskSetOptions {
    fn default() -> Self {
        MaskSetOptions {
            max_vertices: SIGNED_LENGTH_MAX_VERTICES,
            cross_arm: 200e-6,
            cross_width: 20e-6,
            cross_margin: 100e-6,
        }
    }
}

/// One mask of the set.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MaskLayer {
    /// GDSII layer number (= the mask index k, 1 = first etch, deepest).
    pub layer: u16,
    /// GDSII datatype.
    pub datatype: u16,
    /// The bit of the level index this mask opens (M - k).
    pub level_bit: u32,
    /// Etch depth of this step, metres: `period / 2^k`.
    pub etch_depth: f64,
    /// Fraction of the design's pixels that are open (etched).
    pub open_fraction: f64,
    /// Pattern polygons (the 4 alignment crosses not counted).
    pub polygons: usize,
    /// Vertices of the pattern polygons.
    pub vertices: usize,
}

/// What [`write_mask_set`] wrote.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MaskSetStats {
    /// Library name written into LIBNAME ([`LIBRARY_NAME`]).
    pub library: String,
    /// Name of the one structure holding every layer ([`STRUCTURE_NAME`]).
    pub structure: String,
    /// User unit, metres (1e-6).
    pub user_unit: f64,
    /// Database unit, metres (1e-9): the grid of every coordinate.
    pub database_unit: f64,
    /// Number of levels `N` the masks make (a power of two; `log2 N` masks).
    pub level_count: usize,
    /// Etch depth of the deepest level plus one step (`p * h_2pi`), metres.
    pub period: f64,
    /// `[x, y]` pixel pitch, metres (a whole number of database units).
    pub pitch: [f64; 2],
    /// Design extent in GDSII coordinates, metres: `[x_min, y_min, x_max, y_max]`.
    pub design_extent: [f64; 4],
    /// Length of each bar of the alignment crosses (tip to tip), metres.
    pub cross_arm: f64,
    /// Width of the bars of the alignment crosses, metres.
    pub cross_width: f64,
    /// Centres of the alignment crosses in GDSII coordinates, metres: top-left, top-right,
    /// bottom-left, bottom-right.
    pub cross_centres: Vec<[f64; 2]>,
    /// One entry per mask, in layer order (1 = first etch, deepest).
    pub masks: Vec<MaskLayer>,
    /// Pattern polygons over all layers (alignment crosses not counted).
    pub polygons: usize,
    /// Vertices of the pattern polygons over all layers.
    pub vertices: usize,
    /// Size of the GDSII file, bytes.
    pub bytes: usize,
}

/// Checks a level map and the level count; returns the levels as bytes.
fn checked_levels(levels: &Grid, level_count: usize) -> Result<Array2<u8>> {
    if !(2..=256).contains(&level_count) || !level_count.is_power_of_two() {
        return Err(Error::param(
            "level_count",
            format!("a binary mask set needs a power of two in 2..=256 levels, got {level_count}"),
        ));
    }
    if levels.unit() != Unit::Level {
        return Err(Error::param(
            "levels",
            format!("expected a level map (unit 'level'), got values in '{}'", levels.unit().symbol()),
        ));
    }
    if let Some(mask) = levels.mask() {
        if let Some(((i, j), _)) = mask.indexed_iter().find(|(_, &ok)| !ok) {
            let what = format!(
                "level map sample (row {i}, column {j}) is invalid (masked); every sample of a mask set \
                 must be a level"
            );
            return Err(Error::data(DataCause::NotFinite, what));
        }
    }
    let top = (level_count - 1) as f64;
    let mut out = Array2::<u8>::zeros(levels.dim());
    for ((i, j), &v) in levels.values().indexed_iter() {
        if !(v >= 0.0 && v <= top && v == v.round()) {
            return Err(Error::data(
                DataCause::OutOfRange,
                format!(
                    "level map sample (row {i}, column {j}) is {v}; expected an integer level in 0..={top}"
                ),
            ));
        }
        out[[i, j]] = v as u8;
    }
    Ok(out)
}

/// The binary masks of a level map: element `k - 1` is mask `k`, true where the level has
/// bit `M - k` set (M = log2 `level_count`). Refuses level counts that are not a power of
/// two in 2..=256, maps whose unit is not `level`, masked samples and non-integer or
/// out-of-range levels (naming the first offending sample).
pub fn layer_masks(levels: &Grid, level_count: usize) -> Result<Vec<Array2<bool>>> {
    let lv = checked_levels(levels, level_count)?;
    let m = level_count.trailing_zeros();
    Ok((1..=m).map(|k| lv.mapv(|l| (l >> (m - k)) & 1 == 1)).collect())
}

/// Integer nanometre geometry of the design: corner (column c, row r) of the pixel grid sits
/// at `(x0 + c px, y_top - r py)`.
#[derive(Debug, Clone, Copy)]
struct Frame {
    x0: i64,
    y_top: i64,
    px: i64,
    py: i64,
    rows: i64,
    cols: i64,
}

/// `metres` as a whole number of database units, within 1e-6 relative.
fn whole_nm(name: &str, metres: f64) -> Result<i64> {
    let v = metres / DATABASE_UNIT;
    let r = v.round();
    if !((1.0..1e15).contains(&r) && (v - r).abs() <= 1e-6 * v) {
        return Err(Error::param(
            name,
            format!("{v} nm is not a positive whole number of nanometres (the GDSII database unit)"),
        ));
    }
    Ok(r as i64)
}

fn nm(name: &str, metres: f64) -> Result<i64> {
    let v = (metres / DATABASE_UNIT).round();
    if !(v.is_finite() && v.abs() < 1e15) {
        return Err(Error::param(name, format!("{metres} m is out of range")));
    }
    Ok(v as i64)
}

impl Frame {
    fn new(levels: &Grid) -> Result<Frame> {
        let [px, py] = levels.pitch();
        let (px, py) = (whole_nm("pitch", px)?, whole_nm("pitch", py)?);
        let [ox, oy] = levels.origin();
        let (rows, cols) = levels.dim();
        let x0 = nm("origin", ox - 0.5 * levels.pitch()[0])?;
        let y_top = -nm("origin", oy - 0.5 * levels.pitch()[1])?;
        Ok(Frame { x0, y_top, px, py, rows: rows as i64, cols: cols as i64 })
    }

    /// `[x_min, y_min, x_max, y_max]`, nm.
    fn extent(&self) -> [i64; 4] {
        [self.x0, self.y_top - self.rows * self.py, self.x0 + self.cols * self.px, self.y_top]
    }
}

/// The alignment crosses in nm: centres and 12-vertex counter-clockwise outlines.
struct Crosses {
    arm: i64,
    width: i64,
    centres: Vec<[i64; 2]>,
    outlines: Vec<Vec<[i64; 2]>>,
    /// The two bars of each cross as `[x_min, y_min, x_max, y_max]` boxes.
    bars: Vec<[i64; 4]>,
}

fn crosses(frame: &Frame, opts: &MaskSetOptions) -> Result<Crosses> {
    let width = whole_or_round("cross_width", opts.cross_width)?;
    let arm = whole_or_round("cross_arm", opts.cross_arm)?;
    if arm < width + 2 {
        return Err(Error::param(
            "cross_arm",
            format!("{arm} nm must exceed the cross width ({width} nm) by at least 2 nm"),
        ));
    }
    if !(opts.cross_margin.is_finite() && opts.cross_margin >= 0.0) {
        return Err(Error::param_in(
            "cross_margin",
            Allowed::at_least(0.0),
            format!("must be finite and >= 0, got {} m", opts.cross_margin),
        ));
    }
    let margin = nm("cross_margin", opts.cross_margin)?;
    // Bar half-widths and the arm beyond the other bar, split into a lower and upper part.
    let (w_lo, w_hi) = (width / 2, width - width / 2);
    let (t_lo, t_hi) = ((arm - width) / 2, arm - width - (arm - width) / 2);
    let (lo_ext, hi_ext) = (w_lo + t_lo, w_hi + t_hi);
    let [x_min, y_min, x_max, y_max] = frame.extent();
    let left = x_min - margin - hi_ext;
    let right = x_max + margin + lo_ext;
    let top = y_max + margin + lo_ext;
    let bottom = y_min - margin - hi_ext;
    let centres = vec![[left, top], [right, top], [left, bottom], [right, bottom]];
    let mut outlines = Vec::new();
    let mut bars = Vec::new();
    for &[cx, cy] in &centres {
        let (l, r, b, t) = (cx - w_lo, cx + w_hi, cy - w_lo, cy + w_hi);
        let (ll, rr, bb, tt) = (cx - lo_ext, cx + hi_ext, cy - lo_ext, cy + hi_ext);
        outlines.push(vec![
            [l, bb],
            [r, bb],
            [r, b],
            [rr, b],
            [rr, t],
            [r, t],
            [r, tt],
            [l, tt],
            [l, t],
            [ll, t],
            [ll, b],
            [l, b],
        ]);
        bars.push([l, bb, r, tt]);
        bars.push([ll, b, rr, t]);
    }
    Ok(Crosses { arm, width, centres, outlines, bars })
}

fn whole_or_round(name: &str, metres: f64) -> Result<i64> {
    if !(metres.is_finite() && metres > 0.0) {
        return Err(Error::param_in(
            name,
            Allowed::positive(),
            format!("must be finite and positive, got {metres} m"),
        ));
    }
    let v = nm(name, metres)?;
    if v < 1 {
        return Err(Error::param(name, format!("{metres} m is below the 1 nm database unit")));
    }
    Ok(v)
}

fn check_options(opts: &MaskSetOptions) -> Result<()> {
    if !(4..=MAX_BOUNDARY_VERTICES).contains(&opts.max_vertices) {
        return Err(Error::param_in(
            "max_vertices",
            Allowed::between(4.0, MAX_BOUNDARY_VERTICES as f64),
            format!(
                "must be within 4..={MAX_BOUNDARY_VERTICES} (GDSII boundary limit), got {}",
                opts.max_vertices
            ),
        ));
    }
    Ok(())
}

/// Validates everything and computes the shared geometry.
fn prepare(
    levels: &Grid,
    level_count: usize,
    opts: &MaskSetOptions,
) -> Result<(Vec<Array2<bool>>, Frame, Crosses)> {
    check_options(opts)?;
    let masks = layer_masks(levels, level_count)?;
    let frame = Frame::new(levels)?;
    let crosses = crosses(&frame, opts)?;
    // Every coordinate must fit a signed 32-bit integer.
    let e = frame.extent();
    let all = crosses.outlines.iter().flatten().flat_map(|p| [p[0], p[1]]).chain(e);
    for v in all {
        if i32::try_from(v).is_err() {
            let what = format!("coordinate {v} nm does not fit the 32-bit GDSII range (+-2.147 m at 1 nm)");
            return Err(Error::limit(Resource::Coordinate, (v as f64).abs(), f64::from(i32::MAX), what));
        }
    }
    Ok((masks, frame, crosses))
}

/// The elements of one layer: crosses, then the traced pattern (polygon and vertex counts).
fn layer_elements(
    mask: &Array2<bool>,
    layer: u16,
    frame: &Frame,
    crosses: &Crosses,
    max_vertices: usize,
) -> Result<(GdsStream, usize, usize)> {
    let mut s = GdsStream::new();
    for outline in &crosses.outlines {
        // In range: checked by `prepare`.
        s.boundary_from(layer, 0, outline.len(), |k| [outline[k][0] as i32, outline[k][1] as i32])?;
    }
    let polys: Vec<Polygon> = trace(mask, max_vertices)?;
    let vertices = polys.iter().map(Vec::len).sum();
    let f = *frame;
    for p in &polys {
        let n = p.len();
        // The tracer's order is clockwise once Y = -y flips the picture into GDSII
        // coordinates; reversed (keeping the first vertex first), it is counter-clockwise.
        s.boundary_from(layer, 0, n, |k| {
            let v = p[(n - k) % n];
            [(f.x0 + v[0] as i64 * f.px) as i32, (f.y_top - v[1] as i64 * f.py) as i32]
        })?;
    }
    Ok((s, polys.len(), vertices))
}

/// Builds the GDSII mask set of a level map in memory (see the module docs): the bytes of
/// the file and the report. Layers are traced in parallel; the output is deterministic.
pub fn mask_set_gds(
    levels: &Grid,
    level_count: usize,
    period: f64,
    opts: &MaskSetOptions,
) -> Result<(Vec<u8>, MaskSetStats)> {
    if !(period.is_finite() && period > 0.0) {
        return Err(Error::param_in(
            "period",
            Allowed::positive(),
            format!("must be finite and positive, got {period} m"),
        ));
    }
    let (masks, frame, crosses) = prepare(levels, level_count, opts)?;
    let results: Vec<Result<(GdsStream, usize, usize)>> = std::thread::scope(|scope| {
        let handles: Vec<_> = masks
            .iter()
            .enumerate()
            .map(|(k, mask)| {
                let (frame, crosses) = (&frame, &crosses);
                scope.spawn(move || layer_elements(mask, k as u16 + 1, frame, crosses, opts.max_vertices))
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))).collect()
    });
    let mut gds = GdsStream::new();
    gds.begin_library(LIBRARY_NAME, USER_UNIT, DATABASE_UNIT)?;
    gds.begin_structure(STRUCTURE_NAME)?;
    let mut layers = Vec::new();
    let pixels = (frame.rows * frame.cols) as f64;
    for (k, (res, mask)) in results.into_iter().zip(&masks).enumerate() {
        let (elements, polygons, vertices) = res?;
        gds.append(elements);
        let layer = k as u16 + 1;
        layers.push(MaskLayer {
            layer,
            datatype: 0,
            level_bit: masks.len() as u32 - layer as u32,
            etch_depth: period / 2f64.powi(layer as i32),
            open_fraction: mask.iter().filter(|&&v| v).count() as f64 / pixels,
            polygons,
            vertices,
        });
    }
    gds.end_structure()?;
    gds.end_library()?;
    let m = |v: i64| v as f64 * DATABASE_UNIT;
    let e = frame.extent();
    let report = MaskSetStats {
        library: LIBRARY_NAME.into(),
        structure: STRUCTURE_NAME.into(),
        user_unit: USER_UNIT,
        database_unit: DATABASE_UNIT,
        level_count,
        period,
        pitch: [m(frame.px), m(frame.py)],
        design_extent: e.map(m),
        cross_arm: m(crosses.arm),
        cross_width: m(crosses.width),
        cross_centres: crosses.centres.iter().map(|c| [m(c[0]), m(c[1])]).collect(),
        polygons: layers.iter().map(|l| l.polygons).sum(),
        vertices: layers.iter().map(|l| l.vertices).sum(),
        masks: layers,
        bytes: gds.len(),
    };
    Ok((gds.into_bytes(), report))
}

/// Writes the mask set of a level map (values 0..N-1, unit `level`, N a power of two) as a
/// GDSII file at `path` (atomically); `period` is the depth of N levels (`p * h_2pi`, metres).
pub fn write_mask_set(
    levels: &Grid,
    level_count: usize,
    period: f64,
    opts: &MaskSetOptions,
    path: &Path,
) -> Result<MaskSetStats> {
    let (bytes, report) = mask_set_gds(levels, level_count, period, opts)?;
    write_bytes(path, &bytes)?;
    Ok(report)
}

/// An 8-bit grey preview of every layer: one image pixel per grid sample, white (255) where
/// the mask is open (etched), black (0) where chrome stays, the alignment crosses drawn open,
/// on a canvas padded to hold them. Returns `(width, height, pixels)` per layer, row-major.
pub fn layer_previews(
    levels: &Grid,
    level_count: usize,
    opts: &MaskSetOptions,
) -> Result<Vec<(u32, u32, Vec<u8>)>> {
    let (masks, f, crosses) = prepare(levels, level_count, opts)?;
    // Padding in pixels: enough to hold the crosses and one pixel more.
    let reach = crosses.arm + nm("cross_margin", opts.cross_margin)?;
    let (pad_x, pad_y) = (reach / f.px + 2, reach / f.py + 2);
    let (w, h) = (f.cols + 2 * pad_x, f.rows + 2 * pad_y);
    if w > u32::MAX as i64 || h > u32::MAX as i64 || w * h > (1 << 34) {
        let what = format!("a {w} x {h} preview is too large");
        return Err(Error::limit(Resource::Samples, w as f64 * h as f64, (1u64 << 34) as f64, what));
    }
    // The canvas with the crosses; pixel centres tested against the bars, in units of nm / 2.
    let mut base = vec![0u8; (w * h) as usize];
    for bar in &crosses.bars {
        // Canvas columns and rows whose centres may fall in the bar.
        let u0 = ((bar[0] - f.x0) / f.px + pad_x - 1).max(0);
        let u1 = ((bar[2] - f.x0) / f.px + pad_x + 1).min(w - 1);
        let v0 = ((f.y_top - bar[3]) / f.py + pad_y - 1).max(0);
        let v1 = ((f.y_top - bar[1]) / f.py + pad_y + 1).min(h - 1);
        for v in v0..=v1 {
            let y2 = 2 * f.y_top - (2 * (v - pad_y) + 1) * f.py;
            if !(2 * bar[1] <= y2 && y2 < 2 * bar[3]) {
                continue;
            }
            for u in u0..=u1 {
                let x2 = 2 * f.x0 + (2 * (u - pad_x) + 1) * f.px;
                if 2 * bar[0] <= x2 && x2 < 2 * bar[2] {
                    base[(v * w + u) as usize] = 255;
                }
            }
        }
    }
    Ok(masks
        .iter()
        .map(|mask| {
            let mut img = base.clone();
            for (i, row) in mask.outer_iter().enumerate() {
                let o = ((i as i64 + pad_y) * w + pad_x) as usize;
                for (p, &open) in img[o..o + f.cols as usize].iter_mut().zip(row.iter()) {
                    *p = if open { 255 } else { 0 };
                }
            }
            (w as u32, h as u32, img)
        })
        .collect())
}

/// Writes [`layer_previews`] as 8-bit greyscale PNG files `dir/{stem}_layer{k}.png`
/// (atomically); returns their paths in layer order.
pub fn write_layer_previews(
    levels: &Grid,
    level_count: usize,
    opts: &MaskSetOptions,
    dir: &Path,
    stem: &str,
) -> Result<Vec<PathBuf>> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let mut paths = Vec::new();
    for (k, (w, h, img)) in layer_previews(levels, level_count, opts)?.into_iter().enumerate() {
        let path = dir.join(format!("{stem}_layer{}.png", k + 1));
        let mut buf = Vec::new();
        PngEncoder::new_with_quality(&mut buf, CompressionType::Fast, FilterType::Adaptive)
            .write_image(&img, w, h, image::ExtendedColorType::L8)
            .map_err(|e| Error::encoding(&path, format!("cannot encode the PNG preview: {e}")))?;
        write_bytes(&path, &buf)?;
        paths.push(path);
    }
    Ok(paths)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(b: [u8; 8]) -> String {
        b.iter().map(|x| format!("{x:02X}")).collect()
    }

    #[test]
    fn real8_encoding_matches_known_patterns() {
        // Exact powers: 1 = 1/16 * 16^1, 0.5 = 8/16 * 16^0, -2, 1/16.
        assert_eq!(hex(encode_real8(1.0).unwrap()), "4110000000000000");
        assert_eq!(hex(encode_real8(0.5).unwrap()), "4080000000000000");
        assert_eq!(hex(encode_real8(-2.0).unwrap()), "C120000000000000");
        assert_eq!(hex(encode_real8(0.0625).unwrap()), "4010000000000000");
        assert_eq!(hex(encode_real8(0.0).unwrap()), "0000000000000000");
        // The UNITS pair as KLayout 0.30 writes it for a 1 nm database unit in um.
        assert_eq!(hex(encode_real8(1e-3).unwrap()), "3E4189374BC6A7F0");
        assert_eq!(hex(encode_real8(1e-9).unwrap()), "3944B82FA09B5A54");
        // The classic truncated patterns of older writers decode to within 1e-16 of the same.
        let classic = |h: u64| decode_real8(h.to_be_bytes());
        assert!((classic(0x3E4189374BC6A7EF) / 1e-3 - 1.0).abs() < 1e-16);
        assert!((classic(0x3944B82FA09B5A51) / 1e-9 - 1.0).abs() < 1e-15);
        assert!(encode_real8(f64::NAN).is_err());
        assert!(encode_real8(1e80).is_err());
    }

    #[test]
    fn real8_round_trips_exactly() {
        let mut x = 0x9E3779B97F4A7C15u64;
        for _ in 0..20000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let mant = (x >> 11) as f64 / (1u64 << 53) as f64;
            let e = ((x & 0x3ff) as i32 % 300) - 150;
            let v = if x & 0x400 != 0 { -mant } else { mant } * 2f64.powi(e);
            let b = encode_real8(v).unwrap();
            assert_eq!(decode_real8(b).to_bits(), v.to_bits(), "{v:e}");
            // Normalised: the first hex digit of the mantissa is non-zero.
            assert!(v == 0.0 || b[1] >> 4 != 0);
        }
        // Underflow degrades gracefully.
        assert_eq!(decode_real8(encode_real8(1e-300).unwrap()), 0.0);
    }

    #[test]
    fn records_have_the_documented_layout() {
        let mut s = GdsStream::new();
        s.begin_library("AB", USER_UNIT, DATABASE_UNIT).unwrap();
        s.begin_structure("XYZ").unwrap();
        s.boundary(3, 0, &[[0, 0], [10, 0], [10, -5]]).unwrap();
        s.end_structure().unwrap();
        s.end_library().unwrap();
        let b = s.into_bytes();
        // HEADER: length 6, type 0x0002, version 600.
        assert_eq!(&b[0..6], &[0, 6, 0, 2, 0x02, 0x58]);
        // BGNLIB: 4 + 24 bytes, then LIBNAME "AB" (even, no pad).
        assert_eq!(&b[6..10], &[0, 28, 1, 2]);
        assert_eq!(&b[10..12], &1970i16.to_be_bytes());
        assert_eq!(&b[34..40], &[0, 6, 2, 6, b'A', b'B']);
        // UNITS: 4 + 16 bytes.
        assert_eq!(&b[40..44], &[0, 20, 3, 5]);
        // BGNSTR, then STRNAME "XYZ" padded with a NUL.
        assert_eq!(&b[60..64], &[0, 28, 5, 2]);
        assert_eq!(&b[88..96], &[0, 8, 6, 6, b'X', b'Y', b'Z', 0]);
        // BOUNDARY, LAYER 3, DATATYPE 0, XY with 4 points (closing point repeated), ENDEL.
        assert_eq!(&b[96..100], &[0, 4, 8, 0]);
        assert_eq!(&b[100..106], &[0, 6, 0x0D, 2, 0, 3]);
        assert_eq!(&b[106..112], &[0, 6, 0x0E, 2, 0, 0]);
        assert_eq!(&b[112..116], &[0, 36, 0x10, 3]);
        assert_eq!(&b[124..132], &[0, 0, 0, 10, 0, 0, 0, 0]);
        assert_eq!(&b[132..140], &[0, 0, 0, 10, 0xFF, 0xFF, 0xFF, 0xFB]);
        assert_eq!(&b[140..148], &[0; 8]);
        assert_eq!(&b[148..152], &[0, 4, 0x11, 0]);
        assert_eq!(&b[152..], &[0, 4, 7, 0, 0, 4, 4, 0]);
    }

    #[test]
    fn boundary_limits_are_enforced() {
        let mut s = GdsStream::new();
        let pts: Vec<[i32; 2]> = (0..MAX_BOUNDARY_VERTICES as i32).map(|k| [k, k % 2]).collect();
        s.boundary(1, 0, &pts).unwrap();
        // The largest XY record is 4 + 8 * 8191 = 65532 bytes.
        assert_eq!(s.len(), 4 + 6 + 6 + 65532 + 4);
        let more: Vec<[i32; 2]> = (0..MAX_BOUNDARY_VERTICES as i32 + 1).map(|k| [k, 0]).collect();
        let e = s.boundary(1, 0, &more).unwrap_err();
        let n = MAX_BOUNDARY_VERTICES as f64;
        let vertices = |e: &Error| match *e {
            Error::Limit { resource: Resource::Vertices, requested, limit, .. } => Some((requested, limit)),
            _ => None,
        };
        assert_eq!(vertices(&e), Some((n + 1.0, n)), "{e:?}");
        let e = s.boundary(1, 0, &more[..2]).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::TooFew, .. }), "{e:?}");
        assert!(s.boundary(40000, 0, &pts[..4]).is_err());
        // The signed-length-safe limit keeps the XY record within 32767 bytes.
        assert!(4 + 8 * (SIGNED_LENGTH_MAX_VERTICES + 1) <= i16::MAX as usize);
        assert!(4 + 8 * (SIGNED_LENGTH_MAX_VERTICES + 2) > i16::MAX as usize);
    }

    fn level_grid(values: Array2<f64>, pitch: f64) -> Grid {
        Grid::new(values, [pitch, pitch], Unit::Level).unwrap()
    }

    #[test]
    fn masks_decompose_levels_into_bits() {
        let v = Array2::from_shape_fn((4, 8), |(i, j)| ((i * 8 + j) % 8) as f64);
        let g = level_grid(v.clone(), 1e-6);
        let masks = layer_masks(&g, 8).unwrap();
        assert_eq!(masks.len(), 3);
        for ((i, j), &l) in v.indexed_iter() {
            let back: usize = masks.iter().enumerate().map(|(k, m)| (m[[i, j]] as usize) << (2 - k)).sum();
            assert_eq!(back, l as usize);
        }
        // Etch depths add up to the level heights l * period / N.
        let (_, rep) = mask_set_gds(&g, 8, 8e-6, &MaskSetOptions::default()).unwrap();
        let depths: Vec<f64> = rep.masks.iter().map(|m| m.etch_depth).collect();
        assert_eq!(depths, vec![4e-6, 2e-6, 1e-6]);
        assert_eq!(rep.masks.iter().map(|m| m.level_bit).collect::<Vec<_>>(), vec![2, 1, 0]);
    }

    #[test]
    fn bad_inputs_are_refused() {
        let g = level_grid(Array2::from_elem((3, 3), 1.0), 1e-6);
        for n in [0, 1, 3, 6, 512] {
            assert!(matches!(layer_masks(&g, n), Err(Error::Parameter { .. })), "{n}");
        }
        let mut v = Array2::from_elem((3, 4), 1.0);
        v[[1, 2]] = 4.0;
        let e = layer_masks(&level_grid(v.clone(), 1e-6), 4).unwrap_err();
        assert!(
            matches!(e, Error::Data { cause: DataCause::OutOfRange, .. })
                && e.to_string().contains("row 1, column 2"),
            "{e:?}"
        );
        v[[1, 2]] = 1.5;
        assert!(layer_masks(&level_grid(v.clone(), 1e-6), 4).is_err());
        v[[1, 2]] = -1.0;
        assert!(layer_masks(&level_grid(v, 1e-6), 4).is_err());
        let heights = Grid::new(Array2::zeros((2, 2)), [1e-6, 1e-6], Unit::Metre).unwrap();
        assert!(layer_masks(&heights, 4).is_err());
        let mut valid = Array2::from_elem((3, 3), true);
        valid[[2, 0]] = false;
        let masked = g.clone().with_mask(valid).unwrap();
        let e = layer_masks(&masked, 4).unwrap_err();
        assert!(
            matches!(e, Error::Data { cause: DataCause::NotFinite, .. })
                && e.to_string().contains("row 2, column 0"),
            "{e:?}"
        );
        // Pitch not a whole number of nm, bad period, bad options.
        let odd = level_grid(Array2::zeros((2, 2)), 1.0005e-6);
        let o = MaskSetOptions::default();
        let e = mask_set_gds(&odd, 2, 1e-6, &o).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name.contains("pitch")), "{e:?}");
        assert!(mask_set_gds(&g, 2, 0.0, &o).is_err());
        for bad in [
            MaskSetOptions { max_vertices: 3, ..o.clone() },
            MaskSetOptions { max_vertices: 8191, ..o.clone() },
            MaskSetOptions { cross_width: 0.0, ..o.clone() },
            MaskSetOptions { cross_arm: 20e-6, ..o.clone() },
            MaskSetOptions { cross_margin: f64::NAN, ..o.clone() },
        ] {
            assert!(mask_set_gds(&g, 2, 1e-6, &bad).is_err(), "{bad:?}");
        }
        // Coordinates beyond the 32-bit range: 5 m wide at 1 mm pitch.
        let huge = level_grid(Array2::zeros((1, 5000)), 1e-3);
        let e = mask_set_gds(&huge, 2, 1e-6, &o).unwrap_err();
        assert!(matches!(e, Error::Limit { resource: Resource::Coordinate, .. }), "{e:?}");
    }

    #[test]
    fn output_is_deterministic_and_geometry_is_placed() {
        let v = Array2::from_shape_fn((5, 7), |(i, j)| ((i + 2 * j) % 4) as f64);
        let g = level_grid(v, 2e-6).with_origin([10e-6, -3e-6]);
        let o =
            MaskSetOptions { cross_arm: 30e-6, cross_width: 4e-6, cross_margin: 5e-6, ..Default::default() };
        let (a, rep) = mask_set_gds(&g, 4, 1e-6, &o).unwrap();
        let (b, _) = mask_set_gds(&g, 4, 1e-6, &o).unwrap();
        assert_eq!(a, b);
        assert_eq!(rep.bytes, a.len());
        // Column 0 starts at 10 um - 1 um; row 0's top edge is at Y = -(-3 um - 1 um) = 4 um.
        let e = rep.design_extent;
        assert!((e[0] - 9e-6).abs() < 1e-15 && (e[2] - 23e-6).abs() < 1e-15);
        assert!((e[3] - 4e-6).abs() < 1e-15 && (e[1] + 6e-6).abs() < 1e-15);
        // The top-left cross's right tip and bottom tip are 5 um from the extent.
        let c = rep.cross_centres[0];
        assert!((c[0] + 15e-6 - (e[0] - 5e-6)).abs() < 1e-15, "{c:?}");
        assert!((c[1] - 15e-6 - (e[3] + 5e-6)).abs() < 1e-15, "{c:?}");
        let c = rep.cross_centres[3];
        assert!((c[0] - 15e-6 - (e[2] + 5e-6)).abs() < 1e-15 && (c[1] + 15e-6 - (e[1] - 5e-6)).abs() < 1e-15);
    }

    #[test]
    fn previews_show_masks_and_crosses() {
        let v = Array2::from_shape_fn((6, 9), |(i, j)| ((i * 3 + j) % 4) as f64);
        let g = level_grid(v.clone(), 1e-6);
        let o =
            MaskSetOptions { cross_arm: 5e-6, cross_width: 1e-6, cross_margin: 2e-6, ..Default::default() };
        let imgs = layer_previews(&g, 4, &o).unwrap();
        assert_eq!(imgs.len(), 2);
        // Padding: (5 + 2) um / 1 um + 2 = 9 pixels per side.
        let (w, h, _) = imgs[0];
        assert_eq!((w, h), (9 + 18, 6 + 18));
        for (k, (w, _, img)) in imgs.iter().enumerate() {
            for ((i, j), &l) in v.indexed_iter() {
                let open = img[(i + 9) * *w as usize + j + 9] == 255;
                assert_eq!(open, (l as usize >> (1 - k)) & 1 == 1);
            }
            // Each cross covers 2 * 5 - 1 = 9 pixels; four crosses, identical on both layers.
            let outside: usize = img.iter().filter(|&&p| p == 255).count()
                - v.iter().filter(|&&l| (l as usize >> (1 - k)) & 1 == 1).count();
            assert_eq!(outside, 36);
        }
        let a: Vec<usize> =
            (0..imgs[0].2.len()).filter(|&p| imgs[0].2[p] == 255 && !in_design(p, w as usize)).collect();
        let b: Vec<usize> =
            (0..imgs[1].2.len()).filter(|&p| imgs[1].2[p] == 255 && !in_design(p, w as usize)).collect();
        assert_eq!(a, b);
        // The top-left cross centre lies 2 + 2.5 um left of and above the design's corner: the
        // centre of canvas pixel (4, 4), which both bars cover.
        let centre = 4 * w as usize + 4;
        assert_eq!(imgs[0].2[centre], 255);
        fn in_design(p: usize, w: usize) -> bool {
            let (v, u) = (p / w, p % w);
            (9..15).contains(&v) && (9..18).contains(&u)
        }
    }
}
