//! The cubecl kernels of the volumetric Gaussian rasterizer. Everything is f32; buffers are flat.
//!
//! Layouts shared by the kernels (and by [`super`], which launches them):
//! * a projected Gaussian ("splat") is [`SPLAT_FLOATS`] floats: the whitening matrix `L`
//!   (row-major, 9), the whitened centre `m` (3), `sigma` (1) and the colour (3), exactly the
//!   fields of [`crate::math::ViewSplat`];
//! * the view is [`VIEW_FLOATS`] floats, see [`ViewParam`];
//! * a Gaussian's tile rectangle is 4 `u32` (`x0, x1, y0, y1`, half-open), empty when culled;
//! * tile `t` owns `list[offsets[t]..offsets[t + 1]]`, sorted by (centre depth, index).
//!
//! The per-ray maths mirrors [`crate::math`] line for line so the two paths agree to rounding;
//! each helper's gradient sits beside it.

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use cubecl::prelude::*;

/// Floats per projected Gaussian.
pub const SPLAT_FLOATS: usize = 16;
/// Threads per tile (one per pixel of a 16x16 tile) and Gaussians per shared-memory batch.
pub const TILE_THREADS: usize = 256;
/// Tile edge in pixels, as the CPU path.
pub const TILE_EDGE: u32 = 16;

/// Slots of the view parameter buffer.
pub struct ViewParam;

impl ViewParam {
    /// World-to-camera rotation, row-major (0..9).
    pub const ROTATION: usize = 0;
    /// Camera centre in world space (9..12).
    pub const ORIGIN: usize = 9;
    pub const FX: usize = 12;
    pub const FY: usize = 13;
    pub const CX: usize = 14;
    pub const CY: usize = 15;
    pub const ALPHA_MIN: usize = 16;
    pub const ALPHA_MAX: usize = 17;
    pub const TRANSMITTANCE_MIN: usize = 18;
    pub const KERNEL_CUTOFF: usize = 19;
    pub const NEAR_PLANE: usize = 20;
    /// `-ln(1 - alpha_min)`, the optical depth a Gaussian must reach to count.
    pub const MIN_OPTICAL_DEPTH: usize = 21;
    /// 0: Beer-Lambert alpha; 1: splat opacity (`crate::AlphaModel`).
    pub const ALPHA_MODEL: usize = 22;
}

/// Number of floats in the view parameter buffer.
pub const VIEW_FLOATS: usize = 23;

/// `sqrt(2 pi)`.
const SQRT_TAU: f32 = 2.506_628_3;

/// Softplus with torch's cut-over (`x > 20` returns `x`), as [`crate::math::softplus`].
#[cube]
fn softplus(x: f32) -> f32 {
    let mut y = x;
    if x <= 20.0 {
        y = x.exp().log1p();
    }
    y
}

/// Derivative of [`softplus`].
#[cube]
fn softplus_grad(x: f32) -> f32 {
    let mut y = 1.0f32;
    if x <= 20.0 {
        y = 1.0 / (1.0 + (-x).exp());
    }
    y
}

/// Unit camera-space direction of the ray through the centre of pixel `(px, py)`.
#[cube]
fn pixel_direction(view: &[f32], px: u32, py: u32) -> (f32, f32, f32) {
    let x = (f32::cast_from(px) + 0.5 - view[ViewParam::CX]) / view[ViewParam::FX];
    let y = -(f32::cast_from(py) + 0.5 - view[ViewParam::CY]) / view[ViewParam::FY];
    let inv_len = 1.0 / (x * x + y * y + 1.0).sqrt();
    (x * inv_len, y * inv_len, -inv_len)
}

/// One Gaussian on one ray: the quantities of [`crate::math::RaySample`] and the opacity.
#[derive(CubeType, Clone, Copy)]
pub struct RayHit {
    /// `e = L d`.
    pub e0: f32,
    pub e1: f32,
    pub e2: f32,
    /// `a = e.e`.
    pub dir_norm_sq: f32,
    /// `gamma`, the ray parameter of the density peak.
    pub peak_depth: f32,
    /// `gamma e - m`.
    pub r0: f32,
    pub r1: f32,
    pub r2: f32,
    /// `I`, the kernel's line integral.
    pub integral: f32,
    /// Alpha before the clamp (`crate::AlphaModel`).
    pub raw_alpha: f32,
    /// Composited opacity, `min(raw_alpha, alpha_max)`.
    pub alpha: f32,
    /// `d raw_alpha / d sigma`.
    pub d_alpha_d_sigma: f32,
    /// `d raw_alpha / d ln(kernel)` (kernel `I`, or `exp(-K/2)` for splat opacity).
    pub d_alpha_d_log_kernel: f32,
    /// 1 when the kernel is `I` (its `-ln(a)/2` term counts in the gradient), else 0.
    pub length_weight: f32,
    /// Whether the Gaussian contributes to the ray at all.
    pub hit: bool,
}

