//! The optical system of the paper's camera (Metzler et al. 2020, "Modeling the Optical Point
//! Spread Function"): a point source at `object_distance` (infinity by default), the DOE in a
//! circular aperture of diameter `aperture`, free space `doe_to_lens` (d_phi), a thin lens of
//! focal length `focal_length` (g), free space `lens_to_sensor` (d_s, `g` when in focus for a
//! scene at infinity) and a sensor of pixel pitch `sensor_pitch` read out as a `crop x crop`
//! window centred on the optical axis. All lengths in metres.
//!
//! The DOE transmission is `t(u, v) = A(u, v) exp(i k (n(lambda) - 1) h(u, v))` with `A` the
//! binary circular aperture (the paper's eq. for `t_phi`). The DOE height map is a [`Grid`]
//! at any pitch; its centre sits on the optical axis, and it is resampled onto each method's
//! pupil grid ([`OpticalSystem::pupil_field`]).
//!
//! Pixel integration: each pixel is sampled at `subsample x subsample` points and the
//! weighted intensities summed (binned): the centres of equal sub-cells with equal weights (the
//! midpoint rule, [`PixelRule::Midpoint`]) or Gauss-Legendre nodes and weights
//! ([`PixelRule::GaussLegendre`], for methods that evaluate arbitrary sensor points).

use ndarray::Array2;
use rustfft::num_complex::Complex64;
use serde::{Deserialize, Serialize};

use crate::design::{PAPER_APERTURE, PAPER_PITCH};
use crate::error::{Allowed, DataCause, Error, Result};
use crate::grid::{Grid, Interpolation, Unit};
use crate::material::{Material, PAPER_WAVELENGTHS};

/// The focal length of the paper's camera lens (Nikon Nikkor 35 mm), metres.
pub const PAPER_FOCAL_LENGTH: f64 = 35e-3;
/// The paper's PSF crop, pixels per side.
pub const PAPER_CROP: usize = 320;
/// The DOE-to-lens distance used when none is given, metres. The paper mounts the DOE in a
/// lens tube at "a slight distance" without a value; at `d_s = g` the PSF does not depend on it
/// (paraxially), so this only matters for defocus.
pub const DEFAULT_DOE_TO_LENS: f64 = 10e-3;

/// The quadrature of the intensity over each pixel, per axis with `subsample` points.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PixelRule {
    /// Sub-cell centres, equal weights: the composite midpoint rule. A frequency `f` of the
    /// intensity is weighted by the Dirichlet kernel `sin(pi f p) / (s sin(pi f p / s))`
    /// instead of `sinc(f p)` (error `O((f p / s)^2)`, aliasing once `f p / s >= 1`).
    #[default]
    Midpoint,
    /// Gauss-Legendre nodes and weights (Abramowitz and Stegun 25.4.29): exact for
    /// polynomials of degree `2 s - 1`; for `exp(2 pi i f x)` over a pixel of width `p` the
    /// error falls as `(2 pi f p)^(2s) (s!)^4 / ((2s + 1) ((2s)!)^3)`. Needs a method that
    /// evaluates arbitrary sensor points (matrix_dft, rayleigh_sommerfeld).
    GaussLegendre,
}

