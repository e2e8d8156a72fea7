//! Calibration stage: from exposure brackets of real captures to HDR images and the measured
//! PSF of a fabricated part, and the comparison of reconstructions with their references.
//!
//! The paper (Metzler et al. 2020, Sec. 5): "To calibrate our camera system, we capture several
//! different exposures of a white light source behind a 75 um pinhole. These photographs are
//! merged into a single HDR image [Debevec and Malik 1997]."
//!
//! * [`capture`]: 8/16-bit PNG or TIFF captures (RGB or grayscale, linear) and the bracket's
//!   exposure list (`exposures.json` or times given by the caller).
//! * [`clipping`]: where each colour channel of a camera clips (the paper's green at 231 of
//!   255), from where its samples pile up.
//! * [`hdr_merge`]: the weighted merge of a bracket into radiance, with effective exposure
//!   times estimated from the pixels and per-frame agreement figures.
//! * [`response`]: Debevec-Malik recovery of a non-linear 8-bit camera response.
//! * [`psf_extract`]: `calibrate-psf`, the measured PSF from a merged pinhole bracket.
//! * [`evaluate`]: PSNR (linear and gamma) of a reconstruction against a reference, over all
//!   pixels and over those saturated in the capture.
//! * [`capture_registration`]: the affine map between two views of one scene (tile matching with outlier
//!   rejection, then least squares).

pub mod capture;
pub mod capture_registration;
pub mod clipping;
pub mod evaluate;
pub mod hdr_merge;
pub mod psf_extract;
pub mod response;
