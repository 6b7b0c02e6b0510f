//! Backward of stage 5: one cube per tile replays each pixel back to front from its final
//! transmittance (one unit per pixel) over the forward's own tile list and gathers each
//! splat's gradient ([`SplatGrad`]: `L`, `m`, `sigma`, colour) into `splat_grads`. CPU twin:
//! `cpu::composite::backward_tile`.
//!
//! Every unit of a cube visits the same splat at the same time, so the tile's 256 per-pixel
//! gradients of a splat can be summed inside the cube and added to `splat_grads` with one
//! atomic per float per tile, instead of 256 units contending for the same 16 addresses
//! ([`GradientSums`]).

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use burn_cubecl::cubecl::features::Plane;
use cubecl::prelude::*;

use crate::GradientSums;
use crate::cpu::IMAGE_CHANNELS;
use crate::kernels::atomics::GradientAdd;
use crate::kernels::math::{Mat3, Vec3};
use crate::kernels::rasterize::{TILE_THREADS, stage_batch, tile_pixel};
use crate::kernels::splat::{SPLAT_FLOATS, Splat, ViewParam, pixel_direction, ray_hit};

/// Splats staged in shared memory per batch (half the forward's, to leave room for the sums).
pub const BACKWARD_BATCH: usize = 128;
// One unit stages one splat.
const _: () = assert!(BACKWARD_BATCH <= TILE_THREADS);
/// Units per group of [`GradientSums::SharedMemory`].
const GROUP_UNITS: u32 = 16;
/// The smallest plane [`GradientSums::Planes`] is laid out for.
pub const MIN_PLANE_SIZE: u32 = 8;
/// Partial sums per splat held in shared memory: one per plane or group.
const MAX_GROUPS: usize = TILE_THREADS / MIN_PLANE_SIZE as usize;

/// Bytes of shared memory the kernel declares in form `sums`.
pub fn shared_bytes(sums: GradientSums) -> usize {
    let floats = BACKWARD_BATCH * SPLAT_FLOATS + scratch_len(sums) + partials_len(sums);
    4 * (floats + BACKWARD_BATCH)
}

fn scratch_len(sums: GradientSums) -> usize {
    match sums {
        GradientSums::SharedMemory => TILE_THREADS * SPLAT_FLOATS,
        _ => 1,
    }
}

fn partials_len(sums: GradientSums) -> usize {
    match sums {
        GradientSums::PerPixel => 1,
        _ => 2 * MAX_GROUPS * SPLAT_FLOATS,
    }
}

/// The form `client`'s device runs for `requested`: [`GradientSums::Planes`] needs plane
/// operations with planes of [`MIN_PLANE_SIZE`] to [`TILE_THREADS`] units, and either
/// workgroup form needs its shared memory; otherwise [`GradientSums::PerPixel`].
pub fn resolve(client: &Client, requested: GradientSums) -> GradientSums {
    let properties = client.properties();
    let hardware = &properties.hardware;
    let planes = properties.features.plane.contains(Plane::Ops)
        && hardware.plane_size_min >= MIN_PLANE_SIZE
        && hardware.plane_size_max <= TILE_THREADS as u32;
    let runs = match requested {
        GradientSums::Planes => planes,
        GradientSums::SharedMemory => true,
        GradientSums::PerPixel => false,
    };
    if runs && shared_bytes(requested) <= hardware.max_shared_memory_size {
        requested
    } else {
        GradientSums::PerPixel
    }
}

/// One ray's gradient with respect to one splat, laid out as [`Splat`]: the whitening matrix
/// `L` (rows), the whitened centre `m`, `sigma`, the colour.
#[derive(CubeType, Clone, Copy)]
pub struct SplatGrad {
    pub whiten: Mat3,
    pub center: Vec3,
    pub sigma: f32,
    pub color: Vec3,
}

#[cube]
fn vec3_zero() -> Vec3 {
    Vec3::new(0.0, 0.0, 0.0)
}

#[cube]
fn vec3_plane_sum(v: &Vec3) -> Vec3 {
    Vec3::new(plane_sum(v.x), plane_sum(v.y), plane_sum(v.z))
}

