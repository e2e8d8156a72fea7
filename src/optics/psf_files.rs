//! Writing a PSF: an OpenEXR file (one float32 channel per wavelength, metadata: pitch,
//! wavelengths, method, normalisation, warnings), a `.npy` in the paper's layout
//! `(H, W, 1, C)`, a log-scale PNG (the channels side by side, 5 decades below each channel's
//! peak) and a JSON summary (centroid, peak, encircled energy inside the Airy radius, captured
//! power, Strehl relative to a flat DOE). The folder appears all at once
//! ([`StagedDir`]); the same input writes the same bytes.

use std::path::Path;

use ndarray::Array2;
use serde::{Deserialize, Serialize};

use super::plan::{run_reporting, Plan};
use super::propagate::{simulate, Method, Options};
use super::psf::{ChannelSummary, Peak, Psf};
use super::spectrum::Band;
use super::system::{flat_doe, OpticalSystem};
use crate::error::Result;
use crate::grid::Grid;
use crate::io::atomic::{write_json, StagedDir};
use crate::io::exr::write_exr;
use crate::io::npy::write_npy_f32_4d;
use crate::io::png::write_png_u8;
use crate::io::raw_map::Metadata;

/// Peaks listed per channel in the summary (the paper's design: a central peak and six
/// copies).
pub const PEAKS: usize = 7;

/// Decades shown by the log-scale PNG.
pub const LOG_DECADES: f64 = 5.0;

/// What `doefab psf` prints and writes as `psf.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PsfOutcome {
    /// The propagation method that made the PSF (its name, e.g. "asm").
    pub method: String,
    /// How the channels are normalised: "each channel sums to 1 over the crop".
    pub normalisation: String,
    /// The optical system simulated (the plan's, when a plan ran).
    pub system: OpticalSystem,
    /// The automatic plan that chose the configuration, when one did.
    pub plan: Option<Plan>,
    /// Numbers of each channel, in the PSF's channel order.
    pub channels: Vec<ChannelStats>,
    /// Validity conditions a forced run violated.
    pub warnings: Vec<String>,
    /// The files written, relative to the output folder.
    pub files: Vec<String>,
}

/// Per-channel numbers of [`PsfOutcome`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChannelStats {
    /// Name, wavelength, centroid, peak and captured power (flattened into this object).
    #[serde(flatten)]
    pub summary: ChannelSummary,
    /// Fraction of the channel (0..1) inside `1.22 lambda F#` of its peak; `None` for a
    /// channel without a wavelength.
    pub encircled_energy_airy: Option<f64>,
    /// The central peak and its shifted copies: the brightest local maxima at least the Airy
    /// radius `1.22 lambda F#` (two pixels without a wavelength) apart, with the energy
    /// within that radius.
    pub peaks: Vec<Peak>,
    /// Whether the sensor sub-samples resolve the intensity (`pitch / subsample <= lambda F# / 2`,
    /// the intensity's Nyquist pitch). If not, pixel values are point samples rather than pixel
    /// integrals, and `captured` (a Riemann sum) can exceed 1. `None` for a channel without a
    /// wavelength.
    pub pixel_integration_resolved: Option<bool>,
    /// Peak pixel relative to a flat DOE's peak pixel in the same system and method, the flat
    /// one computed on an odd crop so that its peak pixel is centred on the axis.
    pub strehl: Option<f64>,
}

/// The system of the paper with the pupil sampled as the DOE (its pitch and extent).
pub fn system_for(doe: &Grid) -> OpticalSystem {
    let p = doe.pitch()[0].min(doe.pitch()[1]);
    let e = doe.extent();
    OpticalSystem { pupil_pitch: p, pupil_window: e[0].min(e[1]), ..OpticalSystem::default() }
}

/// Simulates the PSF of `doe` in `system` by `method`, with the flat-DOE reference for the
/// Strehl ratio, and writes the outputs into `out` (see the module docs); `notes` go first
/// among the warnings.
pub fn simulate_and_write(
    doe: &Grid,
    system: &OpticalSystem,
    method: Method,
    opts: &Options,
    notes: &[String],
    out: &Path,
) -> Result<PsfOutcome> {
    let (psf, mut report) = simulate_with_report(doe, system, method, opts, notes)?;
    write_psf(&psf, &mut report, out)?;
    Ok(report)
}

/// [`simulate_and_write`] in memory: the PSF and its summary (no files; `files` empty).
pub fn simulate_with_report(
    doe: &Grid,
    system: &OpticalSystem,
    method: Method,
    opts: &Options,
    notes: &[String],
) -> Result<(Psf, PsfOutcome)> {
    let mut psf = simulate(system, doe, method, opts)?;
    psf.warnings.splice(0..0, notes.iter().cloned());
    // The flat reference on an odd crop, so that its peak pixel sits on the axis.
    let odd = OpticalSystem { crop: system.crop | 1, ..system.clone() };
    let flat = simulate(&odd, &flat_doe(&odd)?, method, &Options { allow_invalid: true, ..opts.clone() })?;
    let report = report(&psf, &flat, system, None);
    Ok((psf, report))
}

/// Runs `plan` on `doe` (and on a flat DOE for the Strehl ratio, with the same plan on an odd
/// crop) and writes the outputs into `out`, the plan in the JSON summary. `progress` is told
/// what is being simulated ([`run_reporting`]).
pub fn plan_and_write(
    doe: &Grid,
    plan: &Plan,
    bands: &[Band],
    out: &Path,
    progress: &mut dyn FnMut(&str),
) -> Result<PsfOutcome> {
    let (psf, mut report) = plan_with_report(doe, plan, bands, progress)?;
    write_psf(&psf, &mut report, out)?;
    Ok(report)
}

