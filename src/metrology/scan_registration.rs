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

use std::borrow::Cow;
use std::sync::Arc;

use rayon::prelude::*;
use rustfft::num_complex::{Complex, Complex32, Complex64};
use rustfft::{Fft, FftNum, FftPlanner};
use serde::Serialize;

use crate::error::{Allowed, Condition, Error, Refusal, Result};
use crate::grid::Grid;

/// Placement of the part: scan position `x_s = t + s R(theta) M x_d` of design position `x_d`
/// (both in metres from their grid's centre; `M` mirrors x when `mirror`; rotation
/// counter-clockwise in the (x, y) frame of the grids).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Pose {
    pub mirror: bool,
    /// Radians.
    pub rotation: f64,
    pub scale: f64,
    /// `[x, y]`, metres: the scan position of the design's centre.
    pub shift: [f64; 2],
}

impl Default for Pose {
    fn default() -> Self {
        Pose { mirror: false, rotation: 0.0, scale: 1.0, shift: [0.0, 0.0] }
    }
}

impl Pose {
    /// Refuses non-finite values and a scale that is not positive.
    pub fn check(&self) -> Result<()> {
        if !(self.rotation.is_finite() && self.shift.iter().all(|v| v.is_finite())) {
            return Err(Error::param("pose", "rotation and shift must be finite"));
        }
        if !(self.scale.is_finite() && self.scale > 0.0) {
            return Err(Error::param_in(
                "scale",
                Allowed::positive(),
                format!("must be finite and positive, got {}", self.scale),
            ));
        }
        Ok(())
    }

    /// `x_d = M R(-theta) (x_s - t) / s`.
    pub fn scan_to_design(&self, xs: [f64; 2]) -> [f64; 2] {
        let (sn, cs) = self.rotation.sin_cos();
        let u = [(xs[0] - self.shift[0]) / self.scale, (xs[1] - self.shift[1]) / self.scale];
        let v = [cs * u[0] + sn * u[1], -sn * u[0] + cs * u[1]];
        [if self.mirror { -v[0] } else { v[0] }, v[1]]
    }

    /// `x_s = t + s R(theta) M x_d`.
    pub fn design_to_scan(&self, xd: [f64; 2]) -> [f64; 2] {
        let (sn, cs) = self.rotation.sin_cos();
        let m = [if self.mirror { -xd[0] } else { xd[0] }, xd[1]];
        [
            self.shift[0] + self.scale * (cs * m[0] - sn * m[1]),
            self.shift[1] + self.scale * (sn * m[0] + cs * m[1]),
        ]
    }
}

/// Keys cubic convolution (a = -0.5) of a grid's values with its analytic gradient; positions
/// in metres from the grid's centre or fractional indices. Taps beyond the edge repeat the edge
/// sample; a point more than half a sample outside the grid, or touching an invalid sample,
/// has no value.
#[derive(Debug, Clone)]
pub struct Sampler<'a> {
    /// The values, row-major: borrowed from the grid when it stores them so.
    v: Cow<'a, [f64]>,
    /// Discrete Laplacian of the values (per square metre), when made by [`Sampler::with_laplacian`].
    lap: Option<Vec<f64>>,
    valid: Option<Vec<bool>>,
    rows: usize,
    cols: usize,
    pitch: [f64; 2],
}

impl<'a> Sampler<'a> {
    pub fn new(g: &'a Grid) -> Sampler<'a> {
        let (rows, cols) = g.dim();
        Sampler {
            v: g.values()
                .as_slice()
                .map_or_else(|| Cow::Owned(g.values().iter().copied().collect()), Cow::Borrowed),
            lap: None,
            valid: g.mask().map(|m| m.iter().copied().collect()),
            rows,
            cols,
            pitch: g.pitch(),
        }
    }

    /// A sampler holding its own copy of the values (one that outlives the grid).
    pub fn new_owned(g: &Grid) -> Sampler<'static> {
        let s = Sampler::new(g);
        Sampler {
            v: Cow::Owned(s.v.into_owned()),
            lap: s.lap,
            valid: s.valid,
            rows: s.rows,
            cols: s.cols,
            pitch: s.pitch,
        }
    }

