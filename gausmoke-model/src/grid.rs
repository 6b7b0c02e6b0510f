//! The Eulerian grid: a cell-centred regular grid over the smoke's axis-aligned box.
//!
//! Layout of every grid tensor in this crate: `[nx, ny, nz, channels]` (x slowest), so cell
//! `(i, j, k)` is flat row `(i * ny + j) * nz + k` and its centre is
//! `lo + (i + 0.5, j + 0.5, k + 0.5) * cell_size`. Units: world units; velocities in world
//! units per frame.

use gausmoke_core::glam::Vec3;

/// Grids larger than this many bytes per channel-f32 tensor are refused before allocation.
pub const MAX_GRID_BYTES: usize = 8 << 30;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GridError {
    #[error(
        "grid resolution {resolution:?} has a zero axis; every axis needs at least {min} cells"
    )]
    TooFewCells { resolution: [usize; 3], min: usize },
    #[error(
        "grid resolution {resolution:?} with {channels} channels needs {bytes} bytes per tensor, above the {limit}-byte limit"
    )]
    TooLarge {
        resolution: [usize; 3],
        channels: usize,
        bytes: usize,
        limit: usize,
    },
    #[error("grid box from {lo:?} to {hi:?} has a zero, negative or non-finite extent")]
    BadBox { lo: Vec3, hi: Vec3 },
}

/// A cell-centred grid over `[lo, hi]` with `resolution` cells per axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridSpec {
    lo: Vec3,
    hi: Vec3,
    resolution: [usize; 3],
}

impl GridSpec {
    /// Validates the box and the resolution (at least `min_cells` per axis, e.g. the
    /// interpolation stencil), and estimates the memory of a 4-channel f32 grid first.
    pub fn new(
        lo: Vec3,
        hi: Vec3,
        resolution: [usize; 3],
        min_cells: usize,
    ) -> Result<Self, GridError> {
        let extent = hi - lo;
        if !(lo.is_finite() && hi.is_finite()) || extent.min_element() <= 0.0 {
            return Err(GridError::BadBox { lo, hi });
        }
        let min = min_cells.max(1);
        if resolution.iter().any(|&n| n < min) {
            return Err(GridError::TooFewCells { resolution, min });
        }
        let channels = 4;
        let bytes = resolution
            .iter()
            .try_fold(channels * 4usize, |acc, &n| acc.checked_mul(n))
            .unwrap_or(usize::MAX);
        if bytes > MAX_GRID_BYTES {
            return Err(GridError::TooLarge {
                resolution,
                channels,
                bytes,
                limit: MAX_GRID_BYTES,
            });
        }
        Ok(Self { lo, hi, resolution })
    }

    pub fn lo(&self) -> Vec3 {
        self.lo
    }

    pub fn hi(&self) -> Vec3 {
        self.hi
    }

    pub fn resolution(&self) -> [usize; 3] {
        self.resolution
    }

    pub fn num_cells(&self) -> usize {
        self.resolution.iter().product()
    }

    /// Panics unless `dims` is `[nx, ny, nz, 3]`, a velocity grid on this grid (a programming
    /// error: the ops that take one state the shape in their docs).
    pub fn assert_velocity_shape(&self, dims: [usize; 4]) {
        let [nx, ny, nz, c] = dims;
        assert_eq!(
            ([nx, ny, nz], c),
            (self.resolution, 3),
            "velocity must be [nx, ny, nz, 3] on the grid"
        );
    }

    /// Edge lengths of one cell, world units.
    pub fn cell_size(&self) -> Vec3 {
        let [nx, ny, nz] = self.resolution;
        (self.hi - self.lo) / Vec3::new(nx as f32, ny as f32, nz as f32)
    }

    /// Centre of cell `(i, j, k)`.
    pub fn cell_centre(&self, i: usize, j: usize, k: usize) -> Vec3 {
        self.lo + (Vec3::new(i as f32, j as f32, k as f32) + 0.5) * self.cell_size()
    }

    /// Per cell in the grid's flat order, whether `inside` holds at its centre.
    pub fn cells_where(&self, inside: impl Fn(Vec3) -> bool) -> Vec<bool> {
        let [nx, ny, nz] = self.resolution;
        let mut out = Vec::with_capacity(self.num_cells());
        for i in 0..nx {
            for j in 0..ny {
                for k in 0..nz {
                    out.push(inside(self.cell_centre(i, j, k)));
                }
            }
        }
        out
    }

    /// Centres of every cell in the grid's flat order, `[nx * ny * nz * 3]`.
    pub fn cell_centres(&self) -> Vec<f32> {
        let [nx, ny, nz] = self.resolution;
        let mut out = Vec::with_capacity(3 * self.num_cells());
        for i in 0..nx {
            for j in 0..ny {
                for k in 0..nz {
                    out.extend(self.cell_centre(i, j, k).to_array());
                }
            }
        }
        out
    }
}
