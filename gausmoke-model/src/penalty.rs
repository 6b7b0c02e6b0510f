//! The paper's own form of `Pi` (Eq. 10: "a penalty-based differentiable operator"), kept as
//! an option beside the exact projection of [`crate::projection`].
//!
//! A fixed number of gradient-descent steps on `E(u) = |D u|^2 / 2`, with the same discrete
//! divergence `D` as the exact projection (face velocity = mean of the two cells, zero normal
//! flow on the walls):
//!
//! `u <- u - eta D^T D u`, `eta = step_fraction / sum_a h_a^-2`.
//!
//! The largest eigenvalue of `D^T D` is at most `sum_a h_a^-2` (each axis's averaged central
//! difference has symbol `sin(k h) / h`), so any `step_fraction` in `(0, 2)` decreases `E`
//! monotonically. High-frequency divergence goes in a few steps, smooth divergence slowly:
//! unlike the exact projection this leaves part of `D u` behind, which is the point of
//! comparing the two (`divergence_rms_after` in the report says how much).
//!
//! Everything is plain burn tensor ops, so it runs on every backend and autodiff
//! differentiates it (each step is linear and symmetric, so its backward is the same map).

use burn::tensor::Tensor;

use crate::grid::GridSpec;
use crate::projection::ProjectionReport;

/// Steps and step size of the penalty form.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PenaltyOptions {
    pub steps: usize,
    /// `eta` as a fraction of `1 / sum_a h_a^-2`; stable in `(0, 2)`.
    pub step_fraction: f32,
}

impl Default for PenaltyOptions {
    fn default() -> Self {
        Self {
            steps: 20,
            step_fraction: 1.0,
        }
    }
}

/// Zero face values on both walls of `axis` around the `n - 1` interior faces.
fn pad_walls(interior: Tensor<4>, axis: usize) -> Tensor<4> {
    let mut wall_shape = interior.dims();
    wall_shape[axis] = 1;
    let wall = Tensor::<4>::zeros(wall_shape, &interior.device());
    Tensor::cat(vec![wall.clone(), interior, wall], axis)
}

/// Component `axis` of a velocity grid, `[nx, ny, nz, 1]`.
fn component(velocity: &Tensor<4>, axis: usize) -> Tensor<4> {
    velocity.clone().narrow(3, axis, 1)
}

/// Discrete divergence `D u` of `velocity [nx, ny, nz, 3]` as `[nx, ny, nz, 1]` (per world
/// unit of length; velocities in world units per frame give 1/frame): the same operator as
/// [`crate::projection::Divergence::apply`].
pub fn grid_divergence(grid: &GridSpec, velocity: &Tensor<4>) -> Tensor<4> {
    let cell = grid.cell_size().to_array();
    let resolution = grid.resolution();
    let mut total: Option<Tensor<4>> = None;
    for axis in 0..3 {
        let n = resolution[axis];
        let u = component(velocity, axis);
        let faces = (u.clone().narrow(axis, 0, n - 1) + u.narrow(axis, 1, n - 1)) * 0.5;
        let faces = pad_walls(faces, axis);
        let term = (faces.clone().narrow(axis, 1, n) - faces.narrow(axis, 0, n)) / cell[axis];
        total = Some(match total {
            Some(sum) => sum + term,
            None => term,
        });
    }
    total.expect("three axes")
}

/// The adjoint `D^T p` of [`grid_divergence`] for `p [nx, ny, nz, 1]`, as `[nx, ny, nz, 3]`
/// (`-D^T` is the discrete gradient).
pub fn grid_divergence_transpose(grid: &GridSpec, p: &Tensor<4>) -> Tensor<4> {
    let cell = grid.cell_size().to_array();
    let resolution = grid.resolution();
    let components = (0..3)
        .map(|axis| {
            let n = resolution[axis];
            // q at the face between cells i and i + 1: (p_i - p_{i+1}) / 2, zero on walls;
            // cell i receives the q of both its faces.
            let q = (p.clone().narrow(axis, 0, n - 1) - p.clone().narrow(axis, 1, n - 1)) * 0.5;
            let q = pad_walls(q, axis);
            (q.clone().narrow(axis, 1, n) + q.narrow(axis, 0, n)) / cell[axis]
        })
        .collect();
    Tensor::cat(components, 3)
}

/// The penalty form of `Pi` applied to `velocity [nx, ny, nz, 3]` (see the module docs).
pub fn penalty_projection(
    grid: &GridSpec,
    velocity: Tensor<4>,
    options: &PenaltyOptions,
) -> Tensor<4> {
    grid.assert_velocity_shape(velocity.dims());
    let cell = grid.cell_size();
    let curvature = 1.0 / (cell.x * cell.x) + 1.0 / (cell.y * cell.y) + 1.0 / (cell.z * cell.z);
    let eta = options.step_fraction / curvature;
    let mut u = velocity;
    for _ in 0..options.steps {
        let divergence = grid_divergence(grid, &u);
        u = u - grid_divergence_transpose(grid, &divergence) * eta;
    }
    u
}

/// [`penalty_projection`] with the report the exact solve gives: RMS divergence before and
/// after (iterations = steps; the relative residual is `|D u_after| / |D u_before|`).
pub fn penalty_projection_with_report(
    grid: &GridSpec,
    velocity: Tensor<4>,
    options: &PenaltyOptions,
) -> (Tensor<4>, ProjectionReport) {
    let rms = |t: &Tensor<4>| -> f64 {
        let d = grid_divergence(grid, t);
        gausmoke_render::device_traffic::read_scalar((d.clone() * d).mean()) as f64
    };
    let before = rms(&velocity).sqrt();
    let projected = penalty_projection(grid, velocity, options);
    let after = rms(&projected).sqrt();
    let report = ProjectionReport {
        iterations: options.steps,
        relative_residual: if before > 0.0 { after / before } else { 0.0 },
        divergence_rms_before: before,
        divergence_rms_after: after,
    };
    (projected, report)
}
