//! Real HDR images as training and validation scenes for fine-tuning (`finetune --data`).
//!
//! * *Reading*: every `.exr` and `.hdr` file below a folder, recursively, sorted by path, as
//!   linear Rec. 709 RGB through the one image reader (alpha dropped; luminance/chroma files
//!   and other primaries converted, see [`crate::calibration::capture::read_rgb_exr`]). The
//!   negative values of lossy (DWA) compression's ringing are set to 0 (see
//!   [`NEGATIVE_NOISE`]). Each file keeps its own arbitrary radiance scale: the measurement
//!   model sets every sample's exposure anyway. An image that cannot be read is skipped with a
//!   warning naming it and why; a folder with none readable, or a split that leaves no
//!   training or no validation image, is refused.
//! * *Split*: an image belongs to the validation set when the first byte of the SHA-256 of its
//!   path relative to the folder is below `256 / holdout_every` ([`split`]). The rule looks at
//!   nothing but the name, so adding images never moves one from validation into training,
//!   and validation images are never trained on.
//! * *Photographs* (any aspect ratio but 2:1) give random crops after a random rescale by
//!   `s` in `[0.6, 1]` (bilinear; upscaled only as far as the crop plus its PSF margins needs).
//! * *Equirectangular panoramas* (width = 2 x height) give perspective (gnomonic) views: for
//!   a view direction at yaw `psi` and pitch `theta` (within +-30 degrees of the horizon), the
//!   ray of view pixel `(i, j)` is `d = f e_z + (j - c_x) e_x - (i - c_y) e_y` in the camera
//!   frame, rotated by pitch then yaw; its longitude `atan2(d_x, d_z)` and latitude
//!   `asin(d_y / |d|)` index the panorama (bilinear, wrapping in longitude). The focal length
//!   `f` in view pixels makes the central pixel cover `k` panorama pixels, `k` in `[1, 1.4]`:
//!   `f = W / (2 pi k)`. The camera itself (35 mm lens, 4.29 um pixels) sees 0.007 degrees a
//!   pixel, fifty times finer than a 1024-wide panorama; views at the camera's own angular
//!   pitch would be fifty-fold upsampled blur, so they are rendered at the panorama's own
//!   resolution instead, never upsampled.
//! * *Augmentation* (the paper's: crops, rescaling, flips, hue and saturation): a rotation of
//!   the chroma about the grey axis by an angle in +-15 degrees, a saturation factor in
//!   `[0.7, 1.3]` about the luminance `L = 0.2126 R + 0.7152 G + 0.0722 B`, and a white-balance
//!   gain per channel, log-uniform in `[1/g, g]` (so no colour is favoured on average) with `g`
//!   = [`HdrScenes::white_balance`], by default [`WHITE_BALANCE`] = 2: a capture is the
//!   sensor's unbalanced RGB, whose channel means differ threefold in the paper's Kitchen
//!   (1.55 : 0.93 : 0.52), so the training views must span such casts (with `g` = 1.18 the ratio
//!   of two channels never passes 1.4). Negative values made by the rotation are clipped to 0.
//!   Flips are applied by the trainer.

use std::path::{Path, PathBuf};

use ndarray::{Array3, Axis};
use sha2::{Digest, Sha256};

use super::scenes::SceneSource;
use crate::error::{DataCause, Error, Result};
use crate::image::Image;
use crate::rng::Lcg;

/// Negative values summing to at most this fraction of an image's positive ones are taken as
/// the ringing of lossy compression and set to 0; more and the image is refused. (DWA-coded
/// panoramas of 512 x 256 ring around the sun by up to 11 %, as OpenEXR's own reader shows.)
pub const NEGATIVE_NOISE: f32 = 0.2;

/// One HDR image in memory.
#[derive(Debug, Clone)]
pub struct HdrImage {
    /// The path relative to the folder it was read from.
    pub name: String,
    /// Linear RGB, finite and non-negative.
    pub pixels: Image<f32>,
}

impl HdrImage {
    /// Whether the image is an equirectangular panorama (width exactly twice the height).
    pub fn is_panorama(&self) -> bool {
        let (h, w, _) = self.pixels.dim();
        w == 2 * h
    }
}

