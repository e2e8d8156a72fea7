//! Decoder stage: the paper's U-Net, its training data and the measurement model.
//!
//! * [`scenes`]: seeded procedural HDR scenes (textured surfaces, emitters, filaments,
//!   specular highlights, windows) for fine-tuning and tests without a data set.

pub mod scenes;
