//! `gausmoke-train eval --run DIR`: re-renders every saved frame of a run on the held-out
//! views (PSNR, SSIM), measures the divergence of the recovered velocity, and, for synthetic
//! scenes with ground truth, the density and velocity errors. Writes `DIR/eval.json`.

use std::path::Path;

use burn::tensor::Device;
use gausmoke_core::glam::Vec3;
use gausmoke_data::Obstacle;
use gausmoke_model::GridSpec;
use gausmoke_render::render_volume;
use serde::{Deserialize, Serialize};

use crate::arrays::{read_arrays, take_array};
use crate::run_folder::RunFolder;
use crate::sequence::Sequence;
use crate::{TrainError, metrics};

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct FrameEval {
    pub frame: usize,
    pub test_psnr: Option<f64>,
    pub test_ssim: Option<f64>,
    /// AlexNet LPIPS on the held-out views (only with `--lpips-weights`).
    pub test_lpips: Option<f64>,
    pub mean_abs_divergence: f64,
    /// Against ground truth (synthetic scenes), over the cells where the true density is
    /// above 1% of its maximum: RMS of `u - u_true` and that RMS relative to RMS `u_true`.
    pub velocity_rmse: Option<f64>,
    pub velocity_relative_error: Option<f64>,
    /// Mean over the same cells of the cosine between `u` and `u_true`: the direction alone
    /// (the relative error mixes direction and speed).
    pub velocity_cosine: Option<f64>,
    /// `|sigma - s rho_true| / |s rho_true|` over all cells (`s` the generator's density
    /// scale, `rho_true` its density).
    pub density_relative_error: Option<f64>,
    /// Pearson correlation of `sigma` with `rho_true` over all cells: unlike the relative
    /// error it ignores the overall scale, which the images leave open (a darker smoke colour
    /// with a denser medium renders alike).
    pub density_correlation: Option<f64>,
    /// The relative error left once `sigma` is multiplied by the one factor that brings it
    /// closest to `s rho_true` (least squares over all cells): the error in the density's
    /// shape, apart from the overall scale the images leave open.
    #[serde(default)]
    pub density_scaled_relative_error: Option<f64>,
    /// That factor: below 1 where the run holds more density than the scene (and a darker
    /// colour to match its pictures).
    #[serde(default)]
    pub density_best_scale: Option<f64>,
    /// The share of the run's density in cells outside the true smoke (true density at or
    /// below 1% of its maximum, the cells the velocity errors leave out): haze.
    #[serde(default)]
    pub density_outside_smoke_fraction: Option<f64>,
    /// Data sets with obstacles: the share of the reconstructed density (the run's grid)
    /// that sits in cells whose centre is inside an obstacle (leaked smoke; 0 is right).
    #[serde(default)]
    pub obstacle_density_fraction: Option<f64>,
    /// Data sets with obstacles: over the fluid cells within one cell of an obstacle's
    /// surface, RMS of the velocity's component along the surface normal relative to RMS
    /// speed (0: the flow slides along the surface; 0.58: no preference, as if the obstacle
    /// were not there; 1: straight through).
    #[serde(default)]
    pub obstacle_normal_flow: Option<f64>,
    /// The velocity estimated from the run's densities (`gausmoke-train velocity`, in
    /// `RUN/velocity_estimate/`), when there is one: its mean |div| and, against ground
    /// truth, its relative error and cosine, measured as the run's own velocity's are.
    #[serde(default)]
    pub velocity_estimate_mean_abs_divergence: Option<f64>,
    #[serde(default)]
    pub velocity_estimate_relative_error: Option<f64>,
    #[serde(default)]
    pub velocity_estimate_cosine: Option<f64>,
    /// Data sets with obstacles: [`FrameEval::obstacle_normal_flow`] of the estimate.
    #[serde(default)]
    pub velocity_estimate_obstacle_normal_flow: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct EvalReport {
    pub frames: Vec<FrameEval>,
    pub test_psnr_mean: Option<f64>,
    pub test_ssim_mean: Option<f64>,
    pub mean_abs_divergence: f64,
    pub velocity_relative_error_mean: Option<f64>,
    pub velocity_cosine_mean: Option<f64>,
    pub density_relative_error_mean: Option<f64>,
    pub density_correlation_mean: Option<f64>,
    #[serde(default)]
    pub density_scaled_relative_error_mean: Option<f64>,
    #[serde(default)]
    pub density_best_scale_mean: Option<f64>,
    #[serde(default)]
    pub density_outside_smoke_fraction_mean: Option<f64>,
    #[serde(default)]
    pub obstacle_density_fraction_mean: Option<f64>,
    #[serde(default)]
    pub obstacle_normal_flow_mean: Option<f64>,
    #[serde(default)]
    pub velocity_estimate_relative_error_mean: Option<f64>,
    #[serde(default)]
    pub velocity_estimate_cosine_mean: Option<f64>,
    #[serde(default)]
    pub velocity_estimate_obstacle_normal_flow_mean: Option<f64>,
    pub test_lpips_mean: Option<f64>,
    /// Where the LPIPS weights came from, or why LPIPS is absent.
    pub lpips: String,
}

fn mean(values: impl Iterator<Item = Option<f64>>) -> Option<f64> {
    let values: Vec<f64> = values.flatten().filter(|v| v.is_finite()).collect();
    (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
}

/// Cell-centred trilinear sample of a `[nx, ny, nz, C]` grid at world point `p` (clamped to
/// the outermost cell centres).
fn sample_grid(grid: &GridSpec, values: &[f32], channels: usize, p: Vec3, out: &mut [f64]) {
    let (lo, cell) = (grid.lo(), grid.cell_size());
    crate::host_grid::sample(lo, cell, grid.resolution(), values, channels, p, out);
}

/// One frame against the generator's ground truth (see [`FrameEval`]).
#[derive(Debug, Clone, Copy)]
struct TruthErrors {
    velocity_rmse: f64,
    velocity_relative_error: f64,
    velocity_cosine: f64,
    density: DensityErrors,
}

/// The run's density against the truth's, both sampled at the truth's cells.
#[derive(Debug, Clone, Copy, PartialEq)]
struct DensityErrors {
    relative_error: f64,
    correlation: f64,
    scaled_relative_error: f64,
    /// `None` for an empty reconstruction, which no factor brings nearer.
    best_scale: Option<f64>,
    /// `None` for an empty reconstruction.
    outside_smoke_fraction: Option<f64>,
}

/// [`DensityErrors`] of `ours` against `truth` (the same cells), `in_smoke` marking the cells
/// of the true smoke.
fn density_errors(ours: &[f64], truth: &[f64], in_smoke: &[bool]) -> DensityErrors {
    // Means of ours, truth, their squares and product.
    let mut moments = [0.0f64; 5];
    let (mut ours_total, mut ours_outside) = (0.0f64, 0.0f64);
    for ((&o, &r), &inside) in ours.iter().zip(truth).zip(in_smoke) {
        for (sum, term) in moments.iter_mut().zip([o, r, o * o, r * r, o * r]) {
            *sum += term;
        }
        ours_total += o;
        if !inside {
            ours_outside += o;
        }
    }
    let count = ours.len().max(1) as f64;
    let [o, r, oo, rr, or] = moments.map(|m| m / count);
    let spread = ((oo - o * o) * (rr - r * r)).max(0.0).sqrt();
    // The least-squares factor; the errors are summed directly, not from the moments, which
    // would cancel where ours is close.
    let best_scale = (oo > 0.0).then(|| or / oo);
    let error_with = |factor: f64| {
        let error2: f64 = ours
            .iter()
            .zip(truth)
            .map(|(&o, &r)| (factor * o - r).powi(2))
            .sum();
        (error2 / (rr * count).max(1e-30)).sqrt()
    };
    DensityErrors {
        relative_error: error_with(1.0),
        // An empty (constant) reconstruction is uncorrelated.
        correlation: if spread > 0.0 {
            (or - o * r) / spread
        } else {
            0.0
        },
        scaled_relative_error: error_with(best_scale.unwrap_or(0.0)),
        best_scale,
        outside_smoke_fraction: (ours_total > 0.0).then(|| ours_outside / ours_total),
    }
}

/// Errors against the generator's ground truth for frame `t`.
fn ground_truth_errors(
    scene: &Sequence,
    grid: &GridSpec,
    t: usize,
    density: &[f32],
    velocity: &[f32],
) -> Result<Option<TruthErrors>, TrainError> {
    let (Some(dir), Some(scale)) = (&scene.ground_truth, scene.ground_truth_density_scale) else {
        return Ok(None);
    };
    let path = dir.join(format!("frame_{:03}.safetensors", scene.first_frame + t));
    if !path.is_file() {
        return Ok(None);
    }
    let mut arrays = read_arrays(&path)?;
    let n = arrays
        .get("density")
        .map(|(shape, _)| shape[0])
        .unwrap_or_default();
    let true_density = take_array(&mut arrays, "density", &[n, n, n], &path)?;
    let true_velocity = take_array(&mut arrays, "velocity", &[n, n, n, 3], &path)?;
    let threshold = 0.01 * true_density.iter().cloned().fold(0.0, f32::max);
    let in_smoke: Vec<bool> = true_density.iter().map(|&d| d > threshold).collect();
    let extent = scene.hi - scene.lo;
    let (mut error2, mut truth2, mut smoke_cells) = (0.0, 0.0, 0usize);
    let mut cosine_sum = 0.0;
    let mut ours = [0.0f64; 3];
    let mut ours_density = [0.0f64];
    let mut sampled_density = Vec::with_capacity(n * n * n);
    // Ground truth layout: [z][y][x], x fastest, cell centres at (i + 0.5) / n of the box.
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let cell = (z * n + y) * n + x;
                let p =
                    scene.lo + extent * (Vec3::new(x as f32, y as f32, z as f32) + 0.5) / n as f32;
                sample_grid(grid, density, 1, p, &mut ours_density);
                sampled_density.push(ours_density[0]);
                if in_smoke[cell] {
                    sample_grid(grid, velocity, 3, p, &mut ours);
                    let (mut dot, mut ours2, mut true2) = (0.0, 0.0, 0.0);
                    for a in 0..3 {
                        let truth = true_velocity[3 * cell + a] as f64;
                        error2 += (ours[a] - truth).powi(2);
                        truth2 += truth * truth;
                        dot += ours[a] * truth;
                        ours2 += ours[a] * ours[a];
                        true2 += truth * truth;
                    }
                    let lengths = (ours2 * true2).sqrt();
                    cosine_sum += if lengths > 0.0 { dot / lengths } else { 0.0 };
                    smoke_cells += 1;
                }
            }
        }
    }
    let scaled_truth: Vec<f64> = true_density.iter().map(|&d| (scale * d) as f64).collect();
    let cells = smoke_cells.max(1) as f64;
    Ok(Some(TruthErrors {
        velocity_rmse: (error2 / cells).sqrt(),
        velocity_relative_error: (error2 / truth2.max(1e-30)).sqrt(),
        velocity_cosine: cosine_sum / cells,
        density: density_errors(&sampled_density, &scaled_truth, &in_smoke),
    }))
}

