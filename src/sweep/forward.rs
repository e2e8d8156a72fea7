//! The decoder's measurement model against real captures (`doefab bench forward`): how well
//! `y = clip(g (h * x))`, the bracket-merged reference `x` through the measured PSF `h`, predicts
//! the capture through the element, and what a richer model buys.
//!
//! Per scene the reference is registered onto the capture once, as `evaluate` does it
//! ([`crate::calibration::evaluate::prepare`]: gain `g`, local registration, pixels scored), and
//! each model's prediction is made in the reference's frame and resampled by that registration.
//! The models, each adding to the one before:
//!
//! 1. *paper*: `clip(g (h * x), 0, 1)`, the paper's model with the scene's one gain;
//! 2. *channel clipping*: each channel clipped where the capture's clips
//!    (`crate::calibration::clipping`);
//! 3. *channel gains and offsets*: `a_c g (h * x) + o_c`, `a_c` the median of capture over
//!    prediction on samples exposed between 0.05 and 0.9 of their clipping level in every
//!    channel, `o_c` the median of the remainder over the darks (a colour balance and a black
//!    level that the bracket and the capture do not share);
//! 4. *halo*: the PSF `(1 - eta) h + eta G_rho` ([`Halo`]), `eta` and `rho` from a grid, the
//!    gains and offsets refitted for each;
//! 5. *blur*: the halo model's prediction blurred by a Gaussian of `sigma` pixels from a grid
//!    (0 included: a blur the captures do not support is reported as 0).
//!
//! The figure of each is the RMS of `sqrt(prediction) - sqrt(capture)` over the scored samples
//! of pixels unsaturated in the capture, in bands of the paper model's brightness (its channel
//! mean): darks (below 0.02 of the clipping level), mid-tones (0.02-0.3), brights (above 0.3),
//! and the ring of pixels within [`RING_PX`] of a saturated one, where flare sits; and the
//! agreement of the saturated sets (intersection over union of the pixels saturated in the
//! prediction and in the capture, over the scored pixels; saturated as `evaluate` counts it).
//! A misregistration of a pixel or so
//! (the registration's leave-one-out residual) reads as blur and as residual at edges: the
//! figures bound the model's error from above.

use std::path::{Path, PathBuf};

use ndarray::{Array2, Array3, Axis, Zip};
use serde::Serialize;

use super::decoder::{prepare_scene, scene_dirs, SweepScene, SENSOR_PITCH};
use crate::calibration::evaluate::{convolve_psf, ScoringOptions};
use crate::decoder::measurement::{halo_blur, Halo};
use crate::error::{DataCause, Error, Result};
use crate::image::Image;
use crate::optics::psf::Psf;

/// Pixels within this distance of a pixel saturated in the capture form the flare ring.
pub const RING_PX: usize = 16;
/// The halo fractions `eta` searched: the fraction of all light in the halo (0..1).
pub const HALO_FRACTIONS: [f64; 6] = [0.05, 0.1, 0.15, 0.2, 0.3, 0.4];
/// The halo radii searched (the Gaussian's standard deviation `rho`), sensor pixels.
pub const HALO_RADII_PX: [f64; 5] = [8.0, 16.0, 32.0, 64.0, 128.0];
/// The extra blurs searched: the Gaussian's standard deviation, sensor pixels.
pub const BLURS_PX: [f64; 4] = [0.0, 0.5, 1.0, 1.5];

/// Settings of [`run`].
#[derive(Debug, Clone)]
pub struct ForwardOptions {
    /// The paper's data release: the default scenes (`captures/<scene>/`) and `measured_psf.npz`.
    pub data: PathBuf,
    /// Scene folders; empty: every folder under `<data>/captures`.
    pub scenes: Vec<PathBuf>,
    /// The measured PSF; `None`: `<data>/measured_psf.npz` (array `psf_val`).
    pub psf: Option<PathBuf>,
    /// Registration and scoring settings, the same for every scene.
    pub scoring: ScoringOptions,
}

/// Residuals of one model (see the module docs), sqrt domain, units of the clipping level: the
/// RMS of `sqrt(prediction) - sqrt(capture)` over the samples (pixel and channel) of a band, NaN
/// where the band is empty.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Residuals {
    /// Over the darks: paper-model brightness below 0.02 of the clipping level.
    pub dark: f64,
    /// Over the mid-tones: paper-model brightness 0.02-0.3 of the clipping level.
    pub mid: f64,
    /// Over the brights: paper-model brightness above 0.3 of the clipping level.
    pub bright: f64,
    /// Over the flare ring: pixels within [`RING_PX`] of one saturated in the capture.
    pub ring: f64,
    /// Over every unsaturated scored pixel: the figure the halo and blur are chosen by.
    pub all: f64,
    /// Intersection over union of the saturated pixels of prediction and capture, over the
    /// scored pixels (0..1); NaN when neither has a saturated pixel.
    pub saturated_iou: f64,
}

