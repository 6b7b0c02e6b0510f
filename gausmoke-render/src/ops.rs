//! The renderer as a burn backend extension: one trait, an implementation per backend, and an
//! `Autodiff` implementation whose backward pass calls the backend's own backward kernel.
//!
//! These are the raw ops: inputs are assumed valid (see [`crate::render_volume`] for the
//! checked, public entry point). The forward op returns one packed `[H, W, 5]` tensor (RGB,
//! final transmittance, walked-list length) because an autodiff node has one float output.

// NdArray is deprecated in burn 0.22 in favour of Flex; the design still asks for it, and both
// share one host implementation, so keeping it costs nothing. The macro expansion names it too.
#![allow(deprecated)]

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, backend_extension};
use gausmoke_core::Camera;

use crate::RasterOptions;

/// Burn backend extension for the Beer-Lambert volumetric Gaussian rasterizer.
#[backend_extension(
    Cube: cfg(feature = "cube"),
    NdArray: cfg(feature = "ndarray"),
    Flex: cfg(feature = "flex"),
    Autodiff,
)]
pub trait VolumeRenderBackend: Backend {
    /// Forward pass. Inputs: `means [N, 3]`, `rotations [N, 4]` (quaternions `w, x, y, z`, not
    /// necessarily normalised), `log_scales [N, 3]`, `raw_densities [N]` (`sigma =
    /// softplus(raw)`), `colors [N, 3]`, `background [3]`. Output `[H, W, 5]`.
    #[allow(clippy::too_many_arguments)]
    fn volume_render(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<Self>;

    /// Backward pass: gradients of every input given the forward `output` and its gradient
    /// `grad_output` (both `[H, W, 5]`; the last channel's gradient is ignored).
    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    fn volume_render_backward(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
        output: FloatTensor<Self>,
        grad_output: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    );

    /// Statistics for input validation, `[8]`: for `background`, `means`, `rotations`,
    /// `log_scales`, `raw_densities` and `colors` in turn 1 when every value is finite (else
    /// 0), then the smallest squared quaternion norm (1 when there are no Gaussians) and the
    /// largest `|log_scale|` (0 when there are none). One small read-back validates a render.
    fn volume_render_input_stats(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        background: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// CPU backends read their tensors to host slices and run [`crate::cpu`].
mod host {
    use burn::backend::tensor::FloatTensor;
    use burn::backend::{Backend, TensorMetadata};
    use burn::tensor::{TensorData, read_sync};
    use gausmoke_core::Camera;

    use crate::RasterOptions;
    use crate::cpu::{self, OUTPUT_CHANNELS, SceneRef};

    pub(super) fn to_vec<B: Backend>(tensor: FloatTensor<B>) -> Vec<f32> {
        let data = read_sync(B::float_into_data(tensor)).expect("reading a CPU tensor cannot fail");
        data.try_into_vec_as::<f32>()
            .expect("CPU backends hold float tensors")
    }

    fn from_vec<B: Backend>(
        values: Vec<f32>,
        shape: Vec<usize>,
        device: &B::Device,
    ) -> FloatTensor<B> {
        B::float_from_data(TensorData::new(values, shape), device)
    }

    struct HostScene {
        means: Vec<f32>,
        rotations: Vec<f32>,
        log_scales: Vec<f32>,
        raw_densities: Vec<f32>,
        colors: Vec<f32>,
        background: [f32; 3],
    }

    impl HostScene {
        fn read<B: Backend>(
            means: FloatTensor<B>,
            rotations: FloatTensor<B>,
            log_scales: FloatTensor<B>,
            raw_densities: FloatTensor<B>,
            colors: FloatTensor<B>,
            background: FloatTensor<B>,
        ) -> Self {
            let bg = to_vec::<B>(background);
            assert_eq!(bg.len(), 3, "background must be [3]");
            Self {
                means: to_vec::<B>(means),
                rotations: to_vec::<B>(rotations),
                log_scales: to_vec::<B>(log_scales),
                raw_densities: to_vec::<B>(raw_densities),
                colors: to_vec::<B>(colors),
                background: [bg[0], bg[1], bg[2]],
            }
        }

        fn as_ref(&self) -> SceneRef<'_> {
            SceneRef {
                means: &self.means,
                quats: &self.rotations,
                log_scales: &self.log_scales,
                raw_densities: &self.raw_densities,
                colors: &self.colors,
                background: self.background,
            }
        }
    }

    pub(super) fn input_stats<B: Backend>(
        means: FloatTensor<B>,
        rotations: FloatTensor<B>,
        log_scales: FloatTensor<B>,
        raw_densities: FloatTensor<B>,
        colors: FloatTensor<B>,
        background: FloatTensor<B>,
    ) -> FloatTensor<B> {
        let device = means.device();
        let finite = |t: FloatTensor<B>| -> (f32, Vec<f32>) {
            let v = to_vec::<B>(t);
            (f32::from(v.iter().all(|x| x.is_finite())), v)
        };
        let (bg_ok, _) = finite(background);
        let (means_ok, _) = finite(means);
        let (rot_ok, rot) = finite(rotations);
        let (ls_ok, ls) = finite(log_scales);
        let (raw_ok, _) = finite(raw_densities);
        let (col_ok, _) = finite(colors);
        let min_norm_sq = rot
            .chunks_exact(4)
            .map(|q| q.iter().map(|v| v * v).sum::<f32>())
            .fold(1.0f32, |m, v| if v < m || v.is_nan() { v } else { m });
        let min_norm_sq = if rot.is_empty() { 1.0 } else { min_norm_sq };
        let max_abs = ls.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let stats = vec![
            bg_ok,
            means_ok,
            rot_ok,
            ls_ok,
            raw_ok,
            col_ok,
            min_norm_sq,
            max_abs,
        ];
        from_vec::<B>(stats, vec![8], &device)
    }

    #[allow(clippy::too_many_arguments)]
    pub(super) fn forward<B: Backend>(
        means: FloatTensor<B>,
        rotations: FloatTensor<B>,
        log_scales: FloatTensor<B>,
        raw_densities: FloatTensor<B>,
        colors: FloatTensor<B>,
        background: FloatTensor<B>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<B> {
        let device = means.device();
        let scene = HostScene::read::<B>(
            means,
            rotations,
            log_scales,
            raw_densities,
            colors,
            background,
        );
        let image = cpu::forward(&scene.as_ref(), &camera, &options);
        let shape = vec![
            camera.height() as usize,
            camera.width() as usize,
            OUTPUT_CHANNELS,
        ];
        from_vec::<B>(image, shape, &device)
    }

    #[allow(clippy::too_many_arguments, clippy::type_complexity)]
    pub(super) fn backward<B: Backend>(
        means: FloatTensor<B>,
        rotations: FloatTensor<B>,
        log_scales: FloatTensor<B>,
        raw_densities: FloatTensor<B>,
        colors: FloatTensor<B>,
        background: FloatTensor<B>,
        camera: Camera,
        options: RasterOptions,
        output: FloatTensor<B>,
        grad_output: FloatTensor<B>,
    ) -> (
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
        FloatTensor<B>,
    ) {
        let device = means.device();
        let n = raw_densities.shape()[0];
        let scene = HostScene::read::<B>(
            means,
            rotations,
            log_scales,
            raw_densities,
            colors,
            background,
        );
        let output = to_vec::<B>(output);
        let grad_output = to_vec::<B>(grad_output);
        let grads = cpu::backward(&scene.as_ref(), &camera, &options, &output, &grad_output);
        (
            from_vec::<B>(grads.means, vec![n, 3], &device),
            from_vec::<B>(grads.quats, vec![n, 4], &device),
            from_vec::<B>(grads.log_scales, vec![n, 3], &device),
            from_vec::<B>(grads.raw_densities, vec![n], &device),
            from_vec::<B>(grads.colors, vec![n, 3], &device),
            from_vec::<B>(grads.background.to_vec(), vec![3], &device),
        )
    }
}

/// Implements the trait for a CPU backend by delegating to [`host`].
macro_rules! cpu_backend {
    ($backend:ty) => {
        impl VolumeRenderBackend for $backend {
            fn volume_render(
                means: FloatTensor<Self>,
                rotations: FloatTensor<Self>,
                log_scales: FloatTensor<Self>,
                raw_densities: FloatTensor<Self>,
                colors: FloatTensor<Self>,
                background: FloatTensor<Self>,
                camera: Camera,
                options: RasterOptions,
            ) -> FloatTensor<Self> {
                host::forward::<Self>(
                    means,
                    rotations,
                    log_scales,
                    raw_densities,
                    colors,
                    background,
                    camera,
                    options,
                )
            }

            fn volume_render_backward(
                means: FloatTensor<Self>,
                rotations: FloatTensor<Self>,
                log_scales: FloatTensor<Self>,
                raw_densities: FloatTensor<Self>,
                colors: FloatTensor<Self>,
                background: FloatTensor<Self>,
                camera: Camera,
                options: RasterOptions,
                output: FloatTensor<Self>,
                grad_output: FloatTensor<Self>,
            ) -> (
                FloatTensor<Self>,
                FloatTensor<Self>,
                FloatTensor<Self>,
                FloatTensor<Self>,
                FloatTensor<Self>,
                FloatTensor<Self>,
            ) {
                host::backward::<Self>(
                    means,
                    rotations,
                    log_scales,
                    raw_densities,
                    colors,
                    background,
                    camera,
                    options,
                    output,
                    grad_output,
                )
            }

            fn volume_render_input_stats(
                means: FloatTensor<Self>,
                rotations: FloatTensor<Self>,
                log_scales: FloatTensor<Self>,
                raw_densities: FloatTensor<Self>,
                colors: FloatTensor<Self>,
                background: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                host::input_stats::<Self>(
                    means,
                    rotations,
                    log_scales,
                    raw_densities,
                    colors,
                    background,
                )
            }
        }
    };
}

#[cfg(feature = "ndarray")]
cpu_backend!(burn::backend::NdArray);
#[cfg(feature = "flex")]
cpu_backend!(burn::backend::Flex);

/// The cube backends (wgpu, Vulkan, CUDA) run the kernels of [`crate::kernels`].
#[cfg(feature = "cube")]
impl VolumeRenderBackend for burn_cubecl::CubeBackend {
    fn volume_render(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<Self> {
        crate::kernels::forward(
            means,
            rotations,
            log_scales,
            raw_densities,
            colors,
            background,
            &camera,
            &options,
        )
    }

    fn volume_render_backward(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
        output: FloatTensor<Self>,
        grad_output: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        crate::kernels::backward(
            means,
            rotations,
            log_scales,
            raw_densities,
            colors,
            background,
            &camera,
            &options,
            output,
            grad_output,
            crate::kernels::force_compare_and_swap(),
        )
    }

    fn volume_render_input_stats(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        background: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        crate::kernels::input_stats(
            means,
            rotations,
            log_scales,
            raw_densities,
            colors,
            background,
        )
    }
}

/// What the backward pass needs: the inner-backend inputs and the forward output.
#[derive(Debug, Clone)]
struct RenderState<B: Backend> {
    inputs: [FloatTensor<B>; 6],
    camera: Camera,
    options: RasterOptions,
    output: FloatTensor<B>,
}

#[derive(Debug)]
struct VolumeRenderBackward;

impl<B: Backend + VolumeRenderBackend> Backward<B, 6> for VolumeRenderBackward {
    type State = RenderState<B>;

    fn backward(
        self,
        ops: Ops<Self::State, 6>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad_output = grads.consume::<B>(&ops.node);
        let RenderState {
            inputs,
            camera,
            options,
            output,
        } = ops.state;
        let [
            means,
            rotations,
            log_scales,
            raw_densities,
            colors,
            background,
        ] = inputs;
        let _timed = gausmoke_core::profile::scope("render backward");
        let (g_means, g_rotations, g_log_scales, g_raw_densities, g_colors, g_background) =
            B::volume_render_backward(
                means,
                rotations,
                log_scales,
                raw_densities,
                colors,
                background,
                camera,
                options,
                output,
                grad_output,
            );
        let input_grads = [
            g_means,
            g_rotations,
            g_log_scales,
            g_raw_densities,
            g_colors,
            g_background,
        ];
        for (parent, grad) in ops.parents.into_iter().zip(input_grads) {
            if let Some(node) = parent {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

impl<B: Backend + VolumeRenderBackend, C: CheckpointStrategy> VolumeRenderBackend
    for Autodiff<B, C>
{
    fn volume_render(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<Self> {
        let nodes = [
            means.node(),
            rotations.node(),
            log_scales.node(),
            raw_densities.node(),
            colors.node(),
            background.node(),
        ];
        let inputs = [
            means.into_primitive(),
            rotations.into_primitive(),
            log_scales.into_primitive(),
            raw_densities.into_primitive(),
            colors.into_primitive(),
            background.into_primitive(),
        ];
        let [m, r, s, d, c, bg] = inputs.clone();
        let output = {
            let _timed = gausmoke_core::profile::scope("render");
            B::volume_render(m, r, s, d, c, bg, camera, options)
        };
        match VolumeRenderBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let state = RenderState {
                    inputs,
                    camera,
                    options,
                    output: output.clone(),
                };
                prep.finish(state, output)
            }
            OpsKind::UnTracked(prep) => prep.finish(output),
        }
    }

    /// Gradients are not differentiated again (no double backward): the result is untracked.
    fn volume_render_backward(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
        output: FloatTensor<Self>,
        grad_output: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        use burn::backend::AutodiffBackend;
        let wrap = <Self as AutodiffBackend>::from_inner;
        let (a, b, c, d, e, f) = B::volume_render_backward(
            means.into_primitive(),
            rotations.into_primitive(),
            log_scales.into_primitive(),
            raw_densities.into_primitive(),
            colors.into_primitive(),
            background.into_primitive(),
            camera,
            options,
            output.into_primitive(),
            grad_output.into_primitive(),
        );
        (wrap(a), wrap(b), wrap(c), wrap(d), wrap(e), wrap(f))
    }

    /// Not differentiable: statistics only.
    fn volume_render_input_stats(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        colors: FloatTensor<Self>,
        background: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        use burn::backend::AutodiffBackend;
        <Self as AutodiffBackend>::from_inner(B::volume_render_input_stats(
            means.into_primitive(),
            rotations.into_primitive(),
            log_scales.into_primitive(),
            raw_densities.into_primitive(),
            colors.into_primitive(),
            background.into_primitive(),
        ))
    }
}
