//! `doefab demo`: every stage on the built-in example design, no input needed.
//!
//! Below the output folder:
//!
//! 1. *Fabrication*: the three bundled recipes of `masks/` ([`RECIPES`]), each into a folder of
//!    its name ([`crate::fabrication::recipe_run::run_recipe`]).
//! 2. *Optics*: `psf/`, the design's RGB PSF as the automatic plan chooses it
//!    ([`crate::optics::plan`]).
//! 3. *Metrology*: `metrology/scan.x3p`, a synthetic scan of the part the 8-level recipe makes
//!    (a cast: mirrored, complemented, 5 % too shallow, blurred by 2 um, tilted, noisy, 10 %
//!    missing), compared with the design into `metrology/compare/`
//!    ([`crate::pipeline::compare::compare_scan`]).
//! 4. *The fabrication loop*: `precompensate/`, closed in simulation on the grayscale master
//!    (see [`loop_process`]): the plain mask's part scanned (`scan_before.x3p`), the next mask
//!    pre-compensated from that scan alone (`mask/`, [`crate::pipeline::precompensate::run`]),
//!    its part scanned through the same process (`scan_after.x3p`), both compared with the
//!    design (`difference_before.png`, `difference_after.png`, `loop.json`), and the gain
//!    against the process's blur on a 320-sample version of the design (`gain.png`, `gain.svg`).
//! 5. *Calibration*: `calibration/bracket/`, a synthetic 8-bit pinhole bracket of the simulated
//!    PSF, calibrated back into `calibration/psf/` as `calibrate-psf --crop 319 --centre peak`
//!    does; reports the relative L2 of the result against the simulated PSF ([`window_at_peak`]).
//! 6. *Decoder*: `decoder/`, two fine-tuning steps of the paper's simulated-PSF decoder with the
//!    calibrated PSF on procedural scenes, and the reconstruction of a capture of a procedural
//!    scene simulated through that PSF. The paper's weights are compiled into the binary
//!    ([`crate::decoder::default_init`]), so every stage runs on a fresh machine.
//!
//! Every stage is seeded: the same build writes the same bytes.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::calibration::psf_extract::{self as pe, PsfCalibration};
use crate::decoder::finetune::HistoryEntry;
use crate::decoder::reconstruct::ReconstructOutcome;
use crate::error::{DataCause, Error, Result};
use crate::fabrication::recipe::Recipe;
use crate::fabrication::recipe_run::{self, ChainParams, DesignSource, FabOptions, FabOutcome, LoadedDesign};
use crate::optics::psf::Psf;
use crate::optics::psf_files::PsfOutcome;
use crate::pipeline::compare::CompareOutcome;

/// The bundled recipes (`masks/NAME.toml`) the demo runs, in order.
pub const RECIPES: [&str; 3] = ["laser-writer-grayscale", "binary-3mask-8level", "two-photon-stl"];

/// The recipe whose part the metrology stage scans.
const SCANNED_RECIPE: &str = "binary-3mask-8level";

/// Sensor pixel pitch of the simulated and calibrated PSFs, metres (the paper's 4.29 um).
const SENSOR_PITCH: f64 = 4.29e-6;

/// Side of the calibrated PSF, pixels (the paper's measured PSF is 319 x 319).
const CALIBRATED_CROP: usize = 319;

/// Fine-tuning steps of the decoder stage.
const FINETUNE_STEPS: usize = 2;

/// Progress steps of the stages after fabrication: the PSF; the scan and the four steps of
/// the comparison; the bracket and its calibration; the fine-tuning steps and the
/// reconstruction.
const PSF_STEPS: u64 = 1;
const METROLOGY_STEPS: u64 = 5;
const LOOP_STEPS: u64 = 5 + SWEEP_BLURS.len() as u64;
const CALIBRATION_STEPS: u64 = 2;
const DECODER_STEPS: u64 = FINETUNE_STEPS as u64 + 1;

