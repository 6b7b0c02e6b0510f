//! Stage 1: one unit per Gaussian projects it into the camera's whitened frame (a [`Splat`]),
//! bounds the screen tiles its support can touch, and counts per tile the Gaussians touching
//! it. CPU twin: `cpu::project_and_bin` (which bounds the footprint by the exact conic in f64;
//! the bound here is the tangent planes in f32 with a pixel of slack, never tighter).

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use burn::tensor::DType;
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;

use super::buffers::{Allocator, GAUSSIAN_BLOCK, buffer, linear_cubes};
use super::math::{Mat3, Quat, SQRT_TAU, Vec3, softplus, whiten, whitening_context};
use super::splat::{SPLAT_FLOATS, Splat, ViewParam, view_pose};
use crate::gaussians::Gaussians;

/// Tile edge in pixels, as the CPU path.
pub const TILE_EDGE: u32 = crate::cpu::TILE_SIZE as u32;

/// Half-open rectangle of tiles `[x0, x1) x [y0, y1)`, stored as 4 `u32`; empty when culled.
#[derive(CubeType, Clone, Copy)]
pub struct TileRect {
    pub x0: u32,
    pub x1: u32,
    pub y0: u32,
    pub y1: u32,
}

#[cube]
impl TileRect {
    pub fn load(rects: &[u32], index: usize) -> TileRect {
        TileRect {
            x0: rects[4 * index],
            x1: rects[4 * index + 1],
            y0: rects[4 * index + 2],
            y1: rects[4 * index + 3],
        }
    }

    pub fn store(&self, rects: &mut [u32], index: usize) {
        rects[4 * index] = self.x0;
        rects[4 * index + 1] = self.x1;
        rects[4 * index + 2] = self.y0;
        rects[4 * index + 3] = self.y1;
    }
}

/// The extent of the ellipsoid `(x - mu)^T Sigma^-1 (x - mu) <= tau` along one image axis:
/// the planes through the camera tangent to it are `A s^2 + 2 B s + C = 0` with
/// `A = mu_z^2 - tau S_zz`, `B = mu_a mu_z - tau S_az`, `C = mu_a^2 - tau S_aa`,
/// `S = M M^T`, `M = W R S` (rows `m_a`, `m_z`). Returns `(B, B^2 - AC)`, the discriminant
/// expanded (Lagrange's identity) so no O(mu^4) terms cancel in f32:
/// `B^2 - AC = tau (|mu_z m_a - mu_a m_z|^2 - tau |m_a x m_z|^2)`.
#[cube]
fn tangent_extent(mu_a: f32, mu_z: f32, m_a: &Vec3, m_z: &Vec3, tau: f32) -> (f32, f32) {
    let b = mu_a * mu_z - tau * m_a.dot(m_z);
    let v = m_a.scale(mu_z).sub(&m_z.scale(mu_a));
    let c = m_a.cross(m_z);
    (b, tau * (v.dot(&v) - tau * c.dot(&c)))
}

/// Tiles whose pixels may see rays with `K <= cutoff` of a Gaussian centred at `mu` (camera
/// space) with camera-space axes `axes` (rows `W r_k`) and scales `scale`.
#[cube]
fn footprint(
    view: &[f32],
    mu: &Vec3,
    axes: &Mat3,
    scale: &Vec3,
    cutoff: f32,
    width: u32,
    height: u32,
) -> TileRect {
    let tiles_x = (width + TILE_EDGE - 1) / TILE_EDGE;
    let tiles_y = (height + TILE_EDGE - 1) / TILE_EDGE;
    // Rows of M = W R S: m_j = ((W r_0)_j s_0, (W r_1)_j s_1, (W r_2)_j s_2).
    let m_x = Vec3::new(
        axes.r0.x * scale.x,
        axes.r1.x * scale.y,
        axes.r2.x * scale.z,
    );
    let m_y = Vec3::new(
        axes.r0.y * scale.x,
        axes.r1.y * scale.y,
        axes.r2.y * scale.z,
    );
    let m_z = Vec3::new(
        axes.r0.z * scale.x,
        axes.r1.z * scale.y,
        axes.r2.z * scale.z,
    );
    let quad_a = mu.z * mu.z - cutoff * m_z.dot(&m_z);
    let (bx, disc_x) = tangent_extent(mu.x, mu.z, &m_x, &m_z, cutoff);
    let (by, disc_y) = tangent_extent(mu.y, mu.z, &m_y, &m_z, cutoff);
    let mut rect = TileRect {
        x0: 0,
        x1: tiles_x,
        y0: 0,
        y1: tiles_y,
    };
    // The camera inside the ellipsoid, or an unbounded image: the whole image (conservative).
    if quad_a > 0.0 && disc_x >= 0.0 && disc_y >= 0.0 {
        let root_x = disc_x.sqrt();
        let root_y = disc_y.sqrt();
        let s_lo = (-bx - root_x) / quad_a;
        let s_hi = (-bx + root_x) / quad_a;
        let t_lo = (-by - root_y) / quad_a;
        let t_hi = (-by + root_y) / quad_a;
        let fx = view[ViewParam::FX];
        let fy = view[ViewParam::FY];
        let u_min = view[ViewParam::CX] + fx * s_lo.min(s_hi);
        let u_max = view[ViewParam::CX] + fx * s_lo.max(s_hi);
        let v_min = view[ViewParam::CY] - fy * t_lo.max(t_hi);
        let v_max = view[ViewParam::CY] - fy * t_lo.min(t_hi);
        // Pixel centres i + 0.5 within [min, max], with a pixel of slack for rounding; in
        // f32 because the tile grid is small.
        let px0 = (u_min - 1.5).ceil().max(0.0);
        let px1 = (u_max + 0.5).floor().min(f32::cast_from(width) - 1.0);
        let py0 = (v_min - 1.5).ceil().max(0.0);
        let py1 = (v_max + 0.5).floor().min(f32::cast_from(height) - 1.0);
        rect.x1 = 0;
        rect.y1 = 0;
        if px0 <= px1 && py0 <= py1 {
            rect.x0 = u32::cast_from(px0) / TILE_EDGE;
            rect.x1 = u32::cast_from(px1) / TILE_EDGE + 1;
            rect.y0 = u32::cast_from(py0) / TILE_EDGE;
            rect.y1 = u32::cast_from(py1) / TILE_EDGE + 1;
        }
    }
    rect
}

