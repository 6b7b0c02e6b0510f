//! `cargo xtask bench render|physics|train|estimate`: the renderer next to the torch
//! reference, the physics ops, a whole training iteration ([`train`]), and the velocity
//! estimate after training ([`estimate`]).
//!
//! Scenes: `procedural::smoke_plume` inside the ScalarReal smoke box, seen from the ScalarReal
//! held-out camera `train02` (pose and field of view from its info.json) at the paper's
//! 270x480. Forward = render and read the image back; forward+backward = render under
//! autodiff, backward of `sum(rgb) + sum(T)`, read a gradient back. Median of `--reps` runs
//! after one warm-up run.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use burn::tensor::{Device, Tensor, TensorData};
use clap::{Args, Subcommand};
use gausmoke_core::glam::{Mat4, Vec3};
use gausmoke_core::phases::{PhaseTime, PhaseTotals};
use gausmoke_render::HostGaussians;
use gausmoke_render::procedural::smoke_plume;
use gausmoke_render::{Camera, GradientSums, Intrinsics, RasterOptions, backends, render_volume};
use safetensors::{Dtype, tensor::TensorView};

mod estimate;
mod train;

#[derive(Debug, Subcommand)]
pub enum Which {
    /// Volumetric Gaussian renderer on the CPU backends, and the torch reference.
    Render(RenderArgs),
    /// Physics ops: density splatting, projection solve, U-Net forward+backward.
    Physics(PhysicsArgs),
    /// A training iteration phase by phase, optionally against another build.
    Train(train::TrainArgs),
    /// `gausmoke-train velocity` per frame on a trained run, optionally against another build.
    Estimate(estimate::EstimateArgs),
}

