//! Algorithm 1 end to end on the tiny synthetic scene (CPU, seconds): the held-out view
//! improves on the initialisation, the recovered velocity is divergence-free and points the
//! way the true one does, every promised output is written, and a killed run resumes to the
//! same parameters as an uninterrupted one.
#![allow(clippy::disallowed_methods)] // tests read tensors freely; the library counts its reads

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_model::SolidCells;
use gausmoke_render::backends::device_by_name;
use gausmoke_train::arrays::read_arrays;
use gausmoke_train::metrics::mean_abs_error;
use gausmoke_train::sequence::Sequence;
use gausmoke_train::{Phase, Run, TrainConfig, eval};

/// Small enough for CI in a debug build, large enough that the plume moves and is fitted.
fn test_config() -> TrainConfig {
    {
        let mut config = TrainConfig {
            gaussians: 1500,
            grid_resolution: 16,
            frames: Some(4),
            unet_channels: 8,
            time_frequencies: 2,
            ..TrainConfig::default()
        };
        config.init.iterations = 100;
        config.joint.iterations = 15;
        config.refine.iterations = 5;
        config.learning_rates.velocity = 2e-3;
        config.learning_rates.gaussians = 2e-3;
        config
    }
}

/// The largest absolute difference between two arrays of the same length.
fn largest_difference(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max)
}

/// A scene of closed walls, whatever the data set declares.
fn walls() -> gausmoke_train::scene::SceneConfig {
    gausmoke_train::scene::SceneConfig {
        open_faces: Some(Vec::new()),
        open_face_flow: Some(1.0),
        inflow: None,
    }
}

fn tiny_scene(dir: &Path) -> PathBuf {
    let data = dir.join("data");
    generate(&SynthConfig::tiny(), &data).expect("the tiny scene generates");
    data
}

#[test]
fn training_improves_the_held_out_view_and_writes_every_output() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let config = test_config();
    let scene = Sequence::open(&data, &config).unwrap();
    assert_eq!(scene.frames(), 4);
    assert_eq!(
        scene.test[0].len(),
        1,
        "the synthetic scene holds one view out"
    );
    let device = device_by_name("flex").unwrap().autodiff();
    let run = dir.path().join("run");
    let mut training = Run::new(scene.clone(), config.clone(), device.clone(), &run, false)
        .unwrap()
        .quiet(true);

    // Held-out L1 of the initial Gaussians, per frame.
    let initial: Vec<f64> = (0..scene.frames())
        .map(|t| {
            let observation = &scene.test[t][0];
            let render = &training
                .trainer
                .render_host(std::slice::from_ref(observation))
                .unwrap()[0];
            mean_abs_error(render, observation.image.data())
        })
        .collect();
    let reports = training.run().unwrap().to_vec();
    assert_eq!(reports.len(), 4);
    let trained: Vec<f64> = reports.iter().map(|r| r.test_l1.unwrap()).collect();
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let factor = mean(&initial) / mean(&trained);
    eprintln!("held-out L1 initial {initial:?} trained {trained:?} (x{factor:.1})");
    // Measured x20 (2026-11-22); the initial translucent Gaussians fill the box, the plume
    // does not.
    assert!(factor > 5.0, "held-out L1 improved only x{factor:.2}");
    for t in 1..4 {
        assert!(
            trained[t] < 0.3 * initial[t],
            "frame {t}: advected frames stay fitted ({} vs {})",
            trained[t],
            initial[t]
        );
    }

    // The velocity after Pi is discretely divergence-free (the solver's tolerance is 1e-5
    // relative) and not trivially zero.
    for report in &reports[1..] {
        assert!(
            report.mean_abs_divergence < 1e-5,
            "frame {}: mean |div u| {}",
            report.frame,
            report.mean_abs_divergence
        );
        assert!(
            report.divergence_rms_after <= 1e-5 * report.divergence_rms_before.max(1e-12) + 1e-9
        );
        assert!(
            report.max_speed > 1e-4,
            "frame {}: the fluid moves",
            report.frame
        );
    }

    // Every output the README promises.
    let expect = |relative: &str| {
        let path = run.join(relative);
        assert!(path.is_file(), "missing {}", path.display());
        assert!(
            std::fs::metadata(&path).unwrap().len() > 0,
            "empty {relative}"
        );
    };
    for file in [
        "config.toml",
        "run.json",
        "metrics.json",
        "losses.csv",
        "losses.png",
        "speed.png",
        "refine_moves.png",
        "psnr.png",
        "comparison.gif",
        "comparison.mp4",
        "slices.mp4",
        "exports/grid.pvd",
        "README.txt",
    ] {
        expect(file);
    }
    for t in 0..4 {
        for view in ["view00", "view01", "view02"] {
            expect(&format!("renders/{view}/frame_{t:03}.png"));
        }
        for file in [
            format!("comparison/frame_{t:03}.png"),
            format!("slices/frame_{t:03}.png"),
            format!("exports/gaussians_{t:03}.ply"),
            format!("exports/grid_{t:03}.vti"),
            format!("exports/grid_{t:03}.npz"),
            format!("frames/frame_{t:03}.safetensors"),
        ] {
            expect(&file);
        }
    }
    // The grid exports carry the refinement's move field where there was a refinement.
    for t in 0..4 {
        let file = std::fs::File::open(run.join(format!("exports/grid_{t:03}.npz"))).unwrap();
        let archive = zip::ZipArchive::new(file).unwrap();
        let mut names: Vec<&str> = archive.file_names().collect();
        names.sort_unstable();
        let mut want = vec![
            "density.npy",
            "hi.npy",
            "layout.npy",
            "lo.npy",
            "velocity.npy",
        ];
        if t > 0 {
            want.extend(["refine_move.npy", "refine_move_flow.npy"]);
            want.sort_unstable();
        }
        assert_eq!(names, want, "frame {t}");
    }
    // The move field's persistence needs a frame refined before.
    let field_persistence: Vec<bool> = reports
        .iter()
        .map(|r| {
            r.refine_move_flow_persistence.is_some()
                && r.refine_move_gathering_persistence.is_some()
        })
        .collect();
    assert_eq!(field_persistence, [false, false, true, true]);
    expect("checkpoints/frame_003/state.json");
    assert!(
        !run.join("checkpoints/frame_001").exists(),
        "only two checkpoints are kept"
    );
    let csv = std::fs::read_to_string(run.join("losses.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 100 + 3 * (15 + 5));
    // The configuration as given, with the scene the data set's scene.toml declares.
    let used: TrainConfig = TrainConfig::from_toml_file(&run.join("config.toml")).unwrap();
    let mut scene = config.scene.clone();
    assert!(
        scene.fill_from_data(&data).unwrap(),
        "synth writes a scene.toml"
    );
    assert_eq!(scene.open_faces, Some(vec!["y+".to_string()]));
    assert_eq!(used, TrainConfig { scene, ..config });

    // Evaluation re-renders the saved frames and compares with the ground truth.
    let report = eval::evaluate(&run, &device_by_name("flex").unwrap(), None).unwrap();
    assert_eq!(report.frames.len(), 4);
    let psnr = report.test_psnr_mean.unwrap();
    let expected_psnr = reports.iter().map(|r| r.test_psnr.unwrap()).sum::<f64>() / 4.0;
    assert!(
        (psnr - expected_psnr).abs() < 1e-3,
        "{psnr} vs {expected_psnr}"
    );
    let velocity_error = report.velocity_relative_error_mean.unwrap();
    eprintln!("velocity relative error {velocity_error:.3}");
    // A zero velocity scores exactly 1.0: below it, the recovered flow points with the truth.
    assert!(
        velocity_error < 0.95,
        "velocity relative error {velocity_error}"
    );
    // Direction alone: random directions average 0, the truth 1.
    let cosine = report.velocity_cosine_mean.unwrap();
    eprintln!("velocity cosine {cosine:.3}");
    assert!(cosine > 0.3 && cosine <= 1.0, "velocity cosine {cosine}");
    // Density against the truth from frame 0 on (the frame-alone baseline has only frame 0);
    // velocity from frame 1, since u^0 = 0 by construction.
    let first = &report.frames[0];
    assert!(first.velocity_relative_error.is_none() && first.velocity_cosine.is_none());
    let density_error = first.density_relative_error.unwrap();
    // An empty reconstruction scores exactly 1.0.
    assert!(
        density_error < 0.95,
        "frame-0 density error {density_error}"
    );
    let correlation = first.density_correlation.unwrap();
    eprintln!("frame-0 density: relative error {density_error:.3}, correlation {correlation:.3}");
    assert!(
        correlation > 0.5,
        "frame-0 density correlation {correlation}"
    );
    // The best factor can only bring the density nearer, and the haze is a share.
    let scaled = first.density_scaled_relative_error.unwrap();
    let outside = first.density_outside_smoke_fraction.unwrap();
    assert!(scaled <= density_error, "{scaled} > {density_error}");
    assert!(first.density_best_scale.unwrap() > 0.0);
    assert!((0.0..=1.0).contains(&outside), "share outside {outside}");
    assert!(run.join("eval.json").is_file());
    assert!(
        report
            .frames
            .iter()
            .all(|f| f.velocity_estimate_relative_error.is_none())
    );

    // The velocity estimated from the run's densities (the CLI), scored beside the run's own.
    let stdout = succeeded(binary().args(["velocity", "--quiet", "--run"]).arg(&run));
    assert!(stdout.contains("3 frames"), "{stdout}");
    let report = eval::evaluate(&run, &device_by_name("flex").unwrap(), None).unwrap();
    assert!(report.frames[0].velocity_estimate_relative_error.is_none());
    for frame in &report.frames[1..] {
        let error = frame.velocity_estimate_relative_error.unwrap();
        let divergence = frame.velocity_estimate_mean_abs_divergence.unwrap();
        eprintln!(
            "frame {}: estimate error {error:.3}, mean |div| {divergence:.2e}",
            frame.frame
        );
        assert!(error.is_finite() && frame.velocity_estimate_cosine.unwrap().is_finite());
    }
    assert!(report.velocity_estimate_relative_error_mean.is_some());
    // The same with a smoke solver's step as each fit's start: the source given, as a user
    // would whose run has no inflow box, and the forces it chose printed.
    let stdout = succeeded(
        binary()
            .args(["velocity", "--quiet", "--forces", "--inflow", "0.5"])
            .args(["--source-box", "0.3,0,0.3,0.7,0.3,0.7", "--run"])
            .arg(&run),
    );
    assert!(
        stdout.contains("3 frames") && stdout.contains("smoke step: inflow 0.5"),
        "{stdout}"
    );
    let report = eval::evaluate(&run, &device_by_name("flex").unwrap(), None).unwrap();
    let error = report.velocity_estimate_relative_error_mean.unwrap();
    assert!(error.is_finite(), "{error}");
    // A frame trained again leaves the estimate stale: eval refuses it rather than score it.
    let folder = gausmoke_train::RunFolder::at(&run);
    let info = folder.read_run_info().unwrap();
    let grid = used.grid(info.box_lo.into(), info.box_hi.into()).unwrap();
    let mut state = folder.read_frame_state(2, &grid).unwrap().unwrap();
    state.density[0] += 1.0;
    folder.write_frame_state(2, &grid, &state).unwrap();
    let error = eval::evaluate(&run, &device_by_name("flex").unwrap(), None)
        .unwrap_err()
        .to_string();
    assert!(error.contains("trained again"), "{error}");
}

fn binary() -> Command {
    Command::new(env!("CARGO_BIN_EXE_gausmoke-train"))
}

/// Runs `command`, asserts that it succeeded, and returns what it printed.
fn succeeded(command: &mut Command) -> String {
    let output = command.output().unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&output.stderr)
    );
    stdout
}

