//! NumPy `.npy` files, read and written by our own parser (format versions 1.0, 2.0, 3.0).
//!
//! Layout (NumPy Enhancement Proposal 1, "A simple file format for NumPy arrays"):
//! the magic `\x93NUMPY`, a major and a minor version byte, the header length (u16 little
//! endian for v1, u32 for v2 and v3), then the header: a Python dict literal
//! `{'descr': '<f8', 'fortran_order': False, 'shape': (H, W), }` padded with spaces and a
//! newline so that the data starts on a 64-byte boundary, then the raw data, row-major (C order)
//! or column-major (`fortran_order: True`).
//!
//! Readable element types (`descr`): floats `f2`, `f4`, `f8` and integers `i1`..`i8`, `u1`..`u8`,
//! little (`<`), big (`>`) or no (`|`) byte order; all are converted to `f64` (integers exactly,
//! up to 2^53). Integer arrays are useful for level maps.
//!
//! The writer produces the same bytes as `numpy.save` for the same array (same header text,
//! same spare room for the shape to grow, same 64-byte padding).
//!
//! Why not the `ndarray-npy` crate (0.9.1, measured on files `numpy.save` wrote): it refuses
//! `<f2` ("incorrect descriptor"), reads an integer array only into the matching Rust integer
//! type (an `<i2` level map or scan cannot be asked for as `f64`), writes `{'descr': ...,
//! 'shape': (3, 4)}` where NumPy writes `(3, 4), }` (so its files are not NumPy's bytes), and
//! would compile a third version of `zip` (2.6) beside the two already in the build. Speed
//! (`benches/codecs`, best of 30, from memory): a 4.9 MB `<f4` file in 0.77 ms here (to
//! `f64`) against 0.58 ms for `ndarray-npy` 0.10 (to `f32`, half the bytes written), 1.3x; the
//! measured PSF's `.npz` 0.69 ms against 0.38 ms (the same inflate, then our copy to `f64`).
//! Milliseconds per file, against the seconds the stages spend on the data: ours is kept.

use std::io::Write;
use std::path::Path;

use ndarray::{Array2, ArrayBase, ArrayD, Data, Dimension, IxDyn, ShapeBuilder};

use crate::error::{Error, Result};
use crate::io::atomic::write_atomic;
use crate::io::raw_map::{RawMap, SampleKind};

const MAGIC: &[u8; 6] = b"\x93NUMPY";

/// The parsed header of a `.npy` file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NpyHeader {
    /// Format version `(major, minor)`.
    pub version: (u8, u8),
    /// The dtype string as stored, e.g. `"<f8"`.
    pub descr: String,
    /// True when the data is stored column-major.
    pub fortran_order: bool,
    /// The array shape.
    pub shape: Vec<usize>,
    /// Byte offset of the first data byte.
    pub data_offset: usize,
}

/// Element types the reader understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Elem {
    F2,
    F4,
    F8,
    I1,
    U1,
    I2,
    U2,
    I4,
    U4,
    I8,
    U8,
}

impl Elem {
    fn size(self) -> usize {
        match self {
            Elem::I1 | Elem::U1 => 1,
            Elem::F2 | Elem::I2 | Elem::U2 => 2,
            Elem::F4 | Elem::I4 | Elem::U4 => 4,
            Elem::F8 | Elem::I8 | Elem::U8 => 8,
        }
    }
}

/// Parses the dtype string into element type and byte order (`true` = big endian).
fn parse_descr(path: &Path, descr: &str) -> Result<(Elem, bool)> {
    let bad = || {
        Error::unsupported(
            path,
            format!(
                "dtype '{descr}' is not supported (expected a float f2/f4/f8 or an integer \
                 i1..i8/u1..u8, e.g. '<f8')"
            ),
        )
    };
    let mut chars = descr.chars();
    let order = chars.next().ok_or_else(bad)?;
    let big = match order {
        '<' | '|' => false,
        '>' => true,
        '=' => cfg!(target_endian = "big"),
        _ => return Err(bad()),
    };
    let elem = match chars.as_str() {
        "f2" => Elem::F2,
        "f4" => Elem::F4,
        "f8" => Elem::F8,
        "i1" => Elem::I1,
        "u1" => Elem::U1,
        "i2" => Elem::I2,
        "u2" => Elem::U2,
        "i4" => Elem::I4,
        "u4" => Elem::U4,
        "i8" => Elem::I8,
        "u8" => Elem::U8,
        _ => return Err(bad()),
    };
    Ok((elem, big))
}

/// A value of the header dict.
#[derive(Debug, Clone, PartialEq)]
enum PyValue {
    Str(String),
    Bool(bool),
    Tuple(Vec<usize>),
}