/// The `s` Gauss-Legendre nodes on `[-1, 1]` and their weights (summing to 2), by Newton's
/// iteration on the Legendre polynomial `P_s` from the Chebyshev-like initial guesses
/// `cos(pi (i - 1/4) / (s + 1/2))` (Press et al., Numerical Recipes, sec. 4.6).
pub fn gauss_legendre(s: usize) -> (Vec<f64>, Vec<f64>) {
    let mut nodes = vec![0.0; s];
    let mut weights = vec![0.0; s];
    for i in 0..s.div_ceil(2) {
        let mut x = (std::f64::consts::PI * (i as f64 + 0.75) / (s as f64 + 0.5)).cos();
        let mut dp = 1.0;
        for _ in 0..100 {
            // P_s(x) and P_{s-1}(x) by the three-term recurrence.
            let (mut p0, mut p1) = (1.0, x);
            for k in 2..=s {
                let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                p0 = p1;
                p1 = p2;
            }
            let ps = if s == 0 { 1.0 } else { p1 };
            let psm1 = if s == 1 { 1.0 } else { p0 };
            dp = s as f64 * (x * ps - psm1) / (x * x - 1.0);
            let step = ps / dp;
            x -= step;
            if step.abs() < 1e-15 {
                break;
            }
        }
        let w = 2.0 / ((1.0 - x * x) * dp * dp);
        nodes[i] = -x;
        nodes[s - 1 - i] = x;
        weights[i] = w;
        weights[s - 1 - i] = w;
    }
    (nodes, weights)
}

/// The optical system, SI units. See the module docs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OpticalSystem {
    /// Clear aperture diameter of the DOE, metres (the paper: 5 mm).
    pub aperture: f64,
    /// DOE-to-lens distance d_phi, metres.
    pub doe_to_lens: f64,
    /// Thin-lens focal length g, metres (the paper: 35 mm).
    pub focal_length: f64,
    /// Lens-to-sensor distance d_s, metres (g for a scene at infinity in focus).
    pub lens_to_sensor: f64,
    /// Distance of the point source in front of the DOE, metres; `None` = infinity
    /// (a plane wave). A finite distance gives a diverging spherical wave at the DOE.
    pub object_distance: Option<f64>,
    /// Sensor pixel pitch, metres (the paper: 4.29 um).
    pub sensor_pitch: f64,
    /// Sensor window, pixels per side, centred on the optical axis (the paper: 320).
    pub crop: usize,
    /// Sub-samples per pixel and axis for pixel integration (1 = point sampling).
    pub subsample: usize,
    /// Their quadrature rule.
    #[serde(default)]
    pub pixel_rule: PixelRule,
    /// Pupil sample pitch for the single-transform method, metres (the transfer-function
    /// methods sample the pupil at `sensor_pitch / subsample`, the pitch they keep).
    pub pupil_pitch: f64,
    /// Side of the square pupil window, metres (at least the aperture).
    pub pupil_window: f64,
    /// Wavelengths, metres, one PSF channel each (the paper: 635 / 530 / 450 nm).
    pub wavelengths: Vec<f64>,
    /// The DOE material.
    pub material: Material,
    /// How the DOE heights are resampled onto a pupil grid of another pitch.
    pub interpolation: Interpolation,
    /// Treat each pupil sample as a square cell of constant height (a piecewise-constant
    /// surface, as a pixelated mask writes it) rather than a point sample: the field's angular
    /// spectrum gets the cell's envelope `sinc(fx dx) sinc(fy dx)` (`sinc t = sin(pi t)/(pi t)`).
    /// `false` (point samples) is what the paper's simulation does.
    pub cells: bool,
    /// FFT window side over the pupil samples' side for the transfer-function methods
    /// (`None`: each method's own, 1.5 for the two-step Fresnel method, 2 for the angular
    /// spectrum); rounded up to a fast FFT size. `bench psf` sweeps it.
    #[serde(default)]
    pub padding: Option<f64>,
}

impl Default for OpticalSystem {
    /// The paper's system: 5 mm aperture, g = d_s = 35 mm, 4.29 um pixels, 320 x 320 crop,
    /// RGB 635 / 530 / 450 nm, PDMS, the 1306-sample 4.29 um DOE grid as pupil.
    fn default() -> Self {
        OpticalSystem {
            aperture: PAPER_APERTURE,
            doe_to_lens: DEFAULT_DOE_TO_LENS,
            focal_length: PAPER_FOCAL_LENGTH,
            lens_to_sensor: PAPER_FOCAL_LENGTH,
            object_distance: None,
            sensor_pitch: PAPER_PITCH,
            crop: PAPER_CROP,
            subsample: 1,
            pixel_rule: PixelRule::Midpoint,
            pupil_pitch: PAPER_PITCH,
            pupil_window: crate::design::PAPER_SAMPLES as f64 * PAPER_PITCH,
            wavelengths: PAPER_WAVELENGTHS.to_vec(),
            material: Material::pdms(),
            interpolation: Interpolation::Bilinear,
            cells: false,
            padding: None,
        }
    }
}

