//! Algorithm 1 of the paper over a whole sequence.
//!
//! * Frame 0: a static fit of the Gaussians to the first frame's training views (L1).
//! * Frame t-1 -> t, K iterations (lines 3-9): `sigma = D(G^{t-1})`,
//!   `Delta u = Phi(u^{t-1}, sigma, PE(t))`, `u^t = Pi(u^{t-1} + Delta u)`, centres advected
//!   from `p^{t-1}` through `u^t`, rendered against frame t, loss
//!   `L_render + lambda_div L_div + lambda_adv L_adv`; Adam steps on Phi and on the Gaussians'
//!   shape, density and colour (the centres are the advected ones, so `p^{t-1}` stays).
//! * Then K' refinement iterations (lines 11-13): the centres become free parameters tied to
//!   the advected ones by `lambda_refine L_refine`, with `L_render`.
//!
//! Units: world units, time in frames (`dt` frames per step), velocity in world units per
//! frame. `L_render` is the mean absolute error per pixel and channel over the training views.

use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Gradients, Tensor, TensorData};
use gausmoke_core::profile;
use gausmoke_model::penalty::penalty_projection_with_report;
use gausmoke_model::{
    GridSpec, Integrator, Interpolation, PenaltyOptions, ProjectionOptions, ProjectionReport,
    UNetConfig, VelocityUNet, advect, advection_loss, density_gradient_grid, density_grid,
    divergence_loss, penalty_projection, project_velocity, project_with_report, refine_loss,
};
use gausmoke_render::{GaussianTensors, RasterOptions, render_volume};
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};

use crate::checkpoint::{self, CheckpointMeta, HostArrays};
use crate::config::{IntegratorKind, InterpolationKind, ProjectionKind, TrainConfig};
use crate::gaussians::GaussianModel;
use crate::respawn::{DeficitView, RespawnOptions, RespawnReport, SpawnLattice, respawn};
use crate::scene::{Observation, Scene};
use crate::visuals::Picture;
use crate::{TrainError, export, metrics, visuals};

/// Support of a Gaussian when splatting density to the grid: squared Mahalanobis radius 9
/// (3 sigma), as the paper evaluates each kernel.
const SPLAT_CUTOFF: f32 = 9.0;

/// Everything the optimisation changes; what a checkpoint stores.
pub struct TrainState {
    pub gaussians: GaussianModel,
    /// The velocity grid `u` at the current frame, `[nx, ny, nz, 3]`, world units per frame.
    pub velocity: Tensor<4>,
    pub phi: VelocityUNet,
    pub gaussian_optim: ModuleOptimizer,
    pub phi_optim: ModuleOptimizer,
}

/// One optimisation step's losses (the CSV row of `losses.csv`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct LossRow {
    pub frame: usize,
    /// `init` (frame 0), `advect` (K) or `refine` (K').
    pub phase: String,
    pub iteration: usize,
    pub total: f32,
    pub render: f32,
    pub divergence: f32,
    pub advection: f32,
    pub refine: f32,
}

/// What happened at one frame (in `metrics.json`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct FrameReport {
    pub frame: usize,
    /// Mean absolute error over the training views after the frame's last step.
    pub train_l1: f64,
    /// Mean absolute error, PSNR and SSIM on the held-out views (`None` without any).
    pub test_l1: Option<f64>,
    pub test_psnr: Option<f64>,
    pub test_ssim: Option<f64>,
    /// Mean |div u| over the grid cells after `Pi` (1/frame).
    pub mean_abs_divergence: f64,
    /// The projection's solve at this frame's last step: iterations, relative residual and
    /// RMS divergence before and after.
    pub projection_iterations: usize,
    pub projection_residual: f64,
    pub divergence_rms_before: f64,
    pub divergence_rms_after: f64,
    /// Gaussians whose advected centre left the box and was clamped back onto it.
    pub clamped_to_box: usize,
    /// Gaussians recycled before this frame's optimisation (`respawn_fraction`).
    #[serde(default)]
    pub respawned: usize,
    /// Mean and largest speed of the velocity grid (world units per frame).
    pub mean_speed: f64,
    pub max_speed: f64,
    pub seconds: f64,
}

/// Runs Algorithm 1 on a [`Scene`] and writes a run folder (see the README).
pub struct Trainer {
    pub config: TrainConfig,
    pub scene: Scene,
    pub device: Device,
    pub grid: GridSpec,
    pub out: PathBuf,
    pub state: TrainState,
    /// The last complete frame, `None` before frame 0 is fitted.
    pub frame: Option<usize>,
    pub losses: Vec<LossRow>,
    pub reports: Vec<FrameReport>,
    background: Tensor<1>,
    raster: RasterOptions,
    elapsed_before: f64,
    session_start: Instant,
    quiet: bool,
    /// Wall time per phase of the optimisation (see `gausmoke_core::profile`).
    phase_times: Vec<profile::PhaseTime>,
}

