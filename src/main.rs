//! The `doefab` command line: parses arguments, calls the library, prints. Nothing else.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, Result};
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
// Parsed once per run: the size of the larger variant costs nothing.
#[allow(clippy::large_enum_variant)]
enum BenchCommand {
    /// Error against run time of every PSF method, precision and sub-sampling on a small
    /// scene, and error against pupil sampling with the guard's refusals: PNG + SVG + JSON.
    Psf {
        /// Output folder.
        #[arg(short, long)]
        output: PathBuf,
    },
    /// Decoders on real captures: each scene's reference is registered onto its capture once
    /// (through the measured PSF), and the capture and every decoder are scored on the same
    /// pixels (PSNR-L, PSNR-gamma over all and saturated pixels, coverage, smallest output);
    /// optionally a decoder is fine-tuned on the PSF first. JSON report, decoder x scene chart.
    Decoder {
        /// The paper's data release: the default scenes (captures/<scene>/) and measured_psf.npz.
        #[arg(long, default_value = "../shared/data/deepoptics-hdr")]
        data: PathBuf,
        /// A scene folder (exposures.json with one "doe" capture and a bracket); repeat for more
        /// (default: every folder under <data>/captures).
        #[arg(long = "scene")]
        scenes: Vec<PathBuf>,
        /// A decoder to score: a .safetensors file or built-in:paper-simulated-psf /
        /// built-in:paper-measured-psf; repeat for more (default: the paper's two).
        #[arg(long = "decoder")]
        decoders: Vec<PathBuf>,
        /// The measured PSF (default <data>/measured_psf.npz, array psf_val).
        #[arg(long)]
        psf: Option<PathBuf>,
        /// Smallest fraction of a scene that must be registered; below it the scene is refused.
        #[arg(long, default_value_t = 0.3)]
        min_coverage: f64,
        /// Fine-tuning steps of --init on the PSF (0: no fine-tuning).
        #[arg(long, default_value_t = 50)]
        steps: usize,
        /// The decoder to fine-tune.
        #[arg(long, default_value = "built-in:paper-simulated-psf")]
        init: PathBuf,
        /// Batch size of the fine-tuning.
        #[arg(long, default_value_t = 2)]
        batch: usize,
        /// Training crop side, pixels (a multiple of 16).
        #[arg(long, default_value_t = 128)]
        crop: usize,
        /// Adam step size.
        #[arg(long, default_value_t = 1e-4)]
        lr: f64,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Score the decoder being fine-tuned on the real scenes every this many steps
        /// (default: a fifth of the run).
        #[arg(long)]
        evaluate_every: Option<usize>,
        /// HDR images to fine-tune on (a folder of EXR / Radiance .hdr; default: procedural
        /// scenes). Not the benchmark's own scenes, or the scores measure memory.
        #[arg(long)]
        train_data: Option<PathBuf>,
        /// Tile side of the registration, pixels.
        #[arg(long, default_value_t = 48)]
        tile: usize,
        /// Output folder.
        #[arg(short, long)]
        output: PathBuf,
    },
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
    /// Merge an exposure bracket of linear (or, with --response debevec, non-linear 8-bit)
    /// captures into an HDR radiance image (OpenEXR, channels R, G, B).
    Merge {
        #[command(flatten)]
        bracket: BracketArgs,
        /// Output OpenEXR file.
        #[arg(short, long)]
        output: PathBuf,
        /// Recover the camera response from the bracket (Debevec-Malik) instead of assuming
        /// linear captures.
        #[arg(long, value_enum, default_value_t = ResponseArg::Linear)]
        response: ResponseArg,
        /// Tone-mapped PNG (default: the output with the extension .png).
        #[arg(long)]
        png: Option<PathBuf>,
        /// Exposure of the tone-mapped PNG, stops.
        #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
        ev: f64,
        /// Save the recovered response curve as CSV (z, then ln exposure g(z) per channel);
        /// needs --response debevec.
        #[arg(long)]
        response_out: Option<PathBuf>,
    },
    /// The measured PSF from a pinhole bracket: merge, dark and background, hot pixels,
    /// centring, crop, normalisation. Writes psf.exr, psf.npy (H, W, 1, C), psf_log.png,
    /// merged.exr and psf.json.
    CalibratePsf {
        #[command(flatten)]
        bracket: BracketArgs,
        /// Output folder.
        #[arg(short, long)]
        output: PathBuf,
        /// Crop size in sensor pixels (the paper: 319 measured, 320 simulated).
        #[arg(long, default_value_t = 319)]
        crop: usize,
        /// What goes to the crop centre.
        #[arg(long, value_enum, default_value_t = doefab::calibration::psf_extract::Centre::Axis)]
        centre: doefab::calibration::psf_extract::Centre,
        /// Pixel pitch of the captures.
        #[arg(long, value_parser = clap_length, default_value = "4.29um")]
        capture_pitch: f64,
        /// Pixel pitch of the sensor the PSF is for.
        #[arg(long, value_parser = clap_length, default_value = "4.29um")]
        sensor_pitch: f64,
    },
    /// PSNR of reconstructions against a reference HDR image, linear and gamma (sqrt), over the
    /// registered pixels and the saturated ones: the reference is registered onto the capture
    /// once (through the PSF) and every reconstruction is scored on the same pixels.
    Evaluate {
        /// The reconstructions (OpenEXR, .npy, or PNG/TIFF), in units of the capture's clipping
        /// level; the capture itself is always scored too.
        images: Vec<PathBuf>,
        /// The reference HDR image (OpenEXR or .npy, e.g. from `doefab merge`).
        #[arg(long)]
        reference: PathBuf,
        /// The capture through the DOE the reconstructions were made from (8/16-bit PNG/TIFF).
        #[arg(long, alias = "ldr")]
        capture: PathBuf,
        /// The measured PSF (.npz, .npy or .exr, sampled at the capture's pixels): the reference
        /// is convolved with it before registering onto the capture.
        #[arg(long)]
        psf: Option<PathBuf>,
        /// Array of a .npz PSF holding several (the paper's: psf_val).
        #[arg(long)]
        psf_key: Option<String>,
        /// The capture's pixel pitch: a PSF stating another is refused.
        #[arg(long, value_parser = clap_length, default_value = "4.29um")]
        capture_pitch: f64,
        /// Saturation level of the capture, fraction of its clipping level.
        #[arg(long, default_value_t = 0.98)]
        saturation: f64,
        /// Registration: a local displacement field (parallax) or one affine map.
        #[arg(long, value_enum, default_value = "local")]
        register: RegisterArg,
        /// Largest displacement the registration searches, pixels.
        #[arg(long, default_value_t = 48)]
        max_shift: usize,
        /// Tile side of the registration, pixels.
        #[arg(long, default_value_t = 48)]
        tile: usize,
        /// Smallest fraction of the image that must be registered; below it the scene is refused.
        #[arg(long, default_value_t = 0.3)]
        min_coverage: f64,
        /// Fewest saturated pixels that must be registered for the saturated figures.
        #[arg(long, default_value_t = 100)]
        min_saturated: usize,
    },
    /// Compare two PSFs (design, as-fabricated, measured): each one's peaks, encircled energy
    /// and centroid per channel, and the relative L2 after centroid alignment.
    PsfCompare {
        /// Reference PSF: .npy (with psf.json beside it), .exr as `psf` writes, or .npz.
        a: PathBuf,
        /// PSF compared against it (moved onto its centroid).
        b: PathBuf,
        /// Write the comparison as JSON to this file.
        #[arg(short, long)]
        output: Option<PathBuf>,
        /// Pixel pitch for a file that states none ("4.29 um").
        #[arg(long, value_parser = clap_length)]
        pitch: Option<f64>,
        /// Array to read from a .npz archive holding several (the paper's: psf_val).
        #[arg(long)]
        key: Option<String>,
        /// Radius of the encircled energy and the peak search ("5 um"); default the Airy
        /// radius at the paper's F/7, or two pixels without a wavelength.
        #[arg(long, value_parser = clap_length)]
        radius: Option<f64>,
    },
    /// Benchmarks with charts.
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
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
        /// Process recipe (TOML), e.g. masks/laser-writer-grayscale.toml, or a bundled one:
        /// built-in:laser-writer-grayscale, built-in:binary-3mask-8level, built-in:two-photon-stl.
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
    /// Compare a scan of the fabricated part with its design: registration, difference map,
    /// RMS/PV error, level step heights, fabrication model (depth scale, offset, blur),
    /// efficiency loss, design vs as-fabricated PSF; JSON, maps, profiles, histogram and the
    /// part in the design frame (surface.exr, readable by `doefab psf`). Exit status 3 when the
    /// scan cannot be registered to the design (no match, ambiguous or featureless).
    Compare {
        /// Scan file (.x3p, .gsf, .sdf, .sur, .dat, .xyz, .txt/.csv/.asc, .png, .tif, .npy).
        scan: PathBuf,
        /// Height map file, or built-in:paper / built-in:fresnel.
        #[arg(long)]
        design: String,
        /// Output folder.
        #[arg(short, long)]
        output: PathBuf,
        /// Process recipe: compare with the design wrapped and quantized as it makes it.
        #[arg(long)]
        recipe: Option<PathBuf>,
        /// Level count (overrides the recipe's; without a recipe, wraps and quantizes the
        /// design at --wavelength / --material / --order).
        #[arg(long)]
        levels: Option<usize>,
        /// Clear-aperture diameter (default: 5 mm for built-in:paper, else the largest circle
        /// in the design grid).
        #[arg(long, value_parser = clap_length)]
        aperture: Option<f64>,
        /// PSF method for the design vs as-fabricated comparison, or "none".
        #[arg(long, default_value = "matrix_dft")]
        psf_method: String,
        /// Compute the PSFs even where the method's validity conditions fail (as warnings).
        #[arg(long)]
        allow_invalid: bool,
        /// Scan sample pitch, e.g. "1um" (for scan files that carry none).
        #[arg(long, value_parser = clap_length)]
        scan_pitch: Option<f64>,
        /// Unit of the scan's stored heights, e.g. "nm" (for scan files that state none).
        #[arg(long)]
        scan_z_unit: Option<String>,
        /// Height per count of an integer scan image without a scale, e.g. "0.1nm".
        #[arg(long, value_parser = clap_length)]
        scan_z_scale: Option<f64>,
        #[command(flatten)]
        read: ReadArgs,
        #[command(flatten)]
        optics: OpticsArgs,
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
        /// Levelling before the "levelled" statistics: least-squares plane, facet levelling, or
        /// a plane through the substrate (outside `--aperture`, else the lowest level).
        #[arg(long, value_enum, default_value_t = LevelArg::Plane)]
        level: LevelArg,
        /// Diameter of the part's aperture, centred on the scan, for `--level substrate`.
        #[arg(long, value_parser = clap_length)]
        aperture: Option<f64>,
    },
    /// Reconstruct the linear HDR image of a capture through the DOE with a decoder: EXR plus a
    /// tone-mapped PNG.
    Reconstruct {
        /// The capture: RGB PNG or TIFF, 8 or 16 bits, linear sensor values.
        capture: PathBuf,
        /// Decoder file (.safetensors), e.g. the paper's decoder_measured_psf.safetensors.
        #[arg(long)]
        decoder: PathBuf,
        /// Output EXR (linear, 1 = the capture's clipping level).
        #[arg(short, long)]
        output: PathBuf,
        /// Tone-mapped PNG (default: the output with the extension .png).
        #[arg(long)]
        png: Option<PathBuf>,
        /// Exposure of the tone-mapped PNG, stops.
        #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
        ev: f64,
        /// Largest tile fed to the network, pixels (a multiple of 16).
        #[arg(long, default_value_t = 1024)]
        tile: usize,
        /// Context kept around each tile's core, pixels (a multiple of 16; 128 covers the
        /// receptive field, so tiles then match one pass).
        #[arg(long, default_value_t = 128)]
        overlap: usize,
        /// Mirrored context around the capture, pixels (removes the network's negative blobs
        /// at dark borders; 0 = the paper's demo).
        #[arg(long, default_value_t = doefab::decoder::reconstruct::BORDER)]
        border: usize,
        /// Write negative outputs as they are instead of max(y, 0).
        #[arg(long)]
        keep_negative: bool,
        /// Run on the GPU (builds with the `cuda` feature).
        #[arg(long)]
        gpu: bool,
    },
    /// Fine-tune a decoder for a fixed PSF (the measured PSF of a fabricated part).
    Finetune {
        /// PSF (.npz or .npy, (H, W, 1, 3) as the paper's).
        #[arg(long)]
        psf: PathBuf,
        /// Array name inside a .npz holding several (e.g. psf_val).
        #[arg(long)]
        psf_key: Option<String>,
        /// PSF pixel pitch (the sensor's).
        #[arg(long, value_parser = clap_length, default_value = "4.29um")]
        pitch: f64,
        /// Initial decoder: a file, or built-in:paper-simulated-psf (the default) /
        /// built-in:paper-measured-psf, the paper's decoders compiled in.
        #[arg(long)]
        init: Option<PathBuf>,
        /// Folder of real HDR images (.exr, .hdr, searched recursively; 2:1 images are taken as
        /// equirectangular panoramas); without it, seeded procedural HDR scenes.
        #[arg(long)]
        data: Option<PathBuf>,
        /// Folder of validation HDR images; without it, 1 in --holdout-every of --data's images,
        /// chosen by name, validate and are never trained on.
        #[arg(long)]
        validation_data: Option<PathBuf>,
        #[arg(long, default_value_t = 5)]
        holdout_every: usize,
        /// Leave out equirectangular panoramas narrower than this (pixels).
        #[arg(long, default_value_t = 1024)]
        min_panorama_width: usize,
        /// Largest white-balance gain of the training views' colour jitter: each channel's gain
        /// is log-uniform in [1/G, G] (2 spans the casts of unbalanced sensor RGB).
        #[arg(long, default_value_t = doefab::decoder::dataset::WHITE_BALANCE)]
        white_balance: f64,
        /// Output folder: checkpoint, decoder, training curve.
        #[arg(short, long)]
        output: PathBuf,
        /// Continue the run in the output folder's checkpoint.
        #[arg(long)]
        resume: bool,
        /// Total steps (80: on the paper's real captures, longer runs drift in colour; README).
        #[arg(long, default_value_t = 80)]
        steps: usize,
        #[arg(long, default_value_t = 4)]
        batch: usize,
        /// Crop side, pixels (a multiple of 16).
        #[arg(long, default_value_t = 256)]
        crop: usize,
        /// Adam step size (default 1e-4; on --resume, replaces the saved one when given).
        #[arg(long)]
        lr: Option<f64>,
        /// Step-size decay: lr * lr_decay^(step / 1000).
        #[arg(long, default_value_t = 1.0)]
        lr_decay: f64,
        /// L2-SP pull toward the start weights (0 = none).
        #[arg(long, default_value_t = 0.0)]
        pull: f64,
        /// Keep the encoder at its start weights.
        #[arg(long)]
        freeze_encoder: bool,
        /// Stop after this many validations without a new best (0 = never).
        #[arg(long, default_value_t = 0)]
        patience: usize,
        /// Weight of a penalty on negative outputs, mean(min(y, 0)^2), in the training loss.
        #[arg(long, default_value_t = 0.0)]
        negative_penalty: f64,
        /// Weight of the fine-tuned weights in the decoder written, w0 + blend (w - w0)
        /// (WiSE-FT; 1 = the best validated weights as they are; 0.5 measured best on the
        /// paper's real captures).
        #[arg(long, default_value_t = 0.5)]
        blend: f64,
        /// Read noise of the simulated captures, fraction of full scale (default: as measured
        /// on the paper's captures; the paper trained with 0.02).
        #[arg(long, default_value_t = 0.001)]
        read_noise: f64,
        /// Shot noise of the simulated captures: variance per unit signal (full scale = 1;
        /// default as measured on the paper's captures).
        #[arg(long, default_value_t = 8e-5)]
        shot_noise: f64,
        /// Bit depth of the simulated captures (0 = not quantised; 8 as the paper's captures).
        #[arg(long, default_value_t = 8)]
        bits: u32,
        /// Validate and checkpoint every this many steps.
        #[arg(long, default_value_t = 20)]
        checkpoint_every: usize,
        /// Validation set size.
        #[arg(long, default_value_t = 16)]
        validation: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Run on the GPU (builds with the `cuda` feature).
        #[arg(long)]
        gpu: bool,
    },
}