fn train_command(data: &Path, out: &Path) -> Command {
    let mut command = binary();
    command
        .args(["train", "--quiet", "--data"])
        .arg(data)
        .arg("--out")
        .arg(out);
    let config = test_config();
    for (key, value) in [
        ("gaussians", config.gaussians.to_string()),
        ("grid_resolution", config.grid_resolution.to_string()),
        ("frames", "4".to_string()),
        ("init.iterations", "60".to_string()),
        ("joint.iterations", "10".to_string()),
        ("refine.iterations", "4".to_string()),
        ("unet_channels", config.unet_channels.to_string()),
        ("time_frequencies", config.time_frequencies.to_string()),
        ("output.every", "100".to_string()),
        // Recycling and splitting on, so the resume test also covers them.
        ("population.recycle.fraction", "0.02".to_string()),
        ("population.recycle.threshold", "0.01".to_string()),
        ("population.split.fraction", "0.02".to_string()),
    ] {
        command.arg("--set").arg(format!("{key}={value}"));
    }
    command
}

fn final_state(run: &Path) -> std::collections::BTreeMap<String, (Vec<usize>, Vec<f32>)> {
    read_arrays(&run.join("frames/frame_003.safetensors")).unwrap()
}

#[test]
fn a_killed_run_resumes_to_the_uninterrupted_result() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());

    let straight = dir.path().join("straight");
    let status = train_command(&data, &straight).status().unwrap();
    assert!(status.success());

    let interrupted = dir.path().join("interrupted");
    let mut child = train_command(&data, &interrupted).spawn().unwrap();
    let marker = interrupted.join("checkpoints/frame_001/state.json");
    let start = Instant::now();
    while !marker.exists() {
        assert!(
            start.elapsed() < Duration::from_secs(600),
            "no checkpoint appeared"
        );
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run ended before it was killed"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(
        !interrupted.join("frames/frame_003.safetensors").exists(),
        "the kill came too late to test anything"
    );

    // Without --resume the folder is refused (no work is overwritten) ...
    let refused = train_command(&data, &interrupted).output().unwrap();
    assert!(!refused.status.success());
    assert!(String::from_utf8_lossy(&refused.stderr).contains("--resume"));
    // ... with it, training continues from the last complete frame.
    let resumed = train_command(&data, &interrupted)
        .arg("--resume")
        .output()
        .unwrap();
    assert!(
        resumed.status.success(),
        "{}",
        String::from_utf8_lossy(&resumed.stderr)
    );
    assert!(String::from_utf8_lossy(&resumed.stderr).contains("resumed"));

    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(straight.join("metrics.json")).unwrap())
            .unwrap();
    let count = |key: &str| -> u64 {
        metrics["per_frame"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f[key].as_u64().unwrap())
            .sum()
    };
    assert!(
        count("respawned") > 0,
        "no Gaussian was recycled: the test covers nothing"
    );
    assert!(
        count("split") > 0,
        "no Gaussian was split: the test covers nothing"
    );

    // The phase timings cover both sessions: every training render is counted once.
    let phases = |run: &Path| {
        let text = std::fs::read_to_string(run.join("metrics.json")).unwrap();
        serde_json::from_str::<serde_json::Value>(&text).unwrap()["phase_seconds"].clone()
    };
    // The refinement's persistence, measured against the frame before's moves, continues
    // across the resume: the checkpoint keeps them.
    let persistence = |run: &Path| -> Vec<serde_json::Value> {
        let text = std::fs::read_to_string(run.join("metrics.json")).unwrap();
        let metrics: serde_json::Value = serde_json::from_str(&text).unwrap();
        metrics["per_frame"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["refine_move_persistence"].clone())
            .collect()
    };
    let whole_persistence = persistence(&straight);
    assert!(whole_persistence[2].is_number(), "{whole_persistence:?}");
    let resumed_persistence = persistence(&interrupted);
    for (a, b) in whole_persistence.iter().zip(&resumed_persistence) {
        match (a.as_f64(), b.as_f64()) {
            (Some(a), Some(b)) => assert!((a - b).abs() < 1e-6, "{a} against {b}"),
            _ => assert_eq!(a, b, "{resumed_persistence:?}"),
        }
    }
    let (whole, resumed) = (phases(&straight), phases(&interrupted));
    assert!(whole["render"]["calls"].as_u64().unwrap() > 0, "{whole}");
    assert_eq!(
        whole["render"]["calls"], resumed["render"]["calls"],
        "{resumed}"
    );
    assert_eq!(
        whole["backward (all ops)"]["calls"],
        resumed["backward (all ops)"]["calls"]
    );

    let a = final_state(&straight);
    let b = final_state(&interrupted);
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (name, (shape, values)) in &a {
        let (other_shape, other) = &b[name];
        assert_eq!(shape, other_shape, "{name}");
        let scale = values.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
        let worst = largest_difference(values, other);
        assert!(
            worst <= 1e-5 * scale,
            "{name}: resumed differs by {worst} (scale {scale})"
        );
    }
}