/// What the demo did, stage by stage (the `--json` output of `doefab demo`).
#[derive(Debug, Clone, Serialize)]
pub struct DemoOutcome {
    /// One outcome per recipe of [`RECIPES`], in order.
    pub fabrication: Vec<FabOutcome>,
    /// The optics stage: the design's RGB PSF (`psf/`), as `doefab psf` reports it.
    pub psf: PsfOutcome,
    /// The metrology stage: the synthetic scan of the 8-level part against the design
    /// (`metrology/compare/`), as `doefab compare` reports it.
    pub metrology: CompareOutcome,
    /// The fabrication loop stage (`precompensate/`).
    pub fabrication_loop: LoopStage,
    /// The calibration stage (`calibration/`).
    pub calibration: CalibrationStage,
    /// The decoder stage (`decoder/`).
    pub decoder: DecoderStage,
    /// Where each stage wrote.
    #[serde(skip)]
    pub folders: Folders,
}

/// The folders and files the stages wrote, for a summary.
#[derive(Debug, Clone, Default)]
pub struct Folders {
    /// Each recipe's name and output folder, in the order of [`RECIPES`].
    pub fabrication: Vec<(String, PathBuf)>,
    /// The design's PSF (`psf/`).
    pub psf: PathBuf,
    /// The synthetic scan of the 8-level part (`metrology/scan.x3p`).
    pub scan: PathBuf,
    /// The scan's comparison with the design (`metrology/compare/`).
    pub compare: PathBuf,
    /// The fabrication loop (`precompensate/`).
    pub fabrication_loop: PathBuf,
}

/// The calibration stage: where the bracket and the calibrated PSF are, and how close the
/// calibrated PSF is to the simulated one.
#[derive(Debug, Clone, Serialize)]
pub struct CalibrationStage {
    /// Folder of the synthetic 8-bit pinhole bracket: the frames, `dark.png` and
    /// `exposures.json`.
    pub bracket: PathBuf,
    /// Folder of the calibrated PSF (`psf.npy`, `psf.exr`, `psf.json`, ...).
    pub psf: PathBuf,
    /// Per channel, `||c - s|| / ||s||` ([`Psf::relative_l2`]) of the calibrated PSF `c`
    /// against the simulated PSF's window of the same size around its peak, `s`
    /// ([`window_at_peak`]), each summing to 1. Not [`crate::optics::psf_compare::compare`]: that
    /// one crops to the centred common window and aligns the centroids first.
    pub relative_l2_to_simulated: Vec<f64>,
    /// What the calibration reported, as `calibrate-psf` writes it into `psf.json`.
    pub report: PsfCalibration,
}

/// The decoder stage: the fine-tuned decoder, its training curve and the reconstruction.
#[derive(Debug, Clone, Serialize)]
pub struct DecoderStage {
    /// The fine-tuned decoder's weights (`finetune/decoder.safetensors`).
    pub decoder: PathBuf,
    /// The training curve, one entry per logged step.
    pub history: Vec<HistoryEntry>,
    /// The reconstruction of the simulated capture (`capture.png` -> `reconstruction.exr` and
    /// `.png`).
    pub reconstruction: ReconstructOutcome,
}

impl DecoderStage {
    /// Fine-tuning steps taken.
    pub fn steps(&self) -> usize {
        self.history.last().map_or(0, |h| h.step)
    }
}

/// Counts finished steps towards the total and passes them on.
struct Progress<'a> {
    done: u64,
    total: u64,
    report: &'a mut dyn FnMut(&str, u64, u64),
}

impl Progress<'_> {
    /// Reports `message` (what runs now) at the current count.
    fn show(&mut self, message: &str) {
        (self.report)(message, self.done, self.total);
    }

    /// Counts one more step done and reports `message`.
    fn step(&mut self, message: &str) {
        self.done = (self.done + 1).min(self.total);
        self.show(message);
    }
}

