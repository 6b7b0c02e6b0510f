//! GauSmoke training: the physics-optical joint optimisation of Algorithm 1 (paper Sec. 4.4)
//! over a whole sequence ([`Trainer`]), run frame by frame with evaluation, outputs and
//! checkpoints ([`Run`], [`RunFolder`]). The CLI (`gausmoke-train`) and the evcxr notebook use
//! this same API:
//!
//! ```no_run
//! # fn main() -> Result<(), gausmoke_train::TrainError> {
//! use gausmoke_train::{Run, TrainConfig, sequence::Sequence};
//! let config = TrainConfig::quick_demo();
//! let sequence = Sequence::open("my_scene".as_ref(), &config)?;
//! let device = gausmoke_render::backends::device_by_name("flex").unwrap().autodiff();
//! let mut run = Run::new(sequence, config, device, "runs/demo".as_ref(), false)?;
//! run.run()?;
//! # Ok(()) }
//! ```

use std::path::PathBuf;

pub mod arrays;
pub mod chart;
pub mod checkpoint;
pub mod config;
pub mod config_docs;
mod density_motion;
mod estimate_outputs;
pub mod eval;
pub mod export;
mod hash;
mod host_grid;
pub mod logging;
pub mod lpips;
pub mod lpips_fetch;
pub mod memory;
pub mod metrics;
pub mod novel_views;
pub mod preset;
pub mod respawn;
pub mod run;
pub mod run_folder;
pub mod run_lock;
pub mod scene;
pub mod sequence;
pub mod slices;
pub mod smoke_step;
pub mod split;
pub mod state;
mod step_log;
pub mod tensorboard;
pub mod text;
pub mod trainer;
pub mod velocity_estimate;
pub mod viridis;
pub mod visuals;

pub use config::TrainConfig;
pub use gausmoke_model::GaussianModel;
pub use gausmoke_render::HostGaussians;
pub use run::Run;
pub use run_folder::RunFolder;
pub use state::{FrameReport, LossRow, Phase, TrainState};
pub use trainer::{FrameOutcome, Trainer};

/// What can go wrong in training, evaluation and export; each names the file or quantity.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{origin}: {reason}")]
    Config { origin: String, reason: String },
    #[error(transparent)]
    Data(#[from] gausmoke_data::DataError),
    #[error("data set {path}: {reason}")]
    Dataset { path: PathBuf, reason: String },
    #[error(transparent)]
    Render(#[from] gausmoke_render::RenderError),
    #[error(transparent)]
    Grid(#[from] gausmoke_model::GridError),
    #[error(transparent)]
    UNet(#[from] gausmoke_model::UNetError),
    #[error(
        "{quantity} became {value} at frame {frame}, {phase} iteration {iteration}; training \
         stopped, the last complete frame's checkpoint is kept (continue it with --resume and \
         lower learning rates, e.g. --set learning_rates.gaussians=... --set learning_rates.velocity=...)"
    )]
    NonFinite {
        quantity: String,
        /// The value, or "non-finite (NaN or infinity)" where a check saw several.
        value: String,
        frame: usize,
        phase: &'static str,
        iteration: usize,
    },
    #[error(
        "frame {frame}, {phase} iteration {iteration}: {source}; training stopped, the last \
         complete frame's checkpoint is kept (continue it with --resume and more room, e.g. \
         --set device.tile_list_headroom=3)"
    )]
    TileListOverflow {
        source: gausmoke_render::RenderError,
        frame: usize,
        phase: &'static str,
        iteration: usize,
    },
    #[error("checkpoint {path}: {reason}")]
    Checkpoint { path: PathBuf, reason: String },
    #[error("{path}: {reason}")]
    Arrays { path: PathBuf, reason: String },
    #[error("writing {path}: {reason}")]
    Export { path: PathBuf, reason: String },
    #[error("LPIPS weights from {source_name}: {reason}")]
    Weights { source_name: String, reason: String },
}
