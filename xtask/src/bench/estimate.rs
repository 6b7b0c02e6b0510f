//! `cargo xtask bench estimate --run RUN`: the time of `gausmoke-train velocity` (the velocity
//! estimated from a trained run's densities) per frame, and the ratio against another build
//! measured in the same session.
//!
//! Each measurement estimates the first `--frames` frames of a copy of the run (its settings,
//! and links to its frame files), so the run itself is not written to. Builds alternate round
//! by round, so machine load drifts hit both. The time per frame is the mean of the frames'
//! `seconds` in the estimate's `estimate.json`; its iterations and residuals are reported
//! when the build records them.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};
use clap::Args;
use serde_json::Value;

#[derive(Debug, Args)]
pub struct EstimateArgs {
    /// A finished run folder (`gausmoke-train train --out`).
    #[arg(long)]
    run: PathBuf,
    /// Frames to estimate (1 to N; the run must have frames 0 to N).
    #[arg(long, default_value_t = 20)]
    frames: usize,
    /// Measurements per build.
    #[arg(long, default_value_t = 2)]
    rounds: usize,
    /// Another build's `gausmoke-train` binary, measured in alternation with this one.
    #[arg(long)]
    against: Option<PathBuf>,
    /// Extra arguments for both builds' `velocity` (e.g. `--smoothness=0.001`).
    #[arg(long = "arg", value_name = "ARG", allow_hyphen_values = true)]
    extra: Vec<String>,
    /// Where to write the measurements as JSON.
    #[arg(long, default_value = "target/bench/estimate.json")]
    json: PathBuf,
}

/// One measurement of one build.
#[derive(Debug, Clone, serde::Serialize)]
struct Measurement {
    seconds_per_frame: f64,
    /// The conjugate-gradient iterations per frame and the worst residual, when recorded.
    solver_iterations_per_frame: Option<f64>,
    worst_solver_residual: Option<f64>,
}

/// A copy of the first `frames + 1` frames of `run` in `to`: its settings copied, its frame
/// files linked.
fn copy_run(run: &Path, frames: usize, to: &Path) -> Result<()> {
    let _ = std::fs::remove_dir_all(to);
    std::fs::create_dir_all(to.join("frames"))?;
    for name in ["config.toml", "run.json"] {
        std::fs::copy(run.join(name), to.join(name))
            .with_context(|| format!("{}: not a finished run", run.join(name).display()))?;
    }
    for t in 0..=frames {
        let name = format!("frame_{t:03}.safetensors");
        let source = std::fs::canonicalize(run.join("frames").join(&name)).with_context(|| {
            format!(
                "{}: the run has no frame {t}; pass --frames {} or fewer",
                run.join("frames").join(&name).display(),
                t.saturating_sub(1)
            )
        })?;
        std::os::unix::fs::symlink(&source, to.join("frames").join(&name))?;
    }
    Ok(())
}

fn measure(binary: &Path, args: &EstimateArgs, folder: &Path) -> Result<Measurement> {
    copy_run(&args.run, args.frames, folder)?;
    let status = Command::new(binary)
        .args(["velocity", "--quiet", "--run"])
        .arg(folder)
        .args(&args.extra)
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::null())
        .status()
        .with_context(|| format!("running {}", binary.display()))?;
    if !status.success() {
        bail!("{} velocity failed ({status})", binary.display());
    }
    let path = folder.join("velocity_estimate/estimate.json");
    let summary: Value = serde_json::from_str(
        &std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?,
    )?;
    let frames = summary["frames"]
        .as_array()
        .filter(|f| !f.is_empty())
        .with_context(|| format!("{}: no frames", path.display()))?;
    let mean = |values: Vec<f64>| values.iter().sum::<f64>() / values.len() as f64;
    let field =
        |key: &str| -> Option<Vec<f64>> { frames.iter().map(|f| f[key].as_f64()).collect() };
    Ok(Measurement {
        seconds_per_frame: mean(field("seconds").context("estimate.json: a frame's seconds")?),
        solver_iterations_per_frame: field("solver_iterations").map(mean),
        worst_solver_residual: field("solver_residual").map(|r| r.into_iter().fold(0.0, f64::max)),
    })
}

pub fn estimate(args: EstimateArgs) -> Result<()> {
    if cfg!(debug_assertions) {
        eprintln!(
            "warning: this is a debug build; run `cargo run --release -p xtask -- bench estimate`"
        );
    }
    if args.frames == 0 || args.rounds == 0 {
        bail!("--frames and --rounds must be at least 1");
    }
    let this = std::env::current_exe()?
        .parent()
        .context("the xtask binary's folder")?
        .join("gausmoke-train");
    if !this.is_file() {
        bail!(
            "{} not found: build it beside xtask (`cargo build --release -p gausmoke-train`)",
            this.display()
        );
    }
    let mut builds = vec![("this build".to_string(), this)];
    if let Some(other) = &args.against {
        builds.push((other.display().to_string(), other.clone()));
    }
    let scratch = tempfile::tempdir()?;
    let results = super::in_alternation(
        &builds,
        args.rounds,
        |b, _| {
            measure(
                &builds[b].1,
                &args,
                &scratch.path().join(format!("run-{b}")),
            )
        },
        |m| format!("{:.2} s per frame", m.seconds_per_frame),
    )?;
    let medians = super::medians(&results, |m| m.seconds_per_frame);
    println!(
        "Velocity estimate of {}, frames 1-{}, {} rounds:",
        args.run.display(),
        args.frames,
        args.rounds
    );
    println!();
    println!("| build | s per frame (median) | CG iterations per frame | worst residual |");
    println!("|---|---:|---:|---:|");
    for ((name, _), (median, runs)) in builds.iter().zip(medians.iter().zip(&results)) {
        let last = runs.last().expect("at least one round");
        let recorded = |shown: Option<String>| shown.unwrap_or_else(|| "not recorded".into());
        println!(
            "| {name} | {median:.2} | {} | {} |",
            recorded(last.solver_iterations_per_frame.map(|v| format!("{v:.0}"))),
            recorded(last.worst_solver_residual.map(|v| format!("{v:.1e}")))
        );
    }
    if medians.len() == 2 {
        println!();
        println!("this build / the other: {:.3}", medians[0] / medians[1]);
    }
    if let Some(parent) = args.json.parent() {
        std::fs::create_dir_all(parent)?;
    }
    let json = serde_json::json!({
        "run": args.run,
        "frames": args.frames,
        "rounds": args.rounds,
        "extra_args": args.extra,
        "builds": builds.iter().zip(&results).zip(&medians).map(|(((name, binary), runs), median)| {
            serde_json::json!({
                "name": name,
                "binary": binary,
                "seconds_per_frame_median": median,
                "measurements": runs,
            })
        }).collect::<Vec<_>>(),
    });
    std::fs::write(&args.json, serde_json::to_string_pretty(&json)?)?;
    println!("wrote {}", args.json.display());
    Ok(())
}
