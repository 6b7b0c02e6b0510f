//! The U-Net's convolutions as a burn backend extension: on the CPU backends [`super::host`]
//! (im2col and `gemm`; burn-flex computes a 3D convolution's weight gradient as a convolution
//! whose kernel is the whole output gradient, which dominated training time), on the cube
//! backends burn's convolutions forward and [`super::cube`]'s backward (burn-cubecl computes
//! the weight gradient the same way).

// NdArray is deprecated in burn 0.22; see gausmoke-render's op module. The macro names it too.
#![allow(deprecated)]

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, TensorMetadata, backend_extension};
use gausmoke_render::primitives::{from_vec, to_vec};

use super::host::{self, ConvGeometry};
use super::spec::ConvSpec;

#[backend_extension(
    Cube: cfg(feature = "cube"),
    NdArray: cfg(feature = "ndarray"),
    Flex: cfg(feature = "flex"),
    Autodiff,
)]
pub trait ConvBackend: Backend {
    /// `spec`'s convolution (or transposed convolution) of `x [1, C_in, D, H, W]` with
    /// `weight` and `bias [C_out]` (burn's layouts: `[C_out, C_in, k...]` for a convolution,
    /// `[C_in, C_out, k...]` for a transposed one).
    fn unet_conv(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        spec: ConvSpec,
    ) -> FloatTensor<Self>;
}

/// Gradients of one convolution.
#[derive(Debug)]
pub struct ConvGrads<B: Backend> {
    pub x: FloatTensor<B>,
    pub weight: FloatTensor<B>,
    pub bias: FloatTensor<B>,
}

/// The forward and backward passes of the U-Net's convolutions on one backend.
pub trait ConvPasses: Backend {
    fn conv_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        spec: ConvSpec,
    ) -> FloatTensor<Self>;

    fn conv_backward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        spec: ConvSpec,
    ) -> ConvGrads<Self>;
}

/// The geometry of `spec` on `x`'s shape, seen as a plain convolution (a transposed
/// convolution is the adjoint of the convolution from its output grid to its input grid).
fn geometry(spec: &ConvSpec, x_shape: &[usize], weight_shape: &[usize]) -> ConvGeometry {
    assert_eq!(x_shape.len(), 5, "the U-Net convolves [1, C, D, H, W]");
    assert_eq!(x_shape[0], 1, "the U-Net convolves one grid at a time");
    let input = [x_shape[2], x_shape[3], x_shape[4]];
    if spec.transposed {
        let output = spec.transposed_output(input);
        ConvGeometry {
            channels_in: weight_shape[1],
            channels_out: weight_shape[0],
            input: output,
            kernel: spec.kernel,
            stride: spec.stride,
            padding: spec.padding,
        }
    } else {
        ConvGeometry {
            channels_in: weight_shape[1],
            channels_out: weight_shape[0],
            input,
            kernel: spec.kernel,
            stride: spec.stride,
            padding: spec.padding,
        }
    }
}

fn output_shape(g: &ConvGeometry, transposed: bool) -> Vec<usize> {
    let (channels, cells) = if transposed {
        (g.channels_in, g.input)
    } else {
        (g.channels_out, g.output())
    };
    vec![1, channels, cells[0], cells[1], cells[2]]
}

