//! Speed of the paper's U-Net decoder on the CPU (burn's Flex backend): one training step
//! (batch 8 of 320 x 320, forward + backward + Adam) and inference on one 640 x 640 image,
//! plus the configuration the project measured before choosing a framework (batch 2 of
//! 128 x 128). When Python with `torch` is available (`$DOEFAB_PYTHON`, `.venv/bin/python` or
//! `python3`), `benches/decoder_torch.py` times the same network in PyTorch in the same run and
//! the ratios burn / PyTorch are printed; otherwise that part is skipped with a notice.
//!
//! Weights: the paper's simulated-PSF decoder when the shared data set is beside the checkout,
//! else seeded random weights (speed does not depend on the values).
//!
//! Run with `cargo bench --bench decoder`.

use std::path::PathBuf;
use std::process::Command;

mod common;
use std::time::Instant;

use doefab::decoder::finetune::{Adam, FinetuneConfig};
use doefab::decoder::unet::UNet;
use doefab::decoder::weights::{tensor_specs, DecoderWeights, NamedTensor};
use doefab::decoder::{device, infer, to_tensor};
use doefab::image::Image;
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

fn show(label: &str, (wall, cpu): (f64, Option<f64>)) {
    println!(
        "burn flex  {label:<30} wall {wall:>8.3} s  cpu {}",
        cpu.map_or("-".into(), |c| format!("{c:.3} s"))
    );
}

fn train_step_time(w: &DecoderWeights, batch: usize, side: usize, runs: usize) -> (f64, Option<f64>) {
    let dev = device(false).unwrap();
    let mut net = UNet::from_weights(w, &dev);
    let mut adam = Adam::new(&net, &FinetuneConfig::default());
    let mut g = Lcg(2);
    let xs: Vec<Image<f32>> = (0..batch).map(|_| image(&mut g, side, 1.0)).collect();
    let ts: Vec<Image<f32>> = (0..batch).map(|_| image(&mut g, side, 4.0)).collect();
    let xr: Vec<&Image<f32>> = xs.iter().collect();
    let tr: Vec<&Image<f32>> = ts.iter().collect();
    time(runs, || {
        adam.step(&mut net, to_tensor(&xr, &dev), to_tensor(&tr, &dev)).expect("finite loss");
    })
}

fn torch(python: &str) -> Option<String> {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("benches/decoder_torch.py");
    let out = Command::new(python).arg(script).output().ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).into_owned())
}

fn main() -> doefab::Result<()> {
    let w = weights();
    println!("threads: {}", rayon::current_num_threads());
    let dev = device(false)?;
    let net = UNet::from_weights(&w, &dev);
    let x = image(&mut Lcg(3), 640, 1.0);
    let infer_s = time(3, || {
        infer(&net, &x).expect("inference");
    });
    show("inference 640x640", infer_s);
    let small_s = train_step_time(&w, 2, 128, 3);
    show("train step batch 2, 128x128", small_s);
    let step_s = train_step_time(&w, 8, 320, 2);
    show("train step batch 8, 320x320", step_s);

    let result = common::python_with("torch").and_then(|p| torch(&p));
    let Some(text) = result else {
        println!("notice: no Python with torch found; the PyTorch comparison is skipped");
        return Ok(());
    };
    // Lines "name wall_seconds cpu_seconds" from the script.
    let get = |k: &str| {
        text.lines().find_map(|l| {
            let v: Vec<f64> = l.strip_prefix(k)?.split_whitespace().filter_map(|x| x.parse().ok()).collect();
            (v.len() == 2).then(|| (v[0], v[1]))
        })
    };
    for (k, (wall, cpu)) in [("inference_640", infer_s), ("train_b2_128", small_s), ("train_b8_320", step_s)]
    {
        if let Some((tw, tc)) = get(k) {
            let cpu_ratio = cpu.map_or("-".into(), |c| format!("{:.2}", c / tc));
            println!("torch      {k:<30} wall {tw:>8.3} s  cpu {tc:.3} s   burn / torch: wall {:.2}, cpu {cpu_ratio}", wall / tw);
        }
    }
    Ok(())
}
