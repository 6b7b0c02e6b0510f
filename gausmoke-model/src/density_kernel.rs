//! Density splatting ([`crate::density`]) as cubecl kernels for the cube backends.
//!
//! Both passes take one unit per Gaussian and walk the grid cells inside its support, exactly
//! the cells [`crate::density`] visits:
//! * forward: each unit adds `sigma k(x)` (or its spatial gradient) into the grid with float
//!   atomics (native where the device has them, else compare-and-swap on the bits);
//! * backward: each unit reads the incoming grid gradient at its cells (a gather, no atomics),
//!   sums the gradient of its world-space whitening (`L`, `L mu`, `sigma`), and the renderer's
//!   `view_backward_kernel` (camera at the origin) chains that to the parameters.
//!
//! The whitening comes from the renderer's `project_kernel` with the camera at the origin
//! ([`gausmoke_render::kernels::world_splats`]), so the two ops differentiate one
//! parameterisation. The atomic sums are not ordered: results agree with the CPU path to float
//! tolerance, not bit for bit.

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use burn::tensor::DType;
use burn_cubecl::ops::numeric::{empty_device_contiguous_dtype, zeros_client};
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;
use gausmoke_render::kernels::raster::{CasAdd, GradientAdd, NativeAdd, SPLAT_FLOATS};
use gausmoke_render::kernels::{
    GAUSSIAN_BLOCK, buffer, contiguous_f32, force_compare_and_swap, gaussian_cubes,
    has_native_f32_atomic_add, leading, world_splats, world_splats_backward,
};

use crate::density::SplatGrid;
use crate::density_op::DensityField;

/// Slots of the grid parameter buffer.
struct GridParam;

impl GridParam {
    /// Lower corner of the grid (0..3).
    const LO: usize = 0;
    /// Cell size per axis (3..6).
    const CELL: usize = 3;
    /// Squared Mahalanobis radius of the support.
    const CUTOFF: usize = 6;
}

const GRID_FLOATS: usize = 7;

fn grid_params(grid: &SplatGrid) -> [f32; GRID_FLOATS] {
    let mut params = [0.0; GRID_FLOATS];
    params[GridParam::LO..GridParam::LO + 3].copy_from_slice(&grid.lo);
    params[GridParam::CELL..GridParam::CELL + 3].copy_from_slice(&grid.cell);
    params[GridParam::CUTOFF] = grid.cutoff;
    params
}

/// Half-open range of cell indices along one axis whose centres lie within `radius` of
/// `centre` (as `SplatGrid::support`); empty (`start >= end`) when it misses the grid.
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

/// Radius of the axis-aligned box holding the support: `sqrt(cutoff) * max scale`.
#[cube]
fn support_radius(grid: &[f32], log_scales: &[f32], i: usize) -> f32 {
    let largest = log_scales[3 * i]
        .max(log_scales[3 * i + 1])
        .max(log_scales[3 * i + 2]);
    grid[GridParam::CUTOFF].sqrt() * largest.exp()
}

/// The cell ranges along each axis that hold Gaussian `i`'s support.
#[derive(CubeType, Clone, Copy)]
pub struct GaussianSupport {
    pub x: CellRange,
    pub y: CellRange,
    pub z: CellRange,
}

#[cube]
#[allow(clippy::too_many_arguments)]
fn gaussian_support(
    means: &[f32],
    log_scales: &[f32],
    grid: &[f32],
    i: usize,
    nx: u32,
    ny: u32,
    nz: u32,
) -> GaussianSupport {
    let radius = support_radius(grid, log_scales, i);
    GaussianSupport {
        x: axis_support(grid, 0usize, means[3 * i], radius, nx),
        y: axis_support(grid, 1usize, means[3 * i + 1], radius, ny),
        z: axis_support(grid, 2usize, means[3 * i + 2], radius, nz),
    }
}

/// World coordinate along `axis` of the centre of cell `index`.
#[cube]
fn cell_centre(grid: &[f32], axis: usize, index: u32) -> f32 {
    grid[GridParam::LO + axis] + (f32::cast_from(index) + 0.5) * grid[GridParam::CELL + axis]
}

/// Whitened offset `m = L x - L mu` of the point `x` for the splat at `base`.
#[cube]
fn whitened_offset(splats: &[f32], base: usize, x0: f32, x1: f32, x2: f32) -> (f32, f32, f32) {
    let m0 = splats[base] * x0 + splats[base + 1] * x1 + splats[base + 2] * x2 - splats[base + 9];
    let m1 =
        splats[base + 3] * x0 + splats[base + 4] * x1 + splats[base + 5] * x2 - splats[base + 10];
    let m2 =
        splats[base + 6] * x0 + splats[base + 7] * x1 + splats[base + 8] * x2 - splats[base + 11];
    (m0, m1, m2)
}

