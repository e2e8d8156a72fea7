//! The whole fabrication chain behind `doefab fab`: load -> (fill) -> wrap -> (master) ->
//! quantize -> efficiency and feature checks -> the artifacts a recipe asks for -> report.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::design::{ExampleParams, FresnelParams};
use crate::error::{DataCause, Error, Result};
use crate::fabrication::contrast::ContrastCurve;
use crate::fabrication::gds::{write_layer_previews, write_mask_set, MaskSetOptions, MaskSetStats};
use crate::fabrication::mask::{GrayscaleMask, MaskMeta, MaskOptions};
use crate::fabrication::quantize::{
    efficiency_table, feature_check, quantize, quantize_owned, EfficiencyRow, FeatureStats, QuantizeMethod,
    Quantized,
};
use crate::fabrication::recipe::{Output, Recipe};
use crate::fabrication::stl::{
    level_heights, surface_mesh, surface_stl, write_stl_part, StlOptions, StlStats,
};
use crate::fabrication::wrap::{wrap_owned, wrap_to_master_owned, WrapSpec, WrapStats};
use crate::fabrication::{Provenance, ReplicaMode};
use crate::grid::fill::fill_missing;
use crate::grid::{Grid, Unit};
use crate::io::atomic::{write_json, StagedDir};
use crate::io::exr::write_exr;
use crate::io::heightmap::{heightmap_from_raw, read_raw, read_raw_hashed, ReadOptions};
use crate::io::png::{write_png_u16, write_png_u8};
use crate::io::raw_map::{Metadata, RawMap};
use crate::io::tiff::{write_tiff_u16, write_tiff_u8};
use crate::material::{Material, PAPER_WAVELENGTHS};

/// Where a design comes from.
#[derive(Debug, Clone)]
pub enum DesignSource {
    /// `built-in:paper` (the grating-like example) or `built-in:fresnel`.
    BuiltIn(String),
    /// A height-map file and how to read it.
    File(PathBuf, ReadOptions),
    /// Heights already in memory (metres, with their pitch), named `array` and hashed by
    /// [`grid_sha256`].
    Heights(Grid),
}

impl DesignSource {
    /// Parses a command-line design argument: `built-in:NAME` or a path.
    pub fn parse(arg: Option<&str>, read: ReadOptions) -> DesignSource {
        match arg {
            None => DesignSource::BuiltIn("paper".into()),
            Some(a) => match a.strip_prefix("built-in:") {
                Some(name) => DesignSource::BuiltIn(name.into()),
                None => DesignSource::File(PathBuf::from(a), read),
            },
        }
    }
}

/// A design height map with its name and content hash.
#[derive(Debug, Clone)]
pub struct LoadedDesign {
    /// Design heights, metres.
    pub heights: Grid,
    /// The file path as given, or `built-in:NAME`.
    pub name: String,
    /// SHA-256 (hex) of the file's bytes, or of a built-in design's parameters as JSON.
    pub sha256: String,
}

/// Loads a design. Built-in designs are hashed by their parameters.
pub fn load_design(source: &DesignSource) -> Result<LoadedDesign> {
    match source {
        DesignSource::BuiltIn(name) => {
            let (heights, params) = match name.as_str() {
                "paper" => {
                    let p = ExampleParams::default();
                    (crate::design::paper_example(&p)?, serde_json::to_vec(&p))
                }
                "fresnel" => {
                    let p = FresnelParams::default();
                    (crate::design::fresnel_lens(&p)?, serde_json::to_vec(&p))
                }
                other => {
                    return Err(Error::param(
                        "design",
                        format!(
                            "unknown built-in design '{other}' (known: built-in:paper, built-in:fresnel)"
                        ),
                    ))
                }
            };
            let bytes = params.map_err(|e| Error::internal(e.to_string()))?;
            Ok(LoadedDesign {
                heights,
                name: format!("built-in:{name}"),
                sha256: crate::io::hex_sha256(&bytes),
            })
        }
        DesignSource::File(path, read) => {
            let (raw, sha256) = read_raw_hashed(path, read.channel.as_deref())?;
            let heights = surface_from_raw(path, raw, read)?;
            Ok(LoadedDesign { heights, name: path.display().to_string(), sha256 })
        }
        DesignSource::Heights(grid) => {
            if let Some((_, (i, j))) = grid.non_finite() {
                let what = format!("the design heights at row {i}, column {j} are not finite");
                return Err(Error::data(DataCause::NotFinite, what));
            }
            Ok(LoadedDesign { heights: grid.clone(), name: "array".into(), sha256: grid_sha256(grid) })
        }
    }
}