fn scalar(t: &Tensor<1>) -> f32 {
    t.clone()
        .into_data()
        .try_into_vec_as::<f32>()
        .map(|v| v[0])
        .unwrap_or(f32::NAN)
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .try_into_vec_as::<f32>()
        .expect("float tensors read back as f32")
}

fn image_tensor(observation: &Observation, device: &Device) -> Tensor<3> {
    let image = &observation.image;
    Tensor::from_data(
        TensorData::new(
            image.data().to_vec(),
            [image.height() as usize, image.width() as usize, 3],
        ),
        device,
    )
}

impl Trainer {
    /// Prepares a run in `out`. With `resume`, continues from the newest complete
    /// checkpoint there (the configuration must match the one it was trained with);
    /// without, refuses a folder that already holds a run, so no work is overwritten.
    pub fn new(
        scene: Scene,
        config: TrainConfig,
        device: Device,
        out: &Path,
        resume: bool,
    ) -> Result<Self, TrainError> {
        config.validate()?;
        let resolution = [config.grid_resolution; 3];
        let grid = GridSpec::new(scene.lo, scene.hi, resolution, 4)?;
        let existing = checkpoint::latest(out)?;
        if existing.is_some() && !resume {
            return Err(TrainError::Config {
                origin: out.display().to_string(),
                reason: "this folder already holds a run; pass --resume to continue it or \
                         choose another --out"
                    .into(),
            });
        }
        std::fs::create_dir_all(out).map_err(|source| TrainError::Io {
            path: out.to_path_buf(),
            source,
        })?;
        let state = Self::fresh_state(&scene, &config, &grid, &device);
        let background =
            Tensor::<1>::from_data(TensorData::new(scene.background.to_vec(), [3]), &device);
        let raster = config.raster_options();
        let mut trainer = Self {
            config,
            scene,
            device,
            grid,
            out: out.to_path_buf(),
            state,
            frame: None,
            losses: Vec::new(),
            reports: Vec::new(),
            background,
            raster,
            elapsed_before: 0.0,
            session_start: Instant::now(),
            quiet: false,
            phase_times: Vec::new(),
        };
        profile::set_enabled(true);
        profile::set_sync_hook(trainer.config.sync_phase_timings.then(|| {
            let device = trainer.device.clone();
            let hook: profile::SyncHook = std::sync::Arc::new(move || {
                // A failed wait only blurs the phase boundaries; the work itself reports
                // its own errors.
                let _ = device.sync();
            });
            hook
        }));
        let _ = profile::take();
        if let Some(dir) = existing.filter(|_| resume) {
            trainer.restore(&dir)?;
        }
        let config_path = out.join("config.toml");
        export::write_atomic(&config_path, trainer.config.to_toml().as_bytes())?;
        let run = serde_json::json!({
            "data": trainer.scene.path,
            "frames": trainer.scene.frames(),
            "grid_resolution": trainer.grid.resolution(),
            "box_lo": trainer.grid.lo().to_array(),
            "box_hi": trainer.grid.hi().to_array(),
            "device": format!("{:?}", trainer.device),
            "version": env!("CARGO_PKG_VERSION"),
        });
        export::write_atomic(
            &out.join("run.json"),
            serde_json::to_string_pretty(&run)
                .expect("plain JSON")
                .as_bytes(),
        )?;
        Ok(trainer)
    }

    /// Hides the progress bars (tests, notebooks).
    pub fn quiet(mut self, quiet: bool) -> Self {
        self.quiet = quiet;
        self
    }

    fn fresh_state(
        scene: &Scene,
        config: &TrainConfig,
        grid: &GridSpec,
        device: &Device,
    ) -> TrainState {
        let [nx, ny, nz] = grid.resolution();
        let unet = UNetConfig {
            base_channels: config.unet_channels,
            time_frequencies: config.time_frequencies,
        };
        // Phi's initial weights come from the backend's generator: seed it, so a run is
        // reproducible (and a resumed run matches an uninterrupted one).
        device.seed(config.seed);
        TrainState {
            gaussians: GaussianModel::init_in_box(
                config.gaussians,
                scene.lo,
                scene.hi,
                config.seed,
                device,
            ),
            velocity: Tensor::zeros([nx, ny, nz, 3], device),
            phi: VelocityUNet::new(&unet, device),
            // 3DGS practice: a tiny epsilon, so rarely-seen Gaussians still move.
            gaussian_optim: AdamConfig::new().with_epsilon(1e-15).init(),
            phi_optim: AdamConfig::new().init(),
        }
    }

