//! The options of a comparison ([`CompareOptions`]).

use serde::Serialize;

use crate::fabrication::wrap::WrapSpec;
use crate::metrology::scan_registration::RegisterOptions;

use super::levels::LevelSpec;

/// Options of [`compare`] and [`compare_family`].
///
/// [`compare`]: fn@super::compare
/// [`compare_family`]: super::compare_family
#[derive(Debug, Clone, Serialize)]
pub struct CompareOptions {
    /// Options of the registration of the scan to each member.
    pub register: RegisterOptions,
    /// Clear-aperture diameter centred on the design, metres (`None`: the largest circle the
    /// design grid holds).
    pub aperture: Option<f64>,
    /// The design's quantization, for the per-level statistics and the efficiency ([`compare`];
    /// [`compare_family`] takes each reference's own).
    ///
    /// [`compare`]: fn@super::compare
    /// [`compare_family`]: super::compare_family
    pub levels: Option<LevelSpec>,
    /// Design wavelength, material and order, for the efficiency prediction.
    pub optics: WrapSpec,
    /// Smallest fraction of the aperture that the scan's footprint must cover.
    pub min_coverage: f64,
    /// Side of the central design window (samples) on which the fabrication model is fitted.
    pub fit_side: usize,
    /// Most scan samples used by the fabrication-model fit (a stride thins the rest).
    pub fit_points: usize,
}

impl Default for CompareOptions {
    fn default() -> Self {
        CompareOptions {
            register: RegisterOptions::default(),
            aperture: None,
            levels: None,
            optics: WrapSpec::default(),
            min_coverage: 0.99,
            fit_side: 2048,
            fit_points: 150_000,
        }
    }
}
