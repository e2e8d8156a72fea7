//! The decoder on real captures (`doefab bench decoder`): PSNR of reconstructions of scenes
//! captured through the DOE against the HDR merged from a bracket of the same scene taken
//! without it, for any number of decoders and scenes, every decoder of a scene on one footing.
//!
//! Per scene folder (an `exposures.json` listing one frame with `"doe": true` and a bracket
//! without the DOE, as in the paper's data release):
//!
//! 1. The bracket is merged (`crate::calibration::hdr_merge`) into radiance at the listed
//!    reference exposure (value 1 = the sensor's clipping level).
//! 2. The reference is registered onto the *capture* once, through the measured PSF, and the
//!    gain and the pixels scored are fixed ([`crate::calibration::evaluate::prepare`]): every
//!    decoder of the scene is scored against the same warped reference over the same pixels.
//! 3. Each decoder reconstructs the capture ([`crate::decoder::reconstruct::reconstruct`]) with its
//!    negative outputs *kept*, so that PSNR-L charges them (module docs of
//!    [`crate::calibration::evaluate`]); the smallest output is reported. The capture itself is
//!    scored the same way, as the baseline a decoder must beat.
//!
//! A scene that cannot be merged, registered or scored (too little coverage, a missing file)
//! is reported with its reason and the others go on. Optionally the first decoder is
//! fine-tuned on the measured PSF (`crate::decoder::finetune`) and scored along the run.

use std::path::{Path, PathBuf};

use ndarray::Zip;
use serde::Serialize;

use crate::calibration::capture::{read_capture, read_exposures};
use crate::calibration::evaluate::{prepare, Footing, Psnr, Scoring, ScoringOptions};
use crate::calibration::hdr_merge::{merge, MergeOptions};
use crate::decoder::finetune::{FinetuneConfig, HistoryEntry, Trainer, TrainingScenes};
use crate::decoder::reconstruct::{reconstruct, Negatives, ReconstructOptions};
use crate::decoder::unet::UNet;
use crate::decoder::weights::DecoderWeights;
use crate::error::{Allowed, DataCause, Error, Result};
use crate::image::Image;
use crate::optics::psf::Psf;

/// Saturation level of the 8-bit captures, fraction of full scale.
pub const SATURATION: f64 = 0.98;

/// Pixel pitch of the paper's sensor (Canon Rebel T5), metres: the measured PSF's sampling.
pub const SENSOR_PITCH: f64 = 4.29e-6;

/// A scene prepared for scoring.
#[derive(Debug, Clone)]
pub struct SweepScene {
    /// The scene's name: its folder's name.
    pub name: String,
    /// The capture through the DOE (RGB), 1 = clipping level.
    pub capture: Image,
    /// The bracket merged without the DOE, in the bracket's own frame.
    pub reference: Image,
    /// The reference registered onto the capture, the gain and the pixel sets scored.
    pub scoring: Scoring,
    /// How the scene was prepared, as the benchmark's JSON reports it.
    pub preparation: ScenePreparation,
}

/// How a scene was prepared, or why it could not be (part of the sweep's JSON).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScenePreparation {
    /// The scene's name: its folder's name.
    pub name: String,
    /// The scene folder's path.
    pub dir: String,
    /// Path of the capture through the DOE; `None` when the scene was refused.
    pub capture: Option<String>,
    /// Frames of the bracket merged into the reference (0 when the scene was refused).
    pub bracket_frames: usize,
    /// The HDR merge's warnings.
    pub merge_warnings: Vec<String>,
    /// The registration, gain and pixel sets; `None` when the scene was refused.
    pub footing: Option<Footing>,
    /// Why the scene was not scored.
    pub error: Option<String>,
}

/// PSNR of one decoder (or of the capture as it is) on one scene.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Score {
    /// The scene's name.
    pub scene: String,
    /// The decoder scored: its path or `built-in:NAME` as given, [`CAPTURE`] for the capture as it
    /// is, or the fine-tuned decoder's name.
    pub decoder: String,
    /// PSNR over every scored pixel.
    pub all: Psnr,
    /// `None` when the scene's saturated figures are withheld (too few registered).
    pub saturated: Option<Psnr>,
    /// The smallest output over the whole image (the scored pixels' is in `all`).
    pub min_output: f64,
    /// Channel means over the scored, unsaturated pixels over their mean (see
    /// [`crate::calibration::evaluate::Score::channel_balance`]).
    pub channel_balance: Vec<f64>,
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
        return Err(Error::malformed(dir, "holds no scene folder with an exposures.json"));
    }
    Ok(dirs)
}

