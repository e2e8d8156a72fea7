//! Merging an exposure bracket into one HDR radiance image.
//!
//! For every pixel and channel the radiance is the weighted mean of value over time across the
//! frames (Debevec & Malik, "Recovering High Dynamic Range Radiance Maps from Photographs",
//! SIGGRAPH 1997, eq. 6, here in the linear domain):
//!
//! `E = sum_k w(z_k) (v_k - d) / t_k  /  sum_k w(z_k)`
//!
//! with `z_k` the frame's raw value (fraction of full scale), `v_k` its linear value (`z_k`
//! itself for linear captures, `exp(g(z_k))` through a recovered response), `d` the black
//! level and `t_k` the exposure time. The hat weight `w(z) = min(z - lo, hi - z)` is zero at and
//! below the noise floor `lo` and at and above the saturation level `hi`, so neither clipped nor
//! noise-dominated values contribute. `hi` is the saturation fraction times where the sample's
//! channel clips ([`super::clipping`], detected over the bracket's frames): the paper's camera
//! clips green at 231 of 255, and a green 231 weighted as light biases every highlight low.
//!
//! *Black level* `d` ([`BlackLevel`]): the mean dark frame when dark frames are given, else, for
//! linear captures, one level per channel estimated from the histogram of the shortest frame
//! (most of whose samples see no light): the mode `m` of the counts, refined to a fraction of a
//! count by the vertex of the parabola through the logarithms of the three bins `m - 1, m, m + 1`
//! (exact for a Gaussian peak; the three-point Gaussian fit of Willert & Gharib, "Digital
//! particle image velocimetry", Exp. Fluids 10, 1991). A mode at count 0 (the sensor clips at
//! black) gives `d = 0`. The estimate is refused, with a warning, and `d = 0` used, when fewer
//! than 10 % of the frame's samples lie in those three bins (no dark region) or the mode is
//! above 20 % of full scale. A black level left in the values biases every time ratio towards 1
//! (`(d + E t_s) / (d + E t_l)`) and adds `d / t_k` to the radiance.
//!
//! A pixel that no frame sees between `lo` and `hi` has no trustworthy value: where every frame
//! is saturated it takes the shortest frame's value over time (a lower bound); where every
//! frame is in the noise floor, the longest unsaturated frame's value over time. Both sets are counted
//! and located in the merge's stats ([`PixelSet`]) and the caller decides whether to refuse them.
//!
//! Listed exposure times can be wrong (the paper's shortest frames drift 10-30 % from what the
//! pixels say). With [`MergeOptions::estimate_times`] the time ratio of each pair of
//! neighbouring frames (sorted by time) is the median ratio of their linear values over pixels
//! well exposed in both (`0.1 <= z < hi`); the times are chained from the frame with the most
//! well-exposed pixels, which keeps its listed time.
//!
//! A sample seen well exposed (`z - d >= 0.1`, `z < hi`) by two or more frames whose values over
//! time differ by more than a factor [`INCONSISTENT_RATIO`] does not follow the exposure: a
//! stuck or hot pixel (its value does not scale with time), or motion. Such samples are counted,
//! located and listed ([`Merged::inconsistent_samples`]); the 8-bit noise at `z = 0.1` is 2 %.
//!
//! Each frame's agreement with the merge is reported as the RMS and median of
//! `(v_k / t_k - E) / E` over the pixels it sees well exposed: for 8-bit captures the
//! quantization step alone gives `1 / (255 z sqrt(12))`, 1.1 % at `z = 0.1`.

use std::ops::Bound;
use std::path::Path;

use ndarray::{Array2, Array3, Zip};
use serde::Serialize;

use super::capture::Capture;
use super::clipping::channel_clipping;
use super::response::Response;
use crate::error::{Allowed, DataCause, Error, Result};
use crate::image::tone::tone_map;
use crate::image::Image;
use crate::io::exr::write_exr;
use crate::io::png::write_png_image_u8;
use crate::io::raw_map::Metadata;

/// Values over time of one sample that differ by more than this factor between well-exposed
/// frames mark it as not following the exposure (see the module docs).
pub const INCONSISTENT_RATIO: f64 = 2.0;

/// Where the black level (the value at zero light) comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum BlackLevel {
    /// The mean dark frame when dark frames are given; otherwise, for linear captures, estimated
    /// per channel from the shortest frame (see the module docs); with a response curve, none.
    Auto,
    /// Given: one level for every channel or one per channel, fraction of full scale.
    Fixed(Vec<f64>),
}

