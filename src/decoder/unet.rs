//! The paper's reconstruction U-Net (upstream `my_medium_model`, 630,820 parameters) in burn.
//!
//! Layer by layer as `deepoptics-hdr/DECODER.md` describes it: five encoder levels of two
//! 3x3 'SAME' convolutions with bias and ReLU, 2x2 max-pooling between levels (none after the
//! bottleneck); four decoder levels of a 4x4 stride-2 transposed convolution (padding 1, so the
//! output is exactly twice the input), inference BatchNorm and ReLU, each followed by a 1x1
//! "fuse" convolution of `cat[decoder, skip]` without activation; a head of a 1x1 conv to 3
//! channels, BatchNorm, and a 1x1 fuse of `cat[head, x]`. No output activation: the output is
//! linear HDR radiance on the input's scale (1 = sensor clipping) and can be negative.
//!
//! BatchNorm always uses the stored moving statistics, as TensorLayer evaluates it:
//! `y = x a + (beta - mean a)`, `a = gamma / sqrt(var + 1e-5)`. Fine-tuning trains gamma and
//! beta but keeps the moving statistics frozen (a batch of 8 crops is too small to re-estimate
//! them, and frozen statistics make the network the same function in training and inference).
//!
//! Tensors live flattened, one per checkpoint entry, in burn's layouts: conv weights
//! `[out, in, kh, kw]` and transposed-conv weights `[in, out, kh, kw]`, both the TF array
//! permuted by `(3, 2, 0, 1)` (DECODER.md, "Conversions for other frameworks"). Activations are
//! NCHW. Inputs must have H and W that are multiples of 16 (four poolings), checked here.

use burn::tensor::module::{conv2d, conv_transpose2d, max_pool2d};
use burn::tensor::ops::{ConvOptions, ConvTransposeOptions, MaxPoolOptions};
use burn::tensor::{Device, Tensor, TensorData};
use ndarray::{ArrayD, IxDyn};

use crate::decoder::weights::{tensor_specs, DecoderWeights, NamedTensor};
use crate::error::{Error, Result};

/// BatchNorm epsilon of TensorLayer 1.11.1's `BatchNormLayer` (DECODER.md).
pub const BN_EPS: f32 = 1e-5;

/// Spatial sizes must be multiples of this (2^4 for four 2x2 poolings).
pub const SIZE_MULTIPLE: usize = 16;

/// The U-Net with its parameters on one device.
#[derive(Debug, Clone)]
pub struct UNet {
    names: Vec<String>,
    /// Shapes in burn's layouts.
    shapes: Vec<Vec<usize>>,
    /// Flattened tensors in checkpoint order.
    params: Vec<Tensor<1>>,
    device: Device,
}

/// Whether the checkpoint entry `name` is trained (all but the BatchNorm moving statistics).
pub fn is_trainable(name: &str) -> bool {
    !name.ends_with(".moving_mean") && !name.ends_with(".moving_variance")
}

/// TF layout -> burn layout for rank-4 tensors (permutation (3, 2, 0, 1)); others unchanged.
fn to_burn(t: &NamedTensor) -> (Vec<usize>, Vec<f32>) {
    if t.shape.len() != 4 {
        return (t.shape.clone(), t.values.clone());
    }
    let a = ArrayD::from_shape_vec(IxDyn(&t.shape), t.values.clone()).expect("shape checked on load");
    let p = a.permuted_axes(IxDyn(&[3, 2, 0, 1]));
    (p.shape().to_vec(), p.as_standard_layout().iter().copied().collect())
}

/// burn layout -> TF layout for rank-4 tensors (the inverse permutation (2, 3, 1, 0)).
fn to_tf(shape: &[usize], values: Vec<f32>) -> NamedTensor {
    if shape.len() != 4 {
        return NamedTensor { shape: shape.to_vec(), values };
    }
    let a = ArrayD::from_shape_vec(IxDyn(shape), values).expect("shape kept by the network");
    let p = a.permuted_axes(IxDyn(&[2, 3, 1, 0]));
    NamedTensor { shape: p.shape().to_vec(), values: p.as_standard_layout().iter().copied().collect() }
}

impl UNet {
    /// Builds the network from decoder weights on `device`.
    pub fn from_weights(weights: &DecoderWeights, device: &Device) -> UNet {
        let mut names = Vec::with_capacity(60);
        let mut shapes = Vec::with_capacity(60);
        let mut params = Vec::with_capacity(60);
        for (name, t) in &weights.tensors {
            let (shape, values) = to_burn(t);
            let n = values.len();
            params.push(Tensor::from_data(TensorData::new(values, [n]), device));
            names.push(name.clone());
            shapes.push(shape);
        }
        UNet { names, shapes, params, device: device.clone() }
    }

