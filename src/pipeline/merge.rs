//! `doefab merge`: an exposure bracket and its dark frames, optionally the camera response
//! recovered from it (Debevec-Malik), merged into HDR radiance; written as OpenEXR, a
//! tone-mapped PNG and, where recovered, the response curve as CSV.

use std::path::PathBuf;

use serde::Serialize;

use crate::calibration::capture;
use crate::calibration::hdr_merge::{self, MergeStats, Merged, ToneMapStats};
use crate::calibration::response::{self, Response};
use crate::error::{Error, OptionsCause, Result};

/// An exposure bracket and how to merge it.
#[derive(Debug, Clone)]
pub struct BracketOptions {
    /// Capture files (8/16-bit PNG or TIFF) with `times`, or one exposure list (`.json`).
    pub files: Vec<PathBuf>,
    /// Exposure times of `files` ("1/60", "250ms").
    pub times: Vec<String>,
    /// Exposure list (JSON), instead of `files` with `times`.
    pub exposures: Option<PathBuf>,
    /// From the exposure list take the frames marked `"doe": true` (else those without).
    pub doe_frames: bool,
    /// Dark frames, averaged and subtracted from every frame.
    pub dark: Vec<PathBuf>,
    /// Noise floor above the dark level, fraction of full scale.
    pub noise_floor: f64,
    /// Saturation level, fraction of full scale.
    pub saturation: f64,
    /// Use the listed exposure times as they are instead of estimating them from the pixels.
    pub listed_times: bool,
    /// The exposure the radiance is expressed at ("1/60"); default: the list's, else 1 s.
    pub reference_exposure: Option<String>,
    /// Black level, fraction of full scale: one, or one per channel; empty: automatic.
    pub black_level: Vec<f64>,
}

/// The camera response assumed or recovered before merging.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResponseModel {
    /// Linear captures.
    Linear,
    /// Recovered from the bracket (Debevec-Malik), for non-linear 8-bit captures.
    Debevec,
}

/// A merged bracket and the warnings of the response recovery (the merge's own are in
/// `merged.stats.warnings`).
#[derive(Debug)]
pub struct MergedBracket {
    /// The radiance, its stats and the response used.
    pub merged: Merged,
    /// Warnings of the response recovery, empty for a linear merge.
    pub response_warnings: Vec<String>,
}

/// Reads a bracket (files with times, or an exposure list) and its dark frames, recovers the
/// response where asked, and merges. Progress: one step per frame read, the dark frames
/// together, then the recovery and the merge by message.
pub fn merge_bracket(
    b: &BracketOptions,
    response: ResponseModel,
    progress: &mut dyn FnMut(&str, u64, u64),
) -> Result<MergedBracket> {
    let list = capture::resolve_bracket(&capture::BracketSpec {
        files: b.files.clone(),
        times: b.times.clone(),
        exposures: b.exposures.clone(),
        doe_frames: b.doe_frames,
        reference_exposure: b.reference_exposure.clone(),
    })?;
    let total = list.frames.len() as u64 + b.dark.len() as u64 + 1;
    progress("reading the bracket", 0, total);
    let mut frames = Vec::new();
    for (path, _) in &list.frames {
        frames.push(capture::read_capture(path)?);
        progress("reading the bracket", frames.len() as u64, total);
    }
    let times: Vec<f64> = list.frames.iter().map(|f| f.1).collect();
    let darks = b.dark.iter().map(|p| capture::read_capture(p)).collect::<Result<Vec<_>>>()?;
    let read = list.frames.len() as u64 + b.dark.len() as u64;
    progress("reading the bracket", read, total);
    let dark = (!darks.is_empty()).then(|| hdr_merge::mean_dark(&darks)).transpose()?;
    let (curve, response_warnings) = match response {
        ResponseModel::Linear => (None, Vec::new()),
        ResponseModel::Debevec => {
            progress("recovering the response", read, total);
            let r = response::recover_response(&frames, &times, 0, 50.0)?;
            let w = r.warnings.clone();
            (Some(r), w)
        }
    };
    progress("merging", read, total);
    let opts = hdr_merge::MergeOptions {
        noise_floor: b.noise_floor,
        saturation: b.saturation,
        estimate_times: !b.listed_times,
        reference_exposure: list.reference_exposure,
        black_level: if b.black_level.is_empty() {
            hdr_merge::BlackLevel::Auto
        } else {
            hdr_merge::BlackLevel::Fixed(b.black_level.clone())
        },
    };
    let merged = hdr_merge::merge(&frames, &times, dark.as_ref(), curve.as_ref(), &opts)?;
    Ok(MergedBracket { merged, response_warnings })
}

