//! Sensor captures, exposure brackets, and the one reader of linear images ([`read_image`]:
//! EXR, Radiance HDR, NumPy, and captures) that calibration and the decoder share.
//!
//! A capture is an 8- or 16-bit PNG or TIFF, RGB or grayscale, holding *linear* sensor values
//! (value / full scale proportional to irradiance times exposure time, as the paper's captures
//! are) unless a response curve says otherwise ([`crate::calibration::response`]). It is read
//! into an `(H, W, C)` array of values in `[0, 1]` (counts / (2^bits - 1)); 16-bit palette,
//! alpha, float or other bit depths are refused with what was found.
//!
//! A bracket's exposure times come from a JSON file in the layout of the paper's data
//! (`{"reference_exposure_s": t, "frames": [{"file", "exposure_s", "doe"}]}`, file names
//! relative to the JSON file) or from the caller.

use std::io::Cursor;
use std::path::{Path, PathBuf};

use image::{DynamicImage, ImageEncoder};
use ndarray::Array3;
use serde::Deserialize;

use crate::error::{Error, Result};
use crate::image::Image;
use crate::io::atomic::write_bytes;
use crate::io::exr::decode_exr_channels;

/// One capture: linear values in `[0, 1]` with its bit depth.
#[derive(Debug, Clone, PartialEq)]
pub struct Capture {
    /// The file it was read from.
    pub path: PathBuf,
    /// Counts divided by the full-scale count.
    pub image: Image,
    /// 8 or 16.
    pub bits: u8,
}

impl Capture {
    /// The full-scale count, `2^bits - 1`.
    pub fn full_scale(&self) -> f64 {
        if self.bits == 8 {
            255.0
        } else {
            65535.0
        }
    }
}

/// Reads an 8/16-bit RGB or grayscale PNG or TIFF capture.
pub fn read_capture(path: &Path) -> Result<Capture> {
    let reader = image::ImageReader::open(path)
        .map_err(|e| Error::io(path, e))?
        .with_guessed_format()
        .map_err(|e| Error::io(path, e))?;
    match reader.format() {
        Some(image::ImageFormat::Png | image::ImageFormat::Tiff) => {}
        other => return Err(Error::signature(path, format!("is {other:?}, not a PNG or TIFF capture"))),
    }
    // The decoder is third-party code fed with user bytes: a panic in it becomes an error.
    let img = std::panic::catch_unwind(move || reader.decode())
        .map_err(|_| Error::malformed(path, "the image decoder failed on malformed data"))?
        .map_err(|e| {
            let what = format!("cannot decode it as an 8- or 16-bit RGB or grayscale capture: {e}");
            match e {
                image::ImageError::Unsupported(_) => Error::unsupported(path, what),
                _ => Error::malformed(path, what),
            }
        })?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let (samples, channels, bits): (Vec<f64>, usize, u8) = match &img {
        DynamicImage::ImageLuma8(b) => (b.as_raw().iter().map(|&v| v as f64 / 255.0).collect(), 1, 8),
        DynamicImage::ImageRgb8(b) => (b.as_raw().iter().map(|&v| v as f64 / 255.0).collect(), 3, 8),
        DynamicImage::ImageLuma16(b) => (b.as_raw().iter().map(|&v| v as f64 / 65535.0).collect(), 1, 16),
        DynamicImage::ImageRgb16(b) => (b.as_raw().iter().map(|&v| v as f64 / 65535.0).collect(), 3, 16),
        other => {
            return Err(Error::unsupported(
                path,
                format!(
                "holds {:?} samples; a capture must be 8- or 16-bit RGB or grayscale (no alpha, no float)",
                other.color()
            ),
            ))
        }
    };
    let values = Array3::from_shape_vec((h, w, channels), samples)
        .map_err(|e| Error::malformed(path, format!("the image data does not fill {w} x {h}: {e}")))?;
    Ok(Capture { path: path.to_path_buf(), image: Image::new(values), bits })
}

