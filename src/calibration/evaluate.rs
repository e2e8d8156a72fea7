//! PSNR of reconstructions against a reference HDR image of the same scene (`doefab evaluate`,
//! `doefab bench decoder`).
//!
//! The paper reports PSNR "computed in the linear domain (L) and in the gamma-corrected
//! domain" (Table 1) without printing the formula; its loss uses `gamma = 1/2`. Here, over a
//! set `S` of samples (pixel and channel), reference `x`, reconstruction `y`:
//!
//! * linear: `PSNR_L = 10 log10(P^2 / mean_S (y - x)^2)`, with `P` the reference's maximum
//!   over `S`. **Negative outputs count as they are**: a decoder that writes `y < 0` is charged
//!   the full `(y - x)^2`, not credited with the clamp `max(y, 0)` a user may apply afterwards.
//!   Every score reports the smallest output over `S` and the fraction of samples below zero.
//! * gamma: `PSNR_gamma = 10 log10(P / mean_S (sqrt(y+) - sqrt(x+))^2)`, the same on square
//!   roots (peak `sqrt(P)`), with `y+ = max(y, 0)` (the square root of a negative radiance is
//!   undefined; the paper's loss clamps the same way).
//!
//! # One geometry and one pixel set per scene
//!
//! The reference (a bracket merged without the DOE) and the capture through the DOE differ by
//! the camera's motion when the DOE is attached: a few per cent of scale, tens of pixels, and
//! parallax between objects at different depths. [`prepare`] registers the reference onto the
//! *capture* once, from what both images share, and every reconstruction of that capture is
//! scored against the same warped reference over the same pixels:
//!
//! 1. The capture is predicted from the reference by the measurement model
//!    `c = clip(g (h * x), 0, 1)` (the paper's, Metzler et al. 2020, Sec. 4; `h` the measured
//!    PSF normalised to sum 1 per channel, `*` linear convolution of the reference extended
//!    past its border by its edge values, `g` the gain below, 1 = the capture's clipping
//!    level). Without a PSF, `h` is the identity. The prediction carries the PSF's copies of
//!    bright lights and the clipping that the capture shows, so tiles near lamps match.
//! 2. The prediction is registered onto the capture ([`super::capture_registration::register_local`], or
//!    one affine map [`super::capture_registration::register_affine`]), both compressed by a square root.
//! 3. The gain `g` (the DOE and its mount absorb light; the bracket's times drift) is the
//!    median of `capture / (h * x)` over the samples of covered pixels whose capture is well
//!    exposed (0.05..0.9 of the clipping level in every channel) — where the capture *is*
//!    `g (h * x)` up to noise. At least 300 samples are needed. When `g` is more than 5 % from
//!    the gain the prediction was clipped with, steps 1-3 run once more with it.
//! 4. The reference warped onto the capture's pixels and scaled by `g` is the target every
//!    reconstruction is scored against, over the pixels the registration covers (all pixels)
//!    and over those of them that are saturated in the capture (any channel at or above
//!    `saturation` times the capture's clipping level).
//!
//! **Coverage floor.** The scored fraction of the image is reported with the number of the
//! capture's saturated pixels and how many of them are scored. Below `min_coverage` of the
//! image the scene is refused (with the figure); with fewer than `min_saturated` saturated
//! pixels scored, the saturated figures are withheld and the reason is given, rather than a
//! number over a handful of pixels or a claim that none is saturated.
//!
//! **Clipping level.** Captures are read as counts / full scale. A sensor of fewer bits than
//! its file (12-bit data in a 16-bit PNG) clips below full scale; the capture's clipping level
//! is then its maximum value, recognised by a pile-up of samples there (at least 0.01 % of them
//! at exactly the maximum, which lies below `saturation`), and reported as a warning.

use std::ops::Bound;

use ndarray::{s, Array2, Array3, Axis, Zip};
use serde::Serialize;

use super::capture_registration::{
    luminance, register_affine, register_local, warp, LocalRegistration, Model, RegisterOptions, Registration,
};
use crate::error::{Allowed, Condition, DataCause, Error, Result};
use crate::image::Image;
use crate::optics::convolve::Convolver;
use crate::optics::psf::Psf;