/// SHA-256 (hex) of a grid held in memory: its shape and pitch (metres), its unit's symbol,
/// its values (metres, `f64` little-endian, row-major) and its validity mask (a byte a sample,
/// when it has one), in that order.
pub fn grid_sha256(grid: &Grid) -> String {
    let (rows, cols) = grid.dim();
    let mut bytes = Vec::with_capacity(32 + 9 * rows * cols);
    for n in [rows as u64, cols as u64] {
        bytes.extend_from_slice(&n.to_le_bytes());
    }
    for p in grid.pitch() {
        bytes.extend_from_slice(&p.to_le_bytes());
    }
    bytes.extend_from_slice(grid.unit().symbol().as_bytes());
    for v in grid.values() {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    if let Some(mask) = grid.mask() {
        bytes.extend(mask.iter().map(|&b| u8::from(b)));
    }
    crate::io::hex_sha256(&bytes)
}

/// The physical parameters of the chain (a recipe supplies them, or the command line).
#[derive(Debug, Clone, Serialize)]
pub struct ChainParams {
    /// Design wavelength, metres.
    pub wavelength: f64,
    /// DOE material name ([`Material::by_name`]).
    pub material: String,
    /// Multi-order factor p: the wrap period is `p * h_2pi`.
    pub order: u32,
    /// Number of height levels per period.
    pub level_count: usize,
    /// How heights are mapped onto levels.
    pub quantization: QuantizeMethod,
    /// Whether the outputs show the design or the master that casts it.
    pub replica_mode: ReplicaMode,
    /// Writer's smallest feature, metres.
    pub min_feature: f64,
    /// Fill NaN and non-measured samples (Laplace) instead of refusing them.
    pub fill: bool,
}

impl ChainParams {
    /// The parameters `recipe` fixes; `fill` as `doefab fab --fill` sets it.
    pub fn of_recipe(recipe: &Recipe, fill: bool) -> ChainParams {
        ChainParams {
            wavelength: recipe.wavelength,
            material: recipe.material.clone(),
            order: recipe.order,
            level_count: recipe.level_count,
            quantization: recipe.quantization,
            replica_mode: recipe.replica_mode,
            min_feature: recipe.min_feature,
            fill,
        }
    }

    /// What every output made with these parameters from `design` says of its origin.
    pub fn provenance(&self, design: &LoadedDesign) -> Result<Provenance> {
        let spec = self.wrap_spec()?;
        Ok(Provenance {
            design: design.name.clone(),
            design_sha256: design.sha256.clone(),
            replica_mode: self.replica_mode,
            wavelength_m: self.wavelength,
            material: spec.material.name.clone(),
            order: self.order,
            period_m: spec.period()?,
            level_count: self.level_count,
            quantization: format!("{:?}", self.quantization),
            doefab_version: env!("CARGO_PKG_VERSION").into(),
        })
    }

    /// The wrap these parameters fix: wavelength, material (looked up by name) and order.
    pub fn wrap_spec(&self) -> Result<WrapSpec> {
        Ok(WrapSpec {
            wavelength: self.wavelength,
            material: Material::by_name(&self.material)?,
            order: self.order,
        })
    }
}

/// The surface to make and its checks: what the chain computes before quantizing.
#[derive(Debug, Clone)]
pub struct Shaped {
    /// Wrapped heights of the surface to make (the master in master mode), metres.
    pub surface: Grid,
    /// What wrapping did.
    pub wrap: WrapStats,
    /// Local zone periods against the writer's minimum feature.
    pub features: FeatureStats,
    /// Samples filled (Laplace) because they were non-finite or not measured; 0 without `fill`.
    pub filled_samples: usize,
    /// Narrow terraces, large steps and filled samples, one sentence each.
    pub warnings: Vec<String>,
    /// What every output made from the surface says of its origin.
    pub provenance: Provenance,
}

/// Everything the chain computes before writing artifacts.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// What wrapping did.
    pub wrap: WrapStats,
    /// The level map of the surface to make.
    pub quantized: Quantized,
    /// Predicted efficiency of the design order at the paper's three wavelengths.
    pub efficiency: Vec<EfficiencyRow>,
    /// Local zone periods against the writer's minimum feature.
    pub features: FeatureStats,
    /// Samples filled (Laplace) because they were non-finite or not measured; 0 without `fill`.
    pub filled_samples: usize,
    /// Narrow terraces, large steps and filled samples, one sentence each.
    pub warnings: Vec<String>,
    /// What every output made from the levels says of its origin.
    pub provenance: Provenance,
}