/// Thresholds of the merge.
#[derive(Debug, Clone, PartialEq)]
pub struct MergeOptions {
    /// Raw values at or below this fraction of full scale above the black level (`z - d`) are
    /// in the noise floor.
    pub noise_floor: f64,
    /// Raw values at or above this fraction of full scale are saturated.
    pub saturation: f64,
    /// Estimate effective exposure times from the pixels (see the module docs).
    pub estimate_times: bool,
    /// Express the radiance at this exposure (s): value 1 = full scale at this time. `None`:
    /// full scale per second.
    pub reference_exposure: Option<f64>,
    /// Where the black level comes from.
    pub black_level: BlackLevel,
}

impl Default for MergeOptions {
    fn default() -> Self {
        MergeOptions {
            noise_floor: 0.02,
            saturation: 0.98,
            estimate_times: true,
            reference_exposure: None,
            black_level: BlackLevel::Auto,
        }
    }
}

/// Samples (pixel, channel) of a set: how many, the first in row-major order and the bounding
/// box `[row_min, col_min, row_max, col_max]`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PixelSet {
    /// Samples (pixel and channel) in the set.
    pub count: usize,
    /// `[row, col, channel]` of the first in row-major order; `None` when the set is empty.
    pub first: Option<[usize; 3]>,
    /// `[row_min, col_min, row_max, col_max]`, pixels, inclusive; `None` when the set is empty.
    pub bbox: Option<[usize; 4]>,
}

impl PixelSet {
    fn add(&mut self, i: usize, j: usize, c: usize) {
        self.count += 1;
        if self.first.is_none() {
            self.first = Some([i, j, c]);
        }
        let b = self.bbox.get_or_insert([i, j, i, j]);
        *b = [b[0].min(i), b[1].min(j), b[2].max(i), b[3].max(j)];
    }
}

/// What the merge found about one frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameStats {
    /// The capture file.
    pub file: String,
    /// Seconds, as listed.
    pub exposure_listed: f64,
    /// Seconds, as used (estimated from the pixels when asked).
    pub exposure_used: f64,
    /// Saturated samples per channel.
    pub saturated: Vec<usize>,
    /// Samples in the noise floor per channel.
    pub noise_floor: Vec<usize>,
    /// RMS of the relative deviation `(v_k / t_k - E) / E` from the merge over the samples
    /// this frame sees well exposed (`None` when it sees none).
    pub agreement_rms: Option<f64>,
    /// Median of `|v_k / t_k - E| / E` over the same samples (`None` when it sees none).
    pub agreement_median: Option<f64>,
    /// Samples the agreement was measured over.
    pub agreement_samples: usize,
}

/// What the merge found: the calibration it used, each frame's stats, the samples it could not
/// trust and its warnings.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MergeStats {
    /// `(rows, cols, channels)`.
    pub shape: [usize; 3],
    /// What a radiance value of 1 means.
    pub unit: String,
    /// The exposure `t_ref` (s) at which value 1 is full scale; `None`: full scale in 1 s.
    pub reference_exposure_s: Option<f64>,
    /// Bit depth of the frames.
    pub bits: u8,
    /// Per channel: the black level subtracted, fraction of full scale (the mean of the dark
    /// frame when one is given).
    pub black_level: Vec<f64>,
    /// Per channel: how far the black level may be off, fraction of full scale (0 where it is
    /// given or measured by dark frames; see `estimate_black_level`; where it could not be
    /// measured, the shortest frame's lowest value).
    pub black_level_uncertainty: Vec<f64>,
    /// Where the black level came from: "given", "dark frames", the shortest frame's histogram
    /// (with its file), or none (a response curve).
    pub black_level_source: String,
    /// Noise floor, fraction of full scale above the black level: samples at or below it carry
    /// no weight.
    pub noise_floor: f64,
    /// Saturation, fraction of where each channel clips.
    pub saturation: f64,
    /// Where each channel clips, fraction of full scale (`channel_clipping`; 1 = at full
    /// scale): the paper's camera clips green at 231 of 255.
    pub channel_clipping: Vec<f64>,
    /// One per frame, in the bracket's order.
    pub frames: Vec<FrameStats>,
    /// Samples saturated in every frame (their radiance is a lower bound).
    pub saturated_everywhere: PixelSet,
    /// Samples that no frame sees between the noise floor and saturation, and that some frame
    /// sees below saturation (in practice: in the noise floor in every frame); their radiance is
    /// the longest such frame's value over time.
    pub dark_everywhere: PixelSet,
    /// Samples whose well-exposed frames disagree by more than `INCONSISTENT_RATIO`.
    pub inconsistent: PixelSet,
    /// What the caller should know (channels clipping below full scale, the black level, drifted
    /// times, untrusted samples), one sentence each.
    pub warnings: Vec<String>,
}

