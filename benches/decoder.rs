//! Speed of the paper's U-Net decoder on the CPU (burn's Flex backend): one training step
//! (batch 8 of 320 x 320, forward + backward + Adam) and inference on one 640 x 640 image,
//! plus the configuration the project measured before choosing a framework (batch 2 of
//! 128 x 128); and the CPU work `finetune` does before each step, simulating the batch's
//! captures (procedural scenes through the paper's measured 319 x 319 PSF, `measure`), which
//! stays on the CPU when the network runs on a GPU. When Python with `torch` is available
//! (`$DOEFAB_PYTHON`, `.venv/bin/python` or `python3`), `benches/decoder_torch.py` times the
//! same network in PyTorch in the same run and the ratios burn / PyTorch are printed;
//! otherwise that part is skipped with a notice.
//!
//! Built with `--features gpu`, the same inference and steps run on the GPU too (wgpu; the
//! first discrete GPU, else the adapter wgpu prefers, named in a warning), and where that
//! Python's torch has a CUDA GPU, `decoder_torch.py cuda` times PyTorch on it (float32, TF32
//! off) and the ratios burn wgpu / PyTorch CUDA are printed; without an adapter the GPU part
//! is skipped with the reason, and without CUDA in torch the GPU comparison is.
//!
//! Weights: the paper's simulated-PSF decoder when the shared data set is beside the checkout,
//! else seeded random weights (speed does not depend on the values).
//!
//! Run with `cargo bench --bench decoder` (`--features gpu` for the GPU part).

use std::path::PathBuf;
use std::process::Command;

mod common;
use std::time::Instant;

use burn::tensor::Device;
use doefab::decoder::MeasurementModel;
use doefab::decoder::UNet;
use doefab::decoder::{device, infer, to_tensor};
use doefab::decoder::{procedural_scenes, simulate_captures, Adam, FinetuneConfig};
use doefab::decoder::{tensor_specs, DecoderWeights, NamedTensor};
use doefab::image::Image;
use doefab::optics::convolve::Convolver;
use doefab::optics::Psf;
use doefab::rng::Lcg;
use ndarray::Array3;

fn weights() -> DecoderWeights {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let shared = root.join("../shared/data/deepoptics-hdr/decoder_simulated_psf.safetensors");
    if let Ok(w) = DecoderWeights::read(&shared) {
        return w;
    }
    let mut g = Lcg(1);
    let tensors = tensor_specs()
        .into_iter()
        .map(|(name, shape)| {
            let n: usize = shape.iter().product();
            let values = if name.ends_with("moving_variance") || name.ends_with("gamma") {
                vec![1.0; n]
            } else {
                (0..n).map(|_| (g.normal() * 0.05) as f32).collect()
            };
            (name, NamedTensor { shape, values })
        })
        .collect();
    DecoderWeights { tensors, metadata: Default::default() }
}

fn image(g: &mut Lcg, n: usize, hi: f64) -> Image<f32> {
    Image::new(Array3::from_shape_fn((n, n, 3), |_| (g.uniform() * hi) as f32))
}

/// CPU time of this process (user + system, all threads), seconds, from `/proc/self/stat`
/// (Linux; `None` elsewhere). On a shared machine wall time depends on the other load, CPU
/// time much less.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0) // USER_HZ is 100 on Linux
}

/// Median wall time and mean CPU time of `runs` calls of `f` after one warm-up call, seconds.
fn time(runs: usize, mut f: impl FnMut()) -> (f64, Option<f64>) {
    f();
    let c0 = cpu_seconds();
    let mut t: Vec<f64> = (0..runs)
        .map(|_| {
            let s = Instant::now();
            f();
            s.elapsed().as_secs_f64()
        })
        .collect();
    let cpu = c0.zip(cpu_seconds()).map(|(a, b)| (b - a) / runs as f64);
    t.sort_by(f64::total_cmp);
    (t[runs / 2], cpu)
}

fn show(on: &str, label: &str, (wall, cpu): (f64, Option<f64>)) {
    println!(
        "{on:<10} {label:<30} wall {wall:>8.3} s  cpu {}",
        cpu.map_or("-".into(), |c| format!("{c:.3} s"))
    );
}

/// Inference on `infer_side`^2 and training steps of `(batch, side)` on `dev`, each with its
/// label. A GPU's queue is drained inside every timed call (the output read back, the device
/// synchronised after a step).
fn network_times(
    w: &DecoderWeights,
    dev: &Device,
    infer_side: usize,
    steps: &[(usize, usize, usize)],
) -> Vec<(String, (f64, Option<f64>))> {
    let net = UNet::from_weights(w, dev);
    let x = image(&mut Lcg(3), infer_side, 1.0);
    let mut times = vec![(
        format!("inference {infer_side}x{infer_side}"),
        time(3, || {
            infer(&net, &x).expect("inference");
        }),
    )];
    for &(batch, side, runs) in steps {
        times.push((
            format!("train step batch {batch}, {side}x{side}"),
            train_step_time(w, dev, batch, side, runs),
        ));
    }
    times
}

/// The configurations timed: inference on 640 x 640, steps of batch 2 of 128 x 128 (3 runs)
/// and batch 8 of 320 x 320 (2 runs).
const STEPS: [(usize, usize, usize); 2] = [(2, 128, 3), (8, 320, 2)];

/// What runs on a software rasterizer, with inference on 128 x 128 (lavapipe: 12 to 15 s
/// each, 57 to 117 times the CPU backend's time; the full set would take hours).
#[cfg(feature = "gpu")]
const SOFTWARE_STEPS: [(usize, usize, usize); 1] = [(2, 64, 3)];

