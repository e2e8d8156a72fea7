//! Zygo MetroPro binary data files (`.dat`), the phase (height) map.
//!
//! Big-endian header; the offsets used here (bytes from the start of the file) follow the
//! MetroPro Reference Guide's "Data file format" section (Zygo OMP-0347), as also read by
//! Gwyddion's `metropro.c`:
//!
//! | offset | type | field |
//! |---|---|---|
//! | 0 | u32 | magic: 0x881B036F (header format 1), 0x881B0370 (2), 0x881B0371 (3) |
//! | 4 | i16 | header_format (1, 2 or 3) |
//! | 6 | i32 | header_size (834 for formats 1 and 2, 4096 for 3) |
//! | 52, 54 | u16 | ac_width, ac_height (intensity map) |
//! | 56 | i16 | ac_n_buckets |
//! | 60 | i32 | ac_n_bytes (intensity data size: 2 x buckets x width x height) |
//! | 64, 66 | i16 | cn_org_x, cn_org_y (phase map origin on the camera, pixels) |
//! | 68, 70 | u16 | cn_width, cn_height (phase map) |
//! | 72 | i32 | cn_n_bytes (phase data size: 4 x width x height) |
//! | 164 | f32 | intf_scale_factor S (0.5 for a reflection interferometer) |
//! | 168 | f32 | wavelength_in, metres |
//! | 176 | f32 | obliquity_factor O |
//! | 184 | f32 | camera_res (lateral resolution, metres per pixel; 0 = unknown) |
//! | 218 | i16 | phase_res: 0 -> R = 4096, 1 -> R = 32768, 2 -> R = 131072 (format 3) |
//! | 232 | i16 | data_inverted (1 = heights negated) |
//!
//! The data follow the header: first the intensity buckets (u16), then the phase map: i32 per
//! pixel, row by row; values >= 2147483640 are non-measured. Heights:
//! `z = phase * S * O * wavelength / R` metres. Taking R = 4096 for a high-resolution file
//! (phase_res = 1) makes every height 8 times too large.

use std::path::Path;

use crate::error::Result;
use crate::io::raw_map::{RawMap, SampleKind};
use crate::io::scan::raw::{shape, Bin, ScanFormat, ScanRaw};

const MAGICS: [u32; 3] = [0x881B_036F, 0x881B_0370, 0x881B_0371];
/// Phase values at or above this mark non-measured pixels.
pub const INVALID_PHASE: i32 = 2_147_483_640;

/// True when `head` starts with a MetroPro magic number (or, shorter than one, begins one: a
/// truncated MetroPro file).
pub fn has_magic(head: &[u8]) -> bool {
    if head.len() < 4 {
        return !head.is_empty() && MAGICS.iter().any(|m| m.to_be_bytes().starts_with(head));
    }
    MAGICS.contains(&u32::from_be_bytes([head[0], head[1], head[2], head[3]]))
}

/// The phase resolution R for a `phase_res` code.
pub fn phase_resolution(code: i16) -> Option<f64> {
    match code {
        0 => Some(4096.0),
        1 => Some(32768.0),
        2 => Some(131072.0),
        _ => None,
    }
}

