//! The measured PSF from a merged pinhole bracket (`doefab calibrate-psf`).
//!
//! Steps, on the merged radiance ([`super::hdr_merge`], dark frames already subtracted):
//!
//! 1. *Background*: each channel's mean over a border strip of the capture is subtracted and
//!    its RMS deviation is the noise `sigma`, both over the samples within 4 sigma (five passes,
//!    from the median and the unclipped RMS); `sigma` is never less than the quantization noise
//!    of the longest frame, one count over `sqrt(12)`. Not the median and the MAD: on 8-bit
//!    counts the median sits up to half a count off the mean (0.45 count at a black level of
//!    2.55 counts, which took 2.4 % of the green energy of the paper's PSF out of its faint
//!    tail), and the MAD is 0 when most of the strip reads one count.
//! 2. *Refuse* samples saturated in every frame: their radiance is only a lower bound. A lone
//!    one on the background (its 8 neighbours unsaturated and below `hot_pixel_neighbours`
//!    sigmas) is a pixel stuck at full scale, a hot pixel.
//! 3. *Hot pixels the merge found*: samples whose well-exposed frames disagree in value over time
//!    ([`super::hdr_merge::Merged::inconsistent_samples`]; a stuck pixel reads the same at every
//!    exposure), wherever they lie, and the stuck saturated ones, are replaced by the median of
//!    their unflagged neighbours.
//! 4. *Coarse location*: the maximum of the channel sum after a 3 x 3 box filter (an isolated
//!    hot pixel loses 8/9 of its height, the PSF core does not).
//! 5. *Isolated hot pixels* (one that grows with the exposure like light, without dark frames):
//!    a sample more than `10 sigma` above the median `m` of its 8 neighbours, which all lie
//!    below `hot_pixel_neighbours` sigmas (a spike on the background), or within that of `m`
//!    and below 1/20 of it (a spike on a faint, smooth tail), or below 1/100 of it (a spike on
//!    the PSF's tail), farther
//!    than 3 px from the coarse location, is replaced by the median of its neighbours. A test
//!    on the ratio to the neighbours alone would also remove real PSF structure: a PSF
//!    sampled at 4.29 um is undersampled in green and blue (`lambda F# / 2 < 4.29 um`), and
//!    the built-in design's simulated PSF holds pixels ten times brighter than all their
//!    neighbours. Hot pixels that the dark frames hold are removed by the dark subtraction.
//! 6. *Location*: the peak of the channel sum within 5 px of the coarse location (the brightest
//!    pixel of the principal copy), its sub-pixel position, and the intensity centroid of the
//!    sum over the crop window, re-centred on it three times. A window that leaves the capture
//!    is refused (the PSF is off the crop window); energy outside the window above
//!    `max_outside` is warned about, and so is a second peak of the box-filtered sum (more than
//!    10 px away) reaching 80 % of the principal one, which makes the axis ambiguous.
//! 7. *Centring* ([`Centre`]): the window is resampled (Keys bicubic) so that the chosen point
//!    sits at the crop centre, pixel `(n - 1) / 2`. The default, [`Centre::Axis`], is the
//!    sub-pixel maximum of the principal peak: for an on-axis pinhole the brightest copy of a
//!    DOE's PSF lies on the optical axis, while the centroid follows the side copies and the
//!    halo (2 px off on the paper's measured PSF). Along each axis through the brightest pixel
//!    `b` with neighbours `a`, `c`, the vertex of the parabola through `ln a, ln b, ln c`,
//!    `delta = (ln a - ln c) / (2 (ln a - 2 ln b + ln c))` (three-point Gaussian fit, Willert &
//!    Gharib, Exp. Fluids 10, 1991; exact for a Gaussian core; the plain parabola where a value is
//!    not positive). The paper's `measured_psf.npz` (319 x 319) has its brightest pixel on the
//!    centre pixel (159, 159), i.e. [`Centre::Peak`], a whole-pixel crop; its sub-pixel maximum by
//!    this fit lies 0.35 px to the right of it, its centroid (+2.1, -0.9) px off. When the capture
//!    pitch differs from
//!    the sensor pitch the shifted window is resampled onto the sensor pitch (pixel-area
//!    averaging when the sensor is coarser, bicubic when finer).
//! 8. *Noise floor and normalisation*: a sample is zeroed when the mean of its 5 x 5
//!    neighbourhood (`k` samples inside the crop) lies below `noise_threshold` times that
//!    mean's noise, `sigma / sqrt(k)`: outside the PSF's support. Inside it every sample is kept
//!    as measured (negatives clamped to 0), so that a faint tail keeps its energy: zeroing each
//!    sample below one sigma lost 2.3 % of the green energy of the paper's PSF, which lies in
//!    pixels of 0.5-2 counts; clamping only the negative ones everywhere would add the
//!    noise's positive half over the whole crop, several percent of the energy. The signed
//!    share of the zeroed samples in the channel's energy is reported, and each channel scaled
//!    to sum 1 ([`Psf::new`]).
//! 9. *Its own error*: `e^2 = (sum_S sigma(v)^2 + sum_Z v^2) / sum_S v^2 + (|f| + b)^2` over the
//!    kept samples `S` and zeroed ones `Z`, `f` the energy fraction zeroed, `b` the black
//!    level's uncertainty as a one-signed offset summed over the kept samples, `sigma(v)` the
//!    background noise times the exposure ratio of the frame a sample of radiance `v` comes
//!    from (terms and their bounds on the function `estimated_error`); a warning when over
//!    [`PsfOptions::max_error`]. `doefab bench calibration` checks it against known PSFs.
//!
//! The paper's measured PSF is 319 x 319 (odd: the centre on a pixel); its simulated PSFs are
//! 320 x 320. Both sizes are accepted.

use std::path::Path;

use ndarray::{Array2, Array3};
use serde::Serialize;

