//! The renderer's passes on the CPU backends: tensors are read to host slices and
//! [`crate::cpu`] renders them; the forward pass keeps the host copies and the binning.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, TensorMetadata};
use gausmoke_core::Camera;

use super::{RenderGrads, RenderPasses, Rendered};
use crate::RasterOptions;
use crate::cpu::{self, IMAGE_CHANNELS};
use crate::gaussians::{GaussianPrimitives, HostGaussians};
use crate::primitives::{from_vec, gradient_tensors, host_gaussians, to_vec};

fn background_array<B: Backend>(background: FloatTensor<B>) -> [f32; 3] {
    to_vec::<B>(background)
        .try_into()
        .expect("background must be [3]")
}

/// What the CPU backward pass reuses.
#[derive(Debug, Clone)]
pub struct HostSaved<D> {
    gaussians: HostGaussians,
    background: [f32; 3],
    camera: Camera,
    options: RasterOptions,
    rendered: cpu::Rendered,
    device: D,
}

macro_rules! cpu_render_passes {
    ($backend:ty) => {
        impl RenderPasses for $backend {
            type Saved = HostSaved<<Self as burn::backend::BackendTypes>::Device>;

            fn render_forward(
                gaussians: GaussianPrimitives<Self>,
                background: FloatTensor<Self>,
                camera: Camera,
                options: RasterOptions,
            ) -> Rendered<Self> {
                let device = gaussians.means.device();
                let gaussians = host_gaussians::<Self>(gaussians);
                let background = background_array::<Self>(background);
                let rendered = cpu::forward(&gaussians.slices(), background, &camera, &options);
                let shape = vec![
                    camera.height() as usize,
                    camera.width() as usize,
                    IMAGE_CHANNELS,
                ];
                let image = from_vec::<Self>(rendered.image.clone(), shape, &device);
                Rendered {
                    image,
                    saved: HostSaved {
                        gaussians,
                        background,
                        camera,
                        options,
                        rendered,
                        device,
                    },
                }
            }

            fn render_backward(
                saved: Self::Saved,
                grad_image: FloatTensor<Self>,
            ) -> RenderGrads<Self> {
                let grad_image = to_vec::<Self>(grad_image);
                let (grads, background) = cpu::backward(
                    &saved.gaussians.slices(),
                    saved.background,
                    &saved.camera,
                    &saved.options,
                    &saved.rendered,
                    &grad_image,
                );
                RenderGrads {
                    gaussians: gradient_tensors::<Self>(grads, &saved.device),
                    background: from_vec::<Self>(background.to_vec(), vec![3], &saved.device),
                }
            }

            fn input_stats(
                gaussians: GaussianPrimitives<Self>,
                background: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                let device = gaussians.means.device();
                let gaussians = host_gaussians::<Self>(gaussians);
                let stats = input_stats(&gaussians, &to_vec::<Self>(background));
                from_vec::<Self>(stats.to_vec(), vec![8], &device)
            }

            fn list_buffer_length(
                gaussians: GaussianPrimitives<Self>,
                _camera: Camera,
                _options: RasterOptions,
            ) -> FloatTensor<Self> {
                from_vec::<Self>(vec![0.0], vec![1], &gaussians.means.device())
            }
        }
    };
}

#[cfg(feature = "ndarray")]
cpu_render_passes!(burn::backend::NdArray);
#[cfg(feature = "flex")]
cpu_render_passes!(burn::backend::Flex);

/// See [`super::VolumeRenderBackend::volume_render_input_stats`].
fn input_stats(gaussians: &HostGaussians, background: &[f32]) -> [f32; 8] {
    let finite = |v: &[f32]| f32::from(v.iter().all(|x| x.is_finite()));
    let min_norm_sq = gaussians
        .rotations
        .chunks_exact(4)
        .map(|q| q.iter().map(|v| v * v).sum::<f32>())
        .fold(1.0f32, |m, v| if v < m || v.is_nan() { v } else { m });
    let min_norm_sq = if gaussians.rotations.is_empty() {
        1.0
    } else {
        min_norm_sq
    };
    let max_abs = gaussians
        .log_scales
        .iter()
        .fold(0.0f32, |m, v| m.max(v.abs()));
    [
        finite(background),
        finite(&gaussians.means),
        finite(&gaussians.rotations),
        finite(&gaussians.log_scales),
        finite(&gaussians.raw_densities),
        finite(&gaussians.colors),
        min_norm_sq,
        max_abs,
    ]
}