/// Adds `value` to the three floats of `cells` from `start` on.
#[cube]
fn add_vec3<A: GradientAdd>(cells: &mut [Atomic<A::Cell>], start: usize, value: &Vec3) {
    A::add(cells, start, value.x);
    A::add(cells, start + 1, value.y);
    A::add(cells, start + 2, value.z);
}

#[cube]
impl SplatGrad {
    pub fn zero() -> SplatGrad {
        SplatGrad {
            whiten: Mat3 {
                r0: vec3_zero(),
                r1: vec3_zero(),
                r2: vec3_zero(),
            },
            center: vec3_zero(),
            sigma: 0.0,
            color: vec3_zero(),
        }
    }

    /// The sum over this unit's plane.
    pub fn plane_sum(&self) -> SplatGrad {
        SplatGrad {
            whiten: Mat3 {
                r0: vec3_plane_sum(&self.whiten.r0),
                r1: vec3_plane_sum(&self.whiten.r1),
                r2: vec3_plane_sum(&self.whiten.r2),
            },
            center: vec3_plane_sum(&self.center),
            sigma: plane_sum(self.sigma),
            color: vec3_plane_sum(&self.color),
        }
    }

    /// Writes the [`SPLAT_FLOATS`] floats to `buffer` from `start` on.
    pub fn store(&self, buffer: &mut [f32], start: usize) {
        self.whiten.store(buffer, start);
        self.center.store(buffer, start + 9);
        buffer[start + 12] = self.sigma;
        self.color.store(buffer, start + 13);
    }

    /// Adds the floats to splat `index` of `cells`.
    pub fn add_to<A: GradientAdd>(&self, cells: &mut [Atomic<A::Cell>], index: usize) {
        let out = index * SPLAT_FLOATS;
        add_vec3::<A>(cells, out, &self.whiten.r0);
        add_vec3::<A>(cells, out + 3, &self.whiten.r1);
        add_vec3::<A>(cells, out + 6, &self.whiten.r2);
        add_vec3::<A>(cells, out + 9, &self.center);
        A::add(cells, out + 12, self.sigma);
        add_vec3::<A>(cells, out + 13, &self.color);
    }
}

/// Sums every unit's `grad` over the cube and adds the total to splat `gaussian` of
/// `splat_grads` (units `0..SPLAT_FLOATS`, one float each). First each plane or group of
/// units writes its partial sum to `partials`, then those partial sums are added up.
/// `partials` has two slots, used alternately by `parity`: a slot is written again only after
/// the next splat's barrier, which every unit reading it has passed.
#[cube]
#[allow(clippy::too_many_arguments)]
fn add_tile_sum<A: GradientAdd>(
    grad: &SplatGrad,
    contributes: bool,
    gaussian: u32,
    parity: u32,
    scratch: &mut Shared<[f32]>,
    partials: &mut Shared<[f32]>,
    splat_grads: &mut [Atomic<A::Cell>],
    #[comptime] sums: GradientSums,
) {
    let slot = parity * (MAX_GROUPS * SPLAT_FLOATS) as u32;
    let mut groups = CUBE_DIM / GROUP_UNITS;
    if comptime!(sums == GradientSums::Planes) {
        groups = CUBE_DIM / PLANE_DIM;
        let at = slot + (UNIT_POS / PLANE_DIM) * SPLAT_FLOATS as u32;
        // Planes whose rays all miss the splat skip their sums (the branch is uniform per plane).
        if plane_any(contributes) {
            let sum = grad.plane_sum();
            if UNIT_POS_PLANE == 0 {
                sum.store(partials, at as usize);
            }
        } else if UNIT_POS_PLANE == 0 {
            SplatGrad::zero().store(partials, at as usize);
        }
    } else {
        grad.store(scratch, (UNIT_POS * SPLAT_FLOATS as u32) as usize);
        sync_cube();
        // Unit `u` sums float `u % 16` over the 16 units of group `u / 16`; the partial sums
        // land in `partials` in the planes' layout (group-major).
        let group_first = (UNIT_POS / GROUP_UNITS) * GROUP_UNITS;
        let float = UNIT_POS % SPLAT_FLOATS as u32;
        let mut sum = 0.0f32;
        #[unroll]
        for k in 0..GROUP_UNITS {
            sum += scratch[((group_first + k) * SPLAT_FLOATS as u32 + float) as usize];
        }
        partials[(slot + UNIT_POS) as usize] = sum;
    }
    sync_cube();
    if UNIT_POS < SPLAT_FLOATS as u32 {
        let mut total = 0.0f32;
        let mut group = 0u32;
        while group < groups {
            total += partials[(slot + group * SPLAT_FLOATS as u32 + UNIT_POS) as usize];
            group += 1;
        }
        if total != 0.0 {
            A::add(
                splat_grads,
                gaussian as usize * SPLAT_FLOATS + UNIT_POS as usize,
                total,
            );
        }
    }
}

