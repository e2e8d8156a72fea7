//! The fabrication commands: `fab`, `wrap`, `quantize`, `mask`, `gds`, `stl`, `bench fab`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;

use doefab::fabrication::mask::Polarity;
use doefab::fabrication::quantize::QuantizeMethod;
use doefab::fabrication::recipe::Recipe;
use doefab::fabrication::recipe_run::{self, ChainParams, DesignSource, FabOptions};
use doefab::fabrication::stl::{StlOptions, StlUnit, SurfaceChoice};
use doefab::fabrication::ReplicaMode;

use super::options::{clap_length, Cli, OpticsArgs, ReadArgs};
use super::options::{print_result, progress, report_to, warn};

/// Mesher choice on the command line.
#[derive(Clone, Copy, clap::ValueEnum)]
pub enum SurfaceArg {
    Auto,
    Terraces,
    Heightfield,
}

/// Arguments of `doefab fab`.
#[derive(Args)]
pub struct FabArgs {
    /// Height map file, or built-in:paper / built-in:fresnel (default built-in:paper).
    pub design: Option<String>,
    /// Process recipe (TOML), e.g. masks/laser-writer-grayscale.toml, or a bundled one:
    /// built-in:laser-writer-grayscale, built-in:binary-3mask-8level, built-in:two-photon-stl.
    #[arg(long, short)]
    pub recipe: PathBuf,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Override the recipe's level count.
    #[arg(long)]
    pub levels: Option<usize>,
    #[command(flatten)]
    pub read: ReadArgs,
    /// Fill NaN and non-measured heights from their neighbours instead of refusing them.
    #[arg(long)]
    pub fill: bool,
    /// Write outputs above the size limit.
    #[arg(long)]
    pub force: bool,
    /// Also write the intermediate maps: surface.exr (wrapped heights), levels.exr (the level
    /// map that `mask`, `gds` and `stl` take) and levels_preview.png.
    #[arg(long)]
    pub intermediates: bool,
}

/// Arguments of `doefab wrap`.
#[derive(Args)]
pub struct WrapArgs {
    pub design: String,
    /// Output height map (.exr, with pitch and units in its header).
    #[arg(short, long)]
    pub output: PathBuf,
    #[command(flatten)]
    pub read: ReadArgs,
    #[command(flatten)]
    pub optics: OpticsArgs,
    /// Write the master whose cast equals the design (complemented and mirrored).
    #[arg(long, value_enum, default_value_t = ReplicaMode::Design)]
    pub replica: ReplicaMode,
    #[arg(long)]
    pub fill: bool,
}

/// Arguments of `doefab quantize`.
#[derive(Args)]
pub struct QuantizeArgs {
    /// Wrapped height map (.exr from `doefab wrap`).
    pub heights: PathBuf,
    /// Output level map (.exr).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Number of levels (2..=256, or 65536 for 16-bit writers).
    #[arg(long, short = 'n')]
    pub levels: usize,
    #[arg(long, value_enum, default_value_t = QuantizeMethod::Round)]
    pub method: QuantizeMethod,
    #[command(flatten)]
    pub optics: OpticsArgs,
    /// Writer's minimum feature, for the terrace-width warning.
    #[arg(long, value_parser = clap_length, default_value = "1 um")]
    pub min_feature: f64,
}

/// Arguments of `doefab mask`.
#[derive(Args)]
pub struct MaskArgs {
    /// Level map (.exr from `doefab quantize`).
    pub levels: PathBuf,
    /// Resist contrast curve (CSV: dose,depth_nm).
    #[arg(long)]
    pub curve: PathBuf,
    /// Output image (.png, .tif or .tiff).
    #[arg(short, long)]
    pub output: PathBuf,
    #[arg(long, value_parser = clap_length, default_value = "1 um")]
    pub writer_pitch: f64,
    #[arg(long, default_value_t = 16)]
    pub bits: u8,
    #[arg(long, value_enum, default_value_t = Polarity::Positive)]
    pub polarity: Polarity,
    #[arg(long)]
    pub mirror: bool,
    #[arg(long, value_parser = clap_length, default_value = "500 um")]
    pub border: f64,
    #[arg(long, default_value = "")]
    pub label: String,
    #[arg(long)]
    pub no_marks: bool,
    #[arg(long)]
    pub force: bool,
}

