//! The binary end to end: renders the built-in scene to PNG files of the requested size, and
//! reports a bad `--device` plainly.

use std::process::Command;

fn binary() -> Command {
    Command::new(env!("CARGO_BIN_EXE_gausmoke-train"))
}

#[test]
fn demo_render_writes_images() {
    let out = std::env::temp_dir().join(format!("gausmoke-cli-{}", std::process::id()));
    let result = binary()
        .args([
            "--gaussians",
            "500",
            "--width",
            "48",
            "--height",
            "80",
            "--out",
        ])
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
        .args(["--device", "tpu"])
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
