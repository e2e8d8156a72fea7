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
//!
//! Fabrication polymers and resists, each with its source in [`Material`]'s constructors:
//! NOA61 (Norland data sheet Cauchy), PMMA (Sultanova et al. 2009 Sellmeier) and IP-Dip
//! (Gissibl et al. 2017 Cauchy). A user material comes from Cauchy or Sellmeier coefficients
//! ([`Material::cauchy`], [`Material::sellmeier`]) or from a measured table
//! ([`Material::read_table_csv`]): a CSV `wavelength_nm,n` (or `wavelength_um`, `wavelength_m`)
//! interpolated by a monotone piecewise cubic (PCHIP, Fritsch and Carlson 1980, SIAM J. Numer.
//! Anal. 17(2)), which never overshoots between measured points.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Allowed, Condition, Error, Result};
use crate::tabulated::{column_unit, hermite, pchip_slopes, read_two_columns};

/// A dispersion formula; lengths in the Cauchy and Sellmeier formulas are micrometres, as the
/// sources give them, a table's wavelengths metres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "form", rename_all = "snake_case")]
pub enum Dispersion {
    /// Cauchy, `n = a + b / lambda^2 + c / lambda^4`, lambda in micrometres.
    Cauchy {
        /// Constant term, dimensionless.
        a: f64,
        /// Coefficient of `1 / lambda^2`, um^2.
        b: f64,
        /// Coefficient of `1 / lambda^4`, um^4.
        c: f64,
    },
    /// Sellmeier, `n^2 = 1 + sum_i b_i lambda^2 / (lambda^2 - c_i)`, lambda in micrometres.
    Sellmeier {
        /// Oscillator strengths `b_i`, dimensionless; as many as `c`.
        b: Vec<f64>,
        /// Resonance terms `c_i` (squared resonance wavelengths), um^2.
        c: Vec<f64>,
    },
    /// A measured table: strictly increasing wavelengths (metres) with their index,
    /// interpolated by PCHIP (monotone piecewise cubic Hermite).
    Table {
        /// Wavelengths, metres, strictly increasing (at least two).
        wavelength: Vec<f64>,
        /// Refractive index at each wavelength.
        n: Vec<f64>,
    },
}

