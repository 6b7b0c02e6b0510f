//! `cargo xtask reproduce scalar-real|synthetic [--quick]`: trains with the library API the
//! CLI uses, evaluates on the held-out views, and records what was measured.
//!
//! Every run writes `docs/results/<key>.json` (metrics, timings, memory, storage, machine,
//! date and the command), and the generated blocks are rebuilt from all such files: every
//! record's rows in `docs/RUNS.md` (between `results:begin` / `results:end`) and the summary
//! at the top of `docs/RESULTS.md` (between `summary:begin` / `summary:end`), so the tables
//! hold only measured numbers. The prose around the blocks is written by people.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_render::backends;
use gausmoke_train::preset::Preset;
use gausmoke_train::{Run, TrainConfig, eval, sequence::Sequence};
use serde_json::{Value, json};

mod ablation;
mod independent;
mod presets;
mod record;
pub mod reevaluate;
mod results;
mod summary;

use ablation::Ablation;
use presets::{for_scalar_real, sizes, trains_with_our_update};
use record::{
    command_line, file_size, machine, peak_memory_mib, previous_record, reset_peak_memory,
    session_totals, utc_now,
};
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
    /// show missing smoke (`population.recycle.fraction`; our addition, not the paper's method). Runs
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
    let ours = args.quick && trains_with_our_update(args.target);
    if args.paper_update {
        if !ours {
            let ours: Vec<&str> = Target::value_variants()
                .iter()
                .filter(|&&t| trains_with_our_update(t))
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
    let paper = sizes(args.target, args.quick);
    let mut base = match (ours && !args.paper_update, args.target) {
        (true, Target::ScalarReal) => for_scalar_real(Preset::Ours.apply(paper.clone()), &paper),
        (true, _) => Preset::Ours.apply(paper),
        (false, _) => paper,
    };
    if let Some(frames) = args.frames {
        base.frames = Some(frames);
    }
    if let Some(seed) = args.seed {
        base.seed = seed;
    }
    if let Some(fraction) = args.respawn {
        base.population.recycle.fraction = fraction;
    }
    base = base.with_overrides(&args.overrides)?;
    let overrides = args.overrides.join(", ");
    let keyed = |target: &str, ablation: &str, label: &str, config: TrainConfig| Variant {
        key: format!("{target}{suffix}{ablation}"),
        group: format!("{target}{group_suffix}{ablation}"),
        label: {
            let mut label = label.to_string();
            if config.population.recycle.fraction > 0.0 {
                label += &format!(", respawn {}", config.population.recycle.fraction);
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
    let mut config = record["config"].clone();
    gausmoke_train::config::legacy::upgrade(&mut config);
    let config: TrainConfig = serde_json::from_value(config)
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
            let scene = path.join(gausmoke_train::scene::SCENE_FILE);
            if !scene.is_file() {
                // Generated before the generator wrote the scene beside the cameras.
                eprintln!("writing the solver's scene to {}", scene.display());
                std::fs::write(&scene, gausmoke_data::synth::SCENE_TOML)?;
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
    for variant in &mut variants {
        // What the preset leaves unset of the scene, the data declares (its scene.toml), so
        // that the record holds the scene it ran with.
        variant.config.scene.fill_from_data(&data)?;
    }
    let estimate = if args.velocity_estimate_forces {
        if let Some(variant) = variants.iter().find(|v| v.config.scene.inflow.is_none()) {
            bail!(
                "--velocity-estimate-forces: run {} has no inflow box (scene.inflow) for the \
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
mod tests;
