//! Algorithm 1 of the paper, one frame at a time.
//!
//! * Frame 0: a static fit of the Gaussians to the first frame's training views (L1).
//! * Frame t-1 -> t, K iterations (lines 3-9): `sigma = D(G^{t-1})`,
//!   `Delta u = Phi(u^{t-1}, sigma, PE(t))`, `u^t = Pi(u^{t-1} + Delta u)`, centres advected
//!   from `p^{t-1}` through `u^t`, rendered against frame t, loss
//!   `L_render + lambda_div L_div + lambda_adv L_adv`; Adam steps on Phi and on the Gaussians'
//!   shape, density and colour (the centres are the advected ones, so `p^{t-1}` stays).
//!   With `lambda_lookahead > 0` (ours, off by default) the loss also renders the centres
//!   carried one frame further (`lookahead_frames`: or more) against frame t+1's views, the
//!   other attributes held fixed, so `u^t` is fitted to several frames' pictures; each
//!   further step moves them along `u^t` again or (`lookahead_velocity = "predicted"`)
//!   along Phi's projected prediction for that frame from their density there. With
//!   `lambda_kinetic > 0` (ours, off by default) it also penalises the mean `|u^t|^2` in
//!   cells per frame.
//! * Then K' refinement iterations (lines 11-13): the centres become free parameters tied to
//!   the advected ones by `lambda_refine L_refine`, with `L_render`; `lambda_refine_grid` and
//!   `lambda_refine_subgrid` (ours, off by default) tie the move's grid-scale and sub-grid
//!   parts apart (`gausmoke_model::GridScale`).
//!
//! Units: world units, time in frames (`dt` frames per step), velocity in world units per
//! frame. `L_render` is the mean absolute error per pixel and channel over the training views.
//!
//! The trainer only trains: what each frame produced comes back as a [`FrameOutcome`];
//! evaluating it, writing files and checkpoints is [`crate::run::Run`]'s business.

use std::path::Path;

use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Gradients, Int, Tensor, TensorData};
use gausmoke_core::glam::Vec3;
use gausmoke_core::{Camera, SplitMix64, phase};
use gausmoke_data::Obstacle;
use gausmoke_model::penalty::penalty_projection_with_report;
use gausmoke_model::{
    Advected, BuoyancyForce, GaussianModel, GridScale, GridSpec, INITIAL_RAW_DENSITY, Integrator,
    Interpolation, NO_SIZE_BOUNDS, PenaltyOptions, ProjectionOptions, ProjectionReport, SolidCells,
    SplatOptions, UNetConfig, VelocityUNet, advect, advection_loss, deform_shapes,
    density_and_gradient_grid, density_grid, density_tie_loss, divergence_loss_of, log_density,
    penalty_projection, project_direct, project_velocity, refine_loss, sample_velocity,
    settle_deferred_solves, transport_velocity, uniform_color,
};
use gausmoke_render::cpu::TILE_SIZE;
use gausmoke_render::device_traffic::{
    ReadKind, Traffic, read_floats, read_floats_for, read_scalar,
};
use gausmoke_render::{
    GaussianTensors, Gaussians, HostGaussians, InputCheck, RasterOptions, list_buffer_lengths,
    render_volume, render_volume_deferred,
};
use indicatif::{ProgressBar, ProgressStyle};

use crate::TrainError;
use crate::arrays::{read_arrays, take_array};
use crate::attribute_grads::{
    attribute_grads, attribute_params, grads_over_their_rms, per_attribute_params,
};
use crate::carried_smoothing::{grow_carried_sizes, smooth_carried_densities};
use crate::config::{
    BlurAxes, CarrierShare, CorrectionTarget, DensityMotionPrior, EmissionTiming, HeldView,
    IntegratorKind, InterpolationKind, LookaheadVelocity, Obstacles, OptimizerReset,
    ProjectionKind, TrainConfig,
};
use crate::density_motion::{
    MotionGrid, MotionPriors, Smoothed, fit_density_motion, moves_of_velocity, transport_cells,
    velocity_of_moves,
};
use crate::emission::{EmissionOptions, EmissionReport, emit};
use crate::held_out_trace::{HeldOutTrace, Stage, TracePoint};
use crate::held_view::{
    HeldViewChecks, HeldViewReport, KeptState, fitted_views, held_view, steps_per_turn,
};
use crate::host_grid::smoothed;
use crate::iterate_mean::IterateMean;
use crate::residual_blur::{ResidualBlur, coarse_to_fine};
use crate::respawn::{
    DeficitView, RespawnOptions, RespawnReport, SpawnLattice, recycling_candidates, respawn,
};
use crate::run_folder::read_frame_gaussians;
use crate::sequence::{Observation, Sequence};
use crate::split::{SplitReport, split_largest};
use crate::state::{
    Buoyancy, LoopTraffic, LossRow, Phase, RefineMoveField, StaticGaussians, TrainState,
};
use crate::step_log::{StepLog, StepLosses};
use crate::view_agreement::{combine, masked_attributes};

/// What training one frame produced.
#[derive(Debug, Clone)]
pub struct FrameOutcome {
    pub frame: usize,
    /// Every optimisation step's losses, in order.
    pub losses: Vec<LossRow>,
    /// `L_render` at the frame's last step, over every training view (when that step
    /// rendered some of them, over its last turn of steps: see `refine_views_per_step`).
    pub train_l1: f64,
    /// What `Pi` did at the frame's last joint step (`None` for frame 0).
    pub projection: Option<ProjectionReport>,
    /// Gaussians whose advected centre left the box and was clamped back onto it.
    pub clamped_to_box: usize,
    /// Gaussians recycled between the joint iterations and the refinement.
    pub respawned: usize,
    /// Gaussians emitted at the source between the joint iterations and the refinement.
    pub emitted: usize,
    /// Gaussians split after the recycling.
    pub split: usize,
    /// How far and how coherently the refinement moved the centres (`None` without it).
    pub refine_moves: Option<RefineMoves>,
    /// The refinement's grid-scale move field (`None` without refinement).
    pub refine_move_field: Option<RefineMoveField>,
    /// Device reads and kernel launches of the frame's optimisation loops, loop by loop.
    pub traffic: Vec<LoopTraffic>,
    /// The explicit buoyancy force's coefficient after the frame (`buoyancy_force`).
    pub buoyancy: Option<f64>,
    /// The share of the fitted transport the refinement started from
    /// (`carrier_share = "predicted"` or `"fitted"`; `None` otherwise and at frame 0).
    pub carrier_share: Option<f32>,
    /// The share of the still prediction's loss that the carrier's prediction removed
    /// (`carrier_share = "predicted"`, `"explained"` or `"explained_of_best"`).
    pub carrier_explained: Option<f32>,
    /// What the view held back from the refinement showed (`refine_held_view`).
    pub held_view: Option<HeldViewReport>,
    /// The held-out views' PSNR through the frame (`held_out_trace`).
    pub held_out_trace: Vec<TracePoint>,
}

/// The shares of the predicted move that `carrier_share = "predicted"` renders.
const PREDICTED_SHARES: [f32; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// The shares of the fitted move that `carrier_share = "fitted"` renders: up to twice it,
/// where the velocity falls short of the smoke's speed.
const FITTED_SHARES: [f32; 9] = [0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75, 2.0];

/// What [`Trainer::renew_gaussians`] did to the rows in one frame.
#[derive(Debug, Default)]
struct Renewal {
    emitted: EmissionReport,
    recycled: RespawnReport,
    split: SplitReport,
}

/// A raw density whose softplus is negligible (about 1e-13): a Gaussian left out of a
/// density sum without changing the set's shape.
const OFF_DENSITY: f32 = -30.0;

/// The refinement's move of the centres at one frame, mass-weighted (see
/// [`gausmoke_model::GridScale`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineMoves {
    /// RMS length of the move, in cells of the velocity grid.
    pub rms_cells: f64,
    /// Share of the move's mean square in its grid-scale part.
    pub grid_share: f64,
    /// The same share with the moves shuffled among the Gaussians: what a move without
    /// spatial order gets, the floor to read `grid_share` against.
    pub shuffled_grid_share: f64,
    /// Mass-weighted correlation of each Gaussian's move with its own move at the frame
    /// before, and the same for the moves' grid-scale parts: near 1 the refinement supplies
    /// the same motion frame after frame (motion the velocity keeps missing), near 0 its
    /// moves do not persist. Gaussians that jumped this frame are left out; `None` at the
    /// first frame the trainer refines (after a start or a resume).
    pub persistence: Option<[f64; 2]>,
    /// Share of the grid-scale move field (at each cell the mass-weighted mean move around
    /// it) that the projection keeps: the part a divergence-free velocity can make; the rest
    /// gathers or spreads the Gaussians.
    pub flow_share: f64,
    /// Correlation over the cells of the move field's flow part with the frame before's,
    /// and the same for the rest (the gathering part): which of the two the refinement
    /// asks for again. `None` at the first frame the trainer refines (after a start or a
    /// resume); unlike `persistence`, kept when the number of Gaussians changed.
    pub field_persistence: Option<[f64; 2]>,
}

/// The refinement's moves as a field on the velocity grid and how to project it, for
/// [`RefineMoves::flow_share`].
struct MoveField<'a> {
    /// At each cell the mass-weighted mean move around it, world units, `[nx, ny, nz, 3]`.
    field: Tensor<4>,
    grid: &'a GridSpec,
    projection: ProjectionOptions,
}

impl MoveField<'_> {
    /// `values`, this field read back, and the part the exact projection keeps, both in
    /// cells (projected in world units: the divergence is the world's).
    fn split(&self, values: Vec<f32>) -> RefineMoveField {
        let mut flow = values.clone();
        project_direct(self.grid, &mut flow, &self.projection);
        let in_cells = |values| per_axis(values, self.grid, |x, cell| x / cell);
        RefineMoveField {
            moves: in_cells(values),
            flow: in_cells(flow),
        }
    }
}

/// `values` (rows of 3, one per cell) with `f(value, cell size along its axis)` applied to
/// each: world lengths to cells and back.
fn per_axis(mut values: Vec<f32>, grid: &GridSpec, f: impl Fn(f32, f32) -> f32) -> Vec<f32> {
    let cell = grid.cell_size().to_array();
    values
        .chunks_exact_mut(3)
        .for_each(|u| u.iter_mut().zip(cell).for_each(|(x, c)| *x = f(*x, c)));
    values
}

/// `1 / cell size` per axis, `[3]`: world lengths to cell lengths.
fn cells_per_world_unit(grid: &GridSpec, device: &Device) -> Tensor<1> {
    let cell = grid.cell_size();
    Tensor::<1>::from_data(
        TensorData::new(vec![1.0 / cell.x, 1.0 / cell.y, 1.0 / cell.z], [3]),
        device,
    )
}

/// 1 for each of `n` rows listed in `rows`, 0 for the others.
fn marked_rows(n: usize, rows: &[usize]) -> Vec<f32> {
    let mut marked = vec![0.0; n];
    for &i in rows {
        marked[i] = 1.0;
    }
    marked
}

/// One frame's refinement moves (in cells), their grid-scale parts and their field, kept for
/// the next frame's [`RefineMoves::persistence`] and [`RefineMoves::field_persistence`].
#[derive(Debug, Clone)]
struct FrameMoves {
    moves: Tensor<2>,
    grid_part: Tensor<2>,
    field: RefineMoveField,
}

/// [`RefineMoves`] of `moves` (`[n, 3]`, in cells), against the frame before's where there
/// is one, leaving out the rows `jumped` marks (`[n]`, 1 for a row that jumped), in one read.
/// `field` is the same moves' grid-scale field in world units (its grid part is sampled
/// from it), read with the rest and projected on the host (a device solve would read its
/// residuals). Returns the frame's moves too, for the next frame.
fn refine_moves(
    scale: &GridScale,
    moves: Tensor<2>,
    before: Option<&FrameMoves>,
    jumped: &Tensor<1>,
    field: &MoveField,
) -> (RefineMoves, FrameMoves) {
    let [n, _] = moves.dims();
    let field_before = before.map(|b| &b.field);
    // A stride coprime to n shuffles the rows deterministically.
    let stride = [7919usize, 7927, 7933, 7937]
        .into_iter()
        .find(|p| n % p != 0)
        .unwrap_or(1);
    let order: Vec<i64> = (0..n).map(|i| ((i * stride) % n.max(1)) as i64).collect();
    let order = Tensor::<1, Int>::from_data(TensorData::new(order, [n]), &moves.device());
    let shuffled = moves.clone().select(0, order);
    let per_cell = cells_per_world_unit(field.grid, &moves.device()).reshape([1, 3]);
    let cells = field.grid.num_cells();
    let grid_part = scale.sampled(field.field.clone().reshape([cells, 3]) * per_cell);
    let mut parts = vec![
        scale.mean_square(moves.clone()),
        scale.mean_square(grid_part.clone()),
        scale.mean_square(shuffled.clone()),
        scale.mean_square(scale.grid_part(shuffled)),
    ];
    let before = before.filter(|b| b.moves.dims() == [n, 3]);
    if let Some(before) = before {
        // Weighted dot products from mean squares: a.b = (|a + b|^2 - |a - b|^2) / 4.
        let kept = (jumped.clone().neg() + 1.0).reshape([n, 1]);
        for (now, then) in [
            (moves.clone(), before.moves.clone()),
            (grid_part.clone(), before.grid_part.clone()),
        ] {
            let (now, then) = (now * kept.clone(), then * kept.clone());
            parts.extend([
                scale.mean_square(now.clone() + then.clone()),
                scale.mean_square(now.clone() - then.clone()),
                scale.mean_square(now),
                scale.mean_square(then),
            ]);
        }
    }
    let scalars = parts.len();
    let field_len = field.field.shape().num_elements();
    parts.push(field.field.clone().reshape([field_len]));
    let mut v = read_floats(Tensor::cat(parts, 0));
    let field = field.split(v.split_off(scalars));
    let share = |part: f32, whole: f32| {
        if whole > 0.0 {
            (part / whole) as f64
        } else {
            0.0
        }
    };
    let weighted_correlation = |w: &[f32]| {
        let norms = (w[2] as f64 * w[3] as f64).sqrt();
        if norms > 0.0 {
            (w[0] as f64 - w[1] as f64) / 4.0 / norms
        } else {
            0.0
        }
    };
    let persistence = (scalars == 12).then(|| {
        [
            weighted_correlation(&v[4..8]),
            weighted_correlation(&v[8..12]),
        ]
    });
    (
        RefineMoves {
            rms_cells: (v[0] as f64).sqrt(),
            grid_share: share(v[1], v[0]),
            shuffled_grid_share: share(v[3], v[2]),
            persistence,
            flow_share: field.flow_share(),
            field_persistence: field_before.map(|b| field.persistence(b)),
        },
        FrameMoves {
            moves,
            grid_part,
            field,
        },
    )
}

/// Reads `log` (and `tail` with it), appends its rows to `losses` and shows the last one on
/// `bar`; returns `tail`'s values.
fn read_log(
    log: &mut StepLog,
    losses: &mut Vec<LossRow>,
    bar: &ProgressBar,
    tail: Option<Tensor<1>>,
) -> Result<Vec<f32>, TrainError> {
    let flushed = log.flush(tail)?;
    // The steps' deferred projection solves are judged with their losses.
    let solves = settle_deferred_solves();
    if solves.unconverged > 0 {
        tracing::warn!(
            unconverged = solves.unconverged,
            of = solves.solves,
            worst_relative_residual = solves.worst_relative_residual,
            "projection solves ran out of their iteration budget before converging (the next \
             budgets are raised from what they needed)"
        );
    }
    if let Some(row) = flushed.rows.last() {
        bar.set_message(match row.phase {
            Phase::Statics | Phase::Init => format!("L1 {:.5}", row.render),
            Phase::Advect => format!(
                "L1 {:.5} div {:.2e} adv {:.2e}",
                row.render, row.divergence, row.advection
            ),
            Phase::Refine => format!("L1 {:.5} refine {:.2e}", row.render, row.refine),
        });
    }
    losses.extend(flushed.rows);
    Ok(flushed.tail)
}

/// Fewest entries a tile-list buffer is given, so that a view with almost nothing in it at
/// the loop's first step still has room when the smoke moves in.
const MIN_TILE_LIST_CAPACITY: u32 = 4096;

/// The tile-list buffer sizes of one loop's renders of one set of views (one per view), so
/// that no GPU render reads its list length back: measured (one read for all the views) at the
/// loop's first step and again after each read of the loop's log, so they follow the
/// Gaussians as they grow or move (frame 0's fit changes them most), and given `headroom`;
/// every step checks on the device, with its other checks, that its renders had room (see
/// [`InputCheck::with_list_capacities`]).
struct ListCapacities {
    headroom: f32,
    views: Option<Vec<u32>>,
}

impl ListCapacities {
    fn new(headroom: f32) -> Self {
        Self {
            headroom,
            views: None,
        }
    }

    /// The next step measures again.
    fn expire(&mut self) {
        self.views = None;
    }

