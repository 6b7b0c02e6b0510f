//! Backward of density splatting: one unit per Gaussian gathers the incoming grid gradient at
//! the cells of its support (no atomics), sums the gradient of its world-space whitening
//! (`L`, `L mu`, `sigma`) and chains it to the parameters. The per-cell formulas are those of
//! `density::host::splat_backward` and `splat_gradient_backward`.

use cubecl::prelude::*;
use gausmoke_render::kernels::math::{Mat3, Vec3, Whitening, softplus_grad, whiten_vjp};

use super::support::{GridParam, grid_gaussian};

/// Gradient of one Gaussian's whitening and density, summed over the cells of its support.
#[derive(CubeType)]
pub struct WhiteningSum {
    pub whiten: Mat3,
    pub center: Vec3,
    pub sigma: f32,
}

#[cube]
impl WhiteningSum {
    fn zero() -> WhiteningSum {
        WhiteningSum {
            whiten: Mat3 {
                r0: Vec3::new(0.0, 0.0, 0.0),
                r1: Vec3::new(0.0, 0.0, 0.0),
                r2: Vec3::new(0.0, 0.0, 0.0),
            },
            center: Vec3::new(0.0, 0.0, 0.0),
            sigma: 0.0,
        }
    }

    /// Adds the outer product `a b^T` to the gradient of `L`.
    fn add_outer(&mut self, a: &Vec3, b: &Vec3) {
        self.whiten.r0.add_assign(&b.scale(a.x));
        self.whiten.r1.add_assign(&b.scale(a.y));
        self.whiten.r2.add_assign(&b.scale(a.z));
    }

    /// Adds `dLoss/dm` at the cell centre `x` through `m = L x - L mu`.
    fn add_offset_grad(&mut self, grad_m: &Vec3, x: &Vec3) {
        self.add_outer(grad_m, x);
        self.center.sub_assign(grad_m);
    }
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn splat_field_backward_kernel(
    means: &[f32],
    quats: &[f32],
    log_scales: &[f32],
    raw_densities: &[f32],
    grid: &[f32],
    grad_field: &[f32],
    grad_means: &mut [f32],
    grad_quats: &mut [f32],
    grad_log_scales: &mut [f32],
    grad_raw_densities: &mut [f32],
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
    let l = &g.whitening.whiten;
    let cutoff = grid[GridParam::CUTOFF];
    let mut acc = WhiteningSum::zero();
    let count = g.support.len();
    let mut k = 0u32;
    while k < count {
        let cell = g.support.cell(grid, k, ny, nz);
        let x = &cell.centre;
        let m = l.mul(x).sub(&g.whitening.center);
        let k2 = m.dot(&m);
        if k2 <= cutoff {
            let kernel = (-0.5f32 * k2).exp();
            let base = channels * cell.index;
            if density {
                let up = grad_field[base];
                acc.sigma += up * kernel;
                // d(sigma k)/dm = -sigma k m.
                acc.add_offset_grad(&m.scale(-up * g.sigma * kernel), x);
            }
            if gradient {
                // f = -sigma k m.(L g): see `density::host::splat_field_backward`.
                let up = Vec3::load(grad_field, base + offset);
                let v = l.mul(&up);
                let s = m.dot(&v);
                acc.sigma -= kernel * s;
                let sk = g.sigma * kernel;
                // Direct term: d f / d L = -sigma k m g^T.
                acc.add_outer(&m.scale(-sk), &up);
                acc.add_offset_grad(&m.scale(s).sub(&v).scale(sk), x);
            }
        }
        k += 1;
    }
    grad_raw_densities[i] = acc.sigma * softplus_grad(raw_densities[i]);
    let grads = whiten_vjp(
        &g.context,
        &Mat3::identity(),
        &Whitening {
            whiten: acc.whiten,
            center: acc.center,
        },
    );
    grads.mean.store(grad_means, 3 * i);
    grads.log_scale.store(grad_log_scales, 3 * i);
    grad_quats[4 * i] = grads.rotation.w;
    grad_quats[4 * i + 1] = grads.rotation.x;
    grad_quats[4 * i + 2] = grads.rotation.y;
    grad_quats[4 * i + 3] = grads.rotation.z;
}