/// The images of a folder that could be read, and why the others could not.
#[derive(Debug, Clone)]
pub struct HdrFolder {
    /// The images read, sorted by relative path.
    pub images: Vec<HdrImage>,
    /// One warning for each image skipped: its path and the reader's reason.
    pub skipped: Vec<String>,
}

/// Every `.exr` / `.hdr` file below `dir` (recursively), sorted by relative path; an image
/// that cannot be read is skipped (see [`HdrFolder::skipped`]). Refuses a folder without such
/// files or with none readable.
pub fn read_dir(dir: &Path) -> Result<HdrFolder> {
    let mut paths = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).map_err(|e| Error::io(&d, e))? {
            let p = e.map_err(|e| Error::io(&d, e))?.path();
            if p.is_dir() {
                stack.push(p);
            } else if p
                .extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "exr" | "hdr"))
            {
                paths.push(p);
            }
        }
    }
    paths.sort();
    if paths.is_empty() {
        return Err(Error::malformed(dir, "holds no .exr or .hdr images (searched recursively)"));
    }
    let mut folder = HdrFolder { images: Vec::new(), skipped: Vec::new() };
    for p in &paths {
        match read_hdr_image(dir, p) {
            Ok(img) => folder.images.push(img),
            Err(e) => folder.skipped.push(format!("skipped {}: {e}", p.display())),
        }
    }
    if folder.images.is_empty() {
        return Err(Error::malformed(
            dir,
            format!(
                "none of its {} .exr/.hdr images can be read: {}",
                paths.len(),
                folder.skipped.join("; ")
            ),
        ));
    }
    Ok(folder)
}

/// Reads one HDR image as linear RGB through the one image reader
/// ([`crate::calibration::capture::read_image`], which refuses non-finite values); refuses a
/// black or mostly negative one.
fn read_hdr_image(root: &Path, path: &PathBuf) -> Result<HdrImage> {
    let img = crate::calibration::capture::read_image(path)?;
    if img.channels() != 3 {
        return Err(Error::unsupported(
            path,
            format!("has {} channel(s); an HDR training image is RGB", img.channels()),
        ));
    }
    // Exact: the files hold f16 or f32 samples (EXR) or RGBE decoded to f32 (Radiance).
    let mut pixels = img.to_f32().values;
    let max = pixels.iter().fold(0.0f32, |m, &v| m.max(v));
    if max <= 0.0 {
        return Err(Error::malformed(path, "is black everywhere: nothing to expose"));
    }
    // Lossy compression (DWA) rings below zero around edges and highlights: such values become
    // 0, unless they carry a share of the image's energy that no compressed radiance would.
    let (neg, pos) =
        pixels.iter().fold(
            (0.0f64, 0.0f64),
            |(n, p), &v| {
                if v < 0.0 {
                    (n - v as f64, p)
                } else {
                    (n, p + v as f64)
                }
            },
        );
    if neg > NEGATIVE_NOISE as f64 * pos {
        return Err(Error::malformed(
            path,
            format!(
                "its negative values sum to {:.2} % of its positive ones; HDR radiance must be >= 0 \
                 (up to {} % is taken as compression noise and set to 0)",
                100.0 * neg / pos,
                100.0 * NEGATIVE_NOISE
            ),
        ));
    }
    pixels.mapv_inplace(|v| v.max(0.0));
    let name = path.strip_prefix(root).unwrap_or(path).to_string_lossy().replace('\\', "/");
    Ok(HdrImage { name, pixels: Image::new(pixels) })
}

/// Whether the image named `name` is held out for validation (see the module docs).
pub fn is_validation(name: &str, holdout_every: usize) -> bool {
    let first = Sha256::digest(name.as_bytes())[0] as usize;
    holdout_every > 0 && first * holdout_every < 256
}