/// One model fitted to one scene.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ModelFit {
    /// The model's name ("paper: measured PSF, one gain, clipped at 1", "+ channel clipping", ...).
    pub model: String,
    /// Per channel, relative to the scene's gain (1 where not fitted).
    pub gains: [f64; 3],
    /// Per channel, units of the clipping level (0 where not fitted).
    pub offsets: [f64; 3],
    /// The halo added to the PSF (the fitted one for the halo and blur models); `None` for the
    /// first three models.
    pub halo: Option<Halo>,
    /// Standard deviation of the extra Gaussian blur, sensor pixels (0: none).
    pub blur_px: f64,
    /// Where each channel of the prediction is clipped, fraction of the clipping level.
    pub clipping: [f64; 3],
    /// The residuals of the fitted model.
    pub residuals: Residuals,
}

/// One scene's check.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SceneCheck {
    /// The scene's name: its folder's name.
    pub name: String,
    /// Fraction of the capture's pixels the registration covers (0..1).
    pub coverage: f64,
    /// The scene's gain `g`: median of `capture / (h * reference)` over well-exposed samples.
    pub gain: f64,
    /// Leave-one-out RMS error of the local registration's field, pixels; `None` under the affine
    /// model.
    pub registration_residual_px: Option<f64>,
    /// Pixels in each band: dark, mid, bright, ring, all unsaturated scored.
    pub band_pixels: [usize; 5],
    /// The models, each adding to the one before: paper, channel clipping, channel gains and
    /// offsets, halo (the best of the grid), blur (the best of [`BLURS_PX`]).
    pub models: Vec<ModelFit>,
    /// `all` residual of the halo model over [`HALO_FRACTIONS`] (rows) x [`HALO_RADII_PX`].
    pub halo_grid: Vec<Vec<f64>>,
}

/// What `doefab bench forward` measured (its JSON).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ForwardSweepResults {
    /// What the numbers are in (residuals, gains, offsets, clipping, radii).
    pub units: String,
    /// The measured PSF's file.
    pub psf: String,
    /// [`HALO_FRACTIONS`]: the halo fractions `eta` searched (0..1).
    pub halo_fractions: Vec<f64>,
    /// [`HALO_RADII_PX`]: the halo radii `rho` searched, sensor pixels.
    pub halo_radii_px: Vec<f64>,
    /// [`BLURS_PX`]: the extra blurs searched (Gaussian standard deviation), sensor pixels.
    pub blurs_px: Vec<f64>,
    /// Every scene checked, in the order of the folders (as given, or by name).
    pub scenes: Vec<SceneCheck>,
    /// Scenes that could not be merged or registered, with the reason.
    pub refused: Vec<(String, String)>,
}

/// The pixel sets of a scene, in the capture's frame.
struct Bands {
    /// dark, mid, bright, ring, all (unsaturated scored pixels).
    sets: [Array2<bool>; 5],
    scored: Array2<bool>,
    saturated: Array2<bool>,
}

/// Runs the check on every scene and writes `forward.json` into `out` (its chart is the
/// command's, [`crate::pipeline::sweep::sweep_forward`]).
/// `progress(message, done, total)` counts two steps a scene.
pub fn run(
    opts: &ForwardOptions,
    out: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<ForwardSweepResults> {
    let dirs =
        if opts.scenes.is_empty() { scene_dirs(&opts.data.join("captures"))? } else { opts.scenes.clone() };
    let (psf_path, key) = match &opts.psf {
        Some(p) => (p.clone(), None),
        None => (opts.data.join("measured_psf.npz"), Some("psf_val")),
    };
    let psf = Psf::read(&psf_path, key, Some(SENSOR_PITCH))?;
    let (mut scenes, mut refused) = (Vec::new(), Vec::new());
    let total = 2 * dirs.len() as u64;
    for (k, dir) in dirs.iter().enumerate() {
        let name =
            dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into_owned());
        progress(&format!("{name}: merging and registering"), 2 * k as u64, total);
        match prepare_scene(dir, &psf, &opts.scoring) {
            Ok(scene) => {
                progress(&format!("{name}: fitting the models"), 2 * k as u64 + 1, total);
                scenes.push(check_scene(&scene, &psf, opts.scoring.saturation)?);
            }
            Err(e) => refused.push((name, e.to_string())),
        }
    }
    progress("", total, total);
    if scenes.is_empty() {
        return Err(Error::data(DataCause::Empty, format!("no scene could be registered: {refused:?}")));
    }
    let report = ForwardSweepResults {
        units: "residuals: RMS of sqrt(prediction) - sqrt(capture), the capture's clipping level = 1; gains relative \
                to the scene's gain; offsets and clipping in units of the clipping level; halo and blur radii in \
                sensor pixels (4.29 um)"
            .into(),
        psf: psf_path.display().to_string(),
        halo_fractions: HALO_FRACTIONS.to_vec(),
        halo_radii_px: HALO_RADII_PX.to_vec(),
        blurs_px: BLURS_PX.to_vec(),
        scenes,
        refused,
    };
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    crate::io::atomic::write_bytes(
        &out.join("forward.json"),
        serde_json::to_string_pretty(&report).map_err(|e| Error::internal(e.to_string()))?.as_bytes(),
    )?;
    Ok(report)
}

