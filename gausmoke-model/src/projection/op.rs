//! The exact projection as a burn backend extension: forward projects the velocity grid, and
//! the `Autodiff` backward projects the incoming gradient (`Pi` is self-adjoint).

// NdArray is deprecated in burn 0.22; see gausmoke-render's ops.rs. The macro names it too.
#![allow(deprecated)]

use burn::backend::autodiff::{
    Autodiff,
    checkpoint::{base::Checkpointer, strategy::CheckpointStrategy},
    grads::Gradients,
    ops::{Backward, Ops, OpsKind},
};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, TensorMetadata, backend_extension};
use burn::tensor::{TensorData, read_sync};

use super::host::{ProjectionSpec, SolveKind};

#[backend_extension(
    Cube: cfg(feature = "cube"),
    NdArray: cfg(feature = "ndarray"),
    Flex: cfg(feature = "flex"),
    Autodiff,
)]
pub trait ProjectionBackend: Backend {
    /// `Pi(u)` for `u: [nx, ny, nz, 3]`.
    fn project_velocity(velocity: FloatTensor<Self>, spec: ProjectionSpec) -> FloatTensor<Self>;
}

/// Host implementation shared by the CPU backends (the direct solve of [`super::spectral`],
/// or PCG with obstacles: see [`super::project_on_host`]); logs the solver report.
fn host_project<B: Backend>(velocity: FloatTensor<B>, spec: ProjectionSpec) -> FloatTensor<B> {
    let device = velocity.device();
    let shape = velocity.shape();
    let mut values = read_sync(B::float_into_data(velocity))
        .expect("reading the velocity grid back to the host failed")
        .try_into_vec_as::<f32>()
        .expect("CPU backends hold float tensors");
    let report = super::project_on_host(&spec, &mut values);
    tracing::debug!(?report, "velocity projection");
    B::float_from_data(TensorData::new(values, shape), &device)
}

#[cfg(feature = "ndarray")]
impl ProjectionBackend for burn::backend::NdArray {
    fn project_velocity(velocity: FloatTensor<Self>, spec: ProjectionSpec) -> FloatTensor<Self> {
        host_project::<Self>(velocity, spec)
    }
}

#[cfg(feature = "flex")]
impl ProjectionBackend for burn::backend::Flex {
    fn project_velocity(velocity: FloatTensor<Self>, spec: ProjectionSpec) -> FloatTensor<Self> {
        host_project::<Self>(velocity, spec)
    }
}

/// On the GPU backends the solve stays on the device (`kernels`): direct by matrix products
/// without obstacles, the host's PCG with them, in f32, with no read-back of the velocity
/// grid.
#[cfg(feature = "cube")]
impl ProjectionBackend for burn_cubecl::CubeBackend {
    fn project_velocity(velocity: FloatTensor<Self>, spec: ProjectionSpec) -> FloatTensor<Self> {
        let (projected, report) = super::kernels::project_velocity(velocity, &spec);
        if let Some(report) = report {
            tracing::debug!(?report, "velocity projection (device)");
        }
        projected
    }
}

#[derive(Debug)]
struct ProjectBackward;

impl<B: Backend + ProjectionBackend> Backward<B, 1> for ProjectBackward {
    type State = ProjectionSpec;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        if let [Some(parent)] = ops.parents {
            let _phase = gausmoke_core::phase!("projection backward");
            let spec = ProjectionSpec {
                kind: SolveKind::Gradient,
                ..ops.state.clone()
            };
            grads.register::<B>(parent.id, B::project_velocity(grad, spec));
        }
    }
}

impl<B: Backend + ProjectionBackend, C: CheckpointStrategy> ProjectionBackend for Autodiff<B, C> {
    fn project_velocity(velocity: FloatTensor<Self>, spec: ProjectionSpec) -> FloatTensor<Self> {
        let node = velocity.node();
        let output = {
            let _phase = gausmoke_core::phase!("projection");
            B::project_velocity(velocity.into_primitive(), spec.clone())
        };
        match ProjectBackward
            .prepare::<C>([node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(spec, output),
            OpsKind::UnTracked(prep) => prep.finish(output),
        }
    }
}
