//! Forward of density splatting: one unit per Gaussian walks the cells of its support and adds
//! `sigma k(x)` (or the density's spatial gradient) into the grid with float atomics. CPU twin:
//! `density::host::splat_forward` / `splat_gradient_forward`.

use cubecl::prelude::*;
use gausmoke_render::kernels::atomics::GradientAdd;

use super::support::{GridParam, grid_gaussian};

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
    let g = grid_gaussian(means, quats, log_scales, raw_densities, grid, i, nx, ny, nz);
    let cutoff = grid[GridParam::CUTOFF];
    let count = g.support.len();
    let mut k = 0u32;
    while k < count {
        let cell = g.support.cell(grid, k, ny, nz);
        // m = L x - L mu: the whitened offset of the cell centre.
        let m = g
            .whitening
            .whiten
            .mul(&cell.centre)
            .sub(&g.whitening.center);
        let k2 = m.dot(&m);
        if k2 <= cutoff {
            let kernel = (-0.5f32 * k2).exp();
            if spatial_gradient {
                let v = g
                    .whitening
                    .whiten
                    .transpose_mul(&m)
                    .scale(-g.sigma * kernel);
                A::add(field, 3 * cell.index, v.x);
                A::add(field, 3 * cell.index + 1, v.y);
                A::add(field, 3 * cell.index + 2, v.z);
            } else {
                A::add(field, cell.index, g.sigma * kernel);
            }
        }
        k += 1;
    }
}