/// Writes `image` (1 or 3 channels, clipped to `[0, 1]`, rounded to counts) as an 8- or
/// 16-bit PNG capture, atomically.
pub fn write_capture(path: &Path, image: &Image, bits: u8) -> Result<()> {
    let (h, w, c) = image.dim();
    let full = match bits {
        8 => 255.0,
        16 => 65535.0,
        b => return Err(Error::param("bits", format!("a capture has 8 or 16 bits, not {b}"))),
    };
    let color = match (c, bits) {
        (1, 8) => image::ExtendedColorType::L8,
        (3, 8) => image::ExtendedColorType::Rgb8,
        (1, 16) => image::ExtendedColorType::L16,
        (3, 16) => image::ExtendedColorType::Rgb16,
        _ => return Err(Error::param("channels", format!("a capture has 1 or 3 channels, not {c}"))),
    };
    let counts = image.values.iter().map(|v| (v.clamp(0.0, 1.0) * full).round());
    let data: Vec<u8> = if bits == 8 {
        counts.map(|v| v as u8).collect()
    } else {
        counts.flat_map(|v| (v as u16).to_ne_bytes()).collect()
    };
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(Cursor::new(&mut bytes))
        .write_image(&data, w as u32, h as u32, color)
        .map_err(|e| Error::encoding(path, format!("PNG encoding failed: {e}")))?;
    write_bytes(path, &bytes)
}

/// Reads an RGB (or single-channel) OpenEXR image as linear Rec. 709 RGB, the file read and
/// decoded once:
///
/// * R, G, B (alpha dropped) or a file's only channel, through the `exr` crate, at the largest
///   resolution level (level 0 of a tiled mip-map or rip-map);
/// * luminance/chroma files (`Y`, `RY`, `BY`, the chroma subsampled), through our own decoder,
///   RGB reconstructed exactly as OpenEXR's `RgbaInputFile` does ([`crate::io::exr::yca`]);
/// * RGB in other primaries than Rec. 709 (the `chromaticities` attribute) converted to
///   Rec. 709, the white adapted to D65 by Bradford ([`crate::io::exr::chromaticities`]).
pub fn read_rgb_exr(path: &Path) -> Result<Image> {
    use crate::io::exr::{chromaticities, scanline::Header, yca};
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let header = Header::parse(path, &bytes)?;
    let mut values = if yca::is_luminance_chroma(&header) {
        yca::reconstruct_rgb(&yca::read_luma_chroma(path, &bytes, &header)?).mapv(f64::from)
    } else {
        let planes: Vec<_> = match decode_exr_channels(path, &bytes, &["R", "G", "B"]) {
            Ok(rgb) => rgb.into_iter().map(|m| m.values).collect(),
            Err(Error::Parameter { .. }) => vec![
                decode_exr_channels(path, &bytes, &[])
                    .map_err(|e| {
                        Error::malformed(path, format!("expected channels R, G, B or a single channel: {e}"))
                    })?
                    .swap_remove(0)
                    .values,
            ],
            Err(e) => return Err(e),
        };
        let (h, w) = planes[0].dim();
        Array3::from_shape_fn((h, w, planes.len()), |(i, j, c)| planes[c][[i, j]])
    };
    if let (3, Some(c)) = (values.dim().2, header.chromaticities) {
        let to_709 = chromaticities::to_rec709(&c)
            .map_err(|e| Error::malformed(path, format!("attribute 'chromaticities' {c:?}: {e}")))?;
        if let Some(m) = to_709 {
            for mut px in values.lanes_mut(ndarray::Axis(2)) {
                let v = m * nalgebra::Vector3::new(px[0], px[1], px[2]);
                for c in 0..3 {
                    px[c] = v[c];
                }
            }
        }
    }
    Ok(Image::new(values))
}

