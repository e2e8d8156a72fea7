//! The decoder on real captures (`doefab bench decoder`): PSNR of reconstructions of a scene
//! captured through the DOE against the HDR merged from a bracket of the same scene taken
//! without it, for any number of decoders on one common footing.
//!
//! Per scene folder (an `exposures.json` listing one frame with `"doe": true` and a bracket
//! without the DOE, as in the paper's data release):
//!
//! 1. The bracket is merged ([`crate::calibration::hdr_merge`]) into radiance at the listed
//!    reference exposure (value 1 = the sensor's clipping level).
//! 2. The reference is registered onto the *capture* through the DOE, not onto each
//!    reconstruction, so that every decoder is scored against the same warped reference over
//!    the same pixels. Attaching the DOE moves the camera's centre of projection, and objects
//!    at different depths move differently (on the shared scenes an affine map fits under a
//!    third of the tiles): the registration is a local displacement field
//!    ([`crate::calibration::register::register_local`]), matched on the square root of both
//!    images with the reference clipped at the capture's clipping level. Pixels the field does
//!    not cover are left out, and the report gives the fraction kept and the field's
//!    leave-one-out residual.
//! 3. A gain `g` maps the reference onto the capture: the DOE and its mount absorb part of the
//!    light and the bracket's effective times drift from the listed ones. Where the capture is
//!    well exposed (0.05..0.9 of full scale in every channel) it is the convolution of the scene
//!    with a PSF summing to 1, so `g` = the median of `capture / reference` there.
//! 4. Each decoder reconstructs the capture ([`super::reconstruct::reconstruct`], negatives
//!    clamped), and PSNR ([`crate::calibration::evaluate::psnr`]) is computed over the covered
//!    pixels and over those of them saturated in the capture. The capture itself is scored
//!    the same way as the baseline a decoder must beat.

use std::path::{Path, PathBuf};

use ndarray::{Array2, Array3, Zip};
use serde::Serialize;

use super::finetune::{read_psf, FinetuneConfig, GeneratedScenes, HistoryEntry, SceneSource, Trainer};
use super::reconstruct::{reconstruct, ReconstructOptions};
use super::unet::UNet;
use super::weights::DecoderWeights;
use crate::calibration::capture::{read_capture, read_exposures};
use crate::calibration::evaluate::{psnr, Psnr};
use crate::calibration::hdr_merge::{merge, MergeOptions};
use crate::calibration::register::{luminance, register_local, LocalRegistration, RegisterOptions};
use crate::error::{Error, Result};

/// Saturation level of the 8-bit captures, fraction of full scale.
pub const SATURATION: f64 = 0.98;

/// Pixel pitch of the paper's sensor (Canon Rebel T5), metres: the measured PSF's sampling.
pub const SENSOR_PITCH: f64 = 4.29e-6;

/// A scene prepared for scoring: the capture through the DOE and the registered reference.
#[derive(Debug, Clone)]
pub struct BenchScene {
    pub name: String,
    /// The capture through the DOE, `(H, W, 3)`, 1 = clipping level.
    pub capture: Array3<f64>,
    /// The merged reference mapped onto the capture's pixels and scaled by `gain`.
    pub reference: Array3<f64>,
    /// Pixels the registration covers.
    pub mask: Array2<bool>,
    /// `mask` and saturated (any channel at or above [`SATURATION`]) in the capture.
    pub saturated: Array2<bool>,
    pub report: SceneReport,
}

/// How a scene was prepared (for the JSON report).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SceneReport {
    pub name: String,
    pub capture: String,
    pub bracket_frames: usize,
    pub merge_warnings: Vec<String>,
    pub registration: LocalRegistration,
    /// `capture / reference` over well-exposed pixels (see the module docs).
    pub gain: f64,
    pub gain_samples: usize,
    pub pixels: usize,
    pub saturated_pixels: usize,
}

/// PSNR of one decoder (or of the capture as it is) on one scene.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Score {
    pub scene: String,
    pub decoder: String,
    pub all: Psnr,
    pub saturated: Option<Psnr>,
}

/// The scene folders under `dir`: those holding an `exposures.json`, in name order.
pub fn scene_dirs(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| Error::io(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("exposures.json").is_file())
        .collect();
    dirs.sort();
    if dirs.is_empty() {
        return Err(Error::format(dir, "holds no scene folder with an exposures.json"));
    }
    Ok(dirs)
}

