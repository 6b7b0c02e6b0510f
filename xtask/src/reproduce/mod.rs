//! `cargo xtask reproduce scalar-real|synthetic [--quick]`: trains with the library API the
//! CLI uses, evaluates on the held-out views, and records what was measured.
//!
//! Every run writes `docs/results/<key>.json` (metrics, timings, memory, storage, machine,
//! date and the command), and `docs/RESULTS.md`'s generated block (between the
//! `results:begin` / `results:end` markers) is rebuilt from all such files, so the tables hold
//! only measured numbers. The prose around the block is written by people.

use std::ops::Not as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_render::backends;
use gausmoke_train::config::LookaheadVelocity;
use gausmoke_train::{Run, TrainConfig, eval, sequence::Sequence};
use serde_json::{Value, json};

mod ablation;
mod independent;
pub mod reevaluate;
mod results;

use ablation::Ablation;
pub use results::write_results_md;

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Target {
    /// The real ScalarFlow capture (paper Table 1/2): train00, 01, 03, 04; test train02.
    ScalarReal,
    /// A synthetic plume with ground truth, and the paper's Table 3 ablations.
    Synthetic,
    /// A long synthetic plume with ground truth that leaves through the box's top while the
    /// source keeps feeding it (the drift test; `--quick`: 72 frames, 32^3, 64x96).
    SyntheticLong,
    /// The long plume turning about its vertical axis (about 3 degrees per frame), trained
    /// with the long plume's presets: the scene on which transport can carry what earlier
    /// frames' views saw to directions no present view looks from (issue 18).
    Turning,
    /// A synthetic plume rising past a solid sphere (issue 20), with the solid condition on
    /// and off (`--quick`: 48 frames, 32^3, 64x96).
    Obstacle,
    /// The same plume past the sphere drawn as a textured ball over a grey-blue background
    /// (issue 20), with and without static primitives.
    Ball,
    /// The same plume past a box, in front of a wall across the back of the box, both drawn
    /// checkered (issue 20): static primitives and the solid condition each on and off.
    Blocks,
    /// The blocks scene as a Blender-style multi-view D-NeRF set: 12 cameras round the box at
    /// 800x800, 120 frames (`--quick`: 12 frames, trained at 100x100), static primitives.
    Blender,
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
    /// LPIPS weights (see `gausmoke-train eval --help`); default: the file `cargo xtask
    /// lpips-weights` caches, when present; without weights LPIPS is not reported.
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
    /// The turning plume's swirl, degrees per frame (default: the preset's 5, which turns the
    /// smoke about 3 degrees per frame). Data in `<out>/data-synthetic-turning-swirl<D>`,
    /// runs under `-swirl<D>` keys.
    #[arg(long, value_name = "DEGREES")]
    swirl: Option<f32>,
    /// Train the quick presets of scalar-real, synthetic-long, turning, obstacle, ball and
    /// blocks with the paper's update (Algorithm 1 as written, K = 20) instead of ours. Runs
    /// get `-paper` keys.
    #[arg(long)]
    paper_update: bool,
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
    /// After each run, fit these frames each on their own (the frame-0 fit's settings) and
    /// record them beside it: the independent per-frame baseline (comma list, e.g.
    /// `0,30,60,90,119`). Written to `<out>/<key>-independent/frame_TTT`.
    #[arg(long, value_delimiter = ',', value_name = "FRAMES")]
    independent: Vec<usize>,
    /// Train with the configuration recorded in `<docs>/results/<KEY>.json` instead of the
    /// preset's: re-running a record made before the preset changed, as it was configured
    /// (settings the record predates take their defaults, which are the behaviour it ran
    /// with). The command must name the same run (key) as the record; no --set.
    #[arg(long, value_name = "KEY")]
    config_of: Option<String>,
    /// After each run, estimate its velocity from its density grids (`gausmoke-train
    /// velocity`, the default weights) and record that estimate's errors beside the run's
    /// own velocity's (`velocity_estimate_*`).
    #[arg(long)]
    velocity_estimate: bool,
    /// The same with `gausmoke-train velocity --forces` (each fit started from a smoke
    /// solver's step; the source is the preset's inflow box, so presets without one are
    /// refused before training).
    #[arg(long, conflicts_with = "velocity_estimate")]
    velocity_estimate_forces: bool,
}

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
        open_faces: scalar_real_open_faces(),
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
        open_faces: scalar_real_open_faces(),
        ..TrainConfig::default()
    }
}

/// Our sequential update on top of the paper's, for a scene whose smoke enters through a known
/// inflow (`inflow`: a box in fractions of the smoke box, around the source). The velocity is
/// also fitted to the next frame's views along Phi's prediction for that frame, carried by its
/// own flow from frame to frame, and its increment is kept small; Gaussians the training
/// views leave unused are recycled into the inflow, and the unused rows recycling leaves take
/// the halves of the largest Gaussians (1% of all a frame). Half the joint iterations pay for
/// the look-ahead's second render and U-Net pass. Measured at the quick presets' scale only
/// (three paired seeds on each scene): docs/RESULTS.md, "Why we fall short", item 1.
fn with_look_ahead_and_inflow(config: TrainConfig, inflow: [f32; 6]) -> TrainConfig {
    TrainConfig {
        lambda_lookahead: 1.0,
        lookahead_velocity: LookaheadVelocity::Predicted,
        transport_velocity: true,
        lambda_increment: 0.01,
        respawn_fraction: 0.02,
        respawn_threshold: 0.01,
        respawn_region: Some(inflow),
        split_fraction: 0.01,
        advect_iterations: config.advect_iterations / 2,
        ..config
    }
}

