//! Small-vector maths inside kernels: 3-vectors, 3x3 matrices, quaternions, and the whitening
//! of a Gaussian with its gradient. The renderer's kernels and the density kernels of
//! `gausmoke-model` share these, and each mirrors the host function of [`crate::math`] named
//! in its doc, so the two paths agree to rounding.

use cubecl::prelude::*;

/// `sqrt(2 pi)`.
pub const SQRT_TAU: f32 = 2.506_628_3;

#[derive(CubeType, Clone, Copy)]
pub struct Vec3 {
    pub x: f32,
    pub y: f32,
    pub z: f32,
}

#[cube]
impl Vec3 {
    pub fn new(x: f32, y: f32, z: f32) -> Vec3 {
        Vec3 { x, y, z }
    }

    /// The three floats of `buffer` starting at `start`.
    pub fn load(buffer: &[f32], start: usize) -> Vec3 {
        Vec3 {
            x: buffer[start],
            y: buffer[start + 1],
            z: buffer[start + 2],
        }
    }

    pub fn store(&self, buffer: &mut [f32], start: usize) {
        buffer[start] = self.x;
        buffer[start + 1] = self.y;
        buffer[start + 2] = self.z;
    }

    pub fn dot(&self, other: &Vec3) -> f32 {
        self.x * other.x + self.y * other.y + self.z * other.z
    }

    pub fn scale(&self, factor: f32) -> Vec3 {
        Vec3::new(self.x * factor, self.y * factor, self.z * factor)
    }

    /// `self += other`, in place (cube code cannot reassign a struct variable).
    pub fn add_assign(&mut self, other: &Vec3) {
        self.x += other.x;
        self.y += other.y;
        self.z += other.z;
    }

    /// `self = other`, component by component.
    pub fn set(&mut self, other: &Vec3) {
        self.x = other.x;
        self.y = other.y;
        self.z = other.z;
    }

    /// `self -= other`, in place.
    pub fn sub_assign(&mut self, other: &Vec3) {
        self.x -= other.x;
        self.y -= other.y;
        self.z -= other.z;
    }

    /// A copy (cube code cannot copy a struct out of a reference).
    pub fn copy(&self) -> Vec3 {
        Vec3::new(self.x, self.y, self.z)
    }

    pub fn add(&self, other: &Vec3) -> Vec3 {
        Vec3::new(self.x + other.x, self.y + other.y, self.z + other.z)
    }

    pub fn sub(&self, other: &Vec3) -> Vec3 {
        Vec3::new(self.x - other.x, self.y - other.y, self.z - other.z)
    }

    pub fn cross(&self, other: &Vec3) -> Vec3 {
        Vec3::new(
            self.y * other.z - self.z * other.y,
            self.z * other.x - self.x * other.z,
            self.x * other.y - self.y * other.x,
        )
    }

    pub fn max_element(&self) -> f32 {
        self.x.max(self.y).max(self.z)
    }
}

/// A 3x3 matrix by rows.
#[derive(CubeType, Clone, Copy)]
pub struct Mat3 {
    pub r0: Vec3,
    pub r1: Vec3,
    pub r2: Vec3,
}

#[cube]
impl Mat3 {
    pub fn identity() -> Mat3 {
        Mat3 {
            r0: Vec3::new(1.0, 0.0, 0.0),
            r1: Vec3::new(0.0, 1.0, 0.0),
            r2: Vec3::new(0.0, 0.0, 1.0),
        }
    }

    /// Nine floats of `buffer`, row-major, starting at `start`.
    pub fn load(buffer: &[f32], start: usize) -> Mat3 {
        Mat3 {
            r0: Vec3::load(buffer, start),
            r1: Vec3::load(buffer, start + 3),
            r2: Vec3::load(buffer, start + 6),
        }
    }

    pub fn store(&self, buffer: &mut [f32], start: usize) {
        self.r0.store(buffer, start);
        self.r1.store(buffer, start + 3);
        self.r2.store(buffer, start + 6);
    }

    /// `M v`.
    pub fn mul(&self, v: &Vec3) -> Vec3 {
        Vec3::new(self.r0.dot(v), self.r1.dot(v), self.r2.dot(v))
    }

    /// `M^T v`.
    pub fn transpose_mul(&self, v: &Vec3) -> Vec3 {
        self.r0
            .scale(v.x)
            .add(&self.r1.scale(v.y))
            .add(&self.r2.scale(v.z))
    }
}

/// A quaternion `(w, x, y, z)`.
#[derive(CubeType, Clone, Copy)]
pub struct Quat {
    pub w: f32,
    pub x: f32,
    pub y: f32,
    pub z: f32,
}