/// A merged bracket: radiance `(H, W, C)`, the merge's stats and the response curve the frames were
/// linearized through (`None`: linear captures).
#[derive(Debug, Clone, PartialEq)]
pub struct Merged {
    /// Radiance `(H, W, C)`, in the unit [`MergeStats::unit`] states.
    pub radiance: Image,
    /// What the merge used and found.
    pub stats: MergeStats,
    /// The response curve the frames were linearized through; `None` for linear captures.
    pub response: Option<Response>,
    /// `[row, col, channel]` of every sample saturated in every frame, row-major.
    pub saturated_samples: Vec<[usize; 3]>,
    /// `[row, col, channel]` of every sample that does not follow the exposure, row-major.
    pub inconsistent_samples: Vec<[usize; 3]>,
}

/// Checks that the frames agree in shape and bit depth and that the dark frame matches.
fn check_frames(frames: &[Capture], times: &[f64], dark: Option<&Image>) -> Result<()> {
    let Some(first) = frames.first() else {
        return Err(Error::param("bracket", "needs at least one frame"));
    };
    if times.len() != frames.len() {
        return Err(Error::param("times", format!("{} times for {} frames", times.len(), frames.len())));
    }
    for (f, &t) in frames.iter().zip(times) {
        if f.image.values.dim() != first.image.values.dim() || f.bits != first.bits {
            let (h, w, c) = f.image.values.dim();
            let (h0, w0, c0) = first.image.values.dim();
            let what = format!(
                "{}: is {w} x {h} x {c} at {} bits, but {} is {w0} x {h0} x {c0} at {} bits: a bracket's \
                 frames must match",
                f.path.display(),
                f.bits,
                first.path.display(),
                first.bits
            );
            return Err(Error::data(DataCause::Shape, what));
        }
        if !(t.is_finite() && t > 0.0) {
            return Err(Error::param_in(
                "times",
                Allowed::positive(),
                format!("{}: exposure {t} s is not positive", f.path.display()),
            ));
        }
    }
    if let Some(d) = dark {
        if d.dim() != first.image.values.dim() {
            return Err(Error::param(
                "dark",
                format!("the dark frame is {:?}, the captures {:?}", d.dim(), first.image.values.dim()),
            ));
        }
    }
    Ok(())
}

/// The mean of dark captures (same layout as the frames they correct).
pub fn mean_dark(darks: &[Capture]) -> Result<Image> {
    let times = vec![1.0; darks.len()];
    check_frames(darks, &times, None)?;
    let mut sum = Array3::<f64>::zeros(darks[0].image.values.dim());
    for d in darks {
        sum += &d.image.values;
    }
    Ok(Image::new(sum / darks.len() as f64))
}

/// The black level of each channel of `frame` (fraction of full scale) from the histogram of
/// its counts: the mode refined by a three-point Gaussian fit (see the module docs), with its
/// uncertainty: half a count where every dark sample reads one count (nothing to fit), else 0
/// (the fit's own error, about a hundredth of a count on a dark region of thousands of samples,
/// is not counted). Returns `None` for a channel, with the reason in `warnings`, where the frame
/// has no dark region.
pub fn estimate_black_level(frame: &Capture, warnings: &mut Vec<String>) -> Vec<Option<(f64, f64)>> {
    let full = frame.full_scale();
    let (_, _, nc) = frame.image.values.dim();
    (0..nc)
        .map(|c| {
            let mut hist = vec![0usize; full as usize + 1];
            let plane = frame.image.values.index_axis(ndarray::Axis(2), c);
            for &z in plane.iter() {
                hist[((z.clamp(0.0, 1.0) * full).round()) as usize] += 1;
            }
            let n = plane.len().max(1);
            // The lowest count among the most frequent ones.
            let m = (0..hist.len()).fold(0, |best, k| if hist[k] > hist[best] { k } else { best });
            let side = |k: Option<usize>| k.and_then(|k| hist.get(k)).copied().unwrap_or(0);
            let peak = hist[m] + side(m.checked_sub(1)) + side(Some(m + 1));
            let name = frame.path.display();
            if (peak as f64) < 0.1 * n as f64 || m as f64 > 0.2 * full {
                warnings.push(format!(
                    "{name}, channel {c}: no dark region to measure the black level in (the most frequent \
                     value, {m} counts, holds {:.1} % of the samples with its two neighbours; needed: at \
                     least 10 % at or below 20 % of full scale); black level 0 used: give dark frames",
                    100.0 * peak as f64 / n as f64
                ));
                return None;
            }
            if m == 0 {
                return Some((0.0, 0.0));
            }
            let (a, b, d) = (hist[m - 1], hist[m], hist[m + 1]);
            let offset = if a > 0 && d > 0 {
                let (la, lb, ld) = ((a as f64).ln(), (b as f64).ln(), (d as f64).ln());
                let curv = la - 2.0 * lb + ld;
                if curv < 0.0 {
                    (0.5 * (la - ld) / curv).clamp(-0.5, 0.5)
                } else {
                    0.0
                }
            } else {
                warnings.push(format!(
                    "{name}, channel {c}: the dark samples all read {m} counts; the black level is known \
                     to half a count only"
                ));
                return Some((m as f64 / full, 0.5 / full));
            };
            Some(((m as f64 + offset) / full, 0.0))
        })
        .collect()
}