fn scene_name(dir: &Path) -> String {
    dir.file_name().map_or_else(|| dir.display().to_string(), |n| n.to_string_lossy().into_owned())
}

/// Merges the scene in `dir` and prepares it for scoring through `psf` (steps 1-2 of the
/// module docs).
pub fn prepare_scene(dir: &Path, psf: &Psf, opts: &ScoringOptions) -> Result<SweepScene> {
    let list_path = dir.join("exposures.json");
    let doe = read_exposures(&list_path, true)?;
    let [(capture_path, _)] = doe.frames.as_slice() else {
        return Err(Error::malformed(
            &list_path,
            format!("lists {} frames with \"doe\": true; expected exactly one capture", doe.frames.len()),
        ));
    };
    let bracket = read_exposures(&list_path, false)?;
    let frames = bracket.frames.iter().map(|(p, _)| read_capture(p)).collect::<Result<Vec<_>>>()?;
    let times: Vec<f64> = bracket.frames.iter().map(|f| f.1).collect();
    let merge_opts = MergeOptions {
        saturation: opts.saturation,
        reference_exposure: bracket.reference_exposure,
        ..MergeOptions::default()
    };
    let merged = merge(&frames, &times, None, None, &merge_opts)?;
    let capture = read_capture(capture_path)?.image;
    if capture.dim() != merged.radiance.dim() || capture.channels() != 3 {
        return Err(Error::malformed(
            capture_path,
            format!(
                "is {:?} (rows, cols, channels); the bracket is {:?} and both must be RGB of one size",
                capture.dim(),
                merged.radiance.dim()
            ),
        ));
    }
    let scoring = prepare(&merged.radiance, &capture, Some(psf), opts)
        .map_err(|e| e.reworded(|m| format!("{}: {m}", capture_path.display())))?;
    let clip = scoring.footing.clipping_level;
    let name = scene_name(dir);
    let preparation = ScenePreparation {
        name: name.clone(),
        dir: dir.display().to_string(),
        capture: Some(capture_path.display().to_string()),
        bracket_frames: frames.len(),
        merge_warnings: merged.stats.warnings.clone(),
        footing: Some(scoring.footing.clone()),
        error: None,
    };
    let capture = Image::new(capture.values.mapv(|v| v / clip));
    Ok(SweepScene { name, capture, reference: merged.radiance, scoring, preparation })
}

/// Scores `image` (a reconstruction, or the capture itself) on the scene's footing.
pub fn score_image(scene: &SweepScene, decoder: &str, image: &Image) -> Result<Score> {
    let s = scene.scoring.score(decoder, image)?;
    let min_output = image.values.iter().copied().fold(f64::INFINITY, f64::min);
    Ok(Score {
        scene: scene.name.clone(),
        decoder: decoder.into(),
        all: s.all,
        saturated: s.saturated,
        min_output,
        channel_balance: s.channel_balance,
    })
}

/// Reconstructs the scene's capture with `net` (negatives kept) and scores it; returns the
/// reconstruction too.
pub fn score_decoder(scene: &SweepScene, decoder: &str, net: &UNet) -> Result<(Score, Image<f32>)> {
    let x = scene.capture.to_f32();
    let opts = ReconstructOptions { negatives: Negatives::Keep, ..ReconstructOptions::default() };
    let (y, _) = reconstruct(net, &x, &opts)?;
    Ok((score_image(scene, decoder, &y.to_f64())?, y))
}

/// Exposure of the pictures `run` writes, stops: highlights a few times the clipping level
/// stay visible.
pub const PICTURE_EV: f64 = -2.0;

/// Writes `images` of `scene` as tone-mapped PNGs (sRGB of clip(y 2^[`PICTURE_EV`], 0, 1))
/// into `dir`, each named by its key, with the registered reference (black where it is not
/// scored) as `reference.png`.
fn write_pictures(dir: &Path, scene: &SweepScene, images: &[(String, &Image<f32>)]) -> Result<()> {
    let mut reference = scene.scoring.reference.to_f32();
    Zip::from(reference.values.lanes_mut(ndarray::Axis(2))).and(&scene.scoring.mask).for_each(
        |mut px, &inside| {
            if !inside {
                px.fill(0.0);
            }
        },
    );
    let meta = crate::io::raw_map::Metadata {
        pitch: None,
        unit: None,
        text: vec![
            ("quantity".into(), "linear HDR radiance, 1 = sensor clipping level of the capture".into()),
            ("scene".into(), scene.name.clone()),
            ("tone_map".into(), format!("sRGB of clip(y * 2^{PICTURE_EV}, 0, 1)")),
        ],
    };
    for (name, image) in std::iter::once(("reference".to_string(), &reference)).chain(images.iter().cloned())
    {
        let path = dir.join(format!("{name}.png"));
        crate::io::png::write_png_image_u8(&path, &crate::image::tone::tone_map(image, PICTURE_EV), &meta)?;
    }
    Ok(())
}

