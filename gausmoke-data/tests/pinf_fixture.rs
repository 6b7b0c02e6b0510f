//! PINF / HyFluid `info.json` with PNG frame folders, written by the test: values, resizing,
//! the projection convention, the smoke box, and every bad-input error path.
#![allow(clippy::needless_range_loop)] // per-channel checks read clearer indexed

use std::path::{Path, PathBuf};

use gausmoke_data::glam::{Vec2, Vec3};
use gausmoke_data::{DataError, Image, LoadOptions, Split, load_pinf};
use serde_json::{Value, json};

const W: u32 = 200;
const H: u32 = 100;
const FRAMES: usize = 3;

/// 8-bit test pattern of frame `t`.
fn pattern(x: u32, y: u32, t: usize) -> [u8; 3] {
    [
        ((x + 2 * y + 10 * t as u32) % 256) as u8,
        ((3 * x + y) % 256) as u8,
        (50 * t as u32 + x / 4) as u8,
    ]
}

fn write_frames(dir: &Path, count: usize, w: u32, h: u32) {
    std::fs::create_dir_all(dir).unwrap();
    for t in 0..count {
        let data: Vec<f32> = (0..h)
            .flat_map(|y| (0..w).flat_map(move |x| pattern(x, y, t)))
            .map(|b| b as f32 / 255.0)
            .collect();
        let img = Image::from_vec(w, h, data).unwrap();
        img.save_png(&dir.join(format!("{t:03}.png"))).unwrap();
    }
}

/// Camera A: at (0, 0, 5) looking down -Z. Camera B: at (5, 0, 0) looking down -X (rotated
/// 90 degrees about +Y). Horizontal FOV 90 degrees at 200 px: focal 100 px.
fn info() -> Value {
    json!({
        "train_videos": [{
            "file_name": "front.mp4",
            "frame_rate": 10,
            "frame_num": FRAMES,
            "camera_angle_x": std::f64::consts::FRAC_PI_2,
            "camera_hw": [H, W],
            "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]]
        }],
        "test_videos": [{
            "file_name": "side",
            "frame_rate": 10,
            "frame_num": FRAMES,
            "camera_angle_x": std::f64::consts::FRAC_PI_2,
            "camera_hw": [H, W],
            "transform_matrix_list": (0..FRAMES).map(|_| json!(
                [[0, 0, 1, 5], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]]
            )).collect::<Vec<_>>()
        }],
        "frame_bkg_color": [0.2, 0.3, 0.4],
        "voxel_scale": [1.0, 2.0, 3.0],
        "voxel_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    })
}

fn fixture(info: &Value) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    write_frames(&dir.path().join("front"), FRAMES, W, H);
    write_frames(&dir.path().join("side"), FRAMES, W, H);
    let path = dir.path().join("info.json");
    std::fs::write(&path, serde_json::to_string_pretty(info).unwrap()).unwrap();
    (dir, path)
}

fn load_err(info: &Value) -> DataError {
    let (_dir, path) = fixture(info);
    let err = load_pinf(&path, &LoadOptions::default()).unwrap_err();
    // Every error names a file.
    assert!(err.to_string().contains('/'), "{err}");
    err
}

#[test]
fn loads_pngs_with_cameras_box_and_split() {
    let (_dir, path) = fixture(&info());
    let ds = load_pinf(&path, &LoadOptions::default()).unwrap();
    assert_eq!(ds.views.len(), 2);
    let front = ds.view("front").unwrap();
    let side = ds.view("side").unwrap();
    assert_eq!(front.split, Split::Train);
    assert_eq!(side.split, Split::Test);
    assert_eq!(ds.background, [0.2, 0.3, 0.4]);
    assert_eq!(ds.times, vec![0.0, 0.1, 0.2]);
    for view in [front, side] {
        assert_eq!(view.frames.len(), FRAMES);
        for (t, f) in view.frames.iter().enumerate() {
            assert_eq!(f.time_index, t);
            for (x, y) in [(0, 0), (17, 3), (199, 99), (120, 40)] {
                let expected = pattern(x, y, t).map(|b| b as f32 / 255.0);
                assert_eq!(
                    f.image.pixel(x, y),
                    expected,
                    "{} t={t} ({x},{y})",
                    view.name
                );
            }
        }
    }
    // Column-swapped voxel_matrix (identity) times diag(1, 2, 3): sim (a, b, c) -> world
    // (3c, 2b, a).
    let bbox = ds.bbox.unwrap();
    assert!((bbox.min - Vec3::ZERO).length() < 1e-6, "{bbox:?}");
    assert!(
        (bbox.max - Vec3::new(3.0, 2.0, 1.0)).length() < 1e-6,
        "{bbox:?}"
    );
    let m = ds.sim_to_world.unwrap();
    let w = m.transform_point3(Vec3::new(1.0, 0.0, 0.0));
    assert!((w - Vec3::new(0.0, 0.0, 1.0)).length() < 1e-6, "{w}");
}

