//! OpenEXR scan-line files decoded here, channel sampling included: the reader for what the
//! `exr` crate refuses (it rejects every channel whose x or y sampling is not 1, and its PIZ and
//! B44 code would lay such channels out wrongly), i.e. the luminance/chroma files of
//! [`super::yca`].
//!
//! The layout is the OpenEXR file format's ("OpenEXR File Layout", openexr.com): a header of
//! attributes, a table of chunk offsets, then chunks of `L` scan lines (`L` = 1 for NONE, RLE
//! and ZIPS, 16 for ZIP, 32 for PIZ, B44 and B44A), each `y: i32, size: i32, data`. Within a
//! chunk, uncompressed, the lines follow each other; in each line the channels in header order
//! (sorted by name), each with the samples of the line that it holds, little-endian. A channel
//! with sampling `(sx, sy)` holds samples only at the pixels `(x, y)` with `x mod sx = 0` and
//! `y mod sy = 0` (OpenEXR's `numSamples`: the multiples of `s` in `[a, b]`).
//!
//! A chunk whose data are not shorter than its raw size is stored raw (as OpenEXR writes it).
//! The decompressors follow OpenEXR's (`ImfRleCompressor.cpp`, `ImfZipCompressor.cpp`,
//! `ImfB44Compressor.cpp`; BSD-3-Clause, Contributors to the OpenEXR Project), PIZ in
//! `exr/piz.rs`. PXR24, DWAA and DWAB are refused by name (no luminance/chroma file here uses
//! them); tiled, deep and multi-part files are refused.

use std::path::Path;

use super::chunk::{num_samples, planar_to_lines, ChunkChannel};
use crate::error::{Error, Result};

/// How a channel's samples are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelType {
    /// 32-bit unsigned integers (type code 0; refused as image data).
    Uint,
    /// 16-bit IEEE half floats (type code 1).
    Half,
    /// 32-bit IEEE floats (type code 2).
    Float,
}

impl PixelType {
    fn bytes(self) -> usize {
        match self {
            PixelType::Half => 2,
            PixelType::Uint | PixelType::Float => 4,
        }
    }
}

/// One entry of the header's channel list.
#[derive(Debug, Clone, PartialEq)]
pub struct Channel {
    /// Channel name (`Y`, `RY`, `R`, ...).
    pub name: String,
    /// How the samples are stored.
    pub pixel_type: PixelType,
    /// `pLinear`: the values are perceptually linear (B44 then stores them on a log scale).
    pub linear: bool,
    /// Horizontal sampling, pixels (at least 1): samples sit at the `x` divisible by it.
    pub x_sampling: i32,
    /// Vertical sampling, pixels (at least 1): samples sit at the `y` divisible by it.
    pub y_sampling: i32,
}

/// The header fields this reader needs (of a single-part file: the first header otherwise).
#[derive(Debug, Clone, PartialEq)]
pub struct Header {
    /// The `channels` attribute, in file order (sorted by name).
    pub channels: Vec<Channel>,
    /// OpenEXR's compression code: 0 NONE, 1 RLE, 2 ZIPS, 3 ZIP, 4 PIZ, 5 PXR24, 6 B44, 7 B44A,
    /// 8 DWAA, 9 DWAB.
    pub compression: u8,
    /// `[x_min, y_min, x_max, y_max]`, inclusive.
    pub data_window: [i32; 4],
    /// The `chromaticities` attribute: CIE x, y of red, green, blue and white.
    pub chromaticities: Option<[f32; 8]>,
    /// The file is tiled (version flag 0x200 or a `tiles` attribute); refused by the reader.
    pub tiled: bool,
    /// The file holds deep data (version flag 0x800); refused by the reader.
    pub deep: bool,
    /// The file has several parts (version flag 0x1000); refused by the reader.
    pub multipart: bool,
    /// Where the chunk offset table starts.
    offsets_at: usize,
}

/// One channel's samples: `rows x cols`, row-major, row 0 at the top. Half and float samples
/// are exact in `f32`.
#[derive(Debug, Clone, PartialEq)]
pub struct Plane {
    /// Sampled lines of the data window (its height for a sampling of 1).
    pub rows: usize,
    /// Samples per line (the window's width for a sampling of 1).
    pub cols: usize,
    /// The `rows x cols` samples, row-major.
    pub values: Vec<f32>,
}

