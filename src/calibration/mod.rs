//! Calibration stage: from exposure brackets of real captures to HDR images and the measured
//! PSF of a fabricated part, and the comparison of reconstructions with their references.
//!
//! The paper (Metzler et al. 2020, Sec. 5): "To calibrate our camera system, we capture several
//! different exposures of a white light source behind a 75 um pinhole. These photographs are
//! merged into a single HDR image [Debevec and Malik 1997]."
//!
//! * `capture`: 8/16-bit PNG or TIFF captures (RGB or grayscale, linear) and the bracket's
//!   exposure list (`exposures.json` or times given by the caller).
//! * `clipping`: where each colour channel of a camera clips (the paper's green at 231 of
//!   255), from where its samples pile up.
//! * `hdr_merge`: the weighted merge of a bracket into radiance, with effective exposure
//!   times estimated from the pixels and per-frame agreement figures.
//! * `response`: Debevec-Malik recovery of a non-linear 8-bit camera response.
//! * `psf_extract`: `calibrate-psf`, the measured PSF from a merged pinhole bracket.
//! * [`evaluate`]: PSNR (linear and gamma) of a reconstruction against a reference, over all
//!   pixels and over those saturated in the capture.
//! * `capture_registration`: the affine map between two views of one scene (tile matching with outlier
//!   rejection, then least squares).

pub(crate) mod capture;
pub(crate) mod capture_registration;
pub(crate) mod clipping;
pub(crate) mod evaluate;
pub(crate) mod hdr_merge;
pub(crate) mod psf_extract;
pub(crate) mod response;

pub use capture::{
    read_capture, read_exposures, read_image, read_rgb_exr, write_capture, Capture, ExposureList,
};
pub use capture_registration::{
    luminance, register_affine, register_local, warp, Affine, LocalRegistration, Model, RegisterOptions,
    Registration,
};
pub use evaluate::{
    evaluate, evaluate_files, prepare, psnr, EvaluateFiles, Evaluation, Footing, Psnr, Score, Scoring,
    ScoringOptions,
};
pub use hdr_merge::{
    mean_dark, merge, write_tone_mapped, BlackLevel, FrameStats, MergeOptions, MergeStats, Merged, PixelSet,
    ToneMapStats,
};
pub use psf_extract::{
    calibrate_psf, simulate_pinhole_bracket, Centre, EncircledEnergy, PsfCalibration, PsfOptions,
};
pub use response::{recover_response, Response};