/// PSNR figures over one set of samples.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Psnr {
    /// `PSNR_L = 10 log10(P^2 / mean (y - x)^2)`, dB.
    pub linear_db: f64,
    /// `PSNR_gamma = 10 log10(P / mean (sqrt(y+) - sqrt(x+))^2)`, dB.
    pub gamma_db: f64,
    /// The peak `P`: the reference's maximum over the samples, in the images' units.
    pub peak: f64,
    /// Pixels evaluated (each with all its channels).
    pub pixels: usize,
    /// The smallest reconstruction value over the samples, in the images' units.
    pub min_output: f64,
    /// Fraction of samples (pixel and channel) below zero (0..1), counted as they are in
    /// `linear_db`, as 0 in `gamma_db`.
    pub negative_fraction: f64,
}

/// PSNR of `recon` against `reference` over the pixels where `mask` is true (all when `None`).
pub fn psnr(reference: &Image, recon: &Image, mask: Option<&Array2<bool>>) -> Result<Psnr> {
    let (reference, recon) = (&reference.values, &recon.values);
    if reference.dim() != recon.dim() {
        return Err(Error::data(
            DataCause::Shape,
            format!(
                "the reference is {:?} and the reconstruction {:?} (rows, cols, channels)",
                reference.dim(),
                recon.dim()
            ),
        ));
    }
    let (h, w, nc) = reference.dim();
    if let Some(m) = mask {
        if m.dim() != (h, w) {
            return Err(Error::data(
                DataCause::Shape,
                format!("the pixel mask is {:?}, the images {:?}", m.dim(), (h, w)),
            ));
        }
    }
    let (mut peak, mut sl, mut sg, mut n, mut pixels) = (0.0f64, 0.0, 0.0, 0usize, 0usize);
    let (mut min_output, mut negative) = (f64::INFINITY, 0usize);
    for i in 0..h {
        for j in 0..w {
            if mask.is_some_and(|m| !m[[i, j]]) {
                continue;
            }
            pixels += 1;
            for c in 0..nc {
                let (x, y) = (reference[[i, j, c]], recon[[i, j, c]]);
                if !x.is_finite() || !y.is_finite() {
                    let what = format!(
                        "non-finite value at row {i}, column {j}, channel {c}: reference {x}, reconstruction {y}"
                    );
                    return Err(Error::data(DataCause::NotFinite, what));
                }
                peak = peak.max(x);
                sl += (y - x).powi(2);
                sg += (y.max(0.0).sqrt() - x.max(0.0).sqrt()).powi(2);
                min_output = min_output.min(y);
                negative += usize::from(y < 0.0);
                n += 1;
            }
        }
    }
    if n == 0 || peak <= 0.0 {
        return Err(Error::data(DataCause::Empty, "no samples with a positive reference to evaluate"));
    }
    let (ml, mg) = (sl / n as f64, sg / n as f64);
    Ok(Psnr {
        linear_db: 10.0 * (peak * peak / ml).log10(),
        gamma_db: 10.0 * (peak / mg).log10(),
        peak,
        pixels,
        min_output,
        negative_fraction: negative as f64 / n as f64,
    })
}

/// Settings of [`prepare`].
#[derive(Debug, Clone, PartialEq)]
pub struct ScoringOptions {
    /// The registration (its `model`: a local field or one affine map).
    pub register: RegisterOptions,
    /// Saturation level, fraction of the capture's clipping level.
    pub saturation: f64,
    /// Smallest fraction of the image the registration must cover; below it the scene is refused.
    pub min_coverage: f64,
    /// Fewest saturated pixels of the capture that must be scored for the saturated figures.
    pub min_saturated: usize,
}

impl ScoringOptions {
    /// Refuses a clipping level outside (0, 1] and a coverage floor outside [0, 1].
    fn check(&self) -> Result<()> {
        if !(self.saturation > 0.0 && self.saturation <= 1.0) {
            return Err(Error::param_in(
                "saturation",
                Allowed::within(Bound::Excluded(0.0), Bound::Included(1.0)),
                format!("{} is not in (0, 1]", self.saturation),
            ));
        }
        if !(0.0..=1.0).contains(&self.min_coverage) {
            return Err(Error::param_in(
                "min_coverage",
                Allowed::between(0.0, 1.0),
                format!("{} is not a fraction in [0, 1]", self.min_coverage),
            ));
        }
        Ok(())
    }
}

impl Default for ScoringOptions {
    fn default() -> Self {
        ScoringOptions {
            register: RegisterOptions { model: Model::Local, ..RegisterOptions::default() },
            saturation: 0.98,
            min_coverage: 0.3,
            min_saturated: 100,
        }
    }
}

