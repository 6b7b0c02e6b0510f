//! The grid operators of the projection as kernels, one unit per cell: the divergence `D`,
//! its transpose, and the Jacobi preconditioner (as `projection::host::Divergence`).
//!
//! Obstacles: with `has_solids` set, `fluid` holds one flag per cell (1 fluid, 0 solid); a
//! solid cell has no row in `D` and no velocity, a face between a fluid cell and a solid one
//! is a wall, and a fluid cell's component along an axis on which it touches an obstacle is
//! pinned to zero (`Divergence::component_is_free`). Without, `fluid` is a placeholder that
//! is never read.

use cubecl::prelude::*;

/// Coordinate of flat cell `cell` along `axis` (x slowest, as [`crate::grid`]).
#[cube]
fn axis_coordinate(cell: u32, axis: u32, ny: u32, nz: u32) -> u32 {
    let mut coordinate = cell % nz;
    if axis == 0 {
        coordinate = cell / (ny * nz);
    } else if axis == 1 {
        coordinate = (cell / nz) % ny;
    }
    coordinate
}

/// Flat-index step to the next cell along `axis`.
#[cube]
fn axis_stride(axis: u32, ny: u32, nz: u32) -> u32 {
    let mut stride = 1u32;
    if axis == 0 {
        stride = ny * nz;
    } else if axis == 1 {
        stride = nz;
    }
    stride
}

/// Number of cells along `axis`.
#[cube]
fn axis_cells(axis: u32, nx: u32, ny: u32, nz: u32) -> u32 {
    let mut cells = nz;
    if axis == 0 {
        cells = nx;
    } else if axis == 1 {
        cells = ny;
    }
    cells
}

/// The face velocity on the box face of `axis` (side 0 the low face, 1 the high) as a
/// fraction of the cell inside it: `face_flow[2 axis + side]`, as `OpenFaces::face_flows`
/// (0 on a solid face).
#[cube]
fn box_face_flow(face_flow: &[f32], axis: u32, side: u32) -> f32 {
    face_flow[(2 * axis + side) as usize]
}

/// Whether `cell` holds fluid (see the module's notes on obstacles).
#[cube]
pub fn is_fluid(cell: u32, fluid: &[f32], has_solids: u32) -> bool {
    let mut result = true;
    if has_solids != 0 {
        result = fluid[cell as usize] > 0.5;
    }
    result
}

/// Whether component `axis` of `cell` is free: a fluid cell with no obstacle cell next to it
/// along `axis` (as `Divergence::component_is_free`).
#[cube]
#[allow(clippy::too_many_arguments)]
pub fn component_is_free(
    cell: u32,
    axis: u32,
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
) -> bool {
    let mut free = true;
    if has_solids != 0 {
        let i = axis_coordinate(cell, axis, ny, nz);
        let n = axis_cells(axis, nx, ny, nz);
        let stride = axis_stride(axis, ny, nz);
        free = is_fluid(cell, fluid, has_solids);
        if i + 1 < n {
            free = free && is_fluid(cell + stride, fluid, has_solids);
        }
        if i > 0 {
            free = free && is_fluid(cell - stride, fluid, has_solids);
        }
    }
    free
}

/// The neighbours of `cell` along `axis` (`i` its coordinate there, `n` the cells, `stride`
/// the flat step) that exist and hold fluid, high side first: the faces between them and
/// `cell` are interior.
#[cube]
#[allow(clippy::too_many_arguments)]
fn fluid_neighbours(
    cell: u32,
    i: u32,
    n: u32,
    stride: u32,
    fluid: &[f32],
    has_solids: u32,
) -> (bool, bool) {
    let mut high = false;
    if i + 1 < n {
        high = is_fluid(cell + stride, fluid, has_solids);
    }
    let mut low = false;
    if i > 0 {
        low = is_fluid(cell - stride, fluid, has_solids);
    }
    (high, low)
}

