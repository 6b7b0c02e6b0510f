//! Camera paths for rendering a reconstruction from new viewpoints, in the NeRF/Blender
//! `transforms.json` layout users already write with Blender add-ons and nerfstudio tools:
//!
//! ```json
//! { "camera_angle_x": 0.69, "w": 480, "h": 270,
//!   "frames": [ { "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]] } ] }
//! ```
//!
//! `camera_angle_x` is the horizontal field of view in radians, `w` and `h` the picture size
//! in pixels, and each `transform_matrix` a camera-to-world pose in the OpenGL convention
//! (the camera looks down -Z, +Y up), rows first, as in D-NeRF's files. Other members (such
//! as `file_path` or `time`) are ignored.
//!
//! nerfstudio's `camera_path.json` (what `ns-render camera-path` reads, written by its
//! viewer) is read too, told apart by its `camera_path` member:
//!
//! ```json
//! { "render_width": 480, "render_height": 270,
//!   "camera_path": [ { "camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,4, 0,0,0,1], "fov": 50 } ] }
//! ```
//!
//! `camera_to_world` is the same pose as 16 numbers, rows first, and `fov` the vertical field
//! of view in degrees (square pixels); `aspect`, `fps` and the keyframes are not needed.

use std::path::Path;

use gausmoke_core::glam::Mat4;
use gausmoke_core::{Camera, Intrinsics};

use crate::error::{DataError, Result};
use crate::json::{Node, read_json};

/// The cameras of a camera-path file, in file order.
pub fn read_camera_path(path: &Path) -> Result<Vec<Camera>> {
    let value = read_json(path)?;
    let root = Node::root(path, &value);
    if value.get("camera_path").is_some() {
        return read_nerfstudio_path(path, root);
    }
    let fov_owned = root.get("camera_angle_x")?;
    let fov = fov_owned.node().positive_f64()?;
    if fov >= std::f64::consts::PI {
        return Err(fov_owned.node().err(format!(
            "a horizontal field of view in (0, pi) radians (got {fov})"
        )));
    }
    let (width, height) = (picture_size(root, "w")?, picture_size(root, "h")?);
    let frames_owned = root.get("frames")?;
    let list = frames_owned.node().array()?;
    if list.is_empty() {
        return Err(frames_owned.node().err("a non-empty array of cameras"));
    }
    list.iter()
        .map(|item| {
            let pose_owned = item.node().get("transform_matrix")?;
            let pose = pose_owned.node().mat4_rows()?;
            camera(path, pose_owned.node(), [width, height], fov, pose)
        })
        .collect()
}

/// A picture side `key` of `root`, in 1..=16384 pixels.
fn picture_size(root: Node<'_>, key: &str) -> Result<u32> {
    let owned = root.get(key)?;
    let n = owned.node().usize()?;
    u32::try_from(n)
        .ok()
        .filter(|&n| (1..=16384).contains(&n))
        .ok_or_else(|| {
            owned
                .node()
                .err(format!("a picture size in 1..=16384 pixels (got {n})"))
        })
}

/// nerfstudio's `camera_path.json` (see the module docs).
fn read_nerfstudio_path(path: &Path, root: Node<'_>) -> Result<Vec<Camera>> {
    let (width, height) = (
        picture_size(root, "render_width")?,
        picture_size(root, "render_height")?,
    );
    let list_owned = root.get("camera_path")?;
    let list = list_owned.node().array()?;
    if list.is_empty() {
        return Err(list_owned.node().err("a non-empty array of cameras"));
    }
    list.iter()
        .map(|item| {
            let fov_owned = item.node().get("fov")?;
            let fov_y = fov_owned.node().positive_f64()?;
            if fov_y >= 180.0 {
                return Err(fov_owned.node().err(format!(
                    "a vertical field of view in (0, 180) degrees (got {fov_y})"
                )));
            }
            // Square pixels: the focal length in pixels is the same along both axes.
            let focal = f64::from(height) / 2.0 / (fov_y.to_radians() / 2.0).tan();
            let fov_x = 2.0 * (f64::from(width) / 2.0 / focal).atan();
            let pose_owned = item.node().get("camera_to_world")?;
            let rows = pose_owned.node().f64_array::<16>()?;
            let pose = Mat4::from_cols_array(&rows.map(|v| v as f32)).transpose();
            camera(path, pose_owned.node(), [width, height], fov_x, pose)
        })
        .collect()
}

/// A camera of `size` with horizontal field of view `fov_x` (radians) at `pose`, a refusal
/// naming the pose's `field` of the file at `path`.
fn camera(path: &Path, field: Node<'_>, size: [u32; 2], fov_x: f64, pose: Mat4) -> Result<Camera> {
    let [width, height] = size;
    Camera::new(
        width,
        height,
        Intrinsics::from_fov_x(fov_x as f32, width, height),
        pose,
    )
    .map_err(|source| DataError::Camera {
        path: path.to_path_buf(),
        field: field.field_path().to_string(),
        source,
    })
}
