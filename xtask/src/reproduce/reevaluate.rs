//! `cargo xtask reevaluate`: adds what `eval` measures now to records written before it could
//! (today: LPIPS, once `gausmoke-train lpips-weights` has cached the weights, and the velocity's
//! cosine with the truth on synthetic scenes), from the run
//! folders the records name. A record is only updated when re-rendering its run gives the
//! held-out PSNR it recorded, frame by frame: a folder trained again or changed since is
//! refused, not mixed into the record.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use gausmoke_render::backends::device_by_name;
use gausmoke_train::eval;
use serde_json::{Value, json};

/// Largest held-out PSNR difference (dB) accepted between a record and its re-rendered run;
/// rendering is deterministic on one machine, so any real difference means another run.
const PSNR_TOLERANCE_DB: f64 = 1e-6;

#[derive(Debug, clap::Args)]
pub struct ReevaluateArgs {
    /// Folder holding the run folders (default: each record's own `run` path); a run is
    /// looked up as RUNS/<record key>.
    #[arg(long)]
    runs: Option<PathBuf>,
    /// Only these record keys (default: every record whose run folder exists).
    #[arg(long, value_delimiter = ',')]
    keys: Vec<String>,
    /// Where the records are (docs/results/*.json below it).
    #[arg(long, default_value = "docs")]
    docs: PathBuf,
    #[arg(long, default_value = "flex")]
    device: String,
}

pub fn run(args: ReevaluateArgs) -> Result<()> {
    let weights = gausmoke_train::lpips::weights_to_use(None)
        .context("no cached LPIPS weights: run `gausmoke-train lpips-weights` first")?;
    let device = device_by_name(&args.device).map_err(anyhow::Error::msg)?;
    let results = args.docs.join("results");
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&results)
        .with_context(|| format!("reading {}", results.display()))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    paths.sort();
    let (mut updated, mut missing) = (0, 0);
    for path in paths {
        let mut record: Value = serde_json::from_str(&std::fs::read_to_string(&path)?)
            .with_context(|| format!("{}: not JSON", path.display()))?;
        let key = record["key"].as_str().unwrap_or_default().to_string();
        if !args.keys.is_empty() && !args.keys.contains(&key) {
            continue;
        }
        let run = match &args.runs {
            Some(dir) => dir.join(&key),
            None => PathBuf::from(record["run"].as_str().unwrap_or_default()),
        };
        if !run.join("run.json").is_file() {
            missing += 1;
            continue;
        }
        eprintln!("== {key}: {}", run.display());
        let report = eval::evaluate(&run, &device, Some(&weights))?;
        check_same_run(&path, &record, &report, &run)?;
        record["test_lpips"] = json!(report.test_lpips_mean);
        record["test_lpips_per_frame"] = json!(
            report
                .frames
                .iter()
                .map(|f| f.test_lpips)
                .collect::<Vec<_>>()
        );
        record["lpips"] = json!(report.lpips);
        record["velocity_cosine"] = json!(report.velocity_cosine_mean);
        record["velocity_cosine_per_frame"] = json!(
            report
                .frames
                .iter()
                .map(|f| f.velocity_cosine)
                .collect::<Vec<_>>()
        );
        super::results::write_atomically(&path, &serde_json::to_string_pretty(&record)?)?;
        eprintln!("   LPIPS {:.4}", report.test_lpips_mean.unwrap_or(f64::NAN));
        updated += 1;
    }
    eprintln!("{updated} records updated; {missing} without their run folder left as they were");
    crate::reproduce::write_results_md(&args.docs)
}

fn check_same_run(
    path: &Path,
    record: &Value,
    report: &eval::EvalReport,
    run: &Path,
) -> Result<()> {
    let recorded: Vec<f64> = record["test_psnr_per_frame"]
        .as_array()
        .map(|v| v.iter().filter_map(Value::as_f64).collect())
        .unwrap_or_default();
    let now: Vec<f64> = report.frames.iter().filter_map(|f| f.test_psnr).collect();
    if recorded.len() != now.len() {
        bail!(
            "{}: records {} frames, {} has {}; not the same run",
            path.display(),
            recorded.len(),
            run.display(),
            now.len()
        );
    }
    for (t, (a, b)) in recorded.iter().zip(&now).enumerate() {
        if (a - b).abs() > PSNR_TOLERANCE_DB {
            bail!(
                "{}: frame {t} recorded {a:.6} dB, {} re-renders to {b:.6} dB; not the same run",
                path.display(),
                run.display()
            );
        }
    }
    Ok(())
}
