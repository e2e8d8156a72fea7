//! `doefab precompensate`: the next mask set, corrected for the process that a scan of the last
//! part measured ([`crate::fabrication::precompensate`] holds the physics).
//!
//! The model comes from `doefab compare` (run here on a scan, or read from its `compare.json`):
//! the depth scale, the lateral blur and the mean height of every design level on the part.
//! Through the levels it is a monotone response `R` (commanded level height -> made height);
//! without them (a continuous design, or `--no-levels`) `R(c) = k c`. The reference the part
//! was compared with is the design wrapped and quantized as the recipe makes it, in the design
//! frame; the corrected surface is commanded in that frame and written as the recipe writes the
//! plain one: a master is the complement of the commanded surface, mirrored, and a grayscale
//! mask maps each commanded height to a dose through the resist's contrast curve.
//!
//! The scan is registered to the design's family as `compare` does it (the cast of the
//! master, the wrapped design: [`reference_family`]), and the member it matched is the target:
//! for a scan of the master or its cast, the cast of the master `fab` writes, so that the plain
//! correction commands `fab`'s own master.
//!
//! Refused, with the figure: every registration `compare` refuses (the one trust rule,
//! `check_trust`, on the registration and on the part over the aperture's interior, also for
//! a model read back from `compare.json`), a depth scale outside 0.5..1.5 (a wrong unit or a wrong
//! design, not a process error), a compare.json made against another design, a per-level
//! response that is not monotone, a correction that needs heights beyond what the writer makes
//! (the contrast curve's range), and a recipe asking for a binary mask set (its level heights
//! are etch depths, which a mask cannot correct).

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{Condition, DataCause, Error, Result};
use crate::fabrication::contrast::ContrastCurve;
use crate::fabrication::mask::render_levels;
use crate::fabrication::precompensate::{
    precompensate, DeblurStats, PrecompensateOptions, Precompensated, ProcessModel, Response,
};
use crate::fabrication::quantize::feature_check;
use crate::fabrication::recipe::{Output, Recipe};
use crate::fabrication::recipe_run::{self, write_mask, ChainParams, DesignSource, LoadedDesign};
use crate::fabrication::stl::{surface_mesh, write_stl_part};
use crate::fabrication::ReplicaMode;
use crate::grid::{Grid, Unit};
use crate::io::atomic::{write_json, StagedDir};
use crate::io::raw_map::Metadata;
use crate::io::scan::ScanOptions;
use crate::metrology::scan_compare::{
    check_interior, compare, compare_family, efficiency_loss, CompareOptions, Comparison, EfficiencyLoss,
    FabModel, LevelHeights, LevelSpec, Member,
};
use crate::metrology::scan_registration::{check_trust, TRUSTED_FRACTION};
use crate::metrology::synthetic_scan::{simulate_scan, SimulateParams};
use crate::pipeline::compare::{default_aperture, family_member, reference_family, reference_surface};

/// Depth scales outside this range are refused.
pub const DEPTH_SCALE_RANGE: [f64; 2] = [0.5, 1.5];
/// Up to this many levels the response goes through every measured level height (each level
/// its own dose or etch); above it, through a weighted cubic ([`smooth_response`]).
pub const MAX_PER_LEVEL: usize = 16;
/// A level enters the response only with at least this many terrace samples.
pub const MIN_LEVEL_SAMPLES: usize = 16;

/// What the model is taken from.
#[derive(Debug, Clone)]
pub enum ModelSource {
    /// A scan of the part, compared here.
    Scan {
        /// The scan file (any format `doefab compare` reads).
        path: PathBuf,
        /// How to read it: pitch and height units for files that carry none, checks.
        options: ScanOptions,
    },
    /// The `compare.json` that `doefab compare` wrote.
    CompareJson(PathBuf),
}

/// Which corrections to make.
#[derive(Debug, Clone, Serialize)]
pub struct Corrections {
    /// Per-level heights through the measured level means (else the depth scale alone).
    pub levels: bool,
    /// Constrained deconvolution of the blur.
    pub deblur: bool,
    /// FISTA iterations.
    pub iterations: usize,
    /// Highest commanded height, metres (default: the contrast curve's range, else two periods).
    pub max_height: Option<f64>,
}

