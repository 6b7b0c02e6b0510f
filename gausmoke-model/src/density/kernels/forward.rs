//! Forward of density splatting: one unit per Gaussian walks the cells of its support and adds
//! `sigma k(x)` (or the density's spatial gradient) into the grid with float atomics. CPU twin:
//! `density::host::splat_forward` / `splat_gradient_forward`.

use cubecl::prelude::*;
use gausmoke_render::kernels::atomics::GradientAdd;
use gausmoke_render::kernels::math::{Mat3, Quat, Vec3, softplus, whiten, whitening_context};

use super::support::{GridParam, cell_centre, gaussian_support};

/// Adds every Gaussian's density (`spatial_gradient = false`, one channel) or the density's
/// spatial gradient (`true`, three channels, `-sigma k L^T m`) into `field`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn splat_field_kernel<A: GradientAdd>(
    means: &[f32],
    quats: &[f32],
    log_scales: &[f32],
    raw_densities: &[f32],
    grid: &[f32],
    field: &mut [Atomic<A::Cell>],
    nx: u32,
    ny: u32,
    nz: u32,
    num_gaussians: u32,
    #[comptime] spatial_gradient: bool,
) {
    let i = ABSOLUTE_POS;
    if i >= num_gaussians as usize {
        terminate!();
    }
    let mean = Vec3::load(means, 3 * i);
    let log_scale = Vec3::load(log_scales, 3 * i);
    let context = whitening_context(&Quat::load(quats, 4 * i), &log_scale, &mean);
    let whitening = whiten(&context, &Mat3::identity());
    let sigma = softplus(raw_densities[i]);
    let support = gaussian_support(grid, &mean, &log_scale, nx, ny, nz);
    let cutoff = grid[GridParam::CUTOFF];
    let mut ci = support.x.start;
    while ci < support.x.end {
        let x0 = cell_centre(grid, 0usize, ci);
        let mut cj = support.y.start;
        while cj < support.y.end {
            let x1 = cell_centre(grid, 1usize, cj);
            let mut ck = support.z.start;
            while ck < support.z.end {
                let x = Vec3::new(x0, x1, cell_centre(grid, 2usize, ck));
                // m = L x - L mu: the whitened offset of the cell centre.
                let m = whitening.whiten.mul(&x).sub(&whitening.center);
                let k2 = m.dot(&m);
                if k2 <= cutoff {
                    let kernel = (-0.5f32 * k2).exp();
                    let cell = ((ci * ny + cj) * nz + ck) as usize;
                    if spatial_gradient {
                        let g = whitening.whiten.transpose_mul(&m).scale(-sigma * kernel);
                        A::add(field, 3 * cell, g.x);
                        A::add(field, 3 * cell + 1, g.y);
                        A::add(field, 3 * cell + 2, g.z);
                    } else {
                        A::add(field, cell, sigma * kernel);
                    }
                }
                ck += 1;
            }
            cj += 1;
        }
        ci += 1;
    }
}