#[cube]
impl Quat {
    pub fn load(buffer: &[f32], start: usize) -> Quat {
        Quat {
            w: buffer[start],
            x: buffer[start + 1],
            y: buffer[start + 2],
            z: buffer[start + 3],
        }
    }

    pub fn norm(&self) -> f32 {
        (self.w * self.w + self.x * self.x + self.y * self.y + self.z * self.z).sqrt()
    }

    pub fn scale(&self, factor: f32) -> Quat {
        Quat {
            w: self.w * factor,
            x: self.x * factor,
            y: self.y * factor,
            z: self.z * factor,
        }
    }

    /// Rotation matrix of this unit quaternion (`math::quat_to_rotation`).
    pub fn to_mat3(&self) -> Mat3 {
        let w = self.w;
        let x = self.x;
        let y = self.y;
        let z = self.z;
        Mat3 {
            r0: Vec3::new(
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ),
            r1: Vec3::new(
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ),
            r2: Vec3::new(
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ),
        }
    }

    /// Gradient with respect to this unit quaternion of a loss of [`Quat::to_mat3`], given
    /// `g = dLoss/dR` (`math::quat_to_rotation_vjp`).
    pub fn to_mat3_vjp(&self, g: &Mat3) -> Quat {
        let w = self.w;
        let x = self.x;
        let y = self.y;
        let z = self.z;
        let gw = -z * g.r0.y + y * g.r0.z + z * g.r1.x - x * g.r1.z - y * g.r2.x + x * g.r2.y;
        let gx = y * g.r0.y + z * g.r0.z + y * g.r1.x - 2.0 * x * g.r1.y - w * g.r1.z
            + z * g.r2.x
            + w * g.r2.y
            - 2.0 * x * g.r2.z;
        let gy = -2.0f32 * y * g.r0.x + x * g.r0.y + w * g.r0.z + x * g.r1.x + z * g.r1.z
            - w * g.r2.x
            + z * g.r2.y
            - 2.0 * y * g.r2.z;
        let gz = -2.0f32 * z * g.r0.x - w * g.r0.y + x * g.r0.z + w * g.r1.x - 2.0 * z * g.r1.y
            + y * g.r1.z
            + x * g.r2.x
            + y * g.r2.y;
        Quat {
            w: 2.0 * gw,
            x: 2.0 * gx,
            y: 2.0 * gy,
            z: 2.0 * gz,
        }
    }

    /// Gradient with respect to the raw quaternion of a loss of `q / |q|`, given the gradient
    /// `g` with respect to this normalised quaternion and the raw norm (`math::normalize_vjp`).
    pub fn normalize_vjp(&self, norm: f32, g: &Quat) -> Quat {
        let radial = self.w * g.w + self.x * g.x + self.y * g.y + self.z * g.z;
        Quat {
            w: (g.w - self.w * radial) / norm,
            x: (g.x - self.x * radial) / norm,
            y: (g.y - self.y * radial) / norm,
            z: (g.z - self.z * radial) / norm,
        }
    }
}

/// Softplus with torch's cut-over (`x > 20` returns `x`), as `math::softplus`.
#[cube]
pub fn softplus(x: f32) -> f32 {
    let mut y = x;
    if x <= 20.0 {
        y = x.exp().log1p();
    }
    y
}

/// Derivative of [`softplus`].
#[cube]
pub fn softplus_grad(x: f32) -> f32 {
    let mut y = 1.0f32;
    if x <= 20.0 {
        y = 1.0 / (1.0 + (-x).exp());
    }
    y
}

/// A Gaussian in the whitened frame of a viewer with rotation `W` (world to viewer, rows) at
/// origin `o` (`Gaussian::view`): `L = S^-1 R^T W^T`, whose row `k` is `(W r_k) / s_k`, and
/// `m = S^-1 R^T (mu - o)`. With `W = I` and `o = 0` it is the world-space whitening that
/// density splatting evaluates (`k(x) = exp(-|L x - m|^2 / 2)`).
#[derive(CubeType, Clone, Copy)]
pub struct Whitening {
    pub whiten: Mat3,
    pub center: Vec3,
}

/// What [`whiten`] computes on the way, kept for [`whiten_vjp`] (`math::ViewContext`).
#[derive(CubeType, Clone, Copy)]
pub struct WhiteningContext {
    pub unit_quat: Quat,
    pub quat_norm: f32,
    /// Columns `r_k` of the rotation, as rows.
    pub axes: Mat3,
    pub inv_scale: Vec3,
    /// `mu - o`.
    pub offset: Vec3,
}