/// The paraxial ray-transfer (ABCD) matrix of DOE -> d_phi -> lens g -> d_s:
/// `[[1, d_s], [0, 1]] [[1, 0], [-1/g, 1]] [[1, d_phi], [0, 1]]`, giving
/// `A = 1 - d_s/g`, `B = d_phi + d_s - d_phi d_s / g`, `C = -1/g`, `D = 1 - d_phi/g`
/// (Siegman, Lasers, ch. 15; Collins 1970, JOSA 60, 1168).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Abcd {
    /// `A = 1 - d_s/g`, dimensionless.
    pub a: f64,
    /// `B = d_phi + d_s - d_phi d_s / g`, metres.
    pub b: f64,
    /// `C = -1/g`, 1/metres.
    pub c: f64,
    /// `D = 1 - d_phi/g`, dimensionless.
    pub d: f64,
}

impl OpticalSystem {
    /// Checks every parameter: positive finite distances and pitches, a crop of at least one
    /// pixel, wavelengths within the material's dispersion range, a pupil window that holds
    /// the aperture, a padding from 1 to 16.
    pub fn validate(&self) -> Result<()> {
        let positive = |name: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(Error::param_in(
                    name,
                    Allowed::positive(),
                    format!("must be a positive finite length, got {v} m"),
                ))
            }
        };
        positive("aperture", self.aperture)?;
        positive("doe_to_lens", self.doe_to_lens)?;
        positive("focal_length", self.focal_length)?;
        positive("lens_to_sensor", self.lens_to_sensor)?;
        if let Some(z) = self.object_distance {
            positive("object_distance", z)?;
        }
        positive("sensor_pitch", self.sensor_pitch)?;
        positive("pupil_pitch", self.pupil_pitch)?;
        positive("pupil_window", self.pupil_window)?;
        if self.crop == 0 {
            return Err(Error::param_in(
                "crop",
                Allowed::at_least(1.0),
                "the sensor window needs at least 1 x 1 pixels",
            ));
        }
        if self.subsample == 0 {
            return Err(Error::param_in(
                "subsample",
                Allowed::at_least(1.0),
                "needs at least one sample per pixel",
            ));
        }
        if self.pupil_window < self.aperture {
            return Err(Error::param(
                "pupil_window",
                format!(
                    "{:.4} mm is smaller than the {:.4} mm aperture",
                    self.pupil_window * 1e3,
                    self.aperture * 1e3
                ),
            ));
        }
        if let Some(p) = self.padding {
            if !(p.is_finite() && (1.0..=16.0).contains(&p)) {
                return Err(Error::param_in(
                    "padding",
                    Allowed::between(1.0, 16.0),
                    format!("the FFT window over the pupil's side must be from 1 to 16, got {p}"),
                ));
            }
        }
        if self.wavelengths.is_empty() {
            return Err(Error::param("wavelengths", "needs at least one wavelength"));
        }
        for &l in &self.wavelengths {
            positive("wavelength", l)?;
            self.material.index(l)?;
        }
        Ok(())
    }

    /// The working f-number `g / D`.
    pub fn f_number(&self) -> f64 {
        self.focal_length / self.aperture
    }

    /// The ABCD matrix of the system (see [`Abcd`]).
    pub fn abcd(&self) -> Abcd {
        let (dp, g, ds) = (self.doe_to_lens, self.focal_length, self.lens_to_sensor);
        Abcd { a: 1.0 - ds / g, b: dp + ds - dp * ds / g, c: -1.0 / g, d: 1.0 - dp / g }
    }

    /// Sample pitch on the sensor, `sensor_pitch / subsample`, metres.
    pub fn sample_pitch(&self) -> f64 {
        self.sensor_pitch / self.subsample as f64
    }

    /// Sensor sub-samples per side, `crop * subsample`.
    pub fn samples(&self) -> usize {
        self.crop * self.subsample
    }

    /// Coordinates (metres) of the sensor sub-samples along one axis, centred on the axis,
    /// `subsample` consecutive ones per pixel around the pixel centres
    /// `(j - (crop - 1)/2) sensor_pitch`: for the midpoint rule `x_q = (q - (M - 1)/2) *
    /// sensor_pitch / subsample`, `M = crop * subsample`; for Gauss-Legendre the centre plus
    /// `t_k sensor_pitch / 2` with `t_k` the nodes.
    pub fn sensor_coords(&self) -> Vec<f64> {
        let s = self.subsample;
        match self.pixel_rule {
            PixelRule::Midpoint => {
                let m = self.samples();
                let p = self.sample_pitch();
                (0..m).map(|q| (q as f64 - (m as f64 - 1.0) * 0.5) * p).collect()
            }
            PixelRule::GaussLegendre => {
                let (t, _) = gauss_legendre(s);
                let c = (self.crop as f64 - 1.0) * 0.5;
                (0..self.samples())
                    .map(|q| ((q / s) as f64 - c) * self.sensor_pitch + t[q % s] * 0.5 * self.sensor_pitch)
                    .collect()
            }
        }
    }

    /// The quadrature weight of each sub-sample along one axis (those of a pixel sum to 1).
    pub fn pixel_weights(&self) -> Vec<f64> {
        let s = self.subsample;
        let w: Vec<f64> = match self.pixel_rule {
            PixelRule::Midpoint => vec![1.0 / s as f64; s],
            PixelRule::GaussLegendre => gauss_legendre(s).1.iter().map(|w| 0.5 * w).collect(),
        };
        (0..self.samples()).map(|q| w[q % s]).collect()
    }

    /// Side of the sensor window, metres.
    pub fn sensor_window(&self) -> f64 {
        self.crop as f64 * self.sensor_pitch
    }

    /// The complex field just after the DOE on an `n x n` grid of pitch `pitch`, centred on
    /// the axis, at `wavelength`: `A exp(i k (n - 1) h)` times the incident wave (1 for an object
    /// at infinity; for a finite distance `z_o` the spherical wave `exp(i k (sqrt(r^2 + z_o^2)
    /// - z_o))`, or its paraxial form `exp(i k r^2 / (2 z_o))` when `paraxial`).
    ///
    /// Errors: a DOE grid smaller than the aperture, heights that are not metres, invalid or
    /// non-finite heights inside the aperture (named by row and column).
    pub fn pupil_field(
        &self,
        doe: &Grid,
        n: usize,
        pitch: f64,
        wavelength: f64,
        paraxial: bool,
    ) -> Result<Array2<Complex64>> {
        let heights = self.pupil_heights(doe, n, pitch)?;
        let k = 2.0 * std::f64::consts::PI / wavelength;
        let dn = self.material.index(wavelength)? - 1.0;
        let r2max = (self.aperture * 0.5).powi(2);
        let c = (n as f64 - 1.0) * 0.5;
        let mut field = Array2::<Complex64>::zeros((n, n));
        for ((i, j), v) in field.indexed_iter_mut() {
            let (x, y) = ((j as f64 - c) * pitch, (i as f64 - c) * pitch);
            let r2 = x * x + y * y;
            if r2 <= r2max {
                let mut phase = k * dn * heights[[i, j]];
                if let Some(z) = self.object_distance {
                    phase += if paraxial { k * r2 / (2.0 * z) } else { k * ((r2 + z * z).sqrt() - z) };
                }
                *v = Complex64::from_polar(1.0, phase);
            }
        }
        Ok(field)
    }

    /// The DOE heights on the `n x n` pupil grid of `pitch` (metres), checked inside the
    /// aperture. Outside the aperture the value is 0 and never used.
    pub fn pupil_heights(&self, doe: &Grid, n: usize, pitch: f64) -> Result<Array2<f64>> {
        if doe.unit() != Unit::Metre {
            return Err(Error::param(
                "doe",
                format!("the DOE must hold heights in metres, not '{}'", doe.unit().symbol()),
            ));
        }
        let ext = doe.extent();
        if ext[0] < self.aperture * (1.0 - 1e-9) || ext[1] < self.aperture * (1.0 - 1e-9) {
            return Err(Error::param(
                "aperture",
                format!(
                    "the {:.4} mm aperture is larger than the DOE grid ({:.4} x {:.4} mm)",
                    self.aperture * 1e3,
                    ext[0] * 1e3,
                    ext[1] * 1e3
                ),
            ));
        }
        let (r, c) = doe.dim();
        let g = if takes_doe_samples(doe, n, pitch) {
            let (i0, j0) = ((r - n) / 2, (c - n) / 2);
            doe.crop(i0..i0 + n, j0..j0 + n)?
        } else {
            doe.resample_to(n, n, [pitch, pitch], self.interpolation)?
        };
        let r2max = (self.aperture * 0.5).powi(2);
        let c = (n as f64 - 1.0) * 0.5;
        let mut out = Array2::<f64>::zeros((n, n));
        for ((i, j), v) in out.indexed_iter_mut() {
            let (x, y) = ((j as f64 - c) * pitch, (i as f64 - c) * pitch);
            if x * x + y * y <= r2max {
                let h = g.values()[[i, j]];
                if !g.is_valid(i, j) || !h.is_finite() {
                    return Err(Error::data(
                        DataCause::NotFinite,
                        format!(
                            "the DOE height is missing or not finite inside the aperture \
                         (pupil sample row {i}, column {j}, at x = {:.1} um, y = {:.1} um); \
                         fill the map first",
                            x * 1e6,
                            y * 1e6
                        ),
                    ));
                }
                *v = h;
            }
        }
        Ok(out)
    }

    /// Number of pupil samples per side at `pitch` covering the pupil window, rounded up to
    /// the parity `parity` (0 even, 1 odd).
    pub fn pupil_samples(&self, pitch: f64, parity: usize) -> usize {
        let mut n = (self.pupil_window / pitch - 1e-9).ceil().max(1.0) as usize;
        if n % 2 != parity % 2 {
            n += 1;
        }
        n
    }
}

