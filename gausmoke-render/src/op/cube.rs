//! The renderer's passes on the cube backends (wgpu, Vulkan, CUDA): the kernels of
//! [`crate::kernels`]; the forward pass keeps its splats and tile lists on the device.

use burn::backend::tensor::FloatTensor;
use burn_cubecl::CubeBackend;
use gausmoke_core::Camera;

use super::{RenderGrads, RenderPasses, Rendered};
use crate::RasterOptions;
use crate::gaussians::GaussianPrimitives;
use crate::kernels::{self, DeviceSaved};

impl RenderPasses for CubeBackend {
    type Saved = DeviceSaved;

    fn render_forward(
        gaussians: GaussianPrimitives<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> Rendered<Self> {
        let saved = kernels::forward(gaussians, background, &camera, &options);
        Rendered {
            image: saved.image.clone(),
            saved,
        }
    }

    fn render_backward(saved: Self::Saved, grad_image: FloatTensor<Self>) -> RenderGrads<Self> {
        let (gaussians, background) = kernels::backward(&saved, grad_image);
        RenderGrads {
            gaussians,
            background,
        }
    }

    fn input_stats(
        gaussians: GaussianPrimitives<Self>,
        background: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        kernels::validate::input_stats(gaussians, background)
    }

    fn list_buffer_length(
        gaussians: GaussianPrimitives<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<Self> {
        kernels::list_buffer_length(gaussians, &camera, &options)
    }
}