/// A cell centre of the run's grid, the data set's obstacle nearest to it, and its signed
/// distance from that obstacle (negative inside).
struct NearestObstacle<'a> {
    centre: Vec3,
    obstacle: &'a Obstacle,
    distance: f32,
}

/// [`NearestObstacle`] of every cell of `grid`, `None` without obstacles: the same for every
/// frame.
fn nearest_obstacles<'a>(
    obstacles: &'a [Obstacle],
    grid: &GridSpec,
) -> Option<Vec<NearestObstacle<'a>>> {
    if obstacles.is_empty() {
        return None;
    }
    let centres = grid.cell_centres();
    let cells = centres.chunks(3).map(|centre| {
        let p = Vec3::from_slice(centre);
        let nearest = obstacles
            .iter()
            .min_by(|a, b| a.signed_distance(p).total_cmp(&b.signed_distance(p)))
            .expect("at least one obstacle");
        NearestObstacle {
            centre: p,
            obstacle: nearest,
            distance: nearest.signed_distance(p),
        }
    });
    Some(cells.collect())
}

/// [`FrameEval::obstacle_density_fraction`] of one frame's density `[cells]`.
fn obstacle_density_fraction(nearest: &[NearestObstacle], density: &[f32]) -> f64 {
    let (mut inside, mut total) = (0.0f64, 0.0f64);
    for (cell, &sigma) in nearest.iter().zip(density) {
        let sigma = sigma.max(0.0) as f64;
        total += sigma;
        if cell.distance <= 0.0 {
            inside += sigma;
        }
    }
    if total > 0.0 { inside / total } else { 0.0 }
}

