//! Fine-tuning the decoder for one fixed PSF, as the paper refines its pretrained network for
//! the measured PSF of the fabricated DOE (Metzler et al. 2020, Sec. 5).
//!
//! Each step draws `batch` scenes of `crop + PSF margins` from a [`SceneSource`], flips each at
//! random (left-right, up-down), simulates its capture with [`simulate::measure`] and takes one
//! Adam step on the paper's gamma-corrected L2 loss over the batch:
//!
//! `L = sqrt(mean((sqrt(max(y_hat, 0) + 1/255) - sqrt(x + 1/255))^2))`.
//!
//! Adam as TensorFlow implements it (Kingma & Ba 2015, Sec. 2, with the bias corrections folded
//! into the step size): `m <- b1 m + (1 - b1) g`, `v <- b2 v + (1 - b2) g^2`,
//! `p <- p - lr sqrt(1 - b2^t) / (1 - b1^t) m / (sqrt(v) + eps)`; lr 1e-4, betas 0.9 / 0.999,
//! eps 1e-8. BatchNorm statistics stay frozen (see [`crate::decoder::unet`]).
//!
//! Every `checkpoint_every` steps the network is evaluated on a fixed validation set (simulated
//! once from its own seed); its PSNR in the loss's sqrt domain, `-20 log10 L` (peak = the
//! clipping level), is logged. A non-finite training loss, or a validation loss above
//! `divergence` times the best one so far, stops the run with an error before anything is
//! written, so the checkpoint on disk is the last good one. Otherwise the checkpoint (decoder
//! tensors, Adam moments, step, generator state, history) is written atomically; resuming from
//! it replays the same batches, so N steps equal N/2 steps plus N/2 resumed, bit for bit.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use burn::tensor::{Tensor, TensorData};
use ndarray::{s, Array3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::decoder::simulate::{measure, Convolver, Measurement, MeasurementModel};
use crate::decoder::unet::{is_trainable, tensor_values, UNet};
use crate::decoder::weights::{encode_safetensors, read_safetensors, DecoderWeights, NamedTensor};
use crate::decoder::{to_tensor, weights};
use crate::error::{Error, Result};
use crate::io::atomic::write_bytes;
use crate::optics::psf::{Channel, Psf};
use crate::rng::Lcg;

/// Where training scenes come from: linear HDR `(rows, cols, 3)` arrays, drawn with `rng`.
pub trait SceneSource: Sync {
    /// A short description for the decoder's metadata.
    fn describe(&self) -> String;
    /// One scene of exactly `rows x cols`.
    fn scene(&self, rng: &mut Lcg, rows: usize, cols: usize) -> Result<Array3<f32>>;
}

/// HDR images held in memory (a folder of EXR / Radiance .hdr files, or arrays made by a
/// program); scenes are random crops of a random image.
pub struct ImageSet {
    name: String,
    images: Vec<(String, Array3<f32>)>,
}

impl ImageSet {
    /// Named `(H, W, 3)` linear images; each must be finite and non-negative.
    pub fn new(name: &str, images: Vec<(String, Array3<f32>)>) -> Result<ImageSet> {
        if images.is_empty() {
            return Err(Error::Data(format!("{name}: no training images")));
        }
        for (n, img) in &images {
            if img.dim().2 != 3 {
                return Err(Error::Data(format!("{n}: has {} channels, training needs RGB", img.dim().2)));
            }
            if let Some(v) = img.iter().find(|v| !v.is_finite() || **v < 0.0) {
                return Err(Error::Data(format!("{n}: holds {v}; HDR radiance must be finite and >= 0")));
            }
        }
        Ok(ImageSet { name: name.into(), images })
    }

    /// Every `.exr` and `.hdr` file of `dir` (sorted by name), read as linear RGB.
    pub fn load(dir: &Path) -> Result<ImageSet> {
        let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "exr" | "hdr"))
            })
            .collect();
        paths.sort();
        let mut images = Vec::with_capacity(paths.len());
        for p in paths {
            let img = image::open(&p)
                .map_err(|e| Error::format(&p, format!("cannot read as an HDR image: {e}")))?;
            let rgb = img.to_rgb32f();
            let (w, h) = (rgb.width() as usize, rgb.height() as usize);
            let arr = Array3::from_shape_vec((h, w, 3), rgb.into_raw()).expect("RGB buffer");
            images.push((p.display().to_string(), arr));
        }
        if images.is_empty() {
            return Err(Error::format(dir, "holds no .exr or .hdr images"));
        }
        ImageSet::new(&dir.display().to_string(), images)
    }
}

