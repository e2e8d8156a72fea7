//! Where the decoder runs and the tensors it is fed: the device selection (CPU, or a GPU with
//! `--gpu`), the paper's simulated-PSF decoder as the default start, and the conversions between
//! images and burn tensors.

use burn::tensor::{Device, Tensor, TensorData};
use ndarray::Array4;

use super::unet::{tensor_values, UNet};
use crate::error::Result;
use crate::image::Image;

/// The device the decoder runs on, and what its selection has to report.
#[derive(Debug, Clone)]
pub struct SelectedDevice {
    /// The burn device the decoder's tensors live on.
    pub device: Device,
    /// Whether the device is a software rasterizer (Mesa's lavapipe or llvmpipe: a "GPU" that
    /// runs on the CPU; lavapipe measured 57 to 117 times slower than the CPU backend).
    pub software: bool,
    /// Set when `--gpu` found no discrete GPU and took another adapter (it names it).
    pub warnings: Vec<String>,
}

/// The device the decoder runs on: burn's Flex CPU backend, or with `gpu`:
///
/// * with the `cuda` feature, the first CUDA GPU;
/// * with the `gpu` feature (burn's wgpu backend: Vulkan on Linux and Windows, with DX12 and
///   OpenGL after it, Metal on macOS), the first discrete GPU of the first graphics API that
///   has a GPU adapter; without a discrete one, the adapter wgpu prefers (an integrated GPU,
///   or a software rasterizer such as Mesa's lavapipe) with a warning naming it; without any
///   adapter, an error saying what to install.
///
/// Without either feature `gpu` is refused rather than run on the CPU unasked. The GPU is
/// opened once per process (burn's runtime registers it for the process) and reused.
pub fn select_device(gpu: bool) -> Result<SelectedDevice> {
    if !gpu {
        return Ok(SelectedDevice { device: Device::flex(), software: false, warnings: Vec::new() });
    }
    #[cfg(feature = "cuda")]
    return Ok(SelectedDevice { device: Device::cuda(0), software: false, warnings: Vec::new() });
    #[cfg(all(feature = "gpu", not(feature = "cuda")))]
    return wgpu_device();
    #[cfg(not(any(feature = "cuda", feature = "gpu")))]
    Err(crate::error::Error::param(
        "gpu",
        "this build has no GPU backend; rebuild with `--features gpu` (any vendor's GPU through wgpu) or \
         `--features cuda`",
    ))
}

/// [`select_device`]'s device alone, for callers that run on the CPU or report no warnings
/// (tests, sweeps).
pub fn device(gpu: bool) -> Result<Device> {
    Ok(select_device(gpu)?.device)
}

/// The wgpu device of [`select_device`], opened on the first call: `Device::wgpu_options()
/// .init()` registers a runtime per adapter selector and refuses a second registration, so the
/// outcome (the device, or why there is none) is kept for the process.
#[cfg(all(feature = "gpu", not(feature = "cuda")))]
fn wgpu_device() -> Result<SelectedDevice> {
    use burn::tensor::wgpu::WgpuInitError;
    use burn::tensor::DeviceKind;
    use std::sync::OnceLock;

    static OPENED: OnceLock<std::result::Result<SelectedDevice, String>> = OnceLock::new();
    let open = || {
        let init = |kind| Device::wgpu_options().device_kind(kind).init();
        match init(DeviceKind::DiscreteGpu(0)) {
            Ok(device) => Ok(SelectedDevice { device, software: false, warnings: Vec::new() }),
            Err(WgpuInitError::AdapterUnavailable { .. }) => match init(DeviceKind::DefaultDevice) {
                Ok(device) => {
                    // cubecl names the card behind an adapter, and none behind a CPU adapter.
                    let (name, software) = device
                        .identity()
                        .map_or(("an unnamed adapter".into(), false), |i| (i.name, i.physical.is_none()));
                    let warning = match software {
                        true => format!(
                            "`gpu` found no GPU; the decoder runs on `{name}`, a software rasterizer on the \
                             CPU, tens of times slower than on the CPU backend"
                        ),
                        false => format!("`gpu` found no discrete GPU; the decoder runs on `{name}`"),
                    };
                    Ok(SelectedDevice { device, software, warnings: vec![warning] })
                }
                Err(WgpuInitError::AdapterUnavailable { .. }) => Err(
                    "no GPU adapter found (Vulkan, DX12 or OpenGL; Metal on macOS): install the GPU's Vulkan \
                     driver (or Mesa's lavapipe, `mesa-vulkan-drivers`, a CPU Vulkan driver), or run without --gpu"
                        .to_string(),
                ),
                Err(e) => Err(format!("cannot open the GPU: {e}")),
            },
            Err(e) => Err(format!("cannot open the discrete GPU: {e}")),
        }
    };
    OPENED.get_or_init(open).clone().map_err(|reason| crate::error::Error::param("gpu", reason))
}

/// The paper's decoder trained with the simulated PSF, the default starting point of
/// fine-tuning: compiled into the binary (see `weights::BUILT_IN`).
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