#[test]
fn bad_options_and_data_are_reported_plainly() {
    let dir = tempfile::tempdir().unwrap();
    let out = binary()
        .args(["train", "--data", "/nonexistent/scene", "--out"])
        .arg(dir.path().join("run"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("/nonexistent/scene"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");

    let out = binary()
        .args(["train", "--set", "lamda_div=0.1", "--out"])
        .arg(dir.path().join("run2"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("lamda_div"), "{stderr}");

    let out = binary()
        .args(["train", "--set", "grid_resolution=30", "--out"])
        .arg(dir.path().join("run3"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("grid_resolution"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");

    // An I/O error's cause is quoted in its message, and not printed a second time.
    let out = binary()
        .args(["train", "--config", "/nonexistent/config.toml", "--out"])
        .arg(dir.path().join("run4"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        stderr.matches("No such file or directory").count(),
        1,
        "{stderr}"
    );

    // `eval` on a folder that is not a run says so.
    let out = binary()
        .args(["eval", "--run"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("is not a GauSmoke run"), "{stderr}");

    // `inspect --out` into a folder that does not exist names the write, not a decode.
    let data = tiny_scene(dir.path());
    let out = binary()
        .arg("inspect")
        .arg(&data)
        .arg("--out")
        .arg(dir.path().join("missing/sheet.png"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("sheet.png: cannot write image"), "{stderr}");

    // A configuration far beyond the machine's memory is refused before loading anything,
    // naming the setting; so is one above --max-memory.
    for (setting, named, limit) in [
        ("gaussians=40000000", "gaussians = 40000000", None),
        ("grid_resolution=512", "grid_resolution = 512", None),
        (
            "image_size=[100000,100000]",
            "image_size = [100000, 100000]",
            None,
        ),
        ("gaussians=1500", "gaussians = 1500", Some("1M")),
    ] {
        let mut command = train_command(&data, &dir.path().join("run6"));
        command.args(["--set", setting]);
        if let Some(limit) = limit {
            command.args(["--max-memory", limit]);
        }
        let out = command.output().unwrap();
        assert!(!out.status.success(), "{setting} was accepted");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            stderr.contains("memory: this configuration needs about") && stderr.contains(named),
            "{stderr}"
        );
        assert!(!dir.path().join("run6").exists(), "nothing was written");
    }

    // A frame range past the videos names the view.
    let out = train_command(&data, &dir.path().join("run5"))
        .args(["--frames", "50"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("frames of view `"), "{stderr}");
}

#[test]
fn a_diverging_run_stops_naming_the_quantity_and_keeps_the_last_frame() {
    // The largest velocity learning rate and time step accepted (1, a thousand times the
    // paper's rate; 10 frames a step): Phi's weights move by about 1 a step, the carried
    // centres overflow within a few joint iterations, and the run must stop at frame 1 with
    // frame 0 kept.
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let run = dir.path().join("run");
    let out = train_command(&data, &run)
        .args(["--set", "frames=2", "--set", "init.iterations=5"])
        .args([
            "--set",
            "learning_rates.velocity=1",
            "--set",
            "dt=10",
            "--set",
            "output.every=1",
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(stderr.contains("at frame 1"), "{stderr}");
    assert!(
        stderr.contains("velocity grid")
            || stderr.contains("loss")
            || stderr.contains("L_")
            || stderr.contains("the Gaussians'"),
        "names the quantity: {stderr}"
    );
    assert!(
        run.join("frames/frame_000.safetensors").exists(),
        "frame 0's checkpoint is kept"
    );
    assert!(!run.join("frames/frame_001.safetensors").exists());
}

#[test]
fn the_ablations_train_and_fit_the_held_out_view() {
    // "w/o volumetric rendering" (splat-opacity alpha) and the penalty form of Pi, each on two
    // frames: both must run end to end and fit the scene far better than the initialisation.
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    for (name, config) in [
        (
            "no-volumetric",
            TrainConfig {
                volumetric: false,
                frames: Some(2),
                ..test_config()
            },
        ),
        ("penalty", {
            let mut config = TrainConfig {
                frames: Some(2),
                scene: walls(),
                ..test_config()
            };
            config.projection.kind = gausmoke_train::config::ProjectionKind::Penalty;
            config
        }),
        ("respawn", {
            let mut config = TrainConfig {
                frames: Some(2),
                ..test_config()
            };
            config.population.recycle.fraction = 0.02;
            config.population.recycle.threshold = 0.01;
            config
        }),
    ] {
        let scene = Sequence::open(&data, &config).unwrap();
        let device = device_by_name("flex").unwrap().autodiff();
        let mut training = Run::new(scene.clone(), config, device, &dir.path().join(name), false)
            .unwrap()
            .quiet(true);
        let observation = &scene.test[0][0];
        let before = mean_abs_error(
            &training
                .trainer
                .render_host(std::slice::from_ref(observation))
                .unwrap()[0],
            observation.image.data(),
        );
        let reports = training.run().unwrap().to_vec();
        let after = reports[0].test_l1.unwrap();
        eprintln!(
            "{name}: held-out L1 {before:.4} -> {after:.4}; {:?}",
            reports[1]
        );
        assert!(after < 0.3 * before, "{name}: {before} -> {after}");
        assert!(
            reports[1].test_l1.unwrap() < 0.3 * before,
            "{name}: frame 1"
        );
        if name == "respawn" {
            // Frame 1's smoke is partly where frame 0's Gaussians, carried along, are not; at
            // most 2% of 1500 are moved.
            let moved = reports[1].respawned;
            assert!((1..=30).contains(&moved), "recycled {moved}");
        }
        if name == "penalty" {
            // The penalty form reduces the divergence of Phi's update without zeroing it.
            let r = &reports[1];
            assert!(r.divergence_rms_after < r.divergence_rms_before, "{r:?}");
        }
    }
}

/// Resuming with another data set (other cameras) is refused, naming both, and so is a changed
/// setting that shapes the state, naming it; the same data set under another path resumes
/// with changed learning rates and more frames; `run.json` records the absolute path and the
/// fingerprint.
#[test]
fn resume_refuses_other_data_and_names_changed_settings() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let other = dir.path().join("other");
    generate(
        &SynthConfig {
            camera_distance: SynthConfig::tiny().camera_distance * 1.1,
            ..SynthConfig::tiny()
        },
        &other,
    )
    .unwrap();
    let config = {
        let mut config = TrainConfig {
            frames: Some(1),
            ..test_config()
        };
        config.init.iterations = 5;
        config
    };
    let device = device_by_name("flex").unwrap().autodiff();
    let out = dir.path().join("run");
    let scene = Sequence::open(&data, &config).unwrap();
    let mut run = Run::new(scene, config.clone(), device.clone(), &out, false)
        .unwrap()
        .quiet(true);
    run.run().unwrap();
    drop(run);
    let info = gausmoke_train::RunFolder::at(&out).read_run_info().unwrap();
    assert!(info.data.is_absolute(), "{}", info.data.display());
    assert!(info.data_fingerprint.is_some());

    let elsewhere = Sequence::open(&other, &config).unwrap();
    let Err(err) = Run::new(elsewhere, config.clone(), device.clone(), &out, true) else {
        panic!("resuming on another data set was accepted");
    };
    let message = err.to_string();
    assert!(
        message.contains("--data") && message.contains("other") && message.contains("data"),
        "{message}"
    );
    // Without run.json the checkpoint's own record of the data still refuses it.
    let run_json = out.join("run.json");
    let kept = std::fs::read(&run_json).unwrap();
    std::fs::remove_file(&run_json).unwrap();
    let elsewhere = Sequence::open(&other, &config).unwrap();
    let Err(err) = Run::new(elsewhere, config.clone(), device.clone(), &out, true) else {
        panic!("resuming on another data set without run.json was accepted");
    };
    assert!(err.to_string().contains("not the data set"), "{err}");
    std::fs::write(&run_json, kept).unwrap();

    // A setting that changes what was trained is named, before any tensor is loaded (a
    // different Gaussian count used to fail inside the record loader).
    let more = TrainConfig {
        gaussians: config.gaussians + 1,
        ..config.clone()
    };
    let scene = Sequence::open(&data, &more).unwrap();
    let Err(err) = Run::new(scene, more, device.clone(), &out, true) else {
        panic!("resuming with another Gaussian count was accepted");
    };
    assert!(
        err.to_string()
            .contains("gaussians = 1500 in the run, 1501 now"),
        "{err}"
    );

    // A setting that chooses what is read of the data (and so its fingerprint) is named,
    // not reported as other data.
    let smaller = TrainConfig {
        image_size: Some([32, 48]),
        ..config.clone()
    };
    let scene = Sequence::open(&data, &smaller).unwrap();
    let Err(err) = Run::new(scene, smaller, device.clone(), &out, true) else {
        panic!("resuming with another image size was accepted");
    };
    let message = err.to_string();
    assert!(
        message.contains("image_size = (unset) in the run, [32, 48] now")
            && !message.contains("not the data set"),
        "{message}"
    );

    // The same data through another path (a relative one) resumes, with gentler learning
    // rates and more frames: the settings a diverged or finished run may change.
    let relative = pathdiff_relative(&data);
    let extended = {
        let mut config = TrainConfig {
            frames: Some(2),
            ..config
        };
        config.learning_rates.gaussians /= 2.0;
        config.learning_rates.velocity /= 2.0;
        config
    };
    let same = Sequence::open(&relative, &extended).unwrap();
    let mut resumed = Run::new(same, extended.clone(), device.clone(), &out, true)
        .expect("the same data set resumes")
        .quiet(true);
    assert_eq!(
        resumed.run().unwrap().len(),
        2,
        "frame 1 trained after the resume"
    );
    drop(resumed);
    // Past frame 0, another length would give the trained frames other times.
    let longer = TrainConfig {
        frames: Some(3),
        ..extended.clone()
    };
    let scene = Sequence::open(&data, &longer).unwrap();
    let Err(err) = Run::new(scene, longer, device, &out, true) else {
        panic!("resuming a two-frame run as three frames was accepted");
    };
    assert!(
        err.to_string()
            .contains("run of 2 frames and this one has 3"),
        "{err}"
    );
}

/// `path` relative to the current directory, through `..` components.
fn pathdiff_relative(path: &Path) -> PathBuf {
    let cwd = std::env::current_dir().unwrap();
    let depth = cwd.components().count() - 1;
    let mut relative = PathBuf::new();
    for _ in 0..depth {
        relative.push("..");
    }
    relative.join(path.strip_prefix("/").unwrap())
}

/// A view with fewer frames than the others is refused, naming it and both counts.
#[test]
fn views_with_different_frame_counts_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let mut dataset =
        gausmoke_data::load_pinf(&data, &gausmoke_data::LoadOptions::default()).unwrap();
    let config = test_config();
    let full = dataset.views[0].frames.len();
    Sequence::from_dataset(&data, &dataset, &config).expect("the untouched scene opens");
    let shortened = dataset.views[1].name.clone();
    dataset.views[1].frames.pop();
    let err = Sequence::from_dataset(&data, &dataset, &config).unwrap_err();
    let message = err.to_string();
    assert!(
        message.contains(&format!("view `{shortened}` has {} frames", full - 1))
            && message.contains(&format!("has {full}")),
        "{message}"
    );
}

/// `--out` pointing at a folder of someone's files is refused before anything is written.
#[test]
fn a_folder_that_is_not_a_run_is_not_written_over() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let out = dir.path().join("papers");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("config.toml"), "my own notes").unwrap();
    let config = test_config();
    let scene = Sequence::open(&data, &config).unwrap();
    let device = device_by_name("flex").unwrap().autodiff();
    let Err(err) = Run::new(scene, config, device, &out, false) else {
        panic!("a foreign folder was accepted as --out");
    };
    assert!(err.to_string().contains("holds no GauSmoke run"), "{err}");
    assert_eq!(
        std::fs::read_to_string(out.join("config.toml")).unwrap(),
        "my own notes"
    );
    assert_eq!(
        std::fs::read_dir(&out).unwrap().count(),
        1,
        "nothing was added"
    );
}

/// Tiny settings for the tests of run folders and checkpoints: what is trained hardly matters.
fn brief_config(frames: usize) -> TrainConfig {
    {
        let mut config = TrainConfig {
            frames: Some(frames),
            ..test_config()
        };
        config.init.iterations = 5;
        config.joint.iterations = 3;
        config.refine.iterations = 1;
        config
    }
}

/// A finished run of [`brief_config`] on the tiny scene, and what made it.
struct BriefRun {
    data: PathBuf,
    config: TrainConfig,
    device: burn::tensor::Device,
    out: PathBuf,
    scene: Sequence,
}

fn brief_run(dir: &Path, frames: usize) -> BriefRun {
    let data = tiny_scene(dir);
    let config = brief_config(frames);
    let device = device_by_name("flex").unwrap().autodiff();
    let out = dir.join("run");
    let scene = Sequence::open(&data, &config).unwrap();
    Run::new(scene.clone(), config.clone(), device.clone(), &out, false)
        .unwrap()
        .quiet(true)
        .run()
        .unwrap();
    BriefRun {
        data,
        config,
        device,
        out,
        scene,
    }
}

/// A second run on a folder another run is training into is refused, naming the holder; the
/// lock goes with the first run.
#[test]
fn two_runs_cannot_train_into_one_folder() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let config = brief_config(1);
    let device = device_by_name("flex").unwrap().autodiff();
    let out = dir.path().join("run");
    let scene = Sequence::open(&data, &config).unwrap();
    let first = Run::new(scene.clone(), config.clone(), device.clone(), &out, false).unwrap();
    let Err(err) = Run::new(scene.clone(), config.clone(), device.clone(), &out, false) else {
        panic!("a second run on the same folder was accepted");
    };
    let message = err.to_string();
    assert!(
        message.contains("another process is training into this folder")
            && message.contains(&std::process::id().to_string()),
        "{message}"
    );
    drop(first);
    Run::new(scene, config, device, &out, false).expect("the folder is free again");
}

fn flip_bytes(path: &Path) {
    let mut bytes = std::fs::read(path).unwrap();
    let middle = bytes.len() / 2;
    for byte in &mut bytes[middle..middle + 16] {
        *byte ^= 0x5a;
    }
    std::fs::write(path, bytes).unwrap();
}

/// A damaged newest checkpoint (bytes flipped in place: the file still parses) is detected by
/// its checksum and the run resumes from the one before, saying so; a leftover partial folder
/// is removed; with every checkpoint damaged the resume is refused, naming the files.
#[test]
fn a_damaged_checkpoint_falls_back_to_the_one_before() {
    let dir = tempfile::tempdir().unwrap();
    let BriefRun {
        config,
        device,
        out,
        scene,
        ..
    } = brief_run(dir.path(), 3);
    let checkpoints = out.join("checkpoints");
    assert!(checkpoints.join("frame_001").is_dir() && checkpoints.join("frame_002").is_dir());
    let intact = std::fs::read(checkpoints.join("frame_002/gaussians.bpk")).unwrap();

    flip_bytes(&checkpoints.join("frame_002/gaussians.bpk"));
    let leftover = checkpoints.join(".frame_003.partial");
    std::fs::create_dir_all(&leftover).unwrap();
    std::fs::write(leftover.join("phi.bpk"), b"half").unwrap();

    let mut resumed = Run::new(scene.clone(), config.clone(), device.clone(), &out, true)
        .expect("the older checkpoint resumes")
        .quiet(true);
    assert_eq!(
        resumed.frame,
        Some(1),
        "resumed from frame 1, not the damaged frame 2"
    );
    assert!(!leftover.exists(), "the partial folder was removed");
    assert_eq!(resumed.run().unwrap().len(), 3);
    drop(resumed);
    let retrained = std::fs::read(checkpoints.join("frame_002/gaussians.bpk")).unwrap();
    assert_eq!(
        retrained, intact,
        "frame 2 trained again from frame 1 gives the same Gaussians"
    );

    // An edited state.json (a figure of its history) fails its own checksum.
    let state = checkpoints.join("frame_002/state.json");
    let text = std::fs::read_to_string(&state).unwrap();
    assert!(text.contains("\"state_checksum\""), "sealed");
    std::fs::write(
        &state,
        text.replacen("\"elapsed_seconds\": ", "\"elapsed_seconds\": 1", 1),
    )
    .unwrap();
    let resumed = Run::new(scene.clone(), config.clone(), device.clone(), &out, true)
        .expect("the older checkpoint resumes");
    assert_eq!(resumed.frame, Some(1), "the edited frame 2 is not resumed");
    drop(resumed);
    std::fs::write(&state, text).unwrap();

    flip_bytes(&checkpoints.join("frame_001/velocity.safetensors"));
    flip_bytes(&checkpoints.join("frame_002/phi.bpk"));
    let Err(err) = Run::new(scene, config, device, &out, true) else {
        panic!("a run whose checkpoints are all damaged was resumed");
    };
    let message = err.to_string();
    assert!(
        message.contains("no intact checkpoint")
            && message.contains("frame_002/phi.bpk")
            && message.contains("frame_001/velocity.safetensors")
            && message.contains("damaged"),
        "{message}"
    );
}

/// A frame file the run wrote and then lost is refused by name: by `eval` (which would
/// score fewer frames), by `--resume` (which trains only the frames after its checkpoint),
/// wherever it is missing.
#[test]
fn a_lost_frame_file_is_refused_by_eval_and_resume() {
    let dir = tempfile::tempdir().unwrap();
    let BriefRun {
        data,
        config,
        device,
        out,
        scene,
    } = brief_run(dir.path(), 3);
    let flex = device_by_name("flex").unwrap();
    for lost in [1, 2] {
        let path = out.join(format!("frames/frame_{lost:03}.safetensors"));
        let kept = std::fs::read(&path).unwrap();
        std::fs::remove_file(&path).unwrap();
        let error = eval::evaluate(&out, &flex, None).unwrap_err().to_string();
        assert!(
            error.contains(&format!("frame_{lost:03}.safetensors")) && error.contains("missing"),
            "{error}"
        );
        if lost == 1 {
            // Frame 1 lies before the newest checkpoint (frame 2).
            let Err(err) = Run::new(scene.clone(), config.clone(), device.clone(), &out, true)
            else {
                panic!("a resume over a lost frame file was accepted");
            };
            assert!(err.to_string().contains("frame_001.safetensors"), "{err}");
        }
        std::fs::write(&path, kept).unwrap();
    }
    assert_eq!(eval::evaluate(&out, &flex, None).unwrap().frames.len(), 3);
    // Other data generated at the run's data path is refused, not scored.
    std::fs::remove_dir_all(&data).unwrap();
    generate(
        &SynthConfig {
            camera_distance: SynthConfig::tiny().camera_distance * 1.1,
            ..SynthConfig::tiny()
        },
        &data,
    )
    .unwrap();
    let error = eval::evaluate(&out, &flex, None).unwrap_err().to_string();
    assert!(error.contains("no longer the data set"), "{error}");
}

/// A picture far brighter than every other view's at the same time (what a damaged video frame
/// that still parses decodes to) is reported, naming the view and frame; the clean scene is not.
#[test]
fn a_picture_unlike_the_other_views_is_reported() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let config = test_config();
    let scene = Sequence::open(&data, &config).unwrap();
    assert!(
        gausmoke_train::sequence::implausible_pictures(&scene.train, &scene.test).is_empty(),
        "the clean scene has no outlier"
    );
    let mut damaged = scene.clone();
    for t in 1..3 {
        let picture = &mut damaged.train[t][1];
        let (w, h) = (picture.image.width(), picture.image.height());
        let garbage = (0..picture.image.data().len())
            .map(|i| (i * 7919 % 101) as f32 / 100.0)
            .collect();
        picture.image = gausmoke_data::Image::from_vec(w, h, garbage).unwrap();
    }
    let found = gausmoke_train::sequence::implausible_pictures(&damaged.train, &damaged.test);
    assert_eq!(found.len(), 1, "{found:?}");
    assert_eq!(
        (found[0].view.as_str(), found[0].frame, found[0].count),
        (scene.train[1][1].view.as_str(), 1, 2)
    );
}

/// A black picture in one view's video (what a lost frame decodes to) stands out from that
/// view's own frames before and after it, even where the scene is dark; the clean scene has
/// none.
#[test]
fn a_black_picture_in_a_video_is_reported() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let config = TrainConfig {
        frames: Some(8),
        ..test_config()
    };
    let scene = Sequence::open(&data, &config).unwrap();
    let clean = gausmoke_train::sequence::sudden_changes(&scene.train, &scene.test);
    assert!(clean.is_empty(), "{clean:?}");
    let mut damaged = scene.clone();
    let picture = &mut damaged.train[4][0];
    let (w, h) = (picture.image.width(), picture.image.height());
    picture.image = gausmoke_data::Image::from_vec(w, h, vec![0.0; (w * h * 3) as usize]).unwrap();
    let found = gausmoke_train::sequence::sudden_changes(&damaged.train, &damaged.test);
    let frames: Vec<(&str, usize)> = found.iter().map(|f| (f.view.as_str(), f.frame)).collect();
    let view = scene.train[4][0].view.as_str();
    assert!(frames.contains(&(view, 4)), "{found:?}");
    assert!(frames.iter().all(|&(v, _)| v == view), "{found:?}");
}

/// A full disk, simulated with a file-size limit (writes past it fail with EFBIG), stops the
/// run with an error naming the file, leaves no partial checkpoint or half file behind, and the
/// run resumes from its last complete frame once there is room.
#[cfg(target_os = "linux")]
#[test]
fn a_full_disk_stops_the_run_without_losing_work() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let out = dir.path().join("run");
    let trained = train_command(&data, &out);
    // bash counts `ulimit -f` in KiB; an ignored SIGXFSZ turns the limit into write errors.
    let mut limited = Command::new("bash");
    limited
        .arg("-c")
        .arg("ulimit -f 600; trap '' XFSZ; exec \"$0\" \"$@\"")
        .arg(trained.get_program())
        .args(trained.get_args());
    let failed = limited.output().unwrap();
    let stderr = String::from_utf8_lossy(&failed.stderr);
    assert!(
        !failed.status.success(),
        "the 600 KiB limit did not bite: {stderr}"
    );
    assert!(
        stderr.contains("Error:") && !stderr.contains("panicked"),
        "{stderr}"
    );
    let leftovers: Vec<_> = walk(&out)
        .into_iter()
        .filter(|path| path.to_string_lossy().contains(".partial"))
        .collect();
    assert!(leftovers.is_empty(), "left behind: {leftovers:?}");

    let resumed = train_command(&data, &out).arg("--resume").output().unwrap();
    assert!(
        resumed.status.success(),
        "{}",
        String::from_utf8_lossy(&resumed.stderr)
    );
    assert!(out.join("frames/frame_003.safetensors").is_file());
}

fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let path = entry.path();
        if path.is_dir() {
            found.extend(walk(&path));
        }
        found.push(path);
    }
    found
}

/// `first_frame` starts the run at a later frame of the data (the independent per-frame
/// baseline): its frame 0 holds the data's frame `first_frame`, for every view; without
/// `frames` it is refused.
#[test]
fn first_frame_starts_the_run_later_in_the_data() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let full = Sequence::open(&data, &test_config()).unwrap();
    let later = TrainConfig {
        first_frame: 2,
        frames: Some(1),
        ..test_config()
    };
    let alone = Sequence::open(&data, &later).unwrap();
    assert_eq!((alone.frames(), alone.first_frame), (1, 2));
    for (a, b) in alone.train[0]
        .iter()
        .chain(&alone.test[0])
        .zip(full.train[2].iter().chain(&full.test[2]))
    {
        assert_eq!(a.view, b.view);
        assert_eq!(a.image.data(), b.image.data(), "view {}", a.view);
    }
    assert_ne!(alone.fingerprint(), full.fingerprint());
    let unbounded = TrainConfig {
        first_frame: 2,
        frames: None,
        ..test_config()
    };
    let err = unbounded.validate().unwrap_err().to_string();
    assert!(err.contains("first_frame = 2 needs frames"), "{err}");
}

/// Three frames of the tiny scene at small sizes, for tests of the joint iterations' terms.
fn joint_terms_config() -> TrainConfig {
    {
        let mut config = TrainConfig {
            gaussians: 400,
            grid_resolution: 8,
            frames: Some(3),
            unet_channels: 4,
            time_frequencies: 2,
            ..TrainConfig::default()
        };
        config.init.iterations = 10;
        config.joint.iterations = 3;
        config.refine.iterations = 1;
        config
    }
}

/// A run of `config` on `data` (flex, quiet) in `dir/name`, not trained yet.
fn quiet_run(data: &Path, dir: &Path, config: TrainConfig, name: &str) -> Run {
    let scene = Sequence::open(data, &config).unwrap();
    let device = device_by_name("flex").unwrap().autodiff();
    Run::new(scene, config, device, &dir.join(name), false)
        .unwrap()
        .quiet(true)
}

/// Why a run of `config` on `data` (flex) in `dir/name` is refused; panics when it is not.
fn refusal(data: &Path, dir: &Path, config: TrainConfig, name: &str) -> String {
    let scene = Sequence::open(data, &config).unwrap();
    let device = device_by_name("flex").unwrap().autodiff();
    Run::new(scene, config, device, &dir.join(name), false)
        .err()
        .unwrap_or_else(|| panic!("{name}: the run was not refused"))
        .to_string()
}

/// A run of `config` on `data` (flex, quiet) in `dir/name`, frame 0 fitted.
fn after_frame_0(data: &Path, dir: &Path, config: TrainConfig, name: &str) -> Run {
    let mut run = quiet_run(data, dir, config, name);
    run.trainer.fit_first_frame().unwrap();
    run
}

/// The velocity grid after training `config` on `data` (flex), the run in `dir/name`.
fn velocity_after(data: &Path, dir: &Path, config: TrainConfig, name: &str) -> Vec<f32> {
    let run = trained(data, dir, config, name);
    let velocity = run.trainer.state.velocity.clone().into_data();
    velocity.try_into_vec_as::<f32>().unwrap()
}

#[test]
fn the_look_ahead_changes_the_velocity() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let base = joint_terms_config();
    let without = velocity_after(&data, dir.path(), base.clone(), "without");
    let with = velocity_after(
        &data,
        dir.path(),
        {
            let mut config = base;
            config.joint.look_ahead.weight = 1.0;
            config
        },
        "with",
    );
    assert!(with.iter().all(|v| v.is_finite()));
    assert!(
        largest_difference(&with, &without) > 0.0,
        "the look-ahead term changed nothing"
    );
}

