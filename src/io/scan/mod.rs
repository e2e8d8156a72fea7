//! Profilometer scans: one entry point, [`read_scan`], for every surface format the metrology
//! stage reads, each producing the shared [`Grid`] of heights in metres.
//!
//! | extension | format | module |
//! |---|---|---|
//! | `.x3p` | ISO 25178-72 (XML 3D surface profile: zip of `main.xml` + binary data) | [`x3p`] |
//! | `.gsf` | Gwyddion Simple Field | [`gsf`] |
//! | `.sdf` | ISO 25178-71 / SDF, ASCII (`aBCR`, `aISO`) or binary (`bBCR`, `bISO`) | [`sdf`] |
//! | `.sur` | Digital Surf (MountainsMap) | [`sur`] |
//! | `.gwy` | Gwyddion native (first channel; its mask as non-measured points) | [`gwy`] |
//! | `.opd` | Wyko / Bruker Vision binary | [`opd`] |
//! | `.opdx` | Bruker Vision64 / Dektak "VCA DATA" (the primary 2-D height channel) | [`opdx`] |
//! | `.plu` | Sensofar PLu binary (2000 and later revisions) | [`plu`] |
//! | `.plux` | Sensofar PLUx (zip of `index.xml` + f32 layers; the first layer) | [`plux`] |
//! | `.al3d` | Alicona Imaging / Bruker Alicona AL3D (the depth image) | [`al3d`] |
//! | `.tmd` | TrueMap / GelSight binary TrueMap Data File v2.0 | [`tmd`] |
//! | `.frt` | FRT MicroProf binary, versions 1.00 and 1.01 (the topography) | [`frt`] |
//! | `.lext` | Olympus LEXT (multi-page TIFF: the `HEIGHT` page, its `INVALID` mask as non-measured points) | [`lext`] |
//! | `.vk4`, `.vk6`, `.vk7` | Keyence VK (the first height image; `.vk6`/`.vk7` hold it in a zip) | [`vk`] |
//! | `.datx` | Zygo Mx (HDF5: the surface map, its `No Data` marker, unit and lateral converters) | [`datx`] |
//! | `.spm`, `.001`... | Bruker Nanoscope (versions 4.3 to 9, 16/32-bit; the height channel) | [`nanoscope`] |
//! | `.dat` | Zygo MetroPro binary (recognised by its magic number; else a text matrix) | [`zygo`] |
//! | `.xyz` | three text columns x y z on a regular grid | [`xyz`] |
//! | `.txt`, `.csv`, `.asc` | text matrix ([`crate::io::csv`]; also the SPIP header of Gwyddion's `.asc`: `x-length`, `y-length` in nm, `Bit2nm`) | |
//! | `.png` | 16/8-bit grayscale with a `pCAL` height scale ([`crate::io::png`] + [`png_scale`]) | |
//! | `.tif`, `.tiff` | grayscale TIFF ([`crate::io::tiff`]) | |
//! | `.npy` | NumPy array ([`crate::io::npy`]) | |
//! | `.exr` | OpenEXR height map, as doefab writes them (one float channel, pitch and unit attributes; [`crate::io::exr`]) | |
//!
//! Every format reader returns a [`ScanRaw`]: a [`RawMap`] whose non-measured points are NaN,
//! plus what the file says about its origin and anything worth a warning. The pitch, height
//! unit and plausibility are then resolved exactly as for design maps
//! ([`crate::io::heightmap::heightmap_from_raw`]): the file's statement or the caller's, never a
//! guess; a conflict between the two is refused; a missing one is refused with the option to
//! pass; a peak-to-valley height outside 1e-11..1e-3 m is refused with the unit that would fit
//! when the caller stated the unit, and a warning when the file did (the file is trusted; a
//! comparison with a design refuses it, [`crate::io::heightmap::check_relief`]).
//! NaN values become invalid samples of the grid's validity mask (set to 0, never data).
//!
//! Errors name the file and, for binary formats, the byte offset where the content stopped
//! making sense (truncation, a bad field). Instrument formats that are known but not read are
//! refused by name, with what to export instead ([`unread`]).

pub mod al3d;
pub mod datx;
pub mod frt;
pub mod gsf;
pub mod gwy;
pub mod lext;
pub mod nanoscope;
pub mod opd;
pub mod opdx;
pub mod plu;
pub mod plux;
pub mod png_scale;
pub mod raw;
pub mod sdf;
pub mod sur;
pub mod tmd;
pub mod unread;
pub mod vk;
pub mod x3p;
pub mod xyz;
pub mod zygo;

