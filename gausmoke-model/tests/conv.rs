//! The U-Net's convolution op against burn's own Conv3d / ConvTranspose3d modules on every CPU
//! backend: outputs and the gradients of the input, weights and bias, for each layer shape
//! the U-Net uses (3^3 padded, 2^3 strided down, 2^3 transposed up, 1^3).
//!
//! Tolerance: both sum the same products in different orders (ours tiles im2col through
//! `gemm`): measured within 6e-7 of each tensor's largest magnitude (2026-11-23,
//! `GAUSMOKE_PRINT_ERRORS=1 ... -- --nocapture`); bound 1e-5.
#![allow(clippy::disallowed_methods)] // tests read tensors freely; the library counts its reads

use burn::nn::PaddingConfig3d;
use burn::nn::conv::{Conv3dConfig, ConvTranspose3dConfig};
use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_model::conv::{conv_transpose3d, conv3d};
use gausmoke_render::backends::cpu_devices;

fn random(shape: [usize; 5], seed: u64, device: &Device) -> Tensor<5> {
    let mut rng = SplitMix64::new(seed);
    let values: Vec<f32> = (0..shape.iter().product::<usize>())
        .map(|_| rng.range(-1.0, 1.0))
        .collect();
    Tensor::from_data(TensorData::new(values, shape), device)
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

fn assert_close(what: &str, ours: &[f32], burns: &[f32]) {
    assert_eq!(ours.len(), burns.len(), "{what}: length");
    let scale = burns.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let worst = ours
        .iter()
        .zip(burns)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    if std::env::var_os("GAUSMOKE_PRINT_ERRORS").is_some() {
        eprintln!("{what}: max |diff| {worst:.2e} of {scale:.2e}");
    }
    assert!(scale > 0.0, "{what}: vacuous");
    assert!(
        worst <= 1e-5 * scale,
        "{what}: max |diff| {worst} vs scale {scale}"
    );
}

/// Forward values and input, weight and bias gradients of `sum(y * w)` through burn's layer
/// (`ours = false`) or our op.
fn run(input: [usize; 5], layer: &LayerKind, ours: bool, device: &Device) -> [Vec<f32>; 4] {
    let x = random(input, 1, device).require_grad();
    device.seed(7);
    let (y, weight, bias) = match layer {
        LayerKind::Conv {
            channels,
            kernel,
            stride,
            padding,
        } => {
            let conv = Conv3dConfig::new(*channels, [*kernel; 3])
                .with_stride([*stride; 3])
                .with_padding(PaddingConfig3d::Explicit(*padding, *padding, *padding))
                .init(device);
            let y = if ours {
                conv3d(&conv, x.clone())
            } else {
                conv.forward(x.clone())
            };
            (y, conv.weight.val(), conv.bias.clone().unwrap().val())
        }
        LayerKind::Transposed { channels } => {
            let conv = ConvTranspose3dConfig::new(*channels, [2; 3])
                .with_stride([2; 3])
                .init(device);
            let y = if ours {
                conv_transpose3d(&conv, x.clone())
            } else {
                conv.forward(x.clone())
            };
            (y, conv.weight.val(), conv.bias.clone().unwrap().val())
        }
    };
    let w = random(y.dims(), 2, device);
    let grads = (y.clone() * w).sum().backward();
    [
        host(y),
        host(x.grad(&grads).unwrap()),
        host(weight.grad(&grads).unwrap()),
        host(bias.grad(&grads).unwrap()),
    ]
}

enum LayerKind {
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

#[test]
fn matches_burns_convolutions_and_their_gradients() {
    let layers = [
        (
            [1, 12, 8, 12, 4],
            LayerKind::Conv {
                channels: [12, 8],
                kernel: 3,
                stride: 1,
                padding: 1,
            },
        ),
        (
            [1, 8, 8, 12, 4],
            LayerKind::Conv {
                channels: [8, 16],
                kernel: 2,
                stride: 2,
                padding: 0,
            },
        ),
        (
            [1, 16, 4, 6, 2],
            LayerKind::Transposed { channels: [16, 8] },
        ),
        (
            [1, 8, 8, 12, 4],
            LayerKind::Conv {
                channels: [8, 3],
                kernel: 1,
                stride: 1,
                padding: 0,
            },
        ),
    ];
    for (backend, device) in cpu_devices() {
        let device = device.autodiff();
        for (i, (input, layer)) in layers.iter().enumerate() {
            let burns = run(*input, layer, false, &device);
            let ours = run(*input, layer, true, &device);
            for (name, (a, b)) in ["output", "grad x", "grad weight", "grad bias"]
                .iter()
                .zip(ours.iter().zip(&burns))
            {
                assert_close(&format!("{backend}, layer {i}: {name}"), a, b);
            }
        }
    }
}
