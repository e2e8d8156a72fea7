//! `doefab compare-profile`: a stylus profile read ([`crate::io::profile`]), levelled, and
//! either compared with its design along a line (`crate::metrology::profile::compare_profile`,
//! against the design itself or, given the chain's parameters, the design wrapped and quantized
//! as the recipe makes it) or, without a design, measured by its own terraces
//! ([`crate::metrology::profile::terraces`]); the outputs written all at once.

use std::io::Write;
use std::path::Path;

use serde::Serialize;

use crate::error::{Error, Result};
use crate::fabrication::recipe_run::{self, ChainParams, DesignSource};
use crate::io::profile::{read_profile, ProfileReadOptions};
use crate::metrology::profile::{
    compare_profile, level_profile, terraces, Levelling, LineSpec, ProfileComparison, ProfileLevel,
    ProfileOptions, Terrace,
};
use crate::pipeline::compare::reference_surface;

/// The design side of a profile comparison.
#[derive(Debug, Clone)]
pub struct ProfileDesign {
    /// The design: built-in or a height-map file.
    pub source: DesignSource,
    /// Wrap and quantize the design as these parameters make it (a recipe, or a level count).
    pub chain: Option<ChainParams>,
    /// The line on the design the profile runs along.
    pub line: LineSpec,
    /// Settings of the comparison (`compare_profile`).
    pub options: ProfileOptions,
}

/// What `doefab compare-profile` prints and writes as `profile.json`.
#[derive(Debug, Clone, Serialize)]
pub struct CompareProfileOutcome {
    /// The profile file's path.
    pub profile: String,
    /// SHA-256 of the profile file.
    pub profile_sha256: String,
    /// What the numbers are in: lengths and heights in metres, angles in radians.
    pub units: String,
    /// Metres per stored position value.
    pub x_unit: f64,
    /// Metres per stored height value.
    pub z_unit: f64,
    /// Where `x_unit` was found: the file's header (with its line) or the option that gave it.
    pub x_unit_source: String,
    /// Where `z_unit` was found: the file's header (with its line) or the option that gave it.
    pub z_unit_source: String,
    /// Points of the profile.
    pub points: usize,
    /// Measured points: those with a finite height.
    pub valid_points: usize,
    /// The sampling step: the median spacing of the positions, metres.
    pub step: f64,
    /// The profile's length, last position minus first, metres.
    pub length: f64,
    /// The line the profile was levelled by (`z = offset + slope u`), and how it was fitted.
    pub levelling: Levelling,
    /// Without a design: the profile's own levels, lowest first, heights above the lowest.
    pub terraces: Option<Vec<Terrace>>,
    /// The design: `built-in:NAME` or its file's path; `None` without a design.
    pub design: Option<String>,
    /// SHA-256 of the design file (of its parameters' JSON for a built-in design); `None` without
    /// a design.
    pub design_sha256: Option<String>,
    /// The comparison with the design along the line; `None` without a design.
    pub comparison: Option<ProfileComparison>,
    /// The reader's warnings (the comparison's are in `comparison.warnings`).
    pub profile_warnings: Vec<String>,
    /// Files written, relative to the output folder.
    pub files: Vec<String>,
}

impl CompareProfileOutcome {
    /// Every warning: the reader's and the comparison's.
    pub fn warnings(&self) -> Vec<String> {
        let mut w = self.profile_warnings.clone();
        if let Some(c) = &self.comparison {
            w.extend(c.warnings.iter().cloned());
        }
        w
    }
}

