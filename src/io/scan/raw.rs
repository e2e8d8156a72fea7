//! What the scan format readers share: the formats ([`ScanFormat`]), what a reader returns
//! ([`ScanRaw`]), bounds-checked access to a binary file's fields (`Bin`) and the checks and
//! texts every reader applies.

use std::path::Path;

use serde::Serialize;

use crate::error::{Error, Result};
use crate::io::raw_map::RawMap;

/// The scan formats [`super::read_scan`] understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ScanFormat {
    /// ISO 25178-72 XML 3D surface profile (`.x3p`).
    X3p,
    /// Gwyddion Simple Field (`.gsf`).
    Gsf,
    /// ISO 25178-71 surface data file, ASCII (`.sdf` not starting with `b`).
    SdfAscii,
    /// ISO 25178-71 surface data file, binary (`.sdf` starting with `b`).
    SdfBinary,
    /// Digital Surf SUR (`.sur`).
    Sur,
    /// Gwyddion native GWY (`.gwy`).
    Gwy,
    /// Zygo MetroPro DAT (`.dat` with the MetroPro magic).
    MetroPro,
    /// Wyko / Bruker Vision OPD (`.opd`).
    Opd,
    /// Bruker Vision64 OPDx (`.opdx`).
    Opdx,
    /// Sensofar PLu (`.plu`).
    Plu,
    /// Sensofar PLUx (`.plux`).
    Plux,
    /// Alicona AL3D (`.al3d`).
    Al3d,
    /// TrueMap TMD (`.tmd`).
    Tmd,
    /// Keyence VK4, VK6 or VK7 (`.vk4`, `.vk6`, `.vk7`).
    Vk,
    /// Olympus LEXT (`.lext`).
    Lext,
    /// FRT MicroProf (`.frt`).
    Frt,
    /// Zygo Mx DATX (`.datx`).
    Datx,
    /// Bruker Nanoscope SPM (`.spm`, or a three-digit extension with the Nanoscope magic).
    Nanoscope,
    /// XYZ point list, text (`.xyz`).
    Xyz,
    /// Text matrix of heights (`.txt`, `.csv`, `.asc`, or `.dat` without the MetroPro magic).
    Matrix,
    /// 8/16-bit grayscale PNG, with a `pCAL` height scale or an explicit one (`.png`).
    Png,
    /// TIFF height map (`.tif`, `.tiff`).
    Tiff,
    /// NumPy NPY array (`.npy`).
    Npy,
    /// OpenEXR height map (`.exr`).
    Exr,
}

impl ScanFormat {
    /// A short human name.
    pub fn name(self) -> &'static str {
        match self {
            ScanFormat::X3p => "ISO 25178-72 X3P",
            ScanFormat::Gsf => "Gwyddion Simple Field",
            ScanFormat::SdfAscii => "ISO 25178-71 SDF (ASCII)",
            ScanFormat::SdfBinary => "ISO 25178-71 SDF (binary)",
            ScanFormat::Sur => "Digital Surf SUR",
            ScanFormat::Gwy => "Gwyddion GWY",
            ScanFormat::MetroPro => "Zygo MetroPro DAT",
            ScanFormat::Opd => "Wyko / Bruker Vision OPD",
            ScanFormat::Opdx => "Bruker Vision64 OPDx",
            ScanFormat::Plu => "Sensofar PLu",
            ScanFormat::Plux => "Sensofar PLUx",
            ScanFormat::Al3d => "Alicona AL3D",
            ScanFormat::Tmd => "TrueMap TMD",
            ScanFormat::Vk => "Keyence VK",
            ScanFormat::Lext => "Olympus LEXT",
            ScanFormat::Frt => "FRT MicroProf",
            ScanFormat::Datx => "Zygo Mx DATX",
            ScanFormat::Nanoscope => "Bruker Nanoscope SPM",
            ScanFormat::Xyz => "XYZ point list",
            ScanFormat::Matrix => "text matrix",
            ScanFormat::Png => "PNG",
            ScanFormat::Tiff => "TIFF",
            ScanFormat::Npy => "NumPy NPY",
            ScanFormat::Exr => "OpenEXR height map",
        }
    }
}

/// What a scan reader found, before pitch and unit are resolved.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanRaw {
    /// Stored numbers (non-measured points NaN), pitch and unit as the file states them.
    pub raw: RawMap,
    /// The file format read.
    pub format: ScanFormat,
    /// `[x, y]` position of sample (0, 0) in metres, when the file states it.
    pub origin: Option<[f64; 2]>,
    /// Things the file got wrong but that did not stop the read (e.g. a checksum mismatch).
    pub warnings: Vec<String>,
}

impl ScanRaw {
    pub(crate) fn new(raw: RawMap, format: ScanFormat) -> Self {
        ScanRaw { raw, format, origin: None, warnings: Vec::new() }
    }
}

/// Bounds-checked little/big-endian field access on a binary file's bytes: every failure names
/// the file, the field and its byte offset.
pub(crate) struct Bin<'a> {
    pub path: &'a Path,
    pub bytes: &'a [u8],
}

