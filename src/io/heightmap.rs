//! One entry point for design height maps, whatever the file format: [`read_heightmap`].
//!
//! The format is chosen by extension: `.npy` ([`super::npy`]), `.exr` ([`super::exr`]),
//! `.tif`/`.tiff` ([`super::tiff`]), `.png` ([`super::png`]), `.csv`/`.txt`/`.asc`/`.dat`
//! ([`super::csv`]). Each format reader returns a [`RawMap`]: the stored numbers plus what the
//! file itself states about pitch and value unit. This module then resolves them:
//!
//! * **pitch**: from the file, or from [`ReadOptions::pitch`]. When both are present and
//!   differ (relative difference above 1e-6, f32 attributes hold ~7 digits), the read is
//!   refused with both values; when neither is, it is refused with a request for `--pitch`.
//!   Nothing is guessed.
//! * **height scale** `k` (metres per stored value): floating-point data takes the value unit
//!   from the file or [`ReadOptions::unit`] (same rules as the pitch); integer counts images
//!   (PNG, 8/16-bit TIFF) take it from [`ReadOptions::z_scale`] only (metres per count),
//!   because such files carry no trustworthy scale (Gwyddion's `pCAL` chunk, for one, does
//!   not follow the PNG specification's linear form).
//! * heights `h = k v + z_offset` (metres).
//! * **plausibility**: a design's peak-to-valley height lies between 1e-11 m and 1e-3 m
//!   (one picometre-scale step to a millimetre of relief). Outside that range the stated unit
//!   is almost surely wrong; the read is refused and the unit that would make the map plausible
//!   is suggested (e.g. values ~1e-6 stated in "um" look like metres already).
//! * NaN and infinite values become invalid samples in the grid's mask (never dropped, never
//!   filled here).

use std::path::Path;

use crate::error::{Allowed, DataCause, Error, Result};
use crate::grid::{Grid, Unit};
use crate::io::raw_map::{RawMap, SampleKind};
use crate::units::format_length;

/// Smallest plausible peak-to-valley height of a design map, metres.
pub const MIN_PLAUSIBLE_PV: f64 = 1e-11;
/// Largest plausible peak-to-valley height of a design map, metres.
pub const MAX_PLAUSIBLE_PV: f64 = 1e-3;

/// The height-map formats [`read_heightmap`] understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// NumPy `.npy` array ([`super::npy`]).
    Npy,
    /// OpenEXR `.exr` image ([`super::exr`]).
    Exr,
    /// TIFF `.tif`/`.tiff` image ([`super::tiff`]).
    Tiff,
    /// PNG `.png` image ([`super::png`]).
    Png,
    /// Delimited text `.csv`/`.txt`/`.asc`/`.dat` ([`super::csv`]).
    Csv,
}

impl Format {
    /// The format named by a path's extension (case-insensitive).
    pub fn from_path(path: &Path) -> Result<Format> {
        let ext =
            path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).unwrap_or_default();
        Ok(match ext.as_str() {
            "npy" => Format::Npy,
            "exr" => Format::Exr,
            "tif" | "tiff" => Format::Tiff,
            "png" => Format::Png,
            "csv" | "txt" | "asc" | "dat" => Format::Csv,
            _ => {
                return Err(Error::signature(
                    path,
                    format!(
                        "unknown height-map format '.{ext}' (expected .npy, .exr, .tif/.tiff, .png, \
                         .csv/.txt/.asc/.dat)"
                    ),
                ))
            }
        })
    }
}

/// What the caller states about a height map (from the command line).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReadOptions {
    /// `[x, y]` sample pitch in metres (`--pitch`).
    pub pitch: Option<[f64; 2]>,
    /// Metres per stored value for floating-point data (`--unit`, e.g. 1e-6 for "um").
    pub unit: Option<f64>,
    /// Metres per count for integer images (`--z-scale`), required for PNG and 8/16-bit TIFF.
    pub z_scale: Option<f64>,
    /// Metres added after scaling (`--z-offset`); 0 when `None`.
    pub z_offset: Option<f64>,
    /// The channel to read from a multi-channel OpenEXR file (`--channel`).
    pub channel: Option<String>,
    /// Skips the plausibility check on the peak-to-valley height (for unusual parts).
    pub allow_implausible: bool,
}