/// The refinement's move is reported per frame (its length and how much of it is at the
/// velocity grid's scale), and `refine.lambda_grid` (ours) ties its grid-scale part: the
/// tied move is shorter and less of its mean square is grid-scale.
#[test]
fn the_refinement_moves_can_be_tied_at_the_grid_scale() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let frame_1 = |set: fn(&mut TrainConfig), name| {
        let mut config = {
            let mut config = TrainConfig {
                frames: Some(2),
                ..joint_terms_config()
            };
            config.refine.iterations = 10;
            config
        };
        set(&mut config);
        let mut run = after_frame_0(&data, dir.path(), config, name);
        let outcome = run.trainer.advance_to(1).unwrap();
        outcome
            .refine_moves
            .expect("refinement on: its moves are reported")
    };
    let free = frame_1(|_| {}, "free");
    assert!(
        free.rms_cells > 0.0,
        "the refinement moved nothing: {free:?}"
    );
    assert!((0.0..=1.0).contains(&free.shuffled_grid_share), "{free:?}");
    assert_eq!(
        free.persistence, None,
        "the first frame refined has none before it"
    );
    let grid_tied = frame_1(|c| c.refine.lambda_grid = 1e4, "grid tied");
    assert!(
        grid_tied.grid_share < free.grid_share,
        "tying the grid-scale part: {grid_tied:?} against free {free:?}"
    );
    assert!(
        grid_tied.rms_cells < free.rms_cells,
        "{grid_tied:?} against free {free:?}"
    );
    let none = {
        let config = {
            let mut config = TrainConfig {
                frames: Some(2),
                ..joint_terms_config()
            };
            config.refine.iterations = 0;
            config
        };
        let mut run = after_frame_0(&data, dir.path(), config, "no refinement");
        run.trainer.advance_to(1).unwrap().refine_moves
    };
    assert_eq!(none, None, "without refinement there is no move to report");
}