/// Arguments of `doefab gds`.
#[derive(Args)]
pub struct GdsArgs {
    /// Level map (.exr from `doefab quantize`), N a power of two.
    pub levels: PathBuf,
    /// Output GDSII file.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Mask writer address grid the levels are resampled onto.
    #[arg(long, value_parser = clap_length, default_value = "1 um")]
    pub writer_pitch: f64,
    #[arg(long)]
    pub mirror: bool,
    /// Most vertices per polygon, 4..=8190 (the default, 4094, is read by every GDSII reader
    /// without a warning).
    #[arg(long, default_value_t = doefab::fabrication::gds::SIGNED_LENGTH_MAX_VERTICES)]
    pub max_vertices: usize,
}

/// Arguments of `doefab bench fab`.
#[derive(Args)]
pub struct BenchFabArgs {
    /// Height map file, or built-in:paper / built-in:fresnel (default built-in:paper).
    pub design: Option<String>,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Writer grid the GDSII sweep's level map is resampled onto.
    #[arg(long, value_parser = clap_length, default_value = "2 um")]
    pub gds_pitch: f64,
    /// Timed runs per STL and GDSII configuration (the best is reported).
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    #[command(flatten)]
    pub optics: OpticsArgs,
    #[command(flatten)]
    pub read: ReadArgs,
}

/// Arguments of `doefab stl`.
#[derive(Args)]
pub struct StlArgs {
    /// Level map (.exr from `doefab quantize`) or heights (.exr from `doefab wrap`).
    pub input: PathBuf,
    #[arg(short, long)]
    pub output: PathBuf,
    /// Length unit written into the STL: mm or um.
    #[arg(long, default_value = "mm")]
    pub unit: String,
    /// Thickness of the flat base below the lowest point.
    #[arg(long, value_parser = clap_length, default_value = "0.5 mm")]
    pub base: f64,
    /// Largest height error of the simplified mesh of a continuous surface.
    #[arg(long, value_parser = clap_length, default_value = "2 nm")]
    pub max_error: f64,
    /// Terraces (exact, for quantized maps), heightfield, or auto.
    #[arg(long, value_enum, default_value_t = SurfaceArg::Auto)]
    pub surface: SurfaceArg,
}

/// `doefab fab`.
pub fn fab(cli: &Cli, a: &FabArgs) -> Result<()> {
    let FabArgs { design, recipe, output, levels, read, fill, force, intermediates } = a;
    let mut recipe = Recipe::read(recipe)?;
    if let Some(n) = levels {
        recipe.level_count = *n;
    }
    let source = DesignSource::parse(design.as_deref(), read.options()?);
    let opts = FabOptions { fill: *fill, force: *force, intermediates: *intermediates };
    run_recipe(cli, &source, &recipe, output, &opts)
}

/// `doefab wrap`.
pub fn wrap(cli: &Cli, a: &WrapArgs) -> Result<()> {
    let WrapArgs { design, output, read, optics, replica, fill } = a;
    let source = DesignSource::parse(Some(design), read.options()?);
    let loaded = recipe_run::load_design(&source)?;
    let params = chain_params(optics, 65536, QuantizeMethod::Round, *replica, 1e-6, *fill);
    let report = recipe_run::write_wrapped(loaded, &params, output)?;
    warn(&report.warnings);
    print_result(cli, &report, || {
        println!(
            "wrapped {} samples (at most {} periods of {:.4} um); max height {:.4} um -> {}",
            report.wrap.wrapped_samples,
            report.wrap.max_wraps,
            report.wrap.period * 1e6,
            report.wrap.max_height * 1e6,
            output.display()
        )
    })
}

