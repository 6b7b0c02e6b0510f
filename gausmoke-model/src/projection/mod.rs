//! Incompressibility projection `Pi` (paper Eq. 10), exact: the discrete Helmholtz projection
//! (see [`host`] for the operators and the solver), as a custom op whose backward pass is
//! `Pi` itself ([`op`]), solved on the host for the CPU backends and on the device for the cube
//! backends (`kernels`). The paper's penalty form is [`crate::penalty`].

pub mod host;
#[cfg(feature = "cube")]
mod kernels;
mod op;

use burn::tensor::Tensor;

use crate::grid::GridSpec;
pub use host::{Divergence, ProjectionOptions, ProjectionReport, ProjectionSpec};
pub use op::ProjectionBackend;

/// `Pi(u)`: the divergence-free, wall-tangent part of the velocity grid `[nx, ny, nz, 3]`.
/// Differentiable: its gradient is `Pi` of the incoming gradient.
pub fn project_velocity(
    grid: &GridSpec,
    velocity: Tensor<4>,
    options: ProjectionOptions,
) -> Tensor<4> {
    use burn::backend::Dispatch;
    grid.assert_velocity_shape(velocity.dims());
    Tensor::from_dispatch(<Dispatch as ProjectionBackend>::project_velocity(
        velocity.into_dispatch(),
        ProjectionSpec::new(grid, options),
    ))
}

/// Projects on the host and returns the solver report (for diagnostics and the CLI).
pub fn project_with_report(
    grid: &GridSpec,
    velocity: &mut [f32],
    options: &ProjectionOptions,
) -> ProjectionReport {
    host::project(
        &ProjectionSpec::new(grid, *options).operator(),
        velocity,
        options,
    )
}
