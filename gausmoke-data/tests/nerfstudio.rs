//! nerfstudio `transforms.json`: the tiny synthetic scene written in that layout loads to the
//! same views, cameras, times, images and box as its PINF original; what the renderer cannot
//! honour (distortion, fisheye) and inconsistent splits are refused by field.

use std::path::Path;

use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_data::{LoadOptions, Split, load_nerfstudio, load_pinf, plan_nerfstudio};
use serde_json::{Value, json};

/// Writes the PINF scene at `pinf` as a nerfstudio folder at `out`; returns its JSON.
fn as_nerfstudio(pinf: &Path, out: &Path) -> Value {
    let dataset = load_pinf(pinf, &LoadOptions::default()).unwrap();
    std::fs::create_dir_all(out.join("images")).unwrap();
    let first = dataset.views[0].frames[0].camera;
    let k = first.intrinsics();
    let mut frames = Vec::new();
    let mut test = Vec::new();
    for view in &dataset.views {
        for (t, frame) in view.frames.iter().enumerate() {
            let file = format!("./images/{}_{t:03}.png", view.name);
            frame.image.save_png(&out.join(&file)).unwrap();
            let m = frame.camera.camera_to_world();
            let rows: Vec<Vec<f32>> = (0..4).map(|r| m.row(r).to_array().to_vec()).collect();
            let mut entry =
                json!({"file_path": file, "transform_matrix": rows, "time": frame.time});
            let own = frame.camera.intrinsics();
            if own != k {
                entry["fl_x"] = json!(own.fx);
                entry["fl_y"] = json!(own.fy);
                entry["cx"] = json!(own.cx);
                entry["cy"] = json!(own.cy);
            }
            frames.push(entry);
            if view.split == Split::Test {
                test.push(file.trim_start_matches("./").to_string());
            }
        }
    }
    let bbox = dataset.bbox.unwrap();
    let doc = json!({
        "camera_model": "OPENCV",
        "fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy,
        "w": first.width(), "h": first.height(),
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "aabb": [bbox.min.to_array(), bbox.max.to_array()],
        "test_filenames": test,
        "frames": frames,
    });
    std::fs::write(out.join("transforms.json"), doc.to_string()).unwrap();
    doc
}

#[test]
fn a_nerfstudio_copy_of_a_scene_loads_as_the_original() {
    let dir = tempfile::tempdir().unwrap();
    let pinf = dir.path().join("pinf");
    generate(&SynthConfig::tiny(), &pinf).unwrap();
    let ns = dir.path().join("ns");
    as_nerfstudio(&pinf, &ns);
    let original = load_pinf(&pinf, &LoadOptions::default()).unwrap();
    let loaded = load_nerfstudio(&ns, &LoadOptions::default()).unwrap();
    assert_eq!(loaded.views.len(), original.views.len());
    assert_eq!(loaded.times, original.times);
    assert_eq!(loaded.bbox, original.bbox);
    for (a, b) in original.views.iter().zip(&loaded.views) {
        assert_eq!(a.split, b.split, "{} / {}", a.name, b.name);
        assert_eq!(a.frames.len(), b.frames.len());
        for (fa, fb) in a.frames.iter().zip(&b.frames) {
            assert_eq!(fa.time_index, fb.time_index);
            assert_eq!(fa.camera.intrinsics(), fb.camera.intrinsics());
            let poses = fa.camera.camera_to_world() - fb.camera.camera_to_world();
            assert!(poses.to_cols_array().iter().all(|d| d.abs() < 1e-6));
            let worst = fa
                .image
                .data()
                .iter()
                .zip(fb.image.data())
                .map(|(x, y)| (x - y).abs())
                .fold(0.0f32, f32::max);
            assert!(
                worst <= 0.5 / 255.0 + 1e-6,
                "8-bit PNG rounding only: {worst}"
            );
        }
    }
    // The plan agrees with what is loaded, and a frame range keeps distinct times.
    let options = LoadOptions {
        frames: Some(2..5),
        resolution: Some((32, 48)),
        ..Default::default()
    };
    let planned = plan_nerfstudio(&ns, &options).unwrap();
    assert_eq!(
        gausmoke_data::plan(&ns, &options).unwrap(),
        planned,
        "the format is told by its transforms.json"
    );
    assert!(gausmoke_data::read_obstacles(&ns).unwrap().is_empty());
    let subset = load_nerfstudio(&ns, &options).unwrap();
    assert_eq!(subset.times, original.times[2..5]);
    for (plan, view) in planned.iter().zip(&subset.views) {
        assert_eq!((plan.frames, plan.width, plan.height), (3, 32, 48));
        assert_eq!(view.frames.len(), 3);
        assert_eq!(view.frames[0].image.width(), 32);
    }
}

#[test]
fn what_the_renderer_cannot_honour_is_refused_by_field() {
    let dir = tempfile::tempdir().unwrap();
    let pinf = dir.path().join("pinf");
    generate(&SynthConfig::tiny(), &pinf).unwrap();
    let ns = dir.path().join("ns");
    let doc = as_nerfstudio(&pinf, &ns);
    let expect = |edit: &dyn Fn(&mut Value), field: &str| {
        let mut changed = doc.clone();
        edit(&mut changed);
        std::fs::write(ns.join("transforms.json"), changed.to_string()).unwrap();
        let err = load_nerfstudio(&ns, &LoadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("transforms.json") && err.contains(field),
            "{field}: {err}"
        );
    };
    expect(&|d| d["k1"] = json!(0.05), "k1");
    expect(&|d| d["frames"][3]["p2"] = json!(0.001), "frames[3].p2");
    expect(
        &|d| d["camera_model"] = json!("OPENCV_FISHEYE"),
        "camera_model",
    );
    expect(
        &|d| {
            d.as_object_mut().unwrap().remove("fl_x");
        },
        "fl_x",
    );
    expect(
        &|d| d["frames"][0]["file_path"] = json!("images/none.png"),
        "frames[0].file_path",
    );
    expect(&|d| d["aabb"] = json!([[0, 0, 0], [1, -1, 1]]), "aabb");
    // One frame of a training view listed as test: the view is split across lists.
    expect(
        &|d| {
            let file = d["frames"][0]["file_path"]
                .as_str()
                .unwrap()
                .trim_start_matches("./")
                .to_string();
            d["test_filenames"]
                .as_array_mut()
                .unwrap()
                .push(json!(file));
        },
        "test_filenames",
    );
}
