//! Camera-path files: poses and intrinsics as written, and bad fields named.

use gausmoke_data::read_camera_path;

fn write(dir: &std::path::Path, text: &str) -> std::path::PathBuf {
    let path = dir.join("cameras.json");
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn a_camera_path_gives_its_poses_and_field_of_view() {
    let dir = tempfile::tempdir().unwrap();
    let path = write(
        dir.path(),
        r#"{"camera_angle_x": 1.0, "w": 40, "h": 30, "frames": [
            {"file_path": "ignored", "transform_matrix": [[1,0,0,0.5],[0,1,0,1],[0,0,1,4],[0,0,0,1]]},
            {"transform_matrix": [[0,0,1,4],[0,1,0,1],[-1,0,0,0],[0,0,0,1]]}]}"#,
    );
    let cameras = read_camera_path(&path).unwrap();
    assert_eq!(cameras.len(), 2);
    assert_eq!(cameras[0].position().to_array(), [0.5, 1.0, 4.0]);
    assert_eq!((cameras[1].width(), cameras[1].height()), (40, 30));
    let fx = cameras[0].intrinsics().fx;
    assert!((2.0 * (20.0 / fx).atan() - 1.0).abs() < 1e-5);
}

#[test]
fn bad_camera_paths_name_the_field() {
    let dir = tempfile::tempdir().unwrap();
    for (text, field) in [
        (
            r#"{"camera_angle_x": 3.5, "w": 4, "h": 4, "frames": []}"#,
            "camera_angle_x",
        ),
        (r#"{"camera_angle_x": 1, "h": 4, "frames": []}"#, "w"),
        (
            r#"{"camera_angle_x": 1, "w": 0, "h": 4, "frames": []}"#,
            "w",
        ),
        (
            r#"{"camera_angle_x": 1, "w": 4, "h": 4, "frames": []}"#,
            "frames",
        ),
        (
            r#"{"camera_angle_x": 1, "w": 4, "h": 4, "frames": [{"transform_matrix": [[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
            "frames[0].transform_matrix",
        ),
    ] {
        let err = read_camera_path(&write(dir.path(), text))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("cameras.json") && err.contains(field),
            "{text}: {err}"
        );
    }
}

/// nerfstudio's camera_path.json (ns-render's input) gives the same camera as the NeRF layout
/// with the field of view converted from vertical degrees.
#[test]
fn a_nerfstudio_camera_path_gives_its_poses_and_field_of_view() {
    let dir = tempfile::tempdir().unwrap();
    let path = write(
        dir.path(),
        r#"{"camera_type": "perspective", "render_width": 40, "render_height": 30, "fps": 24,
            "seconds": 1, "keyframes": [], "camera_path": [
            {"camera_to_world": [1,0,0,0.5, 0,1,0,1, 0,0,1,4, 0,0,0,1], "fov": 50, "aspect": 1.33},
            {"camera_to_world": [0,0,1,4, 0,1,0,1, -1,0,0,0, 0,0,0,1], "fov": 50}]}"#,
    );
    let cameras = read_camera_path(&path).unwrap();
    assert_eq!(cameras.len(), 2);
    assert_eq!(cameras[0].position().to_array(), [0.5, 1.0, 4.0]);
    assert_eq!(cameras[1].position().to_array(), [4.0, 1.0, 0.0]);
    assert_eq!((cameras[1].width(), cameras[1].height()), (40, 30));
    let intrinsics = cameras[0].intrinsics();
    let fov_y = 2.0 * (15.0 / intrinsics.fy).atan();
    assert!((fov_y.to_degrees() - 50.0).abs() < 1e-3, "{fov_y}");
    assert!((intrinsics.fx - intrinsics.fy).abs() < 1e-3);
    for (text, field) in [
        (
            r#"{"render_width": 4, "render_height": 4, "camera_path": [{"camera_to_world": [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov": 190}]}"#,
            "camera_path[0].fov",
        ),
        (
            r#"{"render_width": 4, "render_height": 4, "camera_path": [{"camera_to_world": [1,0,0,0], "fov": 50}]}"#,
            "camera_path[0].camera_to_world",
        ),
        (r#"{"render_height": 4, "camera_path": []}"#, "render_width"),
    ] {
        let err = read_camera_path(&write(dir.path(), text))
            .unwrap_err()
            .to_string();
        assert!(err.contains(field), "{text}: {err}");
    }
}