    /// The parameters back in the TF layouts (metadata left empty for the caller).
    pub fn to_weights(&self) -> Result<DecoderWeights> {
        let mut tensors = Vec::with_capacity(60);
        for ((name, shape), p) in self.names.iter().zip(&self.shapes).zip(&self.params) {
            tensors.push((name.clone(), to_tf(shape, tensor_values(p.clone())?)));
        }
        debug_assert_eq!(tensors.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>(), {
            tensor_specs().into_iter().map(|(n, _)| n).collect::<Vec<_>>()
        });
        Ok(DecoderWeights { tensors, metadata: Default::default() })
    }

    /// The device the parameters live on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Checkpoint names, in order.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Flattened parameters, in checkpoint order.
    pub fn params(&self) -> &[Tensor<1>] {
        &self.params
    }

    /// Replaces the parameters (same count and lengths: the optimiser's output).
    pub fn set_params(&mut self, params: Vec<Tensor<1>>) {
        assert_eq!(params.len(), self.params.len(), "one tensor per checkpoint entry");
        self.params = params;
    }

    fn index(&self, name: &str) -> usize {
        self.names.iter().position(|n| n == name).unwrap_or_else(|| panic!("no tensor {name}"))
    }

    fn p1(&self, name: &str) -> Tensor<1> {
        self.params[self.index(name)].clone()
    }

    fn p4(&self, name: &str) -> Tensor<4> {
        let i = self.index(name);
        let s = &self.shapes[i];
        self.params[i].clone().reshape([s[0], s[1], s[2], s[3]])
    }

    /// Convolution with bias: 3x3 'SAME' (padding 1) or 1x1, stride 1, cross-correlation.
    fn conv(&self, x: Tensor<4>, name: &str) -> Tensor<4> {
        let w = self.p4(&format!("{name}.weight"));
        let pad = w.dims()[2] / 2;
        conv2d(x, w, Some(self.p1(&format!("{name}.bias"))), ConvOptions::new([1, 1], [pad, pad], [1, 1], 1))
    }

    /// Inference BatchNorm over channels, TensorLayer's evaluation order.
    fn bn(&self, x: Tensor<4>, name: &str) -> Tensor<4> {
        let gamma = self.p1(&format!("{name}.gamma"));
        let beta = self.p1(&format!("{name}.beta"));
        let mean = self.p1(&format!("{name}.moving_mean"));
        let var = self.p1(&format!("{name}.moving_variance"));
        let c = gamma.dims()[0];
        let a = gamma * (var + BN_EPS).sqrt().recip();
        let shift = beta - mean * a.clone();
        x * a.reshape([1, c, 1, 1]) + shift.reshape([1, c, 1, 1])
    }

    /// `tf.nn.conv2d_transpose` 4x4, stride 2, 'SAME' == burn's transposed conv with padding 1.
    fn up(&self, x: Tensor<4>, name: &str) -> Tensor<4> {
        conv_transpose2d(
            x,
            self.p4(&format!("{name}.weight")),
            Some(self.p1(&format!("{name}.bias"))),
            ConvTransposeOptions::new([2, 2], [1, 1], [0, 0], [1, 1], 1),
        )
    }

    /// The network on an NCHW batch `x` (`x = PNG / 255`, H and W multiples of 16).
    pub fn forward(&self, x: Tensor<4>) -> Result<Tensor<4>> {
        let [_, c, h, w] = x.dims();
        if c != 3 || h == 0 || w == 0 || !h.is_multiple_of(SIZE_MULTIPLE) || !w.is_multiple_of(SIZE_MULTIPLE)
        {
            return Err(Error::param(
                "decoder input",
                format!("is {c} x {h} x {w}; the U-Net needs 3 channels and H, W multiples of 16"),
            ));
        }
        let relu = |t: Tensor<4>| t.clamp_min(0.0);
        let pool = |t: Tensor<4>| max_pool2d(t, MaxPoolOptions::new([2, 2]));
        let mut skips = Vec::with_capacity(4);
        let mut e = x.clone();
        for level in 1..=5 {
            if level > 1 {
                e = pool(e);
            }
            e = relu(self.conv(e, &format!("enc{level}.conv1")));
            e = relu(self.conv(e, &format!("enc{level}.conv2")));
            if level < 5 {
                skips.push(e.clone());
            }
        }
        let mut d = e;
        for level in 1..=4 {
            if level > 1 {
                let skip = skips.pop().expect("four skips");
                d = self.conv(Tensor::cat(vec![d, skip], 1), &format!("dec{level}.fuse"));
            }
            d = relu(self.bn(self.up(d, &format!("dec{level}.deconv")), &format!("dec{level}.bn")));
        }
        let skip = skips.pop().expect("four skips");
        let f5 = self.conv(Tensor::cat(vec![d, skip], 1), "dec5.fuse");
        let hb = self.bn(self.conv(f5, "head.conv"), "head.bn");
        Ok(self.conv(Tensor::cat(vec![hb, x], 1), "head.fuse"))
    }
}

/// Reads a tensor's values back as `f32`.
pub fn tensor_values<const D: usize>(t: Tensor<D>) -> Result<Vec<f32>> {
    t.into_data()
        .try_into_vec::<f32>()
        .map_err(|e| Error::internal(format!("cannot read a tensor back: {e:?}")))
}