/// Forward: adds every Gaussian's density (`spatial_gradient = false`, one channel) or the
/// density's spatial gradient (`true`, three channels, `-sigma k L^T m`) into `field`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn splat_field_kernel<A: GradientAdd>(
    splats: &[f32],
    means: &[f32],
    log_scales: &[f32],
    grid: &[f32],
    field: &mut [Atomic<A::Cell>],
    nx: u32,
    ny: u32,
    nz: u32,
    num_gaussians: u32,
    #[comptime] spatial_gradient: bool,
) {
    let i = ABSOLUTE_POS;
    if i >= num_gaussians as usize {
        terminate!();
    }
    let base = i * SPLAT_FLOATS;
    let sigma = splats[base + 12];
    let support = gaussian_support(means, log_scales, grid, i, nx, ny, nz);
    let cutoff = grid[GridParam::CUTOFF];
    let mut ci = support.x.start;
    while ci < support.x.end {
        let x0 = cell_centre(grid, 0usize, ci);
        let mut cj = support.y.start;
        while cj < support.y.end {
            let x1 = cell_centre(grid, 1usize, cj);
            let mut ck = support.z.start;
            while ck < support.z.end {
                let x2 = cell_centre(grid, 2usize, ck);
                let (m0, m1, m2) = whitened_offset(splats, base, x0, x1, x2);
                let k2 = m0 * m0 + m1 * m1 + m2 * m2;
                if k2 <= cutoff {
                    let kernel = (-0.5f32 * k2).exp();
                    let cell = ((ci * ny + cj) * nz + ck) as usize;
                    if spatial_gradient {
                        let weight = -sigma * kernel;
                        // (L^T m)_a = sum_r L[r][a] m_r.
                        let g0 = splats[base] * m0 + splats[base + 3] * m1 + splats[base + 6] * m2;
                        let g1 =
                            splats[base + 1] * m0 + splats[base + 4] * m1 + splats[base + 7] * m2;
                        let g2 =
                            splats[base + 2] * m0 + splats[base + 5] * m1 + splats[base + 8] * m2;
                        A::add(field, 3 * cell, weight * g0);
                        A::add(field, 3 * cell + 1, weight * g1);
                        A::add(field, 3 * cell + 2, weight * g2);
                    } else {
                        A::add(field, cell, sigma * kernel);
                    }
                }
                ck += 1;
            }
            cj += 1;
        }
        ci += 1;
    }
}

/// Gradient of one Gaussian's whitening `L` (row-major `l00..l22`), whitened centre `L mu`
/// and density, summed over the cells of its support.
#[derive(CubeType)]
pub struct WhiteningGrad {
    pub l00: f32,
    pub l01: f32,
    pub l02: f32,
    pub l10: f32,
    pub l11: f32,
    pub l12: f32,
    pub l20: f32,
    pub l21: f32,
    pub l22: f32,
    pub center0: f32,
    pub center1: f32,
    pub center2: f32,
    pub sigma: f32,
}

#[cube]
impl WhiteningGrad {
    fn zero() -> WhiteningGrad {
        WhiteningGrad {
            l00: 0.0,
            l01: 0.0,
            l02: 0.0,
            l10: 0.0,
            l11: 0.0,
            l12: 0.0,
            l20: 0.0,
            l21: 0.0,
            l22: 0.0,
            center0: 0.0,
            center1: 0.0,
            center2: 0.0,
            sigma: 0.0,
        }
    }

    /// Adds the outer product `a b^T` to the gradient of `L`.
    #[allow(clippy::too_many_arguments)]
    fn add_whiten_outer(&mut self, a0: f32, a1: f32, a2: f32, b0: f32, b1: f32, b2: f32) {
        self.l00 += a0 * b0;
        self.l01 += a0 * b1;
        self.l02 += a0 * b2;
        self.l10 += a1 * b0;
        self.l11 += a1 * b1;
        self.l12 += a1 * b2;
        self.l20 += a2 * b0;
        self.l21 += a2 * b1;
        self.l22 += a2 * b2;
    }