    fn restore(&mut self, dir: &Path) -> Result<(), TrainError> {
        let fresh = Self::fresh_state(&self.scene, &self.config, &self.grid, &self.device);
        let (state, meta) = checkpoint::load(dir, fresh, &self.device)?;
        if meta.config != self.config {
            return Err(TrainError::Checkpoint {
                path: dir.to_path_buf(),
                reason: format!(
                    "it was trained with a different configuration; resume with the same \
                     --config/--set options (its configuration:\n{})",
                    meta.config.to_toml()
                ),
            });
        }
        self.state = state;
        self.frame = Some(meta.frame);
        self.losses = meta.losses;
        self.reports = meta.reports;
        self.elapsed_before = meta.elapsed_seconds;
        tracing::info!(checkpoint = %dir.display(), frame = meta.frame, "resumed");
        Ok(())
    }

    fn interpolation(&self) -> Interpolation {
        match self.config.interpolation {
            InterpolationKind::Gaussian => Interpolation::default(),
            InterpolationKind::Trilinear => Interpolation::Trilinear,
        }
    }

    fn integrator(&self) -> Integrator {
        match self.config.integrator {
            IntegratorKind::Euler => Integrator::Euler,
            IntegratorKind::Rk2 => Integrator::Rk2,
        }
    }

    fn projection(&self) -> ProjectionOptions {
        ProjectionOptions {
            rel_tolerance: self.config.projection_tolerance,
            max_iterations: self.config.projection_max_iterations,
        }
    }

    fn penalty(&self) -> PenaltyOptions {
        PenaltyOptions {
            steps: self.config.penalty_steps,
            ..PenaltyOptions::default()
        }
    }

    /// `Pi(velocity)` in the configured form (differentiable either way).
    fn project(&self, velocity: Tensor<4>) -> Tensor<4> {
        match self.config.projection {
            ProjectionKind::Exact => project_velocity(&self.grid, velocity, self.projection()),
            ProjectionKind::Penalty => penalty_projection(&self.grid, velocity, &self.penalty()),
        }
    }

    /// What the configured `Pi` does to `velocity` (for the frame's metrics).
    fn projection_report(&self, velocity: Tensor<4>) -> ProjectionReport {
        match self.config.projection {
            ProjectionKind::Exact => {
                project_with_report(&self.grid, &mut host(velocity), &self.projection())
            }
            ProjectionKind::Penalty => {
                penalty_projection_with_report(&self.grid, velocity, &self.penalty()).1
            }
        }
    }

    fn elapsed(&self) -> f64 {
        self.elapsed_before + self.session_start.elapsed().as_secs_f64()
    }

    /// Mean L1 over `observations` of the Gaussians' renders.
    fn render_loss(
        &self,
        gaussians: &GaussianTensors,
        observations: &[Observation],
        targets: &[Tensor<3>],
    ) -> Result<Tensor<1>, TrainError> {
        let mut total: Option<Tensor<1>> = None;
        for (observation, target) in observations.iter().zip(targets) {
            let out = render_volume(
                gaussians,
                &observation.camera,
                &self.background,
                &self.raster,
            )?;
            let l1 = (out.rgb - target.clone()).abs().mean();
            total = Some(match total {
                Some(t) => t + l1,
                None => l1,
            });
        }
        Ok(total.expect("at least one training view") / observations.len() as f32)
    }

    /// One Adam step per Gaussian attribute, each with its own learning rate (0 skips it).
    fn step_gaussians(&mut self, grads: &mut Gradients, learning_rates: [f64; 5]) {
        let model = &self.state.gaussians;
        let ids = [
            model.means.id,
            model.rotations.id,
            model.log_scales.id,
            model.raw_densities.id,
            model.colors.id,
        ];
        let mut model = self.state.gaussians.clone();
        for (id, lr) in ids.into_iter().zip(learning_rates) {
            let param_grads = GradientsParams::from_params(grads, &model, &[id]);
            if lr > 0.0 && !param_grads.is_empty() {
                let _timed = profile::scope("optimizer");
                model = self.state.gaussian_optim.step(lr, model, param_grads);
            }
        }
        self.state.gaussians = model.clamped();
    }

    fn check_finite(&self, row: &LossRow, phase: &'static str) -> Result<(), TrainError> {
        self.check_finite_with(row, phase, None)
    }

    /// As [`Self::check_finite`], also checking `extra` (a named quantity such as the largest
    /// velocity) first, so the report names the earliest thing that went wrong.
    fn check_finite_with(
        &self,
        row: &LossRow,
        phase: &'static str,
        extra: Option<(&'static str, f32)>,
    ) -> Result<(), TrainError> {
        let terms = [
            ("the render loss", row.render),
            ("L_div", row.divergence),
            ("L_adv", row.advection),
            ("L_refine", row.refine),
            ("the total loss", row.total),
        ];
        if let Some((quantity, value)) =
            extra.into_iter().chain(terms).find(|(_, v)| !v.is_finite())
        {
            return Err(TrainError::NonFinite {
                quantity,
                value,
                frame: row.frame,
                phase,
                iteration: row.iteration,
            });
        }
        Ok(())
    }

    fn progress(&self, frame: usize, length: usize) -> ProgressBar {
        let bar = if self.quiet {
            ProgressBar::hidden()
        } else {
            ProgressBar::new(length as u64)
        };
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:>12} [{bar:30}] {pos}/{len} {per_sec} eta {eta} {msg}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_prefix(format!("frame {frame}/{}", self.scene.frames() - 1));
        bar
    }