/// The black level of a merge (see [`black_level`]).
struct Black {
    /// Per sample, `(H, W, C)`.
    level: Array3<f64>,
    /// Per channel: the mean level, how far it may be off, both fractions of full scale.
    means: Vec<f64>,
    uncertainty: Vec<f64>,
    /// Where it came from.
    source: String,
}

/// The black level as an `(H, W, C)` array (the mean dark frame, or one level per channel) with
/// its per-channel means and where it came from (see [`BlackLevel`]).
fn black_level(
    frames: &[Capture],
    times: &[f64],
    dark: Option<&Image>,
    response: Option<&Response>,
    level: &BlackLevel,
    warnings: &mut Vec<String>,
) -> Result<Black> {
    let shape = frames[0].image.values.dim();
    let nc = shape.2;
    let per_channel = |v: &[f64]| Array3::from_shape_fn(shape, |(_, _, c)| v[c]);
    match (level, dark, response) {
        (BlackLevel::Fixed(_), Some(_), _) => Err(Error::param(
            "black_level",
            "a black level was given together with dark frames; give one or the other",
        )),
        (BlackLevel::Fixed(_), None, Some(_)) => Err(Error::param(
            "black_level",
            "a recovered response curve maps raw values to exposure including the black level; do \
             not give one",
        )),
        (BlackLevel::Fixed(v), None, None) => {
            let v = match v.len() {
                1 => vec![v[0]; nc],
                k if k == nc => v.clone(),
                k => {
                    return Err(Error::param(
                        "black_level",
                        format!("{k} levels given for {nc} channels; expected 1 or {nc}"),
                    ))
                }
            };
            if let Some(bad) = v.iter().find(|x| !(x.is_finite() && (0.0..0.5).contains(*x))) {
                return Err(Error::param_in(
                    "black_level",
                    Allowed::within(Bound::Included(0.0), Bound::Excluded(0.5)),
                    format!("{bad} is not a fraction of full scale in [0, 0.5)"),
                ));
            }
            Ok(Black { level: per_channel(&v), means: v, uncertainty: vec![0.0; nc], source: "given".into() })
        }
        (BlackLevel::Auto, Some(d), _) => {
            let means =
                (0..nc).map(|c| d.values.index_axis(ndarray::Axis(2), c).mean().unwrap_or(0.0)).collect();
            Ok(Black {
                level: d.values.clone(),
                means,
                uncertainty: vec![0.0; nc],
                source: "dark frames".into(),
            })
        }
        (BlackLevel::Auto, None, Some(_)) => Ok(Black {
            level: Array3::zeros(shape),
            means: vec![0.0; nc],
            uncertainty: vec![0.0; nc],
            source: "none: the recovered response curve maps raw values to exposure".into(),
        }),
        (BlackLevel::Auto, None, None) => {
            let k = (0..frames.len()).fold(0, |best, k| if times[k] < times[best] { k } else { best });
            let est = estimate_black_level(&frames[k], warnings);
            let v: Vec<f64> = est.iter().map(|e| e.map_or(0.0, |e| e.0)).collect();
            // Not measurable: the level lies anywhere between 0 and the frame's lowest value.
            let lowest = |c: usize| {
                frames[k].image.values.index_axis(ndarray::Axis(2), c).iter().copied().fold(1.0, f64::min)
            };
            let uncertainty =
                est.iter().enumerate().map(|(c, e)| e.map_or_else(|| lowest(c), |e| e.1)).collect();
            let source = if est.iter().all(Option::is_some) {
                format!("estimated from the histogram of the shortest frame, {}", frames[k].path.display())
            } else {
                format!("not measurable in the shortest frame, {}: 0 used", frames[k].path.display())
            };
            Ok(Black { level: per_channel(&v), means: v, uncertainty, source })
        }
    }
}

