//! What the rasterizer's kernels share: a projected Gaussian ([`Splat`]), the view buffer
//! ([`ViewParam`]), and the one decision whether a splat contributes to a ray ([`ray_hit`]).
//!
//! Buffers are flat f32: a splat is [`SPLAT_FLOATS`] floats, the view [`VIEW_FLOATS`]. The
//! per-ray maths mirrors [`crate::math`] and `cpu::composite` line for line.

use cubecl::prelude::*;
use gausmoke_core::Camera;

use super::math::{Mat3, Vec3, Whitening};
use crate::{AlphaModel, RasterOptions};

/// Floats per projected Gaussian: `L` (9, row-major), `m` (3), `sigma`, the colour (3).
pub const SPLAT_FLOATS: usize = 16;

/// A Gaussian as one camera sees it (`math::ViewSplat`).
#[derive(CubeType, Clone, Copy)]
pub struct Splat {
    pub whitening: Whitening,
    /// `softplus(raw density)`.
    pub sigma: f32,
    pub color: Vec3,
}

#[cube]
impl Splat {
    /// Splat `index` of `buffer`.
    pub fn load(buffer: &[f32], index: usize) -> Splat {
        let base = index * SPLAT_FLOATS;
        Splat {
            whitening: Whitening {
                whiten: Mat3::load(buffer, base),
                center: Vec3::load(buffer, base + 9),
            },
            sigma: buffer[base + 12],
            color: Vec3::load(buffer, base + 13),
        }
    }

    pub fn store(&self, buffer: &mut [f32], index: usize) {
        let base = index * SPLAT_FLOATS;
        self.whitening.whiten.store(buffer, base);
        self.whitening.center.store(buffer, base + 9);
        buffer[base + 12] = self.sigma;
        self.color.store(buffer, base + 13);
    }
}

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

/// The view as the kernels read it (see [`ViewParam`]).
pub fn view_params(camera: &Camera, options: &RasterOptions) -> [f32; VIEW_FLOATS] {
    let mut params = [0.0f32; VIEW_FLOATS];
    let w2c = camera.rotation_world_to_camera();
    // glam is column-major: row i of W is (x_axis[i], y_axis[i], z_axis[i]).
    for (row, slot) in [0usize, 1, 2].iter().zip([0usize, 3, 6]) {
        params[ViewParam::ROTATION + slot] = w2c.x_axis[*row];
        params[ViewParam::ROTATION + slot + 1] = w2c.y_axis[*row];
        params[ViewParam::ROTATION + slot + 2] = w2c.z_axis[*row];
    }
    let origin = camera.position();
    params[ViewParam::ORIGIN..ViewParam::ORIGIN + 3].copy_from_slice(&origin.to_array());
    let k = camera.intrinsics();
    params[ViewParam::FX] = k.fx;
    params[ViewParam::FY] = k.fy;
    params[ViewParam::CX] = k.cx;
    params[ViewParam::CY] = k.cy;
    params[ViewParam::ALPHA_MIN] = options.alpha_min;
    params[ViewParam::ALPHA_MAX] = options.alpha_max;
    params[ViewParam::TRANSMITTANCE_MIN] = options.transmittance_min;
    params[ViewParam::KERNEL_CUTOFF] = options.kernel_cutoff;
    params[ViewParam::NEAR_PLANE] = options.near_plane;
    params[ViewParam::MIN_OPTICAL_DEPTH] = -(1.0 - options.alpha_min).ln();
    params[ViewParam::ALPHA_MODEL] = match options.alpha_model {
        AlphaModel::BeerLambert => 0.0,
        AlphaModel::SplatOpacity => 1.0,
    };
    params
}

/// The world-to-camera rotation and the camera centre of the view buffer.
#[cube]
pub fn view_pose(view: &[f32]) -> (Mat3, Vec3) {
    (
        Mat3::load(view, ViewParam::ROTATION),
        Vec3::load(view, ViewParam::ORIGIN),
    )
}

/// Unit camera-space direction of the ray through the centre of pixel `(px, py)`.
#[cube]
pub fn pixel_direction(view: &[f32], px: u32, py: u32) -> Vec3 {
    let x = (f32::cast_from(px) + 0.5 - view[ViewParam::CX]) / view[ViewParam::FX];
    let y = -(f32::cast_from(py) + 0.5 - view[ViewParam::CY]) / view[ViewParam::FY];
    let inv_len = 1.0 / (x * x + y * y + 1.0).sqrt();
    Vec3::new(x * inv_len, y * inv_len, -inv_len)
}

/// One splat on one ray: the quantities of `math::RaySample` and the opacity.
#[derive(CubeType, Clone, Copy)]
pub struct RayHit {
    /// `e = L d`.
    pub dir_whitened: Vec3,
    /// `a = e.e`.
    pub dir_norm_sq: f32,
    /// `gamma`, the ray parameter of the density peak.
    pub peak_depth: f32,
    /// `gamma e - m`.
    pub residual: Vec3,
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
    /// Whether the splat contributes to the ray at all.
    pub hit: bool,
}

/// The one decision whether `splat` contributes to the ray `d`, as `cpu::composite::opacity`:
/// `gamma > 0`, `K <= kernel_cutoff`, `alpha >= alpha_min`.
#[cube]
pub fn ray_hit(splat: &Splat, d: &Vec3, view: &[f32]) -> RayHit {
    let e = splat.whitening.whiten.mul(d);
    let a = e.dot(&e);
    let gamma = splat.whitening.center.dot(&e) / a;
    let residual = e.scale(gamma).sub(&splat.whitening.center);
    let transverse = residual.dot(&residual);
    let mut hit = false;
    if gamma > 0.0 && transverse <= view[ViewParam::KERNEL_CUTOFF] {
        hit = true;
    }
    let tau = 6.283_185_5f32;
    let kernel = (-0.5f32 * transverse).exp();
    let integral = (tau / a).sqrt() * kernel;
    let sigma = splat.sigma;
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
        dir_whitened: e,
        dir_norm_sq: a,
        peak_depth: gamma,
        residual,
        raw_alpha,
        alpha: raw_alpha.min(view[ViewParam::ALPHA_MAX]),
        d_alpha_d_sigma,
        d_alpha_d_log_kernel,
        length_weight,
        hit,
    }
}
