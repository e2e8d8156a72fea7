//! Multi-channel images, the shared data model of calibration and the decoder: captures,
//! bracket-merged radiance, references, simulated measurements, training scenes and
//! reconstructions.
//!
//! An [`Image`] is `(H, W, C)` samples, row 0 at the top, channel last (the layout of PNG, EXR
//! and the paper's NHWC network), linear in the light: counts divided by the full-scale count
//! for a capture (1 = the sensor clips), or radiance in the same unit for an HDR image. Its
//! element type is `f64` where images are measured and compared (calibration) and `f32` where
//! they feed the network (the decoder); [`Image::to_f32`] and [`Image::to_f64`] convert.
//! A [`crate::Grid`] is one channel with a physical pitch; an image's pixels are the sensor's.
//! Pictures of them for people (exposure, sRGB) are in [`tone`].

pub mod tone;

use ndarray::{Array2, Array3};

/// An `(H, W, C)` image (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Image<T = f64> {
    /// `values[[row, col, channel]]`.
    pub values: Array3<T>,
}

impl<T> Image<T> {
    /// An image of the given samples.
    pub fn new(values: Array3<T>) -> Image<T> {
        Image { values }
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.values.dim().0
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.values.dim().1
    }

    /// Channels (1 for grayscale, 3 for RGB).
    pub fn channels(&self) -> usize {
        self.values.dim().2
    }
}

impl Image<f64> {
    /// The image in `f32` (rounded to nearest).
    pub fn to_f32(&self) -> Image<f32> {
        Image::new(self.values.mapv(|v| v as f32))
    }

    /// The channel mean at each pixel.
    pub fn channel_mean(&self) -> Array2<f64> {
        let c = self.channels() as f64;
        self.values.sum_axis(ndarray::Axis(2)) / c
    }
}

impl Image<f32> {
    /// The image in `f64` (exact).
    pub fn to_f64(&self) -> Image<f64> {
        Image::new(self.values.mapv(f64::from))
    }
}

/// Element access and array operations (`img[[i, j, c]]`, `iter`, `mapv`, slicing) go to the
/// samples.
impl<T> std::ops::Deref for Image<T> {
    type Target = Array3<T>;
    fn deref(&self) -> &Array3<T> {
        &self.values
    }
}

impl<T> std::ops::DerefMut for Image<T> {
    fn deref_mut(&mut self) -> &mut Array3<T> {
        &mut self.values
    }
}

impl<'a, T> IntoIterator for &'a Image<T> {
    type Item = &'a T;
    type IntoIter = ndarray::iter::Iter<'a, T, ndarray::Ix3>;
    fn into_iter(self) -> Self::IntoIter {
        self.values.iter()
    }
}

impl<T> From<Array3<T>> for Image<T> {
    fn from(values: Array3<T>) -> Image<T> {
        Image::new(values)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dimensions_and_conversions() {
        let img = Image::new(Array3::from_shape_fn((2, 3, 3), |(i, j, k)| (i * 9 + j * 3 + k) as f64 + 0.1));
        assert_eq!((img.height(), img.width(), img.channels()), (2, 3, 3));
        assert_eq!(img.dim(), (2, 3, 3));
        let back = img.to_f32().to_f64();
        assert!(back.values.iter().zip(&img.values).all(|(a, b)| (a - b).abs() < 1e-6 && a != b));
        assert_eq!(img.to_f32().to_f64().to_f32(), img.to_f32());
        // Channel mean of pixel (1, 2): values 15.1, 16.1, 17.1.
        assert!((img.channel_mean()[[1, 2]] - 16.1).abs() < 1e-12);
    }
}
