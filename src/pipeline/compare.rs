//! `doefab compare`: a fabricated part's scan against its design, through the stages: the
//! surfaces the fabrication chain makes of the design, its family ([`reference_family`]: the
//! wrapped design and the cast of the master, from [`reference_surface`]), the comparison of
//! `crate::metrology::scan_compare` with the member the scan shows, and the design PSF
//! against the as-fabricated PSF
//! ([`psf_comparison`], by [`crate::optics`]); the outputs written all at once.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::error::{Error, Result};
use crate::fabrication::recipe_run::{self, ChainParams, DesignSource, LoadedDesign};
use crate::fabrication::wrap::{cast_of_master, WrapSpec};
use crate::fabrication::ReplicaMode;
use crate::grid::fill::fill_missing;
use crate::grid::Grid;
use crate::io::scan::{self, ScanOptions};
use crate::metrology::scan_compare::{
    compare_family, CompareOptions, Comparison, LevelSpec, Member, Reference,
};
use crate::metrology::scan_registration::Registration;
use crate::optics::system::OpticalSystem;
use crate::optics::{Method, Options};

/// Design PSF against the as-fabricated PSF, per channel.
#[derive(Debug, Clone, Serialize)]
pub struct PsfChannelComparison {
    /// Channel name ("635nm", "R", ...).
    pub name: String,
    /// The channel's wavelength, metres; `None` for a colour band without one.
    pub wavelength: Option<f64>,
    /// Peak of the as-fabricated PSF over the design PSF's peak, each in absolute terms (pixel
    /// value times captured power): the Strehl ratio with the design's PSF as the reference.
    pub strehl_vs_design: f64,
    /// `||psf_fab - psf_design|| / ||psf_design||` (each normalised to sum 1 over the crop).
    pub relative_l2: f64,
}

/// [`psf_comparison`]'s result.
#[derive(Debug, Clone, Serialize)]
pub struct PsfComparison {
    /// The propagation method both PSFs were computed by.
    pub method: String,
    /// One per channel of the system, in its order.
    pub channels: Vec<PsfChannelComparison>,
    /// Non-measured samples of the surface filled (Laplace) before propagation.
    pub filled_samples: usize,
    /// Validity conditions either run violated.
    pub warnings: Vec<String>,
}

/// The PSFs of `design` and of the as-fabricated `surface` (non-measured samples filled by
/// [`fill_missing`]) in `system` by `method`, compared channel by channel.
pub fn psf_comparison(
    design: &Grid,
    surface: &Grid,
    system: &OpticalSystem,
    method: Method,
    opts: &Options,
) -> Result<PsfComparison> {
    let (filled, filled_samples) = fill_missing(surface)?;
    let a = crate::optics::propagate::simulate(system, design, method, opts)?;
    let b = crate::optics::propagate::simulate(system, &filled, method, opts)?;
    let strehl = b.strehl(&a)?;
    let l2 = b.relative_l2(&a)?;
    let channels = a
        .channels
        .iter()
        .enumerate()
        .map(|(c, ch)| PsfChannelComparison {
            name: ch.name.clone(),
            wavelength: ch.wavelength,
            strehl_vs_design: strehl[c],
            relative_l2: l2[c],
        })
        .collect();
    let mut warnings = a.warnings.clone();
    warnings.extend(b.warnings.iter().filter(|w| !a.warnings.contains(w)).cloned());
    Ok(PsfComparison { method: method.name().into(), channels, filled_samples, warnings })
}

/// The reference surface a part is compared with: the design itself, or, given the chain's
/// parameters (a recipe or a level count), the design wrapped and quantized as the recipe makes
/// it (design side, not the master), with its level spec. Also returns the optics of the
/// efficiency prediction.
pub fn reference_surface(
    design: &LoadedDesign,
    chain: Option<&ChainParams>,
) -> Result<(Grid, Option<LevelSpec>, WrapSpec)> {
    match chain {
        None => Ok((design.heights.clone(), None, WrapSpec::default())),
        Some(p) => {
            let p = ChainParams { replica_mode: ReplicaMode::Design, ..p.clone() };
            let prep = recipe_run::prepare(design.clone(), &p)?;
            let q = prep.quantized;
            let spec = LevelSpec { count: q.level_count, step: q.period / q.level_count as f64 };
            Ok((q.heights()?, Some(spec), p.wrap_spec()?))
        }
    }
}

