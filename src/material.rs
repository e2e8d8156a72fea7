//! Refractive index n(lambda) of DOE materials.
//!
//! Two dispersion forms:
//! * Cauchy, `n = A + B / lambda^2 + C / lambda^4` (lambda in micrometres);
//! * Sellmeier, `n^2 = 1 + sum_i B_i lambda^2 / (lambda^2 - C_i)` (lambda in micrometres).
//!
//! PDMS (Sylgard 184) uses a three-term Cauchy curve through the three values the paper
//! reports, n = 1.4295 / 1.4349 / 1.4421 at 635 / 530 / 450 nm (Metzler et al. 2020, Sec. 5),
//! so those are reproduced exactly. Fused silica uses Malitson's Sellmeier fit (JOSA 55, 1205,
//! 1965), valid 0.21-3.71 um.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// A dispersion formula; lengths in the formula are micrometres, as the sources give them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "form", rename_all = "snake_case")]
pub enum Dispersion {
    Cauchy { a: f64, b: f64, c: f64 },
    Sellmeier { b: Vec<f64>, c: Vec<f64> },
}

/// A named material with its dispersion and the wavelength range (metres) where it holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Material {
    pub name: String,
    pub dispersion: Dispersion,
    /// `[min, max]` wavelength in metres where the formula is valid.
    pub valid_range: [f64; 2],
}

/// The paper's RGB design wavelengths, metres (red, green, blue).
pub const PAPER_WAVELENGTHS: [f64; 3] = [635e-9, 530e-9, 450e-9];

impl Material {
    /// PDMS (Sylgard 184): Cauchy curve through the paper's three measured values.
    pub fn pdms() -> Material {
        let n = [1.4295, 1.4349, 1.4421];
        let (a, b, c) = cauchy_through(PAPER_WAVELENGTHS.map(|l| l * 1e6), n);
        Material {
            name: "pdms".into(),
            dispersion: Dispersion::Cauchy { a, b, c },
            valid_range: [400e-9, 700e-9],
        }
    }

    /// Fused silica, Malitson 1965 Sellmeier coefficients.
    pub fn fused_silica() -> Material {
        Material {
            name: "fused_silica".into(),
            dispersion: Dispersion::Sellmeier {
                b: vec![0.6961663, 0.4079426, 0.8974794],
                c: vec![0.0684043f64.powi(2), 0.1162414f64.powi(2), 9.896161f64.powi(2)],
            },
            valid_range: [210e-9, 3710e-9],
        }
    }

    /// Looks a material up by name (`pdms`, `fused_silica`).
    pub fn by_name(name: &str) -> Result<Material> {
        match name.to_ascii_lowercase().replace(['-', ' '], "_").as_str() {
            "pdms" | "sylgard184" | "sylgard_184" => Ok(Material::pdms()),
            "fused_silica" | "silica" | "sio2" => Ok(Material::fused_silica()),
            _ => Err(Error::param(
                "material",
                format!("unknown material '{name}' (known: pdms, fused_silica)"),
            )),
        }
    }

    /// Refractive index at `wavelength` (metres). Refuses wavelengths outside the formula's range.
    pub fn index(&self, wavelength: f64) -> Result<f64> {
        let [lo, hi] = self.valid_range;
        if !(wavelength >= lo * 0.999 && wavelength <= hi * 1.001) {
            return Err(Error::Validity(format!(
                "{}: wavelength {:.1} nm is outside the dispersion formula's range {:.0}-{:.0} nm",
                self.name,
                wavelength * 1e9,
                lo * 1e9,
                hi * 1e9
            )));
        }
        let l = wavelength * 1e6;
        Ok(match &self.dispersion {
            Dispersion::Cauchy { a, b, c } => a + b / (l * l) + c / l.powi(4),
            Dispersion::Sellmeier { b, c } => {
                let l2 = l * l;
                (1.0 + b.iter().zip(c).map(|(b, c)| b * l2 / (l2 - c)).sum::<f64>()).sqrt()
            }
        })
    }

    /// The height of one 2 pi phase period at `wavelength`: `h_2pi = lambda / (n - 1)`, metres.
    pub fn height_2pi(&self, wavelength: f64) -> Result<f64> {
        Ok(wavelength / (self.index(wavelength)? - 1.0))
    }
}

/// Cauchy coefficients (A, B, C) through three (lambda_um, n) points: a 3 x 3 linear solve in
/// the unknowns with rows [1, 1/l^2, 1/l^4], by Cramer's rule.
fn cauchy_through(l: [f64; 3], n: [f64; 3]) -> (f64, f64, f64) {
    let row = |l: f64| [1.0, l.powi(-2), l.powi(-4)];
    let m = [row(l[0]), row(l[1]), row(l[2])];
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(m);
    let with_col = |c: usize| {
        let mut k = m;
        for r in 0..3 {
            k[r][c] = n[r];
        }
        det(k) / d
    };
    (with_col(0), with_col(1), with_col(2))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pdms_reproduces_the_paper_values() {
        let m = Material::pdms();
        for (l, n) in PAPER_WAVELENGTHS.iter().zip([1.4295, 1.4349, 1.4421]) {
            assert!((m.index(*l).unwrap() - n).abs() < 1e-12);
        }
        // Normal dispersion: index falls with wavelength between the anchor points.
        assert!(m.index(500e-9).unwrap() > m.index(600e-9).unwrap());
        assert!(m.index(1550e-9).is_err());
    }

    #[test]
    fn fused_silica_matches_malitson_table() {
        // Malitson 1965: n = 1.45846 at the helium d-line region (587.6 nm), 1.45702 at 632.8 nm.
        let m = Material::fused_silica();
        assert!((m.index(587.6e-9).unwrap() - 1.45846).abs() < 2e-5);
        assert!((m.index(632.8e-9).unwrap() - 1.45702).abs() < 2e-5);
    }
}
