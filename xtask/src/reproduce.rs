//! `cargo xtask reproduce scalar-real|synthetic [--quick]`: trains with the library API the
//! CLI uses, evaluates on the held-out views, and records what was measured.
//!
//! Every run writes `docs/results/<key>.json` (metrics, timings, memory, storage, machine,
//! date and the command), and `docs/RESULTS.md`'s generated block (between the
//! `results:begin` / `results:end` markers) is rebuilt from all such files, so the tables hold
//! only measured numbers. The prose around the block is written by people.

use std::fmt::Write as _;
use std::ops::Not as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_render::backends;
use gausmoke_train::{Run, TrainConfig, eval, sequence::Sequence};
use serde_json::{Value, json};

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Target {
    /// The real ScalarFlow capture (paper Table 1/2): train00, 01, 03, 04; test train02.
    ScalarReal,
    /// A synthetic plume with ground truth, and the paper's Table 3 ablations.
    Synthetic,
}

#[derive(Debug, Args)]
pub struct ReproduceArgs {
    target: Target,
    /// A reduced run that finishes on a 2-core CPU in minutes (fewer frames, iterations and
    /// Gaussians, a coarser grid and smaller images): a smoke test of the protocol, not the
    /// paper's setting.
    #[arg(long)]
    quick: bool,
    /// Backend to train on (`flex`, `ndarray`, or a GPU one compiled in).
    #[arg(long, default_value = "flex")]
    device: String,
    /// Folder for the runs (and the generated synthetic data).
    #[arg(long, default_value = "runs/reproduce")]
    out: PathBuf,
    /// Data set (scalar-real: default `../shared/datasets/scalar_real`).
    #[arg(long)]
    data: Option<PathBuf>,
    /// Train only the first N frames (default: all, or the quick preset's count).
    #[arg(long)]
    frames: Option<usize>,
    /// Continue runs found in --out instead of refusing them.
    #[arg(long)]
    resume: bool,
    /// Synthetic: skip the ablations.
    #[arg(long)]
    no_ablations: bool,
    /// LPIPS weights (see `gausmoke-train eval --help`); without them LPIPS is not reported.
    #[arg(long)]
    lpips_weights: Option<PathBuf>,
    /// Seed of the Gaussians' initialisation (default: the configuration's, 2026). Runs with
    /// other seeds get `-s<seed>` keys and are summarised across seeds in RESULTS.md.
    #[arg(long)]
    seed: Option<u64>,
    /// Recycle up to this fraction of the Gaussians per frame to where the training views
    /// show missing smoke (`respawn_fraction`; our addition, not the paper's method). Runs
    /// get `-r<fraction>` keys.
    #[arg(long)]
    respawn: Option<f32>,
    /// Override a configuration value of every variant (`gausmoke-train --set` syntax,
    /// repeatable); needs --tag.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
    /// Appended to the run keys (`-<tag>`) of runs with --set, so they do not overwrite the
    /// preset's.
    #[arg(long)]
    tag: Option<String>,
    /// Folder holding `RESULTS.md` and `results/` (default: the workspace's `docs`).
    #[arg(long)]
    docs: Option<PathBuf>,
}

/// The paper's reference figures (Table 1/2, ScalarFlow real capture).
const PAPER_SCALAR_REAL: &str = "34.83 dB PSNR, 0.955 SSIM, 0.0168 LPIPS; 0.8 h training on an \
                                 RTX 3090; 114 FPS rendering; 42 MB";

/// The paper's Table 3 (ablations; PSNR, SSIM, LPIPS, divergence; the table does not name
/// its scene).
const PAPER_ABLATIONS: &str = "full model 37.98 dB, 0.975, 0.0336, div 0.085; w/o L_div, L_adv \
                               30.12 dB, 0.925, 0.0810, div 0.402; w/o volumetric rendering \
                               30.45 dB, 0.932, 0.0825, div 0.127; w/o L_refine 33.87 dB, 0.964, \
                               0.0418, div 0.098";

fn quick_scalar_real() -> TrainConfig {
    TrainConfig {
        gaussians: 8000,
        grid_resolution: 32,
        image_size: Some([90, 160]),
        frames: Some(8),
        init_iterations: 400,
        advect_iterations: 20,
        refine_iterations: 5,
        lr_velocity: 2e-3,
        lr_gaussians: 2e-3,
        unet_channels: 8,
        time_frequencies: 2,
        output_every: 4,
        ..TrainConfig::default()
    }
}

