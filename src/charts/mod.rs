//! The charts: every chart the crate draws, one file per family, and their shared style
//! ([`style`]: fonts, log axes, legends, PNG and SVG writing, the error of a failed drawing).
//! `plotters` is named here and nowhere else.
//!
//! Charts sit above the stages and the sweeps: they draw the stages' results and the
//! sweeps' reports, and none of those draws or names a chart; the commands that write a
//! run's files ([`crate::pipeline`], [`crate::demo`]) call them.
//!
//! * [`fabrication`]: `bench fab`'s sweeps, the pre-compensation gain.
//! * [`metrology`]: false-colour height maps, profiles, height histograms, registration's
//!   speed against accuracy.
//! * [`failure_maps`]: where a method fails (`bench register`, `bench calibration`).
//! * [`optics`]: the PSF methods' speed against accuracy and sampling, the stability maps, the
//!   spectral sampling.
//! * [`tiling`]: the decoder's output against tile, overlap and precision.
//! * [`training`]: the fine-tuning curve, validation PSNR against training time.
//! * [`decoder`]: decoders on real captures, the fine-tuning against time there, the
//!   measurement model against the captures.

#[cfg(feature = "decoder")]
pub mod decoder;
pub mod fabrication;
pub mod failure_maps;
pub mod metrology;
pub mod optics;
pub mod style;
#[cfg(feature = "decoder")]
pub mod tiling;
#[cfg(feature = "decoder")]
pub mod training;
