//! RGB in a file's own primaries (OpenEXR's `chromaticities` attribute: CIE x, y of the red,
//! green and blue primaries and of white) to linear Rec. 709 RGB (D65 white), the space every
//! image is read into. A file without the attribute is Rec. 709 (the OpenEXR default).
//!
//! * *RGB to XYZ* (SMPTE RP 177-1993, "Derivation of Basic Television Color Equations"): with
//!   `P` the matrix whose columns are the primaries `(x/y, 1, (1 - x - y)/y)` and `W` white's
//!   `(x_w/y_w, 1, (1 - x_w - y_w)/y_w)`, `M = P diag(P^-1 W)`, so that RGB (1, 1, 1) is white
//!   at luminance `Y` = 1.
//! * *White point*: where the file's white differs from D65, XYZ is adapted by the Bradford
//!   transform (Lam 1985; as in Lindbloom, "Chromatic Adaptation", and the ACES and OCIO
//!   conversions between ACES and Rec. 709): `M_A = B^-1 diag(B W_D65 / B W_file) B`,
//!   `B = [[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]]`.
//!   Identical whites (within 1e-5 in x and y) are not adapted.
//! * *XYZ to Rec. 709*: the inverse of Rec. 709's `M`.
//!
//! The whole conversion is the 3 x 3 matrix `M_709^-1 M_A M_file`, applied to each pixel.

use nalgebra::{Matrix3, Vector3};

/// Rec. 709 primaries and D65 white (ITU-R BT.709; OpenEXR's default chromaticities): red,
/// green, blue, white, each CIE (x, y), as a file stores them (single precision).
pub const REC709: [f32; 8] = [0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290];

/// The same, exact: the space converted to.
const REC709_EXACT: [f64; 8] = [0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290];

/// The Bradford cone-response matrix.
const BRADFORD: [[f64; 3]; 3] =
    [[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]];

/// Chromaticities closer than this to another set (in x and y) are taken as equal.
pub const SAME: f64 = 1e-5;

/// `(X, Y, Z)` of a chromaticity at luminance 1.
fn xyz(x: f64, y: f64) -> Vector3<f64> {
    Vector3::new(x / y, 1.0, (1.0 - x - y) / y)
}

/// The RGB-to-XYZ matrix of chromaticities `c` (see the module docs); refuses a white or a
/// primary with `y` = 0 and primaries on one line.
pub fn rgb_to_xyz(c: &[f64; 8]) -> std::result::Result<Matrix3<f64>, String> {
    if let Some(k) =
        (0..4).find(|&k| !c[2 * k].is_finite() || !c[2 * k + 1].is_finite() || c[2 * k + 1].abs() <= 1e-9)
    {
        let name = ["red", "green", "blue", "white"][k];
        return Err(format!(
            "the {name} chromaticity ({}, {}) has y = 0 or is not finite",
            c[2 * k],
            c[2 * k + 1]
        ));
    }
    let p = Matrix3::from_columns(&[xyz(c[0], c[1]), xyz(c[2], c[3]), xyz(c[4], c[5])]);
    let inv = p
        .try_inverse()
        .filter(|_| p.determinant().abs() > 1e-9)
        .ok_or("the primaries lie on one line (no RGB-to-XYZ matrix)")?;
    let s = inv * xyz(c[6], c[7]);
    Ok(p * Matrix3::from_diagonal(&s))
}

/// The Bradford adaptation of XYZ from white `from` to white `to` (chromaticities x, y).
pub fn bradford(from: [f64; 2], to: [f64; 2]) -> Matrix3<f64> {
    let b = Matrix3::from_fn(|i, j| BRADFORD[i][j]);
    let (s, d) = (b * xyz(from[0], from[1]), b * xyz(to[0], to[1]));
    let inv = b.try_inverse().expect("the Bradford matrix is invertible");
    inv * Matrix3::from_diagonal(&d.component_div(&s)) * b
}

/// The matrix taking RGB in chromaticities `c` to linear Rec. 709 RGB, or `None` where `c` is
/// Rec. 709 (within [`SAME`]).
pub fn to_rec709(c: &[f32; 8]) -> std::result::Result<Option<Matrix3<f64>>, String> {
    if c.iter().zip(REC709).all(|(a, b)| (*a as f64 - b as f64).abs() <= SAME) {
        return Ok(None);
    }
    let c = c.map(f64::from);
    let to_xyz = rgb_to_xyz(&c)?;
    let from_xyz = rgb_to_xyz(&REC709_EXACT)?.try_inverse().expect("Rec. 709 primaries are independent");
    let (w, d65) = ([c[6], c[7]], [REC709_EXACT[6], REC709_EXACT[7]]);
    let adapt = match (w[0] - d65[0]).abs() <= SAME && (w[1] - d65[1]).abs() <= SAME {
        true => Matrix3::identity(),
        false => bradford(w, d65),
    };
    Ok(Some(from_xyz * adapt * to_xyz))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rec. 709's matrix is the one IEC 61966-2-1 (sRGB) publishes, to its 4 decimals.
    #[test]
    fn rec709_to_xyz_is_the_published_srgb_matrix() {
        let m = rgb_to_xyz(&REC709_EXACT).unwrap();
        let srgb = [[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]];
        for i in 0..3 {
            for j in 0..3 {
                assert!((m[(i, j)] - srgb[i][j]).abs() < 1e-4, "{m}");
            }
        }
        assert!(to_rec709(&REC709).unwrap().is_none());
    }

    /// White maps to white: (1, 1, 1) in any primaries with any white is (1, 1, 1) in Rec. 709
    /// after the adaptation; degenerate chromaticities are refused.
    #[test]
    fn white_stays_white_and_degenerate_primaries_are_refused() {
        let tree = [0.62955, 0.341, 0.2867, 0.6108, 0.1489, 0.07125, 0.3155, 0.33165];
        let m = to_rec709(&tree).unwrap().unwrap();
        let w = m * Vector3::new(1.0, 1.0, 1.0);
        assert!((w - Vector3::new(1.0, 1.0, 1.0)).amax() < 1e-12, "{w}");
        let line = [0.1, 0.1, 0.2, 0.2, 0.3, 0.3, 0.3127, 0.329];
        assert!(rgb_to_xyz(&line).unwrap_err().contains("one line"));
        let flat = [0.64, 0.0, 0.3, 0.6, 0.15, 0.06, 0.3127, 0.329];
        assert!(rgb_to_xyz(&flat).unwrap_err().contains("red"));
    }
}
