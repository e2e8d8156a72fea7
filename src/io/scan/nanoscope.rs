//! Bruker (Veeco, Digital Instruments) Nanoscope files (`.spm`, and the numbered `.001`,
//! `.002`, ... of older versions): the height image of an AFM scan.
//!
//! Layout (Nanoscope versions 4.3 to 9.x, as described by Gwyddion's `nanoscope` module, the
//! file-format notes it and SurfaceTopography's `DI` reader follow, and the Bruker
//! "SPM file format" note; little-endian):
//!
//! | part | content |
//! |---|---|
//! | header | ISO 8859-1 text lines ending in CR LF, from byte 0 up to the line `\*File list end`: each line is a section title `\*Name` or a parameter `\Key: value` of the section above it |
//! | `\*File list` | the first section (the magic `\*File list` CR LF; `\*EC File list` for electrochemistry): `\Version: 0x09300201` (hex, major version first), `\Date`, `\Data length` = the length of the header in bytes |
//! | `\*Equipment list`, `\*Scanner list`, `\*Ciao scan list` (also `Microscope list`, `Afm list`, ...) | instrument, scanner and scan parameters; among them the soft scales `\@Sens. Name: V 43.91 nm/V` |
//! | `\*Ciao image list` (also `AFM image list`, `STM image list`, `NCAFM image list`, `Image list`), one per channel | `\Data offset`, `\Data length` (bytes from the file start), `\Bytes/pixel`, `\Samps/line` (columns), `\Number of lines` (rows), `\Scan Size: 20 12 ~m` (x and y extent; `~` is the micro sign), `\@2:Image Data: S [Height] "Height"` (the channel), `\@2:Z scale: V [Sens. Name] (0.0067 V/LSB) 440 V` (the height scale) |
//! | data | at `Data offset`: `Number of lines` rows of `Samps/line` signed integers, the bottom line of the image first |
//!
//! A parameter starting with `@` reads `TYPE [soft scale] (hard scale) hard value`, where TYPE is
//! `V` (a value), `S` (a selection) or `C` (a scale), and the bracketed and parenthesised
//! parts are optional.
//!
//! The height of a stored integer `n` (the chain Gwyddion and SurfaceTopography both follow):
//! `z = n / 2^(8 Bytes/pixel) * hard value * soft value`, where the hard value is that of
//! `@2:Z scale` (volts) and the soft value that of the `@Sens. Name` its brackets name (looked up
//! in the scanner list, then in the scan list; e.g. nanometres per volt). A `@2:Z scale` without
//! a soft scale gives the height unit itself; the old-style `\Z scale: 0.5 nm` (before
//! version 4.3) likewise. The hard scale in parentheses (volts per count) should equal the hard
//! value over `2^(8 Bytes/pixel)`: a difference is a warning, and the hard value is used.
//!
//! Stored integers: 16-bit before version 9.2, 32-bit from 9.2 on; the size is taken from
//! `Data length` when it is exactly 2 or 4 bytes a point, else from the version. `Bytes/pixel`
//! (default 2) sets the divisor above, not the storage.
//!
//! The channel read is the one named `Height` (the `[...]` or `"..."` of `@2:Image Data`), else
//! `Height Sensor` / `ZSensor`; the other channels are skipped with a warning naming them. Rows
//! are put top line first (as Gwyddion and SurfaceTopography show them). The pitch is the
//! `Scan Size` extents over the column and row counts. The format has no marker for points not
//! measured. Every header parameter is kept as metadata (`Section: Key`), plus `date`,
//! `instrument`, `software_version` and `channel`.
//!
//! Not read (refused naming what they are): the text variant (`?*File list`), force-curve files
//! (`\*Force file list`), and ISO 28600 `.spm` text files (`ISO/TC 201 SPM data transfer format`),
//! a different format that shares the extension.

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{data_len, scan_length_unit, shape, Bin, ScanFormat, ScanRaw};

/// The first line of a binary Nanoscope file.
pub const MAGIC: &[u8] = b"\\*File list\r\n";
const MAGIC_EC: &[u8] = b"\\*EC File list\r\n";
const MAGIC_TEXT: &[u8] = b"?*File list";
const MAGIC_FORCE: &[u8] = b"\\*Force file list";
/// How an ISO 28600 SPM data transfer file starts.
pub const ISO28600: &[u8] = b"ISO/TC 201 SPM data transfer format";
/// The header of a real file is tens of kilobytes; this bounds the search for its end.
const HEADER_LIMIT: usize = 1 << 22;
const IMAGE_SECTIONS: &[&str] =
    &["ciao image list", "afm image list", "stm image list", "ncafm image list", "image list"];

