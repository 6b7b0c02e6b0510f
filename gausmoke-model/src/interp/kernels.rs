//! The fused Gaussian-kernel interpolation ([`super::host`]) as cubecl kernels: one unit per
//! point, the stencil walked in passes (nearest distance, normalisation, velocity, Jacobian)
//! so nothing per node is stored. The backward pass adds the grid gradient with float atomics
//! (summation order not fixed: the CPU path agrees to float tolerance, not bit for bit).

use burn::tensor::DType;
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;
use gausmoke_render::FloatAtomics;
use gausmoke_render::kernels::atomics::{CasAdd, GradientAdd, NativeAdd, native_float_atomics};
use gausmoke_render::kernels::buffers::{
    Allocator, GAUSSIAN_BLOCK, buffer, contiguous_f32, leading, linear_cubes,
};
use gausmoke_render::kernels::math::Vec3;

use super::host::{KernelGrid, SAMPLE_FLOATS};

/// Slots of the grid parameter buffer.
struct GridParam;

impl GridParam {
    const LO: usize = 0;
    const CELL: usize = 3;
    const INV_VAR: usize = 6;
}

fn grid_params(grid: &KernelGrid) -> [f32; 7] {
    let mut params = [0.0; 7];
    params[GridParam::LO..GridParam::LO + 3].copy_from_slice(&grid.lo);
    params[GridParam::CELL..GridParam::CELL + 3].copy_from_slice(&grid.cell);
    params[GridParam::INV_VAR] = 1.0 / (grid.std_cells * grid.std_cells);
    params
}

/// The dimensions the kernels index with.
#[derive(CubeType, Clone, Copy)]
pub struct Dims {
    pub nx: u32,
    pub ny: u32,
    pub nz: u32,
    pub stencil: u32,
}

/// A point's stencil: its cell coordinates, first node, and the normalisation of its weights.
#[derive(CubeType, Clone, Copy)]
pub struct PointStencil {
    pub c: Vec3,
    pub bx: u32,
    pub by: u32,
    pub bz: u32,
    pub nearest: f32,
    pub total: f32,
}

/// First node along one axis: `clamp(floor(c) - (S/2 - 1), 0, n - S)`.
#[cube]
fn first_node(c: f32, stencil: u32, cells: u32) -> u32 {
    let first = f32::cast_from(stencil / 2 - 1);
    let base = (c.floor() - first)
        .max(0.0)
        .min(f32::cast_from(cells - stencil));
    u32::cast_from(base)
}

/// Grid coordinates of node `n` of the stencil (x slowest).
#[cube]
fn node_coords(s: &PointStencil, d: &Dims, n: u32) -> (u32, u32, u32) {
    let l = n % d.stencil;
    let j = (n / d.stencil) % d.stencil;
    let i = n / (d.stencil * d.stencil);
    (s.bx + i, s.by + j, s.bz + l)
}

/// `delta = node - c` (cells) of node `n`.
#[cube]
fn node_delta(s: &PointStencil, d: &Dims, n: u32) -> Vec3 {
    let (x, y, z) = node_coords(s, d, n);
    Vec3::new(
        f32::cast_from(x) - s.c.x,
        f32::cast_from(y) - s.c.y,
        f32::cast_from(z) - s.c.z,
    )
}

/// Flat grid cell of node `n`.
#[cube]
fn node_cell(s: &PointStencil, d: &Dims, n: u32) -> usize {
    let (x, y, z) = node_coords(s, d, n);
    ((x * d.ny + y) * d.nz + z) as usize
}

