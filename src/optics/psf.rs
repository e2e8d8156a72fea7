//! A point spread function: one [`Grid`] per wavelength or colour channel.
//!
//! Each channel's grid holds the intensity per sensor pixel, centred on the optical axis
//! (sample `(i, j)` at `x = origin_x + j * pitch`, as every grid), normalised to sum 1 over the
//! window as the paper does. `captured`, when known, is the fraction of the power leaving the
//! DOE that lands in the window, so absolute energies can be recovered: pixel value times
//! `captured` is that pixel's share of the transmitted power.
//!
//! Measures: [`Psf::centroid`], [`Psf::peak`], [`Psf::encircled_energy`] (pixels whose centre
//! lies within the radius), [`Psf::strehl`] relative to a flat DOE's PSF, [`Psf::relative_l2`].
//! [`Psf::read_npz`] loads a PSF saved by NumPy in the paper's layout `(H, W, 1, C)`.

use std::io::Read;
use std::path::Path;

use ndarray::{Array2, Array4, ArrayD};
use serde::{Deserialize, Serialize};

use crate::error::{Allowed, DataCause, Error, Result};
use crate::grid::{Grid, Unit};
use crate::io::exr::{decode_exr, exr_channel_names};
use crate::io::npy::{decode_npy, read_npy_nd};

/// One channel of a PSF.
#[derive(Debug, Clone, PartialEq)]
pub struct Channel {
    /// Channel name ("635nm", "R", ...).
    pub name: String,
    /// Its wavelength in metres, when it is one.
    pub wavelength: Option<f64>,
    /// Pixel intensities, normalised to sum 1, with the sensor pitch.
    pub grid: Grid,
    /// Fraction of the DOE's output power that lands in the window, when known: the sum of the
    /// sub-sample intensities times their cell area over the power leaving the DOE, a Riemann
    /// sum that is the integral only where the sub-samples resolve the intensity
    /// (`pitch <= lambda F# / 2`); undersampled, it can exceed 1.
    pub captured: Option<f64>,
}

/// A PSF: channels of one shape and pitch, the method that made it and its warnings.
#[derive(Debug, Clone, PartialEq)]
pub struct Psf {
    /// One per wavelength or colour band, of one shape and pitch.
    pub channels: Vec<Channel>,
    /// The method (propagation method name, or "measured"/"file").
    pub method: String,
    /// Validity conditions a forced run violated (empty when valid).
    pub warnings: Vec<String>,
}

/// A local maximum of a channel: its position (metres from the window centre), its pixel
/// value and the channel's energy within the search radius of it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Peak {
    /// `[x, y]` position of the pixel, metres from the window centre.
    pub position: [f64; 2],
    /// The pixel's value, fraction of the channel's sum (0..1).
    pub value: f64,
    /// Sum of the channel over pixels whose centre lies within the search radius of
    /// `position`, fraction of the channel's sum (0..1).
    pub energy: f64,
}

/// Summary numbers of one channel (for reports and JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelSummary {
    /// Channel name ("635nm", "R", ...).
    pub name: String,
    /// The channel's wavelength in metres; `None` for a colour band without one.
    pub wavelength: Option<f64>,
    /// `[x, y]` centroid, metres from the window centre.
    pub centroid: [f64; 2],
    /// Peak value, fraction of the channel's sum (0..1).
    pub peak: f64,
    /// `[x, y]` position of the peak pixel, metres from the window centre.
    pub peak_position: [f64; 2],
    /// Fraction of the DOE's output power that lands in the window (see
    /// [`Channel::captured`]); `None` when not known (a measured or loaded PSF).
    pub captured: Option<f64>,
}

impl Psf {
    /// Builds a PSF from channels, checking that they share shape and pitch, and normalises
    /// each to sum 1.
    pub fn new(channels: Vec<Channel>, method: &str) -> Result<Psf> {
        let Some(first) = channels.first() else {
            return Err(Error::data(DataCause::Empty, "a PSF needs at least one channel"));
        };
        let (dim, pitch) = (first.grid.dim(), first.grid.pitch());
        for c in &channels {
            if c.grid.dim() != dim || c.grid.pitch() != pitch {
                return Err(Error::data(
                    DataCause::Shape,
                    format!(
                        "PSF channel '{}' is {:?} at pitch {:?}, channel '{}' is {:?} at {:?}",
                        c.name,
                        c.grid.dim(),
                        c.grid.pitch(),
                        first.name,
                        dim,
                        pitch
                    ),
                ));
            }
        }
        let mut psf = Psf { channels, method: method.into(), warnings: Vec::new() };
        psf.normalise()?;
        Ok(psf)
    }

