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
//! `h * x` is [`Convolver`]'s linear convolution (`crate::optics::convolve`), over the crop
//! plus the PSF's margins, so light from outside the crop lands in it as in a real capture.

use ndarray::s;

use crate::error::{Error, Result};
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
    /// Where each channel clips, fraction of the sensor range's top: a camera's white balance
    /// can leave a channel clipping below full scale (the paper's camera clips green at 231 of
    /// 255; [`crate::calibration::clipping`]), and a decoder that never saw such a channel
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
        }
    }
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
    let scaled = Image::new(scene.values.mapv(|x| ((x as f64 * exposure) as f32).clamp(lo, hi)));
    let sensor = crop(&conv.convolve(&scaled)?);
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
    use crate::optics::convolve::psf_of;
    use ndarray::{Array2, Array3};

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
        // A black scene cannot be exposed.
        assert!(measure(&Image::new(Array3::zeros((72, 72, 3))), &conv, &model, &mut Lcg(1)).is_err());
    }
}