/// Splits images into (training, validation) by [`is_validation`]. Refuses a split that
/// leaves either side empty.
pub fn split(images: Vec<HdrImage>, holdout_every: usize) -> Result<(Vec<HdrImage>, Vec<HdrImage>)> {
    let n = images.len();
    let (val, train): (Vec<_>, Vec<_>) =
        images.into_iter().partition(|i| is_validation(&i.name, holdout_every));
    if train.is_empty() || val.is_empty() {
        return Err(Error::param(
            "data",
            format!(
                "holding out 1 in {holdout_every} of {n} images by name leaves {} for training and {} for \
                 validation; give more images, or a separate validation folder (`validation_data`)",
                train.len(),
                val.len()
            ),
        ));
    }
    Ok((train, val))
}

/// Training and validation scenes from a folder of real HDR images: `validation_dir`'s images
/// validate when given (all of `dir` then trains), else 1 in `holdout_every` of `dir`'s,
/// chosen by name (`split`). Panoramas narrower than `min_panorama_width` pixels are left
/// out of both: a view of one spans too wide an angle per crop (measured: training on the
/// 512-wide panoramas of the shared set as well lowered the real captures' scores).
/// Validation views are not colour-jittered. Images that cannot be read are skipped, each
/// with a warning in its side's [`HdrScenes::skipped`] (those of `dir` on the training side).
pub fn training_and_validation(
    dir: &Path,
    validation_dir: Option<&Path>,
    holdout_every: usize,
    min_panorama_width: usize,
) -> Result<(HdrScenes, HdrScenes)> {
    let wide_enough = |i: &HdrImage| !i.is_panorama() || i.pixels.dim().1 >= min_panorama_width;
    let read = |d: &Path| -> Result<HdrFolder> {
        let all = read_dir(d)?;
        let n = all.images.len();
        let images: Vec<HdrImage> = all.images.into_iter().filter(wide_enough).collect();
        if images.is_empty() {
            return Err(Error::malformed(
                d,
                format!(
                    "none of its {n} readable images is a photograph or a panorama at least {min_panorama_width} px wide"
                ),
            ));
        }
        Ok(HdrFolder { images, skipped: all.skipped })
    };
    let folder = read(dir)?;
    let (train, val, val_skipped) = match validation_dir {
        Some(v) => {
            let v = read(v)?;
            (folder.images, v.images, v.skipped)
        }
        None => {
            let (t, v) = split(folder.images, holdout_every).map_err(|e| match e {
                Error::Parameter { name, reason, allowed } if !folder.skipped.is_empty() => {
                    Error::Parameter {
                        name,
                        allowed,
                        reason: format!(
                            "{reason} ({} could not be read: {})",
                            folder.skipped.len(),
                            folder.skipped.join("; ")
                        ),
                    }
                }
                e => e,
            })?;
            (t, v, Vec::new())
        }
    };
    let mut train = HdrScenes::new(&format!("{} (training)", dir.display()), train)?;
    train.skipped = folder.skipped;
    let mut val = HdrScenes::new(&format!("{} (validation)", validation_dir.unwrap_or(dir).display()), val)?;
    val.skipped = val_skipped;
    val.colour_jitter = false;
    Ok((train, val))
}

/// `doefab finetune`'s default hold-out: 1 in this many images (by name) validates.
pub const HOLDOUT_EVERY: usize = 5;
/// `doefab finetune`'s default narrowest panorama used, pixels (narrower ones hurt on the
/// paper's real captures; README, fine-tuning table).
pub const MIN_PANORAMA_WIDTH: usize = 1024;

/// Default largest white-balance gain of the colour jitter (see the module docs).
pub const WHITE_BALANCE: f64 = 2.0;

/// Random views of real HDR images (see the module docs).
pub struct HdrScenes {
    name: String,
    images: Vec<HdrImage>,
    /// Whether to jitter colour (hue, saturation, white balance).
    pub colour_jitter: bool,
    /// Largest white-balance gain `g`: each channel's gain is log-uniform in `[1/g, g]`.
    pub white_balance: f64,
    /// Warnings about the images of its folder that could not be read (see [`read_dir`]).
    pub skipped: Vec<String>,
}