    /// Scales each channel to sum 1. Refuses negative, non-finite or all-zero channels.
    pub fn normalise(&mut self) -> Result<()> {
        for c in &mut self.channels {
            let v = c.grid.values();
            if let Some(bad) = v.iter().find(|x| !x.is_finite() || **x < 0.0) {
                let cause = if bad.is_finite() { DataCause::OutOfRange } else { DataCause::NotFinite };
                return Err(Error::data(cause, format!("PSF channel '{}' holds {bad}", c.name)));
            }
            let s: f64 = v.sum();
            if s <= 0.0 {
                return Err(Error::data(DataCause::Empty, format!("PSF channel '{}' is all zero", c.name)));
            }
            c.grid.values_mut().mapv_inplace(|x| x / s);
        }
        Ok(())
    }

    /// `(rows, cols)` of every channel.
    pub fn dim(&self) -> (usize, usize) {
        self.channels[0].grid.dim()
    }

    /// Pixel pitch `[x, y]`, metres.
    pub fn pitch(&self) -> [f64; 2] {
        self.channels[0].grid.pitch()
    }

    /// Intensity-weighted centroid `[x, y]` of channel `c`, metres from the window centre.
    pub fn centroid(&self, c: usize) -> [f64; 2] {
        let g = &self.channels[c].grid;
        let (mut sx, mut sy, mut s) = (0.0, 0.0, 0.0);
        for ((i, j), &v) in g.values().indexed_iter() {
            sx += v * g.x(j);
            sy += v * g.y(i);
            s += v;
        }
        [sx / s, sy / s]
    }

    /// Largest value of channel `c` with its `[x, y]` position (metres) and `(row, col)`.
    pub fn peak(&self, c: usize) -> (f64, [f64; 2], (usize, usize)) {
        let g = &self.channels[c].grid;
        let mut best = (f64::NEG_INFINITY, (0, 0));
        for (idx, &v) in g.values().indexed_iter() {
            if v > best.0 {
                best = (v, idx);
            }
        }
        (best.0, [g.x(best.1 .1), g.y(best.1 .0)], best.1)
    }

    /// The `count` brightest local maxima of channel `c` (pixels above all 8 neighbours; the
    /// window's border pixels are skipped), each at least `radius` (metres) from a brighter
    /// one, with the energy within `radius` of it: the central peak and its shifted copies.
    pub fn peaks(&self, c: usize, count: usize, radius: f64) -> Vec<Peak> {
        let g = &self.channels[c].grid;
        let v = g.values();
        let (h, w) = v.dim();
        let mut maxima: Vec<(f64, usize, usize)> = Vec::new();
        for i in 1..h.saturating_sub(1) {
            for j in 1..w.saturating_sub(1) {
                let x = v[[i, j]];
                let local = (0..3).all(|a| (0..3).all(|b| (a, b) == (1, 1) || x > v[[i + a - 1, j + b - 1]]));
                if local {
                    maxima.push((x, i, j));
                }
            }
        }
        maxima.sort_by(|a, b| b.0.total_cmp(&a.0));
        let mut out: Vec<Peak> = Vec::new();
        for (x, i, j) in maxima {
            let pos = [g.x(j), g.y(i)];
            if out.iter().any(|p| (p.position[0] - pos[0]).hypot(p.position[1] - pos[1]) < radius) {
                continue;
            }
            out.push(Peak { position: pos, value: x, energy: self.encircled_energy(c, pos, radius) });
            if out.len() == count {
                break;
            }
        }
        out
    }