/// Two runs of one configuration stepped in turn in one process repeat each other: what one
/// draws from the backend's generator (Phi's initial weights, drawn when Phi is made) does not
/// move the other's.
#[test]
fn two_runs_stepped_in_turn_repeat_each_other() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let config = TrainConfig {
        frames: Some(2),
        ..joint_terms_config()
    };
    let mut first = quiet_run(&data, dir.path(), config.clone(), "first");
    let mut second = quiet_run(&data, dir.path(), config, "second");
    for t in 0..2 {
        let first = first.train_frame(t).unwrap().test_psnr;
        let second = second.train_frame(t).unwrap().test_psnr;
        assert_eq!(first, second, "frame {t}");
    }
    let state = |run: &Run| run.trainer.state.gaussians.to_host();
    assert_eq!(state(&first), state(&second));
}

/// `refine.views_per_step` (ours): each refinement step renders that many training views in
/// turn. With no joint iterations the first step starts from frame 0's fit, so its logged L1
/// is known: view 0's alone with one view per step, the mean over the views with all. More
/// views per step than the data set has is refused, naming the setting.
#[test]
fn a_refinement_step_can_render_some_of_the_views() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let config = |per_step| {
        let mut config = TrainConfig {
            frames: Some(2),
            ..joint_terms_config()
        };
        config.joint.iterations = 0;
        config.refine.iterations = 2;
        config.refine.views_per_step = per_step;
        config.output.log_every = 1;
        config
    };
    let first_refine_l1 = |per_step, name| {
        let mut run = after_frame_0(&data, dir.path(), config(per_step), name);
        let views = run.trainer.sequence.train[1].clone();
        let renders = run.trainer.render_host(&views).unwrap();
        let per_view: Vec<f32> = views
            .iter()
            .zip(&renders)
            .map(|(view, render)| mean_abs_error(render, view.image.data()) as f32)
            .collect();
        let outcome = run.trainer.advance_to(1).unwrap();
        let rows: Vec<_> = outcome
            .losses
            .iter()
            .filter(|row| row.phase == Phase::Refine)
            .collect();
        assert_eq!(rows.len(), 2, "{name}: {rows:?}");
        assert!(rows.iter().all(|row| row.render.is_finite()), "{rows:?}");
        (rows[0].render, per_view)
    };
    let (one, per_view) = first_refine_l1(1, "one view");
    assert!(per_view.len() >= 2, "the tiny scene trains on {per_view:?}");
    assert!(
        (one - per_view[0]).abs() < 1e-4 * per_view[0],
        "one view per step: {one}, view 0 alone {per_view:?}"
    );
    let (all, per_view) = first_refine_l1(0, "all views");
    let mean = per_view.iter().sum::<f32>() / per_view.len() as f32;
    assert!(
        (all - mean).abs() < 1e-4 * mean,
        "all views: {all}, their mean {mean} ({per_view:?})"
    );
    assert!(
        (per_view[0] - mean).abs() > 1e-3 * mean,
        "the views' L1 are too alike to tell one from all: {per_view:?}"
    );
    // More views per step than the data set has is refused.
    let err = refusal(&data, dir.path(), config(per_view.len() + 1), "too many");
    assert!(err.contains("refine.views_per_step"), "{err}");
}

