//! `cargo xtask bench train`: the time of a training iteration, phase by phase, and the ratio
//! against another build measured in the same session.
//!
//! Each measurement is a short `xtask reproduce scalar-real` run of the real capture (two
//! frames: a cheap frame 0, then frame 1 with K joint and K' refinement iterations), so any
//! build that has `reproduce` (today's main included) can be measured the same way: pass its
//! binary with `--against`. Builds alternate round by round, so machine load drifts hit both.
//! The time per iteration is frame 1's wall time (its optimisation and one held-out render)
//! over its K + K' iterations; the phase totals are the whole run's (`metrics.json`), frame 0's
//! ten fitting iterations included.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context, Result, bail};
use clap::Args;
use serde_json::Value;

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// The paper-sized iteration (30k Gaussians, 64^3 grid, 270x480 images, 16-channel
    /// U-Net) instead of the reduced ScalarReal preset (8000, 32^3, 90x160, 8 channels).
    #[arg(long)]
    paper: bool,
    /// Joint (advection) iterations K of the timed frame.
    #[arg(long, default_value_t = 20)]
    advect_iterations: usize,
    /// Refinement iterations K' of the timed frame.
    #[arg(long, default_value_t = 5)]
    refine_iterations: usize,
    /// Measurements per build.
    #[arg(long, default_value_t = 3)]
    rounds: usize,
    /// Another build's xtask binary, measured in alternation with this one.
    #[arg(long)]
    against: Option<PathBuf>,
    /// Backend to train on.
    #[arg(long, default_value = "flex")]
    device: String,
    /// The ScalarReal data set (default `../shared/datasets/scalar_real`).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Extra `--set KEY=VALUE` for both builds (e.g. `projection.kind=penalty`).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
    /// Where to write the measurements as JSON.
    #[arg(long, default_value = "target/bench/train.json")]
    json: PathBuf,
}

/// One measurement of one build.
#[derive(Debug, Clone)]
struct Measurement {
    seconds_per_iteration: f64,
    /// The run's phase totals: name, seconds.
    phases: Vec<(String, f64)>,
    /// Frame 1's loops: device reads and kernel launches (`None`: the build does not report
    /// them).
    traffic: Option<Vec<LoopCounts>>,
}

/// One loop's `device_traffic` entry of `metrics.json`.
#[derive(Debug, Clone, serde::Deserialize)]
struct LoopCounts {
    phase: String,
    iterations: usize,
    reads: u64,
    tile_list_reads: u64,
    solver_reads: u64,
    launches: u64,
}

impl LoopCounts {
    fn per_iteration(&self, count: u64) -> f64 {
        count as f64 / self.iterations.max(1) as f64
    }
}

/// Runs `binary`'s reproduce on two frames and reads what frame 1 took.
fn measure(binary: &Path, args: &TrainArgs, scratch: &Path, label: &str) -> Result<Measurement> {
    let docs = scratch.join(format!("docs-{label}"));
    std::fs::create_dir_all(&docs)?;
    std::fs::copy(
        crate::workspace_root().join("docs/RESULTS.md"),
        docs.join("RESULTS.md"),
    )?;
    let out = scratch.join(format!("runs-{label}"));
    let _ = std::fs::remove_dir_all(&out);
    let data = args
        .data
        .clone()
        .unwrap_or_else(|| crate::workspace_root().join("../shared/datasets/scalar_real"));
    let mut command = Command::new(binary);
    command
        .arg("reproduce")
        .arg("scalar-real")
        .args(["--frames", "2", "--device", &args.device, "--tag", "bench"])
        .arg("--data")
        .arg(&data)
        .arg("--docs")
        .arg(&docs)
        .arg("--out")
        .arg(&out);
    if !args.paper {
        command.arg("--quick");
    }
    let iterations = args.advect_iterations + args.refine_iterations;
    let mut sets = vec![
        // Frame 0 only has to leave Gaussians for frame 1 to move.
        "init.iterations=10".to_string(),
        format!("joint.iterations={}", args.advect_iterations),
        format!("refine.iterations={}", args.refine_iterations),
        "output.every=1000".to_string(),
    ];
    sets.extend(args.overrides.iter().cloned());
    for set in &sets {
        command.arg("--set").arg(set);
    }
    let status = command
        .env("RUST_LOG", "warn")
        .status()
        .with_context(|| format!("running {}", binary.display()))?;
    if !status.success() {
        bail!("{} reproduce failed ({status})", binary.display());
    }
    let key = if args.paper {
        "scalar-real-f2-bench"
    } else {
        "scalar-real-quick-f2-bench"
    };
    let path = out.join(key).join("metrics.json");
    let metrics: Value = serde_json::from_str(
        &std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?,
    )?;
    let frame1 = metrics["per_frame"][1]["seconds"]
        .as_f64()
        .context("metrics.json has no frame 1")?;
    let phases = metrics["phase_seconds"]
        .as_object()
        .map(|phases| {
            phases
                .iter()
                .map(|(name, v)| (name.clone(), v["seconds"].as_f64().unwrap_or(f64::NAN)))
                .collect()
        })
        .unwrap_or_default();
    let traffic = metrics["per_frame"][1]
        .get("device_traffic")
        .map(|t| serde_json::from_value::<Vec<LoopCounts>>(t.clone()))
        .transpose()
        .context("metrics.json: device_traffic of frame 1")?;
    Ok(Measurement {
        seconds_per_iteration: frame1 / iterations as f64,
        phases,
        traffic,
    })
}