use super::hdr_merge::{write_merged, MergeStats, Merged};
use crate::error::{Allowed, DataCause, Error, Result};
use crate::grid::{Grid, Interpolation, Unit};
use crate::image::Image;
use crate::io::atomic::{write_json, StagedDir};
use crate::optics::psf::{Channel, ChannelSummary, Psf};
use crate::optics::psf_files::stage_psf_files;

/// A sample this many times brighter than all its neighbours is a hot pixel wherever it lies.
const HOT_RATIO: f64 = 100.0;
/// On a faint, smooth tail (neighbours within `hot_pixel_neighbours` sigmas of their median), a
/// sample this many times brighter than all its neighbours is a hot pixel (real structure of the
/// built-in design's undersampled PSF reaches 10).
const TAIL_HOT_RATIO: f64 = 20.0;

/// What is put at the crop centre (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum Centre {
    /// The optical axis: the sub-pixel maximum of the principal (brightest) peak, by a
    /// sub-pixel shift.
    Axis,
    /// The intensity centroid, by a sub-pixel shift (pulled off the axis by side copies).
    Centroid,
    /// The brightest pixel, by a whole-pixel shift (for odd crops): the paper's crop.
    Peak,
}

/// Parameters of the extraction.
#[derive(Debug, Clone, PartialEq)]
pub struct PsfOptions {
    /// Output size in sensor pixels (square).
    pub crop: usize,
    /// What is put at the crop centre.
    pub centre: Centre,
    /// Pixel pitch of the captures, metres.
    pub capture_pitch: f64,
    /// Pixel pitch of the sensor the PSF is for, metres (the output's pitch).
    pub sensor_pitch: f64,
    /// A hot pixel's 8 neighbours all lie within this many background sigmas above their median.
    pub hot_pixel_neighbours: f64,
    /// Width of the border strip the background is measured in, pixels.
    pub border: usize,
    /// Largest fraction of a channel's energy outside the crop without a warning.
    pub max_outside: f64,
    /// Samples whose 5 x 5 neighbourhood mean lies below this many of its noise sigmas are
    /// zeroed (outside the PSF's support).
    pub noise_threshold: f64,
    /// Channel wavelengths (metres), if known.
    pub wavelengths: Option<Vec<f64>>,
    /// Largest estimated relative L2 error of a channel ([`PsfCalibration::estimated_error`])
    /// without a warning.
    pub max_error: f64,
}

impl PsfOptions {
    /// Refuses pitches that are not positive lengths and a crop under 3 pixels.
    fn check(&self) -> Result<()> {
        for (name, v) in [("capture_pitch", self.capture_pitch), ("sensor_pitch", self.sensor_pitch)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::param_in(
                    name,
                    Allowed::positive(),
                    format!("must be a positive length, got {v} m"),
                ));
            }
        }
        if self.crop < 3 {
            return Err(Error::param_in(
                "crop",
                Allowed::at_least(3.0),
                format!("must be at least 3 pixels, got {}", self.crop),
            ));
        }
        Ok(())
    }
}

impl Default for PsfOptions {
    fn default() -> Self {
        PsfOptions {
            crop: 319,
            centre: Centre::Axis,
            capture_pitch: 4.29e-6,
            sensor_pitch: 4.29e-6,
            hot_pixel_neighbours: 3.0,
            border: 16,
            max_outside: 0.05,
            noise_threshold: 3.0,
            wavelengths: None,
            max_error: 0.02,
        }
    }
}

/// Encircled energy of every channel within a radius of the crop centre.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EncircledEnergy {
    /// The radius, sensor pixels.
    pub radius_px: f64,
    /// Per channel: fraction of its energy (0..1) in the pixels whose centre lies within the
    /// radius.
    pub fraction: Vec<f64>,
}