impl Default for Corrections {
    fn default() -> Self {
        Corrections { levels: true, deblur: true, iterations: 100, max_height: None }
    }
}

/// What a model's registration reached: the fields of `compare.json`'s `registration` that
/// the trust rule reads.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MeasuredRegistration {
    /// Correlation of the registered design with the scan.
    pub correlation: f64,
    /// The correlation the scan's noise allows a right pose.
    pub noise_ceiling: f64,
}

/// The measurement a model is built from (the fields of `compare.json` it needs).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Measured {
    /// The scan file, as named to `compare`.
    pub scan: String,
    /// SHA-256 of the scan file (empty for a simulated scan).
    pub scan_sha256: String,
    /// SHA-256 of the design the scan was compared with (its parameters for a built-in one).
    pub design_sha256: String,
    /// The member of the design's family the scan matched (a `compare.json` without it was
    /// compared with the wrapped design).
    #[serde(default = "wrapped")]
    pub member: Member,
    /// The registration's correlation and noise ceiling, for the trust rule.
    pub registration: MeasuredRegistration,
    /// Correlation of part and design inside the aperture ([`Comparison::interior_correlation`]).
    pub interior_correlation: f64,
    /// RMS of part - design over the aperture, metres.
    pub rms_error: f64,
    /// The fitted fabrication model (depth scale, offset, blur).
    pub model: FabModel,
    /// The per-level statistics, with the design's quantization.
    pub levels: Option<LevelHeights>,
}

fn wrapped() -> Member {
    Member::Wrapped
}

impl Measured {
    fn of_comparison(c: &Comparison, scan: String, scan_sha256: String, design_sha256: String) -> Measured {
        Measured {
            scan,
            scan_sha256,
            design_sha256,
            member: c.member,
            registration: MeasuredRegistration {
                correlation: c.registration.correlation,
                noise_ceiling: c.registration.noise_ceiling,
            },
            interior_correlation: c.interior_correlation,
            rms_error: c.rms_error,
            model: c.model.clone(),
            levels: c.levels.clone(),
        }
    }

    /// Reads `compare.json`; errors name the file and the field.
    pub fn read(path: &Path) -> Result<Measured> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        serde_json::from_str(&text).map_err(|e| {
            Error::malformed(path, format!("not a compare.json written by `doefab compare`: {e}"))
                .at_json(&text, &e)
        })
    }
}