#[cube]
fn point_stencil(grid: &[f32], d: &Dims, point: &Vec3) -> PointStencil {
    let c = Vec3::new(
        (point.x - grid[GridParam::LO]) / grid[GridParam::CELL] - 0.5,
        (point.y - grid[GridParam::LO + 1]) / grid[GridParam::CELL + 1] - 0.5,
        (point.z - grid[GridParam::LO + 2]) / grid[GridParam::CELL + 2] - 0.5,
    );
    let bx = first_node(c.x, d.stencil, d.nx);
    let by = first_node(c.y, d.stencil, d.ny);
    let bz = first_node(c.z, d.stencil, d.nz);
    let mut s = PointStencil {
        c,
        bx,
        by,
        bz,
        nearest: 3.0e38f32,
        total: 0.0f32,
    };
    let nodes = d.stencil * d.stencil * d.stencil;
    let mut n = 0u32;
    while n < nodes {
        let delta = node_delta(&s, d, n);
        s.nearest = s.nearest.min(delta.dot(&delta));
        n += 1;
    }
    let inv_var = grid[GridParam::INV_VAR];
    let mut m = 0u32;
    while m < nodes {
        let delta = node_delta(&s, d, m);
        s.total += ((delta.dot(&delta) - s.nearest) * (-0.5f32 * inv_var)).exp();
        m += 1;
    }
    s
}

/// `p_g`, the normalised weight of a node at `delta`.
#[cube]
fn weight(grid: &[f32], s: &PointStencil, delta: &Vec3) -> f32 {
    ((delta.dot(delta) - s.nearest) * (-0.5f32 * grid[GridParam::INV_VAR])).exp() / s.total
}

/// `u` and `J` (rows) of a point.
#[cube]
fn evaluate(
    grid: &[f32],
    velocity: &[f32],
    s: &PointStencil,
    d: &Dims,
) -> (Vec3, Vec3, Vec3, Vec3) {
    let nodes = d.stencil * d.stencil * d.stencil;
    let inv_var = grid[GridParam::INV_VAR];
    let mut u = Vec3::new(0.0, 0.0, 0.0);
    let mut n = 0u32;
    while n < nodes {
        let delta = node_delta(s, d, n);
        let cell = node_cell(s, d, n);
        u.add_assign(&Vec3::load(velocity, 3 * cell).scale(weight(grid, s, &delta)));
        n += 1;
    }
    let mut jx = Vec3::new(0.0, 0.0, 0.0);
    let mut jy = Vec3::new(0.0, 0.0, 0.0);
    let mut jz = Vec3::new(0.0, 0.0, 0.0);
    let mut m = 0u32;
    while m < nodes {
        let delta = node_delta(s, d, m);
        let cell = node_cell(s, d, m);
        let p = weight(grid, s, &delta);
        let du = Vec3::load(velocity, 3 * cell).sub(&u).scale(p);
        let k = delta.scale(inv_var);
        jx.add_assign(&k.scale(du.x));
        jy.add_assign(&k.scale(du.y));
        jz.add_assign(&k.scale(du.z));
        m += 1;
    }
    let inv_h = Vec3::new(
        1.0 / grid[GridParam::CELL],
        1.0 / grid[GridParam::CELL + 1],
        1.0 / grid[GridParam::CELL + 2],
    );
    (
        u,
        Vec3::new(jx.x * inv_h.x, jx.y * inv_h.y, jx.z * inv_h.z),
        Vec3::new(jy.x * inv_h.x, jy.y * inv_h.y, jy.z * inv_h.z),
        Vec3::new(jz.x * inv_h.x, jz.y * inv_h.y, jz.z * inv_h.z),
    )
}

#[cube(launch)]
pub fn sample_kernel(
    velocity: &[f32],
    points: &[f32],
    grid: &[f32],
    output: &mut [f32],
    nx: u32,
    ny: u32,
    nz: u32,
    stencil: u32,
    num_points: u32,
) {
    let dims = Dims {
        nx,
        ny,
        nz,
        stencil,
    };
    let i = ABSOLUTE_POS;
    if i >= num_points as usize {
        terminate!();
    }
    let s = point_stencil(grid, &dims, &Vec3::load(points, 3 * i));
    let (u, jx, jy, jz) = evaluate(grid, velocity, &s, &dims);
    let out = i * 12;
    u.store(output, out);
    jx.store(output, out + 3);
    jy.store(output, out + 6);
    jz.store(output, out + 9);
}