/// True when `head` starts as a binary Nanoscope file does.
pub fn has_magic(head: &[u8]) -> bool {
    head.starts_with(MAGIC) || head.starts_with(MAGIC_EC)
}

/// One `\Key: value` line, with the byte offset of the line.
#[derive(Debug, Clone)]
struct Param {
    key: String,
    value: String,
    off: usize,
}

#[derive(Debug, Clone)]
struct Section {
    name: String,
    params: Vec<Param>,
}

impl Section {
    fn get(&self, key: &str) -> Option<&Param> {
        self.params.iter().find(|p| p.key.eq_ignore_ascii_case(key))
    }
    fn is_image(&self) -> bool {
        IMAGE_SECTIONS.iter().any(|s| self.name.eq_ignore_ascii_case(s))
    }
}

/// A parsed `@` parameter: `TYPE [soft] (hard scale) hard value`.
#[derive(Debug, Clone, PartialEq)]
struct Value {
    soft: Option<String>,
    hard_scale: Option<f64>,
    /// The text after the hard scale: a number and its unit, or a selection.
    hard: String,
}

/// Parses the value of an `@` parameter (see the module docs); `None` when it is not of that
/// form.
fn parse_at_value(text: &str) -> Option<Value> {
    let t = text.trim();
    let mut chars = t.chars();
    let kind = chars.next()?;
    if !matches!(kind, 'V' | 'S' | 'C') {
        return None;
    }
    let mut rest = chars.as_str();
    if !rest.is_empty() && !rest.starts_with(' ') {
        return None;
    }
    rest = rest.trim_start();
    let mut soft = None;
    if let Some(r) = rest.strip_prefix('[') {
        let end = r.find(']')?;
        let name = r[..end].trim();
        if !name.is_empty() {
            soft = Some(name.to_string());
        }
        rest = r[end + 1..].trim_start();
    }
    let mut hard_scale = None;
    if let Some(r) = rest.strip_prefix('(') {
        let end = r.find(')')?;
        let inner = r[..end].trim();
        hard_scale = inner.split_whitespace().next().and_then(|n| n.parse::<f64>().ok());
        rest = r[end + 1..].trim_start();
    }
    Some(Value { soft, hard_scale, hard: rest.trim().to_string() })
}

/// A number followed by an optional unit: `440 V`, `43.91 nm/V`, `2.5`.
fn number_unit(text: &str) -> Option<(f64, String)> {
    let t = text.trim();
    let (num, unit) = match t.find(char::is_whitespace) {
        Some(i) => (&t[..i], t[i..].trim()),
        None => (t, ""),
    };
    let v = num.parse::<f64>().ok().filter(|v| v.is_finite())?;
    Some((v, unit.to_string()))
}

/// A Nanoscope unit text as a length in metres: `~m` (the micro sign written `~`), `µm`, `nm`.
fn length(unit: &str) -> Option<f64> {
    scan_length_unit(&unit.replace('~', "µ"))
}

/// Text of one header line: UTF-8 when valid, else ISO 8859-1.
fn line_text(b: &[u8]) -> String {
    match std::str::from_utf8(b) {
        Ok(s) => s.to_string(),
        Err(_) => b.iter().map(|&c| c as char).collect(),
    }
}

