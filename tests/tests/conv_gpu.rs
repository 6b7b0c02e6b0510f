//! The U-Net's convolution op on a GPU backend (wgpu; in CI on Mesa's lavapipe) against the
//! same op on the CPU (Flex, whose im2col path `gausmoke-model/tests/conv.rs` checks against
//! burn's own layers): outputs and the gradients of the input, weights and bias for every
//! layer shape the U-Net uses, and for the shapes that take the GPU backward's other branches
//! (a grid plane over 8192 cells; im2col slices split into groups to bound their memory).
//!
//! Like the other GPU tests this FAILS without a GPU adapter rather than skip.
//!
//! Tolerance: both sum the same products in different orders; measured on lavapipe
//! (2026-11-26, `GAUSMOKE_PRINT_ERRORS=1`) within 7e-6 of each tensor's largest magnitude;
//! bound 2e-5.

use burn::nn::PaddingConfig3d;
use burn::nn::conv::{Conv3dConfig, ConvTranspose3dConfig};
use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_model::conv::{conv_transpose3d, conv3d};
use gausmoke_render::backends::{device_by_name, gpu_devices};
use gausmoke_tests::{assert_close, to_vec};

fn random(shape: [usize; 5], seed: u64, device: &Device) -> Tensor<5> {
    let mut rng = SplitMix64::new(seed);
    let values: Vec<f32> = (0..shape.iter().product::<usize>())
        .map(|_| rng.range(-1.0, 1.0))
        .collect();
    Tensor::from_data(TensorData::new(values, shape), device)
}

#[derive(Debug, Clone, Copy)]
enum Layer {
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

/// Output and the input, weight and bias gradients of `sum(y * w)` through our op on `device`;
/// the layer's parameters come from the same seeded initialiser on every device.
fn run(input: [usize; 5], layer: Layer, device: &Device) -> [Vec<f32>; 4] {
    let x = random(input, 1, device).require_grad();
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
            let bias = Tensor::<1>::from_data(
                TensorData::new(vec![0.1; channels[1]], [channels[1]]),
                device,
            )
            .require_grad();
            let conv = burn::nn::conv::Conv3d {
                weight: burn::module::Param::from_tensor(weight.clone()),
                bias: Some(burn::module::Param::from_tensor(bias.clone())),
                ..conv
            };
            (conv3d(&conv, x.clone()), weight, bias)
        }
        Layer::Transposed { channels } => {
            let conv = ConvTranspose3dConfig::new(channels, [2; 3])
                .with_stride([2; 3])
                .init(device);
            let weight = random(conv.weight.dims(), 3, device).require_grad();
            let bias = Tensor::<1>::from_data(
                TensorData::new(vec![0.1; channels[1]], [channels[1]]),
                device,
            )
            .require_grad();
            let conv = burn::nn::conv::ConvTranspose3d {
                weight: burn::module::Param::from_tensor(weight.clone()),
                bias: Some(burn::module::Param::from_tensor(bias.clone())),
                ..conv
            };
            (conv_transpose3d(&conv, x.clone()), weight, bias)
        }
    };
    let w = random(y.dims(), 2, device);
    let grads = (y.clone() * w).sum().backward();
    [
        to_vec(y),
        to_vec(x.grad(&grads).unwrap()),
        to_vec(weight.grad(&grads).unwrap()),
        to_vec(bias.grad(&grads).unwrap()),
    ]
}

fn compare(cases: &[([usize; 5], Layer)]) {
    let (backend, gpu) = gpu_devices()
        .into_iter()
        .next()
        .expect("this test binary is built with gausmoke-model's wgpu feature");
    let cpu = device_by_name("flex").unwrap().autodiff();
    let gpu = gpu.autodiff();
    for (input, layer) in cases {
        let expected = run(*input, *layer, &cpu);
        let actual = run(*input, *layer, &gpu);
        for (name, (a, e)) in ["output", "grad x", "grad weight", "grad bias"]
            .iter()
            .zip(actual.iter().zip(&expected))
        {
            let scale = e.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            assert!(scale > 0.0, "{name}: vacuous");
            assert_close(
                &format!("{backend}, {layer:?} on {input:?}: {name}"),
                a,
                e,
                0.0,
                2e-5,
            );
        }
    }
}

/// The U-Net's layers: 3^3 padded, 2^3 strided down, 2^3 transposed up, 1^3 out.
#[test]
fn the_unet_layers_match_the_cpu_on_the_gpu() {
    compare(&[
        (
            [1, 12, 8, 12, 4],
            Layer::Conv {
                channels: [12, 8],
                kernel: 3,
                stride: 1,
                padding: 1,
            },
        ),
        (
            [1, 8, 8, 12, 4],
            Layer::Conv {
                channels: [8, 16],
                kernel: 2,
                stride: 2,
                padding: 0,
            },
        ),
        ([1, 16, 4, 6, 2], Layer::Transposed { channels: [16, 8] }),
        (
            [1, 8, 8, 12, 4],
            Layer::Conv {
                channels: [8, 3],
                kernel: 1,
                stride: 1,
                padding: 0,
            },
        ),
        // A stride that leaves the last input cells unreached by the forward pass.
        (
            [1, 3, 5, 7, 6],
            Layer::Conv {
                channels: [3, 4],
                kernel: 2,
                stride: 2,
                padding: 0,
            },
        ),
    ]);
}

/// A grid plane of more than 8192 cells (the weight gradient's batches are then rows, not
/// planes), and a 3^3 kernel whose im2col slices exceed the 64 MiB budget together (32
/// channels of a 48^3 grid: split into groups of taps).
#[test]
fn the_large_shapes_of_the_gpu_backward_match_the_cpu() {
    compare(&[
        (
            [1, 2, 3, 96, 96],
            Layer::Conv {
                channels: [2, 3],
                kernel: 3,
                stride: 1,
                padding: 1,
            },
        ),
        (
            [1, 32, 48, 48, 48],
            Layer::Conv {
                channels: [32, 4],
                kernel: 3,
                stride: 1,
                padding: 1,
            },
        ),
    ]);
}
