//! The command line's grammar: the commands (each command's own arguments are in its stage's
//! module, what several share in [`super::options`]).

use clap::{Parser, Subcommand};

use super::calibration::{BenchCalibrationArgs, CalibratePsfArgs, EvaluateArgs, MergeArgs};
use super::decoder::{BenchDecoderArgs, BenchForwardArgs, BenchTilingArgs, FinetuneArgs, ReconstructArgs};
use super::demo::DemoArgs;
use super::fabrication::{
    BenchFabArgs, FabArgs, GdsArgs, MaskArgs, PrecompensateArgs, QuantizeArgs, StlArgs, WrapArgs,
};
use super::metrology::BenchRegisterArgs;
use super::metrology::{CompareArgs, CompareProfileArgs, ScanInfoArgs, SimulateScanArgs};
use super::optics::{
    BenchPsfArgs, BenchSpectralArgs, BenchStabilityArgs, PsfArgs, PsfCompareArgs, ReportArgs,
};
use super::options::Cli;

#[derive(Parser)]
#[command(name = "doefab", version, about = "From a learned DOE design to a fabricated part", long_about = None)]
pub struct CommandLine {
    #[command(subcommand)]
    pub command: Command,
    #[command(flatten)]
    pub cli: Cli,
}

#[derive(Subcommand)]
pub enum Command {
    /// Simulate the RGB PSF of a height map in the paper's camera: EXR, NPY (H, W, 1, 3),
    /// log-scale PNG and a JSON summary.
    Psf(PsfArgs),
    /// Merge an exposure bracket of linear (or, with --response debevec, non-linear 8-bit)
    /// captures into an HDR radiance image (OpenEXR, channels R, G, B).
    Merge(MergeArgs),
    /// The measured PSF from a pinhole bracket: merge, dark and background, hot pixels,
    /// centring, crop, normalisation. Writes psf.exr, psf.npy (H, W, 1, C), psf_log.png,
    /// merged.exr and psf.json.
    CalibratePsf(CalibratePsfArgs),
    /// PSNR of reconstructions against a reference HDR image, linear and gamma (sqrt), over the
    /// registered pixels and the saturated ones: the reference is registered onto the capture
    /// once (through the PSF) and every reconstruction is scored on the same pixels.
    Evaluate(EvaluateArgs),
    /// Compare two PSFs (design, as-fabricated, measured): each one's peaks, encircled energy
    /// and centroid per channel, and the relative L2 after centroid alignment.
    PsfCompare(PsfCompareArgs),
    /// The benchmarks of a design within one time budget, gathered into one static HTML page
    /// (index.html) with its charts (SVG) and data (JSON, CSV).
    Report(ReportArgs),
    /// Benchmarks with charts.
    Bench {
        #[command(subcommand)]
        what: BenchCommand,
    },
    /// Run every stage on the built-in example design (no input needed).
    Demo(DemoArgs),
    /// The whole fabrication chain for a recipe: wrap, quantize, masks, GDSII, STL, report.
    Fab(FabArgs),
    /// The next mask set pre-compensated for the process that a scan of the last part measured
    /// (depth scale, per-level heights, lateral blur): the recipe's grayscale masks and STL with
    /// a sidecar naming the corrections, the scan's SHA-256 and the predicted result.
    Precompensate(PrecompensateArgs),
    /// Wrap heights modulo p * 2 pi at the design wavelength (optionally as the replica master).
    Wrap(WrapArgs),
    /// Quantize wrapped heights to N levels and predict the diffraction efficiency.
    Quantize(QuantizeArgs),
    /// Grayscale lithography mask (PNG or TIFF by extension) with a JSON sidecar.
    Mask(MaskArgs),
    /// Multi-level binary mask set (log2 N layers) as one GDSII file, with layer previews.
    Gds(GdsArgs),
    /// Watertight binary STL of a level map or of wrapped heights.
    Stl(StlArgs),
    /// A synthetic fabricated scan of a design (.x3p or .gsf): lateral blur, depth scale,
    /// offset, tilt, placement (rotation, shift, scale, mirror), complement, noise, missing points.
    SimulateScan(SimulateScanArgs),
    /// Compare a scan of the fabricated part with its design: registration, difference map,
    /// RMS/PV error, level step heights, fabrication model (depth scale, offset, blur),
    /// efficiency loss, design vs as-fabricated PSF; JSON, maps, profiles, histogram and the
    /// part in the design frame (surface.exr, readable by `doefab psf`). Exit status 3 when the
    /// scan cannot be registered to the design (no match, ambiguous or featureless).
    Compare(CompareArgs),
    /// A stylus profile (Dektak, Alpha-Step, P-series CSV/TXT export) levelled and compared with
    /// its design along a line (--line x0,y0,x1,y1 or --angle through the centre): shift along
    /// and across the line, depth scale, offset, tilt, lateral blur with standard errors, and
    /// per-level step heights. Without a design: the step heights of the profile's own terraces.
    /// JSON report, fit table and SVG plot with -o. Exit status 3 when the profile cannot be
    /// registered to the design (no match, or an ambiguous shift).
    CompareProfile(CompareProfileArgs),
    /// What a profilometer scan holds: size, pitch, units, valid fraction, warnings, ISO 25178
    /// height parameters (raw and after removing the least-squares plane).
    ScanInfo(ScanInfoArgs),
    /// Reconstruct the linear HDR image of a capture through the DOE with a decoder: EXR plus a
    /// tone-mapped PNG.
    Reconstruct(ReconstructArgs),
    /// Fine-tune a decoder for a fixed PSF (the measured PSF of a fabricated part).
    Finetune(FinetuneArgs),
}