/// The fine-tuning part of a sweep.
#[derive(Debug, Clone)]
pub struct FinetuneSweep {
    /// The decoder to start from (a file or `built-in:NAME`).
    pub init: PathBuf,
    /// The fine-tuning's settings (steps, batch, learning rate, ...).
    pub config: FinetuneConfig,
    /// Score the decoder being fine-tuned on the scenes every this many steps.
    pub evaluate_every: usize,
    /// HDR images to fine-tune on (a folder of EXR / Radiance .hdr); `None`: procedural scenes.
    pub train_data: Option<PathBuf>,
}

/// Settings of [`run`].
#[derive(Debug, Clone)]
pub struct SweepConfig {
    /// Scene folders (each with an `exposures.json`).
    pub scenes: Vec<PathBuf>,
    /// Decoders to score: files or `built-in:NAME`.
    pub decoders: Vec<PathBuf>,
    /// The measured PSF (`.npz` or `.npy`, at [`SENSOR_PITCH`]): registration and fine-tuning.
    pub psf: PathBuf,
    /// The array of a `.npz` PSF (the paper's: `psf_val`).
    pub psf_key: Option<String>,
    /// Registration and scoring settings, the same for every scene.
    pub scoring: ScoringOptions,
    /// Fine-tune a decoder on the PSF and score it too.
    pub finetune: Option<FinetuneSweep>,
}

/// The decoder being fine-tuned, scored on the real scenes at one step.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CurvePoint {
    /// Fine-tuning steps done when scored (0: the starting decoder).
    pub step: usize,
    /// Training time up to this step (scoring excluded), seconds.
    pub seconds: f64,
    /// The decoder's score on each scene scored, in scene order.
    pub scores: Vec<Score>,
}

/// The fine-tuning run of a sweep.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FinetuneRun {
    /// The decoder fine-tuning started from: its path or `built-in:NAME` as given.
    pub init: String,
    /// Fine-tuning steps run ([`FinetuneConfig::steps`]).
    pub steps: usize,
    /// Training time per step, seconds: training steps and their validation, scoring on the real
    /// scenes excluded.
    pub seconds_per_step: f64,
    /// What it was trained on: the training scenes' description (real HDR images or procedural
    /// scenes).
    pub training_data: String,
    /// The training images that could not be read and were skipped, each with the reason.
    pub skipped_images: Vec<String>,
    /// The scores along the run of the decoder it would write if stopped there (best validated,
    /// blended; step 0 = the starting decoder).
    pub curve: Vec<CurvePoint>,
    /// The training curve on simulated data (loss, validation PSNR).
    pub history: Vec<HistoryEntry>,
}

/// What `doefab bench decoder` measured (its JSON).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DecoderSweepResults {
    /// The measured PSF's file, as given.
    pub psf: String,
    /// What the numbers are in: PSNR in dB, images in units of the capture's clipping level, times
    /// in seconds.
    pub units: &'static str,
    /// How negative outputs are scored: as they are in PSNR-L, as 0 in PSNR-gamma.
    pub negatives: &'static str,
    /// Saturation level, fraction of the capture's clipping level: a pixel with any channel at
    /// or above it is saturated.
    pub saturation: f64,
    /// Smallest fraction of the image (0..1) the registration must cover; below it a scene is
    /// refused.
    pub min_coverage: f64,
    /// Every scene, scored or refused (with the reason).
    pub scenes: Vec<ScenePreparation>,
    /// The decoders in order: the capture as it is, the given decoders, the fine-tuned one.
    pub decoders: Vec<String>,
    /// Decoder x scene, scene-major, for the scenes scored.
    pub scores: Vec<Score>,
    /// The fine-tuning run, scored along; `None` without fine-tuning.
    pub finetune: Option<FinetuneRun>,
}

