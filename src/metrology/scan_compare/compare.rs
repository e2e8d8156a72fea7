//! The comparison of a scan with its design ([`compare`], [`compare_family`]) and its result
//! ([`Comparison`]): registration to each member, the difference map, level statistics, the
//! fabrication model and the efficiency loss.

use serde::Serialize;

use crate::error::{Condition, DataCause, Error, Refusal, Result};
use crate::grid::{Grid, Unit};
use crate::metrology::scan_registration::{check_registration, Registration};

use super::efficiency::{efficiency_loss, EfficiencyLoss};
use super::fab_model::{fit_model, FabModel};
use super::family::{register_family, scan_of, Candidate, Member, Reference};
use super::interior::{check_interior, interior_correlation, INTERIOR};
use super::levels::{level_stats, LevelHeights};
use super::options::CompareOptions;
use super::surface::{aperture_errors, design_frame};

/// Everything [`compare`] finds; heights and lengths in metres.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    /// The member of the design's family the scan matched best.
    pub member: Member,
    /// What the scan shows (`scan_of`): "the master", "the cast of the master", ...
    pub scan_of: String,
    /// Every member the scan was registered to, with the correlation it reached.
    pub candidates: Vec<Candidate>,
    /// The member's surface the part is compared with (design grid, metres).
    #[serde(skip)]
    pub reference: Grid,
    /// The registration of the scan to the member.
    pub registration: Registration,
    /// Correlation coefficient of the part and the design over the central `INTERIOR` of the
    /// aperture (the aperture's edge left out): the confidence that the scan shows this design.
    pub interior_correlation: f64,
    /// The as-fabricated surface on the design grid (invalid: not measured or outside the scan).
    #[serde(skip)]
    pub surface: Grid,
    /// `surface - design` over the aperture (invalid elsewhere).
    #[serde(skip)]
    pub difference: Grid,
    /// Aperture diameter used, metres.
    pub aperture: f64,
    /// Fraction of the aperture's design samples inside the scan's footprint once registered
    /// (0..1).
    pub coverage: f64,
    /// Fraction of the aperture's design samples where the surface is measured (0..1).
    pub measured_fraction: f64,
    /// Mean of the difference over the measured aperture, metres.
    pub mean_error: f64,
    /// RMS of the difference over the measured aperture, metres.
    pub rms_error: f64,
    /// Peak-to-valley of the difference over the measured aperture, metres.
    pub pv_error: f64,
    /// The per-level statistics; `None` for a reference without quantization (continuous).
    pub levels: Option<LevelHeights>,
    /// The fabrication model fitted on the scan.
    pub model: FabModel,
    /// The design order's predicted efficiency with the fitted depth scale, one per wavelength
    /// of [`crate::material::PAPER_WAVELENGTHS`].
    pub efficiency: Vec<EfficiencyLoss>,
    /// Warnings on the result (a blur that is no figure to correct, a design that is not
    /// quantized to the levels given).
    pub warnings: Vec<String>,
}

/// Compares `scan` (heights, metres) with `design` (heights, metres) taken as it is
/// ([`Member::Design`], quantized as `opts.levels` says); see `compare_family`.
pub fn compare(design: &Grid, scan: &Grid, opts: &CompareOptions) -> Result<Comparison> {
    let reference = Reference { member: Member::Design, surface: design.clone(), levels: opts.levels };
    compare_family(std::slice::from_ref(&reference), scan, opts)
}

