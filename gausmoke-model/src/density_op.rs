//! [`crate::density`] as a burn backend extension with hand-written backward passes: the
//! density at the cell centres, and its analytic spatial gradient.

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
use burn::tensor::{Tensor, TensorData, read_sync};
use gausmoke_render::GaussianTensors;

use crate::density::{
    GaussianSlices, SplatGrid, splat_backward, splat_forward, splat_gradient_backward,
    splat_gradient_forward,
};
use crate::grid::GridSpec;

/// Gradients of the four Gaussian inputs `(means, rotations, log_scales, raw_densities)`
/// (the trait spells the tuple out: `backend_extension` reads it syntactically).
pub type GaussianGrads<B> = (
    FloatTensor<B>,
    FloatTensor<B>,
    FloatTensor<B>,
    FloatTensor<B>,
);

/// Which of the two fields an op evaluates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DensityField {
    /// `sigma_grid`, `[nx, ny, nz]`.
    Density,
    /// `grad sigma_grid`, `[nx, ny, nz, 3]`.
    SpatialGradient,
}

#[backend_extension(
    Cube: cfg(feature = "cube"),
    NdArray: cfg(feature = "ndarray"),
    Flex: cfg(feature = "flex"),
    Autodiff,
)]
pub trait DensityBackend: Backend {
    /// `field` of Gaussians `means [N, 3]`, `rotations [N, 4]`, `log_scales [N, 3]`,
    /// `raw_densities [N]` (`sigma = softplus(raw)`) at the grid's cell centres.
    fn splat_field(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
        field: DensityField,
    ) -> FloatTensor<Self>;

    /// Gradients of the four inputs given the gradient of `field`.
    #[allow(clippy::too_many_arguments)]
    fn splat_field_backward(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
        field: DensityField,
        grad: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    );
}

fn host<B: Backend>(t: FloatTensor<B>) -> Vec<f32> {
    read_sync(B::float_into_data(t))
        .expect("reading a CPU tensor cannot fail")
        .try_into_vec_as::<f32>()
        .expect("CPU backends hold float tensors")
}

fn tensor<B: Backend>(v: Vec<f32>, shape: Vec<usize>, device: &B::Device) -> FloatTensor<B> {
    B::float_from_data(TensorData::new(v, shape), device)
}

fn host_forward<B: Backend>(
    inputs: [FloatTensor<B>; 4],
    grid: SplatGrid,
    field: DensityField,
) -> FloatTensor<B> {
    let device = inputs[0].device();
    let [m, q, s, d] = inputs.map(host::<B>);
    let slices = GaussianSlices {
        means: &m,
        quats: &q,
        log_scales: &s,
        raw_densities: &d,
    };
    let mut shape = grid.resolution.to_vec();
    let values = match field {
        DensityField::Density => splat_forward(&slices, &grid),
        DensityField::SpatialGradient => {
            shape.push(3);
            splat_gradient_forward(&slices, &grid)
        }
    };
    tensor::<B>(values, shape, &device)
}

fn host_backward<B: Backend>(
    inputs: [FloatTensor<B>; 4],
    grid: SplatGrid,
    field: DensityField,
    grad: FloatTensor<B>,
) -> GaussianGrads<B> {
    let device = inputs[0].device();
    let [m, q, s, d] = inputs.map(host::<B>);
    let n = d.len();
    let slices = GaussianSlices {
        means: &m,
        quats: &q,
        log_scales: &s,
        raw_densities: &d,
    };
    let grad = host::<B>(grad);
    let (gm, gq, gs, gd) = match field {
        DensityField::Density => splat_backward(&slices, &grid, &grad),
        DensityField::SpatialGradient => splat_gradient_backward(&slices, &grid, &grad),
    };
    (
        tensor::<B>(gm, vec![n, 3], &device),
        tensor::<B>(gq, vec![n, 4], &device),
        tensor::<B>(gs, vec![n, 3], &device),
        tensor::<B>(gd, vec![n], &device),
    )
}

macro_rules! cpu_density_backend {
    ($backend:ty) => {
        impl DensityBackend for $backend {
            fn splat_field(
                means: FloatTensor<Self>,
                rotations: FloatTensor<Self>,
                log_scales: FloatTensor<Self>,
                raw_densities: FloatTensor<Self>,
                grid: SplatGrid,
                field: DensityField,
            ) -> FloatTensor<Self> {
                let inputs = [means, rotations, log_scales, raw_densities];
                host_forward::<Self>(inputs, grid, field)
            }

            fn splat_field_backward(
                means: FloatTensor<Self>,
                rotations: FloatTensor<Self>,
                log_scales: FloatTensor<Self>,
                raw_densities: FloatTensor<Self>,
                grid: SplatGrid,
                field: DensityField,
                grad: FloatTensor<Self>,
            ) -> GaussianGrads<Self> {
                let inputs = [means, rotations, log_scales, raw_densities];
                host_backward::<Self>(inputs, grid, field, grad)
            }
        }
    };
}