/// Merges `frames` taken with exposure `times` (seconds); the black level (`dark`, the mean dark
/// frame, or as `opts.black_level` says) is subtracted from every frame's linear values;
/// `response` linearizes non-linear 8-bit captures.
pub fn merge(
    frames: &[Capture],
    times: &[f64],
    dark: Option<&Image>,
    response: Option<&Response>,
    opts: &MergeOptions,
) -> Result<Merged> {
    check_frames(frames, times, dark)?;
    let (lo, hi) = (opts.noise_floor, opts.saturation);
    if !((0.0..1.0).contains(&lo) && lo < hi && hi <= 1.0) {
        return Err(Error::param(
            "noise_floor/saturation",
            format!("need 0 <= noise floor < saturation <= 1, got {lo} and {hi}"),
        ));
    }
    let shape = frames[0].image.values.dim();
    if let Some(r) = response {
        r.check(frames)?;
    }
    let mut warnings = Vec::new();
    // Saturation per channel: `saturation` times where the channel clips (see `clipping`).
    let images: Vec<&Image> = frames.iter().map(|f| &f.image).collect();
    let channel_clipping = channel_clipping(&images, frames[0].full_scale());
    for (c, &level) in channel_clipping.iter().enumerate() {
        if level < 1.0 {
            warnings.push(format!(
                "channel {c} clips at {level:.4} of full scale ({:.0} counts): its samples at or above {:.4} are \
                 taken as saturated",
                level * frames[0].full_scale(),
                hi * level
            ));
        }
    }
    let sat = Array3::from_shape_fn(shape, |(_, _, c)| hi * channel_clipping[c]);
    let Black { level: black, means: black_means, uncertainty: black_uncertainty, source: black_source } =
        black_level(frames, times, dark, response, &opts.black_level, &mut warnings)?;
    // Linear values with the black level removed.
    let linear: Vec<Array3<f64>> = frames
        .iter()
        .map(|f| {
            let v = match response {
                Some(r) => r.linearize(&f.image).values,
                None => f.image.values.clone(),
            };
            v - &black
        })
        .collect();
    let used = if opts.estimate_times && frames.len() > 1 {
        estimate_times(frames, times, &linear, &black, &sat, &mut warnings)
    } else {
        times.to_vec()
    };

    let bracket = Bracket { frames, linear: &linear, used: &used, black: &black, lo };
    let Radiance {
        mut radiance,
        saturated_everywhere,
        dark_everywhere,
        inconsistent,
        saturated_samples,
        inconsistent_samples,
    } = merge_radiance(&bracket, &sat);
    let sat_level: Vec<f64> = channel_clipping.iter().map(|l| hi * l).collect();
    let per_frame = frame_stats(&bracket, times, &radiance, &sat_level);
    if saturated_everywhere.count > 0 {
        warnings.push(format!(
            "{} samples are saturated in every frame (first at row {}, col {}, channel {}); their \
             radiance is a lower bound",
            saturated_everywhere.count,
            saturated_everywhere.first.map_or(0, |f| f[0]),
            saturated_everywhere.first.map_or(0, |f| f[1]),
            saturated_everywhere.first.map_or(0, |f| f[2]),
        ));
    }
    if inconsistent.count > 0 {
        warnings.push(format!(
            "{} samples do not follow the exposure (their well-exposed frames differ by more than a \
             factor {INCONSISTENT_RATIO} in value over time; first at row {}, col {}, channel {}): stuck \
             or hot pixels, or motion",
            inconsistent.count,
            inconsistent.first.map_or(0, |f| f[0]),
            inconsistent.first.map_or(0, |f| f[1]),
            inconsistent.first.map_or(0, |f| f[2]),
        ));
    }
    if let Some(t) = opts.reference_exposure {
        if !(t.is_finite() && t > 0.0) {
            return Err(Error::param("reference_exposure", format!("{t} s; expected seconds > 0")));
        }
    }
    let unit = match opts.reference_exposure {
        Some(t) => {
            radiance *= t;
            format!("value 1 = full scale at the reference exposure t_ref = {t} s")
        }
        None => "fraction of full scale per second of exposure".to_string(),
    };
    Zip::from(&mut radiance).for_each(|e| {
        if !e.is_finite() {
            *e = 0.0;
        }
    });
    Ok(Merged {
        radiance: Image::new(radiance),
        stats: MergeStats {
            shape: [shape.0, shape.1, shape.2],
            unit,
            reference_exposure_s: opts.reference_exposure,
            bits: frames[0].bits,
            black_level: black_means,
            black_level_uncertainty: black_uncertainty,
            black_level_source: black_source,
            noise_floor: lo,
            saturation: hi,
            channel_clipping,
            frames: per_frame,
            saturated_everywhere,
            dark_everywhere,
            inconsistent,
            warnings,
        },
        response: response.cloned(),
        saturated_samples,
        inconsistent_samples,
    })
}