/// A named material with its dispersion and the wavelength range (metres) where it holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Material {
    /// Name: a built-in's (`pdms`, `fused_silica`, ...), the user's, or a table file's stem.
    pub name: String,
    /// The formula or table that gives n(lambda).
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

    /// Norland Optical Adhesive 61 (UV-cured), Cauchy fit of the manufacturer's data sheet
    /// (Norland Products, "NOA 61" technical data sheet, refractive index vs wavelength):
    /// `n = A + B / lambda^2 + C / lambda^4` with lambda in nanometres, A = 1.5375,
    /// B = 8290.45 nm^2, C = -2.11046e8 nm^4 (here converted to micrometres). The data sheet's
    /// cured index is 1.56 at 589 nm. Valid 400-1000 nm, the range the data sheet plots.
    pub fn noa61() -> Material {
        Material {
            name: "noa61".into(),
            dispersion: Dispersion::Cauchy { a: 1.5375, b: 8290.45e-6, c: -2.11046e8 * 1e-12 },
            valid_range: [400e-9, 1000e-9],
        }
    }

    /// PMMA (poly(methyl methacrylate)), one-term Sellmeier fit of Sultanova, Kasarova and
    /// Nikolov, "Dispersion properties of optical polymers", Acta Physica Polonica A 116, 585
    /// (2009): `n^2 - 1 = 1.1819 lambda^2 / (lambda^2 - 0.011313)`, lambda in micrometres.
    /// Valid 437-1052 nm, the range of their refractometer measurements.
    pub fn pmma() -> Material {
        Material {
            name: "pmma".into(),
            dispersion: Dispersion::Sellmeier { b: vec![1.1819], c: vec![0.011313] },
            valid_range: [437e-9, 1052e-9],
        }
    }

    /// IP-Dip (Nanoscribe two-photon resist, polymerized), Cauchy fit of Gissibl, Wagner,
    /// Sykora, Schmid and Giessen, "Refractive index measurements of photo-resists for
    /// three-dimensional direct laser writing", Opt. Mater. Express 7, 2293 (2017):
    /// `n = 1.5273 + 6.5456e-3 / lambda^2 + 2.5345e-4 / lambda^4`, lambda in micrometres.
    /// Valid 400-1600 nm, the range of their measurements.
    pub fn ip_dip() -> Material {
        Material {
            name: "ip_dip".into(),
            dispersion: Dispersion::Cauchy { a: 1.5273, b: 6.5456e-3, c: 2.5345e-4 },
            valid_range: [400e-9, 1600e-9],
        }
    }

    /// A user-defined Cauchy material, `n = a + b / lambda^2 + c / lambda^4` with lambda in
    /// micrometres (so `b` in um^2, `c` in um^4), valid over `valid_range` (metres).
    pub fn cauchy(name: &str, a: f64, b: f64, c: f64, valid_range: [f64; 2]) -> Result<Material> {
        check_range(name, valid_range)?;
        if ![a, b, c].iter().all(|v| v.is_finite()) {
            return Err(Error::param("cauchy", format!("{name}: coefficients must be finite")));
        }
        let m = Material { name: name.into(), dispersion: Dispersion::Cauchy { a, b, c }, valid_range };
        m.check_physical()?;
        Ok(m)
    }

    /// A user-defined Sellmeier material, `n^2 = 1 + sum_i b_i lambda^2 / (lambda^2 - c_i)`
    /// with lambda in micrometres (`c_i` in um^2), valid over `valid_range` (metres). A pole
    /// `lambda^2 = c_i` inside the range is refused.
    pub fn sellmeier(name: &str, b: Vec<f64>, c: Vec<f64>, valid_range: [f64; 2]) -> Result<Material> {
        check_range(name, valid_range)?;
        if b.is_empty() || b.len() != c.len() || !b.iter().chain(&c).all(|v| v.is_finite()) {
            return Err(Error::param(
                "sellmeier",
                format!("{name}: needs as many finite B as C coefficients (got {} and {})", b.len(), c.len()),
            ));
        }
        let (l0, l1) = ((valid_range[0] * 1e6).powi(2), (valid_range[1] * 1e6).powi(2));
        if let Some(ci) = c.iter().find(|&&ci| ci >= l0 && ci <= l1) {
            return Err(Error::param(
                "sellmeier",
                format!("{name}: resonance at {:.1} nm lies inside the valid range", ci.sqrt() * 1e3),
            ));
        }
        let m = Material { name: name.into(), dispersion: Dispersion::Sellmeier { b, c }, valid_range };
        m.check_physical()?;
        Ok(m)
    }

    /// A material from measured `(wavelength in metres, n)` pairs, strictly increasing in
    /// wavelength (at least two), interpolated by PCHIP; valid between the first and last point.
    pub fn table(name: &str, wavelength: Vec<f64>, n: Vec<f64>) -> Result<Material> {
        if wavelength.len() < 2 || wavelength.len() != n.len() {
            return Err(Error::param(
                "table",
                format!("{name}: needs at least two (wavelength, n) points, got {}", wavelength.len()),
            ));
        }
        for k in 0..wavelength.len() {
            if !(wavelength[k].is_finite() && wavelength[k] > 0.0 && n[k].is_finite() && n[k] > 0.0) {
                return Err(Error::param(
                    "table",
                    format!("{name}: point {} is not positive and finite", k + 1),
                ));
            }
            if k > 0 && wavelength[k] <= wavelength[k - 1] {
                return Err(Error::param(
                    "table",
                    format!("{name}: wavelengths must increase strictly (point {} after point {k})", k + 1),
                ));
            }
        }
        let valid_range = [wavelength[0], wavelength[wavelength.len() - 1]];
        Ok(Material { name: name.into(), dispersion: Dispersion::Table { wavelength, n }, valid_range })
    }

    /// Reads a measured index table from CSV: a header `wavelength_nm,n` (or `wavelength_um`,
    /// `wavelength_m`; the unit may also be written `wavelength (nm)` / `wavelength [um]`),
    /// then one `wavelength,n` pair per line, wavelengths strictly increasing. Blank lines and
    /// `#` comments are skipped. Errors name the file and the line.
    pub fn read_table_csv(path: &Path) -> Result<Material> {
        let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let t = read_two_columns(path, "wavelength_nm,n")?;
        if t.header[1] != "n" {
            return Err(Error::malformed(path, format!("second column must be 'n', got '{}'", t.header[1])));
        }
        let scale = column_unit(path, &t.header[0], "wavelength")?;
        let mut wl: Vec<f64> = Vec::new();
        let mut n = Vec::new();
        for &(line, l, index) in &t.rows {
            if l <= 0.0 || index <= 0.0 {
                return Err(Error::malformed(
                    path,
                    format!("line {line}: wavelength and n must be positive"),
                ));
            }
            if wl.last().is_some_and(|&prev| l * scale <= prev) {
                return Err(Error::malformed(
                    path,
                    format!("line {line}: wavelength {l} does not increase on the previous row"),
                ));
            }
            wl.push(l * scale);
            n.push(index);
        }
        if wl.len() < 2 {
            return Err(Error::malformed(path, format!("needs at least two rows, got {}", wl.len())));
        }
        Material::table(&name, wl, n)
    }

    /// Looks a material up by name (`pdms`, `fused_silica`, `noa61`, `pmma`, `ip_dip`).
    pub fn by_name(name: &str) -> Result<Material> {
        match name.to_ascii_lowercase().replace(['-', ' '], "_").as_str() {
            "pdms" | "sylgard184" | "sylgard_184" => Ok(Material::pdms()),
            "fused_silica" | "silica" | "sio2" => Ok(Material::fused_silica()),
            "noa61" | "noa_61" => Ok(Material::noa61()),
            "pmma" => Ok(Material::pmma()),
            "ip_dip" | "ipdip" => Ok(Material::ip_dip()),
            _ => Err(Error::param_in(
                "material",
                Allowed::one_of(&["pdms", "fused_silica", "noa61", "pmma", "ip_dip"]),
                format!("unknown material '{name}' (known: pdms, fused_silica, noa61, pmma, ip_dip)"),
            )),
        }
    }

    /// Refuses a formula that gives a non-finite index or one below 1 at the range's ends.
    fn check_physical(&self) -> Result<()> {
        for l in self.valid_range {
            let n = self.index(l)?;
            if !(n.is_finite() && n >= 1.0) {
                return Err(Error::param(
                    "dispersion",
                    format!("{}: n = {n} at {:.1} nm is not a physical index", self.name, l * 1e9),
                ));
            }
        }
        Ok(())
    }

    /// Refractive index at `wavelength` (metres). Refuses wavelengths outside the formula's range.
    pub fn index(&self, wavelength: f64) -> Result<f64> {
        let [lo, hi] = self.valid_range;
        if !(wavelength >= lo * 0.999 && wavelength <= hi * 1.001) {
            return Err(Error::validity(
                Condition::Domain,
                format!(
                    "{}: wavelength {:.1} nm is outside the dispersion formula's range {:.0}-{:.0} nm",
                    self.name,
                    wavelength * 1e9,
                    lo * 1e9,
                    hi * 1e9
                ),
            ));
        }
        let l = wavelength * 1e6;
        Ok(match &self.dispersion {
            Dispersion::Cauchy { a, b, c } => a + b / (l * l) + c / l.powi(4),
            Dispersion::Sellmeier { b, c } => {
                let l2 = l * l;
                (1.0 + b.iter().zip(c).map(|(b, c)| b * l2 / (l2 - c)).sum::<f64>()).sqrt()
            }
            Dispersion::Table { wavelength: x, n } => hermite(x, n, &pchip_slopes(x, n), wavelength),
        })
    }

    /// The height of one 2 pi phase period at `wavelength`: `h_2pi = lambda / (n - 1)`, metres.
    pub fn height_2pi(&self, wavelength: f64) -> Result<f64> {
        Ok(wavelength / (self.index(wavelength)? - 1.0))
    }
}