/// Compares `scan` (heights, metres) with the member of `family` it matches best (module
/// docs): registered to each, the best correlation is judged
/// (`check_registration`) and the part compared with that member. All members share the
/// design grid. Ties go to the member listed first.
///
/// Errors: a scan whose footprint is smaller than the aperture, or that covers less than
/// `min_coverage` of it once registered; a registration that is refused (no match, ambiguous,
/// featureless, not trusted), or whose part correlates with the member inside the aperture by
/// less than the registration's `min_correlation` or than the scan's noise allows, is returned
/// as [`Error::Registration`].
pub fn compare_family(family: &[Reference], scan: &Grid, opts: &CompareOptions) -> Result<Comparison> {
    let first =
        family.first().ok_or_else(|| Error::param("family", "no reference surface to compare with"))?;
    for (name, g) in family.iter().map(|r| ("design", &r.surface)).chain([("scan", scan)]) {
        if g.unit() != Unit::Metre {
            return Err(Error::param(
                name,
                format!("must hold heights in metres, not '{}'", g.unit().symbol()),
            ));
        }
        if name == "design" && (g.dim() != first.surface.dim() || g.pitch() != first.surface.pitch()) {
            return Err(Error::param("family", "the reference surfaces must share the design grid"));
        }
    }
    let design = &first.surface;
    let de = design.extent();
    let aperture = opts.aperture.unwrap_or(de[0].min(de[1]));
    if !(aperture.is_finite() && aperture > 0.0) || aperture > de[0].min(de[1]) * (1.0 + 1e-9) {
        return Err(Error::param(
            "aperture",
            format!(
                "{aperture:e} m: expected a positive diameter within the {:.3} x {:.3} mm design",
                de[0] * 1e3,
                de[1] * 1e3
            ),
        ));
    }
    let se = scan.extent();
    if se[0].min(se[1]) < aperture {
        return Err(Error::data(
            DataCause::TooFew,
            format!(
                "the scan ({:.3} x {:.3} mm, {} x {} samples) is smaller than the {:.3} mm aperture it \
             should cover; scan the whole aperture or pass a smaller aperture",
                se[0] * 1e3,
                se[1] * 1e3,
                scan.dim().1,
                scan.dim().0,
                aperture * 1e3
            ),
        ));
    }
    let as_registration = |e| match e {
        Error::Validity { condition: Condition::Registration(refusal), what } => {
            Error::Registration { refusal, what }
        }
        other => other,
    };
    let (tried, best, first_error) = register_family(family, scan, &opts.register);
    let Some((k, reg)) = best else {
        return Err(as_registration(
            first_error
                .unwrap_or_else(|| Error::data(DataCause::Empty, "no reference surface was registered")),
        ));
    };
    let named = |m: String| {
        if family.len() > 1 {
            let searched: Vec<String> =
                tried.iter().map(|c| format!("{} {:.3}", c.member.name(), c.correlation)).collect();
            format!("{m} (best of the design's family: {})", searched.join(", "))
        } else {
            m
        }
    };
    check_registration(&reg, &opts.register).map_err(|e| match as_registration(e) {
        Error::Registration { refusal, what } => Error::Registration { refusal, what: named(what) },
        other => other,
    })?;
    let Reference { member, surface: reference, levels } = family[k].clone();
    let design = &reference;
    let mut warnings = Vec::new();
    let (surface, inside, coverage) = design_frame(design, scan, &reg, aperture)?;
    if coverage < opts.min_coverage {
        return Err(Error::data(
            DataCause::TooFew,
            format!(
                "the registered scan covers only {:.1}% of the {:.3} mm aperture (at least {:.0}% needed): \
             the scan is smaller than the aperture or off its centre",
                coverage * 100.0,
                aperture * 1e3,
                opts.min_coverage * 100.0
            ),
        ));
    }
    let interior_correlation = interior_correlation(design, &surface, aperture);
    if interior_correlation.is_nan() || interior_correlation < opts.register.min_correlation {
        return Err(Error::registration(
            Refusal::NoMatch,
            format!(
            "the scan does not match the design inside the aperture: correlation {interior_correlation:.3} \
             over the central {:.0}% of the aperture is below {:.2} (the registration correlation of {:.3} \
             comes from the aperture's edge or the overall shape, not the design's structure)",
            100.0 * INTERIOR,
            opts.register.min_correlation,
            reg.correlation
        ),
        ));
    }
    check_interior(interior_correlation, reg.noise_ceiling, opts.register.min_correlation_ratio).map_err(
        |e| match e {
            Error::Registration { refusal, what } => Error::Registration { refusal, what: named(what) },
            other => other,
        },
    )?;
    let errors = aperture_errors(design, &surface, &inside)?;
    let model = fit_model(design, scan, &reg, opts)?;
    warnings.extend(model.blur_doubt());
    let levels = levels.map(|l| level_stats(design, &surface, &inside, l, model.blur)).transpose()?;
    if let Some(l) = &levels {
        if l.design_off_level > 0.05 {
            warnings.push(format!(
                "the design is not quantized to {} levels of {:.2} nm (a height lies {:.2} steps from its \
                 level): the level statistics bin a continuous design",
                l.count,
                l.step * 1e9,
                l.design_off_level
            ));
        }
    }
    let efficiency = efficiency_loss(&opts.optics, levels.as_ref().map(|l| l.count), model.depth_scale)?;
    Ok(Comparison {
        member,
        scan_of: scan_of(member, reg.pose.mirror, reg.complement),
        candidates: tried,
        registration: reg,
        interior_correlation,
        surface,
        difference: errors.difference,
        aperture,
        coverage,
        measured_fraction: errors.measured_fraction,
        mean_error: errors.mean,
        rms_error: errors.rms,
        pv_error: errors.pv,
        levels,
        model,
        efficiency,
        warnings,
        reference,
    })
}

#[cfg(test)]
pub(super) mod tests {
    use ndarray::Array2;

