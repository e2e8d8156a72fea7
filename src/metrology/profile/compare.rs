//! The comparison of a profile with the design along a line ([`compare_profile`]): its options,
//! its result, the blur's golden-section search and profile-likelihood error, and the fit's
//! warnings.

use serde::Serialize;

use crate::error::{DataCause, Error, Refusal, Result};
use crate::grid::profile::Profile;
use crate::grid::{Grid, Unit};
use crate::metrology::scan_registration::{check_trust, noise_ceiling, TRUSTED_FRACTION};

use super::coarse::{coarse_search, fit_correlation, second_peak, CoarseMatch};
use super::levelling::{noise_estimate, profile_variance};
use super::line::{line_length_warning, LineSpec};
use super::model::{covariance, fit_table, linear_start, normal, refine, Ctx};
use super::steps::{step_heights, DesignIndex, LevelSteps, MAX_LEVELS};

/// Options of `compare_profile`.
#[derive(Debug, Clone, Serialize)]
pub struct ProfileOptions {
    /// Half-range of the coarse search along the line, metres: how well the profile's start is
    /// known on the part.
    pub along_search: f64,
    /// Half-range of the coarse search across the line, metres.
    pub across_search: f64,
    /// Refuse when a second correlation peak along the line reaches this fraction of the first.
    pub max_peak_ratio: f64,
    /// Refuse below this correlation between the profile and the design, at the coarse match
    /// and for the fitted model (a line has few independent features: a quasi-periodic design
    /// correlates by 0.5-0.6 with a profile along another direction).
    pub min_correlation: f64,
    /// Refuse below this fraction of the correlation the profile's own noise allows (the trust
    /// rule of every registration, `check_trust`).
    pub min_correlation_ratio: f64,
    /// Most profile points in the fit (a stride thins the rest).
    pub max_points: usize,
}

impl Default for ProfileOptions {
    fn default() -> Self {
        ProfileOptions {
            along_search: 50e-6,
            across_search: 10e-6,
            max_peak_ratio: 0.9,
            min_correlation: 0.8,
            min_correlation_ratio: TRUSTED_FRACTION,
            max_points: 20_000,
        }
    }
}

/// The comparison of a profile with its design along a line; lengths and heights in metres,
/// angles in radians, each `*_sigma` a standard error (1 sigma).
#[derive(Debug, Clone, Serialize)]
pub struct ProfileComparison {
    /// The line on the design, as given.
    pub line: LineSpec,
    /// Design position `[x, y]` of the profile's first point before registration, metres from
    /// the design's centre.
    pub line_start: [f64; 2],
    /// Unit direction `d = [d_x, d_y]` of the line in the design's (x, y) frame.
    pub line_direction: [f64; 2],
    /// Shift along the line `s`, metres (the profile's first point lies at
    /// `line_start + s d + v n`).
    pub along_shift: f64,
    /// Standard error of `along_shift`, metres.
    pub along_shift_sigma: f64,
    /// Offset across the line `v`, metres (towards `n = (-d_y, d_x)`).
    pub across_offset: f64,
    /// Standard error of `across_offset`, metres; `NaN` (`null` in JSON) when `across_fixed`.
    pub across_offset_sigma: f64,
    /// The across-line offset was unobservable and held at the coarse value.
    pub across_fixed: bool,
    /// Depth scale `|a|`: measured heights over the design's (1 = as designed).
    pub depth_scale: f64,
    /// Standard error of `depth_scale`.
    pub depth_scale_sigma: f64,
    /// `a < 0`: the part is the design's complement (a cast).
    pub complement: bool,
    /// `b`: measured height of the design's zero at the profile's middle (the mean position of
    /// the fitted points), metres.
    pub offset: f64,
    /// Standard error of `offset`, metres.
    pub offset_sigma: f64,
    /// `c`: remaining tilt along the line, height per length (dimensionless).
    pub tilt: f64,
    /// Standard error of `tilt` (dimensionless).
    pub tilt_sigma: f64,
    /// Gaussian lateral blur `sigma` of the process, metres.
    pub blur: f64,
    /// Standard error of `blur`, metres (from the profile likelihood where the blur is too
    /// small for its Jacobian column; infinite where that is flat).
    pub blur_sigma: f64,
    /// `blur_sigma < blur / 4`: the blur is resolved.
    pub blur_resolved: bool,
    /// Upper end of the blur's search, `3 max(pitch)` of the design, metres.
    pub blur_search_max: f64,
    /// RMS of the residual `sqrt(SSE / points)`, metres.
    pub rms_residual: f64,
    /// Profile points in the fit (on the design once registered).
    pub points: usize,
    /// Pearson correlation of the measured heights and the fitted model, both with their
    /// least-squares line removed.
    pub correlation: f64,
    /// The highest correlation the profile's own noise allows ([`noise_ceiling`]).
    pub noise_ceiling: f64,
    /// Second to first peak of the coarse correlation `|r|` along the line at the winning
    /// offset (0..1; 0 when there is no second peak, near 1 ambiguous).
    pub peak_ratio: f64,
    /// The per-level step heights; `None` when the design has more than [`MAX_LEVELS`]
    /// distinct heights (not multi-level).
    pub levels: Option<LevelSteps>,
    /// Warnings on the fit (unresolved blur, unobservable or poorly determined across-line
    /// offset, line shorter or longer than the profile, no per-level steps).
    pub warnings: Vec<String>,
    /// Profile position (metres, as in the file), measured and model heights at each fitted
    /// point (for plots and `profile_fit.csv`).
    #[serde(skip)]
    pub fit: Vec<[f64; 3]>,
}

