//! Interpolation composed of burn tensor ops, so autodiff differentiates it with respect to
//! the grid velocities and the query points on every backend.

use burn::tensor::{Tensor, TensorData};

use super::kind::{Interpolation, VelocitySample};
use crate::grid::GridSpec;

/// Constant tensors of the stencil: node offsets `[S^3, 3]` (in cells).
fn stencil_offsets(stencil: usize, device: &burn::tensor::Device) -> Tensor<2> {
    let mut offsets = Vec::with_capacity(3 * stencil.pow(3));
    for a in 0..stencil {
        for b in 0..stencil {
            for c in 0..stencil {
                offsets.extend([a as f32, b as f32, c as f32]);
            }
        }
    }
    Tensor::from_data(TensorData::new(offsets, [stencil.pow(3), 3]), device)
}

fn row3(v: [f32; 3], device: &burn::tensor::Device) -> Tensor<2> {
    Tensor::from_data(TensorData::new(v.to_vec(), [1, 3]), device)
}

/// [`super::sample_velocity`] composed of burn tensor ops (differentiated by autodiff): what
/// trilinear interpolation runs, and an independent reference for the fused Gaussian op.
pub fn sample(
    grid: &GridSpec,
    velocity: &Tensor<4>,
    points: &Tensor<2>,
    kind: Interpolation,
) -> VelocitySample {
    let device = points.device();
    let [m, _] = points.dims();
    let [nx, ny, nz] = grid.resolution();
    let stencil = kind.stencil();
    let nodes = stencil.pow(3);
    let cell = grid.cell_size().to_array();
    let lo = grid.lo().to_array();

    // Continuous grid coordinate: cell centre (i, j, k) sits at exactly (i, j, k).
    let coord = (points.clone() - row3(lo, &device)) / row3(cell, &device) - 0.5;
    let first = (stencil / 2 - 1) as f32;
    let max_base = row3(
        [
            (nx - stencil) as f32,
            (ny - stencil) as f32,
            (nz - stencil) as f32,
        ],
        &device,
    )
    .expand([m, 3]);
    let base = (coord.clone().detach().floor() - first)
        .clamp_min(0.0)
        .min_pair(max_base);
    // Node coordinates [M, S^3, 3] and flat row indices into the [nx*ny*nz, 3] grid.
    let node = base.unsqueeze_dim::<3>(1) + stencil_offsets(stencil, &device).unsqueeze_dim::<3>(0);
    let strides = row3([(ny * nz) as f32, nz as f32, 1.0], &device).unsqueeze_dim::<3>(0);
    let flat = (node.clone() * strides)
        .sum_dim(2)
        .reshape([m * nodes])
        .int();
    let node_velocity = velocity
        .clone()
        .reshape([nx * ny * nz, 3])
        .select(0, flat)
        .reshape([m, nodes, 3]);
    // (x_g - x) in cells, [M, S^3, 3].
    let delta = node - coord.unsqueeze_dim::<3>(1);
    let cell_t = row3(cell, &device).unsqueeze_dim::<3>(0);

    match kind {
        Interpolation::Gaussian { std_cells, .. } => {
            let inv_var = 1.0 / (std_cells * std_cells);
            let dist_sq = delta.clone().powi_scalar(2).sum_dim(2); // [M, S^3, 1]
            // Shift by the nearest node's distance before exp so far-away points do not
            // underflow to 0/0; the shift cancels exactly in every normalised ratio below.
            let nearest = dist_sq.clone().detach().min_dim(1); // [M, 1, 1]
            let weights = ((dist_sq - nearest) * (-0.5 * inv_var)).exp();
            let total = weights.clone().sum_dim(1); // [M, 1, 1]
            let u = (weights.clone() * node_velocity.clone()).sum_dim(1) / total.clone(); // [M, 1, 3]
            // g_p = Sigma^-1 (x_g - x) = delta / (std^2 * h), per axis.
            let g = delta * inv_var / cell_t;
            let diff = node_velocity - u.clone(); // u_g - u(x)
            // J = (1 / sum k) sum_g k_g (u_g - u) (x) g_g  (Eq. 22).
            let jacobian = (diff * weights).swap_dims(1, 2).matmul(g) / total;
            VelocitySample {
                velocity: u.reshape([m, 3]),
                jacobian,
            }
        }
        Interpolation::Trilinear => {
            // Per axis, node offset o in {0, 1} gets weight 1 - s (o - t) with s = 2o - 1,
            // i.e. 1 - t or t for the fraction t: linear (and a partition of unity) even when
            // extrapolating outside the box. Its x-derivative is s / h.
            let side = stencil_offsets(2, &device).unsqueeze_dim::<3>(0) * 2.0 - 1.0; // [1, 8, 3]
            let tent = (side.clone() * delta).neg() + 1.0; // [M, 8, 3]
            let slope = side / cell_t; // [1, 8, 3]
            let axis = |t: &Tensor<3>, a: usize| t.clone().narrow(2, a, 1); // [M, 8, 1]
            let (tx, ty, tz) = (axis(&tent, 0), axis(&tent, 1), axis(&tent, 2));
            let weights = tx.clone() * ty.clone() * tz.clone();
            let grad_w = Tensor::cat(
                vec![
                    axis(&slope, 0) * ty.clone() * tz.clone(),
                    tx.clone() * axis(&slope, 1) * tz,
                    tx * ty * axis(&slope, 2),
                ],
                2,
            ); // [M, 8, 3]
            let u = (weights * node_velocity.clone()).sum_dim(1);
            let jacobian = node_velocity.swap_dims(1, 2).matmul(grad_w);
            VelocitySample {
                velocity: u.reshape([m, 3]),
                jacobian,
            }
        }
    }
}