use std::path::Path;

use crate::error::{DataCause, Error, Result};
use crate::grid::Grid;
use crate::io::heightmap::{heightmap_from_raw, ReadOptions};
use crate::io::raw_map::{RawMap, SampleKind};
pub use raw::{ScanFormat, ScanRaw};

/// What the caller states about a scan (from the command line).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ScanOptions {
    /// `[x, y]` sample pitch in metres (`--pitch`), for files that carry none.
    pub pitch: Option<[f64; 2]>,
    /// Metres per stored value for files that state no height unit (`--z-unit`, e.g. 1e-9).
    pub z_unit: Option<f64>,
    /// Metres per count for integer images without a usable scale (`--z-scale`).
    pub z_scale: Option<f64>,
    /// Metres added to every height after scaling (`--z-offset`).
    pub z_offset: Option<f64>,
    /// Skips the plausibility check on the peak-to-valley height.
    pub allow_implausible: bool,
}

impl ScanOptions {
    fn read_options(&self) -> ReadOptions {
        ReadOptions {
            pitch: self.pitch,
            unit: self.z_unit,
            z_scale: self.z_scale,
            z_offset: self.z_offset,
            channel: None,
            allow_implausible: self.allow_implausible,
        }
    }
}

/// A scan read into a grid of heights (metres), with the file's metadata and warnings.
#[derive(Debug, Clone, PartialEq)]
pub struct Scan {
    /// Heights in metres; non-measured points are invalid samples.
    pub grid: Grid,
    /// The file format the scan was read as.
    pub format: ScanFormat,
    /// Every key/value the file carries (header fields, XML elements), in file order.
    pub metadata: Vec<(String, String)>,
    /// Problems that did not stop the read (checksum mismatch, odd header values).
    pub warnings: Vec<String>,
}

/// Picks the format from the extension (and, for `.dat` and `.sdf`, the first bytes).
pub fn detect_format(path: &Path, head: &[u8]) -> Result<ScanFormat> {
    let ext = path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).unwrap_or_default();
    Ok(match ext.as_str() {
        "x3p" => ScanFormat::X3p,
        "gsf" => ScanFormat::Gsf,
        "sdf" => {
            if head.first() == Some(&b'b') {
                ScanFormat::SdfBinary
            } else {
                ScanFormat::SdfAscii
            }
        }
        "sur" => ScanFormat::Sur,
        "gwy" => ScanFormat::Gwy,
        "opd" => ScanFormat::Opd,
        "opdx" => ScanFormat::Opdx,
        "plu" => ScanFormat::Plu,
        "plux" => ScanFormat::Plux,
        "al3d" => ScanFormat::Al3d,
        "tmd" => ScanFormat::Tmd,
        "vk4" | "vk6" | "vk7" => ScanFormat::Vk,
        "lext" => ScanFormat::Lext,
        "frt" => ScanFormat::Frt,
        "datx" => ScanFormat::Datx,
        "spm" => ScanFormat::Nanoscope,
        e if e.len() == 3 && e.bytes().all(|c| c.is_ascii_digit()) && nanoscope::has_magic(head) => {
            ScanFormat::Nanoscope
        }
        "dat" if zygo::has_magic(head) => ScanFormat::MetroPro,
        "xyz" => ScanFormat::Xyz,
        "txt" | "csv" | "asc" | "dat" => ScanFormat::Matrix,
        "png" => ScanFormat::Png,
        "tif" | "tiff" => ScanFormat::Tiff,
        "npy" => ScanFormat::Npy,
        "exr" => ScanFormat::Exr,
        _ => {
            if let Some(why) = unread::refusal(&ext) {
                return Err(Error::malformed(path, why));
            }
            return Err(Error::signature(
                path,
                format!(
                    "unknown scan format '.{ext}' (expected .x3p, .gsf, .sdf, .sur, .gwy, .opd, .opdx, .plu, .plux, .al3d, .tmd, .vk4/.vk6/.vk7, .lext, .frt, .datx, .spm, .dat, .xyz, \
                     .txt/.csv/.asc, .png, .tif/.tiff, .npy or .exr)"
                ),
            ));
        }
    })
}

/// Reads the stored numbers and metadata of a scan file (no unit resolution).
pub fn read_scan_raw(path: &Path, opts: &ScanOptions) -> Result<ScanRaw> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    decode_scan_raw(path, &bytes, opts)
}