/// Reads the stored numbers and metadata of a height map, dispatching on the extension.
/// `channel` selects a channel of a multi-channel OpenEXR file.
pub fn read_raw(path: &Path, channel: Option<&str>) -> Result<RawMap> {
    match Format::from_path(path)? {
        Format::Npy => super::npy::read_npy(path),
        Format::Exr => super::exr::read_exr(path, channel),
        Format::Tiff => super::tiff::read_tiff(path),
        Format::Png => super::png::read_png(path),
        Format::Csv => super::csv::read_csv(path),
    }
}

/// Decodes the bytes of a height-map file (what [`read_raw`] returns for the file holding them),
/// choosing the format by the extension of `path`.
pub fn decode_raw(path: &Path, bytes: &[u8], channel: Option<&str>) -> Result<RawMap> {
    match Format::from_path(path)? {
        Format::Npy => super::npy::decode_npy_map(path, bytes),
        Format::Exr => super::exr::decode_exr(path, bytes, channel),
        Format::Tiff => super::tiff::decode_tiff(path, bytes),
        Format::Png => super::png::decode_png(path, bytes),
        Format::Csv => super::csv::decode_csv(path, bytes),
    }
}

/// Reads a height map (what [`read_raw`] returns) together with the hex SHA-256 of the file's
/// bytes ([`crate::io::file_sha256`]), reading the file once: the hash is computed on one
/// thread while the data is decoded on another.
pub fn read_raw_hashed(path: &Path, channel: Option<&str>) -> Result<(RawMap, String)> {
    if Format::from_path(path)? == Format::Npy {
        return super::npy::read_npy_hashed(path);
    }
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let (sha, raw) = rayon::join(|| crate::io::hex_sha256(&bytes), || decode_raw(path, &bytes, channel));
    Ok((raw?, sha))
}

/// Reads a design height map into a grid of heights in metres (see the module docs for how
/// pitch, unit, scale and plausibility are resolved). Non-finite values are invalid samples.
pub fn read_heightmap(path: &Path, opts: &ReadOptions) -> Result<Grid> {
    let raw = read_raw(path, opts.channel.as_deref())?;
    heightmap_from_raw(path, raw, opts)
}

/// Resolves a [`RawMap`] read from `path` into a height grid (the second half of
/// [`read_heightmap`]).
pub fn heightmap_from_raw(path: &Path, raw: RawMap, opts: &ReadOptions) -> Result<Grid> {
    let file = path.display().to_string();
    let pitch = resolve_pitch(&file, raw.pitch, opts.pitch)?;
    let k = resolve_scale(&file, &raw, opts)?;
    let offset = opts.z_offset.unwrap_or(0.0);
    if !offset.is_finite() {
        return Err(Error::param("z_offset", format!("must be finite, got {offset}")));
    }
    // One pass: the range of the finite stored values (for the plausibility check), the
    // heights `v k + offset` in place (kept as stored when that is the identity), and whether
    // every height is finite. Compare and select, not `f64::min`, whose NaN handling keeps the
    // pass scalar.
    let mut raw = raw;
    let start = (f64::INFINITY, f64::NEG_INFINITY, true);
    let range = |(lo, hi, finite): (f64, f64, bool), x: f64| {
        let ok = x.is_finite();
        (if ok && x < lo { x } else { lo }, if ok && x > hi { x } else { hi }, finite && ok)
    };
    let parts = if k == 1.0 && offset == 0.0 {
        crate::grid::row_blocks::map_blocks(&raw.values, |_, b| b.iter().fold(start, |a, &x| range(a, x)))
    } else {
        crate::grid::row_blocks::map_blocks_mut(&mut raw.values, |_, mut b| {
            let (mut lo, mut hi, mut finite) = start;
            b.map_inplace(|v| {
                (lo, hi, _) = range((lo, hi, true), *v);
                *v = *v * k + offset;
                finite &= v.is_finite();
            });
            (lo, hi, finite)
        })
    };
    let (lo, hi, finite) = parts.into_iter().fold(start, |a, b| (a.0.min(b.0), a.1.max(b.1), a.2 && b.2));
    if !opts.allow_implausible {
        check_plausible_range(&file, &raw, k, lo, hi)?;
    }
    if finite {
        Grid::new(raw.values, pitch, Unit::Metre)
    } else {
        Grid::from_values_nan_invalid(raw.values, pitch, Unit::Metre)
    }
}