    /// Adds `dLoss/dm` at the cell centre `x` through `m = L x - L mu`.
    #[allow(clippy::too_many_arguments)]
    fn add_offset_grad(&mut self, gm0: f32, gm1: f32, gm2: f32, x0: f32, x1: f32, x2: f32) {
        self.add_whiten_outer(gm0, gm1, gm2, x0, x1, x2);
        self.center0 -= gm0;
        self.center1 -= gm1;
        self.center2 -= gm2;
    }
}

/// Backward: per Gaussian, the gradient of its world splat ([`SPLAT_FLOATS`] per Gaussian,
/// colour slots zero) given the gradient of the field (`[cells]` or `[cells, 3]`). The
/// per-cell formulas are those of `density::splat_backward` and
/// `density::splat_gradient_backward`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn splat_field_backward_kernel(
    splats: &[f32],
    means: &[f32],
    log_scales: &[f32],
    grid: &[f32],
    grad_field: &[f32],
    splat_grads: &mut [f32],
    nx: u32,
    ny: u32,
    nz: u32,
    num_gaussians: u32,
    #[comptime] spatial_gradient: bool,
) {
    let i = ABSOLUTE_POS;
    if i >= num_gaussians as usize {
        terminate!();
    }
    let base = i * SPLAT_FLOATS;
    let sigma = splats[base + 12];
    let support = gaussian_support(means, log_scales, grid, i, nx, ny, nz);
    let cutoff = grid[GridParam::CUTOFF];
    let mut acc = WhiteningGrad::zero();
    let mut ci = support.x.start;
    while ci < support.x.end {
        let x0 = cell_centre(grid, 0usize, ci);
        let mut cj = support.y.start;
        while cj < support.y.end {
            let x1 = cell_centre(grid, 1usize, cj);
            let mut ck = support.z.start;
            while ck < support.z.end {
                let x2 = cell_centre(grid, 2usize, ck);
                let (m0, m1, m2) = whitened_offset(splats, base, x0, x1, x2);
                let k2 = m0 * m0 + m1 * m1 + m2 * m2;
                if k2 <= cutoff {
                    let kernel = (-0.5f32 * k2).exp();
                    let cell = ((ci * ny + cj) * nz + ck) as usize;
                    if spatial_gradient {
                        // f = -sigma k m.(L g): see `density::splat_gradient_backward`.
                        let up0 = grad_field[3 * cell];
                        let up1 = grad_field[3 * cell + 1];
                        let up2 = grad_field[3 * cell + 2];
                        let v0 =
                            splats[base] * up0 + splats[base + 1] * up1 + splats[base + 2] * up2;
                        let v1 = splats[base + 3] * up0
                            + splats[base + 4] * up1
                            + splats[base + 5] * up2;
                        let v2 = splats[base + 6] * up0
                            + splats[base + 7] * up1
                            + splats[base + 8] * up2;
                        let s = m0 * v0 + m1 * v1 + m2 * v2;
                        acc.sigma -= kernel * s;
                        let sk = sigma * kernel;
                        // Direct term: d f / d L = -sigma k m g^T.
                        acc.add_whiten_outer(-sk * m0, -sk * m1, -sk * m2, up0, up1, up2);
                        acc.add_offset_grad(
                            sk * (s * m0 - v0),
                            sk * (s * m1 - v1),
                            sk * (s * m2 - v2),
                            x0,
                            x1,
                            x2,
                        );
                    } else {
                        let up = grad_field[cell];
                        acc.sigma += up * kernel;
                        // d(sigma k)/dm = -sigma k m.
                        let scale = -up * sigma * kernel;
                        acc.add_offset_grad(scale * m0, scale * m1, scale * m2, x0, x1, x2);
                    }
                }
                ck += 1;
            }
            cj += 1;
        }
        ci += 1;
    }
    splat_grads[base] = acc.l00;
    splat_grads[base + 1] = acc.l01;
    splat_grads[base + 2] = acc.l02;
    splat_grads[base + 3] = acc.l10;
    splat_grads[base + 4] = acc.l11;
    splat_grads[base + 5] = acc.l12;
    splat_grads[base + 6] = acc.l20;
    splat_grads[base + 7] = acc.l21;
    splat_grads[base + 8] = acc.l22;
    splat_grads[base + 9] = acc.center0;
    splat_grads[base + 10] = acc.center1;
    splat_grads[base + 11] = acc.center2;
    splat_grads[base + 12] = acc.sigma;
    splat_grads[base + 13] = 0.0;
    splat_grads[base + 14] = 0.0;
    splat_grads[base + 15] = 0.0;
}

fn channels(field: DensityField) -> usize {
    match field {
        DensityField::Density => 1,
        DensityField::SpatialGradient => 3,
    }
}

