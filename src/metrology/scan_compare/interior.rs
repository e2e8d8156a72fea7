//! The check that the part matches its design over the aperture's interior, not only at its
//! edge: the correlation over the interior and the trust rule applied to it.

use crate::error::Result;
use crate::grid::Grid;
use crate::metrology::scan_registration::check_trust;

use super::surface::centred;

/// Fraction of the aperture's diameter over which [`Comparison::interior_correlation`] runs.
///
/// [`Comparison::interior_correlation`]: super::Comparison::interior_correlation
pub const INTERIOR: f64 = 0.9;

/// [`check_trust`] on the part's correlation with the reference over the aperture's interior,
/// against the ceiling the scan's noise sets (`compare`, and `precompensate` on a model it reads
/// back). The reference is not blurred here, so a blur of many samples lowers the correlation
/// too: it is refused with the poses the rule exists for. A part blurred by up to 4 pitches
/// still passes (0.975 on the built-in design, `tests`); against the reference blurred by the
/// fitted blur a scan of the unwrapped design, blurred by 2 or 4 pitches, would pass as the
/// wrapped design (0.972, 0.984, where the sharp wrapped design gives 0.931, 0.917): its blur
/// fit is a compromise that [`FabModel::blur_doubt`] does not always catch.
///
/// [`FabModel::blur_doubt`]: super::FabModel::blur_doubt
pub fn check_interior(correlation: f64, noise_ceiling: f64, fraction: f64) -> Result<()> {
    let what = format!("the part over the central {:.0}% of the aperture", 100.0 * INTERIOR);
    check_trust(&what, correlation, noise_ceiling, fraction)
}

/// Pearson correlation of `surface` and `design` over the measured samples within
/// `INTERIOR * aperture / 2` of the centre (NaN when there are none or either is constant).
pub(super) fn interior_correlation(design: &Grid, surface: &Grid, aperture: f64) -> f64 {
    let r2 = (0.5 * INTERIOR * aperture).powi(2);
    let (nr, nc) = design.dim();
    let mut m = [0.0f64; 6];
    for i in 0..nr {
        for j in 0..nc {
            let x = centred(design, i, j);
            if x[0] * x[0] + x[1] * x[1] <= r2 && design.is_valid(i, j) && surface.is_valid(i, j) {
                let (a, b) = (surface.values()[[i, j]], design.values()[[i, j]]);
                for (k, v) in [1.0, a, b, a * a, b * b, a * b].iter().enumerate() {
                    m[k] += v;
                }
            }
        }
    }
    let [n, sa, sb, saa, sbb, sab] = m;
    let cov = sab / n - sa * sb / (n * n);
    cov / ((saa / n - (sa / n).powi(2)) * (sbb / n - (sb / n).powi(2))).sqrt()
}

#[cfg(test)]
mod tests {
    use ndarray::Array2;

    use super::*;
    use crate::design::PAPER_PITCH;
    use crate::error::Error;
    use crate::error::Refusal;
    use crate::grid::Unit;
    use crate::metrology::scan_compare::compare::compare;
    use crate::metrology::scan_compare::compare::tests::paper;
    use crate::metrology::scan_compare::options::CompareOptions;
    use crate::metrology::synthetic_scan::{simulate_scan, SimulateParams};

    /// A Fresnel lens in the same circular aperture registers on the aperture's edge alone: the
    /// registration's noise ceiling refuses it (correlation 0.62 where 5 nm of noise allow
    /// 0.998), and with that test off, the interior correlation does.
    #[test]
    fn a_part_matching_only_at_the_aperture_edge_is_refused() {
        let d = paper(300);
        let aperture = 0.9 * 300.0 * PAPER_PITCH;
        let c = (300.0 - 1.0) * 0.5;
        let f = Array2::from_shape_fn((300, 300), |(i, j)| {
            let r2 = ((i as f64 - c).powi(2) + (j as f64 - c).powi(2)) * PAPER_PITCH * PAPER_PITCH;
            if r2 <= 0.25 * aperture * aperture {
                1.2e-6 * (r2 / 4.2e-8).fract()
            } else {
                0.0
            }
        });
        let f = Grid::new(f, [PAPER_PITCH; 2], Unit::Metre).unwrap();
        let scan = simulate_scan(&f, &SimulateParams { noise: 5e-9, ..Default::default() }).unwrap();
        let opts = CompareOptions { aperture: Some(aperture), ..Default::default() };
        match compare(&d, &scan, &opts) {
            Err(Error::Registration { refusal: Refusal::NotTrusted, .. }) => {}
            other => panic!("expected a registration error, got {other:?}"),
        }
        let mut lenient = opts.clone();
        lenient.register.min_correlation_ratio = 0.0;
        match compare(&d, &scan, &lenient) {
            Err(Error::Registration { refusal: Refusal::NoMatch, what: m }) => {
                assert!(m.contains("inside the aperture"), "{m}")
            }
            other => panic!("expected a registration error, got {other:?}"),
        }
        // The design's own scan passes the same check.
        let own = simulate_scan(&d, &SimulateParams { noise: 5e-9, ..Default::default() }).unwrap();
        let c = compare(&d, &own, &opts).unwrap();
        assert!(c.interior_correlation > 0.99, "{}", c.interior_correlation);
    }

    /// The interior is judged against the sharp design: a part blurred by 2 and 4 pitches
    /// (5 nm of noise) still passes, its correlation falling with the blur (measured: 0.998 and
    /// 0.975, where the noise allows 0.9994), and the fit recovers the blur.
    #[test]
    fn a_part_blurred_by_several_pitches_passes_the_interior_check() {
        let d = paper(300);
        let opts = CompareOptions { aperture: Some(0.8 * 300.0 * PAPER_PITCH), ..Default::default() };
        for (pitches, lo, hi) in [(2.0, 0.99, 0.999), (4.0, 0.96, 0.98)] {
            let sp = SimulateParams { blur: pitches * PAPER_PITCH, noise: 5e-9, ..Default::default() };
            let scan = simulate_scan(&d, &sp).unwrap();
            let c = compare(&d, &scan, &opts).unwrap();
            assert!(c.model.blur_doubt().is_none(), "{:?}", c.model);
            assert!((c.model.blur / (pitches * PAPER_PITCH) - 1.0).abs() < 0.05, "{:?}", c.model);
            let r = c.interior_correlation;
            assert!(r > lo && r < hi, "{pitches} pitches: {r}");
        }
    }
}