/// Refuses a height grid whose peak-to-valley lies outside a DOE's relief
/// ([`MIN_PLAUSIBLE_PV`]..[`MAX_PLAUSIBLE_PV`]), naming the figure: what a comparison with a
/// design asks of a scan that was read on its own stated unit.
pub fn check_relief(path: &Path, grid: &Grid) -> Result<()> {
    let Some((lo, hi)) = grid.min_max() else { return Ok(()) };
    let pv = hi - lo;
    if pv == 0.0 || (MIN_PLAUSIBLE_PV..=MAX_PLAUSIBLE_PV).contains(&pv) {
        return Ok(());
    }
    let what = format!(
        "{}: the heights span {} peak-to-valley, beyond a DOE's relief ({MIN_PLAUSIBLE_PV:e}..{MAX_PLAUSIBLE_PV:e} m): \
         not a scan of this part, or a wrong height unit in the file",
        path.display(),
        format_length(pv)
    );
    Err(Error::data(DataCause::OutOfRange, what))
}

/// The plausibility check of [`heightmap_from_raw`] alone (module docs): the error it would
/// return for an implausible relief.
pub fn check_plausibility(path: &Path, raw: &RawMap, opts: &ReadOptions) -> Result<()> {
    let file = path.display().to_string();
    let k = resolve_scale(&file, raw, opts)?;
    check_plausible(&file, raw, k)
}

fn same(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-6 * a.abs().max(b.abs())
}

fn fmt_pitch(p: [f64; 2]) -> String {
    format!("{} x {}", format_length(p[0]), format_length(p[1]))
}

fn resolve_pitch(file: &str, from_file: Option<[f64; 2]>, given: Option<[f64; 2]>) -> Result<[f64; 2]> {
    if let Some(g) = given {
        if !g.iter().all(|p| p.is_finite() && *p > 0.0) {
            return Err(Error::param_in(
                "pitch",
                Allowed::positive(),
                format!("must be finite and positive, got {g:?} m"),
            ));
        }
    }
    match (from_file, given) {
        (Some(f), Some(g)) if !(same(f[0], g[0]) && same(f[1], g[1])) => Err(Error::param(
            "pitch",
            format!(
                "{file} states a pitch of {} (x by y) but `pitch` gives {}; drop `pitch` to use \
                 the file's, or correct the file",
                fmt_pitch(f),
                fmt_pitch(g)
            ),
        )),
        (_, Some(g)) => Ok(g),
        (Some(f), None) => Ok(f),
        (None, None) => {
            Err(Error::param("pitch", format!("{file} carries no pitch: pass `pitch` (e.g. 4.29 um)")))
        }
    }
}