/// A minimal parser for the Python literal of the header dict: string keys; string, bool and
/// tuple-of-integer values.
struct Literal<'a> {
    s: &'a [u8],
    pos: usize,
}

impl<'a> Literal<'a> {
    fn skip_ws(&mut self) {
        while self.pos < self.s.len() && self.s[self.pos].is_ascii_whitespace() {
            self.pos += 1;
        }
    }
    fn peek(&mut self) -> Option<u8> {
        self.skip_ws();
        self.s.get(self.pos).copied()
    }
    fn expect(&mut self, c: u8) -> std::result::Result<(), String> {
        match self.peek() {
            Some(x) if x == c => {
                self.pos += 1;
                Ok(())
            }
            Some(x) => {
                Err(format!("expected '{}' at header byte {}, found '{}'", c as char, self.pos, x as char))
            }
            None => Err(format!("expected '{}' at header byte {}, found the end", c as char, self.pos)),
        }
    }
    fn string(&mut self) -> std::result::Result<String, String> {
        let q = self.peek().ok_or("header ends where a string was expected")?;
        if q != b'\'' && q != b'"' {
            return Err(format!("expected a quoted string at header byte {}", self.pos));
        }
        self.pos += 1;
        let start = self.pos;
        while self.pos < self.s.len() && self.s[self.pos] != q {
            self.pos += 1;
        }
        if self.pos >= self.s.len() {
            return Err("unterminated string in header".into());
        }
        let text = String::from_utf8_lossy(&self.s[start..self.pos]).into_owned();
        self.pos += 1;
        Ok(text)
    }
    fn word(&mut self) -> String {
        self.skip_ws();
        let start = self.pos;
        while self.pos < self.s.len()
            && (self.s[self.pos].is_ascii_alphanumeric() || self.s[self.pos] == b'_')
        {
            self.pos += 1;
        }
        String::from_utf8_lossy(&self.s[start..self.pos]).into_owned()
    }
    fn value(&mut self) -> std::result::Result<PyValue, String> {
        match self.peek() {
            Some(b'\'') | Some(b'"') => Ok(PyValue::Str(self.string()?)),
            Some(b'(') => {
                self.pos += 1;
                let mut dims = Vec::new();
                loop {
                    if self.peek() == Some(b')') {
                        self.pos += 1;
                        break;
                    }
                    let w = self.word();
                    // Python 2 wrote longs as "3L".
                    let digits = w.strip_suffix('L').unwrap_or(&w);
                    let d: usize = digits
                        .parse()
                        .map_err(|_| format!("shape entry '{w}' is not a non-negative integer"))?;
                    dims.push(d);
                    match self.peek() {
                        Some(b',') => self.pos += 1,
                        Some(b')') => {}
                        _ => return Err("shape tuple is not closed".into()),
                    }
                }
                Ok(PyValue::Tuple(dims))
            }
            Some(b'[') => Err("structured dtypes (a list as 'descr') are not supported".into()),
            Some(_) => match self.word().as_str() {
                "True" => Ok(PyValue::Bool(true)),
                "False" => Ok(PyValue::Bool(false)),
                w => Err(format!("unexpected value '{w}' in header")),
            },
            None => Err("header ends where a value was expected".into()),
        }
    }
    fn dict(&mut self) -> std::result::Result<Vec<(String, PyValue)>, String> {
        self.expect(b'{')?;
        let mut out = Vec::new();
        loop {
            if self.peek() == Some(b'}') {
                self.pos += 1;
                return Ok(out);
            }
            let key = self.string()?;
            self.expect(b':')?;
            let v = self.value()?;
            out.push((key, v));
            match self.peek() {
                Some(b',') => self.pos += 1,
                Some(b'}') => {}
                _ => return Err(format!("expected ',' or '}}' at header byte {}", self.pos)),
            }
        }
    }
}

