//! `render --run`: a trained run seen from its own cameras, an orbit and a camera file, as MP4
//! videos that our own decoder reads back; the run's summary videos and ParaView series.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_data::video::decode_mp4;
use gausmoke_render::backends::device_by_name;
use gausmoke_train::config::VelocityEstimate;
use gausmoke_train::novel_views::{CameraPath, RenderRequest, render_run};
use gausmoke_train::sequence::Sequence;
use gausmoke_train::{Run, TrainConfig};

/// A two-frame run of the tiny scene, trained once for every test of this file.
fn trained_run() -> &'static Path {
    static RUN: OnceLock<PathBuf> = OnceLock::new();
    RUN.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap().keep();
        let data = dir.join("data");
        generate(&SynthConfig::tiny(), &data).unwrap();
        let config = {
            let mut config = TrainConfig {
                gaussians: 800,
                grid_resolution: 12,
                frames: Some(2),
                unet_channels: 8,
                time_frequencies: 2,
                velocity_estimate: VelocityEstimate::Density,
                ..TrainConfig::default()
            };
            config.init.iterations = 60;
            config.joint.iterations = 5;
            config.refine.iterations = 2;
            config
        };
        let scene = Sequence::open(&data, &config).unwrap();
        let device = device_by_name("flex").unwrap().autodiff();
        let run = dir.join("run");
        Run::new(scene, config, device, &run, false)
            .unwrap()
            .quiet(true)
            .run()
            .unwrap();
        run
    })
}

/// The run's data set, as the run read it.
fn run_scene(run: &Path) -> Sequence {
    let config = TrainConfig::from_toml_file(&run.join("config.toml")).unwrap();
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("run.json")).unwrap()).unwrap();
    Sequence::open(Path::new(info["data"].as_str().unwrap()), &config).unwrap()
}

fn request(cameras: CameraPath) -> RenderRequest {
    RenderRequest {
        cameras,
        frames: None,
        size: None,
        fps: 10,
        png: false,
        progress: false,
    }
}

fn psnr(a: &[f32], b: &[f32]) -> f64 {
    let mse = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y as f64).powi(2))
        .sum::<f64>()
        / a.len() as f64;
    -10.0 * mse.log10()
}

fn png(path: &Path) -> Vec<f32> {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8()
        .into_raw()
        .into_iter()
        .map(|v| v as f32 / 255.0)
        .collect()
}

#[test]
fn the_data_sets_views_reproduce_the_runs_own_renders() {
    let run = trained_run();
    let out = tempfile::tempdir().unwrap();
    let device = device_by_name("flex").unwrap();
    let summary = render_run(run, out.path(), &request(CameraPath::DatasetViews), &device).unwrap();
    let mut names: Vec<&str> = summary.videos.iter().map(|v| v.name.as_str()).collect();
    names.sort();
    assert_eq!(
        names,
        ["view00", "view01", "view02"],
        "train and held-out views"
    );
    for video in &summary.videos {
        assert_eq!(video.frames, [0, 1]);
        let decoded = decode_mp4(&video.video, 0..2, None).unwrap();
        assert_eq!((decoded.info.width, decoded.info.height), (64, 96));
        for t in 0..2 {
            let reference = png(&run.join(format!("renders/{}/frame_{t:03}.png", video.name)));
            let p = psnr(decoded.frames[t].data(), &reference);
            // H.264 at QP 18 against the 8-bit PNG of the same render.
            assert!(p > 38.0, "{} frame {t}: {p:.1} dB", video.name);
        }
    }
    let slices = decode_mp4(&summary.slices_video, 0..2, None).unwrap();
    assert_eq!(slices.frames.len(), 2);
    // Density | the grid velocity's speed | the estimate's speed: three panels of the 12^3
    // grid at 21 pixels a cell, with margins, labels and colour bars around them.
    assert!(summary.slices_show_estimate);
    let panel = 12 * (256 / 12);
    assert!(
        (3 * panel..3 * panel + 100).contains(&slices.info.width)
            && slices.info.height > panel + 60,
        "{:?}",
        slices.info
    );
    let listing: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("render.json")).unwrap())
            .unwrap();
    assert_eq!(listing["videos"][2]["pictures"], 2);
}

/// Time and angle both span the video (the schedule of the module docs).
#[test]
fn a_schedule_spans_both_time_and_cameras() {
    use gausmoke_train::novel_views::schedule;
    assert_eq!(
        schedule(2, 6),
        [(0, 0), (0, 1), (0, 2), (1, 3), (1, 4), (1, 5)]
    );
    assert_eq!(schedule(3, 3), [(0, 0), (1, 1), (2, 2)]);
    assert_eq!(schedule(4, 1), [(0, 0), (1, 0), (2, 0), (3, 0)]);
    let long = schedule(8, 60);
    assert_eq!(long.len(), 60);
    assert_eq!((long[7], long[8], long[59]), ((0, 7), (1, 8), (7, 59)));
}