/// A 16-bit value 1/65535 off the 8-bit value `b`, which an 8-bit read would lose.
fn sixteen_bit(b: u8) -> u16 {
    (u16::from(b) * 257) ^ 1
}

/// Frame folders of JPEGs (what many capture rigs write) and of 16-bit PNGs load as PNGs do:
/// JPEG to within its compression error, 16-bit PNG to 1/65535.
#[test]
fn loads_jpeg_and_16_bit_png_frames() {
    let (dir, path) = fixture(&info());
    for (folder, write) in [("front", "jpeg"), ("side", "png16")] {
        let frames = dir.path().join(folder);
        std::fs::remove_dir_all(&frames).unwrap();
        std::fs::create_dir_all(&frames).unwrap();
        for t in 0..FRAMES {
            if write == "jpeg" {
                let raw: Vec<u8> = (0..H)
                    .flat_map(|y| (0..W).flat_map(move |x| pattern(x, y, t)))
                    .collect();
                let picture = image::RgbImage::from_raw(W, H, raw).unwrap();
                let file = std::fs::File::create(frames.join(format!("{t:03}.jpg"))).unwrap();
                image::codecs::jpeg::JpegEncoder::new_with_quality(file, 100)
                    .encode_image(&picture)
                    .unwrap();
            } else {
                let raw: Vec<u16> = (0..H)
                    .flat_map(|y| (0..W).flat_map(move |x| pattern(x, y, t)))
                    .map(sixteen_bit)
                    .collect();
                let picture =
                    image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(W, H, raw).unwrap();
                picture.save(frames.join(format!("{t:03}.png"))).unwrap();
            }
        }
    }
    let ds = load_pinf(&path, &LoadOptions::default()).unwrap();
    for (name, tolerance) in [("front", 0.06), ("side", 1.5 / 65535.0)] {
        let view = ds.view(name).unwrap();
        assert_eq!(view.frames.len(), FRAMES, "{name}");
        let mut worst = 0.0f32;
        for (t, frame) in view.frames.iter().enumerate() {
            for (x, y) in [(0, 0), (17, 3), (199, 99), (120, 40), (60, 60)] {
                let expected = if name == "side" {
                    pattern(x, y, t).map(|b| f32::from(sixteen_bit(b)) / 65535.0)
                } else {
                    pattern(x, y, t).map(|b| b as f32 / 255.0)
                };
                for (a, b) in frame.image.pixel(x, y).iter().zip(expected) {
                    worst = worst.max((a - b).abs());
                }
            }
        }
        assert!(worst <= tolerance, "{name}: off by {worst}");
    }
}

#[test]
fn known_world_points_project_to_hand_computed_pixels() {
    let (_dir, path) = fixture(&info());
    for (scale, resolution) in [(1.0, None), (0.5, Some((W / 2, H / 2)))] {
        let ds = load_pinf(
            &path,
            &LoadOptions {
                resolution,
                ..Default::default()
            },
        )
        .unwrap();
        // front: (1, 0.5, 0) is at depth 5, 1 right and 0.5 up: u = 100 + 100 * 1/5,
        // v = 50 - 100 * 0.5/5.
        let front = &ds.view("front").unwrap().frames[0].camera;
        let p = front.project(Vec3::new(1.0, 0.5, 0.0)).unwrap();
        assert!((p - Vec2::new(120.0, 40.0) * scale).length() < 1e-3, "{p}");
        // side (per-frame poses): camera at (5, 0, 0), camera +X = world -Z, camera -Z =
        // world -X. (0, 0.5, -1) is at depth 5, 1 right, 0.5 up: the same pixel.
        for f in &ds.view("side").unwrap().frames {
            let p = f.camera.project(Vec3::new(0.0, 0.5, -1.0)).unwrap();
            assert!((p - Vec2::new(120.0, 40.0) * scale).length() < 1e-3, "{p}");
        }
    }
}

#[test]
fn resize_is_a_box_average_and_scales_intrinsics() {
    let (_dir, path) = fixture(&info());
    let opts = LoadOptions {
        resolution: Some((W / 2, H / 2)),
        frames: Some(1..3),
        ..Default::default()
    };
    let ds = load_pinf(&path, &opts).unwrap();
    let f = &ds.view("front").unwrap().frames[0];
    assert_eq!(f.time_index, 0);
    assert!((f.time - 0.1).abs() < 1e-6);
    assert_eq!(ds.view("front").unwrap().frames.len(), 2);
    let k = f.camera.intrinsics();
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (50.0, 50.0, 50.0, 25.0));
    for (x, y) in [(0u32, 0u32), (30, 20), (99, 49)] {
        let mut expected = [0.0f32; 3];
        for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            let p = pattern(2 * x + dx, 2 * y + dy, 1);
            for c in 0..3 {
                expected[c] += p[c] as f32 / 255.0 / 4.0;
            }
        }
        let got = f.image.pixel(x, y);
        for c in 0..3 {
            assert!(
                (got[c] - expected[c]).abs() < 1e-6,
                "({x},{y}) {got:?} {expected:?}"
            );
        }
    }
}

