//! The image decoder of the paper: its U-Net ([`unet`]), the weights format ([`weights`]),
//! the measurement model used to train it ([`measurement`]), reconstruction of captures
//! ([`reconstruct`]), fine-tuning for one fabricated part's PSF ([`finetune`]) and seeded
//! procedural HDR scenes to train on without a data set ([`scenes`]). Its benchmarks are in
//! [`crate::bench`], its charts in [`crate::charts`].
//!
//! Images here are `(H, W, 3)` `f32` arrays (row-major, channels last, as the paper's NHWC);
//! the network runs on NCHW burn tensors on the CPU (burn's Flex backend) or, with the `cuda`
//! feature, on an NVIDIA GPU.

pub mod dataset;
pub mod finetune;
pub mod measurement;
pub mod reconstruct;
pub mod scenes;
pub mod unet;
pub mod weights;

use burn::tensor::{Device, Tensor, TensorData};
use ndarray::Array4;

use crate::error::Result;
use crate::image::Image;
use unet::{tensor_values, UNet};

/// The device the decoder runs on: burn's Flex CPU backend, or with `gpu` the first CUDA GPU,
/// which needs a build with the `cuda` feature (refused otherwise, rather than running on the
/// CPU unasked).
pub fn device(gpu: bool) -> Result<Device> {
    if !gpu {
        return Ok(Device::flex());
    }
    #[cfg(feature = "cuda")]
    return Ok(Device::cuda(0));
    #[cfg(not(feature = "cuda"))]
    Err(crate::error::Error::param("gpu", "this build has no GPU backend; rebuild with `--features cuda`"))
}

/// The paper's decoder trained with the simulated PSF, the default starting point of
/// fine-tuning: compiled into the binary (see [`weights::BUILT_IN`]).
pub fn default_init() -> std::path::PathBuf {
    std::path::PathBuf::from("built-in:paper-simulated-psf")
}

/// A batch of images of one size as an NCHW tensor on `device`.
pub fn to_tensor(images: &[&Image<f32>], device: &Device) -> Tensor<4> {
    let (h, w, c) = images[0].dim();
    let mut data: Vec<f32> = Vec::with_capacity(images.len() * h * w * c);
    for img in images {
        assert_eq!(img.dim(), (h, w, c), "a batch of one size");
        for ch in 0..c {
            data.extend(img.values.index_axis(ndarray::Axis(2), ch).iter());
        }
    }
    Tensor::from_data(TensorData::new(data, [images.len(), c, h, w]), device)
}

/// An NCHW tensor back as `(N, H, W, C)`.
pub fn from_tensor(t: Tensor<4>) -> Result<Array4<f32>> {
    let [n, c, h, w] = t.dims();
    let v = tensor_values(t)?;
    let nchw = Array4::from_shape_vec((n, c, h, w), v).expect("tensor shape");
    Ok(nchw.permuted_axes([0, 2, 3, 1]).as_standard_layout().to_owned())
}

/// The network's output for one RGB image (H, W multiples of 16), no clamping.
pub fn infer(net: &UNet, x: &Image<f32>) -> Result<Image<f32>> {
    let y = from_tensor(net.forward(to_tensor(&[x], net.device()))?)?;
    Ok(Image::new(y.index_axis_move(ndarray::Axis(0), 0)))
}