    use super::*;
    use crate::design::{paper_example, ExampleParams, PAPER_PITCH};
    use crate::grid::blur::gaussian_blur;
    use crate::metrology::scan_compare::levels::LevelSpec;
    use crate::metrology::scan_registration::Pose;
    use crate::metrology::synthetic_scan::{simulate_scan, SimulateParams};

    /// The built-in design at its real pitch and grating period, `n` samples, aperture 0.9 n.
    pub(crate) fn paper(n: usize) -> Grid {
        let p = ExampleParams { samples: n, aperture: 0.9 * n as f64 * PAPER_PITCH, ..Default::default() };
        paper_example(&p).unwrap()
    }

    pub(crate) fn goals_params(seed: u64) -> SimulateParams {
        SimulateParams { offset: 0.2e-6, seed, ..SimulateParams::typical_cast() }
    }

    /// The accuracy goals on a synthetic cast (20 nm noise, 2 um blur, 10% missing):
    /// shift <= 0.02 px, rotation <= 0.01 deg, depth scale <= 0.5%; the fabrication model
    /// recovers the blur within 0.15 um and the depth scale within 0.5%.
    #[test]
    fn a_synthetic_cast_is_recovered_within_the_accuracy_goals() {
        let d = paper(300);
        let sp = goals_params(9);
        let scan = simulate_scan(&d, &sp).unwrap();
        let opts = CompareOptions { aperture: Some(0.8 * 300.0 * PAPER_PITCH), ..Default::default() };
        let c = compare(&d, &scan, &opts).unwrap();
        let r = &c.registration;
        let e = [(r.pose.shift[0] - 3.2e-6) / PAPER_PITCH, (r.pose.shift[1] + 1.7e-6) / PAPER_PITCH];
        assert!(e[0].abs() <= 0.02 && e[1].abs() <= 0.02, "shift error {e:?} px");
        assert!((r.pose.rotation.to_degrees() - 0.3).abs() <= 0.01, "{r:?}");
        assert!((r.depth_scale / 0.95 - 1.0).abs() <= 0.005, "{r:?}");
        let m = &c.model;
        assert!(m.complement, "{m:?}");
        assert!((m.depth_scale / 0.95 - 1.0).abs() <= 0.005, "{m:?}");
        assert!((m.blur - 2e-6).abs() <= 0.15e-6, "{m:?}");
        assert!(m.blur_resolved && m.blur_sigma < 0.1e-6, "{m:?}");
        // Offset of the complement: z = -k h + k max(h) + b.
        let hmax = d.min_max().unwrap().1;
        assert!((m.offset - (0.2e-6 + 0.95 * hmax)).abs() < 5e-9, "{m:?}");
        // Residual: the noise (20 nm) and nothing else.
        assert!((m.rms_residual / 20e-9 - 1.0).abs() < 0.05, "{m:?}");
        assert!(c.coverage > 0.999 && c.warnings.is_empty(), "{:?}", c.warnings);
    }

    /// A quantized design (8 levels of 150 nm, a 2-D staircase) made 10% too shallow, with an
    /// offset and 5 nm noise, no blur and no misplacement.
    pub(crate) fn staircase() -> (Grid, LevelSpec) {
        let n = 240;
        let step = 150e-9;
        let c = (n as f64 - 1.0) * 0.5;
        let v = Array2::from_shape_fn((n, n), |(i, j)| {
            let (x, y) = (j as f64 - c, i as f64 - c);
            let t = (x * 0.7 + y * 0.3) / 23.0 + (x * y / 900.0).sin() * 1.5 + (y / 17.0).cos();
            (t.rem_euclid(8.0)).floor() * step
        });
        (Grid::new(v, [PAPER_PITCH; 2], Unit::Metre).unwrap(), LevelSpec { count: 8, step })
    }

