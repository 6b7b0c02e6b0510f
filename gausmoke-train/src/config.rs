//! Training configuration: the paper's defaults (Sec. 5.1), every value overridable from a
//! TOML file and from `--set key=value` on the command line. The configuration actually used
//! is written next to the outputs (`config.toml`).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use gausmoke_model::projection::OpenFaces;

use crate::TrainError;

/// Learning rates of the frame-0 fit, per Gaussian attribute (3DGS practice: centres move
/// slowly, densities fast). Units: Adam step sizes in the parameter's own units.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InitLearningRates {
    /// World units; scaled by the box's largest side at run time.
    pub means: f64,
    pub rotations: f64,
    pub log_scales: f64,
    pub raw_densities: f64,
    pub colors: f64,
}

impl Default for InitLearningRates {
    fn default() -> Self {
        Self {
            means: 1.6e-3,
            rotations: 1e-3,
            log_scales: 5e-3,
            raw_densities: 5e-2,
            colors: 2.5e-3,
        }
    }
}

/// How the continuous velocity is interpolated from the grid (paper Eq. 11).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InterpolationKind {
    /// Normalised Gaussian kernel over 4x4x4 nodes, std 0.6 cells (the closed-form
    /// divergence of Eq. 12 applies).
    Gaussian,
    Trilinear,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum IntegratorKind {
    /// `p + dt u(p)`, paper Eq. 13.
    Euler,
    /// Explicit midpoint.
    Rk2,
}

/// Which form of the incompressibility projection `Pi` (paper Eq. 10) the run uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProjectionKind {
    /// Exact discrete Helmholtz projection (solid walls): a direct Poisson solve by separation
    /// of variables on the CPU backends, Jacobi-PCG on the device backends.
    Exact,
    /// The paper's penalty form: `penalty_steps` gradient steps on `|D u|^2 / 2`.
    Penalty,
}

/// The axes of the exported `.ply` files.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PlyAxes {
    /// The data set's world axes, as the grids and cameras use them.
    World,
    /// The world turned half a turn about x (y and z negated): the OpenCV/COLMAP camera
    /// frame that 3DGS training produces and splat viewers assume (SuperSplat shows such a
    /// file upright by turning it back), so a y-up world opens upright there.
    YDown,
}

/// How much of the joint iterations' transport the refinement starts from (see
/// `carrier_share`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CarrierShare {
    /// All of it, with the whole grid-scale tie (the paper's method).
    Whole,
    /// The share that paid in the frame's prediction: before the frame is fitted, the
    /// previous Gaussians are carried by the velocity Phi predicts and scaled back to each of
    /// the shares 0, 1/4, 1/2, 3/4 and 1 of that move; the share whose render is closest to
    /// the frame's training views is applied to the fitted move, and the grid-scale tie is
    /// weighted by it too.
    Predicted,
    /// The share of the fitted move itself that renders the frame's training views best, of
    /// 0, 1/4, ..., 2 (beyond 1 where the velocity is too slow), found after the joint
    /// iterations; the grid-scale tie is weighted by it up to 1.
    Fitted,
    /// The whole fitted move, with the grid-scale tie weighted by the share of the still
    /// prediction's loss (the previous Gaussians unmoved, against the frame's training views)
    /// that carrying them by the velocity Phi predicts removes: the tie holds the refinement
    /// to the transport as far as the transport's predictions pay.
    Explained,
    /// As `Explained`, with the share over the largest share any frame of the run has had so
    /// far (this one's included): the tie is whole while the predictions pay more and more,
    /// and loosens once they pay less than they did.
    ExplainedOfBest,
}

/// Whether the refinement holds one training view back (see `refine_held_view`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HeldView {
    /// Every training view is fitted (the paper's method).
    Off,
    /// View `t mod views` is left out of frame t's refinement, and the frame keeps the
    /// refinement's state at which that view's L1 was lowest.
    EarlyStop,
    /// View `t mod views` is left out and its L1 checked, but the frame keeps the last state:
    /// what leaving a view out costs without the stop.
    LeftOut,
}

/// Which velocity carries the Gaussians on from frame t+1 in the look-ahead (see
/// `lambda_lookahead` and `lookahead_frames`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LookaheadVelocity {
    /// Frame t's velocity, held for the frames further on.
    Held,
    /// The velocity Phi predicts for each further frame from the carried Gaussians' density
    /// there, projected.
    Predicted,
}

/// When emission at the source (`emission_fraction`) adds a frame's new Gaussians.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EmissionTiming {
    /// After the joint iterations: the box's loss to the velocity they fitted, so the
    /// joint iterations render the inflow as the carrier left it.
    AfterJoint,
    /// Before them: the box's loss to the carrier that starts the frame (the previous
    /// velocity, or the true one), and the new Gaussians stay where they are born through
    /// the joint iterations, so that the velocity is fitted to a filled inflow.
    BeforeJoint,
}

/// When the Gaussians' Adam state (its moment estimates) starts afresh (see
/// `gaussian_optimizer_reset`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OptimizerReset {
    /// Never: one state from frame 0's fit to the last frame.
    Never,
    /// Once, after frame 0's fit.
    AfterFirstFrame,
    /// At the start of every frame after frame 0.
    EveryFrame,
}

/// Which attributes `refine_view_agreement` masks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AgreementAttributes {
    /// Every attribute.
    All,
    /// The densities alone (what one view's rays ask of Gaussians at every depth); the other
    /// attributes take the mean of the views' gradients, as an all-view step does.
    Densities,
}

/// The image axes `refine_loss_blur` blurs the residual along.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BlurAxes {
    /// Along the rows and the columns.
    Both,
    /// Along the rows alone (across the columns): what differs from column to column, as
    /// vertical stripes do, is smoothed; a front's height is not.
    Horizontal,
}

/// What the velocity correction fits the frame's velocity to (see `correction_iterations`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CorrectionTarget {
    /// Each Gaussian's refined centre: the velocity carries every previous centre to it.
    Centres,
    /// The refined Gaussians' density on the grid: the velocity carries the previous centres
    /// so that their density matches it. A move no flow makes (Gaussians trading places
    /// inside the smoke) leaves the density as it is and so does not pull the velocity.
    Density,
}

/// What the density-motion fit (`velocity_from_density_motion`) starts from and is tied to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DensityMotionPrior {
    /// The previous frame's velocity carried along itself (as
    /// `xtask/reference/velocity_from_density.py --chain` tracks it).
    Carried,
    /// The frame's own velocity as the joint iterations fitted it to the pictures.
    Frame,
}

/// What the training does with obstacles the data set describes (PINF `obstacles`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Obstacles {
    /// Their cells become solid in the exact projection: no velocity inside, no flow through
    /// their surface.
    Solid,
    /// Ignored: the flow is free to pass through them (the paper's behaviour, an ablation).
    Ignore,
}

/// When the GPU projection's host learns that a solve converged
/// ([`gausmoke_model::ConvergenceTests`], spelled for TOML); the CPU backends solve directly
/// and ignore it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SolverTests {
    /// Solves run a learnt budget of iterations with no read and are judged with the losses.
    Deferred,
    /// Each solve reads its residuals while it runs (about 1.5 reads per solve).
    Immediate,
}

impl From<SolverTests> for gausmoke_model::ConvergenceTests {
    fn from(tests: SolverTests) -> Self {
        match tests {
            SolverTests::Deferred => Self::Deferred,
            SolverTests::Immediate => Self::Immediate,
        }
    }
}

/// How the GPU backward pass sums one splat's gradients over the pixels of a tile
/// ([`gausmoke_render::GradientSums`], spelled for TOML); the CPU backends ignore it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GradientSums {
    /// Plane (subgroup) sums, one atomic add per float per tile; per pixel on devices without
    /// plane operations.
    Planes,
    /// Shared-memory sums, for GPUs without plane operations.
    SharedMemory,
    /// One atomic add per contributing pixel.
    PerPixel,
}

impl From<GradientSums> for gausmoke_render::GradientSums {
    fn from(sums: GradientSums) -> Self {
        match sums {
            GradientSums::Planes => Self::Planes,
            GradientSums::SharedMemory => Self::SharedMemory,
            GradientSums::PerPixel => Self::PerPixel,
        }
    }
}

/// Keys that may differ when a run is resumed: they change how the rest of the run trains or
/// what it writes, not the shape or meaning of what is already trained. `frames` extends (or
/// shortens) the run; the learning rates let a run that diverged continue more gently.
pub const RESUMABLE_KEYS: &[&str] = &[
    "frames",
    "lr_velocity",
    "lr_gaussians",
    "lr_buoyancy",
    "lr_means",
    "lr_log_scales",
    "lr_colors",
    "lr_raw_densities",
    "lr_decay",
    "lr_decay_every",
    "output_every",
    "log_every",
    "ply_axes",
    "tensorboard",
    "sync_phase_timings",
    "gradient_sums",
    "tile_list_headroom",
    "solver_tests",
];

/// Largest weight of the density-motion fit's priors accepted (see [`TrainConfig::validate`]).
pub const MOST_DENSITY_MOTION_WEIGHT: f32 = 1e6;

/// Largest `time_frequencies` accepted (see [`TrainConfig::validate`]).
pub const MAX_TIME_FREQUENCIES: usize = 16;