/// Axis `k`'s contribution to a [`Whitening`]: row `k` of `L` and `m_k`.
#[cube]
fn whiten_axis(view: &Mat3, axis: &Vec3, offset: &Vec3, inv_scale: f32) -> (Vec3, f32) {
    (
        view.mul(axis).scale(inv_scale),
        axis.dot(offset) * inv_scale,
    )
}

#[cube]
pub fn whitening_context(rotation: &Quat, log_scale: &Vec3, offset: &Vec3) -> WhiteningContext {
    let quat_norm = rotation.norm();
    let unit_quat = rotation.scale(1.0 / quat_norm);
    let rot = unit_quat.to_mat3();
    // Axis k is column k of R.
    let axes = Mat3 {
        r0: Vec3::new(rot.r0.x, rot.r1.x, rot.r2.x),
        r1: Vec3::new(rot.r0.y, rot.r1.y, rot.r2.y),
        r2: Vec3::new(rot.r0.z, rot.r1.z, rot.r2.z),
    };
    WhiteningContext {
        unit_quat,
        quat_norm,
        axes,
        inv_scale: Vec3::new(
            (-log_scale.x).exp(),
            (-log_scale.y).exp(),
            (-log_scale.z).exp(),
        ),
        offset: offset.copy(),
    }
}

/// The whitening of a Gaussian for the viewer `view` (see [`Whitening`]).
#[cube]
pub fn whiten(context: &WhiteningContext, view: &Mat3) -> Whitening {
    let (l0, m0) = whiten_axis(view, &context.axes.r0, &context.offset, context.inv_scale.x);
    let (l1, m1) = whiten_axis(view, &context.axes.r1, &context.offset, context.inv_scale.y);
    let (l2, m2) = whiten_axis(view, &context.axes.r2, &context.offset, context.inv_scale.z);
    Whitening {
        whiten: Mat3 {
            r0: l0,
            r1: l1,
            r2: l2,
        },
        center: Vec3::new(m0, m1, m2),
    }
}

/// Gradient of one Gaussian's world-space parameters through [`whiten`].
#[derive(CubeType, Clone, Copy)]
pub struct WhiteningGrad {
    pub mean: Vec3,
    pub rotation: Quat,
    pub log_scale: Vec3,
}

/// Axis `k`'s share of [`whiten_vjp`]: `dLoss/dr_k`, `dLoss/d log s_k` and its share of
/// `dLoss/dmu`, given the gradients of row `k` of `L` and of `m_k`.
#[cube]
fn whiten_axis_vjp(
    view: &Mat3,
    axis: &Vec3,
    offset: &Vec3,
    inv_scale: f32,
    grad_row: &Vec3,
    grad_center: f32,
) -> (Vec3, f32, Vec3) {
    let (row, center) = whiten_axis(view, axis, offset, inv_scale);
    let grad_log_scale = -grad_row.dot(&row) - grad_center * center;
    // (W^T gL_k + gm_k (mu - o)) / s_k.
    let grad_axis = view
        .transpose_mul(grad_row)
        .add(&offset.scale(grad_center))
        .scale(inv_scale);
    let grad_mean = axis.scale(grad_center * inv_scale);
    (grad_axis, grad_log_scale, grad_mean)
}

/// Gradient of [`whiten`] (`math::view_vjp` without the density and colour terms): from the
/// gradients of `L` and `m` to the mean, raw quaternion and log-scales.
#[cube]
pub fn whiten_vjp(context: &WhiteningContext, view: &Mat3, grad: &Whitening) -> WhiteningGrad {
    let (a0, s0, m0) = whiten_axis_vjp(
        view,
        &context.axes.r0,
        &context.offset,
        context.inv_scale.x,
        &grad.whiten.r0,
        grad.center.x,
    );
    let (a1, s1, m1) = whiten_axis_vjp(
        view,
        &context.axes.r1,
        &context.offset,
        context.inv_scale.y,
        &grad.whiten.r1,
        grad.center.y,
    );
    let (a2, s2, m2) = whiten_axis_vjp(
        view,
        &context.axes.r2,
        &context.offset,
        context.inv_scale.z,
        &grad.whiten.r2,
        grad.center.z,
    );
    // dLoss/dR[l][k] = dLoss/dr_k[l]: the axis gradients are R's columns.
    let grad_rotation = Mat3 {
        r0: Vec3::new(a0.x, a1.x, a2.x),
        r1: Vec3::new(a0.y, a1.y, a2.y),
        r2: Vec3::new(a0.z, a1.z, a2.z),
    };
    let grad_unit = context.unit_quat.to_mat3_vjp(&grad_rotation);
    WhiteningGrad {
        mean: m0.add(&m1).add(&m2),
        rotation: context
            .unit_quat
            .normalize_vjp(context.quat_norm, &grad_unit),
        log_scale: Vec3::new(s0, s1, s2),
    }
}