/// Runs every stage into `output` (see the module docs). `progress(message, done, total)` is
/// called as the work goes on, `done` counting finished steps of `total`.
pub fn run(output: &Path, progress: &mut dyn FnMut(&str, u64, u64)) -> Result<DemoOutcome> {
    let recipes = RECIPES
        .iter()
        .map(|name| Ok((name.to_string(), Recipe::read(Path::new(&format!("built-in:{name}")))?)))
        .collect::<Result<Vec<_>>>()?;
    let fab_steps: u64 = recipes.iter().map(|(_, r)| recipe_run::step_count(r) as u64).sum();
    let total = fab_steps + PSF_STEPS + METROLOGY_STEPS + LOOP_STEPS + CALIBRATION_STEPS + DECODER_STEPS;
    let mut p = Progress { done: 0, total, report: progress };
    let source = DesignSource::BuiltIn("paper".into());
    let mut folders = Folders::default();

    let mut fabrication = Vec::new();
    for (name, recipe) in &recipes {
        let out = output.join(name);
        let report = recipe_run::run_recipe(
            &source,
            recipe,
            &out,
            &FabOptions { intermediates: true, ..Default::default() },
            &mut |step: &str| p.step(&format!("{name}: {step}")),
        )?;
        fabrication.push(report);
        folders.fabrication.push((name.clone(), out));
    }

    let design = recipe_run::load_design(&source)?;
    folders.psf = output.join("psf");
    let psf = design_psf(&design, &folders.psf, &mut p)?;

    let scanned = recipes.iter().find(|(n, _)| n == SCANNED_RECIPE).map(|(_, r)| r);
    let scanned =
        scanned.ok_or_else(|| Error::internal(format!("the demo has no recipe {SCANNED_RECIPE}")))?;
    let metro = output.join("metrology");
    folders.scan = metro.join("scan.x3p");
    folders.compare = metro.join("compare");
    let params = ChainParams::of_recipe(scanned, false);
    let metrology = scan_and_compare(&design, &source, &params, &folders.scan, &folders.compare, &mut p)?;

    folders.fabrication_loop = output.join("precompensate");
    let grayscale = &recipes[0].1;
    let fabrication_loop = close_the_loop(&design, &source, grayscale, &folders.fabrication_loop, &mut p)?;

    let calibration = calibrate(&folders.psf, &output.join("calibration"), &mut p)?;

    let init = crate::decoder::default_init();
    let decoder = fine_tune(&init, &calibration.psf.join("psf.npy"), &output.join("decoder"), &mut p)?;
    Ok(DemoOutcome { fabrication, psf, metrology, fabrication_loop, calibration, decoder, folders })
}

/// The optics stage: the design's RGB PSF as the plan chooses it, into `out`.
fn design_psf(design: &LoadedDesign, out: &Path, p: &mut Progress) -> Result<PsfOutcome> {
    use crate::optics::{plan, psf_files};
    let system = psf_files::system_for(&design.heights);
    let plan = plan::plan(&system, &design.heights, &[], plan::DEFAULT_TOLERANCE)?;
    p.show(&format!("PSF of the built-in design by {}", plan.method));
    let psf = psf_files::plan_and_write(&design.heights, &plan, &[], out, &mut |_| {})?;
    p.step("PSF written");
    Ok(psf)
}