/// Everything a training run needs besides the data set. Field names are the TOML keys.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Number of Gaussians, initialised uniformly inside the data set's smoke box.
    pub gaussians: usize,
    /// Static Gaussians for solids and background (issue 20; 0, the default, has none): the
    /// same primitives as the smoke's, rendered with them in one pass, but never advected,
    /// one set for every frame, placed inside the obstacles the data set describes (their
    /// centres stay there) or else spread through the box, fitted first to the training
    /// views' per-pixel minimum over time (where smoke, which only adds light, is absent at
    /// least once), then their shape, density and colour with the smoke at every step from
    /// frame 1 on (their centres stay). Phi and the physics see the smoke's density only.
    pub static_gaussians: usize,
    /// Steps of the static Gaussians' fit to the per-pixel minimum over time, before frame
    /// 0's; `None` (the default) takes `init_iterations`. What that fit leaves unexplained of
    /// a textured solid, frame 0's smoke Gaussians explain instead, as a layer on its surface.
    pub static_iterations: Option<usize>,
    /// Depth under the solids' surfaces, in world units, within which the static Gaussians
    /// start (and, their centres fixed, stay); `None` (the default) fills the solids. An
    /// opaque solid shows only its surface: a texture painted through its depth shifts with
    /// the view (parallax) and does not hold in a held-out one.
    pub static_shell: Option<f32>,
    /// Cells along each axis of the velocity/density grid (paper: 64). Must be a multiple
    /// of 4 (the U-Net halves it twice).
    pub grid_resolution: usize,
    /// Image size `[width, height]` the frames are resized to (area filter); `None` keeps
    /// the files' size.
    pub image_size: Option<[u32; 2]>,
    /// Train on the first `frames` frames only; `None` means all.
    pub frames: Option<usize>,
    /// Start at this frame of the data: the run's frame 0 is the videos' frame `first_frame`
    /// (with `frames = 1`, a static fit of that frame alone: the independent per-frame
    /// baseline). Needs `frames` when not 0.
    pub first_frame: usize,
    /// Frame 0's fit starts from the smoke Gaussians of a frame file a run wrote
    /// (`RUN/frames/frame_TTT.safetensors`) instead of spreading them through the box: a warm
    /// start. With `first_frame` and `frames = 1` it asks how much frame t's views add, in
    /// `init_iterations` more steps, to what a sequential run carried there. The file must hold
    /// `gaussians` of them; `None` (the default) spreads them.
    pub init_gaussians: Option<PathBuf>,
    /// Views to train on by name; `None` uses the data set's train split.
    pub train_views: Option<Vec<String>>,
    /// Held-out views by name; `None` uses the data set's test split.
    pub test_views: Option<Vec<String>>,
    /// Iterations of the static fit of frame 0.
    pub init_iterations: usize,
    pub init_learning_rates: InitLearningRates,
    /// K: joint physics-optical iterations per frame (Algorithm 1, lines 3-9).
    pub advect_iterations: usize,
    /// K': sub-grid refinement iterations per frame (lines 11-13).
    pub refine_iterations: usize,
    /// Training views each refinement step renders (ours; 0 = all of them, the paper's
    /// method): step i renders this many views in turn from view `i * refine_views_per_step`,
    /// wrapping around, so K' steps of one view render what K' / 4 steps of four do. The step's
    /// loss is the mean over its views; the frame's train L1, the mean over its last turn of
    /// steps (as many as there are views), which renders each view equally often.
    pub refine_views_per_step: usize,
    /// Refinement steps whose Gaussians are averaged into the frame's result (ours; 0 = the
    /// paper's method, the last step's state): the mean of every attribute over the last this
    /// many steps, at most K'. With one view a step the last step's state leans towards the
    /// last view fitted, the same view at every frame; a whole turn's mean weighs them alike.
    /// The frame's train L1 stays the steps' own.
    pub refine_average_steps: usize,
    /// One training view held back from each frame's refinement (ours; `off`, the paper's
    /// method, by default): with `early_stop`, view `t mod views` is not fitted by frame t's
    /// refinement, its L1 is checked before the first step and after each turn of the other
    /// views, and the frame keeps the state (static Gaussians included) where it was lowest;
    /// `left_out` checks it and keeps the last state. The joint iterations and frame 0's fit
    /// still fit every view.
    pub refine_held_view: HeldView,
    /// Records the held-out views' PSNR through each frame after frame 0 (ours, a diagnostic;
    /// off by default): the frame before's state where it stands, the state each joint
    /// iteration renders (carried by that iteration's velocity), and the refinement's state
    /// before its first step and after each turn of its views; `held_out_trace` in each
    /// frame's report. Nothing is fed back; the run learns what it learns without it.
    pub held_out_trace: bool,
    /// Sign agreement the training views must reach for a refinement step to move a
    /// Gaussian's parameter (ours; 0 = off, the paper's method): each step takes every view's
    /// gradient on its own and keeps each element of their mean where `|sum of the views'
    /// signs| >= refine_view_agreement * views` (1: every view agrees; 0.75: three of four,
    /// the fourth silent). What one view alone asks of Gaussians along its rays is what it
    /// cannot place in depth. The ties' gradients are added in full; static Gaussians are
    /// held during the refinement. Needs `refine_views_per_step = 0`; a step costs one render
    /// and backward per view.
    pub refine_view_agreement: f32,
    /// The attributes `refine_view_agreement` masks (`all` or `densities`).
    pub refine_view_agreement_attributes: AgreementAttributes,
    /// Standard deviation, in pixels, of a Gaussian blur on each view's residual before the
    /// refinement's L1 (ours; 0 = off, the paper's method). The refinement then fits what the
    /// views show at coarser scales and leaves finer detail to the carried state: four views
    /// cannot place it in depth, and a view's fine residual goes back along its rays as
    /// stripes. Frame 0's fit and the joint iterations keep the plain L1; the frame's train
    /// L1 is then the blurred residual's.
    pub refine_loss_blur: f32,
    /// The image axes `refine_loss_blur` acts along (`both` or `horizontal`).
    pub refine_loss_blur_axes: BlurAxes,
    /// Standard deviation, in pixels, of a Gaussian blur on each view's residual in the first
    /// joint iteration (ours; 0 = off, the paper's method), shrinking linearly to none at the
    /// last. Coarse to fine: a photometric gradient reaches only as far as the Gaussians
    /// overlap their targets, so smoke that moves further than that between frames pulls
    /// the velocity too little; the blurred residual reaches further. The look-ahead's
    /// frames are blurred alike.
    pub joint_loss_blur: f32,
    /// With `joint_loss_blur`, only the velocity fits the blurred residual; the joint
    /// iterations' steps on the Gaussians' own attributes fit the plain one (a second render
    /// of each view per blurred iteration).
    pub joint_loss_blur_velocity_only: bool,
    /// Adam learning rate of the velocity network Phi.
    pub lr_velocity: f64,
    /// Adam learning rate of the Gaussians after frame 0.
    pub lr_gaussians: f64,
    /// Adam learning rate of the Gaussians' centres in the refinement after frame 0 (ours;
    /// decays with the others; world units, as `lr_gaussians`); unset, `lr_gaussians`. 0
    /// leaves every centre where the velocity carried it.
    pub lr_means: Option<f64>,
    /// Adam learning rate of the Gaussians' log-scales after frame 0 (ours; decays with the
    /// others); unset, `lr_gaussians`. 0 keeps every Gaussian's size from frame 0 on.
    pub lr_log_scales: Option<f64>,
    /// Adam learning rate of the Gaussians' colours after frame 0 (ours; decays with the
    /// others); unset, `lr_gaussians`. 0 keeps every Gaussian's colour from frame 0 on.
    pub lr_colors: Option<f64>,
    /// Adam learning rate of the Gaussians' raw densities after frame 0 (ours; decays with
    /// the others); unset, `lr_gaussians`.
    pub lr_raw_densities: Option<f64>,
    /// The learning rates after frame 0 are multiplied by `lr_decay` every `lr_decay_every`
    /// frames.
    pub lr_decay: f64,
    pub lr_decay_every: usize,
    pub lambda_div: f32,
    pub lambda_adv: f32,
    pub lambda_refine: f32,
    /// Weights of ties on the two parts of the refinement's move (ours; 0 = the paper's
    /// method, which ties the whole move by `lambda_refine`): its grid-scale part, the
    /// mass-weighted mean move around each cell of the velocity grid (a move the velocity
    /// could have made), and the sub-grid rest (each Gaussian on its own). Mass-weighted
    /// means of squared lengths in world units, as `L_refine`
    /// (see `gausmoke_model::GridScale`).
    pub lambda_refine_grid: f32,
    pub lambda_refine_subgrid: f32,
    /// Weight of a tie on the refinement's change of each Gaussian's density (ours; 0 = the
    /// paper's method, whose refinement fits densities freely): the mean squared change of
    /// `ln sigma` from where the refinement started. A change the training views ask for
    /// outweighs it; one they do not see (detail they cannot place in depth) is pulled back.
    pub lambda_refine_density: f32,
    /// Weight of a look-ahead render term in the refinement (ours; 0 = the paper's method):
    /// at each refinement step the refined Gaussians are also carried one frame on and
    /// rendered against the same training views of frame t+1, so what the refinement places
    /// must also explain the next frame's pictures once carried. Not applied at the last
    /// frame, nor with `refine_view_agreement`.
    pub lambda_refine_lookahead: f32,
    /// The carrier of that term: `"held"`, the frame's fitted velocity, or `"predicted"`,
    /// Phi's prediction for frame t+1 from the refinement's starting state; unset, the one
    /// `lookahead_velocity` names.
    pub refine_lookahead_velocity: Option<LookaheadVelocity>,
    /// Weight of a look-ahead render term in the joint iterations (ours; 0 = the paper's
    /// method): the Gaussians carried to frame t are carried on by the same velocity to
    /// frame t+1 (and on: `lookahead_frames`) and rendered against those frames' training
    /// views, so the velocity of frame t must also explain the next frames' pictures (their
    /// attributes are held fixed in that term: it trains the velocity only). Not applied at
    /// the last frame.
    pub lambda_lookahead: f32,
    /// The velocity of each look-ahead step past frame t: `"held"` or `"predicted"`.
    pub lookahead_velocity: LookaheadVelocity,
    /// How many frames past t the look-ahead carries the Gaussians (each step by the
    /// velocity `lookahead_velocity` names, rendered against that frame's training views with
    /// weight `lambda_lookahead`), so that frame t's velocity is fitted to this many more
    /// frames' pictures; steps past the last frame are dropped. 1 by default.
    pub lookahead_frames: usize,
    /// Let the look-ahead train the Gaussians too (ours; `false` = it trains the velocity
    /// only): their shape, density and colour keep the gradient of the look-ahead's render,
    /// so that one carried structure is fitted to the views of frame t and of the frames
    /// after it. Needs `lambda_lookahead > 0`.
    pub lookahead_appearance: bool,
    /// Weight of a kinetic-energy prior in the joint iterations (ours; 0 = the paper's
    /// method): the mean over the grid's cells of `|u^t|^2`, the velocity in cells per frame,
    /// so nothing but the pictures pushes the speed up (hypothesis 3 of issue 18: the
    /// look-ahead's velocity overshoots).
    pub lambda_kinetic: f32,
    /// Carry the previous frame's velocity along itself before Phi's increment (ours; `false`
    /// = the paper's Eq. 9): `u^t = Pi(A(u^{t-1}) + Phi(A(u^{t-1}), sigma, t))` with `A`
    /// semi-Lagrangian transport over `dt` (see `gausmoke_model::transport_velocity`), so
    /// momentum moves with the flow instead of staying at the cell where it was fitted.
    /// The look-ahead's predicted second step does not transport.
    pub transport_velocity: bool,
    /// Weight of an inertia prior in the joint iterations (ours; 0 = the paper's method): the
    /// mean over the grid's cells of `|Phi's increment|^2`, in cells per frame, so the
    /// velocity keeps what it had (carried along itself with `transport_velocity`) unless the
    /// pictures ask for a change.
    pub lambda_increment: f32,
    /// Leave buoyancy out of the inertia prior (ours; `false` = all of the increment counts):
    /// before `lambda_increment` weighs Phi's increment, the part of its upward component
    /// that is proportional to the density (`b sigma`, with `b` the least-squares fit over
    /// the grid at each iteration) is taken out, so the velocity may accelerate where there
    /// is smoke, as buoyancy does, at no cost, while any other change still pays.
    pub buoyancy_free_increment: bool,
    /// Weight of the increment's horizontal components (x and z, across the upward y) in the
    /// inertia prior, against 1 for the vertical one (ours; 1 = all alike): above 1 the
    /// velocity's horizontal flow changes mostly through `Pi`, as continuity makes it from
    /// the vertical flow, rather than freely where the views do not pin it. In [0, 1000];
    /// needs `lambda_increment`.
    pub increment_horizontal_weight: f32,
    /// Add an explicit buoyancy force to the velocity update (ours; `false` = the paper's
    /// method): `u^t = Pi(u' + Phi(u', sigma, t) + b sigma / max(sigma) e_y)`, `u'` the
    /// previous velocity (transported with `transport_velocity`), `sigma` the previous
    /// centres' density, one coefficient `b` for the whole run, starting at 0 and fitted to
    /// the pictures in the joint iterations (see `gausmoke_model::BuoyancyForce`).
    /// The look-ahead's predicted steps and the velocity correction use it too.
    pub buoyancy_force: bool,
    /// Adam's learning rate for `b` (world units per frame per step; decays with the
    /// others).
    pub lr_buoyancy: f64,
    /// Steps fitting Phi, after each frame's refinement, so that the frame's velocity carries
    /// the previous centres to the refined ones (ours; 0 = the paper's method, where what the
    /// refinement finds never reaches the velocity).
    pub correction_iterations: usize,
    /// What those steps fit: `centres` (each Gaussian's refined centre) or `density` (the
    /// refined Gaussians' density on the grid). Either way Phi's increment also pays the
    /// inertia prior (`lambda_increment`) there, as in the joint iterations.
    pub correction_target: CorrectionTarget,
    /// Share of the refinement's move, at the velocity grid's scale, added to the frame's
    /// velocity as a velocity (ours; 0 = the paper's method): after the refinement, at each
    /// cell the mass-weighted mean move of the Gaussians around it, times this share over
    /// `dt`, is added and the sum projected again, so the motion the pictures asked for and
    /// the velocity missed is carried on to the next frame. Phi is not changed. In [0, 1],
    /// or up to 4 with `refine_velocity_blur` (the moves' large scale under-states the
    /// velocity's error there: the refinement is tied to where transport put the Gaussians).
    pub refine_velocity_share: f32,
    /// Width (standard deviation, in cells) of a Gaussian smoothing of that move field before
    /// it is carried on (ours; 0 = none): only the moves' large scale follows the velocity's
    /// error, their grid-scale detail does not. In [0, 8]; needs `refine_velocity_share`.
    pub refine_velocity_blur: f32,
    /// How much of the fitted transport the refinement starts from and is tied to (ours;
    /// `"whole"` = the paper's method; `"predicted"`: the share that the frame's prediction
    /// earned; `"fitted"`: the share of the fitted move that fits the frame's views best;
    /// `"explained"`: the whole move, tied as far as its prediction paid;
    /// `"explained_of_best"`: that against the best any frame has paid; see
    /// [`CarrierShare`]), so that a carrier whose predictions stop paying stops moving the
    /// smoke and stops holding the refinement's grid-scale moves back. On the long plume the
    /// training views endorse the transport at every frame, and none of these helps
    /// (docs/RESULTS.md).
    pub carrier_share: CarrierShare,
    /// After each frame's refinement, refit the frame's velocity on the grid so that one
    /// semi-Lagrangian step of it carries the density of frame t-1's Gaussians onto that of
    /// the refined ones (ours, the `density_motion` module; `false` = the paper's method, where
    /// the velocity is what the joint iterations fitted through the Gaussians' centres). The
    /// fit starts from, and is tied to, `density_motion_prior` (by default the previous
    /// frame's velocity carried along itself); cells in the inflow box (`respawn_region`) are
    /// left out of its data term. The result is projected by `Pi` (which also holds solid
    /// obstacles; the fit itself does not model them). Phi is not changed. On the long plume
    /// it makes the velocity truer and costs the pictures and the 3D density (docs/RESULTS.md,
    /// "Why we fall short", item 1).
    pub velocity_from_density_motion: bool,
    /// Weight of that fit's smoothness prior (`|grad u|^2`, u in cells per step, densities
    /// divided by their largest value).
    pub density_motion_smoothness: f32,
    /// Weight of that fit's divergence prior (`|div u|^2`).
    pub density_motion_divergence: f32,
    /// Weight of that fit's tie to its prior (`density_motion_prior`).
    pub density_motion_inertia: f32,
    /// What that fit starts from and is tied to: `carried` (the previous frame's velocity
    /// carried along itself) or `frame` (the frame's velocity from the joint iterations).
    pub density_motion_prior: DensityMotionPrior,
    /// Time step of the velocity update and advection, in frames.
    pub dt: f32,
    /// Channels of the U-Net's first level.
    pub unet_channels: usize,
    /// Sinusoidal time-encoding frequencies L of PE(t).
    pub time_frequencies: usize,
    pub interpolation: InterpolationKind,
    pub integrator: IntegratorKind,
    /// Share of the flow's deformation each carried Gaussian's shape takes, from frame 1 on
    /// (ours, `gausmoke_model::deform`; 0, the default, is the paper's Eq. 13, which moves
    /// the centres and keeps the shapes): after the joint iterations each covariance becomes
    /// `F Sigma F^T`, `F` the volume-preserving deformation of a step of `shape_transport * dt`
    /// frames of the fitted velocity at the Gaussian's centre, so that smoke the flow strains
    /// or turns arrives strained or turned. In [0, 1].
    pub shape_transport: f32,
    /// Longest over shortest standard deviation beyond which that transport strains no
    /// Gaussian (one already longer is not strained further, nor shortened). 0, the default,
    /// sets no bound; otherwise at least 1.
    pub shape_transport_max_elongation: f32,
    /// Width (standard deviation, in velocity-grid cells) of a Gaussian smoothing of the
    /// carried velocity before each frame's update, from frame 1 on (ours; 0, the default,
    /// is the paper's method): a viscosity against structure finer than the views can fit,
    /// which the fitted velocity's strain shows (`xtask/reference/strain_diagnosis.py`);
    /// the update's projection follows it. In [0, 4].
    pub velocity_smoothing_cells: f32,
    /// Form of `Pi`: `exact` (default) or `penalty` (the paper's description).
    pub projection: ProjectionKind,
    /// Relative residual at which the exact projection's PCG solve stops (device backends
    /// only: the CPU backends solve directly, to a residual near 1e-14).
    pub projection_tolerance: f64,
    /// Iteration cap of that PCG solve (device backends only).
    pub projection_max_iterations: usize,
    /// Gradient steps of the penalty form (`projection = "penalty"`), each with step size
    /// `1 / sum_a h_a^-2`.
    pub penalty_steps: usize,
    /// Box faces the flow may cross (`x-`, `x+`, `y-`, `y+`, `z-`, `z+`; `y+` is the top of
    /// a box with y up); the others are solid walls. Exact projection only.
    pub open_faces: Vec<String>,
    /// The velocity on the open faces as a fraction of the cell's inside them, in (0, 1]:
    /// 1 (the default) a zero-gradient outflow; 0.5 the mean of the cell's velocity and a
    /// still cell's outside, the discrete top of a collocated solver that reads zero velocity
    /// above an open face (the synthetic generator's). Needs open faces.
    pub open_face_flow: f32,
    /// Obstacles described by the data set: `"solid"` (default; no flow into them, exact
    /// projection only) or `"ignore"`.
    pub obstacles: Obstacles,
    /// Ablation switch: `false` drops L_div and L_adv (paper Table 3, "w/o physics").
    pub physics_losses: bool,
    /// Ablation switch: `false` skips the K' refinement iterations ("w/o refinement").
    pub refinement: bool,
    /// Ablation switch: `false` replaces Beer-Lambert volumetric alpha with 3DGS's splat
    /// alpha, an opacity times the projected 2D Gaussian ("w/o volumetric rendering"; see
    /// `gausmoke_render::AlphaModel::SplatOpacity`).
    pub volumetric: bool,
    /// The renderer skips a Gaussian on a ray where its alpha is below this (3DGS's 1/255,
    /// the default). A skipped Gaussian gets no gradient from that pixel, so one fitted
    /// below it in every view is frozen there while still carried and splatted into the
    /// density grid. Thin smoke's Gaussians sit close to 1/255. In (0, 1/255].
    pub alpha_min: f32,
    /// The density grid (Phi's input, `L_adv`, the look-ahead, the exports and the
    /// evaluation) counts only the Gaussians the renderer can see: those whose peak alpha
    /// reaches `alpha_min` on some ray. Off (the default, the paper's method): every one,
    /// including those frozen under the cull.
    pub density_grid_rendered_only: bool,
    /// Most Gaussians moved per frame, as a fraction of all, from the box's faces and from
    /// invisibility to where the training views show missing smoke (`respawn` module). 0 is
    /// the paper's method (a fixed set, only advected).
    pub respawn_fraction: f32,
    /// Smallest smoke deficit (image units in `[0, 1]`) a place must show in every training
    /// view to receive recycled Gaussians.
    pub respawn_threshold: f32,
    /// With `q > 0`, recycled Gaussians go only to cells next to (within one cell of) a cell
    /// whose density, splatted from the Gaussians carried to the frame, is at least `q` times
    /// its largest value: new smoke appears beside smoke, not in the empty parts of the
    /// training views' visual hull. 0 lets every cell receive them.
    pub respawn_near_smoke: f32,
    /// `[x0, y0, z0, x1, y1, z1]`, fractions of the smoke box (its low corner, then its high
    /// one): recycled Gaussians go only to cells whose centre lies in this box, such as the
    /// inflow where a source feeds the plume, so that new smoke enters where it does and is
    /// not placed anywhere in the training views' visual hull. Unset admits the whole box.
    /// It is also the inflow box that `emission_fraction` emits into.
    pub respawn_region: Option<[f32; 6]>,
    /// Most Gaussians emitted per frame at the source, as a fraction of all (ours, `emission`
    /// module; 0, the default, emits none). At each frame (when: `emission_timing`), the density
    /// the carrier took out of the inflow box (`respawn_region`, required; its net loss
    /// since frame t-1) is emitted back into the cells that lost it as new Gaussians as heavy
    /// as their neighbours, in rows recycling would take: a steady source holds its inflow's
    /// density whatever the speed of the flow through it.
    pub emission_fraction: f32,
    /// When the emitted Gaussians are added (`after_joint`, the default, or
    /// `before_joint`; see [`EmissionTiming`]).
    pub emission_timing: EmissionTiming,
    /// Most Gaussians split per frame, as a fraction of all (ours, `split` module): the
    /// largest opaque ones become two halves with the same mass, mean and covariance, the
    /// second half in a row that recycling would take (on a box face, or invisible), after
    /// the frame's joint iterations so that the refinement fits them. 0 is the paper's
    /// method.
    pub split_fraction: f32,
    /// Only Gaussians whose longest standard deviation exceeds this multiple of the
    /// initialisation's (`0.5 (V / N)^(1/3)` for a box of volume `V` and `N` Gaussians) are
    /// split.
    pub split_size_factor: f32,
    /// Split only into rows on a box face (Gaussians that left the box), not into invisible
    /// ones.
    pub split_into_faces_only: bool,
    /// Share of the way each carried Gaussian's density moves, before each frame's fit from
    /// frame 1 on, towards the carried density smoothed horizontally around its centre (ours,
    /// `carried_smoothing` module; 0, the default, is the paper's method): detail the
    /// training views cannot place in depth fades by `1 - carried_smoothing` a frame instead
    /// of being carried up the column, while what the views see is fitted back. In [0, 1].
    pub carried_smoothing: f32,
    /// Width (standard deviation, in velocity-grid cells, along x and z) of that smoothing.
    /// In (0, 8].
    pub carried_smoothing_cells: f32,
    /// Variance, in velocity-grid cells squared, that each carried Gaussian gains along each
    /// of its axes before each frame's fit from frame 1 on (ours, `carried_smoothing` module;
    /// 0, the default, is the paper's method): Gaussians carried as particles keep detail
    /// that a grid-resampled flow of smoke loses a little of every frame. Capped by
    /// `max_size_factor`. In [0, 4].
    pub carried_growth: f32,
    /// From frame 1 on, no smoke Gaussian's standard deviation falls below this multiple of
    /// the initialisation's (`0.5 (V / N)^(1/3)`, as for `split_size_factor`) after an
    /// optimiser step; frame 0's fit, and so the independent per-frame baseline, has no
    /// floor. 0 (the default, the paper's method) sets none. A prior against detail the
    /// training views cannot place in depth. In [0, 10].
    pub min_size_factor: f32,
    /// From frame 1 on, no smoke Gaussian's standard deviation grows above this multiple of
    /// the initialisation's after an optimiser step (frame 0, and so the independent
    /// per-frame baseline, has no ceiling). 0 (the default, the paper's method) sets none.
    /// Against the carried Gaussians' growth, which smooths the density over a video. 0 or
    /// in [1, 100], and not below `min_size_factor`.
    pub max_size_factor: f32,
    /// One colour for every smoke Gaussian, fitted like the per-Gaussian ones (their mean is
    /// what renders, so each step moves all alike): an emission-absorption medium of one
    /// albedo under even light, as the synthetic scenes are rendered, leaves the views only
    /// the density to explain. Off (the default, the paper's method): a colour per Gaussian.
    /// Frame 0 and so the independent per-frame baseline use it too.
    pub uniform_color: bool,
    /// When the smoke Gaussians' Adam state starts afresh (ours): `"never"` (the default),
    /// `"after_first_frame"` or `"every_frame"`. Adam divides each step by a running mean of
    /// the squared gradients with a memory of about a thousand steps, so kept from frame 0's
    /// fit it shapes the step sizes of the frames after it; a fresh state's first step moves
    /// every parameter by the learning rate. Measured on the long plume: within the seeds'
    /// spread after frame 0, worse at every frame (docs/RESULTS.md, issue 18's item).
    pub gaussian_optimizer_reset: OptimizerReset,
    /// From frame 1 on, Adam's epsilon for the smoke Gaussians relative to each attribute's
    /// gradient (ours; 0 = off: the tiny absolute epsilon of 3DGS practice throughout).
    /// Each attribute's gradient is divided by its root mean square over the Gaussians at
    /// that step and Adam's state starts afresh after frame 0 with this epsilon. Adam then
    /// moves a parameter by about the learning rate only where its gradient is large beside
    /// the others', and in proportion to it elsewhere, as plain gradient descent does, so a
    /// fit keeps more of the carried state where the views say little (a step of plain
    /// Adam moves every parameter by about the learning rate whatever its gradient).
    /// In [0, 100].
    pub relative_adam_epsilon: f32,
    /// A diagnostic for synthetic scenes (ours; off by default): from frame 1 on, the joint
    /// iterations carry the Gaussians along the data set's true velocity of frame t
    /// (`gt/frame_TTT.safetensors`, on a grid of `grid_resolution` cells) instead of Phi's,
    /// and it is the frame's velocity; everything else trains as configured (Phi too, but
    /// it carries nothing). What a perfect velocity would give the rest of the method.
    /// Refused for a data set without that ground truth.
    pub velocity_from_ground_truth: bool,
    /// With `velocity_from_ground_truth`, the true velocity is scaled by this (1, the
    /// default: as it is): the truth's flow at another speed. In [0, 10].
    pub ground_truth_velocity_scale: f32,
    /// Seed of the Gaussians' initialisation.
    pub seed: u64,
    /// Write renders, exports and velocity slices every this many frames (1 = all).
    pub output_every: usize,
    /// Read the losses and checks of the optimisation steps back from the device every this
    /// many steps (and at the end of each frame's loops), in one read: a read waits for the
    /// GPU to drain its queue. A non-finite loss or a bad parameter is reported at that read,
    /// naming the step where it first appeared. Every step's losses are still logged.
    pub log_every: usize,
    /// Axes of the exported Gaussians (`exports/gaussians_TTT.ply`): `"world"` or
    /// `"y-down"` (for splat viewers; see [`PlyAxes`]).
    pub ply_axes: PlyAxes,
    /// Also write TensorBoard event files (`RUN/tensorboard/`): per-frame metrics, every
    /// optimisation step's losses and the held-out comparison picture of each output frame.
    pub tensorboard: bool,
    /// Wait for the device at both ends of every timed phase, so the per-phase times in
    /// `metrics.json` charge GPU work to the phase that queued it. Slows GPU runs; changes
    /// nothing on the CPU backends, which run eagerly.
    pub sync_phase_timings: bool,
    /// How the GPU backward sums gradients over a tile: `"planes"` (default), `"shared-memory"`
    /// or `"per-pixel"` (see [`GradientSums`]). The forms differ only in the order of float
    /// additions, so a run may be resumed with another.
    pub gradient_sums: GradientSums,
    /// GPU backends: each optimisation loop measures its views' tile-list lengths at its first
    /// step and after each read of its log (every `log_every` steps), and gives the renders
    /// until the next measurement this many times that room, so no render reads its length
    /// back. A step that needs more stops the run with an error naming it (raise this and
    /// resume). The CPU backends have no list buffer and ignore it.
    pub tile_list_headroom: f32,
    /// GPU backends: `"deferred"` (default; no read per solve: the solves' iteration budgets
    /// are learnt from the last ones, the iterations past convergence cost launches that do no
    /// work, and the verdicts come back with the losses) or `"immediate"` (about 1.5 reads per
    /// solve, no wasted launches). Which is faster depends on the GPU's read latency against
    /// its launch cost; the results agree to the solver's tolerance.
    pub solver_tests: SolverTests,
}