/// Splits the header into sections; the byte offset where the header ends.
fn parse_header(b: &Bin) -> Result<(Vec<Section>, usize)> {
    let bytes = b.bytes;
    let mut sections: Vec<Section> = Vec::new();
    let mut off = 0;
    loop {
        if off >= bytes.len() {
            return Err(
                b.bad(bytes.len(), "truncated: the header ends before its last line '\\*File list end'")
            );
        }
        if off > HEADER_LIMIT {
            return Err(
                b.signature(off, "no '\\*File list end' line in the first 4 MiB: not a Nanoscope header")
            );
        }
        let rest = &bytes[off..];
        let Some(nl) = rest.iter().position(|&c| c == b'\n') else {
            return Err(b.bad(
                bytes.len(),
                "truncated: the header ends inside a line, before its last line '\\*File list end'",
            ));
        };
        let raw = &rest[..nl];
        let raw = raw.strip_suffix(b"\r").unwrap_or(raw);
        let line = line_text(raw);
        let here = off;
        off += nl + 1;
        if line.trim().is_empty() {
            continue;
        }
        if let Some(name) = line.strip_prefix("\\*") {
            let name = name.trim();
            if name.eq_ignore_ascii_case("File list end") {
                break;
            }
            sections.push(Section { name: name.to_string(), params: Vec::new() });
            continue;
        }
        if line.starts_with('\x1a') {
            // The end-of-text byte some versions put after the header.
            continue;
        }
        let Some(body) = line.strip_prefix('\\') else {
            return Err(b.bad(here, format!("header line '{}' does not start with '\\'", clip(&line))));
        };
        let Some(section) = sections.last_mut() else {
            return Err(b.bad(here, "a header parameter before the first section"));
        };
        // `@2:Z scale: ...`: the group prefix holds a colon of its own.
        let start = if body.starts_with('@') && body.as_bytes().get(2) == Some(&b':') { 3 } else { 0 };
        let (key, value) = match body.get(start..).and_then(|s| s.find(':')) {
            Some(i) => (body[..start + i].trim(), body[start + i + 1..].trim()),
            None => (body.trim(), ""),
        };
        section.params.push(Param { key: key.to_string(), value: value.to_string(), off: here });
    }
    Ok((sections, off))
}

fn clip(s: &str) -> String {
    s.chars().take(60).collect()
}

/// The name of an image section's channel: the soft scale of `@2:Image Data` (`[Height]`), else
/// its quoted label, else the old-style `Image data`.
fn channel_name(s: &Section) -> Option<String> {
    for key in ["@2:Image Data", "@3:Image Data", "@4:Image Data"] {
        if let Some(p) = s.get(key) {
            if let Some(v) = parse_at_value(&p.value) {
                if let Some(soft) = v.soft {
                    return Some(soft);
                }
                return Some(v.hard.trim_matches('"').to_string());
            }
        }
    }
    s.get("Image data").map(|p| p.value.trim_matches('"').to_string())
}

/// The quoted label of `@2:Image Data` (`"Height Sensor"`), when there is one.
fn channel_label(s: &Section) -> Option<String> {
    let v = parse_at_value(&s.get("@2:Image Data")?.value)?;
    let h = v.hard.trim();
    (h.len() >= 2 && h.starts_with('"') && h.ends_with('"')).then(|| h[1..h.len() - 1].to_string())
}

/// Preference of a channel as the height: 0 best, `None` not a height.
fn height_rank(s: &Section) -> Option<u8> {
    let name = channel_name(s)?.to_ascii_lowercase();
    let label = channel_label(s).unwrap_or_default().to_ascii_lowercase();
    if name == "height" || label == "height" {
        Some(0)
    } else if name == "zsensor" || name == "height sensor" || label == "height sensor" {
        Some(1)
    } else {
        None
    }
}

/// Refuses what is not a binary Nanoscope file, naming what it is where known: an ISO 28600
/// transfer, a Nanoscope text export or force-curve file, or no Nanoscope magic at all.
fn refuse_other_files(b: &Bin) -> Result<()> {
    let bytes = b.bytes;
    if bytes.starts_with(ISO28600) {
        return Err(b.signature(
            0,
            "an ISO 28600 SPM data transfer (text) file, not a Bruker Nanoscope file: ISO 28600 is not \
             read; export the surface from the software that wrote it as ISO 25178-72 .x3p or \
             ISO 25178-71 .sdf, or convert it with Gwyddion to .gsf",
        ));
    }
    if bytes.starts_with(MAGIC_TEXT) {
        return Err(b.bad(
            0,
            "a Nanoscope text export ('?*File list'), not read: save the scan as a binary Nanoscope \
             file or export it as .x3p / .gsf",
        ));
    }
    if bytes.starts_with(MAGIC_FORCE) {
        return Err(
            b.unsupported(0, "a Nanoscope force-curve file ('\\*Force file list'), not a surface scan")
        );
    }
    let n = bytes.len().min(MAGIC.len());
    let m = bytes.len().min(MAGIC_EC.len());
    if bytes[..n] != MAGIC[..n] && bytes[..m] != MAGIC_EC[..m] {
        return Err(
            b.signature(0, "not a Bruker Nanoscope file: it does not start with '\\*File list' CR LF")
        );
    }
    Ok(())
}