#[derive(Subcommand)]
// Parsed once per run: the size of the larger variant costs nothing.
#[allow(clippy::large_enum_variant)]
pub enum BenchCommand {
    /// Error against run time of every PSF method, precision and sub-sampling on a design at its
    /// own geometry, and error against pupil sampling with the guard's refusals: PNG + SVG + JSON.
    Psf(BenchPsfArgs),
    /// Spectral sampling of colour bands: the error of the midpoint rule over N sub-bands per
    /// band against a converged reference, the plan's estimate beside it, and the plan's rule
    /// placed at each tolerance with the silent failures counted: PNG + SVG + JSON.
    Spectral(BenchSpectralArgs),
    /// Stability maps of the two-step Fresnel method: its error against an exact truth over
    /// pupil sampling x Fresnel number and pupil sampling x wavelength, each run with its
    /// guard's verdict, the silent failures counted, the paper's sampling marked: PNG + SVG + JSON.
    Stability(BenchStabilityArgs),
    /// Where scan registration fails: its error and verdict (registered, refused, accepted but
    /// wrong) over noise, blur, missing fraction, rotation, scale and level count, from simulated
    /// scans of known pose: PNG + SVG + JSON + CSV.
    Register(BenchRegisterArgs),
    /// The fabrication stage's numerical methods against known truths: quantization (predicted
    /// against simulated efficiency per level count and wavelength), the STL heightfield
    /// (triangles, time and measured height error against max_error) and GDSII tracing (polygons,
    /// vertices, file size and time against the vertex limit; polygon area against the bitmap):
    /// PNG + SVG + JSON + CSV.
    Fab(BenchFabArgs),
    /// Where the PSF calibration fails: the error of the PSF recovered from simulated pinhole
    /// brackets of a known PSF (default the paper's measured one) against the frame count, read
    /// noise and black level, each trial calibrated, warned, refused or silently wrong:
    /// PNG + SVG + JSON + CSV.
    Calibration(BenchCalibrationArgs),
    /// The decoder's reconstruction against tile size and overlap, and f32 against f64, on a
    /// simulated capture: difference from the f64 one-pass output and time: PNG + SVG + JSON +
    /// CSV.
    Tiling(BenchTilingArgs),
    /// Decoders on real captures: each scene's reference is registered onto its capture once
    /// (through the measured PSF), and the capture and every decoder are scored on the same
    /// pixels (PSNR-L, PSNR-gamma over all and saturated pixels, coverage, smallest output);
    /// optionally a decoder is fine-tuned on the PSF first. JSON report, decoder x scene chart.
    Decoder(BenchDecoderArgs),
    /// The decoder's measurement model against real captures: each scene's reference through
    /// the measured PSF, registered onto its capture, and what channel clipping, channel gains,
    /// a halo beyond the PSF's crop and a blur add, by brightness band: PNG + JSON.
    Forward(BenchForwardArgs),
}