/// [`plan_and_write`] in memory: the PSF and its summary (no files; `files` empty).
pub fn plan_with_report(
    doe: &Grid,
    plan: &Plan,
    bands: &[Band],
    progress: &mut dyn FnMut(&str),
) -> Result<(Psf, PsfOutcome)> {
    let (psf, ran) = run_reporting(plan, doe, bands, progress)?;
    let odd =
        Plan { system: OpticalSystem { crop: ran.system.crop | 1, ..ran.system.clone() }, ..ran.clone() };
    let (flat, _) = run_reporting(&odd, &flat_doe(&odd.system)?, bands, &mut |what| {
        progress(&format!("flat reference: {what}"))
    })?;
    let report = report(&psf, &flat, &ran.system, Some(&ran));
    Ok((psf, report))
}

/// The summary of `psf`: per channel its numbers, the Strehl ratio against `flat` (a flat
/// DOE's PSF in the same system on an odd crop), the system and plan that made it.
fn report(psf: &Psf, flat: &Psf, system: &OpticalSystem, plan: Option<&Plan>) -> PsfOutcome {
    let strehl: Vec<f64> = (0..psf.channels.len())
        .map(|c| {
            let a = psf.peak(c).0 * psf.channels[c].captured.unwrap_or(f64::NAN);
            a / (flat.peak(c).0 * flat.channels[c].captured.unwrap_or(f64::NAN))
        })
        .collect();
    let f_number = system.f_number();
    let channels = psf
        .summary()
        .into_iter()
        .enumerate()
        .map(|(c, summary)| ChannelStats {
            encircled_energy_airy: summary
                .wavelength
                .map(|l| psf.encircled_energy(c, summary.peak_position, 1.22 * l * f_number)),
            strehl: Some(strehl[c]),
            peaks: psf.peaks(
                c,
                PEAKS,
                summary.wavelength.map_or(2.0 * psf.pitch()[0], |l| 1.22 * l * f_number),
            ),
            pixel_integration_resolved: summary
                .wavelength
                .map(|l| system.sample_pitch() <= 0.5 * l * f_number),
            summary,
        })
        .collect();
    PsfOutcome {
        method: psf.method.clone(),
        normalisation: "each channel sums to 1 over the crop".into(),
        system: system.clone(),
        plan: plan.cloned(),
        channels,
        warnings: psf.warnings.clone(),
        files: Vec::new(),
    }
}

/// Writes `psf.exr`, `psf.npy`, `psf_log.png` and `psf.json` into `out`, atomically as a folder.
pub fn write_psf(psf: &Psf, report: &mut PsfOutcome, out: &Path) -> Result<()> {
    let mut stage = StagedDir::new(out)?;
    report.files = stage_psf_files(psf, &report.normalisation, &mut stage)?;
    report.files.push("psf.json".into());
    write_json(&stage.stage_path("psf.json"), report)?;
    stage.commit()
}

/// Writes `psf.exr`, `psf.npy` and `psf_log.png` into `stage`; returns their names.
pub fn stage_psf_files(psf: &Psf, normalisation: &str, stage: &mut StagedDir) -> Result<Vec<String>> {
    let wavelengths: Vec<String> = psf
        .channels
        .iter()
        .map(|c| c.wavelength.map_or("unknown".to_string(), |l| format!("{l:e}")))
        .collect();
    let mut meta = Metadata { pitch: Some(psf.pitch()), unit: None, text: Vec::new() }
        .with("wavelengths_m", wavelengths.join(","))
        .with("channel_names", psf.channels.iter().map(|c| c.name.as_str()).collect::<Vec<_>>().join(","))
        .with("method", psf.method.clone())
        .with("normalisation", normalisation);
    if !psf.warnings.is_empty() {
        meta = meta.with("warnings", psf.warnings.join(" | "));
    }
    let data: Vec<Array2<f32>> = psf.channels.iter().map(|c| c.grid.values().mapv(|v| v as f32)).collect();
    let channels: Vec<(&str, &Array2<f32>)> =
        psf.channels.iter().zip(&data).map(|(c, d)| (c.name.as_str(), d)).collect();
    write_exr(&stage.stage_path("psf.exr"), &channels, &meta)?;
    write_npy_f32_4d(&stage.stage_path("psf.npy"), &psf.to_array4())?;
    write_png_u8(&stage.stage_path("psf_log.png"), &log_panels(psf), &meta)?;
    Ok(["psf.exr", "psf.npy", "psf_log.png"].map(String::from).to_vec())
}

/// The channels side by side, each `255 * (1 + log10(v / peak) / LOG_DECADES)` clamped to 0..255.
pub fn log_panels(psf: &Psf) -> Array2<u8> {
    let (h, w) = psf.dim();
    let n = psf.channels.len();
    let mut img = Array2::<u8>::zeros((h, w * n));
    for (c, ch) in psf.channels.iter().enumerate() {
        let peak = psf.peak(c).0;
        for ((i, j), &v) in ch.grid.values().indexed_iter() {
            let t = if v > 0.0 { 1.0 + (v / peak).log10() / LOG_DECADES } else { 0.0 };
            img[[i, c * w + j]] = (t.clamp(0.0, 1.0) * 255.0).round() as u8;
        }
    }
    img
}