/// Fill, wrap, feature check and master inversion, in the design's own storage.
pub fn shape(design: LoadedDesign, p: &ChainParams) -> Result<Shaped> {
    let spec = p.wrap_spec()?;
    let provenance = p.provenance(&design)?;
    let (heights, filled_samples) = if p.fill {
        fill_missing(&design.heights)?
    } else {
        if let Some(mask) = design.heights.mask() {
            let missing = mask.iter().filter(|v| !**v).count();
            let (i, j) = mask.indexed_iter().find(|(_, v)| !**v).map(|(ix, _)| ix).unwrap_or_default();
            let what = format!(
                "{}: {missing} samples are NaN, infinite or not measured (first at row {i}, column {j}); \
                 set `fill` to fill them from their neighbours",
                design.name
            );
            return Err(Error::data(DataCause::NotFinite, what));
        }
        // Non-finite heights are refused by `wrap`.
        (design.heights, 0)
    };
    // The master is wrapped, complemented and mirrored in one pass.
    let (surface, wrap_report) = match p.replica_mode {
        ReplicaMode::Design => wrap_owned(heights, &spec)?,
        ReplicaMode::Master => wrap_to_master_owned(heights, &spec)?,
    };
    // The zone periods are the design's: the master's gradients are the design's, negated and
    // mirrored (to the rounding of `P - h`).
    let features = feature_check(&surface, wrap_report.period, p.level_count, p.min_feature);
    let mut warnings = Vec::new();
    if features.fraction_below > 0.0 {
        warnings.push(format!(
            "{:.2}% of the samples have terraces (zone period / N) narrower than the writer's minimum feature \
             of {:.2} um; the narrowest is {:.2} um (zone period {:.2} um / {} levels)",
            features.fraction_below * 100.0,
            p.min_feature * 1e6,
            features.min_terrace_width * 1e6,
            features.min_zone_period * 1e6,
            p.level_count
        ));
    }
    if features.step_samples > 0 {
        warnings.push(format!(
            "{} samples step by more than {:.0}% of a period to a neighbour (the aperture edge, or a design \
             at or beyond its sampling limit); they are left out of the zone-period check",
            features.step_samples,
            crate::fabrication::quantize::UNDERSAMPLED_STEP * 100.0
        ));
    }
    if filled_samples > 0 {
        warnings.push(format!("{filled_samples} non-finite or non-measured samples were filled (Laplace)"));
    }
    Ok(Shaped { surface, wrap: wrap_report, features, filled_samples, warnings, provenance })
}

impl Shaped {
    /// Quantizes the surface (in its own storage) and predicts the efficiency.
    pub fn quantize(self, p: &ChainParams) -> Result<Prepared> {
        let quantized = quantize_owned(self.surface, self.wrap.period, p.level_count, p.quantization)?;
        let efficiency = efficiency_table(&p.wrap_spec()?, p.level_count, &PAPER_WAVELENGTHS)?;
        Ok(Prepared {
            wrap: self.wrap,
            quantized,
            efficiency,
            features: self.features,
            filled_samples: self.filled_samples,
            warnings: self.warnings,
            provenance: self.provenance,
        })
    }
}

/// Runs load-independent steps: fill, wrap, master inversion, quantization and checks.
pub fn prepare(design: LoadedDesign, p: &ChainParams) -> Result<Prepared> {
    shape(design, p)?.quantize(p)
}

/// One file the chain wrote.
#[derive(Debug, Clone, Serialize)]
pub struct Artifact {
    /// Where the file is, in its final place.
    pub path: PathBuf,
    /// What the file is (`level_map`, `grayscale_mask`, `gds_mask_set`, `stl`, `report_json`, ...).
    pub kind: String,
}

/// Lists `path` as an artifact of `kind`.
pub fn artifact(path: &Path, kind: &str) -> Artifact {
    Artifact { path: path.to_path_buf(), kind: kind.into() }
}

/// Metadata keys of doefab's intermediate maps (besides pitch and unit).
const KEY_QUANTITY: &str = "quantity";
const KEY_LEVEL_COUNT: &str = "level_count";
const KEY_PERIOD: &str = "period_m";
const KEY_PROVENANCE: &str = "provenance";

fn provenance_json(p: &Provenance) -> Result<String> {
    serde_json::to_string(p).map_err(|e| Error::internal(e.to_string()))
}

/// Writes wrapped heights (metres) as a float EXR with pitch, unit and provenance.
pub fn write_height_map(path: &Path, heights: &Grid, provenance: &Provenance) -> Result<()> {
    let meta = Metadata::heights(heights.pitch())
        .with(KEY_QUANTITY, "height")
        .with(KEY_PERIOD, format!("{:e}", provenance.period_m))
        .with(KEY_PROVENANCE, provenance_json(provenance)?);
    write_exr(path, &[("height", &heights.values().mapv(|v| v as f32))], &meta)
}

/// Writes a level map as a float EXR (levels are small integers, exact in f32) with its level
/// count, period and provenance.
pub fn write_level_map(path: &Path, q: &Quantized, provenance: &Provenance) -> Result<()> {
    let meta = Metadata { pitch: Some(q.levels.pitch()), unit: None, text: Vec::new() }
        .with(KEY_QUANTITY, "level")
        .with(KEY_LEVEL_COUNT, q.level_count.to_string())
        .with(KEY_PERIOD, format!("{:e}", q.period))
        .with(KEY_PROVENANCE, provenance_json(provenance)?);
    write_exr(path, &[("level", &q.levels.values().mapv(|v| v as f32))], &meta)
}

/// A level map read back: levels, level count, period and provenance.
pub struct LevelMap {
    /// Level index per sample, 0..`level_count` (`Unit::Level`).
    pub levels: Grid,
    /// Number of levels `N` per period.
    pub level_count: usize,
    /// Height of one full period (`p * h_2pi`), metres: level `l` stands for `l period / N`.
    pub period: f64,
    /// Where the map came from (its `provenance` metadata).
    pub provenance: Provenance,
}