/// The bracket as the merge weighs it: the frames (raw values), their linear values with the
/// black level removed, the exposure times used, the black level and the noise floor.
struct Bracket<'a> {
    frames: &'a [Capture],
    linear: &'a [Array3<f64>],
    used: &'a [f64],
    black: &'a Array3<f64>,
    lo: f64,
}

/// The merged radiance and the samples it could not merge as the others (module docs).
struct Radiance {
    radiance: Array3<f64>,
    saturated_everywhere: PixelSet,
    dark_everywhere: PixelSet,
    inconsistent: PixelSet,
    saturated_samples: Vec<[usize; 3]>,
    inconsistent_samples: Vec<[usize; 3]>,
}

/// The radiance of every sample, `E = sum_k w(z_k) (v_k - d) / t_k / sum_k w(z_k)` with the hat
/// weight `w(z) = min(z - d - lo, hi - z)` between the noise floor and the saturation level
/// `sat` (module docs); a sample no frame sees between them takes the longest unsaturated
/// frame's value over its time, or, saturated everywhere, the shortest frame's. Samples whose
/// well-exposed frames differ by more than [`INCONSISTENT_RATIO`] are listed.
fn merge_radiance(b: &Bracket, sat: &Array3<f64>) -> Radiance {
    let Bracket { frames, linear, used, black, lo } = *b;
    let shape = frames[0].image.values.dim();
    // The noise floor is measured above the black level, saturation on the raw value.
    let dark_at = |i: usize, j: usize, c: usize| black[[i, j, c]];
    let weight = |z: f64, d: f64, hi: f64| if z - d > lo && z < hi { (z - d - lo).min(hi - z) } else { 0.0 };
    let mut radiance = Array3::<f64>::zeros(shape);
    let mut saturated_everywhere = PixelSet::default();
    let mut dark_everywhere = PixelSet::default();
    let mut inconsistent = PixelSet::default();
    let (mut saturated_samples, mut inconsistent_samples) = (Vec::new(), Vec::new());
    let (mut order, n) = ((0..frames.len()).collect::<Vec<_>>(), frames.len());
    order.sort_by(|&a, &b| used[a].total_cmp(&used[b]));
    for ((i, j, c), e) in radiance.indexed_iter_mut() {
        let (mut num, mut den) = (0.0, 0.0);
        let (d, hi) = (dark_at(i, j, c), sat[[i, j, c]]);
        let (mut lowest, mut highest, mut well) = (f64::INFINITY, 0.0f64, 0);
        for k in 0..n {
            let z = frames[k].image.values[[i, j, c]];
            let w = weight(z, d, hi);
            let rate = linear[k][[i, j, c]] / used[k];
            num += w * rate;
            den += w;
            if z - d >= 0.1 && z < hi {
                lowest = lowest.min(rate);
                highest = highest.max(rate);
                well += 1;
            }
        }
        if well >= 2 && highest > INCONSISTENT_RATIO * lowest {
            inconsistent.add(i, j, c);
            inconsistent_samples.push([i, j, c]);
        }
        if den > 0.0 {
            *e = num / den;
            continue;
        }
        // No usable frame: the longest unsaturated frame's value over its time (one frame, so
        // that the dark frame's error is not multiplied by the frame count), or a lower bound
        // from the shortest frame.
        if let Some(&k) = order.iter().rev().find(|&&k| frames[k].image.values[[i, j, c]] < hi) {
            *e = linear[k][[i, j, c]] / used[k];
            dark_everywhere.add(i, j, c);
        } else {
            let k = order[0];
            *e = linear[k][[i, j, c]] / used[k];
            saturated_everywhere.add(i, j, c);
            saturated_samples.push([i, j, c]);
        }
    }
    Radiance {
        radiance,
        saturated_everywhere,
        dark_everywhere,
        inconsistent,
        saturated_samples,
        inconsistent_samples,
    }
}

