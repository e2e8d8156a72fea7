//! `doefab bench psf`, `doefab bench stability`, `doefab bench fab` and `doefab bench decoder`: the
//! benchmarks with their defaults and outputs.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::calibration::capture_registration::{Model, RegisterOptions};
use crate::calibration::evaluate::ScoringOptions;
use crate::decoder::capture_bench::{self, scene_dirs, BenchConfig, BenchReport, FinetuneBench};
use crate::decoder::finetune::FinetuneConfig;
use crate::error::Result;
use crate::fabrication::bench::{self as fab_bench, FabBenchOptions, FabBenchReport};
use crate::fabrication::chain::{self, DesignSource};
use crate::io::atomic::{self, StagedDir};
use crate::material::Material;
use crate::optics::charts::{write_psf_charts, write_stability_charts};
use crate::optics::output::system_for;
use crate::optics::psf_bench::{self, run_bench, steps, BenchOptions};
use crate::optics::stability::{self, MapOptions, StabilityReport};
use crate::optics::system::OpticalSystem;
use crate::report::fabrication_charts::write_fab_bench_charts;

/// `bench psf` as the command line states it.
#[derive(Debug, Clone)]
pub struct PsfBenchOptions {
    /// The height map (file or built-in).
    pub design: DesignSource,
    /// Optical system TOML over the paper's values.
    pub system: Option<PathBuf>,
    /// Material of the DOE, by name.
    pub material: String,
    /// What to sweep and the time budget.
    pub bench: BenchOptions,
}

