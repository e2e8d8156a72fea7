//! 8/16-bit grayscale PNG scans with a height scale in the `pCAL` chunk.
//!
//! The counts and pitch come from [`crate::io::png::decode_png`]. The PNG specification
//! (section 11.3.3.2, `pCAL`) maps a stored sample X (with `x0 = 0`, `x1 = 2^bits - 1`) to
//! `p0 + p1 * X / (x1 - x0)` for equation type 0 (linear). Gwyddion 2.62 writes instead
//! `p0 = ZMin` and `p1` = the height of one count, `range / 65535` (so that count 65535 maps to
//! ZMax), while it quantizes with 65536 bins, `count = min(floor(65536 (z - ZMin) / range),
//! 65535)`; read by the specification's formula its files would span 65535 times too little.
//! So files written by Gwyddion (a `Software` text `Gwyddion` or `Gwy::` keys) are read as
//! `z = p0 + p1 * X`, cross-checked against `Gwy::ZMax = p0 + (2^bits - 1) p1` (a warning if
//! not); other files by the specification's formula. Either way a height is known to one count:
//! the bin mismatch moves a read height by at most one count from the true one. The unit string
//! must be a length unit.
//!
//! Without a `pCAL` chunk the counts need an explicit `--z-scale` (never guessed). An explicit
//! `--z-scale` overrides `pCAL` (with a warning).

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::raw_map::SampleKind;
use crate::io::scan::raw::{scan_length_unit, ScanFormat, ScanRaw};

/// The fields of a `pCAL` chunk.
#[derive(Debug, Clone, PartialEq)]
pub struct PCal {
    /// Calibration name (the chunk's keyword).
    pub name: String,
    /// Stored sample value that maps to the first end of the range (`X0`).
    pub x0: i32,
    /// Stored sample value that maps to the other end of the range (`X1`).
    pub x1: i32,
    /// Equation type: 0 linear (the only one read), 1 base-e exponential, 2 arbitrary-base
    /// exponential, 3 hyperbolic.
    pub equation: u8,
    /// Unit of the physical values (a length unit for a height scan: `m`, `um`, `nm`, ...).
    pub unit: String,
    /// The equation's parameters `p0, p1, ...`, in `unit`; the linear one has two.
    pub params: Vec<f64>,
    /// Byte offset of the chunk's data in the file.
    pub offset: usize,
}

/// Finds and parses the `pCAL` chunk of a PNG file's bytes (`None` when absent).
pub fn find_pcal(path: &Path, bytes: &[u8]) -> Result<Option<PCal>> {
    let mut p = 8usize;
    while p + 8 <= bytes.len() {
        let n = u32::from_be_bytes([bytes[p], bytes[p + 1], bytes[p + 2], bytes[p + 3]]) as usize;
        let kind = &bytes[p + 4..p + 8];
        let start = p + 8;
        let Some(end) = start.checked_add(n).filter(|&e| e <= bytes.len()) else {
            return Err(Error::truncated(
                path,
                bytes.len() as u64,
                format!("byte offset {p}: PNG chunk of {n} bytes runs past the end"),
            ));
        };
        if kind == b"pCAL" {
            return parse_pcal(path, &bytes[start..end], start).map(Some);
        }
        if kind == b"IEND" {
            break;
        }
        p = end + 4;
    }
    Ok(None)
}

fn parse_pcal(path: &Path, d: &[u8], offset: usize) -> Result<PCal> {
    let bad = |at: usize, what: &str| {
        Error::malformed(path, format!("byte offset {}: pCAL {what}", offset + at)).at((offset + at) as u64)
    };
    let nul = d.iter().position(|&c| c == 0).ok_or_else(|| bad(0, "keyword is not terminated"))?;
    let name: String = d[..nul].iter().map(|&c| c as char).collect();
    let f = nul + 1;
    if d.len() < f + 10 {
        return Err(bad(d.len(), "is truncated"));
    }
    let x0 = i32::from_be_bytes([d[f], d[f + 1], d[f + 2], d[f + 3]]);
    let x1 = i32::from_be_bytes([d[f + 4], d[f + 5], d[f + 6], d[f + 7]]);
    let (equation, np) = (d[f + 8], d[f + 9] as usize);
    let rest = &d[f + 10..];
    let mut parts = rest.split(|&c| c == 0);
    let unit: String = parts.next().unwrap_or_default().iter().map(|&c| c as char).collect();
    let mut params = Vec::new();
    for s in parts {
        let t = String::from_utf8_lossy(s);
        params.push(
            t.trim().parse::<f64>().map_err(|_| bad(f + 10, &format!("parameter '{t}' is not a number")))?,
        );
    }
    if params.len() != np {
        return Err(bad(f + 9, &format!("declares {np} parameters but holds {}", params.len())));
    }
    Ok(PCal { name, x0, x1, equation, unit, params, offset })
}