#[test]
fn an_orbit_circles_the_box_framing_it_while_time_plays() {
    let run = trained_run();
    let out = tempfile::tempdir().unwrap();
    let device = device_by_name("flex").unwrap();
    let mut ask = request(CameraPath::Orbit { steps: 6 });
    ask.size = Some([48, 64]);
    ask.png = true;
    let summary = render_run(run, out.path(), &ask, &device).unwrap();
    let orbit = &summary.videos[0];
    assert_eq!(orbit.name, "orbit");
    assert_eq!(orbit.frames, [0, 0, 0, 1, 1, 1]);
    assert_eq!(
        orbit.orbit_degrees.as_deref(),
        Some(&[0.0, 60.0, 120.0, 180.0, 240.0, 300.0][..])
    );
    let listing: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.path().join("render.json")).unwrap())
            .unwrap();
    assert_eq!(listing["videos"][0]["orbit_degrees"][3], 180.0);
    assert_eq!(listing["videos"][0]["frames"][3], 1);
    let scene = run_scene(run);
    let centre = (scene.lo + scene.hi) * 0.5;
    let distances: Vec<f32> = orbit
        .camera_positions
        .iter()
        .map(|p| (gausmoke_core::glam::Vec3::from_array(*p) - centre).length())
        .collect();
    assert!(
        distances
            .iter()
            .all(|d| (d - distances[0]).abs() < 1e-3 * distances[0]),
        "one circle about the box centre: {distances:?}"
    );
    // Framed: the box's bounding sphere seen under 90% of the narrower half-angle.
    let camera = &scene.test[0][0].camera;
    let fov_x = 2.0 * (camera.width() as f32 / (2.0 * camera.intrinsics().fx)).atan();
    let focal = 48.0 / 2.0 / (fov_x / 2.0).tan();
    let half_angle = (48.0f32 / 2.0 / focal).atan();
    let sphere = (scene.hi - scene.lo).length() / 2.0;
    let seen = (sphere / distances[0]).asin();
    assert!(
        (seen.tan() / half_angle.tan() - 0.9).abs() < 1e-3,
        "{seen} against {half_angle}"
    );
    // Without a size, the held-out camera's shape at 720 pixels on its long side.
    let cameras =
        gausmoke_train::novel_views::orbit_cameras(camera, &[camera], scene.lo, scene.hi, 2, None)
            .unwrap();
    let (w, h) = (camera.width() as f32, camera.height() as f32);
    assert_eq!(cameras[0].width().max(cameras[0].height()), 720);
    let ratio = cameras[0].width() as f32 / cameras[0].height() as f32;
    assert!((ratio - w / h).abs() < 0.02, "{ratio} against {}", w / h);
    let decoded = decode_mp4(&orbit.video, 0..6, None).unwrap();
    assert_eq!((decoded.info.width, decoded.info.height), (48, 64));
    for (i, frame) in decoded.frames.iter().enumerate() {
        // The smoke is in view from every side: the picture is not background alone.
        let bright = frame.data().iter().filter(|&&v| v > 0.1).count();
        assert!(
            bright > 20,
            "picture {i} shows no smoke ({bright} bright values)"
        );
        let saved = png(&out.path().join(format!("orbit/{i:04}.png")));
        assert!(psnr(frame.data(), &saved) > 38.0);
    }
}

#[test]
fn a_camera_file_with_the_held_out_pose_gives_the_held_out_render() {
    let run = trained_run();
    let out = tempfile::tempdir().unwrap();
    let scene = run_scene(run);
    let held_out = &scene.test[0][0];
    let camera = &held_out.camera;
    let rows: Vec<Vec<f32>> = (0..4)
        .map(|r| camera.camera_to_world().row(r).to_array().to_vec())
        .collect();
    let fov_x = 2.0 * (camera.width() as f32 / (2.0 * camera.intrinsics().fx)).atan();
    let file = out.path().join("path.json");
    std::fs::write(
        &file,
        serde_json::json!({
            "camera_angle_x": fov_x, "w": camera.width(), "h": camera.height(),
            "frames": [{"transform_matrix": rows}],
        })
        .to_string(),
    )
    .unwrap();
    let device = device_by_name("flex").unwrap();
    let mut ask = request(CameraPath::File(file.clone()));
    ask.frames = Some(1..2);
    let summary = render_run(run, &out.path().join("render"), &ask, &device).unwrap();
    assert_eq!(summary.videos[0].name, "path");
    let decoded = decode_mp4(&summary.videos[0].video, 0..1, None).unwrap();
    let reference = png(&run.join(format!("renders/{}/frame_001.png", held_out.view)));
    let p = psnr(decoded.frames[0].data(), &reference);
    assert!(p > 38.0, "{p:.1} dB");

    std::fs::write(
        &file,
        r#"{"camera_angle_x": 0.7, "w": 32, "h": 32, "frames": [{"transform_matrix": [[1,0,0]]}]}"#,
    )
    .unwrap();
    let err = render_run(run, out.path(), &ask, &device)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("path.json") && err.contains("frames[0].transform_matrix"),
        "{err}"
    );
}

