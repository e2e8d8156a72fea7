//! The decoder commands: `reconstruct`, `finetune`, `bench decoder`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use indicatif::ProgressStyle;

use super::options::{clap_length, Cli};
use super::options::{print_result, progress, report_to, warn};

/// Arguments of `doefab reconstruct`.
#[derive(Args)]
pub struct ReconstructArgs {
    /// The capture: RGB PNG or TIFF, 8 or 16 bits, linear sensor values.
    pub capture: PathBuf,
    /// Decoder file (.safetensors), or built-in:paper-simulated-psf / built-in:paper-measured-psf /
    /// built-in:doefab-measured-psf.
    #[arg(long)]
    pub decoder: PathBuf,
    /// Output EXR (linear, 1 = the capture's clipping level).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Tone-mapped PNG (default: the output with the extension .png).
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Exposure of the tone-mapped PNG, stops.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    pub ev: f64,
    /// Largest tile fed to the network, pixels (a multiple of 16).
    #[arg(long, default_value_t = 1024)]
    pub tile: usize,
    /// Context kept around each tile's core, pixels (a multiple of 16; 128 covers the
    /// receptive field, so tiles then match one pass).
    #[arg(long, default_value_t = 128)]
    pub overlap: usize,
    /// Mirrored context around the capture, pixels (removes the network's negative blobs
    /// at dark borders; 0 = the paper's demo).
    #[arg(long, default_value_t = doefab::decoder::BORDER)]
    pub border: usize,
    /// Write negative outputs as they are instead of max(y, 0).
    #[arg(long)]
    pub keep_negative: bool,
    /// Run on the GPU (builds with the `gpu` feature: any vendor's GPU; or `cuda`).
    #[arg(long)]
    pub gpu: bool,
}

