//! The optics commands: `psf`, `psf-compare`, `bench psf`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use doefab::fabrication::recipe_run::DesignSource;
use doefab::pipeline::sweep::PsfSweepOptions;
use doefab::sweep::psf::SweepOptions;

use super::options::{clap_duration, clap_length, Cli, ReadArgs};
use super::options::{print_result, progress, report_to, warn};

/// Arguments of `doefab psf`.
#[derive(Args)]
pub struct PsfArgs {
    /// Height map file, or built-in:paper / built-in:fresnel (default built-in:paper).
    pub design: Option<String>,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Force a method (matrix_dft, fresnel, angular_spectrum or rayleigh_sommerfeld) at the
    /// DOE's pitch with --subsample; without it the automatic plan chooses everything.
    #[arg(long)]
    pub method: Option<String>,
    /// Sub-samples per pixel and axis (pixel integration), with --method.
    #[arg(long, default_value_t = 1)]
    pub subsample: usize,
    /// The plan's tolerance: relative L2 error per channel.
    #[arg(long, default_value_t = doefab::optics::plan::DEFAULT_TOLERANCE)]
    pub tolerance: f64,
    /// Print the plan's choices and the condition that bounds each, and after the run the
    /// cheaper pixel sub-samplings it rejected, run and measured against its own.
    #[arg(long)]
    pub explain: bool,
    /// Sensor spectral response CSV (wavelength_nm,r,g,b): one channel per response column,
    /// integrated over its band (plan only).
    #[arg(long)]
    pub response: Option<PathBuf>,
    /// Optical system TOML (fields of the system, lengths with units: aperture = "5 mm");
    /// unset fields keep the paper's values. The plan chooses pupil_pitch and subsample.
    #[arg(long)]
    pub system: Option<PathBuf>,
    /// Material of the DOE (pdms, fused_silica, noa61, pmma, ip_dip).
    #[arg(long, default_value = "pdms")]
    pub material: String,
    /// Run even where the method's validity conditions fail (recorded as warnings).
    #[arg(long)]
    pub allow_invalid: bool,
    #[command(flatten)]
    pub read: ReadArgs,
}

/// Arguments of `doefab psf-compare`.
#[derive(Args)]
pub struct PsfCompareArgs {
    /// Reference PSF: .npy (with psf.json beside it), .exr as `psf` writes, or .npz.
    pub a: PathBuf,
    /// PSF compared against it (moved onto its centroid).
    pub b: PathBuf,
    /// Write the comparison as JSON to this file.
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Pixel pitch for a file that states none ("4.29 um").
    #[arg(long, value_parser = clap_length)]
    pub pitch: Option<f64>,
    /// Array to read from a .npz archive holding several (the paper's: psf_val).
    #[arg(long)]
    pub key: Option<String>,
    /// Radius of the encircled energy and the peak search ("5 um"); default the Airy
    /// radius at the paper's F/7, or two pixels without a wavelength.
    #[arg(long, value_parser = clap_length)]
    pub radius: Option<f64>,
}

/// The design and camera of `doefab bench psf`, `bench spectral` and `doefab report`.
#[derive(Args)]
pub struct BenchDesignArgs {
    /// Height map file, or built-in:paper / built-in:fresnel (default built-in:paper, at the
    /// paper's geometry).
    pub design: Option<String>,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Optical system TOML (as for `psf`); unset fields keep the paper's values.
    #[arg(long)]
    pub system: Option<PathBuf>,
    /// Material of the DOE (pdms, fused_silica, noa61, pmma, ip_dip).
    #[arg(long, default_value = "pdms")]
    pub material: String,
    #[command(flatten)]
    pub read: ReadArgs,
}

impl BenchDesignArgs {
    /// The PSF sweep's options with `sweep`.
    fn psf_options(&self, sweep: SweepOptions) -> Result<PsfSweepOptions> {
        Ok(PsfSweepOptions {
            design: DesignSource::parse(self.design.as_deref(), self.read.options()?),
            system: self.system.clone(),
            material: self.material.clone(),
            sweep,
        })
    }
}

