//! Algorithm 1 of the paper, one frame at a time.
//!
//! * Frame 0 ([`Trainer::fit_first_frame`]): the static Gaussians' fit, if any, then a
//!   static fit of the smoke Gaussians to the first frame's training views (L1).
//! * Frame t-1 -> t ([`Trainer::advance_to`]), a short list of stages:
//!   1. [`FrameStart`]: the frame's views, learning rates and where it starts from (the
//!      previous velocity, carried along itself with `joint.transport_velocity`).
//!   2. the joint step ([`joint`], lines 3-9): K iterations of `u^t = Pi(u' + Phi(u', sigma,
//!      PE(t)))`, centres advected through `u^t`, loss a sum of named terms (`L_render`,
//!      `L_div`, `L_adv`, and ours: the look-ahead and the inertia prior).
//!   3. the population ([`population`], ours): Gaussians the views leave unused recycled into
//!      the inflow, the largest split.
//!   4. the refinement step ([`refine`], lines 11-13): K' iterations with free centres tied to
//!      the advected ones (and ours: the tie's grid-scale part, one view a step).
//!   5. the refinement's moves measured ([`moves`]), for the frame's report.
//!
//! Units: world units, time in frames (`dt` frames per step), velocity in world units per
//! frame. `L_render` is the mean absolute error per pixel and channel over the training views.
//!
//! The trainer only trains: what each frame produced comes back as a [`FrameOutcome`];
//! evaluating it, writing files and checkpoints is [`crate::run::Run`]'s business.

mod frame;
mod joint;
mod losses;
mod moves;
mod obstacles;
mod physics;
mod population;
mod refine;
mod still;
#[cfg(test)]
mod tests;

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_model::{GridSpec, ProjectionReport, SolidCells, SplatOptions};
use gausmoke_render::device_traffic::read_floats;
use gausmoke_render::{GaussianTensors, RasterOptions, render_volume};
use indicatif::{ProgressBar, ProgressStyle};

use crate::TrainError;
use crate::arrays::HostArrays;
use crate::config::TrainConfig;
use crate::sequence::{Observation, Sequence};
use crate::state::{LoopTraffic, LossRow, Phase, RefineMoveField, TrainState};

pub use frame::FrameStart;
pub use moves::RefineMoves;
pub(crate) use obstacles::solid_cells;

use gausmoke_render::device_traffic::Traffic;
use moves::FrameMoves;
use still::{StillFit, fresh_state};

/// What training one frame produced.
#[derive(Debug, Clone)]
pub struct FrameOutcome {
    pub frame: usize,
    /// Every optimisation step's losses, in order.
    pub losses: Vec<LossRow>,
    /// `L_render` at the frame's last step, over every training view (when that step
    /// rendered some of them, over its last turn of steps: see `refine.views_per_step`).
    pub train_l1: f64,
    /// What `Pi` did at the frame's last joint step (`None` for frame 0).
    pub projection: Option<ProjectionReport>,
    /// Gaussians whose advected centre left the box and was clamped back onto it.
    pub clamped_to_box: usize,
    /// Gaussians recycled between the joint iterations and the refinement.
    pub respawned: usize,
    /// Gaussians split after the recycling.
    pub split: usize,
    /// How far and how coherently the refinement moved the centres (`None` without it).
    pub refine_moves: Option<RefineMoves>,
    /// The refinement's grid-scale move field (`None` without refinement).
    pub refine_move_field: Option<RefineMoveField>,
    /// Device reads and kernel launches of the frame's optimisation loops, loop by loop.
    pub traffic: Vec<LoopTraffic>,
}

/// Runs Algorithm 1 on a [`Sequence`].
pub struct Trainer {
    pub config: TrainConfig,
    pub sequence: Sequence,
    pub device: Device,
    pub grid: GridSpec,
    pub state: TrainState,
    background: Tensor<1>,
    raster: RasterOptions,
    /// The data set's obstacles on the grid, when the configuration makes them solid.
    solids: Option<SolidCells>,
    /// The last frame's refinement moves, for the next frame's persistence (kept in the
    /// checkpoint: [`Trainer::checkpoint_extras`]).
    last_moves: Option<FrameMoves>,
    quiet: bool,
    /// The data set has a `scene.toml` (see [`crate::scene`]): nothing is estimated.
    scene_file: bool,
}

