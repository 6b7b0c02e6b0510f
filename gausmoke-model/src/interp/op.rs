//! The fused Gaussian-kernel interpolation as a burn backend extension with a hand-written
//! backward pass: [`super::host`] on the CPU backends, `super::kernels` on the cube backends.

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

use super::host::{self, KernelGrid, SAMPLE_FLOATS};

#[backend_extension(
    Cube: cfg(feature = "cube"),
    NdArray: cfg(feature = "ndarray"),
    Flex: cfg(feature = "flex"),
    Autodiff,
)]
pub trait SampleBackend: Backend {
    /// `[M, 12]`: the velocity (3) and its Jacobian (9, row-major) at `points [M, 3]` of
    /// `velocity [nx, ny, nz, 3]`.
    fn sample_gaussian(
        velocity: FloatTensor<Self>,
        points: FloatTensor<Self>,
        grid: KernelGrid,
    ) -> FloatTensor<Self>;
}

/// The forward and backward passes of the interpolation on one backend.
pub trait SamplePasses: Backend {
    fn sample_forward(
        velocity: FloatTensor<Self>,
        points: FloatTensor<Self>,
        grid: KernelGrid,
    ) -> FloatTensor<Self>;

    /// Gradients `(velocity, points)` given the gradient of the `[M, 12]` output.
    fn sample_backward(
        velocity: FloatTensor<Self>,
        points: FloatTensor<Self>,
        grid: KernelGrid,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>);
}

macro_rules! cpu_sample_passes {
    ($backend:ty) => {
        impl SamplePasses for $backend {
            fn sample_forward(
                velocity: FloatTensor<Self>,
                points: FloatTensor<Self>,
                grid: KernelGrid,
            ) -> FloatTensor<Self> {
                let device = points.device();
                let m = points.shape()[0];
                let values =
                    host::forward(&grid, &to_vec::<Self>(velocity), &to_vec::<Self>(points));
                from_vec::<Self>(values, vec![m, SAMPLE_FLOATS], &device)
            }

            fn sample_backward(
                velocity: FloatTensor<Self>,
                points: FloatTensor<Self>,
                grid: KernelGrid,
                grad: FloatTensor<Self>,
            ) -> (FloatTensor<Self>, FloatTensor<Self>) {
                let device = points.device();
                let (velocity_shape, points_shape) =
                    (velocity.shape().to_vec(), points.shape().to_vec());
                let (grad_velocity, grad_points) = host::backward(
                    &grid,
                    &to_vec::<Self>(velocity),
                    &to_vec::<Self>(points),
                    &to_vec::<Self>(grad),
                );
                (
                    from_vec::<Self>(grad_velocity, velocity_shape, &device),
                    from_vec::<Self>(grad_points, points_shape, &device),
                )
            }
        }
    };
}

#[cfg(feature = "ndarray")]
cpu_sample_passes!(burn::backend::NdArray);
#[cfg(feature = "flex")]
cpu_sample_passes!(burn::backend::Flex);

#[cfg(feature = "cube")]
impl SamplePasses for burn_cubecl::CubeBackend {
    fn sample_forward(
        velocity: FloatTensor<Self>,
        points: FloatTensor<Self>,
        grid: KernelGrid,
    ) -> FloatTensor<Self> {
        super::kernels::forward(velocity, points, &grid)
    }

    fn sample_backward(
        velocity: FloatTensor<Self>,
        points: FloatTensor<Self>,
        grid: KernelGrid,
        grad: FloatTensor<Self>,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        super::kernels::backward(velocity, points, &grid, grad)
    }
}

/// The public op on a backend that implements the passes.
macro_rules! sample_op_from_passes {
    ($backend:ty) => {
        impl SampleBackend for $backend {
            fn sample_gaussian(
                velocity: FloatTensor<Self>,
                points: FloatTensor<Self>,
                grid: KernelGrid,
            ) -> FloatTensor<Self> {
                <Self as SamplePasses>::sample_forward(velocity, points, grid)
            }
        }
    };
}

#[cfg(feature = "ndarray")]
sample_op_from_passes!(burn::backend::NdArray);
#[cfg(feature = "flex")]
sample_op_from_passes!(burn::backend::Flex);
#[cfg(feature = "cube")]
sample_op_from_passes!(burn_cubecl::CubeBackend);

#[derive(Debug, Clone)]
struct SampleState<B: Backend> {
    velocity: FloatTensor<B>,
    points: FloatTensor<B>,
    grid: KernelGrid,
}

#[derive(Debug)]
struct SampleBackward;

impl<B: SamplePasses> Backward<B, 2> for SampleBackward {
    type State = SampleState<B>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let SampleState {
            velocity,
            points,
            grid,
        } = ops.state;
        let (grad_velocity, grad_points) = {
            let _phase = gausmoke_core::phase!("interpolation backward");
            B::sample_backward(velocity, points, grid, grad)
        };
        let [velocity_parent, points_parent] = ops.parents;
        if let Some(node) = velocity_parent {
            grads.register::<B>(node.id, grad_velocity);
        }
        if let Some(node) = points_parent {
            grads.register::<B>(node.id, grad_points);
        }
    }
}

impl<B: SamplePasses, C: CheckpointStrategy> SampleBackend for Autodiff<B, C> {
    fn sample_gaussian(
        velocity: FloatTensor<Self>,
        points: FloatTensor<Self>,
        grid: KernelGrid,
    ) -> FloatTensor<Self> {
        let nodes = [velocity.node(), points.node()];
        let (velocity, points) = (velocity.into_primitive(), points.into_primitive());
        let output = {
            let _phase = gausmoke_core::phase!("interpolation");
            B::sample_forward(velocity.clone(), points.clone(), grid)
        };
        match SampleBackward
            .prepare::<C>(nodes)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(
                SampleState {
                    velocity,
                    points,
                    grid,
                },
                output,
            ),
            OpsKind::UnTracked(prep) => prep.finish(output),
        }
    }
}