/// Parses the preamble and header of a `.npy` file held in `bytes`.
pub fn parse_header(path: &Path, bytes: &[u8]) -> Result<NpyHeader> {
    if bytes.len() < 10 {
        return Err(Error::truncated(
            path,
            bytes.len() as u64,
            format!("not a .npy file: {} bytes, shorter than the 10-byte preamble", bytes.len()),
        ));
    }
    if &bytes[..6] != MAGIC {
        return Err(Error::signature(path, "not a .npy file: bad magic (expected \\x93NUMPY)"));
    }
    let version = (bytes[6], bytes[7]);
    let (hlen, start) = match version.0 {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(Error::truncated(
                    path,
                    bytes.len() as u64,
                    "truncated: the header length field is cut off",
                ));
            }
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => {
            return Err(Error::unsupported(
                path,
                format!("unsupported .npy format version {v}.{} (expected 1, 2 or 3)", version.1),
            ))
        }
    };
    let end = start + hlen;
    if bytes.len() < end {
        return Err(Error::truncated(
            path,
            bytes.len() as u64,
            format!(
                "truncated: expected a {hlen}-byte header at offset {start}, got {}",
                bytes.len().saturating_sub(start)
            ),
        ));
    }
    let text = &bytes[start..end];
    let dict =
        Literal { s: text, pos: 0 }.dict().map_err(|e| Error::malformed(path, format!("bad header: {e}")))?;
    let field = |name: &str| {
        dict.iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.clone())
            .ok_or_else(|| Error::malformed(path, format!("header field '{name}' is missing")))
    };
    let descr = match field("descr")? {
        PyValue::Str(s) => s,
        v => return Err(Error::malformed(path, format!("header field 'descr' is not a string: {v:?}"))),
    };
    let fortran_order = match field("fortran_order")? {
        PyValue::Bool(b) => b,
        v => {
            return Err(Error::malformed(path, format!("header field 'fortran_order' is not a bool: {v:?}")))
        }
    };
    let shape = match field("shape")? {
        PyValue::Tuple(t) => t,
        v => return Err(Error::malformed(path, format!("header field 'shape' is not a tuple: {v:?}"))),
    };
    Ok(NpyHeader { version, descr, fortran_order, shape, data_offset: end })
}

/// Decodes `n` elements of type `elem` from `data` into `f64`.
fn decode(path: &Path, data: &[u8], elem: Elem, big: bool) -> Result<Vec<f64>> {
    /// `f` on each `N`-byte element, its bytes in little-endian order; one loop per element
    /// type, so the compiler vectorises it (a match per element ran 6x slower than
    /// `ndarray-npy` on a 4.9 MB `<f4` file, `benches/codecs`).
    fn each<const N: usize>(data: &[u8], big: bool, f: impl Fn([u8; N]) -> f64) -> Vec<f64> {
        data.chunks_exact(N)
            .map(|c| {
                let mut b = [0u8; N];
                b.copy_from_slice(c);
                if big {
                    b.reverse();
                }
                f(b)
            })
            .collect()
    }
    let out = match elem {
        Elem::F2 => each(data, big, |b| f16_to_f64(u16::from_le_bytes(b))),
        Elem::F4 => each(data, big, |b| f64::from(f32::from_le_bytes(b))),
        Elem::F8 => each(data, big, f64::from_le_bytes),
        Elem::I1 => each(data, big, |b: [u8; 1]| f64::from(b[0] as i8)),
        Elem::U1 => each(data, big, |b: [u8; 1]| f64::from(b[0])),
        Elem::I2 => each(data, big, |b| f64::from(i16::from_le_bytes(b))),
        Elem::U2 => each(data, big, |b| f64::from(u16::from_le_bytes(b))),
        Elem::I4 => each(data, big, |b| f64::from(i32::from_le_bytes(b))),
        Elem::U4 => each(data, big, |b| f64::from(u32::from_le_bytes(b))),
        Elem::I8 => each(data, big, |b| i64::from_le_bytes(b) as f64),
        Elem::U8 => each(data, big, |b| u64::from_le_bytes(b) as f64),
    };
    // Only 64-bit integers can exceed 2^53, beyond which not every integer is a double.
    const EXACT: f64 = 9_007_199_254_740_992.0;
    if matches!(elem, Elem::I8 | Elem::U8) {
        if let Some(k) = out.iter().position(|v| v.abs() > EXACT) {
            return Err(Error::malformed(
                path,
                format!("integer element {k} exceeds 2^53 and cannot be represented exactly"),
            ));
        }
    }
    Ok(out)
}

/// IEEE 754 binary16 to f64 (exact: every half is a double).
fn f16_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let frac = (h & 0x3ff) as f64;
    sign * match exp {
        0 => frac * 2f64.powi(-24),
        31 if frac == 0.0 => f64::INFINITY,
        31 => f64::NAN,
        e => (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    }
}

/// Reads a `.npy` file of any number of dimensions into an `f64` array in logical (C) order.
pub fn read_npy_nd(path: &Path) -> Result<(NpyHeader, ArrayD<f64>)> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_npy(path, &bytes)
}

