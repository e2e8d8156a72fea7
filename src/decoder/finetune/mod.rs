//! Fine-tuning the decoder for one fixed PSF, as the paper refines its pretrained network for
//! the measured PSF of the fabricated DOE (Metzler et al. 2020, Sec. 5).
//!
//! Each step draws `batch` scenes of `crop + PSF margins` from a [`SceneSource`], flips each at
//! random (left-right, up-down), simulates its capture with [`measurement::measure`](super::measurement::measure) and takes one
//! Adam step on the paper's gamma-corrected L2 loss over the batch:
//!
//! `L = sqrt(mean((sqrt(max(y_hat, 0) + 1/255) - sqrt(x + 1/255))^2))`.
//!
//! Adam as TensorFlow implements it (Kingma & Ba 2015, Sec. 2, with the bias corrections folded
//! into the step size): `m <- b1 m + (1 - b1) g`, `v <- b2 v + (1 - b2) g^2`,
//! `p <- p - lr sqrt(1 - b2^t) / (1 - b1^t) m / (sqrt(v) + eps)`; lr 1e-4, betas 0.9 / 0.999,
//! eps 1e-8. BatchNorm statistics stay frozen (see [`crate::decoder::unet`]).
//!
//! With `grad_clip` `c > 0` a gradient whose global norm `|g| = sqrt(sum g^2)` exceeds `c` is
//! scaled to `c g / |g|` before Adam sees it (Pascanu et al. 2013, Sec. 3.2, Algorithm 2).
//!
//! Every `checkpoint_every` steps the network is evaluated on a fixed validation set (simulated
//! once from its own seed); its PSNR in the loss's sqrt domain, `-20 log10 L` (peak = the
//! clipping level), is logged. A non-finite training loss, or a validation loss above
//! `divergence` times the best one so far, stops the run with an error before anything is
//! written, so the checkpoint on disk is the last good one. Otherwise the checkpoint (decoder
//! tensors, Adam moments, step, generator state, history) is written atomically; resuming from
//! it replays the same batches, so N steps equal N/2 steps plus N/2 resumed, bit for bit.
//!
//! [`SceneSource`]: crate::decoder::scenes::SceneSource

mod config;
mod job;
mod optimiser;
mod outputs;
mod trainer;
mod training_scenes;

pub use config::{
    FinetuneConfig, BATCH, BITS, BLEND, CHANNEL_CLIPPING, CHECKPOINT_EVERY, CROP, GRAD_CLIP, HALO,
    NEGATIVE_PENALTY, READ_NOISE, SHOT_NOISE, STEPS, VALIDATION,
};
pub use job::{run_job, FinetuneJob, FinetuneOutcome};
pub use optimiser::{gamma_loss, psnr_of_loss, Adam};
pub use outputs::DECODER;
pub use trainer::{simulate_captures, HistoryEntry, StepStats, Trainer};
pub use training_scenes::{procedural_scenes, SceneGenerator, TrainingScenes};