fn check_range(name: &str, r: [f64; 2]) -> Result<()> {
    if !(r[0].is_finite() && r[1].is_finite() && r[0] > 0.0 && r[1] > r[0]) {
        return Err(Error::param(
            "valid_range",
            format!("{name}: wavelength range [{}, {}] m must be positive and increasing", r[0], r[1]),
        ));
    }
    Ok(())
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

    #[test]
    fn polymers_match_their_published_values() {
        // Norland's data sheet: cured NOA61 n = 1.56 at 589 nm.
        assert!((Material::noa61().index(589.3e-9).unwrap() - 1.56).abs() < 1.5e-3);
        // Sultanova 2009, PMMA: n_D = 1.4905 (their Table 1 at 587.6 nm).
        assert!((Material::pmma().index(587.6e-9).unwrap() - 1.4905).abs() < 3e-4);
        // Gissibl 2017, polymerized IP-Dip: about 1.548 at 589 nm, 1.539 at 780 nm.
        let ip = Material::ip_dip();
        assert!((ip.index(589.3e-9).unwrap() - 1.548).abs() < 1e-3);
        assert!((ip.index(780e-9).unwrap() - 1.539).abs() < 1e-3);
        for m in [Material::noa61(), Material::pmma(), Material::ip_dip()] {
            // Normal dispersion over the visible.
            assert!(m.index(450e-9).unwrap() > m.index(530e-9).unwrap());
            assert!(m.index(530e-9).unwrap() > m.index(635e-9).unwrap());
            assert_eq!(Material::by_name(&m.name).unwrap(), m);
        }
        let e = Material::pmma().index(400e-9).unwrap_err().to_string();
        assert!(e.contains("437-1052 nm"), "{e}");
    }

    #[test]
    fn user_coefficients_round_trip_the_builtins() {
        let c = Material::cauchy("mine", 1.5273, 6.5456e-3, 2.5345e-4, [400e-9, 1600e-9]).unwrap();
        assert_eq!(c.index(633e-9).unwrap(), Material::ip_dip().index(633e-9).unwrap());
        let s = Material::sellmeier(
            "silica",
            vec![0.6961663, 0.4079426, 0.8974794],
            vec![0.0684043f64.powi(2), 0.1162414f64.powi(2), 9.896161f64.powi(2)],
            [210e-9, 3710e-9],
        )
        .unwrap();
        assert!((s.index(587.6e-9).unwrap() - 1.45846).abs() < 2e-5);
        // A resonance inside the range, mismatched coefficients, a bad range: refused.
        assert!(Material::sellmeier("x", vec![1.0], vec![0.25], [400e-9, 700e-9]).is_err());
        assert!(Material::sellmeier("x", vec![1.0, 2.0], vec![0.01], [400e-9, 700e-9]).is_err());
        assert!(Material::cauchy("x", 1.5, 0.0, 0.0, [700e-9, 400e-9]).is_err());
        assert!(Material::cauchy("x", 0.5, 0.0, 0.0, [400e-9, 700e-9]).is_err());
    }

    #[test]
    fn table_interpolates_monotonically_and_reads_csv() {
        // A table sampled from the PMMA formula reproduces it between the points.
        let pm = Material::pmma();
        let wl: Vec<f64> = (0..7).map(|k| 450e-9 + k as f64 * 100e-9).collect();
        let n: Vec<f64> = wl.iter().map(|&l| pm.index(l).unwrap()).collect();
        let t = Material::table("pmma_table", wl.clone(), n.clone()).unwrap();
        for k in 0..6 {
            assert_eq!(t.index(wl[k]).unwrap(), n[k]);
            let mid = 0.5 * (wl[k] + wl[k + 1]);
            let v = t.index(mid).unwrap();
            assert!((v - pm.index(mid).unwrap()).abs() < 2e-4);
            // Monotone: between its neighbours.
            assert!(v < n[k] && v > n[k + 1]);
        }
        assert!(t.index(440e-9).unwrap_err().to_string().contains("450-1050 nm"));

        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("resin.csv");
        std::fs::write(&p, "# measured\nwavelength (nm),n\n450,1.52\n550,1.51\n650,1.505\n").unwrap();
        let m = Material::read_table_csv(&p).unwrap();
        assert_eq!(m.name, "resin");
        assert!((m.index(550e-9).unwrap() - 1.51).abs() < 1e-15);
        let bad = |text: &str, needle: &str| {
            std::fs::write(&p, text).unwrap();
            let e = Material::read_table_csv(&p).unwrap_err().to_string();
            assert!(e.contains("resin.csv") && e.contains(needle), "{e}");
        };
        bad("wavelength,n\n450,1.5\n", "names no unit");
        bad("wavelength_um,n\n0.45,1.5\n0.55,x\n", "line 3");
        bad("wavelength_um,n\n0.45,1.5\n0.44,1.51\n", "line 3: wavelength 0.44 does not increase");
        bad("wavelength_um,n\n0.45,1.5,7\n", "line 2: expected 2 fields");
        bad("lambda,n\n", "header");
    }
}