/// Whether the `n x n` pupil of `pitch` (metres) takes the DOE's own samples: at the DOE's
/// pitch, with the same parity and no more samples, the pupil is a centred crop of the DOE,
/// with no interpolation.
pub fn takes_doe_samples(doe: &Grid, n: usize, pitch: f64) -> bool {
    let (r, c) = doe.dim();
    let same_pitch = doe.pitch().iter().all(|p| (p / pitch - 1.0).abs() < 1e-12);
    same_pitch && r >= n && c >= n && (r - n).is_multiple_of(2) && (c - n).is_multiple_of(2)
}

/// The whole number `k` of pupil samples per DOE sample and axis when the DOE's pitch is `k`
/// times `pitch` along both axes and `k` times the DOE's rows and columns have one parity:
/// then a centred pupil of that parity ([`nested_parity`]) puts `k x k` samples symmetric
/// inside each DOE sample's cell, at least `pitch / 2` from its edges, so that nearest
/// interpolation reads every pupil sample from the DOE sample whose cell holds it (the
/// piecewise-constant surface a pixelated part has, without ties).
pub fn nested_refinement(doe: &Grid, pitch: f64) -> Option<usize> {
    let [px, py] = doe.pitch();
    let k = (px / pitch).round();
    let whole = |p: f64| k >= 1.0 && (p / pitch - k).abs() < 1e-9 * k;
    let k = k as usize;
    let (r, c) = doe.dim();
    (whole(px) && whole(py) && (r * k) % 2 == (c * k) % 2).then_some(k)
}