const COMPRESSION_NAMES: [&str; 10] =
    ["NONE", "RLE", "ZIPS", "ZIP", "PIZ", "PXR24", "B44", "B44A", "DWAA", "DWAB"];

/// The name of an OpenEXR compression code.
pub fn compression_name(code: u8) -> String {
    COMPRESSION_NAMES.get(code as usize).map_or_else(|| format!("unknown ({code})"), |s| s.to_string())
}

/// A little-endian reader over a byte slice that names the file in its errors.
struct Reader<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8]> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.bytes.len()).ok_or_else(|| {
            Error::truncated(
                self.path,
                self.bytes.len() as u64,
                format!("OpenEXR: the file ends inside {what} (at byte {})", self.pos),
            )
        })?;
        let s = &self.bytes[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn i32(&mut self, what: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.take(4, what)?.try_into().expect("4 bytes")))
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8, what)?.try_into().expect("8 bytes")))
    }
    /// A zero-terminated name of at most `max` bytes.
    fn name(&mut self, max: usize, what: &str) -> Result<String> {
        let rest = &self.bytes[self.pos.min(self.bytes.len())..];
        let n = rest.iter().take(max + 1).position(|&b| b == 0).ok_or_else(|| {
            Error::malformed(
                self.path,
                format!("OpenEXR: {what} at byte {} is not a name of at most {max} bytes", self.pos),
            )
        })?;
        let s = rest[..n].iter().map(|&b| b as char).collect();
        self.pos += n + 1;
        Ok(s)
    }
}

impl Header {
    /// Parses the header of an OpenEXR file (magic, version, attributes).
    pub fn parse(path: &Path, bytes: &[u8]) -> Result<Header> {
        if bytes.len() < 8 || bytes[..4] != [0x76, 0x2f, 0x31, 0x01] {
            return Err(Error::signature(path, "not an OpenEXR file: bad magic (expected 76 2f 31 01)"));
        }
        let version = u32::from_le_bytes(bytes[4..8].try_into().expect("4 bytes"));
        if version & 0xff != 2 {
            return Err(Error::unsupported(
                path,
                format!("OpenEXR: format version {}, expected 2", version & 0xff),
            ));
        }
        let max_name = if version & 0x400 != 0 { 255 } else { 31 };
        let mut r = Reader { path, bytes, pos: 8 };
        let mut channels = None;
        let (mut compression, mut data_window, mut chromaticities, mut tiles) = (None, None, None, false);
        loop {
            let name = r.name(max_name, "an attribute name")?;
            if name.is_empty() {
                break;
            }
            let kind = r.name(max_name, "an attribute type")?;
            let size = r.i32("an attribute size")?;
            let size = usize::try_from(size).map_err(|_| {
                Error::malformed(path, format!("OpenEXR: attribute '{name}' has size {size}"))
            })?;
            let value = r.take(size, &format!("attribute '{name}'"))?;
            let bad = |expected: &str| {
                Error::malformed(
                    path,
                    format!("OpenEXR: attribute '{name}' is a {size}-byte {kind}, expected {expected}"),
                )
            };
            match name.as_str() {
                "channels" if kind == "chlist" => channels = Some(parse_channels(path, value, max_name)?),
                "compression" if kind == "compression" && size == 1 => compression = Some(value[0]),
                "dataWindow" if kind == "box2i" && size == 16 => {
                    let v: Vec<i32> =
                        value.chunks(4).map(|c| i32::from_le_bytes(c.try_into().expect("4 bytes"))).collect();
                    data_window = Some([v[0], v[1], v[2], v[3]]);
                }
                "chromaticities" if kind == "chromaticities" && size == 32 => {
                    let mut c = [0f32; 8];
                    for (k, v) in value.chunks(4).enumerate() {
                        c[k] = f32::from_le_bytes(v.try_into().expect("4 bytes"));
                    }
                    chromaticities = Some(c);
                }
                "tiles" => tiles = true,
                "channels" => return Err(bad("a chlist")),
                "compression" => return Err(bad("a 1-byte compression")),
                "dataWindow" => return Err(bad("a 16-byte box2i")),
                "chromaticities" => return Err(bad("32 bytes of chromaticities")),
                _ => {}
            }
        }
        let missing =
            |what: &str| Error::malformed(path, format!("OpenEXR: the header has no '{what}' attribute"));
        let channels: Vec<Channel> = channels.ok_or_else(|| missing("channels"))?;
        let data_window = data_window.ok_or_else(|| missing("dataWindow"))?;
        let [x0, y0, x1, y1] = data_window;
        if x1 < x0 || y1 < y0 {
            return Err(Error::malformed(path, format!("OpenEXR: the data window {data_window:?} is empty")));
        }
        Ok(Header {
            channels,
            compression: compression.ok_or_else(|| missing("compression"))?,
            data_window,
            chromaticities,
            tiled: version & 0x200 != 0 || tiles,
            deep: version & 0x800 != 0,
            multipart: version & 0x1000 != 0,
            offsets_at: r.pos,
        })
    }