/// Decodes a binary Nanoscope file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    refuse_other_files(&b)?;
    let (sections, header_end) = parse_header(&b)?;
    let file_list = &sections[0];
    let version_text = file_list.get("Version").map(|p| p.value.clone());
    let version = match &version_text {
        Some(v) => {
            let hex = v.trim().trim_start_matches("0x").trim_start_matches("0X");
            Some(u32::from_str_radix(hex, 16).map_err(|_| {
                b.bad(
                    file_list.get("Version").map_or(0, |p| p.off),
                    format!("Version '{v}' is not a hex number"),
                )
            })?)
        }
        None => None,
    };

    let images: Vec<&Section> = sections.iter().filter(|s| s.is_image()).collect();
    if images.is_empty() {
        return Err(b.bad(header_end, "the header holds no image section ('\\*Ciao image list')"));
    }
    let best = images.iter().enumerate().filter_map(|(i, s)| height_rank(s).map(|r| (r, i))).min();
    let Some(image) = best.map(|(_, i)| images[i]) else {
        let names: Vec<String> =
            images.iter().map(|s| channel_name(s).unwrap_or_else(|| "?".into())).collect();
        return Err(b.unsupported(
            header_end,
            format!(
                "no height channel among the images ({}): only 'Height' or 'Height Sensor' is read",
                names.join(", ")
            ),
        ));
    };
    let channel = channel_name(image).unwrap_or_default();
    let sec_off = image.params.first().map_or(header_end, |p| p.off);
    let need_param = |key: &str| -> Result<&Param> {
        image
            .get(key)
            .ok_or_else(|| b.bad(sec_off, format!("the '{channel}' image section has no '{key}' parameter")))
    };
    let count = |key: &str| -> Result<usize> {
        let p = need_param(key)?;
        let v = p.value.split_whitespace().next().unwrap_or("");
        v.parse::<usize>().map_err(|_| b.bad(p.off, format!("'{key}: {}' is not a count", clip(&p.value))))
    };
    let cols = count("Samps/line")?;
    let rows = count("Number of lines")?;
    let offset = count("Data offset")?;
    let length = count("Data length")?;
    let qbpp = match image.get("Bytes/pixel") {
        Some(_) => count("Bytes/pixel")?,
        None => 2,
    };
    if rows == 0 || cols == 0 {
        return Err(
            b.bad(need_param("Samps/line")?.off, format!("the map is empty ({cols} x {rows} points)"))
        );
    }
    if !matches!(qbpp, 1 | 2 | 4) {
        return Err(b.bad(need_param("Bytes/pixel")?.off, format!("Bytes/pixel {qbpp} is not 1, 2 or 4")));
    }
    let n2 = data_len(path, rows, cols, 2)?;
    let n4 = data_len(path, rows, cols, 4)?;
    let bpp = if length == n4 {
        4
    } else if length == n2 {
        2
    } else if version.is_some_and(|v| v >= 0x0920_0000) {
        4
    } else {
        2
    };
    let need = if bpp == 4 { n4 } else { n2 };
    if length < need {
        return Err(b.bad(
            need_param("Data length")?.off,
            format!("Data length {length} is less than {cols} x {rows} points of {bpp} bytes"),
        ));
    }
    if offset < header_end {
        return Err(
            b.bad(need_param("Data offset")?.off, format!("Data offset {offset} points into the header"))
        );
    }
    let data =
        b.take(offset, need, &format!("the {cols} x {rows} '{channel}' image ({bpp} bytes a point)"))?;

    let mut warnings = Vec::new();
    let z = height_scale(&b, &sections, image, qbpp, &mut warnings)?;
    let counts: Vec<f64> = if bpp == 4 {
        data.chunks_exact(4).map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64).collect()
    } else {
        data.chunks_exact(2).map(|c| i16::from_le_bytes([c[0], c[1]]) as f64).collect()
    };
    // The bottom line is stored first: reverse the rows so that row 0 is the top of the image.
    let mut values = Vec::with_capacity(counts.len());
    for r in (0..rows).rev() {
        values.extend(counts[r * cols..(r + 1) * cols].iter().map(|&c| c * z));
    }
    let values = shape(path, rows, cols, values)?;

    let size = image
        .get("Scan Size")
        .or_else(|| sections.iter().filter(|s| !s.is_image()).find_map(|s| s.get("Scan Size")));
    let pitch = match size.map(|p| (scan_size(&p.value), p)) {
        Some((Some((sx, sy)), _)) if sx > 0.0 && sy > 0.0 => Some([sx / cols as f64, sy / rows as f64]),
        Some((_, p)) => {
            warnings.push(format!("'Scan Size: {}' gives no usable pitch: pass `pitch`", clip(&p.value)));
            None
        }
        None => {
            warnings.push("the file states no Scan Size: pass `pitch`".to_string());
            None
        }
    };
    let skipped: Vec<String> = images
        .iter()
        .filter(|s| !std::ptr::eq(**s, image))
        .map(|s| channel_name(s).unwrap_or_else(|| "?".into()))
        .collect();
    if !skipped.is_empty() {
        warnings.push(format!(
            "the file holds {} images: read '{channel}', skipped {}",
            images.len(),
            skipped.iter().map(|s| format!("'{s}'")).collect::<Vec<_>>().join(", ")
        ));
    }

    let mut metadata = vec![("channel".to_string(), channel.clone())];
    if let Some(d) = file_list.get("Date") {
        metadata.push(("date".into(), d.value.clone()));
    }
    if let Some(v) = version_text {
        metadata.push(("software_version".into(), v));
    }
    let equipment = sections.iter().find(|s| s.name.eq_ignore_ascii_case("Equipment list"));
    if let Some(i) = equipment.and_then(|e| e.get("Description").or_else(|| e.get("Microscope"))) {
        metadata.push(("instrument".into(), format!("Bruker {}", i.value)));
    }
    metadata.push(("height_unit".into(), format!("{z:e} m per count ({bpp}-byte integers)")));
    for s in sections.iter().filter(|s| !s.is_image() || std::ptr::eq(*s, image)) {
        for p in &s.params {
            metadata.push((format!("{}: {}", s.name, p.key), p.value.clone()));
        }
    }
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::Nanoscope);
    sr.warnings = warnings;
    Ok(sr)
}