/// How a scene's reference was registered onto its capture, and what is scored.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Footing {
    /// Rows of the capture, pixels.
    pub rows: usize,
    /// Columns of the capture, pixels.
    pub cols: usize,
    /// Whether the capture was predicted through a PSF (else the reference itself, clipped).
    pub psf: bool,
    /// The motion model registered: "affine" or "local".
    pub model: Model,
    /// The affine map of the prediction onto the capture; `None` under the local model.
    pub registration: Option<Registration>,
    /// The displacement field of the prediction onto the capture; `None` under the affine
    /// model.
    pub local_registration: Option<LocalRegistration>,
    /// The gain `g`: median of `capture / (h * reference)` over well-exposed samples (see the
    /// module docs).
    pub gain: f64,
    /// The samples (pixel and channel) that median is taken over, at least 300.
    pub gain_samples: usize,
    /// Registration passes (2 when the gain moved the clipping of the prediction).
    pub passes: usize,
    /// The capture's clipping level, fraction of its full scale (1 unless detected lower).
    pub clipping_level: f64,
    /// Where each channel clips, fraction of the clipping level (`super::clipping`): a sample
    /// at or above `saturation` times it is saturated.
    pub channel_clipping: Vec<f64>,
    /// Pixels scored: those the registration covers.
    pub pixels_scored: usize,
    /// `pixels_scored` over the image's pixels (0..1).
    pub coverage: f64,
    /// Pixels saturated in the capture (any channel at or above `saturation` times its
    /// clipping).
    pub saturated_in_capture: usize,
    /// Of those, the pixels scored.
    pub saturated_scored: usize,
    /// Why the saturated figures are withheld; `None` when they are given.
    pub saturated_withheld: Option<String>,
    /// A lower clipping level detected in the capture or in a channel, one sentence each.
    pub warnings: Vec<String>,
}

/// A scene ready for scoring: the reference on the capture's pixels and the pixel sets.
#[derive(Debug, Clone)]
pub struct Scoring {
    /// The registered reference, scaled by the gain (0 where not covered).
    pub reference: Image,
    /// Pixels scored.
    pub mask: Array2<bool>,
    /// Scored pixels saturated in the capture.
    pub saturated: Array2<bool>,
    /// How the reference was registered and what is scored.
    pub footing: Footing,
}

/// One image scored on a [`Scoring`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Score {
    /// The image's name (its path in `doefab evaluate`; "capture as it is" for the baseline).
    pub name: String,
    /// PSNR over every scored pixel.
    pub all: Psnr,
    /// `None` when the saturated figures are withheld ([`Footing::saturated_withheld`]).
    pub saturated: Option<Psnr>,
    /// Colour balance: each channel's mean over the scored pixels not saturated in the
    /// capture, divided by the mean of the three (1, 1, 1 for a grey balance). A decoder that
    /// casts a colour moves these against the capture's and its start's.
    pub channel_balance: Vec<f64>,
}

/// The capture's clipping level (see the module docs): 1, or the maximum where samples pile up
/// below `saturation`.
fn clipping_level(capture: &Array3<f64>, saturation: f64, warnings: &mut Vec<String>) -> f64 {
    let max = capture.iter().copied().fold(0.0f64, f64::max);
    let at_max = capture.iter().filter(|v| **v == max).count();
    if max > 0.0 && max < saturation && at_max as f64 >= 1e-4 * capture.len() as f64 {
        warnings.push(format!(
            "the capture's samples pile up at {max:.5} of full scale ({at_max} samples): taken as its clipping \
             level (a sensor of fewer bits than its file)"
        ));
        max
    } else {
        1.0
    }
}

/// `h * x` per channel, the same size as `x`, with `x` extended past its border by its edge
/// values (light from just outside the frame lands inside it) and `h` normalised to sum 1.
pub fn convolve_psf(x: &Image, psf: &Psf) -> Result<Image> {
    let x = &x.values;
    let (h, w, nc) = x.dim();
    if psf.channels.len() != nc {
        return Err(Error::data(
            DataCause::Shape,
            format!("the PSF has {} channels and the images {nc}", psf.channels.len()),
        ));
    }
    let mut psf = psf.clone();
    psf.normalise()?;
    let (kh, kw) = psf.dim();
    let (top, left) = (kh / 2, kw / 2);
    let (ph, pw) = (h + kh - 1, w + kw - 1);
    let padded = Array3::from_shape_fn((ph, pw, nc), |(i, j, c)| {
        let (i, j) = (i.saturating_sub(top).min(h - 1), j.saturating_sub(left).min(w - 1));
        x[[i, j, c]] as f32
    });
    let full = Convolver::new(&psf, (ph, pw))?.convolve(&Image::new(padded))?;
    Ok(Image::new(full.values.slice(s![top..top + h, left..left + w, ..]).to_owned()))
}