fn paper_scalar_real() -> TrainConfig {
    TrainConfig {
        image_size: Some([270, 480]),
        train_views: Some(
            ["train00", "train01", "train03", "train04"]
                .map(String::from)
                .into(),
        ),
        test_views: Some(vec!["train02".into()]),
        output_every: 10,
        ..TrainConfig::default()
    }
}

/// One training run of the reproduction: a key for file names, a label for tables, and the
/// group of runs it repeats with another seed.
struct Variant {
    key: String,
    group: String,
    label: String,
    config: TrainConfig,
}

fn variants(args: &ReproduceArgs) -> Result<Vec<Variant>> {
    let mut suffix = if args.quick { "-quick" } else { "" }.to_string();
    if let Some(frames) = args.frames {
        suffix += &format!("-f{frames}");
    }
    if let Some(fraction) = args.respawn {
        suffix += &format!("-r{fraction}");
    }
    match (&args.tag, args.overrides.is_empty()) {
        (Some(tag), _) => suffix += &format!("-{tag}"),
        (None, false) => bail!("--set changes the preset: name the runs with --tag"),
        (None, true) => {}
    }
    let group_suffix = suffix.clone();
    if let Some(seed) = args.seed {
        suffix += &format!("-s{seed}");
    }
    let mut base = match (args.target, args.quick) {
        (Target::ScalarReal, true) => TrainConfig {
            train_views: paper_scalar_real().train_views,
            test_views: paper_scalar_real().test_views,
            ..quick_scalar_real()
        },
        (Target::ScalarReal, false) => paper_scalar_real(),
        (Target::Synthetic, true) => TrainConfig::quick_demo(),
        (Target::Synthetic, false) => TrainConfig::default(),
    };
    if let Some(frames) = args.frames {
        base.frames = Some(frames);
    }
    if let Some(seed) = args.seed {
        base.seed = seed;
    }
    if let Some(fraction) = args.respawn {
        base.respawn_fraction = fraction;
    }
    base = base.with_overrides(&args.overrides)?;
    let overrides = args.overrides.join(", ");
    let keyed = |target: &str, ablation: &str, label: &str, config: TrainConfig| Variant {
        key: format!("{target}{suffix}{ablation}"),
        group: format!("{target}{group_suffix}{ablation}"),
        label: {
            let mut label = label.to_string();
            if config.respawn_fraction > 0.0 {
                label += &format!(", respawn {}", config.respawn_fraction);
            }
            if !overrides.is_empty() {
                label += &format!(", {overrides}");
            }
            label
        },
        config,
    };
    Ok(match args.target {
        Target::ScalarReal => vec![keyed("scalar-real", "", "full method", base)],
        Target::Synthetic => {
            let mut list = vec![keyed("synthetic", "", "full method", base.clone())];
            if !args.no_ablations {
                for ablation in Ablation::ALL {
                    let config = ablation.apply(base.clone());
                    list.push(keyed(
                        "synthetic",
                        ablation.suffix(),
                        ablation.label(),
                        config,
                    ));
                }
            }
            list
        }
    })
}

/// The paper's Table 3 ablations, named by the part of the method each switches off.
#[derive(Debug, Clone, Copy)]
enum Ablation {
    Physics,
    Refinement,
    Volumetric,
}

impl Ablation {
    const ALL: [Ablation; 3] = [
        Ablation::Physics,
        Ablation::Refinement,
        Ablation::Volumetric,
    ];

    /// Appended to the full method's run key and group.
    fn suffix(self) -> &'static str {
        match self {
            Ablation::Physics => "-no-physics",
            Ablation::Refinement => "-no-refinement",
            Ablation::Volumetric => "-no-volumetric",
        }
    }

    fn label(self) -> &'static str {
        match self {
            Ablation::Physics => "w/o physical losses",
            Ablation::Refinement => "w/o refinement",
            Ablation::Volumetric => "w/o volumetric rendering",
        }
    }

    fn apply(self, config: TrainConfig) -> TrainConfig {
        match self {
            Ablation::Physics => TrainConfig {
                physics_losses: false,
                ..config
            },
            Ablation::Refinement => TrainConfig {
                refinement: false,
                ..config
            },
            Ablation::Volumetric => TrainConfig {
                volumetric: false,
                ..config
            },
        }
    }
}