fn meta_get<'a>(path: &Path, meta: &'a [(String, String)], key: &str) -> Result<&'a str> {
    meta.iter().find(|(k, _)| k == key).map(|(_, v)| v.as_str()).ok_or_else(|| {
        Error::malformed(
            path,
            format!("metadata '{key}' is missing: expected a level map written by `doefab quantize`"),
        )
    })
}

/// Reads a level map written by [`write_level_map`].
pub fn read_level_map(path: &Path) -> Result<LevelMap> {
    level_map_from_raw(path, read_raw(path, None)?)
}

/// The heights of a map read from `path`: a level map of doefab's (its `quantity` metadata says
/// so) as the heights its levels stand for, `l P / N` ([`level_heights`]: what the writer
/// makes), any other map as [`heightmap_from_raw`] resolves it with `opts`.
pub fn surface_from_raw(path: &Path, raw: RawMap, opts: &ReadOptions) -> Result<Grid> {
    if !raw.metadata.iter().any(|(k, v)| k == KEY_QUANTITY && v == "level") {
        return heightmap_from_raw(path, raw, opts);
    }
    if opts.unit.is_some() || opts.z_scale.is_some() || opts.z_offset.is_some() {
        return Err(Error::malformed(
            path,
            "a level map's heights come from its level count and period: drop `unit`, `z_scale` and `z_offset`",
        ));
    }
    let lm = level_map_from_raw(path, raw)?;
    level_heights(&lm.levels, lm.level_count, lm.period)
}

fn level_map_from_raw(path: &Path, raw: RawMap) -> Result<LevelMap> {
    if meta_get(path, &raw.metadata, KEY_QUANTITY)? != "level" {
        return Err(Error::malformed(path, "metadata 'quantity' is not 'level': expected a level map"));
    }
    let level_count: usize = meta_get(path, &raw.metadata, KEY_LEVEL_COUNT)?
        .parse()
        .map_err(|_| Error::malformed(path, "metadata 'level_count' is not an integer"))?;
    crate::fabrication::quantize::check_level_count(level_count)
        .map_err(|e| Error::malformed(path, format!("metadata 'level_count': {e}")))?;
    let period: f64 = meta_get(path, &raw.metadata, KEY_PERIOD)?
        .parse()
        .map_err(|_| Error::malformed(path, "metadata 'period_m' is not a number"))?;
    let provenance: Provenance = serde_json::from_str(meta_get(path, &raw.metadata, KEY_PROVENANCE)?)
        .map_err(|e| Error::malformed(path, format!("metadata 'provenance': {e}")))?;
    let pitch = raw.pitch.ok_or_else(|| Error::malformed(path, "metadata 'pitch_x'/'pitch_y' is missing"))?;
    if let Some(((i, j), v)) =
        raw.values.indexed_iter().find(|(_, v)| v.fract() != 0.0 || **v < 0.0 || **v >= level_count as f64)
    {
        return Err(Error::malformed(
            path,
            format!("sample at row {i}, column {j} is {v}, not a level in 0..{level_count}"),
        ));
    }
    Ok(LevelMap { levels: Grid::new(raw.values, pitch, Unit::Level)?, level_count, period, provenance })
}

/// Result of `doefab wrap`.
#[derive(Debug, Clone, Serialize)]
pub struct WrapOutcome {
    /// What wrapping did: period (metres), wrapped samples, heights before and after.
    pub wrap: WrapStats,
    /// Whether the heights written are the design's or the master's.
    pub replica_mode: ReplicaMode,
    /// The wrapped height map written (EXR, metres).
    pub output: PathBuf,
    /// Narrow terraces, large steps and filled samples, one sentence each.
    pub warnings: Vec<String>,
}

/// `doefab wrap`: wraps (and optionally inverts) a design and writes the heights.
pub fn write_wrapped(design: LoadedDesign, p: &ChainParams, output: &Path) -> Result<WrapOutcome> {
    let prepared = shape(design, p)?;
    write_height_map(output, &prepared.surface, &prepared.provenance)?;
    Ok(WrapOutcome {
        wrap: prepared.wrap,
        replica_mode: p.replica_mode,
        output: output.to_path_buf(),
        warnings: prepared.warnings,
    })
}

/// Result of `doefab quantize`.
#[derive(Debug, Clone, Serialize)]
pub struct QuantizeOutcome {
    /// Number of levels per period.
    pub level_count: usize,
    /// How heights were mapped onto levels.
    pub method: QuantizeMethod,
    /// RMS height error of the quantized map, metres.
    pub rms_error: f64,
    /// Predicted efficiency of the design order at the paper's three wavelengths.
    pub efficiency: Vec<EfficiencyRow>,
    /// Local zone periods against the writer's minimum feature.
    pub features: FeatureStats,
    /// The level map written (EXR).
    pub output: PathBuf,
    /// Terraces narrower than the minimum feature, if any, in a sentence.
    pub warnings: Vec<String>,
}

