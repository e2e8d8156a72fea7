//! Dense linear solves for the small normal equations of the least-squares fits (levelling,
//! registration, the camera response), by nalgebra's LU decomposition with partial pivoting.

use nalgebra::{DMatrix, DVector};

use crate::error::{DataCause, Error, Result};

/// A pivot below this fraction of the largest diagonal entry of `a` is taken as singular.
pub const PIVOT_FLOOR: f64 = 1e-12;

/// Solves the `m x m` system `a x = b` (`a` row-major) by LU with partial pivoting (nalgebra
/// `LU`, Golub & Van Loan, Matrix Computations, Alg. 3.4.1). Refuses, with the reason, a
/// system whose smallest pivot falls below [`PIVOT_FLOOR`] of `a`'s largest diagonal entry:
/// singular, or so ill-conditioned that the answer would be rounding noise.
pub fn solve(a: Vec<f64>, b: Vec<f64>, m: usize) -> Result<Vec<f64>> {
    if a.len() != m * m || b.len() != m {
        return Err(Error::param(
            "system",
            format!("{} matrix and {} right-hand values for {m} unknowns", a.len(), b.len()),
        ));
    }
    let scale = (0..m).map(|k| a[k * m + k].abs()).fold(0.0f64, f64::max);
    let lu = DMatrix::from_row_slice(m, m, &a).lu();
    let smallest = lu.u().diagonal().iter().fold(f64::INFINITY, |s, v| s.min(v.abs()));
    let singular = || {
        let what = format!(
            "the fit is singular: the points do not determine the surface (too few or collinear; smallest \
             pivot {smallest:.3e} of {scale:.3e})"
        );
        Error::data(DataCause::Singular, what)
    };
    if smallest.is_nan() || smallest <= PIVOT_FLOOR * scale {
        return Err(singular());
    }
    let x = lu.solve(&DVector::from_vec(b)).ok_or_else(singular)?;
    Ok(x.iter().copied().collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The Hilbert matrix `1 / (i + j + 1)` of order 6 (condition number 1.5e7) against its
    /// known solution, and the refusal on both sides of the pivot floor.
    #[test]
    fn hilbert_systems_solve_and_singular_ones_are_refused() {
        let m = 6;
        let a: Vec<f64> = (0..m * m).map(|k| 1.0 / ((k / m + k % m + 1) as f64)).collect();
        let x_true: Vec<f64> = (0..m).map(|i| i as f64 - 2.5).collect();
        let b: Vec<f64> = (0..m).map(|i| (0..m).map(|j| a[i * m + j] * x_true[j]).sum()).collect();
        let x = solve(a, b, m).unwrap();
        for (u, v) in x.iter().zip(&x_true) {
            assert!((u - v).abs() < 1e-7, "{x:?}");
        }
        // diag(1, e): solvable at e = 1e-11, refused at 1e-13 and at 0.
        for (e, ok) in [(1e-11, true), (1e-13, false), (0.0, false)] {
            let r = solve(vec![1.0, 0.0, 0.0, e], vec![1.0, e], 2);
            assert_eq!(r.is_ok(), ok, "e = {e}: {r:?}");
            if let Ok(x) = r {
                assert!((x[0] - 1.0).abs() < 1e-15 && (x[1] - 1.0).abs() < 1e-6, "{x:?}");
            } else {
                let e = r.unwrap_err();
                assert!(matches!(e, Error::Data { cause: DataCause::Singular, .. }), "{e:?}");
            }
        }
        assert!(solve(vec![1.0; 3], vec![1.0], 2).is_err(), "mis-sized system");
    }
}