/// A frame's cameras and the images they saw, as the render losses take them.
type ViewTargets = (Vec<gausmoke_core::Camera>, Vec<Tensor<3>>);

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
    /// A trainer at the start of Algorithm 1 (fresh, seeded state).
    pub fn new(
        sequence: Sequence,
        mut config: TrainConfig,
        device: Device,
    ) -> Result<Self, TrainError> {
        let scene_file = config.scene.fill_from_data(&sequence.path)?;
        config.validate()?;
        let views = sequence.train.first().map_or(0, Vec::len);
        if config.refine.views_per_step > views {
            return Err(TrainError::Config {
                origin: "refine.views_per_step".into(),
                reason: format!(
                    "{} views a refinement step, but the data set has {views} training views \
                     (0 renders all of them)",
                    config.refine.views_per_step
                ),
            });
        }
        // Each frame reports its loops' kernel launches (no-op without a cube backend).
        gausmoke_render::device_traffic::count_launches();
        let grid = config.grid(sequence.lo, sequence.hi)?;
        let background =
            Tensor::<1>::from_data(TensorData::new(sequence.background.to_vec(), [3]), &device);
        let raster = config.raster_options();
        let solids = solid_cells(&sequence.obstacles, &config, &grid)?;
        let state = fresh_state(&sequence, &config, &grid, &device);
        Ok(Self {
            config,
            sequence,
            device,
            grid,
            state,
            background,
            raster,
            solids,
            last_moves: None,
            quiet: false,
            scene_file,
        })
    }

    /// The grid cells the projection keeps the flow out of (the data set's obstacles), if any.
    pub fn solid_cells(&self) -> Option<&SolidCells> {
        self.solids.as_ref()
    }

    /// Hides the progress bars (tests, notebooks).
    pub fn quiet(mut self, quiet: bool) -> Self {
        self.quiet = quiet;
        self
    }

    /// A fresh state of this trainer's shape for a checkpoint to be loaded into.
    pub fn fresh_state_for_resume(&self) -> TrainState {
        fresh_state(&self.sequence, &self.config, &self.grid, &self.device)
    }

    /// Takes the state and extras a checkpoint held (see [`Trainer::fresh_state_for_resume`]
    /// and [`Trainer::checkpoint_extras`]).
    pub fn restore(&mut self, state: TrainState, extras: HostArrays) -> Result<(), TrainError> {
        let n = state.gaussians.len();
        self.state = state;
        self.last_moves = FrameMoves::from_arrays(&extras, &self.device);
        if let Some(moves) = &self.last_moves {
            let [rows, _] = moves.moves.dims();
            if rows != n {
                return Err(TrainError::Checkpoint {
                    path: "extras.safetensors".into(),
                    reason: format!("it holds moves of {rows} Gaussians, the state {n}"),
                });
            }
        }
        Ok(())
    }

    /// What a checkpoint keeps besides the state: the last frame's refinement moves, so that
    /// a resumed run measures its first frame's persistence as an uninterrupted one does.
    pub fn checkpoint_extras(&self) -> HostArrays {
        self.last_moves
            .as_ref()
            .map(FrameMoves::to_arrays)
            .unwrap_or_default()
    }

    /// Frame `t` of Algorithm 1: the static fit for frame 0, else the step from `t - 1`.
    pub fn train_frame(&mut self, t: usize) -> Result<FrameOutcome, TrainError> {
        if t == 0 {
            self.fit_first_frame()
        } else {
            self.advance_to(t)
        }
    }

    /// Frame 0: the statics' fit (if any), then a static fit of the smoke with per-attribute
    /// learning rates.
    pub fn fit_first_frame(&mut self) -> Result<FrameOutcome, TrainError> {
        // A new sequence of refinements: no moves before the next one.
        self.last_moves = None;
        let observations = self.sequence.train[0].clone();
        let targets: Vec<Tensor<3>> = observations
            .iter()
            .map(|o| image_tensor(o, &self.device))
            .collect();
        let start = Traffic::now();
        let mut losses = self.fit_statics()?;
        // The statics were fitted first; frame 0 fits the smoke in front of them.
        losses.extend(self.fit_to_images(StillFit::FirstFrame, &observations, &targets)?);
        let traffic = vec![LoopTraffic::of(Phase::Init, losses.len(), start)];
        self.settle_scene();
        Ok(FrameOutcome {
            frame: 0,
            train_l1: losses.last().map_or(f32::NAN, |r| r.render) as f64,
            losses,
            projection: None,
            clamped_to_box: 0,
            respawned: 0,
            split: 0,
            refine_moves: None,
            refine_move_field: None,
            traffic,
        })
    }

    /// Frames `t-1 -> t`: the joint step (K iterations), the population's renewal, the
    /// refinement step (K' iterations), and the refinement's moves measured.
    pub fn advance_to(&mut self, t: usize) -> Result<FrameOutcome, TrainError> {
        let frame = FrameStart::new(self, t);
        let bar = self.progress(t, frame.iterations());
        let mut losses = Vec::with_capacity(frame.iterations());

        let joint = self.joint_step(&frame, &mut losses, &bar)?;
        self.state.gaussians = self.state.gaussians.clone().with_means(joint.advected);
        self.keep_out_of_obstacles();

        let renewal = self.renew_population(t)?;

        let refined = self.refine_step(&frame, &mut losses, &bar)?;
        bar.finish_and_clear();

        let (refine_moves, refine_move_field) = match refined.moves {
            Some((scale, anchor)) => {
                let (report, field) = self.measure_moves(&scale, anchor, &renewal.moved_rows());
                (Some(report), Some(field))
            }
            None => {
                self.last_moves = None;
                (None, None)
            }
        };
        let projection = self.projection_report(joint.unprojected);
        self.state.velocity = joint.velocity;
        Ok(FrameOutcome {
            frame: t,
            train_l1: refine::last_turn_l1(
                &losses,
                frame.cameras.len(),
                self.config.refine.views_per_step,
            ),
            losses,
            projection: Some(projection),
            clamped_to_box: joint.clamped,
            respawned: renewal.recycled.indices.len(),
            split: renewal.split.parents.len(),
            refine_moves,
            refine_move_field,
            traffic: vec![joint.traffic, refined.traffic],
        })
    }

    /// What the configuration and the data set's `scene.toml` leave unset of the scene,
    /// estimated from frame 0's density (see [`crate::scene::estimate`]) and reported.
    fn settle_scene(&mut self) {
        let scene = &self.config.scene;
        if self.scene_file || (scene.open_faces.is_some() && scene.inflow.is_some()) {
            return;
        }
        let estimate = crate::scene::estimate(&self.density_host(), self.grid.resolution());
        self.config.scene.fill(estimate);
        let scene = &self.config.scene;
        tracing::info!(
            open_faces = ?scene.open_face_names(),
            inflow = ?scene.inflow,
            "scene estimated from frame 0 (no scene.toml beside the data; set [scene] or \
             --set scene.KEY=... to override)"
        );
    }

    fn progress(&self, frame: usize, length: usize) -> ProgressBar {
        let bar = self.progress_bar(length);
        bar.set_prefix(format!("frame {frame}/{}", self.sequence.frames() - 1));
        bar
    }

    /// A progress bar of `length` steps in the trainer's style (hidden when quiet).
    pub fn progress_bar(&self, length: usize) -> ProgressBar {
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
        bar
    }

    /// Frame `frame`'s training views on the device: every frame's in the same view order
    /// (the sequence gathers each view's frames in one order and refuses a view that
    /// misses a frame).
    fn training_views(&self, frame: usize) -> ViewTargets {
        self.sequence.train[frame]
            .iter()
            .map(|o| (o.camera, image_tensor(o, &self.device)))
            .unzip()
    }

    /// Host density grid of the current Gaussians.
    pub fn density_host(&self) -> Vec<f32> {
        self.density_host_of(&self.state.gaussians.tensors())
    }

    /// The density `gaussians` splat on the velocity grid, on the host.
    fn density_host_of(&self, gaussians: &GaussianTensors) -> Vec<f32> {
        read_floats(self.splat_density(&gaussians.clone().detach(), SplatOptions::default().cutoff))
    }

    /// Renders of the current Gaussians (the static ones with them) for `observations`, as
    /// `[H, W, 3]` host images.
    pub fn render_host(&self, observations: &[Observation]) -> Result<Vec<Vec<f32>>, TrainError> {
        let detached = self.scene(self.state.gaussians.tensors(), false).detach();
        observations
            .iter()
            .map(|o| {
                let out = render_volume(&detached, &o.camera, &self.background, &self.raster)?;
                Ok(read_floats(out.rgb))
            })
            .collect()
    }
}