    /// Also samples the 5-point Laplacian `d2h/dx2 + d2h/dy2` of the values (0 next to an
    /// invalid sample; edges repeat the edge sample).
    pub fn with_laplacian(g: &'a Grid) -> Sampler<'a> {
        let mut s = Sampler::new(g);
        let (nr, nc) = (s.rows, s.cols);
        let (px2, py2) = (s.pitch[0] * s.pitch[0], s.pitch[1] * s.pitch[1]);
        let ok = |k: usize| s.valid.as_ref().is_none_or(|m| m[k]);
        let mut lap = vec![0.0; nr * nc];
        let v = &s.v;
        // Rows in parallel; each sample depends on its neighbours only.
        lap.par_chunks_mut(nc).enumerate().for_each(|(i, row)| {
            for (j, out) in row.iter_mut().enumerate() {
                let k = i * nc + j;
                let (u, d) = (i.saturating_sub(1) * nc + j, (i + 1).min(nr - 1) * nc + j);
                let (l, r) = (i * nc + j.saturating_sub(1), i * nc + (j + 1).min(nc - 1));
                if [k, u, d, l, r].iter().all(|&q| ok(q)) {
                    *out = (v[l] + v[r] - 2.0 * v[k]) / px2 + (v[u] + v[d] - 2.0 * v[k]) / py2;
                }
            }
        });
        s.lap = Some(lap);
        s
    }

    /// Fractional `(row, column)` index of a position (metres from the centre).
    pub fn index_of(&self, x: [f64; 2]) -> (f64, f64) {
        (
            x[1] / self.pitch[1] + (self.rows as f64 - 1.0) * 0.5,
            x[0] / self.pitch[0] + (self.cols as f64 - 1.0) * 0.5,
        )
    }

    /// Value at a position (metres from the centre).
    pub fn at_position(&self, x: [f64; 2]) -> Option<f64> {
        let (fi, fj) = self.index_of(x);
        self.eval(fi, fj).map(|r| r.0)
    }

    /// `(value, d value / d row, d value / d column)` at fractional index `(fi, fj)`.
    #[inline]
    pub fn eval(&self, fi: f64, fj: f64) -> Option<(f64, f64, f64)> {
        self.eval_lap(fi, fj).map(|r| (r[0], r[1], r[2]))
    }

    /// `[h, dh/di, dh/dj, L, dL/di, dL/dj]` with `L` the Laplacian (0 without one).
    #[inline]
    pub fn eval_lap(&self, fi: f64, fj: f64) -> Option<[f64; 6]> {
        let (nr, nc) = (self.rows as isize, self.cols as isize);
        if !(fi >= -0.5 && fj >= -0.5 && fi <= nr as f64 - 0.5 && fj <= nc as f64 - 0.5) {
            return None;
        }
        let (i0, j0) = (fi.floor(), fj.floor());
        let (wi, di) = keys(fi - i0);
        let (wj, dj) = keys(fj - j0);
        let (i0, j0) = (i0 as isize, j0 as isize);
        let mut out = [0.0; 6];
        for a in 0..4 {
            let r = (i0 + a as isize - 1).clamp(0, nr - 1) as usize * self.cols;
            let (mut row, mut drow, mut lrow, mut ldrow) = (0.0, 0.0, 0.0, 0.0);
            for b in 0..4 {
                let k = r + (j0 + b as isize - 1).clamp(0, nc - 1) as usize;
                if let Some(m) = &self.valid {
                    if !m[k] {
                        return None;
                    }
                }
                row += wj[b] * self.v[k];
                drow += dj[b] * self.v[k];
                if let Some(l) = &self.lap {
                    lrow += wj[b] * l[k];
                    ldrow += dj[b] * l[k];
                }
            }
            out[0] += wi[a] * row;
            out[1] += di[a] * row;
            out[2] += wi[a] * drow;
            out[3] += wi[a] * lrow;
            out[4] += di[a] * lrow;
            out[5] += wi[a] * ldrow;
        }
        Some(out)
    }
}

/// Keys weights for taps at -1, 0, 1, 2 from `t` in [0, 1), and their derivatives in `t`.
#[inline]
fn keys(t: f64) -> ([f64; 4], [f64; 4]) {
    let k1 = |x: f64| 1.5 * x * x * x - 2.5 * x * x + 1.0; // |x| <= 1
    let k2 = |x: f64| -0.5 * x * x * x + 2.5 * x * x - 4.0 * x + 2.0; // 1 < |x| < 2
    let d1 = |x: f64| 4.5 * x * x - 5.0 * x;
    let d2 = |x: f64| -1.5 * x * x + 5.0 * x - 4.0;
    ([k2(t + 1.0), k1(t), k1(1.0 - t), k2(2.0 - t)], [d2(t + 1.0), d1(t), -d1(1.0 - t), -d2(2.0 - t)])
}

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

/// Thresholds and search ranges of [`register`].
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

/// The registration of a scan to a design; see the module docs for the model.
#[derive(Debug, Clone, Serialize)]
pub struct Registration {
    pub pose: Pose,
    /// The scan shows the complement of the design (`a < 0`).
    pub complement: bool,
    /// `|a|`.
    pub depth_scale: f64,
    /// `b`, metres.
    pub offset: f64,
    /// `[c_x, c_y]`, slopes of the scan's plane (dimensionless).
    pub tilt: [f64; 2],
    /// Lateral blur of the scan relative to the design: Gaussian standard deviation, metres.
    pub blur: f64,
    /// Correlation coefficient between scan (plane removed) and registered design.
    pub correlation: f64,
    /// The highest correlation the scan's white noise allows a right pose (module docs).
    pub noise_ceiling: f64,
    /// The scan's white noise, RMS metres (`1.4826 MAD / sqrt 2` of its neighbour differences).
    pub noise: f64,
    /// Second to first peak of the coarse correlation (1 = ambiguous shift).
    pub peak_ratio: f64,
    /// Relative drop of the coarse correlation peak across the rotation search.
    pub rotation_contrast: f64,
    /// Best peak of the other mirror state over the winner's (1 = mirror undecided).
    pub mirror_ratio: f64,
    /// RMS of the residual, metres.
    pub rms_residual: f64,
    /// Formal standard errors `sigma^2 (J^T J)^-1` (white residuals assumed, so a lower bound
    /// where the residual is dominated by model error): shift `[x, y]` (metres), rotation
    /// (radians), scale, depth scale. NaN where the normal equations are singular.
    pub shift_sigma: [f64; 2],
    pub rotation_sigma: f64,
    pub scale_sigma: f64,
    pub depth_scale_sigma: f64,
    /// Scan samples in the final fit.
    pub points: usize,
    /// Coarse pitch of the search, metres.
    pub coarse_pitch: f64,
}

/// A real image centred on (0, 0) at `pitch`, row-major.
#[derive(Debug, Clone)]
struct Img {
    v: Vec<f64>,
    rows: usize,
    cols: usize,
    pitch: [f64; 2],
}

impl Img {
    fn centre(&self) -> (f64, f64) {
        ((self.rows as f64 - 1.0) * 0.5, (self.cols as f64 - 1.0) * 0.5)
    }