/// The process model of a measurement, after the stability checks (module docs); warnings
/// name what is left uncorrected.
pub fn process_model(
    m: &Measured,
    c: &Corrections,
    warnings: &mut Vec<String>,
) -> Result<(ProcessModel, String)> {
    // The rule `compare` applies, so that no registration it refuses becomes a correction.
    let named = |e: Error| match e {
        Error::Registration { refusal, what } => Error::registration(
            refusal,
            format!("{}: {what}; a model fitted from it would correct the wrong thing", m.scan),
        ),
        other => other,
    };
    let ceiling = m.registration.noise_ceiling;
    check_trust("the registration", m.registration.correlation, ceiling, TRUSTED_FRACTION).map_err(named)?;
    check_interior(m.interior_correlation, ceiling, TRUSTED_FRACTION).map_err(named)?;
    let k = m.model.depth_scale;
    if !(DEPTH_SCALE_RANGE[0]..=DEPTH_SCALE_RANGE[1]).contains(&k) {
        return Err(Error::validity(Condition::Domain, format!(
            "{}: the fitted depth scale {k:.3} is outside {}..{}: that is a wrong height unit, scan or design, \
             not a process error to pre-compensate",
            m.scan, DEPTH_SCALE_RANGE[0], DEPTH_SCALE_RANGE[1]
        )));
    }
    // The heights fitted with the blur; a comparison without them (an older compare.json, or
    // more levels than are fitted) gives the means over terrace interiors.
    let stats = m.levels.iter().flat_map(|l| l.levels.iter());
    let fitted: Vec<(f64, f64, f64)> = stats
        .clone()
        .filter(|s| s.aperture_samples >= MIN_LEVEL_SAMPLES)
        .filter_map(|s| s.fitted_height.map(|h| (s.design_height, h, s.aperture_samples as f64)))
        .collect();
    let levels: Vec<(f64, f64, f64)> = if fitted.len() >= 2 {
        fitted
    } else {
        stats
            .filter(|s| s.samples >= MIN_LEVEL_SAMPLES)
            .map(|s| (s.design_height, s.mean, s.samples as f64))
            .collect()
    };
    let (response, kind) = if c.levels && levels.len() >= 2 {
        let smooth = levels.len() > MAX_PER_LEVEL;
        let r = if smooth {
            smooth_response(&levels)
        } else {
            Response::new(levels.iter().map(|p| p.0).collect(), levels.iter().map(|p| p.1).collect())
        };
        let r = r.map_err(|e| {
            Error::validity(Condition::Model, format!(
                "{}: the per-level heights of the part: {e}; set `levels` to false to correct the depth scale alone",
                m.scan
            ))
        })?;
        let how = if smooth { "a weighted cubic through" } else { "each of" };
        (r, format!("per-level heights ({how} {} levels measured)", levels.len()))
    } else {
        if c.levels && m.levels.is_some() {
            warnings.push(format!(
                "fewer than 2 levels have {MIN_LEVEL_SAMPLES} terrace samples: only the depth scale is corrected"
            ));
        }
        (Response::linear(k, 0.0)?, format!("depth scale {k:.4}"))
    };
    let blur = match (c.deblur, m.model.blur_doubt()) {
        (false, _) => 0.0,
        (true, Some(why)) => {
            warnings.push(format!("{why}: it is not deconvolved"));
            0.0
        }
        (true, None) => m.model.blur,
    };
    Ok((ProcessModel { response, blur }, kind))
}

/// The response of many levels: a cubic `m(c)` fitted to the level heights by least squares
/// weighted by their sample counts, twice refitted without the levels more than 3 weighted RMS
/// residuals off (the extreme levels beside a phase wrap, with few samples, are the usual
/// ones), then sampled at the measured commands. Refused when it does not rise over them.
pub fn smooth_response(points: &[(f64, f64, f64)]) -> Result<Response> {
    // Heights in micrometres inside the fit, for a well-conditioned system.
    let unit = 1e-6;
    let cubic = |coef: &[f64], c: f64| {
        let x = c / unit;
        unit * (coef[0] + x * (coef[1] + x * (coef[2] + x * coef[3])))
    };
    let mut keep = vec![true; points.len()];
    let mut coef = Vec::new();
    for pass in 0..3 {
        let (mut a, mut r) = (vec![0.0; 16], vec![0.0; 4]);
        for (&(c, m, w), _) in points.iter().zip(&keep).filter(|(_, k)| **k) {
            let x = c / unit;
            let f = [1.0, x, x * x, x * x * x];
            for p in 0..4 {
                r[p] += w * f[p] * m / unit;
                for q in 0..4 {
                    a[p * 4 + q] += w * f[p] * f[q];
                }
            }
        }
        coef = crate::linalg::solve(a, r, 4)?;
        if pass == 2 {
            break;
        }
        let (mut sw, mut swr) = (0.0, 0.0);
        for (&(c, m, w), _) in points.iter().zip(&keep).filter(|(_, k)| **k) {
            sw += w;
            swr += w * (m - cubic(&coef, c)).powi(2);
        }
        let rms = (swr / sw).sqrt();
        for (k, &(c, m, _)) in keep.iter_mut().zip(points) {
            *k = (m - cubic(&coef, c)).abs() <= 3.0 * rms;
        }
    }
    let commanded: Vec<f64> = points.iter().map(|p| p.0).collect();
    let made = commanded.iter().map(|&c| cubic(&coef, c)).collect();
    Response::new(commanded, made)
}