/// Decodes a MetroPro file (see the module docs).
pub fn decode(path: &Path, bytes: &[u8]) -> Result<ScanRaw> {
    let b = Bin::new(path, bytes);
    b.take(0, 4, "the magic number")?;
    if !has_magic(bytes) {
        return Err(b.signature(0, "not a MetroPro file: bad magic number"));
    }
    let fmt = b.i16be(4, "header_format")?;
    let hsize = b.i32be(6, "header_size")?;
    let expected = match fmt {
        1 | 2 => 834,
        3 => 4096,
        _ => return Err(b.bad(4, format!("header_format {fmt} (1, 2 or 3 expected)"))),
    };
    if hsize != expected {
        return Err(b.bad(6, format!("header_size {hsize} for header format {fmt} ({expected} expected)")));
    }
    let hsize = hsize as usize;
    b.take(0, hsize, "the header")?;
    let (aw, ah) = (b.u16be(52, "ac_width")? as usize, b.u16be(54, "ac_height")? as usize);
    let buckets = b.i16be(56, "ac_n_buckets")?;
    let ac_bytes = b.i32be(60, "ac_n_bytes")?;
    if buckets < 0 || ac_bytes < 0 || ac_bytes as usize != 2 * buckets as usize * aw * ah {
        return Err(b.bad(
            60,
            format!("ac_n_bytes {ac_bytes} is not 2 x {buckets} buckets x {aw} x {ah} intensity pixels"),
        ));
    }
    let (org_x, org_y) = (b.i16be(64, "cn_org_x")?, b.i16be(66, "cn_org_y")?);
    let (w, h) = (b.u16be(68, "cn_width")? as usize, b.u16be(70, "cn_height")? as usize);
    if w == 0 || h == 0 {
        return Err(b.bad(68, format!("the phase map is {w} x {h}: the file holds no height data")));
    }
    let cn_bytes = b.i32be(72, "cn_n_bytes")?;
    if cn_bytes < 0 || cn_bytes as usize != 4 * w * h {
        return Err(b.bad(72, format!("cn_n_bytes {cn_bytes} is not 4 x {w} x {h}")));
    }
    let s = b.f32be(164, "intf_scale_factor")? as f64;
    let wavelength = b.f32be(168, "wavelength_in")? as f64;
    let o = b.f32be(176, "obliquity_factor")? as f64;
    let camera_res = b.f32be(184, "camera_res")? as f64;
    let res_code = b.i16be(218, "phase_res")?;
    let r = phase_resolution(res_code)
        .ok_or_else(|| b.bad(218, format!("phase_res {res_code} (0, 1 or 2 expected)")))?;
    if res_code == 2 && fmt != 3 {
        return Err(b.bad(218, "phase_res 2 (131072) exists only in header format 3"));
    }
    let inverted = b.i16be(232, "data_inverted")?;
    if !(wavelength.is_finite() && wavelength > 0.0 && wavelength < 1e-4) {
        return Err(b.bad(168, format!("wavelength_in {wavelength} m is not a wavelength")));
    }
    if !(s.is_finite() && s != 0.0 && o.is_finite() && o > 0.0) {
        return Err(b.bad(164, format!("intf_scale_factor {s} / obliquity_factor {o} are not usable")));
    }
    let mut k = s * o * wavelength / r;
    if inverted == 1 {
        k = -k;
    }
    let start = hsize + ac_bytes as usize;
    let data = b.take(start, 4 * w * h, &format!("the {w} x {h} phase map"))?;
    if bytes.len() > start + 4 * w * h {
        return Err(b.bad(
            start + 4 * w * h,
            format!("{} bytes follow the phase map", bytes.len() - start - 4 * w * h),
        ));
    }
    let values: Vec<f64> = data
        .chunks_exact(4)
        .map(|c| {
            let p = i32::from_be_bytes([c[0], c[1], c[2], c[3]]);
            if p >= INVALID_PHASE {
                f64::NAN
            } else {
                p as f64 * k
            }
        })
        .collect();
    let values = shape(path, h, w, values)?;
    let pitch = (camera_res.is_finite() && camera_res > 0.0).then_some([camera_res, camera_res]);
    let metadata = vec![
        ("header_format".to_string(), fmt.to_string()),
        ("wavelength".to_string(), format!("{wavelength:e} m")),
        ("intf_scale_factor".to_string(), format!("{s}")),
        ("obliquity_factor".to_string(), format!("{o}")),
        ("phase_res".to_string(), format!("{res_code} (R = {r})")),
        ("data_inverted".to_string(), inverted.to_string()),
        ("comment".to_string(), b.text(80, 82, "comment")?),
    ];
    let raw = RawMap { values, kind: SampleKind::Float, pitch, unit: Some(1.0), metadata, scale_hint: None };
    let mut sr = ScanRaw::new(raw, ScanFormat::MetroPro);
    if let Some(p) = pitch {
        sr.origin = Some([org_x as f64 * p[0], org_y as f64 * p[1]]);
    } else {
        sr.warnings.push("camera_res is 0: the file states no lateral resolution".to_string());
    }
    Ok(sr)
}

/// Field values for [`encode`].
#[derive(Debug, Clone)]
pub struct MetroProFields {
    /// Header format 1, 2 or 3 (the magic and the header size follow from it: 834 or 4096
    /// bytes).
    pub header_format: i16,
    /// Phase resolution code: 0 (R = 4096), 1 (32768), 2 (131072, format 3 only).
    pub phase_res: i16,
    /// `wavelength_in`, metres.
    pub wavelength: f32,
    /// `intf_scale_factor` S (0.5 for a reflection interferometer).
    pub scale_factor: f32,
    /// `obliquity_factor` O.
    pub obliquity: f32,
    /// Lateral resolution, metres per pixel (0: unknown).
    pub camera_res: f32,
    /// `data_inverted`: heights negated.
    pub inverted: bool,
    /// Intensity buckets written before the phase map (each `width x height` u16).
    pub buckets: i16,
}

/// Writes a MetroPro file byte by byte from the offsets in the module docs (for tests):
/// `phase` holds raw phase counts (`i32`, >= [`INVALID_PHASE`] = non-measured).
pub fn encode(f: &MetroProFields, phase: &ndarray::Array2<i32>) -> Vec<u8> {
    let (h, w) = phase.dim();
    let hsize: usize = if f.header_format == 3 { 4096 } else { 834 };
    let mut b = vec![0u8; hsize];
    let put = |b: &mut Vec<u8>, off: usize, v: &[u8]| b[off..off + v.len()].copy_from_slice(v);
    put(&mut b, 0, &MAGICS[(f.header_format - 1) as usize].to_be_bytes());
    put(&mut b, 4, &f.header_format.to_be_bytes());
    put(&mut b, 6, &(hsize as i32).to_be_bytes());
    put(&mut b, 52, &(w as u16).to_be_bytes());
    put(&mut b, 54, &(h as u16).to_be_bytes());
    put(&mut b, 56, &f.buckets.to_be_bytes());
    put(&mut b, 60, &((2 * f.buckets as usize * w * h) as i32).to_be_bytes());
    put(&mut b, 68, &(w as u16).to_be_bytes());
    put(&mut b, 70, &(h as u16).to_be_bytes());
    put(&mut b, 72, &((4 * w * h) as i32).to_be_bytes());
    put(&mut b, 80, b"synthetic");
    put(&mut b, 164, &f.scale_factor.to_be_bytes());
    put(&mut b, 168, &f.wavelength.to_be_bytes());
    put(&mut b, 176, &f.obliquity.to_be_bytes());
    put(&mut b, 184, &f.camera_res.to_be_bytes());
    put(&mut b, 218, &f.phase_res.to_be_bytes());
    put(&mut b, 232, &(f.inverted as i16).to_be_bytes());
    for k in 0..(f.buckets as usize * w * h) {
        b.extend_from_slice(&((k % 4000) as u16).to_be_bytes());
    }
    for p in phase {
        b.extend_from_slice(&p.to_be_bytes());
    }
    b
}
