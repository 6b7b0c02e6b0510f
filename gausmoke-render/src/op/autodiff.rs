//! The renderer under `Autodiff`: the forward pass saves what [`RenderPasses::render_backward`]
//! needs, and the backward pass registers a gradient for every tracked input.

use burn::backend::AutodiffBackend;
use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use gausmoke_core::Camera;

use super::{RenderGrads, RenderPasses, VolumeRenderBackend};
use crate::RasterOptions;
use crate::gaussians::GaussianPrimitives;

/// Inputs tracked by the op: the five Gaussian attributes, then the background.
const INPUTS: usize = 6;

#[derive(Debug)]
struct VolumeRenderBackward;

impl<B: RenderPasses> Backward<B, INPUTS> for VolumeRenderBackward {
    type State = B::Saved;

    fn backward(
        self,
        ops: Ops<Self::State, INPUTS>,
        grads: &mut Gradients,
        _checkpointer: &mut Checkpointer,
    ) {
        let grad_image = grads.consume::<B>(&ops.node);
        let RenderGrads {
            gaussians,
            background,
        } = {
            let _phase = gausmoke_core::phase!("render backward");
            B::render_backward(ops.state, grad_image)
        };
        let [means, rotations, log_scales, raw_densities, colors] = gaussians.into_array();
        let input_grads = [
            means,
            rotations,
            log_scales,
            raw_densities,
            colors,
            background,
        ];
        for (parent, grad) in ops.parents.into_iter().zip(input_grads) {
            if let Some(node) = parent {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

impl<B: RenderPasses, C: CheckpointStrategy> VolumeRenderBackend for Autodiff<B, C> {
    fn volume_render(
        gaussians: GaussianPrimitives<Self>,
        background: FloatTensor<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<Self> {
        let [means, rotations, log_scales, raw_densities, colors] =
            gaussians.as_ref().into_array().map(|t| t.node());
        let nodes = [
            means,
            rotations,
            log_scales,
            raw_densities,
            colors,
            background.node(),
        ];
        let inner = gaussians.map(|_, t| t.into_primitive());
        let rendered = {
            let _phase = gausmoke_core::phase!("render");
            B::render_forward(inner, background.into_primitive(), camera, options)
        };
        match VolumeRenderBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(rendered.saved, rendered.image),
            OpsKind::UnTracked(prep) => prep.finish(rendered.image),
        }
    }

    /// Not differentiable: statistics only.
    fn volume_render_input_stats(
        gaussians: GaussianPrimitives<Self>,
        background: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        <Self as AutodiffBackend>::from_inner(B::input_stats(
            gaussians.map(|_, t| t.into_primitive()),
            background.into_primitive(),
        ))
    }

    /// Not differentiable: a count.
    fn volume_render_list_buffer_length(
        gaussians: GaussianPrimitives<Self>,
        camera: Camera,
        options: RasterOptions,
    ) -> FloatTensor<Self> {
        <Self as AutodiffBackend>::from_inner(B::list_buffer_length(
            gaussians.map(|_, t| t.into_primitive()),
            camera,
            options,
        ))
    }
}