/// The one decision whether splat `base` (in `splats`) contributes to the ray `d`, as
/// `cpu::opacity`: `gamma > 0`, `K <= kernel_cutoff`, `alpha >= alpha_min`.
#[cube]
fn ray_hit(splats: &[f32], base: usize, d0: f32, d1: f32, d2: f32, view: &[f32]) -> RayHit {
    let e0 = splats[base] * d0 + splats[base + 1] * d1 + splats[base + 2] * d2;
    let e1 = splats[base + 3] * d0 + splats[base + 4] * d1 + splats[base + 5] * d2;
    let e2 = splats[base + 6] * d0 + splats[base + 7] * d1 + splats[base + 8] * d2;
    let m0 = splats[base + 9];
    let m1 = splats[base + 10];
    let m2 = splats[base + 11];
    let sigma = splats[base + 12];
    let a = e0 * e0 + e1 * e1 + e2 * e2;
    let gamma = (m0 * e0 + m1 * e1 + m2 * e2) / a;
    let r0 = gamma * e0 - m0;
    let r1 = gamma * e1 - m1;
    let r2 = gamma * e2 - m2;
    let transverse = r0 * r0 + r1 * r1 + r2 * r2;
    let mut hit = false;
    if gamma > 0.0 && transverse <= view[ViewParam::KERNEL_CUTOFF] {
        hit = true;
    }
    let tau = 6.283_185_5f32;
    let kernel = (-0.5f32 * transverse).exp();
    let integral = (tau / a).sqrt() * kernel;
    // Beer-Lambert: alpha = 1 - exp(-sigma I).
    let optical_depth = sigma * integral;
    let transmitted = (-optical_depth).exp();
    let mut raw_alpha = -(-optical_depth).exp_m1();
    let mut d_alpha_d_sigma = transmitted * integral;
    let mut d_alpha_d_log_kernel = transmitted * optical_depth;
    let mut length_weight = 1.0f32;
    if view[ViewParam::ALPHA_MODEL] != 0.0 {
        // Splat opacity: alpha = (1 - exp(-sigma)) exp(-K/2).
        raw_alpha = -(-sigma).exp_m1() * kernel;
        d_alpha_d_sigma = (-sigma).exp() * kernel;
        d_alpha_d_log_kernel = raw_alpha;
        length_weight = 0.0;
    }
    if raw_alpha < view[ViewParam::ALPHA_MIN] {
        hit = false;
    }
    RayHit {
        e0,
        e1,
        e2,
        dir_norm_sq: a,
        peak_depth: gamma,
        r0,
        r1,
        r2,
        integral,
        raw_alpha,
        alpha: raw_alpha.min(view[ViewParam::ALPHA_MAX]),
        d_alpha_d_sigma,
        d_alpha_d_log_kernel,
        length_weight,
        hit,
    }
}