/// Merges, registers and gain-matches the scene in `dir` (steps 1-3 of the module docs).
pub fn prepare_scene(dir: &Path, register: &RegisterOptions) -> Result<BenchScene> {
    let list_path = dir.join("exposures.json");
    let doe = read_exposures(&list_path, true)?;
    let [(capture_path, _)] = doe.frames.as_slice() else {
        return Err(Error::format(
            &list_path,
            format!("lists {} frames with \"doe\": true; expected exactly one capture", doe.frames.len()),
        ));
    };
    let bracket = read_exposures(&list_path, false)?;
    let frames = bracket.frames.iter().map(|(p, _)| read_capture(p)).collect::<Result<Vec<_>>>()?;
    let times: Vec<f64> = bracket.frames.iter().map(|f| f.1).collect();
    let opts = MergeOptions {
        saturation: SATURATION,
        reference_exposure: bracket.reference_exposure,
        ..MergeOptions::default()
    };
    let merged = merge(&frames, &times, None, None, &opts)?;
    let capture = read_capture(capture_path)?.values;
    if capture.dim() != merged.radiance.dim() || capture.dim().2 != 3 {
        return Err(Error::format(
            capture_path,
            format!(
                "is {:?} (rows, cols, channels); the bracket is {:?} and both must be RGB of one size",
                capture.dim(),
                merged.radiance.dim()
            ),
        ));
    }
    let clipped = merged.radiance.mapv(|v| v.min(1.0));
    let registration = register_local(&luminance(&clipped), &luminance(&capture), register)?;
    let (mut reference, mask) = registration.warp(&merged.radiance);
    let mut ratios = Vec::new();
    Zip::indexed(&mask).for_each(|(i, j), &inside| {
        let exposed =
            (0..3).all(|c| (0.05..=0.9).contains(&capture[[i, j, c]]) && reference[[i, j, c]] > 0.0);
        if inside && exposed {
            ratios.extend((0..3).map(|c| capture[[i, j, c]] / reference[[i, j, c]]));
        }
    });
    if ratios.len() < 300 {
        return Err(Error::Data(format!(
            "{}: only {} well-exposed samples (0.05..0.9 of full scale) to match the reference's gain; \
             300 needed",
            capture_path.display(),
            ratios.len()
        )));
    }
    ratios.sort_by(f64::total_cmp);
    let gain = ratios[ratios.len() / 2];
    reference.mapv_inplace(|v| v * gain);
    let saturated = Array2::from_shape_fn(mask.dim(), |(i, j)| {
        mask[[i, j]] && (0..3).any(|c| capture[[i, j, c]] >= SATURATION)
    });
    let name =
        dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into_owned());
    let report = SceneReport {
        name: name.clone(),
        capture: capture_path.display().to_string(),
        bracket_frames: frames.len(),
        merge_warnings: merged.report.warnings.clone(),
        registration,
        gain,
        gain_samples: ratios.len(),
        pixels: mask.iter().filter(|v| **v).count(),
        saturated_pixels: saturated.iter().filter(|v| **v).count(),
    };
    Ok(BenchScene { name, capture, reference, mask, saturated, report })
}

/// PSNR of `image` (a reconstruction, or the capture itself) against the scene's reference.
pub fn score_image(scene: &BenchScene, decoder: &str, image: &Array3<f64>) -> Result<Score> {
    let all = psnr(&scene.reference, image, Some(&scene.mask))?;
    let saturated = if scene.report.saturated_pixels > 0 {
        Some(psnr(&scene.reference, image, Some(&scene.saturated))?)
    } else {
        None
    };
    Ok(Score { scene: scene.name.clone(), decoder: decoder.into(), all, saturated })
}

/// Reconstructs the scene's capture with `net` and scores it; returns the reconstruction too.
pub fn score_decoder(scene: &BenchScene, decoder: &str, net: &UNet) -> Result<(Score, Array3<f32>)> {
    let x = scene.capture.mapv(|v| v as f32);
    let (y, _) = reconstruct(net, &x, &ReconstructOptions::default())?;
    Ok((score_image(scene, decoder, &y.mapv(f64::from))?, y))
}

/// Exposure of the pictures `run` writes, stops: highlights a few times the clipping level
/// stay visible.
pub const PICTURE_EV: f64 = -2.0;