    /// Sum of channel `c` over pixels whose centre lies within `radius` of `centre` (metres).
    pub fn encircled_energy(&self, c: usize, centre: [f64; 2], radius: f64) -> f64 {
        let g = &self.channels[c].grid;
        let mut s = 0.0;
        for ((i, j), &v) in g.values().indexed_iter() {
            if (g.x(j) - centre[0]).powi(2) + (g.y(i) - centre[1]).powi(2) <= radius * radius {
                s += v;
            }
        }
        s
    }

    /// Strehl ratio per channel relative to `flat`, the PSF of a flat DOE in the same system:
    /// the ratio of the peak intensities, each in absolute terms (value times `captured`).
    /// Both peaks are pixel values: where the PSF is undersampled, the flat DOE's peak must sit
    /// on a pixel centre (an odd crop puts the axis there) for the ratio to mean Strehl.
    pub fn strehl(&self, flat: &Psf) -> Result<Vec<f64>> {
        self.check_same(flat)?;
        (0..self.channels.len())
            .map(|c| {
                let (a, b) = (self.channels[c].captured, flat.channels[c].captured);
                let (Some(a), Some(b)) = (a, b) else {
                    return Err(Error::data(
                        DataCause::NotFinite,
                        "Strehl ratio needs PSFs with known captured power",
                    ));
                };
                Ok(self.peak(c).0 * a / (flat.peak(c).0 * b))
            })
            .collect()
    }

    /// Relative L2 difference per channel, `||a - b|| / ||b||` with `b = other`.
    pub fn relative_l2(&self, other: &Psf) -> Result<Vec<f64>> {
        self.check_same(other)?;
        Ok(self
            .channels
            .iter()
            .zip(&other.channels)
            .map(|(a, b)| relative_l2(a.grid.values(), b.grid.values()))
            .collect())
    }

    fn check_same(&self, other: &Psf) -> Result<()> {
        if self.channels.len() != other.channels.len() || self.dim() != other.dim() {
            return Err(Error::data(
                DataCause::Shape,
                format!(
                    "PSFs differ in shape: {} channels of {:?} vs {} of {:?}",
                    self.channels.len(),
                    self.dim(),
                    other.channels.len(),
                    other.dim()
                ),
            ));
        }
        Ok(())
    }

    /// Summary numbers of every channel.
    pub fn summary(&self) -> Vec<ChannelSummary> {
        (0..self.channels.len())
            .map(|c| {
                let (peak, pos, _) = self.peak(c);
                ChannelSummary {
                    name: self.channels[c].name.clone(),
                    wavelength: self.channels[c].wavelength,
                    centroid: self.centroid(c),
                    peak,
                    peak_position: pos,
                    captured: self.channels[c].captured,
                }
            })
            .collect()
    }

    /// The PSF as a `(H, W, 1, C)` `f32` array, the paper's layout.
    pub fn to_array4(&self) -> Array4<f32> {
        let (h, w) = self.dim();
        Array4::from_shape_fn((h, w, 1, self.channels.len()), |(i, j, _, c)| {
            self.channels[c].grid.values()[[i, j]] as f32
        })
    }

    /// Reads a PSF from a NumPy `.npz` archive: the array `key` (or the archive's only array)
    /// of shape `(H, W)`, `(H, W, C)` or `(H, W, 1, C)`, at pixel `pitch` (metres). Channels of
    /// three are named R, G, B; `wavelengths`, if given, must have one entry per channel.
    /// Each channel is normalised to sum 1.
    pub fn read_npz(path: &Path, key: Option<&str>, pitch: f64, wavelengths: Option<&[f64]>) -> Result<Psf> {
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        Psf::decode_npz(path, file, key, pitch, wavelengths)
    }

    /// The paper's measured PSF (Metzler et al. 2020, `measured_psf.npz`, array `psf_val`,
    /// 319 x 319 x RGB at 4.29 um; BSD-3, `assets/deepoptics-hdr/LICENSE`), compiled in.
    pub fn paper_measured() -> Result<Psf> {
        const BYTES: &[u8] = include_bytes!("../../assets/deepoptics-hdr/measured_psf.npz");
        let path = Path::new("built-in:paper-measured-psf");
        Psf::decode_npz(path, std::io::Cursor::new(BYTES), Some("psf_val"), 4.29e-6, None)
    }

