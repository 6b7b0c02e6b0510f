//! The configuration's tables: one per stage of Algorithm 1 (`[init]`, `[joint]`, `[refine]`,
//! `[population]`), with a table of its own for each of our additions inside its stage, and
//! the tables of the learning rates, the projection, what a run writes and the GPU. Each
//! default is the paper's method at the paper's sizes; `crate::preset` makes ours from them.

use serde::{Deserialize, Serialize};

use super::kinds::{
    GradientSums, Obstacles, PlyAxes, ProjectionKind, ProjectionSolve, SolverTests,
};

/// A table's keys, refused when given as anything else: serde reads a struct from an array
/// too, so `init.learning_rates = []` would quietly be the defaults.
pub(super) fn table_only<'de, D, T>(deserializer: D) -> Result<T, D::Error>
where
    D: serde::Deserializer<'de>,
    T: serde::de::DeserializeOwned,
{
    // A map of any values, so that JSON (a record's configuration, with nulls) reads too.
    let table = serde_json::Map::deserialize(deserializer)?;
    serde_json::from_value(serde_json::Value::Object(table)).map_err(serde::de::Error::custom)
}

/// `[init]`: the static fit of frame 0.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InitConfig {
    /// Iterations of the static fit of frame 0.
    pub iterations: usize,
    /// Its learning rates per attribute (`[init.learning_rates]`).
    #[serde(deserialize_with = "table_only")]
    pub learning_rates: InitLearningRates,
}

impl Default for InitConfig {
    fn default() -> Self {
        Self {
            iterations: 2000,
            learning_rates: InitLearningRates::default(),
        }
    }
}

/// `[init.learning_rates]`: learning rates of the frame-0 fit, per Gaussian attribute (3DGS
/// practice: centres move slowly, densities fast). Units: Adam step sizes in the parameter's
/// own units.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InitLearningRates {
    /// Centres, world units; scaled by the box's largest side at run time.
    pub means: f64,
    /// Rotations (unit quaternions, renormalised on use).
    pub rotations: f64,
    /// Natural logs of the standard deviations.
    pub log_scales: f64,
    /// Densities before the softplus.
    pub raw_densities: f64,
    /// Colours, in [0, 1].
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

/// `[learning_rates]`: Adam's learning rates from frame 1 on, and their decay.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LearningRates {
    /// The velocity network Phi's.
    pub velocity: f64,
    /// The Gaussians' (the centres' in the refinement only: the joint step advects them).
    pub gaussians: f64,
    /// The Gaussians' log-scales (ours); unset, `gaussians`. 0 keeps every Gaussian's size
    /// from frame 0 on.
    pub log_scales: Option<f64>,
    /// Every rate above is multiplied by `decay` every `decay_every` frames.
    pub decay: f64,
    /// See `decay`.
    pub decay_every: usize,
}

impl Default for LearningRates {
    fn default() -> Self {
        Self {
            velocity: 1e-3,
            gaussians: 5e-4,
            log_scales: None,
            decay: 0.95,
            decay_every: 10,
        }
    }
}

/// `[joint]`: the joint step (Algorithm 1, lines 3-9), K iterations of
/// `u^t = Pi(u' + Phi(u', sigma, PE(t)))` with the centres advected through `u^t`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JointConfig {
    /// K: joint physics-optical iterations per frame.
    pub iterations: usize,
    /// Weight of `L_div` (Eq. 16). With `lambda_adv` also 0, the physical losses are not
    /// computed at all (the paper's Table 3 "w/o physics").
    pub lambda_div: f32,
    /// Weight of `L_adv` (Eq. 17).
    pub lambda_adv: f32,
    /// Carry the previous frame's velocity along itself before Phi's increment (ours; `false`
    /// = the paper's Eq. 9): `u' = A(u^{t-1})` with `A` semi-Lagrangian transport over `dt`
    /// (see `gausmoke_model::transport_velocity`), so momentum moves with the flow instead of
    /// staying at the cell where it was fitted. The look-ahead's second step does not
    /// transport.
    pub transport_velocity: bool,
    /// The look-ahead render term (ours; `[joint.look_ahead]`).
    pub look_ahead: LookAheadConfig,
    /// The inertia prior on Phi's increment (ours; `[joint.inertia]`).
    pub inertia: InertiaConfig,
}