    /// Width of the data window, pixels.
    pub fn width(&self) -> usize {
        (self.data_window[2] as i64 - self.data_window[0] as i64 + 1) as usize
    }

    /// Height of the data window, pixels.
    pub fn height(&self) -> usize {
        (self.data_window[3] as i64 - self.data_window[1] as i64 + 1) as usize
    }

    /// The channel named `name`, `None` where the file has none.
    pub fn channel(&self, name: &str) -> Option<&Channel> {
        self.channels.iter().find(|c| c.name == name)
    }

    /// Scan lines per chunk of this compression (`None`: a code this reader does not decode).
    fn lines_per_chunk(&self) -> Option<usize> {
        match self.compression {
            0..=2 => Some(1),
            3 => Some(16),
            4 | 6 | 7 => Some(32),
            _ => None,
        }
    }
}

/// Checks, in file order, every channel-list attribute of a single-part header other than
/// `channels` (which [`Header::parse`] reads): each must list at least one channel, each with a
/// sampling of at least 1. A header this walk cannot read is left to the caller's decoder.
pub(crate) fn check_custom_channel_lists(path: &Path, bytes: &[u8]) -> Result<()> {
    let Some(version) = bytes.get(4..8).map(|v| u32::from_le_bytes(v.try_into().expect("4 bytes"))) else {
        return Ok(());
    };
    let max_name = if version & 0x400 != 0 { 255 } else { 31 };
    let mut r = Reader { path, bytes, pos: 8 };
    while let Ok(Some((name, kind, value))) = next_attribute(&mut r, max_name) {
        if kind == "chlist" && name != "channels" && parse_channels(path, value, max_name)?.is_empty() {
            return Err(Error::malformed(
                path,
                format!("OpenEXR: attribute '{name}' is an empty channel list"),
            ));
        }
    }
    Ok(())
}

/// The next attribute of a header (name, type, value), `None` at the header's end.
fn next_attribute<'a>(r: &mut Reader<'a>, max_name: usize) -> Result<Option<(String, String, &'a [u8])>> {
    let name = r.name(max_name, "an attribute name")?;
    if name.is_empty() {
        return Ok(None);
    }
    let kind = r.name(max_name, "an attribute type")?;
    let size = usize::try_from(r.i32("an attribute size")?).unwrap_or(usize::MAX);
    Ok(Some((name, kind, r.take(size, "an attribute")?)))
}

fn parse_channels(path: &Path, value: &[u8], max_name: usize) -> Result<Vec<Channel>> {
    let mut r = Reader { path, bytes: value, pos: 0 };
    let mut out = Vec::new();
    loop {
        let name = r.name(max_name, "a channel name")?;
        if name.is_empty() {
            return Ok(out);
        }
        let pixel_type = match r.i32("a channel's pixel type")? {
            0 => PixelType::Uint,
            1 => PixelType::Half,
            2 => PixelType::Float,
            t => {
                return Err(Error::malformed(
                    path,
                    format!("OpenEXR: channel '{name}' has pixel type {t}, expected 0, 1 or 2"),
                ))
            }
        };
        let linear = r.take(4, "a channel's pLinear byte")?[0] != 0;
        let (x_sampling, y_sampling) = (r.i32("a channel's x sampling")?, r.i32("a channel's y sampling")?);
        if x_sampling < 1 || y_sampling < 1 {
            return Err(Error::malformed(
                path,
                format!("OpenEXR: channel '{name}' has sampling {x_sampling} x {y_sampling}, expected >= 1"),
            ));
        }
        out.push(Channel { name, pixel_type, linear, x_sampling, y_sampling });
    }
}