// `create_dummy_kernel`: tests compile the plane variant to WGSL for naga on devices that
// cannot run it.
#[cube(launch, create_dummy_kernel)]
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
    #[comptime] sums: GradientSums,
) {
    let here = tile_pixel(width, height);
    let (tile, px, py, inside) = (here.tile, here.px, here.py, here.inside);
    let d = pixel_direction(view, px, py);

    let mut batch = Shared::<[f32]>::new_slice(BACKWARD_BATCH * SPLAT_FLOATS);
    let mut ids = Shared::<[u32]>::new_slice(BACKWARD_BATCH);
    let mut scratch = Shared::<[f32]>::new_slice(comptime!(scratch_len(sums)));
    let mut partials = Shared::<[f32]>::new_slice(comptime!(partials_len(sums)));

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
    let batch_len = BACKWARD_BATCH as u32;
    let num_batches = (tile_walked + batch_len - 1) / batch_len;
    let alpha_max = view[ViewParam::ALPHA_MAX];

    // Colour composited behind the current splat, background included.
    let mut behind = Vec3::load(background, 0).scale(final_t);
    let mut transmittance_after = final_t;

    let mut bi = 0u32;
    while bi < num_batches {
        let b = num_batches - 1 - bi;
        let first = b * batch_len;
        sync_cube();
        stage_batch(
            splats,
            list,
            start,
            first,
            tile_walked,
            &mut batch,
            &mut ids,
            BACKWARD_BATCH as u32,
        );
        sync_cube();
        let count = (tile_walked - first).min(batch_len);
        let mut jj = 0u32;
        // Uniform across the cube: every unit visits every splat of the batch, contributing
        // or not, so the tile sums see all units.
        while jj < count {
            let j = count - 1 - jj;
            let mut grad = SplatGrad::zero();
            let mut contributes = false;
            if first + j < walked {
                let splat = Splat::load(&batch, j as usize);
                let hit = ray_hit(&splat, &d, view);
                if hit.hit {
                    contributes = true;
                    let one_minus = 1.0 - hit.alpha;
                    let transmittance_before = transmittance_after / one_minus;
                    let weight = transmittance_before * hit.alpha;
                    grad.color.set(&grad_color.scale(weight));
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
                        grad.sigma = grad_alpha * hit.d_alpha_d_sigma;
                        // d lnI/de = -e/a - gamma r, d lnI/dm = r (`math::sample_vjp`); the
                        // splat kernel exp(-K/2) has no -e/a term (length_weight 0).
                        let g_ln = grad_alpha * hit.d_alpha_d_log_kernel;
                        let grad_e = hit
                            .dir_whitened
                            .scale(-hit.length_weight / hit.dir_norm_sq)
                            .sub(&hit.residual.scale(hit.peak_depth))
                            .scale(g_ln);
                        // dLoss/dL = (dLoss/de) d^T, row by row.
                        grad.whiten.r0.set(&d.scale(grad_e.x));
                        grad.whiten.r1.set(&d.scale(grad_e.y));
                        grad.whiten.r2.set(&d.scale(grad_e.z));
                        grad.center.set(&hit.residual.scale(g_ln));
                    }
                }
            }
            if comptime!(sums == GradientSums::PerPixel) {
                if contributes {
                    grad.add_to::<A>(splat_grads, ids[j as usize] as usize);
                }
            } else {
                add_tile_sum::<A>(
                    &grad,
                    contributes,
                    ids[j as usize],
                    jj % 2,
                    &mut scratch,
                    &mut partials,
                    splat_grads,
                    sums,
                );
            }
            jj += 1;
        }
        bi += 1;
    }
}