/// Reads a linear image, by extension (the one image reader of calibration and the decoder):
/// OpenEXR (R, G, B or one channel), Radiance RGBE `.hdr`, OpenEXR (R, G, B or one channel),
/// NumPy `.npy` of shape `(H, W)`, `(H, W, C)`, `(1, H, W, C)` or `(H, W, 1, C)` with `C` 1 or 3,
/// or an 8/16-bit PNG/TIFF capture (counts / full scale). Non-finite values are refused.
pub fn read_image(path: &Path) -> Result<Image> {
    let ext = path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase);
    let img = match ext.as_deref() {
        Some("exr") => read_rgb_exr(path)?.values,
        Some("npy") => {
            let (header, a) = crate::io::npy::read_npy_nd(path)?;
            let (h, w, c) = match header.shape[..] {
                [h, w] => (h, w, 1),
                [h, w, c] if c == 1 || c == 3 => (h, w, c),
                [1, h, w, c] if c == 1 || c == 3 => (h, w, c),
                [h, w, 1, c] if c == 1 || c == 3 => (h, w, c),
                _ => {
                    return Err(Error::malformed(
                        path,
                        format!(
                            "has shape {:?}; an image is (H, W), (H, W, C), (1, H, W, C) or (H, W, 1, C) \
                             with C = 1 or 3",
                            header.shape
                        ),
                    ))
                }
            };
            a.into_shape_with_order((h, w, c)).map_err(|e| Error::malformed(path, e.to_string()))?
        }
        Some("png" | "tif" | "tiff") => read_capture(path)?.image.values,
        Some("hdr") => read_radiance_hdr(path)?,
        _ => {
            return Err(Error::signature(
                path,
                "an image is read from .exr, .hdr, .npy, .png, .tif or .tiff (by extension)",
            ))
        }
    };
    let (h, w, _) = img.dim();
    if h == 0 || w == 0 {
        return Err(Error::malformed(path, "is empty"));
    }
    let bad = img.iter().filter(|v| !v.is_finite()).count();
    if bad > 0 {
        return Err(Error::malformed(path, format!("holds {bad} non-finite values (NaN or infinite)")));
    }
    Ok(Image::new(img))
}

/// A Radiance RGBE (`.hdr`) image, decoded by the `image` crate to `f32` RGB.
fn read_radiance_hdr(path: &Path) -> Result<Array3<f64>> {
    let img = image::open(path)
        .map_err(|e| Error::malformed(path, format!("cannot read as a Radiance HDR image: {e}")))?;
    let rgb = img.to_rgb32f();
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    Array3::from_shape_vec((h, w, 3), rgb.into_raw().into_iter().map(f64::from).collect())
        .map_err(|e| Error::malformed(path, format!("the image data does not fill {w} x {h}: {e}")))
}

/// A bracket: capture files with their exposure times (seconds).
#[derive(Debug, Clone, PartialEq)]
pub struct ExposureList {
    /// Each capture file with its exposure time, seconds, in the list's order.
    pub frames: Vec<(PathBuf, f64)>,
    /// The exposure the merged radiance is expressed at, seconds (value 1 = full scale at this
    /// time); `None`: the radiance is in fraction of full scale per second.
    pub reference_exposure: Option<f64>,
}

#[derive(Deserialize)]
struct JsonList {
    reference_exposure_s: Option<f64>,
    frames: Vec<JsonFrame>,
}

#[derive(Deserialize)]
struct JsonFrame {
    file: String,
    exposure_s: f64,
    #[serde(default)]
    doe: Option<bool>,
}