/// Projects every Gaussian into the camera's whitened frame (as `WorldGaussian::view`), bounds
/// the screen tiles its support can touch and counts, per tile, the Gaussians touching it.
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
    let tiles_y = (height + TILE_EDGE - 1) / TILE_EDGE;

    // Unit quaternion and the rotation's columns r_k (axes of the Gaussian).
    let qw = quats[4 * i];
    let qx = quats[4 * i + 1];
    let qy = quats[4 * i + 2];
    let qz = quats[4 * i + 3];
    let inv_norm = 1.0 / (qw * qw + qx * qx + qy * qy + qz * qz).sqrt();
    let w = qw * inv_norm;
    let x = qx * inv_norm;
    let y = qy * inv_norm;
    let z = qz * inv_norm;
    // R row-major; axis k is column k.
    let r00 = 1.0 - 2.0 * (y * y + z * z);
    let r01 = 2.0 * (x * y - w * z);
    let r02 = 2.0 * (x * z + w * y);
    let r10 = 2.0 * (x * y + w * z);
    let r11 = 1.0 - 2.0 * (x * x + z * z);
    let r12 = 2.0 * (y * z - w * x);
    let r20 = 2.0 * (x * z - w * y);
    let r21 = 2.0 * (y * z + w * x);
    let r22 = 1.0 - 2.0 * (x * x + y * y);

    let ls0 = log_scales[3 * i];
    let ls1 = log_scales[3 * i + 1];
    let ls2 = log_scales[3 * i + 2];
    let inv_s0 = (-ls0).exp();
    let inv_s1 = (-ls1).exp();
    let inv_s2 = (-ls2).exp();

    let off0 = means[3 * i] - view[ViewParam::ORIGIN];
    let off1 = means[3 * i + 1] - view[ViewParam::ORIGIN + 1];
    let off2 = means[3 * i + 2] - view[ViewParam::ORIGIN + 2];

    // W r_k: the axes in camera space. w_jk = W_j . r_k.
    let w00 = view[0] * r00 + view[1] * r10 + view[2] * r20;
    let w10 = view[3] * r00 + view[4] * r10 + view[5] * r20;
    let w20 = view[6] * r00 + view[7] * r10 + view[8] * r20;
    let w01 = view[0] * r01 + view[1] * r11 + view[2] * r21;
    let w11 = view[3] * r01 + view[4] * r11 + view[5] * r21;
    let w21 = view[6] * r01 + view[7] * r11 + view[8] * r21;
    let w02 = view[0] * r02 + view[1] * r12 + view[2] * r22;
    let w12 = view[3] * r02 + view[4] * r12 + view[5] * r22;
    let w22 = view[6] * r02 + view[7] * r12 + view[8] * r22;

    let base = i * SPLAT_FLOATS;
    // Row k of L is (W r_k) / s_k.
    splats[base] = w00 * inv_s0;
    splats[base + 1] = w10 * inv_s0;
    splats[base + 2] = w20 * inv_s0;
    splats[base + 3] = w01 * inv_s1;
    splats[base + 4] = w11 * inv_s1;
    splats[base + 5] = w21 * inv_s1;
    splats[base + 6] = w02 * inv_s2;
    splats[base + 7] = w12 * inv_s2;
    splats[base + 8] = w22 * inv_s2;
    // m_k = r_k . (mu - o) / s_k.
    splats[base + 9] = (r00 * off0 + r10 * off1 + r20 * off2) * inv_s0;
    splats[base + 10] = (r01 * off0 + r11 * off1 + r21 * off2) * inv_s1;
    splats[base + 11] = (r02 * off0 + r12 * off1 + r22 * off2) * inv_s2;
    let sigma = softplus(raw_densities[i]);
    splats[base + 12] = sigma;
    splats[base + 13] = colors[3 * i];
    splats[base + 14] = colors[3 * i + 1];
    splats[base + 15] = colors[3 * i + 2];

    // Camera-space centre.
    let mu_x = view[0] * off0 + view[1] * off1 + view[2] * off2;
    let mu_y = view[3] * off0 + view[4] * off1 + view[5] * off2;
    let mu_z = view[6] * off0 + view[7] * off1 + view[8] * off2;
    let depth = -mu_z;
    depths[i] = depth;

    let mut x0 = 0u32;
    let mut x1 = 0u32;
    let mut y0 = 0u32;
    let mut y1 = 0u32;
    let max_log_scale = ls0.max(ls1).max(ls2);
    // Largest transverse term at which alpha_min is still reachable (`cpu::effective_cutoff`).
    let peak = sigma * SQRT_TAU * max_log_scale.exp();
    let mut alpha_bound = 2.0 * (peak / view[ViewParam::MIN_OPTICAL_DEPTH]).ln();
    if view[ViewParam::ALPHA_MODEL] != 0.0 {
        // Splat opacity: alpha = o exp(-K/2) reaches alpha_min while K <= 2 ln(o / alpha_min).
        alpha_bound = 2.0 * (-(-sigma).exp_m1() / view[ViewParam::ALPHA_MIN]).ln();
    }
    let cutoff = view[ViewParam::KERNEL_CUTOFF].min(alpha_bound * 1.001 + 1e-3);
    if depth > view[ViewParam::NEAR_PLANE] && sigma > 0.0 && cutoff > 0.0 {
        // The rays with K <= cutoff are those meeting the ellipsoid
        // (x - mu)^T Sigma^-1 (x - mu) <= cutoff. Its image is bounded by the planes through
        // the camera tangent to it; for image x = s (the plane x + s z = 0) tangency reads
        // A s^2 + 2 B s + C = 0 with A = mu_z^2 - tau S_zz, B = mu_x mu_z - tau S_xz,
        // C = mu_x^2 - tau S_xx, S = M M^T, M = W R S (rows m_x, m_y, m_z). The discriminant is
        // expanded (Lagrange's identity) so no O(mu^4) terms cancel in f32:
        // B^2 - AC = tau (|mu_z m_x - mu_x m_z|^2 - tau |m_x x m_z|^2).
        let s0 = ls0.exp();
        let s1 = ls1.exp();
        let s2 = ls2.exp();
        // Rows of M: m_j = (w_j0 s0, w_j1 s1, w_j2 s2).
        let mx0 = w00 * s0;
        let mx1 = w01 * s1;
        let mx2 = w02 * s2;
        let my0 = w10 * s0;
        let my1 = w11 * s1;
        let my2 = w12 * s2;
        let mz0 = w20 * s0;
        let mz1 = w21 * s1;
        let mz2 = w22 * s2;
        let szz = mz0 * mz0 + mz1 * mz1 + mz2 * mz2;
        let quad_a = mu_z * mu_z - cutoff * szz;

        let mut full = quad_a <= 0.0;

        // Horizontal extent.
        let sxz = mx0 * mz0 + mx1 * mz1 + mx2 * mz2;
        let bx = mu_x * mu_z - cutoff * sxz;
        let vx0 = mu_z * mx0 - mu_x * mz0;
        let vx1 = mu_z * mx1 - mu_x * mz1;
        let vx2 = mu_z * mx2 - mu_x * mz2;
        let cx0 = mx1 * mz2 - mx2 * mz1;
        let cx1 = mx2 * mz0 - mx0 * mz2;
        let cx2 = mx0 * mz1 - mx1 * mz0;
        let disc_x = cutoff
            * ((vx0 * vx0 + vx1 * vx1 + vx2 * vx2) - cutoff * (cx0 * cx0 + cx1 * cx1 + cx2 * cx2));
        // Vertical extent.
        let syz = my0 * mz0 + my1 * mz1 + my2 * mz2;
        let by = mu_y * mu_z - cutoff * syz;
        let vy0 = mu_z * my0 - mu_y * mz0;
        let vy1 = mu_z * my1 - mu_y * mz1;
        let vy2 = mu_z * my2 - mu_y * mz2;
        let cy0 = my1 * mz2 - my2 * mz1;
        let cy1 = my2 * mz0 - my0 * mz2;
        let cy2 = my0 * mz1 - my1 * mz0;
        let disc_y = cutoff
            * ((vy0 * vy0 + vy1 * vy1 + vy2 * vy2) - cutoff * (cy0 * cy0 + cy1 * cy1 + cy2 * cy2));
        if disc_x < 0.0 || disc_y < 0.0 {
            full = true;
        }

        if full {
            x1 = tiles_x;
            y1 = tiles_y;
        } else {
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
            // Pixel centres i + 0.5 within [min, max], with a pixel of slack for rounding;
            // in f32 because the tile grid is small.
            let px0 = (u_min - 1.5).ceil().max(0.0);
            let px1 = (u_max + 0.5).floor().min(f32::cast_from(width) - 1.0);
            let py0 = (v_min - 1.5).ceil().max(0.0);
            let py1 = (v_max + 0.5).floor().min(f32::cast_from(height) - 1.0);
            if px0 <= px1 && py0 <= py1 {
                x0 = u32::cast_from(px0) / TILE_EDGE;
                x1 = u32::cast_from(px1) / TILE_EDGE + 1;
                y0 = u32::cast_from(py0) / TILE_EDGE;
                y1 = u32::cast_from(py1) / TILE_EDGE + 1;
            }
        }
    }
    rects[4 * i] = x0;
    rects[4 * i + 1] = x1;
    rects[4 * i + 2] = y0;
    rects[4 * i + 3] = y1;
    let mut ty = y0;
    while ty < y1 {
        let mut tx = x0;
        while tx < x1 {
            tile_counts[(ty * tiles_x + tx) as usize].fetch_add(1u32);
            tx += 1;
        }
        ty += 1;
    }
}