/// Decodes a PNG scan; `explicit_scale` is true when the caller gives `--z-scale`.
pub fn decode(path: &Path, bytes: &[u8], explicit_scale: bool) -> Result<ScanRaw> {
    let mut raw = crate::io::png::decode_png(path, bytes)?;
    let pcal = find_pcal(path, bytes)?;
    let mut warnings = Vec::new();
    match (pcal, explicit_scale) {
        (Some(_), true) => {
            warnings.push("the pCAL height scale is ignored in favour of `z_scale`".to_string())
        }
        (None, _) => {}
        (Some(c), false) => {
            let SampleKind::Counts { bits } = raw.kind else {
                return Err(Error::unsupported(path, "pCAL on a non-integer image"));
            };
            if c.equation != 0 || c.params.len() != 2 {
                return Err(Error::param(
                    "z_scale",
                    format!(
                        "{}: pCAL equation type {} is not the linear one (0) this reader applies: pass `z_scale`",
                        path.display(),
                        c.equation
                    ),
                ));
            }
            let s = scan_length_unit(&c.unit).ok_or_else(|| {
                Error::malformed(
                    path,
                    format!("byte offset {}: pCAL unit '{}' is not a length unit", c.offset, c.unit),
                )
                .at(c.offset as u64)
            })?;
            let get =
                |k: &str| raw.metadata.iter().find(|(key, _)| key == k).map(|(_, v)| v.trim().to_string());
            let gwyddion = get("Software").as_deref() == Some("Gwyddion")
                || raw.metadata.iter().any(|(k, _)| k.starts_with("Gwy::"));
            let (p0, p1) = (c.params[0], c.params[1]);
            let full = ((1u64 << bits) - 1) as f64;
            // x0 and x1 are i32: their difference is taken in f64, where it cannot overflow.
            let (x0, x1) = (f64::from(c.x0), f64::from(c.x1));
            if x1 == x0 {
                let what = format!("byte offset {}: pCAL x0 = x1", c.offset);
                return Err(Error::malformed(path, what).at(c.offset as u64));
            }
            // z = z0 + per_count * stored count.
            let (z0, per_count) = if gwyddion {
                if (x0, x1) != (0.0, full) {
                    return Err(Error::malformed(
                        path,
                        format!(
                            "byte offset {}: pCAL x0 = {}, x1 = {} in a file written by Gwyddion, which writes 0 and {full} for {bits}-bit samples",
                            c.offset, c.x0, c.x1
                        ),
                    )
                    .at(c.offset as u64));
                }
                (p0, p1)
            } else {
                // The specification: X = x0 + stored (x1 - x0) / (2^bits - 1), z = p0 + p1 X / (x1 - x0).
                (p0 + p1 * x0 / (x1 - x0), p1 / full)
            };
            if gwyddion {
                let zmax = get("Gwy::ZMax").and_then(|v| v.parse::<f64>().ok());
                if let Some(zmax) = zmax {
                    let predicted = (p0 + full * p1) * s;
                    if (predicted - zmax).abs() > 1e-6 * (full * p1 * s).abs() {
                        warnings.push(format!(
                            "pCAL (p0 = {p0:e}, p1 = {p1:e}) predicts ZMax = {predicted:e} m but Gwy::ZMax = {zmax:e} m"
                        ));
                    }
                }
            }
            raw.values.mapv_inplace(|x| (z0 + per_count * x) * s);
            raw.kind = SampleKind::Float;
            raw.unit = Some(1.0);
            raw.metadata.push((
                "pCAL".to_string(),
                format!(
                    "{}: z = {z0:e} + {per_count:e} * count [{}] ({})",
                    c.name,
                    c.unit,
                    if gwyddion { "Gwyddion's form" } else { "PNG specification's form" }
                ),
            ));
        }
    }
    let mut sr = ScanRaw::new(raw, ScanFormat::Png);
    sr.warnings = warnings;
    Ok(sr)
}