    /// [`Psf::read_npz`] on an open archive; `path` names it in errors.
    fn decode_npz<R: std::io::Read + std::io::Seek>(
        path: &Path,
        reader: R,
        key: Option<&str>,
        pitch: f64,
        wavelengths: Option<&[f64]>,
    ) -> Result<Psf> {
        let mut zip = zip::ZipArchive::new(reader)
            .map_err(|e| Error::signature(path, format!("not a NumPy .npz (zip) archive: {e}")))?;
        let names: Vec<String> = zip.file_names().filter(|n| n.ends_with(".npy")).map(String::from).collect();
        let entry = match key {
            Some(k) => {
                let want = format!("{k}.npy");
                names.iter().find(|n| **n == want).cloned().ok_or_else(|| {
                    Error::malformed(path, format!("no array '{k}' in the archive (it holds {names:?})"))
                })?
            }
            None if names.len() == 1 => names[0].clone(),
            None => {
                return Err(Error::malformed(
                    path,
                    format!("the archive holds {} arrays {names:?}; name the one to read", names.len()),
                ))
            }
        };
        let mut bytes = Vec::new();
        zip.by_name(&entry)
            .map_err(|e| Error::malformed(path, format!("cannot open '{entry}': {e}")))?
            .read_to_end(&mut bytes)
            .map_err(|e| Error::malformed(path, format!("cannot inflate '{entry}': {e}")))?;
        let inner = path.join(&entry);
        let (h, arr) = decode_npy(&inner, &bytes)?;
        Psf::from_array(&inner, &h.shape, arr, [pitch, pitch], wavelengths)
    }

    /// A PSF from an array of shape `(H, W)`, `(H, W, C)` or `(H, W, 1, C)` (the paper's
    /// layout) at pixel `pitch` `[x, y]` (metres); `path` names its source in errors.
    /// Channels of three are named R, G, B; `wavelengths`, if given, must have one entry per
    /// channel. Each channel is normalised to sum 1.
    pub fn from_array(
        path: &Path,
        shape: &[usize],
        arr: ArrayD<f64>,
        pitch: [f64; 2],
        wavelengths: Option<&[f64]>,
    ) -> Result<Psf> {
        let (rows, cols, nc) = match shape {
            [r, c] => (*r, *c, 1),
            [r, c, k] | [r, c, 1, k] => (*r, *c, *k),
            s => {
                return Err(Error::unsupported(
                    path,
                    format!("shape {s:?} is not a PSF (expected (H, W), (H, W, C) or (H, W, 1, C))"),
                ))
            }
        };
        if rows == 0 || cols == 0 || nc == 0 {
            return Err(Error::malformed(path, format!("empty PSF of shape {shape:?}")));
        }
        if let Some(w) = wavelengths {
            if w.len() != nc {
                return Err(Error::param(
                    "wavelengths",
                    format!("{} given for a PSF of {nc} channels", w.len()),
                ));
            }
        }
        let flat = arr
            .into_shape_with_order((rows, cols, nc))
            .map_err(|e| Error::malformed(path, format!("cannot view as {rows} x {cols} x {nc}: {e}")))?;
        let mut channels = Vec::new();
        for c in 0..nc {
            let values = Array2::from_shape_fn((rows, cols), |(i, j)| flat[[i, j, c]]);
            let name = if nc == 3 { ["R", "G", "B"][c].to_string() } else { format!("C{c}") };
            channels.push(Channel {
                name,
                wavelength: wavelengths.map(|w| w[c]),
                grid: Grid::new(values, pitch, Unit::Dimensionless)?,
                captured: None,
            });
        }
        Psf::new(channels, "file").map_err(|e| match e {
            Error::Data { what, .. } => Error::malformed(path, what),
            other => other,
        })
    }
}

/// Pitches of two PSFs (or a file's and a caller's) agree within this relative difference.
pub const PITCH_TOLERANCE: f64 = 1e-6;