/// Writes `images` of `scene` as tone-mapped PNGs (sRGB of clip(y 2^[`PICTURE_EV`], 0, 1))
/// into `dir`, each named by its key, with the registered reference (black where the
/// registration does not cover) as `reference.png`.
fn write_pictures(dir: &Path, scene: &BenchScene, images: &[(&str, &Array3<f32>)]) -> Result<()> {
    let mut reference = scene.reference.mapv(|v| v as f32);
    Zip::from(reference.lanes_mut(ndarray::Axis(2))).and(&scene.mask).for_each(|mut px, &inside| {
        if !inside {
            px.fill(0.0);
        }
    });
    let meta = crate::io::heightmap::Metadata {
        pitch: None,
        unit: None,
        text: vec![
            ("quantity".into(), "linear HDR radiance, 1 = sensor clipping level of the capture".into()),
            ("scene".into(), scene.name.clone()),
            ("tone_map".into(), format!("sRGB of clip(y * 2^{PICTURE_EV}, 0, 1)")),
        ],
    };
    for (name, image) in std::iter::once(("reference", &reference)).chain(images.iter().copied()) {
        let path = dir.join(format!("{name}.png"));
        crate::io::png::write_png_image_u8(&path, &crate::report::tone::tone_map(image, PICTURE_EV), &meta)?;
    }
    Ok(())
}

/// Settings of [`run`].
#[derive(Debug, Clone)]
pub struct BenchConfig {
    /// The paper's data release: `captures/<scene>/`, `measured_psf.npz`, the two decoders.
    pub data: PathBuf,
    /// The fine-tuning of the simulated-PSF decoder on the measured PSF.
    pub finetune: FinetuneConfig,
    /// Score the decoder being fine-tuned on the real scenes every this many steps.
    pub evaluate_every: usize,
    /// HDR images to fine-tune on (a folder of EXR / Radiance .hdr); `None`: procedural scenes.
    pub train_data: Option<PathBuf>,
    pub register: RegisterOptions,
}

/// The decoder being fine-tuned, scored on the real scenes at one step.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CurvePoint {
    pub step: usize,
    /// Training time up to this step (scoring excluded), seconds.
    pub seconds: f64,
    pub scores: Vec<Score>,
}

/// What `doefab bench decoder` reports.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BenchReport {
    pub data: String,
    pub units: &'static str,
    pub saturation: f64,
    pub scenes: Vec<SceneReport>,
    /// The capture as it is, the starting decoder, the fine-tuned one and the paper's
    /// measured-PSF decoder, per scene.
    pub scores: Vec<Score>,
    /// The fine-tuned decoder's scores along the run (step 0 = the starting decoder).
    pub curve: Vec<CurvePoint>,
    pub steps: usize,
    pub seconds_per_step: f64,
    pub training_data: String,
    /// The training curve on simulated data (loss, validation PSNR).
    pub history: Vec<HistoryEntry>,
}

/// Names of the decoders in the report.
pub const START: &str = "paper, simulated PSF (start of the fine-tuning)";
pub const TUNED: &str = "fine-tuned here";
pub const PAPER: &str = "paper, measured PSF";
pub const CAPTURE: &str = "capture as it is";

