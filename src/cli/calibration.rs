//! The calibration commands: `merge`, `calibrate-psf`, `evaluate`.

use std::path::{Path, PathBuf};

use anyhow::Result;
use clap::Args;

use super::options::{clap_length, Cli};
use super::options::{print_result, progress, report_to, warn};

/// An exposure bracket on the command line.
#[derive(Args, Clone)]
pub struct BracketArgs {
    /// Capture files (8/16-bit PNG or TIFF) with --times; or one exposure list (.json).
    files: Vec<PathBuf>,
    /// Exposure list (JSON: {"frames": [{"file", "exposure_s", "doe"}], "reference_exposure_s"}).
    #[arg(long, conflicts_with = "times")]
    exposures: Option<PathBuf>,
    /// Exposure times of FILES, comma-separated ("1/60,1/30,0.1", "250ms").
    #[arg(long, value_delimiter = ',')]
    times: Vec<String>,
    /// From the exposure list take the frames with "doe": true (default: those without).
    #[arg(long)]
    doe_frames: bool,
    /// Dark frames (averaged and subtracted from every frame).
    #[arg(long, num_args = 1..)]
    dark: Vec<PathBuf>,
    /// Noise floor above the dark level, fraction of full scale.
    #[arg(long, default_value_t = 0.02)]
    noise_floor: f64,
    /// Saturation level, fraction of full scale.
    #[arg(long, default_value_t = 0.98)]
    saturation: f64,
    /// Use the listed exposure times as they are (default: estimate them from the pixels).
    #[arg(long)]
    listed_times: bool,
    /// Express the radiance at this exposure (value 1 = full scale at it), e.g. the capture's
    /// "1/60"; default: the list's reference_exposure_s, else 1 s.
    #[arg(long)]
    reference_exposure: Option<String>,
    /// Black level, fraction of full scale (one, or one per channel, comma-separated); default:
    /// the dark frames, else estimated from the shortest frame.
    #[arg(long, value_delimiter = ',', conflicts_with = "dark")]
    black_level: Vec<f64>,
}

impl BracketArgs {
    /// The bracket as the library takes it.
    fn options(&self) -> doefab::pipeline::merge::BracketOptions {
        doefab::pipeline::merge::BracketOptions {
            files: self.files.clone(),
            times: self.times.clone(),
            exposures: self.exposures.clone(),
            doe_frames: self.doe_frames,
            dark: self.dark.clone(),
            noise_floor: self.noise_floor,
            saturation: self.saturation,
            listed_times: self.listed_times,
            reference_exposure: self.reference_exposure.clone(),
            black_level: self.black_level.clone(),
        }
    }
}

/// Camera response choice on the command line.
#[derive(Clone, Copy, PartialEq, clap::ValueEnum)]
pub enum ResponseArg {
    Linear,
    Debevec,
}

impl ResponseArg {
    /// The response model as the library takes it.
    fn model(self) -> doefab::pipeline::merge::ResponseModel {
        match self {
            ResponseArg::Linear => doefab::pipeline::merge::ResponseModel::Linear,
            ResponseArg::Debevec => doefab::pipeline::merge::ResponseModel::Debevec,
        }
    }
}

/// Registration model on the command line.
#[derive(Clone, Copy, clap::ValueEnum)]
pub enum RegisterArg {
    Affine,
    Local,
}

/// Arguments of `doefab merge`.
#[derive(Args)]
pub struct MergeArgs {
    #[command(flatten)]
    pub bracket: BracketArgs,
    /// Output OpenEXR file.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Recover the camera response from the bracket (Debevec-Malik) instead of assuming
    /// linear captures.
    #[arg(long, value_enum, default_value_t = ResponseArg::Linear)]
    pub response: ResponseArg,
    /// Tone-mapped PNG (default: the output with the extension .png).
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Exposure of the tone-mapped PNG, stops.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub ev: f64,
    /// Save the recovered response curve as CSV (z, then ln exposure g(z) per channel);
    /// needs --response debevec.
    #[arg(long)]
    pub response_out: Option<PathBuf>,
}