/// Reads the profile at `path`, levels it by `level`, compares it (as read: the model has its
/// own offset and tilt) with `design`, or finds the levelled profile's terraces without one,
/// and, given `out`, writes `profile.json`, `profile_fit.csv` (position, height and, with a
/// design, the fitted model, each levelled by the levelling's line, in metres) and
/// `profile.svg` there at once.
pub fn compare_profile_file(
    path: &Path,
    read: &ProfileReadOptions,
    level: ProfileLevel,
    design: Option<&ProfileDesign>,
    out: Option<&Path>,
) -> Result<CompareProfileOutcome> {
    let file = read_profile(path, read)?;
    let (levelled, levelling) = level_profile(&file.profile, level)?;
    let (comparison, terr, dname, dsha) = match design {
        Some(d) => {
            let loaded = recipe_run::load_design(&d.source)?;
            let (reference, _, _) = reference_surface(&loaded, d.chain.as_ref())?;
            // On the profile as read: the model fits its own offset and tilt.
            let c = compare_profile(&file.profile, &reference, &d.line, &d.options)?;
            (Some(c), None, Some(loaded.name), Some(loaded.sha256))
        }
        None => (None, Some(terraces(&levelled)?), None, None),
    };
    let mut report = CompareProfileOutcome {
        profile: path.display().to_string(),
        profile_sha256: crate::io::file_sha256(path)?,
        units: "lengths and heights in metres, angles in radians".into(),
        x_unit: file.x_unit,
        z_unit: file.z_unit,
        x_unit_source: file.x_unit_source,
        z_unit_source: file.z_unit_source,
        points: levelled.len(),
        valid_points: levelled.valid_count(),
        step: levelled.step(),
        length: levelled.length(),
        levelling,
        terraces: terr,
        design: dname,
        design_sha256: dsha,
        comparison,
        profile_warnings: file.warnings,
        files: Vec::new(),
    };
    let Some(out) = out else { return Ok(report) };
    let mut stage = crate::io::atomic::StagedDir::new(out)?;
    report.files = ["profile.json", "profile_fit.csv"].map(String::from).to_vec();
    #[cfg(feature = "charts")]
    report.files.push("profile.svg".into());
    let csv = stage.stage_path("profile_fit.csv");
    type Points = Vec<(f64, f64)>;
    let (measured, model, levels): (Points, Points, Vec<f64>) = match &report.comparison {
        Some(c) => {
            // Both levelled by the levelling's line, as the profile is shown without a design.
            let (x0, lv) = (levelled.x()[0], &report.levelling);
            let line = |x: f64| lv.offset + lv.slope * (x - x0);
            (
                c.fit.iter().map(|f| (f[0], f[1] - line(f[0]))).collect(),
                c.fit.iter().map(|f| (f[0], f[2] - line(f[0]))).collect(),
                Vec::new(),
            )
        }
        None => (
            (0..levelled.len())
                .filter(|&k| levelled.is_valid(k))
                .map(|k| (levelled.x()[k], levelled.z()[k]))
                .collect(),
            Vec::new(),
            report.terraces.iter().flatten().map(|t| t.height).collect(),
        ),
    };
    crate::io::atomic::write_atomic(&csv, |w: &mut dyn Write| {
        let io = |e| Error::io(&csv, e);
        if model.is_empty() {
            writeln!(w, "position_m,levelled_height_m").map_err(io)?;
            for (x, z) in &measured {
                writeln!(w, "{x:e},{z:e}").map_err(io)?;
            }
        } else {
            writeln!(w, "position_m,levelled_height_m,model_m").map_err(io)?;
            for ((x, z), (_, m)) in measured.iter().zip(&model) {
                writeln!(w, "{x:e},{z:e},{m:e}").map_err(io)?;
            }
        }
        Ok(())
    })?;
    // The chart (feature `charts`).
    #[cfg(not(feature = "charts"))]
    let _ = levels;
    #[cfg(feature = "charts")]
    {
        // Without a design the levels are drawn above the lowest terrace, where they were measured.
        let base = report.terraces.as_ref().and_then(|_| levelled_base(&levelled, &levels)).unwrap_or(0.0);
        let shown: Vec<f64> = levels.iter().map(|h| h + base).collect();
        let title = match &report.design {
            Some(d) => format!("{} against {d}", path.display()),
            None => format!("{} (levelled), terraces", path.display()),
        };
        crate::charts::metrology::profile_chart(
            &stage.stage_path("profile.svg"),
            &measured,
            &model,
            &shown,
            &title,
        )?;
    }
    crate::io::atomic::write_json(&stage.stage_path("profile.json"), &report)?;
    stage.commit()?;
    Ok(report)
}

/// Height of the lowest terrace of a levelled profile: the mean of the points nearer to the
/// lowest level than to the next (`levels` relative to the lowest, ascending).
#[cfg(feature = "charts")]
fn levelled_base(p: &crate::metrology::profile::Profile, levels: &[f64]) -> Option<f64> {
    let gap = levels.get(1).copied()?;
    let zs: Vec<f64> = (0..p.len()).filter(|&k| p.is_valid(k)).map(|k| p.z()[k]).collect();
    let lo = zs.iter().cloned().fold(f64::INFINITY, f64::min);
    let sel: Vec<f64> = zs.into_iter().filter(|z| *z < lo + 0.5 * gap).collect();
    (!sel.is_empty()).then(|| sel.iter().sum::<f64>() / sel.len() as f64)
}