/// The models of the module docs fitted to one scene.
pub fn check_scene(scene: &SweepScene, psf: &Psf, saturation: f64) -> Result<SceneCheck> {
    let footing = &scene.scoring.footing;
    let g = footing.gain;
    let levels: [f64; 3] = match footing.channel_clipping.as_slice() {
        [r, gr, b] => [*r, *gr, *b],
        other => {
            return Err(Error::data(
                DataCause::Shape,
                format!("{}: {} channels; the check needs RGB", scene.name, other.len()),
            ))
        }
    };
    let capture = &scene.capture.values;
    let scaled = Image::new(scene.reference.values.mapv(|v| g * v));
    let through = convolve_psf(&scaled, psf)?;
    let base = scene.scoring.warp(&through)?.values;
    let bands = bands(scene, &base);
    let evaluate =
        |prediction: &Array3<f64>, fit: bool, clipping: [f64; 3], halo: Option<Halo>, blur_px: f64| {
            let (gains, offsets) =
                if fit { gains_offsets(capture, prediction, &bands, &levels) } else { ([1.0; 3], [0.0; 3]) };
            let mut model = prediction.clone();
            Zip::indexed(&mut model)
                .for_each(|(_, _, c), v| *v = (gains[c] * *v + offsets[c]).clamp(0.0, clipping[c]));
            ModelFit {
                model: String::new(),
                gains,
                offsets,
                halo,
                blur_px,
                clipping,
                residuals: residuals(capture, &model, &bands, &clipping, saturation),
            }
        };
    let named = |name: &str, mut fit: ModelFit| {
        fit.model = name.into();
        fit
    };
    let mut models = vec![
        named("paper: measured PSF, one gain, clipped at 1", evaluate(&base, false, [1.0; 3], None, 0.0)),
        named("+ channel clipping", evaluate(&base, false, levels, None, 0.0)),
        named("+ channel gains and offsets", evaluate(&base, true, levels, None, 0.0)),
    ];
    // Halo: the wide part is computed once per radius in the reference's frame.
    let mut halo_grid = vec![vec![f64::NAN; HALO_RADII_PX.len()]; HALO_FRACTIONS.len()];
    let mut best: Option<(ModelFit, Array3<f64>)> = None;
    for (r, &radius_px) in HALO_RADII_PX.iter().enumerate() {
        let mut wide = Array3::zeros(scaled.values.dim());
        for c in 0..3 {
            let w = halo_blur(&scaled.values.index_axis(Axis(2), c).to_owned(), radius_px)?;
            wide.index_axis_mut(Axis(2), c).assign(&w);
        }
        let wide = scene.scoring.warp(&Image::new(wide))?.values;
        for (f, &fraction) in HALO_FRACTIONS.iter().enumerate() {
            let mixed = (1.0 - fraction) * &base + fraction * &wide;
            let fit = evaluate(&mixed, true, levels, Some(Halo { fraction, radius_px }), 0.0);
            halo_grid[f][r] = fit.residuals.all;
            if best.as_ref().is_none_or(|(b, _)| fit.residuals.all < b.residuals.all) {
                best = Some((fit, mixed));
            }
        }
    }
    let (halo_fit, halo_prediction) = best.ok_or_else(|| Error::internal("no halo model was fitted"))?;
    let halo = halo_fit.halo;
    models.push(named("+ halo", halo_fit));
    let mut blurred_best: Option<ModelFit> = None;
    for &sigma in &BLURS_PX {
        let mut blurred = halo_prediction.clone();
        for c in 0..3 {
            let b =
                crate::grid::blur::blur_samples(&halo_prediction.index_axis(Axis(2), c).to_owned(), sigma)?;
            blurred.index_axis_mut(Axis(2), c).assign(&b);
        }
        let fit = evaluate(&blurred, true, levels, halo, sigma);
        if blurred_best.as_ref().is_none_or(|b| fit.residuals.all < b.residuals.all) {
            blurred_best = Some(fit);
        }
    }
    models.extend(blurred_best.map(|f| named("+ blur", f)));
    Ok(SceneCheck {
        name: scene.name.clone(),
        coverage: footing.coverage,
        gain: g,
        registration_residual_px: footing.local_registration.as_ref().map(|l| l.residual_rms_px),
        band_pixels: bands.sets.clone().map(|s| s.iter().filter(|v| **v).count()),
        models,
        halo_grid,
    })
}

