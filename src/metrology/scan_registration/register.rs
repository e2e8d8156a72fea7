//! The registration of a scan to a design ([`register`]) and its result ([`Registration`]): the
//! coarse search, the refinement and the checks that refuse a registration not to be trusted
//! (periodic, rotationally symmetric, featureless, unobservable).

use std::borrow::Cow;

use serde::Serialize;

use crate::error::{Condition, DataCause, Error, Refusal, Result};
use crate::grid::Grid;

use super::binning::{bin, level_img};
use super::coarse::{coarse_search, COARSE_SIDE};
use super::options::RegisterOptions;
use super::pose::Pose;
use super::refine::{points, refine, Ctx, Params};
use super::sampler::Sampler;
use super::trust::{check_trust, noise_ceiling};

/// The registration of a scan to a design; see the module docs for the model.
#[derive(Debug, Clone, Serialize)]
pub struct Registration {
    /// Where the design lies on the scan: shift, rotation, scale and mirror.
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
    /// Formal standard error of the shift `[x, y]`, metres, from `sigma^2 (J^T J)^-1` (white
    /// residuals assumed, so a lower bound where the residual is dominated by model error); NaN
    /// (`null` in JSON) where the normal equations are singular, as for the errors below.
    pub shift_sigma: [f64; 2],
    /// Formal standard error of the rotation, radians.
    pub rotation_sigma: f64,
    /// Formal standard error of the scale (dimensionless; that of `ln s` times `s`).
    pub scale_sigma: f64,
    /// Formal standard error of the depth scale (dimensionless).
    pub depth_scale_sigma: f64,
    /// Scan samples in the final fit.
    pub points: usize,
    /// Coarse pitch of the search, metres.
    pub coarse_pitch: f64,
}

/// Registers `scan` (heights, metres) to `design` (heights, metres); see the module docs:
/// `register_pose`, then `check_registration`.
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
                    .map_err(|e| Error::internal(e.to_string()))?;
            let v = ndarray::Array2::from_shape_vec((img.rows, img.cols), img.v)
                .map_err(|e| Error::internal(e.to_string()))?;
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
    let fit = fit.ok_or_else(|| Error::internal("no refinement level ran"))?;
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
    let (lo, hi) =
        design.min_max().ok_or_else(|| Error::data(DataCause::Empty, "the design has no valid sample"))?;
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
                Err(Error::Validity { condition: Condition::Registration(Refusal::Featureless), .. }) => {}
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
            Err(Error::Validity { condition: Condition::Registration(Refusal::NoMatch), .. }) => {}
            other => panic!("expected a refusal, got {other:?}"),
        }
    }
}