/// `doefab quantize`.
pub fn quantize(cli: &Cli, a: &QuantizeArgs) -> Result<()> {
    let QuantizeArgs { heights, output, levels, method, optics, min_feature } = a;
    let params = chain_params(optics, *levels, *method, ReplicaMode::Design, *min_feature, false);
    let report = recipe_run::quantize_file(heights, &params, output)?;
    warn(&report.warnings);
    print_result(cli, &report, || {
        println!(
            "{} levels ({:?}), rms error {:.2} nm -> {}",
            levels,
            method,
            report.rms_error * 1e9,
            output.display()
        );
        print_efficiency(&report.efficiency);
    })
}

/// `doefab mask`.
pub fn mask(cli: &Cli, a: &MaskArgs) -> Result<()> {
    let MaskArgs {
        levels,
        curve,
        output,
        writer_pitch,
        bits,
        polarity,
        mirror,
        border,
        label,
        no_marks,
        force,
    } = a;
    let opts = doefab::fabrication::mask::MaskOptions {
        writer_pitch: *writer_pitch,
        bits: *bits,
        polarity: *polarity,
        mirror: *mirror,
        border: *border,
        marks: !no_marks,
        label: label.clone(),
        force: *force,
        ..Default::default()
    };
    let meta = recipe_run::mask_file(levels, curve, &opts, output)?;
    print_result(cli, &meta, || {
        println!("{} x {} px, {}-bit -> {}", meta.size_px[0], meta.size_px[1], meta.bits, output.display())
    })
}

/// `doefab gds`.
pub fn gds(cli: &Cli, a: &GdsArgs) -> Result<()> {
    let GdsArgs { levels, output, writer_pitch, mirror, max_vertices } = a;
    let report = recipe_run::gds_file(levels, *writer_pitch, *mirror, *max_vertices, output)?;
    print_result(cli, &report, || {
        println!(
            "{} masks, {} polygons, {} vertices -> {}",
            report.masks.len(),
            report.polygons,
            report.vertices,
            output.display()
        );
        for m in &report.masks {
            println!("  layer {}: etch {:.1} nm, {} polygons", m.layer, m.etch_depth * 1e9, m.polygons);
        }
    })
}

/// `doefab stl`.
pub fn stl(cli: &Cli, a: &StlArgs) -> Result<()> {
    let StlArgs { input, output, unit, base, max_error, surface } = a;
    let opts = StlOptions {
        unit: StlUnit::parse(unit)?,
        base_thickness: *base,
        max_error: *max_error,
        surface: match surface {
            SurfaceArg::Auto => SurfaceChoice::Auto,
            SurfaceArg::Terraces => SurfaceChoice::Terraces,
            SurfaceArg::Heightfield => SurfaceChoice::Heightfield,
        },
    };
    let report = recipe_run::stl_file(input, &opts, output)?;
    print_result(cli, &report, || {
        println!(
            "{:?}: {} triangles ({:.2}% of naive), max height error {:.2} nm -> {}",
            report.surface,
            report.triangles,
            report.triangle_ratio * 100.0,
            report.max_height_error * 1e9,
            output.display()
        )
    })
}

/// Runs a recipe's fabrication chain with a progress bar over its steps and prints the report.
fn run_recipe(
    cli: &Cli,
    source: &DesignSource,
    recipe: &Recipe,
    output: &Path,
    opts: &FabOptions,
) -> Result<()> {
    let pb = progress(cli, recipe_run::step_count(recipe) as u64);
    let report = recipe_run::run_recipe(source, recipe, output, opts, &mut |step: &str| {
        pb.set_message(step.to_string());
        pb.inc(1);
    })
    .with_context(|| format!("recipe {}", recipe.path.display()))?;
    pb.finish_and_clear();
    warn(&report.warnings);
    print_result(cli, &report, || {
        println!("{} on {}: {}", recipe.name, report.provenance.design, output.display());
        print_efficiency(&report.efficiency);
        for a in &report.artifacts {
            println!("  {:<16} {}", a.kind, a.path.display());
        }
    })
}