/// `doefab quantize`: reads wrapped heights written by `doefab wrap` and writes a level map.
pub fn quantize_file(heights: &Path, p: &ChainParams, output: &Path) -> Result<QuantizeOutcome> {
    let raw = read_raw(heights, None)?;
    let mut provenance: Provenance = match raw.metadata.iter().find(|(k, _)| k == KEY_PROVENANCE) {
        Some((_, v)) => serde_json::from_str(v)
            .map_err(|e| Error::malformed(heights, format!("metadata 'provenance': {e}")))?,
        None => Provenance {
            design: heights.display().to_string(),
            design_sha256: crate::io::file_sha256(heights)?,
            ..Default::default()
        },
    };
    let grid = crate::io::heightmap::heightmap_from_raw(heights, raw, &ReadOptions::default())?;
    let spec = p.wrap_spec()?;
    let period = spec.period()?;
    let q = quantize(&grid, period, p.level_count, p.quantization)?;
    let features = feature_check(&grid, period, p.level_count, p.min_feature);
    provenance.level_count = p.level_count;
    provenance.quantization = format!("{:?}", p.quantization);
    provenance.period_m = period;
    write_level_map(output, &q, &provenance)?;
    let mut warnings = Vec::new();
    if features.fraction_below > 0.0 {
        warnings.push(format!(
            "{:.2}% of the samples have terraces narrower than {:.2} um (narrowest {:.2} um)",
            features.fraction_below * 100.0,
            p.min_feature * 1e6,
            features.min_terrace_width * 1e6
        ));
    }
    Ok(QuantizeOutcome {
        level_count: p.level_count,
        method: p.quantization,
        rms_error: q.rms_error,
        efficiency: efficiency_table(&spec, p.level_count, &PAPER_WAVELENGTHS)?,
        features,
        output: output.to_path_buf(),
        warnings,
    })
}

/// Writes a rendered mask as PNG or TIFF (by extension) plus the JSON sidecar beside it.
pub fn write_mask(mask: &GrayscaleMask, output: &Path) -> Result<()> {
    let ext = output.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).unwrap_or_default();
    let meta = Metadata { pitch: Some(mask.meta.pitch_m), unit: None, text: Vec::new() }
        .with("content", "grayscale lithography mask: gray = round(relative dose * full scale)")
        .with("sidecar", "see the .json file of the same name for levels, doses and provenance");
    let as_u8 = || mask.gray.mapv(|g| g as u8);
    match (ext.as_str(), mask.meta.bits) {
        ("png", 16) => write_png_u16(output, &mask.gray, &meta)?,
        ("png", _) => write_png_u8(output, &as_u8(), &meta)?,
        ("tif" | "tiff", 16) => write_tiff_u16(output, &mask.gray, &meta)?,
        ("tif" | "tiff", _) => write_tiff_u8(output, &as_u8(), &meta)?,
        _ => {
            return Err(Error::param(
                "output",
                format!("{}: a mask is written as .png, .tif or .tiff", output.display()),
            ))
        }
    }
    let sidecar = output.with_extension("json");
    write_json(&sidecar, &mask.meta)
}

/// `doefab mask`: renders a level map into a grayscale mask.
pub fn mask_file(levels: &Path, curve: &Path, opts: &MaskOptions, output: &Path) -> Result<MaskMeta> {
    let lm = read_level_map(levels)?;
    let curve = ContrastCurve::read_csv(curve)?;
    let mask = crate::fabrication::mask::render(
        &lm.levels,
        lm.level_count,
        lm.period,
        &curve,
        opts,
        &lm.provenance,
    )?;
    write_mask(&mask, output)?;
    Ok(mask.meta)
}

/// What the GDSII mask set is made from.
pub struct GdsJob<'a> {
    /// Level map at any pitch.
    pub levels: &'a Grid,
    /// Number of levels `N` (a power of two: `log2 N` masks).
    pub level_count: usize,
    /// Wrap period p * h_2pi, metres.
    pub period: f64,
    /// Mask writer address grid, metres.
    pub address_grid: f64,
    /// Mirror the pattern left-right (for writing through the substrate).
    pub mirror: bool,
    /// Most vertices per polygon ([`MaskSetOptions::max_vertices`]).
    pub max_vertices: usize,
    /// Where the levels came from, written into the sidecar.
    pub provenance: &'a Provenance,
}

