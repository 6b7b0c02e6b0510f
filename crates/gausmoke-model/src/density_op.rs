//! [`crate::density`] as a burn backend extension with a hand-written backward.

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

use crate::density::{GaussianSlices, SplatGrid, splat_backward, splat_forward};
use crate::grid::GridSpec;

#[backend_extension(
    NdArray: cfg(feature = "ndarray"),
    Flex: cfg(feature = "flex"),
    Autodiff,
)]
pub trait DensityBackend: Backend {
    /// `sigma_grid [nx, ny, nz]` of Gaussians `means [N, 3]`, `rotations [N, 4]`,
    /// `log_scales [N, 3]`, `raw_densities [N]` (`sigma = softplus(raw)`).
    fn splat_density(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
    ) -> FloatTensor<Self>;

    /// Gradients of the four inputs given `dLoss/dsigma_grid`.
    #[allow(clippy::type_complexity)]
    fn splat_density_backward(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
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

macro_rules! cpu_density_backend {
    ($backend:ty) => {
        impl DensityBackend for $backend {
            fn splat_density(
                means: FloatTensor<Self>,
                rotations: FloatTensor<Self>,
                log_scales: FloatTensor<Self>,
                raw_densities: FloatTensor<Self>,
                grid: SplatGrid,
            ) -> FloatTensor<Self> {
                let device = means.device();
                let (m, q, s, d) = (
                    host::<Self>(means),
                    host::<Self>(rotations),
                    host::<Self>(log_scales),
                    host::<Self>(raw_densities),
                );
                let slices = GaussianSlices {
                    means: &m,
                    quats: &q,
                    log_scales: &s,
                    raw_densities: &d,
                };
                tensor::<Self>(
                    splat_forward(&slices, &grid),
                    grid.resolution.to_vec(),
                    &device,
                )
            }

            fn splat_density_backward(
                means: FloatTensor<Self>,
                rotations: FloatTensor<Self>,
                log_scales: FloatTensor<Self>,
                raw_densities: FloatTensor<Self>,
                grid: SplatGrid,
                grad: FloatTensor<Self>,
            ) -> (
                FloatTensor<Self>,
                FloatTensor<Self>,
                FloatTensor<Self>,
                FloatTensor<Self>,
            ) {
                let device = means.device();
                let (m, q, s, d) = (
                    host::<Self>(means),
                    host::<Self>(rotations),
                    host::<Self>(log_scales),
                    host::<Self>(raw_densities),
                );
                let n = d.len();
                let slices = GaussianSlices {
                    means: &m,
                    quats: &q,
                    log_scales: &s,
                    raw_densities: &d,
                };
                let (gm, gq, gs, gd) = splat_backward(&slices, &grid, &host::<Self>(grad));
                (
                    tensor::<Self>(gm, vec![n, 3], &device),
                    tensor::<Self>(gq, vec![n, 4], &device),
                    tensor::<Self>(gs, vec![n, 3], &device),
                    tensor::<Self>(gd, vec![n], &device),
                )
            }
        }
    };
}

#[cfg(feature = "ndarray")]
cpu_density_backend!(burn::backend::NdArray);
#[cfg(feature = "flex")]
cpu_density_backend!(burn::backend::Flex);

#[derive(Debug, Clone)]
struct SplatState<B: Backend> {
    inputs: [FloatTensor<B>; 4],
    grid: SplatGrid,
}

#[derive(Debug)]
struct SplatBackward;

impl<B: Backend + DensityBackend> Backward<B, 4> for SplatBackward {
    type State = SplatState<B>;

    fn backward(self, ops: Ops<Self::State, 4>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let [m, q, s, d] = ops.state.inputs;
        let (gm, gq, gs, gd) = B::splat_density_backward(m, q, s, d, ops.state.grid, grad);
        for (parent, g) in ops.parents.into_iter().zip([gm, gq, gs, gd]) {
            if let Some(node) = parent {
                grads.register::<B>(node.id, g);
            }
        }
    }
}

impl<B: Backend + DensityBackend, C: CheckpointStrategy> DensityBackend for Autodiff<B, C> {
    fn splat_density(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
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
        let output = B::splat_density(m, q, s, d, grid);
        match SplatBackward.prepare::<C>(nodes).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish(SplatState { inputs, grid }, output),
            OpsKind::UnTracked(prep) => prep.finish(output),
        }
    }

    /// Not differentiated again: the result is untracked.
    fn splat_density_backward(
        means: FloatTensor<Self>,
        rotations: FloatTensor<Self>,
        log_scales: FloatTensor<Self>,
        raw_densities: FloatTensor<Self>,
        grid: SplatGrid,
        grad: FloatTensor<Self>,
    ) -> (
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
        FloatTensor<Self>,
    ) {
        use burn::backend::AutodiffBackend;
        let wrap = <Self as AutodiffBackend>::from_inner;
        let (a, b, c, d) = B::splat_density_backward(
            means.into_primitive(),
            rotations.into_primitive(),
            log_scales.into_primitive(),
            raw_densities.into_primitive(),
            grid,
            grad.into_primitive(),
        );
        (wrap(a), wrap(b), wrap(c), wrap(d))
    }
}

/// `sigma_grid [nx, ny, nz]`: the Gaussians' density at every cell centre, each Gaussian
/// evaluated inside its `cutoff` support (squared Mahalanobis radius; 9 = 3 sigma).
/// Differentiable with respect to means, rotations, log-scales and raw densities. Inputs are
/// assumed valid (validate them with the renderer's checks first).
pub fn density_grid(gaussians: &GaussianTensors, grid: &GridSpec, cutoff: f32) -> Tensor<3> {
    use burn::backend::Dispatch;
    let spec = SplatGrid {
        lo: grid.lo().to_array(),
        cell: grid.cell_size().to_array(),
        resolution: grid.resolution(),
        cutoff,
    };
    Tensor::from_dispatch(<Dispatch as DensityBackend>::splat_density(
        gaussians.means.clone().into_dispatch(),
        gaussians.rotations.clone().into_dispatch(),
        gaussians.log_scales.clone().into_dispatch(),
        gaussians.raw_densities.clone().into_dispatch(),
        spec,
    ))
}
