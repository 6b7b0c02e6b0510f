//! Stage 2: the exclusive prefix sum of the per-tile counts into list offsets.

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use cubecl::prelude::*;

/// `offsets[t]` = sum of `counts[..t]` for `t` in `0..=num_tiles`, each at most `capacity`
/// (the length of the list buffer), and `offsets[num_tiles + 1]` the unclamped total: a list
/// buffer sized without reading the total back is never written or read past its end, and
/// the total says afterwards whether it was long enough. In one cube: each unit owns a
/// contiguous chunk of tiles and first sums every count before its chunk itself. That is
/// O(tiles) reads per unit, but the tile grid is small (thousands) and the kernel needs no
/// shared memory or barriers.
#[cube(launch)]
pub fn tile_offsets_kernel(counts: &[u32], offsets: &mut [u32], num_tiles: u32, capacity: u32) {
    let units = CUBE_DIM;
    let chunk = (num_tiles + units - 1) / units;
    let begin = (UNIT_POS * chunk).min(num_tiles);
    let end = (begin + chunk).min(num_tiles);
    let mut running = 0u32;
    let mut before = 0u32;
    while before < begin {
        running += counts[before as usize];
        before += 1;
    }
    let mut tile = begin;
    while tile < end {
        offsets[tile as usize] = running.min(capacity);
        running += counts[tile as usize];
        tile += 1;
    }
    if UNIT_POS == units - 1 {
        offsets[num_tiles as usize] = running.min(capacity);
        offsets[num_tiles as usize + 1] = running;
    }
}

/// The unclamped total of [`tile_offsets_kernel`] as one float (exact below 2^24 entries).
#[cube(launch)]
pub fn list_length_kernel(offsets: &[u32], length: &mut [f32], num_tiles: u32) {
    if ABSOLUTE_POS == 0 {
        length[0] = f32::cast_from(offsets[num_tiles as usize + 1]);
    }
}
