//! The paper's measurement model, used to train and fine-tune the decoder:
//!
//! `y = clip(h * x + n, 1e-5, c)`, with `c` the channel's clipping level (1, or lower where the
//! camera clips the channel below full scale: [`MeasurementModel::channel_clipping`]), `x` the
//! target HDR scene clipped to `[1e-5, 64]`,
//! `h` the PSF of one colour channel, `*` linear convolution and `n` Gaussian read noise of
//! standard deviation 0.02 (the paper's fine-tuning value; Metzler et al. 2020, Sec. 4 and the
//! upstream training code). Optionally, as a real sensor adds: shot noise, `n` of variance
//! `sigma^2 + a (h * x)` (the Poisson-Gaussian model, Foi et al. 2008, with `a` in units of
//! the clipping level), and quantisation to `b` bits, `y = round(y (2^b - 1)) / (2^b - 1)`,
//! before the clip. The exposure is scaled so that a chosen fraction (1-2 %) of the
//! noise-free sensor values `h * x` reach the clipping level 1.
//!
//! *Halo* ([`Halo`]): a fabricated element also scatters light well beyond its measured PSF's
//! crop (roughness, the replica's haze), which the crop, normalised to sum 1, does not hold. The
//! PSF is then `(1 - eta) h + eta G_rho`, `G_rho` a Gaussian of `rho` pixels: measured on the
//! paper's captures against their bracket-merged references (`doefab bench forward`), about
//! `eta` 0.1-0.15 at `rho` 64-128 px.
//!
//! `h * x` is [`Convolver`]'s linear convolution (`crate::optics::convolve`), over the crop
//! plus the PSF's margins, so light from outside the crop lands in it as in a real capture.

use ndarray::{s, Array2, Array3, Axis};

use crate::error::{DataCause, Error, Result};
use crate::image::Image;
use crate::optics::convolve::Convolver;
use crate::rng::Lcg;

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
    /// The light spread beyond the PSF's crop (`None`: none; see the module docs).
    pub halo: Option<Halo>,
    /// Where each channel clips, fraction of the sensor range's top: a camera's white balance
    /// can leave a channel clipping below full scale (the paper's camera clips green at 231 of
    /// 255; `crate::calibration::clipping`), and a decoder that never saw such a channel
    /// reads its clipped value as light.
    pub channel_clipping: [f32; 3],
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
            channel_clipping: [1.0; 3],
            halo: None,
        }
    }
}

/// Light a fabricated element spreads beyond its measured PSF: a fraction `eta` of all light,
/// in a Gaussian of standard deviation `radius_px` sensor pixels (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Halo {
    /// `eta`: the fraction of all light in the halo, in `[0, 1)`.
    pub fraction: f64,
    /// `rho`: the Gaussian's standard deviation, sensor pixels.
    pub radius_px: f64,
}

impl Halo {
    /// Refuses a fraction outside `[0, 1)` or a radius that is not positive.
    pub fn check(&self) -> Result<()> {
        if !((0.0..1.0).contains(&self.fraction) && self.radius_px > 0.0 && self.radius_px.is_finite()) {
            return Err(Error::param(
                "halo",
                format!(
                    "fraction {} must lie in [0, 1) and radius {} px be positive",
                    self.fraction, self.radius_px
                ),
            ));
        }
        Ok(())
    }

    /// `(1 - eta) y + eta G_rho * x` for every channel: `y` the scene `x` through the measured
    /// PSF, both the same size.
    pub fn apply(&self, through_psf: &mut Array3<f64>, scene: &Array3<f64>) -> Result<()> {
        for c in 0..scene.dim().2 {
            let wide = halo_blur(&scene.index_axis(Axis(2), c).to_owned(), self.radius_px)?;
            let mut y = through_psf.index_axis_mut(Axis(2), c);
            y.zip_mut_with(&wide, |y, w| *y = (1.0 - self.fraction) * *y + self.fraction * w);
        }
        Ok(())
    }
}