impl Psf {
    /// Reads a PSF file, the one reader of every command: a `.npy` of shape `(H, W)`,
    /// `(H, W, C)` or `(H, W, 1, C)` (the paper's layout, as `doefab psf` and `calibrate-psf`
    /// write it) with the pitch and channel names from the JSON summary beside it (`psf.json`
    /// beside `psf.npy`: `system.sensor_pitch` or `sensor_pitch`, `channels[].name`); the
    /// `psf.exr` that `doefab psf` writes (pitch and channel order from its header); or a
    /// NumPy `.npz` archive such as the paper's measured PSF (array `key`, or its only one).
    /// `pitch` (metres) is used where the file states none, and must agree (to 1e-6) where
    /// it does; with neither the file is refused.
    pub fn read(path: &Path, key: Option<&str>, pitch: Option<f64>) -> Result<Psf> {
        let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("npz") => {
                let pitch = resolve_pitch(path, None, pitch)?;
                Psf::read_npz(path, key, pitch[0], None)
            }
            Some("npy") => read_npy_psf(path, pitch),
            Some("exr") => read_exr_psf(path, pitch),
            _ => Err(Error::signature(path, "a PSF is read from .npy, .npz or .exr (by extension)")),
        }
    }
}

/// The pitch to use: the file's, `given` only when the file states none (they must agree
/// when both are known).
fn resolve_pitch(path: &Path, file: Option<[f64; 2]>, given: Option<f64>) -> Result<[f64; 2]> {
    match (file, given) {
        (Some(p), Some(g)) if p.iter().any(|&q| ((q - g) / g).abs() > PITCH_TOLERANCE) => {
            Err(Error::malformed(
                path,
                format!("states pitch [{:e}, {:e}] m, but `pitch` is {g:e} m", p[0], p[1]),
            ))
        }
        (Some(p), _) => Ok(p),
        (None, Some(g)) if g.is_finite() && g > 0.0 => Ok([g, g]),
        (None, Some(g)) => Err(Error::param_in(
            "pitch",
            Allowed::positive(),
            format!("must be a positive length, got {g} m"),
        )),
        (None, None) => Err(Error::malformed(
            path,
            "states no pixel pitch (no metadata with 'sensor_pitch' or 'pitch_x'/'pitch_y'): give `pitch`",
        )),
    }
}

/// Pitch, channel names and wavelengths from the `psf.json` that `doefab psf` writes beside
/// its `psf.npy` (`None` when there is none).
type SideMetadata = Option<([f64; 2], Vec<(String, Option<f64>)>)>;

fn read_side_json(npy: &Path) -> Result<SideMetadata> {
    let json = npy.with_extension("json");
    if !json.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&json).map_err(|e| Error::io(&json, e))?;
    let v: serde_json::Value = serde_json::from_str(&text)
        .map_err(|e| Error::malformed(&json, format!("not JSON: {e}")).at_json(&text, &e))?;
    // `doefab psf` nests the pitch in its system; `calibrate-psf` states it at the top.
    let pitch = v
        .pointer("/system/sensor_pitch")
        .or_else(|| v.get("sensor_pitch"))
        .and_then(serde_json::Value::as_f64)
        .filter(|p| p.is_finite() && *p > 0.0)
        .ok_or_else(|| {
            Error::malformed(
                &json,
                "field 'system.sensor_pitch' or 'sensor_pitch' (metres, positive) is missing",
            )
        })?;
    let channels = v
        .get("channels")
        .and_then(serde_json::Value::as_array)
        .ok_or_else(|| Error::malformed(&json, "field 'channels' (an array) is missing"))?
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let name = c.get("name").and_then(serde_json::Value::as_str).ok_or_else(|| {
                Error::malformed(&json, format!("field 'channels[{i}].name' (text) is missing"))
            })?;
            Ok((name.to_string(), c.get("wavelength").and_then(serde_json::Value::as_f64)))
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(Some(([pitch, pitch], channels)))
}

fn read_npy_psf(path: &Path, given: Option<f64>) -> Result<Psf> {
    let side = read_side_json(path)?;
    let pitch = resolve_pitch(path, side.as_ref().map(|s| s.0), given)?;
    let (h, arr) = read_npy_nd(path)?;
    let mut psf = Psf::from_array(path, &h.shape, arr, pitch, None)?;
    if let Some((_, names)) = side {
        if names.len() != psf.channels.len() {
            return Err(Error::malformed(
                path.with_extension("json"),
                format!("lists {} channels, {} holds {}", names.len(), path.display(), psf.channels.len()),
            ));
        }
        for (c, (name, wavelength)) in psf.channels.iter_mut().zip(names) {
            c.name = name;
            c.wavelength = wavelength;
        }
    }
    Ok(psf)
}

