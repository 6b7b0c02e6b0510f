//! Density splatting as a burn backend extension with hand-written backward passes.

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
use gausmoke_render::primitives::{from_vec, gradient_tensors, host_gaussians, to_vec};
use gausmoke_render::{FloatAtomics, GaussianPrimitives, HostGaussians};

use super::host::{DensityField, SplatGrid, splat_field_backward, splat_field_forward};

#[backend_extension(
    Cube: cfg(feature = "cube"),
    NdArray: cfg(feature = "ndarray"),
    Flex: cfg(feature = "flex"),
    Autodiff,
)]
pub trait DensityBackend: Backend {
    /// `field` of `gaussians` at the grid's cell centres (`[nx, ny, nz]` or
    /// `[nx, ny, nz, 3]`).
    fn splat_density(
        #[extension_type] gaussians: GaussianPrimitives<Self>,
        grid: SplatGrid,
        field: DensityField,
        float_atomics: FloatAtomics,
    ) -> FloatTensor<Self>;
}

/// The forward and backward passes of density splatting on one backend.
pub trait DensityPasses: Backend {
    fn splat_forward(
        gaussians: GaussianPrimitives<Self>,
        grid: SplatGrid,
        field: DensityField,
        float_atomics: FloatAtomics,
    ) -> FloatTensor<Self>;

    /// Gradients of every attribute (the colours' are zero: splatting does not read them)
    /// given the gradient of the field.
    fn splat_backward(
        gaussians: GaussianPrimitives<Self>,
        grid: SplatGrid,
        field: DensityField,
        grad: FloatTensor<Self>,
    ) -> GaussianPrimitives<Self>;
}

macro_rules! cpu_density_passes {
    ($backend:ty) => {
        impl DensityPasses for $backend {
            fn splat_forward(
                gaussians: GaussianPrimitives<Self>,
                grid: SplatGrid,
                field: DensityField,
                _: FloatAtomics,
            ) -> FloatTensor<Self> {
                let device = gaussians.means.device();
                let host = host_gaussians::<Self>(gaussians);
                let values = splat_field_forward(&host.slices(), &grid, field);
                from_vec::<Self>(values, field.shape(&grid), &device)
            }

            fn splat_backward(
                gaussians: GaussianPrimitives<Self>,
                grid: SplatGrid,
                field: DensityField,
                grad: FloatTensor<Self>,
            ) -> GaussianPrimitives<Self> {
                let device = gaussians.means.device();
                let host: HostGaussians = host_gaussians::<Self>(gaussians);
                let grad = to_vec::<Self>(grad);
                let grads = splat_field_backward(&host.slices(), &grid, field, &grad);
                gradient_tensors::<Self>(grads, &device)
            }
        }
    };
}

#[cfg(feature = "ndarray")]
cpu_density_passes!(burn::backend::NdArray);
#[cfg(feature = "flex")]
cpu_density_passes!(burn::backend::Flex);

#[cfg(feature = "cube")]
impl DensityPasses for burn_cubecl::CubeBackend {
    fn splat_forward(
        gaussians: GaussianPrimitives<Self>,
        grid: SplatGrid,
        field: DensityField,
        float_atomics: FloatAtomics,
    ) -> FloatTensor<Self> {
        super::kernels::splat_field(gaussians, &grid, field, float_atomics)
    }

    fn splat_backward(
        gaussians: GaussianPrimitives<Self>,
        grid: SplatGrid,
        field: DensityField,
        grad: FloatTensor<Self>,
    ) -> GaussianPrimitives<Self> {
        super::kernels::splat_field_backward(gaussians, &grid, field, grad)
    }
}

/// The public op on a backend that implements the passes.
macro_rules! density_op_from_passes {
    ($backend:ty) => {
        impl DensityBackend for $backend {
            fn splat_density(
                gaussians: GaussianPrimitives<Self>,
                grid: SplatGrid,
                field: DensityField,
                float_atomics: FloatAtomics,
            ) -> FloatTensor<Self> {
                <Self as DensityPasses>::splat_forward(gaussians, grid, field, float_atomics)
            }
        }
    };
}

#[cfg(feature = "ndarray")]
density_op_from_passes!(burn::backend::NdArray);
#[cfg(feature = "flex")]
density_op_from_passes!(burn::backend::Flex);
#[cfg(feature = "cube")]
density_op_from_passes!(burn_cubecl::CubeBackend);

/// Tracked inputs: the five Gaussian attributes (the colours receive no gradient).
const INPUTS: usize = 5;

#[derive(Debug, Clone)]
struct SplatState<B: Backend> {
    gaussians: GaussianPrimitives<B>,
    grid: SplatGrid,
    field: DensityField,
}

#[derive(Debug)]
struct SplatBackward;

impl<B: DensityPasses> Backward<B, INPUTS> for SplatBackward {
    type State = SplatState<B>;

    fn backward(self, ops: Ops<Self::State, INPUTS>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let SplatState {
            gaussians,
            grid,
            field,
        } = ops.state;
        let input_grads = {
            let _phase = gausmoke_core::phase!("density splat backward");
            B::splat_backward(gaussians, grid, field, grad)
        };
        let [means, rotations, log_scales, raw_densities, _colors] = input_grads.into_array();
        let [parents @ .., _] = ops.parents;
        for (parent, grad) in parents
            .into_iter()
            .zip([means, rotations, log_scales, raw_densities])
        {
            if let Some(node) = parent {
                grads.register::<B>(node.id, grad);
            }
        }
    }
}

impl<B: DensityPasses, C: CheckpointStrategy> DensityBackend for Autodiff<B, C> {
    fn splat_density(
        gaussians: GaussianPrimitives<Self>,
        grid: SplatGrid,
        field: DensityField,
        float_atomics: FloatAtomics,
    ) -> FloatTensor<Self> {
        let nodes = gaussians.as_ref().into_array().map(|t| t.node());
        let inner = gaussians.map(|_, t| t.into_primitive());
        let output = {
            let _phase = gausmoke_core::phase!("density splat");
            B::splat_forward(inner.clone(), grid, field, float_atomics)
        };
        match SplatBackward.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish(
                SplatState {
                    gaussians: inner,
                    grid,
                    field,
                },
                output,
            ),
            OpsKind::UnTracked(prep) => prep.finish(output),
        }
    }
}
