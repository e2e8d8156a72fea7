//! `doefab bench psf`, `doefab bench spectral`, `doefab bench stability`, `doefab bench register`, `doefab bench fab`,
//! `doefab bench calibration`, `doefab bench tiling`, `doefab bench decoder` and `doefab bench forward`: the sweeps
//! ([`crate::sweep`]) with their defaults and outputs, data and charts ([`crate::charts`]).

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::calibration::capture_registration::{Model, RegisterOptions};
use crate::calibration::evaluate::ScoringOptions;
use crate::charts::decoder::{write_decoder_scene_chart, write_forward_chart, write_sweep_chart};
use crate::charts::fabrication::write_fab_sweep_charts;
use crate::charts::failure_maps::{write_calibration_chart, write_registration_chart};
use crate::charts::optics::{write_psf_charts, write_spectral_charts, write_stability_charts};
use crate::charts::tiling::write_tiling_chart;
use crate::charts::training::write_training_chart;
use crate::decoder::finetune::FinetuneConfig;
use crate::error::Result;
use crate::fabrication::recipe_run::{self, DesignSource};
use crate::io::atomic::{self, StagedDir};
use crate::material::Material;
use crate::optics::psf_files::system_for;
use crate::optics::system::OpticalSystem;
use crate::sweep::decoder::{
    self as capture_sweep, scene_dirs, DecoderSweepResults, FinetuneSweep, SweepConfig,
};
use crate::sweep::fab::{self as fab_sweep, FabSweepOptions, FabSweepResults};
use crate::sweep::forward::{ForwardOptions, ForwardSweepResults};
use crate::sweep::psf::{self as psf_sweep, run_sweep, steps, SweepOptions};
use crate::sweep::spectral::{self as spectral_sweep, SpectralOptions, SpectralSweepResults};
use crate::sweep::stability::{self, MapOptions, StabilitySweepResults};

/// `bench psf` as the command line states it.
#[derive(Debug, Clone)]
pub struct PsfSweepOptions {
    /// The height map (file or built-in).
    pub design: DesignSource,
    /// Optical system TOML over the paper's values.
    pub system: Option<PathBuf>,
    /// Material of the DOE, by name.
    pub material: String,
    /// What to sweep and the time budget.
    pub sweep: SweepOptions,
}