/// `Scan Size: 20 12 ~m` (or an old single extent `20 ~m`): the x and y extents in metres.
fn scan_size(text: &str) -> Option<(f64, f64)> {
    let parts: Vec<&str> = text.split_whitespace().collect();
    let (x, y, unit) = match parts.as_slice() {
        [x, y, u] => (x.parse::<f64>().ok()?, y.parse::<f64>().ok()?, *u),
        [x, u] => {
            let x = x.parse::<f64>().ok()?;
            (x, x, *u)
        }
        _ => return None,
    };
    let m = length(unit)?;
    let (x, y) = (x.abs() * m, y.abs() * m);
    (x.is_finite() && y.is_finite()).then_some((x, y))
}

/// Metres per stored count of the height image (see the module docs).
fn height_scale(
    b: &Bin,
    sections: &[Section],
    image: &Section,
    qbpp: usize,
    warnings: &mut Vec<String>,
) -> Result<f64> {
    let divisor = 2f64.powi(8 * qbpp as i32);
    if let Some(p) = image.get("@2:Z scale") {
        let bad = |what: String| b.bad(p.off, format!("'@2:Z scale: {}': {what}", clip(&p.value)));
        let v = parse_at_value(&p.value)
            .ok_or_else(|| bad("not of the form 'V [soft scale] (hard scale) value'".into()))?;
        let (hard, hard_unit) = number_unit(&v.hard).ok_or_else(|| bad("no hard value".into()))?;
        if let Some(hs) = v.hard_scale {
            let want = hard / divisor;
            if (hs - want).abs() > 1e-3 * want.abs().max(f64::MIN_POSITIVE) {
                warnings.push(format!(
                    "the Z scale's hard scale {hs:e} per count differs from its hard value {hard} / 2^{} = {want:e}; \
                     the hard value is used (as Gwyddion and SurfaceTopography do)",
                    8 * qbpp
                ));
            }
        }
        let Some(soft) = v.soft else {
            let m = length(&hard_unit).ok_or_else(|| {
                bad(format!("the height unit '{hard_unit}' is not a length, and no sensitivity is named"))
            })?;
            return finite(b, p.off, hard / divisor * m);
        };
        let key = format!("@{soft}");
        let order =
            ["scanner list", "microscope list", "ciao scan list", "afm list", "stm list", "nc afm list"];
        let sp = order
            .iter()
            .filter_map(|name| sections.iter().find(|s| s.name.eq_ignore_ascii_case(name)))
            .chain(sections.iter().filter(|s| !s.is_image()))
            .find_map(|s| s.get(&key))
            .ok_or_else(|| bad(format!("the sensitivity '\\{key}' it names is not in the header")))?;
        let sbad = |what: String| b.bad(sp.off, format!("'{key}: {}': {what}", clip(&sp.value)));
        let sv = parse_at_value(&sp.value).ok_or_else(|| sbad("not of the form 'V value unit'".into()))?;
        let (sens, sens_unit) = number_unit(&sv.hard).ok_or_else(|| sbad("no value".into()))?;
        let (num, den) = sens_unit.split_once('/').unwrap_or((sens_unit.as_str(), ""));
        let m = length(num).ok_or_else(|| {
            sbad(format!(
                "'{sens_unit}' is not a length per {}: the channel is not a height",
                if hard_unit.is_empty() { "volt" } else { &hard_unit }
            ))
        })?;
        if !hard_unit.is_empty() && !den.is_empty() && den.trim() != hard_unit.trim() {
            return Err(sbad(format!("its unit '{sens_unit}' is not per '{hard_unit}', the Z scale's unit")));
        }
        return finite(b, p.off, hard / divisor * sens * m);
    }
    if let Some(p) = image.get("Z scale") {
        let (hard, unit) = number_unit(p.value.split('(').next().unwrap_or(""))
            .ok_or_else(|| b.bad(p.off, format!("'Z scale: {}' has no value", clip(&p.value))))?;
        let m = length(&unit).ok_or_else(|| {
            b.bad(p.off, format!("the old-style 'Z scale: {}' is not in a length unit", clip(&p.value)))
        })?;
        return finite(b, p.off, hard / divisor * m);
    }
    let off = image.params.first().map_or(0, |p| p.off);
    Err(b.bad(off, "the height image has no '@2:Z scale' (nor an old-style 'Z scale'): no height unit"))
}

