//! Backward of stage 5: one cube per tile replays each pixel back to front from its final
//! transmittance (one unit per pixel) over the forward's own tile list, adding each splat's
//! gradient (`L`, `m`, `sigma`, colour; [`SPLAT_FLOATS`] floats per Gaussian) into
//! `splat_grads` atomically. CPU twin: `cpu::composite::backward_tile`.

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use cubecl::prelude::*;

use crate::cpu::IMAGE_CHANNELS;
use crate::kernels::atomics::GradientAdd;
use crate::kernels::math::Vec3;
use crate::kernels::rasterize::{TILE_THREADS, stage_batch, tile_pixel};
use crate::kernels::splat::{SPLAT_FLOATS, Splat, ViewParam, pixel_direction, ray_hit};

/// Adds `value` to the three floats of `cells` from `start` on.
#[cube]
fn add_vec3<A: GradientAdd>(cells: &mut [Atomic<A::Cell>], start: usize, value: &Vec3) {
    A::add(cells, start, value.x);
    A::add(cells, start + 1, value.y);
    A::add(cells, start + 2, value.z);
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward_kernel<A: GradientAdd>(
    splats: &[f32],
    offsets: &[u32],
    list: &[u32],
    view: &[f32],
    background: &[f32],
    image: &[f32],
    walked_counts: &[u32],
    grad_image: &[f32],
    splat_grads: &mut [Atomic<A::Cell>],
    width: u32,
    height: u32,
) {
    let here = tile_pixel(width, height);
    let (tile, px, py, inside) = (here.tile, here.px, here.py, here.inside);
    let d = pixel_direction(view, px, py);

    let mut batch = Shared::<[f32]>::new_slice(TILE_THREADS * SPLAT_FLOATS);
    let mut ids = Shared::<[u32]>::new_slice(TILE_THREADS);

    let mut walked = 0u32;
    let mut final_t = 1.0f32;
    let mut grad_color = Vec3::new(0.0, 0.0, 0.0);
    let mut grad_final_t = 0.0f32;
    if inside {
        let pixel = (py * width + px) as usize;
        let base = pixel * IMAGE_CHANNELS;
        final_t = image[base + 3];
        walked = walked_counts[pixel];
        grad_color.x = grad_image[base];
        grad_color.y = grad_image[base + 1];
        grad_color.z = grad_image[base + 2];
        grad_final_t = grad_image[base + 3];
    }

    // Every pixel walked at most the whole list; entries past a pixel's own count are skipped.
    let start = offsets[tile];
    let tile_walked = offsets[tile + 1] - start;
    let num_batches = (tile_walked + TILE_THREADS as u32 - 1) / TILE_THREADS as u32;
    let alpha_max = view[ViewParam::ALPHA_MAX];

    // Colour composited behind the current splat, background included.
    let mut behind = Vec3::load(background, 0).scale(final_t);
    let mut transmittance_after = final_t;

    let mut bi = 0u32;
    while bi < num_batches {
        let b = num_batches - 1 - bi;
        let first = b * TILE_THREADS as u32;
        sync_cube();
        stage_batch(
            splats,
            list,
            start,
            first,
            tile_walked,
            &mut batch,
            &mut ids,
        );
        sync_cube();
        let count = (tile_walked - first).min(TILE_THREADS as u32);
        let mut jj = 0u32;
        while jj < count {
            let j = count - 1 - jj;
            if first + j < walked {
                let splat = Splat::load(&batch, j as usize);
                let hit = ray_hit(&splat, &d, view);
                if hit.hit {
                    let one_minus = 1.0 - hit.alpha;
                    let transmittance_before = transmittance_after / one_minus;
                    let out = ids[j as usize] as usize * SPLAT_FLOATS;
                    let weight = transmittance_before * hit.alpha;
                    add_vec3::<A>(splat_grads, out + 13, &grad_color.scale(weight));
                    let grad_alpha = -grad_final_t * final_t / one_minus
                        + grad_color.x
                            * (transmittance_before * splat.color.x - behind.x / one_minus)
                        + grad_color.y
                            * (transmittance_before * splat.color.y - behind.y / one_minus)
                        + grad_color.z
                            * (transmittance_before * splat.color.z - behind.z / one_minus);
                    behind.add_assign(&splat.color.scale(weight));
                    transmittance_after = transmittance_before;
                    if hit.raw_alpha < alpha_max {
                        A::add(splat_grads, out + 12, grad_alpha * hit.d_alpha_d_sigma);
                        // d lnI/de = -e/a - gamma r, d lnI/dm = r (`math::sample_vjp`); the
                        // splat kernel exp(-K/2) has no -e/a term (length_weight 0).
                        let g_ln = grad_alpha * hit.d_alpha_d_log_kernel;
                        let grad_e = hit
                            .dir_whitened
                            .scale(-hit.length_weight / hit.dir_norm_sq)
                            .sub(&hit.residual.scale(hit.peak_depth))
                            .scale(g_ln);
                        // dLoss/dL = (dLoss/de) d^T, row by row.
                        add_vec3::<A>(splat_grads, out, &d.scale(grad_e.x));
                        add_vec3::<A>(splat_grads, out + 3, &d.scale(grad_e.y));
                        add_vec3::<A>(splat_grads, out + 6, &d.scale(grad_e.z));
                        add_vec3::<A>(splat_grads, out + 9, &hit.residual.scale(g_ln));
                    }
                }
            }
            jj += 1;
        }
        bi += 1;
    }
}