impl<'a> Bin<'a> {
    pub fn new(path: &'a Path, bytes: &'a [u8]) -> Self {
        Bin { path, bytes }
    }
    /// `len` bytes at `off`, or a truncation error naming `what`.
    pub fn take(&self, off: usize, len: usize, what: &str) -> Result<&'a [u8]> {
        match off.checked_add(len) {
            Some(end) if end <= self.bytes.len() => Ok(&self.bytes[off..end]),
            _ => Err(Error::truncated(
                self.path,
                self.bytes.len() as u64,
                format!(
                    "truncated at byte offset {}: {what} needs {len} bytes from offset {off}",
                    self.bytes.len()
                ),
            )),
        }
    }
    fn arr<const N: usize>(&self, off: usize, what: &str) -> Result<[u8; N]> {
        let s = self.take(off, N, what)?;
        let mut a = [0u8; N];
        a.copy_from_slice(s);
        Ok(a)
    }
    pub fn u16le(&self, off: usize, what: &str) -> Result<u16> {
        Ok(u16::from_le_bytes(self.arr(off, what)?))
    }
    pub fn u32le(&self, off: usize, what: &str) -> Result<u32> {
        Ok(u32::from_le_bytes(self.arr(off, what)?))
    }
    pub fn i32le(&self, off: usize, what: &str) -> Result<i32> {
        Ok(i32::from_le_bytes(self.arr(off, what)?))
    }
    pub fn f32le(&self, off: usize, what: &str) -> Result<f32> {
        Ok(f32::from_le_bytes(self.arr(off, what)?))
    }
    pub fn f64le(&self, off: usize, what: &str) -> Result<f64> {
        Ok(f64::from_le_bytes(self.arr(off, what)?))
    }
    pub fn u16be(&self, off: usize, what: &str) -> Result<u16> {
        Ok(u16::from_be_bytes(self.arr(off, what)?))
    }
    pub fn i16be(&self, off: usize, what: &str) -> Result<i16> {
        Ok(i16::from_be_bytes(self.arr(off, what)?))
    }
    pub fn i32be(&self, off: usize, what: &str) -> Result<i32> {
        Ok(i32::from_be_bytes(self.arr(off, what)?))
    }
    pub fn f32be(&self, off: usize, what: &str) -> Result<f32> {
        Ok(f32::from_be_bytes(self.arr(off, what)?))
    }
    /// A fixed-size text field: up to the first NUL, trailing spaces removed; UTF-8 when valid,
    /// else Latin-1 (one byte per character).
    pub fn text(&self, off: usize, len: usize, what: &str) -> Result<String> {
        Ok(decode_text(self.take(off, len, what)?))
    }
    /// A malformed field at `off`.
    pub fn bad(&self, off: usize, what: impl std::fmt::Display) -> Error {
        Error::malformed(self.path, format!("byte offset {off}: {what}")).at(off as u64)
    }
    /// A wrong magic number or identifier at `off`: not a file of this format.
    pub fn signature(&self, off: usize, what: impl std::fmt::Display) -> Error {
        Error::signature(self.path, format!("byte offset {off}: {what}")).at(off as u64)
    }
    /// A valid file, but a version or layout (named at `off`) this reader does not decode.
    pub fn unsupported(&self, off: usize, what: impl std::fmt::Display) -> Error {
        Error::unsupported(self.path, format!("byte offset {off}: {what}")).at(off as u64)
    }
}

/// Text of a fixed-size field: up to the first NUL, trimmed; UTF-8 when valid, else Latin-1.
pub(crate) fn decode_text(b: &[u8]) -> String {
    let end = b.iter().position(|&c| c == 0).unwrap_or(b.len());
    let b = &b[..end];
    let s = match std::str::from_utf8(b) {
        Ok(s) => s.to_string(),
        Err(_) => b.iter().map(|&c| c as char).collect(),
    };
    s.trim().to_string()
}

/// The size in metres of a unit text as profilometer files write it: "m", "mm", "um", "µm"
/// (micro sign or Greek mu), "nm", "pm", "A" (angstrom). `None` for anything else.
pub(crate) fn scan_length_unit(text: &str) -> Option<f64> {
    let t = text.trim();
    match t {
        "A" | "Å" | "\u{212b}" => Some(1e-10),
        "" => None,
        _ => crate::units::length_unit(t).ok(),
    }
}

/// A row-major `rows x cols` array from `data`, or an error naming the file.
pub(crate) fn shape(path: &Path, rows: usize, cols: usize, data: Vec<f64>) -> Result<ndarray::Array2<f64>> {
    if rows == 0 || cols == 0 {
        return Err(Error::malformed(path, format!("the map is empty ({cols} x {rows} points)")));
    }
    ndarray::Array2::from_shape_vec((rows, cols), data)
        .map_err(|e| Error::malformed(path, format!("cannot form a {rows} x {cols} map: {e}")))
}

/// The number of bytes of `rows * cols` samples of `size` bytes, refusing overflow and maps
/// above 2^28 samples (a 16384 x 16384 scan is the largest the instruments write).
pub(crate) fn data_len(path: &Path, rows: usize, cols: usize, size: usize) -> Result<usize> {
    let n = rows.checked_mul(cols).filter(|&n| n <= 1 << 28).ok_or_else(|| {
        Error::malformed(path, format!("{cols} x {rows} points is beyond any profilometer scan (limit 2^28)"))
    })?;
    Ok(n * size)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bin_errors_name_offset() {
        let b = Bin::new(Path::new("f.bin"), &[1, 2, 3]);
        assert_eq!(b.u16le(1, "x").unwrap(), 0x0302);
        let e = b.u32le(1, "the width").unwrap_err().to_string();
        assert!(
            e.contains("f.bin")
                && e.contains("byte offset 3")
                && e.contains("from offset 1")
                && e.contains("the width"),
            "{e}"
        );
        assert!(b.take(usize::MAX, 2, "x").is_err());
        assert_eq!(decode_text(b"ab \0zz"), "ab");
        assert_eq!(decode_text(b"\xb5m"), "µm");
        assert_eq!(decode_text("µm".as_bytes()), "µm");
        assert_eq!(scan_length_unit("µm"), Some(1e-6));
        assert_eq!(scan_length_unit("A"), Some(1e-10));
    }
}