    #[test]
    fn difference_and_level_statistics_of_a_shallow_staircase() {
        let (d, levels) = staircase();
        let sp =
            SimulateParams { depth_scale: 0.9, offset: 40e-9, noise: 5e-9, seed: 3, ..Default::default() };
        let scan = simulate_scan(&d, &sp).unwrap();
        let aperture = 0.9 * d.extent()[0];
        let opts = CompareOptions { aperture: Some(aperture), levels: Some(levels), ..Default::default() };
        let c = compare(&d, &scan, &opts).unwrap();
        // The difference is -0.1 h plus noise: its RMS over the aperture follows from the design.
        let (mut n, mut s2, mut lo, mut hi) = (0.0, 0.0, f64::INFINITY, f64::NEG_INFINITY);
        for ((i, j), h) in d.values().indexed_iter() {
            let x = [
                d.x(j) - d.x(0) - 0.5 * (d.extent()[0] - d.pitch()[0]),
                d.y(i) - d.y(0) - 0.5 * (d.extent()[1] - d.pitch()[1]),
            ];
            if x[0] * x[0] + x[1] * x[1] <= 0.25 * aperture * aperture {
                let e = -0.1 * h;
                n += 1.0;
                s2 += e * e;
                lo = lo.min(e);
                hi = hi.max(e);
            }
        }
        let want = (s2 / n + 5e-9f64.powi(2)).sqrt();
        assert!((c.rms_error / want - 1.0).abs() < 0.02, "{} vs {want}", c.rms_error);
        assert!((c.pv_error - (hi - lo)).abs() < 50e-9, "{} vs {}", c.pv_error, hi - lo);
        assert!(c.measured_fraction > 0.999);
        let l = c.levels.as_ref().unwrap();
        assert_eq!(l.design_off_level, 0.0);
        assert_eq!(l.step_heights.len(), 7);
        for st in &l.levels {
            assert!(st.samples > 200, "{st:?}");
            // Means at 0.9 l step (the fitted offset takes the 40 nm), spread = the noise.
            assert!((st.mean - 0.9 * st.design_height).abs() < 2e-9, "{st:?}");
            assert!((st.std / 5e-9 - 1.0).abs() < 0.15, "{st:?}");
        }
        assert!((l.mean_step / (0.9 * 150e-9) - 1.0).abs() < 0.01 && l.step_std < 2e-9, "{l:?}");
        assert!((c.model.depth_scale - 0.9).abs() < 0.002, "{:?}", c.model);
    }

    #[test]
    fn a_scan_smaller_than_the_aperture_is_refused() {
        let d = paper(200);
        let sp = SimulateParams { size: Some((120, 120)), ..Default::default() };
        let scan = simulate_scan(&d, &sp).unwrap();
        let opts = CompareOptions { aperture: Some(0.9 * d.extent()[0]), ..Default::default() };
        match compare(&d, &scan, &opts) {
            Err(Error::Data { cause: DataCause::TooFew, what }) => {
                assert!(what.contains("smaller than the"), "{what}")
            }
            other => panic!("expected a refusal, got {other:?}"),
        }
        // Large enough but off centre: the registered footprint misses part of the aperture.
        // (A 190-sample scan 25 samples off centre degrades the registration itself, 0.14
        // samples and 0.03 deg off at a correlation of 0.85 on a noise-free scan, and is refused
        // as not trusted.)
        let sp = SimulateParams {
            size: Some((200, 200)),
            pose: Pose { shift: [25.0 * PAPER_PITCH, 0.0], ..Default::default() },
            ..Default::default()
        };
        let scan = simulate_scan(&d, &sp).unwrap();
        let opts = CompareOptions { aperture: Some(0.85 * d.extent()[0]), ..Default::default() };
        match compare(&d, &scan, &opts) {
            Err(Error::Data { cause: DataCause::TooFew, what }) => {
                assert!(what.contains("covers only"), "{what}")
            }
            other => panic!("expected a refusal, got {other:?}"),
        }
    }

    #[test]
    fn a_scan_of_another_part_is_a_registration_error() {
        let mut rng = crate::rng::Lcg(11);
        let v = Array2::from_shape_fn((200, 200), |_| 0.3e-6 * rng.normal());
        let other = Grid::new(v, [PAPER_PITCH; 2], Unit::Metre).unwrap();
        let other = gaussian_blur(&other, 3.0 * PAPER_PITCH).unwrap();
        match compare(&paper(200), &other, &CompareOptions::default()) {
            Err(Error::Registration { refusal: Refusal::NoMatch, .. }) => {}
            other => panic!("expected a registration error, got {other:?}"),
        }
    }

    /// Different x and y pitches (a stage that steps 3.5 um in x and 5 um in y) are supported.
    #[test]
    fn a_scan_with_different_x_and_y_pitches_is_compared() {
        let d = paper(300);
        let sp = SimulateParams { pitch: Some([3.5e-6, 5e-6]), ..goals_params(2) };
        let scan = simulate_scan(&d, &sp).unwrap();
        let opts = CompareOptions { aperture: Some(0.8 * 300.0 * PAPER_PITCH), ..Default::default() };
        let c = compare(&d, &scan, &opts).unwrap();
        let r = &c.registration;
        let e = [(r.pose.shift[0] - 3.2e-6) / PAPER_PITCH, (r.pose.shift[1] + 1.7e-6) / PAPER_PITCH];
        assert!(e[0].abs() <= 0.02 && e[1].abs() <= 0.02, "shift error {e:?} px");
        assert!((r.pose.rotation.to_degrees() - 0.3).abs() <= 0.01, "{r:?}");
        assert!((c.model.depth_scale / 0.95 - 1.0).abs() <= 0.005, "{:?}", c.model);
        assert!((c.model.blur - 2e-6).abs() <= 0.15e-6, "{:?}", c.model);
    }
}
