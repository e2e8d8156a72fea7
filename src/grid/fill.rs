//! Filling non-measured points: the membrane (Laplace) fill, below the stages that use it
//! (fabrication's `--fill`, metrology's comparison, the PSF of a scanned part).

use crate::error::{DataCause, Error, Result};
use crate::grid::Grid;

/// Replaces non-finite and invalid samples by the solution of Laplace's equation with the
/// valid samples as boundary values (a smooth membrane fill; Neumann condition at the grid's
/// border), by Gauss-Seidel relaxation with successive over-relaxation (omega = 1.9, at most
/// 2000 sweeps, stopping when no sample changes by more than 1e-15). Returns the grid with every
/// sample valid and the number of samples filled.
pub fn fill_missing(g: &Grid) -> Result<(Grid, usize)> {
    let (nr, nc) = g.dim();
    let mut v = g.values().clone();
    let mut holes = Vec::new();
    for ((i, j), x) in v.indexed_iter_mut() {
        if !x.is_finite() || !g.is_valid(i, j) {
            holes.push((i, j));
            *x = f64::NAN;
        }
    }
    if holes.len() == v.len() {
        return Err(Error::data(DataCause::Empty, "nothing to fill from: no sample is finite"));
    }
    // Start from the mean of the valid samples.
    let (sum, cnt) = v.iter().filter(|x| x.is_finite()).fold((0.0, 0usize), |(s, c), x| (s + x, c + 1));
    let mean = sum / cnt as f64;
    for &(i, j) in &holes {
        v[[i, j]] = mean;
    }
    let omega = 1.9;
    for _ in 0..2000 {
        let mut change = 0.0f64;
        for &(i, j) in &holes {
            let mut acc = 0.0;
            let mut n = 0.0;
            if i > 0 {
                acc += v[[i - 1, j]];
                n += 1.0;
            }
            if i + 1 < nr {
                acc += v[[i + 1, j]];
                n += 1.0;
            }
            if j > 0 {
                acc += v[[i, j - 1]];
                n += 1.0;
            }
            if j + 1 < nc {
                acc += v[[i, j + 1]];
                n += 1.0;
            }
            let new = v[[i, j]] + omega * (acc / n - v[[i, j]]);
            change = change.max((new - v[[i, j]]).abs());
            v[[i, j]] = new;
        }
        if change < 1e-15 {
            break;
        }
    }
    let filled = Grid::new(v, g.pitch(), g.unit())?.with_origin(g.origin());
    Ok((filled, holes.len()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Unit;
    use ndarray::Array2;

    #[test]
    fn a_harmonic_field_is_restored_under_a_mask() {
        let v =
            Array2::from_shape_fn((20, 20), |(i, j)| 3.0 * i as f64 - 2.0 * j as f64 + (i * j) as f64 * 0.5);
        let mut mask = Array2::from_elem((20, 20), true);
        for i in 5..12 {
            for j in 7..15 {
                mask[[i, j]] = false;
            }
        }
        let g = Grid::new(v.clone(), [1e-6; 2], Unit::Metre).unwrap().with_mask(mask).unwrap();
        let (f, n) = fill_missing(&g).unwrap();
        assert_eq!(n, 56);
        assert!(f.mask().is_none());
        // x, y and x*y are harmonic: the discrete Laplace fill reproduces them.
        for ((i, j), x) in v.indexed_iter() {
            assert!((f.values()[[i, j]] - x).abs() < 1e-9, "({i}, {j})");
        }
    }
}