fn field_of(err: &DataError) -> &str {
    match err {
        DataError::Field { field, .. } | DataError::Camera { field, .. } => field,
        DataError::TooFewFrames { field, .. } => field,
        other => panic!("not a field error: {other}"),
    }
}

#[test]
fn missing_and_malformed_fields_are_named() {
    let mut v = info();
    v["train_videos"][0]
        .as_object_mut()
        .unwrap()
        .remove("camera_angle_x");
    let err = load_err(&v);
    assert_eq!(field_of(&err), "train_videos[0].camera_angle_x");
    assert!(err.to_string().contains("info.json"), "{err}");

    let mut v = info();
    v["test_videos"][0]["camera_hw"] = json!([100]);
    let err = load_err(&v);
    assert_eq!(field_of(&err), "test_videos[0].camera_hw");
    assert!(err.to_string().contains("2 finite numbers"), "{err}");

    let mut v = info();
    v["train_videos"][0]["frame_num"] = json!("three");
    assert_eq!(field_of(&load_err(&v)), "train_videos[0].frame_num");

    let mut v = info();
    v.as_object_mut().unwrap().remove("voxel_matrix");
    assert_eq!(field_of(&load_err(&v)), "voxel_matrix");

    let mut v = info();
    v["voxel_scale"] = json!([1.0, -2.0, 3.0]);
    assert_eq!(field_of(&load_err(&v)), "voxel_scale");

    let mut v = info();
    v["test_videos"][0]["transform_matrix_list"] = json!([[[1, 0, 0, 0]]]);
    assert_eq!(
        field_of(&load_err(&v)),
        "test_videos[0].transform_matrix_list"
    );

    let mut v = info();
    v["train_videos"][0]["transform_matrix"][1] = json!([0, 1, "x", 0]);
    assert_eq!(field_of(&load_err(&v)), "train_videos[0].transform_matrix");

    let mut v = info();
    v["train_videos"][0]["file_name"] = json!("nowhere.mp4");
    let err = load_err(&v);
    assert_eq!(field_of(&err), "train_videos[0].file_name");
    assert!(err.to_string().contains("nowhere"), "{err}");

    let mut v = info();
    v.as_object_mut().unwrap().remove("train_videos");
    v.as_object_mut().unwrap().remove("test_videos");
    assert!(matches!(load_err(&v), DataError::Field { .. }));
}

#[test]
fn invalid_json_is_reported_with_the_file() {
    let (dir, path) = fixture(&info());
    std::fs::write(&path, "{ \"train_videos\": [ ").unwrap();
    let err = load_pinf(dir.path(), &LoadOptions::default()).unwrap_err();
    assert!(matches!(err, DataError::Json { .. }), "{err}");
    assert!(err.to_string().contains("info.json"));
}

#[test]
fn non_invertible_pose_is_refused() {
    let mut v = info();
    v["train_videos"][0]["transform_matrix"] =
        json!([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 5], [0, 0, 0, 1]]);
    let err = load_err(&v);
    assert!(matches!(err, DataError::Camera { .. }), "{err}");
    assert_eq!(field_of(&err), "train_videos[0].transform_matrix");

    let mut v = info();
    v["test_videos"][0]["transform_matrix_list"][2] =
        json!([[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 5], [0, 0, 0, 1]]);
    let err = load_err(&v);
    assert_eq!(field_of(&err), "test_videos[0].transform_matrix_list[2]");
}

#[test]
fn too_few_frames_names_folder_and_counts() {
    let mut v = info();
    v["train_videos"][0]["frame_num"] = json!(4);
    match load_err(&v) {
        DataError::TooFewFrames {
            path,
            field,
            found,
            expected,
            ..
        } => {
            assert!(path.ends_with("front"), "{path:?}");
            assert_eq!(field, "train_videos[0].frame_num");
            assert_eq!((found, expected), (3, 4));
        }
        other => panic!("{other}"),
    }
}

#[test]
fn wrong_frame_size_is_refused() {
    let mut v = info();
    v["train_videos"][0]["camera_hw"] = json!([H, W + 1]);
    match load_err(&v) {
        DataError::FrameSize {
            found_width,
            expected_width,
            origin,
            ..
        } => {
            assert_eq!((found_width, expected_width), (W, W + 1));
            assert!(origin.contains("train_videos[0].camera_hw"), "{origin}");
        }
        other => panic!("{other}"),
    }
}