/// Decodes the bytes of a whole `.npy` file (see [`read_npy_nd`]); `path` names it in errors.
pub fn decode_npy(path: &Path, bytes: &[u8]) -> Result<(NpyHeader, ArrayD<f64>)> {
    let h = parse_header(path, bytes)?;
    let (elem, big) = parse_descr(path, &h.descr)?;
    let count = h.shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
    let nbytes = count
        .and_then(|n| n.checked_mul(elem.size()))
        .ok_or_else(|| Error::malformed(path, format!("shape {:?} is too large to address", h.shape)))?;
    let have = bytes.len() - h.data_offset;
    if have < nbytes {
        return Err(Error::truncated(
            path,
            bytes.len() as u64,
            format!(
                "truncated data: expected {nbytes} bytes at offset {}, got {have} (shape {:?}, dtype '{}')",
                h.data_offset, h.shape, h.descr
            ),
        ));
    }
    if have > nbytes {
        return Err(Error::malformed(
            path,
            format!(
                "{} bytes follow the {nbytes} data bytes of shape {:?}, dtype '{}' (wrong shape?)",
                have - nbytes,
                h.shape,
                h.descr
            ),
        ));
    }
    let data = decode(path, &bytes[h.data_offset..], elem, big)?;
    let shape = IxDyn(&h.shape);
    let arr = if h.fortran_order {
        ArrayD::from_shape_vec(shape.f(), data)
    } else {
        ArrayD::from_shape_vec(shape, data)
    }
    .map_err(|e| Error::malformed(path, format!("data does not fit shape {:?}: {e}", h.shape)))?;
    let arr = if h.fortran_order { arr.as_standard_layout().into_owned() } else { arr };
    Ok((h, arr))
}

/// Reads a 2-D `.npy` map: shape `(H, W)` or `(H, W, 1)`; any other shape is refused.
/// Row `i` of the result is the first index of the file's array.
pub fn read_npy_2d(path: &Path) -> Result<Array2<f64>> {
    Ok(read_npy_checked(path)?.1)
}

fn read_npy_checked(path: &Path) -> Result<(NpyHeader, Array2<f64>)> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_npy_checked(path, &bytes)
}

fn decode_npy_checked(path: &Path, bytes: &[u8]) -> Result<(NpyHeader, Array2<f64>)> {
    let (h, arr) = decode_npy(path, bytes)?;
    let (rows, cols) = match h.shape.as_slice() {
        [r, c] | [r, c, 1] => (*r, *c),
        s => {
            return Err(Error::unsupported(
                path,
                format!("shape {} is not a 2-D map (expected (H, W) or (H, W, 1))", py_shape(s)),
            ))
        }
    };
    if rows == 0 || cols == 0 {
        return Err(Error::malformed(path, format!("the map is empty: shape {}", py_shape(&h.shape))));
    }
    let arr = arr
        .into_shape_with_order((rows, cols))
        .map_err(|e| Error::malformed(path, format!("cannot view as {rows} x {cols}: {e}")))?;
    Ok((h, arr))
}

/// Reads a `.npy` height map for [`crate::io::heightmap::read_heightmap`]. The format carries
/// neither pitch nor unit.
pub fn read_npy(path: &Path) -> Result<RawMap> {
    let (h, values) = read_npy_checked(path)?;
    Ok(raw_map(h, values))
}

/// Decodes the bytes of a whole `.npy` height map (what [`read_npy`] returns).
pub fn decode_npy_map(path: &Path, bytes: &[u8]) -> Result<RawMap> {
    let (h, values) = decode_npy_checked(path, bytes)?;
    Ok(raw_map(h, values))
}

fn raw_map(h: NpyHeader, values: Array2<f64>) -> RawMap {
    RawMap {
        values,
        kind: SampleKind::Float,
        pitch: None,
        unit: None,
        metadata: vec![
            ("descr".into(), h.descr),
            ("fortran_order".into(), if h.fortran_order { "True" } else { "False" }.into()),
        ],
        scale_hint: None,
    }
}

/// Bytes read (and handed to the hash) at a time by [`read_npy_hashed`].
const HASH_CHUNK: usize = 8 << 20;

/// Reads a `.npy` height map (what [`read_npy`] returns) together with the hex SHA-256 of the
/// whole file, reading the file once. A little-endian C-order `f8` map, the common case, is
/// read straight into its values while another thread hashes each chunk read; any other file
/// is read whole, then hashed on one thread while it is decoded on another.
pub fn read_npy_hashed(path: &Path) -> Result<(RawMap, String)> {
    if let Some(found) = read_f8_hashed(path)? {
        return Ok(found);
    }
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let (sha, raw) = rayon::join(|| crate::io::hex_sha256(&bytes), || decode_npy_map(path, &bytes));
    Ok((raw?, sha))
}