impl SceneSource for ImageSet {
    fn describe(&self) -> String {
        format!("{} ({} HDR images)", self.name, self.images.len())
    }

    fn scene(&self, rng: &mut Lcg, rows: usize, cols: usize) -> Result<Array3<f32>> {
        let k = ((rng.uniform() * self.images.len() as f64) as usize).min(self.images.len() - 1);
        let (name, img) = &self.images[k];
        let (h, w, _) = img.dim();
        if h < rows || w < cols {
            return Err(Error::Data(format!(
                "{name}: is {h} x {w}, smaller than a training crop plus the PSF margins ({rows} x {cols})"
            )));
        }
        let r = ((rng.uniform() * (h - rows + 1) as f64) as usize).min(h - rows);
        let c = ((rng.uniform() * (w - cols + 1) as f64) as usize).min(w - cols);
        Ok(img.slice(s![r..r + rows, c..c + cols, ..]).to_owned())
    }
}

/// Scenes from a generator `f(seed, rows, cols)` (such as a procedural scene generator), each
/// with a seed drawn from the run's generator.
pub struct GeneratedScenes<F> {
    pub name: &'static str,
    pub generate: F,
}

impl<F> SceneSource for GeneratedScenes<F>
where
    F: Fn(u64, usize, usize) -> Array3<f32> + Sync,
{
    fn describe(&self) -> String {
        self.name.to_string()
    }

    fn scene(&self, rng: &mut Lcg, rows: usize, cols: usize) -> Result<Array3<f32>> {
        let seed = (rng.uniform() * (1u64 << 53) as f64) as u64;
        let scene = (self.generate)(seed, rows, cols);
        if let Some(v) = scene.iter().find(|v| !v.is_finite() || **v < 0.0) {
            return Err(Error::Data(format!("{} (seed {seed}) made the value {v}", self.name)));
        }
        Ok(scene)
    }
}

