//! The paper's measurement model, used to train and fine-tune the decoder:
//!
//! `y = clip(h * x + n, 1e-5, 1)`, with `x` the target HDR scene clipped to `[1e-5, 64]`,
//! `h` the PSF of one colour channel, `*` linear convolution and `n` Gaussian read noise of
//! standard deviation 0.02 (the paper's fine-tuning value; Metzler et al. 2020, Sec. 4 and the
//! upstream training code). Optionally, as a real sensor adds: shot noise, `n` of variance
//! `sigma^2 + a (h * x)` (the Poisson-Gaussian model, Foi et al. 2008, with `a` in units of
//! the clipping level), and quantisation to `b` bits, `y = round(y (2^b - 1)) / (2^b - 1)`,
//! before the clip. The exposure is scaled so that a chosen fraction (1-2 %) of the
//! noise-free sensor values `h * x` reach the clipping level 1.
//!
//! Convolution: `(h * x)[i, j] = sum_{u, v} h[u, v] x[i + cy - u, j + cx - v]` with the PSF's
//! centre at `(cy, cx) = (rows / 2, cols / 2)` (the sample that `ifftshift` moves to the
//! origin), computed as a linear convolution by zero-padded FFTs (`rustfft`, sizes of 2, 3 and
//! 5 at least `H + kh - 1` by `W + kw - 1`, so no wrap-around). A scene given with a margin of
//! `(cy, cx)` before and `(kh - 1 - cy, kw - 1 - cx)` after the crop lets light from outside
//! the crop land in it, as in a real capture; [`Convolver::margins`] gives those margins.

use std::sync::Arc;

use ndarray::{s, Array2, Array3};
use rustfft::num_complex::Complex64;
use rustfft::{Fft, FftPlanner};

use crate::error::{Error, Result};
use crate::optics::fft::good_size;
use crate::optics::psf::Psf;
use crate::rng::Lcg;

/// Linear convolution of `(H, W, C)` scenes of one size with a PSF's channels.
pub struct Convolver {
    scene: (usize, usize),
    kernel: (usize, usize),
    fft: (usize, usize),
    row_fft: [Arc<dyn Fft<f64>>; 2],
    col_fft: [Arc<dyn Fft<f64>>; 2],
    /// Each channel's spectrum, column-major (the layout after the transposing 2-D FFT).
    spectra: Vec<Vec<Complex64>>,
}

impl Convolver {
    /// Plans the convolution of `(rows, cols, C)` scenes with `psf` (C = its channel count).
    pub fn new(psf: &Psf, scene: (usize, usize)) -> Result<Convolver> {
        let kernel = psf.dim();
        if scene.0 == 0 || scene.1 == 0 {
            return Err(Error::param("scene size", format!("{scene:?} is empty")));
        }
        let fft = (good_size(scene.0 + kernel.0 - 1, 0), good_size(scene.1 + kernel.1 - 1, 0));
        let mut planner = FftPlanner::new();
        let row_fft = [planner.plan_fft_forward(fft.1), planner.plan_fft_inverse(fft.1)];
        let col_fft = [planner.plan_fft_forward(fft.0), planner.plan_fft_inverse(fft.0)];
        let mut conv = Convolver { scene, kernel, fft, row_fft, col_fft, spectra: Vec::new() };
        let (cy, cx) = (kernel.0 / 2, kernel.1 / 2);
        for ch in &psf.channels {
            // Place h[u, v] at (u - cy, v - cx) modulo the FFT size: output index i then reads
            // x[i - (u - cy)], the convolution above with no shift to undo.
            let mut buf = vec![Complex64::new(0.0, 0.0); fft.0 * fft.1];
            for ((u, v), &h) in ch.grid.values().indexed_iter() {
                let r = (u + fft.0 - cy) % fft.0;
                let c = (v + fft.1 - cx) % fft.1;
                buf[r * fft.1 + c] = Complex64::new(h, 0.0);
            }
            conv.spectra.push(conv.transform(buf, false));
        }
        Ok(conv)
    }

    /// Scene margins `(top, left, bottom, right)` that hold the light reaching a crop.
    pub fn margins(&self) -> (usize, usize, usize, usize) {
        let (cy, cx) = (self.kernel.0 / 2, self.kernel.1 / 2);
        (cy, cx, self.kernel.0 - 1 - cy, self.kernel.1 - 1 - cx)
    }

    /// 2-D FFT of a row-major `fft.0 x fft.1` buffer: rows, transpose, rows. The forward result
    /// is column-major; the inverse takes column-major and returns row-major, normalised.
    fn transform(&self, data: Vec<Complex64>, inverse: bool) -> Vec<Complex64> {
        let (r, c) = self.fft;
        let k = usize::from(inverse);
        let (first, second, n1, n2) = if inverse {
            (&self.col_fft[k], &self.row_fft[k], r, c)
        } else {
            (&self.row_fft[k], &self.col_fft[k], c, r)
        };
        let mut data = data;
        let mut scratch = vec![
            Complex64::new(0.0, 0.0);
            first.get_inplace_scratch_len().max(second.get_inplace_scratch_len())
        ];
        first.process_with_scratch(&mut data, &mut scratch[..first.get_inplace_scratch_len()]);
        let mut t = vec![Complex64::new(0.0, 0.0); r * c];
        transpose::transpose(&data, &mut t, n1, n2);
        second.process_with_scratch(&mut t, &mut scratch[..second.get_inplace_scratch_len()]);
        if inverse {
            let scale = 1.0 / (r * c) as f64;
            t.iter_mut().for_each(|v| *v *= scale);
        }
        t
    }