/// On the long plume, on top of [`with_look_ahead_and_inflow`]: K' = 40 refinement steps of
/// one training view each (the renders of ten four-view steps) with the grid-scale part of
/// their moves tied, and horizontal increments charged three times the vertical in the
/// inertia prior: +1.87 +- 0.33 dB held out over the preset without them, the 3D density and
/// the velocity closer to the truth (three paired seeds). On ScalarReal the same costs 0.23 dB
/// held out (three seeds), so that preset does not set it. docs/RESULTS.md, "Why we fall
/// short", item 1.
fn with_one_view_refinement(config: TrainConfig) -> TrainConfig {
    TrainConfig {
        refine_iterations: ONE_VIEW_REFINE_ITERATIONS,
        refine_views_per_step: 1,
        lambda_refine_grid: 3.0,
        increment_horizontal_weight: 3.0,
        ..config
    }
}

/// K' of the long plume's quick preset, in one-view refinement steps.
const ONE_VIEW_REFINE_ITERATIONS: usize = 40;

/// Around the synthetic solver's source disc, on the floor at the box's centre.
const SYNTHETIC_INFLOW: [f32; 6] = [0.35, 0.0, 0.35, 0.65, 0.15, 0.65];

/// Around ScalarFlow's inflow, where the smoke leaves the generator at the bottom of the box.
const SCALAR_REAL_INFLOW: [f32; 6] = [0.4, 0.0, 0.4, 0.66, 0.15, 0.66];

/// On ScalarReal with our update, a quarter of `lr_gaussians` for the Gaussians' sizes after
/// frame 0: +0.21 +- 0.09 dB held out over 120 frames (three paired seeds). On the long plume
/// the same costs 1.0 dB held out (while its 3D density moves closer to the truth), so that
/// preset keeps the sizes at `lr_gaussians`. docs/RESULTS.md, "Why we fall short", item 1.
const SCALAR_REAL_LR_LOG_SCALES: f64 = 5e-4;

/// The long synthetic plume at the reduced scale of the ScalarReal quick preset: the solver's
/// 32^3 grid, its 64x96 images, 4000 Gaussians (a quarter of the pixels per view, as 8000 is
/// for 90x160 there), the same iterations and learning rates.
fn quick_synthetic_long() -> TrainConfig {
    TrainConfig {
        gaussians: 4000,
        frames: None,
        image_size: None,
        open_faces: synthetic_open_faces(),
        ..quick_scalar_real()
    }
}

/// The paper's settings on the synthetic scenes, whose smoke leaves through the box's top.
fn full_synthetic_long() -> TrainConfig {
    TrainConfig {
        open_faces: synthetic_open_faces(),
        ..TrainConfig::default()
    }
}

/// The synthetic solver's boundary: solid floor and sides, open top (`gausmoke_data::synth`).
fn synthetic_open_faces() -> Vec<String> {
    vec!["y+".into()]
}

/// The synthetic solver's top is open to pressure but its divergence reads a still cell above
/// it: half the top cell's velocity on the face. Set for the scenes that train as the long
/// plume does ([`trains_as_the_long_plume`]; with and without `--paper-update`: it is the
/// scene's boundary, not part of our update). The scene's true velocity lies closer to
/// what this projection returns than to an outflow's or a wall's, and on the long plume it
/// gains +0.28 +- 0.32 dB held out and lowers the velocity's error by 0.029 +- 0.018 against
/// the outflow (eight paired seeds), its sampled frames against the frames fitted alone
/// within the spread of a placebo. docs/RESULTS.md, "Why we fall short", item 1.
const SYNTHETIC_TOP_FLOW: f32 = 0.5;

/// The plume rises through the box's top and draws air in at the bottom; with these two faces
/// solid the quick preset fell below fitting each frame alone after frame 60 (three paired
/// seeds, docs/RESULTS.md, "Why we fall short" item 1).
fn scalar_real_open_faces() -> Vec<String> {
    vec!["y-".into(), "y+".into()]
}

/// `config` with as many static Gaussians as smoke ones (4000), for the blocks scene's and
/// the Blender set's quick presets, whose wall fills most of every view. With 2000, 400
/// steps of their fit leave the wall's checker to frame 0's smoke, which paints it
/// (docs/RESULTS.md, "Obstacles and static solids"). Against 2000, three paired seeds each:
/// on blocks the smoke's 3D density correlates with the truth at 0.81-0.86 against
/// 0.65-0.68, on the Blender set at 0.83-0.87 against 0.50-0.65, the smoke inside the
/// solids falls (blocks 14-15% to 6-8%, Blender 46-56% to 21-28%), and the held-out view
/// does not pay (+0.08 +- 0.16 / +0.24 +- 0.39 dB; SSIM higher in 6 of 6). Fitting 2000 for
/// longer instead makes the density about as true (Blender 0.89), but costs the held-out
/// view 0.70 dB on blocks (four views) and 0.47 dB against this on the Blender set.
fn with_statics_for_a_wall(config: TrainConfig) -> TrainConfig {
    TrainConfig {
        static_gaussians: config.gaussians,
        ..config
    }
}

/// The scenes whose quick presets train as the long plume's does (our update, the one-view
/// refinement, the solver's half-open top): the plume itself, the turning plume, the plume
/// past a sphere, undrawn or drawn as a ball, and past a block before a checkered wall, where
/// the same gains +3.80 / +0.90 / +0.64 dB held out and a truer velocity over the paper's
/// update (three paired seeds each, docs/RESULTS.md, "Obstacles and static solids").
fn trains_as_the_long_plume(target: Target) -> bool {
    matches!(
        target,
        Target::SyntheticLong | Target::Turning | Target::Obstacle | Target::Ball | Target::Blocks
    )
}