/// Reads an exposure list (see the module docs). Frames marked `"doe": true` are taken when
/// `with_doe`, the others (`false` or absent) otherwise.
pub fn read_exposures(path: &Path, with_doe: bool) -> Result<ExposureList> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let list: JsonList = serde_json::from_str(&text).map_err(|e| {
        let what = format!("not an exposure list ({{\"frames\": [{{\"file\", \"exposure_s\"}}]}}): {e}");
        // JSON that does not parse is malformed; JSON of another shape is another file.
        match e.classify() {
            serde_json::error::Category::Syntax | serde_json::error::Category::Eof => {
                Error::malformed(path, what)
            }
            _ => Error::signature(path, what),
        }
        .at_json(&text, &e)
    })?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut frames = Vec::new();
    for (k, f) in list.frames.iter().enumerate() {
        if !(f.exposure_s.is_finite() && f.exposure_s > 0.0) {
            return Err(Error::malformed(
                path,
                format!("frames[{k}].exposure_s is {}; expected a positive time in seconds", f.exposure_s),
            ));
        }
        if f.doe.unwrap_or(false) == with_doe {
            frames.push((dir.join(&f.file), f.exposure_s));
        }
    }
    if frames.is_empty() {
        return Err(Error::malformed(
            path,
            format!("lists no frame with \"doe\": {with_doe} (of {} frames)", list.frames.len()),
        ));
    }
    if let Some(t) = list.reference_exposure_s {
        if !(t.is_finite() && t > 0.0) {
            return Err(Error::malformed(path, format!("reference_exposure_s is {t}; expected seconds > 0")));
        }
    }
    Ok(ExposureList { frames, reference_exposure: list.reference_exposure_s })
}

/// How a bracket is named on the command line: capture files with their times, or an
/// exposure list (given with `--exposures`, or as the only file when it is a `.json` file).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BracketSpec {
    /// Capture files (or a single `.json` exposure list).
    pub files: Vec<PathBuf>,
    /// The exposure time of each file, in its order, as text ("1/60", "0.5", "2s", "250ms").
    pub times: Vec<String>,
    /// The exposure list (`--exposures`); `None` when the files and times name the bracket.
    pub exposures: Option<PathBuf>,
    /// Take the frames marked `"doe": true` from the exposure list.
    pub doe_frames: bool,
    /// The exposure the radiance is expressed at ("1/60", "250ms"); overrides the list's
    /// `reference_exposure_s`.
    pub reference_exposure: Option<String>,
}

/// The exposure list a [`BracketSpec`] names. A single `.json` file among the files is read as
/// the exposure list; files without times, times without files, or both files and a list are
/// refused with what was given and what is expected.
pub fn resolve_bracket(spec: &BracketSpec) -> Result<ExposureList> {
    let is_json = |p: &Path| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("json"));
    let json_file = match spec.files.as_slice() {
        [one] if is_json(one) && spec.times.is_empty() => Some(one.clone()),
        _ => None,
    };
    let mut list = match (spec.exposures.clone(), json_file) {
        (Some(_), Some(_)) => {
            return Err(Error::param(
                "bracket",
                "an exposure list was given twice (as a file and as `exposures`); give one",
            ))
        }
        (Some(json), None) | (None, Some(json)) => {
            if !spec.files.is_empty() && spec.exposures.is_some() {
                return Err(Error::param(
                    "bracket",
                    format!(
                        "{} capture files and the exposure list {}: give the files with `times`, or \
                         the list alone",
                        spec.files.len(),
                        json.display()
                    ),
                ));
            }
            if !spec.times.is_empty() {
                return Err(Error::param(
                    "times",
                    format!(
                        "the exposure list {} gives the times; `times` is not used with it",
                        json.display()
                    ),
                ));
            }
            read_exposures(&json, spec.doe_frames)?
        }
        (None, None) => {
            if let Some(j) = spec.files.iter().find(|p| is_json(p)) {
                return Err(Error::param(
                    "bracket",
                    format!(
                        "{} is an exposure list; give it alone (or as `exposures`), not among capture \
                         files",
                        j.display()
                    ),
                ));
            }
            if spec.files.is_empty() {
                return Err(Error::param(
                    "bracket",
                    "no captures: give `files` with `times`, or an exposure list (LIST.json or `exposures`)",
                ));
            }
            exposures_from_times(&spec.files, &spec.times)?
        }
    };
    if let Some(t) = &spec.reference_exposure {
        list.reference_exposure = Some(parse_time(t)?);
    }
    Ok(list)
}

