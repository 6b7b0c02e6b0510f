//! Which grid cells a Gaussian's support covers, inside kernels (as `SplatGrid::support`), and
//! the grid parameter buffer the density kernels read.

use cubecl::prelude::*;
use gausmoke_render::kernels::math::Vec3;

use crate::density::host::SplatGrid;

/// Slots of the grid parameter buffer.
pub struct GridParam;

impl GridParam {
    /// Lower corner of the grid (0..3).
    pub const LO: usize = 0;
    /// Cell size per axis (3..6).
    pub const CELL: usize = 3;
    /// Squared Mahalanobis radius of the support.
    pub const CUTOFF: usize = 6;
}

pub const GRID_FLOATS: usize = 7;

pub fn grid_params(grid: &SplatGrid) -> [f32; GRID_FLOATS] {
    let mut params = [0.0; GRID_FLOATS];
    params[GridParam::LO..GridParam::LO + 3].copy_from_slice(&grid.lo);
    params[GridParam::CELL..GridParam::CELL + 3].copy_from_slice(&grid.cell);
    params[GridParam::CUTOFF] = grid.cutoff;
    params
}

/// Half-open range of cell indices along one axis whose centres lie within `radius` of
/// `centre`; empty (`start >= end`) when it misses the grid.
#[derive(CubeType, Clone, Copy)]
pub struct CellRange {
    pub start: u32,
    pub end: u32,
}

#[cube]
fn axis_support(grid: &[f32], axis: usize, centre: f32, radius: f32, cells: u32) -> CellRange {
    let lo = grid[GridParam::LO + axis];
    let cell = grid[GridParam::CELL + axis];
    let first = ((centre - radius - lo) / cell - 0.5).ceil().max(0.0);
    let last = ((centre + radius - lo) / cell - 0.5)
        .floor()
        .min(f32::cast_from(cells) - 1.0);
    let mut range = CellRange { start: 0, end: 0 };
    // Written so that a NaN bound gives an empty range.
    if first <= last {
        range.start = u32::cast_from(first);
        range.end = u32::cast_from(last) + 1;
    }
    range
}

/// The cell ranges along each axis that hold a Gaussian's support.
#[derive(CubeType, Clone, Copy)]
pub struct GaussianSupport {
    pub x: CellRange,
    pub y: CellRange,
    pub z: CellRange,
}

/// The support of the Gaussian centred at `mean` with log-scales `log_scale`: the
/// axis-aligned box `mean +- sqrt(cutoff) * max scale`, in cells.
#[cube]
pub fn gaussian_support(
    grid: &[f32],
    mean: &Vec3,
    log_scale: &Vec3,
    nx: u32,
    ny: u32,
    nz: u32,
) -> GaussianSupport {
    let radius = grid[GridParam::CUTOFF].sqrt() * log_scale.max_element().exp();
    GaussianSupport {
        x: axis_support(grid, 0usize, mean.x, radius, nx),
        y: axis_support(grid, 1usize, mean.y, radius, ny),
        z: axis_support(grid, 2usize, mean.z, radius, nz),
    }
}

/// World coordinate along `axis` of the centre of cell `index`.
#[cube]
pub fn cell_centre(grid: &[f32], axis: usize, index: u32) -> f32 {
    grid[GridParam::LO + axis] + (f32::cast_from(index) + 0.5) * grid[GridParam::CELL + axis]
}