fn finite(b: &Bin, off: usize, z: f64) -> Result<f64> {
    if z.is_finite() && z != 0.0 {
        Ok(z)
    } else {
        Err(b.bad(off, format!("the height scale {z} m per count is not usable")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A version 9.3 style file: two images (Height, then Amplitude Error), 32-bit data.
    fn sample(rows: usize, cols: usize, counts: &[i32], bpp: usize, version: &str) -> Vec<u8> {
        let header_len = 8192;
        let data_len = rows * cols * bpp;
        let mut h = String::new();
        let mut line = |s: &str| {
            h.push_str(s);
            h.push_str("\r\n");
        };
        line("\\*File list");
        line(&format!("\\Version: {version}"));
        line("\\Date: 01:02:03 PM Tue Mar 04 2025");
        line("\\Start context: OL2");
        line(&format!("\\Data length: {header_len}"));
        line("\\*Equipment list");
        line("\\Description: Dimension Icon");
        line("\\*Scanner list");
        line("\\@Sens. Zsens: V 20.0 nm/V");
        line("\\*Ciao scan list");
        line("\\Scan Size: 20 12 ~m");
        line("\\@Sens. ZsensSens: V 43.91 nm/V");
        for (k, name) in ["Height", "Amplitude Error"].iter().enumerate() {
            line("\\*Ciao image list");
            line(&format!("\\Data offset: {}", header_len + k * data_len));
            line(&format!("\\Data length: {data_len}"));
            line(&format!("\\Bytes/pixel: {bpp}"));
            line(&format!("\\Samps/line: {cols}"));
            line(&format!("\\Number of lines: {rows}"));
            line("\\Scan Size: 20 12 ~m");
            line(&format!("\\@2:Image Data: S [{name}] \"{name}\""));
            let hard = if bpp == 4 { 2f64.powi(32) * 1e-6 } else { 65536.0 * 1e-6 };
            line(&format!("\\@2:Z scale: V [Sens. ZsensSens] (0.000001 V/LSB) {hard} V"));
        }
        line("\\*File list end");
        let mut out = h.into_bytes();
        out.resize(header_len, 0);
        for _ in 0..2 {
            for &c in counts {
                if bpp == 4 {
                    out.extend_from_slice(&c.to_le_bytes());
                } else {
                    out.extend_from_slice(&(c as i16).to_le_bytes());
                }
            }
        }
        out
    }

    #[test]
    fn values_chain_rows_and_channels() {
        let (rows, cols) = (3, 4);
        let counts: Vec<i32> = (0..12).map(|k| k * 100 - 500).collect();
        for (bpp, version) in [(4, "0x09300201"), (2, "0x05310001")] {
            let bytes = sample(rows, cols, &counts, bpp, version);
            let r = decode(Path::new("t.spm"), &bytes).unwrap();
            // z = n * 1e-6 V * 43.91 nm/V; the bottom line first in the file.
            for i in 0..rows {
                for j in 0..cols {
                    let n = counts[(rows - 1 - i) * cols + j] as f64;
                    let want = n * 1e-6 * 43.91e-9;
                    let got = r.raw.values[[i, j]];
                    assert!((got - want).abs() <= 1e-12 * want.abs(), "{bpp} ({i}, {j}) {got} {want}");
                }
            }
            let [px, py] = r.raw.pitch.unwrap();
            assert!((px - 5e-6).abs() < 1e-18 && (py - 4e-6).abs() < 1e-18, "{px} {py}");
            assert_eq!(r.warnings.len(), 1, "{:?}", r.warnings);
            assert!(r.warnings[0].contains("skipped 'Amplitude Error'"), "{:?}", r.warnings);
            let m = &r.raw.metadata;
            assert!(m.iter().any(|(k, v)| k == "instrument" && v == "Bruker Dimension Icon"));
            assert!(m.iter().any(|(k, v)| k == "Ciao scan list: @Sens. ZsensSens" && v == "V 43.91 nm/V"));
        }
    }

    #[test]
    fn value_forms() {
        let v = parse_at_value("V [Sens. ZsensSens] (0.006713867 V/LSB) 440.0000 V").unwrap();
        assert_eq!(v.soft.as_deref(), Some("Sens. ZsensSens"));
        assert_eq!(v.hard_scale, Some(0.006713867));
        assert_eq!(number_unit(&v.hard), Some((440.0, "V".into())));
        let v = parse_at_value("S [Height] \"Height\"").unwrap();
        assert_eq!(v.hard, "\"Height\"");
        assert_eq!(parse_at_value("V 2.5 nm").unwrap().soft, None);
        assert!(parse_at_value("X 1").is_none());
        let (x, y) = scan_size("20 12 ~m").unwrap();
        assert!((x - 20e-6).abs() < 1e-20 && (y - 12e-6).abs() < 1e-20);
        let (x, y) = scan_size("500 nm").unwrap();
        assert!((x - 500e-9).abs() < 1e-20 && x == y);
        assert_eq!(scan_size("20 12 V"), None);
    }

    #[test]
    fn refusals_and_cuts() {
        let counts: Vec<i32> = (0..12).collect();
        let good = sample(3, 4, &counts, 4, "0x09300201");
        let err = |bytes: &[u8]| decode(Path::new("t.spm"), bytes).unwrap_err().to_string();
        assert!(err(b"ISO/TC 201 SPM data transfer format\r\n").contains("ISO 28600"));
        assert!(err(b"?*File list\r\n").contains("text export"));
        assert!(err(b"\\*Force file list\r\n").contains("force-curve"));
        assert!(err(b"PK\x03\x04").contains("not a Bruker Nanoscope file"));
        // The Height image ends at 8192 + 48; the Amplitude Error image after it is not read.
        assert!(decode(Path::new("t.spm"), &good[..8192 + 48]).is_ok());
        for cut in (0..8192 + 48).step_by(7) {
            let e = err(&good[..cut]);
            assert!(e.contains("t.spm") && e.contains("byte offset"), "cut at {cut}: {e}");
        }
        let text = String::from_utf8_lossy(&good[..8192]).to_string();
        let swap = |from: &str, to: &str| {
            let mut b = text.replacen(from, to, 1).into_bytes();
            b.resize(8192, 0);
            b.extend_from_slice(&good[8192..]);
            b
        };
        assert!(
            err(&swap("[Sens. ZsensSens] (", "[Sens. Nothing] (")).contains("'\\@Sens. Nothing' it names")
        );
        assert!(err(&swap("43.91 nm/V", "43.91 deg/V")).contains("not a height"));
        assert!(err(&swap("[Height] \"Height\"", "[Phase] \"Phase\"")).contains("no height channel"));
        assert!(err(&swap("Samps/line: 4", "Samps/line: 5000")).contains("Data length"));
    }
}