fn resolve_scale(file: &str, raw: &RawMap, opts: &ReadOptions) -> Result<f64> {
    match raw.kind {
        SampleKind::Float => {
            if opts.z_scale.is_some() {
                return Err(Error::param(
                    "z_scale",
                    format!(
                        "{file} holds numeric values, not integer image counts; `z_scale` applies to \
                         PNG and 8/16-bit TIFF counts only: give the values' unit with `unit`"
                    ),
                ));
            }
            if let Some(u) = opts.unit {
                if !(u.is_finite() && u > 0.0) {
                    return Err(Error::param_in(
                        "unit",
                        Allowed::positive(),
                        format!("must be a positive length, got {u} m"),
                    ));
                }
            }
            match (raw.unit, opts.unit) {
                (Some(f), Some(g)) if !same(f, g) => Err(Error::param(
                    "unit",
                    format!(
                        "{file} states its values are in units of {} but `unit` gives {}; drop `unit` \
                         to use the file's, or correct the file",
                        format_length(f),
                        format_length(g)
                    ),
                )),
                (_, Some(g)) => Ok(g),
                (Some(f), None) => Ok(f),
                (None, None) => Err(Error::param(
                    "unit",
                    format!("{file} carries no height unit: pass `unit` (e.g. um, nm or m)"),
                )),
            }
        }
        SampleKind::Counts { bits } => {
            if opts.unit.is_some() {
                return Err(Error::param(
                    "unit",
                    format!(
                        "{file} holds {bits}-bit integer counts: their scale is `z_scale` (metres per \
                         count), `unit` does not apply"
                    ),
                ));
            }
            match opts.z_scale {
                Some(s) if s.is_finite() && s != 0.0 => Ok(s),
                Some(s) => Err(Error::param("z_scale", format!("must be finite and non-zero, got {s}"))),
                None => {
                    let hint = raw.scale_hint.as_deref().map(|h| format!(" ({h})")).unwrap_or_default();
                    Err(Error::param(
                        "z_scale",
                        format!(
                            "{file} holds {bits}-bit counts and states no usable height scale: pass \
                             `z_scale` (metres per count, e.g. 0.1 nm) and optionally `z_offset`{hint}"
                        ),
                    ))
                }
            }
        }
    }
}

/// Refuses maps whose peak-to-valley height, scaled by `k` metres per stored value, lies outside
/// [`MIN_PLAUSIBLE_PV`, `MAX_PLAUSIBLE_PV`], suggesting the length unit that would fit (the one
/// putting the height closest to 1 um, the order of a visible-light DOE's relief).
fn check_plausible(file: &str, raw: &RawMap, k: f64) -> Result<()> {
    let start = (f64::INFINITY, f64::NEG_INFINITY);
    let parts = crate::grid::row_blocks::map_blocks(&raw.values, |_, b| {
        b.iter().filter(|v| v.is_finite()).fold(start, |(lo, hi), &v| (lo.min(v), hi.max(v)))
    });
    let (lo, hi) = parts.into_iter().fold(start, |(lo, hi), (a, b)| (lo.min(a), hi.max(b)));
    check_plausible_range(file, raw, k, lo, hi)
}

