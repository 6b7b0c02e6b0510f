//! Training configuration: the paper's defaults (Sec. 5.1), every value overridable from a
//! TOML file and from `--set key=value` on the command line. The configuration actually used
//! is written next to the outputs (`config.toml`).

use std::collections::BTreeMap;
use std::path::Path;

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



/// Which velocity carries the Gaussians on to frame t+1 in the look-ahead (see
/// `lambda_lookahead`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LookaheadVelocity {
    /// Frame t's velocity, held.
    Held,
    /// The velocity Phi predicts for frame t+1 from the carried Gaussians' density there,
    /// projected.
    Predicted,
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
    "lr_log_scales",
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
    /// Adam learning rate of the velocity network Phi.
    pub lr_velocity: f64,
    /// Adam learning rate of the Gaussians after frame 0.
    pub lr_gaussians: f64,
    /// Adam learning rate of the Gaussians' log-scales after frame 0 (ours; decays with the
    /// others); unset, `lr_gaussians`. 0 keeps every Gaussian's size from frame 0 on.
    pub lr_log_scales: Option<f64>,
    /// The learning rates after frame 0 are multiplied by `lr_decay` every `lr_decay_every`
    /// frames.
    pub lr_decay: f64,
    pub lr_decay_every: usize,
    pub lambda_div: f32,
    pub lambda_adv: f32,
    pub lambda_refine: f32,
    /// Weight of a tie on the grid-scale part of the refinement's move (ours; 0 = the
    /// paper's method, which ties the whole move by `lambda_refine`): the mass-weighted mean
    /// move around each cell of the velocity grid (a move the velocity could have made), as
    /// a mass-weighted mean of squared lengths in world units, as `L_refine`
    /// (see `gausmoke_model::GridScale`).
    pub lambda_refine_grid: f32,
    /// Weight of a look-ahead render term in the joint iterations (ours; 0 = the paper's
    /// method): the Gaussians carried to frame t are carried on to frame t+1 and rendered
    /// against its training views, so the velocity of frame t must also explain the next
    /// frame's pictures (their attributes are held fixed in that term: it trains the
    /// velocity only). Not applied at the last frame.
    pub lambda_lookahead: f32,
    /// The velocity of the look-ahead's step past frame t: `"held"` or `"predicted"`.
    pub lookahead_velocity: LookaheadVelocity,
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
    /// Weight of the increment's horizontal components (x and z, across the upward y) in the
    /// inertia prior, against 1 for the vertical one (ours; 1 = all alike): above 1 the
    /// velocity's horizontal flow changes mostly through `Pi`, as continuity makes it from
    /// the vertical flow, rather than freely where the views do not pin it. In [0, 1000];
    /// needs `lambda_increment`.
    pub increment_horizontal_weight: f32,
    /// Time step of the velocity update and advection, in frames.
    pub dt: f32,
    /// Channels of the U-Net's first level.
    pub unet_channels: usize,
    /// Sinusoidal time-encoding frequencies L of PE(t).
    pub time_frequencies: usize,
    pub interpolation: InterpolationKind,
    pub integrator: IntegratorKind,
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
    /// Most Gaussians moved per frame, as a fraction of all, from the box's faces and from
    /// invisibility to where the training views show missing smoke (`respawn` module). 0 is
    /// the paper's method (a fixed set, only advected).
    pub respawn_fraction: f32,
    /// Smallest smoke deficit (image units in `[0, 1]`) a place must show in every training
    /// view to receive recycled Gaussians.
    pub respawn_threshold: f32,
    /// `[x0, y0, z0, x1, y1, z1]`, fractions of the smoke box (its low corner, then its high
    /// one): recycled Gaussians go only to cells whose centre lies in this box, such as the
    /// inflow where a source feeds the plume, so that new smoke enters where it does and is
    /// not placed anywhere in the training views' visual hull. Unset admits the whole box.
    pub respawn_region: Option<[f32; 6]>,
    /// Most Gaussians split per frame, as a fraction of all (ours, `split` module): the
    /// largest opaque ones become two halves with the same mass, mean and covariance, the
    /// second half in a row that recycling would take (on a box face, or invisible), after
    /// the frame's joint iterations so that the refinement fits them. 0 is the paper's
    /// method.
    pub split_fraction: f32,
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
            grid_resolution: 64,
            image_size: None,
            frames: None,
            first_frame: 0,
            train_views: None,
            test_views: None,
            init_iterations: 2000,
            init_learning_rates: InitLearningRates::default(),
            advect_iterations: 250,
            refine_iterations: 50,
            refine_views_per_step: 0,
            lr_velocity: 1e-3,
            lr_gaussians: 5e-4,
            lr_log_scales: None,
            lr_decay: 0.95,
            lr_decay_every: 10,
            lambda_div: 0.02,
            lambda_adv: 0.02,
            lambda_refine: 0.01,
            lambda_refine_grid: 0.0,
            lambda_lookahead: 0.0,
            lookahead_velocity: LookaheadVelocity::Held,
            transport_velocity: false,
            lambda_increment: 0.0,
            increment_horizontal_weight: 1.0,
            dt: 1.0,
            unet_channels: 16,
            time_frequencies: 4,
            interpolation: InterpolationKind::Gaussian,
            integrator: IntegratorKind::Euler,
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
            respawn_fraction: 0.0,
            respawn_threshold: 0.05,
            respawn_region: None,
            split_fraction: 0.0,
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
            ("lr_decay", self.lr_decay),
            ("dt", self.dt as f64),
            ("projection_tolerance", self.projection_tolerance),
        ];
        for (name, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return bad(format!("{name} must be a positive number, got {value}"));
            }
        }
        let weights = [
            ("lambda_div", self.lambda_div),
            ("lambda_adv", self.lambda_adv),
            ("lambda_refine", self.lambda_refine),
            ("lambda_refine_grid", self.lambda_refine_grid),
            ("lambda_lookahead", self.lambda_lookahead),
            ("lambda_increment", self.lambda_increment),
        ];
        for (name, value) in weights {
            if !(value.is_finite() && value >= 0.0) {
                return bad(format!("{name} must be >= 0, got {value}"));
            }
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
        if !(0.0..=1.0).contains(&self.respawn_fraction) {
            return bad(format!(
                "respawn_fraction must be in [0, 1], got {}",
                self.respawn_fraction
            ));
        }
        if !(0.0..=1.0).contains(&self.split_fraction) {
            return bad(format!(
                "split_fraction must be in [0, 1], got {}",
                self.split_fraction
            ));
        }
        if !(self.alpha_min > 0.0 && self.alpha_min <= 1.0 / 255.0) {
            return bad(format!(
                "alpha_min must be in (0, 1/255], got {}",
                self.alpha_min
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
            if self.respawn_fraction == 0.0 {
                return bad(
                    "respawn_region places recycled Gaussians, which are off: set \
                     respawn_fraction > 0 too"
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
            ),        ];
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