/// Starts the peak-resident-memory count again (Linux: writing 5 to `/proc/self/clear_refs`
/// resets `VmHWM`), so each variant of one invocation reports its own peak.
fn reset_peak_memory() {
    if let Err(e) = std::fs::write("/proc/self/clear_refs", "5") {
        eprintln!("warning: cannot reset the peak memory count ({e}); it includes earlier runs");
    }
}

/// Peak resident memory since the last [`reset_peak_memory`] (Linux `VmHWM`), in MiB.
fn peak_memory_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// The CPU, and for GPU devices the NVIDIA adapter and driver where `nvidia-smi` exists.
fn machine(device: &str) -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|info| {
            info.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let gpu = ["flex", "ndarray"]
        .contains(&device)
        .not()
        .then(|| {
            std::process::Command::new("nvidia-smi")
                .args(["--query-gpu=name,driver_version", "--format=csv,noheader"])
                .output()
                .ok()
                .filter(|o| o.status.success())
                .and_then(|o| String::from_utf8(o.stdout).ok())
                .and_then(|s| s.lines().next().map(|l| l.trim().to_string()))
        })
        .flatten()
        .map(|line| match line.split_once(", ") {
            Some((name, driver)) => format!("{name} (driver {driver}), "),
            None => format!("{line}, "),
        })
        .unwrap_or_default();
    format!("{gpu}{cpu}, {threads} threads")
}

fn utc_now() -> String {
    std::process::Command::new("date")
        .args(["-u", "+%Y-%m-%d %H:%M UTC"])
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|| "unknown date".into())
}

fn file_size(path: &Path) -> u64 {
    std::fs::metadata(path).map_or(0, |m| m.len())
}

fn command_line(args: &ReproduceArgs) -> String {
    let mut line = format!(
        "cargo run --release -p xtask -- reproduce {}",
        match args.target {
            Target::ScalarReal => "scalar-real",
            Target::Synthetic => "synthetic",
        }
    );
    if args.quick {
        line += " --quick";
    }
    if args.device != "flex" {
        line += &format!(" --device {}", args.device);
    }
    if let Some(frames) = args.frames {
        line += &format!(" --frames {frames}");
    }
    if let Some(seed) = args.seed {
        line += &format!(" --seed {seed}");
    }
    if let Some(fraction) = args.respawn {
        line += &format!(" --respawn {fraction}");
    }
    for entry in &args.overrides {
        if entry.contains(' ') {
            line += &format!(" --set \"{entry}\"");
        } else {
            line += &format!(" --set {entry}");
        }
    }
    if let Some(tag) = &args.tag {
        line += &format!(" --tag {tag}");
    }
    if args.no_ablations {
        line += " --no-ablations";
    }
    if let Some(data) = &args.data {
        line += &format!(" --data {}", data.display());
    }
    if let Some(weights) = &args.lpips_weights {
        line += &format!(" --lpips-weights {}", weights.display());
    }
    line
}

