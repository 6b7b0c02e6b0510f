//! The conjugate-gradient steps of the projection's solve as kernels: fixed-order dot
//! products (per-cube trees, then one cube over the partial sums, the per-cube part fused
//! into the kernels that produce the vectors where it can be) and the per-cell updates.
//! Every CG scalar lives in the device buffer `scalars` (see `Slot`).

use cubecl::prelude::*;
use gausmoke_render::kernels::reduce::tree_sum;

use super::operators::{component_is_free, divergence_at, inverse_diagonal};

/// Units per cube of every kernel here (one unit per cell).
pub const CELL_BLOCK: usize = 256;

/// Per-cube sums of `a * b` over `len` entries into `partials[CUBE_POS]`.
#[cube(launch)]
pub fn dot_partials_kernel(a: &[f32], b: &[f32], partials: &mut [f32], len: u32) {
    let mut sums = Shared::<[f32]>::new_slice(CELL_BLOCK);
    let index = ABSOLUTE_POS as u32;
    let mut product = 0.0f32;
    if index < len {
        product = a[index as usize] * b[index as usize];
    }
    sums[UNIT_POS as usize] = product;
    tree_sum(&mut sums);
    if UNIT_POS == 0 {
        partials[CUBE_POS] = sums[0];
    }
}

/// Sums `count` partial sums in a fixed order (one cube per sum) into `scalars`: cube 0 sums
/// `partials[0..count]` into `scalars[first_slot]`, cube 1 (when launched) sums
/// `partials[count..2 count]` into `scalars[second_slot]`.
#[cube(launch)]
pub fn finish_sums_kernel(
    partials: &[f32],
    scalars: &mut [f32],
    count: u32,
    first_slot: u32,
    second_slot: u32,
) {
    let mut sums = Shared::<[f32]>::new_slice(CELL_BLOCK);
    let offset = CUBE_POS as u32 * count;
    let mut total = 0.0f32;
    let mut index = UNIT_POS;
    while index < count {
        total += partials[(offset + index) as usize];
        index += CUBE_DIM;
    }
    sums[UNIT_POS as usize] = total;
    tree_sum(&mut sums);
    if UNIT_POS == 0 {
        let mut slot = first_slot;
        if CUBE_POS == 1 {
            slot = second_slot;
        }
        scalars[slot as usize] = sums[0];
    }
}

/// Writes this cube's sum of `value` over its units to `partials[offset + CUBE_POS]` (as
/// [`dot_partials_kernel`] does, so fused and separate dot products agree bit for bit).
#[cube]
fn cube_partial(value: f32, partials: &mut [f32], offset: u32) {
    let mut sums = Shared::<[f32]>::new_slice(CELL_BLOCK);
    sums[UNIT_POS as usize] = value;
    tree_sum(&mut sums);
    if UNIT_POS == 0 {
        partials[(offset + CUBE_POS as u32) as usize] = sums[0];
    }
}

/// Whether a residual `|r|^2` meets the stopping rule: under `tolerance^2 |b|^2` (the
/// requested relative residual) or `floor^2 |u|^2` (what f32 can resolve; see
/// `F32_RESOLVABLE`). The host's `StoppingRule::met` applies the same rule in the same arithmetic.
#[cube]
fn has_converged(
    residual_squared: f32,
    scalars: &[f32],
    tolerance_squared: f32,
    floor_squared: f32,
) -> bool {
    let relative = tolerance_squared * scalars[0];
    let absolute = floor_squared * scalars[1];
    residual_squared <= relative.max(absolute)
}

/// CG's `A d = D (D^T d)`, and this cube's partial sum of the curvature `d . A d` in
/// `partials[CUBE_POS]` (for [`finish_sums_kernel`]). Skipped once the solve has converged
/// (`|r_k|^2` at `residual_slot`, see [`has_converged`]): no step uses it then.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn operator_direction_kernel(
    direction: &[f32],
    operator_direction: &mut [f32],
    partials: &mut [f32],
    scalars: &[f32],
    residual_slot: u32,
    tolerance_squared: f32,
    floor_squared: f32,
    inverse_cell: &[f32],
    face_flow: &[f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    let mut curvature = 0.0f32;
    let converged = has_converged(
        scalars[residual_slot as usize],
        scalars,
        tolerance_squared,
        floor_squared,
    );
    // Cells past the grid only pad the cube's sum (every unit reaches its barriers, so the
    // converged case skips the work, not the sum).
    if cell < nx * ny * nz && !converged {
        let value = divergence_at(
            cell,
            direction,
            inverse_cell,
            face_flow,
            fluid,
            has_solids,
            nx,
            ny,
            nz,
            true,
        );
        operator_direction[cell as usize] = value;
        curvature = direction[cell as usize] * value;
    }
    cube_partial(curvature, partials, 0u32);
}