/// Pairs files with times given on the command line ("1/60", "0.5", "2s", "250ms").
pub fn exposures_from_times(files: &[PathBuf], times: &[String]) -> Result<ExposureList> {
    if files.len() != times.len() {
        return Err(Error::param(
            "times",
            format!(
                "{} exposure times for {} files: expected one time per file (`times` 1/60,1/30,...), or \
                 an exposure list (LIST.json or `exposures`)",
                times.len(),
                files.len()
            ),
        ));
    }
    let frames =
        files.iter().zip(times).map(|(f, t)| Ok((f.clone(), parse_time(t)?))).collect::<Result<Vec<_>>>()?;
    Ok(ExposureList { frames, reference_exposure: None })
}

/// An exposure time in seconds: "0.5", "1/60", "2s", "250ms", "100us".
pub fn parse_time(text: &str) -> Result<f64> {
    let t = text.trim();
    let bad = || Error::param("time", format!("'{text}' is not an exposure time (e.g. 0.5, 1/60, 250ms)"));
    let (num, scale) = if let Some(v) = t.strip_suffix("ms") {
        (v, 1e-3)
    } else if let Some(v) = t.strip_suffix("us") {
        (v, 1e-6)
    } else if let Some(v) = t.strip_suffix('s') {
        (v, 1.0)
    } else {
        (t, 1.0)
    };
    let num = num.trim();
    let value = match num.split_once('/') {
        Some((a, b)) => {
            a.trim().parse::<f64>().map_err(|_| bad())? / b.trim().parse::<f64>().map_err(|_| bad())?
        }
        None => num.parse::<f64>().map_err(|_| bad())?,
    } * scale;
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(bad())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_parse_with_units_and_fractions() {
        assert_eq!(parse_time("1/4").unwrap(), 0.25);
        assert_eq!(parse_time("250ms").unwrap(), 0.25);
        assert_eq!(parse_time("2 s").unwrap(), 2.0);
        assert!((parse_time("100us").unwrap() - 1e-4).abs() < 1e-18);
        for bad in ["", "-1", "0", "1/0", "fast"] {
            assert!(parse_time(bad).is_err(), "{bad}");
        }
    }

    /// A Radiance file written by the `image` crate's encoder, with values RGBE holds exactly
    /// (a shared exponent per pixel, 8-bit mantissas), comes back as they were.
    #[test]
    fn radiance_hdr_images_are_read() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.hdr");
        let px = [[0.5f32, 0.25, 1.0], [2.0, 1.0, 0.5], [8.0, 4.0, 6.0], [0.125, 0.0, 0.0625]];
        let pixels: Vec<image::Rgb<f32>> = px.iter().map(|&c| image::Rgb(c)).collect();
        let file = std::fs::File::create(&p).unwrap();
        image::codecs::hdr::HdrEncoder::new(file).encode(&pixels, 2, 2).unwrap();
        let img = read_image(&p).unwrap();
        assert_eq!((img.height(), img.width(), img.channels()), (2, 2, 3));
        let back: Vec<f64> = img.values.iter().copied().collect();
        let want: Vec<f64> = px.iter().flatten().map(|&v| v as f64).collect();
        assert_eq!(back, want);
    }

    #[test]
    fn captures_round_trip_at_8_and_16_bits() {
        let dir = tempfile::tempdir().unwrap();
        let v = Image::new(Array3::from_shape_fn((5, 7, 3), |(i, j, c)| (i * 21 + j * 3 + c) as f64 / 120.0));
        for bits in [8u8, 16] {
            let p = dir.path().join(format!("c{bits}.png"));
            write_capture(&p, &v, bits).unwrap();
            let c = read_capture(&p).unwrap();
            assert_eq!(c.bits, bits);
            let step = 0.5 / c.full_scale() + 1e-12;
            assert!(c.image.values.iter().zip(&v.values).all(|(a, b)| (a - b).abs() <= step));
        }
    }
}