/// Reads the named channels of a scan-line file (each at its own sampling), in the order asked.
pub fn read_channels(path: &Path, bytes: &[u8], header: &Header, names: &[&str]) -> Result<Vec<Plane>> {
    let fail = |what: String| Error::malformed(path, format!("OpenEXR: {what}"));
    let unsupported = |what: String| Error::unsupported(path, format!("OpenEXR: {what}"));
    if header.tiled || header.deep || header.multipart {
        return Err(unsupported(
            "a tiled, deep or multi-part file; this reader decodes single-part scan-line files".into(),
        ));
    }
    let lines = header.lines_per_chunk().ok_or_else(|| {
        unsupported(format!(
            "{} compression; this reader decodes NONE, RLE, ZIPS, ZIP, PIZ, B44 and B44A",
            compression_name(header.compression)
        ))
    })?;
    let [x0, y0, x1, y1] = header.data_window;
    let (w, h) = (header.width(), header.height());
    // OpenEXR's header check: a subsampled channel's samples tile the window exactly.
    for c in &header.channels {
        let (sx, sy) = (c.x_sampling as i64, c.y_sampling as i64);
        let off = |v: i64, s: i64| v.rem_euclid(s) != 0;
        if off(x0 as i64, sx) || off(w as i64, sx) || off(y0 as i64, sy) || off(h as i64, sy) {
            return Err(fail(format!(
                "channel '{}' is sampled {sx} x {sy}, but the data window starts at ({x0}, {y0}) and is {w} x {h} \
                 pixels; OpenEXR requires its origin and size to be multiples of the sampling",
                c.name
            )));
        }
    }
    let chans: Vec<ChunkChannel> = header
        .channels
        .iter()
        .map(|c| ChunkChannel {
            bytes: c.pixel_type.bytes(),
            nx: num_samples(c.x_sampling, x0, x1),
            ys: c.y_sampling,
            half: c.pixel_type == PixelType::Half,
            linear: c.linear,
        })
        .collect();
    let raw_total: usize = chans.iter().map(|c| c.nx * num_samples(c.ys, y0, y1) * c.bytes).sum();
    // The planes are reserved from the header: refuse a window the file cannot hold (deflate
    // compresses at most 1032:1, RFC 1951; PIZ's run-length codes at most 255 samples in a
    // byte and a half).
    if w.saturating_mul(h) > 1 << 28 || raw_total / (1032 * 64) > bytes.len() {
        return Err(fail(format!(
            "the data window is {w} x {h} pixels ({raw_total} bytes of samples), more than a {}-byte file can hold",
            bytes.len()
        )));
    }
    let wanted: Vec<usize> = names
        .iter()
        .map(|n| {
            let k = header
                .channels
                .iter()
                .position(|c| c.name == *n)
                .ok_or_else(|| fail(format!("no channel '{n}'")))?;
            if header.channels[k].pixel_type == PixelType::Uint {
                return Err(unsupported(format!(
                    "channel '{n}' holds u32 integers, expected half or float samples"
                )));
            }
            Ok(k)
        })
        .collect::<Result<_>>()?;
    let mut planes: Vec<Plane> = header
        .channels
        .iter()
        .enumerate()
        .map(|(k, c)| {
            let (rows, cols) = (num_samples(c.y_sampling, y0, y1), chans[k].nx);
            let values = if wanted.contains(&k) { vec![0f32; rows * cols] } else { Vec::new() };
            Plane { rows, cols, values }
        })
        .collect();

    let chunks = h.div_ceil(lines);
    let mut table = Reader { path, bytes, pos: header.offsets_at };
    let offsets: Vec<u64> =
        (0..chunks).map(|_| table.u64("the chunk offset table")).collect::<Result<_>>()?;
    for (k, &offset) in offsets.iter().enumerate() {
        let first = y0 as i64 + (k * lines) as i64;
        let last = (first + lines as i64 - 1).min(y1 as i64);
        let mut r = Reader { path, bytes, pos: usize::try_from(offset).unwrap_or(usize::MAX) };
        let y = r.i32(&format!("chunk {k}"))?;
        if y as i64 != first {
            return Err(fail(format!("chunk {k} starts at line {y}, expected {first}")));
        }
        let size = r.i32(&format!("chunk {k}"))?;
        let size = usize::try_from(size).map_err(|_| fail(format!("chunk {k} has size {size}")))?;
        let data = r.take(size, &format!("chunk {k}"))?;
        let (first, last) = (first as i32, last as i32);
        let raw_size: usize = chans.iter().map(|c| c.nx * num_samples(c.ys, first, last) * c.bytes).sum();
        let raw = match size.cmp(&raw_size) {
            std::cmp::Ordering::Equal => data.to_vec(),
            std::cmp::Ordering::Greater => {
                return Err(fail(format!("chunk {k} holds {size} bytes, more than its {raw_size} raw bytes")))
            }
            std::cmp::Ordering::Less => {
                let out = match header.compression {
                    1 => unrle(data, raw_size).map(predict_and_interleave),
                    2 | 3 => miniz_oxide::inflate::decompress_to_vec_zlib_with_limit(data, raw_size)
                        .map_err(|e| format!("zlib: {:?}", e.status))
                        .map(predict_and_interleave),
                    4 => super::piz::decompress(data, &chans, first, last, raw_size),
                    6 | 7 => unb44(data, &chans, first, last),
                    c => Err(format!("{} chunk stored compressed", compression_name(c))),
                };
                let out = out.map_err(|e| {
                    fail(format!("chunk {k} ({}): {e}", compression_name(header.compression)))
                })?;
                if out.len() != raw_size {
                    return Err(fail(format!(
                        "chunk {k} decompresses to {} bytes, expected {raw_size}",
                        out.len()
                    )));
                }
                out
            }
        };
        // Scatter the chunk's lines into the planes.
        let mut pos = 0;
        for y in first..=last {
            for (c, ch) in chans.iter().enumerate() {
                if y.rem_euclid(ch.ys) != 0 {
                    continue;
                }
                let n = ch.nx * ch.bytes;
                if wanted.contains(&c) {
                    let row = num_samples(ch.ys, y0, y) - 1;
                    let plane = &mut planes[c];
                    let dst = &mut plane.values[row * plane.cols..(row + 1) * plane.cols];
                    for (d, s) in dst.iter_mut().zip(raw[pos..pos + n].chunks(ch.bytes)) {
                        *d = match ch.half {
                            true => half::f16::from_bits(u16::from_le_bytes([s[0], s[1]])).to_f32(),
                            false => f32::from_le_bytes([s[0], s[1], s[2], s[3]]),
                        };
                    }
                }
                pos += n;
            }
        }
    }
    let mut planes: Vec<Option<Plane>> = planes.into_iter().map(Some).collect();
    Ok(wanted.iter().map(|&k| planes[k].take().expect("each channel asked once")).collect())
}