/// The parity (0 even, 1 odd) of a centred pupil whose samples nest in the DOE's cells at
/// `k` samples per DOE sample ([`nested_refinement`]): that of `k` times the DOE's columns.
pub fn nested_parity(doe: &Grid, k: usize) -> usize {
    (doe.dim().1 * k) % 2
}

/// An optical system as written in a TOML file: every length a string with its unit
/// ("5 mm", "4.29um", "infinity" for the object distance), every field optional (the base
/// system fills the rest), unknown fields refused.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct SystemFile {
    aperture: Option<String>,
    doe_to_lens: Option<String>,
    focal_length: Option<String>,
    lens_to_sensor: Option<String>,
    object_distance: Option<String>,
    sensor_pitch: Option<String>,
    crop: Option<usize>,
    subsample: Option<usize>,
    pixel_rule: Option<PixelRule>,
    pupil_pitch: Option<String>,
    pupil_window: Option<String>,
    wavelengths: Option<Vec<String>>,
    material: Option<String>,
    cells: Option<bool>,
    padding: Option<f64>,
}

impl OpticalSystem {
    /// Reads a system TOML file over `base` (the fields are those of
    /// [`OpticalSystem`], lengths with units, `material` a name as [`Material::by_name`]) and
    /// validates the result. Errors name the file and the field.
    pub fn read_toml(path: &std::path::Path, base: &OpticalSystem) -> Result<OpticalSystem> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let f: SystemFile = toml::from_str(&text).map_err(|e| Error::toml(path, &e))?;
        let length = |field: &str, v: &Option<String>, into: &mut f64| -> Result<()> {
            if let Some(t) = v {
                *into = crate::units::parse_length(t)
                    .map_err(|e| Error::malformed(path, format!("{field}: {e}")))?;
            }
            Ok(())
        };
        let mut s = base.clone();
        length("aperture", &f.aperture, &mut s.aperture)?;
        length("doe_to_lens", &f.doe_to_lens, &mut s.doe_to_lens)?;
        length("focal_length", &f.focal_length, &mut s.focal_length)?;
        length("lens_to_sensor", &f.lens_to_sensor, &mut s.lens_to_sensor)?;
        length("sensor_pitch", &f.sensor_pitch, &mut s.sensor_pitch)?;
        length("pupil_pitch", &f.pupil_pitch, &mut s.pupil_pitch)?;
        length("pupil_window", &f.pupil_window, &mut s.pupil_window)?;
        if let Some(z) = &f.object_distance {
            s.object_distance = if z.trim().eq_ignore_ascii_case("infinity") {
                None
            } else {
                let mut v = 0.0;
                length("object_distance", &Some(z.clone()), &mut v)?;
                Some(v)
            };
        }
        if let Some(w) = &f.wavelengths {
            s.wavelengths = w
                .iter()
                .map(|t| {
                    crate::units::parse_length(t)
                        .map_err(|e| Error::malformed(path, format!("wavelengths: {e}")))
                })
                .collect::<Result<_>>()?;
        }
        if let Some(m) = &f.material {
            s.material =
                Material::by_name(m).map_err(|e| Error::malformed(path, format!("material: {e}")))?;
        }
        s.crop = f.crop.unwrap_or(s.crop);
        s.subsample = f.subsample.unwrap_or(s.subsample);
        s.pixel_rule = f.pixel_rule.unwrap_or(s.pixel_rule);
        s.cells = f.cells.unwrap_or(s.cells);
        if f.padding.is_some() {
            s.padding = f.padding;
        }
        s.validate().map_err(|e| Error::malformed(path, e.to_string()))?;
        Ok(s)
    }
}

