use glam::{Mat3, Mat4, Vec2, Vec3, Vec4};

/// Largest deviation from orthonormality accepted in a camera rotation. Poses read from JSON
/// with 6 to 8 significant digits are orthonormal to about 1e-6; 1e-3 still rejects scaled or
/// sheared matrices.
const ROTATION_TOLERANCE: f32 = 1e-3;

/// Why a camera cannot be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    #[error("camera image size is {width}x{height}; both must be at least 1 pixel")]
    EmptyImage { width: u32, height: u32 },
    #[error(
        "camera intrinsics must be finite with fx, fy > 0 (got fx={fx}, fy={fy}, cx={cx}, cy={cy})"
    )]
    BadIntrinsics { fx: f32, fy: f32, cx: f32, cy: f32 },
    #[error("camera-to-world matrix is not a rigid transform: {reason}")]
    NotRigid { reason: String },
    #[error("look-at camera is degenerate: {reason}")]
    DegenerateLookAt { reason: String },
}

/// Pinhole intrinsics in pixels (see the crate docs for the pixel convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
}

impl Intrinsics {
    /// Intrinsics from a horizontal field of view (radians), principal point at the centre,
    /// square pixels: the NeRF `camera_angle_x` convention.
    pub fn from_fov_x(fov_x: f32, width: u32, height: u32) -> Self {
        let focal = 0.5 * width as f32 / (0.5 * fov_x).tan();
        Self {
            fx: focal,
            fy: focal,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
        }
    }
}

/// A calibrated pinhole camera with a rigid camera-to-world pose in the OpenGL convention
/// (camera looks down -Z, +Y up). Built only through validating constructors, so every
/// `Camera` has a non-empty image, positive focal lengths and an orthonormal, right-handed
/// rotation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    width: u32,
    height: u32,
    intrinsics: Intrinsics,
    camera_to_world: Mat4,
}

impl Camera {
    /// Validates and builds a camera.
    pub fn new(
        width: u32,
        height: u32,
        intrinsics: Intrinsics,
        camera_to_world: Mat4,
    ) -> Result<Self, CameraError> {
        if width == 0 || height == 0 {
            return Err(CameraError::EmptyImage { width, height });
        }
        let Intrinsics { fx, fy, cx, cy } = intrinsics;
        if !(fx.is_finite() && fy.is_finite() && cx.is_finite() && cy.is_finite())
            || fx <= 0.0
            || fy <= 0.0
        {
            return Err(CameraError::BadIntrinsics { fx, fy, cx, cy });
        }
        check_rigid(&camera_to_world)?;
        Ok(Self {
            width,
            height,
            intrinsics,
            camera_to_world,
        })
    }

