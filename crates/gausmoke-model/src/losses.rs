//! Physical losses of Eq. 14 that need no custom op.
//!
//! (`L_adv`, Eq. 17, needs the analytic spatial gradient of the splatted density and is not
//! written yet.)

use burn::tensor::Tensor;

use crate::grid::GridSpec;
use crate::interp::{Interpolation, sample_velocity};

/// `L_div` (Eq. 16): mean squared closed-form divergence (Eq. 12) of the interpolated
/// velocity at `points` `[M, 3]` (e.g. the cell centres, or the Gaussians' centres).
pub fn divergence_loss(
    grid: &GridSpec,
    velocity: &Tensor<4>,
    points: &Tensor<2>,
    interpolation: Interpolation,
) -> Tensor<1> {
    sample_velocity(grid, velocity, points, interpolation)
        .divergence()
        .powi_scalar(2)
        .mean()
}

/// `L_refine` (Eq. 18): mean over Gaussians of the squared distance between the refined
/// centres and the advected ones they may deviate from, both `[N, 3]`.
pub fn refine_loss(refined: &Tensor<2>, advected: &Tensor<2>) -> Tensor<1> {
    (refined.clone() - advected.clone())
        .powi_scalar(2)
        .sum_dim(1)
        .mean()
}
