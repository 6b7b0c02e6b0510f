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

mod kinds;
pub mod legacy;
pub mod tables;
mod validate;

pub use kinds::{
    GradientSums, Obstacles, PlyAxes, ProjectionKind, ProjectionSolve, SolverTests,
    VelocityEstimate,
};
use tables::table_only;
pub use tables::{
    DeviceConfig, InertiaConfig, InitConfig, InitLearningRates, JointConfig, LearningRates,
    LookAheadConfig, OutputConfig, PopulationConfig, ProjectionConfig, RecycleConfig, RefineConfig,
    SplitConfig,
};

/// Keys that may differ when a run is resumed (a table's name covers its keys): they change
/// how the rest of the run trains or what it writes, not the shape or meaning of what is
/// already trained. `frames` only while the run has trained frame 0 alone (Phi's time input
/// is `t / (frames - 1)`); the learning rates let a run that diverged continue more gently.
pub const RESUMABLE_KEYS: &[&str] = &[
    "frames",
    "learning_rates",
    "output",
    "device",
    "velocity_estimate",
];

/// Whether `key` (dotted, as [`TrainConfig::differences`] names it) may change on resume.
pub fn is_resumable(key: &str) -> bool {
    RESUMABLE_KEYS.iter().any(|resumable| {
        key == *resumable
            || key
                .strip_prefix(resumable)
                .is_some_and(|rest| rest.starts_with('.'))
    })
}

/// Largest `time_frequencies` accepted (see [`TrainConfig::validate`]).
pub const MAX_TIME_FREQUENCIES: usize = 16;

/// Everything a training run needs besides the data set. Field names are the TOML keys; the
/// stages of Algorithm 1 and the rest have tables of their own ([`tables`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Number of Gaussians, initialised uniformly inside the data set's smoke box.
    pub gaussians: usize,
    /// Static Gaussians for solids and background (0, the default, has none): the same
    /// primitives as the smoke's, rendered with them in one pass, but never advected, one set
    /// for every frame, placed inside the obstacles the data set describes (their centres stay
    /// there) or else spread through the box, fitted first to the training views' per-pixel
    /// minimum over time (where smoke, which only adds light, is absent at least once), then
    /// their shape, density and colour with the smoke at every step from frame 1 on (their
    /// centres stay). Phi and the physics see the smoke's density only.
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
    /// Seed of the Gaussians' initialisation.
    pub seed: u64,
    /// Time step of the velocity update and advection, in frames.
    pub dt: f32,
    /// Channels of the U-Net's first level.
    pub unet_channels: usize,
    /// Sinusoidal time-encoding frequencies L of PE(t).
    pub time_frequencies: usize,
    /// `false` replaces Beer-Lambert volumetric alpha with 3DGS's splat alpha, an opacity
    /// times the projected 2D Gaussian (the paper's Table 3 "w/o volumetric rendering"; see
    /// `gausmoke_render::AlphaModel::SplatOpacity`).
    pub volumetric: bool,
    /// After the last frame, the run's velocity also estimated from its density grids
    /// (ours; `"none"`, `"density"` or `"forces"`; see [`VelocityEstimate`]): written to
    /// `RUN/velocity_estimate/`, the velocity of the run's exports (the grid's beside it) and
    /// scored by `eval` beside the grid's. On a third-party plume `"forces"` took the
    /// velocity's cosine to the truth from 0.71 to 0.82 and its relative error from 0.63 to
    /// 0.51.
    pub velocity_estimate: VelocityEstimate,
    /// The static fit of frame 0 (`[init]`).
    #[serde(deserialize_with = "table_only")]
    pub init: InitConfig,
    /// Adam's learning rates from frame 1 on (`[learning_rates]`).
    #[serde(deserialize_with = "table_only")]
    pub learning_rates: LearningRates,
    /// The joint step (`[joint]`).
    #[serde(deserialize_with = "table_only")]
    pub joint: JointConfig,
    /// The refinement step (`[refine]`).
    #[serde(deserialize_with = "table_only")]
    pub refine: RefineConfig,
    /// Recycling and splitting between the two (`[population]`).
    #[serde(deserialize_with = "table_only")]
    pub population: PopulationConfig,
    /// The projection `Pi` (`[projection]`).
    #[serde(deserialize_with = "table_only")]
    pub projection: ProjectionConfig,
    /// The scene's open faces and inflow (`[scene]`; see [`crate::scene`]): unset keys come
    /// from the data set's `scene.toml`, else from an estimate after frame 0.
    #[serde(deserialize_with = "table_only")]
    pub scene: SceneConfig,
    /// What a run writes (`[output]`).
    #[serde(deserialize_with = "table_only")]
    pub output: OutputConfig,
    /// How the GPU backends run (`[device]`).
    #[serde(deserialize_with = "table_only")]
    pub device: DeviceConfig,
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
            seed: 2026,
            dt: 1.0,
            unet_channels: 16,
            time_frequencies: 4,
            volumetric: true,
            velocity_estimate: VelocityEstimate::None,
            init: InitConfig::default(),
            learning_rates: LearningRates::default(),
            joint: JointConfig::default(),
            refine: RefineConfig::default(),
            population: PopulationConfig::default(),
            projection: ProjectionConfig::default(),
            scene: SceneConfig::default(),
            output: OutputConfig::default(),
            device: DeviceConfig::default(),
        }
    }
}

impl TrainConfig {
    /// A few-minute CPU run on the tiny synthetic scene: the whole pipeline, small.
    pub fn quick_demo() -> Self {
        let mut config = Self {
            gaussians: 2000,
            grid_resolution: 16,
            unet_channels: 8,
            time_frequencies: 2,
            ..Self::default()
        };
        config.init.iterations = 150;
        config.joint.iterations = 40;
        config.refine.iterations = 10;
        config.learning_rates.velocity = 2e-3;
        config.learning_rates.gaussians = 2e-3;
        config
    }

    /// Reads a TOML file; keys it does not name keep their defaults. A file written before
    /// the keys had tables is read with its keys moved to them (see [`legacy`]), and says so.
    pub fn from_toml_file(path: &Path) -> Result<Self, TrainError> {
        Self::default().with_toml_file(path)
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
        let mut file: toml::Table = toml::from_str(&text).map_err(|e| bad(e.to_string()))?;
        let moves = legacy::upgrade_toml(&mut file);
        if !moves.is_empty() {
            tracing::warn!(
                file = %path.display(),
                moved = ?moves,
                "the file names keys of an older version; they were read at their new places"
            );
        }
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

    /// Applies `key=value` overrides (`value` in TOML syntax, e.g. `joint.lambda_div=0.05`,
    /// `image_size=[135, 240]`, `init.learning_rates.means=1e-3`).
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
            if let Some(now) = legacy::replacement(key.trim()) {
                return Err(bad(format!("`{}` is now {now}", key.trim())));
            }
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
            gradient_sums: self.device.gradient_sums.into(),
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

    /// Learning-rate factor for frame `frame` (x`learning_rates.decay` every `decay_every` frames).
    pub fn lr_factor(&self, frame: usize) -> f64 {
        self.learning_rates
            .decay
            .powi((frame / self.learning_rates.decay_every) as i32)
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
mod tests;