/// Refuses a coarse match below `min_correlation` ([`Refusal::NoMatch`]) or one whose second
/// peak along the line reaches `max_peak_ratio` of the first ([`Refusal::Ambiguous`]); `along`
/// and `across` are the search half-widths, metres.
fn check_coarse_match(
    peak: f64,
    peak_ratio: f64,
    opts: &ProfileOptions,
    along: f64,
    across: f64,
) -> Result<()> {
    if peak < opts.min_correlation {
        return Err(Error::registration(
            Refusal::NoMatch,
            format!(
            "the profile does not match the design along the line: best correlation {peak:.3} (below {:.2}) \
             within +-{:.1} um along and +-{:.1} um across",
            opts.min_correlation,
            along * 1e6,
            across * 1e6
        ),
        ));
    }
    if peak_ratio > opts.max_peak_ratio {
        return Err(Error::registration(Refusal::Ambiguous, format!(
            "the shift along the line is ambiguous: a second correlation peak reaches {:.3} of the first within \
             +-{:.1} um (the design repeats along the line); narrow the search (`along_search`) or choose another line",
            peak_ratio,
            along * 1e6
        )));
    }
    Ok(())
}

/// Compares a profile (heights in metres) with the `design` (heights in metres) along `line`;
/// see the module docs.
///
/// Errors: a line that leaves the design, a featureless profile or design along the line, a
/// multi-level design of which the line crosses fewer than 2 levels (or whose terraces leave
/// fewer than 2 levels with interior points), and, as [`Error::Registration`], an ambiguous or
/// non-matching coarse search.
pub fn compare_profile(
    profile: &Profile,
    design: &Grid,
    line: &LineSpec,
    opts: &ProfileOptions,
) -> Result<ProfileComparison> {
    if design.unit() != Unit::Metre {
        return Err(Error::param(
            "design",
            format!("must hold heights in metres, not '{}'", design.unit().symbol()),
        ));
    }
    line.check()?;
    let mut warnings = Vec::new();
    let length = profile.length();
    let (start, dir) = line.frame(length);
    let nrm = [-dir[1], dir[0]];
    warnings.extend(line_length_warning(line, length));
    let pts = fit_points(profile, opts.max_points)?;
    let u_mean = pts.iter().map(|p| p.0).sum::<f64>() / pts.len() as f64;
    let pd = design.pitch();
    let pmax = pd[0].max(pd[1]);
    let along = opts.along_search.max(0.0);
    let across = opts.across_search.max(0.0);
    let sigma_max = 3.0 * pmax;
    let index = DesignIndex::new(design);
    // Crop of the design around the line (all shifts and offsets searched, plus the blur's reach).
    let reach = [-along, length + along, -across, across];
    let (crop, crop_centre) = index.crop_around_line(start, dir, reach, 4.0 * sigma_max + 3.0 * pmax)?;
    let ctx = Ctx { crop: &crop, crop_centre, pts: &pts, u_mean, start, dir, nrm };
    let sharp = ctx.blurred(0.0)?;
    if index.levels.is_some() {
        index.check_levels_on_line(&ctx)?;
    } else {
        warnings.push(format!(
            "the design has more than {MAX_LEVELS} distinct heights: no per-level step heights (compare with \
             the design quantized as a recipe makes it)"
        ));
    }
    let variance = profile_variance(&pts)?;
    // 1. Coarse search.
    let ds = 0.5 * pd[0].min(pd[1]);
    let ns = (along / ds).ceil() as i64;
    let coarse = coarse_search(&ctx, &sharp, ds, ns, (across / ds).ceil() as i64);
    if coarse.design_flat || coarse.peak <= 0.0 {
        let what = "the design is flat along the line (or the line leaves the design): nothing to register";
        return Err(Error::data(DataCause::Featureless, what));
    }
    let CoarseMatch { peak, along: is0, across: iv0, sign, .. } = coarse;
    let peak_ratio = second_peak(&coarse.row, (is0 + ns) as usize) / peak;
    check_coarse_match(peak, peak_ratio, opts, along, across)?;
    let (s0, v0) = (is0 as f64 * ds, iv0 as f64 * ds);
    let p = linear_start(&ctx, &sharp, [s0, v0, sign, 0.0, 0.0]);
    // Observability of the across-line offset.
    let nm = normal(&ctx, &sharp, &p);
    let across_fixed = nm.col2[1] < 0.02 * 0.02 * nm.col2[0];
    let free: Vec<usize> = if across_fixed { vec![0, 2, 3, 4] } else { vec![0, 1, 2, 3, 4] };
    if across_fixed {
        warnings.push(format!(
            "the design hardly varies across the line here: the across-line offset is unobservable and held at \
             {:.2} um",
            v0 * 1e6
        ));
    }
    // 2. Golden-section search of SSE(sigma), the geometry refined at each blur.
    let eval = |sigma: f64, p: &mut [f64; 5]| -> Result<(f64, usize)> {
        let b = ctx.blurred(sigma)?;
        Ok(refine(&ctx, &b, p, &free))
    };
    let mut p_best = p;
    eval(0.0, &mut p_best)?;
    let (sigma, mut p) = golden_section(sigma_max, 0.01 * pmax, p_best, |s, q| Ok(eval(s, q)?.0))?;
    let (sse, n) = eval(sigma, &mut p)?;
    if n < 10 {
        return Err(Error::data(
            DataCause::TooFew,
            format!("only {n} profile points fall on the design once registered"),
        ));
    }
    // 3. Uncertainty.
    let blurred = ctx.blurred(sigma)?;
    let h = 0.05 * pmax;
    let sse_at = |s: f64| -> Result<f64> {
        let mut q = p;
        Ok(eval(s, &mut q)?.0)
    };
    let np = free.len() + 1;
    let s2 = sse / (n as f64 - np as f64).max(1.0);
    let profile_blur_sigma = profile_likelihood_sigma(sse_at, sigma, h, sse, s2)?;
    // Jacobian with the blur column (central differences) where sigma allows it.
    let (errors, blur_sigma) = covariance(&ctx, &blurred, &p, &free, sigma, h, s2, profile_blur_sigma)?;
    let blur_resolved = blur_sigma < 0.25 * sigma;
    let across = (!across_fixed).then_some((p[1], errors[1]));
    warnings.extend(fit_warnings(sigma, blur_sigma, blur_resolved, sigma_max, pmax, across));
    // Fit table and correlation.
    let fit = fit_table(&ctx, &blurred, &p, profile.x()[0]);
    let correlation = fit_correlation(&fit);
    if correlation.is_nan() || correlation < opts.min_correlation {
        return Err(Error::registration(Refusal::NoMatch, format!(
            "the profile does not match the design along the line: the fitted model correlates by {correlation:.3} \
             (below {:.2}), residual {:.1} nm RMS",
            opts.min_correlation,
            (sse / n as f64).sqrt() * 1e9
        )));
    }
    let noise_ceiling = noise_ceiling(noise_estimate(profile), variance);
    check_trust("the profile's fit along the line", correlation, noise_ceiling, opts.min_correlation_ratio)?;
    // Per-level step heights.
    let levels = match &index.levels {
        None => None,
        Some(dl) => {
            let r = 2.0 * sigma + 1.5 * pmax;
            let heights = index.interior_heights(&ctx, &p, r);
            Some(step_heights(dl, &heights, r)?)
        }
    };
    Ok(ProfileComparison {
        line: *line,
        line_start: start,
        line_direction: dir,
        along_shift: p[0],
        along_shift_sigma: errors[0],
        across_offset: p[1],
        across_offset_sigma: if across_fixed { f64::NAN } else { errors[1] },
        across_fixed,
        depth_scale: p[2].abs(),
        depth_scale_sigma: errors[2],
        complement: p[2] < 0.0,
        offset: p[3],
        offset_sigma: errors[3],
        tilt: p[4],
        tilt_sigma: errors[4],
        blur: sigma,
        blur_sigma,
        blur_resolved,
        blur_search_max: sigma_max,
        rms_residual: (sse / n as f64).sqrt(),
        points: n,
        correlation,
        noise_ceiling,
        peak_ratio,
        levels,
        warnings,
        fit,
    })
}

