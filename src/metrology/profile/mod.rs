//! Stylus profiles: a 1-D height profile along a line across the part (Dektak, Alpha-Step,
//! P-series; read by [`crate::io::profile`]), levelled, and compared with the design along the
//! line the user names.
//!
//! # Profile
//! Positions `x_k` along the line (metres, strictly increasing), heights `z_k` (metres) and a
//! validity flag per point (a non-measured point never enters a sum or a fit). `u_k = x_k - x_0`
//! is the distance from the profile's first point.
//!
//! # Levelling ([`level_profile`])
//! * `line`: the least-squares line `z = o + t u` over all valid points, subtracted.
//! * `substrate`: the line through the lowest level only. With `r` the residuals of the current
//!   line, `R = max r - min r` over the first line's residuals, and `s_n` the noise estimated
//!   from the point-to-point differences (`1.4826 MAD(dz) / sqrt 2`, insensitive to steps and
//!   to the tilt), the band is `w_i = max(R / 2^(i+1), 5 s_n)`; the points with
//!   `r <= q_02 + w_i` (`q_02` the 2 % quantile of `r`, robust to low spikes) are refitted, for
//!   `i = 0..8`. Halving the band each time lets a tilt that first mixes the substrate with the
//!   level above be removed before the band closes on the substrate. The comparison with a
//!   design fits its own offset and tilt (`compare-profile` runs it on the profile as read),
//!   so the levelling changes only the levelled profile reported and plotted, and the
//!   design-free terraces.
//!
//! # The design along the line ([`LineSpec`])
//! Two points `p0 -> p1` (metres from the design's centre, x along columns, y along rows), or an
//! angle `theta` (counter-clockwise from +x in the design's (x, y) frame) through the centre,
//! the profile then centred on the centre. With `d` the unit direction and `n = (-d_y, d_x)`
//! its normal, profile point `k` sees the design at
//! `P_k = p0 + (u_k + s) d + v n`: `s` is the shift along the line, `v` the offset across it.
//!
//! # Model and fit ([`compare_profile`])
//! `z_k = a (G_sigma * h)(P_k) + b + c (u_k - u_mean) + noise`: the design `h` blurred by a 2-D
//! Gaussian of standard deviation `sigma` (the process's lateral blur, as `compare` fits it on a
//! map), read by Keys cubic convolution with its gradient ([`Sampler`]); `|a|` is the depth
//! scale, `a < 0` a complemented part (a cast), `b` the height offset at the profile's middle,
//! `c` the remaining tilt (dimensionless).
//! 1. *Coarse search.* For shifts `s` in `[-S, S]` and offsets `v` in `[-V, V]` (steps of half
//!    the design pitch), the Pearson correlation between the profile and the design along the
//!    line, both with their least-squares line removed (the 1-D cross-correlation); the largest
//!    `|r|` wins, its sign gives the sign of `a`. Along the winning offset's row, a second local
//!    maximum outside the main lobe reaching `max_peak_ratio` of the peak means the shift is
//!    ambiguous (a periodic design along the line): refused, narrow the search. A peak below
//!    `min_correlation` (and a fitted model correlating by less) is refused as not matching; a
//!    fitted model below [`TRUSTED_FRACTION`] of the correlation the profile's own noise allows
//!    is refused as not trusted ([`check_trust`], the rule of every registration).
//! 2. *Refinement.* For each `sigma`, Gauss-Newton with Levenberg-Marquardt damping on
//!    `(s, v, a, b, c)` (Jacobian `a grad H . d`, `a grad H . n`, `H`, `1`, `u - u_mean`);
//!    `sigma` minimises the residual sum of squares `SSE(sigma)` by golden-section search on
//!    `[0, 3 max(pitch)]` (the design blurred on a crop around the line for each `sigma`).
//! 3. *Uncertainty.* `s^2 = SSE / (n - p)`, covariance `s^2 (J^T J)^-1` over the free
//!    parameters, `sigma` included with its Jacobian column by central differences; where
//!    `sigma` is too small for that column to be determined (the blur's effect grows as
//!    `sigma^2`), the others' errors are taken at fixed `sigma` and the blur's from the
//!    profile likelihood, `sqrt(2 s^2 / SSE''(sigma))`. A blur whose standard error exceeds a
//!    quarter of it is reported as not resolved.
//! 4. *Across-line offset.* Where the design hardly varies across the line
//!    (`||J_v|| < 0.02 ||J_s||`), `v` is unobservable: it is held at the coarse value (0 unless
//!    the coarse search found better) and a warning says so; otherwise its standard error is
//!    reported (and a warning raised when it exceeds the design's pitch).
//!
//! # Per-level step heights
//! Where the reference is multi-level (at most [`MAX_LEVELS`] distinct heights: a design
//! quantized by a recipe, or a level map), each point at its registered position `P_k` belongs
//! to the terrace interior of level `l` when every design sample within
//! `r = 2 sigma + 1.5 max(pitch)` of `P_k` is on level `l` (the blur and the interpolation's
//! reach leave the point at the level's height). Its measured height is
//! `y_k = sign(a) (z_k - b - c (u_k - u_mean))`. With `m_l`, `s_l`, `n_l` the mean, spread and
//! count of level `l`'s interior heights, and `l0` the lowest level with at least 3 interior
//! points on the line, the step height is `H_l = m_l - m_l0 +- sqrt(s_l^2 / n_l + s_l0^2 / n_l0)`
//! and its depth scale `H_l / (h_l - h_l0)` against the design's, for every level with at least
//! 3 interior points. Fewer than two such levels on the line is refused.
//!
//! # Terraces without a design ([`terraces`])
//! Runs of at least `max(5, N / 200)` consecutive points whose neighbour differences stay below
//! `max(5 s_n, 1e-3 (max z - min z))` are terraces; terrace means closer than
//! `max(10 s_n, 2 % of the range)` are one level. Each level's height (the mean of its points)
//! is given above the lowest level's, with its standard error.
//!
//! [`Sampler`]: crate::metrology::scan_registration::Sampler
//! [`TRUSTED_FRACTION`]: crate::metrology::scan_registration::TRUSTED_FRACTION
//! [`check_trust`]: crate::metrology::scan_registration::check_trust

mod coarse;
mod compare;
mod levelling;
mod line;
mod model;
mod simulate;
mod steps;

pub use crate::grid::profile::Profile;
pub use compare::{compare_profile, ProfileComparison, ProfileOptions};
pub use levelling::{level_profile, terraces, Levelling, ProfileLevel, Terrace};
pub use line::LineSpec;
pub use simulate::{simulate_profile, SimulateProfile};