#[test]
fn the_velocity_is_carried_along_itself_before_phi_when_asked() {
    use gausmoke_model::{ProjectionOptions, grid_from_fn, project_direct, transport_velocity};
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    // Phi's output layer starts at zero and a negligible learning rate (zero is refused)
    // keeps it there, so frame 1's velocity is the projected previous one, carried along
    // itself or not.
    let config = {
        let mut config = TrainConfig {
            frames: Some(2),
            scene: walls(),
            ..joint_terms_config()
        };
        config.learning_rates.velocity = 1e-20;
        config
    };
    let frame_one = |transport: bool, name: &str| {
        let config = {
            let mut config = config.clone();
            config.joint.transport_velocity = transport;
            config
        };
        let mut run = after_frame_0(&data, dir.path(), config, name);
        let grid = run.trainer.grid;
        // A swirl about the box's vertical axis, over a cell per frame at the rim.
        let centre = (grid.lo() + grid.hi()) * 0.5;
        let omega = 2.5 * grid.cell_size().x / (grid.hi().x - grid.lo().x);
        let swirl = grid_from_fn(&grid, &run.trainer.device, |x| {
            [-omega * (x[2] - centre.z), 0.0, omega * (x[0] - centre.x)]
        });
        run.trainer.state.velocity = swirl.clone();
        run.trainer.advance_to(1).unwrap();
        let after = run.trainer.state.velocity.clone().into_data();
        (grid, swirl, after.try_into_vec_as::<f32>().unwrap())
    };
    let (grid, swirl, carried) = frame_one(true, "carried");
    let (_, _, held) = frame_one(false, "held");
    let projected = |mut field: Vec<f32>| {
        project_direct(&grid, &mut field, &ProjectionOptions::default());
        field
    };
    let host = |t: burn::tensor::Tensor<4>| t.into_data().try_into_vec_as::<f32>().unwrap();
    let expected_carried = projected(host(transport_velocity(&grid, &swirl, 1.0)));
    let expected_held = projected(host(swirl));
    let scale = expected_held.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(
        largest_difference(&carried, &expected_carried) < 1e-4 * scale,
        "with transport, frame 1 is not Pi(A(u^0))"
    );
    assert!(
        largest_difference(&held, &expected_held) < 1e-4 * scale,
        "without transport, frame 1 is not Pi(u^0)"
    );
    let apart = largest_difference(&expected_carried, &expected_held);
    assert!(apart > 0.05 * scale, "the swirl barely moved ({apart})");
}

#[test]
fn the_inertia_prior_slows_the_velocity() {
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let mean_square = |velocity: Vec<f32>| {
        velocity.iter().map(|v| f64::from(v * v)).sum::<f64>() / velocity.len() as f64
    };
    let free = mean_square(velocity_after(
        &data,
        dir.path(),
        joint_terms_config(),
        "free",
    ));
    // The velocity starts at zero, so holding Phi's increments back slows it too.
    let priors = [("inertia", {
        let mut config = joint_terms_config();
        config.joint.inertia.weight = 10.0;
        config
    })];
    for (name, config) in priors {
        let held = mean_square(velocity_after(&data, dir.path(), config, name));
        assert!(free > 0.0 && held.is_finite(), "{name}: {free} {held}");
        assert!(
            held < free,
            "mean |u|^2: {held} with the {name} prior, {free} without"
        );
    }
}

