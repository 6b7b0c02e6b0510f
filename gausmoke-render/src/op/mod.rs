//! The renderer as a burn backend extension.
//!
//! [`VolumeRenderBackend`] is the public op: a forward render, differentiable under
//! `Autodiff`, and the statistics that validate its inputs. How a backend renders, and what its
//! forward pass keeps for the backward pass (the projected Gaussians and the per-tile lists),
//! is the business of [`RenderPasses`], which the `Autodiff` implementation calls
//! (`autodiff.rs`): the CPU backends run [`crate::cpu`] (`host.rs`), the cube backends the
//! kernels of [`crate::kernels`] (`cube.rs`). These are raw ops: inputs are assumed valid (see
//! [`crate::render_volume`] for the checked entry point).

// NdArray is deprecated in burn 0.22 in favour of Flex; the design still asks for it, and both
// share one host implementation, so keeping it costs nothing. The macro expansion names it too.
#![allow(deprecated)]

mod autodiff;
#[cfg(feature = "cube")]
mod cube;
mod host;

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, backend_extension};
use gausmoke_core::Camera;

use crate::RasterOptions;
use crate::gaussians::GaussianPrimitives;

/// Burn backend extension for the Beer-Lambert volumetric Gaussian rasterizer.
#[backend_extension(
    Cube: cfg(feature = "cube"),
    NdArray: cfg(feature = "ndarray"),
    Flex: cfg(feature = "flex"),
    Autodiff,
)]
pub trait VolumeRenderBackend: Backend {
    /// `gaussians` seen by `camera` over `background` (`[3]`): `[H, W, 4]`, the composited RGB
    /// then the final transmittance. (One tensor because an autodiff node has one output;
    /// [`crate::render_volume`] splits it.)
    fn volume_render(
        #[extension_type] gaussians: GaussianPrimitives<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<Self>;

    /// Statistics for input validation, `[8]`: for `background`, `means`, `rotations`,
    /// `log_scales`, `raw_densities` and `colors` in turn 1 when every value is finite (else
    /// 0), then the smallest squared quaternion norm (1 when there are no Gaussians) and the
    /// largest `|log_scale|` (0 when there are none). One small read-back validates a render.
    fn volume_render_input_stats(
        #[extension_type] gaussians: GaussianPrimitives<Self>,
        background: FloatTensor<Self>,
    ) -> FloatTensor<Self>;

    /// `[1]`: the entries of the tile-list buffer that [`Self::volume_render`] of the same
    /// arguments allocates when `options.tile_list_capacity` is `None` (exact below 2^24). The
    /// CPU backends build each tile's list as they render it, with no buffer to size: 0.
    fn volume_render_list_buffer_length(
        #[extension_type] gaussians: GaussianPrimitives<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<Self>;
}

/// A forward render and what the backward pass of the same backend needs.
#[derive(Debug)]
pub struct Rendered<B: RenderPasses> {
    /// `[H, W, 4]`, as [`VolumeRenderBackend::volume_render`].
    pub image: FloatTensor<B>,
    pub saved: B::Saved,
}

/// Gradients of a render with respect to its inputs.
#[derive(Debug)]
pub struct RenderGrads<B: Backend> {
    pub gaussians: GaussianPrimitives<B>,
    pub background: FloatTensor<B>,
}

/// The forward and backward passes of the renderer on one backend. The forward pass returns
/// what its backward pass reuses (inputs, projected Gaussians, tile lists, per-pixel walked
/// counts), so the backward never bins again.
pub trait RenderPasses: Backend {
    type Saved: Clone + std::fmt::Debug + Send + Sync + 'static;

    fn render_forward(
        gaussians: GaussianPrimitives<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> Rendered<Self>;

    /// Gradients given the gradient of the forward pass's `[H, W, 4]` image.
    fn render_backward(saved: Self::Saved, grad_image: FloatTensor<Self>) -> RenderGrads<Self>;

    fn input_stats(
        gaussians: GaussianPrimitives<Self>,
        background: FloatTensor<Self>,
    ) -> FloatTensor<Self>;

    fn list_buffer_length(
        gaussians: GaussianPrimitives<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<Self>;
}

/// The public op on a backend that implements the passes: the forward image, nothing saved.
macro_rules! render_op_from_passes {
    ($backend:ty) => {
        impl VolumeRenderBackend for $backend {
            fn volume_render(
                gaussians: GaussianPrimitives<Self>,
                background: FloatTensor<Self>,
                camera: Camera,
                options: RasterOptions,
            ) -> FloatTensor<Self> {
                <Self as RenderPasses>::render_forward(gaussians, background, camera, options).image
            }

            fn volume_render_input_stats(
                gaussians: GaussianPrimitives<Self>,
                background: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                <Self as RenderPasses>::input_stats(gaussians, background)
            }

            fn volume_render_list_buffer_length(
                gaussians: GaussianPrimitives<Self>,
                camera: Camera,
                options: RasterOptions,
            ) -> FloatTensor<Self> {
                <Self as RenderPasses>::list_buffer_length(gaussians, camera, options)
            }
        }
    };
}

#[cfg(feature = "ndarray")]
render_op_from_passes!(burn::backend::NdArray);
#[cfg(feature = "flex")]
render_op_from_passes!(burn::backend::Flex);
#[cfg(feature = "cube")]
render_op_from_passes!(burn_cubecl::CubeBackend);