/// The profile's measured points `(u, z)` for the fit, thinned by a stride to at most
/// `max_points`; fewer than 10 are refused.
pub(super) fn fit_points(profile: &Profile, max_points: usize) -> Result<Vec<(f64, f64)>> {
    let all = profile.points();
    let stride = all.len().div_ceil(max_points.max(1)).max(1);
    let pts: Vec<(f64, f64)> = all.iter().step_by(stride).copied().collect();
    if pts.len() < 10 {
        return Err(Error::data(
            DataCause::TooFew,
            format!("the profile has {} measured points: too few to compare", pts.len()),
        ));
    }
    Ok(pts)
}

/// Golden-section search of `f` over `[0, hi]` to a bracket narrower than `tol`: the bracket's
/// centre and the parameters of its better end. `f(x, p)` refines the parameters `p` it is
/// given (each new point starts from its neighbour's) and returns the value to minimise.
fn golden_section(
    hi: f64,
    tol: f64,
    start: [f64; 5],
    mut f: impl FnMut(f64, &mut [f64; 5]) -> Result<f64>,
) -> Result<(f64, [f64; 5])> {
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let (mut a, mut bnd) = (0.0, hi);
    let mut x1 = bnd - g * (bnd - a);
    let mut x2 = a + g * (bnd - a);
    let (mut p1, mut p2) = (start, start);
    let mut f1 = f(x1, &mut p1)?;
    let mut f2 = f(x2, &mut p2)?;
    while bnd - a > tol {
        if f1 <= f2 {
            bnd = x2;
            x2 = x1;
            f2 = f1;
            p2 = p1;
            x1 = bnd - g * (bnd - a);
            p1 = p2;
            f1 = f(x1, &mut p1)?;
        } else {
            a = x1;
            x1 = x2;
            f1 = f2;
            p1 = p2;
            x2 = a + g * (bnd - a);
            p2 = p1;
            f2 = f(x2, &mut p2)?;
        }
    }
    Ok((0.5 * (a + bnd), if f1 <= f2 { p1 } else { p2 }))
}

