//! Linear convolution of images with a PSF, the image formation `y = h * x` of the paper's
//! camera model (Metzler et al. 2020, Eq. 1) per colour channel:
//!
//! `(h * x)[i, j] = sum_{u, v} h[u, v] x[i + cy - u, j + cx - v]` with the PSF's
//! centre at `(cy, cx) = (rows / 2, cols / 2)` (the sample that `ifftshift` moves to the
//! origin), computed as a linear convolution by zero-padded FFTs (`rustfft`, sizes of 2, 3 and
//! 5 at least `H + kh - 1` by `W + kw - 1`, so no wrap-around). A scene given with a margin of
//! `(cy, cx)` before and `(kh - 1 - cy, kw - 1 - cx)` after the crop lets light from outside
//! the crop land in it, as in a real capture; [`Convolver::margins`] gives those margins.

use ndarray::{s, Array2, Array3};
use rustfft::num_complex::Complex64;

use crate::error::{Error, Result};
use crate::fft::{good_size, Plan2d};
use crate::image::Image;
use crate::optics::psf::Psf;

/// Linear convolution of `(H, W, C)` scenes of one size with a PSF's channels.
pub struct Convolver {
    scene: (usize, usize),
    kernel: (usize, usize),
    fft: (usize, usize),
    plan: Plan2d,
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
        let plan = Plan2d::rect(fft.0, fft.1);
        let mut conv = Convolver { scene, kernel, fft, plan, spectra: Vec::new() };
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
            conv.spectra.push(conv.plan.forward_transposed(buf));
        }
        Ok(conv)
    }

    /// Scene margins `(top, left, bottom, right)` that hold the light reaching a crop.
    pub fn margins(&self) -> (usize, usize, usize, usize) {
        let (cy, cx) = (self.kernel.0 / 2, self.kernel.1 / 2);
        (cy, cx, self.kernel.0 - 1 - cy, self.kernel.1 - 1 - cx)
    }

    /// `h * x` per channel, the same size as the scene (zero outside it).
    pub fn convolve(&self, scene: &Image<f32>) -> Result<Image> {
        let scene = &scene.values;
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
            let mut spec = self.plan.forward_transposed(buf);
            spec.iter_mut().zip(spectrum).for_each(|(a, b)| *a *= b);
            let back = self.plan.inverse_transposed(spec);
            for i in 0..h {
                for j in 0..w {
                    out[[i, j, ch]] = back[i * fc + j].re;
                }
            }
        }
        Ok(Image::new(out))
    }
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

/// A PSF of the given kernels, one channel each, at the paper's 4.29 um pitch (for tests).
#[cfg(test)]
pub(crate) fn psf_of(kernels: &[Array2<f64>]) -> Psf {
    use crate::grid::{Grid, Unit};
    let channels = kernels
        .iter()
        .enumerate()
        .map(|(c, k)| crate::optics::psf::Channel {
            name: format!("C{c}"),
            wavelength: None,
            grid: Grid::new(k.clone(), [4.29e-6, 4.29e-6], Unit::Dimensionless).unwrap(),
            captured: None,
        })
        .collect();
    Psf::new(channels, "test").unwrap()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Lcg;

    #[test]
    fn fft_convolution_equals_direct_summation() {
        let mut g = Lcg(7);
        let scene = Image::new(Array3::from_shape_fn((13, 18, 3), |_| g.uniform() as f32 * 10.0));
        // Odd and even kernel sizes; per PSF a dense, a one-tap and a sparse channel.
        for (kh, kw) in [(5, 4), (3, 7), (6, 6)] {
            let kernels = [
                Array2::from_shape_fn((kh, kw), |_| g.uniform()),
                Array2::from_shape_fn((kh, kw), |(i, j)| if i == 0 && j == kw - 1 { 1.0 } else { 0.0 }),
                Array2::from_shape_fn((kh, kw), |_| g.uniform().powi(4)),
            ];
            let psf = psf_of(&kernels);
            let conv = Convolver::new(&psf, (13, 18)).unwrap();
            let fast = conv.convolve(&scene).unwrap().values;
            let scene = &scene.values;
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
        assert!(conv.unwrap().convolve(&Image::new(Array3::zeros((12, 18, 3)))).is_err());
    }
}
