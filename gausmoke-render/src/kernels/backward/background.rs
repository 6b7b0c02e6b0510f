//! Backward of the background: `sum over pixels of dLoss/dC * T_final`, in one cube with a
//! fixed-order reduction, so the result does not depend on scheduling.

use cubecl::prelude::*;

use crate::cpu::IMAGE_CHANNELS;
use crate::kernels::rasterize::TILE_THREADS;
use crate::kernels::reduce::tree_sum;

#[cube(launch)]
pub fn background_grad_kernel(
    image: &[f32],
    grad_image: &[f32],
    grad_background: &mut [f32],
    num_pixels: u32,
) {
    let mut partial = Shared::<[f32]>::new_slice(TILE_THREADS);
    #[unroll]
    for channel in 0..3usize {
        let mut sum = 0.0f32;
        let mut p = UNIT_POS;
        while p < num_pixels {
            let base = p as usize * IMAGE_CHANNELS;
            sum += grad_image[base + channel] * image[base + 3];
            p += CUBE_DIM;
        }
        partial[UNIT_POS as usize] = sum;
        tree_sum(&mut partial);
        if UNIT_POS == 0 {
            grad_background[channel] = partial[0];
        }
        sync_cube();
    }
}
