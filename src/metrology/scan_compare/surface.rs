//! The as-fabricated surface in the design frame (the scan resampled at each design sample's
//! registered position, its plane and height reference removed), and the statistics of its
//! difference from the design over the clear aperture.

use ndarray::Array2;

use crate::error::{DataCause, Error, Result};
use crate::grid::{Grid, Interpolation, Unit};
use crate::metrology::scan_registration::Registration;

/// Positions (metres from the grid's centre) of sample `(i, j)`.
pub(super) fn centred(g: &Grid, i: usize, j: usize) -> [f64; 2] {
    let (nr, nc) = g.dim();
    let p = g.pitch();
    [(j as f64 - (nc as f64 - 1.0) * 0.5) * p[0], (i as f64 - (nr as f64 - 1.0) * 0.5) * p[1]]
}

/// The part's error over the aperture: `surface - design` where the surface is measured inside
/// the aperture (`inside`), and its statistics.
pub(super) struct ApertureErrors {
    /// The difference, metres (invalid outside the aperture and where not measured).
    pub(super) difference: Grid,
    /// Measured samples over the aperture's samples.
    pub(super) measured_fraction: f64,
    /// Mean, RMS and peak-to-valley of the difference, metres.
    pub(super) mean: f64,
    pub(super) rms: f64,
    pub(super) pv: f64,
}

/// The difference of `surface` and `design` over the measured samples `inside` the aperture
/// (module docs); none measured there is refused.
pub(super) fn aperture_errors(
    design: &Grid,
    surface: &Grid,
    inside: &Array2<bool>,
) -> Result<ApertureErrors> {
    let (nr, nc) = design.dim();
    let mut diff = Array2::zeros((nr, nc));
    let mut dvalid = Array2::from_elem((nr, nc), false);
    let (mut n, mut s, mut ss, mut lo, mut hi, mut n_ap) =
        (0.0, 0.0, 0.0, f64::INFINITY, f64::NEG_INFINITY, 0.0);
    for i in 0..nr {
        for j in 0..nc {
            if !inside[[i, j]] {
                continue;
            }
            n_ap += 1.0;
            if surface.is_valid(i, j) {
                let d = surface.values()[[i, j]] - design.values()[[i, j]];
                diff[[i, j]] = d;
                dvalid[[i, j]] = true;
                n += 1.0;
                s += d;
                ss += d * d;
                lo = lo.min(d);
                hi = hi.max(d);
            }
        }
    }
    if n == 0.0 {
        return Err(Error::data(DataCause::Empty, "no measured scan sample falls inside the aperture"));
    }
    let difference = design.map_values(diff, Unit::Metre)?.with_mask(dvalid)?;
    Ok(ApertureErrors {
        difference,
        measured_fraction: n / n_ap,
        mean: s / n,
        rms: (ss / n).sqrt(),
        pv: hi - lo,
    })
}

/// The scan on the design grid (module docs), the aperture mask and the fraction of the
/// aperture inside the scan's footprint.
pub(super) fn design_frame(
    design: &Grid,
    scan: &Grid,
    reg: &Registration,
    aperture: f64,
) -> Result<(Grid, Array2<bool>, f64)> {
    use rayon::prelude::*;
    let (nr, nc) = design.dim();
    let (sr, sc) = scan.dim();
    let ps = scan.pitch();
    let sign = if reg.complement { -1.0 } else { 1.0 };
    let r2 = (0.5 * aperture).powi(2);
    // Per design row: heights, measured, inside the aperture, aperture and covered counts.
    type Row = (Vec<f64>, Vec<bool>, Vec<bool>, usize, usize);
    let rows: Vec<Row> = (0..nr)
        .into_par_iter()
        .map(|i| {
            let (mut v, mut ok, mut ins) = (vec![0.0; nc], vec![false; nc], vec![false; nc]);
            let (mut n_ap, mut n_cov) = (0, 0);
            for j in 0..nc {
                let xd = centred(design, i, j);
                let xs = reg.pose.design_to_scan(xd);
                let fi = xs[1] / ps[1] + (sr as f64 - 1.0) * 0.5;
                let fj = xs[0] / ps[0] + (sc as f64 - 1.0) * 0.5;
                let in_scan = fi >= -0.5 && fj >= -0.5 && fi <= sr as f64 - 0.5 && fj <= sc as f64 - 0.5;
                if xd[0] * xd[0] + xd[1] * xd[1] <= r2 && design.is_valid(i, j) {
                    ins[j] = true;
                    n_ap += 1;
                    n_cov += usize::from(in_scan);
                }
                if !in_scan {
                    continue;
                }
                let z = [Interpolation::Bicubic, Interpolation::Bilinear, Interpolation::Nearest]
                    .iter()
                    .find_map(|&m| scan.sample_index(fi, fj, m));
                if let Some(z) = z {
                    let plane = reg.offset + reg.tilt[0] * xs[0] + reg.tilt[1] * xs[1];
                    v[j] = sign * (z - plane);
                    ok[j] = true;
                }
            }
            (v, ok, ins, n_ap, n_cov)
        })
        .collect();
    let (n_ap, n_cov) = rows.iter().fold((0, 0), |(a, c), r| (a + r.3, c + r.4));
    let shape = |e: ndarray::ShapeError| Error::internal(format!("design frame: {e}"));
    let values = Array2::from_shape_vec((nr, nc), rows.iter().flat_map(|r| r.0.iter().copied()).collect())
        .map_err(shape)?;
    let valid = Array2::from_shape_vec((nr, nc), rows.iter().flat_map(|r| r.1.iter().copied()).collect())
        .map_err(shape)?;
    let inside = Array2::from_shape_vec((nr, nc), rows.iter().flat_map(|r| r.2.iter().copied()).collect())
        .map_err(shape)?;
    let surface =
        Grid::new(values, design.pitch(), Unit::Metre)?.with_mask(valid)?.with_origin(design.origin());
    Ok((surface, inside, n_cov as f64 / n_ap.max(1) as f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Over a 4 x 4 aperture less one corner, one sample not measured: the difference of the
    /// other 14 (`i - j` nm on a flat design) has mean -2/14 nm, RMS sqrt(30/14) nm and a
    /// peak-to-valley of 5 nm.
    #[test]
    fn aperture_errors_are_the_measured_differences_statistics() {
        let design = Grid::new(Array2::from_elem((4, 4), 1e-7), [1e-6; 2], Unit::Metre).unwrap();
        let mut valid = Array2::from_elem((4, 4), true);
        valid[[0, 1]] = false;
        let surface = design
            .map_values(
                Array2::from_shape_fn((4, 4), |(i, j)| 1e-7 + (i as f64 - j as f64) * 1e-9),
                Unit::Metre,
            )
            .unwrap()
            .with_mask(valid)
            .unwrap();
        let mut inside = Array2::from_elem((4, 4), true);
        inside[[3, 0]] = false;
        let e = aperture_errors(&design, &surface, &inside).unwrap();
        let close = |a: f64, b: f64| (a - b).abs() < 1e-20;
        assert!(
            close(e.mean, -2e-9 / 14.0) && close(e.rms, (30.0f64 / 14.0).sqrt() * 1e-9),
            "{} {}",
            e.mean,
            e.rms
        );
        assert!(close(e.pv, 5e-9), "{}", e.pv);
        assert_eq!(e.measured_fraction, 14.0 / 15.0);
        assert!(!e.difference.is_valid(0, 1) && !e.difference.is_valid(3, 0) && e.difference.is_valid(3, 3));
        let nothing = Array2::from_elem((4, 4), false);
        assert!(aperture_errors(&design, &surface, &nothing).is_err());
    }
}
