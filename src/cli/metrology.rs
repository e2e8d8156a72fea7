//! The metrology commands: `simulate-scan`, `compare`, `compare-profile`, `scan-info`.

use std::path::{Path, PathBuf};

use anyhow::Result;
use clap::Args;

use doefab::fabrication::recipe_run::{self, ChainParams, DesignSource};
use doefab::units::length_unit;

use super::options::{clap_length, Cli, OpticsArgs, ReadArgs};
use super::options::{print_result, progress, report_to, warn};

/// Levelling choice on the command line (`scan-info --level`).
#[derive(Clone, Copy, PartialEq, clap::ValueEnum)]
pub enum LevelArg {
    Plane,
    Facet,
    Substrate,
}

/// Arguments of `doefab simulate-scan`.
#[derive(Args)]
pub struct SimulateScanArgs {
    /// Height map file, or built-in:paper / built-in:fresnel.
    pub design: String,
    /// Output scan (.x3p or .gsf).
    #[arg(short, long)]
    pub output: PathBuf,
    /// The process's height response before the blur, commanded:made pairs, e.g.
    /// "0nm:0nm,600nm:660nm,1.2um:1.2um" (piecewise linear, extended linearly).
    #[arg(long)]
    pub response: Option<String>,
    /// Gaussian lateral blur (standard deviation), e.g. "2um".
    #[arg(long, value_parser = clap_length, default_value = "0nm")]
    pub blur: f64,
    #[arg(long, default_value_t = 1.0)]
    pub depth_scale: f64,
    /// Height offset, e.g. "100nm".
    #[arg(long, value_parser = clap_length, default_value = "0nm")]
    pub offset: f64,
    /// Plane slopes "SX[,SY]" (dz/dx, dz/dy), e.g. "1e-4".
    #[arg(long, default_value = "0", allow_hyphen_values = true)]
    pub tilt: String,
    /// Counter-clockwise rotation of the part, e.g. "0.3deg".
    #[arg(long, default_value = "0deg", allow_hyphen_values = true)]
    pub rotate: String,
    /// Shift of the part "X,Y", e.g. "3.2um,-1.7um".
    #[arg(long, default_value = "0um,0um", allow_hyphen_values = true)]
    pub shift: String,
    /// Lateral scale of the part.
    #[arg(long, default_value_t = 1.0)]
    pub scale: f64,
    /// The part is mirrored (x -> -x), as a replica is.
    #[arg(long)]
    pub mirror: bool,
    /// The part is the height complement of the design (a cast).
    #[arg(long)]
    pub complement: bool,
    /// White Gaussian noise (standard deviation), e.g. "20nm".
    #[arg(long, value_parser = clap_length, default_value = "0nm")]
    pub noise: f64,
    /// Fraction of non-measured points, e.g. "5%".
    #[arg(long, default_value = "0")]
    pub missing: String,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Scan pitch (default: the design's).
    #[arg(long, value_parser = clap_length)]
    pub scan_pitch: Option<f64>,
    /// Scan size "N" or "COLSxROWS" (default: the design's extent).
    #[arg(long)]
    pub size: Option<String>,
    #[command(flatten)]
    pub read: ReadArgs,
}

/// Arguments of `doefab compare`.
#[derive(Args)]
pub struct CompareArgs {
    /// Scan file (.x3p, .gsf, .sdf, .sur, .gwy, .opd, .opdx, .plu, .al3d, .tmd, .datx, .dat, .xyz, .txt/.csv/.asc, .png, .tif,
    /// .npy).
    pub scan: PathBuf,
    /// Height map file, or built-in:paper / built-in:fresnel.
    #[arg(long)]
    pub design: String,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Process recipe: compare with the design wrapped and quantized as it makes it.
    #[arg(long)]
    pub recipe: Option<PathBuf>,
    /// Level count (overrides the recipe's; without a recipe, wraps and quantizes the
    /// design at --wavelength / --material / --order).
    #[arg(long)]
    pub levels: Option<usize>,
    /// Clear-aperture diameter (default: 5 mm for built-in:paper, else the largest circle
    /// in the design grid).
    #[arg(long, value_parser = clap_length)]
    pub aperture: Option<f64>,
    /// PSF method for the design vs as-fabricated comparison, or "none".
    #[arg(long, default_value = "matrix_dft")]
    pub psf_method: String,
    /// Compute the PSFs even where the method's validity conditions fail (as warnings).
    #[arg(long)]
    pub allow_invalid: bool,
    /// Scan sample pitch, e.g. "1um" (for scan files that carry none).
    #[arg(long, value_parser = clap_length)]
    pub scan_pitch: Option<f64>,
    /// Unit of the scan's stored heights, e.g. "nm" (for scan files that state none).
    #[arg(long)]
    pub scan_z_unit: Option<String>,
    /// Height per count of an integer scan image without a scale, e.g. "0.1nm".
    #[arg(long, value_parser = clap_length)]
    pub scan_z_scale: Option<f64>,
    #[command(flatten)]
    pub read: ReadArgs,
    #[command(flatten)]
    pub optics: OpticsArgs,
}

/// Levelling choice of `compare-profile --level`.
#[derive(Clone, Copy, PartialEq, clap::ValueEnum)]
pub enum ProfileLevelArg {
    Line,
    Substrate,
}

/// Arguments of `doefab compare-profile`.
#[derive(Args)]
pub struct CompareProfileArgs {
    /// Stylus profile export (CSV or TXT: header, then position and height columns).
    pub profile: PathBuf,
    /// Height map file, or built-in:paper / built-in:fresnel (none: the profile's own terraces).
    pub design: Option<String>,
    /// The line on the design, "x0,y0,x1,y1" from its centre (x along columns, y along rows),
    /// e.g. "-1mm,0,1mm,0.2mm"; the profile's first point at (x0, y0).
    #[arg(long, allow_hyphen_values = true, conflicts_with = "angle")]
    pub line: Option<String>,
    /// The line through the design's centre at this angle (counter-clockwise from +x), e.g.
    /// "30deg"; the profile centred on the centre.
    #[arg(long, allow_hyphen_values = true)]
    pub angle: Option<String>,
    /// Levelling of the profile: least-squares line, or a line through the substrate (lowest level).
    #[arg(long, value_enum, default_value_t = ProfileLevelArg::Line)]
    pub level: ProfileLevelArg,
    /// Process recipe: compare with the design wrapped and quantized as it makes it.
    #[arg(long)]
    pub recipe: Option<PathBuf>,
    /// Level count (overrides the recipe's; without a recipe, wraps and quantizes the design
    /// at --wavelength / --material / --order).
    #[arg(long)]
    pub levels: Option<usize>,
    /// Unit of the position column, e.g. "um" (for files whose header names none).
    #[arg(long)]
    pub x_unit: Option<String>,
    /// Unit of the height column, e.g. "nm" or "A" (for files whose header names none).
    #[arg(long)]
    pub z_unit: Option<String>,
    /// How far along the line the profile's start may be from where the line puts it.
    #[arg(long, value_parser = clap_length, default_value = "50um")]
    pub along_search: f64,
    /// How far across the line the profile may lie from it.
    #[arg(long, value_parser = clap_length, default_value = "10um")]
    pub across_search: f64,
    /// Output folder (profile.json, profile_fit.csv, profile.svg).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    #[command(flatten)]
    pub read: ReadArgs,
    #[command(flatten)]
    pub optics: OpticsArgs,
}

/// Arguments of `doefab scan-info`.
#[derive(Args)]
pub struct ScanInfoArgs {
    /// Scan file (.x3p, .gsf, .sdf, .sur, .gwy, .opd, .opdx, .plu, .al3d, .tmd, .datx, .dat, .xyz, .txt/.csv/.asc, .png, .tif,
    /// .npy).
    pub file: PathBuf,
    /// Sample pitch, e.g. "1um" (for files that carry none).
    #[arg(long, value_parser = clap_length)]
    pub pitch: Option<f64>,
    /// Unit of the stored heights, e.g. "nm" (for files that state none).
    #[arg(long, visible_alias = "unit")]
    pub z_unit: Option<String>,
    /// Height per count for integer images without a scale, e.g. "0.1nm".
    #[arg(long, value_parser = clap_length)]
    pub z_scale: Option<f64>,
    /// Levelling before the "levelled" statistics: least-squares plane, facet levelling, or
    /// a plane through the substrate (outside `--aperture`, else the lowest level).
    #[arg(long, value_enum, default_value_t = LevelArg::Plane)]
    pub level: LevelArg,
    /// Diameter of the part's aperture, centred on the scan, for `--level substrate`.
    #[arg(long, value_parser = clap_length)]
    pub aperture: Option<f64>,
}

/// `doefab simulate-scan`.
pub fn simulate_scan(cli: &Cli, a: &SimulateScanArgs) -> Result<()> {
    let SimulateScanArgs {
        design,
        response,
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
    } = a;
    use doefab::metrology::{
        parse_length_pair, parse_size, parse_slopes, simulate_scan, write_scan, SimulateParams,
    };
    let loaded = recipe_run::load_design(&DesignSource::parse(Some(design), read.options()?))?;
    let params = SimulateParams {
        response: response.as_deref().map(doefab::fabrication::precompensate::Response::parse).transpose()?,
        blur: *blur,
        depth_scale: *depth_scale,
        offset: *offset,
        tilt: parse_slopes(tilt)?,
        pose: doefab::metrology::Pose {
            mirror: *mirror,
            rotation: doefab::units::parse_angle(rotate)?,
            scale: *scale,
            shift: parse_length_pair(shift)?,
        },
        complement: *complement,
        noise: *noise,
        missing: doefab::units::parse_fraction(missing)?,
        seed: *seed,
        pitch: scan_pitch.map(|p| [p, p]),
        size: size.as_deref().map(parse_size).transpose()?,
    };
    let scan = simulate_scan(&loaded.heights, &params)?;
    write_scan(output, &scan)?;
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

/// `doefab compare`.
pub fn compare(cli: &Cli, a: &CompareArgs) -> Result<()> {
    let CompareArgs {
        scan,
        design,
        output,
        recipe,
        levels,
        aperture,
        psf_method,
        allow_invalid,
        scan_pitch,
        scan_z_unit,
        scan_z_scale,
        read,
        optics,
    } = a;
    let scan_opts = doefab::io::scan::ScanOptions {
        pitch: scan_pitch.map(|p| [p, p]),
        z_unit: scan_z_unit.as_deref().map(length_unit).transpose()?,
        z_scale: *scan_z_scale,
        ..Default::default()
    };
    let source = DesignSource::parse(Some(design), read.options()?);
    let chain = optics.comparison_chain(recipe.as_deref(), *levels)?;
    let psf = (psf_method != "none").then(|| doefab::optics::Method::from_name(psf_method)).transpose()?;
    let psf =
        psf.map(|m| (m, doefab::optics::Options { allow_invalid: *allow_invalid, ..Default::default() }));
    let scan = doefab::pipeline::compare::ScanSource::File(scan.clone(), scan_opts);
    let report = compare_scan(cli, &scan, &source, chain.as_ref(), *aperture, psf, output)?;
    warn_comparison(&report);
    print_result(cli, &report, || print_comparison(&report, output))
}

/// `doefab compare-profile`.
pub fn compare_profile(cli: &Cli, a: &CompareProfileArgs) -> Result<()> {
    let CompareProfileArgs {
        profile,
        design,
        line,
        angle,
        level,
        recipe,
        levels,
        x_unit,
        z_unit,
        along_search,
        across_search,
        output,
        read,
        optics,
    } = a;
    use doefab::metrology::{LineSpec, ProfileLevel, ProfileOptions};
    use doefab::pipeline::compare_profile::{compare_profile_file, ProfileDesign};
    let read_opts = doefab::io::profile::ProfileReadOptions {
        x_unit: x_unit.as_deref().map(doefab::io::profile::profile_unit_arg).transpose()?,
        z_unit: z_unit.as_deref().map(doefab::io::profile::profile_unit_arg).transpose()?,
    };
    let level = match level {
        ProfileLevelArg::Line => ProfileLevel::Line,
        ProfileLevelArg::Substrate => ProfileLevel::Substrate,
    };
    let design = match design {
        None => {
            if line.is_some() || angle.is_some() || recipe.is_some() || levels.is_some() {
                anyhow::bail!("--line, --angle, --recipe and --levels need a DESIGN to compare with");
            }
            None
        }
        Some(d) => {
            let line = match (line, angle) {
                (Some(l), None) => LineSpec::parse_points(l)?,
                (None, Some(t)) => LineSpec::Angle { angle: doefab::units::parse_angle(t)? },
                _ => anyhow::bail!("name the line on the design: --line x0,y0,x1,y1 or --angle A"),
            };
            let chain = optics.comparison_chain(recipe.as_deref(), *levels)?;
            Some(ProfileDesign {
                source: DesignSource::parse(Some(d), read.options()?),
                chain,
                line,
                options: ProfileOptions {
                    along_search: *along_search,
                    across_search: *across_search,
                    ..Default::default()
                },
            })
        }
    };
    let report = compare_profile_file(profile, &read_opts, level, design.as_ref(), output.as_deref())?;
    warn(&report.warnings());
    print_result(cli, &report, || print_profile(&report, output.as_deref()))
}

/// A profile comparison, or a profile's terraces, for a person (lengths in um, heights in nm).
fn print_profile(r: &doefab::pipeline::compare_profile::CompareProfileOutcome, output: Option<&Path>) {
    println!(
        "{} points ({} measured), step {:.4} um, length {:.2} um; levelled by {}: slope {:.4e}, rms {:.2} nm \
         over {} points",
        r.points,
        r.valid_points,
        r.step * 1e6,
        r.length * 1e6,
        match r.levelling.method {
            doefab::metrology::ProfileLevel::Line => "line",
            doefab::metrology::ProfileLevel::Substrate => "substrate",
        },
        r.levelling.slope,
        r.levelling.rms * 1e9,
        r.levelling.points
    );
    if let Some(t) = &r.terraces {
        for (k, l) in t.iter().enumerate() {
            println!(
                "  level {k}: {:.2} +- {:.2} nm above the lowest ({} points, {} terraces, spread {:.2} nm)",
                l.height * 1e9,
                l.height_sigma * 1e9,
                l.points,
                l.runs,
                l.std * 1e9
            );
        }
    }
    if let Some(c) = &r.comparison {
        println!(
            "registered: along {:.3} +- {:.3} um, across {}, correlation {:.4}",
            c.along_shift * 1e6,
            c.along_shift_sigma * 1e6,
            if c.across_fixed {
                format!("{:.3} um (held: unobservable)", c.across_offset * 1e6)
            } else {
                format!("{:.3} +- {:.3} um", c.across_offset * 1e6, c.across_offset_sigma * 1e6)
            },
            c.correlation
        );
        println!(
            "model: depth scale {:.4} +- {:.4}{}, offset {:.2} +- {:.2} nm, tilt {:.3e} +- {:.1e}, blur {:.3} +- {:.3} um, \
             residual {:.2} nm RMS over {} points",
            c.depth_scale,
            c.depth_scale_sigma,
            if c.complement { " (complement)" } else { "" },
            c.offset * 1e9,
            c.offset_sigma * 1e9,
            c.tilt,
            c.tilt_sigma,
            c.blur * 1e6,
            c.blur_sigma * 1e6,
            c.rms_residual * 1e9,
            c.points
        );
        if let Some(l) = &c.levels {
            for s in &l.levels {
                match (s.step_height, s.step_height_sigma, s.depth_scale, s.depth_scale_sigma) {
                    (Some(h), Some(hs), Some(d), Some(ds)) => println!(
                        "  level {}: step {:.2} +- {:.2} nm (design {:.2} nm), depth scale {:.4} +- {:.4} ({} points)",
                        s.level,
                        h * 1e9,
                        hs * 1e9,
                        s.design_step * 1e9,
                        d,
                        ds,
                        s.points
                    ),
                    _ => println!("  level {}: reference ({} points)", s.level, s.points),
                }
            }
        }
    }
    if let Some(o) = output {
        println!("wrote {}", o.display());
    }
}

/// `doefab scan-info`.
pub fn scan_info(cli: &Cli, a: &ScanInfoArgs) -> Result<()> {
    let ScanInfoArgs { file, pitch, z_unit, z_scale, level, aperture } = a;
    let opts = doefab::io::scan::ScanOptions {
        pitch: pitch.map(|p| [p, p]),
        z_unit: z_unit.as_deref().map(length_unit).transpose()?,
        z_scale: *z_scale,
        ..Default::default()
    };
    use doefab::metrology::LevelMethod;
    let method = match level {
        LevelArg::Plane => LevelMethod::Plane,
        LevelArg::Facet => LevelMethod::Facet,
        LevelArg::Substrate => LevelMethod::Substrate { aperture: *aperture },
    };
    if aperture.is_some() && *level != LevelArg::Substrate {
        anyhow::bail!("--aperture applies to --level substrate only");
    }
    let info = doefab::metrology::scan_info(file, &opts, method)?;
    warn(&info.warnings);
    print_result(cli, &info, || print!("{}", info.summary()))
}

#[allow(clippy::too_many_arguments)]
/// Runs the scan comparison with a progress bar over its steps.
fn compare_scan(
    cli: &Cli,
    scan: &doefab::pipeline::compare::ScanSource,
    source: &DesignSource,
    chain: Option<&ChainParams>,
    aperture: Option<f64>,
    psf: Option<(doefab::optics::Method, doefab::optics::Options)>,
    output: &Path,
) -> Result<doefab::pipeline::compare::CompareOutcome> {
    let pb = progress(cli, 4);
    let report = doefab::pipeline::compare::compare_scan(
        scan,
        source,
        chain,
        aperture,
        psf.as_ref().map(|(m, o)| (*m, o)),
        output,
        &mut |s: &str| {
            pb.inc(1);
            pb.set_message(s.to_string());
        },
    )?;
    pb.finish_and_clear();
    Ok(report)
}

/// Prints the warnings of a scan comparison: the scan reader's, the comparison's, the PSFs'.
pub fn warn_comparison(r: &doefab::pipeline::compare::CompareOutcome) {
    warn(&r.scan_warnings);
    warn(&r.comparison.warnings);
    if let Some(p) = &r.psf {
        warn(&p.warnings);
    }
}

/// A scan comparison: registration, error over the aperture (nm), fabrication model, levels, efficiency, PSFs.
pub fn print_comparison(r: &doefab::pipeline::compare::CompareOutcome, output: &Path) {
    let c = &r.comparison;
    let g = &c.registration;
    let searched: Vec<String> =
        c.candidates.iter().map(|m| format!("{} {:.4}", m.member.name(), m.correlation)).collect();
    println!("the scan shows {} (registered to {}; {})", c.scan_of, c.member.name(), searched.join(", "));
    println!(
        "registered: shift ({:.3}, {:.3}) um, rotation {:.4} deg, scale {:.5}, mirror {}, complement {}, \
         correlation {:.4}",
        g.pose.shift[0] * 1e6,
        g.pose.shift[1] * 1e6,
        g.pose.rotation.to_degrees(),
        g.pose.scale,
        g.pose.mirror,
        g.complement,
        g.correlation
    );
    println!(
        "error over the {:.3} mm aperture: RMS {:.2} nm, PV {:.2} nm, mean {:.2} nm ({:.1}% measured)",
        c.aperture * 1e3,
        c.rms_error * 1e9,
        c.pv_error * 1e9,
        c.mean_error * 1e9,
        c.measured_fraction * 100.0
    );
    let m = &c.model;
    println!(
        "fabrication model: depth scale {:.4}, offset {:.2} nm, blur {:.3} +- {:.3} um, residual {:.2} nm RMS",
        m.depth_scale,
        m.offset * 1e9,
        m.blur * 1e6,
        m.blur_sigma * 1e6,
        m.rms_residual * 1e9
    );
    if let Some(l) = &c.levels {
        println!(
            "{} levels: mean step {:.2} nm (nominal {:.2} nm), spread {:.2} nm",
            l.count,
            l.mean_step * 1e9,
            l.step * 1e9,
            l.step_std * 1e9
        );
    }
    for e in &c.efficiency {
        println!(
            "  {:5.1} nm: efficiency {:.4} -> {:.4} (loss {:.4})",
            e.wavelength * 1e9,
            e.design,
            e.fabricated,
            e.loss
        );
    }
    if let Some(p) = &r.psf {
        for ch in &p.channels {
            println!(
                "  PSF {}: Strehl vs design {:.4}, relative L2 {:.4}",
                ch.name, ch.strehl_vs_design, ch.relative_l2
            );
        }
    }
    println!("wrote {}", output.display());
}

/// Arguments of `doefab bench register`.
#[derive(Args)]
pub struct BenchRegisterArgs {
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// `doefab bench register`.
pub fn bench_register(cli: &Cli, a: &BenchRegisterArgs) -> Result<()> {
    let pb = progress(cli, doefab::sweep::register::steps() as u64);
    let r = doefab::pipeline::sweep::sweep_register(&a.output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    print_result(cli, &r, || {
        for axis in &r.axes {
            let own: Vec<_> = r.trials.iter().filter(|t| t.axis == axis.name).collect();
            let refused: Vec<String> =
                own.iter().filter(|t| t.outcome == "refused").map(|t| format!("{}", t.value)).collect();
            let worst =
                own.iter().filter(|t| t.outcome != "refused").map(|t| t.shift_error).fold(0.0, f64::max);
            println!(
                "{:<9} ({}): worst accepted shift error {:.3} samples; refused at {}",
                axis.name,
                axis.unit,
                worst,
                if refused.is_empty() { "none".to_string() } else { refused.join(", ") }
            );
        }
        println!(
            "{} trials: {} refused, {} accepted but wrong (silent failures); wrote {}",
            r.trials.len(),
            r.refused,
            r.silent_failures,
            a.output.display()
        );
    })
}
