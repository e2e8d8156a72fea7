//! The thresholds and search ranges of a registration ([`RegisterOptions`]).

use serde::Serialize;

use super::trust::TRUSTED_FRACTION;

/// Thresholds and search ranges of [`register`].
///
/// [`register`]: fn@super::register
#[derive(Debug, Clone, Serialize)]
pub struct RegisterOptions {
    /// Largest rotation searched either way, radians.
    pub max_rotation: f64,
    /// Also try the mirrored design (replicas are mirrored).
    pub try_mirror: bool,
    /// Refuse below this correlation coefficient between scan and registered design.
    pub min_correlation: f64,
    /// Refuse below this fraction of the correlation the scan's own noise allows (module docs).
    pub min_correlation_ratio: f64,
    /// Refuse when the second correlation peak reaches this fraction of the first (periodic).
    pub max_peak_ratio: f64,
    /// Refuse when the best correlation changes by less than this fraction over the rotation
    /// search (rotationally symmetric design).
    pub min_rotation_contrast: f64,
    /// Most scan samples used by the least-squares refinement (a stride thins the rest).
    /// Default 100,000, read off `cargo bench --bench register`'s speed-accuracy chart: on a
    /// 2048^2 scan of the paper design (2 um blur, 20 nm noise, 10% holes) the shift error is
    /// 0.003 px (formal 0.004 px), seven times inside the 0.02 px goal, in 0.077 s; 400,000
    /// gives 0.001 px in 0.10 s and 1.6 M 0.0015 px in 0.22 s (the error no longer falls with
    /// the points: model error, not noise, is left).
    pub max_points: usize,
}

impl Default for RegisterOptions {
    fn default() -> Self {
        RegisterOptions {
            max_rotation: 3f64.to_radians(),
            try_mirror: true,
            min_correlation: 0.5,
            min_correlation_ratio: TRUSTED_FRACTION,
            max_peak_ratio: 0.9,
            min_rotation_contrast: 0.01,
            max_points: 100_000,
        }
    }
}