/// One training run of the reproduction: a key for file names, a label for tables, and the
/// group of runs it repeats with another seed.
#[derive(Debug)]
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
    if let Some(degrees) = args.swirl {
        if args.target != Target::Turning {
            bail!("--swirl: only the turning plume has a swirl to set");
        }
        if let Some(data) = &args.data {
            bail!(
                "--swirl sets the swirl of the scene reproduce generates; {} is read as it is \
                 (drop --data or --swirl)",
                data.display()
            );
        }
        suffix += &format!("-swirl{degrees}");
    }
    let inflow = match (args.target, args.quick) {
        (Target::ScalarReal, true) => Some(SCALAR_REAL_INFLOW),
        (target, true) if trains_as_the_long_plume(target) => Some(SYNTHETIC_INFLOW),
        _ => None,
    };
    if args.paper_update {
        if inflow.is_none() {
            let ours: Vec<&str> = Target::value_variants()
                .iter()
                .filter(|&&t| t == Target::ScalarReal || trains_as_the_long_plume(t))
                .map(|t| t.cli_name())
                .collect();
            let (last, rest) = ours.split_last().expect("scalar-real uses our update");
            bail!(
                "--paper-update: only the quick presets of {} and {last} use our update; this \
                 one trains with the paper's already",
                rest.join(", ")
            );
        }
        suffix += "-paper";
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
        (Target::SyntheticLong | Target::Turning | Target::Obstacle, true) => {
            quick_synthetic_long()
        }
        (Target::SyntheticLong | Target::Turning | Target::Obstacle, false) => {
            full_synthetic_long()
        }
        // A quarter as many static Gaussians as smoke ones.
        (Target::Ball, true) => TrainConfig {
            static_gaussians: 1000,
            ..quick_synthetic_long()
        },
        (Target::Ball, false) => TrainConfig {
            static_gaussians: 7500,
            ..full_synthetic_long()
        },
        (Target::Blocks, true) => with_statics_for_a_wall(quick_synthetic_long()),
        // Eleven training views, each loaded from 800x800 down to 100x100.
        (Target::Blender, true) => TrainConfig {
            image_size: Some([100, 100]),
            ..with_statics_for_a_wall(quick_synthetic_long())
        },
        (Target::Blocks | Target::Blender, false) => TrainConfig {
            static_gaussians: 15000,
            ..full_synthetic_long()
        },
    };
    if trains_as_the_long_plume(args.target) {
        // The scene's own top, measured on the long plume. The other scenes keep the outflow
        // their records ran with.
        base.open_face_flow = SYNTHETIC_TOP_FLOW;
    }
    if let Some(inflow) = inflow.filter(|_| !args.paper_update) {
        base = with_look_ahead_and_inflow(base, inflow);
        match args.target {
            Target::ScalarReal => base.lr_log_scales = Some(SCALAR_REAL_LR_LOG_SCALES),
            target if trains_as_the_long_plume(target) => base = with_one_view_refinement(base),
            _ => {}
        }
    }
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
        Target::SyntheticLong => vec![keyed("synthetic-long", "", "full method", base)],
        Target::Turning => vec![keyed("turning", "", "full method", base)],
        Target::Blender => vec![keyed("blender", "", "full method", base)],
        Target::Obstacle | Target::Ball | Target::Blocks => {
            let (name, ablations): (_, &[Ablation]) = match args.target {
                Target::Obstacle => ("obstacle", &[Ablation::Solid]),
                Target::Ball => ("ball", &[Ablation::Statics]),
                _ => ("blocks", &[Ablation::Statics, Ablation::Solid]),
            };
            let mut list = vec![keyed(name, "", "full method", base.clone())];
            if !args.no_ablations {
                for ablation in ablations {
                    list.push(keyed(
                        name,
                        ablation.suffix(),
                        ablation.label(),
                        ablation.apply(base.clone()),
                    ));
                }
            }
            list
        }
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

/// The record this run folder wrote before, if any (the same key and `run`).
fn previous_record(path: &Path, run_dir: &Path) -> Option<Value> {
    let record: Value = serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()?;
    (record["run"].as_str() == Some(&*run_dir.display().to_string())).then_some(record)
}

/// Wall time and peak memory for a record. This process measured only its own session, so
/// a resumed run adds the earlier sessions from the run's previous record, or records
/// neither (null) where there is none, rather than a session's part as the whole.
fn session_totals(
    previous: Option<Value>,
    resumed: bool,
    wall_seconds: f64,
    peak_memory: Option<f64>,
) -> (Value, Value) {
    if !resumed {
        return (json!(wall_seconds), json!(peak_memory));
    }
    let Some(previous) = previous else {
        eprintln!(
            "warning: resumed without this run's earlier record: its wall time and peak \
             memory are recorded as unknown"
        );
        return (Value::Null, Value::Null);
    };
    let wall = previous["wall_seconds_with_outputs"]
        .as_f64()
        .map(|before| before + wall_seconds);
    let peak = previous["peak_memory_mib"]
        .as_f64()
        .zip(peak_memory)
        .map(|(a, b)| a.max(b));
    (json!(wall), json!(peak))
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

/// `value` as one POSIX shell word: as is when it holds no character the shell treats
/// specially, else in single quotes.
fn shell_quoted(value: &str) -> String {
    let plain = |c: char| c.is_ascii_alphanumeric() || "-_=.,/:+@%".contains(c);
    if !value.is_empty() && value.chars().all(plain) {
        value.to_string()
    } else {
        format!("'{}'", value.replace('\'', r"'\''"))
    }
}

impl Target {
    /// The name `reproduce` takes on its command line.
    fn cli_name(self) -> &'static str {
        match self {
            Target::ScalarReal => "scalar-real",
            Target::Synthetic => "synthetic",
            Target::SyntheticLong => "synthetic-long",
            Target::Turning => "turning",
            Target::Obstacle => "obstacle",
            Target::Ball => "ball",
            Target::Blocks => "blocks",
            Target::Blender => "blender",
        }
    }
}

