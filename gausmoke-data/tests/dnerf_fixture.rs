//! A tiny D-NeRF style data set written by the test and read back.
#![allow(clippy::needless_range_loop)] // per-channel checks read clearer indexed

use std::path::Path;

use gausmoke_data::glam::{Vec2, Vec3};
use gausmoke_data::{DataError, LoadOptions, Split, load_dnerf};
use serde_json::{Value, json};

const W: u32 = 40;
const H: u32 = 20;

fn rgba(x: u32, y: u32, t: u32) -> [u8; 4] {
    [
        (x * 6) as u8,
        (y * 12) as u8,
        (t * 70) as u8,
        ((x + y + t) * 5) as u8,
    ]
}

fn write_png(path: &Path, w: u32, h: u32, t: u32) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let img = image::RgbaImage::from_fn(w, h, |x, y| image::Rgba(rgba(x, y, t)));
    img.save(path).unwrap();
}

/// Camera at (0, 0, 5) looking down -Z; FOV 90 degrees at 40 px: focal 20 px.
fn front() -> Value {
    json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 0, 1]])
}

/// Camera at (5, 0, 0) looking down -X.
fn side() -> Value {
    json!([[0, 0, 1, 5], [0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 0, 1]])
}

fn write_set(dir: &Path, train: Value, test: Option<Value>) {
    for t in 0..3 {
        write_png(&dir.join(format!("train/r_{t:03}.png")), W, H, t);
    }
    write_png(&dir.join("test/r_000.png"), W, H, 5);
    std::fs::write(dir.join("transforms_train.json"), train.to_string()).unwrap();
    if let Some(test) = test {
        std::fs::write(dir.join("transforms_test.json"), test.to_string()).unwrap();
    }
}

fn train_json() -> Value {
    json!({
        "camera_angle_x": std::f64::consts::FRAC_PI_2,
        "frames": [
            {"file_path": "./train/r_000", "time": 0.0, "transform_matrix": front()},
            {"file_path": "./train/r_001", "time": 0.5, "transform_matrix": side()},
            {"file_path": "./train/r_002.png", "time": 1.0, "transform_matrix": front()}
        ]
    })
}

fn test_json() -> Value {
    json!({
        "camera_angle_x": std::f64::consts::FRAC_PI_2,
        "frames": [{"file_path": "./test/r_000", "time": 0.5, "transform_matrix": side()}]
    })
}

#[test]
fn round_trip_with_alpha_compositing_and_projection() {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), train_json(), Some(test_json()));
    let bg = [0.1, 0.5, 0.9];
    let ds = load_dnerf(
        dir.path(),
        &LoadOptions {
            background: Some(bg),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(ds.views.len(), 2);
    let train = &ds.views[0];
    let test = &ds.views[1];
    assert_eq!((train.split, test.split), (Split::Train, Split::Test));
    assert_eq!(train.frames.len(), 3);
    assert_eq!(test.frames.len(), 1);
    assert_eq!(ds.times, vec![0.0, 0.5, 1.0]);
    assert_eq!(test.frames[0].time_index, 1);
    assert!(ds.bbox.is_none());
    for (t, f) in train.frames.iter().enumerate() {
        assert_eq!(f.time_index, t);
        for (x, y) in [(0, 0), (13, 7), (39, 19)] {
            let p = rgba(x, y, t as u32);
            let a = p[3] as f32 / 255.0;
            let got = f.image.pixel(x, y);
            for c in 0..3 {
                let expected = p[c] as f32 / 255.0 * a + bg[c] * (1.0 - a);
                assert!((got[c] - expected).abs() < 1e-6, "t={t} ({x},{y}) {got:?}");
            }
        }
    }
    // Hand-computed projections: front camera, (1, 0.5, 0) at depth 5 -> (20 + 20/5,
    // 10 - 10/5); side camera, (0, 0.5, -1) -> the same pixel.
    let p = train.frames[0]
        .camera
        .project(Vec3::new(1.0, 0.5, 0.0))
        .unwrap();
    assert!((p - Vec2::new(24.0, 8.0)).length() < 1e-4, "{p}");
    let p = train.frames[1]
        .camera
        .project(Vec3::new(0.0, 0.5, -1.0))
        .unwrap();
    assert!((p - Vec2::new(24.0, 8.0)).length() < 1e-4, "{p}");

    // Half resolution: pixel coordinates halve, images are 2x2 box averages.
    let half = load_dnerf(
        dir.path(),
        &LoadOptions {
            resolution: Some((W / 2, H / 2)),
            background: Some(bg),
            ..Default::default()
        },
    )
    .unwrap();
    let f = &half.views[0].frames[1];
    let p = f.camera.project(Vec3::new(0.0, 0.5, -1.0)).unwrap();
    assert!((p - Vec2::new(12.0, 4.0)).length() < 1e-4, "{p}");
    let full = &train.frames[1].image;
    let avg = |c: usize| {
        (full.pixel(6, 2)[c] + full.pixel(7, 2)[c] + full.pixel(6, 3)[c] + full.pixel(7, 3)[c])
            / 4.0
    };
    let got = f.image.pixel(3, 1);
    for c in 0..3 {
        assert!((got[c] - avg(c)).abs() < 1e-6);
    }
}

#[test]
fn default_background_is_black_and_test_split_is_optional() {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), train_json(), None);
    let ds = load_dnerf(dir.path(), &LoadOptions::default()).unwrap();
    assert_eq!(ds.views.len(), 1);
    assert_eq!(ds.background, [0.0; 3]);
    // rgba(0, 0, 0) is fully transparent: the background shows.
    assert_eq!(ds.views[0].frames[0].image.pixel(0, 0), [0.0; 3]);
    let p = rgba(10, 5, 0);
    let a = p[3] as f32 / 255.0;
    let got = ds.views[0].frames[0].image.pixel(10, 5)[0];
    assert!((got - p[0] as f32 / 255.0 * a).abs() < 1e-6);
}