/// Registers `reference` (linear HDR, any scale) onto `capture` (values / full scale) through
/// the measurement model with `psf`, and fixes the gain and the pixels scored (module docs).
pub fn prepare(
    reference: &Image,
    capture: &Image,
    psf: Option<&Psf>,
    opts: &ScoringOptions,
) -> Result<Scoring> {
    let (h, w, nc) = capture.dim();
    if reference.dim() != capture.dim() {
        return Err(Error::data(
            DataCause::Shape,
            format!(
                "the reference is {:?} and the capture {:?} (rows, cols, channels): both must be one size",
                reference.dim(),
                capture.dim()
            ),
        ));
    }
    opts.check()?;
    if let Some(bad) = reference.iter().chain(capture.iter()).find(|v| !v.is_finite()) {
        return Err(Error::data(DataCause::NotFinite, format!("the reference or the capture holds {bad}")));
    }
    let mut warnings = Vec::new();
    let clip = clipping_level(capture, opts.saturation, &mut warnings);
    // Where each channel clips, in units of the capture's clipping level (see `clipping`).
    let channel_clipping: Vec<f64> = match super::clipping::full_scale_of(capture) {
        Some(fs) => {
            super::clipping::channel_clipping(&[capture], fs).iter().map(|l| (l / clip).min(1.0)).collect()
        }
        None => vec![1.0; nc],
    };
    for (c, &level) in channel_clipping.iter().enumerate() {
        if level < 1.0 {
            warnings.push(format!(
                "the capture's channel {c} clips at {level:.4} of its clipping level: its samples at or above {:.4} \
                 count as saturated",
                opts.saturation * level
            ));
        }
    }
    let capture = Image::new(capture.mapv(|v| v / clip));
    let predicted = match psf {
        Some(p) => convolve_psf(reference, p)?,
        None => reference.clone(),
    };
    let cap_lum = luminance(&capture);
    // The floor is applied below, to the pixels scored.
    let register = RegisterOptions { min_coverage: 0.0, ..opts.register.clone() };
    let mut gain = 1.0;
    let mut passes = 0;
    let (mask, registration, local_registration, gain_samples) = loop {
        passes += 1;
        let mut clipped = predicted.values.clone();
        Zip::indexed(&mut clipped).for_each(|(_, _, c), v| *v = (gain * *v).clamp(0.0, channel_clipping[c]));
        let source = luminance(&Image::new(clipped));
        let (warped, mask, reg, local) = match opts.register.model {
            Model::Affine => {
                let reg = register_affine(&source, &cap_lum, &register)?;
                let (warped, inside) = warp(&predicted, &reg.affine, h, w)?;
                (warped.values, inside, Some(reg), None)
            }
            Model::Local => {
                let reg = register_local(&source, &cap_lum, &register)?;
                let (warped, inside) = reg.warp(&predicted);
                (warped.values, inside, None, Some(reg))
            }
        };
        let mut ratios = Vec::new();
        Zip::indexed(&mask).for_each(|(i, j), &inside| {
            let exposed = (0..nc).all(|c| {
                (0.05..=0.9 * channel_clipping[c]).contains(&capture[[i, j, c]]) && warped[[i, j, c]] > 0.0
            });
            if inside && exposed {
                ratios.extend((0..nc).map(|c| capture[[i, j, c]] / warped[[i, j, c]]));
            }
        });
        if ratios.len() < 300 {
            return Err(Error::validity(Condition::Coverage, format!(
                "only {} well-exposed samples (0.05..0.9 of the clipping level) among the registered pixels to \
                 match the reference's gain; 300 needed",
                ratios.len()
            )));
        }
        ratios.sort_by(f64::total_cmp);
        let g = ratios[ratios.len() / 2];
        let moved = (g / gain - 1.0).abs() > 0.05;
        gain = g;
        if !moved || passes == 2 {
            break (mask, reg, local, ratios.len());
        }
    };
    let (mut warped_reference, _) = match (&registration, &local_registration) {
        (_, Some(l)) => l.warp(reference),
        (Some(r), None) => warp(reference, &r.affine, h, w)?,
        (None, None) => return Err(Error::internal("no registration was made")),
    };
    Zip::from(warped_reference.values.lanes_mut(Axis(2))).and(&mask).for_each(|mut px, &inside| {
        if inside {
            px.mapv_inplace(|v| v * gain);
        } else {
            px.fill(0.0);
        }
    });
    let saturated_capture = Array2::from_shape_fn((h, w), |(i, j)| {
        (0..nc).any(|c| capture[[i, j, c]] >= opts.saturation * channel_clipping[c])
    });
    let saturated = &saturated_capture & &mask;
    let pixels_scored = mask.iter().filter(|v| **v).count();
    let coverage = pixels_scored as f64 / (h * w) as f64;
    let saturated_in_capture = saturated_capture.iter().filter(|v| **v).count();
    let saturated_scored = saturated.iter().filter(|v| **v).count();
    if coverage < opts.min_coverage {
        return Err(Error::validity(Condition::Coverage, format!(
            "the registration covers {:.1} % of the image ({pixels_scored} of {} pixels; {saturated_scored} of the \
             capture's {saturated_in_capture} saturated pixels); the floor is {:.0} %: too few pixels follow one \
             geometry to score on",
            100.0 * coverage,
            h * w,
            100.0 * opts.min_coverage
        )));
    }
    let saturated_withheld = (saturated_scored < opts.min_saturated).then(|| {
        if saturated_in_capture == 0 {
            format!("no pixel of the capture reaches {} of its clipping level", opts.saturation)
        } else {
            format!(
                "only {saturated_scored} of the capture's {saturated_in_capture} saturated pixels are registered \
                 ({} needed)",
                opts.min_saturated
            )
        }
    });
    let footing = Footing {
        rows: h,
        cols: w,
        psf: psf.is_some(),
        model: opts.register.model,
        registration,
        local_registration,
        gain,
        gain_samples,
        passes,
        clipping_level: clip,
        channel_clipping,
        pixels_scored,
        coverage,
        saturated_in_capture,
        saturated_scored,
        saturated_withheld,
        warnings,
    };
    Ok(Scoring { reference: warped_reference, mask, saturated, footing })
}