/// The fabrication chain's parameters from the optics arguments and the command's own.
pub fn chain_params(
    optics: &OpticsArgs,
    level_count: usize,
    quantization: QuantizeMethod,
    replica_mode: ReplicaMode,
    min_feature: f64,
    fill: bool,
) -> ChainParams {
    ChainParams {
        wavelength: optics.wavelength,
        material: optics.material.clone(),
        order: optics.order,
        level_count,
        quantization,
        replica_mode,
        min_feature,
        fill,
    }
}

/// The predicted diffraction efficiency per wavelength (nm).
fn print_efficiency(rows: &[doefab::fabrication::quantize::EfficiencyRow]) {
    println!("  wavelength  n        detuning  eta(order)  eta(continuous)");
    for r in rows {
        println!(
            "  {:6.1} nm  {:.5}  {:.4}    {:.4}      {:.4}",
            r.wavelength * 1e9,
            r.index,
            r.detuning,
            r.efficiency,
            r.continuous_efficiency
        );
    }
}

/// Arguments of `doefab precompensate`.
#[derive(Args)]
pub struct PrecompensateArgs {
    /// Height map file, or built-in:paper / built-in:fresnel (default built-in:paper).
    pub design: Option<String>,
    /// Process recipe (TOML) of the next mask, as for `doefab fab`.
    #[arg(long, short)]
    pub recipe: PathBuf,
    /// Scan of the last part: compared with the design here.
    #[arg(long, conflicts_with = "model", required_unless_present = "model")]
    pub scan: Option<PathBuf>,
    /// The compare.json that `doefab compare` wrote for the last part.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Correct the depth scale alone, not each level's height.
    #[arg(long)]
    pub no_levels: bool,
    /// Leave the blur uncorrected.
    #[arg(long)]
    pub no_deblur: bool,
    /// Iterations of the blur deconvolution.
    #[arg(long, default_value_t = 100)]
    pub iterations: usize,
    /// Highest height the process can be commanded to make (default: the contrast curve's
    /// range, else two periods).
    #[arg(long, value_parser = clap_length)]
    pub max_height: Option<f64>,
    /// Clear-aperture diameter of the comparison (default: 5 mm for built-in:paper).
    #[arg(long, value_parser = clap_length)]
    pub aperture: Option<f64>,
    /// Scan sample pitch, e.g. "1um" (for scan files that carry none).
    #[arg(long, value_parser = clap_length)]
    pub scan_pitch: Option<f64>,
    /// Unit of the scan's stored heights, e.g. "nm" (for scan files that state none).
    #[arg(long)]
    pub scan_z_unit: Option<String>,
    #[command(flatten)]
    pub read: ReadArgs,
    /// Write masks above the size limit.
    #[arg(long)]
    pub force: bool,
}

