//! Input validation on the device: finiteness of every input, the smallest quaternion norm and
//! the largest `|log_scale|`, in one kernel and one 8-float result (see
//! `VolumeRenderBackend::volume_render_input_stats`).

use burn::backend::ops::FloatTensorOps;
use burn::tensor::DType;
use burn_cubecl::CubeBackend;
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;

use super::buffers::{Allocator, buffer, contiguous_f32};
use crate::gaussians::Gaussians;

/// Units of the one cube that computes the statistics.
const STATS_THREADS: usize = 256;

/// Whether `x` is NaN or infinite, from its exponent bits (immune to fast-math folding).
#[cube]
fn non_finite(x: f32) -> bool {
    (x.to_bits() & 0x7f80_0000u32) == 0x7f80_0000u32
}

/// Statistics for input validation (see `VolumeRenderBackend::volume_render_input_stats`), in
/// one cube: each unit scans a stride of every input, then shared-memory tree reductions.
/// `inputs` is the concatenation background, means, rotations, log-scales, raw densities,
/// colours, with `ends[k]` the end of part `k`.
#[cube(launch)]
pub fn input_stats_kernel(inputs: &[f32], ends: &[u32], stats: &mut [f32]) {
    let unit = UNIT_POS as usize;
    let mut bad_parts = Shared::<[u32]>::new_slice(STATS_THREADS);
    let mut min_norm = Shared::<[f32]>::new_slice(STATS_THREADS);
    let mut max_scale = Shared::<[f32]>::new_slice(STATS_THREADS);
    let mut flags = 0u32;
    let mut part = 0u32;
    let mut begin = 0u32;
    while part < 6 {
        let end = ends[part as usize];
        let mut k = begin + UNIT_POS;
        while k < end {
            if non_finite(inputs[k as usize]) {
                flags |= 1u32 << part;
            }
            k += CUBE_DIM;
        }
        begin = end;
        part += 1;
    }
    // Quaternions: part 2; log-scales: part 3.
    let quat_begin = ends[1];
    let num_quats = (ends[2] - quat_begin) / 4;
    let mut smallest = 1.0f32;
    let mut first = true;
    let mut q = UNIT_POS;
    while q < num_quats {
        let base = (quat_begin + 4 * q) as usize;
        let norm = inputs[base] * inputs[base]
            + inputs[base + 1] * inputs[base + 1]
            + inputs[base + 2] * inputs[base + 2]
            + inputs[base + 3] * inputs[base + 3];
        if first || norm < smallest {
            smallest = norm;
        }
        first = false;
        q += CUBE_DIM;
    }
    let mut largest = 0.0f32;
    let mut s = ends[2] + UNIT_POS;
    while s < ends[3] {
        largest = largest.max(inputs[s as usize].abs());
        s += CUBE_DIM;
    }
    bad_parts[unit] = flags;
    min_norm[unit] = smallest;
    max_scale[unit] = largest;
    sync_cube();
    let mut stride = CUBE_DIM / 2;
    while stride > 0 {
        if UNIT_POS < stride {
            let other = (UNIT_POS + stride) as usize;
            let merged_flags = bad_parts[unit] | bad_parts[other];
            let merged_min = min_norm[unit].min(min_norm[other]);
            let merged_max = max_scale[unit].max(max_scale[other]);
            bad_parts[unit] = merged_flags;
            min_norm[unit] = merged_min;
            max_scale[unit] = merged_max;
        }
        sync_cube();
        stride /= 2;
    }
    if UNIT_POS == 0 {
        let all = bad_parts[0];
        let mut p = 0u32;
        while p < 6 {
            let mut ok = 1.0f32;
            if (all >> p) & 1u32 == 1u32 {
                ok = 0.0;
            }
            stats[p as usize] = ok;
            p += 1;
        }
        stats[6] = min_norm[0];
        stats[7] = max_scale[0];
    }
}

/// The statistics of `gaussians` and `background`: `[8]` on the device.
pub fn input_stats(gaussians: Gaussians<CubeTensor>, background: CubeTensor) -> CubeTensor {
    let parts = [background]
        .into_iter()
        .chain(gaussians.into_array())
        .map(|t| contiguous_f32(t, "render input"));
    let mut ends = Vec::with_capacity(6);
    let mut total = 0usize;
    let flat: Vec<CubeTensor> = parts
        .map(|t| {
            let len = t.meta.num_elements();
            total += len;
            ends.push(total as u32);
            burn_cubecl::ops::reshape(t, [len].into())
        })
        .collect();
    assert!(
        total < u32::MAX as usize,
        "render inputs too large to validate"
    );
    let inputs = CubeBackend::float_cat(flat, 0);
    let alloc = Allocator::like(&inputs);
    let ends = alloc.client.create_from_slice(u32::as_bytes(&ends));
    let stats = alloc.empty(8, DType::F32);
    input_stats_kernel::launch(
        &alloc.client,
        CubeCount::Static(1, 1, 1),
        CubeDim::new_1d(STATS_THREADS as u32),
        buffer(&inputs),
        // SAFETY: the handle holds exactly the 6 offsets written above.
        unsafe { BufferArg::from_raw_parts(ends, 6) },
        buffer(&stats),
    );
    stats
}