/// What `doefab merge` writes and how.
#[derive(Debug, Clone)]
pub struct MergeOptions {
    /// The bracket and how to merge it.
    pub bracket: BracketOptions,
    /// Linear captures, or the response recovered from the bracket.
    pub response: ResponseModel,
    /// The OpenEXR radiance image (channels R, G, B).
    pub output: PathBuf,
    /// The tone-mapped PNG; `None`: `output` with the extension `.png`.
    pub png: Option<PathBuf>,
    /// Exposure of the tone-mapped PNG, stops.
    pub ev: f64,
    /// Where to save the recovered response curve (CSV); needs [`ResponseModel::Debevec`].
    pub response_out: Option<PathBuf>,
}

/// The merge's stats, the tone mapping's and the response curve's file.
#[derive(Debug, Serialize)]
pub struct MergeOutcome {
    /// The merge's stats (frames, exposures, warnings), flattened into the outcome.
    #[serde(flatten)]
    pub stats: MergeStats,
    /// The tone-mapped PNG's stats.
    pub tone_map: ToneMapStats,
    /// The response curve's CSV file, where one was asked for.
    pub response_csv: Option<String>,
    /// The tone-mapped PNG written.
    #[serde(skip)]
    pub png: PathBuf,
    /// The recovered response, with [`ResponseModel::Debevec`].
    #[serde(skip)]
    pub response: Option<Response>,
    /// Warnings of the response recovery (the merge's and the tone mapping's are in their
    /// stats).
    #[serde(skip)]
    pub response_warnings: Vec<String>,
}

/// Checks the options before any work, merges the bracket and writes the EXR, the
/// tone-mapped PNG and, where asked, the response CSV. Refused with [`Error::Options`]: a
/// response file without a recovered response, a non-finite `ev`, and outputs that name the
/// same file.
pub fn merge(opts: &MergeOptions, progress: &mut dyn FnMut(&str, u64, u64)) -> Result<MergeOutcome> {
    if opts.response_out.is_some() && opts.response != ResponseModel::Debevec {
        return Err(Error::options(
            &["response_out", "response"],
            OptionsCause::Requires,
            "`response_out` saves the curve that `response` debevec recovers; a linear merge \
             (the default `response` linear) has none",
        ));
    }
    if !opts.ev.is_finite() {
        let what = format!("`ev` must be a finite number of stops, got {}", opts.ev);
        return Err(Error::options(&["ev"], OptionsCause::Value, what));
    }
    let output = &opts.output;
    let png = opts.png.clone().unwrap_or_else(|| output.with_extension("png"));
    if png == *output || opts.response_out.as_ref().is_some_and(|r| r == output || *r == png) {
        return Err(Error::options(
            &["output", "png", "response_out"],
            OptionsCause::SameFile,
            format!(
                "the EXR ({}), the PNG ({}) and `response_out` must be different files",
                output.display(),
                png.display()
            ),
        ));
    }
    let MergedBracket { merged, response_warnings } = merge_bracket(&opts.bracket, opts.response, progress)?;
    hdr_merge::write_merged(output, &merged, None)?;
    let tone_map = hdr_merge::write_tone_mapped(&png, &merged, opts.ev, None)?;
    if let (Some(path), Some(curve)) = (&opts.response_out, &merged.response) {
        curve.write_csv(path)?;
    }
    Ok(MergeOutcome {
        stats: merged.stats,
        tone_map,
        response_csv: opts.response_out.as_ref().map(|p| p.display().to_string()),
        png,
        response: merged.response,
        response_warnings,
    })
}