/// The fast path of [`read_npy_hashed`]: `None` when the file is not a plain 2-D
/// little-endian C-order `f8` map whose length matches its header (the general path then
/// reads it and reports what is wrong).
fn read_f8_hashed(path: &Path) -> Result<Option<(RawMap, String)>> {
    use sha2::{Digest, Sha256};
    use std::io::Read;
    if cfg!(target_endian = "big") {
        return Ok(None);
    }
    let io = |e| Error::io(path, e);
    let mut file = std::fs::File::open(path).map_err(io)?;
    let len = file.metadata().map_err(io)?.len();
    // Preamble: magic, version, header length (u16 for v1, u32 for v2 and v3).
    let mut head = vec![0u8; 12.min(len as usize)];
    file.read_exact(&mut head).map_err(io)?;
    if head.len() < 12 || &head[..6] != MAGIC {
        return Ok(None);
    }
    let hlen = match head[6] {
        1 => u16::from_le_bytes([head[8], head[9]]) as usize + 10,
        2 | 3 => u32::from_le_bytes([head[8], head[9], head[10], head[11]]) as usize + 12,
        _ => return Ok(None),
    };
    if hlen as u64 > len {
        return Ok(None);
    }
    let have = head.len();
    head.resize(hlen.max(have), 0);
    if hlen > have {
        file.read_exact(&mut head[have..]).map_err(io)?;
    }
    let Ok(h) = parse_header(path, &head) else { return Ok(None) };
    let (rows, cols) = match h.shape.as_slice() {
        [r, c] | [r, c, 1] => (*r, *c),
        _ => return Ok(None),
    };
    let plain = matches!(parse_descr(path, &h.descr), Ok((Elem::F8, false))) && !h.fortran_order;
    let count = rows.checked_mul(cols).filter(|&n| n > 0);
    let fits =
        |n: usize| n.checked_mul(8).and_then(|b| b.checked_add(h.data_offset)).map(|e| e as u64) == Some(len);
    let Some(count) = count.filter(|&n| plain && fits(n)) else {
        return Ok(None);
    };
    // The header bytes read past the preamble may already hold the first data bytes.
    let mut values = vec![0f64; count];
    let data: &mut [u8] = bytemuck::cast_slice_mut(&mut values);
    let early = have.saturating_sub(h.data_offset);
    data[..early].copy_from_slice(&head[h.data_offset..h.data_offset + early]);
    let mut hasher = Sha256::new();
    hasher.update(&head[..h.data_offset]);
    let read: std::io::Result<(bool, Sha256)> = std::thread::scope(|s| {
        let (tx, rx) = std::sync::mpsc::sync_channel::<&[u8]>(4);
        let hashing = s.spawn(move || {
            for chunk in rx {
                hasher.update(chunk);
            }
            hasher
        });
        let (first, rest) = data.split_at_mut(early);
        let mut result = Ok(true);
        if tx.send(&*first).is_ok() {
            for chunk in rest.chunks_mut(HASH_CHUNK) {
                if let Err(e) = file.read_exact(chunk) {
                    result = Err(e);
                    break;
                }
                if tx.send(&*chunk).is_err() {
                    break;
                }
            }
        }
        drop(tx);
        // A file that grew since its length was taken is read again by the general path.
        if let Ok(true) = result {
            result = file.read(&mut [0u8; 1]).map(|n| n == 0);
        }
        let hasher = hashing.join().map_err(|_| std::io::Error::other("the hashing thread failed"))?;
        result.map(|complete| (complete, hasher))
    });
    let (complete, hasher) = read.map_err(io)?;
    if !complete {
        return Ok(None);
    }
    let sha = hasher.finalize().iter().map(|b| format!("{b:02x}")).collect();
    let values = Array2::from_shape_vec((rows, cols), values)
        .map_err(|e| Error::malformed(path, format!("data does not fit shape ({rows}, {cols}): {e}")))?;
    Ok(Some((raw_map(h, values), sha)))
}

/// Element types the writer can store.
pub trait NpyElement: Copy {
    /// The NumPy dtype string, little endian.
    const DESCR: &'static str;
    /// Appends the little-endian bytes of `self`.
    fn put(self, out: &mut Vec<u8>);
}