/// A data set with an obstacle: its cells are solid in the trained velocity (no flow in
/// them), no Gaussian's centre stays inside it, eval reports the leakage into it, `obstacles = "ignore"` lets the flow through,
/// and the penalty form, which cannot keep the flow out, is refused naming the setting.
#[test]
fn obstacles_of_the_data_set_are_solid_in_the_trained_velocity() {
    use gausmoke_train::config::{Obstacles, ProjectionKind};
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    generate(
        &SynthConfig {
            frames: 3,
            solids: SynthConfig::obstacle_plume().solids,
            ..SynthConfig::tiny()
        },
        &data,
    )
    .unwrap();
    let config = {
        let mut config = TrainConfig {
            frames: Some(3),
            scene: gausmoke_train::scene::SceneConfig {
                open_faces: Some(vec!["y+".into()]),
                ..Default::default()
            },
            ..test_config()
        };
        config.init.iterations = 40;
        config.joint.iterations = 8;
        config.refine.iterations = 2;
        config
    };
    let device = device_by_name("flex").unwrap().autodiff();
    let mut inside_speed = Vec::new();
    for obstacles in [Obstacles::Solid, Obstacles::Ignore] {
        let config = {
            let mut config = config.clone();
            config.projection.obstacles = obstacles;
            config
        };
        let scene = Sequence::open(&data, &config).unwrap();
        assert_eq!(scene.obstacles.len(), 1);
        let run = dir.path().join(format!("run-{obstacles:?}"));
        let mut training = Run::new(scene, config.clone(), device.clone(), &run, false)
            .unwrap()
            .quiet(true);
        let solids = training.trainer.solid_cells().cloned();
        assert_eq!(solids.is_some(), obstacles == Obstacles::Solid);
        training.run().unwrap();
        drop(training);
        let arrays = read_arrays(&run.join("frames/frame_002.safetensors")).unwrap();
        let velocity = &arrays["velocity"].1;
        let grid = config
            .grid(
                gausmoke_data::synth::world_box().0,
                gausmoke_data::synth::world_box().1,
            )
            .unwrap();
        let obstacle = SynthConfig::obstacle_plume().solids[0].shape;
        let inside = SolidCells::new(
            grid.resolution(),
            grid.cells_where(|p| obstacle.contains(p)),
        )
        .unwrap();
        assert!(inside.count() > 20);
        if let Some(solids) = &solids {
            assert_eq!(solids, &inside);
        }
        inside_speed.push(inside.speed_inside(velocity));
        let centres_inside = arrays["means"]
            .1
            .chunks(3)
            .filter(|m| obstacle.signed_distance(gausmoke_data::glam::Vec3::from_slice(m)) < 0.0)
            .count();
        if obstacles == Obstacles::Solid {
            assert_eq!(
                centres_inside, 0,
                "Gaussian centres inside the solid obstacle"
            );
        } else {
            assert!(centres_inside > 0, "ignored, the obstacle holds Gaussians");
        }
        // The velocity estimated from the run's densities keeps out of the obstacle too, and
        // eval scores its flow at the surface beside the run's.
        let flex = device_by_name("flex").unwrap();
        gausmoke_train::velocity_estimate::estimate_run_velocity(
            &run,
            &Default::default(),
            &flex,
            |_, _| {},
        )
        .unwrap();
        for t in 1..3 {
            let path = gausmoke_train::velocity_estimate::estimate_path(&run, t);
            let estimate = &read_arrays(&path).unwrap()["velocity"].1;
            let speed = inside.speed_inside(estimate);
            if obstacles == Obstacles::Solid {
                assert_eq!(
                    speed, 0.0,
                    "estimate at frame {t} inside the solid obstacle"
                );
            }
        }
        let report = eval::evaluate(&run, &flex, None).unwrap();
        let fraction = report.obstacle_density_fraction_mean.unwrap();
        let normal = report.obstacle_normal_flow_mean.unwrap();
        let estimate_normal = report.velocity_estimate_obstacle_normal_flow_mean.unwrap();
        eprintln!(
            "{obstacles:?}: density inside {fraction:.4}, normal flow {normal:.3}, the \
             estimate's {estimate_normal:.3}"
        );
        assert!((0.0..=1.0).contains(&fraction) && (0.0..=1.0).contains(&normal));
        assert!((0.0..=1.0).contains(&estimate_normal));
        assert!(report.frames[0].obstacle_normal_flow.is_none());
        assert!(
            report.frames[0]
                .velocity_estimate_obstacle_normal_flow
                .is_none()
        );
    }
    assert_eq!(inside_speed[0], 0.0, "velocity inside the solid obstacle");
    assert!(inside_speed[1] > 0.0, "ignored, the obstacle holds no flow");

    let penalty = {
        let mut config = TrainConfig {
            scene: gausmoke_train::scene::SceneConfig {
                open_faces: Some(Vec::new()),
                ..Default::default()
            },
            ..config.clone()
        };
        config.projection.kind = ProjectionKind::Penalty;
        config
    };
    let scene = Sequence::open(&data, &penalty).unwrap();
    let err = match Run::new(scene, penalty, device, &dir.path().join("penalty"), false) {
        Ok(_) => panic!("the penalty form was accepted with obstacles"),
        Err(e) => e.to_string(),
    };
    assert!(err.contains("obstacles") && err.contains("exact"), "{err}");

    // An obstacle too small for the grid to see is refused, not silently dropped.
    let info = data.join("info.json");
    let text = std::fs::read_to_string(&info).unwrap();
    let gausmoke_data::Obstacle::Sphere { radius, .. } =
        SynthConfig::obstacle_plume().solids[0].shape
    else {
        panic!("the obstacle preset's solid is a sphere");
    };
    let tiny = text.replace(&format!("\"radius\": {radius}"), "\"radius\": 0.001");
    assert_ne!(tiny, text, "the radius was not found in {text}");
    std::fs::write(&info, tiny).unwrap();
    let scene = Sequence::open(&data, &config).unwrap();
    let err = match Run::new(
        scene,
        config.clone(),
        device_by_name("flex").unwrap().autodiff(),
        &dir.path().join("tiny"),
        false,
    ) {
        Ok(_) => panic!("an obstacle covering no cell was accepted"),
        Err(e) => e.to_string(),
    };
    assert!(
        err.contains("obstacles") && err.contains("no cell"),
        "{err}"
    );
}

/// Static Gaussians on the ball scene: placed in the ball the data set describes, fitted
/// before frame 0 (their own loss rows), rendered
/// with the smoke (the held-out view is better than without them where the ball is the only
/// thing the smoke Gaussians would otherwise have to explain), never advected, written to
/// every frame file and exported, and resumed from a checkpoint to what an uninterrupted run
/// reaches.
#[test]
fn static_gaussians_fit_the_ball_and_resume() {
    use gausmoke_train::state::Phase;
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    generate(
        &SynthConfig {
            frames: 3,
            ..SynthConfig {
                grid: 24,
                width: 64,
                height: 96,
                views: 3,
                ..SynthConfig::ball_plume()
            }
        },
        &data,
    )
    .unwrap();
    let mut config = TrainConfig {
        frames: Some(3),
        scene: gausmoke_train::scene::SceneConfig {
            open_faces: Some(vec!["y+".into()]),
            ..Default::default()
        },
        // As many as the quick ball preset packs into the ball: small enough that, started
        // as faint as the smoke, the renderer would skip them.
        static_gaussians: 1000,
        ..test_config()
    };
    config.init.iterations = 60;
    config.joint.iterations = 6;
    config.refine.iterations = 2;
    let device = device_by_name("flex").unwrap().autodiff();
    let train = |config: &TrainConfig, run: &Path, resume: bool| {
        let scene = Sequence::open(&data, config).unwrap();
        let mut training = Run::new(scene, config.clone(), device.clone(), run, resume)
            .unwrap()
            .quiet(true);
        training.run().unwrap();
    };
    let straight = dir.path().join("straight");
    train(&config, &straight, false);
    let losses = std::fs::read_to_string(straight.join("losses.csv")).unwrap();
    let statics_rows: Vec<f32> = losses
        .lines()
        .filter(|l| l.contains(",statics,"))
        .map(|l| l.split(',').nth(5).unwrap().parse().unwrap())
        .collect();
    assert_eq!(
        statics_rows.len(),
        60,
        "{}",
        &losses[..200.min(losses.len())]
    );
    // They learn (Gaussians too faint for the renderer to draw would not).
    let (start, end) = (statics_rows[0], statics_rows[59]);
    assert!(
        end < 0.9 * start,
        "the statics' fit went from {start} to {end}"
    );
    assert!(matches!(Phase::Statics.name(), "statics"));

    let frame = |run: &Path, t: usize| {
        read_arrays(&run.join(format!("frames/frame_{t:03}.safetensors"))).unwrap()
    };
    let (first, last) = (frame(&straight, 0), frame(&straight, 2));
    assert_eq!(first["static_means"].0, vec![1000, 3]);
    assert_eq!(first["means"].0, vec![1500, 3]);
    assert!(straight.join("exports/statics_002.ply").is_file());
    // Placed in the ball the data set describes, never carried by the flow nor moved; their
    // looks still learn.
    let ball = SynthConfig::ball_plume().solids[0].shape;
    assert!(
        first["static_means"]
            .1
            .chunks(3)
            .all(|m| ball.contains(gausmoke_data::glam::Vec3::from_slice(m)))
    );
    assert_eq!(first["static_means"], last["static_means"]);
    assert_ne!(first["means"], last["means"]);
    assert_ne!(first["static_raw_densities"], last["static_raw_densities"]);

    let report = eval::evaluate(&straight, &device_by_name("flex").unwrap(), None).unwrap();
    let without = dir.path().join("without");
    train(
        &TrainConfig {
            static_gaussians: 0,
            ..config.clone()
        },
        &without,
        false,
    );
    let plain = eval::evaluate(&without, &device_by_name("flex").unwrap(), None).unwrap();
    let (with_psnr, plain_psnr) = (
        report.frames[0].test_psnr.unwrap(),
        plain.frames[0].test_psnr.unwrap(),
    );
    eprintln!("frame 0 held-out PSNR: {with_psnr:.2} with statics, {plain_psnr:.2} without");
    assert!(with_psnr > plain_psnr, "{with_psnr} vs {plain_psnr}");

    // The last checkpoint lost: resumed from frame 1's, frame 2 retrains to the same state,
    // statics included.
    let resumed = dir.path().join("resumed");
    copy_without_frame_2(&straight, &resumed);
    train(&config, &resumed, true);
    assert_same_frame_2(&straight, &resumed);
}