fn read_exr_psf(path: &Path, given: Option<f64>) -> Result<Psf> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let header_names = exr_channel_names(path, &bytes)?;
    let first = decode_exr(path, &bytes, header_names.first().map(String::as_str))?;
    let text = |key: &str| first.metadata.iter().find(|(k, _)| k == key).map(|(_, v)| v.clone());
    // Our writer records the channel order (the format sorts channels by name).
    let names: Vec<String> = match text("channel_names") {
        Some(list) => list.split(',').map(str::to_string).collect(),
        None => header_names,
    };
    let wavelengths: Vec<Option<f64>> = match text("wavelengths_m") {
        Some(list) if list.split(',').count() == names.len() => {
            list.split(',').map(|w| w.trim().parse::<f64>().ok()).collect()
        }
        _ => vec![None; names.len()],
    };
    let pitch = resolve_pitch(path, first.pitch, given)?;
    let mut channels = Vec::new();
    for (name, wavelength) in names.iter().zip(wavelengths) {
        let raw = decode_exr(path, &bytes, Some(name))?;
        channels.push(Channel {
            name: name.clone(),
            wavelength,
            grid: Grid::new(raw.values, pitch, Unit::Dimensionless)?,
            captured: None,
        });
    }
    Psf::new(channels, "file").map_err(|e| match e {
        Error::Data { what, .. } => Error::malformed(path, what),
        other => other,
    })
}

/// `||a - b|| / ||b||` over all samples.
pub fn relative_l2(a: &Array2<f64>, b: &Array2<f64>) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
    let den: f64 = b.iter().map(|y| y * y).sum();
    (num / den).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::FormatCause;

    #[test]
    fn a_pitch_comes_from_the_file_or_the_caller_and_must_agree() {
        let e = resolve_pitch(Path::new("m.npz"), None, None).unwrap_err();
        assert!(
            matches!(e, Error::Format { cause: FormatCause::Malformed, .. })
                && e.to_string().contains("give `pitch`"),
            "{e:?}"
        );
        let e = resolve_pitch(Path::new("p.exr"), Some([4.29e-6; 2]), Some(5e-6)).unwrap_err();
        assert!(
            matches!(e, Error::Format { cause: FormatCause::Malformed, .. })
                && e.to_string().contains("`pitch` is 5e-6 m"),
            "{e:?}"
        );
        assert_eq!(resolve_pitch(Path::new("p.exr"), Some([4.29e-6; 2]), None).unwrap(), [4.29e-6; 2]);
        assert_eq!(resolve_pitch(Path::new("m.npz"), None, Some(5e-6)).unwrap(), [5e-6; 2]);
    }

    #[test]
    fn the_summary_beside_a_npy_gives_its_pitch_in_either_layout() {
        let dir = tempfile::tempdir().unwrap();
        let npy = dir.path().join("psf.npy");
        let json = dir.path().join("psf.json");
        // `doefab psf` nests the pitch in its system; `calibrate-psf` states it at the top.
        for (text, pitch) in [
            (
                r#"{"system": {"sensor_pitch": 4.29e-6}, "channels": [{"name": "R", "wavelength": 6.35e-7}]}"#,
                4.29e-6,
            ),
            (r#"{"sensor_pitch": 5e-6, "channels": [{"name": "G"}]}"#, 5e-6),
        ] {
            std::fs::write(&json, text).unwrap();
            let (p, names) = read_side_json(&npy).unwrap().unwrap();
            assert_eq!(p, [pitch; 2]);
            assert_eq!(names.len(), 1);
        }
        std::fs::write(&json, r#"{"channels": []}"#).unwrap();
        let e = read_side_json(&npy).unwrap_err();
        assert!(
            matches!(e, Error::Format { cause: FormatCause::Malformed, ref path, .. } if *path == json),
            "{e:?}"
        );
        assert!(e.to_string().contains("sensor_pitch"), "{e}");
    }
}