impl Default for TrainConfig {
    /// The paper's settings (Sec. 5.1) for ScalarFlow-like data.
    fn default() -> Self {
        Self {
            gaussians: 30_000,
            static_gaussians: 0,
            static_iterations: None,
            static_shell: None,
            grid_resolution: 64,
            image_size: None,
            frames: None,
            first_frame: 0,
            init_gaussians: None,
            train_views: None,
            test_views: None,
            init_iterations: 2000,
            init_learning_rates: InitLearningRates::default(),
            advect_iterations: 250,
            refine_iterations: 50,
            refine_views_per_step: 0,
            refine_average_steps: 0,
            refine_held_view: HeldView::Off,
            held_out_trace: false,
            refine_view_agreement: 0.0,
            refine_view_agreement_attributes: AgreementAttributes::All,
            refine_loss_blur: 0.0,
            refine_loss_blur_axes: BlurAxes::Both,
            joint_loss_blur: 0.0,
            joint_loss_blur_velocity_only: false,
            lr_velocity: 1e-3,
            lr_gaussians: 5e-4,
            lr_means: None,
            lr_log_scales: None,
            lr_colors: None,
            lr_raw_densities: None,
            lr_decay: 0.95,
            lr_decay_every: 10,
            lambda_div: 0.02,
            lambda_adv: 0.02,
            lambda_refine: 0.01,
            lambda_refine_grid: 0.0,
            lambda_refine_subgrid: 0.0,
            lambda_refine_density: 0.0,
            lambda_refine_lookahead: 0.0,
            refine_lookahead_velocity: None,
            lambda_lookahead: 0.0,
            lookahead_velocity: LookaheadVelocity::Held,
            lookahead_frames: 1,
            lookahead_appearance: false,
            lambda_kinetic: 0.0,
            transport_velocity: false,
            lambda_increment: 0.0,
            buoyancy_free_increment: false,
            increment_horizontal_weight: 1.0,
            buoyancy_force: false,
            lr_buoyancy: 3e-4,
            correction_iterations: 0,
            correction_target: CorrectionTarget::Centres,
            refine_velocity_share: 0.0,
            refine_velocity_blur: 0.0,
            carrier_share: CarrierShare::Whole,
            velocity_from_density_motion: false,
            density_motion_smoothness: 0.001,
            density_motion_divergence: 1000.0,
            density_motion_inertia: 0.01,
            density_motion_prior: DensityMotionPrior::Carried,
            dt: 1.0,
            unet_channels: 16,
            time_frequencies: 4,
            interpolation: InterpolationKind::Gaussian,
            integrator: IntegratorKind::Euler,
            shape_transport: 0.0,
            velocity_smoothing_cells: 0.0,
            shape_transport_max_elongation: 0.0,
            projection: ProjectionKind::Exact,
            projection_tolerance: 1e-5,
            projection_max_iterations: 400,
            penalty_steps: 20,
            open_faces: Vec::new(),
            open_face_flow: 1.0,
            obstacles: Obstacles::Solid,
            physics_losses: true,
            refinement: true,
            volumetric: true,
            alpha_min: 1.0 / 255.0,
            density_grid_rendered_only: false,
            respawn_fraction: 0.0,
            respawn_threshold: 0.05,
            respawn_near_smoke: 0.0,
            respawn_region: None,
            emission_fraction: 0.0,
            emission_timing: EmissionTiming::AfterJoint,
            split_fraction: 0.0,
            split_size_factor: 1.0,
            split_into_faces_only: false,
            carried_smoothing: 0.0,
            carried_smoothing_cells: 1.0,
            carried_growth: 0.0,
            min_size_factor: 0.0,
            max_size_factor: 0.0,
            uniform_color: false,
            gaussian_optimizer_reset: OptimizerReset::Never,
            relative_adam_epsilon: 0.0,
            velocity_from_ground_truth: false,
            ground_truth_velocity_scale: 1.0,
            seed: 2026,
            output_every: 1,
            log_every: 10,
            ply_axes: PlyAxes::World,
            tensorboard: false,
            sync_phase_timings: false,
            gradient_sums: GradientSums::Planes,
            tile_list_headroom: 1.5,
            solver_tests: SolverTests::Deferred,
        }
    }
}

