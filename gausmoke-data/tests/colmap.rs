//! A camera rig calibrated with COLMAP, written by the test in COLMAP's text and binary
//! forms: every camera projects world points where COLMAP's own model does, the split, the
//! frames and the box are read, the world can be turned to put `up` along +y, and bad input
//! is refused naming the file and what is wrong.

use std::path::Path;

use gausmoke_data::glam::{DQuat, DVec3, Vec2, Vec3};
use gausmoke_data::{Format, Image, LoadOptions, Split, load, plan};

const W: u32 = 64;
const H: u32 = 48;
const FRAMES: usize = 3;

/// A camera of the rig as COLMAP stores it: world-to-camera rotation (OpenCV axes) and
/// translation, PINHOLE intrinsics.
struct Rigged {
    name: &'static str,
    rotation: DQuat,
    translation: DVec3,
    pinhole: [f64; 4],
}

fn rig() -> Vec<Rigged> {
    // Cameras on a circle of radius 4 about the origin at height 0.5 in a y-down world (as
    // COLMAP's often is), each looking at the origin.
    [("cam00", 0.0f64), ("cam01", 2.1), ("cam02", 4.2)]
        .into_iter()
        .enumerate()
        .map(|(k, (name, angle))| {
            let centre = DVec3::new(4.0 * angle.sin(), -0.5, 4.0 * angle.cos());
            let forward = (-centre).normalize();
            let down = DVec3::Y; // the world's down in a y-down world
            let right = down.cross(forward).normalize();
            let down = forward.cross(right);
            // Rows of R are the camera axes in world coordinates (x right, y down, z forward).
            let rotation = DQuat::from_mat3(
                &gausmoke_data::glam::DMat3::from_cols(right, down, forward).transpose(),
            );
            Rigged {
                name,
                rotation,
                translation: -(rotation * centre),
                pinhole: [50.0 + k as f64, 52.0, 31.5 + k as f64, 24.25],
            }
        })
        .collect()
}

/// Where COLMAP puts world point `x` in camera `c`'s picture.
fn colmap_pixel(c: &Rigged, x: DVec3) -> Vec2 {
    let p = c.rotation * x + c.translation;
    let [fx, fy, cx, cy] = c.pinhole;
    Vec2::new((fx * p.x / p.z + cx) as f32, (fy * p.y / p.z + cy) as f32)
}

fn write_text(dir: &Path, rig: &[Rigged]) {
    let mut cameras = String::from("# Camera list\n# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    let mut images = String::from("# Image list with two lines of data per image\n");
    for (k, c) in rig.iter().enumerate() {
        let [fx, fy, cx, cy] = c.pinhole;
        cameras += &format!("{} PINHOLE {W} {H} {fx} {fy} {cx} {cy}\n", k + 1);
        let q = c.rotation;
        let t = c.translation;
        images += &format!(
            "{} {} {} {} {} {} {} {} {} {}/000.png\n{}\n",
            k + 1,
            q.w,
            q.x,
            q.y,
            q.z,
            t.x,
            t.y,
            t.z,
            k + 1,
            c.name,
            if k == 1 {
                ""
            } else {
                "10.5 20.5 -1 3.0 4.0 17"
            }
        );
    }
    std::fs::write(dir.join("cameras.txt"), cameras).unwrap();
    std::fs::write(dir.join("images.txt"), images).unwrap();
}

fn write_binary(dir: &Path, rig: &[Rigged]) {
    let mut cameras = (rig.len() as u64).to_le_bytes().to_vec();
    let mut images = (rig.len() as u64).to_le_bytes().to_vec();
    for (k, c) in rig.iter().enumerate() {
        let id = (k + 1) as u32;
        cameras.extend(id.to_le_bytes());
        cameras.extend(1u32.to_le_bytes()); // PINHOLE
        cameras.extend(u64::from(W).to_le_bytes());
        cameras.extend(u64::from(H).to_le_bytes());
        c.pinhole
            .iter()
            .for_each(|v| cameras.extend(v.to_le_bytes()));
        images.extend(id.to_le_bytes());
        let q = c.rotation;
        [
            q.w,
            q.x,
            q.y,
            q.z,
            c.translation.x,
            c.translation.y,
            c.translation.z,
        ]
        .iter()
        .for_each(|v| images.extend(v.to_le_bytes()));
        images.extend(id.to_le_bytes());
        images.extend(format!("{}.png", c.name).bytes());
        images.push(0);
        images.extend(1u64.to_le_bytes());
        images.extend(1.5f64.to_le_bytes());
        images.extend(2.5f64.to_le_bytes());
        images.extend((-1i64).to_le_bytes());
    }
    std::fs::write(dir.join("cameras.bin"), cameras).unwrap();
    std::fs::write(dir.join("images.bin"), images).unwrap();
}

/// A rig folder: calibration in `sparse/0/` (text or binary), frames, and `rig.json`.
fn fixture(binary: bool, rig_json: &str) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let sparse = dir.path().join("sparse/0");
    std::fs::create_dir_all(&sparse).unwrap();
    let cameras = rig();
    if binary {
        write_binary(&sparse, &cameras);
    } else {
        write_text(&sparse, &cameras);
    }
    for c in &cameras {
        let frames = dir.path().join("images").join(c.name);
        std::fs::create_dir_all(&frames).unwrap();
        for t in 0..FRAMES {
            let value = t as f32 / 10.0;
            let image = Image::from_vec(W, H, vec![value; (W * H * 3) as usize]).unwrap();
            image.save_png(&frames.join(format!("{t:03}.png"))).unwrap();
        }
    }
    std::fs::write(dir.path().join("rig.json"), rig_json).unwrap();
    dir
}