fn err_with(train: Value) -> DataError {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), train, Some(test_json()));
    let err = load_dnerf(dir.path(), &LoadOptions::default()).unwrap_err();
    assert!(
        err.to_string().contains("transforms_train.json") || err.to_string().contains(".png"),
        "{err}"
    );
    err
}

#[test]
fn bad_inputs_name_file_and_field() {
    let mut v = train_json();
    v["frames"][1].as_object_mut().unwrap().remove("time");
    match err_with(v) {
        DataError::Field { field, .. } => assert_eq!(field, "frames[1].time"),
        other => panic!("{other}"),
    }

    let mut v = train_json();
    v.as_object_mut().unwrap().remove("camera_angle_x");
    match err_with(v) {
        DataError::Field { field, .. } => assert_eq!(field, "camera_angle_x"),
        other => panic!("{other}"),
    }

    let mut v = train_json();
    v["frames"][2]["file_path"] = json!("./train/missing");
    match err_with(v) {
        DataError::Field {
            field, expected, ..
        } => {
            assert_eq!(field, "frames[2].file_path");
            assert!(expected.contains("missing"));
        }
        other => panic!("{other}"),
    }

    let mut v = train_json();
    v["frames"][0]["transform_matrix"] =
        json!([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 5], [0, 0, 1, 1]]);
    match err_with(v) {
        DataError::Camera { field, .. } => assert_eq!(field, "frames[0].transform_matrix"),
        other => panic!("{other}"),
    }

    let mut v = train_json();
    v["frames"][1]["transform_matrix"] = json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]]);
    match err_with(v) {
        DataError::Field { field, .. } => assert_eq!(field, "frames[1].transform_matrix"),
        other => panic!("{other}"),
    }
}

#[test]
fn frame_of_the_wrong_size_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    write_set(dir.path(), train_json(), None);
    write_png(&dir.path().join("train/r_001.png"), W + 2, H, 1);
    match load_dnerf(dir.path(), &LoadOptions::default()).unwrap_err() {
        DataError::FrameSize {
            path,
            found_width,
            expected_width,
            ..
        } => {
            assert!(path.ends_with("r_001.png"));
            assert_eq!((found_width, expected_width), (W + 2, W));
        }
        other => panic!("{other}"),
    }
}

#[test]
fn missing_train_json_is_an_io_error() {
    let dir = tempfile::tempdir().unwrap();
    let err = load_dnerf(dir.path(), &LoadOptions::default()).unwrap_err();
    assert!(matches!(err, DataError::Io { .. }));
    assert!(err.to_string().contains("transforms_train.json"));
}
