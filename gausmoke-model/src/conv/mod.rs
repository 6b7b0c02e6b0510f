//! The U-Net's 3D convolutions as one custom op with a hand-written backward pass: on the CPU
//! backends by im2col and matrix products ([`host`]), on the cube backends burn's forward
//! convolutions and a backward pass from burn's dense ops ([`cube`]). The parameters stay
//! burn's `Conv3d` / `ConvTranspose3d` modules; only the arithmetic changes.

#[cfg(feature = "cube")]
mod cube;
pub mod host;
mod op;
mod spec;

use burn::nn::PaddingConfig3d;
use burn::nn::conv::{Conv3d, ConvTranspose3d};
use burn::tensor::Tensor;

pub use op::{ConvBackend, ConvGrads, ConvPasses};
pub use spec::ConvSpec;

fn apply(x: Tensor<5>, weight: Tensor<5>, bias: Tensor<1>, spec: ConvSpec) -> Tensor<5> {
    use burn::backend::Dispatch;
    Tensor::from_dispatch(<Dispatch as ConvBackend>::unet_conv(
        x.into_dispatch(),
        weight.into_dispatch(),
        bias.into_dispatch(),
        spec,
    ))
}

/// `layer`'s convolution of `x [1, C_in, D, H, W]` (explicit padding, no dilation or groups,
/// with a bias).
pub fn conv3d(layer: &Conv3d, x: Tensor<5>) -> Tensor<5> {
    let [_, _, kd, kh, kw] = layer.weight.dims();
    assert!(
        layer.dilation == [1; 3] && layer.groups == 1,
        "the U-Net's convolutions have no dilation or groups"
    );
    let padding = match layer.padding {
        PaddingConfig3d::Valid => [0; 3],
        PaddingConfig3d::Explicit(d, h, w) => [d, h, w],
        PaddingConfig3d::Same => panic!("the U-Net's convolutions pad explicitly"),
    };
    let bias = layer
        .bias
        .as_ref()
        .expect("the U-Net's convolutions have a bias")
        .val();
    let spec = ConvSpec {
        kernel: [kd, kh, kw],
        stride: layer.stride,
        padding,
        transposed: false,
    };
    apply(x, layer.weight.val(), bias, spec)
}

/// `layer`'s transposed convolution of `x [1, C_in, D, H, W]` (no output padding, dilation or
/// groups, with a bias).
pub fn conv_transpose3d(layer: &ConvTranspose3d, x: Tensor<5>) -> Tensor<5> {
    let [_, _, kd, kh, kw] = layer.weight.dims();
    assert!(
        layer.dilation == [1; 3] && layer.groups == 1 && layer.padding_out == [0; 3],
        "the U-Net's transposed convolutions have no dilation, groups or output padding"
    );
    let bias = layer
        .bias
        .as_ref()
        .expect("the U-Net's convolutions have a bias")
        .val();
    let spec = ConvSpec {
        kernel: [kd, kh, kw],
        stride: layer.stride,
        padding: layer.padding,
        transposed: true,
    };
    apply(x, layer.weight.val(), bias, spec)
}