/// [`BenchDesignArgs`] with a time budget (`doefab bench psf`, `doefab report`).
#[derive(Args)]
pub struct BenchOnArgs {
    #[command(flatten)]
    pub at: BenchDesignArgs,
    /// Wall-clock budget for the whole command ("5min", "90s").
    #[arg(long, default_value = "5min", value_parser = clap_duration)]
    pub budget: f64,
}

impl BenchOnArgs {
    /// The PSF sweep's options over `sweep` (its budget replaced by `--budget`).
    fn psf_options(&self, sweep: SweepOptions) -> Result<PsfSweepOptions> {
        self.at.psf_options(SweepOptions { budget: self.budget, ..sweep })
    }
}

/// Arguments of `doefab bench psf`.
#[derive(Args)]
pub struct BenchPsfArgs {
    #[command(flatten)]
    pub on: BenchOnArgs,
    /// Largest sub-sampling per pixel and axis swept (the reference runs at 2 and 4 more).
    #[arg(long, default_value_t = 5)]
    pub max_subsample: usize,
    /// Tolerances at which the automatic plan is placed on the chart.
    #[arg(long, value_delimiter = ',', default_values_t = [1e-2, 1e-3, 1e-4])]
    pub tolerances: Vec<f64>,
}

/// Arguments of `doefab bench spectral`.
#[derive(Args)]
pub struct BenchSpectralArgs {
    #[command(flatten)]
    pub at: BenchDesignArgs,
    /// Sensor spectral response CSV (wavelength_nm,r,g,b); default the paper's three
    /// wavelengths as 80 nm wide Gaussian bands.
    #[arg(long)]
    pub response: Option<PathBuf>,
    /// The reference takes 3^K sub-bands per band (2..=6).
    #[arg(long, default_value_t = 5)]
    pub reference_power: u32,
    /// Tolerances at which the plan's rule is placed on the chart.
    #[arg(long, value_delimiter = ',', default_values_t = [1e-2, 1e-3, 1e-4])]
    pub tolerances: Vec<f64>,
}

/// Arguments of `doefab report` (its output folder gets index.html, the charts and the data).
#[derive(Args)]
pub struct ReportArgs {
    #[command(flatten)]
    pub on: BenchOnArgs,
}

/// Arguments of `doefab bench stability`.
#[derive(Args)]
pub struct BenchStabilityArgs {
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Error above which a run its guard accepts counts as a silent failure.
    #[arg(long, default_value_t = 1e-2)]
    pub tolerance: f64,
}