/// The blur's standard error from the profile likelihood, `sqrt(2 s2 / SSE''(sigma))`, with
/// `SSE''` by central differences of step `h` (forward ones where `sigma <= h`) of `sse_at`,
/// `sse` its value at `sigma`; infinite where `SSE''` is not positive.
fn profile_likelihood_sigma(
    sse_at: impl Fn(f64) -> Result<f64>,
    sigma: f64,
    h: f64,
    sse: f64,
    s2: f64,
) -> Result<f64> {
    let curv = if sigma > h {
        (sse_at(sigma + h)? - 2.0 * sse + sse_at(sigma - h)?) / (h * h)
    } else {
        (sse_at(sigma + 2.0 * h)? - 2.0 * sse_at(sigma + h)? + sse) / (h * h)
    };
    Ok(if curv > 0.0 { (2.0 * s2 / curv).sqrt() } else { f64::INFINITY })
}

/// The warnings on the fitted blur `sigma` (its standard error `blur_sigma`, whether that
/// resolves it, the search's end `sigma_max`, the design's pitch `pmax`) and, when observable,
/// on the across-line offset and its standard error.
fn fit_warnings(
    sigma: f64,
    blur_sigma: f64,
    blur_resolved: bool,
    sigma_max: f64,
    pmax: f64,
    across: Option<(f64, f64)>,
) -> Vec<String> {
    let mut warnings = Vec::new();
    if !blur_resolved {
        let err = if blur_sigma < sigma_max {
            format!("+- {:.2} um", blur_sigma * 1e6)
        } else {
            format!("with a standard error beyond the {:.2} um search range", sigma_max * 1e6)
        };
        warnings.push(format!(
            "the lateral blur is not resolved: {:.2} um {err} against the design's {:.2} um pitch",
            sigma * 1e6,
            pmax * 1e6
        ));
    }
    if sigma >= 0.98 * sigma_max {
        warnings.push(format!(
            "the fitted blur sits at the end of its search range ({:.2} um): the part is blurred more than the model \
             can follow, or does not match the design along the line",
            sigma_max * 1e6
        ));
    }
    if let Some((v, error)) = across.filter(|a| a.1 > pmax) {
        warnings.push(format!(
            "the across-line offset is poorly determined: {:.2} +- {:.2} um",
            v * 1e6,
            error * 1e6
        ));
    }
    warnings
}