/// The GDSII mask set and its sidecar, with the level map resampled onto the writer's
/// address grid (nearest sample: each design sample is a flat cell). Files are created
/// through `place(name)`, which returns the path to write `name` to; returns the report and
/// the (name, kind) of every file written.
pub fn write_gds_set(
    job: &GdsJob,
    stem: &str,
    place: &mut dyn FnMut(&str) -> PathBuf,
) -> Result<(MaskSetStats, Vec<(String, &'static str)>)> {
    let GdsJob { levels, level_count, period, address_grid, mirror, max_vertices, provenance } = *job;
    let ext = levels.extent();
    let (nc, nr) = ((ext[0] / address_grid).round() as usize, (ext[1] / address_grid).round() as usize);
    let on_grid = levels.resample_to(nr, nc, [address_grid; 2], crate::grid::Interpolation::Nearest)?;
    let on_grid = if mirror { on_grid.mirror(true, false) } else { on_grid };
    let opts = MaskSetOptions { max_vertices, ..MaskSetOptions::default() };
    let gds_name = format!("{stem}.gds");
    let gds_path = place(&gds_name);
    let report = write_mask_set(&on_grid, level_count, period, &opts, &gds_path)?;
    let mut written = vec![(gds_name, "gds_mask_set")];
    let dir = gds_path.parent().map(Path::to_path_buf).unwrap_or_default();
    for p in write_layer_previews(&on_grid, level_count, &opts, &dir, stem)? {
        let name = p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        place(&name);
        written.push((name, "gds_layer_preview"));
    }
    #[derive(Serialize)]
    struct Sidecar<'a> {
        kind: &'static str,
        units: &'static str,
        mirrored: bool,
        mask_set: &'a MaskSetStats,
        provenance: &'a Provenance,
    }
    let sidecar = Sidecar {
        kind: "multi_level_binary_mask_set",
        units:
            "lengths and depths in metres; GDSII user unit 1 um, database unit 1 nm; GDS Y = -row position",
        mirrored: mirror,
        mask_set: &report,
        provenance,
    };
    let sidecar_name = format!("{stem}.json");
    write_json(&place(&sidecar_name), &sidecar)?;
    written.push((sidecar_name, "gds_sidecar"));
    Ok((report, written))
}

/// `doefab gds`: the mask set of a level map written by `doefab quantize`.
pub fn gds_file(
    levels: &Path,
    address_grid: f64,
    mirror: bool,
    max_vertices: usize,
    output: &Path,
) -> Result<MaskSetStats> {
    let lm = read_level_map(levels)?;
    let dir = output.parent().map(Path::to_path_buf).unwrap_or_default();
    let stem =
        output.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "mask_set".into());
    let job = GdsJob {
        levels: &lm.levels,
        level_count: lm.level_count,
        period: lm.period,
        address_grid,
        mirror,
        max_vertices,
        provenance: &lm.provenance,
    };
    let (report, _) = write_gds_set(&job, &stem, &mut |name| dir.join(name))?;
    Ok(report)
}

/// `doefab stl`: the STL of a level map (from `doefab quantize`) or of wrapped heights (from
/// `doefab wrap`); which one is read from the file's `quantity` metadata.
pub fn stl_file(input: &Path, opts: &StlOptions, output: &Path) -> Result<StlStats> {
    let heights = surface_from_raw(input, read_raw(input, None)?, &ReadOptions::default())?;
    surface_stl(&heights, opts, output)
}

/// Options of `doefab fab` beyond the recipe.
#[derive(Debug, Clone, Default)]
pub struct FabOptions {
    /// Fill NaN and non-measured samples (Laplace) instead of refusing them.
    pub fill: bool,
    /// Write a grayscale mask above its pixel limit anyway ([`MaskOptions::force`]).
    pub force: bool,
    /// Also write the intermediate maps: the wrapped surface (`surface.exr`), the level map
    /// (`levels.exr`, what `doefab mask`, `gds` and `stl` take) and its preview.
    pub intermediates: bool,
}

/// Everything `doefab fab` did, written as `report.json` (and summarised in `report.md`).
#[derive(Debug, Clone, Serialize)]
pub struct FabOutcome {
    /// The recipe's name.
    pub recipe: String,
    /// The recipe file, or `built-in:NAME`.
    pub recipe_path: PathBuf,
    /// The unit of each kind of value in the report (`length`, `height`, `pitch`,
    /// `wavelength`: `m`; `efficiency`: fraction of incident power).
    pub units: std::collections::BTreeMap<String, String>,
    /// Where the outputs came from: design, wavelength, material, period, levels.
    pub provenance: Provenance,
    /// `[width, height]` of the design, samples.
    pub design_size: [usize; 2],
    /// `[x, y]` design pitch, metres.
    pub design_pitch_m: [f64; 2],
    /// What wrapping did: period (metres), wrapped samples, heights before and after.
    pub wrap: WrapStats,
    /// Number of levels per period.
    pub level_count: usize,
    /// RMS height error of the quantized surface, metres.
    pub quantization_rms_error_m: f64,
    /// Predicted efficiency of the design order at the paper's three wavelengths.
    pub efficiency: Vec<EfficiencyRow>,
    /// Local zone periods against the writer's minimum feature.
    pub features: FeatureStats,
    /// The grayscale mask's sidecar; `None` when the recipe asks for no grayscale mask.
    pub mask: Option<MaskMeta>,
    /// The GDSII mask set's report; `None` when the recipe asks for none.
    pub gds: Option<MaskSetStats>,
    /// The STL's statistics; `None` when the recipe asks for no STL.
    pub stl: Option<StlStats>,
    /// What the chain found questionable (narrow terraces, filled samples, a large STL), one
    /// sentence each.
    pub warnings: Vec<String>,
    /// Every file written, the reports included.
    pub artifacts: Vec<Artifact>,
}