/// `doefab precompensate`.
pub fn precompensate(cli: &Cli, a: &PrecompensateArgs) -> Result<()> {
    use doefab::pipeline::precompensate::{self as pc, Corrections, ModelSource, PrecompensateJob};
    let model = match (&a.scan, &a.model) {
        (Some(path), _) => ModelSource::Scan {
            path: path.clone(),
            options: doefab::io::scan::ScanOptions {
                pitch: a.scan_pitch.map(|p| [p, p]),
                z_unit: a.scan_z_unit.as_deref().map(doefab::units::length_unit).transpose()?,
                ..Default::default()
            },
        },
        (None, Some(path)) => ModelSource::CompareJson(path.clone()),
        (None, None) => anyhow::bail!("pass --scan or --model"),
    };
    let job = PrecompensateJob {
        design: DesignSource::parse(a.design.as_deref(), a.read.options()?),
        recipe: Recipe::read(&a.recipe)?,
        model,
        corrections: Corrections {
            levels: !a.no_levels,
            deblur: !a.no_deblur,
            iterations: a.iterations,
            max_height: a.max_height,
        },
        aperture: a.aperture,
        force: a.force,
    };
    let pb = progress(cli, 4);
    let report = pc::run(&job, &a.output, &mut |s: &str| {
        pb.inc(1);
        pb.set_message(s.to_string());
    })?;
    pb.finish_and_clear();
    warn(&report.warnings);
    print_result(cli, &report, || {
        let m = &report.measured;
        println!(
            "measured on {}: RMS {:.1} nm, depth scale {:.4}, blur {:.2} um{}",
            m.scan,
            m.rms_error * 1e9,
            m.model.depth_scale,
            m.model.blur * 1e6,
            if m.model.blur_doubt().is_none() { "" } else { " (not used)" }
        );
        for c in &report.corrected {
            println!("corrected: {c}");
        }
        let p = &report.predicted;
        println!(
            "predicted: RMS {:.1} -> {:.1} nm, depth scale {:.4} -> {:.4}",
            p.rms_before * 1e9,
            p.rms_after * 1e9,
            p.depth_scale_before,
            p.depth_scale_after
        );
        for (b, e) in p.efficiency_before.iter().zip(&p.efficiency_after) {
            println!(
                "  {:.0} nm: design-order efficiency {:.4} (design {:.4}, plain mask {:.4})",
                e.wavelength * 1e9,
                e.fabricated,
                e.design,
                b.fabricated
            );
        }
        for f in &report.files {
            println!("  {}", a.output.join(f).display());
        }
    })
}

/// `doefab bench fab`.
pub fn bench_fab(cli: &Cli, a: &BenchFabArgs) -> Result<()> {
    let BenchFabArgs { design, output, gds_pitch, repeats, optics, read } = a;
    use doefab::sweep::fab::{steps, FabSweepOptions};
    let opts = FabSweepOptions {
        wavelength: optics.wavelength,
        material: optics.material.clone(),
        order: optics.order,
        gds_pitch: *gds_pitch,
        repeats: *repeats,
        ..FabSweepOptions::default()
    };
    let design = DesignSource::parse(design.as_deref(), read.options()?);
    let pb = progress(cli, steps(&opts) as u64 + 1);
    let r = doefab::pipeline::sweep::sweep_fab(&design, &opts, output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    print_result(cli, &r, || {
        let q = &r.quantization;
        println!(
            "quantization ({} at {:.0} nm, order {}): simulated vs predicted efficiency, largest difference {:.1e}",
            q.material,
            q.design_wavelength * 1e9,
            q.order,
            q.max_difference
        );
        for n in q.points.iter().map(|p| p.level_count).collect::<std::collections::BTreeSet<_>>() {
            let row: Vec<String> = q
                .points
                .iter()
                .filter(|p| p.level_count == n)
                .map(|p| format!("{:.0} nm {:.4}", p.wavelength * 1e9, p.simulated))
                .collect();
            println!("  N = {n:<3} {}", row.join(", "));
        }
        println!("STL heightfield of {} x {} samples:", r.stl.samples[0], r.stl.samples[1]);
        for p in &r.stl.points {
            println!(
                "  max_error {:>4.0} nm: {:>8} triangles, {:.3} s, measured max {:.3} nm, RMS {:.3} nm{}",
                p.max_error * 1e9,
                p.triangles,
                p.seconds,
                p.measured_max_error * 1e9,
                p.measured_rms_error * 1e9,
                if p.within_bound { "" } else { "  OVER THE BOUND" }
            );
        }
        let g = &r.gds;
        println!(
            "GDSII {}-level mask set, {} x {} at {:.2} um (polygon area - bitmap area: at most {} nm^2):",
            g.level_count,
            g.samples[0],
            g.samples[1],
            g.pitch * 1e6,
            g.max_area_difference
        );
        for p in &g.points {
            println!(
                "  at most {:>4} vertices: {:>6} polygons, {:>7} vertices, {:.2} MB, {:.3} s",
                p.max_vertices,
                p.polygons,
                p.vertices,
                p.bytes as f64 / 1e6,
                p.seconds
            );
        }
        println!("wrote {}", output.display());
    })
}
