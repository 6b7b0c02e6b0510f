//! The U-Net's convolution backward pass on the cube backends, from burn's dense ops.
//!
//! burn-cubecl's weight gradient convolves the input with the whole output gradient as the
//! kernel (on a 64^3 grid, a "kernel" of 64^3 cells over an output of 3^3 cells); its backward
//! pass was 72% of the training time at the paper's sizes on an H100. Here the weight gradient
//! is im2col slices and a batched matrix product whose batches split the grid, summed
//! afterwards, and the input gradient is a forward convolution (or transposed convolution) of
//! the output gradient: 16% faster there, measured side by side, and still most of the time
//! (docs/BENCHMARKS.md, "Training on an H100").

use burn::backend::ops::{FloatTensorOps, ModuleOps};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Shape, TensorMetadata};
use burn::tensor::Slice;
use burn::tensor::ops::{ConvOptions, ConvTransposeOptions};
use burn_cubecl::CubeBackend;

use super::op::ConvGrads;
use super::spec::ConvSpec;

type B = CubeBackend;

/// The most bytes one group of im2col slices may take: a 3^3 kernel on 32 channels of a 64^3
/// grid would otherwise take 0.9 GB at once, and wgpu binds at most 128 MiB of one buffer to a
/// kernel by default (a larger one reads as garbage, not as an error).
const COLUMN_BYTES: usize = 64 << 20;

/// Grid cells per batch of the weight gradient's matrix product at most (one `y, z` plane of
/// the grid when it fits): enough batches to fill a GPU, each long enough to amortise a tile.
const CELLS_PER_BATCH: usize = 8192;

/// Gradients of `spec`'s convolution of `x [1, C_in, D, H, W]` with `weight` for the output
/// gradient `grad`.
pub fn conv_backward(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    grad: FloatTensor<B>,
    spec: ConvSpec,
) -> ConvGrads<B> {
    // A transposed convolution is the adjoint of the plain convolution C (weight
    // [C_in, C_out, k] read as C's [out, in, k]) from its output's grid to its input's: its
    // dx = C(dy), and its dW is C's weight gradient with dy as C's input and x as C's output
    // gradient.
    let grad_x = {
        let _phase = gausmoke_core::phase!("convolution input gradient");
        if spec.transposed {
            B::conv3d(grad.clone(), weight, None, spec.options())
        } else {
            input_grad(grad.clone(), weight, &spec, &x.shape())
        }
    };
    let grad_weight = {
        let _phase = gausmoke_core::phase!("convolution weight gradient");
        if spec.transposed {
            weight_grad(grad.clone(), x, &spec)
        } else {
            weight_grad(x, grad.clone(), &spec)
        }
    };
    let grad_bias = {
        let _phase = gausmoke_core::phase!("convolution bias gradient");
        channel_sums(grad)
    };
    ConvGrads {
        x: grad_x,
        weight: grad_weight,
        bias: grad_bias,
    }
}

/// `[C]` sums of `t [1, C, D, H, W]` over the grid, as one reduction along a contiguous axis
/// of `[C, D H W]` (summing the three grid axes one after the other took longer than both
/// gradients together at 64^3 on an H100).
fn channel_sums(t: FloatTensor<B>) -> FloatTensor<B> {
    let [_, channels, d, h, w] = dims5(&t.shape());
    let rows = B::float_reshape(t, Shape::from([channels, d * h * w]));
    B::float_reshape(B::float_sum_dim(rows, 1), Shape::from([channels]))
}

/// The input gradient of a plain convolution: at stride 1 the convolution of `grad` with the
/// flipped, transposed kernel; otherwise the transposed convolution of `grad`.
fn input_grad(
    grad: FloatTensor<B>,
    weight: FloatTensor<B>,
    spec: &ConvSpec,
    x_shape: &Shape,
) -> FloatTensor<B> {
    let out = grad.shape();
    if spec.stride == [1; 3] && (0..3).all(|a| spec.padding[a] < spec.kernel[a]) {
        let flipped = B::float_flip(B::float_swap_dims(weight, 0, 1), &[2, 3, 4]);
        let padding = [0, 1, 2].map(|a| spec.kernel[a] - 1 - spec.padding[a]);
        B::conv3d(
            grad,
            flipped,
            None,
            ConvOptions::new([1; 3], padding, [1; 3], 1),
        )
    } else {
        // Input cells the forward pass never reached (when the stride does not divide the
        // padded extent) get no gradient: the output padding restores x's extent.
        let padding_out = [0, 1, 2].map(|a| {
            x_shape[a + 2] + 2 * spec.padding[a]
                - ((out[a + 2] - 1) * spec.stride[a] + spec.kernel[a])
        });
        B::conv_transpose3d(
            grad,
            weight,
            None,
            ConvTransposeOptions::new(spec.stride, spec.padding, padding_out, [1; 3], 1),
        )
    }
}