/// The surfaces of the design's fabrication family a scan is registered to
/// (`crate::metrology::scan_compare::compare_family`), with the optics of the efficiency
/// prediction. Given the chain's parameters: the design wrapped and quantized as the recipe
/// makes it ([`reference_surface`]) and the cast of the master written from it
/// ([`cast_of_master`]), the one the recipe makes first (the cast for a master recipe). Without:
/// the design as given, then wrapped at the optics' period and its master's cast (continuous),
/// so that a scan of a master is found with no recipe as well.
pub fn reference_family(
    design: &LoadedDesign,
    chain: Option<&ChainParams>,
) -> Result<(Vec<Reference>, WrapSpec)> {
    let (surface, levels, optics) = reference_surface(design, chain)?;
    let period = optics.period()?;
    let mut family = Vec::with_capacity(3);
    let wrapped = match chain {
        Some(_) => surface,
        None => {
            family.push(Reference { member: Member::Design, surface: surface.clone(), levels: None });
            crate::fabrication::wrap::wrap(&surface, &optics)?.0
        }
    };
    let cast = Reference { member: Member::Replica, surface: cast_of_master(&wrapped, period)?, levels };
    let wrapped = Reference { member: Member::Wrapped, surface: wrapped, levels };
    if chain.is_some_and(|p| p.replica_mode == ReplicaMode::Master) {
        family.extend([cast, wrapped]);
    } else {
        family.extend([wrapped, cast]);
    }
    Ok((family, optics))
}

/// The member of `family` named `member`: the surface a comparison found, made again (for a
/// model read back from its `compare.json`).
pub fn family_member(family: Vec<Reference>, member: Member) -> Result<Reference> {
    family.into_iter().find(|r| r.member == member).ok_or_else(|| {
        Error::param(
            "member",
            format!(
                "the comparison was made against {}, which this recipe's family does not hold; compare the \
                 scan with this recipe",
                member.name()
            ),
        )
    })
}

/// What `doefab compare` prints and writes as `compare.json`.
#[derive(Debug, Clone, Serialize)]
pub struct CompareOutcome {
    /// The scan file's path.
    pub scan: String,
    /// SHA-256 of the scan file.
    pub scan_sha256: String,
    /// The design: `built-in:NAME` or its file's path.
    pub design: String,
    /// SHA-256 of the design file (of its parameters' JSON for a built-in design).
    pub design_sha256: String,
    /// What the numbers are in: lengths and heights in metres, angles in radians.
    pub units: String,
    /// Problems the scan reader reported.
    pub scan_warnings: Vec<String>,
    /// The comparison with the family member the scan matches (its keys inline in the JSON).
    #[serde(flatten)]
    pub comparison: Comparison,
    /// Design PSF against the as-fabricated PSF; `None` when not asked for, or skipped because the
    /// method's validity guard refused the part's surface (the comparison's warnings say so).
    pub psf: Option<PsfComparison>,
    /// Files written, relative to the output folder.
    pub files: Vec<String>,
}

/// `surface.json`: how `surface.exr` was made.
#[derive(Serialize)]
struct SurfaceMeta<'a> {
    units: &'static str,
    pitch: [f64; 2],
    scan: &'a str,
    design: &'a str,
    registration: &'a Registration,
    height_reference: &'static str,
    measured_fraction: f64,
    filled_samples: usize,
}

