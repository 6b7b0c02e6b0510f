//! Stage 5: one cube of 16x16 units per tile composites each pixel front to back (one unit per pixel),
//! staging the tile's splats through shared memory in batches of [`TILE_THREADS`]; the tile
//! stops early once every pixel has reached `transmittance_min`. CPU twin:
//! `cpu::composite::render_tile`.

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use cubecl::prelude::*;

use super::math::Vec3;
use super::project::TILE_EDGE;
use super::splat::{SPLAT_FLOATS, Splat, ViewParam, pixel_direction, ray_hit};
use crate::cpu::IMAGE_CHANNELS;

/// Threads per tile (one per pixel of a 16x16 tile) and splats per shared-memory batch.
pub const TILE_THREADS: usize = 256;

/// The tile of this cube and the pixel of this unit (one unit per pixel of a 16x16 tile).
#[derive(CubeType, Clone, Copy)]
pub struct TilePixel {
    pub tile: usize,
    pub px: u32,
    pub py: u32,
    /// Whether the pixel lies inside the image (edge tiles overhang it).
    pub inside: bool,
}

#[cube]
pub fn tile_pixel(width: u32, height: u32) -> TilePixel {
    let tiles_x = (width + TILE_EDGE - 1) / TILE_EDGE;
    // A one-dimensional cube (naga allows plane built-ins only there), row-major in the tile.
    let px = CUBE_POS_X * TILE_EDGE + UNIT_POS % TILE_EDGE;
    let py = CUBE_POS_Y * TILE_EDGE + UNIT_POS / TILE_EDGE;
    TilePixel {
        tile: (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize,
        px,
        py,
        inside: px < width && py < height,
    }
}

/// Copies list entries `first..first + batch_len` of the tile starting at `start` (those
/// below `len`) into `batch`, one splat per unit, and their indices into `ids`.
#[cube]
#[allow(clippy::too_many_arguments)]
pub fn stage_batch(
    splats: &[f32],
    list: &[u32],
    start: u32,
    first: u32,
    len: u32,
    batch: &mut Shared<[f32]>,
    ids: &mut Shared<[u32]>,
    #[comptime] batch_len: u32,
) {
    let k = first + UNIT_POS;
    if UNIT_POS < batch_len && k < len {
        let gaussian = list[(start + k) as usize];
        ids[UNIT_POS as usize] = gaussian;
        let src = gaussian as usize * SPLAT_FLOATS;
        let dst = UNIT_POS as usize * SPLAT_FLOATS;
        #[unroll]
        for f in 0..SPLAT_FLOATS {
            batch[dst + f] = splats[src + f];
        }
    }
}

/// Output per pixel: RGB over the background and the final transmittance in `image`, and in
/// `walked` the number of list entries walked (what the backward pass replays).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn rasterize_kernel(
    splats: &[f32],
    offsets: &[u32],
    list: &[u32],
    view: &[f32],
    background: &[f32],
    image: &mut [f32],
    walked_counts: &mut [u32],
    width: u32,
    height: u32,
) {
    let here = tile_pixel(width, height);
    let (tile, px, py, inside) = (here.tile, here.px, here.py, here.inside);
    let d = pixel_direction(view, px, py);

    let mut batch = Shared::<[f32]>::new_slice(TILE_THREADS * SPLAT_FLOATS);
    let mut ids = Shared::<[u32]>::new_slice(TILE_THREADS);
    let finished = Shared::<[Atomic<u32>]>::new_slice(1usize);
    if UNIT_POS == 0 {
        finished[0].store(0u32);
    }
    sync_cube();
    let mut done = !inside;
    if done {
        finished[0].fetch_add(1u32);
    }

    let start = offsets[tile];
    let len = offsets[tile + 1] - start;
    let num_batches = (len + TILE_THREADS as u32 - 1) / TILE_THREADS as u32;
    let transmittance_min = view[ViewParam::TRANSMITTANCE_MIN];

    let mut transmittance = 1.0f32;
    let mut color = Vec3::new(0.0, 0.0, 0.0);
    let mut walked = 0u32;

    let mut b = 0u32;
    while b < num_batches {
        sync_cube();
        // Uniform across the cube: nobody finishes between the barrier above and the one below.
        let finished_now = workgroup_uniform_load_atomic(&finished[0]);
        if finished_now >= CUBE_DIM {
            break;
        }
        let first = b * TILE_THREADS as u32;
        stage_batch(
            splats,
            list,
            start,
            first,
            len,
            &mut batch,
            &mut ids,
            TILE_THREADS as u32,
        );
        sync_cube();
        if !done {
            let count = (len - first).min(TILE_THREADS as u32);
            let mut j = 0u32;
            while j < count {
                let splat = Splat::load(&batch, j as usize);
                let hit = ray_hit(&splat, &d, view);
                if hit.hit {
                    let next = transmittance * (1.0 - hit.alpha);
                    if next < transmittance_min {
                        done = true;
                        finished[0].fetch_add(1u32);
                        break;
                    }
                    color.add_assign(&splat.color.scale(transmittance * hit.alpha));
                    transmittance = next;
                    walked = first + j + 1;
                }
                j += 1;
            }
        }
        b += 1;
    }

    if inside {
        let pixel = (py * width + px) as usize;
        let out = pixel * IMAGE_CHANNELS;
        image[out] = color.x + transmittance * background[0];
        image[out + 1] = color.y + transmittance * background[1];
        image[out + 2] = color.z + transmittance * background[2];
        image[out + 3] = transmittance;
        walked_counts[pixel] = walked;
    }
}
