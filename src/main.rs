//! The `doefab` command line: parses arguments, calls the library, prints. Nothing else.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use doefab::fabrication::chain::{self, ChainParams, DesignSource, FabOptions};
use doefab::fabrication::mask::Polarity;
use doefab::fabrication::quantize::QuantizeMethod;
use doefab::fabrication::recipe::Recipe;
use doefab::fabrication::stl::{StlOptions, StlUnit, SurfaceChoice};
use doefab::fabrication::ReplicaMode;
use doefab::io::heightmap::ReadOptions;
use doefab::units::{clap_length, length_unit};

#[derive(Parser)]
#[command(name = "doefab", version, about = "From a learned DOE design to a fabricated part", long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
    /// No progress bars and no summaries; errors and warnings still go to stderr.
    #[arg(long, short, global = true)]
    quiet: bool,
    /// Print the result as JSON on stdout.
    #[arg(long, global = true)]
    json: bool,
}

#[derive(Subcommand)]
enum Command {
    /// Simulate the RGB PSF of a height map in the paper's camera: EXR, NPY (H, W, 1, 3),
    /// log-scale PNG and a JSON summary.
    Psf {
        /// Height map file, or built-in:paper / built-in:fresnel (default built-in:paper).
        design: Option<String>,
        /// Output folder.
        #[arg(short, long)]
        output: PathBuf,
        /// Force a method (matrix_dft, fresnel, angular_spectrum or rayleigh_sommerfeld) at the
        /// DOE's pitch with --subsample; without it the automatic plan chooses everything.
        #[arg(long)]
        method: Option<String>,
        /// Sub-samples per pixel and axis (pixel integration), with --method.
        #[arg(long, default_value_t = 1)]
        subsample: usize,
        /// The plan's tolerance: relative L2 error per channel.
        #[arg(long, default_value_t = doefab::optics::plan::DEFAULT_TOLERANCE)]
        tolerance: f64,
        /// Print the plan's choices and the condition that bounds each.
        #[arg(long)]
        explain: bool,
        /// Sensor spectral response CSV (wavelength_nm,r,g,b): one channel per response column,
        /// integrated over its band (plan only).
        #[arg(long)]
        response: Option<PathBuf>,
        /// Optical system TOML (fields of the system, lengths with units: aperture = "5 mm");
        /// unset fields keep the paper's values. The plan chooses pupil_pitch and subsample.
        #[arg(long)]
        system: Option<PathBuf>,
        /// Material of the DOE (pdms, fused_silica, noa61, pmma, ip_dip).
        #[arg(long, default_value = "pdms")]
        material: String,
        /// Run even where the method's validity conditions fail (recorded as warnings).
        #[arg(long)]
        allow_invalid: bool,
        #[command(flatten)]
        read: ReadArgs,
    },
    /// Run every stage on the built-in example design (no input needed).
    Demo {
        /// Output folder.
        #[arg(short, long, default_value = "out")]
        output: PathBuf,
    },
    /// The whole fabrication chain for a recipe: wrap, quantize, masks, GDSII, STL, report.
    Fab {
        /// Height map file, or built-in:paper / built-in:fresnel (default built-in:paper).
        design: Option<String>,
        /// Process recipe (TOML), e.g. masks/laser-writer-grayscale.toml.
        #[arg(long, short)]
        recipe: PathBuf,
        /// Output folder.
        #[arg(short, long)]
        output: PathBuf,
        /// Override the recipe's level count.
        #[arg(long)]
        levels: Option<usize>,
        #[command(flatten)]
        read: ReadArgs,
        /// Fill NaN and non-measured heights from their neighbours instead of refusing them.
        #[arg(long)]
        fill: bool,
        /// Write outputs above the size limit.
        #[arg(long)]
        force: bool,
    },
    /// Wrap heights modulo p * 2 pi at the design wavelength (optionally as the replica master).
    Wrap {
        design: String,
        /// Output height map (.exr, with pitch and units in its header).
        #[arg(short, long)]
        output: PathBuf,
        #[command(flatten)]
        read: ReadArgs,
        #[command(flatten)]
        optics: OpticsArgs,
        /// Write the master whose cast equals the design (complemented and mirrored).
        #[arg(long, value_enum, default_value_t = ReplicaMode::Design)]
        replica: ReplicaMode,
        #[arg(long)]
        fill: bool,
    },
    /// Quantize wrapped heights to N levels and predict the diffraction efficiency.
    Quantize {
        /// Wrapped height map (.exr from `doefab wrap`).
        heights: PathBuf,
        /// Output level map (.exr).
        #[arg(short, long)]
        output: PathBuf,
        /// Number of levels (2..=256, or 65536 for 16-bit writers).
        #[arg(long, short = 'n')]
        levels: usize,
        #[arg(long, value_enum, default_value_t = QuantizeMethod::Round)]
        method: QuantizeMethod,
        #[command(flatten)]
        optics: OpticsArgs,
        /// Writer's minimum feature, for the terrace-width warning.
        #[arg(long, value_parser = clap_length, default_value = "1 um")]
        min_feature: f64,
    },
    /// Grayscale lithography mask (PNG or TIFF by extension) with a JSON sidecar.
    Mask {
        /// Level map (.exr from `doefab quantize`).
        levels: PathBuf,
        /// Resist contrast curve (CSV: dose,depth_nm).
        #[arg(long)]
        curve: PathBuf,
        /// Output image (.png, .tif or .tiff).
        #[arg(short, long)]
        output: PathBuf,
        #[arg(long, value_parser = clap_length, default_value = "1 um")]
        writer_pitch: f64,
        #[arg(long, default_value_t = 16)]
        bits: u8,
        #[arg(long, value_enum, default_value_t = Polarity::Positive)]
        polarity: Polarity,
        #[arg(long)]
        mirror: bool,
        #[arg(long, value_parser = clap_length, default_value = "500 um")]
        border: f64,
        #[arg(long, default_value = "")]
        label: String,
        #[arg(long)]
        no_marks: bool,
        #[arg(long)]
        force: bool,
    },
    /// Multi-level binary mask set (log2 N layers) as one GDSII file, with layer previews.
    Gds {
        /// Level map (.exr from `doefab quantize`), N a power of two.
        levels: PathBuf,
        /// Output GDSII file.
        #[arg(short, long)]
        output: PathBuf,
        /// Mask writer address grid the levels are resampled onto.
        #[arg(long, value_parser = clap_length, default_value = "1 um")]
        writer_pitch: f64,
        #[arg(long)]
        mirror: bool,
    },
    /// Watertight binary STL of a level map or of wrapped heights.
    Stl {
        /// Level map (.exr from `doefab quantize`) or heights (.exr from `doefab wrap`).
        input: PathBuf,
        #[arg(short, long)]
        output: PathBuf,
        /// Length unit written into the STL: mm or um.
        #[arg(long, default_value = "mm")]
        unit: String,
        /// Thickness of the flat base below the lowest point.
        #[arg(long, value_parser = clap_length, default_value = "0.5 mm")]
        base: f64,
        /// Largest height error of the simplified mesh of a continuous surface.
        #[arg(long, value_parser = clap_length, default_value = "2 nm")]
        max_error: f64,
        /// Terraces (exact, for quantized maps), heightfield, or auto.
        #[arg(long, value_enum, default_value_t = SurfaceArg::Auto)]
        surface: SurfaceArg,
    },
    /// A synthetic fabricated scan of a design (.x3p or .gsf): lateral blur, depth scale,
    /// offset, tilt, placement (rotation, shift, scale, mirror), complement, noise, missing points.
    SimulateScan {
        /// Height map file, or built-in:paper / built-in:fresnel.
        design: String,
        /// Output scan (.x3p or .gsf).
        #[arg(short, long)]
        output: PathBuf,
        /// Gaussian lateral blur (standard deviation), e.g. "2um".
        #[arg(long, value_parser = clap_length, default_value = "0nm")]
        blur: f64,
        #[arg(long, default_value_t = 1.0)]
        depth_scale: f64,
        /// Height offset, e.g. "100nm".
        #[arg(long, value_parser = clap_length, default_value = "0nm")]
        offset: f64,
        /// Plane slopes "SX[,SY]" (dz/dx, dz/dy), e.g. "1e-4".
        #[arg(long, default_value = "0", allow_hyphen_values = true)]
        tilt: String,
        /// Counter-clockwise rotation of the part, e.g. "0.3deg".
        #[arg(long, default_value = "0deg", allow_hyphen_values = true)]
        rotate: String,
        /// Shift of the part "X,Y", e.g. "3.2um,-1.7um".
        #[arg(long, default_value = "0um,0um", allow_hyphen_values = true)]
        shift: String,
        /// Lateral scale of the part.
        #[arg(long, default_value_t = 1.0)]
        scale: f64,
        /// The part is mirrored (x -> -x), as a replica is.
        #[arg(long)]
        mirror: bool,
        /// The part is the height complement of the design (a cast).
        #[arg(long)]
        complement: bool,
        /// White Gaussian noise (standard deviation), e.g. "20nm".
        #[arg(long, value_parser = clap_length, default_value = "0nm")]
        noise: f64,
        /// Fraction of non-measured points, e.g. "5%".
        #[arg(long, default_value = "0")]
        missing: String,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Scan pitch (default: the design's).
        #[arg(long, value_parser = clap_length)]
        scan_pitch: Option<f64>,
        /// Scan size "N" or "COLSxROWS" (default: the design's extent).
        #[arg(long)]
        size: Option<String>,
        #[command(flatten)]
        read: ReadArgs,
    },
    /// What a profilometer scan holds: size, pitch, units, valid fraction, warnings, ISO 25178
    /// height parameters (raw and after removing the least-squares plane).
    ScanInfo {
        /// Scan file (.x3p, .gsf, .sdf, .sur, .dat, .xyz, .txt/.csv/.asc, .png, .tif, .npy).
        file: PathBuf,
        /// Sample pitch, e.g. "1um" (for files that carry none).
        #[arg(long, value_parser = clap_length)]
        pitch: Option<f64>,
        /// Unit of the stored heights, e.g. "nm" (for files that state none).
        #[arg(long, visible_alias = "unit")]
        z_unit: Option<String>,
        /// Height per count for integer images without a scale, e.g. "0.1nm".
        #[arg(long, value_parser = clap_length)]
        z_scale: Option<f64>,
    },
}

/// Mesher choice on the command line.
#[derive(Clone, Copy, clap::ValueEnum)]
enum SurfaceArg {
    Auto,
    Terraces,
    Heightfield,
}

/// How to read a height map that does not say everything about itself.
#[derive(Args, Clone, Default)]
struct ReadArgs {
    /// Sample pitch, e.g. "4.29um" (required when the file carries none).
    #[arg(long, value_parser = clap_length)]
    pitch: Option<f64>,
    /// Unit of the stored heights, e.g. "um" or "nm" (required when the file carries none).
    #[arg(long)]
    unit: Option<String>,
    /// Height per count for integer images (16-bit PNG/TIFF), e.g. "0.1nm".
    #[arg(long, value_parser = clap_length)]
    z_scale: Option<f64>,
}

impl ReadArgs {
    fn options(&self) -> Result<ReadOptions> {
        Ok(ReadOptions {
            pitch: self.pitch.map(|p| [p, p]),
            unit: self.unit.as_deref().map(length_unit).transpose()?,
            z_scale: self.z_scale,
            ..Default::default()
        })
    }
}

/// Design wavelength, material, multi-order factor.
#[derive(Args, Clone)]
struct OpticsArgs {
    /// Design wavelength.
    #[arg(long, value_parser = clap_length, default_value = "530nm")]
    wavelength: f64,
    /// Material of the part (pdms, fused_silica).
    #[arg(long, default_value = "pdms")]
    material: String,
    /// Multi-order factor p (wrap modulo p * 2 pi).
    #[arg(long, default_value_t = 1)]
    order: u32,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(&cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            for cause in e.chain().skip(1) {
                eprintln!("  caused by: {cause}");
            }
            ExitCode::from(2)
        }
    }
}