/// The least-squares depth scale of `part` against `target` (means removed).
fn fitted_scale(part: &Grid, target: &Grid) -> f64 {
    let n = target.values().len().max(1) as f64;
    let (mt, mp) = (target.values().sum() / n, part.values().sum() / n);
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for (t, p) in target.values().iter().zip(part.values()) {
        sxy += (t - mt) * (p - mp);
        sxx += (t - mt) * (t - mt);
    }
    sxy / sxx
}

/// What the model predicts of the part, before (the plain mask) and after pre-compensation.
#[derive(Debug, Clone, Serialize)]
pub struct Prediction {
    /// RMS of the part the model predicts from the plain mask minus the target (the design
    /// wrapped and quantized as the recipe makes it), piston removed, metres.
    pub rms_before: f64,
    /// RMS of the part the model predicts from the corrected mask minus the target, piston
    /// removed, metres.
    pub rms_after: f64,
    /// Least-squares depth scale of the predicted plain part against the target (means
    /// removed).
    pub depth_scale_before: f64,
    /// Least-squares depth scale of the predicted corrected part against the target (means
    /// removed).
    pub depth_scale_after: f64,
    /// Design-order efficiency per wavelength at `depth_scale_before` (Swanson).
    pub efficiency_before: Vec<EfficiencyLoss>,
    /// Design-order efficiency per wavelength at `depth_scale_after` (Swanson).
    pub efficiency_after: Vec<EfficiencyLoss>,
}

fn predict(target: &Grid, p: &Precompensated, params: &ChainParams) -> Result<Prediction> {
    let spec = params.wrap_spec()?;
    let (kb, ka) = (fitted_scale(&p.plain, target), fitted_scale(&p.predicted, target));
    let n = (params.level_count <= 256).then_some(params.level_count);
    Ok(Prediction {
        rms_before: p.rms_before,
        rms_after: p.rms_after,
        depth_scale_before: kb,
        depth_scale_after: ka,
        efficiency_before: efficiency_loss(&spec, n, kb)?,
        efficiency_after: efficiency_loss(&spec, n, ka)?,
    })
}

/// A job of `doefab precompensate`.
#[derive(Debug, Clone)]
pub struct PrecompensateJob {
    /// The design the part was made from.
    pub design: DesignSource,
    /// The recipe of the next mask (the same process the part went through).
    pub recipe: Recipe,
    /// Where the process model comes from.
    pub model: ModelSource,
    /// Which corrections to make.
    pub corrections: Corrections,
    /// Clear aperture for the comparison, metres (as `doefab compare`).
    pub aperture: Option<f64>,
    /// Write masks above the size limit.
    pub force: bool,
}

/// What `doefab precompensate` prints and writes as `precompensate.json`.
#[derive(Debug, Clone, Serialize)]
pub struct PrecompensateOutcome {
    /// The units of every figure.
    pub units: String,
    /// The design: `built-in:NAME` or its file's path.
    pub design: String,
    /// SHA-256 of the design file (of its parameters' JSON for a built-in design).
    pub design_sha256: String,
    /// The recipe's name.
    pub recipe: String,
    /// What the model was taken from.
    pub measured: Measured,
    /// What was corrected, in words.
    pub corrected: Vec<String>,
    /// The process the correction inverts.
    pub process_model: ProcessModel,
    /// Commanded height of each level of the target, metres (design frame; `null` for a level
    /// it does not hold: level 0 of the cast of the master, which lies at the full period).
    pub level_commands: Vec<Option<f64>>,
    /// Piston added to the target, metres.
    pub piston: f64,
    /// Highest commanded height allowed, metres.
    pub max_height: f64,
    /// What the deconvolution did, when it ran.
    pub deblur: Option<DeblurStats>,
    /// The model's prediction for the plain and the corrected mask.
    pub predicted: Prediction,
    /// What is left uncorrected or named as beyond the writer.
    pub warnings: Vec<String>,
    /// Files written, relative to the output folder.
    pub files: Vec<String>,
}