/// OpenEXR's run-length decoding (`rleUncompress`): a signed count byte `n`; `n < 0`: `-n`
/// literal bytes follow; `n >= 0`: the next byte repeats `n + 1` times.
fn unrle(data: &[u8], max: usize) -> std::result::Result<Vec<u8>, String> {
    let mut out = Vec::with_capacity(max);
    let mut i = 0;
    while i < data.len() {
        let n = data[i] as i8;
        i += 1;
        if n < 0 {
            let n = -(n as i32) as usize;
            let lit = data.get(i..i + n).ok_or("a literal run passes the end of the data")?;
            out.extend_from_slice(lit);
            i += n;
        } else {
            let v = *data.get(i).ok_or("a repeat run has no value")?;
            out.resize(out.len() + n as usize + 1, v);
            i += 1;
        }
        if out.len() > max {
            return Err("runs longer than the chunk".into());
        }
    }
    Ok(out)
}

/// Undoes RLE's and ZIP's byte predictor (`t[i] = t[i-1] + t[i] - 128`) and their split of the
/// bytes into even and odd halves.
fn predict_and_interleave(mut t: Vec<u8>) -> Vec<u8> {
    for i in 1..t.len() {
        t[i] = t[i - 1].wrapping_add(t[i]).wrapping_sub(128);
    }
    let half = t.len().div_ceil(2);
    let mut out = Vec::with_capacity(t.len());
    for i in 0..half {
        out.push(t[i]);
        if half + i < t.len() {
            out.push(t[half + i]);
        }
    }
    out
}