impl HdrScenes {
    /// Scenes from `images`, described as `name` in the decoder's metadata.
    pub fn new(name: &str, images: Vec<HdrImage>) -> Result<HdrScenes> {
        if images.is_empty() {
            return Err(Error::data(DataCause::Empty, format!("{name}: no images")));
        }
        Ok(HdrScenes {
            name: name.into(),
            images,
            colour_jitter: true,
            white_balance: WHITE_BALANCE,
            skipped: Vec::new(),
        })
    }

    /// The images' names.
    pub fn names(&self) -> Vec<&str> {
        self.images.iter().map(|i| i.name.as_str()).collect()
    }
}

impl SceneSource for HdrScenes {
    fn describe(&self) -> String {
        let panoramas = self.images.iter().filter(|i| i.is_panorama()).count();
        let jitter = match self.colour_jitter {
            true => format!("; colour jitter, white-balance gains in [1/{0}, {0}]", self.white_balance),
            false => String::new(),
        };
        let skipped = match self.skipped.len() {
            0 => String::new(),
            n => format!("; {n} unreadable image{} skipped", if n == 1 { "" } else { "s" }),
        };
        format!(
            "{} ({} real HDR images: {} photographs, {} panoramas as perspective views{jitter}{skipped})",
            self.name,
            self.images.len(),
            self.images.len() - panoramas,
            panoramas
        )
    }

    fn scene(&self, rng: &mut Lcg, rows: usize, cols: usize) -> Result<Image<f32>> {
        let k = ((rng.uniform() * self.images.len() as f64) as usize).min(self.images.len() - 1);
        let img = &self.images[k];
        let mut out = if img.is_panorama() {
            let yaw = rng.uniform() * std::f64::consts::TAU;
            let pitch = (rng.uniform() * 2.0 - 1.0) * 30f64.to_radians();
            let k = 1.0 + 0.4 * rng.uniform();
            perspective_view(&img.pixels.values, yaw, pitch, k, rows, cols)
        } else {
            photo_crop(&img.pixels.values, rng, rows, cols)
        };
        if self.colour_jitter {
            jitter_colour(&mut out, rng, self.white_balance);
        }
        if out.iter().all(|&v| v == 0.0) {
            return Err(Error::data(DataCause::Empty, format!("{}: a black view was drawn", img.name)));
        }
        Ok(Image::new(out))
    }
}

/// Bilinear sample of channel `c` at fractional `(y, x)` (clamped at the edges; `wrap_x` wraps
/// in x instead, for longitude).
fn bilinear(img: &Array3<f32>, y: f64, x: f64, wrap_x: bool) -> [f32; 3] {
    let (h, w, _) = img.dim();
    let y = y.clamp(0.0, (h - 1) as f64);
    let (y0, fy) = (y.floor() as usize, y - y.floor());
    let y1 = (y0 + 1).min(h - 1);
    let (x0, x1, fx) = if wrap_x {
        let x = x.rem_euclid(w as f64);
        let x0 = (x.floor() as usize).min(w - 1);
        (x0, (x0 + 1) % w, x - x.floor())
    } else {
        let x = x.clamp(0.0, (w - 1) as f64);
        let x0 = x.floor() as usize;
        (x0, (x0 + 1).min(w - 1), x - x.floor())
    };
    let mut out = [0.0f32; 3];
    for (c, o) in out.iter_mut().enumerate() {
        let top = img[[y0, x0, c]] as f64 * (1.0 - fx) + img[[y0, x1, c]] as f64 * fx;
        let bottom = img[[y1, x0, c]] as f64 * (1.0 - fx) + img[[y1, x1, c]] as f64 * fx;
        *o = (top * (1.0 - fy) + bottom * fy) as f32;
    }
    out
}

/// A random crop of a photograph after a random rescale (see the module docs).
fn photo_crop(img: &Array3<f32>, rng: &mut Lcg, rows: usize, cols: usize) -> Array3<f32> {
    let (h, w, _) = img.dim();
    let needed = (rows as f64 / h as f64).max(cols as f64 / w as f64);
    let lo = needed.max(0.6);
    let s = lo + (needed.max(1.0) - lo) * rng.uniform();
    // Output pixel (i, j) reads input (r0 + i / s, c0 + j / s).
    let (span_r, span_c) = ((rows - 1) as f64 / s, (cols - 1) as f64 / s);
    let r0 = rng.uniform() * ((h - 1) as f64 - span_r).max(0.0);
    let c0 = rng.uniform() * ((w - 1) as f64 - span_c).max(0.0);
    let mut out = Array3::zeros((rows, cols, 3));
    for i in 0..rows {
        for j in 0..cols {
            let v = bilinear(img, r0 + i as f64 / s, c0 + j as f64 / s, false);
            for c in 0..3 {
                out[[i, j, c]] = v[c];
            }
        }
    }
    out
}