    /// Bilinear value at a position (metres from the centre), 0 outside.
    fn bilinear(&self, x: [f64; 2]) -> f64 {
        let (ci, cj) = self.centre();
        let (fi, fj) = (x[1] / self.pitch[1] + ci, x[0] / self.pitch[0] + cj);
        if !(fi >= 0.0 && fj >= 0.0 && fi <= self.rows as f64 - 1.0 && fj <= self.cols as f64 - 1.0) {
            return 0.0;
        }
        let (i0, j0) = (fi.floor() as usize, fj.floor() as usize);
        let (i1, j1) = ((i0 + 1).min(self.rows - 1), (j0 + 1).min(self.cols - 1));
        let (ti, tj) = (fi - i0 as f64, fj - j0 as f64);
        let g = |i: usize, j: usize| self.v[i * self.cols + j];
        (1.0 - ti) * ((1.0 - tj) * g(i0, j0) + tj * g(i0, j1))
            + ti * ((1.0 - tj) * g(i1, j0) + tj * g(i1, j1))
    }
}

/// Bins a grid's valid samples into cells of `pitch` centred on the grid's centre (cell of a
/// sample = nearest cell centre). Returns the cell means (0 where empty) and counts.
fn bin(g: &Grid, pitch: [f64; 2]) -> (Img, Vec<f64>) {
    let (nr, nc) = g.dim();
    let p = g.pitch();
    let cols = ((nc as f64 * p[0] / pitch[0]).ceil() as usize).max(1);
    let rows = ((nr as f64 * p[1] / pitch[1]).ceil() as usize).max(1);
    let mut sum = vec![0.0; rows * cols];
    let mut cnt = vec![0.0; rows * cols];
    let jmap: Vec<usize> = (0..nc)
        .map(|j| {
            let x = (j as f64 - (nc as f64 - 1.0) * 0.5) * p[0];
            ((x / pitch[0] + (cols as f64 - 1.0) * 0.5).round().max(0.0) as usize).min(cols - 1)
        })
        .collect();
    // Cell row of each sample row: non-decreasing, so each cell row takes a contiguous run of
    // sample rows. Cell rows are filled in parallel, each summing its samples in row-major
    // order (the same order, and so the same sums, on any number of threads).
    let imap: Vec<usize> = (0..nr)
        .map(|i| {
            let y = (i as f64 - (nr as f64 - 1.0) * 0.5) * p[1];
            ((y / pitch[1] + (rows as f64 - 1.0) * 0.5).round().max(0.0) as usize).min(rows - 1)
        })
        .collect();
    // Standard layout is contiguous, so the slices always exist.
    let values = g.values().as_standard_layout();
    let vals = values.as_slice().expect("standard layout is contiguous");
    let mask = g.mask().map(|m| m.as_standard_layout());
    let mvals = mask.as_ref().map(|m| m.as_slice().expect("standard layout is contiguous"));
    sum.par_chunks_mut(cols).zip(cnt.par_chunks_mut(cols)).enumerate().for_each(|(bi, (srow, crow))| {
        let (i0, i1) = (imap.partition_point(|&b| b < bi), imap.partition_point(|&b| b <= bi));
        for i in i0..i1 {
            let row = &vals[i * nc..(i + 1) * nc];
            let ok = mvals.map(|m| &m[i * nc..(i + 1) * nc]);
            for (j, &z) in row.iter().enumerate() {
                if ok.is_none_or(|m| m[j]) {
                    srow[jmap[j]] += z;
                    crow[jmap[j]] += 1.0;
                }
            }
        }
    });
    let v = sum.iter().zip(&cnt).map(|(s, c)| if *c > 0.0 { s / c } else { 0.0 }).collect();
    (Img { v, rows, cols, pitch }, cnt)
}

/// Removes the weighted least-squares plane from the occupied cells; empty cells become 0.
fn level_img(img: &mut Img, w: &[f64]) {
    let (ci, cj) = img.centre();
    let mut a = [0.0; 9];
    let mut r = [0.0; 3];
    for i in 0..img.rows {
        for j in 0..img.cols {
            let k = i * img.cols + j;
            if w[k] > 0.0 {
                let f = [1.0, j as f64 - cj, i as f64 - ci];
                for p in 0..3 {
                    r[p] += w[k] * f[p] * img.v[k];
                    for q in 0..3 {
                        a[p * 3 + q] += w[k] * f[p] * f[q];
                    }
                }
            }
        }
    }
    let c = solve(&mut a, &mut r, 3).unwrap_or([0.0; 3].to_vec());
    for i in 0..img.rows {
        for j in 0..img.cols {
            let k = i * img.cols + j;
            img.v[k] = if w[k] > 0.0 {
                img.v[k] - c[0] - c[1] * (j as f64 - cj) - c[2] * (i as f64 - ci)
            } else {
                0.0
            };
        }
    }
}

/// Solves the `n x n` system `a x = r` ([`crate::linalg::solve`]); `None` where it
/// is singular or the solution is not finite.
fn solve(a: &mut [f64], r: &mut [f64], n: usize) -> Option<Vec<f64>> {
    let x = crate::linalg::solve(a.to_vec(), r.to_vec(), n).ok()?;
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// A 2-D complex FFT of fixed shape, planned once (rows, then columns through a transpose).
#[derive(Clone)]
struct Fft2<T: FftNum> {
    rows: usize,
    cols: usize,
    fr: Arc<dyn Fft<T>>,
    fc: Arc<dyn Fft<T>>,
    ir: Arc<dyn Fft<T>>,
    ic: Arc<dyn Fft<T>>,
    scratch: Vec<Complex<T>>,
    tmp: Vec<Complex<T>>,
}

impl<T: FftNum> Fft2<T> {
    fn new(rows: usize, cols: usize) -> Fft2<T> {
        let mut p = FftPlanner::new();
        let (fr, fc) = (p.plan_fft_forward(cols), p.plan_fft_forward(rows));
        let (ir, ic) = (p.plan_fft_inverse(cols), p.plan_fft_inverse(rows));
        let n = [&fr, &fc, &ir, &ic].iter().map(|f| f.get_inplace_scratch_len()).max().unwrap_or(0);
        Fft2 {
            rows,
            cols,
            fr,
            fc,
            ir,
            ic,
            scratch: vec![Complex::new(T::zero(), T::zero()); n],
            tmp: vec![Complex::new(T::zero(), T::zero()); rows * cols],
        }
    }

    fn run(&mut self, buf: &mut [Complex<T>], inverse: bool) {
        let (r, c) = (self.rows, self.cols);
        let (row, col) = if inverse { (&self.ir, &self.ic) } else { (&self.fr, &self.fc) };
        row.process_with_scratch(buf, &mut self.scratch);
        for i in 0..r {
            for j in 0..c {
                self.tmp[j * r + i] = buf[i * c + j];
            }
        }
        col.process_with_scratch(&mut self.tmp, &mut self.scratch);
        for j in 0..c {
            for i in 0..r {
                buf[i * c + j] = self.tmp[j * r + i];
            }
        }
    }
}

/// The smallest `n >= m` of the form `2^a 3^b 5^c` (fast for `rustfft`).
fn fast_len(m: usize) -> usize {
    let mut n = m.max(1);
    loop {
        let mut k = n;
        for f in [2, 3, 5] {
            while k.is_multiple_of(f) {
                k /= f;
            }
        }
        if k == 1 {
            return n;
        }
        n += 1;
    }
}

/// Design samples per side of the coarse search (the coarse pitch is a power-of-two multiple
/// of the design's pitch chosen to stay at or below this).
const COARSE_SIDE: usize = 192;

/// Peak of a correlation map (signed, normalised).
#[derive(Debug, Clone, Copy)]
struct Peak {
    value: f64,
}

/// Registers `scan` (heights, metres) to `design` (heights, metres); see the module docs:
/// [`register_pose`], then [`check_registration`].
pub fn register(design: &Grid, scan: &Grid, opts: &RegisterOptions) -> Result<Registration> {
    let reg = register_pose(design, scan, opts)?;
    check_registration(&reg, opts)?;
    Ok(reg)
}

/// Steps 1, 2 and 4 of the module docs: the best pose and its figures, without the verdicts of
/// steps 3 and 5 ([`check_registration`]), so that a caller can register one scan to several
/// candidate surfaces and judge the best. Refused here: a flat design, a featureless scan, no
/// overlap.
pub fn register_pose(design: &Grid, scan: &Grid, opts: &RegisterOptions) -> Result<Registration> {
    let (noise_ceiling, noise) = check_observable(design, scan)?;
    let pd = design.pitch();
    let (dr, dc) = design.dim();
    let mut f = 1usize;
    while dr.max(dc) / f > COARSE_SIDE {
        f *= 2;
    }
    let pc = [pd[0] * f as f64, pd[1] * f as f64];
    let (mut dimg, dw) = bin(design, pc);
    level_img(&mut dimg, &dw);
    let (mut simg, sw) = bin(scan, pc);
    level_img(&mut simg, &sw);
    let coarse = coarse_search(&dimg, &simg, opts)?;
    // Step 4 runs before the ambiguity verdicts of step 3 so that a scan of another part is
    // reported as a mismatch, not as an ambiguity.
    // Least squares, first against the design binned to half the coarse pitch, then at its pitch.
    let mut p = Params {
        t: [coarse.pose.shift[0] / pd[0], coarse.pose.shift[1] / pd[1]],
        theta: coarse.pose.rotation,
        ln_s: 0.0,
        lin: [0.0; 5],
    };
    // Levels: (binning factor, blur applied to the design first).
    let mut levels = vec![];
    if f >= 4 {
        levels.push(f / 2);
    }
    levels.push(1);
    levels.push(0);
    let mut fit = None;
    let mut blur2 = 0.0;
    for g in levels {
        let dg = if g == 0 {
            // The design blurred by the first-order estimate sigma^2 = 2 e / a, then refitted.
            let s2 = 2.0 * p.lin[4] / p.lin[0];
            if s2.is_nan() || s2 <= 0.0 {
                break;
            }
            blur2 = s2;
            p.lin[4] = 0.0;
            Cow::Owned(crate::grid::blur::gaussian_blur(design, s2.sqrt())?)
        } else if g == 1 {
            Cow::Borrowed(design)
        } else {
            let (img, w) = bin(design, [pd[0] * g as f64, pd[1] * g as f64]);
            let valid =
                ndarray::Array2::from_shape_vec((img.rows, img.cols), w.iter().map(|&c| c > 0.0).collect())
                    .map_err(|e| Error::Data(e.to_string()))?;
            let v = ndarray::Array2::from_shape_vec((img.rows, img.cols), img.v)
                .map_err(|e| Error::Data(e.to_string()))?;
            Cow::Owned(Grid::new(v, img.pitch, design.unit())?.with_mask(valid)?)
        };
        // The last level (design blurred) takes the full point budget; the unblurred pass
        // before it only supplies the blur's first-order estimate and a closer start, for which
        // a quarter of the points does.
        let limit = match g {
            0 => opts.max_points,
            1 => (opts.max_points / 4).max(20_000),
            g => (opts.max_points / (g * g)).max(20_000),
        };
        let g = g.max(1);
        let pts = points(scan, limit);
        let sampler = Sampler::with_laplacian(&dg);
        let ctx = Ctx { sampler: &sampler, mirror: coarse.pose.mirror, pd, g: g as f64 };
        fit = Some(refine(&ctx, &pts, &mut p, dr.max(dc) as f64 * 0.5, fit.is_none())?);
    }
    let fit = fit.ok_or_else(|| Error::Data("no refinement level ran".into()))?;
    let a = p.lin[0];
    let blur = (blur2 + 2.0 * p.lin[4] / a).max(0.0).sqrt();
    let reg = Registration {
        blur,
        pose: Pose {
            mirror: coarse.pose.mirror,
            rotation: p.theta,
            scale: p.ln_s.exp(),
            shift: [p.t[0] * pd[0], p.t[1] * pd[1]],
        },
        complement: a < 0.0,
        depth_scale: a.abs(),
        offset: p.lin[1],
        tilt: [p.lin[2], p.lin[3]],
        correlation: fit.correlation,
        noise_ceiling,
        noise,
        peak_ratio: coarse.peak_ratio,
        rotation_contrast: coarse.rotation_contrast,
        mirror_ratio: coarse.mirror_ratio,
        rms_residual: fit.rms,
        shift_sigma: [fit.sigma[0] * pd[0], fit.sigma[1] * pd[1]],
        rotation_sigma: fit.sigma[2],
        scale_sigma: fit.sigma[3] * p.ln_s.exp(),
        depth_scale_sigma: fit.sigma[4],
        points: fit.points,
        coarse_pitch: pc[0],
    };
    Ok(reg)
}

/// The verdicts of steps 3 and 5 of the module docs on a registration [`register_pose`] found:
/// no match (below `min_correlation`, [`Error::Validity`]), not trusted ([`check_trust`],
/// [`Error::Registration`]), an ambiguous shift or rotation ([`Error::Validity`]).
pub fn check_registration(reg: &Registration, opts: &RegisterOptions) -> Result<()> {
    if reg.correlation.is_nan() || reg.correlation < opts.min_correlation {
        return Err(Error::validity(
            Condition::Registration(Refusal::NoMatch),
            format!(
                "the scan does not match the design: correlation {:.3} after registration is below {:.2} \
             (wrong design, wrong scan, or a part too damaged to register)",
                reg.correlation, opts.min_correlation
            ),
        ));
    }
    check_trust("the registration", reg.correlation, reg.noise_ceiling, opts.min_correlation_ratio)?;
    if reg.peak_ratio > opts.max_peak_ratio {
        return Err(Error::validity(
            Condition::Registration(Refusal::Ambiguous),
            format!(
                "registration is ambiguous: the second correlation peak is {:.1}% of the first \
             (a periodic structure such as a grating fixes the shift only modulo its period); \
             a fiducial or an aperture edge in the scan would fix it",
                100.0 * reg.peak_ratio
            ),
        ));
    }
    if opts.max_rotation > 0.0 && reg.rotation_contrast < opts.min_rotation_contrast {
        return Err(Error::validity(
            Condition::Registration(Refusal::Ambiguous),
            format!(
                "registration is ambiguous: the correlation changes by only {:.2}% over +-{:.2} deg of \
             rotation (a rotationally symmetric design: rotation is unobservable without a fiducial)",
                100.0 * reg.rotation_contrast,
                opts.max_rotation.to_degrees()
            ),
        ));
    }
    Ok(())
}

/// Rows of the scan [`check_observable`] reads at most.
const OBSERVABLE_ROWS: usize = 256;

/// Refuses a flat design and a scan that is flat or white noise (step 1 of the module docs);
/// returns the correlation the scan's white noise allows (step 5) and that noise (RMS, metres).
fn check_observable(design: &Grid, scan: &Grid) -> Result<(f64, f64)> {
    let (lo, hi) = design.min_max().ok_or_else(|| Error::Data("the design has no valid sample".into()))?;
    if hi <= lo {
        return Err(Error::validity(
            Condition::Registration(Refusal::Featureless),
            "the design is flat: there is nothing to register against",
        ));
    }
    // The statistics from at most OBSERVABLE_ROWS rows spread over the scan: half a million
    // samples of a 2048^2 scan tell structure from white noise as well as four million.
    let row_step = scan.dim().0.div_ceil(OBSERVABLE_ROWS).max(1);
    let plane = crate::metrology::level::fit_plane_rows(scan, None, row_step)?;
    let (mut n, mut s, mut ss, mut nd, mut sd) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let mut diffs = Vec::new();
    for (i, row) in scan.values().outer_iter().enumerate().step_by(row_step) {
        let mut prev: Option<f64> = None;
        for (j, &z) in row.iter().enumerate() {
            if scan.is_valid(i, j) {
                let r = z - plane.at(i as f64, j as f64);
                n += 1.0;
                s += r;
                ss += r * r;
                if let Some(q) = prev {
                    nd += 1.0;
                    sd += (r - q) * (r - q);
                    // Every fourth difference is plenty for a median.
                    if j % 4 == 0 {
                        diffs.push(r - q);
                    }
                }
                prev = Some(r);
            } else {
                prev = None;
            }
        }
    }
    let var = (ss / n - (s / n).powi(2)).max(0.0);
    let dvar = if nd > 0.0 { sd / nd } else { 0.0 };
    if var.is_nan() || var.sqrt() <= 1e-12 {
        return Err(Error::validity(
            Condition::Registration(Refusal::Featureless),
            "the scan is featureless (flat after levelling): nothing to register",
        ));
    }
    let ratio = (dvar / (2.0 * var)).sqrt();
    if ratio > 0.8 {
        return Err(Error::validity(
            Condition::Registration(Refusal::Featureless),
            format!(
                "the scan is featureless: after levelling it looks like white noise (neighbour \
             differences {ratio:.2} x sqrt(2) x its RMS {:.3} nm); nothing to register",
                var.sqrt() * 1e9
            ),
        ));
    }
    // White noise from the neighbour differences' median absolute deviation (steps at zone
    // edges are outliers to it).
    let noise = 1.4826 * median_abs_deviation(&mut diffs) / std::f64::consts::SQRT_2;
    Ok((noise_ceiling(noise, var), noise))
}

/// The median absolute deviation of `v` from its median (reorders `v`); 0 for no values.
fn median_abs_deviation(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    let median = *v.select_nth_unstable_by(mid, f64::total_cmp).1;
    for x in v.iter_mut() {
        *x = (*x - median).abs();
    }
    *v.select_nth_unstable_by(mid, f64::total_cmp).1
}

struct Coarse {
    pose: Pose,
    peak_ratio: f64,
    rotation_contrast: f64,
    mirror_ratio: f64,
}

/// Step 2 and the measures of step 3 of the module docs.
fn coarse_search(d: &Img, s: &Img, opts: &RegisterOptions) -> Result<Coarse> {
    let (tr, tc) = (d.rows, d.cols);
    let nr = fast_len(s.rows + tr);
    let nc = fast_len(s.cols + tc);
    let mut fft = Fft2::<f64>::new(nr, nc);
    let mut sh = vec![Complex64::default(); nr * nc];
    for i in 0..s.rows {
        for j in 0..s.cols {
            sh[i * nc + j] = Complex64::new(s.v[i * s.cols + j], 0.0);
        }
    }
    fft.run(&mut sh, false);
    let s_norm = s.v.iter().map(|v| v * v).sum::<f64>().sqrt();
    if s_norm.is_nan() || s_norm <= 0.0 {
        return Err(Error::validity(
            Condition::Registration(Refusal::Featureless),
            "the scan is featureless at the coarse scale",
        ));
    }
    let radius = 0.5 * tr.min(tc) as f64;
    let step = (1.0 / radius).min(0.5f64.to_radians());
    let n_ang = (opts.max_rotation.max(0.0) / step).ceil() as isize;
    let angles: Vec<f64> = (-n_ang..=n_ang).map(|k| k as f64 * step).collect();
    let mirrors: &[bool] = if opts.try_mirror { &[false, true] } else { &[false] };
    let (ct_i, ct_j) = d.centre();
    let template = |theta: f64, mirror: bool| -> (Vec<f64>, f64) {
        // Pose::scan_to_design with rotation theta, unit scale and no shift, written out so
        // that the sine and cosine are taken once.
        let (sn, cs) = theta.sin_cos();
        let mx = if mirror { -1.0 } else { 1.0 };
        let mut t = vec![0.0; tr * tc];
        for i in 0..tr {
            let y = (i as f64 - ct_i) * d.pitch[1];
            for j in 0..tc {
                let x = (j as f64 - ct_j) * d.pitch[0];
                t[i * tc + j] = d.bilinear([mx * (cs * x + sn * y), -sn * x + cs * y]);
            }
        }
        let n = t.iter().map(|v| v * v).sum::<f64>().sqrt();
        (t, n)
    };
    let lag = |k: usize, len: usize, n: usize| if k >= len { k as isize - n as isize } else { k as isize };
    let scale = 1.0 / (nr * nc) as f64;
    // For each angle (in parallel, each with its own transform buffers) and mirror state: the
    // best |c| / (|S| |T|). Every angle is computed alone, so threads do not change the result.
    // The sweep in single precision (it only ranks peaks; the winner's map is redone in f64).
    let fft32 = Fft2::<f32>::new(nr, nc);
    let sh32: Vec<Complex32> = sh.iter().map(|c| Complex32::new(c.re as f32, c.im as f32)).collect();
    let per_angle: Vec<Vec<Peak>> = angles
        .par_iter()
        .map_init(
            || (fft32.clone(), vec![Complex32::default(); nr * nc]),
            |(fft, buf), &theta| {
                let ts: Vec<(Vec<f64>, f64)> = mirrors.iter().map(|&m| template(theta, m)).collect();
                buf.iter_mut().for_each(|c| *c = Complex32::default());
                for i in 0..tr {
                    for j in 0..tc {
                        let re = ts[0].0[i * tc + j];
                        let im = ts.get(1).map_or(0.0, |t| t.0[i * tc + j]);
                        buf[i * nc + j] = Complex32::new(re as f32, im as f32);
                    }
                }
                fft.run(buf, false);
                for (b, sv) in buf.iter_mut().zip(&sh32) {
                    *b = sv * b.conj();
                }
                fft.run(buf, true);
                ts.iter()
                    .enumerate()
                    .map(|(m, t)| {
                        let norm = scale / (s_norm * t.1.max(1e-300));
                        let mut best = Peak { value: 0.0 };
                        for c in buf.iter() {
                            // Real part: plain template; minus imaginary part: mirrored template.
                            let v = f64::from(if m == 0 { c.re } else { -c.im }) * norm;
                            if v.abs() > best.value.abs() {
                                best = Peak { value: v };
                            }
                        }
                        best
                    })
                    .collect()
            },
        )
        .collect();
    // peaks[m][a]: mirror state m, angle a.
    let peaks: Vec<Vec<Peak>> =
        (0..mirrors.len()).map(|m| per_angle.iter().map(|ps| ps[m]).collect()).collect();
    let mut buf = vec![Complex64::default(); nr * nc];
    let (mut bm, mut ba) = (0, 0);
    for (m, ps) in peaks.iter().enumerate() {
        for (a, p) in ps.iter().enumerate() {
            if p.value.abs() > peaks[bm][ba].value.abs() {
                (bm, ba) = (m, a);
            }
        }
    }
    let best = peaks[bm][ba];
    if best.value.is_nan() || best.value == 0.0 {
        return Err(Error::validity(
            Condition::Registration(Refusal::NoMatch),
            "no correlation between scan and design at any placement",
        ));
    }
    let mirror = mirrors[bm];
    let mirror_ratio = if mirrors.len() > 1 {
        peaks[1 - bm].iter().map(|p| p.value.abs()).fold(0.0, f64::max) / best.value.abs()
    } else {
        0.0
    };
    let amin = peaks[bm].iter().map(|p| p.value.abs()).fold(f64::INFINITY, f64::min);
    let rotation_contrast = 1.0 - amin / best.value.abs();
    // Parabolic refinement of the angle.
    let mut theta = angles[ba];
    if ba > 0 && ba + 1 < angles.len() {
        let (y0, y1, y2) = (peaks[bm][ba - 1].value.abs(), best.value.abs(), peaks[bm][ba + 1].value.abs());
        let den = y0 - 2.0 * y1 + y2;
        if den < 0.0 {
            theta += step * (0.5 * (y0 - y2) / den).clamp(-0.5, 0.5);
        }
    }
    // The winner's map once more, real template only: second peak and upsampled refinement.
    let (t, tn) = template(theta, mirror);
    buf.iter_mut().for_each(|c| *c = Complex64::default());
    for i in 0..tr {
        for j in 0..tc {
            buf[i * nc + j] = Complex64::new(t[i * tc + j], 0.0);
        }
    }
    fft.run(&mut buf, false);
    for (b, sv) in buf.iter_mut().zip(&sh) {
        *b = sv * b.conj();
    }
    let spectrum = buf.clone();
    fft.run(&mut buf, true);
    let sign = best.value.signum();
    let map: Vec<f64> = buf.iter().map(|c| sign * c.re * scale / (s_norm * tn)).collect();
    let (k0, peak) =
        map.iter().enumerate().fold((0, f64::NEG_INFINITY), |b, (k, &v)| if v > b.1 { (k, v) } else { b });
    let peak_ratio = second_peak(&map, nr, nc, k0) / peak;
    let at = (lag(k0 / nc, s.rows, nr), lag(k0 % nc, s.cols, nc));
    let (dy, dx) = upsampled_peak(&spectrum, nr, nc, at, 10, sign);
    let (cs_i, cs_j) = s.centre();
    let shift = [(dx - cs_j + ct_j) * s.pitch[0], (dy - cs_i + ct_i) * s.pitch[1]];
    Ok(Coarse {
        pose: Pose { mirror, rotation: theta, scale: 1.0, shift },
        peak_ratio,
        rotation_contrast,
        mirror_ratio,
    })
}

/// The largest local maximum of `map` outside the main lobe around `k0` (the connected region,
/// along rows and columns, where the map stays above half the peak), relative to 0.
fn second_peak(map: &[f64], nr: usize, nc: usize, k0: usize) -> f64 {
    let (i0, j0) = ((k0 / nc) as isize, (k0 % nc) as isize);
    let peak = map[k0];
    let at = |i: isize, j: isize| {
        map[(i.rem_euclid(nr as isize) as usize) * nc + j.rem_euclid(nc as isize) as usize]
    };
    let mut r = 1isize;
    for (di, dj) in [(0, 1), (0, -1), (1, 0), (-1, 0)] {
        let mut k = 1;
        while k < (nr.max(nc) as isize) / 2 && at(i0 + di * k, j0 + dj * k) > 0.5 * peak {
            k += 1;
        }
        r = r.max(k);
    }
    let mut second = 0.0f64;
    for i in 0..nr as isize {
        for j in 0..nc as isize {
            let (di, dj) = ((i - i0).rem_euclid(nr as isize), (j - j0).rem_euclid(nc as isize));
            let (di, dj) = (di.min(nr as isize - di), dj.min(nc as isize - dj));
            if di.max(dj) <= r {
                continue;
            }
            let v = at(i, j);
            if v > second
                && v >= at(i - 1, j)
                && v >= at(i + 1, j)
                && v >= at(i, j - 1)
                && v >= at(i, j + 1)
                && v >= at(i - 1, j - 1)
                && v >= at(i + 1, j + 1)
                && v >= at(i - 1, j + 1)
                && v >= at(i + 1, j - 1)
            {
                second = v;
            }
        }
    }
    second
}

/// Guizar-Sicairos et al. (2008): the cross-correlation `sum_k P[k] e^{2 pi i k x / N} / N` on a
/// 1.5-pixel window around the integer peak `at`, sampled every `1/up` pixel by two matrix
/// products; returns the (row, column) lag of its largest value (times `sign`).
fn upsampled_peak(
    p: &[Complex64],
    nr: usize,
    nc: usize,
    at: (isize, isize),
    up: usize,
    sign: f64,
) -> (f64, f64) {
    let w = (1.5 * up as f64).ceil() as usize + 1;
    let off = |a: usize| (a as f64 - (w as f64 - 1.0) * 0.5) / up as f64;
    let freq = |k: usize, n: usize| if k > n / 2 { k as f64 - n as f64 } else { k as f64 };
    let kern = |n: usize, centre: isize| -> Vec<Complex64> {
        // kern[a * n + k] = exp(2 pi i f_k (centre + off_a) / n)
        let mut e = vec![Complex64::default(); w * n];
        for a in 0..w {
            let x = centre as f64 + off(a);
            for k in 0..n {
                let ph = 2.0 * std::f64::consts::PI * freq(k, n) * x / n as f64;
                e[a * n + k] = Complex64::new(ph.cos(), ph.sin());
            }
        }
        e
    };
    let ec = kern(nc, at.1);
    let er = kern(nr, at.0);
    // a[k_r][b] = sum_kc p[k_r][k_c] ec[b][k_c]
    let mut a = vec![Complex64::default(); nr * w];
    for kr in 0..nr {
        let row = &p[kr * nc..(kr + 1) * nc];
        for b in 0..w {
            let e = &ec[b * nc..(b + 1) * nc];
            a[kr * w + b] = row.iter().zip(e).map(|(x, y)| x * y).sum();
        }
    }
    let mut best = (f64::NEG_INFINITY, 0.0, 0.0);
    for ai in 0..w {
        let e = &er[ai * nr..(ai + 1) * nr];
        for b in 0..w {
            let v: Complex64 = (0..nr).map(|kr| e[kr] * a[kr * w + b]).sum();
            let v = sign * v.re;
            if v > best.0 {
                best = (v, at.0 as f64 + off(ai), at.1 as f64 + off(b));
            }
        }
    }
    (best.1, best.2)
}

/// Scan samples for the fit: `[x, y, z]` (positions from the scan's centre, metres) with a
/// stride so that at most about `limit` remain.
fn points(scan: &Grid, limit: usize) -> Vec<[f64; 3]> {
    let (nr, nc) = scan.dim();
    let n = scan.valid_count().max(1);
    let stride = ((n as f64 / limit.max(1) as f64).sqrt().ceil() as usize).max(1);
    let p = scan.pitch();
    let (ci, cj) = ((nr as f64 - 1.0) * 0.5, (nc as f64 - 1.0) * 0.5);
    let mut out = Vec::with_capacity(n / (stride * stride) + 1);
    for i in (0..nr).step_by(stride) {
        for j in (0..nc).step_by(stride) {
            if scan.is_valid(i, j) {
                out.push([(j as f64 - cj) * p[0], (i as f64 - ci) * p[1], scan.values()[[i, j]]]);
            }
        }
    }
    out
}

/// The parameters of the least-squares model: shift in design pixels, rotation, log scale and
/// the linear `(a, b, c_x, c_y)`.
#[derive(Debug, Clone, Copy)]
struct Params {
    t: [f64; 2],
    theta: f64,
    ln_s: f64,
    /// `(a, b, c_x, c_y, e)`: `e` weighs the design's Laplacian (first-order blur, `e = a sigma^2 / 2`).
    lin: [f64; 5],
}

impl Params {
    fn vec(&self) -> [f64; NP] {
        let l = self.lin;
        [self.t[0], self.t[1], self.theta, self.ln_s, l[0], l[1], l[2], l[3], l[4]]
    }
    fn from_vec(v: &[f64; NP]) -> Params {
        Params { t: [v[0], v[1]], theta: v[2], ln_s: v[3], lin: [v[4], v[5], v[6], v[7], v[8]] }
    }
}

/// Parameters of the least-squares model.
const NP: usize = 9;

struct Ctx<'a> {
    sampler: &'a Sampler<'a>,
    mirror: bool,
    /// Design pitch (shift unit).
    pd: [f64; 2],
    /// Binning factor of the sampler's grid relative to the design.
    g: f64,
}

/// Normal equations and moments over the points at one parameter set.
#[derive(Debug, Clone, Copy)]
struct Normal {
    n: f64,
    sse: f64,
    a: [f64; NP * NP],
    r: [f64; NP],
    /// Moments of (z - plane) and h: sums of z', z'^2, h, h^2, z' h.
    m: [f64; 5],
}

impl Normal {
    fn zero() -> Normal {
        Normal { n: 0.0, sse: 0.0, a: [0.0; NP * NP], r: [0.0; NP], m: [0.0; 5] }
    }
    fn add(&mut self, o: &Normal) {
        self.n += o.n;
        self.sse += o.sse;
        self.a.iter_mut().zip(&o.a).for_each(|(x, y)| *x += y);
        self.r.iter_mut().zip(&o.r).for_each(|(x, y)| *x += y);
        self.m.iter_mut().zip(&o.m).for_each(|(x, y)| *x += y);
    }
    fn mse(&self) -> f64 {
        if self.n > 0.0 {
            self.sse / self.n
        } else {
            f64::INFINITY
        }
    }
}

/// Points per chunk of [`accumulate`]: fixed, so that the sums are added in the same order
/// whatever the number of threads (the result is bit-identical on 1 or 64 cores).
const ACCUMULATE_CHUNK: usize = 8192;

/// The normal equations over all points: fixed chunks accumulated in parallel, then added in
/// chunk order. A worker that panics is reported as an error, never taken as zeros.
fn accumulate(ctx: &Ctx, pts: &[[f64; 3]], p: &Params, half: [f64; 2]) -> Result<Normal> {
    use rayon::prelude::*;
    let parts = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        pts.par_chunks(ACCUMULATE_CHUNK).map(|c| accumulate_chunk(ctx, c, p, half)).collect::<Vec<_>>()
    }))
    .map_err(|e| {
        let why = e
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| e.downcast_ref::<String>().cloned())
            .unwrap_or_else(|| "unknown cause".into());
        Error::Data(format!("registration: a worker accumulating the normal equations panicked ({why})"))
    })?;
    let mut total = Normal::zero();
    for q in &parts {
        total.add(q);
    }
    Ok(total)
}