/// Decodes the bytes of a scan file; `path` names it in errors and gives the extension.
pub fn decode_scan_raw(path: &Path, bytes: &[u8], opts: &ScanOptions) -> Result<ScanRaw> {
    let format = detect_format(path, bytes)?;
    let text = || {
        std::str::from_utf8(bytes).map_err(|e| {
            let at = e.valid_up_to();
            Error::malformed(path, format!("byte offset {at}: not UTF-8 text")).at(at as u64)
        })
    };
    match format {
        ScanFormat::X3p => x3p::decode(path, bytes),
        ScanFormat::Gsf => gsf::decode(path, bytes),
        ScanFormat::SdfAscii | ScanFormat::SdfBinary => sdf::decode(path, bytes),
        ScanFormat::Sur => sur::decode(path, bytes),
        ScanFormat::Gwy => gwy::decode(path, bytes),
        ScanFormat::MetroPro => zygo::decode(path, bytes),
        ScanFormat::Opd => opd::decode(path, bytes),
        ScanFormat::Opdx => opdx::decode(path, bytes),
        ScanFormat::Plu => plu::decode(path, bytes),
        ScanFormat::Plux => plux::decode(path, bytes),
        ScanFormat::Al3d => al3d::decode(path, bytes),
        ScanFormat::Tmd => tmd::decode(path, bytes),
        ScanFormat::Vk => vk::decode(path, bytes),
        ScanFormat::Lext => lext::decode(path, bytes),
        ScanFormat::Frt => frt::decode(path, bytes),
        ScanFormat::Datx => datx::decode(path, bytes),
        ScanFormat::Nanoscope => nanoscope::decode(path, bytes),
        ScanFormat::Xyz => xyz::parse(path, text()?, opts.z_unit),
        ScanFormat::Matrix => {
            let mut raw = crate::io::csv::parse_csv(path, text()?)?;
            spip_header(path, &mut raw)?;
            Ok(ScanRaw::new(raw, format))
        }
        ScanFormat::Png => png_scale::decode(path, bytes, opts.z_scale.is_some()),
        ScanFormat::Tiff => Ok(ScanRaw::new(crate::io::tiff::decode_tiff(path, bytes)?, format)),
        ScanFormat::Npy => {
            let (_, arr) = crate::io::npy::decode_npy(path, bytes)?;
            let shape = arr.shape().to_vec();
            let values = match shape.as_slice() {
                [r, c] | [r, c, 1] if *r > 0 && *c > 0 => arr
                    .into_shape_with_order((shape[0], shape[1]))
                    .map_err(|e| Error::malformed(path, format!("cannot view as a 2-D map: {e}")))?,
                _ => return Err(Error::unsupported(path, format!("shape {shape:?} is not a 2-D map"))),
            };
            let raw = RawMap {
                values,
                kind: SampleKind::Float,
                pitch: None,
                unit: None,
                metadata: vec![],
                scale_hint: None,
            };
            Ok(ScanRaw::new(raw, format))
        }
        ScanFormat::Exr => Ok(ScanRaw::new(crate::io::exr::decode_exr(path, bytes, None)?, format)),
    }
}

/// Applies the SPIP ASCII header (Gwyddion's `.asc` export: `# x-length = 200000` field size
/// in nm, `# Bit2nm = 1.0` nm per value) to a text matrix that states no pitch or unit itself.
fn spip_header(path: &Path, raw: &mut RawMap) -> Result<()> {
    let get = |k: &str| raw.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.trim().to_string());
    let num = |k: &str| -> Result<Option<f64>> {
        match get(k) {
            None => Ok(None),
            Some(v) => {
                v.parse::<f64>().ok().filter(|x| x.is_finite() && *x > 0.0).map(Some).ok_or_else(|| {
                    Error::malformed(path, format!("header '{k} = {v}' is not a positive number"))
                })
            }
        }
    };
    let (rows, cols) = raw.values.dim();
    if raw.pitch.is_none() {
        if let (Some(xl), Some(yl)) = (num("x-length")?, num("y-length")?) {
            raw.pitch = Some([xl * 1e-9 / cols as f64, yl * 1e-9 / rows as f64]);
        }
    }
    if raw.unit.is_none() {
        if let Some(b) = num("Bit2nm")? {
            raw.unit = Some(b * 1e-9);
        }
    }
    Ok(())
}

/// Reads a scan into a height grid (see the module docs for how pitch and units are resolved).
pub fn read_scan(path: &Path, opts: &ScanOptions) -> Result<Scan> {
    let raw = read_scan_raw(path, opts)?;
    scan_from_raw(path, raw, opts)
}