/// The written surface of a commanded one: itself, or for a master its complement mirrored.
fn written_surface(commanded: &Grid, mode: ReplicaMode) -> Result<Grid> {
    match mode {
        ReplicaMode::Design => Ok(commanded.clone()),
        ReplicaMode::Master => {
            let (lo, hi) =
                commanded.min_max().ok_or_else(|| Error::data(DataCause::Empty, "empty surface"))?;
            let v = commanded.values().mapv(|c| hi + lo - c);
            Ok(commanded.map_values(v, Unit::Metre)?.mirror(true, false))
        }
    }
}

/// Most levels a pre-compensated grayscale mask takes: a deconvolved surface takes this many
/// equal steps between its lowest and highest heights (or the mask's gray values, if fewer).
pub const MAX_MASK_LEVELS: usize = 1024;

/// A level map and its heights for a written surface: its distinct heights when they are few
/// (a level table corrected level by level), else `max_levels` equal steps.
fn surface_levels(w: &Grid, max_levels: usize) -> Result<(Grid, Vec<f64>)> {
    let mut distinct: Vec<f64> = w.values().iter().copied().collect();
    distinct.sort_by(f64::total_cmp);
    distinct.dedup();
    let (levels, heights) = if distinct.len() <= max_levels {
        let lv = w.values().mapv(|h| distinct.partition_point(|&d| d < h) as f64);
        (lv, distinct)
    } else {
        let (lo, hi) = (distinct[0], distinct[distinct.len() - 1]);
        let step = (hi - lo) / (max_levels - 1) as f64;
        let lv = w.values().mapv(|h| ((h - lo) / step).round().clamp(0.0, (max_levels - 1) as f64));
        (lv, (0..max_levels).map(|l| lo + l as f64 * step).collect())
    };
    Ok((w.map_values(levels, Unit::Level)?, heights))
}

/// `doefab precompensate`: the model (a scan compared here, or `compare.json`), the corrected
/// commanded surface, and the recipe's outputs into `out` (see the module docs): the grayscale
/// mask(s) with a sidecar that says what was corrected, from which scan and what is predicted,
/// the STL of the written surface, `commanded.exr` (the design-frame commanded surface, for
/// `doefab simulate-scan`) and `precompensate.json`. `step` is called before each stage.
pub fn run(job: &PrecompensateJob, out: &Path, step: &mut dyn FnMut(&str)) -> Result<PrecompensateOutcome> {
    if job.recipe.outputs.contains(&Output::Gds) {
        return Err(Error::param(
            "recipe",
            format!(
                "{}: asks for a multi-level binary mask set (gds), whose level heights are set by etch depths that \
                 no mask can correct; pre-compensation writes grayscale masks and STL: drop \"gds\" from its outputs",
                job.recipe.path.display()
            ),
        ));
    }
    step("load the design");
    let design = recipe_run::load_design(&job.design)?;
    let params = ChainParams::of_recipe(&job.recipe, false);
    let (family, optics) = reference_family(&design, Some(&params))?;
    let (measured, target) = match &job.model {
        ModelSource::Scan { path, options } => {
            step("register and compare the scan");
            let scan = crate::io::scan::read_scan(path, options)?;
            crate::io::heightmap::check_relief(path, &scan.grid)?;
            let aperture = default_aperture(&job.design, job.aperture);
            let opts = CompareOptions { aperture, optics, ..Default::default() };
            let c = compare_family(&family, &scan.grid, &opts)?;
            let m = Measured::of_comparison(
                &c,
                path.display().to_string(),
                crate::io::file_sha256(path)?,
                design.sha256.clone(),
            );
            (m, family_member(family, c.member)?)
        }
        ModelSource::CompareJson(path) => {
            let m = Measured::read(path)?;
            if m.design_sha256 != design.sha256 {
                return Err(Error::malformed(
                    path,
                    format!(
                        "design_sha256 {} is not that of {} ({}): the comparison was made against another design",
                        m.design_sha256, design.name, design.sha256
                    ),
                ));
            }
            let target =
                family_member(family, m.member).map_err(|e| Error::malformed(path, e.to_string()))?;
            (m, target)
        }
    };
    let curve = match &job.recipe.contrast_curve {
        Some(p) => Some(ContrastCurve::read_csv(p)?),
        None => None,
    };
    step("pre-compensate");
    let written = precompensate_design(
        target.surface,
        target.levels,
        &params,
        &measured,
        &job.corrections,
        curve.as_ref(),
    )?;
    step("write");
    write_outputs(job, &design, &params, curve.as_ref(), measured, written, out)
}