fn accumulate_chunk(ctx: &Ctx, pts: &[[f64; 3]], p: &Params, half: [f64; 2]) -> Normal {
    let mut nm = Normal::zero();
    let s = p.ln_s.exp();
    let (sn, cs) = p.theta.sin_cos();
    let mx = if ctx.mirror { -1.0 } else { 1.0 };
    let t = [p.t[0] * ctx.pd[0], p.t[1] * ctx.pd[1]];
    let pitch = [ctx.pd[0] * ctx.g, ctx.pd[1] * ctx.g];
    let (ci, cj) = ((ctx.sampler.rows as f64 - 1.0) * 0.5, (ctx.sampler.cols as f64 - 1.0) * 0.5);
    let [a, b, cx, cy, e] = p.lin;
    let mut jac = [0.0; NP];
    for q in pts {
        let u = [(q[0] - t[0]) / s, (q[1] - t[1]) / s];
        let v = [cs * u[0] + sn * u[1], -sn * u[0] + cs * u[1]];
        let w = [mx * v[0], v[1]];
        let Some([h, hi, hj, l, li, lj]) = ctx.sampler.eval_lap(w[1] / pitch[1] + ci, w[0] / pitch[0] + cj)
        else {
            continue;
        };
        // Gradient (per metre) of the model's design term a h + e L.
        let (gx, gy) = ((a * hj + e * lj) / pitch[0], (a * hi + e * li) / pitch[1]);
        let (xn, yn) = (q[0] / half[0], q[1] / half[1]);
        let plane = b + cx * xn + cy * yn;
        let r = q[2] - a * h - e * l - plane;
        // d w / d t_x (per design pixel), d t_y, d theta, d ln s.
        let dtx = [-mx * cs / s * ctx.pd[0], sn / s * ctx.pd[0]];
        let dty = [-mx * sn / s * ctx.pd[1], -cs / s * ctx.pd[1]];
        let dth = [mx * v[1], -v[0]];
        let dls = [-w[0], -w[1]];
        jac[0] = gx * dtx[0] + gy * dtx[1];
        jac[1] = gx * dty[0] + gy * dty[1];
        jac[2] = gx * dth[0] + gy * dth[1];
        jac[3] = gx * dls[0] + gy * dls[1];
        jac[4] = h;
        jac[5] = 1.0;
        jac[6] = xn;
        jac[7] = yn;
        jac[8] = l;
        for k in 0..NP {
            nm.r[k] += jac[k] * r;
            for m in k..NP {
                nm.a[k * NP + m] += jac[k] * jac[m];
            }
        }
        nm.n += 1.0;
        nm.sse += r * r;
        let zp = q[2] - plane - e * l;
        nm.m[0] += zp;
        nm.m[1] += zp * zp;
        nm.m[2] += h;
        nm.m[3] += h * h;
        nm.m[4] += zp * h;
    }
    for k in 0..NP {
        for m in 0..k {
            nm.a[k * NP + m] = nm.a[m * NP + k];
        }
    }
    nm
}