/// Exclusive prefix sum of the per-tile counts into `offsets` (`num_tiles + 1` entries, the
/// last one the total), in one cube: each unit owns a contiguous chunk of tiles and first sums
/// every count before its chunk itself. That is O(tiles) reads per unit, but the tile grid is
/// small (thousands) and the kernel needs no shared memory or barriers.
#[cube(launch)]
pub fn tile_offsets_kernel(counts: &[u32], offsets: &mut [u32], num_tiles: u32) {
    let units = CUBE_DIM;
    let chunk = (num_tiles + units - 1) / units;
    let begin = (UNIT_POS * chunk).min(num_tiles);
    let end = (begin + chunk).min(num_tiles);
    let mut running = 0u32;
    let mut before = 0u32;
    while before < begin {
        running += counts[before as usize];
        before += 1;
    }
    let mut tile = begin;
    while tile < end {
        offsets[tile as usize] = running;
        running += counts[tile as usize];
        tile += 1;
    }
    if UNIT_POS == units - 1 {
        offsets[num_tiles as usize] = running;
    }
}

/// Writes each visible Gaussian's index into the list of every tile it touches (in arbitrary
/// order within a tile; [`sort_tiles_kernel`] makes it deterministic).
#[cube(launch)]
pub fn fill_tiles_kernel(
    rects: &[u32],
    offsets: &[u32],
    cursors: &mut [Atomic<u32>],
    list: &mut [u32],
    num_gaussians: u32,
    width: u32,
) {
    let i = ABSOLUTE_POS;
    if i >= num_gaussians as usize {
        terminate!();
    }
    let tiles_x = (width + TILE_EDGE - 1) / TILE_EDGE;
    let x0 = rects[4 * i];
    let x1 = rects[4 * i + 1];
    let y0 = rects[4 * i + 2];
    let y1 = rects[4 * i + 3];
    let mut ty = y0;
    while ty < y1 {
        let mut tx = x0;
        while tx < x1 {
            let tile = (ty * tiles_x + tx) as usize;
            let slot = cursors[tile].fetch_add(1u32);
            list[(offsets[tile] + slot) as usize] = i as u32;
            tx += 1;
        }
        ty += 1;
    }
}

/// Whether list entry `a` must come after entry `b`: by centre depth, then index, as the CPU
/// path orders them.
#[cube]
fn after(depths: &[f32], a: u32, b: u32) -> bool {
    let da = depths[a as usize];
    let db = depths[b as usize];
    da > db || (da == db && a > b)
}

/// One comparator of the sorting network: puts list entries `a < b` of the tile starting at
/// `start` in order. `b` past the list's end is virtual +infinity padding, already in place.
#[cube]
fn order_pair(depths: &[f32], list: &mut [u32], start: u32, a: u32, b: u32, len: u32) {
    if b < len {
        let ia = list[(start + a) as usize];
        let ib = list[(start + b) as usize];
        if after(depths, ia, ib) {
            list[(start + a) as usize] = ib;
            list[(start + b) as usize] = ia;
        }
    }
}

/// Sorts each tile's list in place, one cube per tile, with a bitonic network in its
/// "flip" form: every sub-block is sorted ascending, so the list can be padded virtually to a
/// power of two with +infinity and comparisons against the padding skipped.
#[cube(launch)]
pub fn sort_tiles_kernel(depths: &[f32], offsets: &[u32], list: &mut [u32]) {
    let tile = CUBE_POS;
    let start = offsets[tile];
    let len = offsets[tile + 1] - start;
    let mut padded = 1u32;
    while padded < len {
        padded *= 2;
    }
    let pairs = padded / 2;
    let mut size = 2u32;
    while size <= padded {
        // Flip: compare i with its mirror in the block of `size`.
        let half = size / 2;
        let mut p = UNIT_POS;
        while p < pairs {
            let block = p / half;
            let pos = p % half;
            let a = block * size + pos;
            let b = block * size + size - 1 - pos;
            order_pair(depths, list, start, a, b, len);
            p += CUBE_DIM;
        }
        sync_storage();
        // Half-cleaners.
        let mut stride = half / 2;
        while stride > 0 {
            let mut p = UNIT_POS;
            while p < pairs {
                let a = (p / stride) * 2 * stride + p % stride;
                order_pair(depths, list, start, a, a + stride, len);
                p += CUBE_DIM;
            }
            sync_storage();
            stride /= 2;
        }
        size *= 2;
    }
}