/// A gnomonic view of an equirectangular panorama (see the module docs): yaw and pitch in
/// radians, `k` panorama pixels per view pixel at the centre.
pub fn perspective_view(
    pano: &Array3<f32>,
    yaw: f64,
    pitch: f64,
    k: f64,
    rows: usize,
    cols: usize,
) -> Array3<f32> {
    let (h, w, _) = pano.dim();
    let f = w as f64 / (std::f64::consts::TAU * k);
    let (cy, cx) = ((rows as f64 - 1.0) / 2.0, (cols as f64 - 1.0) / 2.0);
    let (sp, cp) = pitch.sin_cos();
    let (sy, cy_) = yaw.sin_cos();
    let mut out = Array3::zeros((rows, cols, 3));
    for i in 0..rows {
        for j in 0..cols {
            // Camera frame: x right, y up, z forward.
            let (x, y, z) = (j as f64 - cx, cy - i as f64, f);
            // Pitch about x, then yaw about y.
            let (y1, z1) = (y * cp + z * sp, -y * sp + z * cp);
            let (x2, z2) = (x * cy_ + z1 * sy, -x * sy + z1 * cy_);
            let lon = x2.atan2(z2);
            let lat = (y1 / (x2 * x2 + y1 * y1 + z2 * z2).sqrt()).asin();
            // Column 0 at longitude -pi, row 0 at latitude +pi/2 (pixel centres).
            let px = (lon + std::f64::consts::PI) / std::f64::consts::TAU * w as f64 - 0.5;
            let py = (std::f64::consts::FRAC_PI_2 - lat) / std::f64::consts::PI * h as f64 - 0.5;
            let v = bilinear(pano, py, px, true);
            for c in 0..3 {
                out[[i, j, c]] = v[c];
            }
        }
    }
    out
}