/// Solves the damped, diagonally scaled normal equations for the free parameters.
fn lm_step(nm: &Normal, lambda: f64, free: &[usize]) -> Option<[f64; NP]> {
    let n = free.len();
    let d: Vec<f64> = free.iter().map(|&k| nm.a[k * NP + k].sqrt().max(1e-300)).collect();
    let mut a = vec![0.0; n * n];
    let mut r = vec![0.0; n];
    for (x, &k) in free.iter().enumerate() {
        r[x] = nm.r[k] / d[x];
        for (y, &l) in free.iter().enumerate() {
            a[x * n + y] = nm.a[k * NP + l] / (d[x] * d[y]);
        }
        a[x * n + x] += lambda;
    }
    let x = solve(&mut a, &mut r, n)?;
    let mut out = [0.0; NP];
    for (i, &k) in free.iter().enumerate() {
        out[k] = x[i] / d[i];
    }
    Some(out)
}

struct Fit {
    correlation: f64,
    rms: f64,
    sigma: [f64; NP],
    points: usize,
}

/// Levenberg-Marquardt on the eight parameters (step 4 of the module docs); `linear_first`: an
/// exact least-squares step of the linear parameters alone first (for a start whose heights are
/// not yet fitted).
fn refine(ctx: &Ctx, pts: &[[f64; 3]], p: &mut Params, radius_px: f64, linear_first: bool) -> Result<Fit> {
    // Plane slopes are fitted per metre (the normal equations are diagonally scaled).
    let half = [1.0, 1.0];
    // The linear parameters first, with the geometry fixed (exact least squares).
    let mut nm = accumulate(ctx, pts, p, half)?;
    if nm.n < 16.0 {
        return Err(Error::validity(
            Condition::Registration(Refusal::NoOverlap),
            "the scan and the design barely overlap at the coarse placement: nothing to refine",
        ));
    }
    let all: Vec<usize> = (0..NP).collect();
    if let Some(d) = lm_step(&nm, 0.0, &[4, 5, 6, 7, 8]).filter(|_| linear_first) {
        let mut v = p.vec();
        v.iter_mut().zip(&d).for_each(|(x, y)| *x += y);
        *p = Params::from_vec(&v);
        nm = accumulate(ctx, pts, p, half)?;
    }
    let mut lambda = 1e-3;
    for _ in 0..50 {
        let Some(d) = lm_step(&nm, lambda, &all) else { break };
        let mut v = p.vec();
        v.iter_mut().zip(&d).for_each(|(x, y)| *x += y);
        let q = Params::from_vec(&v);
        let nq = accumulate(ctx, pts, &q, half)?;
        if nq.n >= 16.0 && nq.mse() <= nm.mse() {
            *p = q;
            nm = nq;
            lambda = (lambda * 0.1).max(1e-9);
            let geo = d[0].abs().max(d[1].abs()).max((d[2].abs() + d[3].abs()) * radius_px);
            if geo < 1e-5 {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > 1e8 {
                break;
            }
        }
    }
    let n = nm.n;
    let [sz, szz, sh, shh, szh] = nm.m;
    let cov_zh = szh / n - sz * sh / (n * n);
    let var_z = szz / n - (sz / n).powi(2);
    let var_h = shh / n - (sh / n).powi(2);
    let correlation = (cov_zh / (var_z * var_h).sqrt()).abs();
    // Formal covariance sigma^2 (J^T J)^-1, column by column, solved on the diagonally scaled
    // matrix D^-1 (J^T J) D^-1 (the parameters' units differ by orders of magnitude) and scaled
    // back: (J^T J)^-1 = D^-1 (D^-1 J^T J D^-1)^-1 D^-1. NaN when the matrix is singular.
    let s2 = nm.sse / (n - NP as f64).max(1.0);
    let d: Vec<f64> = (0..NP).map(|k| nm.a[k * NP + k].sqrt().max(1e-300)).collect();
    let scaled: Vec<f64> = (0..NP * NP).map(|q| nm.a[q] / (d[q / NP] * d[q % NP])).collect();
    let mut sigma = [f64::NAN; NP];
    for (k, sk) in sigma.iter_mut().enumerate() {
        let mut a = scaled.clone();
        let mut e = vec![0.0; NP];
        e[k] = 1.0;
        if let Some(x) = solve(&mut a, &mut e, NP) {
            *sk = (s2 * x[k]).max(0.0).sqrt() / d[k];
        }
    }
    Ok(Fit {
        correlation: if correlation.is_finite() { correlation } else { 0.0 },
        rms: nm.mse().sqrt(),
        sigma,
        points: n as usize,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::design::{paper_example, ExampleParams, PAPER_PITCH};
    use crate::metrology::synthetic_scan::{simulate_scan, SimulateParams};

    /// The built-in design at its real pitch and grating period, cropped to `n` samples.
    fn paper(n: usize) -> Grid {
        let p = ExampleParams { samples: n, aperture: 0.9 * n as f64 * PAPER_PITCH, ..Default::default() };
        paper_example(&p).unwrap()
    }

    /// The accuracy goals: 20 nm noise, 2 um blur, 10% missing points; shift <= 0.02 px,
    /// rotation <= 0.01 deg, depth scale <= 0.5%.
    fn check_goals(mirror: bool, complement: bool, seed: u64) {
        let d = paper(320);
        let pose = Pose { mirror, rotation: 0.3f64.to_radians(), scale: 1.0, shift: [3.2e-6, -1.7e-6] };
        let sp = SimulateParams {
            blur: 2e-6,
            depth_scale: 0.95,
            offset: 0.2e-6,
            tilt: [1e-4, -0.5e-4],
            pose,
            complement,
            noise: 20e-9,
            missing: 0.1,
            seed,
            ..Default::default()
        };
        let s = simulate_scan(&d, &sp).unwrap();
        let r = register(&d, &s, &RegisterOptions::default()).unwrap();
        let e = [
            (r.pose.shift[0] - pose.shift[0]) / PAPER_PITCH,
            (r.pose.shift[1] - pose.shift[1]) / PAPER_PITCH,
        ];
        let rot = (r.pose.rotation - pose.rotation).to_degrees();
        let depth = r.depth_scale / 0.95 - 1.0;
        assert_eq!((r.pose.mirror, r.complement), (mirror, complement), "{r:?}");
        assert!(e[0].abs() <= 0.02 && e[1].abs() <= 0.02, "shift error {e:?} px; {r:?}");
        assert!(rot.abs() <= 0.01, "rotation error {rot} deg; {r:?}");
        assert!(depth.abs() <= 0.005, "depth scale error {depth}; {r:?}");
        assert!((r.pose.scale - 1.0).abs() < 1e-3 && r.correlation > 0.99, "{r:?}");
        assert!((r.tilt[0] - 1e-4).abs() < 2e-6 && (r.tilt[1] + 0.5e-4).abs() < 2e-6, "{r:?}");
        let hmax = d.min_max().unwrap().1;
        let offset = if complement { 0.2e-6 + 0.95 * hmax } else { 0.2e-6 };
        assert!((r.offset - offset).abs() < 5e-9, "{} vs {offset}", r.offset);
        assert!((r.blur - 2e-6).abs() < 0.5e-6, "{r:?}");
        // The formal standard errors exist (the normal equations are solved scaled) and are
        // below the accuracy goals.
        let sig = [r.shift_sigma[0], r.shift_sigma[1], r.rotation_sigma, r.scale_sigma, r.depth_scale_sigma];
        assert!(sig.iter().all(|s| s.is_finite() && *s > 0.0), "{sig:?}");
        assert!(r.shift_sigma[0] < 0.02 * PAPER_PITCH && r.rotation_sigma < 0.01f64.to_radians(), "{sig:?}");
    }

    #[test]
    fn accuracy_goals_on_a_mirrored_complemented_cast() {
        check_goals(true, true, 3);
    }

    #[test]
    fn accuracy_goals_on_the_master_side() {
        check_goals(false, false, 4);
    }

    #[test]
    fn pose_maps_round_trip() {
        let p = Pose { mirror: true, rotation: 0.7, scale: 1.1, shift: [1e-3, -2e-3] };
        let x = [3e-4, 5e-4];
        let y = p.scan_to_design(p.design_to_scan(x));
        assert!((x[0] - y[0]).abs() < 1e-15 && (x[1] - y[1]).abs() < 1e-15);
        assert!(Pose { scale: 0.0, ..p }.check().is_err());
    }

    fn grid(n: usize, f: impl Fn(f64, f64) -> f64) -> Grid {
        let c = (n as f64 - 1.0) * 0.5;
        let v = ndarray::Array2::from_shape_fn((n, n), |(i, j)| f(j as f64 - c, i as f64 - c));
        Grid::new(v, [PAPER_PITCH, PAPER_PITCH], crate::grid::Unit::Metre).unwrap()
    }

    /// The registration's refusal of a scan of `design` and its message.
    fn refusal(design: &Grid, sp: &SimulateParams) -> (Refusal, String) {
        let s = simulate_scan(design, sp).unwrap();
        match register(design, &s, &RegisterOptions::default()) {
            Err(Error::Validity { condition: Condition::Registration(r), what }) => (r, what),
            other => panic!("expected a refusal, got {other:?}"),
        }
    }

    #[test]
    fn a_grating_is_refused_as_periodic() {
        let tau = 2.0 * std::f64::consts::PI;
        let d = grid(256, |x, y| 0.3e-6 * ((tau * x / 32.0).cos() + (tau * y / 32.0).cos()));
        let pose = Pose { shift: [9.0 * PAPER_PITCH, 4.0 * PAPER_PITCH], ..Default::default() };
        let sp = SimulateParams { pose, noise: 5e-9, size: Some((180, 180)), ..Default::default() };
        let (r, m) = refusal(&d, &sp);
        assert!(r == Refusal::Ambiguous && m.contains("periodic"), "{m}");
    }

    #[test]
    fn a_rotationally_symmetric_design_is_refused() {
        let d = grid(256, |x, y| {
            let r = (x * x + y * y).sqrt();
            if r < 110.0 {
                0.4e-6 * (1.0 + (2.0 * std::f64::consts::PI * r * r / 4000.0).cos())
            } else {
                0.0
            }
        });
        let pose = Pose { shift: [5.5 * PAPER_PITCH, -2.0 * PAPER_PITCH], ..Default::default() };
        let (r, m) = refusal(&d, &SimulateParams { pose, noise: 5e-9, blur: 2e-6, ..Default::default() });
        assert!(r == Refusal::Ambiguous && m.contains("rotationally symmetric"), "{m}");
    }

    #[test]
    fn featureless_scans_are_refused() {
        let d = paper(200);
        let flat = grid(200, |x, _| 1e-6 + 1e-9 * x);
        let noisy = simulate_scan(&flat, &SimulateParams { noise: 20e-9, ..Default::default() }).unwrap();
        for s in [flat, noisy] {
            match register(&d, &s, &RegisterOptions::default()) {
                Err(Error::Validity {
                    condition: Condition::Registration(Refusal::Featureless),
                    what: m,
                }) => {
                    assert!(m.contains("featureless"), "{m}")
                }
                other => panic!("expected a refusal, got {other:?}"),
            }
        }
        let (r, m) = refusal(&grid(64, |_, _| 1e-6), &SimulateParams::default());
        assert!(r == Refusal::Featureless && m.contains("design is flat"), "{m}");
    }

    #[test]
    fn a_scan_of_another_part_does_not_match() {
        // Smooth random bumps (white noise blurred by 3 samples) against the built-in design.
        let mut rng = crate::rng::Lcg(11);
        let v = ndarray::Array2::from_shape_fn((200, 200), |_| 0.3e-6 * rng.normal());
        let other = Grid::new(v, [PAPER_PITCH, PAPER_PITCH], crate::grid::Unit::Metre).unwrap();
        let other = crate::grid::blur::gaussian_blur(&other, 3.0 * PAPER_PITCH).unwrap();
        let s = simulate_scan(&other, &SimulateParams { noise: 5e-9, ..Default::default() }).unwrap();
        match register(&paper(200), &s, &RegisterOptions::default()) {
            Err(Error::Validity { condition: Condition::Registration(Refusal::NoMatch), what: m }) => {
                assert!(m.contains("does not match"), "{m}")
            }
            other => panic!("expected a refusal, got {other:?}"),
        }
    }
}