impl Default for JointConfig {
    fn default() -> Self {
        Self {
            iterations: 250,
            lambda_div: 0.02,
            lambda_adv: 0.02,
            transport_velocity: false,
            look_ahead: LookAheadConfig::default(),
            inertia: InertiaConfig::default(),
        }
    }
}

impl JointConfig {
    /// Whether `L_div` or `L_adv` weighs anything (else neither is computed).
    pub fn has_physics_losses(&self) -> bool {
        self.lambda_div > 0.0 || self.lambda_adv > 0.0
    }
}

/// `[joint.look_ahead]` (ours): the Gaussians carried to frame t are carried on to frame t+1
/// along Phi's projected prediction for it (from their density there) and rendered against
/// its training views, so the velocity of frame t must also explain the next frame's
/// pictures. Their other attributes are held in this term: it trains the velocity only. Not
/// applied at the last frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LookAheadConfig {
    /// Weight of the term against `L_render`'s 1 (0 = off, the paper's method).
    pub weight: f32,
}

/// `[joint.inertia]` (ours): a prior that the velocity keeps what it had (carried along itself
/// with `transport_velocity`) unless the pictures ask for a change: the mean over the grid's
/// cells of `|Phi's increment|^2`, in cells per frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InertiaConfig {
    /// Weight of the prior (0 = off, the paper's method).
    pub weight: f32,
    /// Weight of the increment's horizontal components (x and z, across the upward y)
    /// against 1 for the vertical one, in [0, 1000]: above 1 the horizontal flow changes
    /// mostly through `Pi`, as continuity makes it from the vertical flow, rather than
    /// freely where the views do not pin it. Needs `weight`.
    pub horizontal_weight: f32,
}

impl Default for InertiaConfig {
    fn default() -> Self {
        Self {
            weight: 0.0,
            horizontal_weight: 1.0,
        }
    }
}

/// `[refine]`: the refinement step (Algorithm 1, lines 11-13), K' iterations in which the
/// centres are free, tied to the advected ones.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RefineConfig {
    /// K': refinement iterations per frame (0 = none, the paper's Table 3 "w/o refinement").
    pub iterations: usize,
    /// Weight of `L_refine` (Eq. 18), the refined centres' tie to the advected ones.
    pub lambda: f32,
    /// Weight of a tie on the grid-scale part of the move (ours; 0 = the paper's method,
    /// which ties the whole move by `lambda`): the mass-weighted mean move around each cell
    /// of the velocity grid (a move the velocity could have made), as a mass-weighted mean
    /// of squared lengths in world units, as `L_refine` (see `gausmoke_model::GridScale`).
    pub lambda_grid: f32,
    /// Training views each step renders (ours; 0 = all of them, the paper's method): step i
    /// renders this many views in turn from view `i * views_per_step`, wrapping around, so K'
    /// steps of one view render what K' / 4 steps of four do. The step's loss is the mean
    /// over its views; the frame's train L1, the mean over its last turn of steps (as many as
    /// there are views), which renders each view equally often.
    pub views_per_step: usize,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self {
            iterations: 50,
            lambda: 0.01,
            lambda_grid: 0.0,
            views_per_step: 0,
        }
    }
}

/// `[population]` (ours): between the joint step and the refinement, Gaussians the views
/// leave unused are recycled and the largest split. The paper's method keeps a fixed set,
/// only advected.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PopulationConfig {
    /// `[population.recycle]`.
    pub recycle: RecycleConfig,
    /// `[population.split]`.
    pub split: SplitConfig,
}

/// `[population.recycle]` (ours, `respawn` module): Gaussians on the box's faces or invisible
/// moved to where every training view shows missing smoke, inside the scene's inflow.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RecycleConfig {
    /// Most Gaussians moved per frame, as a fraction of all, in [0, 1] (0 = off).
    pub fraction: f32,
    /// Smallest smoke deficit (image units in `[0, 1]`) a place must show in every training
    /// view to receive recycled Gaussians.
    pub threshold: f32,
}

impl Default for RecycleConfig {
    fn default() -> Self {
        Self {
            fraction: 0.0,
            threshold: 0.05,
        }
    }
}

/// `[population.split]` (ours, `split` module): the largest opaque Gaussians become two
/// halves with the same mass, mean and covariance, the second half in a row that recycling
/// would take (on a box face, or invisible), after the recycling, so that the refinement
/// fits them.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SplitConfig {
    /// Most Gaussians split per frame, as a fraction of all, in [0, 1] (0 = off).
    pub fraction: f32,
}