fn bands(scene: &SweepScene, base: &Array3<f64>) -> Bands {
    let scored = scene.scoring.mask.clone();
    let (h, w) = scored.dim();
    let saturated = scene.scoring.saturated.clone();
    // Within RING_PX (chessboard distance) of a saturated pixel: a separable max filter.
    let dilate = |a: &Array2<bool>, along_rows: bool| {
        Array2::from_shape_fn((h, w), |(i, j)| {
            let (n, k) = if along_rows { (w, j) } else { (h, i) };
            (k.saturating_sub(RING_PX)..(k + RING_PX + 1).min(n)).any(|m| {
                if along_rows {
                    a[[i, m]]
                } else {
                    a[[m, j]]
                }
            })
        })
    };
    let near = dilate(&dilate(&saturated, true), false);
    let unsaturated = &scored & &saturated.mapv(|s| !s);
    let lum = base.mean_axis(Axis(2)).unwrap_or_else(|| Array2::zeros((h, w)));
    let band =
        |lo: f64, hi: f64| Zip::from(&unsaturated).and(&lum).map_collect(|&u, &l| u && l >= lo && l < hi);
    let ring = &unsaturated & &near;
    Bands {
        sets: [band(f64::NEG_INFINITY, 0.02), band(0.02, 0.3), band(0.3, f64::INFINITY), ring, unsaturated],
        scored,
        saturated,
    }
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let k = v.len() / 2;
    Some(*v.select_nth_unstable_by(k, f64::total_cmp).1)
}

/// Per channel: `a_c`, the median of capture over prediction on well-exposed samples, and
/// `o_c`, the median remainder over the darks (module docs); 1 and 0 where a set is empty.
fn gains_offsets(
    capture: &Array3<f64>,
    prediction: &Array3<f64>,
    b: &Bands,
    levels: &[f64; 3],
) -> ([f64; 3], [f64; 3]) {
    let (h, w, _) = capture.dim();
    let well = |i: usize, j: usize| {
        b.sets[4][[i, j]]
            && (0..3).all(|c| {
                (0.05..=0.9 * levels[c]).contains(&capture[[i, j, c]]) && prediction[[i, j, c]] > 0.0
            })
    };
    let pixels: Vec<(usize, usize)> = (0..h).flat_map(|i| (0..w).map(move |j| (i, j))).collect();
    let (mut gains, mut offsets) = ([1.0; 3], [0.0; 3]);
    for c in 0..3 {
        let ratios: Vec<f64> = pixels
            .iter()
            .filter(|&&(i, j)| well(i, j))
            .map(|&(i, j)| capture[[i, j, c]] / prediction[[i, j, c]])
            .collect();
        gains[c] = median(ratios).unwrap_or(1.0);
        let rest: Vec<f64> = pixels
            .iter()
            .filter(|&&(i, j)| b.sets[0][[i, j]])
            .map(|&(i, j)| capture[[i, j, c]] - gains[c] * prediction[[i, j, c]])
            .collect();
        offsets[c] = median(rest).unwrap_or(0.0);
    }
    (gains, offsets)
}