#[cfg(feature = "ndarray")]
cpu_density_backend!(burn::backend::NdArray);
#[cfg(feature = "flex")]
cpu_density_backend!(burn::backend::Flex);
/// The cube backends (wgpu, Vulkan, CUDA) run the kernels of [`crate::density_kernel`].
#[cfg(feature = "cube")]
impl DensityBackend for burn_cubecl::CubeBackend {
    fn splat_field(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
        field: DensityField,
    ) -> FloatTensor<Self> {
        crate::density_kernel::splat_field(
            means,
            rotations,
            log_scales,
            raw_densities,
            &grid,
            field,
        )
    }

    fn splat_field_backward(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
        field: DensityField,
        grad: FloatTensor<Self>,
    ) -> GaussianGrads<Self> {
        crate::density_kernel::splat_field_backward(
            means,
            rotations,
            log_scales,
            raw_densities,
            &grid,
            field,
            grad,
        )
    }
}

#[derive(Debug, Clone)]
struct SplatState<B: Backend> {
    inputs: [FloatTensor<B>; 4],
    grid: SplatGrid,
    field: DensityField,
}

#[derive(Debug)]
struct SplatBackward;

impl<B: Backend + DensityBackend> Backward<B, 4> for SplatBackward {
    type State = SplatState<B>;

    fn backward(self, ops: Ops<Self::State, 4>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let SplatState {
            inputs: [m, q, s, d],
            grid,
            field,
        } = ops.state;
        let (gm, gq, gs, gd) = {
            let _timed = gausmoke_core::profile::scope("density splat backward");
            B::splat_field_backward(m, q, s, d, grid, field, grad)
        };
        for (parent, g) in ops.parents.into_iter().zip([gm, gq, gs, gd]) {
            if let Some(node) = parent {
                grads.register::<B>(node.id, g);
            }
        }
    }
}

impl<B: Backend + DensityBackend, C: CheckpointStrategy> DensityBackend for Autodiff<B, C> {
    fn splat_field(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
        field: DensityField,
    ) -> FloatTensor<Self> {
        let nodes = [
            means.node(),
            rotations.node(),
            log_scales.node(),
            raw_densities.node(),
        ];
        let inputs = [
            means.into_primitive(),
            rotations.into_primitive(),
            log_scales.into_primitive(),
            raw_densities.into_primitive(),
        ];
        let [m, q, s, d] = inputs.clone();
        let output = {
            let _timed = gausmoke_core::profile::scope("density splat");
            B::splat_field(m, q, s, d, grid, field)
        };
        let state = SplatState {
            inputs,
            grid,
            field,
        };
        match SplatBackward.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish(state, output),
            OpsKind::UnTracked(prep) => prep.finish(output),
        }
    }

    /// Not differentiated again: the result is untracked.
    fn splat_field_backward(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
        field: DensityField,
        grad: FloatTensor<Self>,
    ) -> GaussianGrads<Self> {
        use burn::backend::AutodiffBackend;
        let wrap = <Self as AutodiffBackend>::from_inner;
        let (a, b, c, d) = B::splat_field_backward(
            means.into_primitive(),
            rotations.into_primitive(),
            log_scales.into_primitive(),
            raw_densities.into_primitive(),
            grid,
            field,
            grad.into_primitive(),
        );
        (wrap(a), wrap(b), wrap(c), wrap(d))
    }
}

fn splat<const D: usize>(
    gaussians: &GaussianTensors,
    grid: &GridSpec,
    cutoff: f32,
    field: DensityField,
) -> Tensor<D> {
    use burn::backend::Dispatch;
    let spec = SplatGrid {
        lo: grid.lo().to_array(),
        cell: grid.cell_size().to_array(),
        resolution: grid.resolution(),
        cutoff,
    };
    Tensor::from_dispatch(<Dispatch as DensityBackend>::splat_field(
        gaussians.means.clone().into_dispatch(),
        gaussians.rotations.clone().into_dispatch(),
        gaussians.log_scales.clone().into_dispatch(),
        gaussians.raw_densities.clone().into_dispatch(),
        spec,
        field,
    ))
}

/// `sigma_grid [nx, ny, nz]`: the Gaussians' density at every cell centre, each Gaussian
/// evaluated inside its `cutoff` support (squared Mahalanobis radius; 9 = 3 sigma).
/// Differentiable with respect to means, rotations, log-scales and raw densities. Inputs are
/// assumed valid (validate them with the renderer's checks first).
pub fn density_grid(gaussians: &GaussianTensors, grid: &GridSpec, cutoff: f32) -> Tensor<3> {
    splat(gaussians, grid, cutoff, DensityField::Density)
}

/// Analytic `grad sigma_grid [nx, ny, nz, 3]` (per world unit), differentiable like
/// [`density_grid`].
pub fn density_gradient_grid(
    gaussians: &GaussianTensors,
    grid: &GridSpec,
    cutoff: f32,
) -> Tensor<4> {
    splat(gaussians, grid, cutoff, DensityField::SpatialGradient)
}
