//! Writes a synthetic smoke scene with ground truth in the PINF format.
//!
//! `cargo run --release -p gausmoke-data --example synth -- tiny|scalarflow OUT_DIR [SEED]`

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use gausmoke_data::synth::{self, SynthConfig};

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let usage = "usage: synth tiny|scalarflow OUT_DIR [SEED]";
    let (Some(preset), Some(out)) = (args.first(), args.get(1)) else {
        eprintln!("{usage}");
        return ExitCode::FAILURE;
    };
    let mut cfg = match preset.as_str() {
        "tiny" => SynthConfig::tiny(),
        "scalarflow" => SynthConfig::scalarflow(),
        other => {
            eprintln!("unknown preset `{other}`; {usage}");
            return ExitCode::FAILURE;
        }
    };
    if let Some(seed) = args.get(2) {
        match seed.parse() {
            Ok(s) => cfg.seed = s,
            Err(_) => {
                eprintln!("SEED must be an unsigned integer, got `{seed}`");
                return ExitCode::FAILURE;
            }
        }
    }
    let start = Instant::now();
    match synth::generate(&cfg, &PathBuf::from(out)) {
        Ok(scene) => {
            let last = scene.divergence.last().copied().unwrap_or(0.0);
            println!(
                "wrote {} ({} views x {} frames at {}x{}, grid {}^3) in {:.1} s; mean |div u| at the last frame {last:.2e} cells/frame per cell",
                scene.dir.display(),
                cfg.views,
                cfg.frames,
                cfg.width,
                cfg.height,
                cfg.grid,
                start.elapsed().as_secs_f64()
            );
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