/// `G_rho * x` for one channel, `rho` = `radius_px`: the Gaussian's edge-normalised blur
/// ([`crate::grid::blur::blur_samples`]) of the means of `b x b` blocks, `b = floor(rho / 8)`
/// (at least 1), interpolated back bilinearly between block centres. The blocks widen the
/// Gaussian by their own variance, `rho^2 + b^2 / 12` plus the interpolation's, under 0.2 % of
/// `rho` for `b = rho / 8`, at a `b^2`-th of the direct blur's cost.
pub fn halo_blur(channel: &Array2<f64>, radius_px: f64) -> Result<Array2<f64>> {
    let (h, w) = channel.dim();
    let b = ((radius_px / 8.0).floor() as usize).max(1);
    let (nh, nw) = (h.div_ceil(b), w.div_ceil(b));
    let blocks = Array2::from_shape_fn((nh, nw), |(i, j)| {
        let block = channel.slice(s![i * b..((i + 1) * b).min(h), j * b..((j + 1) * b).min(w)]);
        block.sum() / block.len() as f64
    });
    let blurred = crate::grid::blur::blur_samples(&blocks, radius_px / b as f64)?;
    let at = |x: usize, n: usize| {
        let t = ((x as f64 - (b as f64 - 1.0) / 2.0) / b as f64).clamp(0.0, (n - 1) as f64);
        let k = (t.floor() as usize).min(n.saturating_sub(2));
        (k, (k + 1).min(n - 1), t - k as f64)
    };
    Ok(Array2::from_shape_fn((h, w), |(i, j)| {
        let (i0, i1, ty) = at(i, nh);
        let (j0, j1, tx) = at(j, nw);
        (1.0 - ty) * ((1.0 - tx) * blurred[[i0, j0]] + tx * blurred[[i0, j1]])
            + ty * ((1.0 - tx) * blurred[[i1, j0]] + tx * blurred[[i1, j1]])
    }))
}

/// The scene through the PSF (and the halo, if any), uncropped.
fn through(scene: &Image<f32>, conv: &Convolver, halo: Option<&Halo>) -> Result<Image> {
    let mut y = conv.convolve(scene)?;
    if let Some(halo) = halo {
        halo.apply(&mut y.values, &scene.values.mapv(f64::from))?;
    }
    Ok(y)
}

/// One simulated training pair.
#[derive(Debug, Clone)]
pub struct Measurement {
    /// The clipped, exposure-scaled target HDR (crop size).
    pub target: Image<f32>,
    /// The simulated capture `y` (crop size).
    pub capture: Image<f32>,
    /// The exposure factor applied to the scene.
    pub exposure: f64,
    /// Fraction of noise-free sensor values `h * x >= 1` in the crop.
    pub saturated_fraction: f64,
}