pub fn run(args: ReproduceArgs) -> Result<()> {
    if cfg!(debug_assertions) {
        eprintln!("warning: a debug build; use `cargo run --release -p xtask -- reproduce ...`");
    }
    let root = crate::workspace_root();
    let data = match (args.target, &args.data) {
        (_, Some(path)) => path.clone(),
        (Target::ScalarReal, None) => root.join("../shared/datasets/scalar_real"),
        (Target::Synthetic, None) => {
            let preset = if args.quick { "tiny" } else { "scalarflow" };
            let path = args.out.join(format!("data-synthetic-{preset}"));
            if !path.join("info.json").is_file() {
                let config = if args.quick {
                    SynthConfig::tiny()
                } else {
                    SynthConfig::scalarflow()
                };
                eprintln!(
                    "generating the `{preset}` synthetic scene in {}",
                    path.display()
                );
                generate(&config, &path)?;
            }
            path
        }
    };
    if !data.join("info.json").is_file() {
        bail!(
            "{}: no info.json (is this the data set folder?)",
            data.display()
        );
    }
    let device = backends::device_by_name(&args.device).map_err(anyhow::Error::msg)?;
    let docs = args.docs.clone().unwrap_or_else(|| root.join("docs"));
    let results_dir = docs.join("results");
    std::fs::create_dir_all(&results_dir)?;
    for variant in variants(&args)? {
        let run_dir = args.out.join(&variant.key);
        eprintln!(
            "== {} ({}) -> {}",
            variant.key,
            variant.label,
            run_dir.display()
        );
        reset_peak_memory();
        let scene = Sequence::open(&data, &variant.config)
            .with_context(|| format!("loading {}", data.display()))?;
        let frames = scene.frames();
        let start = Instant::now();
        let mut trainer = Run::new(
            scene,
            variant.config.clone(),
            device.clone().autodiff(),
            &run_dir,
            args.resume,
        )?;
        trainer.run()?;
        let wall_seconds = start.elapsed().as_secs_f64();
        let gaussians = trainer.trainer.state.gaussians.len();
        drop(trainer);
        let report = eval::evaluate(&run_dir, &device, args.lpips_weights.as_deref())?;
        let metrics: Value = serde_json::from_str(
            &std::fs::read_to_string(run_dir.join("metrics.json")).context("metrics.json")?,
        )?;
        let last_frame = run_dir
            .join("frames")
            .join(format!("frame_{:03}.safetensors", frames - 1));
        let frames_bytes: u64 = std::fs::read_dir(run_dir.join("frames"))
            .map(|dir| dir.flatten().map(|e| file_size(&e.path())).sum())
            .unwrap_or(0);
        let record = json!({
            "key": variant.key,
            "group": variant.group,
            "seed": variant.config.seed,
            "target": format!("{:?}", args.target),
            "variant": variant.label,
            "quick": args.quick,
            "command": command_line(&args),
            "data": data.display().to_string(),
            "device": args.device,
            "machine": machine(&args.device),
            "date": utc_now(),
            "frames": frames,
            "gaussians": gaussians,
            "config": serde_json::to_value(&variant.config)?,
            "test_psnr": report.test_psnr_mean,
            "test_ssim": report.test_ssim_mean,
            "test_lpips": report.test_lpips_mean,
            "lpips": report.lpips,
            "mean_abs_divergence": report.mean_abs_divergence,
            "velocity_relative_error": report.velocity_relative_error_mean,
            "density_relative_error": report.density_relative_error_mean,
            "training_seconds": metrics["training_seconds"],
            "wall_seconds_with_outputs": wall_seconds,
            "phase_seconds": metrics["phase_seconds"],
            "peak_memory_mib": peak_memory_mib(),
            "state_bytes_per_frame": file_size(&last_frame),
            "state_bytes_all_frames": frames_bytes,
            "run": run_dir.display().to_string(),
        });
        let path = results_dir.join(format!("{}.json", variant.key));
        std::fs::write(&path, serde_json::to_string_pretty(&record)?)?;
        eprintln!(
            "   PSNR {:?} SSIM {:?} |div u| {:.3e} in {:.0} s; wrote {}",
            report.test_psnr_mean,
            report.test_ssim_mean,
            report.mean_abs_divergence,
            wall_seconds,
            path.display()
        );
    }
    write_results_md(&docs)
}

fn number(value: &Value, digits: usize) -> String {
    value
        .as_f64()
        .map_or("n/a".into(), |v| format!("{v:.digits$}"))
}

fn mib(value: &Value) -> String {
    value
        .as_f64()
        .map_or("n/a".into(), |v| format!("{:.1}", v / (1024.0 * 1024.0)))
}

/// Mean and sample standard deviation.
fn mean_std(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (mean, var.sqrt())
}

/// The seed of a record's Gaussians' initialisation.
fn seed_of(record: &Value) -> u64 {
    record["seed"]
        .as_u64()
        .or(record["config"]["seed"].as_u64())
        .unwrap_or(2026)
}

/// A metric summarised over seeds.
struct SeedMetric {
    /// Its name in the records.
    name: &'static str,
    higher_is_better: bool,
    format: fn(f64) -> String,
}

const SEED_METRICS: [SeedMetric; 4] = [
    SeedMetric {
        name: "test_psnr",
        higher_is_better: true,
        format: |v| format!("{v:.2}"),
    },
    SeedMetric {
        name: "velocity_relative_error",
        higher_is_better: false,
        format: |v| format!("{v:.3}"),
    },
    SeedMetric {
        name: "density_relative_error",
        higher_is_better: false,
        format: |v| format!("{v:.3}"),
    },
    SeedMetric {
        name: "mean_abs_divergence",
        higher_is_better: false,
        format: |v| format!("{v:.2e}"),
    },
];