/// Arguments of `doefab finetune`.
#[derive(Args)]
pub struct FinetuneArgs {
    /// PSF (.npz or .npy, (H, W, 1, 3) as the paper's).
    #[arg(long)]
    pub psf: PathBuf,
    /// Array name inside a .npz holding several (e.g. psf_val).
    #[arg(long)]
    pub psf_key: Option<String>,
    /// PSF pixel pitch (the sensor's).
    #[arg(long, value_parser = clap_length, default_value = "4.29um")]
    pub pitch: f64,
    /// Initial decoder: a file, or built-in:paper-simulated-psf (the default) /
    /// built-in:paper-measured-psf (the paper's decoders) / built-in:doefab-measured-psf
    /// (doefab's fine-tune on the paper's measured PSF), compiled in.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Folder of real HDR images (.exr, .hdr, searched recursively; 2:1 images are taken as
    /// equirectangular panoramas; an unreadable one is skipped with a warning); without it,
    /// seeded procedural HDR scenes.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Folder of validation HDR images; without it, 1 in --holdout-every of --data's images,
    /// chosen by name, validate and are never trained on.
    #[arg(long)]
    pub validation_data: Option<PathBuf>,
    #[arg(long, default_value_t = doefab::decoder::HOLDOUT_EVERY)]
    pub holdout_every: usize,
    /// Leave out equirectangular panoramas narrower than this (pixels).
    #[arg(long, default_value_t = doefab::decoder::MIN_PANORAMA_WIDTH)]
    pub min_panorama_width: usize,
    /// Largest white-balance gain of the training views' colour jitter: each channel's gain
    /// is log-uniform in [1/G, G] (2 spans the casts of unbalanced sensor RGB).
    #[arg(long, default_value_t = doefab::decoder::WHITE_BALANCE)]
    pub white_balance: f64,
    /// Output folder: checkpoint, decoder, training curve.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Continue the run in the output folder's checkpoint.
    #[arg(long)]
    pub resume: bool,
    /// Total steps (80, measured with three seeds on 2 cores; 240 with --blend 0.5 made
    /// built-in:doefab-measured-psf; README).
    #[arg(long, default_value_t = doefab::decoder::STEPS)]
    pub steps: usize,
    #[arg(long, default_value_t = doefab::decoder::BATCH)]
    pub batch: usize,
    /// Crop side, pixels (a multiple of 16).
    #[arg(long, default_value_t = doefab::decoder::CROP)]
    pub crop: usize,
    /// Adam step size (default 1e-4; on --resume, replaces the saved one when given).
    #[arg(long)]
    pub lr: Option<f64>,
    /// Step-size decay: lr * lr_decay^(step / 1000).
    #[arg(long, default_value_t = 1.0)]
    pub lr_decay: f64,
    /// L2-SP pull toward the start weights (0 = none).
    #[arg(long, default_value_t = 0.0)]
    pub pull: f64,
    /// Keep the encoder at its start weights.
    #[arg(long)]
    pub freeze_encoder: bool,
    /// Stop after this many validations without a new best (0 = never).
    #[arg(long, default_value_t = 0)]
    pub patience: usize,
    /// Weight of a penalty on negative outputs, mean(min(y, 0)^2), in the training loss (10:
    /// the fine-tuned decoder then scores above its start on both of the paper's real scenes,
    /// which without it lose on Kitchen; 0 = the paper's loss alone; README)
    #[arg(long, default_value_t = doefab::decoder::NEGATIVE_PENALTY)]
    pub negative_penalty: f64,
    /// Weight of the fine-tuned weights in the decoder written, w0 + blend (w - w0)
    /// (WiSE-FT; 1 = the best validated weights as they are; 0.25 keeps the colour balance
    /// on the paper's real captures within 5 % with every seed tried; README).
    #[arg(long, default_value_t = doefab::decoder::BLEND)]
    pub blend: f64,
    /// Read noise of the simulated captures, fraction of full scale (default: as measured
    /// on the paper's captures; the paper trained with 0.02).
    #[arg(long, default_value_t = doefab::decoder::READ_NOISE)]
    pub read_noise: f64,
    /// Shot noise of the simulated captures: variance per unit signal (full scale = 1;
    /// default as measured on the paper's captures).
    #[arg(long, default_value_t = doefab::decoder::SHOT_NOISE)]
    pub shot_noise: f64,
    /// Bit depth of the simulated captures (0 = not quantised; 8 as the paper's captures).
    #[arg(long, default_value_t = doefab::decoder::BITS)]
    pub bits: u32,
    /// Where the simulated captures' R, G and B clip, fractions of full scale (default: as the
    /// paper's camera, green at 231 of 255; `evaluate` and `merge` report a camera's own).
    #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = doefab::decoder::CHANNEL_CLIPPING)]
    pub channel_clipping: Vec<f64>,
    #[command(flatten)]
    pub halo: HaloArgs,
    /// Validate and checkpoint every this many steps.
    #[arg(long, default_value_t = doefab::decoder::CHECKPOINT_EVERY)]
    pub checkpoint_every: usize,
    /// Validation set size.
    #[arg(long, default_value_t = doefab::decoder::VALIDATION)]
    pub validation: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Largest global gradient norm a step takes; larger ones are scaled down to it (0 = no
    /// clipping; the first steps' norms reach 10^3-10^4 where the usual ones are 0.5-2, and
    /// cut to 2 they no longer stall Adam; README).
    #[arg(long, default_value_t = doefab::decoder::GRAD_CLIP)]
    pub grad_clip: f64,
    /// Run on the GPU (builds with the `gpu` feature: any vendor's GPU; or `cuda`).
    #[arg(long)]
    pub gpu: bool,
}

/// Arguments of `doefab bench decoder`.
#[derive(Args)]
pub struct BenchDecoderArgs {
    /// The paper's data release: the default scenes (captures/<scene>/) and measured_psf.npz.
    #[arg(long, default_value = "../shared/data/deepoptics-hdr")]
    pub data: PathBuf,
    /// A scene folder (exposures.json with one "doe" capture and a bracket); repeat for more
    /// (default: every folder under <data>/captures).
    #[arg(long = "scene")]
    pub scenes: Vec<PathBuf>,
    /// A decoder to score: a .safetensors file or built-in:paper-simulated-psf /
    /// built-in:paper-measured-psf / built-in:doefab-measured-psf; repeat for more (default:
    /// the paper's two).
    #[arg(long = "decoder")]
    pub decoders: Vec<PathBuf>,
    /// The measured PSF (default <data>/measured_psf.npz, array psf_val).
    #[arg(long)]
    pub psf: Option<PathBuf>,
    /// Smallest fraction of a scene that must be registered; below it the scene is refused.
    #[arg(long, default_value_t = 0.3)]
    pub min_coverage: f64,
    /// Fine-tuning steps of --init on the PSF (0: no fine-tuning; default finetune's).
    #[arg(long, default_value_t = doefab::decoder::STEPS)]
    pub steps: usize,
    /// The decoder to fine-tune.
    #[arg(long, default_value = "built-in:paper-simulated-psf")]
    pub init: PathBuf,
    /// Batch size of the fine-tuning (finetune's).
    #[arg(long, default_value_t = doefab::decoder::BATCH)]
    pub batch: usize,
    /// Training crop side, pixels (a multiple of 16; finetune's: 128 px crops, smaller than
    /// the 320 px PSF, lose on the real captures).
    #[arg(long, default_value_t = doefab::decoder::CROP)]
    pub crop: usize,
    /// Adam step size.
    #[arg(long, default_value_t = 1e-4)]
    pub lr: f64,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Score the decoder being fine-tuned on the real scenes every this many steps
    /// (default: at each validation, every 20 steps).
    #[arg(long)]
    pub evaluate_every: Option<usize>,
    /// HDR images to fine-tune on (a folder of EXR / Radiance .hdr), with finetune's hold-out
    /// for validation and its narrowest panorama. Not the benchmark's own scenes, or the
    /// scores measure memory.
    #[arg(long, default_value = "../shared/data/hdr")]
    pub train_data: PathBuf,
    /// Fine-tune on seeded procedural HDR scenes instead of --train-data.
    #[arg(long)]
    pub procedural: bool,
    /// Where the fine-tuning's simulated captures clip, R, G, B (finetune's: the paper's camera).
    #[arg(long, value_delimiter = ',', num_args = 3, default_values_t = doefab::decoder::CHANNEL_CLIPPING)]
    pub channel_clipping: Vec<f64>,
    #[command(flatten)]
    pub halo: HaloArgs,
    /// Tile side of the registration, pixels.
    #[arg(long, default_value_t = 48)]
    pub tile: usize,
    /// The fine-tuning's largest gradient norm (finetune's --grad-clip; 0 = no clipping).
    #[arg(long, default_value_t = doefab::decoder::GRAD_CLIP)]
    pub grad_clip: f64,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// `doefab reconstruct`.
pub fn reconstruct(cli: &Cli, a: &ReconstructArgs) -> Result<()> {
    let ReconstructArgs { capture, decoder, output, png, ev, tile, overlap, border, keep_negative, gpu } = a;
    use doefab::decoder::{reconstruct_file, Negatives, ReconstructOptions};
    let opts = ReconstructOptions {
        tile: *tile,
        overlap: *overlap,
        border: *border,
        negatives: if *keep_negative { Negatives::Keep } else { Negatives::Clamp },
    };
    let png = png.clone().unwrap_or_else(|| output.with_extension("png"));
    let selected = doefab::decoder::select_device(*gpu)?;
    let mut report = reconstruct_file(capture, decoder, output, &png, *ev, &opts, &selected.device)?;
    report.stats.warnings.extend(selected.warnings);
    warn(&report.stats.warnings);
    print_result(cli, &report, || {
        let r = &report.stats;
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

/// `doefab finetune`.
pub fn finetune(cli: &Cli, a: &FinetuneArgs) -> Result<()> {
    use doefab::decoder::{FinetuneConfig, FinetuneJob};
    use doefab::pipeline::finetune::finetune;
    let FinetuneArgs {
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
        grad_clip,
        read_noise,
        shot_noise,
        bits,
        channel_clipping,
        halo,
        checkpoint_every,
        validation,
        seed,
        gpu,
    } = a;
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
            grad_clip: *grad_clip,
            noise_sigma: *read_noise,
            shot_noise: *shot_noise,
            bits: (*bits > 0).then_some(*bits),
            channel_clipping: [channel_clipping[0], channel_clipping[1], channel_clipping[2]],
            halo: halo.halo(),
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
    let outcome = finetune(&job, &mut |r| {
        last_psnr = r.val_psnr.or(last_psnr);
        let val = last_psnr.map_or(String::new(), |p: f64| format!(", validation {p:.2} dB"));
        pb.set_message(format!("loss {:.5}{val}", r.loss));
        pb.set_position(r.step as u64);
    });
    pb.finish_and_clear();
    let outcome = outcome?;
    warn(&outcome.warnings);
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

/// `doefab bench decoder`: see [`doefab::pipeline::sweep`].
pub fn bench_decoder(cli: &Cli, a: &BenchDecoderArgs) -> Result<()> {
    use doefab::pipeline::sweep::{sweep_decoder, DecoderSweepOptions};
    let BenchDecoderArgs {
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
        procedural,
        channel_clipping,
        halo,
        tile,
        grad_clip,
        output,
    } = a;
    let opts = DecoderSweepOptions {
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
        train_data: (!procedural).then(|| train_data.clone()),
        tile: *tile,
        channel_clipping: [channel_clipping[0], channel_clipping[1], channel_clipping[2]],
        halo: halo.halo(),
        grad_clip: *grad_clip,
    };
    let pb = progress(cli, 0);
    let outcome = sweep_decoder(&opts, output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    warn(&outcome.warnings);
    let report = &outcome.results;
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

/// The halo of the simulated captures (`finetune`, `bench decoder`).
#[derive(Args, Clone)]
pub struct HaloArgs {
    /// Fraction of the light the element spreads beyond its measured PSF's crop, in a Gaussian
    /// of --halo-radius (0 = none; `doefab bench forward` measures it on real captures).
    #[arg(long, default_value_t = doefab::decoder::HALO.fraction)]
    pub halo: f64,
    /// The halo's Gaussian standard deviation, sensor pixels.
    #[arg(long, default_value_t = doefab::decoder::HALO.radius_px)]
    pub halo_radius: f64,
}

impl HaloArgs {
    fn halo(&self) -> Option<doefab::decoder::Halo> {
        (self.halo > 0.0)
            .then_some(doefab::decoder::Halo { fraction: self.halo, radius_px: self.halo_radius })
    }
}

/// Arguments of `doefab bench forward`.
#[derive(Args)]
pub struct BenchForwardArgs {
    /// The paper's data release: the default scenes (captures/<scene>/) and measured_psf.npz.
    #[arg(long, default_value = "../shared/data/deepoptics-hdr")]
    pub data: PathBuf,
    /// A scene folder (exposures.json with one "doe" capture and a bracket); repeat for more
    /// (default: every folder under <data>/captures).
    #[arg(long = "scene")]
    pub scenes: Vec<PathBuf>,
    /// The measured PSF (default <data>/measured_psf.npz, array psf_val).
    #[arg(long)]
    pub psf: Option<PathBuf>,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// `doefab bench forward`.
pub fn bench_forward(cli: &Cli, a: &BenchForwardArgs) -> Result<()> {
    use doefab::pipeline::sweep::sweep_forward;
    use doefab::sweep::forward::ForwardOptions;
    let opts = ForwardOptions {
        data: a.data.clone(),
        scenes: a.scenes.clone(),
        psf: a.psf.clone(),
        scoring: doefab::calibration::ScoringOptions::default(),
    };
    let pb = progress(cli, 0);
    let r = sweep_forward(&opts, &a.output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    print_result(cli, &r, || {
        for s in &r.scenes {
            println!(
                "{}: {:.0} % scored, gain {:.3}; RMS of sqrt(model) - sqrt(capture), unsaturated pixels: darks / mid-tones / brights / flare ring / all; saturated IoU",
                s.name,
                100.0 * s.coverage,
                s.gain
            );
            for m in &s.models {
                let x = &m.residuals;
                let halo =
                    m.halo.map_or(String::new(), |h| format!(" eta {} rho {} px", h.fraction, h.radius_px));
                println!(
                    "  {:<46} {:.4} {:.4} {:.4} {:.4} {:.4}  {:.2}  gains {:.3} {:.3} {:.3}{halo} blur {} px",
                    m.model,
                    x.dark,
                    x.mid,
                    x.bright,
                    x.ring,
                    x.all,
                    x.saturated_iou,
                    m.gains[0],
                    m.gains[1],
                    m.gains[2],
                    m.blur_px
                );
            }
        }
        for (name, why) in &r.refused {
            println!("{name} refused: {why}");
        }
        println!("wrote {}", a.output.display());
    })
}

/// Arguments of `doefab bench tiling`.
#[derive(Args)]
pub struct BenchTilingArgs {
    /// The decoder: a .safetensors file or built-in:paper-simulated-psf /
    /// built-in:paper-measured-psf / built-in:doefab-measured-psf.
    #[arg(long, default_value = "built-in:paper-measured-psf")]
    pub decoder: PathBuf,
    /// Side of the simulated capture, pixels (a multiple of 16).
    #[arg(long, default_value_t = 512)]
    pub size: usize,
    /// Tile sides to try (multiples of 16), comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [128, 256, 384])]
    pub tiles: Vec<usize>,
    /// Overlaps to try (multiples of 16), comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = [0, 16, 32, 64, 96, 128])]
    pub overlaps: Vec<usize>,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Output folder.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// `doefab bench tiling`.
pub fn bench_tiling(cli: &Cli, a: &BenchTilingArgs) -> Result<()> {
    use doefab::sweep::tiling::{steps, TilingOptions};
    let opts =
        TilingOptions { size: a.size, tiles: a.tiles.clone(), overlaps: a.overlaps.clone(), seed: a.seed };
    let pb = progress(cli, steps(&opts) as u64);
    let r = doefab::pipeline::sweep::sweep_tiling(&a.decoder, &opts, &a.output, &mut report_to(&pb))?;
    pb.finish_and_clear();
    print_result(cli, &r, || {
        println!("f64 one pass (the reference): {:.2} s", r.reference_seconds);
        for p in &r.runs {
            let how = match (p.tile, p.overlap) {
                (Some(t), Some(o)) => format!("tile {t:>4}, overlap {o:>3}, {:>3} passes", p.passes),
                _ => "one pass".to_string(),
            };
            println!(
                "{} {how:<34} {:>6.2} s  relative L2 {:.2e}  largest difference {:.2e}",
                p.precision, p.seconds, p.relative_l2, p.max_abs
            );
        }
        if !r.skipped.is_empty() {
            let s: Vec<String> = r.skipped.iter().map(|[t, o]| format!("{t}/{o}")).collect();
            println!("skipped (tile <= 2 overlap, or over 9 passes' cost): {}", s.join(", "));
        }
        println!("wrote {}", a.output.display());
    })
}