/// Number of progress steps `run_recipe` reports for `recipe`.
pub fn step_count(recipe: &Recipe) -> usize {
    let grayscale = recipe.outputs.iter().any(|o| matches!(o, Output::GrayscalePng | Output::GrayscaleTiff));
    3 + grayscale as usize + recipe.outputs.iter().filter(|o| matches!(o, Output::Gds | Output::Stl)).count()
}

/// `doefab fab`: the whole chain for a recipe, every artifact into `out_dir`.
/// `progress` is called once per finished step with the step's name.
pub fn run_recipe(
    source: &DesignSource,
    recipe: &Recipe,
    out_dir: &Path,
    opts: &FabOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<FabOutcome> {
    let design = load_design(source)?;
    progress("design loaded");
    let params = ChainParams::of_recipe(recipe, opts.fill);
    let shaped = shape(design, &params)?;
    let mut stage = StagedDir::new(out_dir)?;
    let mut artifacts = Vec::new();
    // The surface is written before quantization turns it into levels in place.
    if opts.intermediates {
        write_height_map(&stage.stage_path("surface.exr"), &shaped.surface, &shaped.provenance)?;
        artifacts.push(artifact(&stage.final_path("surface.exr"), "wrapped_surface"));
    }
    let prep = shaped.quantize(&params)?;
    let mut warnings = prep.warnings.clone();
    progress("wrapped and quantized");
    if opts.intermediates {
        write_level_map(&stage.stage_path("levels.exr"), &prep.quantized, &prep.provenance)?;
        artifacts.push(artifact(&stage.final_path("levels.exr"), "level_map"));
        write_png_u8(
            &stage.stage_path("levels_preview.png"),
            &level_preview(&prep.quantized),
            &Metadata {
                pitch: Some(prep.quantized.levels.pitch()),
                unit: None,
                text: vec![
                    ("content".into(), "level map preview: gray = level * 255 / (N - 1)".into()),
                    ("provenance".into(), provenance_json(&prep.provenance)?),
                ],
            },
        )?;
        artifacts.push(artifact(&stage.final_path("levels_preview.png"), "level_preview"));
    }

    let mut mask_meta = None;
    let grayscale = recipe.grayscale_extensions();
    if !grayscale.is_empty() {
        let curve_path = recipe
            .contrast_curve
            .as_ref()
            .ok_or_else(|| Error::malformed(&recipe.path, "no contrast_curve"))?;
        let curve = ContrastCurve::read_csv(curve_path)?;
        let mopts = recipe.mask_options(opts.force);
        let mask = crate::fabrication::mask::render(
            &prep.quantized.levels,
            recipe.level_count,
            prep.wrap.period,
            &curve,
            &mopts,
            &prep.provenance,
        )?;
        for ext in grayscale {
            let name = format!("grayscale_mask.{ext}");
            write_mask(&mask, &stage.stage_path(&name))?;
            stage.stage_path("grayscale_mask.json");
            artifacts.push(artifact(&stage.final_path(&name), "grayscale_mask"));
        }
        artifacts.push(artifact(&stage.final_path("grayscale_mask.json"), "mask_sidecar"));
        mask_meta = Some(mask.meta);
        progress("grayscale mask written");
    }

    let mut gds = None;
    if recipe.outputs.contains(&Output::Gds) {
        let job = GdsJob {
            levels: &prep.quantized.levels,
            level_count: recipe.level_count,
            period: prep.wrap.period,
            address_grid: recipe.address_grid,
            mirror: recipe.mask_mirror,
            max_vertices: recipe.gds_max_vertices,
            provenance: &prep.provenance,
        };
        let (report, written) = write_gds_set(&job, "mask_set", &mut |name| stage.stage_path(name))?;
        for (name, kind) in written {
            artifacts.push(artifact(&stage.final_path(&name), kind));
        }
        gds = Some(report);
        progress("GDSII mask set written");
    }

    let mut stl = None;
    if recipe.outputs.contains(&Output::Stl) {
        let opts = recipe.stl_options();
        let mesh = surface_mesh(&prep.quantized.heights()?, &opts)?;
        let part = recipe.replica_mode.part_name();
        let report = write_stl_part(&mesh, opts.unit, Some(part), &stage.stage_path("surface.stl"))?;
        artifacts.push(artifact(&stage.final_path("surface.stl"), "stl"));
        if report.triangle_ratio > 1.0 {
            warnings.push(format!(
                "the terrace STL has {} triangles, {:.0}% of a plain two-per-pixel mesh: the terraces are \
                 mostly single pixels at {} levels",
                report.triangles,
                report.triangle_ratio * 100.0,
                recipe.level_count
            ));
        }
        stl = Some(report);
        progress("STL written");
    }

    let mut units = std::collections::BTreeMap::new();
    for (k, v) in [
        ("length", "m"),
        ("height", "m"),
        ("pitch", "m"),
        ("wavelength", "m"),
        ("efficiency", "fraction of incident power"),
    ] {
        units.insert(k.to_string(), v.to_string());
    }
    let report = FabOutcome {
        recipe: recipe.name.clone(),
        recipe_path: recipe.path.clone(),
        units,
        provenance: prep.provenance.clone(),
        // The levels keep the design's sampling.
        design_size: [prep.quantized.levels.dim().1, prep.quantized.levels.dim().0],
        design_pitch_m: prep.quantized.levels.pitch(),
        wrap: prep.wrap.clone(),
        level_count: recipe.level_count,
        quantization_rms_error_m: prep.quantized.rms_error,
        efficiency: prep.efficiency.clone(),
        features: prep.features.clone(),
        mask: mask_meta,
        gds,
        stl,
        warnings,
        artifacts,
    };
    let mut report = report;
    report.artifacts.push(artifact(&stage.final_path("report.json"), "report_json"));
    report.artifacts.push(artifact(&stage.final_path("report.md"), "report_markdown"));
    write_json(&stage.stage_path("report.json"), &report)?;
    crate::io::atomic::write_bytes(&stage.stage_path("report.md"), report_markdown(&report).as_bytes())?;
    stage.commit()?;
    progress("report written");
    Ok(report)
}

/// An 8-bit preview of a level map: gray = level * 255 / (N - 1).
fn level_preview(q: &Quantized) -> ndarray::Array2<u8> {
    let scale = 255.0 / (q.level_count - 1).max(1) as f64;
    q.levels.values().mapv(|l| (l * scale).round() as u8)
}

/// The human-readable summary of a fabrication run.
pub fn report_markdown(r: &FabOutcome) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    let _ = writeln!(s, "# Fabrication report: {}\n", r.recipe);
    let _ = writeln!(s, "- design: `{}` (sha256 `{}`)", r.provenance.design, r.provenance.design_sha256);
    let _ = writeln!(
        s,
        "- {} x {} samples at {:.3} um; design wavelength {:.1} nm in {}, order p = {}",
        r.design_size[0],
        r.design_size[1],
        r.design_pitch_m[0] * 1e6,
        r.provenance.wavelength_m * 1e9,
        r.provenance.material,
        r.provenance.order
    );
    let _ = writeln!(
        s,
        "- replica mode: {:?} (outputs {} the design)",
        r.provenance.replica_mode,
        match r.provenance.replica_mode {
            ReplicaMode::Design => "are",
            ReplicaMode::Master => "are the master whose PDMS cast is",
        }
    );
    let _ = writeln!(
        s,
        "- wrap period {:.4} um; {} samples wrapped (up to {} periods); max height {:.4} um -> {:.4} um",
        r.wrap.period * 1e6,
        r.wrap.wrapped_samples,
        r.wrap.max_wraps,
        r.wrap.input_max_height * 1e6,
        r.wrap.max_height * 1e6
    );
    let _ = writeln!(
        s,
        "- {} levels ({}), rms quantization error {:.2} nm",
        r.level_count,
        r.provenance.quantization,
        r.quantization_rms_error_m * 1e9
    );
    let _ = writeln!(
        s,
        "- narrowest terrace {:.2} um (zone period {:.2} um); writer minimum feature {:.2} um\n",
        r.features.min_terrace_width * 1e6,
        r.features.min_zone_period * 1e6,
        r.features.min_feature * 1e6
    );
    let _ = writeln!(s, "## Predicted diffraction efficiency of the design order (Swanson 1989)\n");
    let _ = writeln!(s, "| wavelength | n | detuning a | {} levels | continuous |", r.level_count);
    let _ = writeln!(s, "|---|---|---|---|---|");
    for e in &r.efficiency {
        let _ = writeln!(
            s,
            "| {:.0} nm | {:.4} | {:.4} | {:.4} | {:.4} |",
            e.wavelength * 1e9,
            e.index,
            e.detuning,
            e.efficiency,
            e.continuous_efficiency
        );
    }
    if let Some(g) = &r.gds {
        let _ = writeln!(s, "\n## GDSII mask set\n");
        for m in &g.masks {
            let _ = writeln!(
                s,
                "- layer {}: etch {:.1} nm, {} polygons, {} vertices",
                m.layer,
                m.etch_depth * 1e9,
                m.polygons,
                m.vertices
            );
        }
    }
    if let Some(t) = &r.stl {
        let _ = writeln!(s, "\n## STL\n");
        let _ = writeln!(
            s,
            "- {:?} mesh in {}: {} triangles ({:.2}% of the naive two per pixel), max height error {:.2} nm, \
             max lateral deviation {:.3} um, volume {:.6e} m^3",
            t.surface,
            t.unit.symbol(),
            t.triangles,
            t.triangle_ratio * 100.0,
            t.max_height_error * 1e9,
            t.max_lateral_deviation * 1e6,
            t.volume
        );
    }
    let _ = writeln!(s, "\n## Warnings\n");
    if r.warnings.is_empty() {
        let _ = writeln!(s, "none");
    }
    for w in &r.warnings {
        let _ = writeln!(s, "- {w}");
    }
    let _ = writeln!(s, "\n## Artifacts\n");
    for a in &r.artifacts {
        let name = a.path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        if name.ends_with(".png") {
            let _ = writeln!(s, "- {}: ![{name}]({name})", a.kind);
        } else {
            let _ = writeln!(s, "- {}: `{name}`", a.kind);
        }
    }
    s
}