/// A copy of the run in `from` at `to` with frame 2's checkpoint and frame file gone, as if
/// the run had been killed while training frame 2.
fn copy_without_frame_2(from: &Path, to: &Path) {
    copy_dir(from, to);
    std::fs::remove_dir_all(to.join("checkpoints/frame_002")).unwrap();
    std::fs::remove_file(to.join("frames/frame_002.safetensors")).unwrap();
}

/// Frame 2's files of two runs hold the same arrays, each within 1e-5 of its largest value.
fn assert_same_frame_2(straight: &Path, resumed: &Path) {
    let frame_2 = |run: &Path| read_arrays(&run.join("frames/frame_002.safetensors")).unwrap();
    let (a, b) = (frame_2(straight), frame_2(resumed));
    assert_eq!(a.keys().collect::<Vec<_>>(), b.keys().collect::<Vec<_>>());
    for (name, (_, values)) in &a {
        let scale = values.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
        let worst = largest_difference(values, &b[name].1);
        assert!(worst <= 1e-5 * scale, "{name}: resumed differs by {worst}");
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap().flatten() {
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

/// A Blender-style multi-view set in the D-NeRF layout (fixed cameras filmed together: one
/// `transforms_*.json` per split listing every camera at every time), with the ours `aabb` and
/// `obstacles` keys, made from the ball scene over black (D-NeRF's PNGs carry no background
/// colour, and RGB ones are taken as composited over black): one view per camera, `frames` counting time
/// steps, the plan agreeing with the load, and the scene training with its obstacle solid.
#[test]
fn a_multi_view_dnerf_scene_groups_its_cameras_and_trains() {
    use gausmoke_data::{LoadOptions, Split, load_dnerf, plan};
    let dir = tempfile::tempdir().unwrap();
    let pinf = dir.path().join("pinf");
    let scene = SynthConfig {
        frames: 3,
        ..SynthConfig {
            grid: 16,
            views: 3,
            background: [0.0; 3],
            ..SynthConfig::ball_plume()
        }
    };
    generate(&scene, &pinf).unwrap();
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(pinf.join("info.json")).unwrap()).unwrap();
    let data = dir.path().join("blender");
    let (lo, hi) = gausmoke_data::synth::world_box();
    for (file, key) in [
        ("transforms_train.json", "train_videos"),
        ("transforms_test.json", "test_videos"),
    ] {
        let mut frames = Vec::new();
        for t in 0..3 {
            for camera in info[key].as_array().unwrap() {
                let view = camera["file_name"].as_str().unwrap();
                let target = data.join(format!("{view}_{t:03}.png"));
                std::fs::create_dir_all(&data).unwrap();
                std::fs::copy(pinf.join(view).join(format!("{t:03}.png")), &target).unwrap();
                frames.push(serde_json::json!({
                    "file_path": format!("./{view}_{t:03}"),
                    "time": t as f64 / 2.0,
                    "transform_matrix": camera["transform_matrix"],
                }));
            }
        }
        let mut json = serde_json::json!({
            "camera_angle_x": scene.fov_x,
            "frames": frames,
        });
        if key == "train_videos" {
            json["aabb"] = serde_json::json!([lo.to_array(), hi.to_array()]);
            json["obstacles"] = info["obstacles"].clone();
        }
        std::fs::write(data.join(file), json.to_string()).unwrap();
    }

    let options = LoadOptions {
        frames: Some(0..2),
        ..LoadOptions::default()
    };
    let dataset = load_dnerf(&data, &options).unwrap();
    let names: Vec<&str> = dataset.views.iter().map(|v| v.name.as_str()).collect();
    // Two training cameras grouped into views; the held-out camera alone in its file is one
    // camera over time, D-NeRF's own layout.
    assert_eq!(names, ["train_00", "train_01", "test"]);
    assert!(dataset.views.iter().all(|v| v.frames.len() == 2));
    assert_eq!(dataset.view("test").unwrap().split, Split::Test);
    let bbox = dataset.bbox.expect("the aabb");
    assert_eq!((bbox.min, bbox.max), (lo, hi));
    assert_eq!(dataset.obstacles.len(), 1);
    let planned: Vec<(String, usize)> = plan(&data, &options)
        .unwrap()
        .into_iter()
        .map(|v| (v.name, v.frames))
        .collect();
    let loaded: Vec<(String, usize)> = dataset
        .views
        .iter()
        .map(|v| (v.name.clone(), v.frames.len()))
        .collect();
    assert_eq!(planned, loaded);

    let config = {
        let mut config = TrainConfig {
            frames: Some(2),
            scene: gausmoke_train::scene::SceneConfig {
                open_faces: Some(vec!["y+".into()]),
                ..Default::default()
            },
            ..test_config()
        };
        config.init.iterations = 20;
        config.joint.iterations = 4;
        config.refine.iterations = 2;
        config
    };
    let sequence = Sequence::open(&data, &config).unwrap();
    assert_eq!((sequence.train[0].len(), sequence.test[0].len()), (2, 1));
    let mut training = Run::new(
        sequence,
        config,
        device_by_name("flex").unwrap().autodiff(),
        &dir.path().join("run"),
        false,
    )
    .unwrap()
    .quiet(true);
    assert!(training.trainer.solid_cells().is_some());
    let reports = training.run().unwrap();
    assert!(
        reports.iter().all(|r| r.test_psnr.unwrap() > 20.0),
        "{reports:?}"
    );
}

/// A run of `config` on `data` (flex, quiet) in `dir/name`, trained to its last frame.
fn trained(data: &Path, dir: &Path, config: TrainConfig, name: &str) -> Run {
    let mut run = quiet_run(data, dir, config, name);
    run.run().unwrap();
    run
}

/// A data set without a scene.toml: frame 0 settles the scene from its density (reported in
/// config.toml), a resume keeps what it settled, and `velocity_estimate` ends the run with the
/// velocity read off the densities, from the estimated inflow.
#[test]
fn a_data_set_without_a_scene_file_gets_its_scene_from_frame_0() {
    use gausmoke_train::config::VelocityEstimate;
    use gausmoke_train::scene::SCENE_FILE;
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    std::fs::remove_file(data.join(SCENE_FILE)).unwrap();
    let config = TrainConfig {
        frames: Some(3),
        velocity_estimate: VelocityEstimate::Forces,
        ..test_config()
    };
    let mut run = quiet_run(&data, dir.path(), config.clone(), "estimated");
    assert_eq!(run.trainer.config.scene.open_faces, None);
    run.train_frame(0).unwrap();
    let scene = run.trainer.config.scene.clone();
    // The tiny plume rises from its source on the floor.
    assert_eq!(
        scene.open_faces,
        Some(vec!["y-".to_string(), "y+".to_string()])
    );
    let inflow = scene.inflow.expect("an inflow box");
    assert_eq!(
        inflow[1], 0.0,
        "the inflow box stands on the floor: {inflow:?}"
    );
    assert!(
        inflow[0] < 0.5 && inflow[3] > 0.5,
        "around the source: {inflow:?}"
    );
    let written = TrainConfig::from_toml_file(&dir.path().join("estimated/config.toml")).unwrap();
    assert_eq!(written.scene, scene);
    run.train_frame(1).unwrap();
    drop(run);
    // Resumed with the scene unset again, the run keeps frame 0's.
    let sequence = Sequence::open(&data, &config).unwrap();
    let device = device_by_name("flex").unwrap().autodiff();
    let mut resumed = Run::new(
        sequence,
        config,
        device,
        &dir.path().join("estimated"),
        true,
    )
    .unwrap()
    .quiet(true);
    assert_eq!(resumed.trainer.config.scene, scene);
    resumed.run().unwrap();
    let estimate = dir.path().join("estimated/velocity_estimate");
    assert!(estimate.join("estimate.json").is_file());
    assert!(estimate.join("frame_002.safetensors").is_file());
}

/// A data set whose path is not UTF-8 is refused naming it, before the run folder is
/// created (it used to panic writing run.json and leave a folder no start accepted).
#[test]
fn a_data_path_that_is_not_utf8_is_refused_before_anything_is_written() {
    use std::os::unix::ffi::OsStrExt;
    let dir = tempfile::tempdir().unwrap();
    let data = tiny_scene(dir.path());
    let odd = dir.path().join(std::ffi::OsStr::from_bytes(b"nu_\xff\xfe"));
    std::fs::rename(&data, &odd).unwrap();
    let config = TrainConfig {
        frames: Some(1),
        ..test_config()
    };
    let sequence = Sequence::open(&odd, &config).unwrap();
    let device = device_by_name("flex").unwrap().autodiff();
    let out = dir.path().join("run");
    let err = match Run::new(sequence, config, device, &out, false) {
        Ok(_) => panic!("a non-UTF-8 data path was accepted"),
        Err(e) => e.to_string(),
    };
    assert!(err.contains("UTF-8") && err.contains("nu_"), "{err}");
    assert!(!out.exists(), "nothing is written");
}