const RIG: &str = r#"{"aabb": [[-1, -1, -1], [1, 1, 1]], "test_cameras": ["cam02"]}"#;

#[test]
fn a_colmap_rig_projects_as_colmap_does_in_text_and_binary_form() {
    for binary in [false, true] {
        let dir = fixture(binary, RIG);
        assert_eq!(Format::detect(dir.path()), Some(Format::Colmap));
        let planned = plan(dir.path(), &LoadOptions::default()).unwrap();
        assert_eq!(planned.len(), 3);
        let ds = load(dir.path(), &LoadOptions::default()).unwrap();
        assert_eq!(ds.format, Format::Colmap);
        assert_eq!(ds.times, [0.0, 1.0, 2.0]);
        let bbox = ds.bbox.unwrap();
        assert_eq!((bbox.min, bbox.max), (Vec3::splat(-1.0), Vec3::splat(1.0)));
        for c in rig() {
            let view = ds.view(c.name).unwrap();
            let split = if c.name == "cam02" {
                Split::Test
            } else {
                Split::Train
            };
            assert_eq!(view.split, split, "{}", c.name);
            assert_eq!(view.frames.len(), FRAMES);
            assert!((view.frames[2].image.pixel(5, 5)[0] - 0.2).abs() < 0.003);
            let camera = &view.frames[1].camera;
            let centre = -(c.rotation.inverse() * c.translation);
            assert!((camera.position().as_dvec3() - centre).length() < 1e-5);
            for x in [
                DVec3::ZERO,
                DVec3::new(0.3, -0.2, 0.1),
                DVec3::new(-0.5, 0.4, 0.6),
            ] {
                let ours = camera.project(x.as_vec3()).unwrap();
                let colmap = colmap_pixel(&c, x);
                assert!(
                    (ours - colmap).length() < 1e-3,
                    "{}: {ours} against {colmap}",
                    c.name
                );
            }
        }
    }
}

/// `up` turns COLMAP's y-down world so that the cameras' up is +y, keeping the pictures.
#[test]
fn up_turns_the_world_and_keeps_the_pictures() {
    let dir = fixture(
        false,
        r#"{"aabb": [[-1, -1, -1], [1, 1, 1]], "up": [0, -1, 0]}"#,
    );
    let ds = load(dir.path(), &LoadOptions::default()).unwrap();
    let turn = DQuat::from_rotation_arc(DVec3::NEG_Y, DVec3::Y);
    for c in rig() {
        let camera = &ds.view(c.name).unwrap().frames[0].camera;
        // Upright cameras: their up axis is the turned world's +y, leaning with the view.
        assert!(camera.camera_to_world().y_axis.y > 0.9, "{}", c.name);
        let x = DVec3::new(0.3, -0.2, 0.1);
        let ours = camera.project((turn * x).as_vec3()).unwrap();
        assert!((ours - colmap_pixel(&c, x)).length() < 1e-3, "{}", c.name);
    }
}

#[test]
fn bad_rigs_are_refused_naming_the_file_and_the_reason() {
    let no_box = fixture(false, r#"{"test_cameras": []}"#);
    let err = load(no_box.path(), &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("rig.json") && err.contains("aabb"), "{err}");

    let unknown = fixture(
        false,
        r#"{"aabb": [[-1, -1, -1], [1, 1, 1]], "test_cameras": ["cam09"]}"#,
    );
    let err = load(unknown.path(), &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("cam09"), "{err}");

    let distorted = fixture(false, RIG);
    let cameras = distorted.path().join("sparse/0/cameras.txt");
    let text = std::fs::read_to_string(&cameras).unwrap();
    let text = text.replacen(
        "1 PINHOLE 64 48 50 52 31.5 24.25",
        "1 OPENCV 64 48 50 52 31.5 24.25 0.1 0 0 0",
        1,
    );
    std::fs::write(&cameras, text).unwrap();
    let err = load(distorted.path(), &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("cameras.txt") && err.contains("undistort"),
        "{err}"
    );

    let fisheye = fixture(false, RIG);
    let cameras = fisheye.path().join("sparse/0/cameras.txt");
    let text = std::fs::read_to_string(&cameras).unwrap();
    std::fs::write(&cameras, text.replacen("PINHOLE", "OPENCV_FISHEYE", 1)).unwrap();
    let err = load(fisheye.path(), &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("OPENCV_FISHEYE"), "{err}");

    let truncated = fixture(true, RIG);
    let images = truncated.path().join("sparse/0/images.bin");
    let bytes = std::fs::read(&images).unwrap();
    std::fs::write(&images, &bytes[..bytes.len() - 30]).unwrap();
    let err = load(truncated.path(), &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("images.bin") && err.contains("ends early"),
        "{err}"
    );

    let no_frames = fixture(false, RIG);
    std::fs::remove_dir_all(no_frames.path().join("images/cam01")).unwrap();
    let err = load(no_frames.path(), &LoadOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("cam01"), "{err}");
}