/// Runs grouped by what they share apart from the seed (records written before groups existed
/// are their own group).
fn seed_groups(records: &[Value]) -> std::collections::BTreeMap<&str, Vec<&Value>> {
    let mut groups: std::collections::BTreeMap<&str, Vec<&Value>> = Default::default();
    for r in records {
        let group = r["group"].as_str().or(r["key"].as_str()).unwrap_or("?");
        groups.entry(group).or_default().push(r);
    }
    groups
}

/// For every group of runs that differ only in their seed (two or more), the mean and
/// standard deviation of the held-out metrics; then, for every ablation, its per-seed
/// differences from the full method run with the same seed.
fn write_seed_summary(block: &mut String, records: &[Value]) -> Result<()> {
    let groups = seed_groups(records);
    let repeated: Vec<_> = groups.iter().filter(|(_, runs)| runs.len() >= 2).collect();
    if repeated.is_empty() {
        return Ok(());
    }
    writeln!(
        block,
        "\nAcross seeds (mean +- sample standard deviation over the runs of a group):\n"
    )?;
    writeln!(
        block,
        "| group | variant | seeds | held-out PSNR (dB) | SSIM | velocity rel. error | density rel. error | mean abs div u (1/frame) |"
    )?;
    writeln!(block, "|---|---|---|---:|---:|---:|---:|---:|")?;
    for (group, runs) in &repeated {
        let column = |name: &str, format: fn(f64) -> String| {
            let values: Vec<f64> = runs.iter().filter_map(|r| r[name].as_f64()).collect();
            if values.len() < 2 {
                return "n/a".to_string();
            }
            let (mean, std) = mean_std(&values);
            format!("{} +- {}", format(mean), format(std))
        };
        let seeds: Vec<String> = runs.iter().map(|r| seed_of(r).to_string()).collect();
        writeln!(
            block,
            "| `{group}` | {} | {} | {} | {} | {} | {} | {} |",
            runs[0]["variant"].as_str().unwrap_or("?"),
            seeds.join(", "),
            column("test_psnr", SEED_METRICS[0].format),
            column("test_ssim", |v| format!("{v:.4}")),
            column("velocity_relative_error", SEED_METRICS[1].format),
            column("density_relative_error", SEED_METRICS[2].format),
            column("mean_abs_divergence", SEED_METRICS[3].format),
        )?;
    }
    write_paired_ablations(block, &groups)
}

/// Each ablation against the full method with the same seed: the mean +- standard deviation
/// of the per-seed difference (full minus ablation) and in how many seeds the full method
/// is the better of the two. Pairing removes the spread that the initialisation puts into
/// both runs alike.
fn write_paired_ablations(
    block: &mut String,
    groups: &std::collections::BTreeMap<&str, Vec<&Value>>,
) -> Result<()> {
    let mut rows = Vec::new();
    for (group, runs) in groups {
        let Some(ablation) = Ablation::ALL
            .into_iter()
            .find(|a| group.ends_with(a.suffix()))
        else {
            continue;
        };
        let full_group = &group[..group.len() - ablation.suffix().len()];
        let Some(full_runs) = groups.get(full_group) else {
            continue;
        };
        let pairs: Vec<(&Value, &Value)> = runs
            .iter()
            .filter_map(|r| {
                full_runs
                    .iter()
                    .find(|f| seed_of(f) == seed_of(r))
                    .map(|f| (*f, *r))
            })
            .collect();
        if pairs.len() < 2 {
            continue;
        }
        let mut row = format!(
            "| `{full_group}` | {} | {} |",
            ablation.label(),
            pairs.len()
        );
        for SeedMetric {
            name,
            higher_is_better,
            format,
        } in SEED_METRICS
        {
            let differences: Vec<f64> = pairs
                .iter()
                .filter_map(|(full, ablated)| Some(full[name].as_f64()? - ablated[name].as_f64()?))
                .collect();
            if differences.len() < 2 {
                row += " n/a |";
                continue;
            }
            let (mean, std) = mean_std(&differences);
            let full_better = differences
                .iter()
                .filter(|&&d| if higher_is_better { d > 0.0 } else { d < 0.0 })
                .count();
            row += &format!(
                " {}{} +- {} ({}/{}) |",
                if mean >= 0.0 { "+" } else { "" },
                format(mean),
                format(std),
                full_better,
                differences.len()
            );
        }
        rows.push(row);
    }
    if rows.is_empty() {
        return Ok(());
    }
    writeln!(
        block,
        "\nAblations paired by seed (full method minus ablation, mean +- sample standard deviation \
         over seeds; in brackets, the seeds in which the full method is better: higher PSNR, \
         lower errors and divergence):\n"
    )?;
    writeln!(
        block,
        "| full-method group | ablation | seeds | PSNR (dB) | velocity rel. error | density rel. error | mean abs div u (1/frame) |"
    )?;
    writeln!(block, "|---|---|---:|---:|---:|---:|---:|")?;
    for row in rows {
        writeln!(block, "{row}")?;
    }
    Ok(())
}