/// B44 and B44A (OpenEXR's `B44Compressor::uncompress`): each half channel of the chunk, in
/// header order, as blocks of 4 x 4 samples (its `nx` x `ny` samples padded to multiples of
/// 4), 14 bytes a block, or 3 bytes for a block of one value; `pLinear` channels stored on a
/// log scale. Float and uint channels are stored raw. Returns the chunk in the line layout.
fn unb44(data: &[u8], chans: &[ChunkChannel], first: i32, last: i32) -> std::result::Result<Vec<u8>, String> {
    let mut planar: Vec<Vec<u16>> = Vec::with_capacity(chans.len());
    let mut pos = 0;
    for ch in chans {
        let ny = num_samples(ch.ys, first, last);
        let n = ch.nx * ny * ch.bytes / 2;
        if !ch.half {
            let raw = data.get(pos..pos + 2 * n).ok_or("a float channel runs past the data")?;
            planar.push(raw.chunks(2).map(|b| u16::from_le_bytes([b[0], b[1]])).collect());
            pos += 2 * n;
            continue;
        }
        let mut v = vec![0u16; n];
        for by in (0..ny).step_by(4) {
            for bx in (0..ch.nx).step_by(4) {
                let flag = *data.get(pos + 2).ok_or("a block runs past the data")?;
                let s = if flag >= 13 << 2 {
                    let s = unpack3(&data[pos..pos + 3]);
                    pos += 3;
                    s
                } else {
                    let s = unpack14(data.get(pos..pos + 14).ok_or("a block runs past the data")?);
                    pos += 14;
                    s
                };
                let s = match ch.linear {
                    true => s.map(|x| log_table()[x as usize]),
                    false => s,
                };
                for dy in 0..4.min(ny - by) {
                    for dx in 0..4.min(ch.nx - bx) {
                        v[(by + dy) * ch.nx + bx + dx] = s[dy * 4 + dx];
                    }
                }
            }
        }
        planar.push(v);
    }
    Ok(planar_to_lines(&planar, chans, first, last))
}

/// Decodes a 14-byte B44 block: the first sample `t0` (16 bits), a shift `e`, and 15 six-bit
/// differences `r`, each a step `(r - 32) << e` from a neighbour; then undoes the map of half
/// bits to ordered integers (OpenEXR's `unpack14`).
fn unpack14(b: &[u8]) -> [u16; 16] {
    let b: Vec<u32> = b.iter().map(|&x| x as u32).collect();
    let mut s = [0u16; 16];
    s[0] = ((b[0] << 8) | b[1]) as u16;
    let shift = b[2] >> 2;
    let bias = 0x20u32 << shift;
    let step =
        |from: u16, bits: u32| (from as u32).wrapping_add((bits & 0x3f) << shift).wrapping_sub(bias) as u16;
    s[4] = step(s[0], (b[2] << 4) | (b[3] >> 4));
    s[8] = step(s[4], (b[3] << 2) | (b[4] >> 6));
    s[12] = step(s[8], b[4]);
    s[1] = step(s[0], b[5] >> 2);
    s[5] = step(s[4], (b[5] << 4) | (b[6] >> 4));
    s[9] = step(s[8], (b[6] << 2) | (b[7] >> 6));
    s[13] = step(s[12], b[7]);
    s[2] = step(s[1], b[8] >> 2);
    s[6] = step(s[5], (b[8] << 4) | (b[9] >> 4));
    s[10] = step(s[9], (b[9] << 2) | (b[10] >> 6));
    s[14] = step(s[13], b[10]);
    s[3] = step(s[2], b[11] >> 2);
    s[7] = step(s[6], (b[11] << 4) | (b[12] >> 4));
    s[11] = step(s[10], (b[12] << 2) | (b[13] >> 6));
    s[15] = step(s[14], b[13]);
    s.map(ordered_to_half)
}