    /// Trains every remaining frame, writes the summary outputs and returns the reports.
    pub fn run(&mut self) -> Result<&[FrameReport], TrainError> {
        let frames = self.scene.frames();
        let first = match self.frame {
            None => {
                self.fit_first_frame()?;
                0
            }
            Some(done) => done + 1,
        };
        for t in first.max(1)..frames {
            self.advance_to(t)?;
        }
        self.write_summary()?;
        Ok(&self.reports)
    }

    /// Frame 0: a static fit with per-attribute learning rates.
    pub fn fit_first_frame(&mut self) -> Result<(), TrainError> {
        let start = Instant::now();
        let observations = self.scene.train[0].clone();
        let targets: Vec<Tensor<3>> = observations
            .iter()
            .map(|o| image_tensor(o, &self.device))
            .collect();
        let rates = &self.config.init_learning_rates;
        let extent = (self.scene.hi - self.scene.lo).max_element() as f64;
        let learning_rates = [
            rates.means * extent,
            rates.rotations,
            rates.log_scales,
            rates.raw_densities,
            rates.colors,
        ];
        let iterations = self.config.init_iterations;
        let bar = self.progress(0, iterations);
        let mut last_render = f32::NAN;
        for iteration in 0..iterations {
            let loss =
                self.render_loss(&self.state.gaussians.tensors(), &observations, &targets)?;
            let value = scalar(&loss);
            let row = LossRow {
                frame: 0,
                phase: "init".into(),
                iteration,
                total: value,
                render: value,
                divergence: 0.0,
                advection: 0.0,
                refine: 0.0,
            };
            self.check_finite(&row, "init")?;
            self.losses.push(row);
            let mut grads = {
                let _timed = profile::scope("backward (all ops)");
                loss.backward()
            };
            self.step_gaussians(&mut grads, learning_rates);
            last_render = value;
            bar.set_message(format!("L1 {value:.5}"));
            bar.inc(1);
        }
        bar.finish_and_clear();
        let velocity = self.state.velocity.clone();
        self.finish_frame(0, last_render as f64, None, [0, 0], start)?;
        self.state.velocity = velocity;
        Ok(())
    }

