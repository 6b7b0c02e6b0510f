//! Stage 4: each tile's list sorted by (centre depth, index), so every backend composites in
//! the same order as the CPU path.

use cubecl::prelude::*;

/// Whether list entry `a` must come after entry `b`: by centre depth, then index.
#[cube]
fn after(depths: &[f32], a: u32, b: u32) -> bool {
    let da = depths[a as usize];
    let db = depths[b as usize];
    da > db || (da == db && a > b)
}

/// One comparator of the sorting network: puts list entries `a < b` of the tile starting at
/// `start` in order. `b` past the list's end is virtual +infinity padding, already in place.
#[cube]
fn order_pair(depths: &[f32], list: &mut [u32], start: u32, a: u32, b: u32, len: u32) {
    if b < len {
        let ia = list[(start + a) as usize];
        let ib = list[(start + b) as usize];
        if after(depths, ia, ib) {
            list[(start + a) as usize] = ib;
            list[(start + b) as usize] = ia;
        }
    }
}

/// Sorts each tile's list in place, one cube per tile, with a bitonic network in its "flip"
/// form: every sub-block is sorted ascending, so the list can be padded virtually to a power
/// of two with +infinity and comparisons against the padding skipped.
#[cube(launch)]
pub fn sort_tiles_kernel(depths: &[f32], offsets: &[u32], list: &mut [u32]) {
    let tile = CUBE_POS;
    let start = offsets[tile];
    let len = offsets[tile + 1] - start;
    let mut padded = 1u32;
    while padded < len {
        padded *= 2;
    }
    let pairs = padded / 2;
    let mut size = 2u32;
    while size <= padded {
        // Flip: compare i with its mirror in the block of `size`.
        let half = size / 2;
        let mut p = UNIT_POS;
        while p < pairs {
            let block = p / half;
            let pos = p % half;
            let a = block * size + pos;
            let b = block * size + size - 1 - pos;
            order_pair(depths, list, start, a, b, len);
            p += CUBE_DIM;
        }
        sync_storage();
        // Half-cleaners.
        let mut stride = half / 2;
        while stride > 0 {
            let mut p = UNIT_POS;
            while p < pairs {
                let a = (p / stride) * 2 * stride + p % stride;
                order_pair(depths, list, start, a, a + stride, len);
                p += CUBE_DIM;
            }
            sync_storage();
            stride /= 2;
        }
        size *= 2;
    }
}