    /// The capacities, measured from `lengths` (`[views]`, on the device) on the first call
    /// after [`ListCapacities::new`] or [`ListCapacities::expire`]; none above `most`, the
    /// length if every Gaussian touched every tile.
    fn for_lengths(&mut self, lengths: &Tensor<1>, most: &[u64]) -> Vec<u32> {
        let headroom = self.headroom as f64;
        self.views
            .get_or_insert_with(|| {
                read_floats_for(lengths.clone(), ReadKind::TileListLength)
                    .into_iter()
                    .zip(most)
                    .map(|(length, &most)| {
                        let room = (length as f64 * headroom).ceil() as u64;
                        let room = room.max(u64::from(MIN_TILE_LIST_CAPACITY)).min(most);
                        u32::try_from(room).unwrap_or(u32::MAX)
                    })
                    .collect()
            })
            .clone()
    }
}

/// One Adam step per attribute of `model` with its own learning rate (0 skips it), the
/// gradients taken from `grads`; every log-scale ends within `log_scale_bounds`.
fn adam_per_attribute(
    model: GaussianModel,
    optim: &mut ModuleOptimizer,
    grads: &mut Gradients,
    learning_rates: Gaussians<f64>,
    log_scale_bounds: [f32; 2],
) -> GaussianModel {
    let per_attribute = attribute_params(grads, &model);
    adam_on_attributes(
        model,
        optim,
        per_attribute,
        learning_rates,
        log_scale_bounds,
    )
}

/// [`adam_per_attribute`] on gradients already taken out, one [`GradientsParams`] per
/// attribute.
fn adam_on_attributes(
    mut model: GaussianModel,
    optim: &mut ModuleOptimizer,
    grads: Gaussians<GradientsParams>,
    learning_rates: Gaussians<f64>,
    log_scale_bounds: [f32; 2],
) -> GaussianModel {
    let steps = model
        .param_ids()
        .zip(learning_rates)
        .zip(grads)
        .into_array();
    for ((_, lr), params) in steps {
        if lr > 0.0 && !params.is_empty() {
            let _phase = phase!("optimizer");
            model = optim.step(lr, model, params);
        }
    }
    model.clamped(log_scale_bounds)
}

/// Which Gaussians a fit to still images trains (see [`Trainer::fit_to_images`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum StillFit {
    /// The static Gaussians alone, before frame 0.
    Statics,
    /// Frame 0's smoke, in front of the (fixed) static Gaussians.
    FirstFrame,
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
    /// The last frame's refinement moves, for the next frame's persistence (not saved:
    /// a resumed run reports none at its first frame).
    last_moves: Option<FrameMoves>,
    /// The largest share of the still prediction's loss any frame's carrier has removed so
    /// far (`carrier_share = "explained_of_best"`); a resumed run takes it from its reports.
    pub best_explained: f32,
    quiet: bool,
    /// Frame 0's fit is done (or a checkpoint was loaded): the Gaussians step as the frames
    /// after it do (`relative_adam_epsilon`).
    past_first_frame: bool,
}

/// A frame's cameras and the images they saw, as the render losses take them.
type ViewTargets = (Vec<Camera>, Vec<Tensor<3>>);