pub fn train(args: TrainArgs) -> Result<()> {
    if cfg!(debug_assertions) {
        eprintln!(
            "warning: this is a debug build; run `cargo run --release -p xtask -- bench train`"
        );
    }
    let this = std::env::current_exe()?;
    let mut builds = vec![("this build".to_string(), this)];
    if let Some(other) = &args.against {
        builds.push((format!("{}", other.display()), other.clone()));
    }
    let scratch = tempfile::tempdir()?;
    let results = super::in_alternation(
        &builds,
        args.rounds,
        |b, round| measure(&builds[b].1, &args, scratch.path(), &format!("{b}-{round}")),
        |m| format!("{:.3} s per iteration", m.seconds_per_iteration),
    )?;
    let medians = super::medians(&results, |m| m.seconds_per_iteration);
    let workload = if args.paper {
        "paper-sized (30k Gaussians, 64^3, 270x480, 16 channels)"
    } else {
        "reduced ScalarReal (8000 Gaussians, 32^3, 90x160, 8 channels)"
    };
    println!(
        "Training iteration, {workload}, K = {}, K' = {}, {} rounds, device {}:",
        args.advect_iterations, args.refine_iterations, args.rounds, args.device
    );
    println!();
    println!("| build | s per iteration (median) | rounds |");
    println!("|---|---:|---|");
    for ((name, _), (median, runs)) in builds.iter().zip(medians.iter().zip(&results)) {
        let all: Vec<String> = runs
            .iter()
            .map(|m| format!("{:.3}", m.seconds_per_iteration))
            .collect();
        println!("| {name} | {median:.3} | {} |", all.join(", "));
    }
    if medians.len() == 2 {
        println!();
        println!(
            "this build is {:.2}x faster per iteration than {}",
            medians[1] / medians[0],
            builds[1].0
        );
    }
    println!();
    println!("Phase totals of the median round's run, seconds (frame 0's 10 fitting iterations");
    println!("included; nested phases are inside \"backward (all ops)\"):");
    for ((name, _), runs) in builds.iter().zip(&results) {
        let mut sorted = runs.clone();
        sorted.sort_by(|a, b| a.seconds_per_iteration.total_cmp(&b.seconds_per_iteration));
        let m = &sorted[sorted.len() / 2];
        let mut phases = m.phases.clone();
        phases.sort_by(|a, b| b.1.total_cmp(&a.1));
        let parts: Vec<String> = phases
            .iter()
            .map(|(phase, s)| format!("{phase} {s:.2}"))
            .collect();
        println!("- {name}: {}", parts.join(", "));
    }
    println!();
    println!("Device reads and kernel launches per iteration of frame 1 (last round; reads of");
    println!("every kind, and of them tile-list lengths and projection-solver tests):");
    println!();
    println!("| build | loop | iterations | reads | tile lists | solver | other | launches |");
    println!("|---|---|---:|---:|---:|---:|---:|---:|");
    for ((name, _), runs) in builds.iter().zip(&results) {
        match runs.last().and_then(|m| m.traffic.as_ref()) {
            None => println!("| {name} | not reported by this build | | | | | | |"),
            Some(loops) => {
                for l in loops {
                    let other = l.reads - l.tile_list_reads - l.solver_reads;
                    println!(
                        "| {name} | {} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.1} |",
                        l.phase,
                        l.iterations,
                        l.per_iteration(l.reads),
                        l.per_iteration(l.tile_list_reads),
                        l.per_iteration(l.solver_reads),
                        l.per_iteration(other),
                        l.per_iteration(l.launches),
                    );
                }
            }
        }
    }
    let json: Vec<Value> = builds
        .iter()
        .zip(&results)
        .map(|((name, binary), runs)| {
            serde_json::json!({
                "build": name,
                "binary": binary,
                "workload": workload,
                "seconds_per_iteration": runs.iter().map(|m| m.seconds_per_iteration).collect::<Vec<_>>(),
                "phases": runs.iter().map(|m| m.phases.iter().map(|(k, v)| (k.clone(), Value::from(*v))).collect::<serde_json::Map<String, Value>>()).collect::<Vec<_>>(),
            })
        })
        .collect();
    if let Some(dir) = args.json.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(&args.json, serde_json::to_string_pretty(&json)?)?;
    Ok(())
}
