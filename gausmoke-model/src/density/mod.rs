//! Density of the Gaussians sampled at the grid's cell centres (paper Sec. 4.2),
//! `sigma_grid(x) = sum_i sigma_i k_i(x)`, and its analytic spatial gradient, as a custom op
//! with hand-written backward passes: [`host`] on the CPU backends, `kernels` on the cube
//! backends, `op` the burn extension that routes between them and differentiates.

pub mod host;
#[cfg(feature = "cube")]
mod kernels;
mod op;

use burn::tensor::Tensor;
use gausmoke_render::{FloatAtomics, GaussianTensors};

use crate::grid::GridSpec;
pub use host::{DensityField, SplatGrid};
pub use op::{DensityBackend, DensityPasses};

/// How the Gaussians are splatted.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplatOptions {
    /// Each Gaussian is evaluated inside this squared Mahalanobis radius (9 = 3 sigma, as the
    /// paper evaluates each kernel).
    pub cutoff: f32,
    /// How the GPU kernels add into the grid (ignored on the CPU).
    pub float_atomics: FloatAtomics,
}

impl Default for SplatOptions {
    fn default() -> Self {
        Self {
            cutoff: 9.0,
            float_atomics: FloatAtomics::Native,
        }
    }
}

/// `field` of `gaussians` at every cell centre of `grid`. Differentiable with respect to the
/// means, rotations, log-scales and raw densities (colours are not read). Inputs are assumed
/// valid (validate them with the renderer's checks first).
pub fn density_field<const D: usize>(
    gaussians: &GaussianTensors,
    grid: &GridSpec,
    options: &SplatOptions,
    field: DensityField,
) -> Tensor<D> {
    use burn::backend::Dispatch;
    let spec = SplatGrid {
        lo: grid.lo().to_array(),
        cell: grid.cell_size().to_array(),
        resolution: grid.resolution(),
        cutoff: options.cutoff,
    };
    Tensor::from_dispatch(<Dispatch as DensityBackend>::splat_density(
        gaussians.clone().into_dispatch(),
        spec,
        field,
        options.float_atomics,
    ))
}

/// `sigma_grid [nx, ny, nz]`, each Gaussian evaluated inside its `cutoff` support (squared
/// Mahalanobis radius; 9 = 3 sigma). See [`density_field`].
pub fn density_grid(gaussians: &GaussianTensors, grid: &GridSpec, cutoff: f32) -> Tensor<3> {
    let options = SplatOptions {
        cutoff,
        ..SplatOptions::default()
    };
    density_field(gaussians, grid, &options, DensityField::Density)
}

/// `sigma_grid` and its analytic gradient in one pass over the Gaussians (cheaper than
/// [`density_grid`] and [`density_gradient_grid`] apart). See [`density_field`].
pub fn density_and_gradient_grid(
    gaussians: &GaussianTensors,
    grid: &GridSpec,
    cutoff: f32,
) -> (Tensor<3>, Tensor<4>) {
    let options = SplatOptions {
        cutoff,
        ..SplatOptions::default()
    };
    let both: Tensor<4> = density_field(gaussians, grid, &options, DensityField::Both);
    let [nx, ny, nz, _] = both.dims();
    (
        both.clone()
            .slice([0..nx, 0..ny, 0..nz, 0..1])
            .reshape([nx, ny, nz]),
        both.slice([0..nx, 0..ny, 0..nz, 1..4]),
    )
}

/// Analytic `grad sigma_grid [nx, ny, nz, 3]` (per world unit). See [`density_field`].
pub fn density_gradient_grid(
    gaussians: &GaussianTensors,
    grid: &GridSpec,
    cutoff: f32,
) -> Tensor<4> {
    let options = SplatOptions {
        cutoff,
        ..SplatOptions::default()
    };
    density_field(gaussians, grid, &options, DensityField::SpatialGradient)
}