/// `[projection]`: the incompressibility projection `Pi` (Eq. 10).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ProjectionConfig {
    /// `"exact"` (default; the discrete Helmholtz projection, open faces allowed) or
    /// `"penalty"` (the paper's description; solid walls only).
    pub kind: ProjectionKind,
    /// Relative residual at which the exact projection's PCG solve stops (device backends
    /// only: the CPU backends solve directly, to a residual near 1e-14).
    pub tolerance: f64,
    /// Iteration cap of that PCG solve (device backends only).
    pub max_iterations: usize,
    /// Gradient steps of the penalty form, each with step size `1 / sum_a h_a^-2`.
    pub penalty_steps: usize,
    /// Obstacles described by the data set: `"solid"` (default; no flow into them, exact
    /// projection only) or `"ignore"` (the paper's behaviour).
    pub obstacles: Obstacles,
}

impl Default for ProjectionConfig {
    fn default() -> Self {
        Self {
            kind: ProjectionKind::Exact,
            tolerance: 1e-5,
            max_iterations: 400,
            penalty_steps: 20,
            obstacles: Obstacles::Solid,
        }
    }
}

/// `[output]`: what a run writes, and how often.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OutputConfig {
    /// Write renders, exports and velocity slices every this many frames (1 = all).
    pub every: usize,
    /// Read the losses and checks of the optimisation steps back from the device every this
    /// many steps (and at the end of each frame's loops), in one read: a read waits for the
    /// GPU to drain its queue. A non-finite loss or a bad parameter is reported at that read,
    /// naming the step where it first appeared. Every step's losses are still logged.
    pub log_every: usize,
    /// Axes of the exported Gaussians (`exports/gaussians_TTT.ply`): `"world"` or `"y-down"`
    /// (the OpenCV/COLMAP camera frame splat viewers assume; see [`PlyAxes`]).
    pub ply_axes: PlyAxes,
    /// Also write TensorBoard event files (`RUN/tensorboard/`): per-frame metrics, every
    /// optimisation step's losses and the held-out comparison picture of each output frame.
    pub tensorboard: bool,
}

impl Default for OutputConfig {
    fn default() -> Self {
        Self {
            every: 1,
            log_every: 10,
            ply_axes: PlyAxes::World,
            tensorboard: false,
        }
    }
}

/// `[device]`: how the GPU backends run; the CPU backends ignore these, and a run may be
/// resumed with others.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DeviceConfig {
    /// How the backward sums gradients over a tile: `"planes"` (default), `"shared-memory"`
    /// or `"per-pixel"` (see [`GradientSums`]). The forms differ only in the order of float
    /// additions.
    pub gradient_sums: GradientSums,
    /// Each optimisation loop measures its views' tile-list lengths at its first step and
    /// after each read of its log, and gives the renders until the next measurement this many
    /// times that room, so no render reads its length back. A step that needs more stops the
    /// run with an error naming it (raise this and resume).
    pub tile_list_headroom: f32,
    /// `"deferred"` (default; no read per solve: the solves' iteration budgets are learnt from
    /// the last ones, and the verdicts come back with the losses) or `"immediate"` (about 1.5
    /// reads per solve, no wasted launches). Which is faster depends on the GPU's read latency
    /// against its launch cost; the results agree to the solver's tolerance.
    pub solver_tests: SolverTests,
    /// How the projection is solved on a grid without obstacles: `"direct"` (default; by
    /// separation of variables as matrix products, a dozen launches and no read) or
    /// `"iterative"` (Jacobi-PCG, as with obstacles; `solver_tests` applies). They agree to
    /// the PCG's tolerance.
    pub projection_solve: ProjectionSolve,
    /// Wait for the device at both ends of every timed phase, so the per-phase times in
    /// `metrics.json` charge GPU work to the phase that queued it. Slows GPU runs.
    pub sync_phase_timings: bool,
}

impl Default for DeviceConfig {
    fn default() -> Self {
        Self {
            gradient_sums: GradientSums::Planes,
            tile_list_headroom: 1.5,
            solver_tests: SolverTests::Deferred,
            projection_solve: ProjectionSolve::Direct,
            sync_phase_timings: false,
        }
    }
}
