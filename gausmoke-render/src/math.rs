//! Per-Gaussian and per-ray maths of the Beer-Lambert renderer, with each gradient beside the
//! function it differentiates. Plain f32 so the CPU path and the kernels share one definition.
//!
//! # Whitened formulation of Appendix B
//!
//! With `Sigma = R S S^T R^T`, the whitening map `x -> S^-1 R^T (x - mu)` turns the Gaussian
//! into a unit isotropic one. A ray `o + t d` (unit `d`) becomes `t e - m` with `e = L d`,
//! `L = S^-1 R^T` and `m = S^-1 R^T (mu - o)`. Then, exactly as in Eq. 25-26,
//!
//! * `d^T Sigma^-1 d = e.e = a`, so `beta = 1 / sqrt(a)`;
//! * `gamma = (m.e) / a` is the ray parameter of the density peak;
//! * `K = |gamma e - m|^2`, the squared Mahalanobis distance from the centre to the ray.
//!
//! Computing `K` as the norm of a residual instead of `c - b^2 / a` avoids the catastrophic
//! cancellation that the textbook form suffers in f32 for small Gaussians far from the camera.

// Small fixed-size loops index several 3-vectors and matrices at once; an index reads best.
#![allow(clippy::needless_range_loop)]

use std::f32::consts::TAU;

use crate::gaussians::Gaussian;

/// Softplus with the same large-input cut-over as torch (`x > 20` returns `x`).
#[inline]
pub fn softplus(x: f32) -> f32 {
    if x > 20.0 { x } else { x.exp().ln_1p() }
}

/// Derivative of [`softplus`].
#[inline]
pub fn softplus_grad(x: f32) -> f32 {
    if x > 20.0 {
        1.0
    } else {
        1.0 / (1.0 + (-x).exp())
    }
}