#[test]
fn bad_requests_are_refused_by_name() {
    let run = trained_run();
    let out = tempfile::tempdir().unwrap();
    let device = device_by_name("flex").unwrap();
    let mut ask = request(CameraPath::Orbit { steps: 4 });
    ask.frames = Some(1..5);
    let err = render_run(run, out.path(), &ask, &device)
        .unwrap_err()
        .to_string();
    assert!(err.contains("--frames") && err.contains("0..2"), "{err}");
    let err = render_run(
        out.path(),
        out.path(),
        &request(CameraPath::DatasetViews),
        &device,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("not a GauSmoke run"), "{err}");
}

#[test]
fn the_cli_renders_an_orbit_and_says_where_it_went() {
    let run = trained_run();
    let out = tempfile::tempdir().unwrap();
    let result = Command::new(env!("CARGO_BIN_EXE_gausmoke-train"))
        .args([
            "render", "--orbit", "3", "--frames", "0..=1", "--size", "32x48", "--quiet",
        ])
        .arg("--run")
        .arg(run)
        .arg("--out")
        .arg(out.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&result.stdout);
    assert!(
        result.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&result.stderr)
    );
    assert!(stdout.contains("orbit: 3 pictures"), "{stdout}");
    assert!(out.path().join("orbit.mp4").is_file());
    let render = |extra: &[&str]| {
        let result = Command::new(env!("CARGO_BIN_EXE_gausmoke-train"))
            .args(["render", "--orbit", "2", "--frames", "1", "--quiet"])
            .args(extra)
            .arg("--run")
            .arg(run)
            .arg("--out")
            .arg(out.path())
            .output()
            .unwrap();
        (
            result.status.success(),
            String::from_utf8_lossy(&result.stderr).into_owned(),
        )
    };
    // The earlier render is not overwritten unless asked; nonsense sizes and rates are refused.
    let (ok, stderr) = render(&["--size", "32x48"]);
    assert!(!ok && stderr.contains("--overwrite"), "{stderr}");
    let (ok, stderr) = render(&["--size", "32x48", "--overwrite"]);
    assert!(ok, "{stderr}");
    for (extra, expected) in [
        (&["--fps", "4294967295"][..], "--fps"),
        (&["--fps", "0"][..], "--fps"),
        (&["--overwrite", "--size", "16385x10"][..], "at most 8192"),
    ] {
        let (ok, stderr) = render(extra);
        assert!(!ok && stderr.contains(expected), "{extra:?}: {stderr}");
    }
    // Options that only mean something for a run are refused without one.
    let result = Command::new(env!("CARGO_BIN_EXE_gausmoke-train"))
        .args(["render", "--frames", "0-3"])
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(
        !result.status.success() && stderr.contains("--run"),
        "{stderr}"
    );
    let result = Command::new(env!("CARGO_BIN_EXE_gausmoke-train"))
        .args(["render", "--frames", "2..1", "--run"])
        .arg(run)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(
        !result.status.success() && stderr.contains("--frames `2..1` is empty"),
        "{stderr}"
    );
}

#[test]
fn the_runs_summary_videos_decode_and_its_paraview_series_lists_every_grid() {
    let run = trained_run();
    for name in ["comparison.mp4", "slices.mp4"] {
        let decoded = decode_mp4(&run.join(name), 0..2, None).unwrap();
        assert_eq!(decoded.frames.len(), 2, "{name}");
    }
    // VTK's Collection format: a VTKFile of type Collection holding DataSet elements whose
    // `file` is relative to the .pvd and whose `timestep` is a number.
    let pvd = std::fs::read_to_string(run.join("exports/grid.pvd")).unwrap();
    let doc = roxmltree::Document::parse(&pvd).expect("well-formed XML");
    let root = doc.root_element();
    assert_eq!(root.tag_name().name(), "VTKFile");
    assert_eq!(root.attribute("type"), Some("Collection"));
    let collection = root
        .children()
        .find(|n| n.is_element())
        .expect("a Collection element");
    assert_eq!(collection.tag_name().name(), "Collection");
    let datasets: Vec<_> = collection.children().filter(|n| n.is_element()).collect();
    assert_eq!(datasets.len(), 2);
    for (t, dataset) in datasets.iter().enumerate() {
        assert_eq!(dataset.tag_name().name(), "DataSet");
        let step: f64 = dataset.attribute("timestep").unwrap().parse().unwrap();
        assert_eq!(step, t as f64);
        let file = dataset.attribute("file").unwrap();
        assert!(run.join("exports").join(file).is_file(), "{file}");
    }
}