/// `doefab psf`.
pub fn psf(cli: &Cli, a: &PsfArgs) -> Result<()> {
    let PsfArgs {
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
    } = a;
    use doefab::pipeline::psf;
    let job = psf::prepare(&psf::PsfOptions {
        design: DesignSource::parse(design.as_deref(), read.options()?),
        method: method.clone(),
        subsample: *subsample,
        tolerance: *tolerance,
        response: response.clone(),
        system: system_file.clone(),
        material: material.clone(),
        allow_invalid: *allow_invalid,
    })?;
    if *explain {
        if let Some(text) = job.explain() {
            eprint!("{text}");
        }
    }
    let pb = progress(cli, 1);
    let report = job.run(output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    warn(&report.warnings);
    if *explain {
        if let Some(measured) = job.measure_cheaper()? {
            eprint!("{}", measured.explain());
        }
    }
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

/// `doefab psf-compare`.
pub fn psf_compare(cli: &Cli, a: &PsfCompareArgs) -> Result<()> {
    let PsfCompareArgs { a, b, output, pitch, key, radius } = a;
    use doefab::pipeline::psf_compare::{psf_compare, PsfCompareOptions};
    let r = psf_compare(&PsfCompareOptions {
        a: a.clone(),
        b: b.clone(),
        compare: doefab::optics::psf_compare::CompareOptions {
            pitch: *pitch,
            key: key.clone(),
            radius: *radius,
        },
        output: output.clone(),
    })?;
    warn(&r.warnings);
    print_result(cli, &r, || {
        if r.window != "same size" {
            println!("{}", r.window);
        }
        for c in &r.channels {
            let um = |p: [f64; 2]| format!("({:.2}, {:.2}) um", p[0] * 1e6, p[1] * 1e6);
            println!(
                "{}: L2 {:.3e}, aligned {:.3e} (B's centroid {} from A's); peak A {:.3e} at {}, \
                         B {:.3e} at {}; EE({:.2} um) A {:.4}, B {:.4}",
                c.name,
                c.relative_l2,
                c.relative_l2_aligned,
                um(c.centroid_offset),
                c.a.summary.peak,
                um(c.a.summary.peak_position),
                c.b.summary.peak,
                um(c.b.summary.peak_position),
                c.radius * 1e6,
                c.a.encircled_energy,
                c.b.encircled_energy
            );
        }
    })
}

/// `doefab bench psf`.
pub fn bench_psf(cli: &Cli, a: &BenchPsfArgs) -> Result<()> {
    use doefab::pipeline::sweep::sweep_psf;
    use doefab::sweep::psf::steps;
    let sweep = SweepOptions {
        max_subsample: a.max_subsample,
        tolerances: a.tolerances.clone(),
        ..Default::default()
    };
    let opts = a.on.psf_options(sweep)?;
    let output = &a.on.at.output;
    let pb = progress(cli, steps(&opts.sweep) as u64);
    let r = sweep_psf(&opts, output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    print_result(cli, &r, || {
        println!(
            "reference: matrix DFT f64, Gauss-Legendre s={} (against s={}: {:.1e}), {:.2} s",
            r.reference.subsamples[1], r.reference.subsamples[0], r.reference.difference, r.reference.seconds
        );
        for p in &r.points {
            println!(
                "{:<17} {} s={} pupil {:.2} um  {:.4} s  L2 {:.2e}{}{}",
                p.method,
                p.precision,
                p.subsample,
                p.pupil_pitch * 1e6,
                p.seconds,
                p.error,
                if p.pareto { "  [Pareto]" } else { "" },
                if p.violations.is_empty() {
                    String::new()
                } else {
                    format!("  refused: {}", p.violations.join("; "))
                }
            );
        }
        for p in &r.plans {
            println!(
                "plan at {:.0e}: {} {} s={}  {:.4} s  L2 {:.2e} ({}){}",
                p.tolerance,
                p.method,
                p.precision,
                p.subsample,
                p.seconds,
                p.error,
                if p.meets_tolerance { "meets it" } else { "MISSES it" },
                match (&p.cheapest_adequate, p.time_ratio) {
                    (Some(c), Some(t)) => format!("; {t:.2}x the time of the cheapest adequate run, {c}"),
                    _ => "; no run of the sweep meets it".into(),
                }
            );
        }
        println!("silent failures (plans that miss their tolerance): {}", r.silent_failures);
        if !r.skipped.is_empty() {
            println!("left out: {}", r.skipped.join(", "));
        }
        println!("wrote {}", output.display());
    })
}

/// `doefab bench spectral`.
pub fn bench_spectral(cli: &Cli, a: &BenchSpectralArgs) -> Result<()> {
    use doefab::sweep::spectral::{steps, SpectralOptions};
    let bands = match &a.response {
        Some(p) => doefab::optics::spectrum::read_response_csv(p)?,
        None => doefab::sweep::spectral::paper_bands()?,
    };
    let opts =
        SpectralOptions { bands, reference_power: a.reference_power, tolerances: a.tolerances.clone() };
    let on = a.at.psf_options(SweepOptions::default())?;
    let pb = progress(cli, steps(&opts) as u64);
    let r = doefab::pipeline::sweep::sweep_spectral(&on, &opts, &a.at.output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    print_result(cli, &r, || {
        println!(
            "{} in f64, one sample per pixel, {:.2} s a wavelength; reference {} sub-bands (against {}: {:.1e})",
            r.method,
            r.seconds_per_wavelength,
            r.reference_samples,
            r.reference_samples / 3,
            r.reference_difference
        );
        for p in &r.points {
            println!(
                "band {:<4} N={:<3} error {:.2e}  estimate {:.2e}  {:.2} s",
                p.band, p.samples, p.error, p.estimate, p.seconds
            );
        }
        for p in &r.plans {
            let rule = p.rule_samples.map_or("refused".into(), |n| n.to_string());
            match (p.samples, p.error) {
                (Some(n), Some(e)) => println!(
                    "plan at {:.0e}: estimate asks {rule}, the run settled on N = {n}, error {e:.2e} ({}), {:.1} s; \
                     smallest adequate N of the sweep: {}",
                    p.tolerance,
                    if p.meets_tolerance { "meets" } else { "MISSES" },
                    p.seconds.unwrap_or(0.0),
                    p.smallest_adequate.map_or("none".into(), |n| n.to_string())
                ),
                _ => println!(
                    "plan at {:.0e}: estimate asks {rule}; {}",
                    p.tolerance,
                    match (&p.refused, &p.not_scored) {
                        (Some(why), _) => format!("refused ({why})"),
                        (_, Some(why)) => format!("not scored ({why})"),
                        _ => String::new(),
                    }
                ),
            }
        }
        println!("silent failures: {}", r.silent_failures);
        println!("wrote {}", a.at.output.display());
    })
}

/// `doefab bench stability`.
pub fn bench_stability(cli: &Cli, a: &BenchStabilityArgs) -> Result<()> {
    use doefab::sweep::stability::{steps, MapOptions};
    let opts = MapOptions { tolerance: a.tolerance, ..MapOptions::default() };
    let pb = progress(cli, steps(&opts) as u64);
    let r = doefab::pipeline::sweep::sweep_stability(&opts, &a.output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    print_result(cli, &r, || {
        println!("truth: {}", r.truth);
        for m in &r.maps {
            let refused = m.cells.iter().filter(|c| !c.violations.is_empty()).count();
            println!(
                "{}{} over pupil sampling x {}: {} runs, {} refused by the guard ({} of them within the \
                 tolerance), silent failures at {:.0e}: {}",
                m.method,
                if m.design == "smooth" { String::new() } else { format!(" on the {} DOE", m.design) },
                m.y_axis.replace('_', " "),
                m.cells.len(),
                refused,
                m.refused_within_tolerance,
                r.tolerance,
                m.silent_failures
            );
        }
        println!("wrote {}", a.output.display());
    })
}

/// `doefab report`.
pub fn report(cli: &Cli, a: &ReportArgs) -> Result<()> {
    use doefab::pipeline::report::{run_report, steps, ReportOptions};
    let opts = ReportOptions::new(a.on.psf_options(SweepOptions::default())?, a.on.budget);
    let pb = progress(cli, steps(&opts) as u64);
    let page = run_report(&opts, &a.on.at.output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    print_result(cli, &page, || {
        let b = &page.budget;
        println!("budget {:.0} s, spent {:.0} s", b.budget_seconds, b.spent_seconds);
        for p in b.left_out() {
            println!(
                "left out: {} (predicted {:.0} s, {:.0} s left)",
                p.name, p.predicted_seconds, p.left_seconds
            );
        }
        println!(
            "wrote {} ({} sections, {} figures; open index.html in a browser)",
            a.on.at.output.display(),
            page.sections.len(),
            page.figures.len()
        );
    })
}