/// The captures of one training batch of 8 crops of 320 x 320, simulated as `finetune` does
/// (procedural scenes, the paper's measured PSF, 8-bit captures).
fn simulation_time() -> doefab::Result<(f64, Option<f64>)> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let psf =
        Psf::read(&root.join("assets/deepoptics-hdr/measured_psf.npz"), Some("psf_val"), Some(4.29e-6))?;
    let (kh, kw) = psf.dim();
    let conv = Convolver::new(&psf, (320 + kh - 1, 320 + kw - 1))?;
    let model = MeasurementModel { bits: Some(8), ..MeasurementModel::default() };
    let source = procedural_scenes();
    let mut g = Lcg(4);
    Ok(time(2, || {
        simulate_captures(&source, &conv, &model, 320, &mut g, 8).expect("simulated captures");
    }))
}

fn train_step_time(
    w: &DecoderWeights,
    dev: &Device,
    batch: usize,
    side: usize,
    runs: usize,
) -> (f64, Option<f64>) {
    let mut net = UNet::from_weights(w, dev);
    let mut adam = Adam::new(&net, &FinetuneConfig::default());
    let mut g = Lcg(2);
    let xs: Vec<Image<f32>> = (0..batch).map(|_| image(&mut g, side, 1.0)).collect();
    let ts: Vec<Image<f32>> = (0..batch).map(|_| image(&mut g, side, 4.0)).collect();
    let xr: Vec<&Image<f32>> = xs.iter().collect();
    let tr: Vec<&Image<f32>> = ts.iter().collect();
    time(runs, || {
        adam.step(&mut net, to_tensor(&xr, dev), to_tensor(&tr, dev)).expect("finite loss");
        dev.sync().expect("the step ran");
    })
}

/// `benches/decoder_torch.py`'s output on `on` ("cpu" or "cuda"), `None` when it fails (no
/// torch, or no CUDA GPU).
fn torch(python: &str, on: &str) -> Option<String> {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("benches/decoder_torch.py");
    let out = Command::new(python).arg(script).arg(on).output().ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).into_owned())
}

/// PyTorch's times from `text` (lines "name wall_seconds cpu_seconds") beside burn's, in the
/// order of [`network_times`] on 640 x 640 with [`STEPS`], and the ratios burn / PyTorch.
fn compare(torch_on: &str, burn: &[(String, (f64, Option<f64>))], text: &str) {
    let get = |k: &str| {
        text.lines().find_map(|l| {
            let v: Vec<f64> = l.strip_prefix(k)?.split_whitespace().filter_map(|x| x.parse().ok()).collect();
            (v.len() == 2).then(|| (v[0], v[1]))
        })
    };
    for (k, (_, (wall, cpu))) in ["inference_640", "train_b2_128", "train_b8_320"].into_iter().zip(burn) {
        if let Some((tw, tc)) = get(k) {
            let cpu_ratio = cpu.map_or("-".into(), |c| format!("{:.2}", c / tc));
            println!(
                "{torch_on:<10} {k:<30} wall {tw:>8.3} s  cpu {tc:.3} s   burn / torch: wall {:.2}, cpu {cpu_ratio}",
                wall / tw
            );
        }
    }
}

fn main() -> doefab::Result<()> {
    let w = weights();
    println!("threads: {}", rayon::current_num_threads());
    let cpu = network_times(&w, &device(false)?, 640, &STEPS);
    for (label, t) in &cpu {
        show("burn flex", label, *t);
    }
    show("cpu", "simulate batch 8, 320x320", simulation_time()?);
    let python = common::python_with("torch");
    match python.as_deref().and_then(|p| torch(p, "cpu")) {
        Some(text) => compare("torch cpu", &cpu, &text),
        None => println!("notice: no Python with torch found; the PyTorch comparison is skipped"),
    }
    #[cfg(feature = "gpu")]
    gpu_times(&w, python.as_deref())?;
    Ok(())
}

/// The same on the GPU (a software rasterizer: less, with the CPU's times beside it), and
/// against PyTorch on the first CUDA GPU where `python`'s torch has one.
#[cfg(feature = "gpu")]
fn gpu_times(w: &DecoderWeights, python: Option<&str>) -> doefab::Result<()> {
    let gpu = match doefab::decoder::select_device(true) {
        Ok(gpu) => gpu,
        Err(e) => {
            println!("notice: the GPU part is skipped: {e}");
            return Ok(());
        }
    };
    for warning in &gpu.warnings {
        println!("warning: {warning}");
    }
    if gpu.software {
        println!("notice: a software rasterizer: only inference on 128x128 and a step of batch 2 of 64x64 run, on both");
        for (label, t) in network_times(w, &device(false)?, 128, &SOFTWARE_STEPS) {
            show("burn flex", &label, t);
        }
        for (label, t) in network_times(w, &gpu.device, 128, &SOFTWARE_STEPS) {
            show("burn wgpu", &label, t);
        }
        return Ok(());
    }
    let times = network_times(w, &gpu.device, 640, &STEPS);
    for (label, t) in &times {
        show("burn wgpu", label, *t);
    }
    match python.and_then(|p| torch(p, "cuda")) {
        Some(text) => {
            if let Some(name) = text.lines().find_map(|l| l.strip_prefix("device ")) {
                println!("torch cuda on {name}");
            }
            compare("torch cuda", &times, &text)
        }
        None => {
            println!("notice: no PyTorch with a CUDA GPU found; the GPU comparison with PyTorch is skipped")
        }
    }
    Ok(())
}
