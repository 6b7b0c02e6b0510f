//! Advection of Gaussian centres through the velocity grid (paper Eq. 13).
//!
//! Box rule: a centre that would leave the grid's box is clamped back onto the box boundary
//! (per axis) and flagged in [`Advected::left_box`], so the caller can freeze or prune it; its
//! gradient along a clamped axis is zero, which is what a wall does.

use burn::tensor::{Bool, Device, Tensor, TensorData};

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
    let [m, _] = points.dims();
    let (lo, hi) = box_bounds(grid, m, &points.device());
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

/// Carries the velocity grid along itself for `dt` frames (semi-Lagrangian: each cell takes
/// the trilinear sample at the point its own velocity brings to it, `u(x - dt u_g)`), so
/// every new value lies between values the field held (a maximum principle).
///
/// This is momentum transport, the `(u . grad) u` of the Navier-Stokes equations that the
/// paper's residual update `u + Phi(u, sigma, t)` leaves to the network: without it a swirl
/// stays where it formed while the smoke it turns rises through it. Trilinear rather than the
/// Gaussian kernel because the kernel does not reproduce the grid at cell centres, so it
/// would blur the field a little at every frame.
pub fn transport_velocity(grid: &GridSpec, velocity: &Tensor<4>, dt: f32) -> Tensor<4> {
    grid.assert_velocity_shape(velocity.dims());
    let [nx, ny, nz] = grid.resolution();
    let device = velocity.device();
    let cells = nx * ny * nz;
    let centres = Tensor::<2>::from_data(TensorData::new(grid.cell_centres(), [cells, 3]), &device);
    let own = velocity.clone().reshape([cells, 3]);
    // Clamped to the outermost cell centres, not the box: beyond them trilinear sampling
    // extrapolates and could create values the field does not hold.
    let half = grid.cell_size() * 0.5;
    let first = Tensor::<2>::from_data(
        TensorData::new((grid.lo() + half).to_array().to_vec(), [1, 3]),
        &device,
    )
    .expand([cells, 3]);
    let last = Tensor::<2>::from_data(
        TensorData::new((grid.hi() - half).to_array().to_vec(), [1, 3]),
        &device,
    )
    .expand([cells, 3]);
    let departure = (centres - own * dt).max_pair(first).min_pair(last);
    sample_velocity(grid, velocity, &departure, Interpolation::Trilinear)
        .velocity
        .reshape([nx, ny, nz, 3])
}

/// The box's lower and upper corners, `[m, 3]` each.
fn box_bounds(grid: &GridSpec, m: usize, device: &Device) -> (Tensor<2>, Tensor<2>) {
    let bound = |v: [f32; 3]| {
        Tensor::<2>::from_data(TensorData::new(v.to_vec(), [1, 3]), device).expand([m, 3])
    };
    (bound(grid.lo().to_array()), bound(grid.hi().to_array()))
}