    /// Frames `t-1 -> t`: K joint iterations, then K' refinement iterations.
    pub fn advance_to(&mut self, t: usize) -> Result<(), TrainError> {
        let start = Instant::now();
        let respawned = self.respawn(t - 1)?.indices.len();
        let config = self.config.clone();
        let observations = self.scene.train[t].clone();
        let targets: Vec<Tensor<3>> = observations
            .iter()
            .map(|o| image_tensor(o, &self.device))
            .collect();
        let factor = config.lr_factor(t);
        let lr_velocity = config.lr_velocity * factor;
        let lr_gaussians = config.lr_gaussians * factor;
        let time = t as f32 / (self.scene.frames() - 1).max(1) as f32;
        let previous_means = self.state.gaussians.means.val().detach();
        let previous_velocity = self.state.velocity.clone().detach();
        let interpolation = self.interpolation();
        let refine_iterations = if config.refinement {
            config.refine_iterations
        } else {
            0
        };
        let bar = self.progress(t, config.advect_iterations + refine_iterations);

        // K joint iterations (Algorithm 1, lines 3-9).
        let mut velocity = previous_velocity.clone();
        let mut unprojected = previous_velocity.clone();
        let mut advected = previous_means.clone();
        let mut clamped = 0;
        let mut last_render = f32::NAN;
        for iteration in 0..config.advect_iterations {
            let step_start = Instant::now();
            let previous = self.state.gaussians.tensors_at(previous_means.clone());
            let sigma_previous = density_grid(&previous, &self.grid, SPLAT_CUTOFF);
            let delta = {
                let _timed = profile::scope("U-Net forward");
                self.state.phi.forward(
                    previous_velocity.clone(),
                    sigma_previous.clone().detach(),
                    time,
                )?
            };
            let update = previous_velocity.clone() + delta;
            let projected = self.project(update.clone());
            let moved = advect(
                &self.grid,
                &projected,
                &previous_means,
                config.dt,
                self.integrator(),
                interpolation,
            );
            let next = self.state.gaussians.tensors_at(moved.positions.clone());
            let render = self.render_loss(&next, &observations, &targets)?;
            let mut loss = render.clone();
            let (mut divergence_value, mut advection_value) = (0.0, 0.0);
            if config.physics_losses {
                let divergence =
                    divergence_loss(&self.grid, &projected, &previous_means, interpolation);
                let sigma_next = density_grid(&next, &self.grid, SPLAT_CUTOFF);
                let gradient_previous = density_gradient_grid(&previous, &self.grid, SPLAT_CUTOFF);
                let gradient_next = density_gradient_grid(&next, &self.grid, SPLAT_CUTOFF);
                let advection = advection_loss(
                    &sigma_previous,
                    &sigma_next,
                    &gradient_previous,
                    &gradient_next,
                    &projected,
                    config.dt,
                );
                divergence_value = scalar(&divergence);
                advection_value = scalar(&advection);
                loss = loss + divergence * config.lambda_div + advection * config.lambda_adv;
            }
            let render_value = scalar(&render);
            let row = LossRow {
                frame: t,
                phase: "advect".into(),
                iteration,
                total: scalar(&loss),
                render: render_value,
                divergence: divergence_value,
                advection: advection_value,
                refine: 0.0,
            };
            let speed = scalar(&projected.clone().abs().max());
            self.check_finite_with(&row, "advect", Some(("the velocity grid (max |u|)", speed)))?;
            bar.set_message(format!(
                "L1 {render_value:.5} div {divergence_value:.2e} adv {advection_value:.2e}"
            ));
            self.losses.push(row);
            last_render = render_value;

            velocity = projected.clone().detach();
            unprojected = update.detach();
            advected = moved.positions.detach();
            clamped = scalar(&moved.left_box.float().sum()) as usize;

            let mut grads = {
                let _timed = profile::scope("backward (all ops)");
                loss.backward()
            };
            let phi_grads = GradientsParams::from_module(&mut grads, &self.state.phi);
            let phi = self.state.phi.clone();
            self.state.phi = {
                let _timed = profile::scope("optimizer");
                self.state.phi_optim.step(lr_velocity, phi, phi_grads)
            };
            self.step_gaussians(
                &mut grads,
                [0.0, lr_gaussians, lr_gaussians, lr_gaussians, lr_gaussians],
            );
            tracing::debug!(
                frame = t,
                iteration,
                ms = step_start.elapsed().as_millis() as u64,
                "advect step"
            );
            bar.inc(1);
        }
        if config.advect_iterations == 0 {
            // No joint iterations: carry the Gaussians along the previous velocity.
            let moved = advect(
                &self.grid,
                &previous_velocity,
                &previous_means,
                config.dt,
                self.integrator(),
                interpolation,
            );
            advected = moved.positions.detach();
        }

        // K' refinement iterations (lines 11-13): free centres tied to the advected ones.
        let anchor = advected.clone();
        self.state.gaussians = self.state.gaussians.clone().with_means(anchor.clone());
        for iteration in 0..refine_iterations {
            let gaussians = self.state.gaussians.tensors();
            let render = self.render_loss(&gaussians, &observations, &targets)?;
            let refine = refine_loss(&gaussians.means, &anchor);
            let (render_value, refine_value) = (scalar(&render), scalar(&refine));
            let loss = render + refine * config.lambda_refine;
            let row = LossRow {
                frame: t,
                phase: "refine".into(),
                iteration,
                total: scalar(&loss),
                render: render_value,
                divergence: 0.0,
                advection: 0.0,
                refine: refine_value,
            };
            self.check_finite(&row, "refine")?;
            bar.set_message(format!("L1 {render_value:.5} refine {refine_value:.2e}"));
            self.losses.push(row);
            last_render = render_value;
            let mut grads = {
                let _timed = profile::scope("backward (all ops)");
                loss.backward()
            };
            self.step_gaussians(&mut grads, [lr_gaussians; 5]);
            bar.inc(1);
        }
        bar.finish_and_clear();
        self.state.velocity = velocity;
        let report = self.projection_report(unprojected);
        self.finish_frame(
            t,
            last_render as f64,
            Some(report),
            [clamped, respawned],
            start,
        )
    }