/// The pre-compensated commanded surface of `design` as `params` makes it, from `measured`.
#[derive(Debug, Clone)]
pub struct Written {
    /// The design wrapped and quantized as the recipe makes it (design frame, metres).
    pub target: Grid,
    /// The process model inverted.
    pub model: ProcessModel,
    /// The commanded surface and the deconvolution's report.
    pub result: Precompensated,
    /// The model's prediction for the plain and the corrected mask.
    pub prediction: Prediction,
    /// What was corrected, in words.
    pub corrected: Vec<String>,
    /// Highest commanded height allowed, metres.
    pub max_height: f64,
    /// What is left uncorrected or named as beyond the writer.
    pub warnings: Vec<String>,
}

/// The correction itself, without files: model, checks, commanded surface and prediction, for
/// the `target` [`reference_surface`] makes of the design with `params` (and its `levels`).
pub fn precompensate_design(
    target: Grid,
    levels: Option<LevelSpec>,
    params: &ChainParams,
    measured: &Measured,
    corrections: &Corrections,
    curve: Option<&ContrastCurve>,
) -> Result<Written> {
    let mut warnings = Vec::new();
    let (model, kind) = process_model(measured, corrections, &mut warnings)?;
    let period = params.wrap_spec()?.period()?;
    let max_height =
        corrections.max_height.unwrap_or_else(|| curve.map_or(2.0 * period, |c| c.depth_range()[1]));
    let opts =
        PrecompensateOptions { deblur: model.blur > 0.0, max_height, iterations: corrections.iterations };
    let top = target.min_max().map_or(0.0, |m| m.1);
    let result = precompensate(&target, levels.map(|l| (l.indices(top), l.step)), &model, &opts)?;
    warnings.extend(result.warnings.iter().cloned());
    let mut corrected = vec![kind];
    if let Some(d) = &result.deblur {
        corrected.push(format!(
            "blur {:.2} um deconvolved ({} iterations): residual {:.1} -> {:.1} nm RMS, {:.1}% of samples at the \
             reachable range's bounds",
            model.blur * 1e6,
            d.iterations,
            d.residual_before * 1e9,
            d.residual_after * 1e9,
            d.at_bounds * 100.0
        ));
    }
    // What the writer cannot make: features the deconvolution adds below its minimum.
    if result.deblur.is_some() {
        let check =
            |g: &Grid| feature_check(g, period, params.level_count, params.min_feature).fraction_below;
        let (plain, corrected) = (check(&target), check(&result.commanded));
        if corrected > plain {
            warnings.push(format!(
                "the deconvolution puts {:.2}% of the samples on terraces narrower than the writer's minimum feature \
                 of {:.2} um (local zone period / level count, as fab checks; the plain mask: {:.2}%): there the \
                 correction asks for detail the writer may not resolve",
                corrected * 100.0,
                params.min_feature * 1e6,
                plain * 100.0
            ));
        }
    }
    let prediction = predict(&target, &result, params)?;
    Ok(Written { target, model, result, prediction, corrected, max_height, warnings })
}