/// Arguments of `doefab calibrate-psf`.
#[derive(Args)]
pub struct CalibratePsfArgs {
    #[command(flatten)]
    pub bracket: BracketArgs,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Crop size in sensor pixels (the paper: 319 measured, 320 simulated).
    #[arg(long, default_value_t = 319)]
    pub crop: usize,
    /// What goes to the crop centre.
    #[arg(long, value_enum, default_value_t = doefab::calibration::Centre::Axis)]
    pub centre: doefab::calibration::Centre,
    /// Pixel pitch of the captures.
    #[arg(long, value_parser = clap_length, default_value = "4.29um")]
    pub capture_pitch: f64,
    /// Pixel pitch of the sensor the PSF is for.
    #[arg(long, value_parser = clap_length, default_value = "4.29um")]
    pub sensor_pitch: f64,
}

/// Arguments of `doefab evaluate`.
#[derive(Args)]
pub struct EvaluateArgs {
    /// The reconstructions (OpenEXR, .npy, or PNG/TIFF), in units of the capture's clipping
    /// level; the capture itself is always scored too.
    pub images: Vec<PathBuf>,
    /// The reference HDR image (OpenEXR or .npy, e.g. from `doefab merge`).
    #[arg(long)]
    pub reference: PathBuf,
    /// The capture through the DOE the reconstructions were made from (8/16-bit PNG/TIFF).
    #[arg(long, alias = "ldr")]
    pub capture: PathBuf,
    /// The measured PSF (.npz, .npy or .exr, sampled at the capture's pixels): the reference
    /// is convolved with it before registering onto the capture.
    #[arg(long)]
    pub psf: Option<PathBuf>,
    /// Array of a .npz PSF holding several (the paper's: psf_val).
    #[arg(long)]
    pub psf_key: Option<String>,
    /// The capture's pixel pitch: a PSF stating another is refused.
    #[arg(long, value_parser = clap_length, default_value = "4.29um")]
    pub capture_pitch: f64,
    /// Saturation level of the capture, fraction of its clipping level.
    #[arg(long, default_value_t = 0.98)]
    pub saturation: f64,
    /// Registration: a local displacement field (parallax) or one affine map.
    #[arg(long, value_enum, default_value = "local")]
    pub register: RegisterArg,
    /// Largest displacement the registration searches, pixels.
    #[arg(long, default_value_t = 48)]
    pub max_shift: usize,
    /// Tile side of the registration, pixels.
    #[arg(long, default_value_t = 48)]
    pub tile: usize,
    /// Smallest fraction of the image that must be registered; below it the scene is refused.
    #[arg(long, default_value_t = 0.3)]
    pub min_coverage: f64,
    /// Fewest saturated pixels that must be registered for the saturated figures.
    #[arg(long, default_value_t = 100)]
    pub min_saturated: usize,
    /// Write what is scored against to this OpenEXR file: the registered reference (R, G, B,
    /// in units of the capture's clipping level) and the pixel sets (channels scored, saturated).
    #[arg(long)]
    pub registered: Option<PathBuf>,
}

/// `doefab merge`.
pub fn merge(cli: &Cli, a: &MergeArgs) -> Result<()> {
    let MergeArgs { bracket, output, response, png, ev, response_out } = a;
    use doefab::pipeline::merge::{merge, MergeOptions};
    let opts = MergeOptions {
        bracket: bracket.options(),
        response: response.model(),
        output: output.clone(),
        png: png.clone(),
        ev: *ev,
        response_out: response_out.clone(),
    };
    let pb = progress(cli, 0);
    let out = merge(&opts, &mut report_to(&pb))?;
    pb.finish_and_clear();
    warn(&out.response_warnings);
    warn(&out.stats.warnings);
    warn(&out.tone_map.warnings);
    print_result(cli, &out, || {
        print_merge(&out.stats, output);
        println!(
            "  tone-mapped at EV {} ({:.1} % white) -> {}",
            out.tone_map.ev,
            100.0 * out.tone_map.clipped_fraction,
            out.png.display()
        );
        if let (Some(path), Some(curve)) = (response_out, &out.response) {
            let ranges: Vec<String> = curve.observed.iter().map(|[a, b]| format!("{a}..{b}")).collect();
            println!("  response curve (observed values {}) -> {}", ranges.join(", "), path.display());
        }
    })
}