/// Compares a scan with the member of the design's `family` it matches
/// (`compare_family`), computes the PSF comparison against that member (unless `psf` is
/// `None`; skipped with a warning where the method's validity guard refuses the part's surface
/// and the options do not force it) and writes the outputs into `out` at once: `compare.json`, `surface.exr` (the part
/// on the design grid, non-measured samples filled, readable by `doefab psf`) with
/// `surface.json`, false-colour maps `design.png`, `scan.png`, `difference.png`,
/// `profiles.png` and `histogram.png`. `step` is called before each stage.
#[allow(clippy::too_many_arguments)]
pub fn compare_and_write(
    scan: &ScanInput,
    design: &LoadedDesign,
    family: &[Reference],
    opts: &CompareOptions,
    psf: Option<(Method, &Options)>,
    out: &Path,
    step: &mut dyn FnMut(&str),
) -> Result<CompareOutcome> {
    step("register and compare");
    let mut c = compare_family(family, &scan.grid, opts)?;
    let reference = &c.reference;
    let (filled, filled_samples) = fill_missing(&c.surface)?;
    let psf = match psf {
        Some((method, o)) => {
            step("design and as-fabricated PSFs");
            let mut system = crate::optics::psf_files::system_for(reference);
            system.material = opts.optics.material.clone();
            system.aperture = c.aperture;
            match psf_comparison(reference, &filled, &system, method, o) {
                Ok(p) => Some(p),
                Err(Error::Validity { what, .. }) => {
                    c.warnings.push(format!("the PSF comparison was skipped: {what}"));
                    None
                }
                Err(e) => return Err(e),
            }
        }
        None => None,
    };
    step("write");
    let mut stage = crate::io::atomic::StagedDir::new(out)?;
    let scan_name = scan.name.clone();
    let meta = SurfaceMeta {
        units: "lengths and heights in metres, angles in radians",
        pitch: reference.pitch(),
        scan: &scan_name,
        design: &design.name,
        registration: &c.registration,
        height_reference:
            "sign(a) (z - b - tilt . x): the scan's plane and offset removed, depth errors kept",
        measured_fraction: c.measured_fraction,
        filled_samples,
    };
    let json = serde_json::to_string(&meta).map_err(|e| Error::internal(e.to_string()))?;
    let exr_meta = crate::io::raw_map::Metadata::heights(reference.pitch())
        .with("quantity", "height")
        .with("surface", json);
    crate::io::exr::write_exr(
        &stage.stage_path("surface.exr"),
        &[("height", &filled.values().mapv(|v| v as f32))],
        &exr_meta,
    )?;
    crate::io::atomic::write_json(&stage.stage_path("surface.json"), &meta)?;
    let files: Vec<String> =
        ["compare.json", "surface.exr", "surface.json"].iter().map(|s| s.to_string()).collect();
    #[cfg(feature = "charts")]
    let files = [files, write_compare_pictures(&mut stage, reference, &c)?].concat();
    let report = CompareOutcome {
        scan_sha256: scan.sha256.clone(),
        scan: scan_name,
        design: design.name.clone(),
        design_sha256: design.sha256.clone(),
        units: "lengths and heights in metres, angles in radians".into(),
        scan_warnings: scan.warnings.clone(),
        comparison: c,
        psf,
        files,
    };
    crate::io::atomic::write_json(&stage.stage_path("compare.json"), &report)?;
    stage.commit()?;
    Ok(report)
}

/// The comparison's pictures, staged in `stage`: false-colour maps `design.png`, `scan.png`,
/// `difference.png` (heights in metres), `profiles.png` and `histogram.png`; their names.
#[cfg(feature = "charts")]
fn write_compare_pictures(
    stage: &mut crate::io::atomic::StagedDir,
    reference: &Grid,
    c: &Comparison,
) -> Result<Vec<String>> {
    use crate::charts::metrology::{height_histogram, height_map, profiles, Palette};
    height_map(&stage.stage_path("design.png"), reference, "design", Palette::Sequential)?;
    height_map(&stage.stage_path("scan.png"), &c.surface, "part (registered scan)", Palette::Sequential)?;
    height_map(&stage.stage_path("difference.png"), &c.difference, "part - design", Palette::Diverging)?;
    profiles(&stage.stage_path("profiles.png"), reference, &c.surface)?;
    let heights: Vec<f64> = c
        .surface
        .values()
        .indexed_iter()
        .filter(|((i, j), _)| c.difference.is_valid(*i, *j))
        .map(|(_, v)| *v)
        .collect();
    let (dl, ml): (Vec<f64>, Vec<f64>) = c
        .levels
        .as_ref()
        .map_or((vec![], vec![]), |l| l.levels.iter().map(|s| (s.design_height, s.mean)).unzip());
    height_histogram(&stage.stage_path("histogram.png"), &heights, &dl, &ml)?;
    Ok(["design.png", "scan.png", "difference.png", "profiles.png", "histogram.png"]
        .iter()
        .map(|s| s.to_string())
        .collect())
}