/// Composites each pixel of a tile front to back (one cube per tile, one unit per pixel).
/// Gaussians are staged through shared memory in batches of [`TILE_THREADS`]; the tile stops
/// early once every pixel has reached `transmittance_min`. Output per pixel: RGB over the
/// background, final transmittance, number of list entries walked (as `cpu::render_tile`).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn rasterize_kernel(
    splats: &[f32],
    offsets: &[u32],
    list: &[u32],
    view: &[f32],
    background: &[f32],
    output: &mut [f32],
    width: u32,
    height: u32,
) {
    let tiles_x = (width + TILE_EDGE - 1) / TILE_EDGE;
    let tile = (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize;
    let px = CUBE_POS_X * TILE_EDGE + UNIT_POS_X;
    let py = CUBE_POS_Y * TILE_EDGE + UNIT_POS_Y;
    let inside = px < width && py < height;
    let (d0, d1, d2) = pixel_direction(view, px, py);

    let mut batch = Shared::<[f32]>::new_slice(TILE_THREADS * SPLAT_FLOATS);
    let finished = Shared::<[Atomic<u32>]>::new_slice(1usize);
    if UNIT_POS == 0 {
        finished[0].store(0u32);
    }
    sync_cube();
    let mut done = !inside;
    if done {
        finished[0].fetch_add(1u32);
    }

    let start = offsets[tile];
    let len = offsets[tile + 1] - start;
    let num_batches = (len + TILE_THREADS as u32 - 1) / TILE_THREADS as u32;
    let transmittance_min = view[ViewParam::TRANSMITTANCE_MIN];

    let mut transmittance = 1.0f32;
    let mut red = 0.0f32;
    let mut green = 0.0f32;
    let mut blue = 0.0f32;
    let mut walked = 0u32;

    let mut b = 0u32;
    while b < num_batches {
        sync_cube();
        // Uniform across the cube: nobody finishes between the barrier above and the one below.
        let finished_now = workgroup_uniform_load_atomic(&finished[0]);
        if finished_now >= CUBE_DIM {
            break;
        }
        let first = b * TILE_THREADS as u32;
        let k = first + UNIT_POS;
        if k < len {
            let gaussian = list[(start + k) as usize] as usize;
            let src = gaussian * SPLAT_FLOATS;
            let dst = UNIT_POS as usize * SPLAT_FLOATS;
            #[unroll]
            for f in 0..SPLAT_FLOATS {
                batch[dst + f] = splats[src + f];
            }
        }
        sync_cube();
        if !done {
            let count = (len - first).min(TILE_THREADS as u32);
            let mut j = 0u32;
            while j < count {
                let base = j as usize * SPLAT_FLOATS;
                let hit = ray_hit(&batch, base, d0, d1, d2, view);
                if hit.hit {
                    let next = transmittance * (1.0 - hit.alpha);
                    if next < transmittance_min {
                        done = true;
                        finished[0].fetch_add(1u32);
                        break;
                    }
                    let weight = transmittance * hit.alpha;
                    red += weight * batch[base + 13];
                    green += weight * batch[base + 14];
                    blue += weight * batch[base + 15];
                    transmittance = next;
                    walked = first + j + 1;
                }
                j += 1;
            }
        }
        b += 1;
    }

    if inside {
        let out = ((py * width + px) * 5) as usize;
        output[out] = red + transmittance * background[0];
        output[out + 1] = green + transmittance * background[1];
        output[out + 2] = blue + transmittance * background[2];
        output[out + 3] = transmittance;
        output[out + 4] = f32::cast_from(walked);
    }
}

/// How the backward pass adds floats into the per-Gaussian gradient buffer: a native
/// `f32` atomic add where the device has one, else a compare-and-swap loop on the bits.
#[cube]
pub trait GradientAdd: Send + Sync + 'static {
    type Cell: Numeric;
    fn add(cells: &mut [Atomic<Self::Cell>], index: usize, value: f32);
}

/// Native `f32` atomic add.
#[derive(CubeType)]
pub struct NativeAdd;

/// Compare-and-swap on the `u32` bits of an `f32`.
#[derive(CubeType)]
pub struct CasAdd;

#[cube]
impl GradientAdd for NativeAdd {
    type Cell = f32;
    fn add(cells: &mut [Atomic<f32>], index: usize, value: f32) {
        cells[index].fetch_add(value);
    }
}

#[cube]
impl GradientAdd for CasAdd {
    type Cell = u32;
    fn add(cells: &mut [Atomic<u32>], index: usize, value: f32) {
        if value != 0.0 {
            let mut current = cells[index].load();
            loop {
                let expected = current;
                let updated = (f32::from_bits(expected) + value).to_bits();
                current = cells[index].compare_exchange_weak(expected, updated);
                if current == expected {
                    break;
                }
            }
        }
    }
}

