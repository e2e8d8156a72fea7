//! The trust rule of every registration of a part to its design: the correlation the data's
//! own noise allows ([`noise_ceiling`]) and the fraction of it a registration must reach
//! ([`check_trust`], [`TRUSTED_FRACTION`]).

use crate::error::{Error, Refusal, Result};

/// The fraction of the correlation its own noise allows ([`noise_ceiling`]) below which a
/// registration is not trusted ([`check_trust`]).
pub const TRUSTED_FRACTION: f64 = 0.95;

/// The highest correlation coefficient a right registration reaches on data whose white noise
/// has RMS `noise` and whose total variance (plane removed) is `variance`:
/// `rho_max = sqrt(1 - noise^2 / variance)` (the design explains everything but the noise).
pub fn noise_ceiling(noise: f64, variance: f64) -> f64 {
    (1.0 - noise * noise / variance).max(0.0).sqrt()
}

/// The trust rule of every registration of a part to its design (module docs, step 5): the
/// correlation reached must be at least `fraction` of the `ceiling` the data's own noise
/// allows ([`noise_ceiling`]). `what` names what correlated ("the registration", "the part over
/// the aperture's interior", ...). Refused as [`Error::Registration`], with the figures.
pub fn check_trust(what: &str, correlation: f64, ceiling: f64, fraction: f64) -> Result<()> {
    if correlation >= fraction * ceiling {
        return Ok(());
    }
    Err(Error::registration(Refusal::NotTrusted, format!(
        "{what} is not trusted: it correlates {correlation:.3} with the design where the scan's own noise \
         allows {ceiling:.3} (below {:.0}% of it): the design it was registered to does not describe the part \
         (another design, or another surface of its family, such as the design unwrapped where the recipe \
         wraps it) or the pose is wrong (a rotation or scale beyond the search, a blur of many samples)",
        100.0 * fraction
    )))
}
