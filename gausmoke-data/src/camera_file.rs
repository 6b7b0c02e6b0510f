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

use std::path::Path;

use gausmoke_core::{Camera, Intrinsics};

use crate::error::{DataError, Result};
use crate::json::{Node, read_json};

/// The cameras of a camera-path file, in file order.
pub fn read_camera_path(path: &Path) -> Result<Vec<Camera>> {
    let value = read_json(path)?;
    let root = Node::root(path, &value);
    let fov_owned = root.get("camera_angle_x")?;
    let fov = fov_owned.node().positive_f64()?;
    if fov >= std::f64::consts::PI {
        return Err(fov_owned.node().err(format!(
            "a horizontal field of view in (0, pi) radians (got {fov})"
        )));
    }
    let size = |key: &str| -> Result<u32> {
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
    };
    let (width, height) = (size("w")?, size("h")?);
    let frames_owned = root.get("frames")?;
    let list = frames_owned.node().array()?;
    if list.is_empty() {
        return Err(frames_owned.node().err("a non-empty array of cameras"));
    }
    list.iter()
        .map(|item| {
            let pose_owned = item.node().get("transform_matrix")?;
            let pose = pose_owned.node().mat4_rows()?;
            Camera::new(
                width,
                height,
                Intrinsics::from_fov_x(fov as f32, width, height),
                pose,
            )
            .map_err(|source| DataError::Camera {
                path: path.to_path_buf(),
                field: pose_owned.node().field_path().to_string(),
                source,
            })
        })
        .collect()
}
