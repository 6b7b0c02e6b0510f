//! Which grid cells a Gaussian's support covers, inside kernels (as `SplatGrid::support`), and
//! the grid parameter buffer the density kernels read.

use cubecl::prelude::*;
use gausmoke_render::kernels::math::{
    Mat3, Quat, Vec3, Whitening, WhiteningContext, softplus, whiten, whitening_context,
};

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

/// One cell of a support: its flat index in the grid and its centre.
#[derive(CubeType, Clone, Copy)]
pub struct SupportCell {
    pub index: usize,
    pub centre: Vec3,
}

#[cube]
impl GaussianSupport {
    /// Number of cells in the box (empty axes give 0).
    pub fn len(&self) -> u32 {
        (self.x.end - self.x.start) * (self.y.end - self.y.start) * (self.z.end - self.z.start)
    }

    /// Cell `k` of the box, x slowest and z fastest (the order the host path visits).
    pub fn cell(&self, grid: &[f32], k: u32, ny: u32, nz: u32) -> SupportCell {
        let depth = self.z.end - self.z.start;
        let height = self.y.end - self.y.start;
        let ck = self.z.start + k % depth;
        let cj = self.y.start + (k / depth) % height;
        let ci = self.x.start + k / (depth * height);
        SupportCell {
            index: ((ci * ny + cj) * nz + ck) as usize,
            centre: Vec3::new(
                cell_centre(grid, 0usize, ci),
                cell_centre(grid, 1usize, cj),
                cell_centre(grid, 2usize, ck),
            ),
        }
    }
}

/// Gaussian `i` as both density kernels see it: its world-space whitening (and what its
/// gradient reuses), density and support.
#[derive(CubeType)]
pub struct GridGaussian {
    pub context: WhiteningContext,
    pub whitening: Whitening,
    pub sigma: f32,
    pub support: GaussianSupport,
}

#[cube]
#[allow(clippy::too_many_arguments)]
pub fn grid_gaussian(
    means: &[f32],
    quats: &[f32],
    log_scales: &[f32],
    raw_densities: &[f32],
    grid: &[f32],
    i: usize,
    nx: u32,
    ny: u32,
    nz: u32,
) -> GridGaussian {
    let mean = Vec3::load(means, 3 * i);
    let log_scale = Vec3::load(log_scales, 3 * i);
    let context = whitening_context(&Quat::load(quats, 4 * i), &log_scale, &mean);
    let whitening = whiten(&context, &Mat3::identity());
    GridGaussian {
        context,
        whitening,
        sigma: softplus(raw_densities[i]),
        support: gaussian_support(grid, &mean, &log_scale, nx, ny, nz),
    }
}

/// World coordinate along `axis` of the centre of cell `index`.
#[cube]
fn cell_centre(grid: &[f32], axis: usize, index: u32) -> f32 {
    grid[GridParam::LO + axis] + (f32::cast_from(index) + 0.5) * grid[GridParam::CELL + axis]
}
