//! The `doefab` command line: parses arguments, calls the library, prints. Nothing else: the
//! grammar and each stage's commands are in [`cli`].

mod cli;

use std::process::ExitCode;

use anyhow::Result;
use clap::Parser;

use cli::args::{BenchCommand, Command, CommandLine};
use cli::{calibration, decoder, demo, fabrication, metrology, optics};

/// Exit status of a scan that cannot be registered to its design (`doefab compare`).
const EXIT_UNREGISTERED: u8 = 3;

fn main() -> ExitCode {
    let line = CommandLine::parse();
    match run(&line) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            for cause in e.chain().skip(1) {
                eprintln!("  caused by: {cause}");
            }
            let unregistered = e.chain().any(|c| {
                matches!(c.downcast_ref::<doefab::Error>(), Some(doefab::Error::Registration { .. }))
            });
            ExitCode::from(if unregistered { EXIT_UNREGISTERED } else { 2 })
        }
    }
}

fn run(line: &CommandLine) -> Result<()> {
    let cli = &line.cli;
    match &line.command {
        Command::Psf(a) => optics::psf(cli, a),
        Command::Merge(a) => calibration::merge(cli, a),
        Command::CalibratePsf(a) => calibration::calibrate_psf(cli, a),
        Command::Evaluate(a) => calibration::evaluate(cli, a),
        Command::PsfCompare(a) => optics::psf_compare(cli, a),
        Command::Report(a) => optics::report(cli, a),
        Command::Bench { what: BenchCommand::Psf(a) } => optics::bench_psf(cli, a),
        Command::Bench { what: BenchCommand::Spectral(a) } => optics::bench_spectral(cli, a),
        Command::Bench { what: BenchCommand::Stability(a) } => optics::bench_stability(cli, a),
        Command::Bench { what: BenchCommand::Register(a) } => metrology::bench_register(cli, a),
        Command::Bench { what: BenchCommand::Fab(a) } => fabrication::bench_fab(cli, a),
        Command::Bench { what: BenchCommand::Calibration(a) } => calibration::bench_calibration(cli, a),
        Command::Bench { what: BenchCommand::Tiling(a) } => decoder::bench_tiling(cli, a),
        Command::Bench { what: BenchCommand::Decoder(a) } => decoder::bench_decoder(cli, a),
        Command::Bench { what: BenchCommand::Forward(a) } => decoder::bench_forward(cli, a),
        Command::Demo(a) => demo::demo(cli, a),
        Command::Fab(a) => fabrication::fab(cli, a),
        Command::Precompensate(a) => fabrication::precompensate(cli, a),
        Command::Wrap(a) => fabrication::wrap(cli, a),
        Command::Quantize(a) => fabrication::quantize(cli, a),
        Command::Mask(a) => fabrication::mask(cli, a),
        Command::Gds(a) => fabrication::gds(cli, a),
        Command::Stl(a) => fabrication::stl(cli, a),
        Command::SimulateScan(a) => metrology::simulate_scan(cli, a),
        Command::Compare(a) => metrology::compare(cli, a),
        Command::CompareProfile(a) => metrology::compare_profile(cli, a),
        Command::ScanInfo(a) => metrology::scan_info(cli, a),
        Command::Reconstruct(a) => decoder::reconstruct(cli, a),
        Command::Finetune(a) => decoder::finetune(cli, a),
    }
}