/// Name of the capture scored as it is.
pub const CAPTURE: &str = "capture as it is";

/// A file-name stem for a decoder's picture: its file stem or built-in name, made unique.
fn picture_name(decoder: &Path, taken: &mut Vec<String>) -> String {
    let text = decoder.to_string_lossy();
    let base = match text.strip_prefix("built-in:") {
        Some(n) => n.to_string(),
        None => decoder.file_stem().map_or_else(|| "decoder".into(), |s| s.to_string_lossy().into_owned()),
    };
    let clean: String = base
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' })
        .collect();
    let mut name = clean.clone();
    let mut k = 2;
    while taken.contains(&name) || ["reference", "capture", "finetuned"].contains(&name.as_str()) {
        name = format!("{clean}-{k}");
        k += 1;
    }
    taken.push(name.clone());
    name
}

/// Runs the sweep: prepares every scene (a scene that fails is reported with its reason),
/// scores the capture and every decoder on each scene, and with `finetune` fine-tunes its
/// initial decoder on the PSF, scoring it along the run. Writes into `out`: `report.json`, per
/// scene `<scene>/*.png` (the registered reference, the capture and each reconstruction
/// tone-mapped at [`PICTURE_EV`]) and, with fine-tuning, `finetuned/` (decoder, training
/// record); the charts are the command's ([`crate::pipeline::sweep::sweep_decoder`]).
/// `progress` is told what is happening and each unit of work done. Refuses when no scene can
/// be scored.
pub fn run(
    cfg: &SweepConfig,
    out: &Path,
    progress: &mut dyn FnMut(&str, u64),
) -> Result<DecoderSweepResults> {
    if cfg.scenes.is_empty() {
        return Err(Error::param("scenes", "no scene folder given"));
    }
    if let Some(f) = &cfg.finetune {
        if f.evaluate_every == 0 {
            return Err(Error::param_in("evaluate_every", Allowed::at_least(1.0), "must be at least 1 step"));
        }
    }
    let device = crate::decoder::device(false)?;
    let nets = cfg
        .decoders
        .iter()
        .map(|p| Ok(UNet::from_weights(&DecoderWeights::read(p)?, &device)))
        .collect::<Result<Vec<_>>>()?;
    let psf = Psf::read(&cfg.psf, cfg.psf_key.as_deref(), Some(SENSOR_PITCH))?;
    let mut scenes = Vec::new();
    let mut reports = Vec::new();
    for d in &cfg.scenes {
        progress(&format!("merging and registering {}", d.display()), 0);
        match prepare_scene(d, &psf, &cfg.scoring) {
            Ok(s) => {
                reports.push(s.preparation.clone());
                scenes.push(s);
            }
            Err(e) => reports.push(ScenePreparation {
                name: scene_name(d),
                dir: d.display().to_string(),
                capture: None,
                bracket_frames: 0,
                merge_warnings: Vec::new(),
                footing: None,
                error: Some(e.to_string()),
            }),
        }
        progress("", 1);
    }
    if scenes.is_empty() {
        let why: Vec<String> =
            reports.iter().map(|r| format!("{}: {}", r.name, r.error.as_deref().unwrap_or("?"))).collect();
        return Err(Error::data(DataCause::Empty, format!("no scene could be scored: {}", why.join("; "))));
    }
    let mut names = vec![CAPTURE.to_string()];
    names.extend(cfg.decoders.iter().map(|p| p.display().to_string()));
    let mut taken = Vec::new();
    let stems: Vec<String> = cfg.decoders.iter().map(|p| picture_name(p, &mut taken)).collect();
    // Scores and pictures per scene, in decoder order.
    let mut scores: Vec<Vec<Score>> = Vec::new();
    let mut images: Vec<Vec<(String, Image<f32>)>> = Vec::new();
    for s in &scenes {
        progress(&format!("scoring the decoders on {}", s.name), 0);
        let mut sc = vec![score_image(s, CAPTURE, &s.capture)?];
        let mut im = vec![("capture".to_string(), s.capture.to_f32())];
        for ((net, name), stem) in nets.iter().zip(&names[1..]).zip(&stems) {
            let (score, y) = score_decoder(s, name, net)?;
            sc.push(score);
            im.push((stem.clone(), y));
        }
        scores.push(sc);
        images.push(im);
        progress("", 1);
    }
    let finetune = match &cfg.finetune {
        Some(f) => {
            let (report, last) = run_finetune(f, cfg, &psf, &scenes, &device, out, progress)?;
            let name = format!("fine-tuned here ({} steps from {})", report.steps, report.init);
            names.push(name.clone());
            for (k, y) in last.into_iter().enumerate() {
                let point = report.curve.last().map(|p| p.scores[k].clone());
                scores[k].extend(point.map(|sc| Score { decoder: name.clone(), ..sc }));
                images[k].push(("finetuned".into(), y));
            }
            Some(report)
        }
        None => None,
    };
    for (s, im) in scenes.iter().zip(&images) {
        let refs: Vec<(String, &Image<f32>)> = im.iter().map(|(n, y)| (n.clone(), y)).collect();
        write_pictures(&out.join(&s.name), s, &refs)?;
    }
    let report = DecoderSweepResults {
        psf: cfg.psf.display().to_string(),
        units: "PSNR in dB; images in units of the capture's clipping level; seconds",
        negatives:
            "reconstructions scored as the network writes them: negative outputs count as they are in \
                    PSNR-L and as 0 in PSNR-gamma",
        saturation: cfg.scoring.saturation,
        min_coverage: cfg.scoring.min_coverage,
        scenes: reports,
        decoders: names,
        scores: scores.into_iter().flatten().collect(),
        finetune,
    };
    crate::io::atomic::write_json(&out.join("report.json"), &report)?;
    Ok(report)
}