    /// A camera at `eye` looking at `target`, with `up` giving the image's upward direction.
    pub fn look_at(
        eye: Vec3,
        target: Vec3,
        up: Vec3,
        width: u32,
        height: u32,
        fov_x: f32,
    ) -> Result<Self, CameraError> {
        let forward = target - eye;
        if !forward.is_finite() || forward.length() < 1e-9 {
            return Err(CameraError::DegenerateLookAt {
                reason: "eye and target coincide".into(),
            });
        }
        let back = -forward.normalize();
        let right = up.cross(back);
        if right.length() < 1e-6 {
            return Err(CameraError::DegenerateLookAt {
                reason: "up is parallel to the viewing direction".into(),
            });
        }
        let right = right.normalize();
        let true_up = back.cross(right);
        let camera_to_world = Mat4::from_cols(
            right.extend(0.0),
            true_up.extend(0.0),
            back.extend(0.0),
            eye.extend(1.0),
        );
        if !(fov_x.is_finite() && fov_x > 0.0 && fov_x < std::f32::consts::PI) {
            return Err(CameraError::DegenerateLookAt {
                reason: format!("horizontal field of view {fov_x} rad is not in (0, pi)"),
            });
        }
        Self::new(
            width,
            height,
            Intrinsics::from_fov_x(fov_x, width, height),
            camera_to_world,
        )
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    pub fn intrinsics(&self) -> Intrinsics {
        self.intrinsics
    }

    /// Camera-to-world rigid transform (OpenGL convention).
    pub fn camera_to_world(&self) -> Mat4 {
        self.camera_to_world
    }

    /// World-to-camera rigid transform (the exact inverse of the rigid pose).
    pub fn world_to_camera(&self) -> Mat4 {
        let rotation_t = self.rotation_world_to_camera();
        let translation = -(rotation_t * self.position());
        Mat4::from_cols(
            rotation_t.x_axis.extend(0.0),
            rotation_t.y_axis.extend(0.0),
            rotation_t.z_axis.extend(0.0),
            translation.extend(1.0),
        )
    }

    /// Rotation taking world directions to camera directions.
    pub fn rotation_world_to_camera(&self) -> Mat3 {
        Mat3::from_mat4(self.camera_to_world).transpose()
    }

    /// Camera centre in world space.
    pub fn position(&self) -> Vec3 {
        self.camera_to_world.w_axis.truncate()
    }

    /// Direction (camera space, not normalised, z = -1) of the ray through pixel coordinates
    /// `(u, v)`; pass `i + 0.5, j + 0.5` for the centre of pixel `(i, j)`.
    pub fn ray_direction_camera(&self, u: f32, v: f32) -> Vec3 {
        let Intrinsics { fx, fy, cx, cy } = self.intrinsics;
        Vec3::new((u - cx) / fx, -(v - cy) / fy, -1.0)
    }

    /// Pixel coordinates of a world point, or `None` when it is not in front of the camera.
    pub fn project(&self, world: Vec3) -> Option<Vec2> {
        let p = self.world_to_camera().transform_point3(world);
        if p.z >= 0.0 {
            return None;
        }
        let Intrinsics { fx, fy, cx, cy } = self.intrinsics;
        let depth = -p.z;
        Some(Vec2::new(cx + fx * p.x / depth, cy - fy * p.y / depth))
    }
}

fn check_rigid(m: &Mat4) -> Result<(), CameraError> {
    let cols = m.to_cols_array_2d();
    if cols.iter().flatten().any(|v| !v.is_finite()) {
        return Err(CameraError::NotRigid {
            reason: "it contains a non-finite value".into(),
        });
    }
    let last_row = m.row(3);
    if (last_row - Vec4::new(0.0, 0.0, 0.0, 1.0))
        .abs()
        .max_element()
        > 1e-6
    {
        return Err(CameraError::NotRigid {
            reason: format!("its last row is {last_row:?}, expected (0, 0, 0, 1)"),
        });
    }
    let rotation = Mat3::from_mat4(*m);
    let gram = rotation.transpose() * rotation;
    let deviation = (gram - Mat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f32, |acc, v| acc.max(v.abs()));
    if deviation > ROTATION_TOLERANCE {
        return Err(CameraError::NotRigid {
            reason: format!(
                "its 3x3 block is not orthonormal (max |R^T R - I| = {deviation:.3e}, tolerance {ROTATION_TOLERANCE:.0e})"
            ),
        });
    }
    if rotation.determinant() < 0.0 {
        return Err(CameraError::NotRigid {
            reason: "its 3x3 block is a reflection (determinant < 0)".into(),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn front_camera() -> Camera {
        Camera::look_at(Vec3::new(0.0, 0.0, 5.0), Vec3::ZERO, Vec3::Y, 64, 48, 1.0).unwrap()
    }

    #[test]
    fn look_at_projects_target_to_principal_point() {
        let cam = front_camera();
        let p = cam.project(Vec3::ZERO).unwrap();
        assert!((p - Vec2::new(32.0, 24.0)).length() < 1e-4, "{p:?}");
    }

    #[test]
    fn projection_matches_hand_computation() {
        // Camera at z = 5 looking down -Z: world (1, 0.5, 0) is at depth 5.
        let cam = front_camera();
        let f = cam.intrinsics().fx;
        let p = cam.project(Vec3::new(1.0, 0.5, 0.0)).unwrap();
        let expected = Vec2::new(32.0 + f * 1.0 / 5.0, 24.0 - f * 0.5 / 5.0);
        assert!((p - expected).length() < 1e-4, "{p:?} vs {expected:?}");
        // And the ray through that pixel points at the world point.
        let dir = cam.ray_direction_camera(p.x, p.y);
        let world_dir = Mat3::from_mat4(cam.camera_to_world()) * dir;
        let to_point = (Vec3::new(1.0, 0.5, 0.0) - cam.position()).normalize();
        assert!((world_dir.normalize() - to_point).length() < 1e-5);
    }

    #[test]
    fn points_behind_do_not_project() {
        assert!(front_camera().project(Vec3::new(0.0, 0.0, 6.0)).is_none());
    }

    #[test]
    fn world_to_camera_inverts_pose() {
        let cam = Camera::look_at(
            Vec3::new(1.0, 2.0, 3.0),
            Vec3::new(-0.5, 0.1, 0.2),
            Vec3::Y,
            10,
            10,
            0.8,
        )
        .unwrap();
        let product = cam.world_to_camera() * cam.camera_to_world();
        assert!(product.abs_diff_eq(Mat4::IDENTITY, 1e-5));
    }

    #[test]
    fn rejects_bad_cameras() {
        let k = Intrinsics::from_fov_x(1.0, 8, 8);
        assert!(matches!(
            Camera::new(0, 8, k, Mat4::IDENTITY),
            Err(CameraError::EmptyImage { .. })
        ));
        let bad_k = Intrinsics { fx: -1.0, ..k };
        assert!(matches!(
            Camera::new(8, 8, bad_k, Mat4::IDENTITY),
            Err(CameraError::BadIntrinsics { .. })
        ));
        let scaled = Mat4::from_scale(Vec3::splat(2.0));
        assert!(matches!(
            Camera::new(8, 8, k, scaled),
            Err(CameraError::NotRigid { .. })
        ));
        let mirrored = Mat4::from_scale(Vec3::new(1.0, 1.0, -1.0));
        assert!(matches!(
            Camera::new(8, 8, k, mirrored),
            Err(CameraError::NotRigid { .. })
        ));
        let mut projective = Mat4::IDENTITY;
        projective.x_axis.w = 0.5;
        assert!(matches!(
            Camera::new(8, 8, k, projective),
            Err(CameraError::NotRigid { .. })
        ));
        assert!(Camera::look_at(Vec3::ZERO, Vec3::ZERO, Vec3::Y, 8, 8, 1.0).is_err());
        assert!(Camera::look_at(Vec3::Y, Vec3::ZERO, Vec3::Y, 8, 8, 1.0).is_err());
    }
}