/// Hue rotation, saturation and white-balance jitter (see the module docs).
fn jitter_colour(img: &mut Array3<f32>, rng: &mut Lcg, white_balance: f64) {
    let angle = (rng.uniform() * 2.0 - 1.0) * 15f64.to_radians();
    let sat = 0.7 + 0.6 * rng.uniform();
    let gains: Vec<f64> = (0..3).map(|_| ((rng.uniform() * 2.0 - 1.0) * white_balance.ln()).exp()).collect();
    // Rotation about the grey axis (1, 1, 1)/sqrt(3) by `angle` (Rodrigues' formula).
    let (s, c) = angle.sin_cos();
    let (a, b) = ((1.0 - c) / 3.0, s / 3f64.sqrt());
    let rot = [[c + a, a - b, a + b], [a + b, c + a, a - b], [a - b, a + b, c + a]];
    for mut px in img.lanes_mut(Axis(2)) {
        let v = [px[0] as f64, px[1] as f64, px[2] as f64];
        let r: Vec<f64> = (0..3).map(|o| rot[o][0] * v[0] + rot[o][1] * v[1] + rot[o][2] * v[2]).collect();
        let l = 0.2126 * r[0] + 0.7152 * r[1] + 0.0722 * r[2];
        for ch in 0..3 {
            px[ch] = ((l + sat * (r[ch] - l)) * gains[ch]).max(0.0) as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A synthetic panorama whose value at a pixel centre is a closed-form function of the
    /// direction: a gnomonic view must read each ray's own direction back.
    #[test]
    fn a_perspective_view_looks_where_its_rays_point() {
        let (h, w) = (256, 512);
        // Value = longitude in [0, 1) in R, latitude in [0, 1] in G.
        let pano = Array3::from_shape_fn((h, w, 3), |(i, j, c)| match c {
            0 => (j as f32 + 0.5) / w as f32,
            1 => (i as f32 + 0.5) / h as f32,
            _ => 1.0,
        });
        let (yaw, pitch) = (1.0f64, 0.3f64);
        let v = perspective_view(&pano, yaw, pitch, 1.0, 33, 33);
        // The centre looks along (yaw, pitch): longitude yaw, latitude pitch.
        let lon = (yaw + std::f64::consts::PI) / std::f64::consts::TAU;
        let lat = (std::f64::consts::FRAC_PI_2 - pitch) / std::f64::consts::PI;
        assert!((v[[16, 16, 0]] as f64 - lon).abs() < 1e-4, "{} vs {lon}", v[[16, 16, 0]]);
        assert!((v[[16, 16, 1]] as f64 - lat).abs() < 1e-4, "{} vs {lat}", v[[16, 16, 1]]);
        // One view pixel right of the centre turns by atan(1 / f) in the tilted camera frame:
        // longitude moves by atan2(1, f cos(pitch)) (spherical trigonometry of the ray).
        let f = w as f64 / std::f64::consts::TAU;
        let dlon = (1.0f64).atan2(f * pitch.cos()) / std::f64::consts::TAU;
        assert!(((v[[16, 17, 0]] - v[[16, 16, 0]]) as f64 - dlon).abs() < 2e-5);
        // Up in the view is up in the world: row 0 has the smaller latitude index.
        assert!(v[[0, 16, 1]] < v[[32, 16, 1]]);
    }

    #[test]
    fn the_split_is_stable_and_leaves_both_sides_something() {
        let names: Vec<String> = (0..40).map(|k| format!("img{k}.exr")).collect();
        let held: Vec<bool> = names.iter().map(|n| is_validation(n, 5)).collect();
        let count = held.iter().filter(|&&b| b).count();
        assert!((3..=14).contains(&count), "{count} of 40 held out at 1 in 5");
        // Adding images leaves the others where they were.
        assert!(names.iter().zip(&held).all(|(n, &b)| is_validation(n, 5) == b));
        let one = vec![HdrImage { name: "a.exr".into(), pixels: Image::new(Array3::ones((4, 4, 3))) }];
        assert!(split(one, 5).is_err());
    }

    #[test]
    fn colour_jitter_keeps_grey_grey_on_average_and_values_non_negative() {
        let mut sums = [0.0f64; 3];
        let mut rng = Lcg(4);
        for _ in 0..400 {
            let mut img = Array3::from_elem((2, 2, 3), 1.0f32);
            img[[0, 0, 0]] = 5.0;
            jitter_colour(&mut img, &mut rng, 1.18);
            assert!(img.iter().all(|&v| v >= 0.0 && v.is_finite()));
            for c in 0..3 {
                sums[c] += img[[1, 1, c]] as f64;
            }
        }
        let mean = (sums[0] + sums[1] + sums[2]) / 3.0;
        for s in sums {
            assert!((s / mean - 1.0).abs() < 0.03, "{sums:?}");
        }
    }

    /// The largest red/blue ratio a grey pixel reaches over many draws: near `g^2` (times the
    /// hue rotation's small share), so `g` = 2 spans the threefold casts of real sensor RGB
    /// where 1.18 does not.
    #[test]
    fn white_balance_gains_span_the_casts_of_sensor_rgb() {
        let widest = |g: f64| {
            let mut rng = Lcg(8);
            (0..2000)
                .map(|_| {
                    let mut img = Array3::from_elem((1, 1, 3), 1.0f32);
                    jitter_colour(&mut img, &mut rng, g);
                    (img[[0, 0, 0]] / img[[0, 0, 2]]) as f64
                })
                .fold(0.0, f64::max)
        };
        let (narrow, wide) = (widest(1.18), widest(WHITE_BALANCE));
        eprintln!("largest R/B of a grey pixel: {narrow:.2} (g 1.18), {wide:.2} (g 2)");
        assert!(narrow < 1.6, "{narrow}");
        assert!(wide > 3.0 && wide < 4.5, "{wide}");
    }
}