/// Each frame's stats: its saturated samples (at or above `sat_level`, per channel) and
/// those in the noise floor, and the RMS and median of `(v_k / t_k - E) / E` over the samples
/// it sees well exposed (module docs); `times` as listed.
fn frame_stats(b: &Bracket, times: &[f64], radiance: &Array3<f64>, sat_level: &[f64]) -> Vec<FrameStats> {
    let Bracket { frames, linear, used, black, lo } = *b;
    let dark_at = |i: usize, j: usize, c: usize| black[[i, j, c]];
    let mut stats = Vec::new();
    for (k, f) in frames.iter().enumerate() {
        let nc = radiance.dim().2;
        let (mut saturated, mut floor) = (vec![0; nc], vec![0; nc]);
        let mut dev = Vec::new();
        for ((i, j, c), &z) in f.image.values.indexed_iter() {
            if z >= sat_level[c] {
                saturated[c] += 1;
            } else if z - dark_at(i, j, c) <= lo {
                floor[c] += 1;
            } else if z - dark_at(i, j, c) >= 0.1 {
                let e = radiance[[i, j, c]];
                if e > 0.0 {
                    dev.push((linear[k][[i, j, c]] / used[k] - e) / e);
                }
            }
        }
        let rms =
            (!dev.is_empty()).then(|| (dev.iter().map(|d| d * d).sum::<f64>() / dev.len() as f64).sqrt());
        let mut abs: Vec<f64> = dev.iter().map(|d| d.abs()).collect();
        abs.sort_by(f64::total_cmp);
        stats.push(FrameStats {
            file: f.path.display().to_string(),
            exposure_listed: times[k],
            exposure_used: used[k],
            saturated,
            noise_floor: floor,
            agreement_rms: rms,
            agreement_median: abs.get(abs.len() / 2).copied(),
            agreement_samples: dev.len(),
        });
    }
    stats
}

/// Effective exposure times from neighbouring frames' value ratios (see the module docs).
fn estimate_times(
    frames: &[Capture],
    times: &[f64],
    linear: &[Array3<f64>],
    black: &Array3<f64>,
    sat: &Array3<f64>,
    warnings: &mut Vec<String>,
) -> Vec<f64> {
    const MIN_SAMPLES: usize = 50;
    let well_raw = |z: f64, d: f64, hi: f64| z - d >= 0.1 && z < hi;
    let mut order: Vec<usize> = (0..frames.len()).collect();
    order.sort_by(|&a, &b| times[a].total_cmp(&times[b]));
    // Anchor: the frame with the most well-exposed samples keeps its listed time.
    let anchor_pos = (0..order.len())
        .max_by_key(|&p| {
            Zip::from(&frames[order[p]].image.values)
                .and(black)
                .and(sat)
                .fold(0usize, |n, &z, &d, &hi| n + well_raw(z, d, hi) as usize)
        })
        .unwrap_or(0);
    // ratio[p] = t(order[p]) / t(order[p + 1]).
    let ratios: Vec<f64> = order
        .windows(2)
        .map(|w| {
            let (s, l) = (w[0], w[1]);
            let mut r: Vec<f64> = Zip::from(&frames[s].image.values)
                .and(&frames[l].image.values)
                .and(&linear[s])
                .and(&linear[l])
                .and(black)
                .and(sat)
                .fold(Vec::new(), |mut acc, &zs, &zl, &vs, &vl, &d, &hi| {
                    if well_raw(zs, d, hi) && well_raw(zl, d, hi) && vl > 0.0 {
                        acc.push(vs / vl);
                    }
                    acc
                });
            let listed = times[s] / times[l];
            if r.len() < MIN_SAMPLES {
                warnings.push(format!(
                    "{} and {} share {} well-exposed samples (fewer than {MIN_SAMPLES}): their listed \
                     exposure ratio is kept",
                    frames[s].path.display(),
                    frames[l].path.display(),
                    r.len()
                ));
                return listed;
            }
            r.sort_by(f64::total_cmp);
            r[r.len() / 2]
        })
        .collect();
    let mut used = times.to_vec();
    for p in (0..anchor_pos).rev() {
        used[order[p]] = used[order[p + 1]] * ratios[p];
    }
    for p in anchor_pos + 1..order.len() {
        used[order[p]] = used[order[p - 1]] / ratios[p - 1];
    }
    for k in 0..frames.len() {
        let d = used[k] / times[k] - 1.0;
        if d.abs() > 0.05 {
            warnings.push(format!(
                "{}: the pixels say {:.4e} s, {:+.1} % from the listed {:.4e} s",
                frames[k].path.display(),
                used[k],
                100.0 * d,
                times[k]
            ));
        }
    }
    used
}

/// The metadata of the merge's files: radiance unit, method, thresholds, pitch when known.
fn metadata(merged: &Merged, pitch: Option<f64>) -> Metadata {
    Metadata { pitch: pitch.map(|p| [p, p]), unit: None, text: Vec::new() }
        .with("radiance_unit", merged.stats.unit.clone())
        .with(
            "reference_exposure_s",
            merged
                .stats
                .reference_exposure_s
                .map_or("none (value 1 = full scale in 1 s)".into(), |t| format!("{t}")),
        )
        .with(
            "black_level",
            format!(
                "{} ({})",
                merged.stats.black_level.iter().map(|v| format!("{v}")).collect::<Vec<_>>().join(", "),
                merged.stats.black_level_source
            ),
        )
        .with("merge", "Debevec-Malik weighted mean of value/time, hat weights")
        .with("noise_floor", format!("{}", merged.stats.noise_floor))
        .with("saturation", format!("{}", merged.stats.saturation))
}