impl Scoring {
    /// An image in the reference's frame (the reference through a model of the camera, say)
    /// resampled onto the capture's pixels by the scene's registration, unscaled; 0 where the
    /// registration does not reach.
    pub fn warp(&self, image: &Image) -> Result<Image> {
        match (&self.footing.local_registration, &self.footing.registration) {
            (Some(l), _) => Ok(l.warp(image).0),
            (None, Some(r)) => Ok(warp(image, &r.affine, self.footing.rows, self.footing.cols)?.0),
            (None, None) => Err(Error::internal("no registration was made")),
        }
    }

    /// Scores `image` (a reconstruction, or the capture itself, in units of the capture's
    /// clipping level) against the registered reference over the scene's pixel sets.
    pub fn score(&self, name: &str, image: &Image) -> Result<Score> {
        if image.dim() != self.reference.dim() {
            return Err(Error::data(
                DataCause::Shape,
                format!(
                    "{name}: is {:?} (rows, cols, channels); the capture is {:?}",
                    image.dim(),
                    self.reference.dim()
                ),
            ));
        }
        let all = psnr(&self.reference, image, Some(&self.mask))?;
        let saturated = match self.footing.saturated_withheld {
            None => Some(psnr(&self.reference, image, Some(&self.saturated))?),
            Some(_) => None,
        };
        let channels = image.channels();
        let mut sums = vec![0.0; channels];
        for ((i, j), &scored) in self.mask.indexed_iter() {
            if scored && !self.saturated[[i, j]] {
                for (c, s) in sums.iter_mut().enumerate() {
                    *s += image.values[[i, j, c]];
                }
            }
        }
        let mean = sums.iter().sum::<f64>() / channels as f64;
        let channel_balance = sums.iter().map(|s| if mean != 0.0 { s / mean } else { f64::NAN }).collect();
        Ok(Score { name: name.into(), all, saturated, channel_balance })
    }
}

/// What `doefab evaluate` reports: one footing and every image's scores on it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Evaluation {
    /// How the reference was registered onto the capture and what is scored.
    pub footing: Footing,
    /// The capture's own score first (the baseline), then each image's, in the order given.
    pub scores: Vec<Score>,
}