/// Reads a PSF for training: NumPy `.npz` (array `key`, or its only array) or `.npy`, of shape
/// `(H, W)`, `(H, W, C)` or `(H, W, 1, C)` (the paper's layout), at pixel `pitch` (metres).
pub fn read_psf(path: &Path, key: Option<&str>, pitch: f64) -> Result<Psf> {
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    match ext.as_str() {
        "npz" => Psf::read_npz(path, key, pitch, None),
        "npy" => {
            let (h, a) = crate::io::npy::read_npy_nd(path)?;
            let (rows, cols, nc) = match h.shape[..] {
                [r, c] => (r, c, 1),
                [r, c, k] | [r, c, 1, k] => (r, c, k),
                _ => return Err(Error::format(path, format!("shape {:?} is not a PSF", h.shape))),
            };
            let a =
                a.into_shape_with_order((rows, cols, nc)).map_err(|e| Error::format(path, e.to_string()))?;
            let channels = (0..nc)
                .map(|c| {
                    Ok(Channel {
                        name: if nc == 3 { ["R", "G", "B"][c].into() } else { format!("C{c}") },
                        wavelength: None,
                        grid: crate::grid::Grid::new(
                            a.slice(s![.., .., c]).to_owned(),
                            [pitch, pitch],
                            crate::grid::Unit::Dimensionless,
                        )?,
                        captured: None,
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            Psf::new(channels, "file").map_err(|e| Error::format(path, e.to_string()))
        }
        _ => Err(Error::format(path, "a PSF for fine-tuning must be .npz or .npy (H, W, 1, 3)")),
    }
}

/// Fine-tuning settings (defaults: the paper's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinetuneConfig {
    /// Total steps of the run (a resumed run continues to this count).
    pub steps: usize,
    pub batch: usize,
    /// Crop side, pixels (a multiple of 16).
    pub crop: usize,
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub epsilon: f64,
    /// Validate and checkpoint every this many steps (and at the end).
    pub checkpoint_every: usize,
    /// Size of the fixed validation set.
    pub validation: usize,
    pub seed: u64,
    /// Stop when the validation loss exceeds this factor times the best so far.
    pub divergence: f64,
    pub noise_sigma: f64,
}

impl Default for FinetuneConfig {
    fn default() -> Self {
        FinetuneConfig {
            steps: 1000,
            batch: 8,
            crop: 320,
            lr: 1e-4,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            checkpoint_every: 100,
            validation: 8,
            seed: 1,
            divergence: 10.0,
            noise_sigma: 0.02,
        }
    }
}

impl FinetuneConfig {
    fn check(&self) -> Result<()> {
        let bad = |n: &str, r: String| Err(Error::param(n, r));
        if self.crop == 0 || !self.crop.is_multiple_of(16) {
            return bad("crop", format!("{} is not a positive multiple of 16", self.crop));
        }
        if self.batch == 0 || self.checkpoint_every == 0 || self.validation == 0 {
            return bad("batch", "batch, checkpoint interval and validation size must be at least 1".into());
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            return bad("lr", format!("{} is not a positive step size", self.lr));
        }
        if !(0.0..1.0).contains(&self.beta1) || !(0.0..1.0).contains(&self.beta2) {
            return bad("betas", format!("{} / {} must lie in [0, 1)", self.beta1, self.beta2));
        }
        if self.divergence <= 1.0 {
            return bad("divergence", format!("{} must exceed 1", self.divergence));
        }
        Ok(())
    }

    fn model(&self) -> MeasurementModel {
        MeasurementModel { noise_sigma: self.noise_sigma, ..MeasurementModel::default() }
    }
}

/// One logged point of the training curve.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HistoryEntry {
    pub step: usize,
    /// Training loss of this step's batch (before its update); none at step 0.
    pub loss: Option<f64>,
    /// Validation loss and PSNR (sqrt domain, dB) after this step, at evaluations.
    pub val_loss: Option<f64>,
    pub val_psnr: Option<f64>,
}

/// The paper's loss on NCHW tensors: `sqrt(mean((sqrt(max(y,0) + 1/255) - sqrt(x + 1/255))^2))`.
pub fn gamma_loss(y_hat: Tensor<4>, x: Tensor<4>) -> Tensor<1> {
    let e = 1.0 / 255.0;
    let d = (y_hat.clamp_min(0.0) + e).sqrt() - (x + e).sqrt();
    (d.clone() * d).mean().sqrt()
}

/// PSNR of a loss value in the sqrt domain, peak 1: `-20 log10 L`.
pub fn psnr_of_loss(loss: f64) -> f64 {
    -20.0 * loss.log10()
}

/// Adam (TensorFlow's form, see the module docs) over a [`UNet`]'s trainable tensors.
pub struct Adam {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub epsilon: f64,
    /// Steps taken (`t` of the bias corrections).
    pub t: usize,
    /// First and second moments per checkpoint entry (`None` for frozen or not yet updated).
    m: Vec<Option<Tensor<1>>>,
    v: Vec<Option<Tensor<1>>>,
}

impl Adam {
    /// Fresh moments for `net`, hyper-parameters from `cfg`.
    pub fn new(net: &UNet, cfg: &FinetuneConfig) -> Adam {
        let n = net.params().len();
        Adam {
            lr: cfg.lr,
            beta1: cfg.beta1,
            beta2: cfg.beta2,
            epsilon: cfg.epsilon,
            t: 0,
            m: vec![None; n],
            v: vec![None; n],
        }
    }

    /// Forward, the paper's loss, backward and one update of `net` for the NCHW batch `x`
    /// with targets `target` (on the network's device). Returns the loss before the update;
    /// a non-finite loss is an error and leaves `net` and the moments unchanged.
    pub fn step(&mut self, net: &mut UNet, x: Tensor<4>, target: Tensor<4>) -> Result<f64> {
        let leaves: Vec<Tensor<1>> = net
            .names()
            .iter()
            .zip(net.params())
            .map(|(n, p)| {
                let t = p.clone().autodiff();
                if is_trainable(n) {
                    t.require_grad()
                } else {
                    t
                }
            })
            .collect();
        let mut tracked = net.clone();
        tracked.set_params(leaves.clone());
        let loss = gamma_loss(tracked.forward(x.autodiff())?, target.autodiff());
        let value = tensor_values(loss.clone().inner())?[0] as f64;
        if !value.is_finite() {
            return Err(Error::Data(format!("training loss is {value}")));
        }
        let grads = loss.backward();
        let t = (self.t + 1) as i32;
        let (b1, b2) = (self.beta1, self.beta2);
        let lr_t = (self.lr * (1.0 - b2.powi(t)).sqrt() / (1.0 - b1.powi(t))) as f32;
        let mut params = Vec::with_capacity(leaves.len());
        for (i, (leaf, p)) in leaves.iter().zip(net.params()).enumerate() {
            let Some(g) = leaf.grad(&grads) else {
                params.push(p.clone());
                continue;
            };
            let m = match self.m[i].take() {
                Some(m) => m * b1 as f32 + g.clone() * (1.0 - b1) as f32,
                None => g.clone() * (1.0 - b1) as f32,
            };
            let v = match self.v[i].take() {
                Some(v) => v * b2 as f32 + g.clone() * g * (1.0 - b2) as f32,
                None => g.clone() * g * (1.0 - b2) as f32,
            };
            params.push(p.clone() - m.clone() * lr_t / (v.clone().sqrt() + self.epsilon as f32));
            self.m[i] = Some(m);
            self.v[i] = Some(v);
        }
        net.set_params(params);
        self.t += 1;
        Ok(value)
    }
}

/// A fine-tuning run in memory.
pub struct Trainer<'a> {
    cfg: FinetuneConfig,
    net: UNet,
    adam: Adam,
    step: usize,
    rng: Lcg,
    history: Vec<HistoryEntry>,
    best_val: f64,
    conv: Convolver,
    source: &'a dyn SceneSource,
    validation: Vec<Measurement>,
    psf_sha256: String,
    init: String,
}

/// What one step reports to the caller (for a progress bar).
#[derive(Debug, Clone, PartialEq)]
pub struct StepReport {
    pub step: usize,
    pub steps: usize,
    pub loss: f64,
    pub val_psnr: Option<f64>,
}

impl<'a> Trainer<'a> {
    /// Starts a run from `net`. `psf_sha256` and `init` (the initial decoder's description)
    /// are recorded in the outputs.
    pub fn new(
        net: UNet,
        psf: &Psf,
        psf_sha256: &str,
        source: &'a dyn SceneSource,
        cfg: FinetuneConfig,
        init: &str,
    ) -> Result<Trainer<'a>> {
        cfg.check()?;
        if psf.channels.len() != 3 {
            return Err(Error::param(
                "psf",
                format!("has {} channels; the decoder needs RGB", psf.channels.len()),
            ));
        }
        let (kh, kw) = psf.dim();
        let conv = Convolver::new(psf, (cfg.crop + kh - 1, cfg.crop + kw - 1))?;
        let mut t = Trainer {
            rng: Lcg(cfg.seed),
            adam: Adam::new(&net, &cfg),
            cfg,
            net,
            step: 0,
            history: Vec::new(),
            best_val: f64::INFINITY,
            conv,
            source,
            validation: Vec::new(),
            psf_sha256: psf_sha256.into(),
            init: init.into(),
        };
        t.validation = t.simulate_batch(&mut Lcg(t.cfg.seed ^ 0x5eed_0000_7a11_da7e), t.cfg.validation)?;
        let v0 = t.validation_loss()?;
        t.check_validation(v0)?;
        t.history.push(HistoryEntry {
            step: 0,
            loss: None,
            val_loss: Some(v0),
            val_psnr: Some(psnr_of_loss(v0)),
        });
        Ok(t)
    }

    /// Continues the run saved in `checkpoint`, to `steps` total steps, with step size `lr`
    /// (`None`: the saved one). The PSF must be the one the run started with.
    pub fn resume(
        checkpoint: &Path,
        psf: &Psf,
        psf_sha256: &str,
        source: &'a dyn SceneSource,
        steps: usize,
        lr: Option<f64>,
        device: &burn::tensor::Device,
    ) -> Result<Trainer<'a>> {
        let (mut tensors, meta) = read_safetensors(checkpoint)?;
        let field = |k: &str| {
            meta.get(k)
                .ok_or_else(|| Error::format(checkpoint, format!("not a checkpoint: no '{k}' metadata")))
        };
        let parse_err = |k: &str, e: String| Error::format(checkpoint, format!("metadata '{k}': {e}"));
        if field("psf_sha256")? != psf_sha256 {
            return Err(Error::param(
                "psf",
                format!(
                    "its SHA-256 {psf_sha256} differs from the one the checkpoint was trained with ({})",
                    field("psf_sha256")?
                ),
            ));
        }
        let mut cfg: FinetuneConfig =
            serde_json::from_str(field("config")?).map_err(|e| parse_err("config", e.to_string()))?;
        let step: usize = field("checkpoint_step")?
            .parse()
            .map_err(|e: std::num::ParseIntError| parse_err("checkpoint_step", e.to_string()))?;
        let rng: u64 = field("rng_state")?
            .parse()
            .map_err(|e: std::num::ParseIntError| parse_err("rng_state", e.to_string()))?;
        let history: Vec<HistoryEntry> =
            serde_json::from_str(field("history")?).map_err(|e| parse_err("history", e.to_string()))?;
        let best_val: f64 = field("best_val_loss")?
            .parse()
            .map_err(|e: std::num::ParseFloatError| parse_err("best_val_loss", e.to_string()))?;
        let init = field("init")?.clone();
        let mut moments = BTreeMap::new();
        tensors.retain(|name, t| {
            if name.starts_with("adam.") {
                moments.insert(name.clone(), t.clone());
                false
            } else {
                true
            }
        });
        let weights = DecoderWeights::from_map(checkpoint, tensors, BTreeMap::new())?;
        let net = UNet::from_weights(&weights, device);
        cfg.steps = steps;
        if let Some(lr) = lr {
            cfg.lr = lr;
        }
        let mut t = Trainer::new(net, psf, psf_sha256, source, cfg, &init)?;
        for (i, name) in weights::tensor_specs().iter().map(|(n, _)| n).enumerate() {
            if !is_trainable(name) {
                continue;
            }
            for (which, slot) in [("m", &mut t.adam.m[i]), ("v", &mut t.adam.v[i])] {
                let key = format!("adam.{which}.{name}");
                let mt = moments
                    .remove(&key)
                    .ok_or_else(|| Error::format(checkpoint, format!("checkpoint lacks tensor '{key}'")))?;
                let n = mt.values.len();
                *slot = Some(Tensor::from_data(TensorData::new(mt.values, [n]), device));
            }
        }
        t.step = step;
        t.adam.t = step;
        t.rng = Lcg(rng);
        t.history = history;
        t.best_val = best_val;
        Ok(t)
    }

    pub fn step(&self) -> usize {
        self.step
    }

    pub fn history(&self) -> &[HistoryEntry] {
        &self.history
    }

    pub fn config(&self) -> &FinetuneConfig {
        &self.cfg
    }

    /// `count` simulated captures, their scenes drawn from `rng` (seeds drawn in order, the
    /// simulations run in parallel, so the result does not depend on the thread count).
    fn simulate_batch(&self, rng: &mut Lcg, count: usize) -> Result<Vec<Measurement>> {
        let (t, l, b, r) = self.conv.margins();
        let (rows, cols) = (self.cfg.crop + t + b, self.cfg.crop + l + r);
        let seeds: Vec<u64> = (0..count).map(|_| (rng.uniform() * (1u64 << 53) as f64) as u64).collect();
        let model = self.cfg.model();
        seeds
            .par_iter()
            .map(|&seed| {
                let mut g = Lcg(seed);
                let mut scene = self.source.scene(&mut g, rows, cols)?;
                if scene.dim() != (rows, cols, 3) {
                    return Err(Error::Data(format!(
                        "the scene source gave {:?}, not {rows} x {cols} x 3",
                        scene.dim()
                    )));
                }
                if g.uniform() < 0.5 {
                    scene.invert_axis(ndarray::Axis(1));
                }
                if g.uniform() < 0.5 {
                    scene.invert_axis(ndarray::Axis(0));
                }
                measure(&scene.as_standard_layout().to_owned(), &self.conv, &model, &mut g)
            })
            .collect()
    }

    fn tensors(&self, batch: &[Measurement], device: &burn::tensor::Device) -> (Tensor<4>, Tensor<4>) {
        let caps: Vec<&Array3<f32>> = batch.iter().map(|m| &m.capture).collect();
        let tgts: Vec<&Array3<f32>> = batch.iter().map(|m| &m.target).collect();
        (to_tensor(&caps, device), to_tensor(&tgts, device))
    }

    /// The loss over the validation set (evaluated in chunks of the batch size).
    pub fn validation_loss(&self) -> Result<f64> {
        let mut sum_sq = 0.0;
        let mut count = 0usize;
        for chunk in self.validation.chunks(self.cfg.batch) {
            let (x, t) = self.tensors(chunk, self.net.device());
            let l = tensor_values(gamma_loss(self.net.forward(x)?, t))?[0] as f64;
            let n = chunk.len();
            sum_sq += l * l * n as f64;
            count += n;
        }
        Ok((sum_sq / count as f64).sqrt())
    }

    fn check_validation(&mut self, val: f64) -> Result<()> {
        if !val.is_finite() {
            return Err(Error::Data(format!("validation loss is {val} after step {}; stopped", self.step)));
        }
        if val > self.cfg.divergence * self.best_val {
            return Err(Error::Data(format!(
                "training diverged: validation loss {val:.4} after step {} exceeds {} x the best {:.4}; stopped",
                self.step, self.cfg.divergence, self.best_val
            )));
        }
        self.best_val = self.best_val.min(val);
        Ok(())
    }

    /// One Adam step on a fresh batch; returns the batch's loss (before the update).
    pub fn train_step(&mut self) -> Result<f64> {
        let mut rng = self.rng.clone();
        let batch = self.simulate_batch(&mut rng, self.cfg.batch)?;
        let (x, target) = self.tensors(&batch, &self.net.device().clone());
        let value = self.adam.step(&mut self.net, x, target).map_err(|e| match e {
            Error::Data(m) => Error::Data(format!("{m} at step {}; stopped", self.step + 1)),
            other => other,
        })?;
        self.step += 1;
        self.rng = rng;
        self.history.push(HistoryEntry {
            step: self.step,
            loss: Some(value),
            val_loss: None,
            val_psnr: None,
        });
        Ok(value)
    }

    /// Evaluates on the validation set, logs it and checks for divergence.
    pub fn evaluate(&mut self) -> Result<f64> {
        let val = self.validation_loss()?;
        self.check_validation(val)?;
        if let Some(last) = self.history.last_mut().filter(|h| h.step == self.step) {
            last.val_loss = Some(val);
            last.val_psnr = Some(psnr_of_loss(val));
        }
        Ok(psnr_of_loss(val))
    }

    /// The current decoder with its training record in the metadata.
    pub fn decoder(&self) -> Result<DecoderWeights> {
        let mut w = self.net.to_weights()?;
        let last_loss = self.history.iter().rev().find_map(|h| h.loss);
        let last_val = self.history.iter().rev().find_map(|h| h.val_loss);
        w.metadata = BTreeMap::from([
            ("model".into(), "DeepOpticsHDR my_medium_model (is_training=False, log_domain=False)".into()),
            ("psf_sha256".into(), self.psf_sha256.clone()),
            ("init".into(), self.init.clone()),
            ("training_steps".into(), self.step.to_string()),
            ("training_data".into(), self.source.describe()),
            ("final_loss".into(), last_loss.map_or("none".into(), |l| format!("{l:.6e}"))),
            ("final_validation_loss".into(), last_val.map_or("none".into(), |l| format!("{l:.6e}"))),
            (
                "loss".into(),
                "sqrt(mean((sqrt(max(y_hat,0)+1/255) - sqrt(x+1/255))^2)) per batch; values relative to the sensor \
                 clipping level"
                    .into(),
            ),
            ("config".into(), serde_json::to_string(&self.cfg).map_err(|e| Error::Data(e.to_string()))?),
        ]);
        Ok(w)
    }

    /// Writes the checkpoint (decoder, Adam moments, step, generator state, history) atomically.
    pub fn write_checkpoint(&self, path: &Path) -> Result<()> {
        let w = self.decoder()?;
        let mut meta = w.metadata.clone();
        meta.insert("checkpoint_step".into(), self.step.to_string());
        meta.insert("rng_state".into(), self.rng.0.to_string());
        meta.insert("best_val_loss".into(), format!("{:e}", self.best_val));
        meta.insert(
            "history".into(),
            serde_json::to_string(&self.history).map_err(|e| Error::Data(e.to_string()))?,
        );
        let mut owned: Vec<(String, NamedTensor)> = w.tensors.clone();
        for (i, name) in self.net.names().iter().enumerate() {
            for (which, slot) in [("m", &self.adam.m[i]), ("v", &self.adam.v[i])] {
                if let Some(t) = slot {
                    let values = tensor_values(t.clone())?;
                    owned.push((
                        format!("adam.{which}.{name}"),
                        NamedTensor { shape: vec![values.len()], values },
                    ));
                } else if is_trainable(name) {
                    let n = self.net.params()[i].dims()[0];
                    owned.push((
                        format!("adam.{which}.{name}"),
                        NamedTensor { shape: vec![n], values: vec![0.0; n] },
                    ));
                }
            }
        }
        let refs: Vec<(&str, &NamedTensor)> = owned.iter().map(|(n, t)| (n.as_str(), t)).collect();
        write_bytes(path, &encode_safetensors(&refs, &meta))
    }

    /// Runs to the configured step count, validating and checkpointing into `out` every
    /// `checkpoint_every` steps and at the end; `on_step` sees every step.
    pub fn run(&mut self, out: &Path, on_step: &mut dyn FnMut(&StepReport)) -> Result<()> {
        std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
        while self.step < self.cfg.steps {
            let loss = self.train_step()?;
            let mut val_psnr = None;
            if self.step.is_multiple_of(self.cfg.checkpoint_every) || self.step == self.cfg.steps {
                val_psnr = Some(self.evaluate()?);
                self.write_checkpoint(&out.join(CHECKPOINT))?;
            }
            on_step(&StepReport { step: self.step, steps: self.cfg.steps, loss, val_psnr });
        }
        Ok(())
    }

    /// Writes the final outputs into `out`: [`DECODER`] (the fine-tuned decoder with its
    /// training record), `training.json` (configuration and curve) and `training_curve.png`.
    pub fn write_outputs(&self, out: &Path) -> Result<()> {
        self.decoder()?.write(&out.join(DECODER))?;
        let record = serde_json::json!({
            "config": self.cfg,
            "steps": self.step,
            "psf_sha256": self.psf_sha256,
            "init": self.init,
            "data": self.source.describe(),
            "loss_units": "sqrt domain, relative to the sensor clipping level; PSNR in dB with peak 1",
            "history": self.history,
        });
        crate::io::atomic::write_json(&out.join("training.json"), &record)?;
        crate::report::training_chart::write_training_chart(&out.join("training_curve.png"), &self.history)
    }
}

/// File name of the fine-tuned decoder inside the output folder.
pub const DECODER: &str = "decoder.safetensors";

/// File name of the checkpoint inside the output folder.
pub const CHECKPOINT: &str = "checkpoint.safetensors";