/// [`FrameEval::obstacle_normal_flow`] of a velocity `[cells, 3]` over the fluid cells within
/// `shell` of an obstacle.
fn obstacle_normal_flow(nearest: &[NearestObstacle], shell: f32, velocity: &[f32]) -> f64 {
    let (mut normal2, mut speed2) = (0.0f64, 0.0f64);
    for (cell, u) in nearest.iter().zip(velocity.chunks(3)) {
        if cell.distance > 0.0 && cell.distance <= shell {
            let u = Vec3::from_slice(u);
            normal2 += u.dot(cell.obstacle.outward_normal(cell.centre)).powi(2) as f64;
            speed2 += u.length_squared() as f64;
        }
    }
    if speed2 > 0.0 {
        (normal2 / speed2).sqrt()
    } else {
        0.0
    }
}

/// Evaluates the run folder `run` (written by [`crate::Trainer`]) on `device`.
pub fn evaluate(
    run: &Path,
    device: &Device,
    lpips_weights: Option<&Path>,
) -> Result<EvalReport, TrainError> {
    // Load the weights first: a bad file is reported before any rendering.
    let lpips = lpips_weights
        .map(|path| crate::lpips::Lpips::load(path, device))
        .transpose()?;
    let folder = RunFolder::at(run);
    if !folder.root().join("run.json").is_file() {
        return Err(TrainError::Config {
            origin: run.display().to_string(),
            reason: "this folder is not a GauSmoke run (it has no run.json); pass the --out \
                     folder of a `gausmoke-train train`"
                .into(),
        });
    }
    folder.require_whole()?;
    let config = folder.read_config()?;
    let info = folder.read_run_info()?;
    let scene = Sequence::open(&info.data, &config)?;
    info.check_data(&scene.fingerprint())?;
    let grid = config.grid(scene.lo, scene.hi)?;
    let open_faces = config.open_faces()?;
    let solids = crate::trainer::solid_cells(&scene.obstacles, &config, &grid)?;
    let background = burn::tensor::Tensor::<1>::from_data(
        burn::tensor::TensorData::new(scene.background.to_vec(), [3]),
        device,
    );
    let stored_estimate = crate::velocity_estimate::StoredEstimate::open(run)?;
    let nearest = nearest_obstacles(&scene.obstacles, &grid);
    // The shell of fluid cells beside an obstacle whose flow is scored.
    let shell = grid.cell_size().max_element();
    let mut frames = Vec::new();
    let mut previous_density: Option<Vec<f32>> = None;
    for t in 0..scene.frames().min(folder.finished_frames()) {
        let Some(state) = folder.read_frame_state(t, &grid)? else {
            break;
        };
        let estimate = match (&stored_estimate, &previous_density) {
            (Some(stored), Some(before)) => {
                stored.frame(t, grid.resolution(), [before, &state.density])?
            }
            _ => None,
        };
        let velocity = &state.velocity;
        let density = &state.density;
        let gaussians = state.rendered().to_tensors(device)?;
        let mut psnr = Vec::new();
        let mut ssim = Vec::new();
        let mut perceptual = Vec::new();
        for observation in &scene.test[t] {
            let out = render_volume(
                &gaussians,
                &observation.camera,
                &background,
                &config.raster_options(),
            )?;
            let rgb = gausmoke_render::device_traffic::read_floats(out.rgb);
            let (w, h) = (
                observation.image.width() as usize,
                observation.image.height() as usize,
            );
            psnr.push(metrics::psnr(&rgb, observation.image.data()));
            if let Some(lpips) = &lpips {
                perceptual.push(lpips.distance(&rgb, observation.image.data(), w, h));
            }
            ssim.push(metrics::ssim(&rgb, observation.image.data(), w, h));
        }
        let average = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
        let truth = ground_truth_errors(&scene, &grid, t, density, velocity)?;
        let estimate_truth = match &estimate {
            Some(estimated) => ground_truth_errors(&scene, &grid, t, density, estimated)?,
            None => None,
        };
        // u^0 is zero by construction (Algorithm 1, line 1): velocity errors from frame 1.
        let velocity_truth = truth.filter(|_| t > 0);
        frames.push(FrameEval {
            frame: t,
            test_psnr: average(&psnr),
            test_ssim: average(&ssim),
            test_lpips: average(&perceptual),
            mean_abs_divergence: metrics::mean_abs_divergence(
                &grid,
                open_faces,
                solids.as_ref(),
                velocity,
            ),
            velocity_rmse: velocity_truth.map(|e| e.velocity_rmse),
            velocity_relative_error: velocity_truth.map(|e| e.velocity_relative_error),
            velocity_cosine: velocity_truth.map(|e| e.velocity_cosine),
            density_relative_error: truth.map(|e| e.density.relative_error),
            density_correlation: truth.map(|e| e.density.correlation),
            density_scaled_relative_error: truth.map(|e| e.density.scaled_relative_error),
            density_best_scale: truth.and_then(|e| e.density.best_scale),
            density_outside_smoke_fraction: truth.and_then(|e| e.density.outside_smoke_fraction),
            obstacle_density_fraction: nearest
                .as_deref()
                .map(|nearest| obstacle_density_fraction(nearest, density)),
            // u^0 is zero by construction.
            obstacle_normal_flow: nearest
                .as_deref()
                .filter(|_| t > 0)
                .map(|nearest| obstacle_normal_flow(nearest, shell, velocity)),
            velocity_estimate_mean_abs_divergence: estimate.as_ref().map(|estimated| {
                metrics::mean_abs_divergence(&grid, open_faces, solids.as_ref(), estimated)
            }),
            velocity_estimate_relative_error: estimate_truth.map(|e| e.velocity_relative_error),
            velocity_estimate_cosine: estimate_truth.map(|e| e.velocity_cosine),
            velocity_estimate_obstacle_normal_flow: nearest
                .as_deref()
                .zip(estimate.as_ref())
                .map(|(nearest, estimated)| obstacle_normal_flow(nearest, shell, estimated)),
        });
        previous_density = Some(state.density);
    }
    if frames.is_empty() {
        return Err(TrainError::Dataset {
            path: run.to_path_buf(),
            reason: "no frames/frame_000.safetensors: the run has not finished a frame".into(),
        });
    }
    let report = EvalReport {
        test_psnr_mean: mean(frames.iter().map(|f| f.test_psnr)),
        test_ssim_mean: mean(frames.iter().map(|f| f.test_ssim)),
        mean_abs_divergence: mean(frames.iter().map(|f| Some(f.mean_abs_divergence)))
            .unwrap_or(f64::NAN),
        velocity_relative_error_mean: mean(frames.iter().map(|f| f.velocity_relative_error)),
        velocity_cosine_mean: mean(frames.iter().map(|f| f.velocity_cosine)),
        density_relative_error_mean: mean(frames.iter().map(|f| f.density_relative_error)),
        density_correlation_mean: mean(frames.iter().map(|f| f.density_correlation)),
        density_scaled_relative_error_mean: mean(
            frames.iter().map(|f| f.density_scaled_relative_error),
        ),
        density_best_scale_mean: mean(frames.iter().map(|f| f.density_best_scale)),
        density_outside_smoke_fraction_mean: mean(
            frames.iter().map(|f| f.density_outside_smoke_fraction),
        ),
        obstacle_density_fraction_mean: mean(frames.iter().map(|f| f.obstacle_density_fraction)),
        obstacle_normal_flow_mean: mean(frames.iter().map(|f| f.obstacle_normal_flow)),
        velocity_estimate_relative_error_mean: mean(
            frames.iter().map(|f| f.velocity_estimate_relative_error),
        ),
        velocity_estimate_cosine_mean: mean(frames.iter().map(|f| f.velocity_estimate_cosine)),
        velocity_estimate_obstacle_normal_flow_mean: mean(
            frames
                .iter()
                .map(|f| f.velocity_estimate_obstacle_normal_flow),
        ),
        test_lpips_mean: mean(frames.iter().map(|f| f.test_lpips)),
        lpips: match lpips_weights {
            Some(path) => format!("AlexNet LPIPS v0.1, weights from {}", path.display()),
            None => format!(
                "not computed: no LPIPS weights; `gausmoke-train lpips-weights` writes them to {} \
                 where eval finds them, or pass --lpips-weights FILE",
                crate::lpips::cached_weights_path()
                    .map_or("the cache".into(), |p| p.display().to_string())
            ),
        },
        frames,
    };
    folder.write_eval(&report)?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_density_errors_part_the_scale_from_the_shape_and_count_the_haze() {
        let truth = [0.0, 1.0, 2.0, 3.0, 0.0, 0.0];
        let in_smoke = [false, true, true, true, false, false];
        // Twice the truth: the whole error is the scale.
        let twice: Vec<f64> = truth.iter().map(|r| 2.0 * r).collect();
        let errors = density_errors(&twice, &truth, &in_smoke);
        assert!((errors.relative_error - 1.0).abs() < 1e-12, "{errors:?}");
        assert!((errors.best_scale.unwrap() - 0.5).abs() < 1e-12);
        assert!(errors.scaled_relative_error < 1e-12);
        assert!((errors.correlation - 1.0).abs() < 1e-12);
        assert_eq!(errors.outside_smoke_fraction, Some(0.0));
        // A haze of 0.5 in each cell outside the smoke: a fifth of the mass (1.5 of 7.5),
        // and an error no factor removes.
        let hazy = [0.5, 1.0, 2.0, 3.0, 0.5, 0.5];
        let errors = density_errors(&hazy, &truth, &in_smoke);
        assert!((errors.outside_smoke_fraction.unwrap() - 0.2).abs() < 1e-12);
        assert_eq!(errors.relative_error, (0.75f64 / 14.0).sqrt());
        let scale = 14.0 / 14.75;
        let left: f64 = hazy
            .iter()
            .zip(truth)
            .map(|(o, r)| (scale * o - r).powi(2))
            .sum();
        assert!((errors.best_scale.unwrap() - scale).abs() < 1e-12);
        assert!((errors.scaled_relative_error - (left / 14.0).sqrt()).abs() < 1e-12);
        assert!(errors.scaled_relative_error < errors.relative_error);
        // An empty reconstruction: error 1 either way, no factor, no share.
        let errors = density_errors(&[0.0; 6], &truth, &in_smoke);
        assert_eq!(errors.relative_error, 1.0);
        assert_eq!(errors.scaled_relative_error, 1.0);
        assert_eq!(errors.best_scale, None);
        assert_eq!(errors.outside_smoke_fraction, None);
        assert_eq!(errors.correlation, 0.0);
    }
}