/// A progress bar over `steps` named steps (hidden with --quiet or --json).
fn progress(cli: &Cli, steps: u64) -> ProgressBar {
    if cli.quiet || cli.json {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(steps);
    if let Ok(style) = ProgressStyle::with_template("{bar:30} {pos}/{len} {elapsed_precise} {msg}") {
        pb.set_style(style);
    }
    pb
}

fn print_result<T: serde::Serialize>(cli: &Cli, value: &T, human: impl FnOnce()) -> Result<()> {
    if cli.json {
        println!("{}", serde_json::to_string_pretty(value)?);
    } else if !cli.quiet {
        human();
    }
    Ok(())
}

fn warn(warnings: &[String]) {
    for w in warnings {
        eprintln!("warning: {w}");
    }
}

fn run(cli: &Cli) -> Result<()> {
    match &cli.command {
        Command::Psf {
            design,
            output,
            method,
            subsample,
            tolerance,
            explain,
            response,
            system: system_file,
            material,
            allow_invalid,
            read,
        } => {
            use doefab::optics::{output as psf_out, plan, spectrum, Method, Options};
            let loaded = chain::load_design(&DesignSource::parse(design.as_deref(), read.options()?))?;
            let mut system = psf_out::system_for(&loaded.heights);
            system.material = doefab::material::Material::by_name(material)?;
            if let Some(p) = system_file {
                system = doefab::optics::system::OpticalSystem::read_toml(p, &system)?;
            }
            let report = if let Some(method) = method {
                if response.is_some() {
                    bail!("--response needs the automatic plan: leave out --method");
                }
                system.subsample = *subsample;
                let opts = Options { allow_invalid: *allow_invalid, ..Default::default() };
                psf_out::simulate_and_write(
                    &loaded.heights,
                    &system,
                    Method::from_name(method)?,
                    &opts,
                    output,
                )?
            } else {
                let bands = match response {
                    Some(p) => spectrum::read_response_csv(p)?,
                    None => Vec::new(),
                };
                let plan = plan::plan(&system, &loaded.heights, &bands, *tolerance)?;
                if *explain {
                    eprint!("{}", plan.explain());
                }
                let pb = progress(cli, 1);
                pb.set_message(format!(
                    "PSF by {} ({} wavelengths)",
                    plan.method,
                    plan.system.wavelengths.len()
                ));
                let r = psf_out::plan_and_write(&loaded.heights, &plan, &bands, output)?;
                pb.finish_and_clear();
                r
            };
            warn(&report.warnings);
            print_result(cli, &report, || {
                for c in &report.channels {
                    println!(
                        "{}: peak {:.3e} at ({:.2}, {:.2}) um, Strehl {:.3}, captured {:.4}",
                        c.summary.name,
                        c.summary.peak,
                        c.summary.peak_position[0] * 1e6,
                        c.summary.peak_position[1] * 1e6,
                        c.strehl.unwrap_or(f64::NAN),
                        c.summary.captured.unwrap_or(f64::NAN)
                    );
                }
                println!("wrote {}", output.display());
            })
        }
        Command::Demo { output } => demo(cli, output),
        Command::Fab { design, recipe, output, levels, read, fill, force } => {
            let mut recipe = Recipe::read(recipe)?;
            if let Some(n) = levels {
                recipe.level_count = *n;
            }
            let source = DesignSource::parse(design.as_deref(), read.options()?);
            fab(cli, &source, &recipe, output, *fill, *force)
        }
        Command::Wrap { design, output, read, optics, replica, fill } => {
            let source = DesignSource::parse(Some(design), read.options()?);
            let loaded = chain::load_design(&source)?;
            let params = chain_params(optics, 65536, QuantizeMethod::Round, *replica, 1e-6, *fill);
            let report = chain::write_wrapped(&loaded, &params, output)?;
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
        Command::Quantize { heights, output, levels, method, optics, min_feature } => {
            let params = chain_params(optics, *levels, *method, ReplicaMode::Design, *min_feature, false);
            let report = chain::quantize_file(heights, &params, output)?;
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
        Command::Mask {
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
        } => {
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
            let meta = chain::mask_file(levels, curve, &opts, output)?;
            print_result(cli, &meta, || {
                println!(
                    "{} x {} px, {}-bit -> {}",
                    meta.size_px[0],
                    meta.size_px[1],
                    meta.bits,
                    output.display()
                )
            })
        }
        Command::SimulateScan {
            design,
            output,
            blur,
            depth_scale,
            offset,
            tilt,
            rotate,
            shift,
            scale,
            mirror,
            complement,
            noise,
            missing,
            seed,
            scan_pitch,
            size,
            read,
        } => {
            use doefab::metrology::simulate as sim;
            let loaded = chain::load_design(&DesignSource::parse(Some(design), read.options()?))?;
            let params = sim::SimulateParams {
                blur: *blur,
                depth_scale: *depth_scale,
                offset: *offset,
                tilt: sim::parse_slopes(tilt)?,
                pose: doefab::metrology::register::Pose {
                    mirror: *mirror,
                    rotation: doefab::units::parse_angle(rotate)?,
                    scale: *scale,
                    shift: sim::parse_length_pair(shift)?,
                },
                complement: *complement,
                noise: *noise,
                missing: doefab::units::parse_fraction(missing)?,
                seed: *seed,
                pitch: scan_pitch.map(|p| [p, p]),
                size: size.as_deref().map(sim::parse_size).transpose()?,
            };
            let scan = sim::simulate_scan(&loaded.heights, &params)?;
            sim::write_scan(output, &scan)?;
            let (rows, cols) = scan.dim();
            print_result(cli, &params, || {
                println!(
                    "{} x {} scan of {} ({:.1}% measured) -> {}",
                    cols,
                    rows,
                    loaded.name,
                    100.0 * scan.valid_count() as f64 / (rows * cols) as f64,
                    output.display()
                )
            })
        }
        Command::ScanInfo { file, pitch, z_unit, z_scale } => {
            let opts = doefab::io::scan::ScanOptions {
                pitch: pitch.map(|p| [p, p]),
                z_unit: z_unit.as_deref().map(length_unit).transpose()?,
                z_scale: *z_scale,
                ..Default::default()
            };
            let info = doefab::metrology::info::scan_info(file, &opts)?;
            warn(&info.warnings);
            print_result(cli, &info, || print!("{}", info.summary()))
        }
        Command::Gds { levels, output, writer_pitch, mirror } => {
            let report = chain::gds_file(levels, *writer_pitch, *mirror, output)?;
            print_result(cli, &report, || {
                println!(
                    "{} masks, {} polygons, {} vertices -> {}",
                    report.masks.len(),
                    report.polygons,
                    report.vertices,
                    output.display()
                );
                for m in &report.masks {
                    println!(
                        "  layer {}: etch {:.1} nm, {} polygons",
                        m.layer,
                        m.etch_depth * 1e9,
                        m.polygons
                    );
                }
            })
        }
        Command::Stl { input, output, unit, base, max_error, surface } => {
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
            let report = chain::stl_file(input, &opts, output)?;
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
    }
}

fn chain_params(
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

fn fab(
    cli: &Cli,
    source: &DesignSource,
    recipe: &Recipe,
    output: &Path,
    fill: bool,
    force: bool,
) -> Result<()> {
    let pb = progress(cli, chain::step_count(recipe) as u64);
    let opts = FabOptions { fill, force };
    let report = chain::run_recipe(source, recipe, output, &opts, &mut |step: &str| {
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

fn demo(cli: &Cli, output: &Path) -> Result<()> {
    let masks = Path::new(env!("CARGO_MANIFEST_DIR")).join("masks");
    let names = ["laser-writer-grayscale", "binary-3mask-8level", "two-photon-stl"];
    let source = DesignSource::BuiltIn("paper".into());
    let mut reports = Vec::new();
    for name in names {
        let path = masks.join(format!("{name}.toml"));
        if !path.exists() {
            bail!("the bundled recipe {} is missing", path.display());
        }
        let recipe = Recipe::read(&path)?;
        let out = output.join(name);
        let pb = progress(cli, chain::step_count(&recipe) as u64);
        let report = chain::run_recipe(&source, &recipe, &out, &FabOptions::default(), &mut |step: &str| {
            pb.set_message(format!("{name}: {step}"));
            pb.inc(1);
        })?;
        pb.finish_and_clear();
        warn(&report.warnings);
        if !cli.quiet && !cli.json {
            println!("{name}: {}", out.join("report.md").display());
            for a in &report.artifacts {
                println!("  {:<16} {}", a.kind, a.path.display());
            }
        }
        reports.push(report);
    }
    // The optics stage: the built-in design's RGB PSF as the plan chooses it.
    use doefab::optics::{output as psf_out, plan};
    let loaded = chain::load_design(&source)?;
    let system = psf_out::system_for(&loaded.heights);
    let psf_dir = output.join("psf");
    let plan = plan::plan(&system, &loaded.heights, &[], plan::DEFAULT_TOLERANCE)?;
    let pb = progress(cli, 1);
    pb.set_message(format!("PSF of the built-in design by {}", plan.method));
    let psf = psf_out::plan_and_write(&loaded.heights, &plan, &[], &psf_dir)?;
    pb.finish_and_clear();
    warn(&psf.warnings);
    if cli.json {
        let all = serde_json::json!({ "fabrication": reports, "psf": psf });
        println!("{}", serde_json::to_string_pretty(&all)?);
    } else if !cli.quiet {
        println!("psf: {}", psf_dir.display());
        for f in &psf.files {
            println!("  {}", psf_dir.join(f).display());
        }
    }
    Ok(())
}
