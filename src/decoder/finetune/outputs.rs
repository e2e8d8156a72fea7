//! What a fine-tuning run writes: the decoder (the best validated weights blended with the
//! start's, [`Written`]), the checkpoint a run resumes from, and the run to the last step with
//! its outputs.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;

use crate::decoder::unet::{is_trainable, tensor_values, UNet};
use crate::decoder::weights::{encode_safetensors, DecoderWeights, NamedTensor};
use crate::error::{Error, Result};
use crate::io::atomic::write_bytes;

use super::optimiser::psnr_of_loss;
use super::trainer::{StepStats, Trainer};

impl<'a> Trainer<'a> {
    /// The decoder `write_outputs` writes (see [`Trainer::decoder`]): the best validated
    /// weights blended with the start's by `blend` (see [`FinetuneConfig::blend`]), and its
    /// validation loss. Should the blend validate worse than the start (it lies between the
    /// start and the best, so it seldom can), the best validated weights are written instead,
    /// so the decoder written never validates below its start.
    ///
    /// [`FinetuneConfig::blend`]: super::FinetuneConfig::blend
    pub fn written_decoder(&self) -> Result<(DecoderWeights, Written)> {
        let mut net = self.net.clone();
        net.set_params(self.best.clone());
        let mut val = self.best_val;
        let mut blend = 1.0;
        if self.cfg.blend < 1.0 && self.best_step > 0 {
            let b = self.cfg.blend as f32;
            let mut blended = net.clone();
            blended.set_params(
                self.start
                    .iter()
                    .zip(&self.best)
                    .map(|(w0, w)| w0.clone() + (w.clone() - w0.clone()) * b)
                    .collect(),
            );
            let v = self.validation_loss_of(&blended)?;
            let start_val = self.history.iter().find(|h| h.step == 0).and_then(|h| h.val_loss);
            if start_val.is_none_or(|s| v <= s) {
                (net, val, blend) = (blended, v, self.cfg.blend);
            }
        }
        let mut w = self.decoder_of(&net)?;
        w.metadata.insert("best_step".into(), self.best_step.to_string());
        w.metadata.insert("best_validation_loss".into(), format!("{:e}", self.best_val));
        w.metadata.insert("blend".into(), blend.to_string());
        w.metadata.insert("validation_loss".into(), format!("{val:e}"));
        Ok((w, Written { blend, validation_loss: val }))
    }

    /// The current decoder with its training record in the metadata.
    pub fn decoder(&self) -> Result<DecoderWeights> {
        self.decoder_of(&self.net)
    }

    fn decoder_of(&self, net: &UNet) -> Result<DecoderWeights> {
        let mut w = net.to_weights()?;
        let last_loss = self.history.iter().rev().find_map(|h| h.loss);
        let last_val = self.history.iter().rev().find_map(|h| h.val_loss);
        w.metadata = BTreeMap::from([
            ("model".into(), "DeepOpticsHDR my_medium_model (is_training=False, log_domain=False)".into()),
            ("psf_sha256".into(), self.psf_sha256.clone()),
            ("init".into(), self.init.clone()),
            ("training_steps".into(), self.step.to_string()),
            ("training_data".into(), self.source.describe()),
            ("validation_data".into(), self.validation_data.clone()),
            ("final_loss".into(), last_loss.map_or("none".into(), |l| format!("{l:.6e}"))),
            ("final_validation_loss".into(), last_val.map_or("none".into(), |l| format!("{l:.6e}"))),
            (
                "loss".into(),
                "sqrt(mean((sqrt(max(y_hat,0)+1/255) - sqrt(x+1/255))^2)) per batch; values relative to the sensor \
                 clipping level"
                    .into(),
            ),
            ("config".into(), serde_json::to_string(&self.cfg).map_err(|e| Error::internal(e.to_string()))?),
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
        meta.insert("best_step".into(), self.best_step.to_string());
        meta.insert("stale".into(), self.stale.to_string());
        meta.insert(
            "history".into(),
            serde_json::to_string(&self.history).map_err(|e| Error::internal(e.to_string()))?,
        );
        let mut owned: Vec<(String, NamedTensor)> = w.tensors.clone();
        for (i, name) in self.net.names().iter().enumerate() {
            for (which, t) in [("best", &self.best[i]), ("start", &self.start[i])] {
                let values = tensor_values(t.clone())?;
                owned.push((format!("{which}.{name}"), NamedTensor { shape: vec![values.len()], values }));
            }
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
    /// `checkpoint_every` steps and at the end; `on_step` sees every step. With `patience`
    /// set, stops early after that many validations without a new best.
    pub fn run(&mut self, out: &Path, on_step: &mut dyn FnMut(&StepStats)) -> Result<()> {
        std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
        while self.step < self.cfg.steps {
            let loss = self.train_step()?;
            let mut val_psnr = None;
            if self.step.is_multiple_of(self.cfg.checkpoint_every) || self.step == self.cfg.steps {
                val_psnr = Some(self.evaluate()?);
                self.write_checkpoint(&out.join(CHECKPOINT))?;
            }
            on_step(&StepStats { step: self.step, steps: self.cfg.steps, loss, val_psnr });
            if self.stopped_early() {
                break;
            }
        }
        Ok(())
    }

    /// Whether `patience` validations have passed without a new best.
    pub fn stopped_early(&self) -> bool {
        self.cfg.patience > 0 && self.stale >= self.cfg.patience
    }

    /// Writes the final outputs into `out`: `DECODER` (the blended best validated decoder,
    /// see [`Trainer::written_decoder`]; the start decoder itself when no step validated
    /// better, with its training record) and `training.json` (configuration and curve); the
    /// curve's chart, `training_curve.png`, is drawn by the commands
    /// ([`crate::charts::training::write_training_chart`]).
    pub fn write_outputs(&self, out: &Path) -> Result<Written> {
        let (decoder, written) = self.written_decoder()?;
        decoder.write(&out.join(DECODER))?;
        let record = serde_json::json!({
            "config": self.cfg,
            "steps": self.step,
            "stopped_early": self.stopped_early(),
            "best_step": self.best_step,
            "best_validation_loss": self.best_val,
            "best_validation_psnr": psnr_of_loss(self.best_val),
            "blend": written.blend,
            "written_validation_psnr": psnr_of_loss(written.validation_loss),
            "psf_sha256": self.psf_sha256,
            "init": self.init,
            "data": self.source.describe(),
            "validation_data": self.validation_data,
            "loss_units": "sqrt domain, relative to the sensor clipping level; PSNR in dB with peak 1",
            "history": self.history,
        });
        crate::io::atomic::write_json(&out.join("training.json"), &record)?;
        Ok(written)
    }
}

/// The decoder a run wrote: its blend with the start (1 = the best validated weights) and its
/// validation loss.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Written {
    /// The blend written: [`FinetuneConfig::blend`](super::FinetuneConfig::blend), or 1 (the
    /// best validated weights) where no step validated better than the start or the blend
    /// would validate worse than it.
    pub blend: f64,
    /// Validation loss of the decoder written (the paper's loss, sqrt domain, relative to the
    /// clipping level).
    pub validation_loss: f64,
}

/// File name of the fine-tuned decoder inside the output folder.
pub const DECODER: &str = "decoder.safetensors";

/// File name of the checkpoint inside the output folder.
pub const CHECKPOINT: &str = "checkpoint.safetensors";
