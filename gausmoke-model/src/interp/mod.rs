//! Continuous velocity from the Eulerian grid (paper Eq. 11) with its closed-form Jacobian and
//! divergence (Eq. 12, Appendix A Eq. 22-23), and trilinear interpolation as an alternative.
//!
//! The Gaussian kernel is one fused custom op with a closed-form backward pass ([`host`] on
//! the CPU backends, `kernels` on the cube backends); trilinear interpolation is composed of
//! burn tensor ops ([`composed`]). Both are differentiable with respect to the grid velocities
//! and the query points on every backend.
//!
//! # Choice of kernel
//!
//! The normalised Gaussian kernel does not reproduce linear fields exactly, and its bias
//! depends strongly on the stencil and the kernel width. For a linear field the interpolated
//! slope (1 is exact) is, over all positions within a cell:
//!
//! | stencil | std (cells) | slope        | position bias |
//! |---------|-------------|--------------|---------------|
//! | 2x2x2   | 1.0         | 0.24 .. 0.25 | 0.38 cell     |
//! | 2x2x2   | 0.5         | 0.42 .. 1.00 | 0.12 cell     |
//! | 4x4x4   | 0.6         | 0.95 .. 1.02 | 0.005 cell    |
//! | 6x6x6   | 0.7         | 0.997 .. 1.002 | < 0.001 cell |
//!
//! A 2x2x2 stencil with a one-cell kernel underestimates every velocity gradient (and so the
//! divergence the losses penalise) about four times; the default here is 4x4x4 with a 0.6-cell
//! standard deviation. (Checked by the `kernel_bias_table` test.)
//!
//! The stencil follows the query point, so where it moves by one cell (when a coordinate
//! crosses a cell centre) the Gaussian interpolant jumps by the weight of the node it drops:
//! about `exp(-2 / std^2)` relative, 0.4% for the default. Trilinear is continuous but has
//! kinks there. Neither matters for advection; finite-difference checks must avoid them.

pub mod composed;
pub mod host;
#[cfg(feature = "cube")]
mod kernels;
mod kind;
mod op;

use burn::tensor::{Tensor, TensorData};

use crate::grid::GridSpec;
pub use host::KernelGrid;
pub use kind::{Interpolation, VelocitySample};
pub use op::{SampleBackend, SamplePasses};

/// Samples the velocity grid `velocity` (`[nx, ny, nz, 3]`, see [`crate::grid`]) at
/// `points` (`[M, 3]`, world units). Points outside the box use the nearest in-box stencil
/// (the kernel extrapolates smoothly).
pub fn sample_velocity(
    grid: &GridSpec,
    velocity: &Tensor<4>,
    points: &Tensor<2>,
    kind: Interpolation,
) -> VelocitySample {
    let Interpolation::Gaussian { stencil, std_cells } = kind else {
        return composed::sample(grid, velocity, points, kind);
    };
    use burn::backend::Dispatch;
    let [m, _] = points.dims();
    let spec = KernelGrid {
        lo: grid.lo().to_array(),
        cell: grid.cell_size().to_array(),
        resolution: grid.resolution(),
        stencil,
        std_cells,
    };
    let sampled = Tensor::<2>::from_dispatch(<Dispatch as SampleBackend>::sample_gaussian(
        velocity.clone().into_dispatch(),
        points.clone().into_dispatch(),
        spec,
    ));
    VelocitySample {
        velocity: sampled.clone().slice([0..m, 0..3]),
        jacobian: sampled.slice([0..m, 3..12]).reshape([m, 3, 3]),
    }
}

/// Velocity grid `[nx, ny, nz, 3]` holding `field(cell centre)` (for tests and analytic
/// initial conditions).
pub fn grid_from_fn(
    grid: &GridSpec,
    device: &burn::tensor::Device,
    field: impl Fn([f32; 3]) -> [f32; 3],
) -> Tensor<4> {
    let [nx, ny, nz] = grid.resolution();
    let values: Vec<f32> = grid
        .cell_centres()
        .chunks_exact(3)
        .flat_map(|c| field([c[0], c[1], c[2]]))
        .collect();
    Tensor::from_data(TensorData::new(values, [nx, ny, nz, 3]), device)
}
