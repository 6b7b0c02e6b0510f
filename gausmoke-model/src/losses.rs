//! Physical losses of Eq. 14.

use burn::tensor::Tensor;

use crate::grid::GridSpec;
use crate::interp::{Interpolation, VelocitySample, sample_velocity};

/// `L_div` (Eq. 16): mean squared closed-form divergence (Eq. 12) of the interpolated
/// velocity at `points` `[M, 3]` (e.g. the cell centres, or the Gaussians' centres).
pub fn divergence_loss(
    grid: &GridSpec,
    velocity: &Tensor<4>,
    points: &Tensor<2>,
    interpolation: Interpolation,
) -> Tensor<1> {
    divergence_loss_of(&sample_velocity(grid, velocity, points, interpolation))
}

/// [`divergence_loss`] of velocity already sampled at the points (e.g. by
/// [`crate::advect`]).
pub fn divergence_loss_of(sample: &VelocitySample) -> Tensor<1> {
    sample.divergence().powi_scalar(2).mean()
}

/// `L_refine` (Eq. 18): mean over Gaussians of the squared distance between the refined
/// centres and the advected ones they may deviate from, both `[N, 3]`.
pub fn refine_loss(refined: &Tensor<2>, advected: &Tensor<2>) -> Tensor<1> {
    (refined.clone() - advected.clone())
        .powi_scalar(2)
        .sum_dim(1)
        .mean()
}

/// `L_adv` (Eq. 17): mean over cells of the squared material derivative of the density,
/// `(sigma^{t+1} - sigma^t) / dt + u . grad sigma`, with `grad sigma` the mean of the two
/// frames' analytic gradients (time-centred, so translation at the true velocity leaves only
/// an O(dt^2) residual). `sigma_*: [nx, ny, nz]`, `grad_*` and `velocity: [nx, ny, nz, 3]`.
pub fn advection_loss(
    sigma_now: &Tensor<3>,
    sigma_next: &Tensor<3>,
    grad_now: &Tensor<4>,
    grad_next: &Tensor<4>,
    velocity: &Tensor<4>,
    dt: f32,
) -> Tensor<1> {
    let [nx, ny, nz] = sigma_now.dims();
    let transport = (velocity.clone() * (grad_now.clone() + grad_next.clone()) * 0.5)
        .sum_dim(3)
        .reshape([nx, ny, nz]);
    ((sigma_next.clone() - sigma_now.clone()) / dt + transport)
        .powi_scalar(2)
        .mean()
}