/// A 3-byte B44 block: 16 copies of one value (OpenEXR's `unpack3`).
fn unpack3(b: &[u8]) -> [u16; 16] {
    [ordered_to_half(((b[0] as u16) << 8) | b[1] as u16); 16]
}

/// B44 orders half bit patterns as integers: positive values get the top bit set, negative
/// ones are complemented.
fn ordered_to_half(v: u16) -> u16 {
    if v & 0x8000 != 0 {
        v & 0x7fff
    } else {
        !v
    }
}

/// B44's table from the log scale of `pLinear` channels back to linear values (OpenEXR's
/// `logTable` of `b44ExpLogTable.h`): `half(8 ln h)` for finite `h >= 0`, else 0. OpenEXR's
/// table was made with single-precision `log`, which at one entry (`0x1d78`, 8 ln h =
/// -41.85937388, within 2e-6 of the tie between -41.84375 and -41.875) rounds to the tie and
/// then to the even neighbour; computed in double precision that entry rounds the other way,
/// so it is set as OpenEXR's table has it. (Every other entry lies at least 3e-9 of its value
/// from a rounding tie, so any correctly rounded `ln` gives the same table; a unit test checks
/// that margin.)
fn log_table() -> &'static [u16; 65536] {
    static TABLE: std::sync::OnceLock<Box<[u16; 65536]>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let mut t = Box::new([0u16; 65536]);
        for (bits, v) in t.iter_mut().enumerate() {
            let h = half::f16::from_bits(bits as u16);
            *v = if h.is_finite() && h.to_f64() >= 0.0 {
                half::f16::from_f64(8.0 * h.to_f64().ln()).to_bits()
            } else {
                0
            };
        }
        t[0x1d78] = 0xd13c;
        t
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn num_samples_counts_multiples_in_a_range() {
        assert_eq!(num_samples(1, 0, 9), 10);
        assert_eq!(num_samples(2, 0, 9), 5);
        assert_eq!(num_samples(2, 0, 8), 5);
        assert_eq!(num_samples(2, 1, 8), 4);
        assert_eq!(num_samples(2, -3, 3), 3); // -2, 0, 2
        assert_eq!(num_samples(3, 4, 5), 0);
        assert_eq!(num_samples(2, 5, 4), 0);
    }

    /// A minimal scan-line file header: channels `(name, x sampling, y sampling)` (half),
    /// NONE compression, the data window, then an empty offset table.
    fn header_bytes(channels: &[(&str, i32, i32)], window: [i32; 4]) -> Vec<u8> {
        let mut b = vec![0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0];
        let mut attr = |name: &str, kind: &str, value: &[u8]| {
            b.extend_from_slice(name.as_bytes());
            b.push(0);
            b.extend_from_slice(kind.as_bytes());
            b.push(0);
            b.extend_from_slice(&(value.len() as i32).to_le_bytes());
            b.extend_from_slice(value);
        };
        let mut ch = Vec::new();
        for (n, sx, sy) in channels {
            ch.extend_from_slice(n.as_bytes());
            ch.push(0);
            ch.extend_from_slice(&1i32.to_le_bytes());
            ch.extend_from_slice(&[0, 0, 0, 0]);
            ch.extend_from_slice(&sx.to_le_bytes());
            ch.extend_from_slice(&sy.to_le_bytes());
        }
        ch.push(0);
        attr("channels", "chlist", &ch);
        attr("compression", "compression", &[0]);
        attr("dataWindow", "box2i", &window.iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>());
        b.push(0);
        b
    }

    /// OpenEXR's rule: a subsampled channel's window starts and spans multiples of its
    /// sampling; refused on the wrong side, read up to the offset table on the right side.
    #[test]
    fn subsampled_windows_must_be_multiples_of_the_sampling() {
        let p = Path::new("s.exr");
        let chans = [("BY", 2, 2), ("RY", 2, 2), ("Y", 1, 1)];
        for (window, ok) in [
            ([0, 0, 5, 3], true),
            ([-2, 4, 3, 7], true),
            ([0, 0, 4, 3], false),
            ([1, 0, 4, 3], false),
            ([0, 0, 5, 2], false),
        ] {
            let bytes = header_bytes(&chans, window);
            let h = Header::parse(p, &bytes).unwrap();
            assert_eq!(h.channel("RY").map(|c| (c.x_sampling, c.y_sampling)), Some((2, 2)));
            let e = read_channels(p, &bytes, &h, &["Y"]).unwrap_err().to_string();
            assert_eq!(e.contains("multiples of the sampling"), !ok, "{window:?}: {e}");
            if ok {
                assert!(e.contains("offset table"), "{e}");
            }
        }
    }

    #[test]
    fn rle_and_predictor_undo_openexr_encoding() {
        // Runs: 2 literal bytes, then a value repeated 3 times.
        assert_eq!(unrle(&[0xfe, 7, 9, 2, 5], 5).unwrap(), vec![7, 9, 5, 5, 5]);
        assert!(unrle(&[0xfe, 7], 5).is_err());
        assert!(unrle(&[9, 1], 5).is_err());
        // Encode [a0 b0 a1 b1 a2] as OpenEXR does: split, then differences + 128.
        let raw = [10u8, 200, 30, 7, 255];
        let split = [10u8, 30, 255, 200, 7];
        let mut enc = split;
        for i in (1..enc.len()).rev() {
            enc[i] = enc[i].wrapping_sub(enc[i - 1]).wrapping_add(128);
        }
        assert_eq!(predict_and_interleave(enc.to_vec()), raw.to_vec());
    }

    #[test]
    fn b44_blocks_decode_flat_and_graded_values() {
        // A flat block of 1.0 (0x3c00): ordered form 0xbc00.
        assert_eq!(unpack3(&[0xbc, 0x00, 0xfc]), [0x3c00; 16]);
        // A 14-byte block with shift 0 and all differences 32 (zero steps): all equal t0.
        let mut b = [0u8; 14];
        b[0] = 0xbc;
        // r values of 32 = 0b100000 packed in 6 bits each after the 6-bit shift field.
        let r = [32u32; 15];
        let bits: u128 = r.iter().fold(0u128, |acc, &x| (acc << 6) | x as u128);
        // 6 bits of shift (0) then 15 x 6 bits = 96 bits in bytes 2..14.
        for k in 0..12 {
            b[2 + k] = (bits >> (8 * (11 - k))) as u8;
        }
        assert_eq!(unpack14(&b), [0x3c00; 16]);
    }

    /// Every double-precision entry of the log table lies far enough from a rounding tie that
    /// any correctly rounded `ln` reproduces it (the one near-tie entry is set explicitly).
    #[test]
    fn the_b44_log_table_is_robust_to_the_platform_ln() {
        let t = log_table();
        let mut closest = f64::INFINITY;
        for bits in 0..=u16::MAX {
            let h = half::f16::from_bits(bits);
            if !h.is_finite() || h.to_f64() <= 0.0 || bits == 0x1d78 {
                continue;
            }
            let v = 8.0 * h.to_f64().ln();
            let q = half::f16::from_bits(t[bits as usize]).to_f64();
            // The neighbour on the far side of v, and the tie between them.
            let other = if v > q {
                half::f16::from_bits(next_up(t[bits as usize]))
            } else {
                half::f16::from_bits(next_down(t[bits as usize]))
            };
            let tie = 0.5 * (q + other.to_f64());
            closest = closest.min(((v - tie) / v).abs());
        }
        assert!(closest > 3e-9, "{closest:e}");
        assert_eq!(t[0x3c00], 0); // 8 ln 1 = 0
        assert_eq!(t[0x1d78], 0xd13c);
        assert_eq!(t[0xbc00], 0); // negative
    }

    fn next_up(bits: u16) -> u16 {
        if bits & 0x8000 != 0 {
            bits - 1
        } else {
            bits + 1
        }
    }
    fn next_down(bits: u16) -> u16 {
        if bits & 0x8000 != 0 {
            bits + 1
        } else if bits == 0 {
            0x8001
        } else {
            bits - 1
        }
    }
}