/// What `calibrate-psf` reports and writes as `psf.json`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PsfCalibration {
    /// Output size, sensor pixels (square).
    pub crop: usize,
    /// What was put at the crop centre.
    pub centre: Centre,
    /// Pixel pitch of the captures, metres.
    pub capture_pitch: f64,
    /// Pixel pitch of the PSF written, metres.
    pub sensor_pitch: f64,
    /// `[row, col]` of the brightest pixel of the channel sum in the capture, pixels.
    pub peak_px: [usize; 2],
    /// `[row, col]` of the axis (the brightest pixel's sub-pixel maximum) in the capture,
    /// pixels.
    pub axis_px: [f64; 2],
    /// `[row, col]` of the intensity centroid of the channel sum in the capture, pixels.
    pub centroid_px: [f64; 2],
    /// Per channel: the background level subtracted, in the merged radiance's unit.
    pub background: Vec<f64>,
    /// Per channel: the background's noise `sigma` (RMS), in the merged radiance's unit.
    pub background_sigma: Vec<f64>,
    /// Hot samples replaced (pixel and channel: a hot pixel counts once per channel).
    pub hot_pixels: usize,
    /// The first 1000 of them as `[row, col, channel]`, row-major.
    pub hot_pixel_positions: Vec<[usize; 3]>,
    /// Per channel: energy outside the crop window, fraction of the channel's energy.
    pub energy_outside: Vec<f64>,
    /// Per channel: the signed energy of the samples below the noise floor that were zeroed,
    /// fraction of the channel's energy.
    pub below_floor: Vec<f64>,
    /// Per channel: the relative L2 error the calibration expects of itself: the noise of the
    /// samples it kept (the background's, times the exposure ratio of the frame each comes
    /// from), the samples it zeroed, the energy fraction zeroed, and the black level's
    /// uncertainty as a one-signed offset (the equation is in the module docs, step 9).
    pub estimated_error: Vec<f64>,
    /// Centroid and peak of each channel after centring (metres from the crop centre).
    pub channels: Vec<ChannelSummary>,
    /// Encircled energy about the crop centre at radii of 2, 5, 10, 20, 40 and 80 pixels and
    /// half the crop.
    pub encircled_energy: Vec<EncircledEnergy>,
    /// What the merge of the pinhole bracket used and found.
    pub merge: MergeStats,
    /// The merge's warnings, then the extraction's (a second peak, energy outside the crop, an
    /// uncertain channel), one sentence each.
    pub warnings: Vec<String>,
    /// The files written, relative to the output folder (empty until written).
    pub files: Vec<String>,
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The mean and RMS deviation of the `values` within 4 RMS of the mean (five passes, starting
/// from the median and the RMS about it). `values` is sorted.
fn clipped_mean_rms(values: &mut [f64]) -> (f64, f64) {
    let mut centre = median(values);
    let rms = |c: f64, s: f64| {
        let (sum, sq, n) = values
            .iter()
            .filter(|v| (*v - c).abs() <= 4.0 * s)
            .fold((0.0, 0.0, 0usize), |(a, q, n), v| (a + v, q + (v - c) * (v - c), n + 1));
        (sum, sq, n)
    };
    let (_, sq, n) = rms(centre, f64::INFINITY);
    let mut s = (sq / n.max(1) as f64).sqrt();
    for _ in 0..5 {
        let (sum, _, n) = rms(centre, s);
        if n == 0 {
            break;
        }
        let mean = sum / n as f64;
        let (_, sq, n) = rms(mean, s);
        centre = mean;
        s = (sq / n.max(1) as f64).sqrt();
    }
    (centre, s)
}

/// The quantization noise of the merged background, one count of the longest frame over
/// `sqrt(12)`, in the merge's units.
fn quantization_noise(report: &MergeStats) -> f64 {
    let full = if report.bits == 8 { 255.0 } else { 65535.0 };
    let longest = report.frames.iter().map(|f| f.exposure_used).fold(0.0, f64::max);
    if longest > 0.0 {
        report.reference_exposure_s.unwrap_or(1.0) / (full * longest * 12f64.sqrt())
    } else {
        0.0
    }
}

/// The samples whose 5 x 5 neighbourhood mean (over the `k` neighbours inside the array)
/// reaches `floor / sqrt(k)`, `floor` being the threshold for one sample (see the module docs).
fn support(values: &Array2<f64>, floor: f64) -> Array2<bool> {
    let (h, w) = values.dim();
    Array2::from_shape_fn((h, w), |(i, j)| {
        let (mut s, mut k) = (0.0, 0usize);
        for a in i.saturating_sub(2)..(i + 3).min(h) {
            for b in j.saturating_sub(2)..(j + 3).min(w) {
                s += values[[a, b]];
                k += 1;
            }
        }
        s / k as f64 >= floor / (k as f64).sqrt()
    })
}

/// The relative L2 error a calibrated channel expects of itself, from three terms over the
/// crop (background subtracted, before clamping), `S` the kept samples and `Z` the zeroed ones:
///
/// `e^2 = (sum_S sigma(v)^2 + sum_Z v^2) / sum_S v^2 + (|f| + b)^2`
///
/// * noise: a kept sample of radiance `v` takes its value from the longest frame that does not
///   saturate at `v`, whose noise is the background's `sigma` (that of the longest frame) times
///   the ratio of the longest time to that frame's: `sigma(v) = sigma g(v)`,
///   `g(v) = max(1, v t_max / (s r))`, `s` the saturation level, `r` the reference exposure
///   (frames one stop apart and the weighted merge of several make it an upper bound within a
///   factor of about 2);
/// * black level: an error `delta` of it (the merge's
///   [`MergeStats::black_level_uncertainty`], fraction of full scale, plus half a count where
///   the background is too quiet to dither the counts, so that each count's rounding is a bias)
///   is an offset of `delta r / t` in a sample from a frame of time `t`, of one sign in every
///   sample: it adds `b = delta r / t_max sum_S g(v) / sum_S v` to the channel's sum, the
///   fraction by which normalising to sum 1 scales every sample (an upper bound: the merge's
///   weights favour frames in which the sample is brighter);
/// * the tail: a zeroed sample loses its value, measured as `v` (truth plus noise), and the
///   energy zeroed, the fraction `f` of the channel's ([`PsfCalibration::below_floor`]), scales
///   every kept sample by `1 / (1 - f)` when the channel is normalised to sum 1.
fn estimated_error(
    values: &Array2<f64>,
    support: &Array2<bool>,
    sigma: f64,
    black_uncertainty: f64,
    lost: f64,
    merge: &MergeStats,
) -> f64 {
    let t_max = merge.frames.iter().map(|f| f.exposure_used).fold(0.0, f64::max);
    let r = merge.reference_exposure_s.unwrap_or(1.0);
    let full = merge.saturation * r;
    let beta = if t_max > 0.0 { black_uncertainty * r / t_max } else { f64::INFINITY };
    let (mut noise, mut signal, mut offset, mut sum) = (0.0, 0.0, 0.0, 0.0);
    for (v, &kept) in values.iter().zip(support) {
        if kept {
            let g = (v * t_max / full).max(1.0);
            noise += sigma * sigma * g * g;
            signal += v * v;
            offset += beta * g;
            sum += v.max(0.0);
        } else {
            noise += v * v;
        }
    }
    if signal > 0.0 && sum > 0.0 {
        let b = offset / sum;
        (noise / signal + (lost.abs() + b).powi(2)).sqrt()
    } else {
        f64::INFINITY
    }
}

/// Each channel's background (module docs, step 1), already subtracted from the image.
struct Background {
    /// The mean over the border strip, merged units.
    level: Vec<f64>,
    /// Its noise, never below the quantization noise.
    sigma: Vec<f64>,
    /// The strip is quieter than one count's rounding: the counts are not dithered.
    undithered: Vec<bool>,
}

/// Step 1: each channel's clipped mean and RMS ([`clipped_mean_rms`]) over the strip of
/// `border` pixels along the image's edges, the mean subtracted from `img`.
fn subtract_background(img: &mut Array3<f64>, border: usize, report: &MergeStats) -> Background {
    let (h, w, nc) = img.dim();
    let (mut background, mut sigma, mut undithered) = (Vec::new(), Vec::new(), Vec::new());
    for c in 0..nc {
        let mut strip: Vec<f64> = img
            .indexed_iter()
            .filter(|((i, j, cc), _)| {
                *cc == c && (*i < border || *j < border || *i >= h - border || *j >= w - border)
            })
            .map(|(_, &v)| v)
            .collect();
        let (b, s) = clipped_mean_rms(&mut strip);
        background.push(b);
        let q = quantization_noise(report);
        // A background quieter than one count's rounding: the counts are not dithered by noise,
        // so every sample's rounding is a bias, not noise.
        undithered.push(s < q);
        sigma.push(s.max(q));
        img.index_axis_mut(ndarray::Axis(2), c).mapv_inplace(|v| v - b);
    }
    Background { level: background, sigma, undithered }
}

/// The 8-neighbourhood of `(i, j)` within an `h x w` image, row by row.
fn neighbours(i: usize, j: usize, h: usize, w: usize) -> impl Iterator<Item = (usize, usize)> {
    (i.saturating_sub(1)..=(i + 1).min(h - 1))
        .flat_map(move |a| (j.saturating_sub(1)..=(j + 1).min(w - 1)).map(move |b| (a, b)))
        .filter(move |&p| p != (i, j))
}

/// Step 2: the samples saturated in every frame, flagged, and those of them that are stuck
/// pixels (their 8 neighbours unsaturated and below `hot_neighbours` sigmas); any other one
/// is refused with where they lie.
fn stuck_pixels(
    merged: &Merged,
    img: &Array3<f64>,
    sigma: &[f64],
    hot_neighbours: f64,
) -> Result<(Array3<bool>, Vec<[usize; 3]>)> {
    let (h, w, _) = img.dim();
    let mut flagged = Array3::from_elem(img.dim(), false);
    for &[i, j, c] in &merged.saturated_samples {
        flagged[[i, j, c]] = true;
    }
    let mut hot_list: Vec<[usize; 3]> = Vec::new();
    let mut refused: Vec<[usize; 3]> = Vec::new();
    for &[i, j, c] in &merged.saturated_samples {
        let lone = neighbours(i, j, h, w)
            .all(|(a, b)| !flagged[[a, b, c]] && img[[a, b, c]] < hot_neighbours * sigma[c]);
        if lone {
            hot_list.push([i, j, c]);
        } else {
            refused.push([i, j, c]);
        }
    }
    if let Some(f) = refused.first() {
        let b = refused.iter().fold([f[0], f[1], f[0], f[1]], |b, p| {
            [b[0].min(p[0]), b[1].min(p[1]), b[2].max(p[0]), b[3].max(p[1])]
        });
        return Err(Error::data(
            DataCause::OutOfRange,
            format!(
                "{} samples have no unsaturated frame (first at row {}, col {}, channel {}; all within rows \
             {}..={}, cols {}..={}): add a shorter exposure to the bracket",
                refused.len(),
                f[0],
                f[1],
                f[2],
                b[0],
                b[2],
                b[1],
                b[3]
            ),
        ));
    }
    Ok((flagged, hot_list))
}

/// Step 3: the `hot` samples flagged and replaced by the median of their unflagged neighbours
/// (0 where none is).
fn replace_by_neighbours(img: &mut Array3<f64>, flagged: &mut Array3<bool>, hot: &[[usize; 3]]) {
    let (h, w, _) = img.dim();
    for &[i, j, c] in hot {
        flagged[[i, j, c]] = true;
    }
    let source = img.clone();
    for &[i, j, c] in hot {
        let mut nb: Vec<f64> = neighbours(i, j, h, w)
            .filter(|&(a, b)| !flagged[[a, b, c]])
            .map(|(a, b)| source[[a, b, c]])
            .collect();
        img[[i, j, c]] = if nb.is_empty() { 0.0 } else { median(&mut nb) };
    }
}

/// The sum of the channels at each pixel.
fn channel_sum(img: &Array3<f64>) -> Array2<f64> {
    let (h, w, nc) = img.dim();
    Array2::from_shape_fn((h, w), |(i, j)| (0..nc).map(|c| img[[i, j, c]]).sum::<f64>())
}

/// Step 4: the interior pixel where the 3 x 3 box sum of `total` is largest (the first in
/// row-major order on a tie).
fn coarse_location(total: &Array2<f64>) -> (usize, usize) {
    let (h, w) = total.dim();
    let mut coarse = (0, 0, f64::NEG_INFINITY);
    for i in 1..h - 1 {
        for j in 1..w - 1 {
            let s: f64 =
                (i - 1..=i + 1).flat_map(|a| (j - 1..=j + 1).map(move |b| (a, b))).map(|p| total[p]).sum();
            if s > coarse.2 {
                coarse = (i, j, s);
            }
        }
    }
    (coarse.0, coarse.1)
}

/// Step 5: the isolated hot pixels farther than 3 px from `coarse` (module docs; `sigma` the
/// background noise per channel, `hot_neighbours` the neighbours' ceiling in sigmas) that are
/// not `flagged`, replaced by the median of their neighbours; returns them in scan order.
fn remove_isolated_hot_pixels(
    img: &mut Array3<f64>,
    flagged: &Array3<bool>,
    coarse: (usize, usize),
    sigma: &[f64],
    hot_neighbours: f64,
) -> Vec<[usize; 3]> {
    let (h, w, nc) = img.dim();
    let mut hot = Vec::new();
    let source = img.clone();
    for c in 0..nc {
        for i in 1..h - 1 {
            for j in 1..w - 1 {
                if i.abs_diff(coarse.0).max(j.abs_diff(coarse.1)) <= 3 {
                    continue;
                }
                let v = source[[i, j, c]];
                let mut nb: Vec<f64> = (i - 1..=i + 1)
                    .flat_map(|a| (j - 1..=j + 1).map(move |b| (a, b)))
                    .filter(|&(a, b)| (a, b) != (i, j))
                    .map(|(a, b)| source[[a, b, c]])
                    .collect();
                let max8 = nb.iter().fold(f64::NEG_INFINITY, |m, &x| m.max(x));
                let level = median(&mut nb);
                let floor = hot_neighbours * sigma[c];
                let isolated = max8 < floor
                    || (max8 - level < floor && v > TAIL_HOT_RATIO * max8)
                    || v > HOT_RATIO * max8;
                if v - level > 10.0 * sigma[c] && isolated && !flagged[[i, j, c]] {
                    img[[i, j, c]] = level;
                    hot.push([i, j, c]);
                }
            }
        }
    }
    hot
}

/// Step 6: the brightest pixel of `total` within 5 px of `coarse` (the first in row-major
/// order on a tie, `coarse` itself unless another is brighter).
fn peak_near(total: &Array2<f64>, coarse: (usize, usize)) -> (usize, usize) {
    let (h, w) = total.dim();
    let mut peak = coarse;
    for i in coarse.0.saturating_sub(5)..(coarse.0 + 6).min(h) {
        for j in coarse.1.saturating_sub(5)..(coarse.1 + 6).min(w) {
            if total[[i, j]] > total[peak] {
                peak = (i, j);
            }
        }
    }
    peak
}

/// The vertex offset of the parabola through `ln a, ln b, ln c` at -1, 0, 1 (through `a, b, c`
/// where one is not positive), within half a pixel; 0 where it is not a maximum.
fn vertex(a: f64, b: f64, c: f64) -> f64 {
    let gauss = (a > 0.0 && b > 0.0 && c > 0.0).then(|| {
        let (la, lb, lc) = (a.ln(), b.ln(), c.ln());
        (la - 2.0 * lb + lc, 0.5 * (la - lc))
    });
    let (curv, slope) = gauss.unwrap_or((a - 2.0 * b + c, 0.5 * (a - c)));
    if curv < 0.0 {
        (slope / curv).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// The axis: the sub-pixel maximum of `total` at `peak` by [`vertex`] along each axis (module
/// docs, step 7); whole pixels on the image's first row or column.
fn subpixel_axis(total: &Array2<f64>, peak: (usize, usize)) -> [f64; 2] {
    let (h, w) = total.dim();
    let at = |i: usize, j: usize| total[[i.min(h - 1), j.min(w - 1)]];
    [
        peak.0 as f64
            + if peak.0 > 0 {
                vertex(at(peak.0 - 1, peak.1), total[peak], at(peak.0 + 1, peak.1))
            } else {
                0.0
            },
        peak.1 as f64
            + if peak.1 > 0 {
                vertex(at(peak.0, peak.1 - 1), total[peak], at(peak.0, peak.1 + 1))
            } else {
                0.0
            },
    ]
}

/// The warning when the 3 x 3 box sum of `total` farther than 10 px from `coarse` reaches
/// 80 % of its value at `coarse`: a second peak makes the axis ambiguous.
fn second_peak_warning(total: &Array2<f64>, coarse: (usize, usize)) -> Option<String> {
    let (h, w) = total.dim();
    let boxed = |i: usize, j: usize| neighbours(i, j, h, w).map(|p| total[p]).sum::<f64>() + total[[i, j]];
    let mut second = (0, 0, f64::NEG_INFINITY);
    for i in 1..h - 1 {
        for j in 1..w - 1 {
            if i.abs_diff(coarse.0).max(j.abs_diff(coarse.1)) > 10 {
                let s = boxed(i, j);
                if s > second.2 {
                    second = (i, j, s);
                }
            }
        }
    }
    let principal = boxed(coarse.0, coarse.1);
    (principal > 0.0 && second.2 > 0.8 * principal).then(|| {
        format!(
            "a second peak at row {}, col {} reaches {:.0} % of the principal one at row {}, col {}: \
             the axis (the brightest peak) is ambiguous",
            second.0,
            second.1,
            100.0 * second.2 / principal,
            coarse.0,
            coarse.1
        )
    })
}

/// Per channel, the fraction of its energy outside the crop `window` (rows, columns), with a
/// warning above `opts.max_outside`.
fn energy_outside(
    img: &Array3<f64>,
    (ri, rj): (std::ops::RangeInclusive<usize>, std::ops::RangeInclusive<usize>),
    opts: &PsfOptions,
    warnings: &mut Vec<String>,
) -> Vec<f64> {
    let mut energy_outside = Vec::new();
    for c in 0..img.dim().2 {
        let all: f64 = img.index_axis(ndarray::Axis(2), c).sum();
        let inside: f64 =
            ri.clone().flat_map(|i| rj.clone().map(move |j| (i, j))).map(|(i, j)| img[[i, j, c]]).sum();
        let out = if all > 0.0 { 1.0 - inside / all } else { 1.0 };
        if out > opts.max_outside {
            warnings.push(format!(
                "channel {c}: {:.1} % of the energy lies outside the {}-px crop window",
                100.0 * out,
                opts.crop
            ));
        }
        energy_outside.push(out);
    }
    energy_outside
}

/// Steps 7-9 for channel `c`: the capture resampled (Keys bicubic) with `target` at the crop
/// centre, onto the sensor pitch, the samples outside the support ([`support`], `noise` the
/// channel's background sigma and whether it is undithered) zeroed and the negative ones
/// clamped; with the signed fraction of the energy zeroed and the estimated error
/// ([`estimated_error`]).
fn centred_channel(
    img: &Array3<f64>,
    c: usize,
    target: [f64; 2],
    (sigma, undithered): (f64, bool),
    merged: &Merged,
    opts: &PsfOptions,
) -> Result<(Channel, f64, f64)> {
    let nc = img.dim().2;
    let n = opts.crop;
    let ratio = opts.sensor_pitch / opts.capture_pitch;
    let same_pitch = (ratio - 1.0).abs() < 1e-9;
    let m = if same_pitch { n } else { (n as f64 * ratio).ceil() as usize + 4 };
    let plane = Grid::new(
        img.index_axis(ndarray::Axis(2), c).to_owned(),
        [opts.capture_pitch; 2],
        Unit::Dimensionless,
    )?;
    let off = (m as f64 - 1.0) * 0.5;
    let mut shifted = Array2::<f64>::zeros((m, m));
    for ((a, b), v) in shifted.indexed_iter_mut() {
        let (fi, fj) = (target[0] + a as f64 - off, target[1] + b as f64 - off);
        *v = plane.sample_index(fi, fj, Interpolation::Bicubic).ok_or_else(|| {
            Error::data(
                DataCause::OutOfRange,
                format!("the crop window leaves the capture at row {fi:.1}, col {fj:.1}"),
            )
        })?;
    }
    let mut grid = Grid::new(shifted, [opts.capture_pitch; 2], Unit::Dimensionless)?;
    if !same_pitch {
        let method = if ratio > 1.0 { Interpolation::Area } else { Interpolation::Bicubic };
        grid = grid.resample_to(n, n, [opts.sensor_pitch; 2], method)?;
    }
    let values = grid.values();
    let support = support(values, opts.noise_threshold * sigma);
    let all: f64 = values.sum();
    let zeroed: f64 = values.iter().zip(&support).filter(|(_, s)| !**s).map(|(v, _)| v).sum();
    let below_floor = if all > 0.0 { zeroed / all } else { 1.0 };
    let full = if merged.stats.bits == 8 { 255.0 } else { 65535.0 };
    let black_uncertainty = merged.stats.black_level_uncertainty.get(c).copied().unwrap_or(0.0)
        + if undithered { 0.5 / full } else { 0.0 };
    let e = estimated_error(values, &support, sigma, black_uncertainty, below_floor, &merged.stats);
    let clamped = Array2::from_shape_fn(values.dim(), |p| if support[p] { values[p].max(0.0) } else { 0.0 });
    let origin = -(n as f64 - 1.0) * 0.5 * opts.sensor_pitch;
    let name = if nc == 3 { ["R", "G", "B"][c].to_string() } else { format!("C{c}") };
    let channel = Channel {
        name,
        wavelength: opts.wavelengths.as_ref().map(|wl| wl[c]),
        grid: Grid::new(clamped, [opts.sensor_pitch; 2], Unit::Dimensionless)?.with_origin([origin, origin]),
        captured: None,
    };
    Ok((channel, below_floor, e))
}

/// Extracts the PSF from a merged pinhole bracket (see the module docs).
pub fn calibrate_psf(merged: &Merged, opts: &PsfOptions) -> Result<(Psf, PsfCalibration)> {
    let (h, w, nc) = merged.radiance.dim();
    opts.check()?;
    if let Some(wl) = &opts.wavelengths {
        if wl.len() != nc {
            return Err(Error::param("wavelengths", format!("{} given for {nc} channels", wl.len())));
        }
    }
    let border = opts.border.max(1);
    if 2 * border >= h.min(w) {
        return Err(Error::param("border", format!("{border} px leaves no interior in {w} x {h}")));
    }
    let mut warnings = merged.stats.warnings.clone();

    // 1. Background from the border strip.
    let mut img = merged.radiance.values.clone();
    let Background { level: background, sigma, undithered } =
        subtract_background(&mut img, border, &merged.stats);
    // 2. Saturated in every frame: a lone one on the background is stuck; any other is refused.
    let (mut flagged, mut hot_list) = stuck_pixels(merged, &img, &sigma, opts.hot_pixel_neighbours)?;
    // 3. Samples that do not follow the exposure, and the stuck saturated ones.
    hot_list.extend_from_slice(&merged.inconsistent_samples);
    hot_list.sort_unstable();
    hot_list.dedup();
    replace_by_neighbours(&mut img, &mut flagged, &hot_list);
    // 4. Coarse location on the box-filtered channel sum.
    let coarse = coarse_location(&channel_sum(&img));
    // 5. Isolated hot pixels away from the PSF core.
    hot_list.extend(remove_isolated_hot_pixels(
        &mut img,
        &flagged,
        coarse,
        &sigma,
        opts.hot_pixel_neighbours,
    ));

    // 6. Peak, then the centroid over the crop window.
    let total = channel_sum(&img);
    let peak = peak_near(&total, coarse);
    hot_list.sort_unstable();
    let axis = subpixel_axis(&total, peak);
    warnings.extend(second_peak_warning(&total, coarse));
    let ratio = opts.sensor_pitch / opts.capture_pitch;
    let half = ((opts.crop as f64 - 1.0) * 0.5 * ratio).max(0.5) + 2.0; // + bicubic support
    let fits = |ci: f64, cj: f64| -> Result<()> {
        let (lo_i, hi_i, lo_j, hi_j) = (ci - half, ci + half, cj - half, cj + half);
        if lo_i < 0.0 || lo_j < 0.0 || hi_i > (h - 1) as f64 || hi_j > (w - 1) as f64 {
            return Err(Error::data(
                DataCause::OutOfRange,
                format!(
                    "the PSF at row {ci:.1}, col {cj:.1} of the {w} x {h} capture is off the crop window: a \
                 {0} x {0} crop at the sensor pitch needs {1:.0} px of capture on every side (it has \
                 {2:.0} above, {3:.0} below, {4:.0} left, {5:.0} right); centre the pinhole or choose a \
                 smaller `crop`",
                    opts.crop,
                    half,
                    ci,
                    (h - 1) as f64 - ci,
                    cj,
                    (w - 1) as f64 - cj
                ),
            ));
        }
        Ok(())
    };
    fits(peak.0 as f64, peak.1 as f64)?;
    let window = |ci: f64, cj: f64| {
        let r = (half - 2.0).floor() as isize;
        let (i0, j0) = (ci.round() as isize, cj.round() as isize);
        (
            (i0 - r).max(0) as usize..=(i0 + r).min(h as isize - 1) as usize,
            (j0 - r).max(0) as usize..=(j0 + r).min(w as isize - 1) as usize,
        )
    };
    let mut centroid = [peak.0 as f64, peak.1 as f64];
    for _ in 0..3 {
        let (ri, rj) = window(centroid[0], centroid[1]);
        let (mut si, mut sj, mut s) = (0.0, 0.0, 0.0);
        for i in ri {
            for j in rj.clone() {
                let v = total[[i, j]];
                si += v * i as f64;
                sj += v * j as f64;
                s += v;
            }
        }
        if s <= 0.0 {
            return Err(Error::data(
                DataCause::Empty,
                "the crop window holds no energy above the background: no PSF found",
            ));
        }
        centroid = [si / s, sj / s];
        fits(centroid[0], centroid[1])?;
    }
    let target = match opts.centre {
        Centre::Axis => axis,
        Centre::Centroid => centroid,
        Centre::Peak => [peak.0 as f64, peak.1 as f64],
    };
    fits(target[0], target[1])?;
    let energy_outside = energy_outside(&img, window(target[0], target[1]), opts, &mut warnings);

    // 7-9. Centre, resample, clamp, normalise; each channel's own error.
    let n = opts.crop;
    let (mut channels, mut below_floor, mut estimated) = (Vec::new(), Vec::new(), Vec::new());
    for c in 0..nc {
        let (channel, lost, e) = centred_channel(&img, c, target, (sigma[c], undithered[c]), merged, opts)?;
        if e > opts.max_error {
            warnings.push(format!(
                "channel {c}: the PSF is uncertain: its estimated relative L2 error is {:.1} % (over {:.1} %), \
                 from the read noise and the tail below the noise floor; add longer exposures to the bracket \
                 (or average more frames per exposure)",
                100.0 * e,
                100.0 * opts.max_error
            ));
        }
        channels.push(channel);
        below_floor.push(lost);
        estimated.push(e);
    }
    let mut psf = Psf::new(channels, "measured")?;
    psf.warnings = warnings.clone();
    let radii = [2.0, 5.0, 10.0, 20.0, 40.0, 80.0, (n as f64 - 1.0) * 0.5];
    let encircled_energy = radii
        .iter()
        .map(|&r| EncircledEnergy {
            radius_px: r,
            fraction: (0..nc).map(|c| psf.encircled_energy(c, [0.0, 0.0], r * opts.sensor_pitch)).collect(),
        })
        .collect();
    let report = PsfCalibration {
        crop: n,
        centre: opts.centre,
        capture_pitch: opts.capture_pitch,
        sensor_pitch: opts.sensor_pitch,
        peak_px: [peak.0, peak.1],
        axis_px: axis,
        centroid_px: centroid,
        background,
        background_sigma: sigma,
        hot_pixels: hot_list.len(),
        hot_pixel_positions: hot_list.iter().take(1000).copied().collect(),
        energy_outside,
        below_floor,
        estimated_error: estimated,
        channels: psf.summary(),
        encircled_energy,
        merge: merged.stats.clone(),
        warnings,
        files: Vec::new(),
    };
    Ok((psf, report))
}

/// Writes the PSF (`psf.exr`, `psf.npy` `(H, W, 1, C)`, `psf_log.png`), the merged bracket
/// (`merged.exr`) and `psf.json` into `out`, atomically as a folder.
pub fn write_calibration(psf: &Psf, merged: &Merged, report: &mut PsfCalibration, out: &Path) -> Result<()> {
    let mut stage = StagedDir::new(out)?;
    report.files = stage_psf_files(psf, "each channel sums to 1 over the crop (measured)", &mut stage)?;
    write_merged(&stage.stage_path("merged.exr"), merged, Some(report.capture_pitch))?;
    report.files.extend(["merged.exr".to_string(), "psf.json".to_string()]);
    write_json(&stage.stage_path("psf.json"), report)?;
    stage.commit()
}

/// A synthetic 8-bit pinhole bracket of `psf` (for the demo and for trying the calibration):
/// `frames` exposures one stop apart, the longest 1 s; the PSF centred in a capture `margin`
/// pixels larger on every side, scaled so that its brightest pixel is at half full scale in
/// the shortest frame (saturating the longest by `2^(frames - 2)`); a dark level `dark` and
/// Gaussian read noise `noise` (fractions of full scale), seeded. Returns the frames' values,
/// their times and one dark frame.
pub fn simulate_pinhole_bracket(
    psf: &Psf,
    margin: usize,
    frames: usize,
    noise: f64,
    dark: f64,
    seed: u64,
) -> (Vec<Image>, Vec<f64>, Image) {
    let (ph, pw) = psf.dim();
    let nc = psf.channels.len();
    let (h, w) = (ph + 2 * margin, pw + 2 * margin);
    let brightest = (0..nc).map(|c| psf.peak(c).0).fold(0.0f64, f64::max);
    let scale = 0.5 * 2f64.powi(frames as i32 - 1) / brightest;
    let mut radiance = Array3::<f64>::zeros((h, w, nc));
    for (c, ch) in psf.channels.iter().enumerate() {
        for ((i, j), &v) in ch.grid.values().indexed_iter() {
            radiance[[i + margin, j + margin, c]] = v * scale;
        }
    }
    let mut rng = crate::rng::Lcg(seed);
    let quant = |v: f64| (v.clamp(0.0, 1.0) * 255.0).round() / 255.0;
    let times: Vec<f64> = (0..frames).map(|k| 2f64.powi(-(k as i32))).collect();
    let values = times
        .iter()
        .map(|&t| Image::new(radiance.mapv(|e| quant(dark + e * t + noise * rng.normal()))))
        .collect();
    let dark_frame = Image::new(Array3::from_shape_fn((h, w, nc), |_| quant(dark + noise * rng.normal())));
    (values, times, dark_frame)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The three-point Gaussian fit is exact on a Gaussian; the plain parabola, where a value is
    /// not positive, exact on a parabola; a minimum gives 0 and a far vertex half a pixel.
    #[test]
    fn the_vertex_is_exact_on_a_gaussian_and_on_a_parabola() {
        let g = |x: f64| (-(x - 0.3f64).powi(2) / (2.0 * 0.8 * 0.8)).exp();
        assert!((vertex(g(-1.0), g(0.0), g(1.0)) - 0.3).abs() < 1e-12);
        let p = |x: f64| 1.0 - (x - 0.2f64).powi(2);
        assert!(p(-1.0) < 0.0 && (vertex(p(-1.0), p(0.0), p(1.0)) - 0.2).abs() < 1e-12);
        assert_eq!(vertex(2.0, 1.0, 2.0), 0.0);
        assert_eq!(vertex(1.0, 2.0, 3.0), 0.5);
    }

    /// A separable Gaussian spot centred at row 10.3, column 7.6: its brightest pixel (10, 8)
    /// is found from a coarse location 3 px off, and the axis is the spot's centre.
    #[test]
    fn the_peak_and_axis_of_a_gaussian_spot() {
        let spot = |i: usize, j: usize| {
            (-((i as f64 - 10.3).powi(2) + (j as f64 - 7.6).powi(2)) / (2.0 * 1.5 * 1.5)).exp()
        };
        let total = Array2::from_shape_fn((24, 20), |(i, j)| spot(i, j));
        assert_eq!(peak_near(&total, (12, 10)), (10, 8));
        let axis = subpixel_axis(&total, (10, 8));
        assert!((axis[0] - 10.3).abs() < 1e-9 && (axis[1] - 7.6).abs() < 1e-9, "{axis:?}");
    }

    /// A lone bright pixel loses 8/9 of its height in the 3 x 3 box sum: the coarse location is
    /// the spread spot, and a second spot as bright 20 px away is warned about.
    #[test]
    fn the_coarse_location_prefers_a_spot_to_a_hot_pixel() {
        let mut total = Array2::<f64>::zeros((40, 40));
        total[[3, 3]] = 5.0;
        for i in 9..12 {
            for j in 9..12 {
                total[[i, j]] = 1.0;
            }
        }
        assert_eq!(coarse_location(&total), (10, 10));
        assert_eq!(second_peak_warning(&total, (10, 10)), None);
        for i in 29..32 {
            for j in 9..12 {
                total[[i, j]] = 0.9;
            }
        }
        let w = second_peak_warning(&total, (10, 10)).unwrap();
        assert!(w.contains("row 30, col 10 reaches 90 %"), "{w}");
    }

    /// Replaced samples take the (upper) median of their unflagged neighbours; isolated spikes
    /// on the background are removed away from the core only.
    #[test]
    fn hot_samples_take_their_neighbours_median() {
        let mut img = Array3::from_shape_fn((5, 5, 1), |(i, j, _)| (i * 5 + j) as f64);
        let mut flagged = Array3::from_elem((5, 5, 1), false);
        flagged[[1, 1, 0]] = true;
        replace_by_neighbours(&mut img, &mut flagged, &[[2, 2, 0]]);
        // Unflagged neighbours of (2, 2): 7, 8, 11, 13, 16, 17, 18 (6 is flagged): median 13.
        assert_eq!(img[[2, 2, 0]], 13.0);
        assert!(flagged[[2, 2, 0]]);
        let mut img = Array3::<f64>::zeros((30, 30, 1));
        img[[5, 5, 0]] = 100.0;
        img[[20, 21, 0]] = 100.0;
        let flagged = Array3::from_elem((30, 30, 1), false);
        let hot = remove_isolated_hot_pixels(&mut img, &flagged, (20, 20), &[1.0], 3.0);
        assert_eq!(hot, vec![[5, 5, 0]]);
        assert_eq!((img[[5, 5, 0]], img[[20, 21, 0]]), (0.0, 100.0));
    }

    /// The border strip alternates 0.09 and 0.11 (mean 0.1, RMS 0.01) around a bright interior:
    /// 0.1 is the background and is subtracted everywhere.
    #[test]
    fn the_background_is_the_border_strips_mean() {
        let mut img = Array3::from_shape_fn((20, 20, 2), |(i, j, c)| {
            let edge = i < 3 || j < 3 || i >= 17 || j >= 17;
            if edge {
                if (i + j) % 2 == 0 {
                    0.09
                } else {
                    0.11
                }
            } else {
                1.0 + c as f64
            }
        });
        let report = MergeStats {
            shape: [20, 20, 2],
            unit: String::new(),
            reference_exposure_s: None,
            bits: 8,
            black_level: vec![0.0; 2],
            black_level_uncertainty: vec![0.0; 2],
            black_level_source: String::new(),
            noise_floor: 0.0,
            saturation: 1.0,
            channel_clipping: vec![1.0; 2],
            frames: Vec::new(),
            saturated_everywhere: Default::default(),
            dark_everywhere: Default::default(),
            inconsistent: Default::default(),
            warnings: Vec::new(),
        };
        let b = subtract_background(&mut img, 3, &report);
        for c in 0..2 {
            assert!((b.level[c] - 0.1).abs() < 1e-12 && (b.sigma[c] - 0.01).abs() < 1e-12, "{c}");
            assert!((img[[10, 10, c]] - (0.9 + c as f64)).abs() < 1e-12);
        }
        assert_eq!(b.undithered, vec![false; 2]);
    }
}