fn field_shape(grid: &SplatGrid, field: DensityField) -> Vec<usize> {
    let mut shape = grid.resolution.to_vec();
    if field == DensityField::SpatialGradient {
        shape.push(3);
    }
    shape
}

fn resolution_u32(grid: &SplatGrid) -> [u32; 3] {
    grid.resolution.map(|n| {
        u32::try_from(n).expect("grid resolution checked by GridSpec (under 8 GiB per tensor)")
    })
}

fn upload(like: &CubeTensor, values: &[f32]) -> CubeTensor {
    use burn::backend::ops::FloatTensorOps;
    burn_cubecl::CubeBackend::float_from_data(
        burn::tensor::TensorData::new(values.to_vec(), [values.len()]),
        &like.device,
    )
}

/// `field` of the Gaussians at the grid's cell centres, on the device.
pub fn splat_field(
    means: CubeTensor,
    quats: CubeTensor,
    log_scales: CubeTensor,
    raw_densities: CubeTensor,
    grid: &SplatGrid,
    field: DensityField,
) -> CubeTensor {
    let means = contiguous_f32(means, "means");
    let log_scales = contiguous_f32(log_scales, "log_scales");
    let n = raw_densities.meta.num_elements();
    let splats = world_splats(means.clone(), quats, log_scales.clone(), raw_densities);
    let client = means.client.clone();
    let len = channels(field) * grid.resolution.iter().product::<usize>();
    let output = zeros_client(
        client.clone(),
        means.device.clone(),
        [len.max(1)].into(),
        DType::F32,
    );
    let params = upload(&means, &grid_params(grid));
    let [nx, ny, nz] = resolution_u32(grid);
    let spatial_gradient = field == DensityField::SpatialGradient;
    macro_rules! launch_forward {
        ($adder:ty) => {
            splat_field_kernel::launch::<$adder>(
                &client,
                gaussian_cubes(n),
                CubeDim::new_1d(GAUSSIAN_BLOCK),
                buffer(&splats),
                buffer(&means),
                buffer(&log_scales),
                buffer(&params),
                buffer(&output),
                nx,
                ny,
                nz,
                n as u32,
                spatial_gradient,
            )
        };
    }
    if n > 0 && len > 0 {
        if has_native_f32_atomic_add(&client) && !force_compare_and_swap() {
            launch_forward!(NativeAdd);
        } else {
            launch_forward!(CasAdd);
        }
    }
    leading(output, field_shape(grid, field))
}

/// Gradients `(means, quats, log_scales, raw_densities)` of [`splat_field`] given the
/// gradient of its output, on the device.
pub fn splat_field_backward(
    means: CubeTensor,
    quats: CubeTensor,
    log_scales: CubeTensor,
    raw_densities: CubeTensor,
    grid: &SplatGrid,
    field: DensityField,
    grad: CubeTensor,
) -> (CubeTensor, CubeTensor, CubeTensor, CubeTensor) {
    let means = contiguous_f32(means, "means");
    let quats = contiguous_f32(quats, "rotations");
    let log_scales = contiguous_f32(log_scales, "log_scales");
    let raw_densities = contiguous_f32(raw_densities, "raw_densities");
    let grad = contiguous_f32(grad, "density grid gradient");
    let expected = channels(field) * grid.resolution.iter().product::<usize>();
    assert_eq!(
        grad.meta.num_elements(),
        expected,
        "the gradient of the density field must match the field's shape {:?}",
        field_shape(grid, field)
    );
    let n = raw_densities.meta.num_elements();
    let splats = world_splats(
        means.clone(),
        quats.clone(),
        log_scales.clone(),
        raw_densities.clone(),
    );
    let client = means.client.clone();
    let splat_grads = empty_device_contiguous_dtype(
        client.clone(),
        means.device.clone(),
        [(n * SPLAT_FLOATS).max(1)].into(),
        DType::F32,
    );
    let params = upload(&means, &grid_params(grid));
    let [nx, ny, nz] = resolution_u32(grid);
    if n > 0 {
        splat_field_backward_kernel::launch(
            &client,
            gaussian_cubes(n),
            CubeDim::new_1d(GAUSSIAN_BLOCK),
            buffer(&splats),
            buffer(&means),
            buffer(&log_scales),
            buffer(&params),
            buffer(&grad),
            buffer(&splat_grads),
            nx,
            ny,
            nz,
            n as u32,
            field == DensityField::SpatialGradient,
        );
    }
    world_splats_backward(means, quats, log_scales, raw_densities, splat_grads)
}