/// Fine-tunes `f.init` on `psf`, scoring on `scenes` every `f.evaluate_every` steps and at
/// the end the decoder the run would write if it stopped there; writes `finetuned/`. Returns
/// the run's report and the last reconstructions.
fn run_finetune(
    f: &FinetuneSweep,
    cfg: &SweepConfig,
    psf: &Psf,
    scenes: &[SweepScene],
    device: &burn::tensor::Device,
    out: &Path,
    progress: &mut dyn FnMut(&str, u64),
) -> Result<(FinetuneRun, Vec<Image<f32>>)> {
    let start = DecoderWeights::read(&f.init)?;
    // Real images as `finetune` takes them by default: its hold-out validates, narrow
    // panoramas left out.
    let training = TrainingScenes::new(
        f.train_data.as_deref(),
        None,
        crate::decoder::dataset::HOLDOUT_EVERY,
        crate::decoder::dataset::MIN_PANORAMA_WIDTH,
        crate::decoder::dataset::WHITE_BALANCE,
    )?;
    let (source, validation) = training.sources();
    let init = f.init.display().to_string();
    let desc = format!("{init} (sha256 {})", crate::decoder::weights::decoder_sha256(&f.init)?);
    let mut trainer = Trainer::new(
        UNet::from_weights(&start, device),
        psf,
        &crate::io::file_sha256(&cfg.psf)?,
        source,
        validation,
        f.config.clone(),
        &desc,
    )?;
    let name = "fine-tuned here";
    let mut curve = Vec::new();
    let mut last = Vec::new();
    let mut seconds = 0.0;
    let steps = f.config.steps;
    loop {
        if trainer.step() % f.evaluate_every == 0 || trainer.step() == steps {
            progress(&format!("scoring step {} on the real scenes", trainer.step()), 0);
            // The decoder the run would write if it stopped here (the best validated weights,
            // blended), the one `finetuned/` receives at the end; not the raw current weights.
            let net = UNet::from_weights(&trainer.written_decoder()?.0, device);
            let (sc, im): (Vec<Score>, Vec<Image<f32>>) = scenes
                .iter()
                .map(|s| score_decoder(s, name, &net))
                .collect::<Result<Vec<_>>>()?
                .into_iter()
                .unzip();
            curve.push(CurvePoint { step: trainer.step(), seconds, scores: sc });
            last = im;
        }
        if trainer.step() >= steps {
            break;
        }
        let clock = std::time::Instant::now();
        let loss = trainer.train_step()?;
        if trainer.step() % f.config.checkpoint_every == 0 || trainer.step() == steps {
            trainer.evaluate()?;
        }
        seconds += clock.elapsed().as_secs_f64();
        progress(&format!("fine-tuning: loss {loss:.5}"), 1);
    }
    trainer.write_outputs(&out.join("finetuned"))?;
    let report = FinetuneRun {
        init,
        steps,
        seconds_per_step: seconds / steps.max(1) as f64,
        training_data: source.describe(),
        skipped_images: training.warnings(),
        curve,
        history: trainer.history().to_vec(),
    };
    Ok((report, last))
}
