//! `doefab demo`: every stage on the built-in design.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

use super::metrology::{print_comparison, warn_comparison};
use super::options::Cli;
use super::options::{print_result, progress, report_to, warn};

/// Arguments of `doefab demo`.
#[derive(Args)]
pub struct DemoArgs {
    /// Output folder.
    #[arg(short, long, default_value = "out")]
    pub output: PathBuf,
}

/// `doefab demo`.
pub fn demo(cli: &Cli, a: &DemoArgs) -> Result<()> {
    let output = &a.output;
    let pb = progress(cli, 0);
    let report = doefab::demo::run(output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    for r in &report.fabrication {
        warn(&r.warnings);
    }
    warn(&report.psf.warnings);
    warn_comparison(&report.metrology);
    warn(&report.fabrication_loop.precompensate.warnings);
    warn(&report.calibration.report.warnings);
    // Through a JSON value, whose maps sort their keys: one order at every depth.
    print_result(cli, &serde_json::to_value(&report)?, || print_demo(&report))
}

/// Where the demo wrote each stage's outputs, and the comparison's and calibration's figures.
fn print_demo(r: &doefab::demo::DemoOutcome) {
    let dirs = &r.folders;
    for ((name, out), fab) in dirs.fabrication.iter().zip(&r.fabrication) {
        println!("{name}: {}", out.join("report.md").display());
        for a in &fab.artifacts {
            println!("  {:<16} {}", a.kind, a.path.display());
        }
    }
    println!("simulated scan: {}", dirs.scan.display());
    print_comparison(&r.metrology, &dirs.compare);
    let l = &r.fabrication_loop;
    println!("fabrication loop: {} ({})", dirs.fabrication_loop.display(), l.process);
    for (name, side) in [("plain mask", &l.before), ("pre-compensated", &l.after)] {
        println!(
            "  {name:<16} RMS {:.1} nm, depth scale {:.4}, PSF relative L2 {:.4?}",
            side.rms_error * 1e9,
            side.depth_scale,
            side.psf_relative_l2
        );
    }
    let c = &r.calibration;
    println!("calibration: {} (bracket in {})", c.psf.display(), c.bracket.display());
    println!("  calibrated vs simulated PSF, relative L2 per channel: {:.4?}", c.relative_l2_to_simulated);
    let d = &r.decoder;
    println!("decoder: {} (fine-tuned {} steps)", d.decoder.display(), d.steps());
    println!("  reconstruction of {}: {}", d.reconstruction.capture, d.reconstruction.exr);
    println!("psf: {}", dirs.psf.display());
    for f in &r.psf.files {
        println!("  {}", dirs.psf.join(f).display());
    }
}
