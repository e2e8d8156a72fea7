//! Resist contrast curves: developed depth as a function of exposure dose, read from a CSV,
//! interpolated monotonically and inverted (depth -> dose) for grayscale lithography.
//!
//! The CSV has a header `dose,<depth column>` where the depth column is `depth_nm`,
//! `depth_um` or `depth_m` (the unit is part of the name, so a file cannot be misread), and one
//! row per calibration point. Dose is relative to the writer's full scale, in [0, 1]. For a
//! positive resist "depth" is the developed (removed) depth; for a negative resist it is the
//! remaining thickness. Either way depth must rise strictly with dose.
//!
//! Interpolation is monotone PCHIP ([`crate::tabulated`]): it never overshoots the data, so its
//! inverse exists and is unique. The inverse is found by bisection on the forward curve, so forward
//! and inverse agree to round-off.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{DataCause, Error, Result};
use crate::tabulated::{column_unit, hermite, parse_two_columns, pchip_slopes};

/// A monotone contrast curve. Invariants: at least 2 points, doses strictly increasing in
/// [0, 1], depths strictly increasing.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ContrastCurve {
    /// Relative dose, 0..=1.
    pub dose: Vec<f64>,
    /// Depth (or remaining thickness) at each dose, metres.
    pub depth: Vec<f64>,
    /// Hermite slopes d(depth)/d(dose) at the points.
    slopes: Vec<f64>,
    /// Where the curve came from.
    pub source: PathBuf,
}

impl ContrastCurve {
    /// Builds a curve from points; `source` names them in error messages.
    pub fn new(dose: Vec<f64>, depth: Vec<f64>, source: &Path) -> Result<Self> {
        let bad = |what: String| Error::malformed(source, what);
        if dose.len() != depth.len() || dose.len() < 2 {
            return Err(bad(format!(
                "a contrast curve needs at least 2 (dose, depth) rows, got {}",
                dose.len()
            )));
        }
        for (k, (&d, &z)) in dose.iter().zip(&depth).enumerate() {
            if !(0.0..=1.0).contains(&d) {
                return Err(bad(format!("row {}: dose {d} is outside the relative range 0..=1", k + 1)));
            }
            if !z.is_finite() {
                return Err(bad(format!("row {}: depth is not finite", k + 1)));
            }
            if k > 0 {
                if d <= dose[k - 1] {
                    return Err(bad(format!(
                        "row {}: doses must increase strictly (dose {d} after {})",
                        k + 1,
                        dose[k - 1]
                    )));
                }
                if z <= depth[k - 1] {
                    return Err(bad(format!(
                        "row {}: the curve is not monotone: depth {:.1} nm at dose {d} does not exceed {:.1} nm at dose {}",
                        k + 1,
                        z * 1e9,
                        depth[k - 1] * 1e9,
                        dose[k - 1]
                    )));
                }
            }
        }
        let slopes = pchip_slopes(&dose, &depth);
        Ok(ContrastCurve { dose, depth, slopes, source: source.to_path_buf() })
    }

    /// Reads the CSV described in the module docs.
    /// `built-in:NAME` reads a curve bundled with the recipes (see [`crate::fabrication::built_in::BUNDLED`]).
    pub fn read_csv(path: &Path) -> Result<Self> {
        let text = crate::fabrication::built_in::read_text(path, ".csv")?;
        let t = parse_two_columns(path, &text, "dose,depth_nm")?;
        if t.header[0] != "dose" {
            return Err(Error::malformed(
                path,
                format!("first column must be 'dose', got '{}'", t.header[0]),
            ));
        }
        let scale = column_unit(path, &t.header[1], "depth")?;
        let dose = t.rows.iter().map(|r| r.1).collect();
        let depth = t.rows.iter().map(|r| r.2 * scale).collect();
        ContrastCurve::new(dose, depth, path)
    }

    /// Depth range `[min, max]` the curve covers, metres.
    pub fn depth_range(&self) -> [f64; 2] {
        [self.depth[0], self.depth[self.depth.len() - 1]]
    }

    /// Developed depth at relative `dose` (clamped to the curve's dose range).
    pub fn depth_at(&self, dose: f64) -> f64 {
        hermite(&self.dose, &self.depth, &self.slopes, dose)
    }