/// Simulates one capture of `scene`, which holds the crop plus the convolver's margins (see
/// the module docs). Refuses a scene too dark to expose (its brightest values are zero).
pub fn measure(
    scene: &Image<f32>,
    conv: &Convolver,
    model: &MeasurementModel,
    rng: &mut Lcg,
) -> Result<Measurement> {
    let (t, l, b, r) = conv.margins();
    let (h, w, _) = scene.dim();
    let (ch, cw) = (h - t - b, w - l - r);
    let crop = |a: &Image| a.values.slice(s![t..t + ch, l..l + cw, ..]).to_owned();
    // Exposure: the (1 - f) quantile of the unscaled sensor values is set to 1.
    let f = model.saturation.0 + (model.saturation.1 - model.saturation.0) * rng.uniform();
    let blurred = crop(&through(scene, conv, model.halo.as_ref())?);
    let mut v: Vec<f64> = blurred.iter().copied().collect();
    let k = (((1.0 - f) * v.len() as f64) as usize).min(v.len() - 1);
    let (_, q, _) = v.select_nth_unstable_by(k, f64::total_cmp);
    let q = *q;
    if !(q > 0.0 && q.is_finite()) {
        let cause = if q.is_finite() { DataCause::Empty } else { DataCause::NotFinite };
        return Err(Error::data(
            cause,
            format!("the scene's {:.1} % brightest sensor values are {q}: cannot set an exposure", 100.0 * f),
        ));
    }
    let exposure = 1.0 / q;
    let (lo, hi) = model.target_range;
    let scaled = Image::new(scene.values.mapv(|x| ((x as f64 * exposure) as f32).clamp(lo, hi)));
    let sensor = crop(&through(&scaled, conv, model.halo.as_ref())?);
    let saturated_fraction = sensor.iter().filter(|&&y| y >= 1.0).count() as f64 / sensor.len() as f64;
    let (slo, shi) = model.sensor_range;
    let levels = model.bits.map(|b| ((1u64 << b) - 1) as f64);
    let mut capture = sensor.mapv(|y| {
        let sd = (model.noise_sigma.powi(2) + model.shot_noise * y.max(0.0)).sqrt();
        let v = y + sd * rng.normal();
        let v = levels.map_or(v, |l| (v * l).round() / l);
        v as f32
    });
    for ((_, _, c), v) in capture.indexed_iter_mut() {
        let top = shi * model.channel_clipping.get(c).copied().unwrap_or(1.0);
        *v = v.clamp(slo, top.max(slo));
    }
    let target = Image::new(scaled.values.slice(s![t..t + ch, l..l + cw, ..]).to_owned());
    Ok(Measurement { target, capture: Image::new(capture), exposure, saturated_fraction })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The halo's blocked blur against the direct Gaussian blur of a random image: the same to
    /// 1 % (RMS over the mean) at radii where blocks are used, and exactly below 8 px.
    #[test]
    fn the_halo_blur_is_the_gaussian_blur() {
        let mut g = Lcg(5);
        let img = Array2::from_shape_fn((150, 170), |_| (1.5 * g.normal()).exp());
        for radius in [4.0, 16.0, 40.0] {
            let fast = halo_blur(&img, radius).unwrap();
            let exact = crate::grid::blur::blur_samples(&img, radius).unwrap();
            let rms = ((&fast - &exact).mapv(|d| d * d).mean().unwrap()).sqrt() / exact.mean().unwrap();
            assert!(rms < if radius < 8.0 { 1e-12 } else { 1e-2 }, "{radius}: {rms}");
        }
        assert!(Halo { fraction: 1.0, radius_px: 4.0 }.check().is_err());
        assert!(Halo { fraction: 0.1, radius_px: 0.0 }.check().is_err());
    }
    use crate::optics::convolve::psf_of;

    #[test]
    fn exposure_saturates_the_chosen_fraction() {
        let k = Array2::from_shape_fn((9, 9), |(i, j)| {
            (-((i as f64 - 4.0).powi(2) + (j as f64 - 4.0).powi(2)) / 4.0).exp()
        });
        let psf = psf_of(&[k.clone(), k.clone(), k]);
        let conv = Convolver::new(&psf, (72, 72)).unwrap();
        let mut g = Lcg(3);
        // A log-normal scene: dynamic range of a few hundred, nothing clipped at 64 after scaling.
        let scene = Image::new(Array3::from_shape_fn((72, 72, 3), |_| (1.2 * g.normal()).exp() as f32));
        let model = MeasurementModel::default();
        for seed in 0..5 {
            let m = measure(&scene, &conv, &model, &mut Lcg(seed)).unwrap();
            assert_eq!(m.capture.dim(), (64, 64, 3));
            assert!((0.0099..=0.0201).contains(&m.saturated_fraction), "{}", m.saturated_fraction);
            assert!(m.capture.values.iter().all(|&y| (1e-5..=1.0).contains(&y)));
            assert!(m.target.values.iter().all(|&x| (1e-5..=64.0).contains(&x)));
        }
        // A camera whose green clips at 231 of 255: green piles up there, red and blue at 1.
        let top = 231.0 / 255.0;
        let camera = MeasurementModel { channel_clipping: [1.0, top as f32, 1.0], bits: Some(8), ..model };
        let m = measure(&scene, &conv, &camera, &mut Lcg(7)).unwrap();
        let at = |c: usize, v: f32| {
            m.capture.values.index_axis(ndarray::Axis(2), c).iter().filter(|&&y| y == v).count()
        };
        assert!(m.capture.values.index_axis(ndarray::Axis(2), 1).iter().all(|&y| y <= top as f32));
        assert!(
            at(1, top as f32) > 10 && at(0, 1.0) > 10 && at(1, 1.0) == 0,
            "{} {}",
            at(1, top as f32),
            at(0, 1.0)
        );
        // A halo takes its fraction of the light from the PSF's image into a wide Gaussian:
        // the saturated fraction is still the one asked for, and the halo's light is there.
        let halo = MeasurementModel {
            halo: Some(Halo { fraction: 0.15, radius_px: 16.0 }),
            noise_sigma: 0.0,
            ..model
        };
        let m = measure(&scene, &conv, &halo, &mut Lcg(9)).unwrap();
        assert!((0.0099..=0.0201).contains(&m.saturated_fraction), "{}", m.saturated_fraction);
        // A black scene cannot be exposed.
        assert!(measure(&Image::new(Array3::zeros((72, 72, 3))), &conv, &model, &mut Lcg(1)).is_err());
    }
}