/// Back-to-front replay of each pixel of a tile (one cube per tile) from its final
/// transmittance, as `cpu::backward_tile`, adding each Gaussian's gradient with respect to its
/// splat (`L`, `m`, `sigma`, colour; [`SPLAT_FLOATS`] per Gaussian) into `splat_grads`.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward_kernel<A: GradientAdd>(
    splats: &[f32],
    offsets: &[u32],
    list: &[u32],
    view: &[f32],
    background: &[f32],
    output: &[f32],
    grad_output: &[f32],
    splat_grads: &mut [Atomic<A::Cell>],
    width: u32,
    height: u32,
) {
    let tiles_x = (width + TILE_EDGE - 1) / TILE_EDGE;
    let tile = (CUBE_POS_Y * tiles_x + CUBE_POS_X) as usize;
    let px = CUBE_POS_X * TILE_EDGE + UNIT_POS_X;
    let py = CUBE_POS_Y * TILE_EDGE + UNIT_POS_Y;
    let inside = px < width && py < height;
    let (d0, d1, d2) = pixel_direction(view, px, py);

    let mut batch = Shared::<[f32]>::new_slice(TILE_THREADS * SPLAT_FLOATS);
    let mut batch_ids = Shared::<[u32]>::new_slice(TILE_THREADS);

    let mut walked = 0u32;
    let mut final_t = 1.0f32;
    let mut grad_r = 0.0f32;
    let mut grad_g = 0.0f32;
    let mut grad_b = 0.0f32;
    let mut grad_final_t = 0.0f32;
    if inside {
        let pixel = ((py * width + px) * 5) as usize;
        final_t = output[pixel + 3];
        walked = u32::cast_from(output[pixel + 4]);
        grad_r = grad_output[pixel];
        grad_g = grad_output[pixel + 1];
        grad_b = grad_output[pixel + 2];
        grad_final_t = grad_output[pixel + 3];
    }

    // Every pixel walked at most the whole list; entries past a pixel's own count are skipped.
    let start = offsets[tile];
    let tile_walked = offsets[tile + 1] - start;
    let num_batches = (tile_walked + TILE_THREADS as u32 - 1) / TILE_THREADS as u32;
    let alpha_max = view[ViewParam::ALPHA_MAX];

    // Colour composited behind the current Gaussian, background included.
    let mut behind_r = background[0] * final_t;
    let mut behind_g = background[1] * final_t;
    let mut behind_b = background[2] * final_t;
    let mut transmittance_after = final_t;

    let mut bi = 0u32;
    while bi < num_batches {
        let b = num_batches - 1 - bi;
        let first = b * TILE_THREADS as u32;
        sync_cube();
        let k = first + UNIT_POS;
        if k < tile_walked {
            let gaussian = list[(start + k) as usize];
            batch_ids[UNIT_POS as usize] = gaussian;
            let src = gaussian as usize * SPLAT_FLOATS;
            let dst = UNIT_POS as usize * SPLAT_FLOATS;
            #[unroll]
            for f in 0..SPLAT_FLOATS {
                batch[dst + f] = splats[src + f];
            }
        }
        sync_cube();
        let count = (tile_walked - first).min(TILE_THREADS as u32);
        let mut jj = 0u32;
        while jj < count {
            let j = count - 1 - jj;
            if first + j < walked {
                let base = j as usize * SPLAT_FLOATS;
                let hit = ray_hit(&batch, base, d0, d1, d2, view);
                if hit.hit {
                    let one_minus = 1.0 - hit.alpha;
                    let transmittance_before = transmittance_after / one_minus;
                    let out = batch_ids[j as usize] as usize * SPLAT_FLOATS;
                    let cr = batch[base + 13];
                    let cg = batch[base + 14];
                    let cb = batch[base + 15];
                    let weight = transmittance_before * hit.alpha;
                    A::add(splat_grads, out + 13, grad_r * weight);
                    A::add(splat_grads, out + 14, grad_g * weight);
                    A::add(splat_grads, out + 15, grad_b * weight);
                    let grad_alpha = -grad_final_t * final_t / one_minus
                        + grad_r * (transmittance_before * cr - behind_r / one_minus)
                        + grad_g * (transmittance_before * cg - behind_g / one_minus)
                        + grad_b * (transmittance_before * cb - behind_b / one_minus);
                    behind_r += weight * cr;
                    behind_g += weight * cg;
                    behind_b += weight * cb;
                    transmittance_after = transmittance_before;
                    if hit.raw_alpha < alpha_max {
                        A::add(splat_grads, out + 12, grad_alpha * hit.d_alpha_d_sigma);
                        // d lnI/de = -e/a - gamma r, d lnI/dm = r (`math::sample_vjp`); the
                        // splat kernel exp(-K/2) has no -e/a term (length_weight 0).
                        let g_ln = grad_alpha * hit.d_alpha_d_log_kernel;
                        let lw = hit.length_weight / hit.dir_norm_sq;
                        let ge0 = g_ln * (-hit.e0 * lw - hit.peak_depth * hit.r0);
                        let ge1 = g_ln * (-hit.e1 * lw - hit.peak_depth * hit.r1);
                        let ge2 = g_ln * (-hit.e2 * lw - hit.peak_depth * hit.r2);
                        A::add(splat_grads, out, ge0 * d0);
                        A::add(splat_grads, out + 1, ge0 * d1);
                        A::add(splat_grads, out + 2, ge0 * d2);
                        A::add(splat_grads, out + 3, ge1 * d0);
                        A::add(splat_grads, out + 4, ge1 * d1);
                        A::add(splat_grads, out + 5, ge1 * d2);
                        A::add(splat_grads, out + 6, ge2 * d0);
                        A::add(splat_grads, out + 7, ge2 * d1);
                        A::add(splat_grads, out + 8, ge2 * d2);
                        A::add(splat_grads, out + 9, g_ln * hit.r0);
                        A::add(splat_grads, out + 10, g_ln * hit.r1);
                        A::add(splat_grads, out + 11, g_ln * hit.r2);
                    }
                }
            }
            jj += 1;
        }
        bi += 1;
    }
}