#[test]
fn bad_options_are_refused() {
    let (_dir, path) = fixture(&info());
    for opts in [
        LoadOptions {
            resolution: Some((0, 10)),
            ..Default::default()
        },
        LoadOptions {
            frames: Some(2..2),
            ..Default::default()
        },
        LoadOptions {
            background: Some([0.0, 2.0, 0.0]),
            ..Default::default()
        },
        LoadOptions {
            frames: Some(2..4),
            ..Default::default()
        },
    ] {
        assert!(matches!(
            load_pinf(&path, &opts),
            Err(DataError::Options { .. })
        ));
    }
}

fn real_video() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/datasets/scalar_real/train00.mp4")
}

/// A one-camera info.json pointing at `video` (copied into the temp folder).
fn video_fixture(video: Option<&Path>, garbage: bool, hw: [u32; 2], frames: usize) -> DataError {
    let dir = tempfile::tempdir().unwrap();
    let target = dir.path().join("cam.mp4");
    if let Some(v) = video {
        std::fs::copy(v, &target).unwrap();
    }
    if garbage {
        std::fs::write(&target, b"this is not an mp4 file at all, just text").unwrap();
    }
    let mut v = info();
    v.as_object_mut().unwrap().remove("test_videos");
    v["train_videos"][0]["file_name"] = json!("cam.mp4");
    v["train_videos"][0]["camera_hw"] = json!(hw);
    v["train_videos"][0]["frame_num"] = json!(frames);
    let path = dir.path().join("info.json");
    std::fs::write(&path, v.to_string()).unwrap();
    load_pinf(
        &path,
        &LoadOptions {
            frames: Some(0..1),
            resolution: Some((27, 48)),
            ..Default::default()
        },
    )
    .unwrap_err()
}

#[test]
fn unreadable_video_names_the_file() {
    let err = video_fixture(None, true, [H, W], 1);
    assert!(matches!(err, DataError::Video { .. }), "{err}");
    assert!(err.to_string().contains("cam.mp4"), "{err}");
}

#[test]
fn video_with_fewer_frames_than_announced() {
    match video_fixture(Some(&real_video()), false, [1920, 1080], 121) {
        DataError::TooFewFrames {
            path,
            found,
            expected,
            field,
            ..
        } => {
            assert!(path.ends_with("cam.mp4"));
            assert_eq!((found, expected), (120, 121));
            assert_eq!(field, "train_videos[0].frame_num");
        }
        other => panic!("{other}"),
    }
}

#[test]
fn video_of_the_wrong_size() {
    match video_fixture(Some(&real_video()), false, [1920, 1000], 120) {
        DataError::FrameSize {
            path,
            found_width,
            found_height,
            expected_width,
            ..
        } => {
            assert!(path.ends_with("cam.mp4"));
            assert_eq!(
                (found_width, found_height, expected_width),
                (1080, 1920, 1000)
            );
        }
        other => panic!("{other}"),
    }
}

/// A damaged payload in the real capture's first picture (300 bytes overwritten) is refused,
/// naming the file and the frame, rather than decoded into a picture of garbage.
#[test]
fn a_damaged_frame_is_refused_naming_it() {
    let mut bytes = std::fs::read(real_video()).unwrap();
    // The first IDR slice: walk the top-level boxes to `mdat`, then its length-prefixed NALs.
    let mut at = 0;
    let mdat = loop {
        let size = u32::from_be_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
        if &bytes[at + 4..at + 8] == b"mdat" {
            break at + 8;
        }
        at += size;
    };
    let mut nal = mdat;
    while bytes[nal + 4] & 31 != 5 {
        nal += 4 + u32::from_be_bytes(bytes[nal..nal + 4].try_into().unwrap()) as usize;
    }
    let length = u32::from_be_bytes(bytes[nal..nal + 4].try_into().unwrap()) as usize;
    assert!(
        length > 3400,
        "the IDR slice is long enough to damage its middle"
    );
    for byte in &mut bytes[nal + 4 + 3000..nal + 4 + 3300] {
        *byte ^= 0xff;
    }
    let dir = tempfile::tempdir().unwrap();
    let damaged = dir.path().join("damaged.mp4");
    std::fs::write(&damaged, bytes).unwrap();
    let Err(err) = gausmoke_data::video::decode_mp4(&damaged, 0..2, Some((27, 48))) else {
        panic!("the damaged frame was decoded");
    };
    let message = err.to_string();
    assert!(
        message.contains("damaged.mp4")
            && message.contains("frame 0 (sample 1")
            && message.contains("damaged"),
        "{message}"
    );
}
