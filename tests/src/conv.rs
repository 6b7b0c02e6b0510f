//! The U-Net's convolution layers the convolution tests share (`conv.rs`: our op against
//! burn's layers on the CPU; `conv_gpu.rs`: our op on a GPU against the CPU).

use burn::module::Param;
use burn::nn::PaddingConfig3d;
use burn::nn::conv::{Conv3dConfig, ConvTranspose3dConfig};
use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_model::conv::{conv_transpose3d, conv3d};

use crate::to_vec;

/// Uniform values in `[-1, 1)` from `seed`: the same on every device.
pub fn random(shape: [usize; 5], seed: u64, device: &Device) -> Tensor<5> {
    let mut rng = SplitMix64::new(seed);
    let values: Vec<f32> = (0..shape.iter().product::<usize>())
        .map(|_| rng.range(-1.0, 1.0))
        .collect();
    Tensor::from_data(TensorData::new(values, shape), device)
}

/// One layer: a convolution (cubic kernel, stride and padding) or the U-Net's 2^3 transposed
/// convolution with stride 2.
#[derive(Debug, Clone, Copy)]
pub enum Layer {
    Conv {
        channels: [usize; 2],
        kernel: usize,
        stride: usize,
        padding: usize,
    },
    Transposed {
        channels: [usize; 2],
    },
}

impl Layer {
    pub const fn conv(channels: [usize; 2], kernel: usize, stride: usize, padding: usize) -> Self {
        Self::Conv {
            channels,
            kernel,
            stride,
            padding,
        }
    }
}

/// Each layer shape the U-Net uses, on an input of that layer (non-cubic grids): 3^3 padded,
/// 2^3 strided down, 2^3 transposed up, 1^3 out.
pub const UNET_LAYERS: [([usize; 5], Layer); 4] = [
    ([1, 12, 8, 12, 4], Layer::conv([12, 8], 3, 1, 1)),
    ([1, 8, 8, 12, 4], Layer::conv([8, 16], 2, 2, 0)),
    ([1, 16, 4, 6, 2], Layer::Transposed { channels: [16, 8] }),
    ([1, 8, 8, 12, 4], Layer::conv([8, 3], 1, 1, 0)),
];

/// Whose arithmetic convolves: our op (`gausmoke_model::conv`) or burn's layer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arithmetic {
    Ours,
    Burns,
}

/// The output and the input, weight and bias gradients of `sum(y * w)` for seeded input,
/// weights, bias and `w`: the same values on every device.
pub fn outputs_and_gradients(
    input: [usize; 5],
    layer: Layer,
    arithmetic: Arithmetic,
    device: &Device,
) -> [Vec<f32>; 4] {
    let x = random(input, 1, device).require_grad();
    let bias_of = |channels: usize| {
        let values: Vec<f32> = (0..channels).map(|c| 0.1 * c as f32 - 0.2).collect();
        Tensor::<1>::from_data(TensorData::new(values, [channels]), device).require_grad()
    };
    let (y, weight, bias) = match layer {
        Layer::Conv {
            channels,
            kernel,
            stride,
            padding,
        } => {
            let conv = Conv3dConfig::new(channels, [kernel; 3])
                .with_stride([stride; 3])
                .with_padding(PaddingConfig3d::Explicit(padding, padding, padding))
                .init(device);
            let weight = random(conv.weight.dims(), 3, device).require_grad();
            let bias = bias_of(channels[1]);
            let conv = burn::nn::conv::Conv3d {
                weight: Param::from_tensor(weight.clone()),
                bias: Some(Param::from_tensor(bias.clone())),
                ..conv
            };
            let y = match arithmetic {
                Arithmetic::Ours => conv3d(&conv, x.clone()),
                Arithmetic::Burns => conv.forward(x.clone()),
            };
            (y, weight, bias)
        }
        Layer::Transposed { channels } => {
            let conv = ConvTranspose3dConfig::new(channels, [2; 3])
                .with_stride([2; 3])
                .init(device);
            let weight = random(conv.weight.dims(), 3, device).require_grad();
            let bias = bias_of(channels[1]);
            let conv = burn::nn::conv::ConvTranspose3d {
                weight: Param::from_tensor(weight.clone()),
                bias: Some(Param::from_tensor(bias.clone())),
                ..conv
            };
            let y = match arithmetic {
                Arithmetic::Ours => conv_transpose3d(&conv, x.clone()),
                Arithmetic::Burns => conv.forward(x.clone()),
            };
            (y, weight, bias)
        }
    };
    let w = random(y.dims(), 2, device);
    let grads = (y.clone() * w).sum().backward();
    [
        to_vec(y),
        to_vec(x.grad(&grads).expect("x has a gradient")),
        to_vec(weight.grad(&grads).expect("the weight has a gradient")),
        to_vec(bias.grad(&grads).expect("the bias has a gradient")),
    ]
}

/// What [`outputs_and_gradients`] returns, in its order.
pub const RESULTS: [&str; 4] = ["output", "grad x", "grad weight", "grad bias"];
