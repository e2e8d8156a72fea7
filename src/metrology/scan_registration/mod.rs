//! Registration of a profilometer scan to its design: where the part lies on the stage
//! (shift, rotation, scale, mirror), its height sign (a cast is the complement of its master),
//! depth scale, height offset and tilt.
//!
//! # Model
//! Positions are metres from each grid's centre. A scan sample at `x_s` sees the design at
//! `x_d = M R(-theta) (x_s - t) / s` ([`Pose::scan_to_design`]; `M` = diag(-1, 1) when mirrored)
//! and reads `z = a h(x_d) + b + c_x x_s + c_y y_s + noise`: `|a|` is the depth scale, `a < 0`
//! a complemented (cast) part.
//!
//! # Algorithm
//! 1. *Observability.* The scan's surface, with its least-squares plane removed, must hold
//!    structure beyond white noise: for white noise the neighbour differences have
//!    `std(dz) = sqrt(2) std(z)`; a scan with `std(dz) > 0.8 sqrt(2) std(z)` (or no height
//!    variation at all) is featureless and refused; so is a flat design.
//! 2. *Coarse search.* Scan and design are binned to a common coarse pitch (mean of the valid
//!    samples of each cell; empty cells take the mean), levelled by a least-squares plane and
//!    mean-removed (non-measured points thus count as the mean). For each candidate rotation
//!    (steps of one coarse pixel at the design's half-width, within `max_rotation`) and both
//!    mirror states, the design is turned into a template and cross-correlated with the scan by
//!    FFT (`rustfft`, zero-padded to avoid wrap-around; the mirrored and plain templates share one
//!    complex transform as real and imaginary parts; angles in parallel, in single precision, as
//!    the sweep only ranks peaks). The largest `|c| / |T|` wins; its sign is the height sign, and
//!    the winner's map is computed again in double precision. The correlation peak is refined to 1/10 coarse pixel by the matrix-multiply
//!    upsampled DFT of Guizar-Sicairos, Thurman & Fienup, "Efficient subpixel image
//!    registration algorithms", Opt. Lett. 33, 156 (2008), applied to the plain (not
//!    phase-normalised) cross-power spectrum, and the angle by a parabola through the peaks of
//!    the neighbouring angles.
//! 3. *Ambiguity.* The second-highest local maximum of the winning correlation map outside the
//!    main lobe (where the peak falls to half) is compared with the peak: a ratio above
//!    `max_peak_ratio` means the shift is known only modulo a period (a grating) and is refused.
//!    Over the rotation search, a peak that changes by less than `min_rotation_contrast` means
//!    the design is (nearly) rotationally symmetric and its rotation unobservable: refused.
//! 4. *Least squares.* Gauss-Newton with Levenberg-Marquardt damping on all eight parameters
//!    `(t_x, t_y, theta, ln s, a, b, c_x, c_y)`, minimising the residual over the scan's valid
//!    samples (their exact positions, no resampling of the scan), the design read by Keys cubic
//!    convolution with its analytic gradient. It runs first on the design binned to half the
//!    coarse pitch, then at the design's own pitch (a quarter of `max_points` scan samples, taken
//!    with a stride), then against the design blurred by the first-order blur estimate
//!    (`max_points` samples). The point budget trades time for accuracy: `cargo bench --bench
//!    register` charts one against the other. Formal standard errors come from
//!    `sigma^2 (J^T J)^-1`.
//! 5. *Confidence.* The correlation coefficient between the scan (fitted plane removed) and the
//!    design at the registered positions; below `min_correlation` the scan is refused as not
//!    matching the design. The scan's own white noise `sigma_n` (from its neighbour differences,
//!    robustly: `1.4826 MAD / sqrt 2`, so zone edges do not count) caps what a right pose can
//!    reach, `rho_max = sqrt(1 - sigma_n^2 / var(scan))`; below `min_correlation_ratio *
//!    rho_max` the pose is refused as not trusted. `doefab bench register` found the poses this
//!    catches: a rotation far beyond the search (20-90 deg), a scale 20 % off, a blur of 10-20
//!    design samples, each accepted before at correlations of 0.53-0.94 on scans whose noise
//!    allowed 0.998, with the pose 0.2-14 deg or 1-14 samples off; a right pose on a scan with
//!    300 nm of noise correlates 0.76 and stays accepted. The rule is [`check_trust`], the one
//!    every registration of a part to its design answers to: this pose, the part's correlation
//!    over the aperture's interior in `compare`, a model `precompensate` reads back, a stylus
//!    profile's fit.

mod binning;
mod coarse;
mod options;
mod pose;
mod refine;
mod register;
mod sampler;
mod trust;

pub use options::RegisterOptions;
pub use pose::Pose;
pub use register::{check_registration, register, register_pose, Registration};
pub use sampler::Sampler;
pub use trust::{check_trust, noise_ceiling, TRUSTED_FRACTION};
