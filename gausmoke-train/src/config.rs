//! Training configuration: every key of a run, its default the paper's Algorithm 1 at the
//! paper's sizes (Sec. 5.1; [`crate::preset`] makes ours and the quick sizes from it), every
//! value overridable from a TOML file and from `--set key=value` on the command line. The
//! configuration actually used is written next to the outputs (`config.toml`, annotated by
//! [`crate::config_docs`]).

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use gausmoke_model::projection::OpenFaces;

use crate::TrainError;
use crate::scene::SceneConfig;

/// A table's keys, refused when given as anything else: serde reads a struct from an array
/// too, so `init_learning_rates = []` would quietly be the defaults.
fn table_only<'de, D, T>(deserializer: D) -> Result<T, D::Error>
where
    D: serde::Deserializer<'de>,
    T: serde::de::DeserializeOwned,
{
    let table = toml::Table::deserialize(deserializer)?;
    table.try_into().map_err(serde::de::Error::custom)
}

/// Learning rates of the frame-0 fit, per Gaussian attribute (3DGS practice: centres move
/// slowly, densities fast). Units: Adam step sizes in the parameter's own units.
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

/// The velocity a finished run ends with besides its grid's (see `velocity_estimate`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VelocityEstimate {
    /// None: the run's velocity is the grid the joint iterations fitted.
    None,
    /// The velocity that carries each frame's density grid onto the next, tracked through
    /// the frames (`gausmoke-train velocity`).
    Density,
    /// The same, each frame's fit started from a smoke solver's step with a source in
    /// `scene.inflow` (`gausmoke-train velocity --forces`); without an inflow, `density`.
    Forces,
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
/// what it writes, not the shape or meaning of what is already trained. `frames` only while
/// the run has trained frame 0 alone (Phi's time input is `t / (frames - 1)`); the learning
/// rates let a run that diverged continue more gently.
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
    "velocity_estimate",
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
    /// Frame 0's learning rates per attribute (`[init_learning_rates]`).
    #[serde(deserialize_with = "table_only")]
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
    /// See `lr_decay`.
    pub lr_decay_every: usize,
    /// Weight of `L_div` (Eq. 16) in the joint iterations.
    pub lambda_div: f32,
    /// Weight of `L_adv` (Eq. 17) in the joint iterations.
    pub lambda_adv: f32,
    /// Weight of `L_refine` (Eq. 18), the refined centres' tie to the advected ones.
    pub lambda_refine: f32,
    /// Weight of a tie on the grid-scale part of the refinement's move (ours; 0 = the
    /// paper's method, which ties the whole move by `lambda_refine`): the mass-weighted mean
    /// move around each cell of the velocity grid (a move the velocity could have made), as
    /// a mass-weighted mean of squared lengths in world units, as `L_refine`
    /// (see `gausmoke_model::GridScale`).
    pub lambda_refine_grid: f32,
    /// Weight of a look-ahead render term in the joint iterations (ours; 0 = the paper's
    /// method): the Gaussians carried to frame t are carried on to frame t+1 along Phi's
    /// projected prediction for it (from their density there) and rendered against its
    /// training views, so the velocity of frame t must also explain the next
    /// frame's pictures (their attributes are held fixed in that term: it trains the
    /// velocity only). Not applied at the last frame.
    pub lambda_lookahead: f32,
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
    /// Most Gaussians moved per frame, as a fraction of all, from the box's faces and from
    /// invisibility to where the training views show missing smoke (`respawn` module). 0 is
    /// the paper's method (a fixed set, only advected).
    pub respawn_fraction: f32,
    /// Smallest smoke deficit (image units in `[0, 1]`) a place must show in every training
    /// view to receive recycled Gaussians.
    pub respawn_threshold: f32,
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
    /// After the last frame, the run's velocity also estimated from its density grids
    /// (ours; `"none"`, `"density"` or `"forces"`; see [`VelocityEstimate`]), written to
    /// `RUN/velocity_estimate/` and scored by `eval` beside the grid's. On a third-party
    /// plume `"forces"` took the velocity's cosine to the truth from 0.71 to 0.82 and its
    /// relative error from 0.63 to 0.51.
    pub velocity_estimate: VelocityEstimate,
    /// The scene's open faces and inflow (`[scene]`; see [`crate::scene`]): unset keys come
    /// from the data set's `scene.toml`, else from an estimate after frame 0.
    pub scene: SceneConfig,
}

impl Default for TrainConfig {
    /// The paper's Algorithm 1 at the paper's sizes (Sec. 5.1), with the exact projection
    /// (Eq. 10) and the data set's obstacles solid; `crate::preset` builds ours and the quick
    /// sizes on it.
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
            transport_velocity: false,
            lambda_increment: 0.0,
            increment_horizontal_weight: 1.0,
            dt: 1.0,
            unet_channels: 16,
            time_frequencies: 4,
            projection: ProjectionKind::Exact,
            projection_tolerance: 1e-5,
            projection_max_iterations: 400,
            penalty_steps: 20,
            obstacles: Obstacles::Solid,
            physics_losses: true,
            refinement: true,
            volumetric: true,
            respawn_fraction: 0.0,
            respawn_threshold: 0.05,
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
            velocity_estimate: VelocityEstimate::None,
            scene: SceneConfig::default(),
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

    /// The keys a TOML file names, on top of this configuration (nested tables key by key);
    /// refused naming the file and the key when one is unknown or of the wrong type.
    pub fn with_toml_file(self, path: &Path) -> Result<Self, TrainError> {
        let bad = |reason: String| TrainError::Config {
            origin: path.display().to_string(),
            reason,
        };
        let text = std::fs::read_to_string(path).map_err(|source| TrainError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let file: toml::Table = toml::from_str(&text).map_err(|e| bad(e.to_string()))?;
        fn merge(into: &mut toml::Table, from: toml::Table) {
            for (key, value) in from {
                match (into.get_mut(&key), value) {
                    (Some(toml::Value::Table(inner)), toml::Value::Table(value)) => {
                        merge(inner, value)
                    }
                    (_, value) => {
                        into.insert(key, value);
                    }
                }
            }
        }
        let mut table = toml::Table::try_from(&self).map_err(|e| bad(e.to_string()))?;
        merge(&mut table, file);
        toml::Value::Table(table)
            .try_into()
            .map_err(|e: toml::de::Error| bad(e.to_string()))
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

    /// The faces of `scene.open_faces` with `scene.open_face_flow` (none while the scene is
    /// unsettled; validated by [`TrainConfig::validate`]).
    pub fn open_faces(&self) -> Result<OpenFaces, TrainError> {
        OpenFaces::from_names(self.scene.open_face_names())
            .map(|faces| faces.with_flow(self.scene.flow()))
            .map_err(|reason| TrainError::Config {
                origin: "scene.open_faces".into(),
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

    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("the configuration serialises to TOML")
    }

    /// The rasterizer's options: the defaults (3DGS's cull at alpha 1/255), with the
    /// ablation's alpha model when `volumetric` is off and the configured backward tile sums.
    pub fn raster_options(&self) -> gausmoke_render::RasterOptions {
        gausmoke_render::RasterOptions {
            gradient_sums: self.gradient_sums.into(),
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

mod validate;

#[cfg(test)]
mod tests;