/// Rotation matrix (row-major) of a unit quaternion `(w, x, y, z)`.
#[inline]
pub fn quat_to_rotation(q: [f32; 4]) -> [[f32; 3]; 3] {
    let [w, x, y, z] = q;
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// Gradient with respect to the unit quaternion of `L(quat_to_rotation(q))`, given `dL/dR`.
#[inline]
pub fn quat_to_rotation_vjp(q: [f32; 4], g: [[f32; 3]; 3]) -> [f32; 4] {
    let [w, x, y, z] = q;
    let gw = -z * g[0][1] + y * g[0][2] + z * g[1][0] - x * g[1][2] - y * g[2][0] + x * g[2][1];
    let gx = y * g[0][1] + z * g[0][2] + y * g[1][0] - 2.0 * x * g[1][1] - w * g[1][2]
        + z * g[2][0]
        + w * g[2][1]
        - 2.0 * x * g[2][2];
    let gy = -2.0 * y * g[0][0] + x * g[0][1] + w * g[0][2] + x * g[1][0] + z * g[1][2]
        - w * g[2][0]
        + z * g[2][1]
        - 2.0 * y * g[2][2];
    let gz = -2.0 * z * g[0][0] - w * g[0][1] + x * g[0][2] + w * g[1][0] - 2.0 * z * g[1][1]
        + y * g[1][2]
        + x * g[2][0]
        + y * g[2][1];
    [2.0 * gw, 2.0 * gx, 2.0 * gy, 2.0 * gz]
}

/// Gradient with respect to the raw quaternion `q` of a loss of `q / |q|`, given the gradient
/// `g` with respect to the normalised quaternion `n`.
#[inline]
pub fn normalize_vjp(n: [f32; 4], norm: f32, g: [f32; 4]) -> [f32; 4] {
    let dot = n[0] * g[0] + n[1] * g[1] + n[2] * g[2] + n[3] * g[3];
    [
        (g[0] - n[0] * dot) / norm,
        (g[1] - n[1] * dot) / norm,
        (g[2] - n[2] * dot) / norm,
        (g[3] - n[3] * dot) / norm,
    ]
}

#[inline]
pub fn dot3(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// A Gaussian as one camera sees it: what the per-pixel loop needs, and nothing else.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ViewSplat {
    /// Whitening matrix `L = S^-1 R^T W^T` (row-major), taking camera-space directions into
    /// the Gaussian's isotropic frame (`W` is the world-to-camera rotation).
    pub whiten: [[f32; 3]; 3],
    /// Whitened centre `m = S^-1 R^T (mu - o)` relative to the camera centre `o`.
    pub center: [f32; 3],
    /// Physical density coefficient `sigma_i = softplus(raw) >= 0` (per world unit).
    pub sigma: f32,
    pub color: [f32; 3],
}

/// The Gaussian's line integral along one ray and everything its gradient reuses.
#[derive(Debug, Clone, Copy)]
pub struct RaySample {
    /// `e = L d`.
    pub dir_whitened: [f32; 3],
    /// `a = e.e = 1 / beta^2`.
    pub dir_norm_sq: f32,
    /// `gamma`, the ray parameter of the density peak.
    pub peak_depth: f32,
    /// `gamma e - m`; its squared norm is the transverse term `K`.
    pub residual: [f32; 3],
    /// `K` of Eq. 26.
    pub transverse: f32,
    /// `I = sqrt(2 pi) beta exp(-K / 2)`: the Gaussian kernel integrated along the ray.
    pub integral: f32,
}

impl ViewSplat {
    /// Line integral of this Gaussian along the unit camera-space direction `dir`, or `None`
    /// where the ray misses its `cutoff` support (`K > cutoff`) or its peak lies behind the
    /// camera (`gamma <= 0`).
    #[inline]
    pub fn sample(&self, dir: [f32; 3], cutoff: f32) -> Option<RaySample> {
        let l = &self.whiten;
        let e = [dot3(l[0], dir), dot3(l[1], dir), dot3(l[2], dir)];
        let a = dot3(e, e);
        let gamma = dot3(self.center, e) / a;
        if gamma <= 0.0 {
            return None;
        }
        let r = [
            gamma * e[0] - self.center[0],
            gamma * e[1] - self.center[1],
            gamma * e[2] - self.center[2],
        ];
        let k = dot3(r, r);
        if k > cutoff {
            return None;
        }
        Some(RaySample {
            dir_whitened: e,
            dir_norm_sq: a,
            peak_depth: gamma,
            residual: r,
            transverse: k,
            integral: (TAU / a).sqrt() * (-0.5 * k).exp(),
        })
    }
}

/// Gradient of a loss with respect to `L` and `m` of one [`ViewSplat`], given the loss's
/// gradient with respect to `ln I` (`grad_log_integral`) for one ray, accumulated into
/// `grad_whiten` / `grad_center`.
///
/// `ln I = ln sqrt(2 pi) - ln(a) / 2 - K / 2`, whence `d lnI / de = -e / a - gamma r` and
/// `d lnI / dm = r`; `e = L d` gives `dLoss/dL += (dLoss/de) d^T`. With
/// `length_weight = 0` only the `-K / 2` part is differentiated: the gradient of the projected
/// kernel `ln exp(-K / 2)` used by [`crate::AlphaModel::SplatOpacity`].
#[inline]
pub fn sample_vjp(
    s: &RaySample,
    dir: [f32; 3],
    grad_log_integral: f32,
    length_weight: f32,
    grad_whiten: &mut [[f32; 3]; 3],
    grad_center: &mut [f32; 3],
) {
    let g_ln = grad_log_integral;
    for k in 0..3 {
        let g_e = g_ln
            * (-length_weight * s.dir_whitened[k] / s.dir_norm_sq - s.peak_depth * s.residual[k]);
        for j in 0..3 {
            grad_whiten[k][j] += g_e * dir[j];
        }
        grad_center[k] += g_ln * s.residual[k];
    }
}

/// Quantities of [`Gaussian::view`] that its gradient reuses.
#[derive(Debug, Clone, Copy)]
pub struct ViewContext {
    pub unit_quat: [f32; 4],
    pub quat_norm: f32,
    /// Columns `r_k` of the rotation, stored as rows: `axes[k] = R e_k`.
    pub axes: [[f32; 3]; 3],
    pub inv_scale: [f32; 3],
    /// `mu - o`.
    pub offset: [f32; 3],
}

impl Gaussian {
    /// Transforms the Gaussian into the whitened view of a camera with world-to-camera
    /// rotation `world_to_cam` (row-major) centred at `origin`. The quaternion must be non-zero
    /// (checked by the caller).
    #[inline]
    pub fn view(&self, world_to_cam: &[[f32; 3]; 3], origin: [f32; 3]) -> (ViewSplat, ViewContext) {
        let q = self.rotation;
        let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
        let n = [q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm];
        let rot = quat_to_rotation(n);
        let axes = [
            [rot[0][0], rot[1][0], rot[2][0]],
            [rot[0][1], rot[1][1], rot[2][1]],
            [rot[0][2], rot[1][2], rot[2][2]],
        ];
        let inv_scale = [
            (-self.log_scale[0]).exp(),
            (-self.log_scale[1]).exp(),
            (-self.log_scale[2]).exp(),
        ];
        let offset = [
            self.mean[0] - origin[0],
            self.mean[1] - origin[1],
            self.mean[2] - origin[2],
        ];
        let mut whiten = [[0.0; 3]; 3];
        let mut center = [0.0; 3];
        for k in 0..3 {
            // Row k of L is (W r_k) / s_k.
            for j in 0..3 {
                whiten[k][j] = dot3(world_to_cam[j], axes[k]) * inv_scale[k];
            }
            center[k] = dot3(axes[k], offset) * inv_scale[k];
        }
        let splat = ViewSplat {
            whiten,
            center,
            sigma: softplus(self.raw_density),
            color: self.color,
        };
        let ctx = ViewContext {
            unit_quat: n,
            quat_norm: norm,
            axes,
            inv_scale,
            offset,
        };
        (splat, ctx)
    }
}

/// Gradient of [`Gaussian::view`]: from the gradients of `L`, `m`, `sigma` and the colour
/// back to the world-space parameters (a [`Gaussian`] of gradients).
#[inline]
pub fn view_vjp(
    g: &Gaussian,
    ctx: &ViewContext,
    world_to_cam: &[[f32; 3]; 3],
    grad_whiten: &[[f32; 3]; 3],
    grad_center: [f32; 3],
    grad_sigma: f32,
    grad_color: [f32; 3],
) -> Gaussian {
    let mut grad = Gaussian {
        raw_density: grad_sigma * softplus_grad(g.raw_density),
        color: grad_color,
        ..Default::default()
    };
    // Gradient with respect to each rotation axis r_k (a column of R).
    let mut grad_axes = [[0.0f32; 3]; 3];
    for k in 0..3 {
        let inv_s = ctx.inv_scale[k];
        // L_k = W r_k / s_k  and  m_k = r_k . (mu - o) / s_k.
        let whiten_row = [
            dot3(world_to_cam[0], ctx.axes[k]) * inv_s,
            dot3(world_to_cam[1], ctx.axes[k]) * inv_s,
            dot3(world_to_cam[2], ctx.axes[k]) * inv_s,
        ];
        let center_k = dot3(ctx.axes[k], ctx.offset) * inv_s;
        grad.log_scale[k] = -dot3(grad_whiten[k], whiten_row) - grad_center[k] * center_k;
        for l in 0..3 {
            // (W^T gL_k)_l = sum_j W_jl gL_kj
            let wt_g = world_to_cam[0][l] * grad_whiten[k][0]
                + world_to_cam[1][l] * grad_whiten[k][1]
                + world_to_cam[2][l] * grad_whiten[k][2];
            grad_axes[k][l] = (wt_g + grad_center[k] * ctx.offset[l]) * inv_s;
            grad.mean[l] += grad_center[k] * ctx.axes[k][l] * inv_s;
        }
    }
    // dL/dR[l][k] = dL/dr_k[l].
    let grad_rot = [
        [grad_axes[0][0], grad_axes[1][0], grad_axes[2][0]],
        [grad_axes[0][1], grad_axes[1][1], grad_axes[2][1]],
        [grad_axes[0][2], grad_axes[1][2], grad_axes[2][2]],
    ];
    let grad_unit = quat_to_rotation_vjp(ctx.unit_quat, grad_rot);
    grad.rotation = normalize_vjp(ctx.unit_quat, ctx.quat_norm, grad_unit);
    grad
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Central finite difference of `f` at `x[i]`, in f64 for a clean reference.
    fn fd(f: &dyn Fn(&[f64]) -> f64, x: &[f64], i: usize, h: f64) -> f64 {
        let mut p = x.to_vec();
        let mut m = x.to_vec();
        p[i] += h;
        m[i] -= h;
        (f(&p) - f(&m)) / (2.0 * h)
    }

    fn rotation_f64(q: &[f64]) -> [[f64; 3]; 3] {
        let r = quat_to_rotation([q[0] as f32, q[1] as f32, q[2] as f32, q[3] as f32]);
        r.map(|row| row.map(f64::from))
    }

    #[test]
    fn rotation_is_orthonormal_and_vjp_matches_fd() {
        let n = {
            let q = [0.8f32, -0.3, 0.4, 0.2];
            let len = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            q.map(|v| v / len)
        };
        let r = quat_to_rotation(n);
        for i in 0..3 {
            for j in 0..3 {
                let d: f32 = (0..3).map(|k| r[i][k] * r[j][k]).sum();
                assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-5);
            }
        }
        let weights = [[0.3, -1.2, 0.5], [0.7, 0.1, -0.4], [-0.9, 0.6, 0.2]];
        let loss = |q: &[f64]| {
            let r = rotation_f64(q);
            (0..3)
                .flat_map(|i| (0..3).map(move |j| (i, j)))
                .map(|(i, j)| r[i][j] * weights[i][j] as f64)
                .sum::<f64>()
        };
        let g = quat_to_rotation_vjp(n, weights);
        let x: Vec<f64> = n.iter().map(|&v| v as f64).collect();
        for i in 0..4 {
            let num = fd(&loss, &x, i, 1e-3);
            assert!(
                (num - g[i] as f64).abs() < 2e-3,
                "quat {i}: {num} vs {}",
                g[i]
            );
        }
    }

    #[test]
    fn whitened_integral_matches_appendix_b_closed_form() {
        // Camera at the origin looking down -Z, identity world-to-camera rotation.
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let g = Gaussian {
            mean: [0.2, -0.1, -3.0],
            rotation: [0.9, 0.1, -0.3, 0.2],
            log_scale: [-1.0, -0.5, -1.5],
            raw_density: 0.3,
            color: [1.0, 1.0, 1.0],
        };
        let (splat, ctx) = g.view(&identity, [0.0; 3]);
        let dir = {
            let d = [0.05f32, -0.02, -1.0];
            let len = dot3(d, d).sqrt();
            d.map(|v| v / len)
        };
        let s = splat.sample(dir, 1e9).unwrap();
        // Sigma^-1 = R S^-2 R^T directly.
        let mut inv_cov = [[0.0f64; 3]; 3];
        for (k, axis) in ctx.axes.iter().enumerate() {
            let w = (ctx.inv_scale[k] as f64).powi(2);
            for i in 0..3 {
                for j in 0..3 {
                    inv_cov[i][j] += w * axis[i] as f64 * axis[j] as f64;
                }
            }
        }
        let quad = |u: [f64; 3], v: [f64; 3]| -> f64 {
            (0..3)
                .map(|i| (0..3).map(|j| u[i] * inv_cov[i][j] * v[j]).sum::<f64>())
                .sum()
        };
        let d64 = dir.map(f64::from);
        let om = [-0.2, 0.1, 3.0]; // o - mu
        let a = quad(d64, d64);
        let k = quad(om, om) - quad(om, d64).powi(2) / a;
        let gamma = quad([0.2, -0.1, -3.0], d64) / a;
        let integral = (2.0 * std::f64::consts::PI).sqrt() / a.sqrt() * (-k / 2.0).exp();
        assert!((s.dir_norm_sq as f64 - a).abs() < 1e-4 * a);
        assert!(
            (s.transverse as f64 - k).abs() < 1e-4,
            "{} vs {k}",
            s.transverse
        );
        assert!((s.peak_depth as f64 - gamma).abs() < 1e-5);
        assert!((s.integral as f64 - integral).abs() < 1e-5 * integral.max(1.0));
    }
}