macro_rules! cpu_conv_passes {
    ($backend:ty) => {
        impl ConvPasses for $backend {
            fn conv_forward(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                bias: FloatTensor<Self>,
                spec: ConvSpec,
            ) -> FloatTensor<Self> {
                let device = x.device();
                let g = geometry(&spec, &x.shape(), &weight.shape());
                let (x, weight, bias) = (
                    to_vec::<Self>(x),
                    to_vec::<Self>(weight),
                    to_vec::<Self>(bias),
                );
                let y = if spec.transposed {
                    let mut y = host::adjoint(&g, &x, &weight);
                    let cells = g.input_cells();
                    for (channel, b) in y.chunks_mut(cells).zip(&bias) {
                        channel.iter_mut().for_each(|v| *v += b);
                    }
                    y
                } else {
                    host::forward(&g, &x, &weight, &bias)
                };
                from_vec::<Self>(y, output_shape(&g, spec.transposed), &device)
            }

            fn conv_backward(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                grad: FloatTensor<Self>,
                spec: ConvSpec,
            ) -> ConvGrads<Self> {
                let device = x.device();
                let (x_shape, weight_shape) = (x.shape().to_vec(), weight.shape().to_vec());
                let g = geometry(&spec, &x_shape, &weight_shape);
                let (x, weight, grad) = (
                    to_vec::<Self>(x),
                    to_vec::<Self>(weight),
                    to_vec::<Self>(grad),
                );
                let (grad_x, grad_weight, grad_bias) = if spec.transposed {
                    // y = adjoint(x): dx = forward(dy), dW = weight_grad(dy, x).
                    let no_bias = vec![0.0; g.channels_out];
                    let grad_x = {
                        let _phase = gausmoke_core::phase!("convolution input gradient");
                        host::forward(&g, &grad, &weight, &no_bias)
                    };
                    let grad_weight = {
                        let _phase = gausmoke_core::phase!("convolution weight gradient");
                        host::weight_grad(&g, &grad, &x)
                    };
                    (
                        grad_x,
                        grad_weight,
                        host::channel_sums(&grad, g.channels_in),
                    )
                } else {
                    let grad_x = {
                        let _phase = gausmoke_core::phase!("convolution input gradient");
                        host::adjoint(&g, &grad, &weight)
                    };
                    let grad_weight = {
                        let _phase = gausmoke_core::phase!("convolution weight gradient");
                        host::weight_grad(&g, &x, &grad)
                    };
                    (
                        grad_x,
                        grad_weight,
                        host::channel_sums(&grad, g.channels_out),
                    )
                };
                let bias_len = grad_bias.len();
                ConvGrads {
                    x: from_vec::<Self>(grad_x, x_shape, &device),
                    weight: from_vec::<Self>(grad_weight, weight_shape, &device),
                    bias: from_vec::<Self>(grad_bias, vec![bias_len], &device),
                }
            }
        }
    };
}

#[cfg(feature = "ndarray")]
cpu_conv_passes!(burn::backend::NdArray);
#[cfg(feature = "flex")]
cpu_conv_passes!(burn::backend::Flex);

#[cfg(feature = "cube")]
impl ConvPasses for burn_cubecl::CubeBackend {
    fn conv_forward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        spec: ConvSpec,
    ) -> FloatTensor<Self> {
        use burn::backend::ops::ModuleOps;
        if spec.transposed {
            Self::conv_transpose3d(x, weight, Some(bias), spec.transpose_options())
        } else {
            Self::conv3d(x, weight, Some(bias), spec.options())
        }
    }

    fn conv_backward(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        spec: ConvSpec,
    ) -> ConvGrads<Self> {
        super::cube::conv_backward(x, weight, grad, spec)
    }
}

/// The public op on a backend that implements the passes.
macro_rules! conv_op_from_passes {
    ($backend:ty) => {
        impl ConvBackend for $backend {
            fn unet_conv(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                bias: FloatTensor<Self>,
                spec: ConvSpec,
            ) -> FloatTensor<Self> {
                <Self as ConvPasses>::conv_forward(x, weight, bias, spec)
            }
        }
    };
}

#[cfg(feature = "ndarray")]
conv_op_from_passes!(burn::backend::NdArray);
#[cfg(feature = "flex")]
conv_op_from_passes!(burn::backend::Flex);
#[cfg(feature = "cube")]
conv_op_from_passes!(burn_cubecl::CubeBackend);

#[derive(Debug, Clone)]
struct ConvState<B: Backend> {
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    spec: ConvSpec,
}

#[derive(Debug)]
struct ConvBackward;

impl<B: ConvPasses> Backward<B, 3> for ConvBackward {
    type State = ConvState<B>;

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let ConvState { x, weight, spec } = ops.state;
        let ConvGrads {
            x: grad_x,
            weight: grad_weight,
            bias: grad_bias,
        } = {
            let _phase = gausmoke_core::phase!("convolution backward");
            B::conv_backward(x, weight, grad, spec)
        };
        for (parent, grad) in ops
            .parents
            .into_iter()
            .zip([grad_x, grad_weight, grad_bias])
        {
            if let Some(node) = parent {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

impl<B: ConvPasses, C: CheckpointStrategy> ConvBackend for Autodiff<B, C> {
    fn unet_conv(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: FloatTensor<Self>,
        spec: ConvSpec,
    ) -> FloatTensor<Self> {
        let nodes = [x.node(), weight.node(), bias.node()];
        let (x, weight) = (x.into_primitive(), weight.into_primitive());
        let output = {
            let _phase = gausmoke_core::phase!("convolution");
            B::conv_forward(x.clone(), weight.clone(), bias.into_primitive(), spec)
        };
        match ConvBackward.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish(ConvState { x, weight, spec }, output),
            OpsKind::UnTracked(prep) => prep.finish(output),
        }
    }
}