    /// The dose that develops `depth`; an error if the curve does not reach it.
    pub fn dose_for(&self, depth: f64) -> Result<f64> {
        let [lo, hi] = self.depth_range();
        let tol = 1e-12 * (hi - lo);
        if depth < lo - tol || depth > hi + tol {
            return Err(Error::data(
                DataCause::OutOfRange,
                format!(
                    "{}: the contrast curve covers {:.1}..{:.1} nm but {:.1} nm is needed",
                    self.source.display(),
                    lo * 1e9,
                    hi * 1e9,
                    depth * 1e9
                ),
            ));
        }
        // The segment whose end depths bracket the target: the interpolant there is one cubic
        // (`hermite` evaluates the same cubic strictly inside the segment).
        let n = self.dose.len();
        let k = self.depth.partition_point(|&z| z < depth).saturating_sub(1).min(n - 2);
        let (x0, h) = (self.dose[k], self.dose[k + 1] - self.dose[k]);
        let (y0, y1, m0, m1) = (self.depth[k], self.depth[k + 1], self.slopes[k], self.slopes[k + 1]);
        let at = |x: f64| {
            let t = (x - x0) / h;
            let (t2, t3) = (t * t, t * t * t);
            (2.0 * t3 - 3.0 * t2 + 1.0) * y0
                + (t3 - 2.0 * t2 + t) * h * m0
                + (-2.0 * t3 + 3.0 * t2) * y1
                + (t3 - t2) * h * m1
        };
        let slope = |x: f64| {
            let t = (x - x0) / h;
            (6.0 * t * t - 6.0 * t) * (y0 - y1) / h
                + (3.0 * t * t - 4.0 * t + 1.0) * m0
                + (3.0 * t * t - 2.0 * t) * m1
        };
        let (mut a, mut b) = (x0, self.dose[k + 1]);
        // Newton steps from the chord, each kept inside the bracket and narrowing it; then the
        // bracket is closed around the estimate by widening steps, so that the bisection below
        // starts within a few thousand ulp of the root instead of the whole segment.
        let mut x = a + (b - a) * ((depth - y0) / (y1 - y0)).clamp(0.0, 1.0);
        for _ in 0..8 {
            if !(x > a && x < b) {
                break;
            }
            let f = at(x) - depth;
            if f < 0.0 {
                a = x;
            } else {
                b = x;
            }
            let next = x - f / slope(x);
            if f == 0.0 || next == x || !next.is_finite() {
                break;
            }
            x = next;
        }
        if x > a && x < b {
            let mut w = 4.0 * f64::EPSILON * x.abs().max(f64::MIN_POSITIVE);
            while w < b - a {
                let (lo, hi) = (x - w, x + w);
                let lo_ok = lo <= a || at(lo) < depth;
                let hi_ok = hi >= b || at(hi) >= depth;
                if lo_ok && hi_ok {
                    a = a.max(lo);
                    b = b.min(hi);
                    break;
                }
                w *= 16.0;
            }
        }
        for _ in 0..80 {
            let m = 0.5 * (a + b);
            // A midpoint on an end stays the answer: either the bracket keeps that end or
            // shrinks onto it, and every later step repeats itself.
            if m == a || m == b {
                break;
            }
            if at(m) < depth {
                a = m;
            } else {
                b = m;
            }
        }
        Ok(0.5 * (a + b))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::FormatCause;

    fn curve(dose: &[f64], depth_nm: &[f64]) -> Result<ContrastCurve> {
        ContrastCurve::new(dose.to_vec(), depth_nm.iter().map(|d| d * 1e-9).collect(), Path::new("test.csv"))
    }

    /// The plain bisection over the whole dose range on `depth_at` that `dose_for` replaced.
    fn bisect(c: &ContrastCurve, depth: f64) -> f64 {
        let (mut a, mut b) = (c.dose[0], c.dose[c.dose.len() - 1]);
        for _ in 0..80 {
            let m = 0.5 * (a + b);
            if m == a || m == b {
                break;
            }
            if c.depth_at(m) < depth {
                a = m;
            } else {
                b = m;
            }
        }
        0.5 * (a + b)
    }

    #[test]
    fn dose_for_equals_a_plain_bisection_on_the_forward_curve() {
        let text = crate::fabrication::built_in::read_text(
            Path::new("built-in:positive-resist-contrast.csv"),
            ".csv",
        )
        .unwrap();
        let t = parse_two_columns(Path::new("c.csv"), &text, "dose,depth_nm").unwrap();
        let bundled = ContrastCurve::new(
            t.rows.iter().map(|r| r.1).collect(),
            t.rows.iter().map(|r| r.2 * 1e-9).collect(),
            Path::new("c.csv"),
        )
        .unwrap();
        let steep = curve(&[0.0, 0.1, 0.15, 0.9, 1.0], &[0.0, 1.0, 900.0, 1000.0, 1300.0]).unwrap();
        for c in [bundled, steep] {
            let [lo, hi] = c.depth_range();
            let mut differ = 0;
            for i in 0..=4000 {
                let z = lo + (hi - lo) * i as f64 / 4000.0;
                let (fast, slow) = (c.dose_for(z).unwrap(), bisect(&c, z));
                // Equal but where the cubic's rounding makes it wiggle by a few ulp of depth
                // around the root (several adjacent doses then bracket it), or where the root
                // is a dose of 0, which neither bisection reaches in 80 halvings.
                assert!((fast - slow).abs() <= 64.0 * f64::EPSILON * slow + 1e-20, "{z}: {fast} {slow}");
                differ += (fast != slow) as usize;
            }
            assert!(differ <= 200, "{differ} of 4001 inversions differ in the last bits");
        }
    }

    #[test]
    fn pchip_is_exact_on_a_line_and_inverse_matches_forward() {
        let c = curve(&[0.0, 0.25, 0.5, 1.0], &[0.0, 250.0, 500.0, 1000.0]).unwrap();
        for k in 0..=100 {
            let d = k as f64 / 100.0;
            assert!((c.depth_at(d) - d * 1e-6).abs() < 1e-18);
        }
        let c = curve(&[0.0, 0.1, 0.3, 0.6, 1.0], &[0.0, 20.0, 300.0, 1100.0, 1500.0]).unwrap();
        let mut prev = -1.0;
        for k in 0..=1000 {
            let z = c.depth_at(k as f64 / 1000.0);
            assert!(z > prev, "monotone");
            prev = z;
        }
        for z in [0.0, 1e-9, 123e-9, 1.1e-6, 1.5e-6] {
            let d = c.dose_for(z).unwrap();
            assert!((c.depth_at(d) - z).abs() < 1e-15, "{z}");
        }
        // Never overshoots between data points.
        for k in 0..1000 {
            let z = c.depth_at(0.3 + 0.3 * k as f64 / 1000.0);
            assert!((300e-9..=1100e-9).contains(&z));
        }
    }

    #[test]
    fn interior_slopes_are_the_weighted_harmonic_mean() {
        let c = curve(&[0.0, 0.1, 0.3, 0.6, 1.0], &[0.0, 20.0, 300.0, 1100.0, 1500.0]).unwrap();
        let slopes: Vec<f64> = c.slopes.iter().map(|s| s * 1e9).collect();
        // Interior slopes by the weighted harmonic mean, checked by hand:
        // k=1: h0=.1,h1=.2, d0=200, d1=1400, w1=.5, w2=.4 -> .9/(.5/200+.4/1400) = 322.58...
        assert!((slopes[1] - 0.9 / (0.5 / 200.0 + 0.4 / 1400.0)).abs() < 1e-6);
        assert!(slopes.iter().all(|&s| s >= 0.0));
    }

    #[test]
    fn refuses_non_monotone_and_out_of_range() {
        let e = curve(&[0.0, 0.5, 1.0], &[0.0, 600.0, 550.0]).unwrap_err();
        assert!(matches!(e, Error::Format { cause: FormatCause::Malformed, .. }), "{e:?}");
        let e = e.to_string();
        assert!(e.contains("test.csv") && e.contains("not monotone") && e.contains("row 3"), "{e}");
        assert!(curve(&[0.0, 0.5, 0.5], &[0.0, 1.0, 2.0]).is_err());
        assert!(curve(&[0.0, 1.5], &[0.0, 1.0]).is_err());
        assert!(curve(&[0.0], &[0.0]).is_err());
        let c = curve(&[0.0, 1.0], &[0.0, 800.0]).unwrap();
        let e = c.dose_for(1.2e-6).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::OutOfRange, .. }), "{e:?}");
        let e = e.to_string();
        assert!(e.contains("covers 0.0..800.0 nm") && e.contains("1200.0 nm"), "{e}");
    }

    #[test]
    fn reads_csv_with_units_in_the_header() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("c.csv");
        std::fs::write(&p, "# calibration\ndose,depth_um\n0,0\n0.5,0.7\n1,1.6\n").unwrap();
        let c = ContrastCurve::read_csv(&p).unwrap();
        assert_eq!(c.depth_range(), [0.0, 1.6e-6]);
        std::fs::write(&p, "dose,depth\n0,0\n1,1\n").unwrap();
        let e = ContrastCurve::read_csv(&p).unwrap_err();
        assert!(
            matches!(e, Error::Format { cause: FormatCause::Malformed, .. })
                && e.to_string().contains("names no unit"),
            "{e:?}"
        );
        std::fs::write(&p, "dose,depth_nm\n0,0\n1,x\n").unwrap();
        let e = ContrastCurve::read_csv(&p).unwrap_err();
        assert!(
            matches!(e, Error::Format { cause: FormatCause::Malformed, .. })
                && e.to_string().contains("line 3"),
            "{e:?}"
        );
    }
}