    /// `h * x` per channel, the same size as the scene (zero outside it).
    pub fn convolve(&self, scene: &Array3<f32>) -> Result<Array3<f64>> {
        let (h, w, nc) = scene.dim();
        if (h, w) != self.scene || nc != self.spectra.len() {
            return Err(Error::param(
                "scene",
                format!(
                    "is {h} x {w} x {nc}; this convolver was planned for {} x {} x {}",
                    self.scene.0,
                    self.scene.1,
                    self.spectra.len()
                ),
            ));
        }
        let (fr, fc) = self.fft;
        let mut out = Array3::zeros((h, w, nc));
        for (ch, spectrum) in self.spectra.iter().enumerate() {
            let mut buf = vec![Complex64::new(0.0, 0.0); fr * fc];
            for ((i, j), &v) in scene.slice(s![.., .., ch]).indexed_iter() {
                buf[i * fc + j] = Complex64::new(v as f64, 0.0);
            }
            let mut spec = self.transform(buf, false);
            spec.iter_mut().zip(spectrum).for_each(|(a, b)| *a *= b);
            let back = self.transform(spec, true);
            for i in 0..h {
                for j in 0..w {
                    out[[i, j, ch]] = back[i * fc + j].re;
                }
            }
        }
        Ok(out)
    }
}

/// Parameters of the measurement model (defaults: the paper's fine-tuning values).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct MeasurementModel {
    /// Standard deviation of the Gaussian read noise, in units of the clipping level.
    pub noise_sigma: f64,
    /// Shot noise: variance `shot_noise * y` (units of the clipping level; 0 = none).
    pub shot_noise: f64,
    /// Bit depth of the capture (`None`: not quantised).
    pub bits: Option<u32>,
    /// The fraction of saturated sensor values is drawn uniformly from this range.
    pub saturation: (f64, f64),
    /// Target HDR range (the loss compares against the clipped target).
    pub target_range: (f32, f32),
    /// Sensor range: the capture is clipped to it.
    pub sensor_range: (f32, f32),
}

impl Default for MeasurementModel {
    fn default() -> Self {
        MeasurementModel {
            noise_sigma: 0.02,
            shot_noise: 0.0,
            bits: None,
            saturation: (0.01, 0.02),
            target_range: (1e-5, 64.0),
            sensor_range: (1e-5, 1.0),
        }
    }
}

/// One simulated training pair.
#[derive(Debug, Clone)]
pub struct Measurement {
    /// The clipped, exposure-scaled target HDR (crop size).
    pub target: Array3<f32>,
    /// The simulated capture `y` (crop size).
    pub capture: Array3<f32>,
    /// The exposure factor applied to the scene.
    pub exposure: f64,
    /// Fraction of noise-free sensor values `h * x >= 1` in the crop.
    pub saturated_fraction: f64,
}

/// Simulates one capture of `scene`, which holds the crop plus the convolver's margins (see
/// the module docs). Refuses a scene too dark to expose (its brightest values are zero).
pub fn measure(
    scene: &Array3<f32>,
    conv: &Convolver,
    model: &MeasurementModel,
    rng: &mut Lcg,
) -> Result<Measurement> {
    let (t, l, b, r) = conv.margins();
    let (h, w, _) = scene.dim();
    let (ch, cw) = (h - t - b, w - l - r);
    let crop = |a: &Array3<f64>| a.slice(s![t..t + ch, l..l + cw, ..]).to_owned();
    // Exposure: the (1 - f) quantile of the unscaled sensor values is set to 1.
    let f = model.saturation.0 + (model.saturation.1 - model.saturation.0) * rng.uniform();
    let blurred = crop(&conv.convolve(scene)?);
    let mut v: Vec<f64> = blurred.iter().copied().collect();
    let k = (((1.0 - f) * v.len() as f64) as usize).min(v.len() - 1);
    let (_, q, _) = v.select_nth_unstable_by(k, f64::total_cmp);
    let q = *q;
    if !(q > 0.0 && q.is_finite()) {
        return Err(Error::Data(format!(
            "the scene's {:.1} % brightest sensor values are {q}: cannot set an exposure",
            100.0 * f
        )));
    }
    let exposure = 1.0 / q;
    let (lo, hi) = model.target_range;
    let scaled = scene.mapv(|x| ((x as f64 * exposure) as f32).clamp(lo, hi));
    let sensor = crop(&conv.convolve(&scaled)?);
    let saturated_fraction = sensor.iter().filter(|&&y| y >= 1.0).count() as f64 / sensor.len() as f64;
    let (slo, shi) = model.sensor_range;
    let levels = model.bits.map(|b| ((1u64 << b) - 1) as f64);
    let capture = sensor.mapv(|y| {
        let sd = (model.noise_sigma.powi(2) + model.shot_noise * y.max(0.0)).sqrt();
        let v = y + sd * rng.normal();
        let v = levels.map_or(v, |l| (v * l).round() / l);
        (v as f32).clamp(slo, shi)
    });
    let target = scaled.slice(s![t..t + ch, l..l + cw, ..]).to_owned();
    Ok(Measurement { target, capture, exposure, saturated_fraction })
}

