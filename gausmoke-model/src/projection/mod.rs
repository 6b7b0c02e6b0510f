//! Incompressibility projection `Pi` (paper Eq. 10), exact: the discrete Helmholtz projection
//! (see [`host`] for the operators), as a custom op whose backward pass is `Pi` itself
//! ([`op`]). The CPU backends solve its Poisson equation directly ([`spectral`]: separation
//! of variables, no iterations); the cube backends run Jacobi-PCG on the device (`kernels`,
//! with [`host::project`] its host twin). The paper's penalty form is [`crate::penalty`].

pub mod host;
#[cfg(feature = "cube")]
mod kernels;
mod op;
pub mod spectral;

use burn::tensor::Tensor;

use crate::grid::GridSpec;
pub use host::{
    ConvergenceTests, DeviceSolve, Divergence, OpenFaces, ProjectionOptions, ProjectionReport,
    ProjectionSpec, SolidCells, SolveKind,
};
pub use op::ProjectionBackend;

/// `Pi(u)`: the divergence-free, wall-tangent part of the velocity grid `[nx, ny, nz, 3]`
/// (zero in `options`' obstacle cells).
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

/// What the device solves run with [`ConvergenceTests::Deferred`] reached, judged together.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct DeferredSolves {
    /// Solves judged.
    pub solves: usize,
    /// Of them, those that ran out of their iteration budget before converging.
    pub unconverged: usize,
    /// The largest final `|r| / |D u|` among the unconverged ones (0 when none).
    pub worst_relative_residual: f64,
}

/// Judges every device solve run with [`ConvergenceTests::Deferred`] since the last call, in
/// one read of the device, and sets the iteration budgets of the next ones from what they
/// needed. Nothing to judge (no such solve, or a build without cube backends): no read.
pub fn settle_deferred_solves() -> DeferredSolves {
    #[cfg(feature = "cube")]
    {
        kernels::settle_deferred_solves()
    }
    #[cfg(not(feature = "cube"))]
    {
        DeferredSolves::default()
    }
}

/// Projects on the host as the CPU backends do and returns the report (for diagnostics and the
/// CLI): the direct solve of [`spectral`], with `options`' open faces; with obstacle cells,
/// which the direct solve cannot separate, Jacobi-PCG in f64 to `options`' tolerance.
pub fn project_direct(
    grid: &GridSpec,
    velocity: &mut [f32],
    options: &ProjectionOptions,
) -> ProjectionReport {
    project_on_host(&ProjectionSpec::new(grid, options.clone()), velocity)
}

/// [`project_direct`] for a [`ProjectionSpec`]. With obstacles, CG is preconditioned by the
/// direct solve of the same box without them: the two operators differ only around the
/// obstacles, so few iterations remain (14 for a relative residual of 1e-10 on a 14 x 16 x 12
/// grid around a sphere, against 90 with the Jacobi preconditioner). It stops at `options`'
/// tolerance, as the device solver does.
pub(crate) fn project_on_host(spec: &ProjectionSpec, velocity: &mut [f32]) -> ProjectionReport {
    let op = spec.operator();
    match &op.solids {
        Some(solids) => {
            let free = op.clone().with_solids(None);
            let solver = spectral::SpectralSolver::for_grid(&free);
            host::project_preconditioned(&op, velocity, &spec.options, |r, z| {
                z.copy_from_slice(r);
                solver.solve(z);
                for (z, &solid) in z.iter_mut().zip(solids.flags()) {
                    if solid {
                        *z = 0.0;
                    }
                }
            })
        }
        None => spectral::project(&op, &spectral::SpectralSolver::for_grid(&op), velocity),
    }
}

/// Projects on the host with Jacobi-PCG, `options`' tolerance and iteration limit (the twin
/// of the device solver of the cube backends), and returns the solver report.
pub fn project_with_report(
    grid: &GridSpec,
    velocity: &mut [f32],
    options: &ProjectionOptions,
) -> ProjectionReport {
    host::project(
        &ProjectionSpec::new(grid, options.clone()).operator(),
        velocity,
        options,
    )
}