/// Writes merged radiance as an OpenEXR file (channels R, G, B, or Y for one channel; f32),
/// with its unit and the pixel pitch when known.
pub fn write_merged(path: &Path, merged: &Merged, pitch: Option<f64>) -> Result<()> {
    let nc = merged.radiance.channels();
    let planes: Vec<Array2<f32>> =
        (0..nc).map(|c| merged.radiance.values.index_axis(ndarray::Axis(2), c).mapv(|v| v as f32)).collect();
    let names: Vec<String> = if nc == 3 {
        ["R", "G", "B"].map(String::from).to_vec()
    } else {
        (0..nc).map(|c| if nc == 1 { "Y".into() } else { format!("C{c}") }).collect()
    };
    let channels: Vec<(&str, &Array2<f32>)> = names.iter().map(|s| s.as_str()).zip(planes.iter()).collect();
    write_exr(path, &channels, &metadata(merged, pitch))
}

/// What the tone-mapped picture of a merge shows.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ToneMapStats {
    /// The PNG file written.
    pub png: String,
    /// Exposure of the picture, stops.
    pub ev: f64,
    /// Fraction of samples at white (`E 2^ev >= 1`), 0..1.
    pub clipped_fraction: f64,
    /// The exposure, stops, that puts the 99th percentile of the radiance at white,
    /// `-log2(p99)` (`None` where it is not positive).
    pub ev_p99: Option<f64>,
    /// The exposure, stops, that puts the maximum of the radiance at white, `-log2(max)`
    /// (`None` where it is not positive).
    pub ev_max: Option<f64>,
    /// More than a quarter of the samples white, or the brightest below 5 % of white, each
    /// with the EV that fits.
    pub warnings: Vec<String>,
}

/// Writes the merge's picture at exposure `ev` stops: [`tone_map`] (sRGB of
/// `clip(E 2^ev, 0, 1)`) of the radiance as the EXR stores it (f32), as an 8-bit grayscale or
/// RGB PNG with the EXR's metadata and the tone map. Warns, with the EV that fits, when more
/// than a quarter of the samples are white or the brightest is below 5 % of white.
pub fn write_tone_mapped(path: &Path, merged: &Merged, ev: f64, pitch: Option<f64>) -> Result<ToneMapStats> {
    if !ev.is_finite() {
        return Err(Error::param("ev", format!("must be a finite number of stops, got {ev}")));
    }
    let radiance = merged.radiance.to_f32();
    let gain = 2f64.powf(ev);
    let n = radiance.values.len().max(1);
    let clipped_fraction =
        radiance.values.iter().filter(|&&v| v as f64 * gain >= 1.0).count() as f64 / n as f64;
    let mut values: Vec<f32> = radiance.values.iter().copied().collect();
    let p99 = if values.is_empty() {
        0.0
    } else {
        let k = (values.len() - 1) * 99 / 100;
        *values.select_nth_unstable_by(k, f32::total_cmp).1 as f64
    };
    let max = radiance.values.iter().fold(0.0f64, |m, &v| m.max(v as f64));
    let fit = |v: f64| (v > 0.0).then(|| -v.log2());
    let (ev_p99, ev_max) = (fit(p99), fit(max));
    let mut warnings = Vec::new();
    if let (true, Some(e)) = (clipped_fraction > 0.25, ev_p99) {
        warnings.push(format!(
            "{}: at EV {ev}, {:.1} % of the samples are white; `ev` {e:.1} puts the 99th percentile at white",
            path.display(),
            100.0 * clipped_fraction
        ));
    }
    if let (true, Some(e)) = (max * gain < 0.05, ev_max) {
        warnings.push(format!(
            "{}: at EV {ev}, the brightest sample is at {:.4} of white; `ev` {e:.1} puts it at white",
            path.display(),
            max * gain
        ));
    }
    let meta = metadata(merged, pitch)
        .with("tone_map", format!("sRGB (IEC 61966-2-1) of clip(E * 2^{ev}, 0, 1), 8 bits"))
        .with("ev", format!("{ev}"));
    write_png_image_u8(path, &tone_map(&radiance, ev), &meta)?;
    Ok(ToneMapStats { png: path.display().to_string(), ev, clipped_fraction, ev_p99, ev_max, warnings })
}