/// Component `axis` of a vector.
#[cube]
fn component(v: &Vec3, axis: u32) -> f32 {
    let mut value = v.z;
    if axis == 0 {
        value = v.x;
    } else if axis == 1 {
        value = v.y;
    }
    value
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn sample_backward_kernel<A: GradientAdd>(
    velocity: &[f32],
    points: &[f32],
    grid: &[f32],
    grad: &[f32],
    grad_velocity: &mut [Atomic<A::Cell>],
    grad_points: &mut [f32],
    nx: u32,
    ny: u32,
    nz: u32,
    stencil: u32,
    num_points: u32,
) {
    let dims = Dims {
        nx,
        ny,
        nz,
        stencil,
    };
    let i = ABSOLUTE_POS;
    if i >= num_points as usize {
        terminate!();
    }
    let s = point_stencil(grid, &dims, &Vec3::load(points, 3 * i));
    let (u, jx, jy, jz) = evaluate(grid, velocity, &s, &dims);
    let g = i * 12;
    let ubar = Vec3::load(grad, g);
    let jbar_x = Vec3::load(grad, g + 3);
    let jbar_y = Vec3::load(grad, g + 6);
    let jbar_z = Vec3::load(grad, g + 9);
    let inv_var = grid[GridParam::INV_VAR];
    let h = Vec3::new(
        grid[GridParam::CELL],
        grid[GridParam::CELL + 1],
        grid[GridParam::CELL + 2],
    );
    let nodes = dims.stencil * dims.stencil * dims.stencil;
    let mut kbar = Vec3::new(0.0, 0.0, 0.0);
    let mut n = 0u32;
    while n < nodes {
        let delta = node_delta(&s, &dims, n);
        kbar.add_assign(&delta.scale(inv_var * weight(grid, &s, &delta)));
        n += 1;
    }
    // Jbar_ab / h_b and J_ab, flat a * 3 + b.
    let mut jh = Array::<f32>::new(9usize);
    let mut jm = Array::<f32>::new(9usize);
    #[unroll]
    for b in 0..3u32 {
        let h_b = component(&h, b);
        jh[b as usize] = component(&jbar_x, b) / h_b;
        jh[3 + b as usize] = component(&jbar_y, b) / h_b;
        jh[6 + b as usize] = component(&jbar_z, b) / h_b;
        jm[b as usize] = component(&jx, b);
        jm[3 + b as usize] = component(&jy, b);
        jm[6 + b as usize] = component(&jz, b);
    }
    // second[a][b][e] = sum_g p_g (u_ga - u_a) k_gb (k_ge - kbar_e), flat (a * 3 + b) * 3 + e.
    let mut second = Array::<f32>::new(27usize);
    #[unroll]
    for f in 0..27usize {
        second[f] = 0.0;
    }
    let mut m = 0u32;
    while m < nodes {
        let delta = node_delta(&s, &dims, m);
        let cell = node_cell(&s, &dims, m);
        let p = weight(grid, &s, &delta);
        let k = delta.scale(inv_var);
        let centred = k.sub(&kbar);
        let du = Vec3::load(velocity, 3 * cell).sub(&u).scale(p);
        // dL/du_ga = p_g (ubar_a + sum_b Jbar_ab (k_gb - kbar_b) / h_b).
        #[unroll]
        for a in 0..3u32 {
            let row = (a * 3) as usize;
            let along = jh[row] * centred.x + jh[row + 1] * centred.y + jh[row + 2] * centred.z;
            A::add(
                grad_velocity,
                3 * cell + a as usize,
                p * (component(&ubar, a) + along),
            );
            #[unroll]
            for b in 0..3u32 {
                let factor = component(&du, a) * component(&k, b);
                let base = ((a * 3 + b) * 3) as usize;
                second[base] += factor * centred.x;
                second[base + 1] += factor * centred.y;
                second[base + 2] += factor * centred.z;
            }
        }
        m += 1;
    }
    // dL/dc_e = sum_a ubar_a J_ae h_e + sum_ab Jbar_ab / h_b (second_abe - J_ae h_e kbar_b).
    #[unroll]
    for e in 0..3u32 {
        let h_e = component(&h, e);
        let mut total = 0.0f32;
        #[unroll]
        for a in 0..3u32 {
            let j_ae = jm[(a * 3 + e) as usize];
            total += component(&ubar, a) * j_ae * h_e;
            #[unroll]
            for b in 0..3u32 {
                let value =
                    second[((a * 3 + b) * 3 + e) as usize] - j_ae * h_e * component(&kbar, b);
                total += jh[(a * 3 + b) as usize] * value;
            }
        }
        grad_points[3 * i + e as usize] = total / h_e;
    }
}

/// `[nx, ny, nz, stencil]` as the kernels take them.
fn dims(grid: &KernelGrid) -> [u32; 4] {
    let [nx, ny, nz] = grid.resolution.map(|n| {
        u32::try_from(n).expect("grid resolution checked by GridSpec (under 8 GiB per tensor)")
    });
    [nx, ny, nz, grid.stencil as u32]
}

/// `[M, SAMPLE_FLOATS]` on the device, as [`super::host::forward`].
pub fn forward(velocity: CubeTensor, points: CubeTensor, grid: &KernelGrid) -> CubeTensor {
    let velocity = contiguous_f32(velocity, "velocity grid");
    let points = contiguous_f32(points, "points");
    let m = points.meta.num_elements() / 3;
    let alloc = Allocator::like(&points);
    let params = alloc.f32s(&grid_params(grid));
    let output = alloc.empty(m * SAMPLE_FLOATS, DType::F32);
    let [nx, ny, nz, stencil] = dims(grid);
    if m > 0 {
        sample_kernel::launch(
            &alloc.client,
            linear_cubes(m),
            CubeDim::new_1d(GAUSSIAN_BLOCK),
            buffer(&velocity),
            buffer(&points),
            buffer(&params),
            buffer(&output),
            nx,
            ny,
            nz,
            stencil,
            m as u32,
        );
    }
    leading(output, vec![m, SAMPLE_FLOATS])
}

/// Gradients `(velocity, points)` on the device, as [`super::host::backward`].
pub fn backward(
    velocity: CubeTensor,
    points: CubeTensor,
    grid: &KernelGrid,
    grad: CubeTensor,
) -> (CubeTensor, CubeTensor) {
    let velocity = contiguous_f32(velocity, "velocity grid");
    let points = contiguous_f32(points, "points");
    let grad = contiguous_f32(grad, "interpolation gradient");
    let velocity_shape = velocity.meta.shape().to_vec();
    let m = points.meta.num_elements() / 3;
    let alloc = Allocator::like(&points);
    let params = alloc.f32s(&grid_params(grid));
    let grad_velocity = alloc.zeros(velocity.meta.num_elements(), DType::F32);
    let grad_points = alloc.empty(3 * m, DType::F32);
    let [nx, ny, nz, stencil] = dims(grid);
    macro_rules! launch {
        ($adder:ty) => {
            sample_backward_kernel::launch::<$adder>(
                &alloc.client,
                linear_cubes(m),
                CubeDim::new_1d(GAUSSIAN_BLOCK),
                buffer(&velocity),
                buffer(&points),
                buffer(&params),
                buffer(&grad),
                buffer(&grad_velocity),
                buffer(&grad_points),
                nx,
                ny,
                nz,
                stencil,
                m as u32,
            )
        };
    }
    if m > 0 {
        if native_float_atomics(&alloc.client, FloatAtomics::Native) {
            launch!(NativeAdd);
        } else {
            launch!(CasAdd);
        }
    }
    (
        leading(grad_velocity, velocity_shape),
        leading(grad_points, vec![m, 3]),
    )
}