/// A height map's message about its `unit` ([`ReadOptions`]) as the scan's: `z_unit`.
fn as_z_unit(reason: String) -> String {
    reason.replace("`unit`", "`z_unit`")
}

/// [`as_z_unit`] on a parameter error of the height-map reader.
fn z_unit_error(e: Error) -> Error {
    match e {
        Error::Parameter { name, reason, allowed } => {
            let name = if name == "unit" { "z_unit".to_string() } else { name };
            Error::Parameter { name, reason: as_z_unit(reason), allowed }
        }
        e => e,
    }
}

/// Resolves a [`ScanRaw`] into a [`Scan`] (the second half of [`read_scan`]).
pub fn scan_from_raw(path: &Path, sr: ScanRaw, opts: &ScanOptions) -> Result<Scan> {
    let ScanRaw { raw, format, origin, mut warnings } = sr;
    if !raw.values.iter().any(|v| v.is_finite()) {
        return Err(Error::data(
            DataCause::Empty,
            format!(
                "{}: no measured point in the scan ({} x {} samples, all non-measured)",
                path.display(),
                raw.values.nrows(),
                raw.values.ncols()
            ),
        ));
    }
    let metadata = raw.metadata.clone();
    // A file that states its own height unit is trusted: an implausible relief is a warning
    // here (a 7 mm part is a part), and only a comparison with a DOE design refuses it.
    let stated = raw.unit.is_some() && opts.z_unit.is_none() && opts.z_scale.is_none();
    let mut read = opts.read_options();
    if stated && !read.allow_implausible {
        match crate::io::heightmap::check_plausibility(path, &raw, &read) {
            // The relief is implausible in the file's own unit (the refusal states the
            // plausible range): a warning here, as the comment above says.
            Err(Error::Parameter { name, reason, allowed: Some(_) }) if name == "unit" => {
                warnings.push(format!("{} (kept: the file states its unit)", as_z_unit(reason)));
            }
            other => other.map_err(z_unit_error)?,
        }
        // Checked once, here.
        read.allow_implausible = true;
    }
    let mut grid = heightmap_from_raw(path, raw, &read).map_err(z_unit_error)?;
    if let Some(o) = origin {
        if o.iter().all(|v| v.is_finite()) {
            grid = grid.with_origin(o);
        } else {
            warnings.push(format!("the file's origin {o:?} is not finite; the grid is centred instead"));
        }
    }
    Ok(Scan { grid, format, metadata, warnings })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_by_extension_and_magic() {
        let p = |s: &str| Path::new(s).to_path_buf();
        assert_eq!(detect_format(&p("a.X3P"), b"PK").unwrap(), ScanFormat::X3p);
        assert_eq!(detect_format(&p("a.sdf"), b"bISO").unwrap(), ScanFormat::SdfBinary);
        assert_eq!(detect_format(&p("a.sdf"), b"aISO").unwrap(), ScanFormat::SdfAscii);
        assert_eq!(detect_format(&p("a.dat"), b"\x88\x1b\x03\x6f....").unwrap(), ScanFormat::MetroPro);
        assert_eq!(detect_format(&p("a.dat"), b"1 2 3\n").unwrap(), ScanFormat::Matrix);
        assert_eq!(detect_format(&p("a.gwy"), b"GWYP").unwrap(), ScanFormat::Gwy);
        assert_eq!(detect_format(&p("a.AL3D"), al3d::MAGIC).unwrap(), ScanFormat::Al3d);
        assert_eq!(detect_format(&p("a.tmd"), tmd::MAGIC).unwrap(), ScanFormat::Tmd);
        assert_eq!(detect_format(&p("a.VK6"), b"VK6").unwrap(), ScanFormat::Vk);
        assert_eq!(detect_format(&p("a.frt"), frt::MAGIC).unwrap(), ScanFormat::Frt);
        assert_eq!(detect_format(&p("a.LEXT"), b"II*\0").unwrap(), ScanFormat::Lext);
        assert_eq!(detect_format(&p("a.DATX"), datx::MAGIC).unwrap(), ScanFormat::Datx);
        assert_eq!(detect_format(&p("a.opdx"), opdx::MAGIC).unwrap(), ScanFormat::Opdx);
        assert_eq!(detect_format(&p("a.spm"), b"").unwrap(), ScanFormat::Nanoscope);
        assert_eq!(detect_format(&p("a.003"), nanoscope::MAGIC).unwrap(), ScanFormat::Nanoscope);
        assert!(detect_format(&p("a.003"), b"x").is_err());
        assert!(detect_format(&p("a.mnt"), b"").unwrap_err().to_string().contains("a.mnt"));
    }
}