/// Gradient of one rotation axis of a Gaussian (see [`axis_backward`]).
#[derive(CubeType, Clone, Copy)]
pub struct AxisGrad {
    /// dLoss/dR[l][k] for l = 0, 1, 2.
    pub rotation0: f32,
    pub rotation1: f32,
    pub rotation2: f32,
    pub log_scale: f32,
    /// This axis's share of dLoss/dmu.
    pub mean0: f32,
    pub mean1: f32,
    pub mean2: f32,
}

/// Gradient through axis `k` (`a`, a column of R) of one Gaussian: `L_k = W a / s_k`,
/// `m_k = a . (mu - o) / s_k`. Returns dLoss/da (3), dLoss/d log s_k, and the axis's share of
/// dLoss/dmu (3).
#[cube]
#[allow(clippy::too_many_arguments)]
fn axis_backward(
    splat_grads: &[f32],
    g: usize,
    k: usize,
    view: &[f32],
    a0: f32,
    a1: f32,
    a2: f32,
    off0: f32,
    off1: f32,
    off2: f32,
    log_scale: f32,
) -> AxisGrad {
    let inv_s = (-log_scale).exp();
    let gl0 = splat_grads[g + 3 * k];
    let gl1 = splat_grads[g + 3 * k + 1];
    let gl2 = splat_grads[g + 3 * k + 2];
    let gc = splat_grads[g + 9 + k];
    let l0 = (view[0] * a0 + view[1] * a1 + view[2] * a2) * inv_s;
    let l1 = (view[3] * a0 + view[4] * a1 + view[5] * a2) * inv_s;
    let l2 = (view[6] * a0 + view[7] * a1 + view[8] * a2) * inv_s;
    let center_k = (a0 * off0 + a1 * off1 + a2 * off2) * inv_s;
    let grad_log_scale = -(gl0 * l0 + gl1 * l1 + gl2 * l2) - gc * center_k;
    // (W^T gL_k)_l + gc (mu - o)_l, over s_k.
    let ga0 = (view[0] * gl0 + view[3] * gl1 + view[6] * gl2 + gc * off0) * inv_s;
    let ga1 = (view[1] * gl0 + view[4] * gl1 + view[7] * gl2 + gc * off1) * inv_s;
    let ga2 = (view[2] * gl0 + view[5] * gl1 + view[8] * gl2 + gc * off2) * inv_s;
    AxisGrad {
        rotation0: ga0,
        rotation1: ga1,
        rotation2: ga2,
        log_scale: grad_log_scale,
        mean0: gc * a0 * inv_s,
        mean1: gc * a1 * inv_s,
        mean2: gc * a2 * inv_s,
    }
}

