//! `doefab calibrate-psf`: the measured PSF from a pinhole bracket (merge, then
//! `crate::calibration::psf_extract`), written with the merged radiance.

use std::path::PathBuf;

use crate::calibration::psf_extract::{self, PsfCalibration, PsfOptions};
use crate::error::Result;
use crate::pipeline::merge::{merge_bracket, BracketOptions, ResponseModel};

/// The bracket, the extraction's options and the output folder.
#[derive(Debug, Clone)]
pub struct CalibrateOptions {
    /// The pinhole bracket, merged as linear captures.
    pub bracket: BracketOptions,
    /// Crop, centring and pitches of the extraction.
    pub psf: PsfOptions,
    /// Output folder: psf.exr, psf.npy, psf_log.png, merged.exr, psf.json.
    pub output: PathBuf,
}

/// Merges the bracket (linear response), extracts the PSF and writes the calibration; the
/// report carries the warnings. Progress as in [`merge_bracket`].
pub fn calibrate_psf(
    opts: &CalibrateOptions,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<PsfCalibration> {
    let merged = merge_bracket(&opts.bracket, ResponseModel::Linear, progress)?.merged;
    let (psf, mut report) = psf_extract::calibrate_psf(&merged, &opts.psf)?;
    psf_extract::write_calibration(&psf, &merged, &mut report, &opts.output)?;
    Ok(report)
}
