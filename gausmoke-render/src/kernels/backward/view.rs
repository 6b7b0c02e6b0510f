//! Backward of stage 1: one unit per Gaussian chains its splat gradient back to the
//! world-space parameters (`math::view_vjp`).

use cubecl::prelude::*;

use crate::kernels::math::{Quat, Vec3, softplus_grad, whiten_vjp, whitening_context};
use crate::kernels::splat::{Splat, view_pose};

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn view_backward_kernel(
    means: &[f32],
    quats: &[f32],
    log_scales: &[f32],
    raw_densities: &[f32],
    view: &[f32],
    splat_grads: &[f32],
    grad_means: &mut [f32],
    grad_quats: &mut [f32],
    grad_log_scales: &mut [f32],
    grad_raw_densities: &mut [f32],
    grad_colors: &mut [f32],
    num_gaussians: u32,
) {
    let i = ABSOLUTE_POS;
    if i >= num_gaussians as usize {
        terminate!();
    }
    let grad = Splat::load(splat_grads, i);
    grad_raw_densities[i] = grad.sigma * softplus_grad(raw_densities[i]);
    grad.color.store(grad_colors, 3 * i);

    let (rotation, origin) = view_pose(view);
    let offset = Vec3::load(means, 3 * i).sub(&origin);
    let context = whitening_context(
        &Quat::load(quats, 4 * i),
        &Vec3::load(log_scales, 3 * i),
        &offset,
    );
    let world = whiten_vjp(&context, &rotation, &grad.whitening);
    world.mean.store(grad_means, 3 * i);
    world.log_scale.store(grad_log_scales, 3 * i);
    grad_quats[4 * i] = world.rotation.w;
    grad_quats[4 * i + 1] = world.rotation.x;
    grad_quats[4 * i + 2] = world.rotation.y;
    grad_quats[4 * i + 3] = world.rotation.z;
}
