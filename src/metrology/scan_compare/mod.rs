//! Comparison of a fabricated part's scan with its design: the scan registered
//! ([`crate::metrology::scan_registration`]) and resampled onto the design grid, the difference map with
//! its RMS and PV over the clear aperture, the mean and spread of every quantization level, a
//! fitted fabrication model and the diffraction-efficiency loss its depth error predicts (the
//! design PSF against the as-fabricated PSF, and the outputs of `doefab compare`, are
//! [`crate::pipeline::compare`]'s).
//!
//! # The as-fabricated surface in the design frame
//! Registration gives `z(x_s) = a h(x_d) + b + c . x_s` (see [`crate::metrology::scan_registration`]).
//! For every design sample `x_d`, the scan is read at `x_s = pose.design_to_scan(x_d)` with
//! [`Grid::sample_index`] (Keys bicubic where its 16 taps are measured, else bilinear where its 4
//! taps are, else the nearest sample if it is measured; otherwise the design sample is
//! non-measured), and the surface is `s(x_d) = sign(a) (z(x_s) - b - c . x_s)`: the scan's
//! plane and height reference removed and a complemented part (a cast of the scanned side)
//! turned the right way up, but its depth and shape errors kept, so that `s = |a| h` for a part
//! that is only too shallow.
//!
//! # The master, the cast and the design: one family
//! A recipe makes several surfaces of one design ([`Member`]): the design wrapped modulo the
//! period `P` (and quantized), `w` in `[0, P)`, what a writer makes directly; the master, its
//! complement modulo the period, mirrored, `m(x, y) = (P - w(-x, y)) mod P`; and the cast of the
//! master, `P - m(-x, y)`, which is `w` with its zero heights lifted to the full period (in
//! `(0, P]`). The master is the cast's complement, mirrored: registration's mirror and height
//! sign find it against the cast. But neither is linear in `w` (nor in the unwrapped design):
//! where `w = 0` the master is 0, not `P`. [`compare_family`] therefore registers the scan to
//! each member it is given, keeps the best correlation, judges that registration, and compares
//! the part with that member; the report names it and what the scan shows
//! ([`scan_of`]: the master, the cast, ...).
//!
//! # Fabrication model
//! `z(x_s) = k (G_sigma * h)(x_d) + b + c . x_s`: the design blurred by a Gaussian of standard
//! deviation `sigma` (the writer's and replication's lateral resolution), scaled by the signed
//! depth scale `k` and offset. It is fitted on the scan's own samples (no resampling of the
//! scan, whose interpolation would add a blur of its own), at the registered pose, over a
//! central window of the design: for each `sigma` the linear parameters `(k, b, c)` are exact
//! least squares; `sigma` minimises the residual sum of squares `SSE(sigma)` by golden-section
//! search. Its standard error is the profile-likelihood one, `sqrt(2 s^2 / SSE''(sigma))` with
//! `s^2 = SSE / (n - 5)`; a blur whose standard error exceeds a quarter of its value is
//! reported as not resolved (blurs well below the design's pitch leave the sampled design
//! unchanged, so the data cannot see them). The blur is also checked against the fit's own
//! residual ([`FabModel::blur_doubt`]): one that lowers the residual variance by less than the
//! variance it leaves is a compromise with what the model does not describe, and is named as
//! such rather than taken for the process's resolution.
//!
//! # Efficiency loss
//! A depth scale `k` multiplies every phase step of an `N`-level profile exactly as a detuning
//! does, so the design order's efficiency is Swanson's with `a -> k a`
//! ([`order_efficiency`]; `sinc^2(k a - m)` for a continuous profile).
//!
//! [`Grid::sample_index`]: crate::grid::Grid::sample_index
//! [`order_efficiency`]: crate::fabrication::quantize::order_efficiency

mod compare;
mod efficiency;
mod fab_model;
mod family;
mod interior;
mod levels;
mod options;
mod surface;

pub use compare::{compare, compare_family, Comparison};
pub use efficiency::{efficiency_loss, EfficiencyLoss};
pub use fab_model::FabModel;
pub use family::{Candidate, Member, Reference};
pub use interior::check_interior;
pub use levels::{LevelHeights, LevelSpec, LevelStat};
pub use options::CompareOptions;