/// Registers `reference` onto `capture` once ([`prepare`]) and scores each named image on the
/// same pixels (the capture itself first, as the baseline a decoder must beat).
pub fn evaluate(
    reference: &Image,
    capture: &Image,
    psf: Option<&Psf>,
    images: &[(String, Image)],
    opts: &ScoringOptions,
) -> Result<Evaluation> {
    prepare(reference, capture, psf, opts)?.evaluate(capture, images)
}

impl Scoring {
    /// Scores the capture itself (the baseline a decoder must beat) and then each named image.
    pub fn evaluate(self, capture: &Image, images: &[(String, Image)]) -> Result<Evaluation> {
        let clip = self.footing.clipping_level;
        let mut scores =
            vec![self.score("capture as it is", &Image::new(capture.values.mapv(|v| v / clip)))?];
        for (name, img) in images {
            scores.push(self.score(name, img)?);
        }
        Ok(Evaluation { footing: self.footing, scores })
    }
}

/// The files of one `doefab evaluate` run.
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluateFiles {
    /// The reference HDR (see [`super::capture::read_image`]), e.g. from `doefab merge`.
    pub reference: std::path::PathBuf,
    /// The capture through the DOE that the reconstructions were made from (PNG/TIFF).
    pub capture: std::path::PathBuf,
    /// The measured PSF (`.npz`, `.npy`, `.exr`), sampled at the capture's pixels.
    pub psf: Option<std::path::PathBuf>,
    /// The array of a `.npz` PSF holding several (the paper's: `psf_val`).
    pub psf_key: Option<String>,
    /// The capture's pixel pitch, metres: a PSF file stating another pitch is refused.
    pub capture_pitch: f64,
    /// The reconstructions to score (see [`super::capture::read_image`]).
    pub images: Vec<std::path::PathBuf>,
    /// Registration, saturation level and coverage floors.
    pub options: ScoringOptions,
    /// Where to write what was scored against (see `write_registered`), if anywhere.
    pub registered: Option<std::path::PathBuf>,
}

/// Reads the files and runs [`evaluate`]; each image is named by its path.
pub fn evaluate_files(files: &EvaluateFiles) -> Result<Evaluation> {
    let reference = super::capture::read_image(&files.reference)?;
    let capture = super::capture::read_capture(&files.capture)?.image;
    let psf = match &files.psf {
        Some(p) => Some(Psf::read(p, files.psf_key.as_deref(), Some(files.capture_pitch))?),
        None => None,
    };
    let images = files
        .images
        .iter()
        .map(|p| Ok((p.display().to_string(), super::capture::read_image(p)?)))
        .collect::<Result<Vec<_>>>()?;
    let scoring = prepare(&reference, &capture, psf.as_ref(), &files.options)?;
    if let Some(path) = &files.registered {
        write_registered(path, &scoring, files.capture_pitch)?;
    }
    scoring.evaluate(&capture, &images)
}

/// Writes what a scene is scored against as OpenEXR (f32): channels `R`, `G`, `B`, the
/// reference registered onto the capture's pixels and scaled by the gain, in units of the
/// capture's clipping level (0 where not scored), and the pixel sets `scored` and `saturated`
/// (1 = in the set, 0 = not), so that another program can score the same pixels or check the
/// registration.
pub fn write_registered(path: &std::path::Path, scoring: &Scoring, pitch: f64) -> Result<()> {
    let planes: Vec<Array2<f32>> = (0..scoring.reference.channels())
        .map(|c| scoring.reference.index_axis(Axis(2), c).mapv(|v| v as f32))
        .collect();
    if planes.len() != 3 {
        return Err(Error::data(
            DataCause::Shape,
            format!("the reference has {} channels; RGB is written", planes.len()),
        ));
    }
    let set = |m: &Array2<bool>| m.mapv(|v| f32::from(u8::from(v)));
    let (scored, saturated) = (set(&scoring.mask), set(&scoring.saturated));
    let meta = crate::io::raw_map::Metadata { pitch: Some([pitch; 2]), unit: None, text: Vec::new() }
        .with("quantity", "R, G, B: the reference registered onto the capture and scaled by the gain, 1 = the capture's clipping level; scored, saturated: the pixel sets (1 = in)")
        .with("registration", format!("{:?}", scoring.footing.model).to_lowercase())
        .with("gain", format!("{}", scoring.footing.gain));
    crate::io::exr::write_exr(
        path,
        &[
            ("R", &planes[0]),
            ("G", &planes[1]),
            ("B", &planes[2]),
            ("saturated", &saturated),
            ("scored", &scored),
        ],
        &meta,
    )
}
