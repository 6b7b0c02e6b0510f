//! Stage 3: every visible Gaussian writes its index into the list of each tile it touches
//! (in arbitrary order within a tile; [`super::tile_sort`] makes it deterministic). A tile
//! whose range was clamped to the buffer's capacity ([`super::tile_offsets`]) keeps only what
//! fits, so an undersized buffer is never written past its end.

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use cubecl::prelude::*;

use super::project::{TILE_EDGE, TileRect};

#[cube(launch)]
pub fn fill_tiles_kernel(
    rects: &[u32],
    offsets: &[u32],
    cursors: &mut [Atomic<u32>],
    list: &mut [u32],
    num_gaussians: u32,
    width: u32,
) {
    let i = ABSOLUTE_POS;
    if i >= num_gaussians as usize {
        terminate!();
    }
    let tiles_x = (width + TILE_EDGE - 1) / TILE_EDGE;
    let rect = TileRect::load(rects, i);
    let mut ty = rect.y0;
    while ty < rect.y1 {
        let mut tx = rect.x0;
        while tx < rect.x1 {
            let tile = (ty * tiles_x + tx) as usize;
            let entry = offsets[tile] + cursors[tile].fetch_add(1u32);
            if entry < offsets[tile + 1] {
                list[entry as usize] = i as u32;
            }
            tx += 1;
        }
        ty += 1;
    }
}