fn write_outputs(
    job: &PrecompensateJob,
    design: &LoadedDesign,
    params: &ChainParams,
    curve: Option<&ContrastCurve>,
    measured: Measured,
    w: Written,
    out: &Path,
) -> Result<PrecompensateOutcome> {
    let recipe = &job.recipe;
    let mut stage = StagedDir::new(out)?;
    let mut files = Vec::new();
    let mut warnings = w.warnings.clone();
    let written = written_surface(&w.result.commanded, recipe.replica_mode)?;
    let period = params.wrap_spec()?.period()?;
    let provenance = params.provenance(design)?;
    let mut report = PrecompensateOutcome {
        units: "lengths and heights in metres, efficiency as a fraction of incident power".into(),
        design: design.name.clone(),
        design_sha256: design.sha256.clone(),
        recipe: recipe.name.clone(),
        measured,
        corrected: w.corrected,
        process_model: w.model,
        level_commands: w.result.level_commands.clone(),
        piston: w.result.piston,
        max_height: w.max_height,
        deblur: w.result.deblur.clone(),
        predicted: w.prediction,
        warnings: Vec::new(),
        files: Vec::new(),
    };
    let grayscale = recipe.grayscale_extensions();
    if !grayscale.is_empty() {
        let curve = curve.ok_or_else(|| Error::malformed(&recipe.path, "no contrast_curve"))?;
        let grays = (1usize << recipe.mask_bits.min(16)).max(2);
        let (levels, heights) = surface_levels(&written, MAX_MASK_LEVELS.min(grays))?;
        let mopts = recipe.mask_options(job.force);
        let mut mask = render_levels(&levels, &heights, period, curve, &mopts, &provenance)?;
        mask.meta.precompensation = Some(serde_json::json!({
            "scan": report.measured.scan,
            "scan_sha256": report.measured.scan_sha256,
            "corrected": report.corrected,
            "process_model": report.process_model,
            "level_commands_m": report.level_commands,
            "predicted": report.predicted,
        }));
        for ext in grayscale {
            let name = format!("grayscale_mask.{ext}");
            write_mask(&mask, &stage.stage_path(&name))?;
            stage.stage_path("grayscale_mask.json");
            files.push(name);
        }
        files.push("grayscale_mask.json".into());
    }
    if recipe.outputs.contains(&Output::Stl) {
        let opts = recipe.stl_options();
        let base = written.min_max().map_or(0.0, |(lo, _)| lo);
        let lifted = written.map_values(written.values().mapv(|h| h - base), Unit::Metre)?;
        let mesh = surface_mesh(&lifted, &opts)?;
        let part = recipe.replica_mode.part_name();
        write_stl_part(&mesh, opts.unit, Some(part), &stage.stage_path("surface.stl"))?;
        files.push("surface.stl".into());
    }
    let meta = Metadata::heights(w.result.commanded.pitch())
        .with("quantity", "height")
        .with("content", "pre-compensated commanded surface, design frame (doefab precompensate)")
        .with("provenance", serde_json::to_string(&provenance).map_err(|e| Error::internal(e.to_string()))?);
    crate::io::exr::write_exr(
        &stage.stage_path("commanded.exr"),
        &[("height", &w.result.commanded.values().mapv(|v| v as f32))],
        &meta,
    )?;
    files.push("commanded.exr".into());
    files.push("precompensate.json".into());
    warnings.dedup();
    report.warnings = warnings;
    report.files = files;
    write_json(&stage.stage_path("precompensate.json"), &report)?;
    stage.commit()?;
    Ok(report)
}

/// One pass of the closed loop in simulation, on the design-frame reference `target`: the part
/// made through `process` from the plain target and its scan compared, the pre-compensated
/// surface commanded from that comparison, and the part made from it scanned and compared again
/// against the target.
#[derive(Debug, Clone)]
pub struct LoopResult {
    /// The plain mask's part against the target.
    pub before: Comparison,
    /// The pre-compensated mask's part against the target.
    pub after: Comparison,
    /// The correction made from `before`.
    pub written: Written,
}

/// Runs the loop of [`LoopResult`]: `process` is the known truth the scans are simulated
/// through (its pose, noise and missing samples included); the same `compare_opts` serve both
/// comparisons.
pub fn simulate_loop(
    design: &LoadedDesign,
    params: &ChainParams,
    process: &SimulateParams,
    compare_opts: &CompareOptions,
    corrections: &Corrections,
    curve: Option<&ContrastCurve>,
) -> Result<LoopResult> {
    let (target, levels, _) = reference_surface(design, Some(params))?;
    let before = compare(&target, &simulate_scan(&target, process)?, compare_opts)?;
    let measured = Measured::of_comparison(&before, "simulated".into(), String::new(), design.sha256.clone());
    let written = precompensate_design(target, levels, params, &measured, corrections, curve)?;
    let target = &written.target;
    let after = compare(target, &simulate_scan(&written.result.commanded, process)?, compare_opts)?;
    Ok(LoopResult { before, after, written })
}