impl TrainConfig {
    /// A few-minute CPU run on the tiny synthetic scene: the whole pipeline, small.
    pub fn quick_demo() -> Self {
        Self {
            gaussians: 2000,
            grid_resolution: 16,
            init_iterations: 150,
            advect_iterations: 40,
            refine_iterations: 10,
            lr_velocity: 2e-3,
            lr_gaussians: 2e-3,
            unet_channels: 8,
            time_frequencies: 2,
            ..Self::default()
        }
    }

    /// Reads a TOML file; keys it does not name keep their defaults.
    pub fn from_toml_file(path: &Path) -> Result<Self, TrainError> {
        let text = std::fs::read_to_string(path).map_err(|source| TrainError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        toml::from_str(&text).map_err(|e| TrainError::Config {
            origin: path.display().to_string(),
            reason: e.to_string(),
        })
    }

    /// Applies `key=value` overrides (`value` in TOML syntax, e.g. `lambda_div=0.05`,
    /// `image_size=[135, 240]`, `init_learning_rates.means=1e-3`).
    pub fn with_overrides(self, overrides: &[String]) -> Result<Self, TrainError> {
        if overrides.is_empty() {
            return Ok(self);
        }
        let mut table = toml::Table::try_from(&self).map_err(|e| TrainError::Config {
            origin: "configuration".into(),
            reason: e.to_string(),
        })?;
        for entry in overrides {
            let bad = |reason: String| TrainError::Config {
                origin: format!("--set {entry}"),
                reason,
            };
            let (key, value) = entry
                .split_once('=')
                .ok_or_else(|| bad("expected KEY=VALUE".into()))?;
            let parsed: toml::Table = toml::from_str(&format!("v = {}", value.trim()))
                .or_else(|_| toml::from_str(&format!("v = \"{}\"", value.trim())))
                .map_err(|e| bad(e.to_string()))?;
            let value = parsed["v"].clone();
            let mut path = key.trim().split('.').peekable();
            let mut node = &mut table;
            while let Some(part) = path.next() {
                if path.peek().is_none() {
                    node.insert(part.to_string(), value.clone());
                    break;
                }
                node = node
                    .entry(part.to_string())
                    .or_insert_with(|| toml::Value::Table(Default::default()))
                    .as_table_mut()
                    .ok_or_else(|| bad(format!("`{part}` is not a table")))?;
            }
        }
        let config: Self = toml::Value::Table(table)
            .try_into()
            .map_err(|e: toml::de::Error| TrainError::Config {
                origin: format!("--set {}", overrides.join(" ")),
                reason: e.to_string(),
            })?;
        Ok(config)
    }

    /// The faces of `open_faces` with `open_face_flow` (validated by
    /// [`TrainConfig::validate`]).
    pub fn open_faces(&self) -> Result<OpenFaces, TrainError> {
        OpenFaces::from_names(&self.open_faces)
            .map(|faces| faces.with_flow(self.open_face_flow))
            .map_err(|reason| TrainError::Config {
                origin: "open_faces".into(),
                reason,
            })
    }

    /// The keys whose values differ between `self` and `other` (nested ones as
    /// `table.key`), each with both values, in key order.
    pub fn differences(&self, other: &TrainConfig) -> Vec<(String, String, String)> {
        fn flatten(prefix: &str, table: &toml::Table, out: &mut BTreeMap<String, String>) {
            for (key, value) in table {
                let key = if prefix.is_empty() {
                    key.clone()
                } else {
                    format!("{prefix}.{key}")
                };
                match value {
                    toml::Value::Table(inner) => flatten(&key, inner, out),
                    value => {
                        out.insert(key, value.to_string());
                    }
                }
            }
        }
        let table = |config: &TrainConfig| {
            let mut flat = BTreeMap::new();
            if let Ok(table) = toml::Table::try_from(config) {
                flatten("", &table, &mut flat);
            }
            flat
        };
        let (mine, theirs) = (table(self), table(other));
        let keys: std::collections::BTreeSet<&String> = mine.keys().chain(theirs.keys()).collect();
        let missing = || "(unset)".to_string();
        keys.into_iter()
            .filter(|key| mine.get(*key) != theirs.get(*key))
            .map(|key| {
                (
                    key.clone(),
                    mine.get(key).cloned().unwrap_or_else(missing),
                    theirs.get(key).cloned().unwrap_or_else(missing),
                )
            })
            .collect()
    }

    /// Checks ranges before any work starts.
    pub fn validate(&self) -> Result<(), TrainError> {
        let bad = |reason: String| {
            Err(TrainError::Config {
                origin: "configuration".into(),
                reason,
            })
        };
        if self.gaussians == 0 {
            return bad("gaussians must be at least 1".into());
        }
        if self.grid_resolution < 8 || !self.grid_resolution.is_multiple_of(4) {
            return bad(format!(
                "grid_resolution must be a multiple of 4 and at least 8, got {}",
                self.grid_resolution
            ));
        }
        let positive = [
            ("lr_velocity", self.lr_velocity),
            ("lr_gaussians", self.lr_gaussians),
            ("lr_buoyancy", self.lr_buoyancy),
            ("lr_decay", self.lr_decay),
            ("dt", self.dt as f64),
            ("projection_tolerance", self.projection_tolerance),
        ];
        for (name, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return bad(format!("{name} must be a positive number, got {value}"));
            }
        }
        for (name, rate) in [
            ("lr_means", self.lr_means),
            ("lr_log_scales", self.lr_log_scales),
            ("lr_colors", self.lr_colors),
            ("lr_raw_densities", self.lr_raw_densities),
        ] {
            if let Some(lr) = rate
                && !(lr.is_finite() && lr >= 0.0)
            {
                return bad(format!("{name} must be >= 0 when set, got {lr}"));
            }
        }
        let weights = [
            ("lambda_div", self.lambda_div),
            ("lambda_adv", self.lambda_adv),
            ("lambda_refine", self.lambda_refine),
            ("lambda_refine_grid", self.lambda_refine_grid),
            ("lambda_refine_subgrid", self.lambda_refine_subgrid),
            ("lambda_refine_density", self.lambda_refine_density),
            ("lambda_refine_lookahead", self.lambda_refine_lookahead),
            ("lambda_lookahead", self.lambda_lookahead),
            ("lambda_kinetic", self.lambda_kinetic),
            ("lambda_increment", self.lambda_increment),
        ];
        for (name, value) in weights {
            if !(value.is_finite() && value >= 0.0) {
                return bad(format!("{name} must be >= 0, got {value}"));
            }
        }
        if !(0.0..=1.0).contains(&self.refine_view_agreement) {
            return bad(format!(
                "refine_view_agreement must be in [0, 1], got {}",
                self.refine_view_agreement
            ));
        }
        if self.refine_view_agreement > 0.0 && self.refine_views_per_step != 0 {
            return bad(format!(
                "refine_view_agreement takes every training view's gradient at each refinement \
                 step, and refine_views_per_step is {}: set refine_views_per_step = 0",
                self.refine_views_per_step
            ));
        }
        if self.refine_held_view != HeldView::Off
            && (self.refine_view_agreement > 0.0 || self.refine_average_steps > 1)
        {
            return bad(format!(
                "refine_held_view keeps one of the refinement's states, which \
                 refine_view_agreement ({}) and refine_average_steps ({}) replace: set them to 0 \
                 or refine_held_view = \"off\"",
                self.refine_view_agreement, self.refine_average_steps
            ));
        }
        for (name, pixels) in [
            ("refine_loss_blur", self.refine_loss_blur),
            ("joint_loss_blur", self.joint_loss_blur),
        ] {
            if !(0.0..=32.0).contains(&pixels) {
                return bad(format!("{name} (pixels) must be in [0, 32], got {pixels}"));
            }
        }
        if self.joint_loss_blur_velocity_only && self.joint_loss_blur == 0.0 {
            return bad(
                "joint_loss_blur_velocity_only = true needs joint_loss_blur above 0 (pixels): \
                 without a blur it changes nothing"
                    .into(),
            );
        }
        if !(0.0..=1000.0).contains(&self.increment_horizontal_weight) {
            return bad(format!(
                "increment_horizontal_weight must be in [0, 1000], got {}",
                self.increment_horizontal_weight
            ));
        }
        if self.increment_horizontal_weight != 1.0 && self.lambda_increment == 0.0 {
            return bad(
                "increment_horizontal_weight weighs the inertia prior, which is off: set \
                 lambda_increment > 0 too"
                    .into(),
            );
        }
        if self.buoyancy_free_increment && self.lambda_increment == 0.0 {
            return bad(
                "buoyancy_free_increment changes the inertia prior, which is off: set \
                 lambda_increment > 0 too"
                    .into(),
            );
        }
        if !(0.0..=8.0).contains(&self.refine_velocity_blur) {
            return bad(format!(
                "refine_velocity_blur must be in [0, 8] cells, got {}",
                self.refine_velocity_blur
            ));
        }
        let most_share = if self.refine_velocity_blur > 0.0 {
            4.0
        } else {
            1.0
        };
        if !(0.0..=most_share).contains(&self.refine_velocity_share) {
            return bad(format!(
                "refine_velocity_share must be in [0, 1] (up to 4 with refine_velocity_blur > \
                 0), got {}",
                self.refine_velocity_share
            ));
        }
        if self.refine_velocity_blur > 0.0 && self.refine_velocity_share == 0.0 {
            return bad(
                "refine_velocity_blur smooths the move field refine_velocity_share carries on, \
                 and that share is 0: set refine_velocity_share > 0 too"
                    .into(),
            );
        }
        if self.refine_velocity_share > 0.0 && !(self.refinement && self.refine_iterations > 0) {
            return bad(
                "refine_velocity_share adds the refinement's move to the velocity, and the \
                 refinement is off: set refinement = true and refine_iterations > 0 too"
                    .into(),
            );
        }
        if self.refine_velocity_share > 0.0 && self.correction_iterations > 0 {
            return bad(
                "refine_velocity_share and correction_iterations both make the frame's velocity \
                 from the refinement's move: set one of them to 0"
                    .into(),
            );
        }
        for (key, weight) in [
            ("density_motion_smoothness", self.density_motion_smoothness),
            ("density_motion_divergence", self.density_motion_divergence),
            ("density_motion_inertia", self.density_motion_inertia),
        ] {
            if !(0.0..=MOST_DENSITY_MOTION_WEIGHT).contains(&weight) {
                return bad(format!(
                    "{key} must be in [0, {MOST_DENSITY_MOTION_WEIGHT:e}], got {weight}"
                ));
            }
        }
        if self.velocity_from_density_motion {
            let other = if self.refine_velocity_share > 0.0 {
                Some("refine_velocity_share > 0")
            } else if self.correction_iterations > 0 {
                Some("correction_iterations > 0")
            } else if self.velocity_from_ground_truth {
                Some("velocity_from_ground_truth")
            } else {
                None
            };
            if let Some(other) = other {
                return bad(format!(
                    "velocity_from_density_motion and {other} both set the frame's velocity \
                     after the refinement: keep one of them"
                ));
            }
        }
        if self.correction_target != CorrectionTarget::Centres && self.correction_iterations == 0 {
            return bad(
                "correction_target chooses what the velocity correction fits, which is off: \
                 set correction_iterations > 0 too"
                    .into(),
            );
        }
        if !(0.0..=1.0).contains(&self.respawn_fraction) {
            return bad(format!(
                "respawn_fraction must be in [0, 1], got {}",
                self.respawn_fraction
            ));
        }
        if !(0.0..=1.0).contains(&self.emission_fraction) {
            return bad(format!(
                "emission_fraction must be in [0, 1], got {}",
                self.emission_fraction
            ));
        }
        if self.emission_fraction > 0.0 && self.respawn_region.is_none() {
            return bad(
                "emission_fraction emits into the inflow box, which is unset: set \
                 respawn_region too"
                    .into(),
            );
        }
        if !(0.0..=1.0).contains(&self.split_fraction) {
            return bad(format!(
                "split_fraction must be in [0, 1], got {}",
                self.split_fraction
            ));
        }
        if !(self.split_size_factor.is_finite() && self.split_size_factor > 0.0) {
            return bad(format!(
                "split_size_factor must be a positive number, got {}",
                self.split_size_factor
            ));
        }
        if !(0.0..=1.0).contains(&self.shape_transport) {
            return bad(format!(
                "shape_transport must be in [0, 1], got {}",
                self.shape_transport
            ));
        }
        let elongation = self.shape_transport_max_elongation;
        if !(elongation == 0.0 || (1.0..=f32::MAX).contains(&elongation)) {
            return bad(format!(
                "shape_transport_max_elongation must be 0 (no bound) or at least 1, got {elongation}"
            ));
        }
        if !(0.0..=4.0).contains(&self.velocity_smoothing_cells) {
            return bad(format!(
                "velocity_smoothing_cells must be in [0, 4], got {}",
                self.velocity_smoothing_cells
            ));
        }
        if !(0.0..=1.0).contains(&self.carried_smoothing) {
            return bad(format!(
                "carried_smoothing must be in [0, 1], got {}",
                self.carried_smoothing
            ));
        }
        if !(0.0..=4.0).contains(&self.carried_growth) {
            return bad(format!(
                "carried_growth must be in [0, 4] cells squared, got {}",
                self.carried_growth
            ));
        }
        if !(self.carried_smoothing_cells > 0.0 && self.carried_smoothing_cells <= 8.0) {
            return bad(format!(
                "carried_smoothing_cells must be in (0, 8], got {}",
                self.carried_smoothing_cells
            ));
        }
        if !(0.0..=10.0).contains(&self.min_size_factor) {
            return bad(format!(
                "min_size_factor must be in [0, 10], got {}",
                self.min_size_factor
            ));
        }
        if !(self.alpha_min > 0.0 && self.alpha_min <= 1.0 / 255.0) {
            return bad(format!(
                "alpha_min must be in (0, 1/255], got {}",
                self.alpha_min
            ));
        }
        if !(0.0..=10.0).contains(&self.ground_truth_velocity_scale) {
            return bad(format!(
                "ground_truth_velocity_scale must be in [0, 10], got {}",
                self.ground_truth_velocity_scale
            ));
        }
        if !(0.0..=100.0).contains(&self.relative_adam_epsilon) {
            return bad(format!(
                "relative_adam_epsilon must be in [0, 100], got {}",
                self.relative_adam_epsilon
            ));
        }
        let ceiling = self.max_size_factor;
        if !(ceiling == 0.0 || (1.0..=100.0).contains(&ceiling)) {
            return bad(format!(
                "max_size_factor must be 0 (none) or in [1, 100], got {ceiling}"
            ));
        }
        if ceiling > 0.0 && ceiling < self.min_size_factor {
            return bad(format!(
                "max_size_factor ({ceiling}) must not be below min_size_factor ({})",
                self.min_size_factor
            ));
        }
        if !(0.0..=1.0).contains(&self.respawn_near_smoke) {
            return bad(format!(
                "respawn_near_smoke must be in [0, 1], got {}",
                self.respawn_near_smoke
            ));
        }
        if !(self.respawn_threshold.is_finite() && self.respawn_threshold >= 0.0) {
            return bad(format!(
                "respawn_threshold must be >= 0, got {}",
                self.respawn_threshold
            ));
        }
        if let Some(region) = self.respawn_region {
            if !is_box_of_fractions(&region) {
                return bad(format!(
                    "respawn_region must be [x0, y0, z0, x1, y1, z1] with 0 <= lo < hi <= 1 \
                     on each axis (fractions of the smoke box), got {region:?}"
                ));
            }
            if self.respawn_fraction == 0.0 && self.emission_fraction == 0.0 {
                return bad(
                    "respawn_region places recycled and emitted Gaussians, both off: set \
                     respawn_fraction or emission_fraction > 0 too"
                        .into(),
                );
            }
        }
        if !(self.tile_list_headroom.is_finite() && self.tile_list_headroom >= 1.0) {
            return bad(format!(
                "tile_list_headroom must be >= 1, got {}",
                self.tile_list_headroom
            ));
        }
        if self.lr_decay_every == 0
            || self.output_every == 0
            || self.log_every == 0
            || self.unet_channels == 0
        {
            return bad(
                "lr_decay_every, output_every, log_every and unet_channels must be >= 1".into(),
            );
        }
        if self.lookahead_frames == 0 {
            return bad(
                "lookahead_frames must be >= 1 (lambda_lookahead = 0 turns the look-ahead off)"
                    .into(),
            );
        }
        if let Some(shell) = self.static_shell
            && !(shell.is_finite() && shell > 0.0)
        {
            return bad(format!(
                "static_shell must be a positive depth in world units when set, got {shell}"
            ));
        }
        if (self.static_iterations.is_some() || self.static_shell.is_some())
            && self.static_gaussians == 0
        {
            return bad(
                "static_iterations and static_shell set the static Gaussians' start and fit, and \
                 there are none: set static_gaussians > 0 too"
                    .into(),
            );
        }
        if self.lookahead_appearance && self.lambda_lookahead == 0.0 {
            return bad(
                "lookahead_appearance lets the look-ahead train the Gaussians, and the \
                 look-ahead is off: set lambda_lookahead > 0 too"
                    .into(),
            );
        }
        if self.refine_lookahead_velocity.is_some() && self.lambda_refine_lookahead == 0.0 {
            return bad(
                "refine_lookahead_velocity names the carrier of the refinement's look-ahead, \
                 which is off: set lambda_refine_lookahead > 0 too"
                    .into(),
            );
        }
        if self.lambda_refine_lookahead > 0.0 && self.refine_view_agreement > 0.0 {
            return bad(format!(
                "lambda_refine_lookahead ({}) adds a render to each refinement step, which \
                 refine_view_agreement ({}) replaces by one gradient per view: set one of them \
                 to 0",
                self.lambda_refine_lookahead, self.refine_view_agreement
            ));
        }
        if let Some([w, h]) = self.image_size
            && (w == 0 || h == 0)
        {
            return bad("image_size must not be empty".into());
        }
        let rates = &self.init_learning_rates;
        let init_rates = [
            ("init_learning_rates.means", rates.means),
            ("init_learning_rates.rotations", rates.rotations),
            ("init_learning_rates.log_scales", rates.log_scales),
            ("init_learning_rates.raw_densities", rates.raw_densities),
            ("init_learning_rates.colors", rates.colors),
        ];
        for (name, value) in init_rates {
            if !(value.is_finite() && value > 0.0) {
                return bad(format!("{name} must be a positive number, got {value}"));
            }
        }
        // PE(t) uses frequencies 2^0 .. 2^(L-1): beyond 16 an f32 phase keeps no digits of t.
        if !(1..=MAX_TIME_FREQUENCIES).contains(&self.time_frequencies) {
            return bad(format!(
                "time_frequencies must be in 1..={MAX_TIME_FREQUENCIES}, got {}",
                self.time_frequencies
            ));
        }
        if self.projection_max_iterations == 0 {
            return bad("projection_max_iterations must be >= 1".into());
        }
        if self.projection == ProjectionKind::Penalty && self.penalty_steps == 0 {
            return bad("penalty_steps must be >= 1 with projection = \"penalty\"".into());
        }
        if let Err(reason) = OpenFaces::from_names(&self.open_faces) {
            return bad(format!("open_faces: {reason}"));
        }
        let flow = self.open_face_flow;
        if !(flow > 0.0 && flow <= 1.0) {
            return bad(format!("open_face_flow must be in (0, 1], got {flow}"));
        }
        if flow != 1.0 && self.open_faces.is_empty() {
            return bad(format!(
                "open_face_flow = {flow} has no effect with no open faces: set open_faces \
                 too, or open_face_flow = 1 (a preset may set it: the long plume's does)"
            ));
        }
        if !self.open_faces.is_empty() && self.projection != ProjectionKind::Exact {
            return bad(
                "open_faces needs projection = \"exact\" (the penalty form has solid \
                        walls only); with the penalty form, also set open_faces = []"
                    .into(),
            );
        }
        if self.first_frame > 0 && self.frames.is_none() {
            return bad(format!(
                "first_frame = {} needs frames (how many frames from there)",
                self.first_frame
            ));
        }
        if self.frames == Some(0) {
            return bad("frames must be >= 1 (or left out for all)".into());
        }
        for (name, views) in [
            ("train_views", &self.train_views),
            ("test_views", &self.test_views),
        ] {
            if views.as_ref().is_some_and(|v| v.is_empty()) {
                return bad(format!(
                    "{name} must name at least one view (or be left out)"
                ));
            }
        }
        Ok(())
    }

    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("the configuration serialises to TOML")
    }

    /// The rasterizer's options: the defaults, with the configured `alpha_min`, the
    /// ablation's alpha model when `volumetric` is off and the configured backward tile sums.
    pub fn raster_options(&self) -> gausmoke_render::RasterOptions {
        gausmoke_render::RasterOptions {
            gradient_sums: self.gradient_sums.into(),
            alpha_min: self.alpha_min,
            alpha_model: if self.volumetric {
                gausmoke_render::AlphaModel::BeerLambert
            } else {
                gausmoke_render::AlphaModel::SplatOpacity
            },
            ..Default::default()
        }
    }

    /// The velocity and density grid over the smoke box `[lo, hi]` (at least 4 cells per
    /// axis: the interpolation stencil).
    pub fn grid(
        &self,
        lo: gausmoke_core::glam::Vec3,
        hi: gausmoke_core::glam::Vec3,
    ) -> Result<gausmoke_model::GridSpec, TrainError> {
        Ok(gausmoke_model::GridSpec::new(
            lo,
            hi,
            [self.grid_resolution; 3],
            4,
        )?)
    }

    /// Learning-rate factor for frame `frame` (x`lr_decay` every `lr_decay_every` frames).
    pub fn lr_factor(&self, frame: usize) -> f64 {
        self.lr_decay.powi((frame / self.lr_decay_every) as i32)
    }
}