macro_rules! npy_element {
    ($t:ty, $d:literal) => {
        impl NpyElement for $t {
            const DESCR: &'static str = $d;
            fn put(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
        }
    };
}
npy_element!(f64, "<f8");
npy_element!(f32, "<f4");
npy_element!(u8, "|u1");
npy_element!(i8, "|i1");
npy_element!(u16, "<u2");
npy_element!(i16, "<i2");
npy_element!(u32, "<u4");
npy_element!(i32, "<i4");
npy_element!(i64, "<i8");
npy_element!(u64, "<u8");

/// Python's `repr` of a shape tuple: `(3,)`, `(3, 4)`.
fn py_shape(shape: &[usize]) -> String {
    match shape {
        [d] => format!("({d},)"),
        s => format!("({})", s.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ")),
    }
}

/// The preamble and header `numpy.save` writes for a C-order array of `shape` and dtype `descr`
/// (format 1.0; 2.0 only if the header exceeds 65535 bytes).
pub fn header_bytes(descr: &str, shape: &[usize]) -> Vec<u8> {
    let mut text = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {}, }}", py_shape(shape));
    // numpy leaves room for the first axis to grow to 21 digits.
    if let Some(d0) = shape.first() {
        text.push_str(&" ".repeat(21usize.saturating_sub(d0.to_string().len())));
    }
    let hlen = text.len() + 1;
    let (prefix_len, v1) = if hlen + 10 + 64 <= u16::MAX as usize { (10, true) } else { (12, false) };
    let pad = 64 - ((prefix_len + hlen) % 64);
    let total = hlen + pad;
    let mut out = Vec::with_capacity(prefix_len + total);
    out.extend_from_slice(MAGIC);
    if v1 {
        out.extend_from_slice(&[1, 0]);
        out.extend_from_slice(&(total as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&[2, 0]);
        out.extend_from_slice(&(total as u32).to_le_bytes());
    }
    out.extend_from_slice(text.as_bytes());
    out.extend(std::iter::repeat_n(b' ', pad));
    out.push(b'\n');
    out
}

/// Writes any array as `.npy` (C order, little endian), atomically. The bytes equal what
/// `numpy.save` writes for the same array.
pub fn write_npy<T, S, D>(path: &Path, array: &ArrayBase<S, D>) -> Result<()>
where
    T: NpyElement,
    S: Data<Elem = T>,
    D: Dimension,
{
    let header = header_bytes(T::DESCR, array.shape());
    write_atomic(path, |w: &mut dyn Write| {
        w.write_all(&header).map_err(|e| Error::io(path, e))?;
        let mut buf = Vec::with_capacity(1 << 16);
        // `iter` walks the logical (row-major) order whatever the memory layout.
        for &v in array.iter() {
            v.put(&mut buf);
            if buf.len() >= (1 << 16) {
                w.write_all(&buf).map_err(|e| Error::io(path, e))?;
                buf.clear();
            }
        }
        w.write_all(&buf).map_err(|e| Error::io(path, e))
    })
}

/// Writes a 2-D `f64` map as `.npy` (`<f8`, shape `(H, W)`).
pub fn write_npy_f64(path: &Path, array: &Array2<f64>) -> Result<()> {
    write_npy(path, array)
}

/// Writes a 2-D `f32` map as `.npy` (`<f4`, shape `(H, W)`).
pub fn write_npy_f32(path: &Path, array: &Array2<f32>) -> Result<()> {
    write_npy(path, array)
}

/// Writes a 4-D `f32` array as `.npy`, typically a PSF stack in the layout `(H, W, 1, C)`
/// (rows, columns, one depth plane, colour channels).
pub fn write_npy_f32_4d(path: &Path, array: &ndarray::Array4<f32>) -> Result<()> {
    write_npy(path, array)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{Array3, Array4};

    fn raw_npy(descr: &str, fortran: bool, shape: &str, data: &[u8], version: u8) -> Vec<u8> {
        let text = format!(
            "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}\n",
            if fortran { "True" } else { "False" }
        );
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&[version, 0]);
        if version == 1 {
            out.extend_from_slice(&(text.len() as u16).to_le_bytes());
        } else {
            out.extend_from_slice(&(text.len() as u32).to_le_bytes());
        }
        out.extend_from_slice(text.as_bytes());
        out.extend_from_slice(data);
        out
    }

    fn decode2(bytes: &[u8]) -> Result<ArrayD<f64>> {
        decode_npy(Path::new("t.npy"), bytes).map(|(_, a)| a)
    }

    #[test]
    fn reads_c_and_fortran_order_in_all_versions() {
        // Logical array [[1, 2, 3], [4, 5, 6]].
        let c: Vec<u8> = [1.0f64, 2.0, 3.0, 4.0, 5.0, 6.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let f: Vec<u8> = [1.0f64, 4.0, 2.0, 5.0, 3.0, 6.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        for v in [1, 2, 3] {
            let a = decode2(&raw_npy("<f8", false, "(2, 3)", &c, v)).unwrap();
            let b = decode2(&raw_npy("<f8", true, "(2, 3)", &f, v)).unwrap();
            assert_eq!(a, b);
            assert_eq!(a[[1, 0]], 4.0);
            assert_eq!(a[[0, 2]], 3.0);
        }
    }

    #[test]
    fn reads_big_endian_and_integers() {
        let be: Vec<u8> = [1.5f32, -2.25].iter().flat_map(|v| v.to_be_bytes()).collect();
        let a = decode2(&raw_npy(">f4", false, "(1, 2)", &be, 1)).unwrap();
        assert_eq!(a.as_slice().unwrap(), &[1.5, -2.25]);
        let be8: Vec<u8> = [1e-7f64, 3.0].iter().flat_map(|v| v.to_be_bytes()).collect();
        assert_eq!(
            decode2(&raw_npy(">f8", false, "(2,)", &be8, 1)).unwrap().as_slice().unwrap(),
            &[1e-7, 3.0]
        );
        let u2: Vec<u8> = [0u16, 65535].iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_eq!(
            decode2(&raw_npy("<u2", false, "(2,)", &u2, 1)).unwrap().as_slice().unwrap(),
            &[0.0, 65535.0]
        );
        let i2: Vec<u8> = [-3i16, 7].iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_eq!(
            decode2(&raw_npy("<i2", false, "(2,)", &i2, 1)).unwrap().as_slice().unwrap(),
            &[-3.0, 7.0]
        );
        let i4: Vec<u8> = [-70000i32, 5].iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_eq!(
            decode2(&raw_npy("<i4", false, "(2,)", &i4, 1)).unwrap().as_slice().unwrap(),
            &[-70000.0, 5.0]
        );
        let u4: Vec<u8> = [4_000_000_000u32, 1].iter().flat_map(|v| v.to_le_bytes()).collect();
        assert_eq!(decode2(&raw_npy("<u4", false, "(2,)", &u4, 1)).unwrap().as_slice().unwrap(), &[4e9, 1.0]);
        assert_eq!(
            decode2(&raw_npy("|u1", false, "(2,)", &[7, 255], 1)).unwrap().as_slice().unwrap(),
            &[7.0, 255.0]
        );
        assert_eq!(
            decode2(&raw_npy("<u1", false, "(2,)", &[7, 255], 1)).unwrap().as_slice().unwrap(),
            &[7.0, 255.0]
        );
        let big = (1u64 << 60).to_le_bytes();
        assert!(decode2(&raw_npy("<u8", false, "(1,)", &big, 1)).unwrap_err().to_string().contains("2^53"));
    }

    #[test]
    fn half_floats_decode_exactly() {
        assert_eq!(f16_to_f64(0x3c00), 1.0);
        assert_eq!(f16_to_f64(0xc000), -2.0);
        assert_eq!(f16_to_f64(0x0001), 2f64.powi(-24));
        assert_eq!(f16_to_f64(0x7bff), 65504.0);
        assert!(f16_to_f64(0x7e00).is_nan());
        assert_eq!(f16_to_f64(0xfc00), f64::NEG_INFINITY);
    }

    #[test]
    fn errors_name_what_failed() {
        let p = Path::new("t.npy");
        let d: Vec<u8> = [1.0f64; 6].iter().flat_map(|v| v.to_le_bytes()).collect();
        let good = raw_npy("<f8", false, "(2, 3)", &d, 1);
        let e = decode2(&good[..good.len() - 5]).unwrap_err().to_string();
        assert!(e.contains("t.npy") && e.contains("expected 48 bytes") && e.contains("got 43"), "{e}");
        let mut bad = good.clone();
        bad[1] = b'X';
        assert!(decode2(&bad).unwrap_err().to_string().contains("bad magic"));
        let e = decode2(
            &raw_npy("<f8", false, "(2, 3)", &d, 1).iter().copied().chain([0u8; 8]).collect::<Vec<_>>(),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("8 bytes follow"), "{e}");
        let text = b"{'descr': '<f8', 'shape': (2, 3), }\n";
        let mut m = MAGIC.to_vec();
        m.extend_from_slice(&[1, 0, text.len() as u8, 0]);
        m.extend_from_slice(text);
        m.extend_from_slice(&d);
        let e = decode2(&m).unwrap_err().to_string();
        assert!(e.contains("'fortran_order' is missing"), "{e}");
        let e = decode2(&raw_npy("<c16", false, "(1,)", &[0; 16], 1)).unwrap_err().to_string();
        assert!(e.contains("'<c16' is not supported"), "{e}");
        assert!(parse_header(p, b"\x93NUM").unwrap_err().to_string().contains("preamble"));
        // Every cut of a valid file is an error, never a panic.
        for cut in 0..good.len() {
            assert!(decode2(&good[..cut]).is_err(), "cut at {cut}");
        }
    }

    #[test]
    fn hashed_read_equals_read_and_file_hash() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.npy");
        let mut vals: Vec<f64> = (0..2 * 3).map(|k| k as f64 * 1.5e-7 - 2e-7).collect();
        vals[4] = f64::NAN;
        let d: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
        let f4: Vec<u8> = vals.iter().flat_map(|v| (*v as f32).to_le_bytes()).collect();
        let fd: Vec<u8> = [1.0f64, 4.0, 2.0, 5.0, 3.0, 6.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        // The fast path (plain f8, versions 1-3, a (H, W, 1) shape), and the general one (f4,
        // Fortran order, big endian) and the errors of cut, overlong and tiny files.
        let mut files = vec![
            raw_npy("<f8", false, "(2, 3)", &d, 1),
            raw_npy("<f8", false, "(2, 3)", &d, 2),
            raw_npy("<f8", false, "(2, 3, 1)", &d, 3),
            raw_npy("<f4", false, "(2, 3)", &f4, 1),
            raw_npy("<f8", true, "(2, 3)", &fd, 1),
            raw_npy(
                ">f8",
                false,
                "(2, 3)",
                &vals.iter().flat_map(|v| v.to_be_bytes()).collect::<Vec<_>>(),
                1,
            ),
        ];
        files.push(files[0][..files[0].len() - 3].to_vec());
        files.push(files[0].iter().copied().chain([0u8; 8]).collect());
        files.push(files[0][..7].to_vec());
        for (k, bytes) in files.iter().enumerate() {
            std::fs::write(&p, bytes).unwrap();
            match (read_npy(&p), read_npy_hashed(&p)) {
                (Ok(a), Ok((b, sha))) => {
                    assert_eq!(format!("{:?}", a), format!("{:?}", b), "file {k}");
                    assert_eq!(sha, crate::io::file_sha256(&p).unwrap(), "file {k}");
                }
                (Err(a), Err(b)) => assert_eq!(a.to_string(), b.to_string(), "file {k}"),
                (a, b) => panic!("file {k}: {a:?} against {b:?}"),
            }
        }
        // A file larger than one read chunk.
        let big: Vec<f64> = (0..(HASH_CHUNK / 8 + 1000)).map(|k| k as f64).collect();
        let a = Array2::from_shape_vec((big.len() / 8, 8), big).unwrap();
        write_npy_f64(&p, &a).unwrap();
        let (raw, sha) = read_npy_hashed(&p).unwrap();
        assert_eq!(raw.values, a);
        assert_eq!(sha, crate::io::file_sha256(&p).unwrap());
    }

    #[test]
    fn header_matches_numpy_layout() {
        let h = header_bytes("<f8", &[3, 4]);
        assert_eq!(h.len() % 64, 0);
        let text = std::str::from_utf8(&h[10..]).unwrap();
        assert!(text.starts_with("{'descr': '<f8', 'fortran_order': False, 'shape': (3, 4), }"));
        assert!(text.ends_with(" \n"));
        let h1 = header_bytes("<f4", &[5]);
        assert!(std::str::from_utf8(&h1[10..]).unwrap().contains("'shape': (5,), }"));
    }

    #[test]
    fn round_trips_f64_f32_and_4d() {
        let dir = tempfile::tempdir().unwrap();
        let a = Array2::from_shape_fn((3, 5), |(i, j)| (i as f64 - 1.3) * 1e-7 + j as f64 * 1.0e-9);
        let p = dir.path().join("a.npy");
        write_npy_f64(&p, &a).unwrap();
        assert_eq!(read_npy_2d(&p).unwrap(), a);
        let b = a.mapv(|v| v as f32);
        write_npy_f32(&p, &b).unwrap();
        assert_eq!(read_npy_2d(&p).unwrap(), b.mapv(|v| v as f64));
        // A transposed (Fortran-layout) view is written in logical order.
        write_npy(&p, &a.t()).unwrap();
        assert_eq!(read_npy_2d(&p).unwrap(), a.t());
        let c = Array4::from_shape_fn((4, 3, 1, 2), |(i, j, _, k)| (i * 100 + j * 10 + k) as f32);
        let q = dir.path().join("psf.npy");
        write_npy_f32_4d(&q, &c).unwrap();
        let (h, back) = read_npy_nd(&q).unwrap();
        assert_eq!(h.shape, vec![4, 3, 1, 2]);
        assert_eq!(back[[3, 2, 0, 1]], 321.0);
        assert_eq!(back.mapv(|v| v as f32), c.into_dyn());
        // (H, W, 1) reads as a map, (H, W, 2) is refused.
        write_npy(&q, &Array3::from_elem((2, 3, 1), 1.5f64)).unwrap();
        assert_eq!(read_npy_2d(&q).unwrap().dim(), (2, 3));
        write_npy(&q, &Array3::from_elem((2, 3, 2), 1.5f64)).unwrap();
        let e = read_npy_2d(&q).unwrap_err().to_string();
        assert!(e.contains("(2, 3, 2)") && e.contains("not a 2-D map"), "{e}");
    }
}