/// One point of [`blur_sweep`]: the loop at one blur width.
#[derive(Debug, Clone, Serialize)]
pub struct SweepPoint {
    /// Blur of the simulated process, in design samples (standard deviation / pitch).
    pub blur_samples: f64,
    /// RMS of part - design over the aperture before pre-compensation, metres.
    pub rms_before: f64,
    /// RMS of part - design over the aperture after pre-compensation, metres.
    pub rms_after: f64,
    /// PSF relative L2 against the design's before pre-compensation, mean over the channels
    /// (matrix DFT, guards not enforced).
    pub psf_before: f64,
    /// PSF relative L2 against the design's after pre-compensation, mean over the channels.
    pub psf_after: f64,
    /// The blur was deconvolved (else at or below the pitch, or not resolved).
    pub deconvolved: bool,
}

/// The loop of [`simulate_loop`] at each blur width (in design samples) on top of `process`:
/// where pre-compensation of the blur stops paying.
pub fn blur_sweep(
    design: &LoadedDesign,
    params: &ChainParams,
    process: &SimulateParams,
    compare_opts: &CompareOptions,
    widths: &[f64],
    step: &mut dyn FnMut(&str),
) -> Result<Vec<SweepPoint>> {
    use crate::optics::{Method, Options};
    let pitch = design.heights.pitch()[0];
    let psf_opts = Options { allow_invalid: true, ..Default::default() };
    widths
        .iter()
        .map(|&w| {
            step(&format!("pre-compensation at a blur of {w} samples"));
            let p = SimulateParams { blur: w * pitch, ..process.clone() };
            let r = simulate_loop(design, params, &p, compare_opts, &Corrections::default(), None)?;
            let target = &r.written.target;
            let mut system = crate::optics::psf_files::system_for(target);
            system.aperture = r.before.aperture;
            let psf = |c: &Comparison| -> Result<f64> {
                let p = crate::pipeline::compare::psf_comparison(
                    target,
                    &c.surface,
                    &system,
                    Method::MatrixDft,
                    &psf_opts,
                )?;
                Ok(p.channels.iter().map(|c| c.relative_l2).sum::<f64>() / p.channels.len().max(1) as f64)
            };
            Ok(SweepPoint {
                blur_samples: w,
                rms_before: r.before.rms_error,
                rms_after: r.after.rms_error,
                psf_before: psf(&r.before)?,
                psf_after: psf(&r.after)?,
                deconvolved: r.written.result.deblur.is_some(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A few distinct heights are kept exactly; a continuous surface takes `max_levels` equal
    /// steps (an 8-bit mask's 256), each sample within half a step of its level's height.
    #[test]
    fn surface_levels_are_exact_when_few_and_equal_steps_when_many() {
        let few = Grid::new(
            ndarray::Array2::from_shape_fn((4, 5), |(i, j)| ((i + j) % 3) as f64 * 1e-7),
            [1e-6; 2],
            Unit::Metre,
        )
        .unwrap();
        let (lv, h) = surface_levels(&few, 256).unwrap();
        assert_eq!(h, vec![0.0, 1e-7, 2e-7]);
        assert!(lv.values().iter().zip(few.values()).all(|(l, v)| h[*l as usize] == *v));
        let many = Grid::new(
            ndarray::Array2::from_shape_fn((40, 50), |(i, j)| (i * 50 + j) as f64 * 1e-9),
            [1e-6; 2],
            Unit::Metre,
        )
        .unwrap();
        let (lv, h) = surface_levels(&many, 256).unwrap();
        assert_eq!(h.len(), 256);
        let step = h[1] - h[0];
        for (l, v) in lv.values().iter().zip(many.values()) {
            assert!((h[*l as usize] - v).abs() <= 0.5 * step * (1.0 + 1e-9), "{l} {v}");
        }
    }
}