/// Chains each Gaussian's splat gradient back to its world-space parameters
/// (`math::view_vjp`): one unit per Gaussian.
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn view_backward_kernel(
    means: &[f32],
    quats: &[f32],
    log_scales: &[f32],
    raw_densities: &[f32],
    view: &[f32],
    splat_grads: &[f32],
    grad_means: &mut [f32],
    grad_quats: &mut [f32],
    grad_log_scales: &mut [f32],
    grad_raw_densities: &mut [f32],
    grad_colors: &mut [f32],
    num_gaussians: u32,
) {
    let i = ABSOLUTE_POS;
    if i >= num_gaussians as usize {
        terminate!();
    }
    let g = i * SPLAT_FLOATS;
    grad_raw_densities[i] = splat_grads[g + 12] * softplus_grad(raw_densities[i]);
    grad_colors[3 * i] = splat_grads[g + 13];
    grad_colors[3 * i + 1] = splat_grads[g + 14];
    grad_colors[3 * i + 2] = splat_grads[g + 15];

    let qw = quats[4 * i];
    let qx = quats[4 * i + 1];
    let qy = quats[4 * i + 2];
    let qz = quats[4 * i + 3];
    let norm = (qw * qw + qx * qx + qy * qy + qz * qz).sqrt();
    let w = qw / norm;
    let x = qx / norm;
    let y = qy / norm;
    let z = qz / norm;
    let r00 = 1.0 - 2.0 * (y * y + z * z);
    let r01 = 2.0 * (x * y - w * z);
    let r02 = 2.0 * (x * z + w * y);
    let r10 = 2.0 * (x * y + w * z);
    let r11 = 1.0 - 2.0 * (x * x + z * z);
    let r12 = 2.0 * (y * z - w * x);
    let r20 = 2.0 * (x * z - w * y);
    let r21 = 2.0 * (y * z + w * x);
    let r22 = 1.0 - 2.0 * (x * x + y * y);
    let off0 = means[3 * i] - view[ViewParam::ORIGIN];
    let off1 = means[3 * i + 1] - view[ViewParam::ORIGIN + 1];
    let off2 = means[3 * i + 2] - view[ViewParam::ORIGIN + 2];

    // Axis k of the rotation is its column k.
    let ls = 3 * i;
    let axis0 = axis_backward(
        splat_grads,
        g,
        0usize,
        view,
        r00,
        r10,
        r20,
        off0,
        off1,
        off2,
        log_scales[ls],
    );
    let axis1 = axis_backward(
        splat_grads,
        g,
        1usize,
        view,
        r01,
        r11,
        r21,
        off0,
        off1,
        off2,
        log_scales[ls + 1],
    );
    let axis2 = axis_backward(
        splat_grads,
        g,
        2usize,
        view,
        r02,
        r12,
        r22,
        off0,
        off1,
        off2,
        log_scales[ls + 2],
    );
    grad_log_scales[ls] = axis0.log_scale;
    grad_log_scales[ls + 1] = axis1.log_scale;
    grad_log_scales[ls + 2] = axis2.log_scale;
    let gm0 = axis0.mean0 + axis1.mean0 + axis2.mean0;
    let gm1 = axis0.mean1 + axis1.mean1 + axis2.mean1;
    let gm2 = axis0.mean2 + axis1.mean2 + axis2.mean2;
    let gr00 = axis0.rotation0;
    let gr10 = axis0.rotation1;
    let gr20 = axis0.rotation2;
    let gr01 = axis1.rotation0;
    let gr11 = axis1.rotation1;
    let gr21 = axis1.rotation2;
    let gr02 = axis2.rotation0;
    let gr12 = axis2.rotation1;
    let gr22 = axis2.rotation2;
    grad_means[3 * i] = gm0;
    grad_means[3 * i + 1] = gm1;
    grad_means[3 * i + 2] = gm2;

    // `math::quat_to_rotation_vjp` with g[l][k] = gr_lk = dLoss/dR[l][k].
    let gw = -z * gr01 + y * gr02 + z * gr10 - x * gr12 - y * gr20 + x * gr21;
    let gx = y * gr01 + z * gr02 + y * gr10 - 2.0 * x * gr11 - w * gr12 + z * gr20 + w * gr21
        - 2.0 * x * gr22;
    let gy = -2.0f32 * y * gr00 + x * gr01 + w * gr02 + x * gr10 + z * gr12 - w * gr20 + z * gr21
        - 2.0 * y * gr22;
    let gz = -2.0f32 * z * gr00 - w * gr01 + x * gr02 + w * gr10 - 2.0 * z * gr11
        + y * gr12
        + x * gr20
        + y * gr21;
    let unit_w = 2.0 * gw;
    let unit_x = 2.0 * gx;
    let unit_y = 2.0 * gy;
    let unit_z = 2.0 * gz;
    // `math::normalize_vjp`.
    let radial = w * unit_w + x * unit_x + y * unit_y + z * unit_z;
    grad_quats[4 * i] = (unit_w - w * radial) / norm;
    grad_quats[4 * i + 1] = (unit_x - x * radial) / norm;
    grad_quats[4 * i + 2] = (unit_y - y * radial) / norm;
    grad_quats[4 * i + 3] = (unit_z - z * radial) / norm;
}

/// Gradient of the background colour: `sum over pixels of dLoss/dC * T_final`, reduced in one
/// cube (a strided partial sum per unit, then a tree in shared memory), so the order is fixed.
#[cube(launch)]
pub fn background_grad_kernel(
    output: &[f32],
    grad_output: &[f32],
    grad_background: &mut [f32],
    num_pixels: u32,
) {
    let mut partial = Shared::<[f32]>::new_slice(3 * TILE_THREADS);
    let unit = UNIT_POS as usize;
    let mut red = 0.0f32;
    let mut green = 0.0f32;
    let mut blue = 0.0f32;
    let mut p = UNIT_POS;
    while p < num_pixels {
        let base = (p * 5) as usize;
        let final_t = output[base + 3];
        red += grad_output[base] * final_t;
        green += grad_output[base + 1] * final_t;
        blue += grad_output[base + 2] * final_t;
        p += CUBE_DIM;
    }
    partial[3 * unit] = red;
    partial[3 * unit + 1] = green;
    partial[3 * unit + 2] = blue;
    sync_cube();
    // A runtime stride: a compile-time one here trips cubecl's IR verifier.
    let mut stride = CUBE_DIM / 2;
    while stride > 0 {
        if UNIT_POS < stride {
            let mine = 3 * unit;
            let other = 3 * (unit + stride as usize);
            let red = partial[mine] + partial[other];
            let green = partial[mine + 1] + partial[other + 1];
            let blue = partial[mine + 2] + partial[other + 2];
            partial[mine] = red;
            partial[mine + 1] = green;
            partial[mine + 2] = blue;
        }
        sync_cube();
        stride /= 2;
    }
    if unit == 0 {
        grad_background[0] = partial[0];
        grad_background[1] = partial[1];
        grad_background[2] = partial[2];
    }
}

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
    let mut bad_parts = Shared::<[u32]>::new_slice(TILE_THREADS);
    let mut min_norm = Shared::<[f32]>::new_slice(TILE_THREADS);
    let mut max_scale = Shared::<[f32]>::new_slice(TILE_THREADS);
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