/// Runs the PSF methods' sweep ([`crate::sweep::psf`]) on a design in its system and
/// writes its charts (PNG, SVG) and `bench_psf.json` into the folder `output`, all or nothing.
/// Progress: one step per run or skipped configuration.
pub fn sweep_psf(
    opts: &PsfSweepOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<psf_sweep::PsfSweepResults> {
    let loaded = recipe_run::load_design(&opts.design)?;
    let total = steps(&opts.sweep) as u64;
    let mut done = 0;
    let report = run_psf_sweep(opts, &loaded.heights, |what| {
        progress(what, done, total);
        done += 1;
    })?;
    let mut stage = StagedDir::new(output)?;
    write_psf_charts(|n| stage.stage_path(n), &report)?;
    atomic::write_json(&stage.stage_path("bench_psf.json"), &report)?;
    stage.commit()?;
    Ok(report)
}

/// The PSF sweep of `opts` on the design's `heights` (loaded already), in the paper's camera
/// fitted to the design, with the material and system file of `opts`; writes nothing.
pub fn run_psf_sweep(
    opts: &PsfSweepOptions,
    heights: &crate::grid::Grid,
    tick: impl FnMut(&str),
) -> Result<psf_sweep::PsfSweepResults> {
    run_sweep(&design_system(opts, heights)?, heights, &opts.sweep, tick)
}

/// The paper's camera fitted to the design, with the material and system file of `opts`.
pub(crate) fn design_system(opts: &PsfSweepOptions, heights: &crate::grid::Grid) -> Result<OpticalSystem> {
    let mut system = system_for(heights);
    system.material = Material::by_name(&opts.material)?;
    if let Some(p) = &opts.system {
        system = OpticalSystem::read_toml(p, &system)?;
    }
    Ok(system)
}

/// Runs the spectral-sampling sweep ([`crate::sweep::spectral`]) on a design in its
/// system (the design, system file and material of `on`; its budget is not used) and writes
/// `spectral.{png,svg}` and `spectral.json` into the folder `output`, all or nothing. Progress:
/// one step per monochromatic run.
pub fn sweep_spectral(
    on: &PsfSweepOptions,
    opts: &SpectralOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<SpectralSweepResults> {
    let loaded = recipe_run::load_design(&on.design)?;
    let system = design_system(on, &loaded.heights)?;
    let total = spectral_sweep::steps(opts) as u64;
    let mut done = 0;
    let report = spectral_sweep::run_spectral(&system, &loaded.heights, opts, |what| {
        progress(what, done.min(total), total);
        done += 1;
    })?;
    let mut stage = StagedDir::new(output)?;
    write_spectral_charts(|n| stage.stage_path(n), &report)?;
    atomic::write_json(&stage.stage_path("spectral.json"), &report)?;
    stage.commit()?;
    Ok(report)
}

/// Runs the stability maps ([`crate::sweep::stability`]) and writes their charts (PNG, SVG)
/// and `stability.json` into the folder `output`, all or nothing. Progress: one step per run.
pub fn sweep_stability(
    opts: &MapOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<StabilitySweepResults> {
    let total = stability::steps(opts) as u64;
    let mut done = 0;
    let report = stability::run_maps(opts, |what| {
        progress(what, done, total);
        done += 1;
    })?;
    let mut stage = StagedDir::new(output)?;
    write_stability_charts(|n| stage.stage_path(n), &report)?;
    atomic::write_json(&stage.stage_path("stability.json"), &report)?;
    stage.commit()?;
    Ok(report)
}

/// Runs the registration trials ([`crate::sweep::register`]) and writes their
/// chart (PNG, SVG), `register.json` and `register.csv` into the folder `output`, all or
/// nothing. Progress: one step per trial.
pub fn sweep_register(
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<crate::sweep::register::RegistrationSweep> {
    use crate::sweep::register as rb;
    let total = rb::steps() as u64;
    let mut done = 0;
    let report = rb::run(|what| {
        progress(what, done, total);
        done += 1;
    })?;
    let mut stage = StagedDir::new(output)?;
    write_registration_chart(|n| stage.stage_path(n), &report)?;
    atomic::write_json(&stage.stage_path("register.json"), &report)?;
    let mut csv = String::from("axis,value,seed,outcome,shift_error_samples,rotation_error_deg,seconds\n");
    for t in &report.trials {
        csv.push_str(&format!(
            "{},{:e},{},{},{:e},{:e},{:e}\n",
            t.axis, t.value, t.seed, t.outcome, t.shift_error, t.rotation_error_deg, t.seconds
        ));
    }
    atomic::write_bytes(&stage.stage_path("register.csv"), csv.as_bytes())?;
    stage.commit()?;
    Ok(report)
}

/// Runs the PSF calibration trials ([`crate::sweep::calibration`]) on the PSF file `psf` (any
/// file `psf` writes or `calibrate-psf` reads; `None`: the paper's measured PSF, compiled in)
/// and writes their chart (PNG, SVG), `calibration.json` and `calibration.csv` into the folder
/// `output`, all or nothing. Progress: one step per trial.
pub fn sweep_calibration(
    psf: Option<&Path>,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<crate::sweep::calibration::CalibrationSweep> {
    use crate::sweep::calibration as cb;
    let (truth, name) = match psf {
        Some(p) => (crate::optics::Psf::read(p, None, None)?, p.display().to_string()),
        None => (crate::optics::Psf::paper_measured()?, "built-in:paper-measured-psf".to_string()),
    };
    let total = cb::steps() as u64;
    let mut done = 0;
    let report = cb::run(&truth, &name, |what| {
        progress(what, done, total);
        done += 1;
    })?;
    let mut stage = StagedDir::new(output)?;
    write_calibration_chart(|n| stage.stage_path(n), &report)?;
    atomic::write_json(&stage.stage_path("calibration.json"), &report)?;
    let mut csv = String::from("axis,value,seed,outcome,worst_relative_l2,estimated_relative_l2,seconds\n");
    for t in &report.trials {
        csv.push_str(&format!(
            "{},{:e},{},{},{:e},{:e},{:e}\n",
            t.axis, t.value, t.seed, t.outcome, t.worst, t.estimated, t.seconds
        ));
    }
    atomic::write_bytes(&stage.stage_path("calibration.csv"), csv.as_bytes())?;
    stage.commit()?;
    Ok(report)
}

/// Runs the reconstruction's tiling and precision sweep ([`crate::sweep::tiling`]) with
/// the decoder file `decoder` (or a built-in name) and writes its chart (PNG, SVG),
/// `tiling.json` and `tiling.csv` into the folder `output`, all or nothing. Progress: one step
/// per reconstruction.
pub fn sweep_tiling(
    decoder: &Path,
    opts: &crate::sweep::tiling::TilingOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<crate::sweep::tiling::TilingSweep> {
    use crate::sweep::tiling as tb;
    let total = tb::steps(opts) as u64;
    let mut done = 0;
    let report = tb::run(decoder, opts, |what| {
        progress(what, done, total);
        done += 1;
    })?;
    let mut stage = StagedDir::new(output)?;
    write_tiling_chart(|n| stage.stage_path(n), &report)?;
    atomic::write_json(&stage.stage_path("tiling.json"), &report)?;
    let mut csv = String::from("precision,tile,overlap,passes,seconds,relative_l2,max_abs\n");
    for r in &report.runs {
        let opt = |v: Option<usize>| v.map_or("one pass".to_string(), |v| v.to_string());
        csv.push_str(&format!(
            "{},{},{},{},{:e},{:e},{:e}\n",
            r.precision,
            opt(r.tile),
            opt(r.overlap),
            r.passes,
            r.seconds,
            r.relative_l2,
            r.max_abs
        ));
    }
    atomic::write_bytes(&stage.stage_path("tiling.csv"), csv.as_bytes())?;
    stage.commit()?;
    Ok(report)
}

/// Runs the fabrication stage's sweeps ([`crate::sweep::fab`]) on a design (any height
/// map `fab` takes) and writes their charts (PNG, SVG), `bench_fab.json` and one CSV per sweep
/// (`quantization.csv`, `stl_heightfield.csv`, `gds.csv`) into the folder `output`, all or
/// nothing. Progress: one step per sweep point ([`fab_sweep::steps`]).
pub fn sweep_fab(
    design: &DesignSource,
    opts: &FabSweepOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<FabSweepResults> {
    opts.check()?;
    let total = fab_sweep::steps(opts) as u64 + 1;
    progress("loading the design", 0, total);
    let loaded = recipe_run::load_design(design)?;
    let mut done = 1;
    let report = fab_sweep::run_sweep(&loaded.heights, &loaded.name, opts, |what| {
        progress(what, done, total);
        done += 1;
    })?;
    let mut stage = StagedDir::new(output)?;
    write_fab_sweep_charts(|n| stage.stage_path(n), &report)?;
    atomic::write_json(&stage.stage_path("bench_fab.json"), &report)?;
    for (name, text) in [
        ("quantization.csv", report.quantization.csv()),
        ("stl_heightfield.csv", report.stl.csv()),
        ("gds.csv", report.gds.csv()),
    ] {
        atomic::write_bytes(&stage.stage_path(name), text.as_bytes())?;
    }
    stage.commit()?;
    progress("", total, total);
    Ok(report)
}

/// The decoders' sweep as the command line states it, before defaults.
#[derive(Debug, Clone)]
pub struct DecoderSweepOptions {
    /// The paper's data release: the default scenes (`captures/<scene>/`) and
    /// `measured_psf.npz`.
    pub data: PathBuf,
    /// Scene folders; empty: every folder under `<data>/captures`.
    pub scenes: Vec<PathBuf>,
    /// Decoders to score; empty: the paper's two built-in decoders.
    pub decoders: Vec<PathBuf>,
    /// The measured PSF; `None`: `<data>/measured_psf.npz` (array `psf_val`).
    pub psf: Option<PathBuf>,
    /// Smallest fraction of a scene that must be registered.
    pub min_coverage: f64,
    /// Fine-tuning steps of `init` on the PSF (0: no fine-tuning).
    pub steps: usize,
    /// The decoder to fine-tune.
    pub init: PathBuf,
    /// Batch size of the fine-tuning.
    pub batch: usize,
    /// Training crop side, pixels (a multiple of 16).
    pub crop: usize,
    /// Adam step size.
    pub lr: f64,
    /// Seed of the fine-tuning's random choices.
    pub seed: u64,
    /// Score the decoder being fine-tuned every this many steps; `None`: at each validation.
    pub evaluate_every: Option<usize>,
    /// HDR images to fine-tune on; `None`: procedural scenes.
    pub train_data: Option<PathBuf>,
    /// Tile side of the registration, pixels.
    pub tile: usize,
    /// Where the fine-tuning's simulated captures clip, per channel (see
    /// [`FinetuneConfig::channel_clipping`]).
    pub channel_clipping: [f64; 3],
    /// The fine-tuning's halo (see [`FinetuneConfig::halo`]).
    pub halo: Option<crate::decoder::measurement::Halo>,
    /// The fine-tuning's gradient clipping (see [`FinetuneConfig::grad_clip`]).
    pub grad_clip: f64,
}

/// The sweep's results (serialised as they are) and the warnings about its scenes.
#[derive(Debug, Serialize)]
#[serde(transparent)]
pub struct DecoderSweepOutcome {
    /// What [`crate::sweep::decoder::run`] measured.
    pub results: DecoderSweepResults,
    /// Scenes whose bracket merged with warnings, scenes refused, training images skipped.
    #[serde(skip)]
    pub warnings: Vec<String>,
}

/// The scenes on which the fine-tuned decoder (the curve's last point) scores below its start
/// (the first), PSNR-gamma over all scored pixels, as warnings with the figures.
fn below_start(f: &capture_sweep::FinetuneRun) -> Vec<String> {
    let (Some(start), Some(end)) = (f.curve.first(), f.curve.last()) else { return Vec::new() };
    start
        .scores
        .iter()
        .zip(&end.scores)
        .filter(|(a, b)| b.all.gamma_db < a.all.gamma_db)
        .map(|(a, b)| {
            format!(
                "{}: the decoder fine-tuned for {} step{} scores {:.2} dB PSNR-gamma, below its start's {:.2} dB{}",
                a.scene,
                end.step,
                if end.step == 1 { "" } else { "s" },
                b.all.gamma_db,
                a.all.gamma_db,
                if end.step < crate::decoder::finetune::STEPS {
                    format!(" (a run shorter than {} steps can be: see the curve)", crate::decoder::finetune::STEPS)
                } else {
                    String::new()
                }
            )
        })
        .collect()
}

/// The sweep's settings with the defaults filled in (lists the scene folders under
/// `<data>/captures` when no scene is given).
pub fn decoder_sweep_config(o: &DecoderSweepOptions) -> Result<SweepConfig> {
    let scenes = if o.scenes.is_empty() { scene_dirs(&o.data.join("captures"))? } else { o.scenes.clone() };
    let decoders = if o.decoders.is_empty() {
        vec![PathBuf::from("built-in:paper-simulated-psf"), PathBuf::from("built-in:paper-measured-psf")]
    } else {
        o.decoders.clone()
    };
    // By default the real scenes score the decoder as each validation leaves it.
    let evaluate_every = o.evaluate_every.unwrap_or(crate::decoder::finetune::CHECKPOINT_EVERY);
    let finetune = (o.steps > 0).then(|| FinetuneSweep {
        init: o.init.clone(),
        config: FinetuneConfig {
            steps: o.steps,
            batch: o.batch,
            crop: o.crop,
            lr: o.lr,
            seed: o.seed,
            channel_clipping: o.channel_clipping,
            halo: o.halo,
            grad_clip: o.grad_clip,
            ..FinetuneConfig::recommended()
        },
        evaluate_every,
        train_data: o.train_data.clone(),
    });
    Ok(SweepConfig {
        scenes,
        decoders,
        psf: o.psf.clone().unwrap_or_else(|| o.data.join("measured_psf.npz")),
        psf_key: Some("psf_val".into()),
        scoring: ScoringOptions {
            register: RegisterOptions { tile: o.tile, model: Model::Local, ..RegisterOptions::default() },
            min_coverage: o.min_coverage,
            ..ScoringOptions::default()
        },
        finetune,
    })
}

/// Runs the decoders' sweep ([`crate::sweep::decoder::run`]) with the defaults filled in,
/// writing into the folder `output` its files and charts: `decoders.png` (decoder x scene) and,
/// with fine-tuning, `psnr_vs_time.png` and `finetuned/training_curve.png`. Progress: the
/// fine-tuning steps and two steps a scene.
pub fn sweep_decoder(
    o: &DecoderSweepOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<DecoderSweepOutcome> {
    let cfg = decoder_sweep_config(o)?;
    let total = o.steps as u64 + 2 * cfg.scenes.len() as u64;
    let mut done = 0;
    let mut message = String::new();
    progress("", 0, total);
    let report = capture_sweep::run(&cfg, output, &mut |msg, n| {
        if !msg.is_empty() {
            message = msg.to_string();
        }
        done += n;
        progress(&message, done, total);
    })?;
    write_decoder_scene_chart(&output.join("decoders.png"), &report)?;
    if let Some(f) = &report.finetune {
        write_training_chart(&output.join("finetuned").join("training_curve.png"), &f.history)?;
        write_sweep_chart(&output.join("psnr_vs_time.png"), &report)?;
    }
    let mut warnings = Vec::new();
    for s in report.scenes.iter().filter(|s| !s.merge_warnings.is_empty()) {
        let n = s.merge_warnings.len();
        warnings.push(format!("{}: the merge of its bracket gave {n} warnings (in report.json)", s.name));
    }
    for s in &report.scenes {
        if let Some(e) = &s.error {
            warnings.push(format!("scene {} not scored: {e}", s.name));
        }
    }
    if let Some(f) = &report.finetune {
        warnings.extend(f.skipped_images.iter().cloned());
        warnings.extend(below_start(f));
    }
    Ok(DecoderSweepOutcome { results: report, warnings })
}

/// Runs the check of the decoder's measurement model against the real captures
/// ([`crate::sweep::forward::run`]) and writes `forward.json` and its chart `forward.png` into
/// the folder `output`. Progress: two steps a scene.
pub fn sweep_forward(
    opts: &ForwardOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<ForwardSweepResults> {
    let report = crate::sweep::forward::run(opts, output, progress)?;
    write_forward_chart(&output.join("forward.png"), &report)?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibration::evaluate::Psnr;
    use crate::sweep::decoder::{CurvePoint, FinetuneRun, Score};

    fn point(step: usize, db: [f64; 2]) -> CurvePoint {
        let score = |scene: &str, gamma_db: f64| Score {
            scene: scene.into(),
            decoder: "fine-tuned here".into(),
            all: Psnr {
                linear_db: 0.0,
                gamma_db,
                peak: 1.0,
                pixels: 1,
                min_output: 0.0,
                negative_fraction: 0.0,
            },
            saturated: None,
            min_output: 0.0,
            channel_balance: Vec::new(),
        };
        CurvePoint { step, seconds: 0.0, scores: vec![score("Fruit", db[0]), score("Kitchen", db[1])] }
    }

    /// A fine-tuned decoder below its start on a scene is a warning naming the scene and both
    /// figures (the measured 20-step point of the README's curve), and says why when the run
    /// was short; one above its start on every scene is not.
    #[test]
    fn a_fine_tuned_decoder_below_its_start_is_a_warning() {
        let run = |steps: usize, end: [f64; 2]| FinetuneRun {
            init: "start".into(),
            steps,
            seconds_per_step: 1.0,
            training_data: "images".into(),
            skipped_images: Vec::new(),
            curve: vec![point(0, [39.72, 32.78]), point(steps, end)],
            history: Vec::new(),
        };
        let w = below_start(&run(20, [39.17, 32.09]));
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(w[1].starts_with("Kitchen") && w[1].contains("32.09") && w[1].contains("32.78"), "{}", w[1]);
        assert!(w[0].contains("shorter than 80 steps"), "{}", w[0]);
        let w = below_start(&run(80, [40.24, 32.09]));
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(w[0].starts_with("Kitchen") && !w[0].contains("shorter"), "{}", w[0]);
        assert!(below_start(&run(80, [40.24, 32.96])).is_empty());
    }
}
