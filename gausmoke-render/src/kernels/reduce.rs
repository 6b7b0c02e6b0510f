//! Fixed-order reductions inside one cube (a tree over shared memory), so a sum does not
//! depend on thread scheduling as an atomic one would.

use cubecl::prelude::*;

/// Sums `values[0..CUBE_DIM)` into `values[0]`, pairwise (`CUBE_DIM` a power of two). Every
/// unit of the cube must call it.
#[cube]
pub fn tree_sum(values: &mut Shared<[f32]>) {
    sync_cube();
    // A runtime stride: a compile-time one trips cubecl's IR verifier.
    let mut stride = CUBE_DIM / 2;
    while stride > 0 {
        if UNIT_POS < stride {
            let other = values[(UNIT_POS + stride) as usize];
            values[UNIT_POS as usize] += other;
        }
        sync_cube();
        stride /= 2;
    }
}