/// `doefab calibrate-psf`.
pub fn calibrate_psf(cli: &Cli, a: &CalibratePsfArgs) -> Result<()> {
    let CalibratePsfArgs { bracket, output, crop, centre, capture_pitch, sensor_pitch } = a;
    use doefab::pipeline::calibrate_psf::{calibrate_psf, CalibrateOptions};
    let opts = CalibrateOptions {
        bracket: bracket.options(),
        psf: doefab::calibration::PsfOptions {
            crop: *crop,
            centre: *centre,
            capture_pitch: *capture_pitch,
            sensor_pitch: *sensor_pitch,
            ..Default::default()
        },
        output: output.clone(),
    };
    let pb = progress(cli, 0);
    let report = calibrate_psf(&opts, &mut report_to(&pb))?;
    pb.finish_and_clear();
    warn(&report.warnings);
    print_result(cli, &report, || print_calibration(&report, output))
}

/// `doefab evaluate`.
pub fn evaluate(cli: &Cli, a: &EvaluateArgs) -> Result<()> {
    let EvaluateArgs {
        images,
        reference,
        capture,
        psf,
        psf_key,
        capture_pitch,
        saturation,
        register,
        max_shift,
        tile,
        min_coverage,
        min_saturated,
        registered,
    } = a;
    use doefab::calibration::{evaluate_files, EvaluateFiles, Model, RegisterOptions, ScoringOptions};
    let files = EvaluateFiles {
        reference: reference.clone(),
        capture: capture.clone(),
        psf: psf.clone(),
        psf_key: psf_key.clone(),
        capture_pitch: *capture_pitch,
        images: images.clone(),
        options: ScoringOptions {
            register: RegisterOptions {
                max_shift: *max_shift,
                tile: *tile,
                min_coverage: 0.0,
                model: match register {
                    RegisterArg::Affine => Model::Affine,
                    RegisterArg::Local => Model::Local,
                },
            },
            saturation: *saturation,
            min_coverage: *min_coverage,
            min_saturated: *min_saturated,
        },
        registered: registered.clone(),
    };
    let e = evaluate_files(&files)?;
    warn(&e.footing.warnings);
    print_result(cli, &e, || {
        print_footing(&e.footing);
        for s in &e.scores {
            print_score(s);
        }
    })
}

/// How a scene was registered and what is scored (`evaluate`, `bench decoder`).
fn print_footing(f: &doefab::calibration::Footing) {
    if let Some(r) = &f.registration {
        println!(
            "registered (affine): scale {:.4}, rotation {:.3} deg, shift ({:.2}, {:.2}) px; {} of {} tiles, residual {:.3} px RMS",
            r.scale, r.rotation_deg, r.affine.b[0], r.affine.b[1], r.tiles_used, r.tiles_matched, r.residual_rms_px
        );
    }
    if let Some(r) = &f.local_registration {
        print_local_registration(r, f.rows * f.cols - f.pixels_scored);
    }
    println!(
        "{} the PSF; gain {:.3} ({} samples); scored {} pixels ({:.1} %), {} of the capture's {} saturated pixels",
        if f.psf { "predicted through" } else { "registered without" },
        f.gain,
        f.gain_samples,
        f.pixels_scored,
        100.0 * f.coverage,
        f.saturated_scored,
        f.saturated_in_capture
    );
    if let Some(why) = &f.saturated_withheld {
        println!("saturated figures withheld: {why}");
    }
}

/// One image's scores: PSNR-L and PSNR-gamma over all scored pixels and the saturated ones.
fn print_score(s: &doefab::calibration::Score) {
    let sat = s
        .saturated
        .as_ref()
        .map_or("withheld".into(), |p| format!("{:.2} / {:.2} dB", p.linear_db, p.gamma_db));
    println!(
        "{}: all {:.2} / {:.2} dB, saturated {sat} (PSNR-L / PSNR-gamma); min output {:.3}, {:.2} % negative",
        s.name,
        s.all.linear_db,
        s.all.gamma_db,
        s.all.min_output,
        100.0 * s.all.negative_fraction
    );
}