/// The weight gradient `[C_out, C_in, k...]` of the plain convolution of `input
/// [1, C_in, D, H, W]` whose output gradient is `out_grad [1, C_out, D', H', W']`:
/// `dW[o, i, a] = sum_p out_grad[o, p] * input_padded[i, stride * p + a]`.
fn weight_grad(input: FloatTensor<B>, out_grad: FloatTensor<B>, spec: &ConvSpec) -> FloatTensor<B> {
    let [_, c_in, d, h, w] = dims5(&input.shape());
    let [_, c_out, od, oh, ow] = dims5(&out_grad.shape());
    let device = input.device();
    let dtype = input.dtype();
    let [pd, ph, pw] = spec.padding;
    let x = B::float_reshape(input, Shape::from([c_in, d, h, w]));
    let x = if spec.padding == [0; 3] {
        x
    } else {
        let padded = B::float_zeros(
            Shape::from([c_in, d + 2 * pd, h + 2 * ph, w + 2 * pw]),
            &device,
            dtype.into(),
        );
        B::float_slice_assign(
            padded,
            &[
                Slice::full(),
                range(pd, pd + d, 1),
                range(ph, ph + h, 1),
                range(pw, pw + w, 1),
            ],
            x,
        )
    };
    let (batches, per_batch) = if oh * ow <= CELLS_PER_BATCH {
        (od, oh * ow)
    } else {
        (od * oh, ow)
    };
    // [B, C_out, cells of a batch]
    let g = B::float_permute(
        B::float_reshape(out_grad, Shape::from([c_out, batches, per_batch])),
        &[1, 0, 2],
    );
    let offsets: Vec<[usize; 3]> = (0..spec.kernel[0])
        .flat_map(|a| {
            (0..spec.kernel[1]).flat_map(move |b| (0..spec.kernel[2]).map(move |c| [a, b, c]))
        })
        .collect();
    let column_bytes = c_in * od * oh * ow * std::mem::size_of::<f32>();
    let per_group = (COLUMN_BYTES / column_bytes.max(1)).clamp(1, offsets.len());
    let [sd, sh, sw] = spec.stride;
    let mut groups = Vec::new();
    for group in offsets.chunks(per_group) {
        let columns: Vec<FloatTensor<B>> = group
            .iter()
            .map(|&[a, b, c]| {
                let column = B::float_slice(
                    x.clone(),
                    &[
                        Slice::full(),
                        range(a, a + sd * (od - 1) + 1, sd),
                        range(b, b + sh * (oh - 1) + 1, sh),
                        range(c, c + sw * (ow - 1) + 1, sw),
                    ],
                );
                B::float_reshape(column, Shape::from([1, c_in, od, oh, ow]))
            })
            .collect();
        let k = columns.len();
        // [k * C_in, B, cells] -> [B, cells, k * C_in]
        let columns = B::float_permute(
            B::float_reshape(
                B::float_cat(columns, 0),
                Shape::from([k * c_in, batches, per_batch]),
            ),
            &[1, 2, 0],
        );
        let products = B::float_matmul(g.clone(), columns); // [B, C_out, k * C_in]
        let summed = B::float_sum_dim(products, 0); // [1, C_out, k * C_in]
        groups.push(B::float_reshape(summed, Shape::from([c_out, k, c_in])));
    }
    let all = B::float_cat(groups, 1); // [C_out, taps, C_in]
    let [kd, kh, kw] = spec.kernel;
    B::float_reshape(
        B::float_permute(all, &[0, 2, 1]),
        Shape::from([c_out, c_in, kd, kh, kw]),
    )
}

fn range(start: usize, end: usize, step: usize) -> Slice {
    Slice::new(start as isize, Some(end as isize), step as isize)
}

fn dims5(shape: &Shape) -> [usize; 5] {
    assert_eq!(shape.num_dims(), 5, "the U-Net convolves [1, C, D, H, W]");
    [0, 1, 2, 3, 4].map(|a| shape[a])
}