/// Jacobi preconditioner `1 / (D D^T)_cc` of one cell (as `Divergence::normal_diagonal`).
#[cube]
#[allow(clippy::too_many_arguments)]
pub fn inverse_diagonal(
    cell: u32,
    inverse_cell: &[f32],
    face_flow: &[f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
) -> f32 {
    let mut diagonal = 0.0f32;
    if is_fluid(cell, fluid, has_solids) {
        let mut axis = 0u32;
        while axis < 3 {
            let i = axis_coordinate(cell, axis, ny, nz);
            let n = axis_cells(axis, nx, ny, nz);
            let stride = axis_stride(axis, ny, nz);
            let (high, low) = fluid_neighbours(cell, i, n, stride, fluid, has_solids);
            let mut interior = 0.0f32;
            let mut own = 0.0f32;
            if high {
                own += 0.5;
                if component_is_free(cell + stride, axis, fluid, has_solids, nx, ny, nz) {
                    interior += 1.0;
                }
            } else if i + 1 >= n {
                own += box_face_flow(face_flow, axis, 1);
            }
            if low {
                own -= 0.5;
                if component_is_free(cell - stride, axis, fluid, has_solids, nx, ny, nz) {
                    interior += 1.0;
                }
            } else if i == 0 {
                own -= box_face_flow(face_flow, axis, 0);
            }
            if !component_is_free(cell, axis, fluid, has_solids, nx, ny, nz) {
                own = 0.0;
            }
            let h_inv = inverse_cell[axis as usize];
            diagonal += (0.25 * interior + own * own) * h_inv * h_inv;
            axis += 1;
        }
    } else {
        // No row: the residual stays 0 there, any scale will do.
        diagonal = 1.0;
    }
    1.0 / diagonal.max(1e-30)
}

/// The net outflow along one axis of a cell whose velocity component is `own`, with `high` and
/// `low` its neighbours' (read only where `high_fluid` / `low_fluid`): face velocity = mean of
/// its two cells, zero on solid walls and obstacle faces, the inner cell's times the face's
/// flow on open faces.
#[cube]
#[allow(clippy::too_many_arguments)]
fn axis_flux(
    own: f32,
    high: f32,
    low: f32,
    high_fluid: bool,
    low_fluid: bool,
    i: u32,
    n: u32,
    face_flow: &[f32],
    axis: u32,
) -> f32 {
    let mut flux = 0.0f32;
    if high_fluid {
        flux += 0.5 * (own + high);
    } else if i + 1 >= n {
        flux += box_face_flow(face_flow, axis, 1) * own;
    }
    if low_fluid {
        flux -= 0.5 * (own + low);
    } else if i == 0 {
        flux -= box_face_flow(face_flow, axis, 0) * own;
    }
    flux
}

/// Component `axis` of the velocity at `cell` that [`divergence_at`] takes: read from `source`
/// (`[cells, 3]`), or with `of_gradient` computed from the pressure `source` as `(D^T p)`, the
/// value `divergence_transpose_kernel` would have stored there.
#[cube]
#[allow(clippy::too_many_arguments)]
fn velocity_component(
    cell: u32,
    axis: u32,
    source: &[f32],
    inverse_cell: &[f32],
    face_flow: &[f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
    #[comptime] of_gradient: bool,
) -> f32 {
    if comptime!(of_gradient) {
        gradient_component(
            cell,
            axis,
            source,
            inverse_cell,
            face_flow,
            fluid,
            has_solids,
            nx,
            ny,
            nz,
        )
    } else {
        let mut value = 0.0f32;
        if component_is_free(cell, axis, fluid, has_solids, nx, ny, nz) {
            value = source[(3 * cell + axis) as usize];
        }
        value
    }
}

/// `(D u)_c`, summed over the axes of the flux over the cell size; with `of_gradient`,
/// `(D (D^T p))_c` from the pressure `source` without storing `D^T p` (see
/// [`velocity_component`]).
#[cube]
#[allow(clippy::too_many_arguments)]
pub fn divergence_at(
    cell: u32,
    source: &[f32],
    inverse_cell: &[f32],
    face_flow: &[f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
    #[comptime] of_gradient: bool,
) -> f32 {
    let mut total = 0.0f32;
    if is_fluid(cell, fluid, has_solids) {
        let mut axis = 0u32;
        while axis < 3 {
            let i = axis_coordinate(cell, axis, ny, nz);
            let n = axis_cells(axis, nx, ny, nz);
            let stride = axis_stride(axis, ny, nz);
            let (high_fluid, low_fluid) = fluid_neighbours(cell, i, n, stride, fluid, has_solids);
            let own = velocity_component(
                cell,
                axis,
                source,
                inverse_cell,
                face_flow,
                fluid,
                has_solids,
                nx,
                ny,
                nz,
                of_gradient,
            );
            let mut high = 0.0f32;
            if high_fluid {
                high = velocity_component(
                    cell + stride,
                    axis,
                    source,
                    inverse_cell,
                    face_flow,
                    fluid,
                    has_solids,
                    nx,
                    ny,
                    nz,
                    of_gradient,
                );
            }
            let mut low = 0.0f32;
            if low_fluid {
                low = velocity_component(
                    cell - stride,
                    axis,
                    source,
                    inverse_cell,
                    face_flow,
                    fluid,
                    has_solids,
                    nx,
                    ny,
                    nz,
                    of_gradient,
                );
            }
            total += axis_flux(own, high, low, high_fluid, low_fluid, i, n, face_flow, axis)
                * inverse_cell[axis as usize];
            axis += 1;
        }
    }
    total
}

/// `D u`, one unit per cell.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn divergence_kernel(
    velocity: &[f32],
    divergence: &mut [f32],
    inverse_cell: &[f32],
    face_flow: &[f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    if cell >= nx * ny * nz {
        terminate!();
    }
    divergence[cell as usize] = divergence_at(
        cell,
        velocity,
        inverse_cell,
        face_flow,
        fluid,
        has_solids,
        nx,
        ny,
        nz,
        false,
    );
}

/// Component `axis` of `(D^T p)_c` (`-D^T` is the discrete gradient; 0 in obstacle cells and
/// pinned components).
#[cube]
#[allow(clippy::too_many_arguments)]
fn gradient_component(
    cell: u32,
    axis: u32,
    pressure: &[f32],
    inverse_cell: &[f32],
    face_flow: &[f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
) -> f32 {
    let mut value = 0.0f32;
    if component_is_free(cell, axis, fluid, has_solids, nx, ny, nz) {
        let own = pressure[cell as usize];
        let i = axis_coordinate(cell, axis, ny, nz);
        let n = axis_cells(axis, nx, ny, nz);
        let stride = axis_stride(axis, ny, nz);
        let (high, low) = fluid_neighbours(cell, i, n, stride, fluid, has_solids);
        if high {
            value += 0.5 * (own - pressure[(cell + stride) as usize]);
        } else if i + 1 >= n {
            value += box_face_flow(face_flow, axis, 1) * own;
        }
        if low {
            value -= 0.5 * (own - pressure[(cell - stride) as usize]);
        } else if i == 0 {
            value -= box_face_flow(face_flow, axis, 0) * own;
        }
        value *= inverse_cell[axis as usize];
    }
    value
}

/// `D^T p`, three components per cell.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn divergence_transpose_kernel(
    pressure: &[f32],
    output: &mut [f32],
    inverse_cell: &[f32],
    face_flow: &[f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    if cell >= nx * ny * nz {
        terminate!();
    }
    let mut axis = 0u32;
    while axis < 3 {
        output[(3 * cell + axis) as usize] = gradient_component(
            cell,
            axis,
            pressure,
            inverse_cell,
            face_flow,
            fluid,
            has_solids,
            nx,
            ny,
            nz,
        );
        axis += 1;
    }
}

/// Start of CG from `p = 0`: `z = M^-1 r` and `d = z`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn precondition_kernel(
    residual: &[f32],
    preconditioned: &mut [f32],
    direction: &mut [f32],
    inverse_cell: &[f32],
    face_flow: &[f32],
    fluid: &[f32],
    has_solids: u32,
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    if cell >= nx * ny * nz {
        terminate!();
    }
    let z = residual[cell as usize]
        * inverse_diagonal(cell, inverse_cell, face_flow, fluid, has_solids, nx, ny, nz);
    preconditioned[cell as usize] = z;
    direction[cell as usize] = z;
}