/// Levelling choice on the command line (`scan-info --level`).
#[derive(Clone, Copy, PartialEq, clap::ValueEnum)]
enum LevelArg {
    Plane,
    Facet,
    Substrate,
}

/// An exposure bracket on the command line.
#[derive(Args, Clone)]
struct BracketArgs {
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

/// Camera response choice on the command line.
#[derive(Clone, Copy, PartialEq, clap::ValueEnum)]
enum ResponseArg {
    Linear,
    Debevec,
}

/// Registration model on the command line.
#[derive(Clone, Copy, clap::ValueEnum)]
enum RegisterArg {
    Affine,
    Local,
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

impl ResponseArg {
    /// The response model as the library takes it.
    fn model(self) -> doefab::pipeline::merge::ResponseModel {
        match self {
            ResponseArg::Linear => doefab::pipeline::merge::ResponseModel::Linear,
            ResponseArg::Debevec => doefab::pipeline::merge::ResponseModel::Debevec,
        }
    }
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

/// Exit status of a scan that cannot be registered to its design (`doefab compare`).
const EXIT_UNREGISTERED: u8 = 3;

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(&cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            for cause in e.chain().skip(1) {
                eprintln!("  caused by: {cause}");
            }
            let unregistered = e
                .chain()
                .any(|c| matches!(c.downcast_ref::<doefab::Error>(), Some(doefab::Error::Registration(_))));
            ExitCode::from(if unregistered { EXIT_UNREGISTERED } else { 2 })
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

/// Shows a library progress callback `(message, done, total)` on a progress bar.
fn report_to(pb: &ProgressBar) -> impl FnMut(&str, u64, u64) + '_ {
    move |message, done, total| {
        pb.set_length(total);
        pb.set_position(done);
        pb.set_message(message.to_string());
    }
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
        Command::Merge { bracket, output, response, png, ev, response_out } => {
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
            warn(&out.report.warnings);
            warn(&out.tone_map.warnings);
            print_result(cli, &out, || {
                print_merge(&out.report, output);
                println!(
                    "  tone-mapped at EV {} ({:.1} % white) -> {}",
                    out.tone_map.ev,
                    100.0 * out.tone_map.clipped_fraction,
                    out.png.display()
                );
                if let (Some(path), Some(curve)) = (response_out, &out.response) {
                    let ranges: Vec<String> =
                        curve.observed.iter().map(|[a, b]| format!("{a}..{b}")).collect();
                    println!(
                        "  response curve (observed values {}) -> {}",
                        ranges.join(", "),
                        path.display()
                    );
                }
            })
        }
        Command::CalibratePsf { bracket, output, crop, centre, capture_pitch, sensor_pitch } => {
            use doefab::pipeline::calibrate_psf::{calibrate_psf, CalibrateOptions};
            let opts = CalibrateOptions {
                bracket: bracket.options(),
                psf: doefab::calibration::psf_extract::PsfOptions {
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
        Command::Evaluate {
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
        } => {
            use doefab::calibration::{evaluate as ev, register as rg};
            let files = ev::EvaluateFiles {
                reference: reference.clone(),
                capture: capture.clone(),
                psf: psf.clone(),
                psf_key: psf_key.clone(),
                capture_pitch: *capture_pitch,
                images: images.clone(),
                options: ev::ScoringOptions {
                    register: rg::RegisterOptions {
                        max_shift: *max_shift,
                        tile: *tile,
                        min_coverage: 0.0,
                        model: match register {
                            RegisterArg::Affine => rg::Model::Affine,
                            RegisterArg::Local => rg::Model::Local,
                        },
                    },
                    saturation: *saturation,
                    min_coverage: *min_coverage,
                    min_saturated: *min_saturated,
                },
            };
            let e = ev::evaluate_files(&files)?;
            warn(&e.footing.warnings);
            print_result(cli, &e, || {
                print_footing(&e.footing);
                for s in &e.scores {
                    print_score(s);
                }
            })
        }
        Command::PsfCompare { a, b, output, pitch, key, radius } => {
            use doefab::pipeline::psf_compare::{psf_compare, PsfCompareOptions};
            let r = psf_compare(&PsfCompareOptions {
                a: a.clone(),
                b: b.clone(),
                compare: doefab::optics::compare::CompareOptions {
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
        Command::Bench { what: BenchCommand::Decoder { .. } } => bench_decoder(cli),
        Command::Bench { what: BenchCommand::Psf { output } } => {
            let pb = progress(cli, doefab::optics::bench::RUNS as u64);
            let points = doefab::pipeline::bench::bench_psf(output, &mut report_to(&pb))?;
            pb.finish_and_clear();
            print_result(cli, &points, || {
                for p in &points {
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
        Command::Compare {
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
        } => {
            let scan_opts = doefab::io::scan::ScanOptions {
                pitch: scan_pitch.map(|p| [p, p]),
                z_unit: scan_z_unit.as_deref().map(length_unit).transpose()?,
                z_scale: *scan_z_scale,
                ..Default::default()
            };
            let source = DesignSource::parse(Some(design), read.options()?);
            let chain = match (recipe, levels) {
                (Some(r), _) => {
                    let r = Recipe::read(r)?;
                    let n = levels.unwrap_or(r.level_count);
                    Some(ChainParams { level_count: n, ..ChainParams::of_recipe(&r, false) })
                }
                (None, Some(n)) => {
                    Some(chain_params(optics, *n, QuantizeMethod::Round, ReplicaMode::Design, 1e-6, false))
                }
                (None, None) => None,
            };
            let psf =
                (psf_method != "none").then(|| doefab::optics::Method::from_name(psf_method)).transpose()?;
            let psf = psf.map(|m| {
                (m, doefab::optics::Options { allow_invalid: *allow_invalid, ..Default::default() })
            });
            let report = compare(cli, scan, &scan_opts, &source, chain.as_ref(), *aperture, psf, output)?;
            warn_comparison(&report);
            print_result(cli, &report, || print_comparison(&report, output))
        }
        Command::ScanInfo { file, pitch, z_unit, z_scale, level, aperture } => {
            let opts = doefab::io::scan::ScanOptions {
                pitch: pitch.map(|p| [p, p]),
                z_unit: z_unit.as_deref().map(length_unit).transpose()?,
                z_scale: *z_scale,
                ..Default::default()
            };
            use doefab::metrology::level::LevelMethod;
            let method = match level {
                LevelArg::Plane => LevelMethod::Plane,
                LevelArg::Facet => LevelMethod::Facet,
                LevelArg::Substrate => LevelMethod::Substrate { aperture: *aperture },
            };
            if aperture.is_some() && *level != LevelArg::Substrate {
                anyhow::bail!("--aperture applies to --level substrate only");
            }
            let info = doefab::metrology::info::scan_info(file, &opts, method)?;
            warn(&info.warnings);
            print_result(cli, &info, || print!("{}", info.summary()))
        }
        Command::Reconstruct {
            capture,
            decoder,
            output,
            png,
            ev,
            tile,
            overlap,
            border,
            keep_negative,
            gpu,
        } => {
            use doefab::decoder::reconstruct::{reconstruct_file, Negatives, ReconstructOptions};
            let opts = ReconstructOptions {
                tile: *tile,
                overlap: *overlap,
                border: *border,
                negatives: if *keep_negative { Negatives::Keep } else { Negatives::Clamp },
            };
            let png = png.clone().unwrap_or_else(|| output.with_extension("png"));
            let device = doefab::decoder::device(*gpu)?;
            let report = reconstruct_file(capture, decoder, output, &png, *ev, &opts, &device)?;
            warn(&report.report.warnings);
            print_result(cli, &report, || {
                let r = &report.report;
                println!(
                    "{} x {} in {} pass(es); raw minimum {:.3}, {} values < 0 and {} < -1 ({}) -> {}, {}",
                    r.cols,
                    r.rows,
                    r.tiles,
                    r.min_raw,
                    r.values_below_zero,
                    r.values_below_minus_one,
                    if *keep_negative { "kept" } else { "clamped to 0" },
                    output.display(),
                    png.display()
                )
            })
        }
        Command::Finetune { .. } => finetune(cli),
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

/// How a scene was registered and what is scored (`evaluate`, `bench decoder`).
fn print_footing(f: &doefab::calibration::evaluate::Footing) {
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
fn print_score(s: &doefab::calibration::evaluate::Score) {
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

fn print_local_registration(r: &doefab::calibration::register::LocalRegistration, excluded: usize) {
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

fn print_merge(r: &doefab::calibration::hdr_merge::MergeReport, output: &Path) {
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

fn print_calibration(r: &doefab::calibration::psf_extract::PsfCalibration, output: &Path) {
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

#[allow(clippy::too_many_arguments)]
fn compare(
    cli: &Cli,
    scan_path: &Path,
    scan_opts: &doefab::io::scan::ScanOptions,
    source: &DesignSource,
    chain: Option<&ChainParams>,
    aperture: Option<f64>,
    psf: Option<(doefab::optics::Method, doefab::optics::Options)>,
    output: &Path,
) -> Result<doefab::metrology::compare::CompareReport> {
    let pb = progress(cli, 4);
    let report = doefab::metrology::compare::compare_scan_file(
        scan_path,
        scan_opts,
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
fn warn_comparison(r: &doefab::metrology::compare::CompareReport) {
    warn(&r.scan_warnings);
    warn(&r.comparison.warnings);
    if let Some(p) = &r.psf {
        warn(&p.warnings);
    }
}

fn print_comparison(r: &doefab::metrology::compare::CompareReport, output: &Path) {
    let c = &r.comparison;
    let g = &c.registration;
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
    let pb = progress(cli, 0);
    let report = doefab::demo::run(output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    for r in &report.fabrication {
        warn(&r.warnings);
    }
    warn(&report.psf.warnings);
    warn_comparison(&report.metrology);
    warn(&report.calibration.report.warnings);
    // Through a JSON value, whose maps sort their keys: one order at every depth.
    print_result(cli, &serde_json::to_value(&report)?, || print_demo(&report))
}

fn print_demo(r: &doefab::demo::DemoReport) {
    let dirs = &r.folders;
    for ((name, out), fab) in dirs.fabrication.iter().zip(&r.fabrication) {
        println!("{name}: {}", out.join("report.md").display());
        for a in &fab.artifacts {
            println!("  {:<16} {}", a.kind, a.path.display());
        }
    }
    println!("simulated scan: {}", dirs.scan.display());
    print_comparison(&r.metrology, &dirs.compare);
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

fn finetune(cli: &Cli) -> Result<()> {
    use doefab::decoder::finetune::{run_job, FinetuneConfig, FinetuneJob};
    let Command::Finetune {
        psf,
        psf_key,
        pitch,
        init,
        data,
        validation_data,
        holdout_every,
        min_panorama_width,
        white_balance,
        output,
        resume,
        steps,
        batch,
        crop,
        lr,
        lr_decay,
        pull,
        freeze_encoder,
        patience,
        negative_penalty,
        blend,
        read_noise,
        shot_noise,
        bits,
        checkpoint_every,
        validation,
        seed,
        gpu,
    } = &cli.command
    else {
        unreachable!("called for finetune only")
    };
    let job = FinetuneJob {
        psf: psf.clone(),
        psf_key: psf_key.clone(),
        pitch: *pitch,
        init: init.clone(),
        data: data.clone(),
        validation_data: validation_data.clone(),
        holdout_every: *holdout_every,
        min_panorama_width: *min_panorama_width,
        white_balance: *white_balance,
        output: output.clone(),
        resume: *resume,
        lr: *lr,
        cfg: FinetuneConfig {
            steps: *steps,
            batch: *batch,
            crop: *crop,
            lr_decay: *lr_decay,
            pull: *pull,
            freeze_encoder: *freeze_encoder,
            patience: *patience,
            negative_penalty: *negative_penalty,
            blend: *blend,
            noise_sigma: *read_noise,
            shot_noise: *shot_noise,
            bits: (*bits > 0).then_some(*bits),
            checkpoint_every: *checkpoint_every,
            validation: *validation,
            seed: *seed,
            ..FinetuneConfig::default()
        },
        gpu: *gpu,
    };
    let pb = progress(cli, *steps as u64);
    if let Ok(style) =
        ProgressStyle::with_template("{bar:30} {pos}/{len} {elapsed_precise} eta {eta_precise} {msg}")
    {
        pb.set_style(style);
    }
    let mut last_psnr = None;
    let outcome = run_job(&job, &mut |r| {
        last_psnr = r.val_psnr.or(last_psnr);
        let val = last_psnr.map_or(String::new(), |p: f64| format!(", validation {p:.2} dB"));
        pb.set_message(format!("loss {:.5}{val}", r.loss));
        pb.set_position(r.step as u64);
    });
    pb.finish_and_clear();
    let outcome = outcome?;
    print_result(cli, &outcome, || {
        println!(
            "{} steps{}; validation PSNR {} at the start, best {:.2} dB at step {}, written (blend {}) {:.2} dB -> {}",
            outcome.steps,
            if outcome.stopped_early { " (stopped early)" } else { "" },
            outcome.start_validation_psnr.map_or("n/a".into(), |p| format!("{p:.2} dB")),
            outcome.best_validation_psnr,
            outcome.best_step,
            outcome.blend,
            outcome.written_validation_psnr,
            outcome.decoder.display()
        )
    })
}

/// `doefab bench decoder`: see [`doefab::decoder::bench`].
fn bench_decoder(cli: &Cli) -> Result<()> {
    use doefab::pipeline::bench::{bench_decoder, DecoderBenchOptions};
    let Command::Bench {
        what:
            BenchCommand::Decoder {
                data,
                scenes,
                decoders,
                psf,
                min_coverage,
                steps,
                init,
                batch,
                crop,
                lr,
                seed,
                evaluate_every,
                train_data,
                tile,
                output,
            },
    } = &cli.command
    else {
        unreachable!("called for bench decoder only")
    };
    let opts = DecoderBenchOptions {
        data: data.clone(),
        scenes: scenes.clone(),
        decoders: decoders.clone(),
        psf: psf.clone(),
        min_coverage: *min_coverage,
        steps: *steps,
        init: init.clone(),
        batch: *batch,
        crop: *crop,
        lr: *lr,
        seed: *seed,
        evaluate_every: *evaluate_every,
        train_data: train_data.clone(),
        tile: *tile,
    };
    let pb = progress(cli, 0);
    let outcome = bench_decoder(&opts, output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    warn(&outcome.warnings);
    let report = &outcome.report;
    print_result(cli, &outcome, || {
        println!(
            "{:<16} {:<52} {:>8} {:>15} {:>15} {:>9} {:>10}",
            "scene", "decoder", "PSNR-L", "gamma all", "gamma sat.", "scored", "min out"
        );
        for r in &report.scenes {
            let Some(f) = &r.footing else {
                println!("{:<16} refused: {}", r.name, r.error.as_deref().unwrap_or(""));
                continue;
            };
            for sc in report.scores.iter().filter(|sc| sc.scene == r.name) {
                let sat = sc.saturated.as_ref().map_or("withheld".into(), |p| format!("{:.2}", p.gamma_db));
                let name: String = sc.decoder.chars().take(52).collect();
                println!(
                    "{:<16} {:<52} {:>8.2} {:>15.2} {:>15} {:>8.1}% {:>10.3}",
                    r.name,
                    name,
                    sc.all.linear_db,
                    sc.all.gamma_db,
                    sat,
                    100.0 * f.coverage,
                    sc.min_output
                );
            }
            println!(
                "{:<16} {} pixels scored, {} of the capture's {} saturated pixels; gain {:.3}, residual {}",
                "",
                f.pixels_scored,
                f.saturated_scored,
                f.saturated_in_capture,
                f.gain,
                f.local_registration
                    .as_ref()
                    .map_or("n/a".into(), |l| format!("{:.2} px", l.residual_rms_px))
            );
        }
        if let Some(run) = &report.finetune {
            println!(
                "fine-tuning: {} steps from {} on {}, {:.2} s a step",
                run.steps, run.init, run.training_data, run.seconds_per_step
            );
        }
        println!("-> {}", output.display());
    })
}
