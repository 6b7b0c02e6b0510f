//! GauSmoke training: the physics-optical joint optimisation of Algorithm 1 (paper Sec. 4.4)
//! over a whole sequence, with checkpoints, evaluation and exports. The CLI
//! (`gausmoke-train`) and the evcxr notebook use this same API:
//!
//! ```no_run
//! # fn main() -> Result<(), gausmoke_train::TrainError> {
//! use gausmoke_train::{TrainConfig, Trainer, scene::Scene};
//! let config = TrainConfig::quick_demo();
//! let scene = Scene::open("my_scene".as_ref(), &config)?;
//! let device = gausmoke_render::backends::device_by_name("flex").unwrap().autodiff();
//! let mut trainer = Trainer::new(scene, config, device, "runs/demo".as_ref(), false)?;
//! trainer.run()?;
//! # Ok(()) }
//! ```

use std::path::PathBuf;

pub mod checkpoint;
pub mod config;
pub mod eval;
pub mod export;
pub mod gaussians;
pub mod lpips;
pub mod metrics;
pub mod respawn;
pub mod scene;
pub mod trainer;
pub mod visuals;

pub use config::TrainConfig;
pub use gaussians::{GaussianModel, HostGaussians};
pub use trainer::{FrameReport, LossRow, Trainer};

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
    Scene { path: PathBuf, reason: String },
    #[error(transparent)]
    Render(#[from] gausmoke_render::RenderError),
    #[error(transparent)]
    Grid(#[from] gausmoke_model::GridError),
    #[error(transparent)]
    UNet(#[from] gausmoke_model::UNetError),
    #[error(
        "{quantity} became {value} at frame {frame}, {phase} iteration {iteration}; training \
         stopped, the last complete frame's checkpoint is kept (resume with --resume after \
         lowering the learning rates)"
    )]
    NonFinite {
        quantity: &'static str,
        value: f32,
        frame: usize,
        phase: &'static str,
        iteration: usize,
    },
    #[error("checkpoint {path}: {reason}")]
    Checkpoint { path: PathBuf, reason: String },
    #[error("writing {path}: {reason}")]
    Export { path: PathBuf, reason: String },
}