#[cfg(test)]
mod tests {
    use ndarray::Array2;

    use super::*;
    use crate::metrology::profile::simulate::tests::{sim, staircase};
    use crate::metrology::profile::simulate::{simulate_profile, SimulateProfile};

    #[test]
    fn a_simulated_staircase_profile_is_recovered() {
        let d = staircase();
        let (sp, prof) = sim(&d, 0.9, 3.3e-6, 4.1e-6, 3);
        let c = compare_profile(&prof, &d, &sp.line, &ProfileOptions::default()).unwrap();
        let within = |name: &str, got: f64, want: f64, sig: f64, tol: f64| {
            assert!(
                (got - want).abs() <= 4.0 * sig && (got - want).abs() <= tol,
                "{name}: {got} vs {want} (sigma {sig}, tol {tol}); {c:#?}"
            );
        };
        within("along", c.along_shift, 3.3e-6, c.along_shift_sigma, 0.1e-6);
        within("across", c.across_offset, 4.1e-6, c.across_offset_sigma, 0.3e-6);
        within("depth", c.depth_scale, 0.9, c.depth_scale_sigma, 0.009);
        within("blur", c.blur, 2e-6, c.blur_sigma, 0.2e-6);
        within("tilt", c.tilt, 2e-4, c.tilt_sigma, 1e-5);
        within("offset", c.offset, 40e-9, c.offset_sigma, 2e-9);
        assert!(!c.complement && !c.across_fixed);
        eprintln!(
            "staircase: along {:.4} +- {:.4} um, across {:.4} +- {:.4} um, depth {:.5} +- {:.5}, blur {:.4} +- {:.4} um, \
             tilt {:.3e} +- {:.1e}, offset {:.3} +- {:.3} nm, rms {:.3} nm",
            c.along_shift * 1e6, c.along_shift_sigma * 1e6, c.across_offset * 1e6, c.across_offset_sigma * 1e6,
            c.depth_scale, c.depth_scale_sigma, c.blur * 1e6, c.blur_sigma * 1e6, c.tilt, c.tilt_sigma,
            c.offset * 1e9, c.offset_sigma * 1e9, c.rms_residual * 1e9
        );
        for s in &c.levels.as_ref().unwrap().levels {
            eprintln!(
                "  level {} ({} pts): step {:?} +- {:?}, ratio {:?} +- {:?}",
                s.level, s.points, s.step_height, s.step_height_sigma, s.depth_scale, s.depth_scale_sigma
            );
        }
        let l = c.levels.as_ref().unwrap();
        assert_eq!(l.levels.len(), 4, "{l:#?}");
        for s in &l.levels[1..] {
            let ds = s.depth_scale.unwrap();
            assert!(
                (ds - 0.9).abs() < 0.01 && (ds - 0.9).abs() < 5.0 * s.depth_scale_sigma.unwrap(),
                "{s:?}"
            );
        }
        assert!((c.rms_residual - 5e-9).abs() < 0.5e-9, "{}", c.rms_residual);
    }