/// Whether `region` is a box inside the unit box, `[x0, y0, z0, x1, y1, z1]` with `0 <= lo <
/// hi <= 1` on each axis (fractions of a smoke box): an inflow box, or a smoke step's source.
pub(crate) fn is_box_of_fractions(region: &[f32; 6]) -> bool {
    region
        .iter()
        .all(|v| v.is_finite() && (0.0..=1.0).contains(v))
        && (0..3).all(|axis| region[axis] < region[axis + 3])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overrides_reach_nested_keys_and_round_trip_through_toml() {
        let config = TrainConfig::default()
            .with_overrides(&[
                "lambda_div=0.5".into(),
                "image_size=[135, 240]".into(),
                "init_learning_rates.means=0.01".into(),
                "interpolation=trilinear".into(),
            ])
            .unwrap();
        assert_eq!(config.lambda_div, 0.5);
        assert_eq!(config.image_size, Some([135, 240]));
        assert_eq!(config.init_learning_rates.means, 0.01);
        assert_eq!(config.interpolation, InterpolationKind::Trilinear);
        let back: TrainConfig = toml::from_str(&config.to_toml()).unwrap();
        assert_eq!(back, config);
    }

    #[test]
    fn unknown_keys_and_bad_values_are_named() {
        let err = TrainConfig::default()
            .with_overrides(&["lamda_div=0.5".into()])
            .unwrap_err();
        assert!(err.to_string().contains("lamda_div"), "{err}");
        // Each invalid configuration is refused naming the setting to change.
        let invalid = [
            (
                TrainConfig {
                    grid_resolution: 30,
                    ..TrainConfig::default()
                },
                "grid_resolution",
            ),
            (
                TrainConfig {
                    buoyancy_free_increment: true,
                    ..TrainConfig::default()
                },
                "lambda_increment",
            ),
            (
                TrainConfig {
                    correction_target: CorrectionTarget::Density,
                    ..TrainConfig::default()
                },
                "correction_iterations",
            ),
            (
                TrainConfig {
                    refine_velocity_share: -0.5,
                    ..TrainConfig::default()
                },
                "refine_velocity_share",
            ),
            (
                TrainConfig {
                    density_motion_divergence: -1.0,
                    ..TrainConfig::default()
                },
                "density_motion_divergence",
            ),
            (
                TrainConfig {
                    density_motion_inertia: f32::NAN,
                    ..TrainConfig::default()
                },
                "density_motion_inertia",
            ),
            (
                TrainConfig {
                    velocity_from_density_motion: true,
                    correction_iterations: 5,
                    ..TrainConfig::default()
                },
                "correction_iterations",
            ),
            (
                TrainConfig {
                    velocity_from_density_motion: true,
                    velocity_from_ground_truth: true,
                    ..TrainConfig::default()
                },
                "velocity_from_ground_truth",
            ),
            (
                TrainConfig {
                    refine_velocity_share: 0.5,
                    refine_iterations: 0,
                    ..TrainConfig::default()
                },
                "refine_iterations",
            ),
            (
                TrainConfig {
                    increment_horizontal_weight: 10.0,
                    ..TrainConfig::default()
                },
                "lambda_increment",
            ),
            (
                TrainConfig {
                    increment_horizontal_weight: -1.0,
                    lambda_increment: 0.01,
                    ..TrainConfig::default()
                },
                "increment_horizontal_weight",
            ),
            (
                TrainConfig {
                    refine_velocity_share: 2.0,
                    ..TrainConfig::default()
                },
                "refine_velocity_blur",
            ),
            (
                TrainConfig {
                    refine_velocity_blur: 2.0,
                    ..TrainConfig::default()
                },
                "refine_velocity_share",
            ),
            (
                TrainConfig {
                    refine_velocity_share: 1.0,
                    refine_velocity_blur: f32::NAN,
                    ..TrainConfig::default()
                },
                "refine_velocity_blur",
            ),
            (
                TrainConfig {
                    lookahead_frames: 0,
                    ..TrainConfig::default()
                },
                "lookahead_frames",
            ),
            (
                TrainConfig {
                    open_face_flow: 0.5,
                    ..TrainConfig::default()
                },
                "set open_faces",
            ),
            (
                TrainConfig {
                    open_faces: vec!["y+".into()],
                    open_face_flow: 1.5,
                    ..TrainConfig::default()
                },
                "open_face_flow",
            ),
            (
                TrainConfig {
                    open_faces: vec!["y+".into()],
                    open_face_flow: f32::NAN,
                    ..TrainConfig::default()
                },
                "open_face_flow",
            ),
            (
                TrainConfig {
                    refine_view_agreement: 1.5,
                    ..TrainConfig::default()
                },
                "refine_view_agreement",
            ),
            (
                TrainConfig {
                    refine_view_agreement: 0.75,
                    refine_views_per_step: 1,
                    ..TrainConfig::default()
                },
                "refine_views_per_step = 0",
            ),
            (
                TrainConfig {
                    refine_loss_blur: -1.0,
                    ..TrainConfig::default()
                },
                "refine_loss_blur",
            ),
            (
                TrainConfig {
                    refine_loss_blur: f32::NAN,
                    ..TrainConfig::default()
                },
                "refine_loss_blur",
            ),
            (
                TrainConfig {
                    joint_loss_blur: 40.0,
                    ..TrainConfig::default()
                },
                "joint_loss_blur",
            ),
            (
                TrainConfig {
                    joint_loss_blur_velocity_only: true,
                    ..TrainConfig::default()
                },
                "joint_loss_blur_velocity_only",
            ),
        ];
        for (config, named) in invalid {
            let err = config.validate().unwrap_err();
            assert!(err.to_string().contains(named), "{err}");
        }
        let region = |value: &str, fraction: &str| {
            TrainConfig::default()
                .with_overrides(&[
                    format!("respawn_region={value}"),
                    format!("respawn_fraction={fraction}"),
                ])
                .and_then(|config| config.validate().map(|()| config))
        };
        let config = region("[0.3, 0, 0.3, 0.7, 0.15, 0.7]", "0.02").unwrap();
        assert_eq!(config.respawn_region, Some([0.3, 0.0, 0.3, 0.7, 0.15, 0.7]));
        for bad in ["[0.3, 0, 0.3, 0.2, 0.15, 0.7]", "[0, 0, 0, 1, 1, 1.5]"] {
            let err = region(bad, "0.02").unwrap_err();
            assert!(err.to_string().contains("respawn_region"), "{bad}: {err}");
        }
        let err = region("[0.3, 0, 0.3, 0.7, 0.15, 0.7]", "0").unwrap_err();
        assert!(err.to_string().contains("respawn_fraction"), "{err}");
        // Emission needs the inflow box, and the box is enough with emission alone.
        let emission = |overrides: &[&str]| {
            let overrides: Vec<String> = overrides.iter().map(|s| s.to_string()).collect();
            TrainConfig::default()
                .with_overrides(&overrides)
                .and_then(|config| config.validate().map(|()| config))
        };
        let err = emission(&["emission_fraction=0.02"]).unwrap_err();
        assert!(err.to_string().contains("respawn_region"), "{err}");
        let err = emission(&["emission_fraction=1.5"]).unwrap_err();
        assert!(err.to_string().contains("emission_fraction"), "{err}");
        let config = emission(&[
            "emission_fraction=0.02",
            "respawn_region=[0.3, 0, 0.3, 0.7, 0.15, 0.7]",
        ])
        .unwrap();
        assert_eq!(config.emission_fraction, 0.02);
        // A half-open top reaches the projection's faces.
        let half_open = TrainConfig::default()
            .with_overrides(&["open_faces=[\"y+\"]".into(), "open_face_flow=0.5".into()])
            .unwrap();
        half_open.validate().unwrap();
        let faces = half_open.open_faces().unwrap();
        assert_eq!(faces.face_flows(), [0.0, 0.0, 0.0, 0.5, 0.0, 0.0]);
    }

    #[test]
    fn gradient_sums_reach_the_rasterizer_and_bad_spellings_are_refused() {
        assert_eq!(
            TrainConfig::default().raster_options().gradient_sums,
            gausmoke_render::GradientSums::Planes
        );
        let config = TrainConfig::default()
            .with_overrides(&["gradient_sums=per-pixel".into()])
            .unwrap();
        assert_eq!(
            config.raster_options().gradient_sums,
            gausmoke_render::GradientSums::PerPixel
        );
        let err = TrainConfig::default()
            .with_overrides(&["gradient_sums=warp".into()])
            .unwrap_err();
        assert!(err.to_string().contains("warp"), "{err}");
    }

    #[test]
    fn the_statics_settings_need_static_gaussians_and_a_positive_shell() {
        let err = TrainConfig {
            static_iterations: Some(1600),
            ..TrainConfig::default()
        }
        .validate()
        .unwrap_err();
        assert!(err.to_string().contains("static_gaussians"), "{err}");
        for shell in [0.0, -0.01, f32::NAN] {
            let err = TrainConfig {
                static_shell: Some(shell),
                static_gaussians: 10,
                ..TrainConfig::default()
            }
            .validate()
            .unwrap_err();
            assert!(err.to_string().contains("static_shell"), "{err}");
        }
        TrainConfig {
            static_shell: Some(0.02),
            static_iterations: Some(1600),
            static_gaussians: 10,
            ..TrainConfig::default()
        }
        .validate()
        .unwrap();
    }

    #[test]
    fn the_look_aheads_on_the_gaussians_are_refused_where_they_cannot_act() {
        let err = TrainConfig {
            lookahead_appearance: true,
            ..TrainConfig::default()
        }
        .validate()
        .unwrap_err();
        assert!(err.to_string().contains("lambda_lookahead"), "{err}");
        let err = TrainConfig {
            lambda_refine_lookahead: 1.0,
            refine_view_agreement: 0.75,
            ..TrainConfig::default()
        }
        .validate()
        .unwrap_err();
        assert!(err.to_string().contains("lambda_refine_lookahead"), "{err}");
        let on = TrainConfig::default()
            .with_overrides(&[
                "lambda_lookahead=1".into(),
                "lookahead_appearance=true".into(),
                "lambda_refine_lookahead=0.5".into(),
            ])
            .unwrap();
        assert!(on.validate().is_ok());
        assert_eq!(on.refine_lookahead_velocity, None);
        let held = on
            .with_overrides(&["refine_lookahead_velocity=held".into()])
            .unwrap();
        assert_eq!(
            held.refine_lookahead_velocity,
            Some(LookaheadVelocity::Held)
        );
        let err = TrainConfig::default()
            .with_overrides(&["refine_lookahead_velocity=ahead".into()])
            .unwrap_err();
        assert!(err.to_string().contains("ahead"), "{err}");
        let err = TrainConfig {
            refine_lookahead_velocity: Some(LookaheadVelocity::Predicted),
            ..TrainConfig::default()
        }
        .validate()
        .unwrap_err();
        assert!(err.to_string().contains("lambda_refine_lookahead"), "{err}");
        // A run folder written before the settings existed reads back with both off.
        let old: TrainConfig = toml::from_str("lambda_lookahead = 1.0").unwrap();
        assert!(!old.lookahead_appearance);
        assert_eq!(old.lambda_refine_lookahead, 0.0);
        assert_eq!(old.refine_lookahead_velocity, None);
    }

    #[test]
    fn alpha_min_reaches_the_rasterizer_and_old_configs_keep_3dgs_cull() {
        assert_eq!(
            TrainConfig::default().raster_options().alpha_min,
            1.0 / 255.0
        );
        let config = TrainConfig::default()
            .with_overrides(&["alpha_min=1e-5".into()])
            .unwrap();
        assert_eq!(config.raster_options().alpha_min, 1e-5);
        assert!(config.validate().is_ok());
        for bad in [0.0, 0.01, -1e-5, f32::NAN] {
            let err = TrainConfig {
                alpha_min: bad,
                ..TrainConfig::default()
            }
            .validate()
            .unwrap_err();
            assert!(err.to_string().contains("alpha_min"), "{bad}: {err}");
        }
        // A run folder written before the setting existed reads back with the old cull.
        let old: TrainConfig = toml::from_str("gaussians = 100").unwrap();
        assert_eq!(old.alpha_min, 1.0 / 255.0);
    }

    #[test]
    fn solver_tests_are_spelled_for_toml_and_bad_spellings_are_refused() {
        assert_eq!(TrainConfig::default().solver_tests, SolverTests::Deferred);
        let config = TrainConfig::default()
            .with_overrides(&["solver_tests=immediate".into()])
            .unwrap();
        assert_eq!(
            gausmoke_model::ConvergenceTests::from(config.solver_tests),
            gausmoke_model::ConvergenceTests::Immediate
        );
        let err = TrainConfig::default()
            .with_overrides(&["solver_tests=sometimes".into()])
            .unwrap_err();
        assert!(err.to_string().contains("sometimes"), "{err}");
        assert!(RESUMABLE_KEYS.contains(&"solver_tests"));
    }
}
