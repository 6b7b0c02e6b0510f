//! Advection of Gaussian centres through the velocity grid (paper Eq. 13).
//!
//! Box rule: a centre that would leave the grid's box is clamped back onto the box boundary
//! (per axis) and flagged in [`Advected::left_box`], so the caller can freeze or prune it; its
//! gradient along a clamped axis is zero, which is what a wall does.

use burn::tensor::{Bool, Tensor, TensorData};

use crate::grid::GridSpec;
use crate::interp::{Interpolation, VelocitySample, sample_velocity};

/// Time integrator of `dp/dt = u(p)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Integrator {
    /// `p + dt u(p)` (Eq. 13, the paper's choice).
    #[default]
    Euler,
    /// Explicit midpoint: `p + dt u(p + dt/2 u(p))`; second order.
    Rk2,
}

#[derive(Debug, Clone)]
pub struct Advected {
    /// New centres `[M, 3]`, inside the box.
    pub positions: Tensor<2>,
    /// Which centres were clamped back into the box, `[M]`.
    pub left_box: Tensor<1, Bool>,
    /// The velocity and its Jacobian at the starting points (what `L_div` at the centres
    /// reads, so it is sampled once).
    pub start: VelocitySample,
}

/// Moves `points` (`[M, 3]`) for `dt` frames through `velocity` (`[nx, ny, nz, 3]`, world
/// units per frame).
pub fn advect(
    grid: &GridSpec,
    velocity: &Tensor<4>,
    points: &Tensor<2>,
    dt: f32,
    integrator: Integrator,
    interpolation: Interpolation,
) -> Advected {
    let start = sample_velocity(grid, velocity, points, interpolation);
    let moved = match integrator {
        Integrator::Euler => points.clone() + start.velocity.clone() * dt,
        Integrator::Rk2 => {
            let midpoint = points.clone() + start.velocity.clone() * (0.5 * dt);
            let u = sample_velocity(grid, velocity, &midpoint, interpolation).velocity;
            points.clone() + u * dt
        }
    };
    let device = points.device();
    let [m, _] = points.dims();
    let bound = |v: [f32; 3]| {
        Tensor::<2>::from_data(TensorData::new(v.to_vec(), [1, 3]), &device).expand([m, 3])
    };
    let lo = bound(grid.lo().to_array());
    let hi = bound(grid.hi().to_array());
    let outside = moved
        .clone()
        .lower(lo.clone())
        .any_dim(1)
        .bool_or(moved.clone().greater(hi.clone()).any_dim(1));
    Advected {
        positions: moved.max_pair(lo).min_pair(hi),
        left_box: outside.reshape([m]),
        start,
    }
}