/// Runs the PSF methods' benchmark ([`crate::optics::psf_bench`]) on a design in its system and
/// writes its charts (PNG, SVG) and `bench_psf.json` into the folder `output`, all or nothing.
/// Progress: one step per run or skipped configuration.
pub fn bench_psf(
    opts: &PsfBenchOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<psf_bench::BenchReport> {
    let loaded = chain::load_design(&opts.design)?;
    let mut system = system_for(&loaded.heights);
    system.material = Material::by_name(&opts.material)?;
    if let Some(p) = &opts.system {
        system = OpticalSystem::read_toml(p, &system)?;
    }
    let total = steps(&opts.bench) as u64;
    let mut done = 0;
    let report = run_bench(&system, &loaded.heights, &opts.bench, |what| {
        progress(what, done, total);
        done += 1;
    })?;
    let mut stage = StagedDir::new(output)?;
    write_psf_charts(|n| stage.stage_path(n), &report)?;
    atomic::write_json(&stage.stage_path("bench_psf.json"), &report)?;
    stage.commit()?;
    Ok(report)
}

/// Runs the stability maps ([`crate::optics::stability`]) and writes their charts (PNG, SVG)
/// and `stability.json` into the folder `output`, all or nothing. Progress: one step per run.
pub fn bench_stability(
    opts: &MapOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<StabilityReport> {
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

/// Runs the fabrication stage's sweeps ([`crate::fabrication::bench`]) on a design (any height
/// map `fab` takes) and writes their charts (PNG, SVG), `bench_fab.json` and one CSV per sweep
/// (`quantization.csv`, `stl_heightfield.csv`, `gds.csv`) into the folder `output`, all or
/// nothing. Progress: one step per sweep point ([`fab_bench::steps`]).
pub fn bench_fab(
    design: &DesignSource,
    opts: &FabBenchOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<FabBenchReport> {
    opts.check()?;
    let total = fab_bench::steps(opts) as u64 + 1;
    progress("loading the design", 0, total);
    let loaded = chain::load_design(design)?;
    let mut done = 1;
    let report = fab_bench::run_bench(&loaded.heights, &loaded.name, opts, |what| {
        progress(what, done, total);
        done += 1;
    })?;
    let mut stage = StagedDir::new(output)?;
    write_fab_bench_charts(|n| stage.stage_path(n), &report)?;
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

/// The decoders' benchmark as the command line states it, before defaults.
#[derive(Debug, Clone)]
pub struct DecoderBenchOptions {
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
    /// Score the decoder being fine-tuned every this many steps; `None`: a fifth of the run.
    pub evaluate_every: Option<usize>,
    /// HDR images to fine-tune on; `None`: procedural scenes.
    pub train_data: Option<PathBuf>,
    /// Tile side of the registration, pixels.
    pub tile: usize,
}

/// The benchmark's report (serialised as it is) and the warnings about its scenes.
#[derive(Debug, Serialize)]
#[serde(transparent)]
pub struct DecoderBenchOutcome {
    /// What [`crate::decoder::capture_bench::run`] reports.
    pub report: BenchReport,
    /// Scenes whose bracket merged with warnings, and scenes refused.
    #[serde(skip)]
    pub warnings: Vec<String>,
}

/// The benchmark's settings with the defaults filled in (lists the scene folders under
/// `<data>/captures` when no scene is given).
pub fn decoder_bench_config(o: &DecoderBenchOptions) -> Result<BenchConfig> {
    let scenes = if o.scenes.is_empty() { scene_dirs(&o.data.join("captures"))? } else { o.scenes.clone() };
    let decoders = if o.decoders.is_empty() {
        vec![PathBuf::from("built-in:paper-simulated-psf"), PathBuf::from("built-in:paper-measured-psf")]
    } else {
        o.decoders.clone()
    };
    let evaluate_every = o.evaluate_every.unwrap_or((o.steps / 5).max(1));
    let finetune = (o.steps > 0).then(|| FinetuneBench {
        init: o.init.clone(),
        config: FinetuneConfig {
            steps: o.steps,
            batch: o.batch,
            crop: o.crop,
            lr: o.lr,
            seed: o.seed,
            checkpoint_every: evaluate_every,
            validation: 4,
            ..FinetuneConfig::default()
        },
        evaluate_every,
        train_data: o.train_data.clone(),
    });
    Ok(BenchConfig {
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

/// Runs the decoders' benchmark ([`crate::decoder::capture_bench::run`]) with the defaults filled in,
/// writing into the folder `output`. Progress: the fine-tuning steps and two steps a scene.
pub fn bench_decoder(
    o: &DecoderBenchOptions,
    output: &Path,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<DecoderBenchOutcome> {
    let cfg = decoder_bench_config(o)?;
    let total = o.steps as u64 + 2 * cfg.scenes.len() as u64;
    let mut done = 0;
    let mut message = String::new();
    progress("", 0, total);
    let report = capture_bench::run(&cfg, output, &mut |msg, n| {
        if !msg.is_empty() {
            message = msg.to_string();
        }
        done += n;
        progress(&message, done, total);
    })?;
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
    Ok(DecoderBenchOutcome { report, warnings })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::heightmap::ReadOptions;

    #[test]
    fn bench_fab_writes_every_output_or_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let npy = dir.path().join("design.npy");
        let h = ndarray::Array2::from_shape_fn((30, 34), |(i, j)| {
            0.5 + 0.4 * ((i as f64 * 0.31).sin() * (j as f64 * 0.27).cos())
        });
        crate::io::npy::write_npy_f64(&npy, &h).unwrap();
        let read = ReadOptions { pitch: Some([4e-6; 2]), unit: Some(1e-6), ..Default::default() };
        let design = DesignSource::File(npy.clone(), read.clone());
        let opts = FabBenchOptions {
            level_counts: vec![2, 8],
            max_errors: vec![2e-9, 20e-9],
            vertex_limits: vec![8, 8190],
            repeats: 1,
            ..FabBenchOptions::default()
        };
        let out = dir.path().join("out");
        let mut calls = 0;
        let r = bench_fab(&design, &opts, &out, &mut |_, done, total| {
            assert!(done <= total);
            calls += 1;
        })
        .unwrap();
        assert!(calls >= fab_bench::steps(&opts));
        assert_eq!(r.design_samples, [30, 34]);
        assert_eq!(r.gds.max_area_difference, 0);
        assert!(r.stl.points.iter().all(|p| p.within_bound));
        for n in [
            "bench_fab.json",
            "quantization.csv",
            "stl_heightfield.csv",
            "gds.csv",
            "quantization.png",
            "quantization.svg",
            "stl_heightfield.png",
            "stl_heightfield.svg",
            "gds.png",
            "gds.svg",
        ] {
            assert!(std::fs::metadata(out.join(n)).unwrap().len() > 100, "{n}");
        }
        let svg = std::fs::read_to_string(out.join("stl_heightfield.svg")).unwrap();
        assert!(svg.contains("max_error, nm") && svg.contains("bound held; over: 0"), "{svg}");
        let svg = std::fs::read_to_string(out.join("gds.svg")).unwrap();
        assert!(svg.contains("file size, MB") && svg.contains("at most 0 nm^2"));
        let csv = std::fs::read_to_string(out.join("gds.csv")).unwrap();
        assert_eq!(csv.lines().count(), 1 + 2 * 3);
        // Nothing but the timings changes between runs.
        let again = dir.path().join("again");
        let r2 = bench_fab(&design, &opts, &again, &mut |_, _, _| {}).unwrap();
        let strip = |r: &FabBenchReport| {
            let mut v = serde_json::to_value(r).unwrap();
            for sweep in ["stl", "gds"] {
                for p in v[sweep]["points"].as_array_mut().unwrap() {
                    p["seconds"] = serde_json::Value::Null;
                }
            }
            v
        };
        assert_eq!(strip(&r), strip(&r2));
        // A failing run leaves no output folder.
        let missing = DesignSource::File(dir.path().join("none.npy"), read);
        let none = dir.path().join("none");
        assert!(bench_fab(&missing, &opts, &none, &mut |_, _, _| {}).is_err());
        let bad = FabBenchOptions { vertex_limits: vec![2], ..opts };
        assert!(bench_fab(&design, &bad, &none, &mut |_, _, _| {}).is_err());
        assert!(!none.exists());
    }
}