/// Step of iteration `k`: `a = (r.z) / (d.A d)` read from the scalar buffer, then
/// `p += a d`, `r -= a A d`, `z = M^-1 r`, and this cube's partial sums of `|r|^2` (to
/// `partials[CUBE_POS]`) and `r.z` (to `partials[cubes + CUBE_POS]`) for
/// [`finish_sums_kernel`].
///
/// No step is taken once the solve has converged (`|r_k|^2` at `residual_slot` under
/// `tolerance^2 |b|^2` or `floor^2 |u|^2`, see [`has_converged`]): the iterations the host launches
/// before its next convergence test are then no-ops, and the result is the first converged
/// iterate. Nor when the curvature is not positive and finite (the direction lies in the
/// operator's null space).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn step_kernel(
    pressure: &mut [f32],
    residual: &mut [f32],
    preconditioned: &mut [f32],
    direction: &[f32],
    operator_direction: &[f32],
    scalars: &[f32],
    inverse_cell: &[f32],
    partials: &mut [f32],
    residual_slot: u32,
    rz_slot: u32,
    curvature_slot: u32,
    tolerance_squared: f32,
    floor_squared: f32,
    face_flow: &[f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    let mut r = 0.0f32;
    let mut z = 0.0f32;
    // Cells past the grid only pad the cube's sums (every unit reaches their barriers).
    if cell < nx * ny * nz {
        let converged = has_converged(
            scalars[residual_slot as usize],
            scalars,
            tolerance_squared,
            floor_squared,
        );
        let curvature = scalars[curvature_slot as usize];
        let mut step = 0.0f32;
        if !converged && curvature > 0.0 && curvature < f32::MAX {
            step = scalars[rz_slot as usize] / curvature;
        }
        let c = cell as usize;
        pressure[c] += step * direction[c];
        r = residual[c] - step * operator_direction[c];
        residual[c] = r;
        z = r * inverse_diagonal(cell, inverse_cell, face_flow, fluid, has_solids, nx, ny, nz);
        preconditioned[c] = z;
    }
    cube_partial(r * r, partials, 0u32);
    cube_partial(r * z, partials, CUBE_COUNT as u32);
}

/// New direction of iteration `k`: `d = z + b d`, `b = (r.z)_{k+1} / (r.z)_k` (zero when the
/// old product is zero). Skipped once the solve has converged (as the step was).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn direction_kernel(
    preconditioned: &[f32],
    direction: &mut [f32],
    scalars: &[f32],
    rz_slot: u32,
    next_rz_slot: u32,
    residual_slot: u32,
    tolerance_squared: f32,
    floor_squared: f32,
    cells: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    if cell >= cells
        || has_converged(
            scalars[residual_slot as usize],
            scalars,
            tolerance_squared,
            floor_squared,
        )
    {
        terminate!();
    }
    let previous = scalars[rz_slot as usize];
    let mut beta = 0.0f32;
    if previous != 0.0 {
        beta = scalars[next_rz_slot as usize] / previous;
    }
    let c = cell as usize;
    direction[c] = preconditioned[c] + beta * direction[c];
}

/// `M u - D^T p`, the projected velocity (`M` zeroes the obstacle cells and the pinned
/// components).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn subtract_kernel(
    velocity: &[f32],
    gradient: &[f32],
    output: &mut [f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let index = ABSOLUTE_POS as u32;
    if index >= 3 * nx * ny * nz {
        terminate!();
    }
    let mut value = 0.0f32;
    if component_is_free(index / 3, index % 3, fluid, has_solids, nx, ny, nz) {
        value = velocity[index as usize] - gradient[index as usize];
    }
    output[index as usize] = value;
}