/// [`check_plausible`] given the smallest and largest finite stored values `lo`, `hi` (`lo > hi`
/// when there is none); `raw` supplies the kind of the values.
fn check_plausible_range(file: &str, raw: &RawMap, k: f64, lo: f64, hi: f64) -> Result<()> {
    if lo > hi {
        return Err(Error::data(DataCause::Empty, format!("{file}: no finite height value in the map")));
    }
    let pv_raw = hi - lo;
    let pv = pv_raw * k.abs();
    // A flat map (every value equal) is a statement, not a scale error.
    if pv_raw == 0.0 || (MIN_PLAUSIBLE_PV..=MAX_PLAUSIBLE_PV).contains(&pv) {
        return Ok(());
    }
    let units = [("pm", 1e-12), ("nm", 1e-9), ("um", 1e-6), ("mm", 1e-3), ("m", 1.0)];
    let best = |scale: f64| {
        units
            .iter()
            .filter(|(_, s)| (MIN_PLAUSIBLE_PV..=MAX_PLAUSIBLE_PV).contains(&(pv_raw * scale * s)))
            .min_by(|a, b| {
                let d = |s: f64| (pv_raw * scale * s / 1e-6).log10().abs();
                d(a.1).total_cmp(&d(b.1))
            })
            .copied()
    };
    let range = format!("a design's relief lies within {MIN_PLAUSIBLE_PV:e}..{MAX_PLAUSIBLE_PV:e} m");
    // The range the heights' peak-to-valley must reach under the refused unit or scale.
    let plausible = Allowed::between(MIN_PLAUSIBLE_PV, MAX_PLAUSIBLE_PV);
    match raw.kind {
        SampleKind::Float => {
            let head = format!(
                "{file}: with values in units of {} the heights span {} peak-to-valley, implausible \
                 ({range})",
                format_length(k),
                format_length(pv)
            );
            let tail = match best(1.0) {
                Some(("m", _)) => "; the values look like metres already: did you mean `unit` m?".to_string(),
                Some((name, s)) => format!(
                    "; in {name} they would span {}: did you mean `unit` {name}?",
                    format_length(pv_raw * s)
                ),
                None => "; no length unit makes them plausible: check the file".to_string(),
            };
            Err(Error::param_in("unit", plausible, head + &tail))
        }
        SampleKind::Counts { .. } => {
            let head = format!(
                "{file}: with `z_scale` {k:e} m per count the heights span {} peak-to-valley, \
                 implausible ({range})",
                format_length(pv)
            );
            let tail = match best(k.abs()) {
                Some(("m", _)) | None => "; check the scale: it is metres per count".to_string(),
                Some((name, s)) => format!(
                    "; if the scale was meant in {name} per count, pass `z_scale` {:e}m (heights would \
                     span {})",
                    k * s,
                    format_length(pv * s)
                ),
            };
            Err(Error::param_in("z_scale", plausible, head + &tail))
        }
    }
}

#[cfg(test)]
mod tests {
    use ndarray::Array2;

    use super::*;
    use crate::error::FormatCause;

    fn raw(values: Array2<f64>, kind: SampleKind) -> RawMap {
        RawMap { values, kind, pitch: None, unit: None, metadata: vec![], scale_hint: None }
    }

