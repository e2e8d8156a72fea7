//! What the commands' modules share: the options every command takes ([`Cli`]), the argument
//! groups several commands take ([`ReadArgs`], [`OpticsArgs`]), the progress bar and the
//! printing of results and warnings.

use anyhow::Result;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use doefab::io::heightmap::ReadOptions;
use doefab::units::{length_unit, parse_duration, parse_length};

/// What a command's run reads of the command line besides its own arguments: the options every
/// command takes.
#[derive(Args)]
pub struct Cli {
    /// No progress bars and no summaries; errors and warnings still go to stderr.
    #[arg(long, short, global = true)]
    pub quiet: bool,
    /// Print the result as JSON on stdout.
    #[arg(long, global = true)]
    pub json: bool,
}

/// How to read a height map that does not say everything about itself.
#[derive(Args, Clone, Default)]
pub struct ReadArgs {
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
    pub fn options(&self) -> Result<ReadOptions> {
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
pub struct OpticsArgs {
    /// Design wavelength.
    #[arg(long, value_parser = clap_length, default_value = "530nm")]
    pub wavelength: f64,
    /// Material of the part (pdms, fused_silica).
    #[arg(long, default_value = "pdms")]
    pub material: String,
    /// Multi-order factor p (wrap modulo p * 2 pi).
    #[arg(long, default_value_t = 1)]
    pub order: u32,
}

impl OpticsArgs {
    /// The chain a comparison makes of the design: the recipe's, or `levels` levels at these
    /// optics ([`doefab::pipeline::compare::comparison_chain`]).
    pub fn comparison_chain(
        &self,
        recipe: Option<&std::path::Path>,
        levels: Option<usize>,
    ) -> Result<Option<doefab::fabrication::recipe_run::ChainParams>> {
        let OpticsArgs { wavelength, material, order } = self;
        Ok(doefab::pipeline::compare::comparison_chain(recipe, levels, *wavelength, material, *order)?)
    }
}

/// A progress bar over `steps` named steps (hidden with --quiet or --json).
pub fn progress(cli: &Cli, steps: u64) -> ProgressBar {
    if cli.quiet || cli.json {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new(steps);
    if let Ok(style) = ProgressStyle::with_template("{bar:30} {pos}/{len} {elapsed_precise} {msg}") {
        pb.set_style(style);
    }
    pb
}

/// Shows a library progress callback `(message, done, total)` on a progress bar.
pub fn report_to(pb: &ProgressBar) -> impl FnMut(&str, u64, u64) + '_ {
    move |message, done, total| {
        pb.set_length(total);
        pb.set_position(done);
        pb.set_message(message.to_string());
    }
}

/// Prints `value` as JSON with --json, else the human-readable `human` unless --quiet.
pub fn print_result<T: serde::Serialize>(cli: &Cli, value: &T, human: impl FnOnce()) -> Result<()> {
    if cli.json {
        println!("{}", serde_json::to_string_pretty(value)?);
    } else if !cli.quiet {
        human();
    }
    Ok(())
}

/// Prints each warning to stderr.
pub fn warn(warnings: &[String]) {
    for w in warnings {
        eprintln!("warning: {w}");
    }
}

/// clap value parser for lengths.
pub fn clap_length(s: &str) -> std::result::Result<f64, String> {
    parse_length(s).map_err(|e| e.to_string())
}

/// clap value parser for durations (seconds).
pub fn clap_duration(s: &str) -> std::result::Result<f64, String> {
    parse_duration(s).map_err(|e| e.to_string())
}