    /// Recycles Gaussians (see [`crate::respawn`]) against frame `t`'s training views, before
    /// they move on from frame `t`; nothing happens with `respawn_fraction = 0`.
    fn respawn(&mut self, t: usize) -> Result<RespawnReport, TrainError> {
        if self.config.respawn_fraction <= 0.0 {
            return Ok(RespawnReport::default());
        }
        let _timed = profile::scope("respawn");
        let observations = &self.scene.train[t];
        let renders = self.render_host(observations)?;
        let views: Vec<DeficitView> = observations
            .iter()
            .zip(&renders)
            .map(|(observation, rendered)| DeficitView {
                camera: &observation.camera,
                observed: observation.image.data(),
                rendered,
            })
            .collect();
        let mut host = self.state.gaussians.to_host();
        let extent = self.grid.hi() - self.grid.lo();
        let options = RespawnOptions {
            fraction: self.config.respawn_fraction,
            threshold: self.config.respawn_threshold,
            // The initialisation's size (see `GaussianModel::init_in_box`).
            std: 0.5 * (extent.x * extent.y * extent.z / host.len() as f32).cbrt(),
            background: self.scene.background,
            // A per-frame stream, so a resumed run draws what an uninterrupted one did.
            seed: self.config.seed ^ (t as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        };
        let lattice = SpawnLattice {
            lo: self.grid.lo(),
            hi: self.grid.hi(),
            resolution: self.grid.resolution(),
        };
        let report = respawn(&mut host, &views, &lattice, &options);
        if !report.indices.is_empty() {
            self.state.gaussians = self.state.gaussians.clone().with_host_values(&host);
        }
        tracing::debug!(
            frame = t,
            recycled = report.indices.len(),
            from_box_faces = report.from_box_faces,
            deficit_cells = report.deficit_cells,
            max_deficit = report.max_deficit,
            "respawn"
        );
        Ok(report)
    }

    /// The current Gaussians outside the autodiff graph (for outputs and metrics).
    fn detached_gaussians(&self) -> GaussianTensors {
        let g = self.state.gaussians.tensors();
        GaussianTensors {
            means: g.means.detach(),
            rotations: g.rotations.detach(),
            log_scales: g.log_scales.detach(),
            raw_densities: g.raw_densities.detach(),
            colors: g.colors.detach(),
        }
    }

    /// Host density grid of the current Gaussians.
    pub fn density_host(&self) -> Vec<f32> {
        let detached = self.detached_gaussians();
        host(density_grid(&detached, &self.grid, SPLAT_CUTOFF))
    }

    /// Renders of the current Gaussians for `observations`, as `[H, W, 3]` host images.
    pub fn render_host(&self, observations: &[Observation]) -> Result<Vec<Vec<f32>>, TrainError> {
        let detached = self.detached_gaussians();
        observations
            .iter()
            .map(|o| {
                let out = render_volume(&detached, &o.camera, &self.background, &self.raster)?;
                Ok(host(out.rgb))
            })
            .collect()
    }

    /// Per-frame outputs, metrics and the checkpoint.
    fn finish_frame(
        &mut self,
        t: usize,
        train_l1: f64,
        projection: Option<gausmoke_model::ProjectionReport>,
        [clamped_to_box, respawned]: [usize; 2],
        start: Instant,
    ) -> Result<(), TrainError> {
        // The optimisation's phase times so far; the evaluation and outputs below render too,
        // and their time goes to "outputs and evaluation" instead (at the end).
        for time in profile::take() {
            profile::accumulate(&mut self.phase_times, time);
        }
        let outputs_start = Instant::now();
        let velocity = host(self.state.velocity.clone());
        let density = self.density_host();
        let gaussians = self.state.gaussians.to_host();
        let test = self.scene.test[t].clone();
        let train = self.scene.train[t].clone();
        let test_renders = self.render_host(&test)?;
        let (mut l1, mut psnr, mut ssim) = (0.0, 0.0, 0.0);
        for (observation, render) in test.iter().zip(&test_renders) {
            let (w, h) = (
                observation.image.width() as usize,
                observation.image.height() as usize,
            );
            l1 += metrics::mean_abs_error(render, observation.image.data());
            psnr += metrics::psnr(render, observation.image.data());
            ssim += metrics::ssim(render, observation.image.data(), w, h);
        }
        let tests = test.len() as f64;
        let speeds: Vec<f64> = velocity
            .chunks(3)
            .map(|v| ((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) as f64).sqrt())
            .collect();
        let projection = projection.unwrap_or_default();
        let report = FrameReport {
            frame: t,
            train_l1,
            test_l1: (tests > 0.0).then_some(l1 / tests),
            test_psnr: (tests > 0.0).then_some(psnr / tests),
            test_ssim: (tests > 0.0).then_some(ssim / tests),
            mean_abs_divergence: metrics::mean_abs_divergence(&self.grid, &velocity),
            projection_iterations: projection.iterations,
            projection_residual: projection.relative_residual,
            divergence_rms_before: projection.divergence_rms_before,
            divergence_rms_after: projection.divergence_rms_after,
            clamped_to_box,
            respawned,
            mean_speed: speeds.iter().sum::<f64>() / speeds.len().max(1) as f64,
            max_speed: speeds.iter().cloned().fold(0.0, f64::max),
            seconds: start.elapsed().as_secs_f64(),
        };

        // The per-frame state evaluation reads back (always written).
        let [nx, ny, nz] = self.grid.resolution();
        let n = gaussians.len();
        let frames_dir = self.out.join("frames");
        self.create_dir(&frames_dir)?;
        checkpoint::write_arrays(
            &frames_dir.join(format!("frame_{t:03}.safetensors")),
            &HostArrays::from([
                ("means".to_string(), (vec![n, 3], gaussians.means.clone())),
                (
                    "rotations".to_string(),
                    (vec![n, 4], gaussians.rotations.clone()),
                ),
                (
                    "log_scales".to_string(),
                    (vec![n, 3], gaussians.log_scales.clone()),
                ),
                (
                    "raw_densities".to_string(),
                    (vec![n], gaussians.raw_densities.clone()),
                ),
                ("colors".to_string(), (vec![n, 3], gaussians.colors.clone())),
                (
                    "velocity".to_string(),
                    (vec![nx, ny, nz, 3], velocity.clone()),
                ),
                ("density".to_string(), (vec![nx, ny, nz], density.clone())),
            ]),
        )?;

        let last = t + 1 == self.scene.frames();
        if t.is_multiple_of(self.config.output_every) || last {
            let train_renders = self.render_host(&train)?;
            for (observation, render) in train
                .iter()
                .chain(&test)
                .zip(train_renders.iter().chain(&test_renders))
            {
                let dir = self.out.join("renders").join(&observation.view);
                self.create_dir(&dir)?;
                let (w, h) = (observation.image.width(), observation.image.height());
                Picture::from_rgb(render, w, h).save_png(&dir.join(format!("frame_{t:03}.png")))?;
            }
            // Held-out (or first training) view: reference | render, for the GIF.
            let (reference, render) = match test.first() {
                Some(o) => (o, &test_renders[0]),
                None => (&train[0], &train_renders[0]),
            };
            let (w, h) = (reference.image.width(), reference.image.height());
            let comparison = Picture::side_by_side(&[
                &Picture::from_rgb(reference.image.data(), w, h),
                &Picture::from_rgb(render, w, h),
            ]);
            let dir = self.out.join("comparison");
            self.create_dir(&dir)?;
            comparison.save_png(&dir.join(format!("frame_{t:03}.png")))?;
            let dir = self.out.join("slices");
            self.create_dir(&dir)?;
            let scale = (256 / nx.max(ny)).max(1) as u32;
            visuals::grid_slices(&self.grid, &density, &velocity, scale)
                .0
                .save_png(&dir.join(format!("frame_{t:03}.png")))?;
            let dir = self.out.join("exports");
            self.create_dir(&dir)?;
            export::write_ply(&dir.join(format!("gaussians_{t:03}.ply")), &gaussians)?;
            export::write_vti(
                &dir.join(format!("grid_{t:03}.vti")),
                &self.grid,
                &density,
                &velocity,
            )?;
            export::write_npz(
                &dir.join(format!("grid_{t:03}.npz")),
                &self.grid,
                &density,
                &velocity,
            )?;
        }

        tracing::info!(
            frame = t,
            train_l1 = format!("{:.5}", report.train_l1),
            test_psnr = format!("{:.2}", report.test_psnr.unwrap_or(f64::NAN)),
            test_ssim = format!("{:.4}", report.test_ssim.unwrap_or(f64::NAN)),
            mean_abs_div = format!("{:.3e}", report.mean_abs_divergence),
            seconds = format!("{:.1}", report.seconds),
            eta_seconds = format!(
                "{:.0}",
                report.seconds * (self.scene.frames() - 1 - t) as f64
            ),
            "frame done"
        );
        self.reports.push(report);
        self.frame = Some(t);
        let meta = CheckpointMeta {
            frame: t,
            config: self.config.clone(),
            losses: self.losses.clone(),
            reports: self.reports.clone(),
            elapsed_seconds: self.elapsed(),
        };
        checkpoint::save(&self.out, &self.state, &meta)?;
        self.write_losses()?;
        let _ = profile::take();
        profile::accumulate(
            &mut self.phase_times,
            profile::PhaseTime {
                name: "outputs and evaluation",
                seconds: outputs_start.elapsed().as_secs_f64(),
                calls: 1,
            },
        );
        Ok(())
    }

    fn create_dir(&self, dir: &Path) -> Result<(), TrainError> {
        std::fs::create_dir_all(dir).map_err(|source| TrainError::Io {
            path: dir.to_path_buf(),
            source,
        })
    }

    fn write_losses(&self) -> Result<(), TrainError> {
        let mut csv =
            String::from("step,frame,phase,iteration,total,render,divergence,advection,refine\n");
        for (step, r) in self.losses.iter().enumerate() {
            csv += &format!(
                "{step},{},{},{},{},{},{},{},{}\n",
                r.frame,
                r.phase,
                r.iteration,
                r.total,
                r.render,
                r.divergence,
                r.advection,
                r.refine
            );
        }
        export::write_atomic(&self.out.join("losses.csv"), csv.as_bytes())
    }

    /// Loss and speed plots, the comparison GIF and `metrics.json`.
    pub fn write_summary(&self) -> Result<(), TrainError> {
        self.write_losses()?;
        let column = |f: fn(&LossRow) -> f32| -> Vec<f64> {
            self.losses.iter().map(|r| f(r) as f64).collect()
        };
        visuals::line_plot(
            &[
                column(|r| r.total),
                column(|r| r.render),
                column(|r| r.divergence),
                column(|r| r.advection),
                column(|r| r.refine),
            ],
            900,
            400,
            true,
        )
        .save_png(&self.out.join("losses.png"))?;
        visuals::line_plot(
            &[
                self.reports.iter().map(|r| r.mean_speed).collect(),
                self.reports.iter().map(|r| r.max_speed).collect(),
            ],
            600,
            300,
            false,
        )
        .save_png(&self.out.join("speed.png"))?;
        let mut pictures = Vec::new();
        for t in 0..self.scene.frames() {
            let path = self
                .out
                .join("comparison")
                .join(format!("frame_{t:03}.png"));
            if let Ok(image) = image::open(&path) {
                let rgb = image.to_rgb8();
                pictures.push(Picture {
                    width: rgb.width(),
                    height: rgb.height(),
                    pixels: rgb.into_raw(),
                });
            }
        }
        if !pictures.is_empty() {
            visuals::save_gif(&self.out.join("comparison.gif"), &pictures, 100)?;
        }
        let mean = |f: fn(&FrameReport) -> Option<f64>| {
            let values: Vec<f64> = self
                .reports
                .iter()
                .filter_map(f)
                .filter(|v| v.is_finite())
                .collect();
            (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
        };
        let metrics = serde_json::json!({
            "frames": self.reports.len(),
            "gaussians": self.state.gaussians.len(),
            "grid_resolution": self.grid.resolution(),
            "test_l1_mean": mean(|r| r.test_l1),
            "test_psnr_mean": mean(|r| r.test_psnr),
            "test_ssim_mean": mean(|r| r.test_ssim),
            "mean_abs_divergence": mean(|r| Some(r.mean_abs_divergence)),
            "train_l1_mean": mean(|r| Some(r.train_l1)),
            "training_seconds": self.elapsed(),
            "device": format!("{:?}", self.device),
            // Wall time per phase in this session (a resumed run counts from the resume).
            // Nested: "backward (all ops)" includes the ops' own backward phases, "density
            // splat" counts every splatting call (U-Net input and physics losses).
            "phase_seconds": self.phase_times.iter().map(|p| (p.name.to_string(), serde_json::json!({
                "seconds": p.seconds,
                "calls": p.calls,
            }))).collect::<serde_json::Map<String, serde_json::Value>>(),
            "per_frame": self.reports.iter().map(|r| serde_json::json!({
                "frame": r.frame,
                "train_l1": r.train_l1,
                "test_l1": r.test_l1,
                "test_psnr": r.test_psnr,
                "test_ssim": r.test_ssim,
                "mean_abs_divergence": r.mean_abs_divergence,
                "projection_iterations": r.projection_iterations,
                "projection_residual": r.projection_residual,
                "divergence_rms_before": r.divergence_rms_before,
                "divergence_rms_after": r.divergence_rms_after,
                "clamped_to_box": r.clamped_to_box,
                "respawned": r.respawned,
                "mean_speed": r.mean_speed,
                "max_speed": r.max_speed,
                "seconds": r.seconds,
            })).collect::<Vec<_>>(),
        });
        export::write_atomic(
            &self.out.join("metrics.json"),
            serde_json::to_string_pretty(&metrics)
                .expect("plain JSON")
                .as_bytes(),
        )?;
        export::write_atomic(&self.out.join("README.txt"), RUN_README.as_bytes())
    }
}

/// What the files of a run folder are (written into it).
const RUN_README: &str = "\
GauSmoke-rs run folder
config.toml        the configuration used (pass it back with --config to reproduce)
run.json           data set, grid box and resolution, device
metrics.json       per-frame and mean metrics: held-out PSNR/SSIM, mean |div u| (1/frame),
                   projection solver iterations/residual, speeds, seconds per frame
losses.csv         every optimisation step: frame, phase (init/advect/refine), loss terms
losses.png         log-scale loss curves over steps: blue total, orange L_render,
                   green L_div, red L_adv, purple L_refine
speed.png          per frame: blue mean speed, orange max speed (world units per frame)
renders/VIEW/      per-frame renders of every camera (train and held-out)
comparison/        per frame: held-out reference | render; comparison.gif animates them
slices/            per frame, middle z slice: density (grey) | speed (dark blue -> yellow)
exports/           per frame: gaussians_TTT.ply (3DGS layout), grid_TTT.vti (ParaView),
                   grid_TTT.npz (density [nx,ny,nz], velocity [nx,ny,nz,3], lo, hi)
frames/            per frame: Gaussians, velocity and density grids (safetensors), read by
                   `gausmoke-train eval`
checkpoints/       the two newest complete frames; `--resume` continues from the newest
";