/// Runs the benchmark: prepares every scene, fine-tunes the paper's simulated-PSF decoder on
/// the measured PSF (scoring it on the scenes every `evaluate_every` steps) and scores the
/// capture, the start, the result and the paper's measured-PSF decoder. Writes into `out`:
/// `finetuned/` (the decoder and its training record), `report.json`,
/// `psnr_vs_steps.png` (PSNR-gamma on the real scenes along the run against the paper's
/// decoder) and per scene `<scene>/*.png`, the registered reference, the capture and the
/// three reconstructions tone-mapped at [`PICTURE_EV`]. `progress` is told what is happening and each unit of work done.
pub fn run(cfg: &BenchConfig, out: &Path, progress: &mut dyn FnMut(&str, u64)) -> Result<BenchReport> {
    if cfg.evaluate_every == 0 {
        return Err(Error::param("evaluate_every", "must be at least 1 step"));
    }
    let dirs = scene_dirs(&cfg.data.join("captures"))?;
    let mut scenes = Vec::new();
    for d in &dirs {
        progress(&format!("merging and registering {}", d.display()), 0);
        scenes.push(prepare_scene(d, &cfg.register)?);
        progress("", 1);
    }
    let device = super::device(false)?;
    let start_path = cfg.data.join("decoder_simulated_psf.safetensors");
    let paper_path = cfg.data.join("decoder_measured_psf.safetensors");
    let psf_path = cfg.data.join("measured_psf.npz");
    let start = DecoderWeights::read(&start_path)?;
    let psf = read_psf(&psf_path, Some("psf_val"), SENSOR_PITCH)?;
    let source: Box<dyn SceneSource> = match &cfg.train_data {
        Some(dir) => Box::new(super::dataset::HdrScenes::new(
            &dir.display().to_string(),
            super::dataset::read_dir(dir)?,
        )?),
        None => Box::new(GeneratedScenes {
            name: "procedural HDR scenes",
            generate: super::scenes::procedural_scene,
        }),
    };
    let desc = format!("{} (sha256 {})", start_path.display(), crate::io::file_sha256(&start_path)?);
    let tuned_dir = out.join("finetuned");
    let mut trainer = Trainer::new(
        UNet::from_weights(&start, &device),
        &psf,
        &crate::io::file_sha256(&psf_path)?,
        source.as_ref(),
        None,
        cfg.finetune.clone(),
        &desc,
    )?;
    let score_all = |name: &str, net: &UNet| -> Result<Vec<(Score, Array3<f32>)>> {
        scenes.iter().map(|s| score_decoder(s, name, net)).collect()
    };
    let mut curve = Vec::new();
    let (mut first, mut last) = (Vec::new(), Vec::new());
    let mut seconds = 0.0;
    let steps = cfg.finetune.steps;
    while trainer.step() <= steps {
        if trainer.step() % cfg.evaluate_every == 0 || trainer.step() == steps {
            progress(&format!("scoring step {} on the real scenes", trainer.step()), 0);
            let net = UNet::from_weights(&trainer.decoder()?, &device);
            let (scores, images): (Vec<Score>, Vec<Array3<f32>>) =
                score_all(TUNED, &net)?.into_iter().unzip();
            curve.push(CurvePoint { step: trainer.step(), seconds, scores });
            if trainer.step() == 0 {
                first = images.clone();
            }
            last = images;
        }
        if trainer.step() == steps {
            break;
        }
        let clock = std::time::Instant::now();
        let loss = trainer.train_step()?;
        if trainer.step() % cfg.finetune.checkpoint_every == 0 || trainer.step() == steps {
            trainer.evaluate()?;
        }
        seconds += clock.elapsed().as_secs_f64();
        progress(&format!("fine-tuning: loss {loss:.5}"), 1);
    }
    trainer.write_outputs(&tuned_dir)?;
    progress("scoring the paper's decoders", 0);
    let paper = UNet::from_weights(&DecoderWeights::read(&paper_path)?, &device);
    let mut scores = Vec::new();
    for (k, s) in scenes.iter().enumerate() {
        scores.push(score_image(s, CAPTURE, &s.capture)?);
        let at = |step: usize| curve.iter().find(|p| p.step == step).map(|p| p.scores[k].clone());
        scores.extend(at(0).map(|sc| Score { decoder: START.into(), ..sc }));
        scores.extend(at(steps));
        let (score, paper_image) = score_decoder(s, PAPER, &paper)?;
        scores.push(score);
        let capture = s.capture.mapv(|v| v as f32);
        let pictures = [
            ("capture", &capture),
            ("start", &first[k]),
            ("finetuned", &last[k]),
            ("paper_measured_psf", &paper_image),
        ];
        write_pictures(&out.join(&s.name), s, &pictures)?;
        progress("", 1);
    }
    let report = BenchReport {
        data: cfg.data.display().to_string(),
        units: "PSNR in dB; images in units of the capture's clipping level; seconds",
        saturation: SATURATION,
        scenes: scenes.iter().map(|s| s.report.clone()).collect(),
        scores,
        curve,
        steps,
        seconds_per_step: seconds / steps.max(1) as f64,
        training_data: source.describe(),
        history: trainer.history().to_vec(),
    };
    crate::io::atomic::write_json(&out.join("report.json"), &report)?;
    crate::report::decoder_charts::write_bench_chart(&out.join("psnr_vs_steps.png"), &report)?;
    Ok(report)
}