/// How a scene was registered locally; `excluded`: pixels left out of the scoring.
fn print_local_registration(r: &doefab::calibration::LocalRegistration, excluded: usize) {
    let [lo, hi] = r.displacement_range_px;
    println!(
        "registered locally: {} of {} tiles on a {} px grid, leave-one-out residual {:.2} px RMS, \
         displacements x {:.1}..{:.1} px, y {:.1}..{:.1} px; {:.0} % covered, {} pixels left out",
        r.tiles_used,
        r.tiles_matched,
        r.node_spacing_px,
        r.residual_rms_px,
        lo[0],
        hi[0],
        lo[1],
        hi[1],
        100.0 * r.covered_fraction,
        excluded
    );
}

/// A merge: the radiance image and, per frame, its listed and used exposure (s), saturation and agreement.
fn print_merge(r: &doefab::calibration::MergeStats, output: &Path) {
    println!(
        "{} x {} x {} radiance ({}) -> {}",
        r.shape[1],
        r.shape[0],
        r.shape[2],
        r.unit,
        output.display()
    );
    println!("  frame                              listed s    used s   saturated  agreement (median)");
    for f in &r.frames {
        println!(
            "  {:<32} {:>9.4} {:>9.4} {:>11} {:>8}",
            Path::new(&f.file).file_name().map_or(f.file.clone(), |n| n.to_string_lossy().into_owned()),
            f.exposure_listed,
            f.exposure_used,
            f.saturated.iter().sum::<usize>(),
            f.agreement_median.map_or("-".into(), |m| format!("{:.2} %", 100.0 * m))
        );
    }
    println!(
        "  no usable frame: {} saturated everywhere, {} in the noise floor everywhere",
        r.saturated_everywhere.count, r.dark_everywhere.count
    );
}

/// A measured PSF: its position in the capture and, per channel, centroid (pixels), peak and losses.
fn print_calibration(r: &doefab::calibration::PsfCalibration, output: &Path) {
    println!(
        "PSF at row {:.2}, col {:.2} of the capture (peak {}, {}); {} hot pixels; {} x {} crop -> {}",
        r.centroid_px[0],
        r.centroid_px[1],
        r.peak_px[0],
        r.peak_px[1],
        r.hot_pixels,
        r.crop,
        r.crop,
        output.display()
    );
    for (c, ch) in r.channels.iter().enumerate() {
        println!(
            "  {}: centroid ({:+.3}, {:+.3}) px, peak {:.3e}, outside the crop {:.2} %, zeroed below the noise floor {:.2} %",
            ch.name,
            ch.centroid[0] / r.sensor_pitch,
            ch.centroid[1] / r.sensor_pitch,
            ch.peak,
            100.0 * r.energy_outside[c],
            100.0 * r.below_floor[c]
        );
    }
}

/// Arguments of `doefab bench calibration`.
#[derive(Args)]
pub struct BenchCalibrationArgs {
    /// The true PSF the brackets are simulated from (a PSF file: .npy, .npz, .exr); default the
    /// paper's measured PSF, built in.
    psf: Option<PathBuf>,
    /// Output folder.
    #[arg(short, long)]
    output: PathBuf,
}

/// `doefab bench calibration`.
pub fn bench_calibration(cli: &Cli, a: &BenchCalibrationArgs) -> Result<()> {
    let pb = progress(cli, doefab::sweep::calibration::steps() as u64);
    let r = doefab::pipeline::sweep::sweep_calibration(a.psf.as_deref(), &a.output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    print_result(cli, &r, || {
        for axis in &r.axes {
            let own: Vec<_> = r.trials.iter().filter(|t| t.axis == axis.name).collect();
            // Trials come in the axis's order, the seeds of one value together.
            let mut within: Vec<String> =
                own.iter().filter(|t| t.outcome == "calibrated").map(|t| format!("{}", t.value)).collect();
            within.dedup();
            let worst = own.iter().map(|t| t.worst).filter(|e| e.is_finite()).fold(0.0, f64::max);
            println!(
                "{:<11} ({}): within {:.0} % at {}; worst error {:.2} %",
                axis.name,
                axis.unit,
                100.0 * r.tolerance,
                if within.is_empty() { "none".to_string() } else { within.join(", ") },
                100.0 * worst
            );
        }
        println!(
            "{} trials: {} warned, {} refused, {} over the tolerance silently; wrote {}",
            r.trials.len(),
            r.warned,
            r.refused,
            r.silent_failures,
            a.output.display()
        );
    })
}