    #[test]
    fn demands_pitch_and_unit_and_refuses_conflicts() {
        let p = Path::new("map.npy");
        let r = raw(Array2::from_shape_fn((2, 2), |(i, j)| (i + j) as f64), SampleKind::Float);
        let e = heightmap_from_raw(p, r.clone(), &ReadOptions::default()).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name == "pitch"), "{e:?}");
        assert!(e.to_string().contains("map.npy carries no pitch: pass `pitch` (e.g. 4.29 um)"), "{e}");
        let o = ReadOptions { pitch: Some([1e-6, 1e-6]), ..Default::default() };
        let e = heightmap_from_raw(p, r.clone(), &o).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name == "unit"), "{e:?}");
        let o = ReadOptions { pitch: Some([1e-6, 2e-6]), unit: Some(1e-6), ..Default::default() };
        let g = heightmap_from_raw(p, r.clone(), &o).unwrap();
        assert_eq!(g.pitch(), [1e-6, 2e-6]);
        assert_eq!(g.values()[[1, 1]], 2e-6);
        let mut r2 = r.clone();
        r2.pitch = Some([1e-6, 1e-6]);
        r2.unit = Some(1e-9);
        let e = heightmap_from_raw(p, r2.clone(), &o).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name == "pitch"), "{e:?}");
        let e = e.to_string();
        assert!(e.contains("1 um x 1 um") && e.contains("1 um x 2 um"), "{e}");
        let o = ReadOptions { unit: Some(1e-6), ..Default::default() };
        let e = heightmap_from_raw(p, r2.clone(), &o).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name == "unit"), "{e:?}");
        let e = e.to_string();
        assert!(e.contains("1 nm") && e.contains("1 um") && e.contains("drop `unit`"), "{e}");
        // Agreeing options are fine.
        let o = ReadOptions { unit: Some(1e-9), pitch: Some([1e-6, 1e-6]), ..Default::default() };
        assert!(heightmap_from_raw(p, r2, &o).is_ok());
    }

    #[test]
    fn counts_need_an_explicit_scale() {
        let p = Path::new("m.png");
        let mut r =
            raw(Array2::from_shape_fn((2, 2), |(i, j)| (i * 2 + j) as f64), SampleKind::Counts { bits: 16 });
        r.pitch = Some([1e-6; 2]);
        r.scale_hint = Some("hint here".into());
        let e = heightmap_from_raw(p, r.clone(), &ReadOptions::default()).unwrap_err();
        assert!(
            matches!(e, Error::Parameter { ref name, .. } if name == "z_scale")
                && e.to_string().contains("hint here"),
            "{e:?}"
        );
        let o = ReadOptions { unit: Some(1e-9), ..Default::default() };
        let e = heightmap_from_raw(p, r.clone(), &o).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name == "unit"), "{e:?}");
        let o = ReadOptions { z_scale: Some(1e-9), z_offset: Some(5e-9), ..Default::default() };
        let g = heightmap_from_raw(p, r.clone(), &o).unwrap();
        assert!((g.values()[[1, 1]] - 8e-9).abs() < 1e-20);
        let o = ReadOptions { z_scale: Some(0.5), ..Default::default() };
        let e = heightmap_from_raw(p, r, &o).unwrap_err();
        assert!(
            matches!(e, Error::Parameter { ref name, .. } if name == "z_scale")
                && e.to_string().contains("`z_scale` 5e-7m"),
            "{e:?}"
        );
    }

    #[test]
    fn implausible_units_get_a_suggestion() {
        let p = Path::new("d.exr");
        let v = Array2::from_shape_fn((3, 3), |(i, j)| (i * 3 + j) as f64 * 2e-7);
        let mut r = raw(v, SampleKind::Float);
        r.pitch = Some([1e-6; 2]);
        r.unit = Some(1e-6);
        let e = heightmap_from_raw(p, r.clone(), &ReadOptions::default()).unwrap_err().to_string();
        assert!(e.contains("look like metres already: did you mean `unit` m?"), "{e}");
        let g =
            heightmap_from_raw(p, r.clone(), &ReadOptions { allow_implausible: true, ..Default::default() });
        assert!(g.is_ok());
        r.values.mapv_inplace(|v| v * 1e9); // 0..1600 "um" = 1.6 mm: nm intended
        let e = heightmap_from_raw(p, r.clone(), &ReadOptions::default()).unwrap_err().to_string();
        assert!(e.contains("did you mean `unit` nm?"), "{e}");
        r.values.fill(3.0);
        assert!(heightmap_from_raw(p, r.clone(), &ReadOptions::default()).is_ok());
        r.values.fill(f64::NAN);
        let e = heightmap_from_raw(p, r, &ReadOptions::default()).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::Empty, .. }), "{e:?}");
    }

    #[test]
    fn non_finite_values_become_invalid_samples() {
        let mut v = Array2::from_shape_fn((3, 3), |(i, j)| (i + j) as f64);
        v[[1, 1]] = f64::NAN;
        v[[0, 2]] = f64::INFINITY;
        let mut r = raw(v, SampleKind::Float);
        r.pitch = Some([1e-6; 2]);
        r.unit = Some(1e-9);
        let g = heightmap_from_raw(Path::new("x.npy"), r, &ReadOptions::default()).unwrap();
        assert_eq!(g.valid_count(), 7);
        assert!(!g.is_valid(1, 1) && !g.is_valid(0, 2));
    }

    #[test]
    fn format_by_extension() {
        assert_eq!(Format::from_path(Path::new("a/B.TIF")).unwrap(), Format::Tiff);
        assert_eq!(Format::from_path(Path::new("x.asc")).unwrap(), Format::Csv);
        let e = Format::from_path(Path::new("x.bmp")).unwrap_err();
        assert!(
            matches!(e, Error::Format { cause: FormatCause::Signature, ref path, .. } if path.ends_with("x.bmp"))
        );
        assert!(Format::from_path(Path::new("noext")).is_err());
    }
}
