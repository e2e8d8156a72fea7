//! The image decoder of the paper: its U-Net (`unet`), the weights format (`weights`),
//! the measurement model used to train it (`measurement`), reconstruction of captures
//! ([`reconstruct`]), fine-tuning for one fabricated part's PSF (`finetune`) and seeded
//! procedural HDR scenes to train on without a data set (`scenes`). Its sweeps are in
//! [`crate::sweep`], its charts in [`crate::charts`].
//!
//! Images here are `(H, W, 3)` `f32` arrays (row-major, channels last, as the paper's NHWC);
//! the network runs on NCHW burn tensors on the CPU (burn's Flex backend) or, with the `gpu`
//! feature, on any vendor's GPU through wgpu, or with the `cuda` feature on an NVIDIA GPU
//! ([`select_device`]).

pub(crate) mod dataset;
pub(crate) mod finetune;
pub(crate) mod measurement;
pub(crate) mod reconstruct;
pub(crate) mod runtime;
pub(crate) mod scenes;
pub(crate) mod unet;
pub(crate) mod weights;

pub use dataset::{
    is_validation, read_dir, training_and_validation, HdrFolder, HdrImage, HdrScenes, HOLDOUT_EVERY,
    MIN_PANORAMA_WIDTH, WHITE_BALANCE,
};
pub use finetune::{
    gamma_loss, procedural_scenes, run_job, simulate_captures, Adam, FinetuneConfig, FinetuneJob,
    FinetuneOutcome, HistoryEntry, SceneGenerator, StepStats, Trainer, BATCH, BITS, BLEND, CHANNEL_CLIPPING,
    CHECKPOINT_EVERY, CROP, DECODER, GRAD_CLIP, HALO, NEGATIVE_PENALTY, READ_NOISE, SHOT_NOISE, STEPS,
    VALIDATION,
};
pub use measurement::{Halo, Measurement, MeasurementModel};
pub use reconstruct::{
    infer_tiled, read_capture, reconstruct, reconstruct_file, Negatives, ReconstructOptions,
    ReconstructOutcome, ReconstructStats, BORDER,
};
pub use runtime::{default_init, device, from_tensor, infer, select_device, to_tensor, SelectedDevice};
pub use scenes::{procedural_scene, GeneratedScenes, SceneSource};
pub use unet::{tensor_values, UNet};
pub use weights::{
    decode_safetensors, decoder_bytes, decoder_sha256, encode_safetensors, tensor_specs, DecoderWeights,
    NamedTensor,
};