    #[test]
    fn the_complement_is_detected_and_one_level_lines_refused() {
        let d = staircase();
        let (sp, prof) = sim(&d, -0.9, -2.0e-6, 1.0e-6, 5);
        let c = compare_profile(&prof, &d, &sp.line, &ProfileOptions::default()).unwrap();
        assert!(c.complement && (c.depth_scale - 0.9).abs() < 0.01, "{c:#?}");
        let l = c.levels.as_ref().unwrap();
        assert!(l.levels[1..].iter().all(|s| (s.depth_scale.unwrap() - 0.9).abs() < 0.01), "{l:#?}");
        // A line along y inside one terrace column crosses one level only.
        let line = LineSpec::Points { start: [-21e-6, -100e-6], end: [-21e-6, 100e-6] };
        let flat = Grid::new(
            Array2::from_shape_fn((300, 300), |(_, j)| if j < 150 { 0.0 } else { 1e-7 }),
            [2e-6; 2],
            Unit::Metre,
        )
        .unwrap();
        let sp1 = SimulateProfile { line, length: 200e-6, ..sp.clone() };
        let p1 = simulate_profile(&flat, &sp1).unwrap();
        let e = compare_profile(&p1, &flat, &line, &ProfileOptions::default()).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::Featureless, .. }), "{e:?}");
    }

    /// A part with one level made 180 nm too high (above the next) correlates below 0.95 with
    /// the design along the line: above the absolute floor of 0.8, below 95% of what its 5 nm
    /// of noise allow: not trusted, the rule of every registration ([`check_trust`]).
    #[test]
    fn a_profile_fitting_worse_than_its_noise_allows_is_not_trusted() {
        let d = staircase();
        let wrong = d.values().mapv(|h| if (h - 200e-9).abs() < 1e-12 { 380e-9 } else { h });
        let wrong = d.map_values(wrong, Unit::Metre).unwrap();
        let (sp, prof) = sim(&wrong, 0.9, 3.3e-6, 4.1e-6, 3);
        let e = compare_profile(&prof, &d, &sp.line, &ProfileOptions::default()).unwrap_err();
        assert!(matches!(e, Error::Registration { refusal: Refusal::NotTrusted, .. }), "{e:?}");
        let lenient = ProfileOptions { min_correlation_ratio: 0.0, ..Default::default() };
        let c = compare_profile(&prof, &d, &sp.line, &lenient).unwrap();
        assert!(c.correlation > 0.8 && c.correlation < 0.95 * c.noise_ceiling, "{c:#?}");
        // The right design passes the same rule.
        let (sp, prof) = sim(&d, 0.9, 3.3e-6, 4.1e-6, 3);
        let c = compare_profile(&prof, &d, &sp.line, &ProfileOptions::default()).unwrap();
        assert!(c.correlation > 0.99 && c.noise_ceiling > 0.99, "{c:#?}");
    }

    #[test]
    fn a_shift_searched_over_a_period_is_ambiguous() {
        // The staircase repeats every 160 um along the line: a +-200 um search sees it twice.
        let d = staircase();
        let (sp, prof) = sim(&d, 0.9, 3.3e-6, 0.0, 7);
        let opts = ProfileOptions { along_search: 200e-6, ..Default::default() };
        let e = compare_profile(&prof, &d, &sp.line, &opts).unwrap_err();
        assert!(matches!(e, Error::Registration { refusal: Refusal::Ambiguous, .. }), "{e:?}");
    }

    #[test]
    fn line_text_and_featureless_profiles() {
        let close = |text: &str, want: [f64; 4]| {
            let LineSpec::Points { start, end } = LineSpec::parse_points(text).unwrap() else { panic!() };
            let got = [start[0], start[1], end[0], end[1]];
            assert!(got.iter().zip(&want).all(|(g, w)| (g - w).abs() < 1e-15), "{text}: {got:?}");
        };
        close("-1mm, 0, 1mm, 20um", [-1e-3, 0.0, 1e-3, 20e-6]);
        close("-100,0,100,5um", [-100e-6, 0.0, 100e-6, 5e-6]);
        assert!(LineSpec::parse_points("1,2,3").is_err());
        assert!(LineSpec::parse_points("0,0,0,0").is_err());
        let d = staircase();
        let mut rng = crate::rng::Lcg(1);
        let x: Vec<f64> = (0..800).map(|k| k as f64 * 0.5e-6).collect();
        let z: Vec<f64> = (0..800).map(|_| 5e-9 * rng.normal()).collect();
        let p = Profile::new(x, z, None).unwrap();
        let e =
            compare_profile(&p, &d, &LineSpec::Angle { angle: 0.0 }, &ProfileOptions::default()).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::Featureless, .. }), "{e:?}");
    }

    #[test]
    fn golden_section_finds_a_parabola_minimum_and_keeps_its_parameters() {
        let (x, p) = golden_section(1.0, 1e-7, [0.0; 5], |x, p| {
            p[0] = x;
            Ok((x - 0.37).powi(2))
        })
        .unwrap();
        assert!((x - 0.37).abs() < 1e-7 && (p[0] - x).abs() < 1e-7, "{x} {p:?}");
        // A minimum at the end of the range.
        let (x, _) = golden_section(2.0, 1e-6, [0.0; 5], |x, _| Ok(-x)).unwrap();
        assert!((x - 2.0).abs() < 1e-6, "{x}");
    }

    /// On `SSE(x) = c (x - x0)^2 + m`, `SSE'' = 2 c` on either difference, so the error is
    /// `sqrt(s2 / c)`; a flat or concave SSE gives an infinite error.
    #[test]
    fn the_profile_likelihood_error_of_a_parabolic_sse() {
        let (c, x0, m, s2) = (4.0e12, 1.1e-6, 3e-15, 2e-17);
        let sse = |x: f64| -> Result<f64> { Ok(c * (x - x0).powi(2) + m) };
        for sigma in [2e-6, 0.05e-6] {
            let got = profile_likelihood_sigma(sse, sigma, 0.1e-6, sse(sigma).unwrap(), s2).unwrap();
            assert!((got / (s2 / c).sqrt() - 1.0).abs() < 1e-6, "{sigma}: {got}");
        }
        let flat = |_: f64| -> Result<f64> { Ok(m) };
        assert_eq!(profile_likelihood_sigma(flat, 2e-6, 0.1e-6, m, s2).unwrap(), f64::INFINITY);
    }
}