fn residuals(
    capture: &Array3<f64>,
    model: &Array3<f64>,
    b: &Bands,
    clipping: &[f64; 3],
    saturation: f64,
) -> Residuals {
    let rms = |set: &Array2<bool>| {
        let (mut s, mut n) = (0.0, 0usize);
        for ((i, j), &inside) in set.indexed_iter() {
            if inside {
                for c in 0..3 {
                    s += (model[[i, j, c]].max(0.0).sqrt() - capture[[i, j, c]].max(0.0).sqrt()).powi(2);
                    n += 1;
                }
            }
        }
        if n == 0 {
            f64::NAN
        } else {
            (s / n as f64).sqrt()
        }
    };
    let (mut both, mut either) = (0usize, 0usize);
    for ((i, j), &scored) in b.scored.indexed_iter() {
        if scored {
            let predicted = (0..3).any(|c| model[[i, j, c]] >= saturation * clipping[c]);
            both += usize::from(predicted && b.saturated[[i, j]]);
            either += usize::from(predicted || b.saturated[[i, j]]);
        }
    }
    Residuals {
        dark: rms(&b.sets[0]),
        mid: rms(&b.sets[1]),
        bright: rms(&b.sets[2]),
        ring: rms(&b.sets[3]),
        all: rms(&b.sets[4]),
        saturated_iou: if either == 0 { f64::NAN } else { both as f64 / either as f64 },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A prediction and a capture that is `a_c p + o_c` exactly: the fit recovers `a_c` and
    /// `o_c`, and the fitted model's residual is 0 in every band; the unfitted one's is not.
    #[test]
    fn gains_and_offsets_of_an_affine_capture_are_recovered() {
        let (h, w) = (40, 50);
        let prediction = Array3::from_shape_fn((h, w, 3), |(i, j, c)| {
            // Darks on the left (below 0.02), exposed samples on the right.
            let x = j as f64 / w as f64;
            let v =
                if x < 0.4 { 0.002 + 0.01 * x } else { 0.05 + 0.6 * x * (1.0 + 0.1 * (i as f64 / h as f64)) };
            v * [1.0, 0.8, 0.9][c]
        });
        let (a, o) = ([0.93, 1.11, 0.98], [0.004, -0.002, 0.001]);
        let capture = Array3::from_shape_fn((h, w, 3), |(i, j, c)| a[c] * prediction[[i, j, c]] + o[c]);
        let all = Array2::from_elem((h, w), true);
        let lum = prediction.mean_axis(Axis(2)).expect("three channels");
        let dark = lum.mapv(|l| l < 0.02);
        let bands = Bands {
            sets: [
                dark.clone(),
                dark.mapv(|d| !d),
                Array2::from_elem((h, w), false),
                all.clone(),
                all.clone(),
            ],
            scored: all,
            saturated: Array2::from_elem((h, w), false),
        };
        let (gains, offsets) = gains_offsets(&capture, &prediction, &bands, &[1.0; 3]);
        for c in 0..3 {
            // The median ratio is a_c + o_c / p over the exposed samples: within o_c / 0.05.
            assert!((gains[c] - a[c]).abs() < 0.02 * a[c], "gain {c}: {} vs {}", gains[c], a[c]);
        }
        let fitted =
            Array3::from_shape_fn((h, w, 3), |(i, j, c)| gains[c] * prediction[[i, j, c]] + offsets[c]);
        let r = residuals(&capture, &fitted, &bands, &[1.0; 3], 0.99);
        let r0 = residuals(&capture, &prediction, &bands, &[1.0; 3], 0.99);
        assert!(r.all < 0.5 * r0.all, "fitted {:?} vs unfitted {:?}", r, r0);
        assert!(r.dark < 0.2 * r0.dark, "dark: fitted {} vs unfitted {}", r.dark, r0.dark);
        let exact = residuals(&capture, &capture, &bands, &[1.0; 3], 0.99);
        assert_eq!((exact.all, exact.dark, exact.mid), (0.0, 0.0, 0.0));
        assert!(exact.bright.is_nan(), "an empty band is NaN, not 0");
        assert!(exact.saturated_iou.is_nan(), "no saturated pixel on either side");
    }

    /// The saturated sets' agreement: 2 pixels saturated in both, 1 only in the prediction,
    /// 1 only in the capture: IoU 2/4; green counts as saturated at its own clipping level.
    #[test]
    fn saturated_agreement_is_intersection_over_union_at_each_channels_level() {
        let (h, w) = (2, 3);
        let mut model = Array3::zeros((h, w, 3));
        let mut saturated = Array2::from_elem((h, w), false);
        for &(i, j) in &[(0, 0), (0, 1), (1, 2)] {
            model[[i, j, 1]] = 0.9; // green at its clipping level 0.9
        }
        for &(i, j) in &[(0, 0), (0, 1), (1, 0)] {
            saturated[[i, j]] = true;
        }
        let all = Array2::from_elem((h, w), true);
        let bands = Bands { sets: std::array::from_fn(|_| all.clone()), scored: all, saturated };
        let r = residuals(&model, &model, &bands, &[1.0, 0.9, 1.0], 0.99);
        assert_eq!(r.saturated_iou, 0.5);
        let r = residuals(&model, &model, &bands, &[1.0; 3], 0.99);
        assert_eq!(r.saturated_iou, 0.0, "at a clipping level of 1 green 0.9 is not saturated");
    }
}