/// `sin(pi t) / (pi t)`.
pub fn sinc(t: f64) -> f64 {
    if t.abs() < 1e-8 {
        1.0
    } else {
        (std::f64::consts::PI * t).sin() / (std::f64::consts::PI * t)
    }
}

/// A flat DOE (all heights 0) covering the system's pupil window at its pupil pitch: the
/// reference for Strehl ratios.
pub fn flat_doe(system: &OpticalSystem) -> Result<Grid> {
    let n = system.pupil_samples(system.pupil_pitch, 0);
    Grid::new(Array2::zeros((n, n)), [system.pupil_pitch; 2], Unit::Metre)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_defaults_and_abcd() {
        let s = OpticalSystem::default();
        s.validate().unwrap();
        assert!((s.f_number() - 7.0).abs() < 1e-12);
        let m = s.abcd();
        // In focus: A = 0, B = g whatever d_phi; determinant AD - BC = 1.
        assert!(m.a.abs() < 1e-15 && (m.b - 35e-3).abs() < 1e-15);
        assert!((m.a * m.d - m.b * m.c - 1.0).abs() < 1e-12);
        assert_eq!(s.sensor_coords().len(), 320);
        assert!((s.sensor_coords()[160] - 0.5 * 4.29e-6).abs() < 1e-18);
    }

    #[test]
    fn a_system_file_sets_lengths_with_units_and_names_bad_fields() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("system.toml");
        std::fs::write(
            &p,
            "aperture = \"2.5 mm\"\nfocal_length = \"17.5mm\"\nlens_to_sensor = \"17.5 mm\"\n\
             object_distance = \"infinity\"\nwavelengths = [\"550nm\", \"0.45 um\"]\ncrop = 64\n\
             material = \"fused_silica\"\npixel_rule = \"gauss_legendre\"\npadding = 3\n",
        )
        .unwrap();
        let s = OpticalSystem::read_toml(&p, &OpticalSystem::default()).unwrap();
        assert_eq!((s.aperture, s.focal_length, s.crop), (2.5e-3, 17.5e-3, 64));
        assert!((s.wavelengths[1] - 450e-9).abs() < 1e-20 && (s.f_number() - 7.0).abs() < 1e-12);
        assert_eq!((s.material, s.pixel_rule), (Material::fused_silica(), PixelRule::GaussLegendre));
        assert_eq!(s.padding, Some(3.0));
        for (text, needle) in [
            ("padding = 0.5", "padding"),
            ("aperture = \"5\"", "aperture: "),
            ("lens_to_sensor = \"-3 mm\"", "lens_to_sensor"),
            ("focal = \"3 mm\"", "unknown field `focal`"),
            ("wavelengths = [\"1500 nm\"]", "400-700 nm"),
            ("sensor_pitch = \"4.29 furlongs\"", "sensor_pitch"),
        ] {
            std::fs::write(&p, text).unwrap();
            let e = OpticalSystem::read_toml(&p, &OpticalSystem::default()).unwrap_err().to_string();
            assert!(e.contains(needle) && e.contains("system.toml"), "{text}: {e}");
        }
    }

    #[test]
    fn gauss_legendre_integrates_polynomials_of_degree_2s_minus_1() {
        // Abramowitz and Stegun table 25.4: s = 3 nodes 0, +-sqrt(3/5), weights 8/9, 5/9.
        let (x, w) = gauss_legendre(3);
        assert!((x[2] - 0.6f64.sqrt()).abs() < 1e-15 && x[1].abs() < 1e-15 && x[0] == -x[2]);
        assert!((w[1] - 8.0 / 9.0).abs() < 1e-14 && (w[0] - 5.0 / 9.0).abs() < 1e-14);
        for s in 1..=12 {
            let (x, w) = gauss_legendre(s);
            for d in 0..2 * s {
                let got: f64 = x.iter().zip(&w).map(|(x, w)| w * x.powi(d as i32)).sum();
                let want = if d % 2 == 1 { 0.0 } else { 2.0 / (d as f64 + 1.0) };
                assert!((got - want).abs() < 1e-13, "s {s} degree {d}: {got} vs {want}");
            }
            // Degree 2s is not exact (its error, 2^(2s+1) (s!)^4 / ((2s+1) ((2s)!)^2), is
            // 0.046 at s = 3 and falls below 1e-6 by s = 11).
            if s > 6 {
                continue;
            }
            let got: f64 = x.iter().zip(&w).map(|(x, w)| w * x.powi(2 * s as i32)).sum();
            assert!((got - 2.0 / (2 * s + 1) as f64).abs() > 1e-6, "s {s}");
        }
        // The sensor points of a Gauss-Legendre system lie symmetric about the axis.
        let s = OpticalSystem {
            crop: 5,
            subsample: 4,
            pixel_rule: PixelRule::GaussLegendre,
            ..Default::default()
        };
        let xs = s.sensor_coords();
        assert!((0..20).all(|q| (xs[q] + xs[19 - q]).abs() < 1e-18));
        assert!((s.pixel_weights()[..4].iter().sum::<f64>() - 1.0).abs() < 1e-15);
    }

    #[test]
    fn bad_parameters_are_named() {
        let bad = |f: &dyn Fn(&mut OpticalSystem), needle: &str| {
            let mut s = OpticalSystem::default();
            f(&mut s);
            let e = s.validate().unwrap_err().to_string();
            assert!(e.contains(needle), "{e}");
        };
        bad(&|s| s.doe_to_lens = 0.0, "doe_to_lens");
        bad(&|s| s.lens_to_sensor = -1e-3, "lens_to_sensor");
        bad(&|s| s.object_distance = Some(0.0), "object_distance");
        bad(&|s| s.crop = 0, "crop");
        bad(&|s| s.padding = Some(f64::NAN), "padding");
        bad(&|s| s.pupil_window = 1e-3, "smaller than");
        bad(&|s| s.wavelengths = vec![1.5e-6], "outside the dispersion formula's range 400-700 nm");
    }

    #[test]
    fn pupil_field_refuses_small_grids_and_nan() {
        let s =
            OpticalSystem { aperture: 1e-3, pupil_window: 1.2e-3, pupil_pitch: 10e-6, ..Default::default() };
        let small = Grid::new(Array2::zeros((50, 50)), [10e-6; 2], Unit::Metre).unwrap();
        let e = s.pupil_field(&small, 120, 10e-6, 530e-9, true).unwrap_err();
        assert!(matches!(e, Error::Parameter { ref name, .. } if name == "aperture"), "{e:?}");
        let mut v = Array2::zeros((120, 120));
        v[[60, 61]] = f64::NAN;
        let nan = Grid::new(v, [10e-6; 2], Unit::Metre).unwrap();
        let e = s.pupil_field(&nan, 120, 10e-6, 530e-9, true).unwrap_err();
        assert!(matches!(e, Error::Data { cause: DataCause::NotFinite, .. }), "{e:?}");
        assert!(e.to_string().contains("row 60, column 61"), "{e}");
        // Outside the aperture a NaN does no harm.
        let mut v = Array2::zeros((120, 120));
        v[[0, 0]] = f64::NAN;
        let corner = Grid::new(v, [10e-6; 2], Unit::Metre).unwrap();
        let f = s.pupil_field(&corner, 120, 10e-6, 530e-9, true).unwrap();
        assert_eq!(f[[0, 0]], Complex64::new(0.0, 0.0));
        assert_eq!(f[[60, 60]], Complex64::new(1.0, 0.0));
    }
}