#[derive(Debug, Args)]
pub struct PhysicsArgs {
    #[arg(long, default_value_t = 30_000)]
    gaussians: usize,
    /// Grid cells per axis.
    #[arg(long, default_value_t = 64)]
    resolution: usize,
    #[arg(long, default_value_t = 3)]
    reps: usize,
    #[arg(long, default_value = "flex")]
    device: String,
    /// Base channels of the U-Net (the paper's 16; the reduced preset's 8).
    #[arg(long, default_value_t = 16)]
    unet_channels: usize,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum SumsArg {
    Planes,
    SharedMemory,
    PerPixel,
}

#[derive(Debug, Args)]
pub struct RenderArgs {
    /// Gaussian counts to time.
    #[arg(long, value_delimiter = ',', default_value = "1000,10000,30000")]
    gaussians: Vec<usize>,
    #[arg(long, default_value_t = 270)]
    width: u32,
    #[arg(long, default_value_t = 480)]
    height: u32,
    /// Timed repetitions per case (after one warm-up).
    #[arg(long, default_value_t = 5)]
    reps: usize,
    /// Our backends to time (comma-separated names).
    #[arg(long, value_delimiter = ',', default_value = "flex,ndarray")]
    devices: Vec<String>,
    /// Skip the torch reference.
    #[arg(long)]
    no_torch: bool,
    /// Largest wall time (s) per torch case before it stops repeating.
    #[arg(long, default_value_t = 120.0)]
    torch_budget_s: f64,
    /// Where to write the results as JSON.
    #[arg(long, default_value = "target/bench/render.json")]
    json: PathBuf,
    /// Also compare each device's image and gradients with this device's (e.g. `flex`) on
    /// every scene and fail on a real disagreement (see `check_against`): a correctness check
    /// for GPUs that CI cannot run.
    #[arg(long)]
    check_against: Option<String>,
    /// How the GPU backward sums a splat's gradients over a tile (`gausmoke_render::
    /// GradientSums`): `planes` (the default; per pixel on devices without plane operations),
    /// `shared-memory`, `per-pixel`.
    #[arg(long, value_enum, default_value_t = SumsArg::Planes)]
    gradient_sums: SumsArg,
    /// Where to write the benchmark scenes (safetensors, read by the torch and gsplat scripts);
    /// default `target/bench/scenes` in the workspace.
    #[arg(long)]
    scene_dir: Option<PathBuf>,
}

pub fn run(which: Which) -> Result<()> {
    match which {
        Which::Render(args) => render(args),
        Which::Physics(args) => physics(args),
        Which::Train(args) => train::train(args),
        Which::Estimate(args) => estimate::estimate(args),
    }
}

/// The ScalarReal held-out camera `train02` (info.json), at `width x height`.
pub fn scalar_real_test_camera(width: u32, height: u32) -> Camera {
    #[rustfmt::skip]
    let rows = [
        0.999_511_2, -0.003_040_663, -0.031_113_517, 0.284_436_14,
        -0.005_995_775, 0.958_136_5, -0.286_249_07, 0.011_681_095,
        0.030_681_38, 0.286_295_7, 0.957_649_95, 0.985_783,
        0.0, 0.0, 0.0, 1.0,
    ];
    let c2w = Mat4::from_cols_array(&rows).transpose();
    let intrinsics = Intrinsics::from_fov_x(0.415_056_97, width, height);
    Camera::new(width, height, intrinsics, c2w).expect("ScalarReal pose is rigid")
}

/// ScalarReal's smoke box in world space (see its README).
pub const SCALAR_REAL_BOX: (Vec3, Vec3) =
    (Vec3::new(0.08, -0.04, -0.50), Vec3::new(0.57, 0.69, 0.00));

/// The middle value (the upper one of an even count).
fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn median_ms(samples: Vec<f64>) -> f64 {
    median(samples) * 1e3
}

/// The median of `value` over each build's measurements.
fn medians<M>(results: &[Vec<M>], value: impl Fn(&M) -> f64) -> Vec<f64> {
    results
        .iter()
        .map(|runs| median(runs.iter().map(&value).collect()))
        .collect()
}

/// `measure(build, round)` for every build in turn, `rounds` times, so that drifts in the
/// machine's load hit every build; each measurement is reported with `describe`.
fn in_alternation<M>(
    builds: &[(String, PathBuf)],
    rounds: usize,
    mut measure: impl FnMut(usize, usize) -> Result<M>,
    describe: impl Fn(&M) -> String,
) -> Result<Vec<Vec<M>>> {
    let mut results: Vec<Vec<M>> = builds.iter().map(|_| Vec::new()).collect();
    for round in 0..rounds {
        for (b, (name, _)) in builds.iter().enumerate() {
            let m = measure(b, round)?;
            eprintln!("round {round}: {name}: {}", describe(&m));
            results[b].push(m);
        }
    }
    Ok(results)
}

/// Median forward and forward+backward times of our renderer. The scene is uploaded once;
/// each timed call renders (and, for forward+backward, runs the backward of
/// `sum(rgb) + sum(T)`) and then waits for the device (`Device::sync`), so GPU timings are
/// whole calls including the tile-list read-back, not kernel times alone.
fn time_ours(
    scene: &HostGaussians,
    camera: &Camera,
    device: &Device,
    reps: usize,
    gradient_sums: GradientSums,
) -> Result<(f64, f64, Vec<PhaseTime>)> {
    let options = RasterOptions {
        gradient_sums,
        ..RasterOptions::default()
    };
    let sync = |device: &Device| device.sync().map_err(|e| anyhow::anyhow!("{e:?}"));
    let tensors = scene.to_tensors(device)?;
    let background = Tensor::<1>::from_data(TensorData::new(vec![0.0f32; 3], [3]), device);
    let forward = || -> Result<()> {
        let out = render_volume(&tensors, camera, &background, &options)?;
        drop(out);
        sync(device)
    };
    let ad = device.clone().autodiff();
    let ad_tensors = scene.to_tensors(&ad)?;
    let ad_background = Tensor::<1>::from_data(TensorData::new(vec![0.0f32; 3], [3]), &ad);
    let forward_backward = || -> Result<()> {
        let tensors = ad_tensors.clone().require_grad();
        let out = render_volume(&tensors, camera, &ad_background, &options)?;
        let grads = (out.rgb.sum() + out.transmittance.sum()).backward();
        let grad = tensors.means.grad(&grads).context("means tracked")?;
        drop(grad);
        sync(&ad)
    };
    let forward_ms = time_ms(reps, forward)?;
    let forward_backward_ms = time_ms(reps, forward_backward)?;
    let stages = stage_times(&ad, forward_backward)?;
    Ok((forward_ms, forward_backward_ms, stages))
}

/// Wall time of every phase of one call of `work` (on a GPU, of every kernel stage: see
/// `gausmoke_core::phases`), each phase waiting for the device at both ends so it is charged
/// with its own work.
fn stage_times(device: &Device, work: impl FnOnce() -> Result<()>) -> Result<Vec<PhaseTime>> {
    let totals = PhaseTotals::current()
        .context("no PhaseLayer in the subscriber (gausmoke_train::logging::init installs it)")?;
    let waiting = device.clone();
    totals.set_sync(Some(std::sync::Arc::new(move || {
        let _ = waiting.sync();
    })));
    let _ = totals.take();
    let result = work();
    let times = totals.take();
    totals.set_sync(None);
    result.map(|()| times)
}

/// Image and every gradient of `sum(rgb * w) + sum(T)` on `device` and on `reference`.
fn check_against(
    scene: &HostGaussians,
    camera: &Camera,
    device: &Device,
    reference: &Device,
    name: &str,
) -> Result<()> {
    let run = |device: &Device| -> Result<Vec<Vec<f32>>> {
        let ad = device.clone().autodiff();
        let t = scene.to_tensors(&ad)?.require_grad();
        let background = Tensor::<1>::from_data(TensorData::new(vec![0.1f32, 0.2, 0.3], [3]), &ad)
            .require_grad();
        let out = render_volume(&t, camera, &background, &RasterOptions::default())?;
        let [h, w, _] = out.rgb.dims();
        let weights: Vec<f32> = (0..h * w * 3)
            .map(|i| ((i * 7919) % 101) as f32 / 101.0 - 0.3)
            .collect();
        let weights = Tensor::<3>::from_data(TensorData::new(weights, [h, w, 3]), &ad);
        let image = out.rgb.clone();
        let grads = ((out.rgb * weights).sum() + out.transmittance.sum()).backward();
        let v = |t: Tensor<2>| t.into_data().try_into_vec_as::<f32>().unwrap_or_default();
        let v1 = |t: Tensor<1>| t.into_data().try_into_vec_as::<f32>().unwrap_or_default();
        Ok(vec![
            image
                .into_data()
                .try_into_vec_as::<f32>()
                .unwrap_or_default(),
            v(t.means.grad(&grads).context("means")?),
            v(t.rotations.grad(&grads).context("rotations")?),
            v(t.log_scales.grad(&grads).context("log_scales")?),
            v1(t.raw_densities.grad(&grads).context("raw_densities")?),
            v(t.colors.grad(&grads).context("colors")?),
            v1(background.grad(&grads).context("background")?),
        ])
    };
    let ours = run(device)?;
    let theirs = run(reference)?;
    let names = [
        "rgb",
        "means",
        "rotations",
        "log_scales",
        "raw_densities",
        "colors",
        "background",
    ];
    let mut report = Vec::new();
    let mut failures = Vec::new();
    for ((name_k, a), b) in names.iter().zip(&ours).zip(&theirs) {
        let diff = a
            .iter()
            .zip(b)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        let scale = b.iter().fold(0.0f32, |m, y| m.max(y.abs()));
        let finite = a.iter().all(|x| x.is_finite());
        if *name_k == "rgb" {
            // A Gaussian whose alpha on a ray sits at the alpha_min threshold (1/255) can be
            // kept by one device and skipped by the other when their exp() differ in the last
            // bits: single pixels then differ by up to ~alpha_min. Check the mean tightly and
            // the maximum at that scale.
            let mean = a
                .iter()
                .zip(b)
                .map(|(x, y)| (x - y).abs() as f64)
                .sum::<f64>()
                / a.len().max(1) as f64;
            let over = a
                .iter()
                .zip(b)
                .filter(|(x, y)| (*x - *y).abs() > 1e-4)
                .count();
            report.push(format!(
                "rgb max {diff:.1e} mean {mean:.1e} ({over} of {} values > 1e-4)",
                a.len()
            ));
            if !finite || diff > 1e-2 || mean > 1e-5 {
                failures.push(format!("rgb: max {diff:e}, mean {mean:e}"));
            }
        } else {
            let relative = diff / scale.max(1e-12);
            report.push(format!("{name_k} {relative:.1e}"));
            if !finite || relative.is_nan() || relative > 1e-2 {
                failures.push(format!("{name_k}: relative {relative:e}"));
            }
        }
    }
    eprintln!(
        "check {name} vs reference, {} Gaussians: max error (gradients relative to each tensor's largest): {}",
        scene.len(),
        report.join(", ")
    );
    if !failures.is_empty() {
        bail!("{name} differs from the reference: {}", failures.join("; "));
    }
    Ok(())
}

fn write_scene(path: &Path, scene: &HostGaussians, camera: &Camera) -> Result<()> {
    let n = scene.len();
    let k = camera.intrinsics();
    let mut cam = vec![
        camera.width() as f32,
        camera.height() as f32,
        k.fx,
        k.fy,
        k.cx,
        k.cy,
    ];
    cam.extend(camera.camera_to_world().transpose().to_cols_array());
    let tensors: Vec<(&str, Vec<f32>, Vec<usize>)> = vec![
        ("means", scene.means.clone(), vec![n, 3]),
        ("rotations", scene.rotations.clone(), vec![n, 4]),
        ("log_scales", scene.log_scales.clone(), vec![n, 3]),
        ("raw_densities", scene.raw_densities.clone(), vec![n]),
        ("colors", scene.colors.clone(), vec![n, 3]),
        ("background", vec![0.0; 3], vec![3]),
        ("camera", cam, vec![22]),
    ];
    let bytes: Vec<(&str, Vec<u8>, Vec<usize>)> = tensors
        .into_iter()
        .map(|(name, v, shape)| {
            (
                name,
                v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                shape,
            )
        })
        .collect();
    let views = bytes
        .iter()
        .map(|(name, b, shape)| Ok((*name, TensorView::new(Dtype::F32, shape.clone(), b)?)))
        .collect::<Result<Vec<_>>>()?;
    safetensors::serialize_to_file(views, None, path)?;
    Ok(())
}

fn render(args: RenderArgs) -> Result<()> {
    if cfg!(debug_assertions) {
        eprintln!(
            "warning: this is a debug build; run `cargo run --release -p xtask -- bench render`"
        );
    }
    let camera = scalar_real_test_camera(args.width, args.height);
    let gradient_sums = match args.gradient_sums {
        SumsArg::Planes => GradientSums::Planes,
        SumsArg::SharedMemory => GradientSums::SharedMemory,
        SumsArg::PerPixel => GradientSums::PerPixel,
    };
    let scene_dir = args
        .scene_dir
        .clone()
        .unwrap_or_else(|| crate::workspace_root().join("target/bench/scenes"));
    std::fs::create_dir_all(&scene_dir)?;
    let threads = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    let mut rows = Vec::new();
    let mut scene_files = Vec::new();
    for &n in &args.gaussians {
        let scene = smoke_plume(n, SCALAR_REAL_BOX.0, SCALAR_REAL_BOX.1, 7);
        let path = scene_dir.join(format!(
            "plume_{n}_{}x{}.safetensors",
            args.width, args.height
        ));
        write_scene(&path, &scene, &camera)?;
        scene_files.push(path);
        for name in &args.devices {
            let device = backends::device_by_name(name).map_err(anyhow::Error::msg)?;
            if let Some(reference) = &args.check_against {
                let reference = backends::device_by_name(reference).map_err(anyhow::Error::msg)?;
                check_against(&scene, &camera, &device, &reference, name)?;
            }
            let (f, fb, stages) = time_ours(&scene, &camera, &device, args.reps, gradient_sums)?;
            eprintln!("ours/{name}: {n} Gaussians: forward {f:.2} ms, forward+backward {fb:.2} ms");
            let stages: serde_json::Map<String, serde_json::Value> = stages
                .iter()
                .map(|p| (p.name.to_string(), serde_json::json!(p.seconds * 1e3)))
                .collect();
            eprintln!(
                "  stages of one forward+backward, each waiting for the device (ms): {}",
                stages
                    .iter()
                    .map(|(name, ms)| format!("{name} {:.3}", ms.as_f64().unwrap_or(f64::NAN)))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
            rows.push(serde_json::json!({
                "impl": format!("gausmoke-rs ({name})"), "gaussians": n,
                "width": args.width, "height": args.height, "threads": threads,
                "forward_ms": f, "forward_backward_ms": fb, "stages_ms": stages,
            }));
        }
    }
    if !args.no_torch {
        let python = crate::venv::reference_python()?;
        let script = crate::workspace_root().join("xtask/reference/torch_reference.py");
        let out = Command::new(python)
            .arg(script)
            .arg("bench")
            .args(&scene_files)
            .args([
                "--threads",
                &threads.to_string(),
                "--reps",
                &args.reps.to_string(),
            ])
            .args(["--budget-s", &args.torch_budget_s.to_string()])
            .output()
            .context("running the torch reference benchmark")?;
        if !out.status.success() {
            bail!(
                "torch benchmark failed:\n{}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        for line in String::from_utf8_lossy(&out.stdout).lines() {
            let r: serde_json::Value = serde_json::from_str(line)?;
            rows.push(serde_json::json!({
                "impl": "torch reference (dense, f32)", "gaussians": r["gaussians"],
                "width": r["width"], "height": r["height"], "threads": r["threads"],
                "forward_ms": r["forward"]["median_ms"],
                "forward_backward_ms": r["forward_backward"]["median_ms"],
            }));
        }
    }
    if let Some(dir) = args.json.parent() {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(&args.json, serde_json::to_string_pretty(&rows)?)?;
    println!(
        "| implementation | Gaussians | image | threads | forward (ms) | forward+backward (ms) |"
    );
    println!("|---|---:|---|---:|---:|---:|");
    for r in &rows {
        println!(
            "| {} | {} | {}x{} | {} | {:.2} | {:.2} |",
            r["impl"].as_str().unwrap_or("?"),
            r["gaussians"],
            r["width"],
            r["height"],
            r["threads"],
            r["forward_ms"].as_f64().unwrap_or(f64::NAN),
            r["forward_backward_ms"].as_f64().unwrap_or(f64::NAN),
        );
    }
    println!("(results also in {})", args.json.display());
    Ok(())
}

fn time_ms(reps: usize, mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    f()?;
    let mut samples = Vec::with_capacity(reps);
    for _ in 0..reps {
        let t0 = Instant::now();
        f()?;
        samples.push(t0.elapsed().as_secs_f64());
    }
    Ok(median_ms(samples))
}

fn physics(args: PhysicsArgs) -> Result<()> {
    use gausmoke_model::{
        GridSpec, ProjectionOptions, UNetConfig, VelocityUNet, density_grid, project_with_report,
    };
    if cfg!(debug_assertions) {
        eprintln!(
            "warning: this is a debug build; run `cargo run --release -p xtask -- bench physics`"
        );
    }
    let device = backends::device_by_name(&args.device).map_err(anyhow::Error::msg)?;
    let (lo, hi) = SCALAR_REAL_BOX;
    let n = args.resolution;
    let grid = GridSpec::new(lo, hi, [n, n, n], 4)?;
    let scene = smoke_plume(args.gaussians, lo, hi, 7);

    let ad = device.clone().autodiff();
    let splat = time_ms(args.reps, || {
        let mut g = scene.to_tensors(&ad)?;
        g.means = g.means.require_grad();
        let sigma = density_grid(&g, &grid, 9.0);
        let grads = sigma.sum().backward();
        let _ = g.means.grad(&grads).context("tracked")?.into_data();
        Ok(())
    })?;
    let splat_forward = time_ms(args.reps, || {
        let g = scene.to_tensors(&device)?;
        let _ = density_grid(&g, &grid, 9.0).into_data();
        Ok(())
    })?;

    // Projection of a random (divergent) field to the default tolerance.
    let mut rng = gausmoke_core::SplitMix64::new(3);
    let field: Vec<f32> = (0..3 * n * n * n).map(|_| rng.range(-1.0, 1.0)).collect();
    let options = ProjectionOptions::default();
    let mut report = None;
    let projection = time_ms(args.reps, || {
        let mut u = field.clone();
        report = Some(project_with_report(&grid, &mut u, &options));
        Ok(())
    })?;

    let mut direct_report = None;
    let direct = time_ms(args.reps, || {
        let mut u = field.clone();
        direct_report = Some(gausmoke_model::project_direct(&grid, &mut u, &options));
        Ok(())
    })?;

    // With an obstacle (a sphere of 0.14 of the box's height, as the `obstacle` scene's): the
    // host PCG preconditioned by the obstacle-free direct solve (what the CPU backends run),
    // and the Jacobi-preconditioned twin of the device solver.
    let extent = hi - lo;
    let centre = lo + extent * gausmoke_core::glam::Vec3::new(0.54, 0.4, 0.5);
    let radius = 0.14 * extent.y;
    let solids = gausmoke_model::SolidCells::new(
        grid.resolution(),
        grid.cells_where(|p| p.distance(centre) <= radius),
    )
    .context("one flag per cell")?;
    let obstacle_options = ProjectionOptions {
        solids: Some(solids.clone()),
        ..options.clone()
    };
    let mut obstacle_report = None;
    let obstacle_direct = time_ms(args.reps, || {
        let mut u = field.clone();
        obstacle_report = Some(gausmoke_model::project_direct(
            &grid,
            &mut u,
            &obstacle_options,
        ));
        Ok(())
    })?;
    let mut obstacle_jacobi_report = None;
    let obstacle_jacobi = time_ms(args.reps, || {
        let mut u = field.clone();
        obstacle_jacobi_report = Some(project_with_report(&grid, &mut u, &obstacle_options));
        Ok(())
    })?;

    // The same projection as the training op on this backend: on the cube backends the PCG
    // runs on the device (f32); on the CPU ones it is the host solve plus the tensor copies.
    let field_tensor =
        Tensor::<4>::from_data(TensorData::new(field.clone(), [n, n, n, 3]), &device);
    let projection_op = time_ms(args.reps, || {
        let projected =
            gausmoke_model::project_velocity(&grid, field_tensor.clone(), options.clone());
        let _ = projected.into_data();
        Ok(())
    })?;

    // The paper's penalty form of Pi on the same field, as tensor ops on the device.
    let penalty_options = gausmoke_model::PenaltyOptions::default();
    let (_, penalty_report) = gausmoke_model::penalty::penalty_projection_with_report(
        &grid,
        field_tensor.clone(),
        &penalty_options,
    );
    let penalty = time_ms(args.reps, || {
        let projected =
            gausmoke_model::penalty_projection(&grid, field_tensor.clone(), &penalty_options);
        let _ = projected.into_data();
        Ok(())
    })?;

    // Velocity at the Gaussians' centres with its Jacobian (advection and L_div), and the
    // backward of a loss of both.
    let centres =
        Tensor::<2>::from_data(TensorData::new(scene.means.clone(), [scene.len(), 3]), &ad);
    let grid_velocity =
        Tensor::<4>::from_data(TensorData::new(field.clone(), [n, n, n, 3]), &ad).require_grad();
    let interpolation_ms = time_ms(args.reps, || {
        let sample = gausmoke_model::sample_velocity(
            &grid,
            &grid_velocity,
            &centres,
            gausmoke_model::Interpolation::default(),
        );
        let loss = sample.divergence().powi_scalar(2).sum() + sample.velocity.sum();
        let grads = loss.backward();
        let _ = grid_velocity.grad(&grads).context("tracked")?.into_data();
        Ok(())
    })?;

    let unet_config = UNetConfig {
        base_channels: args.unet_channels,
        ..UNetConfig::default()
    };
    let unet = VelocityUNet::new(&unet_config, 0, &ad);
    let velocity = Tensor::<4>::from_data(TensorData::new(field.clone(), [n, n, n, 3]), &ad);
    let density = Tensor::<3>::zeros([n, n, n], &ad);
    let unet_ms = time_ms(args.reps, || {
        let delta = unet.forward(velocity.clone(), density.clone(), 0.5)?;
        let grads = delta.powi_scalar(2).sum().backward();
        drop(grads);
        Ok(())
    })?;

    let threads = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    println!(
        "| op ({} backend, {threads} threads) | size | median (ms) |",
        args.device
    );
    println!("|---|---|---:|");
    println!(
        "| density splatting, forward | {} Gaussians -> {n}^3 | {splat_forward:.1} |",
        args.gaussians
    );
    println!(
        "| density splatting, forward+backward | {} Gaussians -> {n}^3 | {splat:.1} |",
        args.gaussians
    );
    let r = report.expect("ran");
    println!(
        "| projection, host (Jacobi-PCG in f64, rel. residual {:.1e}, {} iterations, RMS div {:.2e} -> {:.2e}) | {n}^3 | {projection:.1} |",
        r.relative_residual, r.iterations, r.divergence_rms_before, r.divergence_rms_after
    );
    let d = direct_report.expect("ran");
    println!(
        "| projection, host direct solve (separated eigenbases, f64, rel. residual {:.1e}) | {n}^3 | {direct:.1} |",
        d.relative_residual
    );
    println!(
        "| projection op on this backend (CPU: the direct solve; cube backends: device PCG in f32), incl. copies | {n}^3 | {projection_op:.1} |"
    );
    let o = obstacle_report.expect("ran");
    println!(
        "| projection with a spherical obstacle ({} cells), host PCG preconditioned by the obstacle-free direct solve (what the CPU op runs; rel. residual {:.1e}, {} iterations) | {n}^3 | {obstacle_direct:.1} |",
        solids.count(),
        o.relative_residual,
        o.iterations
    );
    let o = obstacle_jacobi_report.expect("ran");
    println!(
        "| the same, Jacobi-PCG (the device solver's host twin; rel. residual {:.1e}, {} iterations) | {n}^3 | {obstacle_jacobi:.1} |",
        o.relative_residual, o.iterations
    );
    let p = penalty_report;
    println!(
        "| projection, penalty form ({} steps, RMS div {:.2e} -> {:.2e}) | {n}^3 | {penalty:.1} |",
        p.iterations, p.divergence_rms_before, p.divergence_rms_after
    );
    println!(
        "| velocity and Jacobian at the centres (4^3 Gaussian stencil), forward+backward | {} points, {n}^3 | {interpolation_ms:.1} |",
        args.gaussians
    );
    println!(
        "| U-Net Phi forward+backward ({} base channels) | {n}^3 | {unet_ms:.1} |",
        args.unet_channels
    );
    Ok(())
}
