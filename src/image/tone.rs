//! Pictures of linear HDR images for people: an exposure and the sRGB transfer function.

use ndarray::Array3;

use crate::image::Image;

/// Tone-maps linear HDR to 8-bit sRGB at exposure `ev` stops: `v = clip(y 2^ev, 0, 1)`, then
/// the sRGB transfer function (IEC 61966-2-1: `12.92 v` below 0.0031308, else
/// `1.055 v^(1/2.4) - 0.055`), rounded to 8 bits.
pub fn tone_map(y: &Image<f32>, ev: f64) -> Array3<u8> {
    let gain = 2f64.powf(ev);
    y.values.mapv(|v| {
        let v = (v as f64 * gain).clamp(0.0, 1.0);
        let s = if v <= 0.0031308 { 12.92 * v } else { 1.055 * v.powf(1.0 / 2.4) - 0.055 };
        (s * 255.0).round() as u8
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tone_map_follows_srgb() {
        let y = Image::new(Array3::from_shape_vec((1, 4, 1), vec![0.0, 0.5, 1.0, 8.0]).unwrap());
        let t = tone_map(&y, 0.0);
        assert_eq!(t.iter().copied().collect::<Vec<_>>(), vec![0, 188, 255, 255]);
        assert_eq!(tone_map(&y, -3.0)[[0, 3, 0]], 255);
        assert_eq!(tone_map(&y, -4.0)[[0, 3, 0]], 188);
    }
}
