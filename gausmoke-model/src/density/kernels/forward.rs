//! Forward of density splatting: one unit per Gaussian walks the cells of its support and adds
//! `sigma k(x)` (or the density's spatial gradient) into the grid with float atomics. CPU twin:
//! `density::host::splat_forward` / `splat_gradient_forward`.

use cubecl::prelude::*;
use gausmoke_render::kernels::atomics::GradientAdd;

use super::support::{GridParam, grid_gaussian};

/// Adds every Gaussian's density (one channel) and/or the density's spatial gradient (three
/// channels, `-sigma k L^T m`) into `field` (channels in that order).
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
    #[comptime] density: bool,
    #[comptime] gradient: bool,
) {
    let channels = comptime!(density as usize + 3 * gradient as usize);
    let offset = comptime!(density as usize);
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
            let base = channels * cell.index;
            if density {
                A::add(field, base, g.sigma * kernel);
            }
            if gradient {
                let v = g
                    .whitening
                    .whiten
                    .transpose_mul(&m)
                    .scale(-g.sigma * kernel);
                A::add(field, base + offset, v.x);
                A::add(field, base + offset + 1, v.y);
                A::add(field, base + offset + 2, v.z);
            }
        }
        k += 1;
    }
}
