//! The Python environment of the torch reference: a venv at `.venv-reference/` in the
//! workspace, created on first use with pinned packages from PyPI.
//!
//! PyPI's Linux torch wheel is a CUDA build that needs its CUDA libraries even to import on a
//! CPU, so the first install downloads about 3 GB. Only `cargo xtask goldens` and the torch
//! half of `cargo xtask bench render` need it; tests use the committed golden files.

use std::path::PathBuf;
use std::process::Command;

use anyhow::{Context, Result, bail};

const PACKAGES: &[&str] = &["torch==2.15.0", "numpy", "safetensors"];

pub fn reference_python() -> Result<PathBuf> {
    let venv = crate::workspace_root().join(".venv-reference");
    let python = venv.join("bin/python");
    let marker = venv.join(".installed");
    if !marker.exists() {
        eprintln!("creating {} with {}", venv.display(), PACKAGES.join(" "));
        run(Command::new("python3").arg("-m").arg("venv").arg(&venv))?;
        run(Command::new(&python)
            .args(["-m", "pip", "install", "--quiet"])
            .args(PACKAGES))?;
        std::fs::write(&marker, PACKAGES.join("\n"))?;
    }
    Ok(python)
}

pub fn run(cmd: &mut Command) -> Result<()> {
    let status = cmd.status().with_context(|| format!("starting {cmd:?}"))?;
    if !status.success() {
        bail!("{cmd:?} failed with {status}");
    }
    Ok(())
}