/// The metrology stage: a synthetic scan of the part `params` makes of `design` (see the
/// module docs) written to `scan`, then compared with the design into `out`, with the design
/// and as-fabricated PSFs by the matrix DFT (run past its validity guard, with warnings).
fn scan_and_compare(
    design: &LoadedDesign,
    source: &DesignSource,
    params: &ChainParams,
    scan: &Path,
    out: &Path,
    p: &mut Progress,
) -> Result<CompareOutcome> {
    use crate::metrology::synthetic_scan::{simulate_scan, write_scan, SimulateParams};
    p.show("simulated scan of the 8-level part");
    let (part, _, _) = crate::pipeline::compare::reference_surface(design, Some(params))?;
    let sp = SimulateParams::typical_cast();
    if let Some(dir) = scan.parent() {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    write_scan(scan, &simulate_scan(&part, &sp)?)?;
    p.step("scan written");
    let psf_opts = crate::optics::Options { allow_invalid: true, ..Default::default() };
    let scan = crate::pipeline::compare::ScanSource::File(scan.to_path_buf(), Default::default());
    let report = crate::pipeline::compare::compare_scan(
        &scan,
        source,
        Some(params),
        None,
        Some((crate::optics::Method::MatrixDft, &psf_opts)),
        out,
        &mut |s: &str| p.step(s),
    )?;
    Ok(report)
}

/// How much the demo's resist response bows: `c + LOOP_BOW c (P - c) / P` over the period `P`.
/// Mild: with the demo's blur, a bow of 10 % or 25 % lowers the part's correlation with the
/// design over the aperture's interior to 0.949 or 0.946 where the scan's noise allows 0.999,
/// and the trust rule (Pearson's correlation, linear in the heights) refuses the scan.
pub const LOOP_BOW: f64 = 0.03;

/// The process of the demo's fabrication loop, the truth the correction never sees: a resist
/// whose response bows ([`LOOP_BOW`]), a part 8 % too shallow, a lateral blur of 1.5 design
/// samples, scanned with a small pose error, 10 nm of noise and 5 % of samples missing.
pub fn loop_process(period: f64, pitch: f64) -> Result<crate::metrology::synthetic_scan::SimulateParams> {
    use crate::fabrication::precompensate::Response;
    let c: Vec<f64> = (0..=8).map(|k| k as f64 * period / 8.0).collect();
    let m = c.iter().map(|c| c + LOOP_BOW * c * (period - c) / period).collect();
    Ok(crate::metrology::synthetic_scan::SimulateParams {
        response: Some(Response::new(c, m)?),
        depth_scale: 0.92,
        blur: 1.5 * pitch,
        pose: crate::metrology::scan_registration::Pose {
            mirror: false,
            rotation: 0.1f64.to_radians(),
            scale: 1.0,
            shift: [1.3e-6, -0.8e-6],
        },
        noise: 10e-9,
        missing: 0.05,
        ..Default::default()
    })
}

/// [`loop_process`] in words, from its parameters.
fn describe_process(p: &crate::metrology::synthetic_scan::SimulateParams, pitch: f64) -> String {
    format!(
        "bowed response (c + {LOOP_BOW} c (P - c) / P), depth scale {:.3}, blur {:.2} samples, {:.2} deg and \
         ({:.2}, {:.2}) um pose error, {:.1} nm noise, {:.1}% missing",
        p.depth_scale,
        p.blur / pitch,
        p.pose.rotation.to_degrees(),
        p.pose.shift[0] * 1e6,
        p.pose.shift[1] * 1e6,
        p.noise * 1e9,
        p.missing * 100.0
    )
}

/// Blur widths (design samples) of the loop's gain chart.
pub const SWEEP_BLURS: [f64; 6] = [0.5, 1.0, 1.5, 2.0, 3.0, 4.0];

/// One side of the loop: the part of the plain or of the pre-compensated mask against the design.
#[derive(Debug, Clone, Serialize)]
pub struct LoopSide {
    /// The simulated scan of the part.
    pub scan: PathBuf,
    /// RMS of part - design over the aperture, metres.
    pub rms_error: f64,
    /// The fitted depth scale of the part.
    pub depth_scale: f64,
    /// Design-order efficiency per wavelength at that depth scale.
    pub efficiency: Vec<crate::metrology::scan_compare::EfficiencyLoss>,
    /// PSF relative L2 against the design's, per channel.
    pub psf_relative_l2: Vec<f64>,
}

/// The fabrication loop stage (module docs).
#[derive(Debug, Clone, Serialize)]
pub struct LoopStage {
    /// The simulated process, in words.
    pub process: String,
    /// What `precompensate` wrote and predicted.
    pub precompensate: crate::pipeline::precompensate::PrecompensateOutcome,
    /// The plain mask's part against the design.
    pub before: LoopSide,
    /// The pre-compensated mask's part against the design.
    pub after: LoopSide,
    /// The loop at each blur of [`SWEEP_BLURS`] on the 320-sample design.
    pub sweep: Vec<crate::pipeline::precompensate::SweepPoint>,
}

/// The fabrication loop (module docs) into `out`.
fn close_the_loop(
    design: &LoadedDesign,
    source: &DesignSource,
    recipe: &Recipe,
    out: &Path,
    p: &mut Progress,
) -> Result<LoopStage> {
    use crate::charts::metrology::{height_map, Palette};
    use crate::metrology::scan_compare::{compare, CompareOptions, Comparison};
    use crate::metrology::synthetic_scan::{simulate_scan, write_scan};
    use crate::pipeline::precompensate::{self as pc, blur_sweep, ModelSource, PrecompensateJob};
    let params = ChainParams::of_recipe(recipe, false);
    let (target, levels, optics) = crate::pipeline::compare::reference_surface(design, Some(&params))?;
    let process = loop_process(params.wrap_spec()?.period()?, design.heights.pitch()[0])?;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    p.show("the plain mask's part, scanned");
    let scan_before = out.join("scan_before.x3p");
    write_scan(&scan_before, &simulate_scan(&target, &process)?)?;
    p.step("scan of the plain part written");
    let job = PrecompensateJob {
        design: source.clone(),
        recipe: recipe.clone(),
        model: ModelSource::Scan { path: scan_before.clone(), options: Default::default() },
        corrections: Default::default(),
        aperture: None,
        force: false,
    };
    let mask = out.join("mask");
    let report = pc::run(&job, &mask, &mut |s: &str| p.show(s))?;
    p.step("pre-compensated mask written");
    let commanded = crate::io::heightmap::read_heightmap(&mask.join("commanded.exr"), &Default::default())?;
    let scan_after = out.join("scan_after.x3p");
    write_scan(&scan_after, &simulate_scan(&commanded, &process)?)?;
    p.step("scan of the pre-compensated part written");
    let opts = CompareOptions {
        aperture: Some(crate::design::PAPER_APERTURE),
        levels,
        optics,
        ..Default::default()
    };
    let psf_opts = crate::optics::Options { allow_invalid: true, ..Default::default() };
    let mut system = crate::optics::psf_files::system_for(&target);
    system.aperture = crate::design::PAPER_APERTURE;
    let mut side = |scan: &Path, name: &str| -> Result<LoopSide> {
        let s = crate::io::scan::read_scan(scan, &Default::default())?;
        let c: Comparison = compare(&target, &s.grid, &opts)?;
        height_map(
            &out.join(format!("difference_{name}.png")),
            &c.difference,
            &format!("part - design, {name}"),
            Palette::Diverging,
        )?;
        let psf = crate::pipeline::compare::psf_comparison(
            &target,
            &c.surface,
            &system,
            crate::optics::Method::MatrixDft,
            &psf_opts,
        )?;
        p.step(&format!("part {name} pre-compensation compared"));
        Ok(LoopSide {
            scan: scan.to_path_buf(),
            rms_error: c.rms_error,
            depth_scale: c.model.depth_scale,
            efficiency: c.efficiency,
            psf_relative_l2: psf.channels.iter().map(|c| c.relative_l2).collect(),
        })
    };
    let before = side(&scan_before, "before")?;
    let after = side(&scan_after, "after")?;
    // The sweep on a 320-sample version of the built-in design (the same grating and pitch,
    // an aperture of 0.9 x 320 samples whose edge fixes the registration).
    let n = 320;
    let pitch = crate::design::PAPER_PITCH;
    let ep =
        crate::design::ExampleParams { samples: n, aperture: 0.9 * n as f64 * pitch, ..Default::default() };
    let small = LoadedDesign {
        heights: crate::design::paper_example(&ep)?,
        name: "built-in:paper at 320 samples".into(),
        sha256: String::new(),
    };
    let aperture = Some(0.85 * n as f64 * pitch);
    let small_opts = CompareOptions { aperture, levels, optics: opts.optics.clone(), ..Default::default() };
    let sweep = blur_sweep(&small, &params, &process, &small_opts, &SWEEP_BLURS, &mut |s: &str| p.step(s))?;
    let points: Vec<crate::charts::fabrication::GainPoint> = sweep
        .iter()
        .map(|s| crate::charts::fabrication::GainPoint {
            blur_samples: s.blur_samples,
            rms: [s.rms_before, s.rms_after],
            psf: [s.psf_before, s.psf_after],
        })
        .collect();
    crate::charts::fabrication::precompensation_gain(&out.join("gain.png"), &points)?;
    let process = describe_process(&process, design.heights.pitch()[0]);
    let stage = LoopStage { process, precompensate: report, before, after, sweep };
    crate::io::atomic::write_json(&out.join("loop.json"), &stage)?;
    Ok(stage)
}

/// The calibration stage: a synthetic pinhole bracket of the simulated PSF in `psf_dir`
/// (8-bit PNGs, `exposures.json` and a dark frame in `out/bracket`), merged and calibrated
/// back into `out/psf`, and compared with the simulated PSF.
fn calibrate(psf_dir: &Path, out: &Path, p: &mut Progress) -> Result<CalibrationStage> {
    use crate::calibration::{capture, hdr_merge};
    let simulated = Psf::read(&psf_dir.join("psf.npy"), None, Some(SENSOR_PITCH))?;
    p.show("synthetic pinhole bracket of the simulated PSF");
    let (frames, times, dark) = pe::simulate_pinhole_bracket(&simulated, 60, 12, 0.002, 0.03, 1);
    let bracket = out.join("bracket");
    let mut list = Vec::new();
    for (k, (f, t)) in frames.iter().zip(&times).enumerate() {
        let name = format!("pinhole_{k:02}.png");
        capture::write_capture(&bracket.join(&name), f, 8)?;
        list.push(serde_json::json!({ "file": name, "exposure_s": t }));
    }
    capture::write_capture(&bracket.join("dark.png"), &dark, 8)?;
    crate::io::atomic::write_json(&bracket.join("exposures.json"), &serde_json::json!({ "frames": list }))?;
    p.step("calibrate-psf");
    let read = capture::read_exposures(&bracket.join("exposures.json"), false)?;
    let captures = read.frames.iter().map(|(f, _)| capture::read_capture(f)).collect::<Result<Vec<_>>>()?;
    let dark = hdr_merge::mean_dark(&[capture::read_capture(&bracket.join("dark.png"))?])?;
    let merge_opts = hdr_merge::MergeOptions { estimate_times: false, ..Default::default() };
    let merged = hdr_merge::merge(&captures, &times, Some(&dark), None, &merge_opts)?;
    let opts = pe::PsfOptions { crop: CALIBRATED_CROP, centre: pe::Centre::Peak, ..Default::default() };
    let (psf, mut report) = pe::calibrate_psf(&merged, &opts)?;
    let psf_out = out.join("psf");
    pe::write_calibration(&psf, &merged, &mut report, &psf_out)?;
    p.step("calibrated");
    let relative_l2_to_simulated = psf.relative_l2(&window_at_peak(&simulated, CALIBRATED_CROP)?)?;
    Ok(CalibrationStage { bracket, psf: psf_out, relative_l2_to_simulated, report })
}

/// The `size` x `size` window of `psf` whose centre pixel, `(size - 1) / 2` (rounded down),
/// is the peak of the channel sum (the first maximum in row-major order), each channel
/// renormalised to sum 1 over the window: what `calibrate-psf --centre peak --crop size`
/// keeps of a pinhole image of `psf`, to compare its output with. Refused where the window
/// would leave the PSF.
pub fn window_at_peak(psf: &Psf, size: usize) -> Result<Psf> {
    let (h, w) = psf.dim();
    let (mut peak, mut best) = ((0, 0), f64::NEG_INFINITY);
    for i in 0..h {
        for j in 0..w {
            let v: f64 = psf.channels.iter().map(|c| c.grid.values()[[i, j]]).sum();
            if v > best {
                (peak, best) = ((i, j), v);
            }
        }
    }
    let before = (size.max(1) - 1) / 2;
    let (pi, pj) = peak;
    if pi < before || pj < before || pi - before + size > h || pj - before + size > w {
        return Err(Error::data(
            DataCause::OutOfRange,
            format!(
                "the PSF's peak at ({pi}, {pj}) is too close to the border of its {h} x {w} window for a \
             {size} x {size} window around it"
            ),
        ));
    }
    let (rows, cols) = (pi - before..pi - before + size, pj - before..pj - before + size);
    let channels = psf
        .channels
        .iter()
        .map(|c| {
            let grid = c.grid.crop(rows.clone(), cols.clone())?;
            Ok(crate::optics::psf::Channel { grid, ..c.clone() })
        })
        .collect::<Result<Vec<_>>>()?;
    Psf::new(channels, &psf.method)
}

/// The decoder stage: fine-tunes the paper's decoder `init` with the PSF at `psf_path` on
/// procedural scenes into `out/finetune`, then reconstructs a capture simulated through that
/// PSF (`out/capture.png` -> `out/reconstruction.exr` and `.png`).
fn fine_tune(init: &Path, psf_path: &Path, out: &Path, p: &mut Progress) -> Result<DecoderStage> {
    use crate::decoder::{finetune as ft, measurement, reconstruct as rc, scenes};
    let psf = Psf::read(psf_path, None, Some(SENSOR_PITCH))?;
    let psf_sha = crate::io::file_sha256(psf_path)?;
    let source = ft::procedural_scenes();
    let cfg = ft::FinetuneConfig {
        steps: FINETUNE_STEPS,
        batch: 1,
        crop: 64,
        validation: 1,
        checkpoint_every: FINETUNE_STEPS,
        grad_clip: ft::GRAD_CLIP,
        ..Default::default()
    };
    let device = crate::decoder::device(false)?;
    let net = crate::decoder::unet::UNet::from_weights(
        &crate::decoder::weights::DecoderWeights::read(init)?,
        &device,
    );
    let desc = format!("{} (sha256 {})", init.display(), crate::decoder::weights::decoder_sha256(init)?);
    let mut trainer = ft::Trainer::new(net, &psf, &psf_sha, &source, None, cfg, &desc)?;
    let message = format!("fine-tuning the decoder on the calibrated PSF ({FINETUNE_STEPS} steps)");
    p.show(&message);
    let ft_dir = out.join("finetune");
    trainer.run(&ft_dir, &mut |_| p.step(&message))?;
    trainer.write_outputs(&ft_dir)?;
    crate::charts::training::write_training_chart(&ft_dir.join("training_curve.png"), trainer.history())?;
    p.show("reconstructing a simulated capture");
    let (kh, kw) = psf.dim();
    let size = 256;
    let conv = crate::optics::convolve::Convolver::new(&psf, (size + kh - 1, size + kw - 1))?;
    let scene = scenes::procedural_scene(7, size + kh - 1, size + kw - 1);
    let m = measurement::measure(
        &scene,
        &conv,
        &measurement::MeasurementModel::default(),
        &mut crate::rng::Lcg(7),
    )?;
    let capture = out.join("capture.png");
    crate::calibration::capture::write_capture(&capture, &m.capture.to_f64(), 8)?;
    let decoder = ft_dir.join(ft::DECODER);
    let reconstruction = rc::reconstruct_file(
        &capture,
        &decoder,
        &out.join("reconstruction.exr"),
        &out.join("reconstruction.png"),
        0.0,
        &rc::ReconstructOptions::default(),
        &device,
    )?;
    p.step("reconstructed");
    Ok(DecoderStage { decoder, history: trainer.history().to_vec(), reconstruction })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::{Grid, Unit};
    use crate::optics::psf::Channel;
    use ndarray::Array2;

    /// A 3-channel 9 x 11 PSF whose channel sum peaks at `peak` (row, col), while each
    /// channel alone peaks elsewhere.
    fn psf_peaking_at(peak: (usize, usize)) -> Psf {
        let channels = (0..3)
            .map(|c| {
                let mut v = Array2::from_shape_fn((9, 11), |(i, j)| 1.0 + (i * 11 + j) as f64 * 1e-3);
                v[peak] += 5.0;
                v[[c * 3, 10 - c]] += 6.0;
                Channel {
                    name: format!("C{c}"),
                    wavelength: None,
                    grid: Grid::new(v, [2e-6, 2e-6], Unit::Dimensionless).unwrap(),
                    captured: None,
                }
            })
            .collect();
        Psf::new(channels, "test").unwrap()
    }

    #[test]
    fn the_window_is_centred_on_the_peak_of_the_channel_sum_and_renormalised() {
        let psf = psf_peaking_at((4, 6));
        for size in [5, 4] {
            let w = window_at_peak(&psf, size).unwrap();
            assert_eq!(w.dim(), (size, size));
            let centre = (size - 1) / 2;
            for (a, b) in psf.channels.iter().zip(&w.channels) {
                let (g, h) = (&a.grid, &b.grid);
                assert!((h.values().sum() - 1.0).abs() < 1e-12);
                // Same physical position of the centre pixel, values scaled by one factor.
                assert!((h.x(centre) - g.x(6)).abs() < 1e-15 && (h.y(centre) - g.y(4)).abs() < 1e-15);
                let scale = h.values()[[centre, centre]] / g.values()[[4, 6]];
                let corner = h.values()[[0, 0]] / g.values()[[4 - centre, 6 - centre]];
                assert!((corner / scale - 1.0).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn a_window_leaving_the_psf_is_refused_on_every_side() {
        // 9 x 11, a 5 x 5 window needs 2 pixels before the peak and 2 after it.
        for (peak, fits) in [
            ((2, 5), true),
            ((1, 5), false),
            ((6, 5), true),
            ((7, 5), false),
            ((4, 2), true),
            ((4, 1), false),
            ((4, 8), true),
            ((4, 9), false),
        ] {
            let r = window_at_peak(&psf_peaking_at(peak), 5);
            assert_eq!(r.is_ok(), fits, "peak {peak:?}");
            if let Err(e) = r {
                assert!(matches!(e, Error::Data { cause: DataCause::OutOfRange, .. }), "{e:?}");
            }
        }
    }
}