/// Largest transverse term at which `alpha_min` is still reachable (`cpu::effective_cutoff`).
#[cube]
fn effective_cutoff(view: &[f32], sigma: f32, max_log_scale: f32) -> f32 {
    let peak = sigma * SQRT_TAU * max_log_scale.exp();
    let mut alpha_bound = 2.0 * (peak / view[ViewParam::MIN_OPTICAL_DEPTH]).ln();
    if view[ViewParam::ALPHA_MODEL] != 0.0 {
        // Splat opacity: alpha = o exp(-K/2) reaches alpha_min while K <= 2 ln(o / alpha_min).
        alpha_bound = 2.0 * (-(-sigma).exp_m1() / view[ViewParam::ALPHA_MIN]).ln();
    }
    view[ViewParam::KERNEL_CUTOFF].min(alpha_bound * 1.001 + 1e-3)
}

#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn project_kernel(
    means: &[f32],
    quats: &[f32],
    log_scales: &[f32],
    raw_densities: &[f32],
    colors: &[f32],
    view: &[f32],
    splats: &mut [f32],
    depths: &mut [f32],
    rects: &mut [u32],
    tile_counts: &mut [Atomic<u32>],
    num_gaussians: u32,
    width: u32,
    height: u32,
) {
    let i = ABSOLUTE_POS;
    if i >= num_gaussians as usize {
        terminate!();
    }
    let tiles_x = (width + TILE_EDGE - 1) / TILE_EDGE;
    let (rotation, origin) = view_pose(view);
    let log_scale = Vec3::load(log_scales, 3 * i);
    let offset = Vec3::load(means, 3 * i).sub(&origin);
    let context = whitening_context(&Quat::load(quats, 4 * i), &log_scale, &offset);
    let sigma = softplus(raw_densities[i]);
    let splat = Splat {
        whitening: whiten(&context, &rotation),
        sigma,
        color: Vec3::load(colors, 3 * i),
    };
    splat.store(splats, i);

    let mu = rotation.mul(&offset);
    let depth = -mu.z;
    depths[i] = depth;
    let cutoff = effective_cutoff(view, sigma, log_scale.max_element());
    let mut rect = TileRect {
        x0: 0,
        x1: 0,
        y0: 0,
        y1: 0,
    };
    if depth > view[ViewParam::NEAR_PLANE] && sigma > 0.0 && cutoff > 0.0 {
        let axes = Mat3 {
            r0: rotation.mul(&context.axes.r0),
            r1: rotation.mul(&context.axes.r1),
            r2: rotation.mul(&context.axes.r2),
        };
        let scale = Vec3::new(log_scale.x.exp(), log_scale.y.exp(), log_scale.z.exp());
        let bound = footprint(view, &mu, &axes, &scale, cutoff, width, height);
        rect.x0 = bound.x0;
        rect.x1 = bound.x1;
        rect.y0 = bound.y0;
        rect.y1 = bound.y1;
    }
    rect.store(rects, i);
    let mut ty = rect.y0;
    while ty < rect.y1 {
        let mut tx = rect.x0;
        while tx < rect.x1 {
            tile_counts[(ty * tiles_x + tx) as usize].fetch_add(1u32);
            tx += 1;
        }
        ty += 1;
    }
}

/// What [`project`] writes for one view: the splats, centre depths, tile rectangles and
/// per-tile counts.
#[derive(Debug, Clone)]
pub struct Projection {
    pub splats: CubeTensor,
    pub depths: CubeTensor,
    pub rects: CubeTensor,
    pub counts: CubeTensor,
}

/// Projects every Gaussian (contiguous f32 attributes) into `view` for a `width` x `height`
/// image.
pub fn project(
    gaussians: &Gaussians<CubeTensor>,
    view: &CubeTensor,
    width: u32,
    height: u32,
) -> Projection {
    let n = gaussians.raw_densities.meta.num_elements();
    let num_tiles = (width.div_ceil(TILE_EDGE) * height.div_ceil(TILE_EDGE)) as usize;
    let alloc = Allocator::like(view);
    let projection = Projection {
        splats: alloc.empty(n * SPLAT_FLOATS, DType::F32),
        depths: alloc.empty(n, DType::F32),
        rects: alloc.empty(n * 4, DType::U32),
        counts: alloc.zeros(num_tiles, DType::U32),
    };
    if n > 0 {
        project_kernel::launch(
            &alloc.client,
            linear_cubes(n),
            CubeDim::new_1d(GAUSSIAN_BLOCK),
            buffer(&gaussians.means),
            buffer(&gaussians.rotations),
            buffer(&gaussians.log_scales),
            buffer(&gaussians.raw_densities),
            buffer(&gaussians.colors),
            buffer(view),
            buffer(&projection.splats),
            buffer(&projection.depths),
            buffer(&projection.rects),
            buffer(&projection.counts),
            n as u32,
            width,
            height,
        );
    }
    projection
}