/// The views of `group` (indices into `views`), in its order.
fn views_of(group: &[usize], (cameras, targets): (&[Camera], &[Tensor<3>])) -> ViewTargets {
    group
        .iter()
        .map(|&v| (cameras[v], targets[v].clone()))
        .unzip()
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
    /// A trainer at the start of Algorithm 1 (fresh, seeded state).
    pub fn new(
        sequence: Sequence,
        config: TrainConfig,
        device: Device,
    ) -> Result<Self, TrainError> {
        config.validate()?;
        let views = sequence.train.first().map_or(0, Vec::len);
        if config.refine_views_per_step > views {
            return Err(TrainError::Config {
                origin: "configuration".into(),
                reason: format!(
                    "refine_views_per_step is {} but the data set has {views} training views \
                     (0 renders all of them)",
                    config.refine_views_per_step
                ),
            });
        }
        if config.refine_held_view != HeldView::Off {
            let fitted = views.saturating_sub(1);
            if fitted == 0 || config.refine_views_per_step > fitted {
                return Err(TrainError::Config {
                    origin: "configuration".into(),
                    reason: format!(
                        "refine_held_view holds one of the data set's {views} training views \
                         back from the refinement, which leaves {fitted} to fit, and \
                         refine_views_per_step is {}: it needs two views or more, and at most \
                         {fitted} a step",
                        config.refine_views_per_step
                    ),
                });
            }
        }
        if config.velocity_from_ground_truth && sequence.ground_truth.is_none() {
            return Err(TrainError::Config {
                origin: "configuration".into(),
                reason: "velocity_from_ground_truth needs a data set with ground truth \
                         (gt/frame_TTT.safetensors, as the synthetic scenes have)"
                    .into(),
            });
        }
        // Each frame reports its loops' kernel launches (no-op without a cube backend).
        gausmoke_render::device_traffic::count_launches();
        let grid = config.grid(sequence.lo, sequence.hi)?;
        let background =
            Tensor::<1>::from_data(TensorData::new(sequence.background.to_vec(), [3]), &device);
        let raster = config.raster_options();
        let solids = solid_cells(&sequence.obstacles, &config, &grid)?;
        let mut state = fresh_state(&sequence, &config, &grid, &device);
        if let Some(path) = &config.init_gaussians {
            state.gaussians = warm_start(path, config.gaussians, &device)?;
        }
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
            best_explained: 0.0,
            quiet: false,
            past_first_frame: false,
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

    /// A fresh state of this trainer's shape for a checkpoint to be loaded into. Every
    /// checkpoint is written after a frame, so its Gaussians' optimizer is the one the frames
    /// after frame 0 step with.
    pub fn fresh_state_for_resume(&self) -> TrainState {
        TrainState {
            gaussian_optim: frame_gaussian_optimizer(&self.config),
            ..fresh_state(&self.sequence, &self.config, &self.grid, &self.device)
        }
    }

    /// Takes the state a checkpoint held (see [`Trainer::fresh_state_for_resume`]): the
    /// Gaussians step from now on as they do past frame 0.
    pub fn restore(&mut self, state: TrainState) {
        self.state = state;
        self.past_first_frame = true;
    }

    fn interpolation(&self) -> Interpolation {
        match self.config.interpolation {
            InterpolationKind::Gaussian => Interpolation::default(),
            InterpolationKind::Trilinear => Interpolation::Trilinear,
        }
    }

    /// `means` carried one step of `dt` by `velocity`, with the configured integrator and
    /// interpolation: how the trainer moves Gaussians from frame to frame.
    fn carry(&self, velocity: &Tensor<4>, means: &Tensor<2>) -> Advected {
        advect(
            &self.grid,
            velocity,
            means,
            self.config.dt,
            self.integrator(),
            self.interpolation(),
        )
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
            // Validated with the configuration.
            open_faces: self.config.open_faces().unwrap_or_default(),
            solids: self.solids.clone(),
            // Deferred solves are judged when the steps' losses are read (`read_log`).
            convergence_tests: self.config.solver_tests.into(),
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

    /// The mean over the grid's cells of `|field|^2`, the field in cells per frame.
    fn mean_square_in_cells(&self, field: Tensor<4>) -> Tensor<1> {
        let in_cells = self.cells_per_world_unit().reshape([1, 1, 1, 3]);
        (field * in_cells).powi_scalar(2).sum_dim(3).mean()
    }

    /// `lambda_increment` times the mean square of Phi's increment `delta` in cells per frame
    /// (its horizontal components weighted by `increment_horizontal_weight`), less what a
    /// multiple of the density `sigma` explains in its upward component with
    /// `buoyancy_free_increment`.
    fn inertia_prior(&self, delta: Tensor<4>, sigma: Tensor<3>) -> Tensor<1> {
        let counted = if self.config.buoyancy_free_increment {
            without_buoyancy(delta, sigma)
        } else {
            delta
        };
        let cell = self.grid.cell_size();
        let across = self.config.increment_horizontal_weight.sqrt();
        let weights = Tensor::<1>::from_data(
            TensorData::new(vec![across / cell.x, 1.0 / cell.y, across / cell.z], [3]),
            &self.device,
        );
        (counted * weights.reshape([1, 1, 1, 3]))
            .powi_scalar(2)
            .sum_dim(3)
            .mean()
            * self.config.lambda_increment
    }

    /// `1 / cell size` per axis, `[3]`: world lengths to cell lengths.
    fn cells_per_world_unit(&self) -> Tensor<1> {
        cells_per_world_unit(&self.grid, &self.device)
    }

    /// One optimizer step of Phi on the gradients of a loss.
    fn step_phi(&mut self, grads: &mut Gradients, lr: f64) {
        let phi_grads = GradientsParams::from_module(grads, &self.state.phi);
        let phi = self.state.phi.clone();
        self.state.phi = {
            let _phase = phase!("optimizer");
            self.state.phi_optim.step(lr, phi, phi_grads)
        };
    }

    fn step_buoyancy(&mut self, grads: &mut Gradients, lr: f64) {
        let Some(buoyancy) = self.state.buoyancy.as_mut() else {
            return;
        };
        let force_grads = GradientsParams::from_module(grads, &buoyancy.force);
        let force = buoyancy.force.clone();
        buoyancy.force = {
            let _phase = phase!("optimizer");
            buoyancy.optim.step(lr, force, force_grads)
        };
    }

    /// The velocity before `Pi`: `previous` plus Phi's increment `delta`, plus the explicit
    /// buoyancy force over one frame on `density` (`buoyancy_force`).
    fn unprojected_update(
        &self,
        previous: Tensor<4>,
        delta: Tensor<4>,
        density: Tensor<3>,
    ) -> Tensor<4> {
        match &self.state.buoyancy {
            Some(buoyancy) => previous + delta + buoyancy.force.velocity_change(density),
            None => previous + delta,
        }
    }

    /// The velocity Phi predicts at `time` from `velocity` and the density of `gaussians`
    /// (not differentiated through), projected: one step of Eq. 9 with no fitting.
    fn predicted_velocity(
        &self,
        velocity: Tensor<4>,
        gaussians: &GaussianTensors,
        time: f32,
    ) -> Result<Tensor<4>, TrainError> {
        let sigma = self
            .splat_density(gaussians, SplatOptions::default().cutoff)
            .detach();
        let delta = self
            .state
            .phi
            .forward(velocity.clone(), sigma.clone(), time)?;
        Ok(self.project(self.unprojected_update(velocity, delta, sigma)))
    }

    /// Of the moves from `previous` to `carried` scaled by each of `shares`, the share whose
    /// render is closest to `targets` (mean L1; the smaller share on a tie), and every share's
    /// loss (one read).
    fn best_carried_share(
        &self,
        previous: &Tensor<2>,
        carried: &Tensor<2>,
        shares: &[f32],
        cameras: &[Camera],
        targets: &[Tensor<3>],
    ) -> Result<(f32, Vec<f32>), TrainError> {
        let mut lists = ListCapacities::new(self.config.tile_list_headroom);
        let whole_move = carried.clone() - previous.clone();
        let losses = shares
            .iter()
            .map(|&share| {
                let means = previous.clone() + whole_move.clone() * share;
                let gaussians = self.scene(self.state.gaussians.tensors_at(means), false);
                Ok(self
                    .render_loss(&gaussians.detach(), cameras, targets, &mut lists)?
                    .0
                    .detach())
            })
            .collect::<Result<Vec<_>, TrainError>>()?;
        let losses = read_floats(Tensor::cat(losses, 0));
        let best = losses
            .iter()
            .zip(shares)
            .min_by(|a, b| a.0.total_cmp(b.0))
            .map(|(_, &share)| share)
            .expect("several shares");
        Ok((best, losses))
    }

    /// The explicit buoyancy force's coefficient (one read), if there is one.
    fn buoyancy_coefficient(&self) -> Option<f64> {
        self.state
            .buoyancy
            .as_ref()
            .map(|b| read_scalar(b.force.coefficient.val()) as f64)
    }

    /// What the configured `Pi` does to `velocity` (for the frame's metrics).
    fn projection_report(&self, velocity: Tensor<4>) -> ProjectionReport {
        match self.config.projection {
            ProjectionKind::Exact => {
                project_direct(&self.grid, &mut read_floats(velocity), &self.projection())
            }
            ProjectionKind::Penalty => {
                penalty_projection_with_report(&self.grid, velocity, &self.penalty()).1
            }
        }
    }

    /// Mean L1 of the Gaussians' renders from `cameras` against `targets`, their tile-list
    /// buffers sized by `lists`.
    fn render_loss(
        &self,
        gaussians: &GaussianTensors,
        cameras: &[Camera],
        targets: &[Tensor<3>],
        lists: &mut ListCapacities,
    ) -> Result<(Tensor<1>, InputCheck), TrainError> {
        self.render_loss_blurred(gaussians, cameras, targets, lists, None)
    }

    /// `render_loss`, each view's residual blurred first by the matching entry of `blurs`
    /// when given (`refine_loss_blur`, `joint_loss_blur`).
    fn render_loss_blurred(
        &self,
        gaussians: &GaussianTensors,
        cameras: &[Camera],
        targets: &[Tensor<3>],
        lists: &mut ListCapacities,
        blurs: Option<&[ResidualBlur]>,
    ) -> Result<(Tensor<1>, InputCheck), TrainError> {
        let lengths = list_buffer_lengths(gaussians, cameras, &self.raster);
        let most: Vec<u64> = cameras
            .iter()
            .map(|c| {
                let tiles =
                    c.width().div_ceil(TILE_SIZE as u32) * c.height().div_ceil(TILE_SIZE as u32);
                (gaussians.len() as u64 * u64::from(tiles)).max(1)
            })
            .collect();
        let capacities = lists.for_lengths(&lengths, &most);
        // Every view renders the same Gaussians: one check covers them.
        let check = InputCheck::new(gaussians, &self.background)?
            .with_list_capacities(lengths, capacities.clone())?;
        let mut total: Option<Tensor<1>> = None;
        for (view, ((camera, target), capacity)) in
            cameras.iter().zip(targets).zip(capacities).enumerate()
        {
            let options = RasterOptions {
                tile_list_capacity: Some(capacity),
                ..self.raster
            };
            let out =
                render_volume_deferred(gaussians, camera, &self.background, &options, &check)?;
            let residual = out.rgb - target.clone();
            let residual = match blurs {
                Some(blurs) => blurs[view].apply(residual),
                None => residual,
            };
            let l1 = residual.abs().mean();
            total = Some(match total {
                Some(t) => t + l1,
                None => l1,
            });
        }
        Ok((
            total.expect("at least one training view") / cameras.len() as f32,
            check,
        ))
    }

    /// A joint iteration's render loss of the carried Gaussians `next`, each view's residual
    /// blurred by the matching entry of `blurs` when given (`joint_loss_blur`). With
    /// `joint_loss_blur_velocity_only` the same state is rendered twice: the carrier's
    /// gradient comes through the blurred residual and the Gaussians' own attributes' through
    /// the plain one, returned third (the first stays the loss that is logged).
    fn joint_render_loss(
        &self,
        next: &GaussianTensors,
        cameras: &[Camera],
        targets: &[Tensor<3>],
        lists: &mut ListCapacities,
        blurs: Option<&[ResidualBlur]>,
    ) -> Result<(Tensor<1>, InputCheck, Option<Tensor<1>>), TrainError> {
        match blurs {
            Some(blurs) if self.config.joint_loss_blur_velocity_only => {
                let carried = Gaussians {
                    means: next.means.clone(),
                    ..next.clone().detach()
                };
                let placed = Gaussians {
                    means: next.means.clone().detach(),
                    ..next.clone()
                };
                let scene = self.scene(carried, false);
                let (render, check) =
                    self.render_loss_blurred(&scene, cameras, targets, lists, Some(blurs))?;
                let scene = self.scene(placed, true);
                let (appearance, _) = self.render_loss(&scene, cameras, targets, lists)?;
                Ok((render, check, Some(appearance)))
            }
            _ => {
                let scene = self.scene(next.clone(), true);
                let (render, check) =
                    self.render_loss_blurred(&scene, cameras, targets, lists, blurs)?;
                Ok((render, check, None))
            }
        }
    }

    /// What the renders composite: the smoke Gaussians `smoke` (in their mean colour with
    /// `uniform_color`) and, when there are any, the static ones after them, tracked for
    /// their optimiser when `learn_statics`.
    fn scene(&self, smoke: GaussianTensors, learn_statics: bool) -> GaussianTensors {
        let smoke = if self.config.uniform_color {
            Gaussians {
                colors: uniform_color(smoke.colors),
                ..smoke
            }
        } else {
            smoke
        };
        match &self.state.statics {
            Some(statics) => {
                let fixed = statics.gaussians.tensors();
                let fixed = if learn_statics { fixed } else { fixed.detach() };
                smoke.concat(fixed)
            }
            None => smoke,
        }
    }

    /// One Adam step of the static Gaussians' shape, density and colour at `lr`, if there are
    /// any. Their centres stay where their own fit put them: Adam moves every parameter by
    /// about `lr` per step whatever its gradient, which would make a still object jitter.
    fn step_statics(&mut self, grads: &mut Gradients, lr: f64) {
        let Some(statics) = &mut self.state.statics else {
            return;
        };
        statics.gaussians = adam_per_attribute(
            statics.gaussians.clone(),
            &mut statics.optim,
            grads,
            Gaussians {
                means: 0.0,
                rotations: lr,
                log_scales: lr,
                raw_densities: lr,
                colors: lr,
            },
            NO_SIZE_BOUNDS,
        );
    }

    /// Fits the static Gaussians alone to the training views' per-pixel minimum over the
    /// loaded frames: smoke only adds light (emission over what it attenuates), so the minimum
    /// is what each pixel shows when the smoke in front of it is thinnest, the static scene
    /// wherever smoke is absent at least once. Frame 0's settings (iterations, learning rates).
    fn fit_statics(&mut self) -> Result<Vec<LossRow>, TrainError> {
        if self.state.statics.is_none() {
            return Ok(Vec::new());
        }
        let observations = self.sequence.train[0].clone();
        let targets: Vec<Tensor<3>> = (0..observations.len())
            .map(|view| {
                let mut least = observations[view].image.data().to_vec();
                for frame in &self.sequence.train[1..] {
                    for (l, v) in least.iter_mut().zip(frame[view].image.data()) {
                        *l = l.min(*v);
                    }
                }
                let image = &observations[view].image;
                Tensor::from_data(
                    TensorData::new(least, [image.height() as usize, image.width() as usize, 3]),
                    &self.device,
                )
            })
            .collect();
        self.fit_to_images(StillFit::Statics, &observations, &targets)
    }

    /// `init_iterations` steps (`static_iterations` for the statics) of `L_render` against
    /// the still images `targets` of `observations`' cameras, every attribute learning at
    /// frame 0's rates.
    fn fit_to_images(
        &mut self,
        fit: StillFit,
        observations: &[Observation],
        targets: &[Tensor<3>],
    ) -> Result<Vec<LossRow>, TrainError> {
        let mut learning_rates = self.init_learning_rates();
        if fit == StillFit::Statics && !self.sequence.obstacles.is_empty() {
            // Placed where the data set says the solids are: they stay there.
            learning_rates.means = 0.0;
        }
        let iterations = match fit {
            StillFit::Statics => self
                .config
                .static_iterations
                .unwrap_or(self.config.init_iterations),
            StillFit::FirstFrame => self.config.init_iterations,
        };
        let bar = self.progress(0, iterations);
        let phase = match fit {
            StillFit::Statics => {
                bar.set_prefix("statics");
                Phase::Statics
            }
            StillFit::FirstFrame => Phase::Init,
        };
        let mut losses = Vec::with_capacity(iterations);
        let mut log = StepLog::new(self.config.log_every);
        let mut lists = ListCapacities::new(self.config.tile_list_headroom);
        let cameras: Vec<Camera> = observations.iter().map(|o| o.camera).collect();
        for iteration in 0..iterations {
            let gaussians = match (fit, &self.state.statics) {
                (StillFit::Statics, Some(statics)) => statics.gaussians.tensors(),
                _ => self.scene(self.state.gaussians.tensors(), false),
            };
            let (loss, check) = self.render_loss(&gaussians, &cameras, targets, &mut lists)?;
            log.push(
                (0, phase, iteration),
                StepLosses {
                    total: loss.clone(),
                    render: loss.clone(),
                    divergence: None,
                    advection: None,
                    refine: None,
                },
                None,
                vec![check],
            );
            let mut grads = {
                let _phase = phase!("backward (all ops)");
                loss.backward()
            };
            match (fit, &mut self.state.statics) {
                (StillFit::Statics, Some(statics)) => {
                    statics.gaussians = adam_per_attribute(
                        statics.gaussians.clone(),
                        &mut statics.optim,
                        &mut grads,
                        learning_rates,
                        NO_SIZE_BOUNDS,
                    );
                }
                // Frame 0 fits with no size bounds (`min_size_factor`, `max_size_factor`).
                _ => self.step_gaussians(&mut grads, learning_rates, NO_SIZE_BOUNDS),
            }
            if log.due() || iteration + 1 == iterations {
                read_log(&mut log, &mut losses, &bar, None)?;
                lists.expire();
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        Ok(losses)
    }

    /// Frame 0's learning rates per attribute (the centres' scaled by the box's extent).
    fn init_learning_rates(&self) -> Gaussians<f64> {
        let rates = &self.config.init_learning_rates;
        let extent = (self.sequence.hi - self.sequence.lo).max_element() as f64;
        Gaussians {
            means: rates.means * extent,
            rotations: rates.rotations,
            log_scales: rates.log_scales,
            raw_densities: rates.raw_densities,
            colors: rates.colors,
        }
    }

    /// One Adam step per Gaussian attribute, each with its own learning rate (0 skips it).
    fn step_gaussians(
        &mut self,
        grads: &mut Gradients,
        learning_rates: Gaussians<f64>,
        log_scale_bounds: [f32; 2],
    ) {
        let per_attribute = attribute_params(grads, &self.state.gaussians);
        self.step_gaussians_with(per_attribute, learning_rates, log_scale_bounds);
    }

    /// [`Trainer::step_gaussians`] on gradients already taken out, one per attribute.
    fn step_gaussians_with(
        &mut self,
        grads: Gaussians<GradientsParams>,
        learning_rates: Gaussians<f64>,
        log_scale_bounds: [f32; 2],
    ) {
        let grads = if self.past_first_frame && self.config.relative_adam_epsilon > 0.0 {
            grads_over_their_rms(grads, &self.state.gaussians)
        } else {
            grads
        };
        self.state.gaussians = adam_on_attributes(
            self.state.gaussians.clone(),
            &mut self.state.gaussian_optim,
            grads,
            learning_rates,
            log_scale_bounds,
        );
        if self.config.uniform_color {
            // Every row holds the colour that renders (exports, checkpoints, novel views).
            self.state.gaussians = self.state.gaussians.clone().with_uniform_color();
        }
        // Only a step that moved the centres can have moved one into an obstacle.
        if learning_rates.means > 0.0 {
            self.keep_out_of_obstacles();
        }
    }

    /// Strains and turns each Gaussian's shape by a step `dt` of `velocity` read at `from`,
    /// its centre before the step (`shape_transport`; see [`gausmoke_model::deform`]); the
    /// rows born this frame, which the carrier did not move, keep theirs.
    fn carry_shapes(
        &mut self,
        velocity: &Tensor<4>,
        from: &Tensor<2>,
        dt: f32,
        born: &[usize],
        [lowest, highest]: [f32; 2],
    ) {
        let _phase = phase!("shape transport");
        let sample = sample_velocity(&self.grid, velocity, from, self.interpolation());
        let jacobians = read_floats(sample.jacobian);
        // 0 sets no bound.
        let max_elongation = match self.config.shape_transport_max_elongation {
            bound if bound > 0.0 => bound,
            _ => f32::INFINITY,
        };
        // Only the shapes change: the other attributes stay on the device.
        let current = self.state.gaussians.tensors();
        let mut rotations = read_floats(current.rotations.clone());
        let mut log_scales = read_floats(current.log_scales.clone());
        let n = self.state.gaussians.len();
        let born = marked_rows(n, born);
        let rows = (0..n).filter(|&row| born[row] == 0.0);
        let kept = deform_shapes(
            &mut rotations,
            &mut log_scales,
            &jacobians,
            dt,
            max_elongation,
            rows,
        );
        for value in &mut log_scales {
            *value = value.clamp(lowest, highest);
        }
        if kept > 0 {
            tracing::warn!(
                kept,
                "shape transport: steps too large for these Gaussians, their shapes kept"
            );
        }
        let upload = |values: Vec<f32>, width: usize| {
            Tensor::<2>::from_data(TensorData::new(values, [n, width]), &self.device)
        };
        let shapes = Gaussians {
            rotations: upload(rotations, 4),
            log_scales: upload(log_scales, 3),
            ..current
        };
        self.state.gaussians = self.state.gaussians.clone().with_values(shapes);
    }

    /// `velocity` smoothed by a Gaussian of `cells` grid cells along every axis
    /// (`velocity_smoothing_cells`), weights renormalised at the walls.
    fn smoothed_velocity(&self, velocity: Tensor<4>, cells: f32) -> Tensor<4> {
        let _phase = phase!("velocity smoothing");
        let resolution = self.grid.resolution();
        let values = smoothed(&read_floats(velocity), resolution, 3, cells, [true; 3]);
        let [nx, ny, nz] = resolution;
        Tensor::from_data(TensorData::new(values, [nx, ny, nz, 3]), &self.device)
    }

    /// Moves the Gaussians whose centre lies inside a solid obstacle onto its surface: smoke
    /// has no business there, and the velocity, zero inside, would never carry it out.
    fn keep_out_of_obstacles(&mut self) {
        if self.solids.is_none() {
            return;
        }
        let means = self.state.gaussians.means.val().detach();
        let outside = outside_obstacles(means, &self.sequence.obstacles);
        self.state.gaussians = self.state.gaussians.clone().with_means(outside);
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
        bar.set_prefix(format!("frame {frame}/{}", self.sequence.frames() - 1));
        bar
    }

    /// Frame `t` of Algorithm 1: the static fit for frame 0, else the step from `t - 1`.
    pub fn train_frame(&mut self, t: usize) -> Result<FrameOutcome, TrainError> {
        if t == 0 {
            self.fit_first_frame()
        } else {
            self.advance_to(t)
        }
    }

    /// Frame 0: a static fit with per-attribute learning rates.
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
        if self.config.gaussian_optimizer_reset == OptimizerReset::AfterFirstFrame
            || self.config.relative_adam_epsilon > 0.0
        {
            self.state.gaussian_optim = frame_gaussian_optimizer(&self.config);
        }
        self.past_first_frame = true;
        Ok(FrameOutcome {
            frame: 0,
            train_l1: losses.last().map_or(f32::NAN, |r| r.render) as f64,
            losses,
            projection: None,
            clamped_to_box: 0,
            respawned: 0,
            emitted: 0,
            split: 0,
            refine_moves: None,
            refine_move_field: None,
            traffic,
            buoyancy: self.buoyancy_coefficient(),
            carrier_share: None,
            carrier_explained: None,
            held_view: None,
            held_out_trace: Vec::new(),
        })
    }

    /// Frames `t-1 -> t`: K joint iterations, then K' refinement iterations.
    pub fn advance_to(&mut self, t: usize) -> Result<FrameOutcome, TrainError> {
        let config = self.config.clone();
        if config.gaussian_optimizer_reset == OptimizerReset::EveryFrame {
            self.state.gaussian_optim = frame_gaussian_optimizer(&config);
        }
        if config.carried_smoothing > 0.0 {
            self.smooth_carried(t);
        }
        if config.carried_growth > 0.0 {
            self.grow_carried();
        }
        let (cameras, targets) = self.training_views(t);
        let factor = config.lr_factor(t);
        let lr_velocity = config.lr_velocity * factor;
        let lr_gaussians = config.lr_gaussians * factor;
        // The Gaussians' rates after frame 0; the centres' applies to the refinement alone,
        // the joint iterations leave them to the advection.
        let own_or_shared = |own: Option<f64>| own.map_or(lr_gaussians, |lr| lr * factor);
        let rates = Gaussians {
            means: own_or_shared(config.lr_means),
            log_scales: own_or_shared(config.lr_log_scales),
            colors: own_or_shared(config.lr_colors),
            raw_densities: own_or_shared(config.lr_raw_densities),
            ..Gaussians::default().map(|_, ()| lr_gaussians)
        };
        // The count is fixed, so the bounds hold for the whole frame.
        let log_scale_bounds = self.log_scale_bounds();
        let last_frame = (self.sequence.frames() - 1).max(1) as f32;
        let time = t as f32 / last_frame;
        let previous_velocity = if config.transport_velocity {
            let _phase = phase!("velocity transport");
            transport_velocity(&self.grid, &self.state.velocity.clone().detach(), config.dt)
        } else {
            self.state.velocity.clone().detach()
        };
        let previous_velocity = if config.velocity_smoothing_cells > 0.0 {
            self.smoothed_velocity(previous_velocity, config.velocity_smoothing_cells)
        } else {
            previous_velocity
        };
        let splat = SplatOptions::default();
        let refine_iterations = if config.refinement {
            config.refine_iterations
        } else {
            0
        };
        let bar = self.progress(t, config.advect_iterations + refine_iterations);
        let mut losses = Vec::with_capacity(config.advect_iterations + refine_iterations);
        // The next frames' training views, for the look-ahead terms.
        let ahead_frames = if config.lambda_lookahead > 0.0 {
            config.lookahead_frames.min(self.sequence.frames() - 1 - t)
        } else {
            0
        };
        let ahead: Vec<ViewTargets> = (t + 1..=t + ahead_frames)
            .map(|frame| self.training_views(frame))
            .collect();

        // Frame t-1's density, splatted once: what the source must hold (`emission_fraction`)
        // and what the density-motion fit carries onto frame t's
        // (`velocity_from_density_motion`).
        let emitting = config.emission_fraction > 0.0;
        let frame_start_density =
            (emitting || config.velocity_from_density_motion).then(|| self.density_host());
        let density_before = frame_start_density.as_deref().filter(|_| emitting);
        let motion_before = frame_start_density
            .as_deref()
            .filter(|_| config.velocity_from_density_motion);
        let true_velocity = if config.velocity_from_ground_truth {
            Some(self.true_velocity(t)?)
        } else {
            None
        };
        // Emission before the joint iterations: the box's loss to the carrier that starts
        // the frame, born at frame t's positions and held there while the velocity is fitted.
        let born = match (density_before, config.emission_timing) {
            (Some(before), EmissionTiming::BeforeJoint) => {
                let carrier = true_velocity.as_ref().unwrap_or(&previous_velocity);
                self.emit_before_joint(t, carrier, before)
            }
            _ => EmissionReport::default(),
        };
        let previous_means = self.state.gaussians.means.val().detach();
        // `[N, 1]`: 1 on the rows born this frame, whose centres the carrier does not move.
        let born_rows = (!born.indices.is_empty()).then(|| {
            let [n, _] = previous_means.dims();
            Tensor::<2>::from_data(
                TensorData::new(marked_rows(n, &born.indices), [n, 1]),
                &self.device,
            )
        });
        let hold_born = |positions: Tensor<2>| match &born_rows {
            Some(born) => positions.clone() + (previous_means.clone() - positions) * born.clone(),
            None => positions,
        };

        // What the frame's prediction earned (`carrier_share`).
        let prediction = match config.carrier_share {
            CarrierShare::Whole | CarrierShare::Fitted => None,
            CarrierShare::Predicted | CarrierShare::Explained | CarrierShare::ExplainedOfBest => {
                let _phase = phase!("carrier share");
                let carrier = match &true_velocity {
                    Some(truth) => truth.clone(),
                    None => {
                        let previous = self.state.gaussians.tensors_at(previous_means.clone());
                        self.predicted_velocity(
                            previous_velocity.clone(),
                            &previous.detach(),
                            time,
                        )?
                        .detach()
                    }
                };
                let carried = self.carry(&carrier, &previous_means);
                let carried = hold_born(carried.positions).detach();
                let shares: &[f32] = match config.carrier_share {
                    CarrierShare::Predicted => &PREDICTED_SHARES,
                    _ => &[0.0, 1.0],
                };
                let (share, losses) =
                    self.best_carried_share(&previous_means, &carried, shares, &cameras, &targets)?;
                // The shares run from 0 (no move) to 1 (the whole predicted move).
                let (still, whole) = (losses[0], losses[losses.len() - 1]);
                let explained = if still > 0.0 {
                    (1.0 - whole / still).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                tracing::debug!(frame = t, share, explained, ?losses, "carrier share");
                Some((share, explained))
            }
        };

        // K joint iterations (Algorithm 1, lines 3-9).
        let mut velocity = previous_velocity.clone();
        let mut unprojected = previous_velocity.clone();
        let mut advected = previous_means.clone();
        let mut clamped = 0;
        let mut log = StepLog::new(config.log_every);
        let mut lists = ListCapacities::new(config.tile_list_headroom);
        let mut ahead_lists: Vec<ListCapacities> = ahead
            .iter()
            .map(|_| ListCapacities::new(config.tile_list_headroom))
            .collect();
        // The held-out views, for the diagnostic trace (`held_out_trace`).
        let held_out: Vec<(Camera, Tensor<3>)> = match self.sequence.test.get(t) {
            Some(test) if config.held_out_trace => test
                .iter()
                .map(|o| (o.camera, image_tensor(o, &self.device)))
                .collect(),
            _ => Vec::new(),
        };
        let mut held_out_trace = (!held_out.is_empty()).then(HeldOutTrace::new);
        if let Some(trace) = held_out_trace.as_mut() {
            let state = self.state.gaussians.tensors();
            self.trace_held_out(trace, (Stage::Still, 0), state, &held_out)?;
        }
        let start = Traffic::now();
        for iteration in 0..config.advect_iterations {
            let previous = self.state.gaussians.tensors_at(previous_means.clone());
            // The density and (for L_adv) its gradient, in one pass over the Gaussians.
            let (sigma_previous, gradient_previous) = if config.physics_losses {
                let (sigma, gradient) = self.splat_density_and_gradient(&previous, splat.cutoff);
                (sigma, Some(gradient))
            } else {
                (self.splat_density(&previous, splat.cutoff), None)
            };
            let delta = {
                let _phase = phase!("U-Net forward");
                self.state.phi.forward(
                    previous_velocity.clone(),
                    sigma_previous.clone().detach(),
                    time,
                )?
            };
            let update = self.unprojected_update(
                previous_velocity.clone(),
                delta.clone(),
                sigma_previous.clone(),
            );
            let projected = match &true_velocity {
                Some(truth) => truth.clone(),
                None => self.project(update.clone()),
            };
            let moved = self.carry(&projected, &previous_means);
            let positions = hold_born(moved.positions.clone());
            let next = self.state.gaussians.tensors_at(positions.clone());
            if let Some(trace) = held_out_trace.as_mut() {
                let point = (Stage::Joint, iteration);
                self.trace_held_out(trace, point, next.clone(), &held_out)?;
            }
            let sigma = coarse_to_fine(config.joint_loss_blur, iteration, config.advect_iterations);
            let blurs_of =
                |views: &[Camera]| ResidualBlur::for_views(views, sigma, false, &self.device);
            let (render, check, appearance) = self.joint_render_loss(
                &next,
                &cameras,
                &targets,
                &mut lists,
                blurs_of(&cameras).as_deref(),
            )?;
            let mut checks = vec![check];
            let mut loss = match appearance {
                Some(appearance) => render.clone() + appearance,
                None => render.clone(),
            };
            // Frames further on; only the velocity learns here, unless the Gaussians' other
            // attributes keep their gradient too (`lookahead_appearance`).
            let mut carrier = projected.clone();
            let mut carried = next.clone();
            let held = (!ahead.is_empty()).then(|| {
                if config.lookahead_appearance {
                    next.clone()
                } else {
                    self.state.gaussians.tensors().detach()
                }
            });
            for (step, ((views, ahead_targets), lists)) in
                ahead.iter().zip(ahead_lists.iter_mut()).enumerate()
            {
                if config.lookahead_velocity == LookaheadVelocity::Predicted {
                    let time = (t + 1 + step) as f32 / last_frame;
                    carrier = self.predicted_velocity(carrier, &carried, time)?;
                }
                let means = self.carry(&carrier, &carried.means).positions;
                carried = Gaussians {
                    means,
                    ..held.clone().expect("made when there are frames ahead")
                };
                let (lookahead, check) = self.render_loss_blurred(
                    &self.scene(carried.clone(), false),
                    views,
                    ahead_targets,
                    lists,
                    blurs_of(views).as_deref(),
                )?;
                checks.push(check);
                loss = loss + lookahead * config.lambda_lookahead;
            }
            if config.lambda_kinetic > 0.0 {
                let kinetic = self.mean_square_in_cells(projected.clone());
                loss = loss + kinetic * config.lambda_kinetic;
            }
            if config.lambda_increment > 0.0 {
                loss = loss + self.inertia_prior(delta, sigma_previous.clone().detach());
            }
            let mut physical = None;
            if let Some(gradient_previous) = gradient_previous {
                let divergence = divergence_loss_of(&moved.start);
                let (sigma_next, gradient_next) =
                    self.splat_density_and_gradient(&next, splat.cutoff);
                let advection = advection_loss(
                    &sigma_previous,
                    &sigma_next,
                    &gradient_previous,
                    &gradient_next,
                    &projected,
                    config.dt,
                );
                physical = Some((divergence.clone(), advection.clone()));
                loss = loss + divergence * config.lambda_div + advection * config.lambda_adv;
            }
            let (divergence, advection) = physical.unzip();
            log.push(
                (t, Phase::Advect, iteration),
                StepLosses {
                    total: loss.clone(),
                    render,
                    divergence,
                    advection,
                    refine: None,
                },
                Some((
                    "the velocity grid (max |u|)",
                    projected.clone().abs().max().reshape([1]),
                )),
                checks,
            );

            velocity = projected.clone().detach();
            unprojected = update.detach();
            advected = positions.detach();
            let left_box = moved.left_box.float().sum().reshape([1]);

            let mut grads = {
                let _phase = phase!("backward (all ops)");
                loss.backward()
            };
            self.step_phi(&mut grads, lr_velocity);
            self.step_buoyancy(&mut grads, config.lr_buoyancy * factor);
            self.step_gaussians(
                &mut grads,
                Gaussians {
                    means: 0.0,
                    ..rates
                },
                log_scale_bounds,
            );
            self.step_statics(&mut grads, lr_gaussians);
            if log.due() || iteration + 1 == config.advect_iterations {
                // The clamped count of the last step is read with its losses.
                let tail = (iteration + 1 == config.advect_iterations).then_some(left_box);
                if let Some(&count) = read_log(&mut log, &mut losses, &bar, tail)?.first() {
                    clamped = count as usize;
                }
                lists.expire();
                ahead_lists.iter_mut().for_each(ListCapacities::expire);
            }
            bar.inc(1);
        }
        let mut traffic = vec![LoopTraffic::of(
            Phase::Advect,
            config.advect_iterations,
            start,
        )];
        if config.advect_iterations == 0 {
            // No joint iterations: carry the Gaussians along the previous velocity.
            if let Some(truth) = &true_velocity {
                velocity = truth.clone();
            }
            let moved = self.carry(&velocity, &previous_means);
            advected = hold_born(moved.positions).detach();
        }

        // The share of the fitted move the refinement starts from, and its tie's factor.
        let (carrier_share, tie_factor) = match (config.carrier_share, prediction) {
            (CarrierShare::Predicted, Some((share, _))) => (Some(share), share),
            (CarrierShare::Explained, Some((_, explained))) => (None, explained),
            (CarrierShare::ExplainedOfBest, Some((_, explained))) => {
                self.best_explained = self.best_explained.max(explained);
                let best = self.best_explained;
                (None, if best > 0.0 { explained / best } else { 1.0 })
            }
            (CarrierShare::Fitted, _) => {
                let _phase = phase!("carrier share");
                let (share, losses) = self.best_carried_share(
                    &previous_means,
                    &advected,
                    &FITTED_SHARES,
                    &cameras,
                    &targets,
                )?;
                tracing::debug!(frame = t, share, ?losses, "carrier share");
                (Some(share), share.min(1.0))
            }
            _ => (None, 1.0),
        };
        let share = carrier_share.unwrap_or(1.0);
        if share != 1.0 {
            advected = previous_means.clone() + (advected - previous_means.clone()) * share;
        }
        // K' refinement iterations (lines 11-13): free centres tied to the advected ones.
        self.state.gaussians = self.state.gaussians.clone().with_means(advected);
        if config.shape_transport > 0.0 {
            let dt = config.dt * config.shape_transport * share;
            self.carry_shapes(
                &velocity,
                &previous_means,
                dt,
                &born.indices,
                log_scale_bounds,
            );
        }
        self.keep_out_of_obstacles();
        // Recycling sees the transported Gaussians against frame t: what they miss entered
        // the box (or was never fitted), and the refinement fits the recycled ones.
        let after_joint =
            density_before.filter(|_| config.emission_timing == EmissionTiming::AfterJoint);
        let renewal = self.renew_gaussians(t, after_joint, born)?;
        let (respawned, emitted, split) = (
            renewal.recycled.indices,
            renewal.emitted.indices,
            renewal.split,
        );
        // Rows that jumped here, which the velocity correction must not fit.
        let moved: Vec<usize> = [&respawned, &emitted, &split.parents, &split.children]
            .into_iter()
            .flatten()
            .copied()
            .collect();
        let anchor = self.state.gaussians.means.val().detach();
        // Detached after the log too: burn's detach keeps `require_grad`, so the log's nodes
        // would be tracked and consumed by the first step's backward.
        let density_anchor = (config.lambda_refine_density > 0.0)
            .then(|| log_density(self.state.gaussians.raw_densities.val().detach()).detach());
        // The split of the moves is fixed by where they start.
        let grid_scale = (refine_iterations > 0)
            .then(|| GridScale::of(&self.grid, &self.state.gaussians.tensors()));
        // One set of list capacities per group of views a step renders (keyed by its first).
        let mut group_lists: Vec<ListCapacities> = (0..cameras.len())
            .map(|_| ListCapacities::new(config.tile_list_headroom))
            .collect();
        // The steps whose states are averaged into the frame's result (none: the last one).
        let average_from = refine_iterations.saturating_sub(config.refine_average_steps);
        let horizontal_only = config.refine_loss_blur_axes == BlurAxes::Horizontal;
        let blurs = ResidualBlur::for_views(
            &cameras,
            config.refine_loss_blur,
            horizontal_only,
            &self.device,
        );
        let mut iterate_mean = IterateMean::new();
        // With a held view (`refine_held_view`), the refinement fits the other views and
        // checks the held one before its first step and after each turn of them.
        let mut held_checks = (config.refine_held_view != HeldView::Off && refine_iterations > 0)
            .then(|| HeldViewChecks::new(held_view(t, cameras.len())));
        let fitted = match &held_checks {
            Some(checks) => fitted_views(cameras.len(), checks.view()),
            None => (0..cameras.len()).collect(),
        };
        let turn = steps_per_turn(fitted.len(), config.refine_views_per_step);
        let mut held_lists = ListCapacities::new(config.tile_list_headroom);
        // The refinement's look-ahead: frame t+1's training views (the joint look-ahead's
        // when it has them) and the carrier to them (the frame's velocity held, or Phi's
        // prediction for frame t+1 from the refinement's starting state).
        let refine_ahead = if config.lambda_refine_lookahead > 0.0
            && refine_iterations > 0
            && t + 1 < self.sequence.frames()
        {
            let views = match ahead.first() {
                Some(next) => next.clone(),
                None => self.training_views(t + 1),
            };
            let carrier = match config
                .refine_lookahead_velocity
                .unwrap_or(config.lookahead_velocity)
            {
                LookaheadVelocity::Held => velocity.clone(),
                LookaheadVelocity::Predicted => {
                    let time = (t + 1) as f32 / last_frame;
                    let state = self.state.gaussians.tensors().detach();
                    self.predicted_velocity(velocity.clone(), &state, time)?
                        .detach()
                }
            };
            Some((views, carrier))
        } else {
            None
        };
        let mut ahead_group_lists: Vec<ListCapacities> = (0..cameras.len())
            .map(|_| ListCapacities::new(config.tile_list_headroom))
            .collect();
        let start = Traffic::now();
        if let Some(checks) = held_checks.as_mut() {
            self.check_held_view(checks, 0, (&cameras, &targets), &mut held_lists)?;
        }
        if let Some(trace) = held_out_trace.as_mut() {
            let state = self.state.gaussians.tensors();
            self.trace_held_out(trace, (Stage::Refine, 0), state, &held_out)?;
        }
        // The refinement's ties (lines 11-13 and ours): the centres to the advected ones, the
        // moves' grid-scale part, the densities; `(L_refine, the ties' weighted sum)`.
        let tie_losses = |gaussians: &GaussianTensors| {
            let refine = refine_loss(&gaussians.means, &anchor);
            let mut ties = refine.clone() * config.lambda_refine;
            if let Some(scale) = &grid_scale
                && (config.lambda_refine_grid > 0.0 || config.lambda_refine_subgrid > 0.0)
            {
                let moves = gaussians.means.clone() - anchor.clone();
                let grid_part = scale.grid_part(moves.clone());
                ties = ties
                    + scale.mean_square(grid_part.clone())
                        * (config.lambda_refine_grid * tie_factor)
                    + scale.mean_square(moves - grid_part) * config.lambda_refine_subgrid;
            }
            if let Some(density_anchor) = &density_anchor {
                ties = ties
                    + density_tie_loss(&gaussians.raw_densities, density_anchor)
                        * config.lambda_refine_density;
            }
            (refine, ties)
        };
        let masked = masked_attributes(config.refine_view_agreement_attributes);
        for iteration in 0..refine_iterations {
            if config.refine_view_agreement > 0.0 {
                // Each view's gradient on its own, kept where the views agree; the static
                // Gaussians (obstacle scenes) are held meanwhile.
                let mut per_view = Vec::with_capacity(cameras.len());
                let mut render_sum: Option<Tensor<1>> = None;
                let mut checks = Vec::with_capacity(cameras.len());
                for (view, lists) in group_lists.iter_mut().enumerate() {
                    let (render, check) = self.render_loss_blurred(
                        &self.scene(self.state.gaussians.tensors(), false),
                        &cameras[view..=view],
                        &targets[view..=view],
                        lists,
                        blurs.as_ref().map(|b| &b[view..=view]),
                    )?;
                    let mut grads = {
                        let _phase = phase!("backward (all ops)");
                        render.clone().backward()
                    };
                    per_view.push(attribute_grads(&mut grads, &self.state.gaussians));
                    let render = render.detach();
                    render_sum = Some(render_sum.map_or(render.clone(), |sum| sum + render));
                    checks.push(check);
                }
                let render = render_sum.expect("at least one training view") / cameras.len() as f32;
                let (refine, ties) = tie_losses(&self.state.gaussians.tensors());
                let mut tie_grads = {
                    let _phase = phase!("backward (all ops)");
                    ties.clone().backward()
                };
                let ties_grads = attribute_grads(&mut tie_grads, &self.state.gaussians);
                log.push(
                    (t, Phase::Refine, iteration),
                    StepLosses {
                        total: render.clone() + ties.detach(),
                        render,
                        divergence: None,
                        advection: None,
                        refine: Some(refine.detach()),
                    },
                    None,
                    checks,
                );
                let agreed = combine(per_view, ties_grads, config.refine_view_agreement, masked);
                let params = per_attribute_params(agreed, &self.state.gaussians);
                self.step_gaussians_with(params, rates, log_scale_bounds);
            } else {
                let gaussians = self.state.gaussians.tensors();
                let group: Vec<usize> =
                    refinement_views(iteration, fitted.len(), config.refine_views_per_step)
                        .into_iter()
                        .map(|i| fitted[i])
                        .collect();
                let (group_cameras, group_targets) = views_of(&group, (&cameras, &targets));
                let group_blurs: Option<Vec<ResidualBlur>> = blurs
                    .as_ref()
                    .map(|b| group.iter().map(|&v| b[v].clone()).collect());
                let (render, check) = self.render_loss_blurred(
                    &self.scene(gaussians.clone(), true),
                    &group_cameras,
                    &group_targets,
                    &mut group_lists[group[0]],
                    group_blurs.as_deref(),
                )?;
                let (refine, ties) = tie_losses(&gaussians);
                let mut loss = render.clone() + ties;
                let mut checks = vec![check];
                if let Some(((ahead_cameras, ahead_targets), carrier)) = &refine_ahead {
                    // The same views one frame on, the refined Gaussians carried there.
                    let carried = Gaussians {
                        means: self.carry(carrier, &gaussians.means).positions,
                        ..gaussians.clone()
                    };
                    let (ahead_cameras, ahead_targets) =
                        views_of(&group, (ahead_cameras, ahead_targets));
                    let (ahead_render, check) = self.render_loss_blurred(
                        &self.scene(carried, true),
                        &ahead_cameras,
                        &ahead_targets,
                        &mut ahead_group_lists[group[0]],
                        None,
                    )?;
                    loss = loss + ahead_render * config.lambda_refine_lookahead;
                    checks.push(check);
                }
                log.push(
                    (t, Phase::Refine, iteration),
                    StepLosses {
                        total: loss.clone(),
                        render,
                        divergence: None,
                        advection: None,
                        refine: Some(refine),
                    },
                    None,
                    checks,
                );
                let mut grads = {
                    let _phase = phase!("backward (all ops)");
                    loss.backward()
                };
                self.step_gaussians(&mut grads, rates, log_scale_bounds);
                self.step_statics(&mut grads, lr_gaussians);
            }
            if config.refine_average_steps > 1 && iteration >= average_from {
                iterate_mean.add(self.state.gaussians.tensors());
            }
            let done = iteration + 1;
            if done % turn == 0 || done == refine_iterations {
                if let Some(checks) = held_checks.as_mut() {
                    self.check_held_view(checks, done, (&cameras, &targets), &mut held_lists)?;
                }
                if let Some(trace) = held_out_trace.as_mut() {
                    let state = self.state.gaussians.tensors();
                    self.trace_held_out(trace, (Stage::Refine, done), state, &held_out)?;
                }
            }
            if log.due() || iteration + 1 == refine_iterations {
                read_log(&mut log, &mut losses, &bar, None)?;
                group_lists.iter_mut().for_each(ListCapacities::expire);
                ahead_group_lists
                    .iter_mut()
                    .for_each(ListCapacities::expire);
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        if iterate_mean.count() > 1
            && let Some(mean) = iterate_mean.mean()
        {
            self.state.gaussians = self.state.gaussians.clone().with_values(mean);
            self.keep_out_of_obstacles();
        }
        let keep_best = config.refine_held_view == HeldView::EarlyStop;
        let held_report = match held_checks.and_then(|checks| checks.finish(keep_best)) {
            Some((report, kept)) => {
                if let Some(kept) = kept {
                    self.keep_refinement_state(kept);
                }
                Some(report)
            }
            None => None,
        };
        traffic.push(LoopTraffic::of(Phase::Refine, refine_iterations, start));
        let (refine_moves, refine_move_field) = match grid_scale {
            Some(scale) => {
                let moves = self.state.gaussians.means.val().detach() - anchor;
                let field = self.move_field(&scale, moves.clone());
                let moves = moves * self.cells_per_world_unit().reshape([1, 3]);
                let [n, _] = moves.dims();
                let jumped = marked_rows(n, &moved);
                let jumped = Tensor::<1>::from_data(TensorData::new(jumped, [n]), &self.device);
                let (report, frame_moves) =
                    refine_moves(&scale, moves, self.last_moves.as_ref(), &jumped, &field);
                if config.refine_velocity_share > 0.0 {
                    let carried = self.carried_moves(&field, &frame_moves.field);
                    (velocity, unprojected) = self.with_refinement_moves(velocity, &carried);
                }
                let field = frame_moves.field.clone();
                self.last_moves = Some(frame_moves);
                (Some(report), Some(field))
            }
            None => {
                self.last_moves = None;
                (None, None)
            }
        };
        if config.correction_iterations > 0
            && let Some(corrected) = self.correct_velocity(
                &previous_means,
                &previous_velocity,
                &moved,
                time,
                lr_velocity,
            )?
        {
            (velocity, unprojected) = corrected;
        }
        if let Some(before) = motion_before {
            let prior = match config.density_motion_prior {
                DensityMotionPrior::Carried => previous_velocity.clone(),
                DensityMotionPrior::Frame => velocity.clone(),
            };
            (velocity, unprojected) = self.velocity_from_density_motion(t, before, prior);
        }
        self.state.velocity = velocity;
        Ok(FrameOutcome {
            frame: t,
            train_l1: last_turn_l1(&losses, fitted.len(), config.refine_views_per_step),
            losses,
            projection: Some(self.projection_report(unprojected)),
            clamped_to_box: clamped,
            respawned: respawned.len(),
            emitted: emitted.len(),
            split: split.parents.len(),
            refine_moves,
            refine_move_field,
            traffic,
            buoyancy: self.buoyancy_coefficient(),
            carrier_share,
            carrier_explained: prediction.map(|(_, explained)| explained),
            held_view: held_report,
            held_out_trace: held_out_trace.map(HeldOutTrace::finish).unwrap_or_default(),
        })
    }

    /// Renders the held view (`refine_held_view`, one of the frame's `cameras` and `targets`)
    /// from the refinement's state after `step` steps, outside the autodiff graph, and records
    /// its L1 with the state.
    fn check_held_view(
        &self,
        checks: &mut HeldViewChecks,
        step: usize,
        (cameras, targets): (&[Camera], &[Tensor<3>]),
        lists: &mut ListCapacities,
    ) -> Result<(), TrainError> {
        let _phase = phase!("held view check");
        let view = checks.view();
        let smoke = self.state.gaussians.tensors().detach();
        let statics = self
            .state
            .statics
            .as_ref()
            .map(|s| s.gaussians.tensors().detach());
        // Both parts are detached: the smoke here, the statics by `scene`.
        let (l1, _) = self.render_loss(
            &self.scene(smoke.clone(), false),
            &cameras[view..=view],
            &targets[view..=view],
            lists,
        )?;
        checks.record(step, l1, smoke, statics);
        Ok(())
    }

    /// Records the held-out views' squared errors from `smoke` at `point` (`held_out_trace`),
    /// outside the autodiff graph, clamped as the reports' PSNR clamps them.
    fn trace_held_out(
        &self,
        trace: &mut HeldOutTrace,
        point: (Stage, usize),
        smoke: GaussianTensors,
        held_out: &[(Camera, Tensor<3>)],
    ) -> Result<(), TrainError> {
        let _phase = phase!("held-out trace");
        let scene = self.scene(smoke, false).detach();
        let errors = held_out
            .iter()
            .map(|(camera, target)| {
                let out = render_volume(&scene, camera, &self.background, &self.raster)?;
                let residual = out.rgb.clamp(0.0, 1.0) - target.clone().clamp(0.0, 1.0);
                Ok(residual.powi_scalar(2).mean())
            })
            .collect::<Result<Vec<_>, TrainError>>()?;
        trace.record(point, Tensor::cat(errors, 0));
        Ok(())
    }

    /// Ends the refinement on an earlier state of it (the held view's best, static
    /// Gaussians included), keeping the parameters' ids for the optimisers.
    fn keep_refinement_state(&mut self, kept: KeptState) {
        self.state.gaussians = self.state.gaussians.clone().with_values(kept.smoke);
        if let (Some(statics), Some(values)) = (self.state.statics.as_mut(), kept.statics) {
            statics.gaussians = statics.gaussians.clone().with_values(values);
        }
        self.keep_out_of_obstacles();
    }

    /// The data set's true velocity of frame `t` on the grid (`velocity_from_ground_truth`),
    /// times `ground_truth_velocity_scale`.
    fn true_velocity(&self, t: usize) -> Result<Tensor<4>, TrainError> {
        let dir = self
            .sequence
            .ground_truth
            .as_ref()
            .expect("checked when the trainer was made");
        let path = dir.join(format!(
            "frame_{:03}.safetensors",
            self.sequence.first_frame + t
        ));
        let mut arrays = read_arrays(&path)?;
        let n = self.config.grid_resolution;
        let truth = take_array(&mut arrays, "velocity", &[n, n, n, 3], &path).map_err(|error| {
            TrainError::Config {
                origin: "configuration".into(),
                reason: format!(
                    "velocity_from_ground_truth reads the true velocity on the grid of \
                     grid_resolution ({n}) cells a side: {error}"
                ),
            }
        })?;
        let scale = self.config.ground_truth_velocity_scale;
        // The ground truth is [z][y][x] with x fastest, the grid [x][y][z] with z fastest.
        let truth = Tensor::<4>::from_data(TensorData::new(truth, [n, n, n, 3]), &self.device);
        Ok(truth.permute([2, 1, 0, 3]) * scale)
    }

    /// The grid-scale field of `moves` (world units, one row per Gaussian `scale` was built
    /// for), with this run's walls and obstacles for its projection.
    fn move_field(&self, scale: &GridScale, moves: Tensor<2>) -> MoveField<'_> {
        let [nx, ny, nz] = self.grid.resolution();
        MoveField {
            field: scale.cell_means(moves).reshape([nx, ny, nz, 3]),
            grid: &self.grid,
            projection: self.projection(),
        }
    }

    /// The move field `refine_velocity_share` carries on (world units): `field` itself, or
    /// with `refine_velocity_blur` its host copy `read` (in cells) smoothed.
    fn carried_moves(&self, field: &MoveField, read: &RefineMoveField) -> Tensor<4> {
        let sigma = self.config.refine_velocity_blur;
        if sigma == 0.0 {
            return field.field.clone();
        }
        let resolution = self.grid.resolution();
        let smooth = smoothed(&read.moves, resolution, 3, sigma, [true; 3]);
        let smooth = per_axis(smooth, &self.grid, |x, cell| x * cell);
        let [nx, ny, nz] = resolution;
        Tensor::from_data(TensorData::new(smooth, [nx, ny, nz, 3]), &self.device)
    }

    /// `velocity` with `refine_velocity_share` of the refinement's move `field` (see
    /// [`MoveField::field`]) added as a velocity, then projected: the projected and the
    /// unprojected sum.
    fn with_refinement_moves(
        &self,
        velocity: Tensor<4>,
        field: &Tensor<4>,
    ) -> (Tensor<4>, Tensor<4>) {
        let unprojected =
            velocity + field.clone() * (self.config.refine_velocity_share / self.config.dt);
        (self.project(unprojected.clone()), unprojected)
    }

    /// The velocity whose semi-Lagrangian step carries `before` (frame t-1's density on the
    /// grid) onto the density of the Gaussians as they are now, starting from and tied to
    /// `prior` (`velocity_from_density_motion`, `density_motion_prior`; see
    /// [`crate::density_motion`]): the projected and the unprojected fit.
    fn velocity_from_density_motion(
        &self,
        t: usize,
        before: &[f32],
        prior: Tensor<4>,
    ) -> (Tensor<4>, Tensor<4>) {
        let _phase = phase!("velocity from density motion");
        let after = self.density_host();
        let dt = self.config.dt as f64;
        let cell = self.grid.cell_size().to_array().map(f64::from);
        let prior_moves = moves_of_velocity(&read_floats(prior.detach()), cell, dt);
        let in_data = transport_cells(&self.grid, self.config.respawn_region);
        let priors = MotionPriors {
            smoothness: self.config.density_motion_smoothness as f64,
            divergence: self.config.density_motion_divergence as f64,
            // Frame 1's carried velocity is frame 0's still one, which is no estimate.
            inertia: if t <= 1 && self.config.density_motion_prior == DensityMotionPrior::Carried {
                0.0
            } else {
                self.config.density_motion_inertia as f64
            },
            smoothed: Smoothed::Move,
        };
        let grid = MotionGrid {
            resolution: self.grid.resolution(),
            open: self.projection().open_faces,
        };
        let fit = fit_density_motion(
            &grid,
            before,
            &after,
            &in_data,
            &prior_moves,
            priors,
            DENSITY_MOTION_CG_ITERATIONS,
        );
        tracing::debug!(
            frame = t,
            misfit_prior = fit.misfit_prior,
            misfit_fitted = fit.misfit_fitted,
            rejected_steps = fit.rejected_steps,
            kept_start = fit.kept_start,
            solver_iterations = fit.solver_iterations,
            solver_residual = fit.solver_residual,
            "velocity from density motion"
        );
        let velocity = velocity_of_moves(&fit.moves, cell, dt);
        let [nx, ny, nz] = self.grid.resolution();
        let unprojected =
            Tensor::from_data(TensorData::new(velocity, [nx, ny, nz, 3]), &self.device);
        (self.project(unprojected.clone()).detach(), unprojected)
    }

    /// Fits Phi so that the frame's velocity carries the previous centres to where the
    /// refinement put the smoke (ours, `correction_iterations`): to each refined centre, or
    /// (`correction_target = "density"`) so that the carried Gaussians' density matches the
    /// refined ones'. The refinement moved the Gaussians where the pictures put the smoke,
    /// and without this the velocity never learns from that move. Recycled and split
    /// Gaussians, which jumped, are left out, and for the centres also ones the velocity
    /// would carry out of the box. Returns the projected and unprojected velocity of the
    /// last step, or `None` when every Gaussian jumped (nothing to fit).
    fn correct_velocity(
        &mut self,
        previous_means: &Tensor<2>,
        previous_velocity: &Tensor<4>,
        moved: &[usize],
        time: f32,
        lr_velocity: f64,
    ) -> Result<Option<(Tensor<4>, Tensor<4>)>, TrainError> {
        let config = self.config.clone();
        let cutoff = SplatOptions::default().cutoff;
        let refined = self.state.gaussians.tensors().detach();
        let [n, _] = refined.means.dims();
        let previous = self.state.gaussians.tensors_at(previous_means.clone());
        let sigma_previous = self.splat_density(&previous, cutoff).detach();
        let jumped = marked_rows(n, moved);
        if !jumped.contains(&0.0) {
            return Ok(None);
        }
        let kept = Tensor::<1>::from_data(TensorData::new(jumped, [n]), &self.device)
            .neg()
            .add_scalar(1.0);
        // The density counts the kept Gaussians only: the others' at (nearly) zero. Detached
        // again because burn 0.22 keeps an op on a detached parameter's value on the tape,
        // which the first step's backward would consume and the next step's refuse.
        let refined = Gaussians {
            raw_densities: refined
                .raw_densities
                .mask_fill(kept.clone().equal_elem(0.0), OFF_DENSITY),
            ..refined
        }
        .detach();
        // The density target, and its mean square to make the miss a relative one.
        let target = (config.correction_target == CorrectionTarget::Density).then(|| {
            let sigma = self.splat_density(&refined, cutoff).detach();
            let scale = sigma.clone().powi_scalar(2).mean().clamp_min(1e-12);
            (sigma, scale)
        });
        let in_cells = self.cells_per_world_unit().reshape([1, 3]);
        let mut last = None;
        for _ in 0..config.correction_iterations {
            let delta = {
                let _phase = phase!("U-Net forward");
                self.state
                    .phi
                    .forward(previous_velocity.clone(), sigma_previous.clone(), time)?
            };
            let update = self.unprojected_update(
                previous_velocity.clone(),
                delta.clone(),
                sigma_previous.clone(),
            );
            let projected = self.project(update.clone());
            let moved = self.carry(&projected, previous_means);
            let mut loss = match &target {
                Some((sigma_target, scale)) => {
                    let carried = Gaussians {
                        means: moved.positions,
                        ..refined.clone()
                    };
                    let sigma = self.splat_density(&carried, cutoff);
                    (sigma - sigma_target.clone()).powi_scalar(2).mean() / scale.clone()
                }
                None => {
                    let weight = kept.clone() * moved.left_box.bool_not().float();
                    let miss = ((moved.positions - refined.means.clone()) * in_cells.clone())
                        .powi_scalar(2)
                        .sum_dim(1)
                        .reshape([n]);
                    (miss * weight.clone()).sum() / weight.sum().clamp_min(1.0)
                }
            };
            if config.lambda_increment > 0.0 {
                loss = loss + self.inertia_prior(delta, sigma_previous.clone());
            }
            last = Some((projected.detach(), update.detach()));
            let mut grads = {
                let _phase = phase!("backward (all ops)");
                loss.backward()
            };
            self.step_phi(&mut grads, lr_velocity);
        }
        Ok(last)
    }

    /// Emission at the source, recycling, then splitting, on one host copy of the Gaussians:
    /// one read from the device and a write back when rows changed (two when emission
    /// changed some and recycling follows, so that its renders show them). `density_before` is frame
    /// t-1's density on the grid (with `emission_fraction > 0`). No row is taken twice.
    fn renew_gaussians(
        &mut self,
        t: usize,
        density_before: Option<&[f32]>,
        born: EmissionReport,
    ) -> Result<Renewal, TrainError> {
        if self.config.respawn_fraction <= 0.0
            && self.config.split_fraction <= 0.0
            && density_before.is_none()
        {
            return Ok(Renewal {
                emitted: born,
                ..Renewal::default()
            });
        }
        let mut host = self.state.gaussians.to_host();
        let emitted = match density_before {
            Some(before) => self.emit(t, &mut host, before, &self.density_host()),
            None => born,
        };
        // Rows changed on the host that the device does not have yet (born rows are written).
        let mut unwritten = density_before.is_some() && !emitted.indices.is_empty();
        if unwritten && self.config.respawn_fraction > 0.0 {
            self.state.gaussians = self.state.gaussians.clone().with_host_values(&host);
            unwritten = false;
        }
        let recycled = self.respawn(t, &mut host, &emitted.indices)?;
        let taken: Vec<usize> = [&emitted.indices, &recycled.indices]
            .into_iter()
            .flatten()
            .copied()
            .collect();
        let split = self.split(&mut host, &taken);
        if unwritten || !recycled.indices.is_empty() || !split.parents.is_empty() {
            self.state.gaussians = self.state.gaussians.clone().with_host_values(&host);
        }
        if !split.parents.is_empty() || !emitted.indices.is_empty() {
            // A half or an emitted Gaussian may land in an obstacle, as an advected centre may.
            self.keep_out_of_obstacles();
        }
        Ok(Renewal {
            emitted,
            recycled,
            split,
        })
    }

    /// Emits into the rows recycling would take the density the carrier took out of the
    /// inflow box since frame t-1 (`density_before`; see [`crate::emission`]).
    fn emit(
        &self,
        t: usize,
        host: &mut HostGaussians,
        density_before: &[f32],
        density_after: &[f32],
    ) -> EmissionReport {
        let _phase = phase!("emission");
        let lattice = self.spawn_lattice();
        let Some(fractions) = self.config.respawn_region else {
            return EmissionReport::default();
        };
        let options = EmissionOptions {
            region: lattice.region_from_fractions(fractions),
            budget: (self.config.emission_fraction * host.len() as f32).floor() as usize,
            std: self.initial_std(),
            // Apart from recycling's stream of the same frame.
            seed: self.config.seed ^ (t as u64 + 1).wrapping_mul(0xD1B5_4A32_D192_ED03),
        };
        let (slots, _) = recycling_candidates(host, &lattice, &[]);
        let report = emit(
            host,
            density_before,
            density_after,
            &lattice,
            &slots,
            &options,
        );
        tracing::debug!(
            frame = t,
            emitted = report.indices.len(),
            mass = report.mass,
            "emission"
        );
        report
    }

    /// Emission before frame `t`'s joint iterations (`emission_timing = "before_joint"`): the
    /// box's loss when the Gaussians of frame t-1 (`density_before` on the grid) are carried
    /// one frame by `carrier`, emitted at frame t's positions and written to the device.
    fn emit_before_joint(
        &mut self,
        t: usize,
        carrier: &Tensor<4>,
        density_before: &[f32],
    ) -> EmissionReport {
        let previous = self.state.gaussians.tensors().detach();
        let carried = self.carry(&carrier.clone().detach(), &previous.means);
        let density_after = self.density_host_of(&Gaussians {
            means: carried.positions,
            ..previous
        });
        let mut host = self.state.gaussians.to_host();
        let report = self.emit(t, &mut host, density_before, &density_after);
        if !report.indices.is_empty() {
            self.state.gaussians = self.state.gaussians.clone().with_host_values(&host);
            self.keep_out_of_obstacles();
        }
        report
    }

    /// Recycles rows of `host` (see [`crate::respawn`]) against frame `t`'s training views,
    /// after the Gaussians were carried to frame `t`; nothing happens with
    /// `respawn_fraction = 0`.
    fn respawn(
        &self,
        t: usize,
        host: &mut HostGaussians,
        taken: &[usize],
    ) -> Result<RespawnReport, TrainError> {
        if self.config.respawn_fraction <= 0.0 {
            return Ok(RespawnReport::default());
        }
        let _phase = phase!("respawn");
        let observations = &self.sequence.train[t];
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
        let lattice = self.spawn_lattice();
        let options = RespawnOptions {
            fraction: self.config.respawn_fraction,
            threshold: self.config.respawn_threshold,
            std: self.initial_std(),
            background: self.sequence.background,
            // A per-frame stream, so a resumed run draws what an uninterrupted one did.
            seed: self.config.seed ^ (t as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
            near_smoke: self.config.respawn_near_smoke,
            region: self
                .config
                .respawn_region
                .map(|fractions| lattice.region_from_fractions(fractions)),
        };
        let density = if options.near_smoke > 0.0 {
            self.density_host()
        } else {
            Vec::new()
        };
        let report = respawn(host, &views, &lattice, &options, &density, taken);
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

    /// Moves the carried Gaussians' densities towards their horizontal smoothing before
    /// frame `t`'s fit (`carried_smoothing`; see [`crate::carried_smoothing`]).
    fn smooth_carried(&mut self, t: usize) {
        let _phase = phase!("carried smoothing");
        let mut host = self.state.gaussians.to_host();
        let report = smooth_carried_densities(
            &mut host,
            &self.density_host(),
            &self.spawn_lattice(),
            self.config.carried_smoothing,
            self.config.carried_smoothing_cells,
        );
        if report.changed > 0 {
            self.state.gaussians = self.state.gaussians.clone().with_host_values(&host);
        }
        tracing::debug!(
            frame = t,
            changed = report.changed,
            mean_change = report.mean_change,
            "carried smoothing"
        );
    }

    /// Widens the carried Gaussians before a frame's fit (`carried_growth`; see
    /// [`crate::carried_smoothing`]); the variance is in cells of the velocity grid, the mean
    /// of its three sides where the cells are not cubes.
    fn grow_carried(&mut self) {
        let _phase = phase!("carried growth");
        let mut host = self.state.gaussians.to_host();
        let cell = self.grid.cell_size().element_sum() / 3.0;
        let [_, max_log_scale] = self.log_scale_bounds();
        grow_carried_sizes(
            &mut host,
            self.config.carried_growth * cell * cell,
            max_log_scale,
        );
        self.state.gaussians = self.state.gaussians.clone().with_host_values(&host);
    }

    /// The box and lattice recycled and split Gaussians are placed in: the velocity grid's.
    fn spawn_lattice(&self) -> SpawnLattice {
        SpawnLattice {
            lo: self.grid.lo(),
            hi: self.grid.hi(),
            resolution: self.grid.resolution(),
        }
    }

    /// The smoke Gaussians' smallest and largest log standard deviation after frame 0
    /// (`min_size_factor`, `max_size_factor`); infinite bounds leave the renderer's range.
    fn log_scale_bounds(&self) -> [f32; 2] {
        let bound = |factor: f32, none: f32| {
            if factor > 0.0 {
                (factor * self.initial_std()).ln()
            } else {
                none
            }
        };
        [
            bound(self.config.min_size_factor, f32::NEG_INFINITY),
            bound(self.config.max_size_factor, f32::INFINITY),
        ]
    }

    /// The Gaussians' standard deviation at initialisation (see `GaussianModel::init_in_box`).
    fn initial_std(&self) -> f32 {
        let extent = self.grid.hi() - self.grid.lo();
        let [count, _] = self.state.gaussians.means.val().dims();
        let count = count as f32;
        0.5 * (extent.x * extent.y * extent.z / count).cbrt()
    }

    /// Splits the largest rows of `host` (see [`crate::split`]) into rows recycling would
    /// take, other than the `taken` ones (emitted or recycled this frame); nothing happens
    /// with `split_fraction = 0`.
    fn split(&self, host: &mut HostGaussians, taken: &[usize]) -> SplitReport {
        if self.config.split_fraction <= 0.0 {
            return SplitReport::default();
        }
        let _phase = phase!("split");
        let lattice = self.spawn_lattice();
        let min_std = self.config.split_size_factor * self.initial_std();
        let budget = (self.config.split_fraction * host.len() as f32).floor() as usize;
        let (mut slots, on_faces) = recycling_candidates(host, &lattice, taken);
        if self.config.split_into_faces_only {
            slots.truncate(on_faces);
        }
        let report = split_largest(host, &slots, budget, min_std, &lattice);
        tracing::debug!(split = report.parents.len(), slots = slots.len(), "split");
        report
    }

    /// Host density grid of the current Gaussians.
    pub fn density_host(&self) -> Vec<f32> {
        self.density_host_of(&self.state.gaussians.tensors())
    }

    /// `gaussians` as the density grid counts them: with `density_grid_rendered_only`, the
    /// ones the renderer skips on every ray (peak alpha under `alpha_min`, the bound of
    /// `gausmoke_render`'s cull) at (nearly) zero density; otherwise all of them.
    fn as_splatted(&self, gaussians: &GaussianTensors) -> GaussianTensors {
        if !self.config.density_grid_rendered_only {
            return gaussians.clone();
        }
        let needed_optical_depth = -(1.0 - self.config.alpha_min).ln();
        let sigma =
            burn::tensor::activation::softplus(gaussians.raw_densities.clone().detach(), 1.0);
        let largest_scale = gaussians
            .log_scales
            .clone()
            .detach()
            .max_dim(1)
            .exp()
            .squeeze_dim::<1>(1);
        let peak = sigma * largest_scale * (2.0 * std::f32::consts::PI).sqrt();
        Gaussians {
            raw_densities: gaussians
                .raw_densities
                .clone()
                .mask_fill(peak.lower_elem(needed_optical_depth), OFF_DENSITY),
            ..gaussians.clone()
        }
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

    /// The density grid of `gaussians` (every density the trainer splats goes through here,
    /// so that `density_grid_rendered_only` holds for all of them).
    fn splat_density(&self, gaussians: &GaussianTensors, cutoff: f32) -> Tensor<3> {
        density_grid(&self.as_splatted(gaussians), &self.grid, cutoff)
    }

    /// [`Self::splat_density`] with the density's gradient, in one pass.
    fn splat_density_and_gradient(
        &self,
        gaussians: &GaussianTensors,
        cutoff: f32,
    ) -> (Tensor<3>, Tensor<4>) {
        density_and_gradient_grid(&self.as_splatted(gaussians), &self.grid, cutoff)
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

/// `means` `[N, 3]` with every centre inside one of `obstacles` moved onto its surface (a hair
/// outside; radially for a sphere, through the nearest face for a box), in tensor operations
/// (no read).
fn outside_obstacles(means: Tensor<2>, obstacles: &[Obstacle]) -> Tensor<2> {
    let device = means.device();
    let [n, _] = means.dims();
    obstacles
        .iter()
        .fold(means, |means, obstacle| match *obstacle {
            Obstacle::Sphere { centre, radius } => {
                let centre = Tensor::<2>::from_data(
                    TensorData::new(centre.to_array().to_vec(), [1, 3]),
                    &device,
                );
                let offset = means.clone() - centre.clone();
                let squared = offset.clone().powi_scalar(2).sum_dim(1);
                let inside = squared.clone().lower_elem(radius * radius).expand([n, 3]);
                let distance = squared.sqrt().clamp_min(1e-12);
                let surface = centre + offset / distance * (radius * 1.001);
                means.mask_where(inside, surface)
            }
            Obstacle::Box { min, max } => {
                let row = |v: Vec3| {
                    Tensor::<2>::from_data(TensorData::new(v.to_array().to_vec(), [1, 3]), &device)
                        .expand([n, 3])
                };
                let offset = means.clone() - row(0.5 * (min + max));
                // Per axis, how far outside the nearer face (negative inside).
                let q = offset.clone().abs() - row(0.5 * (max - min));
                let deepest = q.clone().max_dim(1);
                let inside = deepest.clone().lower_elem(0.0).expand([n, 3]);
                // Out through the nearest face, a hair beyond it.
                let nearest = q.clone().equal(deepest.expand([n, 3])).float();
                let hair = 5e-4 * (max - min).max_element();
                let surface = means.clone() + nearest * offset.sign() * (q.neg() + hair);
                means.mask_where(inside, surface)
            }
        })
}

/// The data set's obstacles as solid cells of `grid` (cell centre inside), when there are any
/// and `config.obstacles` makes them solid; refused with the penalty form of `Pi`, which has no
/// notion of them, and when they cover no cell (a sphere smaller than the grid can see).
pub(crate) fn solid_cells(
    obstacles: &[Obstacle],
    config: &TrainConfig,
    grid: &GridSpec,
) -> Result<Option<SolidCells>, TrainError> {
    if obstacles.is_empty() || config.obstacles == Obstacles::Ignore {
        return Ok(None);
    }
    let refuse = |reason: String| TrainError::Config {
        origin: "obstacles".into(),
        reason,
    };
    if config.projection != ProjectionKind::Exact {
        return Err(refuse(format!(
            "the data set describes {} obstacle(s), which only projection = \"exact\" keeps \
             the flow out of: use it, or set obstacles = \"ignore\"",
            obstacles.len()
        )));
    }
    let flags = grid.cells_where(|p| obstacles.iter().any(|o| o.contains(p)));
    let solids = SolidCells::new(grid.resolution(), flags).expect("one flag per cell");
    if solids.count() == 0 {
        return Err(refuse(format!(
            "the data set's obstacles cover no cell centre of the {:?} grid: refine \
             grid_resolution, or set obstacles = \"ignore\"",
            grid.resolution()
        )));
    }
    tracing::info!(
        cells = solids.count(),
        of = grid.num_cells(),
        "obstacle cells are solid in the projection"
    );
    Ok(Some(solids))
}

/// The frame's L1 on its training views after its loops: the last step's, or, when that step
/// was a refinement step rendering some of the `views` (`per_step`), the mean of the last
/// `views` refinement steps' (one turn in which each view is rendered equally often).
fn last_turn_l1(losses: &[LossRow], views: usize, per_step: usize) -> f64 {
    let Some(last) = losses.last() else {
        return f64::NAN;
    };
    if last.phase != Phase::Refine || per_step == 0 || per_step >= views {
        return last.render as f64;
    }
    let turn: Vec<f32> = losses
        .iter()
        .rev()
        .take_while(|row| row.phase == Phase::Refine)
        .take(views)
        .map(|row| row.render)
        .collect();
    turn.iter().map(|&l1| l1 as f64).sum::<f64>() / turn.len() as f64
}

/// The training views (indices into the frame's `views`) that refinement step `step`
/// renders: `per_step` of them in turn from view `step * per_step`, wrapping around, so that
/// every view is rendered equally often over `views` steps; all of them when `per_step` is 0
/// or not below `views`. The first index names the group (a group's views are fixed by it).
fn refinement_views(step: usize, views: usize, per_step: usize) -> Vec<usize> {
    if per_step == 0 || per_step >= views {
        return (0..views).collect();
    }
    let first = step * per_step % views;
    (0..per_step).map(|i| (first + i) % views).collect()
}

/// `increment` `[nx, ny, nz, 3]` less its buoyancy-like part: `b sigma` taken from the upward
/// (y) component, with `b = <increment_y, sigma> / <sigma, sigma>` the least-squares fit over
/// the grid (0 where there is no density), so what is left is what buoyancy cannot explain.
fn without_buoyancy(increment: Tensor<4>, sigma: Tensor<3>) -> Tensor<4> {
    let [nx, ny, nz, _] = increment.dims();
    let sigma = sigma.reshape([nx, ny, nz, 1]);
    let upward = increment.clone().slice([0..nx, 0..ny, 0..nz, 1..2]);
    let b = (upward * sigma.clone()).sum() / (sigma.clone().powi_scalar(2).sum() + 1e-12);
    let buoyancy = Tensor::cat(
        vec![
            sigma.zeros_like(),
            sigma.clone() * b.reshape([1, 1, 1, 1]),
            sigma.zeros_like(),
        ],
        3,
    );
    increment - buoyancy
}

/// Points drawn to estimate the volume of the solids' surface layer (`static_shell`).
const SHELL_VOLUME_SAMPLES: usize = 200_000;

/// The static Gaussians before their fit: inside the obstacles the data set describes, if any
/// (where the solids are; within `static_shell` of their surfaces when set), else spread
/// through the box like the smoke's.
fn static_gaussians_at_start(
    sequence: &Sequence,
    config: &TrainConfig,
    device: &Device,
) -> GaussianModel {
    // Their own stream: not the smoke's positions again.
    let seed = config.seed ^ 0x5747_4943;
    let count = config.static_gaussians;
    let mut bounds: Option<(Vec3, Vec3)> = None;
    let mut volume = 0.0;
    for obstacle in &sequence.obstacles {
        let (lo, hi, v) = obstacle.bounds();
        volume += v;
        bounds = Some(bounds.map_or((lo, hi), |(a, b)| (a.min(lo), b.max(hi))));
    }
    // Packed into a smaller volume, the Gaussians are smaller: as dense as the smoke's at
    // their start, a ray through one would see so little that the renderer skips it
    // (`alpha_min`) and it would never learn. Give them the optical depth through the centre
    // that a smoke Gaussian starts with instead (it scales with density times size).
    let size = |volume: f32, count: usize| (volume / count.max(1) as f32).cbrt();
    let extent = sequence.hi - sequence.lo;
    let softplus = |x: f32| x.exp().ln_1p();
    let depth_scale =
        softplus(INITIAL_RAW_DENSITY) * size(extent.x * extent.y * extent.z, config.gaussians);
    let placed = |p: Vec3| in_static_region(&sequence.obstacles, config.static_shell, p);
    match bounds {
        Some((lo, hi)) => {
            let within = (lo.max(sequence.lo), hi.min(sequence.hi));
            if config.static_shell.is_some() {
                volume =
                    static_region_volume(&sequence.obstacles, config.static_shell, within, seed);
            }
            GaussianModel::init_where(
                count,
                within,
                volume,
                placed,
                // The raw value (softplus^-1) of the density that keeps density x size.
                (depth_scale / size(volume, count)).exp_m1().ln(),
                seed,
                device,
            )
            // An obstacle reaching outside the box: fall back to the box.
            .unwrap_or_else(|| {
                GaussianModel::init_in_box(count, sequence.lo, sequence.hi, seed, device)
            })
        }
        None => GaussianModel::init_in_box(count, sequence.lo, sequence.hi, seed, device),
    }
}

/// Whether static Gaussians start at `p`: inside one of `obstacles`, and no deeper than
/// `shell` under its surface when that is set.
fn in_static_region(obstacles: &[Obstacle], shell: Option<f32>, p: Vec3) -> bool {
    obstacles.iter().any(|o| {
        let depth = -o.signed_distance(p);
        depth >= 0.0 && shell.is_none_or(|shell| depth <= shell)
    })
}

/// The volume of [`in_static_region`] within `(lo, hi)`: its share of `SHELL_VOLUME_SAMPLES`
/// points drawn there (for the Gaussians' starting size, so a few percent will do).
fn static_region_volume(
    obstacles: &[Obstacle],
    shell: Option<f32>,
    (lo, hi): (Vec3, Vec3),
    seed: u64,
) -> f32 {
    let mut rng = SplitMix64::new(seed);
    let hits = (0..SHELL_VOLUME_SAMPLES)
        .filter(|_| {
            let p = Vec3::from_array([0, 1, 2].map(|a| rng.range(lo[a], hi[a])));
            in_static_region(obstacles, shell, p)
        })
        .count();
    (hi - lo).max(Vec3::ZERO).element_product() * hits as f32 / SHELL_VOLUME_SAMPLES as f32
}

/// Conjugate-gradient iterations per Gauss-Newton pass of the density-motion fit, the
/// default of `xtask/reference/velocity_from_density.py`, whose bound it was measured with.
const DENSITY_MOTION_CG_ITERATIONS: usize = 400;

/// The state Algorithm 1 starts from: Gaussians spread in the box, zero velocity, Phi's
/// initial weights.
fn fresh_state(
    sequence: &Sequence,
    config: &TrainConfig,
    grid: &GridSpec,
    device: &Device,
) -> TrainState {
    let [nx, ny, nz] = grid.resolution();
    let unet = UNetConfig {
        base_channels: config.unet_channels,
        time_frequencies: config.time_frequencies,
    };
    TrainState {
        gaussians: GaussianModel::init_in_box(
            config.gaussians,
            sequence.lo,
            sequence.hi,
            config.seed,
            device,
        ),
        statics: (config.static_gaussians > 0).then(|| StaticGaussians {
            gaussians: static_gaussians_at_start(sequence, config, device),
            optim: AdamConfig::new().with_epsilon(1e-15).init(),
        }),
        velocity: Tensor::zeros([nx, ny, nz, 3], device),
        phi: VelocityUNet::new(&unet, config.seed, device),
        gaussian_optim: gaussian_optimizer(),
        phi_optim: AdamConfig::new().init(),
        buoyancy: config.buoyancy_force.then(|| Buoyancy {
            force: BuoyancyForce::new(0.0, device),
            optim: AdamConfig::new().init(),
        }),
    }
}

/// The smoke Gaussians of another run's frame file, which must hold `count` of them
/// (`init_gaussians`).
fn warm_start(path: &Path, count: usize, device: &Device) -> Result<GaussianModel, TrainError> {
    let refuse = |reason: String| TrainError::Config {
        origin: format!("init_gaussians = {}", path.display()),
        reason,
    };
    if !path.is_file() {
        return Err(refuse(
            "no such file (a run's frames/frame_TTT.safetensors)".into(),
        ));
    }
    let host = read_frame_gaussians(path).map_err(|e| refuse(e.to_string()))?;
    if host.len() != count {
        return Err(refuse(format!(
            "the file holds {} Gaussians but gaussians is {count}",
            host.len()
        )));
    }
    Ok(GaussianModel::from_host(&host, device))
}

/// A fresh Adam state for the smoke Gaussians.
fn gaussian_optimizer() -> ModuleOptimizer {
    // 3DGS practice: a tiny epsilon, so rarely-seen Gaussians still move.
    AdamConfig::new().with_epsilon(1e-15).init()
}

/// A fresh Adam state for the smoke Gaussians past frame 0: with `relative_adam_epsilon`
/// its epsilon, in units of each attribute's gradient RMS (see [`grads_over_their_rms`]).
fn frame_gaussian_optimizer(config: &TrainConfig) -> ModuleOptimizer {
    if config.relative_adam_epsilon > 0.0 {
        AdamConfig::new()
            .with_epsilon(config.relative_adam_epsilon)
            .init()
    } else {
        gaussian_optimizer()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::disallowed_methods)] // tests read tensors freely

    use super::*;
    use gausmoke_core::SplitMix64;
    use gausmoke_render::backends::cpu_devices;

    /// The correction steps fit the velocity to a move of the centres that a velocity can
    /// make (a swirl about the box's vertical axis), and leave recycled rows out.
    #[test]
    fn the_velocity_correction_fits_the_move_of_the_centres() {
        velocity_correction_fits_a_swirl(CorrectionTarget::Centres);
    }

    /// The density-motion fit in the trainer's units: Gaussians gathered in a ball and moved by
    /// a known shift between the two densities give back that shift over `dt` as a velocity
    /// (world units per frame) where the smoke is.
    #[test]
    fn the_density_motion_velocity_is_the_shift_of_the_density() {
        let dir = tempfile::tempdir().unwrap();
        let config = TrainConfig {
            gaussians: 400,
            grid_resolution: 16,
            frames: Some(3),
            unet_channels: 4,
            time_frequencies: 2,
            dt: 0.5,
            velocity_from_density_motion: true,
            ..TrainConfig::default()
        };
        let (mut trainer, device) = tiny_trainer(dir.path(), config);
        let grid = trainer.grid;
        let cell = grid.cell_size();
        let centre = (grid.lo() + grid.hi()) * 0.5;
        let shift = cell * Vec3::new(0.8, 1.2, -0.5);
        let mut rng = SplitMix64::new(7);
        let n = 400;
        let ball: Vec<Vec3> = (0..n)
            .map(|_| {
                let r = Vec3::new(
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                    rng.range(-1.0, 1.0),
                );
                centre + r * (grid.hi() - grid.lo()) * 0.15
            })
            .collect();
        let density_at = |trainer: &mut Trainer, offset: Vec3| {
            let means: Vec<f32> = ball.iter().flat_map(|p| (*p + offset).to_array()).collect();
            let means = Tensor::<2>::from_data(TensorData::new(means, [n, 3]), &device);
            trainer.state.gaussians = trainer.state.gaussians.clone().with_means(means);
            trainer.density_host()
        };
        let before = density_at(&mut trainer, Vec3::ZERO);
        let after = density_at(&mut trainer, shift);
        let [nx, ny, nz] = grid.resolution();
        let still = Tensor::<4>::zeros([nx, ny, nz, 3], &device);
        // Frame 1: not tied to the prior (frame 0's still velocity), which would pull the
        // flat inside of the ball, where the density shows no motion, towards zero.
        let (_, fitted) = trainer.velocity_from_density_motion(1, &before, still);
        let fitted = read_floats(fitted);
        let largest = after.iter().fold(0.0f32, |m, &v| m.max(v));
        let smoke: Vec<usize> = (0..after.len())
            .filter(|&c| after[c] > 0.2 * largest)
            .collect();
        assert!(smoke.len() > 20, "{} cells of smoke", smoke.len());
        let expected = shift / 0.5;
        for axis in 0..3 {
            let mean =
                smoke.iter().map(|&c| fitted[3 * c + axis]).sum::<f32>() / smoke.len() as f32;
            assert!(
                (mean - expected[axis]).abs() < 0.2 * expected.abs().max_element(),
                "axis {axis}: mean {mean} in the smoke, expected {}",
                expected[axis]
            );
        }
    }

    /// The same with the refined density as the target.
    #[test]
    fn the_velocity_correction_fits_the_refined_density() {
        velocity_correction_fits_a_swirl(CorrectionTarget::Density);
    }

    /// A trainer for `config` on the tiny synthetic scene with `config.frames` frames, written
    /// to `dir`; on the flex backend.
    fn tiny_trainer(dir: &Path, config: TrainConfig) -> (Trainer, Device) {
        use gausmoke_data::synth::{SynthConfig, generate};
        use gausmoke_render::backends::device_by_name;
        let data = dir.join("data");
        let scene = SynthConfig {
            frames: config.frames.expect("the test names its frames"),
            ..SynthConfig::tiny()
        };
        generate(&scene, &data).unwrap();
        let device = device_by_name("flex").unwrap().autodiff();
        let sequence = Sequence::open(&data, &config).unwrap();
        (
            Trainer::new(sequence, config, device.clone()).unwrap(),
            device,
        )
    }

    fn velocity_correction_fits_a_swirl(target: CorrectionTarget) {
        let dir = tempfile::tempdir().unwrap();
        let config = TrainConfig {
            gaussians: 400,
            grid_resolution: 8,
            frames: Some(2),
            unet_channels: 4,
            time_frequencies: 2,
            correction_iterations: 60,
            correction_target: target,
            ..TrainConfig::default()
        };
        let (mut trainer, device) = tiny_trainer(dir.path(), config);
        let grid = trainer.grid;
        let previous = trainer.state.gaussians.means.val().detach();
        let centre = (grid.lo() + grid.hi()) * 0.5;
        // Half a cell at the rim.
        let angle = 0.5 * grid.cell_size().x / (0.5 * (grid.hi().x - grid.lo().x));
        let (sin, cos) = angle.sin_cos();
        let moved: Vec<f32> = previous
            .clone()
            .into_data()
            .try_into_vec_as::<f32>()
            .unwrap()
            .chunks_exact(3)
            .flat_map(|p| {
                let (x, z) = (p[0] - centre.x, p[2] - centre.z);
                [
                    centre.x + cos * x - sin * z,
                    p[1],
                    centre.z + sin * x + cos * z,
                ]
            })
            .collect();
        let [n, _] = previous.dims();
        let refined = Tensor::<2>::from_data(TensorData::new(moved, [n, 3]), &device);
        trainer.state.gaussians = trainer.state.gaussians.clone().with_means(refined.clone());
        let [nx, ny, nz] = grid.resolution();
        let still = Tensor::<4>::zeros([nx, ny, nz, 3], &device);
        let miss = |velocity: &Tensor<4>| {
            let carried = advect(
                &grid,
                velocity,
                &previous,
                1.0,
                Integrator::Euler,
                Interpolation::default(),
            )
            .positions;
            let squared = (carried - refined.clone()).powi_scalar(2).sum_dim(1).mean();
            squared.into_scalar::<f32>()
        };
        // Every row recycled: nothing to fit.
        let all: Vec<usize> = (0..n).collect();
        let rest = trainer
            .correct_velocity(&previous, &still, &all, 0.5, 0.01)
            .unwrap();
        assert!(rest.is_none());
        let before = miss(&still);
        let (fitted, _) = trainer
            .correct_velocity(&previous, &still, &[], 0.5, 0.01)
            .unwrap()
            .unwrap();
        let after = miss(&fitted);
        assert!(
            after < 0.3 * before,
            "mean squared miss {after} after the correction, {before} before"
        );
    }

    /// The tiny synthetic scene in a temporary folder (kept while the first value lives).
    fn tiny_scene() -> (tempfile::TempDir, std::path::PathBuf) {
        use gausmoke_data::synth::{SynthConfig, generate};
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("data");
        generate(&SynthConfig::tiny(), &data).unwrap();
        (dir, data)
    }

    /// `init_gaussians` starts from the Gaussians another run wrote for a frame, not from a
    /// spread of its own seed, and refuses a file that is missing or holds another count.
    #[test]
    fn a_warm_start_begins_with_another_runs_gaussians() {
        use crate::run_folder::{FrameState, RunFolder};
        use gausmoke_render::backends::device_by_name;
        let (dir, data) = tiny_scene();
        let device = device_by_name("flex").unwrap().autodiff();
        let config = |seed: u64, init_gaussians: Option<std::path::PathBuf>| TrainConfig {
            gaussians: 500,
            grid_resolution: 8,
            frames: Some(1),
            seed,
            init_gaussians,
            ..TrainConfig::default()
        };
        let trainer = |config: TrainConfig| {
            Trainer::new(
                Sequence::open(&data, &config).unwrap(),
                config,
                device.clone(),
            )
        };
        let source = trainer(config(1, None)).unwrap();
        let mut written = source.state.gaussians.to_host();
        // Frames carry fitted Gaussians, not a fresh spread: make these unlike any seed's.
        for density in &mut written.raw_densities {
            *density += 0.5;
        }
        let grid = source.grid;
        let [nx, ny, nz] = grid.resolution();
        let folder = RunFolder::at(&dir.path().join("source"));
        folder
            .write_frame_state(
                7,
                &grid,
                &FrameState {
                    gaussians: written.clone(),
                    statics: None,
                    velocity: vec![0.0; nx * ny * nz * 3],
                    density: vec![0.0; nx * ny * nz],
                },
            )
            .unwrap();
        let path = folder.frame_state_path(7);
        let warm = trainer(config(2, Some(path.clone()))).unwrap();
        assert_eq!(warm.state.gaussians.to_host(), written);
        let cold = trainer(config(2, None)).unwrap();
        assert_ne!(cold.state.gaussians.to_host(), written);

        let refused = |config: TrainConfig| match trainer(config) {
            Err(err) => err.to_string(),
            Ok(_) => panic!("accepted"),
        };
        let other_count = refused(TrainConfig {
            gaussians: 400,
            ..config(2, Some(path.clone()))
        });
        assert!(
            other_count.contains("init_gaussians") && other_count.contains("holds 500"),
            "{other_count}"
        );
        let missing = refused(config(2, Some(dir.path().join("nothing.safetensors"))));
        assert!(
            missing.contains("init_gaussians") && missing.contains("no such file"),
            "{missing}"
        );
    }

    /// The share search finds the share of a move whose render the targets are, and runs with
    /// each `carrier_share` report what they chose.
    #[test]
    fn the_carrier_share_is_the_share_of_the_move_the_views_show() {
        use gausmoke_render::backends::device_by_name;
        let (_dir, data) = tiny_scene();
        let device = device_by_name("flex").unwrap().autodiff();
        let config = TrainConfig {
            gaussians: 500,
            grid_resolution: 8,
            frames: Some(2),
            init_iterations: 2,
            advect_iterations: 2,
            refine_iterations: 2,
            carrier_share: CarrierShare::Predicted,
            ..TrainConfig::default()
        };
        let sequence = Sequence::open(&data, &config).unwrap();
        let mut trainer = Trainer::new(sequence, config.clone(), device.clone()).unwrap();
        let previous = trainer.state.gaussians.means.val().detach();
        let [n, _] = previous.dims();
        // A rise of most of a cell, and a sideways drift.
        let cell = trainer.grid.cell_size();
        let step: Vec<f32> = (0..n)
            .flat_map(|_| [0.3 * cell.x, 0.8 * cell.y, 0.0])
            .collect();
        let carried =
            previous.clone() + Tensor::<2>::from_data(TensorData::new(step, [n, 3]), &device);
        let observations = &trainer.sequence.train[1];
        let cameras: Vec<Camera> = observations.iter().map(|o| o.camera).collect();
        for expected in [0.0, 0.5, 1.0, 1.5] {
            let means = previous.clone() + (carried.clone() - previous.clone()) * expected;
            let seen = trainer
                .scene(trainer.state.gaussians.tensors_at(means), false)
                .detach();
            let targets: Vec<Tensor<3>> = cameras
                .iter()
                .map(|camera| {
                    render_volume(&seen, camera, &trainer.background, &trainer.raster)
                        .unwrap()
                        .rgb
                })
                .collect();
            let (share, losses) = trainer
                .best_carried_share(&previous, &carried, &FITTED_SHARES, &cameras, &targets)
                .unwrap();
            assert_eq!(share, expected, "losses {losses:?}");
            assert_eq!(losses.len(), FITTED_SHARES.len());
            assert!(losses.iter().all(|l| l.is_finite()), "losses {losses:?}");
        }
        trainer.fit_first_frame().unwrap();
        let outcome = trainer.advance_to(1).unwrap();
        let share = outcome.carrier_share.expect("a share at frame 1");
        assert!(PREDICTED_SHARES.contains(&share), "share {share}");
        let explained = outcome.carrier_explained.expect("a prediction at frame 1");
        assert!((0.0..=1.0).contains(&explained), "explained {explained}");
        for carrier_share in [CarrierShare::Explained, CarrierShare::ExplainedOfBest] {
            let mut tied = Trainer::new(
                Sequence::open(&data, &config).unwrap(),
                TrainConfig {
                    carrier_share,
                    ..config.clone()
                },
                device.clone(),
            )
            .unwrap();
            tied.fit_first_frame().unwrap();
            let outcome = tied.advance_to(1).unwrap();
            assert_eq!(outcome.carrier_share, None, "the whole move");
            let explained = outcome.carrier_explained.expect("a prediction at frame 1");
            assert!((0.0..=1.0).contains(&explained), "explained {explained}");
            let best = if carrier_share == CarrierShare::ExplainedOfBest {
                explained
            } else {
                0.0
            };
            assert_eq!(tied.best_explained, best);
        }
        let mut fitted = Trainer::new(
            Sequence::open(&data, &config).unwrap(),
            TrainConfig {
                carrier_share: CarrierShare::Fitted,
                ..config.clone()
            },
            device.clone(),
        )
        .unwrap();
        fitted.fit_first_frame().unwrap();
        let share = fitted.advance_to(1).unwrap().carrier_share;
        assert!(
            share.is_some_and(|share| FITTED_SHARES.contains(&share)),
            "share {share:?}"
        );
    }

    /// A swirl of the centres (a move a velocity can make) comes back as that velocity,
    /// scaled by `refine_velocity_share`, where the Gaussians are.
    #[test]
    fn the_refinement_moves_become_a_share_of_the_velocity() {
        use gausmoke_model::sample_velocity;
        use gausmoke_render::backends::device_by_name;
        let (_dir, data) = tiny_scene();
        let device = device_by_name("flex").unwrap().autodiff();
        for share in [1.0f32, 0.5] {
            let config = TrainConfig {
                gaussians: 3000,
                grid_resolution: 8,
                frames: Some(2),
                refine_velocity_share: share,
                ..TrainConfig::default()
            };
            let sequence = Sequence::open(&data, &config).unwrap();
            let trainer = Trainer::new(sequence, config, device.clone()).unwrap();
            let grid = trainer.grid;
            let centres = trainer.state.gaussians.means.val().detach();
            let [n, _] = centres.dims();
            let middle = (grid.lo() + grid.hi()) * 0.5;
            // A tenth of a cell per world unit from the axis, about y.
            let rate = 0.1 * grid.cell_size().x;
            let swirl: Vec<f32> = read_floats(centres.clone())
                .chunks_exact(3)
                .flat_map(|p| [-(p[2] - middle.z) * rate, 0.0, (p[0] - middle.x) * rate])
                .collect();
            let swirl = Tensor::<2>::from_data(TensorData::new(swirl, [n, 3]), &device);
            let scale = GridScale::of(&grid, &trainer.state.gaussians.tensors());
            let [nx, ny, nz] = grid.resolution();
            let still = Tensor::<4>::zeros([nx, ny, nz, 3], &device);
            let field = trainer.move_field(&scale, swirl.clone());
            let (velocity, _) = trainer.with_refinement_moves(still, &field.field);
            let at_centres =
                sample_velocity(&grid, &velocity, &centres, Interpolation::Trilinear).velocity;
            // Away from the walls, which the swirl crosses near the box's corners and the
            // projection does not let it.
            let half = 0.3 * (grid.hi().x - grid.lo().x);
            let inner: Vec<f32> = read_floats(centres.clone())
                .chunks_exact(3)
                .map(|p| {
                    let inside = (p[0] - middle.x).abs() < half && (p[2] - middle.z).abs() < half;
                    f32::from(u8::from(inside))
                })
                .collect();
            let inner = Tensor::<2>::from_data(TensorData::new(inner, [n, 1]), &device);
            let expected = swirl.clone() * share * inner.clone();
            let miss = (at_centres * inner - expected.clone())
                .powi_scalar(2)
                .sum()
                .into_scalar::<f32>();
            let size = expected.powi_scalar(2).sum().into_scalar::<f32>();
            assert!(
                miss < 0.1 * size,
                "share {share}: squared miss {miss} against the move's {size}"
            );
            // The swirl is a flow, a gathering towards the middle is not.
            let gathering: Vec<f32> = read_floats(centres.clone())
                .chunks_exact(3)
                .flat_map(|p| {
                    [
                        -(p[0] - middle.x) * rate,
                        -(p[1] - middle.y) * rate,
                        -(p[2] - middle.z) * rate,
                    ]
                })
                .collect();
            let gathering = Tensor::<2>::from_data(TensorData::new(gathering, [n, 3]), &device);
            let flow_share = |moves: Tensor<2>| {
                let field = trainer.move_field(&scale, moves);
                field.split(read_floats(field.field.clone())).flow_share()
            };
            let swirl_share = flow_share(swirl.clone());
            let gathering_share = flow_share(gathering.clone());
            assert!(
                swirl_share > 0.7 && gathering_share < 0.1,
                "the projection keeps {swirl_share} of the swirl, {gathering_share} of the gathering"
            );
            // The same swirl with the gathering reversed: the flow parts persist, the
            // gathering parts turn round.
            let split = |moves: Tensor<2>| {
                let field = trainer.move_field(&scale, moves);
                field.split(read_floats(field.field.clone()))
            };
            let [flow, gathers] = split(swirl.clone() + gathering.clone())
                .persistence(&split(swirl.clone() - gathering));
            assert!(
                flow > 0.75 && gathers < -0.75,
                "persistence of the flow parts {flow}, of the gathering parts {gathers}"
            );
        }
    }

    /// `increment_horizontal_weight` scales what a sideways increment pays in the inertia
    /// prior and leaves what an upward one pays.
    #[test]
    fn the_inertia_prior_weighs_horizontal_increments_apart() {
        use gausmoke_render::backends::device_by_name;
        let (_dir, data) = tiny_scene();
        let device = device_by_name("flex").unwrap();
        let prior = |weight: f32, component: usize| {
            let config = TrainConfig {
                gaussians: 100,
                grid_resolution: 8,
                frames: Some(2),
                lambda_increment: 0.5,
                increment_horizontal_weight: weight,
                ..TrainConfig::default()
            };
            let sequence = Sequence::open(&data, &config).unwrap();
            let trainer = Trainer::new(sequence, config, device.clone()).unwrap();
            let cell = trainer.grid.cell_size().to_array()[component];
            let mut values = vec![0.0f32; 8 * 8 * 8 * 3];
            // One cell moves one cell's length along `component`.
            values[component] = cell;
            let delta = Tensor::<4>::from_data(TensorData::new(values, [8, 8, 8, 3]), &device);
            let sigma = Tensor::<3>::zeros([8, 8, 8], &device);
            read_scalar(trainer.inertia_prior(delta, sigma))
        };
        let one = 0.5 / 512.0;
        for (component, weight, want) in [
            (0, 1.0, one),
            (0, 10.0, 10.0 * one),
            (2, 10.0, 10.0 * one),
            (1, 10.0, one),
            (2, 0.0, 0.0),
        ] {
            let got = prior(weight, component);
            assert!(
                (got - want).abs() < 1e-6 * want.max(1.0),
                "component {component}, weight {weight}: {got} against {want}"
            );
        }
    }

    /// The smoothing keeps a uniform field, keeps an impulse's sum away from the walls and
    /// spreads it by sigma along each axis, each component on its own.
    #[test]
    fn the_move_field_is_smoothed_by_a_gaussian_of_sigma_cells() {
        // Wide enough that no cell the impulse reaches has a wall within reach.
        let resolution = [23, 23, 23];
        let cells = 23 * 23 * 23;
        let uniform: Vec<f32> = (0..cells).flat_map(|_| [0.5, -1.0, 2.0]).collect();
        let smooth = smoothed(&uniform, resolution, 3, 2.0, [true; 3]);
        assert!(
            smooth
                .iter()
                .zip(&uniform)
                .all(|(a, b)| (a - b).abs() < 1e-5)
        );
        let index = |x: usize, y: usize, z: usize| (x * 23 + y) * 23 + z;
        let mut impulse = vec![0.0f32; 3 * cells];
        impulse[3 * index(11, 11, 11) + 1] = 1.0;
        let sigma = 1.5;
        let smooth = smoothed(&impulse, resolution, 3, sigma, [true; 3]);
        let mut sum = 0.0f64;
        let mut second = [0.0f64; 3];
        for x in 0..23 {
            for y in 0..23 {
                for z in 0..23 {
                    let v = smooth[3 * index(x, y, z) + 1] as f64;
                    assert_eq!(smooth[3 * index(x, y, z)], 0.0);
                    assert_eq!(smooth[3 * index(x, y, z) + 2], 0.0);
                    sum += v;
                    let d = [x as f64 - 11.0, y as f64 - 11.0, z as f64 - 11.0];
                    second.iter_mut().zip(d).for_each(|(m, d)| *m += v * d * d);
                }
            }
        }
        assert!((sum - 1.0).abs() < 1e-5, "sum {sum}");
        // A sampled Gaussian cut at 3 sigma has a variance a little under sigma^2.
        for m in second {
            assert!(
                (m - 2.25).abs() < 0.1,
                "variance {m} against {}",
                sigma * sigma
            );
        }
    }

    /// The persistence of the refinement's moves is their correlation with the frame
    /// before's: 1 for the same moves, -1 for reversed ones, about 0 for unrelated ones,
    /// and rows that jumped this frame do not count.
    #[test]
    fn the_persistence_of_the_moves_is_their_correlation_with_the_frame_before() {
        let (_, device) = cpu_devices().into_iter().next().unwrap();
        let grid = GridSpec::new(Vec3::ZERO, Vec3::ONE, [8, 8, 8], 1).unwrap();
        let mut rng = SplitMix64::new(3);
        let n = 500;
        let mut random = |lo: f32, hi: f32| -> Tensor<2> {
            let values: Vec<f32> = (0..3 * n).map(|_| rng.range(lo, hi)).collect();
            Tensor::from_data(TensorData::new(values, [n, 3]), &device)
        };
        let centres = random(0.05, 0.95);
        let moves = random(-1.0, 1.0);
        let unrelated = random(-1.0, 1.0);
        let masses = Tensor::<1>::ones([n], &device);
        let scale = GridScale::new(&grid, centres, masses);
        let none = Tensor::<1>::zeros([n], &device);
        // Each frame's grid-scale field, in world units (a cell is an eighth of the box).
        let field_of = |m: Tensor<2>| MoveField {
            field: scale.cell_means(m / 8.0).reshape([8, 8, 8, 3]),
            grid: &grid,
            projection: ProjectionOptions::default(),
        };
        let field = field_of(moves.clone());
        // The field's share is the swirl test's business; still moves have none.
        let still = moves.clone() * 0.0;
        assert_eq!(
            refine_moves(&scale, still.clone(), None, &none, &field_of(still))
                .0
                .flow_share,
            0.0
        );
        let frame = |m: Tensor<2>| {
            let before = field_of(m.clone());
            FrameMoves {
                grid_part: scale.grid_part(m.clone()),
                moves: m,
                field: before.split(read_floats(before.field.clone())),
            }
        };
        let persistence = |before: Option<&FrameMoves>, jumped: &Tensor<1>| {
            refine_moves(&scale, moves.clone(), before, jumped, &field)
                .0
                .persistence
        };
        assert_eq!(persistence(None, &none), None);
        let field_persistence = |before: Option<&FrameMoves>| {
            refine_moves(&scale, moves.clone(), before, &none, &field)
                .0
                .field_persistence
        };
        assert_eq!(field_persistence(None), None);
        let close = |got: Option<[f64; 2]>, want: f64, tolerance: f64| {
            let got = got.expect("a frame before");
            assert!(
                got.iter().all(|g| (g - want).abs() < tolerance),
                "{got:?} against {want}"
            );
        };
        close(persistence(Some(&frame(moves.clone())), &none), 1.0, 1e-4);
        close(persistence(Some(&frame(-moves.clone())), &none), -1.0, 1e-4);
        // Both parts of the field, the flow and the gathering, follow the moves.
        close(field_persistence(Some(&frame(moves.clone()))), 1.0, 1e-4);
        close(field_persistence(Some(&frame(-moves.clone()))), -1.0, 1e-4);
        close(
            persistence(Some(&frame(unrelated.clone())), &none),
            0.0,
            0.15,
        );
        // The first half jumped, and only there did the moves change.
        let half: Vec<f32> = (0..n).map(|i| if i < n / 2 { 1.0 } else { 0.0 }).collect();
        let jumped = Tensor::<1>::from_data(TensorData::new(half.clone(), [n]), &device);
        let first_half = Tensor::<2>::from_data(TensorData::new(half, [n, 1]), &device);
        let changed = moves.clone() * (first_half.clone().neg() + 1.0) + unrelated * first_half;
        let persistence_of = |jumped: &Tensor<1>| {
            refine_moves(
                &scale,
                moves.clone(),
                Some(&frame(changed.clone())),
                jumped,
                &field,
            )
            .0
            .persistence
            .expect("a frame before")[0]
        };
        assert!((persistence_of(&jumped) - 1.0).abs() < 1e-4);
        assert!(persistence_of(&none) < 0.8);
    }

    /// The tensor form that keeps smoke centres out of obstacles against its host twin,
    /// `Obstacle::pushed_out`, for points in and around a sphere and a box.
    /// Buoyancy is what a multiple of the density in the upward component explains: such an
    /// increment leaves nothing, a sideways one is untouched, and of a mix only the part
    /// orthogonal to the density stays (worked by hand on a 2x2x1 grid).
    #[test]
    fn the_buoyancy_free_increment_leaves_what_density_cannot_explain() {
        let (_, device) = cpu_devices().into_iter().next().unwrap();
        let sigma = Tensor::<3>::from_data(
            TensorData::new(vec![1.0f32, 2.0, 0.0, 3.0], [2, 2, 1]),
            &device,
        );
        let field = |values: Vec<f32>| {
            Tensor::<4>::from_data(TensorData::new(values, [2, 2, 1, 3]), &device)
        };
        let read = |t: Tensor<4>| t.into_data().try_into_vec_as::<f32>().unwrap();
        // Upward 0.5 sigma: all buoyancy.
        let buoyant = field(vec![
            0.0, 0.5, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.5, 0.0,
        ]);
        let left = read(without_buoyancy(buoyant, sigma.clone()));
        assert!(left.iter().all(|v| v.abs() < 1e-6), "{left:?}");
        // Sideways: untouched.
        let sideways = vec![1.0, 0.0, -2.0, 0.5, 0.0, 0.0, 0.0, 0.0, 3.0, -1.0, 0.0, 0.0];
        assert_eq!(
            read(without_buoyancy(field(sideways.clone()), sigma.clone())),
            sideways
        );
        // Upward 1 everywhere: b = (1 + 2 + 3) / (1 + 4 + 9) = 3/7, leaving 1 - 3/7 sigma.
        let uniform = field(vec![
            0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0,
        ]);
        let left = read(without_buoyancy(uniform, sigma));
        let b = 3.0 / 7.0;
        let expected = [1.0 - b, 1.0 - 2.0 * b, 1.0, 1.0 - 3.0 * b];
        for (cell, want) in expected.iter().enumerate() {
            assert!(
                (left[3 * cell + 1] - want).abs() < 1e-6,
                "cell {cell}: {left:?}"
            );
            assert_eq!([left[3 * cell], left[3 * cell + 2]], [0.0, 0.0]);
        }
    }

    #[test]
    fn refinement_steps_take_the_views_in_turn() {
        for views in 1..=5 {
            for per_step in 0..=views + 1 {
                let all = per_step == 0 || per_step >= views;
                let mut seen = vec![0; views];
                let mut groups = std::collections::HashMap::new();
                for step in 0..3 * views {
                    let group = refinement_views(step, views, per_step);
                    assert_eq!(group.len(), if all { views } else { per_step });
                    // A group is fixed by its first view (it keys the list capacities).
                    let known = groups.entry(group[0]).or_insert_with(|| group.clone());
                    assert_eq!(*known, group, "{views} views, {per_step} per step");
                    for v in group {
                        seen[v] += 1;
                    }
                }
                // Over any whole number of turns every view is rendered equally often.
                let want = if all { 3 * views } else { 3 * per_step };
                assert!(
                    seen.iter().all(|&n| n == want),
                    "{views} views, {per_step} per step: {seen:?}"
                );
            }
        }
        assert_eq!(refinement_views(1, 4, 1), vec![1]);
        assert_eq!(refinement_views(1, 4, 3), vec![3, 0, 1]);
    }

    #[test]
    fn the_train_l1_of_a_frame_covers_every_view() {
        let row = |phase, render| LossRow {
            frame: 1,
            phase,
            iteration: 0,
            total: render,
            render,
            divergence: 0.0,
            advection: 0.0,
            refine: 0.0,
        };
        let rows = [
            row(Phase::Advect, 9.0),
            row(Phase::Refine, 1.0),
            row(Phase::Refine, 2.0),
            row(Phase::Refine, 4.0),
            row(Phase::Refine, 6.0),
        ];
        // All views per step: the last step's.
        assert_eq!(last_turn_l1(&rows, 3, 0), 6.0);
        assert_eq!(last_turn_l1(&rows, 3, 3), 6.0);
        // One of three per step: the last three steps'.
        assert_eq!(last_turn_l1(&rows, 3, 1), 4.0);
        // Fewer refinement steps than a turn: those there are, never the joint step's.
        assert_eq!(last_turn_l1(&rows[..3], 4, 1), 1.5);
        assert_eq!(last_turn_l1(&rows[..1], 4, 1), 9.0);
        assert!(last_turn_l1(&[], 4, 1).is_nan());
    }

    /// The statics' layer under a wall's surface: as deep as asked, and as large as the wall
    /// less its core.
    #[test]
    fn static_gaussians_start_in_a_layer_under_the_solids_surfaces() {
        let wall = Obstacle::Box {
            min: Vec3::new(-0.5, 0.0, -0.5),
            max: Vec3::new(0.5, 1.0, -0.42),
        };
        let bounds = (Vec3::new(-0.5, 0.0, -0.5), Vec3::new(0.5, 1.0, -0.42));
        let at_depth = |depth: f32| Vec3::new(0.0, 0.5, -0.42 - depth);
        for (depth, whole, layer) in [
            (0.01, true, true),
            (0.03, true, false),
            (-0.01, false, false),
        ] {
            assert_eq!(
                in_static_region(&[wall], None, at_depth(depth)),
                whole,
                "{depth}"
            );
            assert_eq!(
                in_static_region(&[wall], Some(0.02), at_depth(depth)),
                layer,
                "{depth}"
            );
        }
        let whole = static_region_volume(&[wall], None, bounds, 7);
        assert!((whole - 0.08).abs() < 1e-6, "{whole}");
        // 1 x 1 x 0.08 less its core 0.96 x 0.96 x 0.04.
        let expected = 0.08 - 0.96 * 0.96 * 0.04;
        let layer = static_region_volume(&[wall], Some(0.02), bounds, 7);
        assert!(
            (layer / expected - 1.0).abs() < 0.02,
            "{layer} against {expected}"
        );
    }

    #[test]
    fn centres_inside_obstacles_are_pushed_out_like_the_host_twin() {
        let obstacles = [
            Obstacle::Sphere {
                centre: Vec3::new(0.3, 0.5, 0.0),
                radius: 0.2,
            },
            Obstacle::Box {
                min: Vec3::new(-0.6, 0.1, -0.2),
                max: Vec3::new(-0.1, 0.4, 0.3),
            },
        ];
        let mut rng = SplitMix64::new(7);
        let points: Vec<Vec3> = (0..2000)
            .map(|_| {
                Vec3::new(
                    rng.range(-0.8, 0.8),
                    rng.range(0.0, 0.8),
                    rng.range(-0.4, 0.4),
                )
            })
            .collect();
        let expected: Vec<Vec3> = points
            .iter()
            .map(|&p| obstacles.iter().fold(p, |p, o| o.pushed_out(p)))
            .collect();
        let inside = points
            .iter()
            .filter(|p| obstacles.iter().any(|o| o.contains(**p)))
            .count();
        assert!(inside > 150, "only {inside} points inside");
        for (_, device) in cpu_devices() {
            let flat: Vec<f32> = points.iter().flat_map(|p| p.to_array()).collect();
            let means = Tensor::<2>::from_data(TensorData::new(flat, [points.len(), 3]), &device);
            let moved = outside_obstacles(means, &obstacles)
                .into_data()
                .try_into_vec_as::<f32>()
                .unwrap();
            for ((p, want), got) in points.iter().zip(&expected).zip(moved.chunks_exact(3)) {
                let got = Vec3::from_slice(got);
                assert!(
                    got.distance(*want) < 1e-5,
                    "{p} -> {got}, the host twin says {want}"
                );
                assert!(obstacles.iter().all(|o| !o.contains(got)), "{p} -> {got}");
            }
        }
    }
}