/// Rebuilds the generated block of `docs/RESULTS.md` from `docs/results/*.json`.
pub fn write_results_md(docs: &Path) -> Result<()> {
    let mut records: Vec<Value> = std::fs::read_dir(docs.join("results"))?
        .flatten()
        .filter(|e| e.path().extension().is_some_and(|x| x == "json"))
        .map(|e| -> Result<Value> {
            Ok(serde_json::from_str(&std::fs::read_to_string(e.path())?)?)
        })
        .collect::<Result<_>>()?;
    records.sort_by(|a, b| a["key"].as_str().cmp(&b["key"].as_str()));

    let mut block = String::new();
    writeln!(
        block,
        "Generated by `cargo xtask reproduce` from `docs/results/*.json`; do not edit by hand.\n"
    )?;
    writeln!(
        block,
        "| run | variant | frames | Gaussians | held-out PSNR (dB) | SSIM | LPIPS | mean abs div u (1/frame) | velocity rel. error | density rel. error | training (s) | peak memory (MiB) | state per frame (MiB) | device, machine, date |"
    )?;
    writeln!(
        block,
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"
    )?;
    for r in &records {
        writeln!(
            block,
            "| `{}` | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {}, {}, {} |",
            r["key"].as_str().unwrap_or("?"),
            r["variant"].as_str().unwrap_or("?"),
            r["frames"],
            r["gaussians"],
            number(&r["test_psnr"], 2),
            number(&r["test_ssim"], 4),
            number(&r["test_lpips"], 4),
            r["mean_abs_divergence"]
                .as_f64()
                .map_or("n/a".into(), |v| format!("{v:.2e}")),
            number(&r["velocity_relative_error"], 3),
            number(&r["density_relative_error"], 3),
            number(&r["training_seconds"], 0),
            number(&r["peak_memory_mib"], 0),
            mib(&r["state_bytes_per_frame"]),
            r["device"].as_str().unwrap_or("?"),
            r["machine"].as_str().unwrap_or("?"),
            r["date"].as_str().unwrap_or("?"),
        )?;
    }
    write_seed_summary(&mut block, &records)?;
    writeln!(
        block,
        "\nPaper, ScalarFlow real capture (Table 1/2): {PAPER_SCALAR_REAL}.\n"
    )?;
    writeln!(block, "Paper, ablations (Table 3): {PAPER_ABLATIONS}.\n")?;
    writeln!(
        block,
        "Per-phase wall time (s) of each run's optimisation (calls in brackets; nested phases are inside \"backward (all ops)\"):\n"
    )?;
    for r in &records {
        let Some(phases) = r["phase_seconds"].as_object() else {
            continue;
        };
        let mut phases: Vec<(&String, &Value)> = phases.iter().collect();
        phases.sort_by(|a, b| {
            b.1["seconds"]
                .as_f64()
                .partial_cmp(&a.1["seconds"].as_f64())
                .unwrap_or(std::cmp::Ordering::Equal)
        });
        let parts: Vec<String> = phases
            .iter()
            .map(|(name, v)| format!("{name} {} ({})", number(&v["seconds"], 1), v["calls"]))
            .collect();
        writeln!(
            block,
            "- `{}`: {}",
            r["key"].as_str().unwrap_or("?"),
            parts.join(", ")
        )?;
    }
    writeln!(block, "\nCommands:\n")?;
    let mut commands: Vec<&str> = records
        .iter()
        .filter_map(|r| r["command"].as_str())
        .collect();
    commands.sort();
    commands.dedup();
    for command in commands {
        writeln!(block, "- `{command}`")?;
    }

    let path = docs.join("RESULTS.md");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|_| {
        "# Results\n\n<!-- results:begin -->\n<!-- results:end -->\n".to_string()
    });
    let (begin, end) = ("<!-- results:begin -->", "<!-- results:end -->");
    let (Some(start), Some(stop)) = (text.find(begin), text.find(end)) else {
        bail!(
            "{}: the {begin} / {end} markers are missing",
            path.display()
        );
    };
    let updated = format!("{}{begin}\n{block}{}", &text[..start], &text[stop..]);
    std::fs::write(&path, updated)?;
    eprintln!("wrote {}", path.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ablations_are_paired_with_the_full_method_of_the_same_seed() {
        let record = |group: &str, seed: u64, psnr: f64, divergence: f64| {
            json!({
                "key": format!("{group}-s{seed}"),
                "group": group,
                "seed": seed,
                "variant": "v",
                "test_psnr": psnr,
                "test_ssim": 0.9,
                "velocity_relative_error": 0.5,
                "density_relative_error": 0.5,
                "mean_abs_divergence": divergence,
            })
        };
        let records = vec![
            record("synthetic-quick", 1, 40.0, 0.01),
            record("synthetic-quick", 2, 44.0, 0.01),
            // No ablation ran with seed 3: it is left out of the pairs.
            record("synthetic-quick", 3, 10.0, 0.01),
            record("synthetic-quick-no-physics", 1, 39.0, 0.1),
            record("synthetic-quick-no-physics", 2, 42.0, 0.2),
        ];
        let mut block = String::new();
        write_seed_summary(&mut block, &records).unwrap();
        // PSNR differences 1 and 2 dB: mean 1.5, sample sd 0.71, the full method better in
        // both; divergence differences -0.09 and -0.19: lower with the full method in both.
        assert!(
            block.contains(
                "| `synthetic-quick` | w/o physical losses | 2 | +1.50 +- 0.71 (2/2) \
                 | +0.000 +- 0.000 (0/2) | +0.000 +- 0.000 (0/2) | -1.40e-1 +- 7.07e-2 (2/2) |"
            ),
            "{block}"
        );
    }

    /// The slice of `reproduce scalar-real --quick` that CI runs: two frames of the real
    /// capture, recorded into a temporary docs folder (the repository's results stay as they
    /// are).
    #[test]
    fn a_two_frame_scalar_real_slice_is_recorded() {
        let root = crate::workspace_root();
        let dir = tempfile::tempdir().unwrap();
        let docs = dir.path().join("docs");
        std::fs::create_dir_all(&docs).unwrap();
        std::fs::copy(root.join("docs/RESULTS.md"), docs.join("RESULTS.md")).unwrap();
        let args = ReproduceArgs {
            target: Target::ScalarReal,
            quick: true,
            device: "flex".into(),
            out: dir.path().join("runs"),
            data: Some(root.join("../shared/datasets/scalar_real")),
            frames: Some(2),
            resume: false,
            no_ablations: false,
            lpips_weights: None,
            seed: None,
            respawn: None,
            overrides: Vec::new(),
            tag: None,
            docs: Some(docs.clone()),
        };
        run(args).unwrap();

        let record: Value = serde_json::from_str(
            &std::fs::read_to_string(docs.join("results/scalar-real-quick-f2.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(record["frames"], 2);
        assert_eq!(record["gaussians"], 8000);
        // Measured 36.1 and 35.7 dB on frames 0 and 1 (2026-11-22). A broken loader, camera
        // convention or renderer lands far below: an all-black render scores roughly 28 dB.
        let psnr = record["test_psnr"].as_f64().unwrap();
        assert!(psnr > 33.0, "held-out PSNR {psnr} dB");
        let divergence = record["mean_abs_divergence"].as_f64().unwrap();
        assert!(divergence < 1e-4, "mean |div u| {divergence}");
        let results = std::fs::read_to_string(docs.join("RESULTS.md")).unwrap();
        assert!(
            results.contains("| `scalar-real-quick-f2` | full method | 2 | 8000 |"),
            "{results}"
        );
        assert!(
            results.contains("## Why we fall short"),
            "the hand-written part of RESULTS.md is kept"
        );
    }
}