/// Where the scan of a comparison comes from: a file read with its options, or heights
/// already in memory (metres, with their pitch; non-measured samples invalid).
#[derive(Debug, Clone)]
pub enum ScanSource {
    /// A scan file and how to read it.
    File(PathBuf, ScanOptions),
    /// A scan held in memory, named `array` and hashed by [`recipe_run::grid_sha256`].
    Heights(Grid),
}

/// A loaded scan with the name and hash its comparison records.
#[derive(Debug, Clone)]
pub struct ScanInput {
    /// Heights in metres; non-measured points are invalid samples.
    pub grid: Grid,
    /// The file path as given, or `array`.
    pub name: String,
    /// SHA-256 (hex) of the file's bytes, or [`recipe_run::grid_sha256`] of the heights.
    pub sha256: String,
    /// What the reader found questionable without refusing the file.
    pub warnings: Vec<String>,
}

impl ScanSource {
    /// Reads the scan (a file: by its format's reader) and checks that it holds a relief
    /// ([`crate::io::heightmap::check_relief`]).
    pub fn load(&self) -> Result<ScanInput> {
        let input = match self {
            ScanSource::File(path, opts) => {
                let scan = scan::read_scan(path, opts)?;
                ScanInput {
                    grid: scan.grid,
                    name: path.display().to_string(),
                    sha256: crate::io::file_sha256(path)?,
                    warnings: scan.warnings,
                }
            }
            ScanSource::Heights(grid) => ScanInput {
                grid: grid.clone(),
                name: "array".into(),
                sha256: recipe_run::grid_sha256(grid),
                warnings: Vec::new(),
            },
        };
        crate::io::heightmap::check_relief(Path::new(&input.name), &input.grid)?;
        Ok(input)
    }
}

/// `doefab compare`: loads the scan and the design, makes the design's reference surface
/// ([`reference_surface`] with `chain`, the design itself without) and runs
/// [`compare_and_write`] into `out`. The clear aperture is `aperture` (metres), else the
/// paper's 5 mm for `built-in:paper`, else the largest circle the design grid holds. The scan
/// reader's warnings are in the report's `scan_warnings`. `step` is called before each stage
/// (four with a PSF comparison, three without).
#[allow(clippy::too_many_arguments)]
pub fn compare_scan(
    scan: &ScanSource,
    source: &DesignSource,
    chain: Option<&ChainParams>,
    aperture: Option<f64>,
    psf: Option<(Method, &Options)>,
    out: &Path,
    step: &mut dyn FnMut(&str),
) -> Result<CompareOutcome> {
    step("read");
    let scan = scan.load()?;
    let design = recipe_run::load_design(source)?;
    let (family, optics) = reference_family(&design, chain)?;
    let opts = CompareOptions { aperture: default_aperture(source, aperture), optics, ..Default::default() };
    compare_and_write(&scan, &design, &family, &opts, psf, out, step)
}