fn command_line(args: &ReproduceArgs) -> String {
    let mut line = format!(
        "cargo run --release -p xtask -- reproduce {}",
        args.target.cli_name()
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
    if let Some(degrees) = args.swirl {
        line += &format!(" --swirl {degrees}");
    }
    if args.paper_update {
        line += " --paper-update";
    }
    for entry in &args.overrides {
        line += &format!(" --set {}", shell_quoted(entry));
    }
    if let Some(tag) = &args.tag {
        line += &format!(" --tag {}", shell_quoted(tag));
    }
    if let Some(key) = &args.config_of {
        line += &format!(" --config-of {}", shell_quoted(key));
    }
    if args.no_ablations {
        line += " --no-ablations";
    }
    if args.velocity_estimate {
        line += " --velocity-estimate";
    }
    if args.velocity_estimate_forces {
        line += " --velocity-estimate-forces";
    }
    if let Some(data) = &args.data {
        line += &format!(" --data {}", shell_quoted(&data.display().to_string()));
    }
    if let Some(weights) = &args.lpips_weights {
        line += &format!(
            " --lpips-weights {}",
            shell_quoted(&weights.display().to_string())
        );
    }
    if !args.independent.is_empty() {
        let frames: Vec<String> = args.independent.iter().map(|t| t.to_string()).collect();
        line += &format!(" --independent {}", frames.join(","));
    }
    line
}

/// The one run `variants` names, configured as the record `key` in `results_dir` says (see
/// `--config-of`).
fn recorded_variant(
    variants: Vec<Variant>,
    key: &str,
    results_dir: &Path,
    args: &ReproduceArgs,
) -> Result<Variant> {
    if !args.overrides.is_empty() {
        bail!("--config-of takes the whole configuration from the record: no --set");
    }
    let [variant] = <[Variant; 1]>::try_from(variants).map_err(|all| {
        anyhow::anyhow!(
            "--config-of re-runs one record, and this command names {} runs (add \
             --no-ablations)",
            all.len()
        )
    })?;
    if variant.key != key {
        bail!(
            "--config-of {key}: this command names the run `{}`, not that record's",
            variant.key
        );
    }
    let path = results_dir.join(format!("{key}.json"));
    let record: Value = serde_json::from_str(
        &std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?,
    )
    .with_context(|| format!("parsing {}", path.display()))?;
    let config: TrainConfig = serde_json::from_value(record["config"].clone())
        .with_context(|| format!("{}: the field `config`", path.display()))?;
    config
        .validate()
        .with_context(|| format!("{}: the recorded configuration", path.display()))?;
    let label = record["variant"]
        .as_str()
        .map_or(variant.label, str::to_string);
    Ok(Variant {
        label,
        config,
        ..variant
    })
}

/// Whether `dir` holds a data set `Sequence::open` reads: PINF (`info.json`), D-NeRF
/// (`transforms_train.json`) or nerfstudio (`transforms.json`).
fn is_data_set(dir: &Path) -> bool {
    dir.join("info.json").is_file()
        || dir.join("transforms_train.json").is_file()
        || gausmoke_data::is_nerfstudio(dir)
}

pub fn run(args: ReproduceArgs) -> Result<()> {
    if cfg!(debug_assertions) {
        eprintln!("warning: a debug build; use `cargo run --release -p xtask -- reproduce ...`");
    }
    let root = crate::workspace_root();
    let data = match (args.target, &args.data) {
        (_, Some(path)) => path.clone(),
        (Target::ScalarReal, None) => root.join("../shared/datasets/scalar_real"),
        (
            Target::Synthetic
            | Target::SyntheticLong
            | Target::Turning
            | Target::Obstacle
            | Target::Ball
            | Target::Blocks
            | Target::Blender,
            None,
        ) => {
            let (preset, config) = match (args.target, args.quick) {
                (Target::Synthetic, true) => ("tiny", SynthConfig::tiny()),
                (Target::SyntheticLong, true) => ("long", SynthConfig::long_plume()),
                (Target::Turning, true) => ("turning", SynthConfig::turning_plume()),
                (Target::Obstacle, true) => ("obstacle", SynthConfig::obstacle_plume()),
                (Target::Ball, true) => ("ball", SynthConfig::ball_plume()),
                (Target::Blocks, true) => ("blocks", SynthConfig::blocks_plume()),
                (Target::Blender, true) => (
                    "blender-blocks-f12",
                    SynthConfig {
                        frames: 12,
                        ..SynthConfig::blender_blocks()
                    },
                ),
                (Target::Blender, false) => ("blender-blocks", SynthConfig::blender_blocks()),
                (Target::Blocks, false) => (
                    "blocks-scalarflow",
                    SynthConfig {
                        solids: SynthConfig::blocks_plume().solids,
                        background: SynthConfig::blocks_plume().background,
                        ..SynthConfig::scalarflow()
                    },
                ),
                (Target::Ball, false) => (
                    "ball-scalarflow",
                    SynthConfig {
                        solids: SynthConfig::ball_plume().solids,
                        background: SynthConfig::ball_plume().background,
                        ..SynthConfig::scalarflow()
                    },
                ),
                (Target::Turning, false) => (
                    "turning-scalarflow",
                    SynthConfig {
                        swirl_degrees: SynthConfig::turning_plume().swirl_degrees,
                        ..SynthConfig::scalarflow()
                    },
                ),
                (Target::Obstacle, false) => (
                    "obstacle-scalarflow",
                    SynthConfig {
                        solids: SynthConfig::obstacle_plume().solids,
                        ..SynthConfig::scalarflow()
                    },
                ),
                _ => ("scalarflow", SynthConfig::scalarflow()),
            };
            let (preset, config) = match args.swirl {
                Some(degrees) => (
                    format!("{preset}-swirl{degrees}"),
                    SynthConfig {
                        swirl_degrees: degrees,
                        ..config
                    },
                ),
                None => (preset.to_string(), config),
            };
            let path = args.out.join(format!("data-synthetic-{preset}"));
            if !is_data_set(&path) {
                eprintln!(
                    "generating the `{preset}` synthetic scene in {}",
                    path.display()
                );
                if let Err(e) = generate(&config, &path) {
                    // Another run started beside this one may have finished it meanwhile.
                    if !is_data_set(&path) {
                        return Err(e.into());
                    }
                    eprintln!(
                        "another run generated {} meanwhile; using it",
                        path.display()
                    );
                }
            }
            path
        }
    };
    if !is_data_set(&data) {
        bail!(
            "{}: neither info.json, transforms_train.json nor transforms.json (is this the \
             data set folder?)",
            data.display()
        );
    }
    let device = backends::device_by_name(&args.device).map_err(anyhow::Error::msg)?;
    let docs = args.docs.clone().unwrap_or_else(|| root.join("docs"));
    let results_dir = docs.join("results");
    std::fs::create_dir_all(&results_dir)?;
    let lpips_weights = gausmoke_train::lpips::weights_to_use(args.lpips_weights.as_deref());
    let baseline = independent::Baseline {
        frames: &args.independent,
        data: &data,
        device: &device,
        resume: args.resume,
        lpips_weights: lpips_weights.as_deref(),
    };
    let mut variants = variants(&args)?;
    if let Some(key) = &args.config_of {
        variants = vec![recorded_variant(variants, key, &results_dir, &args)?];
    }
    let estimate = if args.velocity_estimate_forces {
        if let Some(variant) = variants.iter().find(|v| v.config.respawn_region.is_none()) {
            bail!(
                "--velocity-estimate-forces: run {} has no inflow box (respawn_region) for the \
                 smoke step's source; estimate it afterwards with `gausmoke-train velocity \
                 --forces --source-box x0,y0,z0,x1,y1,z1`",
                variant.key
            );
        }
        Some(gausmoke_train::velocity_estimate::EstimateOptions::forced())
    } else {
        args.velocity_estimate
            .then(gausmoke_train::velocity_estimate::EstimateOptions::default)
    };
    for variant in variants {
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
        independent::check_frames(&args.independent, frames)?;
        let start = Instant::now();
        let mut trainer = Run::new(
            scene,
            variant.config.clone(),
            device.clone().autodiff(),
            &run_dir,
            args.resume,
        )?;
        let resumed = trainer.frame.is_some();
        trainer.run()?;
        let wall_seconds = start.elapsed().as_secs_f64();
        let gaussians = trainer.trainer.state.gaussians.len();
        drop(trainer);
        let estimate_seconds = match &estimate {
            Some(options) => {
                let start = Instant::now();
                gausmoke_train::velocity_estimate::estimate_run_velocity(
                    &run_dir,
                    options,
                    &device,
                    |_, _| {},
                )?;
                Some(start.elapsed().as_secs_f64())
            }
            None => None,
        };
        let report = eval::evaluate(&run_dir, &device, lpips_weights.as_deref())?;
        let metrics: Value = serde_json::from_str(
            &std::fs::read_to_string(run_dir.join("metrics.json")).context("metrics.json")?,
        )?;
        let independent = baseline.fit(
            &variant.config,
            &report,
            &args.out.join(format!("{}-independent", variant.key)),
        )?;
        let per_frame = |value: fn(&eval::FrameEval) -> Option<f64>| -> Vec<Option<f64>> {
            report.frames.iter().map(value).collect()
        };
        let from_metrics = |name: &str| -> Vec<Value> {
            metrics["per_frame"]
                .as_array()
                .map(|rows| rows.iter().map(|row| row[name].clone()).collect())
                .unwrap_or_default()
        };
        let last_frame = run_dir
            .join("frames")
            .join(format!("frame_{:03}.safetensors", frames - 1));
        let frames_bytes: u64 = std::fs::read_dir(run_dir.join("frames"))
            .map(|dir| dir.flatten().map(|e| file_size(&e.path())).sum())
            .unwrap_or(0);
        let path = results_dir.join(format!("{}.json", variant.key));
        let (wall_seconds, peak_memory) = session_totals(
            resumed.then(|| previous_record(&path, &run_dir)).flatten(),
            resumed,
            wall_seconds,
            peak_memory_mib(),
        );
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
            "velocity_cosine": report.velocity_cosine_mean,
            "density_relative_error": report.density_relative_error_mean,
            "density_correlation": report.density_correlation_mean,
            "density_scaled_relative_error": report.density_scaled_relative_error_mean,
            "density_best_scale": report.density_best_scale_mean,
            "density_outside_smoke_fraction": report.density_outside_smoke_fraction_mean,
            "test_psnr_per_frame": per_frame(|f| f.test_psnr),
            "test_ssim_per_frame": per_frame(|f| f.test_ssim),
            "test_lpips_per_frame": per_frame(|f| f.test_lpips),
            "velocity_relative_error_per_frame": per_frame(|f| f.velocity_relative_error),
            "velocity_rmse_per_frame": per_frame(|f| f.velocity_rmse),
            "velocity_cosine_per_frame": per_frame(|f| f.velocity_cosine),
            "density_relative_error_per_frame": per_frame(|f| f.density_relative_error),
            "density_correlation_per_frame": per_frame(|f| f.density_correlation),
            "density_scaled_relative_error_per_frame":
                per_frame(|f| f.density_scaled_relative_error),
            "density_best_scale_per_frame": per_frame(|f| f.density_best_scale),
            "density_outside_smoke_fraction_per_frame":
                per_frame(|f| f.density_outside_smoke_fraction),
            "velocity_estimate_relative_error": report.velocity_estimate_relative_error_mean,
            "velocity_estimate_cosine": report.velocity_estimate_cosine_mean,
            "velocity_estimate_relative_error_per_frame":
                per_frame(|f| f.velocity_estimate_relative_error),
            "velocity_estimate_cosine_per_frame": per_frame(|f| f.velocity_estimate_cosine),
            "velocity_estimate_mean_abs_divergence_per_frame":
                per_frame(|f| f.velocity_estimate_mean_abs_divergence),
            "velocity_estimate_seconds": estimate_seconds,
            "velocity_estimate_options": estimate,
            "velocity_estimate_obstacle_normal_flow":
                report.velocity_estimate_obstacle_normal_flow_mean,
            "velocity_estimate_obstacle_normal_flow_per_frame":
                per_frame(|f| f.velocity_estimate_obstacle_normal_flow),
            "obstacle_density_fraction": report.obstacle_density_fraction_mean,
            "obstacle_normal_flow": report.obstacle_normal_flow_mean,
            "obstacle_density_fraction_per_frame": per_frame(|f| f.obstacle_density_fraction),
            "obstacle_normal_flow_per_frame": per_frame(|f| f.obstacle_normal_flow),
            "mean_abs_divergence_per_frame": per_frame(|f| Some(f.mean_abs_divergence)),
            "train_l1_per_frame": from_metrics("train_l1"),
            "clamped_to_box_per_frame": from_metrics("clamped_to_box"),
            "refine_move_cells_per_frame": from_metrics("refine_move_cells"),
            "refine_move_grid_share_per_frame": from_metrics("refine_move_grid_share"),
            "refine_move_grid_share_shuffled_per_frame": from_metrics("refine_move_grid_share_shuffled"),
            "refine_move_persistence_per_frame": from_metrics("refine_move_persistence"),
            "refine_move_grid_persistence_per_frame": from_metrics("refine_move_grid_persistence"),
            "refine_move_flow_share_per_frame": from_metrics("refine_move_flow_share"),
            "refine_move_flow_persistence_per_frame": from_metrics("refine_move_flow_persistence"),
            "refine_move_gathering_persistence_per_frame": from_metrics("refine_move_gathering_persistence"),
            "independent": independent,
            "training_seconds": metrics["training_seconds"],
            "wall_seconds_with_outputs": wall_seconds,
            "phase_seconds": metrics["phase_seconds"],
            "peak_memory_mib": peak_memory,
            "state_bytes_per_frame": file_size(&last_frame),
            "state_bytes_all_frames": frames_bytes,
            "run": run_dir.display().to_string(),
        });
        results::write_atomically(&path, &serde_json::to_string_pretty(&record)?)?;
        eprintln!(
            "   PSNR {:?} SSIM {:?} |div u| {:.3e}; wrote {}",
            report.test_psnr_mean,
            report.test_ssim_mean,
            report.mean_abs_divergence,
            path.display()
        );
    }
    write_results_md(&docs)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resumed_record_keeps_the_earlier_sessions_wall_time_and_peak_memory() {
        let fresh = session_totals(None, false, 12.5, Some(80.0));
        assert_eq!(fresh, (json!(12.5), json!(80.0)));
        let earlier = json!({"wall_seconds_with_outputs": 500.0, "peak_memory_mib": 130.0});
        let resumed = session_totals(Some(earlier), true, 0.5, Some(75.0));
        assert_eq!(resumed, (json!(500.5), json!(130.0)));
        // Resumed with no earlier record: unknown, not this session's part.
        assert_eq!(
            session_totals(None, true, 0.5, Some(75.0)),
            (Value::Null, Value::Null)
        );
    }

    #[test]
    fn recorded_settings_are_single_shell_words() {
        assert_eq!(shell_quoted("frames=4"), "frames=4");
        assert_eq!(
            shell_quoted(r#"open_faces=["y-","y+"]"#),
            r#"'open_faces=["y-","y+"]'"#
        );
        assert_eq!(shell_quoted("a b"), "'a b'");
        assert_eq!(shell_quoted("it's"), r"'it'\''s'");
        assert_eq!(shell_quoted(""), "''");
    }

    /// `reproduce TARGET --quick` on flex with nothing else set, as the tests start from.
    fn quick_args(target: Target) -> ReproduceArgs {
        ReproduceArgs {
            target,
            quick: true,
            device: "flex".into(),
            out: PathBuf::from("runs"),
            data: None,
            frames: None,
            resume: false,
            no_ablations: false,
            lpips_weights: None,
            seed: None,
            respawn: None,
            swirl: None,
            paper_update: false,
            overrides: Vec::new(),
            tag: None,
            docs: None,
            independent: Vec::new(),
            config_of: None,
            velocity_estimate: false,
            velocity_estimate_forces: false,
        }
    }

    #[test]
    fn the_long_synthetic_plume_trains_all_frames_with_an_open_top() {
        let args = ReproduceArgs {
            seed: Some(3),
            independent: vec![0, 36, 71],
            ..quick_args(Target::SyntheticLong)
        };
        let list = variants(&args).unwrap();
        assert_eq!(list.len(), 1, "no ablations on the long plume");
        let config = &list[0].config;
        assert_eq!(list[0].key, "synthetic-long-quick-s3");
        assert_eq!(list[0].group, "synthetic-long-quick");
        assert_eq!(config.open_faces, ["y+"]);
        assert_eq!((config.frames, config.image_size), (None, None));
        assert_eq!(config.gaussians, 4000);
        assert_eq!(config.grid_resolution, SynthConfig::long_plume().grid);
        assert_eq!(config.seed, 3);
        config.validate().unwrap();
        assert!(
            command_line(&args)
                .ends_with("reproduce synthetic-long --quick --seed 3 --independent 0,36,71"),
            "{}",
            command_line(&args)
        );
    }

    /// The turning plume is trained exactly as the long plume is, under its own key, so the
    /// two scenes' gains over the frames fitted alone compare like for like.
    #[test]
    fn the_turning_plume_trains_with_the_long_plumes_preset() {
        let turning = |target| ReproduceArgs {
            seed: Some(2),
            independent: vec![18, 36],
            ..quick_args(target)
        };
        let long = variants(&turning(Target::SyntheticLong)).unwrap().remove(0);
        let list = variants(&turning(Target::Turning)).unwrap();
        assert_eq!(list.len(), 1);
        assert_eq!(
            (list[0].key.as_str(), list[0].group.as_str()),
            ("turning-quick-s2", "turning-quick")
        );
        assert_eq!(list[0].config, long.config);
        assert!(
            command_line(&turning(Target::Turning))
                .ends_with("reproduce turning --quick --seed 2 --independent 18,36")
        );
        let faster = ReproduceArgs {
            swirl: Some(15.0),
            ..turning(Target::Turning)
        };
        let list = variants(&faster).unwrap();
        assert_eq!(list[0].key, "turning-quick-swirl15-s2");
        assert_eq!(list[0].config, long.config);
        assert!(command_line(&faster).contains("--seed 2 --swirl 15 --independent"));
        let err = variants(&ReproduceArgs {
            swirl: Some(15.0),
            ..quick_args(Target::SyntheticLong)
        })
        .unwrap_err()
        .to_string();
        assert!(err.contains("--swirl"), "{err}");
        let err = variants(&ReproduceArgs {
            data: Some(PathBuf::from("scenes/mine")),
            ..faster
        })
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("--swirl") && err.contains("scenes/mine"),
            "{err}"
        );
    }

    /// The quick presets of the scenes with an inflow train with our update, each
    /// recycling into its own source; `--paper-update` gives the paper's back under `-paper`
    /// keys, and is refused where a preset has nothing to give back.
    #[test]
    fn the_quick_plume_presets_train_with_our_update_unless_told_otherwise() {
        for (target, inflow) in [
            (Target::ScalarReal, SCALAR_REAL_INFLOW),
            (Target::SyntheticLong, SYNTHETIC_INFLOW),
            (Target::Obstacle, SYNTHETIC_INFLOW),
            (Target::Ball, SYNTHETIC_INFLOW),
            (Target::Blocks, SYNTHETIC_INFLOW),
        ] {
            let ours = &variants(&quick_args(target)).unwrap()[0];
            let config = &ours.config;
            assert_eq!(config.respawn_region, Some(inflow), "{target:?}");
            assert!(config.lambda_lookahead > 0.0 && config.transport_velocity);
            assert_eq!(config.lookahead_velocity, LookaheadVelocity::Predicted);
            assert_eq!(config.advect_iterations, 10);
            let sizes = (target == Target::ScalarReal).then_some(SCALAR_REAL_LR_LOG_SCALES);
            assert_eq!(config.lr_log_scales, sizes, "{target:?}");
            assert_eq!(config.split_fraction, 0.01);
            let one_view = target != Target::ScalarReal;
            let (steps, views, tie, horizontal) = if one_view {
                (ONE_VIEW_REFINE_ITERATIONS, 1, 3.0, 3.0)
            } else {
                (5, 0, 0.0, 1.0)
            };
            assert_eq!(
                (config.refine_iterations, config.refine_views_per_step),
                (steps, views),
                "{target:?}"
            );
            assert_eq!(config.lambda_refine_grid, tie, "{target:?}");
            assert_eq!(config.increment_horizontal_weight, horizontal, "{target:?}");
            let top_flow = if one_view { SYNTHETIC_TOP_FLOW } else { 1.0 };
            assert_eq!(config.open_face_flow, top_flow, "{target:?}");
            config.validate().unwrap();

            let args = ReproduceArgs {
                paper_update: true,
                seed: Some(2),
                ..quick_args(target)
            };
            let paper = &variants(&args).unwrap()[0];
            assert!(paper.key.ends_with("-quick-paper-s2"), "{}", paper.key);
            // The ablations train with the same update.
            for variant in &variants(&args).unwrap()[1..] {
                assert_eq!(variant.config.lambda_lookahead, 0.0, "{}", variant.key);
            }
            for variant in &variants(&quick_args(target)).unwrap()[1..] {
                assert_eq!(
                    variant.config.respawn_region,
                    Some(inflow),
                    "{}",
                    variant.key
                );
            }
            assert!(command_line(&args).ends_with("--quick --seed 2 --paper-update"));
            let config = &paper.config;
            assert_eq!(config.lambda_lookahead, 0.0);
            assert!(!config.transport_velocity);
            assert_eq!(
                (config.lambda_increment, config.respawn_fraction),
                (0.0, 0.0)
            );
            assert_eq!(config.respawn_region, None);
            assert_eq!(config.advect_iterations, 20);
            assert_eq!(config.lr_log_scales, None);
            assert_eq!(config.split_fraction, 0.0);
            assert_eq!(
                (config.refine_iterations, config.refine_views_per_step),
                (5, 0)
            );
            assert_eq!(config.lambda_refine_grid, 0.0);
            assert_eq!(config.increment_horizontal_weight, 1.0);
            // Everything else is the preset's.
            assert_eq!(config.open_faces, ours.config.open_faces);
            assert_eq!(config.open_face_flow, ours.config.open_face_flow);
            assert_eq!(config.gaussians, ours.config.gaussians);
        }
        // The Blender set's preset keeps the paper's update and the outflow.
        let blender = &variants(&quick_args(Target::Blender)).unwrap()[0];
        assert_eq!(blender.config.lambda_lookahead, 0.0);
        assert_eq!(blender.config.open_face_flow, 1.0);
        // Both textured-wall scenes have as many statics as smoke Gaussians, fitted as long
        // as frame 0.
        let blocks = &variants(&quick_args(Target::Blocks)).unwrap()[0];
        for config in [&blender.config, &blocks.config] {
            assert_eq!(config.static_gaussians, 4000);
            assert_eq!(config.static_gaussians, config.gaussians);
        }
        blender.config.validate().unwrap();
        let full = ReproduceArgs {
            quick: false,
            ..quick_args(Target::SyntheticLong)
        };
        assert_eq!(
            variants(&full).unwrap()[0].config.open_face_flow,
            SYNTHETIC_TOP_FLOW
        );
        assert_eq!(blender.config.respawn_region, None);
        for args in [
            quick_args(Target::Blender),
            ReproduceArgs {
                quick: false,
                ..quick_args(Target::ScalarReal)
            },
        ] {
            let err = variants(&ReproduceArgs {
                paper_update: true,
                ..args
            })
            .unwrap_err()
            .to_string();
            assert!(err.contains("--paper-update"), "{err}");
            assert!(
                err.contains(
                    "of scalar-real, synthetic-long, turning, obstacle, ball and blocks use"
                ),
                "{err}"
            );
        }
    }

    /// `--config-of` trains the named run with the configuration its record holds (a
    /// setting the record predates takes its default), and refuses a record of another run,
    /// overrides, or a command naming several runs.
    #[test]
    fn a_record_is_re_run_with_its_recorded_configuration() {
        let dir = tempfile::tempdir().unwrap();
        let args = |config_of: &str, target: Target, overrides: Vec<String>| ReproduceArgs {
            seed: Some(3),
            tag: (!overrides.is_empty()).then(|| "x".to_string()),
            overrides,
            config_of: Some(config_of.to_string()),
            ..quick_args(target)
        };
        let recorded = TrainConfig {
            open_faces: Vec::new(),
            open_face_flow: 1.0,
            gaussians: 1234,
            seed: 3,
            ..quick_synthetic_long()
        };
        let mut config = serde_json::to_value(&recorded).unwrap();
        // A record older than the inertia prior.
        config.as_object_mut().unwrap().remove("lambda_increment");
        let record = json!({"config": config, "variant": "full method, closed walls"});
        let key = "synthetic-long-quick-s3";
        std::fs::write(dir.path().join(format!("{key}.json")), record.to_string()).unwrap();
        let named = |a: &ReproduceArgs| {
            let asked = a.config_of.as_deref().unwrap();
            recorded_variant(variants(a).unwrap(), asked, dir.path(), a)
        };

        let variant = named(&args(key, Target::SyntheticLong, Vec::new())).unwrap();
        assert_eq!(variant.key, key);
        assert_eq!(variant.config, recorded);
        assert_eq!(variant.label, "full method, closed walls");
        assert!(
            command_line(&args(key, Target::SyntheticLong, Vec::new())).ends_with(
                "reproduce synthetic-long --quick --seed 3 --config-of synthetic-long-quick-s3"
            )
        );

        let other = args("synthetic-long-quick-s4", Target::SyntheticLong, Vec::new());
        let err = named(&other).unwrap_err().to_string();
        assert!(err.contains("synthetic-long-quick-s3"), "{err}");
        let with_set = args(key, Target::SyntheticLong, vec!["lambda_div=1".into()]);
        let err = named(&with_set).unwrap_err().to_string();
        assert!(err.contains("--set"), "{err}");
        let several = args(key, Target::Obstacle, Vec::new());
        let err = named(&several).unwrap_err().to_string();
        assert!(err.contains("--no-ablations"), "{err}");
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
            out: dir.path().join("runs"),
            data: Some(root.join("../shared/datasets/scalar_real")),
            frames: Some(2),
            docs: Some(docs.clone()),
            independent: vec![0, 1],
            ..quick_args(Target::ScalarReal)
        };
        run(args).unwrap();

        let record: Value = serde_json::from_str(
            &std::fs::read_to_string(docs.join("results/scalar-real-quick-f2.json")).unwrap(),
        )
        .unwrap();
        assert_eq!(record["frames"], 2);
        assert_eq!(record["gaussians"], 8000);
        // Measured 35.43 dB over frames 0 and 1 (2026-11-26, the preset with our update, its
        // sizes' learning rate and the split). A broken loader, camera convention or renderer
        // lands far below: an all-black render scores roughly 28 dB.
        let psnr = record["test_psnr"].as_f64().unwrap();
        assert!(psnr > 33.0, "held-out PSNR {psnr} dB");
        let divergence = record["mean_abs_divergence"].as_f64().unwrap();
        assert!(divergence < 1e-4, "mean |div u| {divergence}");
        assert_eq!(record["test_psnr_per_frame"].as_array().unwrap().len(), 2);
        // Frame 0 fitted alone is the sequential run's frame-0 fit (same settings and seed),
        // so it must agree exactly; frame 1 alone is a real fit of the next frame.
        let alone = record["independent"].as_array().unwrap();
        assert_eq!(alone.len(), 2);
        assert_eq!(alone[0]["frame"], 0);
        assert_eq!(
            alone[0]["sequential_minus_independent_psnr"], 0.0,
            "{alone:?}"
        );
        let frame1 = alone[1]["test_psnr"].as_f64().unwrap();
        assert!(frame1 > 33.0, "frame 1 alone: {frame1} dB");
        let sequential1 = record["test_psnr_per_frame"][1].as_f64().unwrap();
        assert_eq!(
            alone[1]["sequential_minus_independent_psnr"].as_f64(),
            Some(sequential1 - frame1)
        );
        let results = std::fs::read_to_string(docs.join("RESULTS.md")).unwrap();
        assert!(
            results.contains("| `scalar-real-quick-f2` | 1 | "),
            "{results}"
        );
        assert_eq!(record["config"]["open_faces"], json!(["y-", "y+"]));
        assert!(
            results.contains(
                "| `scalar-real-quick-f2` | full method, respawn 0.02, velocity transported, \
                           look-ahead 1 along Phi's prediction, inertia prior 0.01, recycled into \
                           [0.4, 0, 0.4, 0.66, 0.15, 0.66], sizes at lr 0.0005, split 0.01 a \
                           frame, open faces y- y+ | 2 | 8000 |"
            ),
            "{results}"
        );
        assert!(
            results.contains("## Why we fall short"),
            "the hand-written part of RESULTS.md is kept"
        );
    }
}