/// Direct summation of the convolution (for tests: O(H W kh kw)).
pub fn convolve_direct(scene: &Array2<f64>, psf: &Array2<f64>) -> Array2<f64> {
    let (h, w) = scene.dim();
    let (kh, kw) = psf.dim();
    let (cy, cx) = (kh as isize / 2, kw as isize / 2);
    Array2::from_shape_fn((h, w), |(i, j)| {
        let mut s = 0.0;
        for ((u, v), &k) in psf.indexed_iter() {
            let (y, x) = (i as isize + cy - u as isize, j as isize + cx - v as isize);
            if y >= 0 && x >= 0 && (y as usize) < h && (x as usize) < w {
                s += k * scene[[y as usize, x as usize]];
            }
        }
        s
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::{Grid, Unit};
    use crate::optics::psf::Channel;

    fn psf_of(kernels: &[Array2<f64>]) -> Psf {
        let channels = kernels
            .iter()
            .enumerate()
            .map(|(c, k)| Channel {
                name: format!("C{c}"),
                wavelength: None,
                grid: Grid::new(k.clone(), [4.29e-6, 4.29e-6], Unit::Dimensionless).unwrap(),
                captured: None,
            })
            .collect();
        Psf::new(channels, "test").unwrap()
    }

    #[test]
    fn fft_convolution_equals_direct_summation() {
        let mut g = Lcg(7);
        let scene = Array3::from_shape_fn((13, 18, 3), |_| g.uniform() as f32 * 10.0);
        // Odd and even kernel sizes; per PSF a dense, a one-tap and a sparse channel.
        for (kh, kw) in [(5, 4), (3, 7), (6, 6)] {
            let kernels = [
                Array2::from_shape_fn((kh, kw), |_| g.uniform()),
                Array2::from_shape_fn((kh, kw), |(i, j)| if i == 0 && j == kw - 1 { 1.0 } else { 0.0 }),
                Array2::from_shape_fn((kh, kw), |_| g.uniform().powi(4)),
            ];
            let psf = psf_of(&kernels);
            let conv = Convolver::new(&psf, (13, 18)).unwrap();
            let fast = conv.convolve(&scene).unwrap();
            for c in 0..3 {
                let x = scene.slice(s![.., .., c]).mapv(f64::from);
                let direct = convolve_direct(&x, psf.channels[c].grid.values());
                let err = (&fast.slice(s![.., .., c]) - &direct).iter().fold(0.0f64, |m, d| m.max(d.abs()));
                assert!(err < 1e-12, "{kh} x {kw}, channel {c}: {err}");
            }
            // The one-tap kernel is a pure shift: h[0, kw - 1] reads x[i + cy, j + cx - kw + 1].
            let (cy, cx) = (kh / 2, kw / 2);
            let (i, j) = (5, 9);
            assert!((fast[[i, j, 1]] - scene[[i + cy, j + cx + 1 - kw, 1]] as f64).abs() < 1e-12);
        }
        // A scene of the wrong size is refused.
        let conv = Convolver::new(
            &psf_of(&[Array2::ones((3, 3)), Array2::ones((3, 3)), Array2::ones((3, 3))]),
            (13, 18),
        );
        assert!(conv.unwrap().convolve(&Array3::zeros((12, 18, 3))).is_err());
    }

    #[test]
    fn exposure_saturates_the_chosen_fraction() {
        let k = Array2::from_shape_fn((9, 9), |(i, j)| {
            (-((i as f64 - 4.0).powi(2) + (j as f64 - 4.0).powi(2)) / 4.0).exp()
        });
        let psf = psf_of(&[k.clone(), k.clone(), k]);
        let conv = Convolver::new(&psf, (72, 72)).unwrap();
        let mut g = Lcg(3);
        // A log-normal scene: dynamic range of a few hundred, nothing clipped at 64 after scaling.
        let scene = Array3::from_shape_fn((72, 72, 3), |_| (1.2 * g.normal()).exp() as f32);
        let model = MeasurementModel::default();
        for seed in 0..5 {
            let m = measure(&scene, &conv, &model, &mut Lcg(seed)).unwrap();
            assert_eq!(m.capture.dim(), (64, 64, 3));
            assert!((0.0099..=0.0201).contains(&m.saturated_fraction), "{}", m.saturated_fraction);
            assert!(m.capture.iter().all(|&y| (1e-5..=1.0).contains(&y)));
            assert!(m.target.iter().all(|&x| (1e-5..=64.0).contains(&x)));
        }
        // A black scene cannot be exposed.
        assert!(measure(&Array3::zeros((72, 72, 3)), &conv, &model, &mut Lcg(1)).is_err());
    }
}