/// How the design is made for a comparison: the recipe's chain (its level count unless
/// `levels` overrides it), or `levels` levels by rounding at `wavelength` (metres) in
/// `material` with multi-order factor `order`, or `None`: the design as it is.
pub fn comparison_chain(
    recipe: Option<&Path>,
    levels: Option<usize>,
    wavelength: f64,
    material: &str,
    order: u32,
) -> Result<Option<ChainParams>> {
    Ok(match (recipe, levels) {
        (Some(r), _) => {
            let r = crate::fabrication::recipe::Recipe::read(r)?;
            let n = levels.unwrap_or(r.level_count);
            Some(ChainParams { level_count: n, ..ChainParams::of_recipe(&r, false) })
        }
        (None, Some(n)) => Some(ChainParams {
            wavelength,
            material: material.to_string(),
            order,
            level_count: n,
            quantization: crate::fabrication::quantize::QuantizeMethod::Round,
            replica_mode: ReplicaMode::Design,
            min_feature: 1e-6,
            fill: false,
        }),
        (None, None) => None,
    })
}

/// The clear aperture of a comparison: `aperture` (metres), else the paper's 5 mm for
/// `built-in:paper`, else `None` (the largest circle the design grid holds).
pub fn default_aperture(source: &DesignSource, aperture: Option<f64>) -> Option<f64> {
    let paper = matches!(source, DesignSource::BuiltIn(n) if n == "paper");
    aperture.or(paper.then_some(crate::design::PAPER_APERTURE))
}

#[cfg(test)]
mod tests {
    use ndarray::Array2;

    use super::*;
    use crate::design::PAPER_PITCH;
    use crate::grid::blur::gaussian_blur;
    use crate::grid::Unit;

    /// Piston does not change a PSF; a small random height error lowers the peak by Marechal's
    /// `exp(-sigma_phi^2)`.
    #[test]
    fn psf_comparison_is_piston_invariant_and_follows_marechal() {
        let n = 256;
        let design = Grid::new(Array2::zeros((n, n)), [PAPER_PITCH; 2], Unit::Metre).unwrap();
        let system = OpticalSystem {
            aperture: 0.95 * n as f64 * PAPER_PITCH,
            pupil_window: n as f64 * PAPER_PITCH,
            crop: 33,
            ..Default::default()
        };
        let opts = Options { allow_invalid: true, ..Default::default() };
        let piston = design.map_values(Array2::from_elem((n, n), 0.3e-6), Unit::Metre).unwrap();
        let p = psf_comparison(&design, &piston, &system, Method::MatrixDft, &opts).unwrap();
        for c in &p.channels {
            assert!((c.strehl_vs_design - 1.0).abs() < 1e-9 && c.relative_l2 < 1e-9, "{c:?}");
        }
        // White noise blurred by 2 samples, 15 nm RMS inside the aperture.
        let mut rng = crate::rng::Lcg(4);
        let w = Grid::new(Array2::from_shape_fn((n, n), |_| rng.normal()), [PAPER_PITCH; 2], Unit::Metre)
            .unwrap();
        let w = gaussian_blur(&w, 2.0 * PAPER_PITCH).unwrap();
        let r2 = (0.5 * system.aperture).powi(2);
        let inside = |i: usize, j: usize| {
            let c = (n as f64 - 1.0) * 0.5;
            ((i as f64 - c).powi(2) + (j as f64 - c).powi(2)) * PAPER_PITCH * PAPER_PITCH <= r2
        };
        let (mut m, mut s2, mut k) = (0.0, 0.0, 0.0);
        for ((i, j), v) in w.values().indexed_iter() {
            if inside(i, j) {
                m += v;
                s2 += v * v;
                k += 1.0;
            }
        }
        let rms = (s2 / k - (m / k).powi(2)).sqrt();
        let bumpy = w.map_values(w.values().mapv(|v| 15e-9 * v / rms), Unit::Metre).unwrap();
        let p = psf_comparison(&design, &bumpy, &system, Method::MatrixDft, &opts).unwrap();
        for c in &p.channels {
            let l = c.wavelength.unwrap();
            let sigma_phi =
                2.0 * std::f64::consts::PI / l * (system.material.index(l).unwrap() - 1.0) * 15e-9;
            let want = (-sigma_phi * sigma_phi).exp();
            assert!((c.strehl_vs_design / want - 1.0).abs() < 0.01, "{c:?} vs {want}");
            assert!(c.relative_l2 > 0.0);
        }
    }
}
