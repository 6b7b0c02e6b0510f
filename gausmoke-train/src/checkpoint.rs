//! Checkpoints after every frame: the Gaussians, the velocity grid, Phi's weights, both
//! optimisers' state, the frame index and the loss history. A checkpoint is written into a
//! hidden `.frame_TTT.partial` folder and renamed when complete, so a folder named
//! `frame_TTT` is always whole; the two newest are kept.

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::TrainError;
use crate::arrays::{HostArrays, read_arrays, take_array, write_arrays};
use crate::config::TrainConfig;
use crate::state::{FrameReport, LossRow, TrainState};

fn checkpoint_error(path: &Path, reason: impl ToString) -> TrainError {
    TrainError::Checkpoint {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

/// What a checkpoint stores besides tensors.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointMeta {
    /// The last frame whose Gaussians and velocity are complete.
    pub frame: usize,
    pub config: TrainConfig,
    pub losses: Vec<LossRow>,
    pub reports: Vec<FrameReport>,
    /// Training seconds spent up to this checkpoint (across resumed sessions).
    pub elapsed_seconds: f64,
}

pub fn checkpoint_root(run: &Path) -> PathBuf {
    run.join("checkpoints")
}

/// The newest complete checkpoint folder of a run, if any.
pub fn latest(run: &Path) -> Result<Option<PathBuf>, TrainError> {
    let root = checkpoint_root(run);
    if !root.is_dir() {
        return Ok(None);
    }
    let entries = std::fs::read_dir(&root).map_err(|source| TrainError::Io {
        path: root.clone(),
        source,
    })?;
    let mut best: Option<(usize, PathBuf)> = None;
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if let Some(frame) = name
            .strip_prefix("frame_")
            .and_then(|n| n.parse::<usize>().ok())
            && best.as_ref().is_none_or(|(b, _)| frame > *b)
        {
            best = Some((frame, entry.path()));
        }
    }
    Ok(best.map(|(_, p)| p))
}

pub fn save(run: &Path, state: &TrainState, meta: &CheckpointMeta) -> Result<PathBuf, TrainError> {
    let root = checkpoint_root(run);
    let name = format!("frame_{:03}", meta.frame);
    let partial = root.join(format!(".{name}.partial"));
    let done = root.join(&name);
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(|source| TrainError::Io {
            path: partial.clone(),
            source,
        })?;
    }
    std::fs::create_dir_all(&partial).map_err(|source| TrainError::Io {
        path: partial.clone(),
        source,
    })?;
    let record = |e: burn::store::RecordError| checkpoint_error(&partial, e);
    state
        .gaussians
        .clone()
        .save_file(partial.join("gaussians.bpk"))
        .map_err(record)?;
    state
        .phi
        .clone()
        .save_file(partial.join("phi.bpk"))
        .map_err(record)?;
    state
        .gaussian_optim
        .save(partial.join("gaussian_optim.bpk"))
        .map_err(record)?;
    state
        .phi_optim
        .save(partial.join("phi_optim.bpk"))
        .map_err(record)?;
    let velocity = state.velocity.clone();
    let shape = velocity.dims().to_vec();
    let values = velocity
        .into_data()
        .try_into_vec_as::<f32>()
        .map_err(|e| checkpoint_error(&partial, format!("{e:?}")))?;
    write_arrays(
        &partial.join("velocity.safetensors"),
        &HostArrays::from([("velocity".to_string(), (shape, values))]),
    )?;
    let json = serde_json::to_string_pretty(meta).map_err(|e| checkpoint_error(&partial, e))?;
    std::fs::write(partial.join("state.json"), json).map_err(|source| TrainError::Io {
        path: partial.join("state.json"),
        source,
    })?;
    if done.exists() {
        std::fs::remove_dir_all(&done).map_err(|source| TrainError::Io {
            path: done.clone(),
            source,
        })?;
    }
    std::fs::rename(&partial, &done).map_err(|source| TrainError::Io {
        path: done.clone(),
        source,
    })?;
    // Keep the newest two complete checkpoints.
    if meta.frame >= 2 {
        let old = root.join(format!("frame_{:03}", meta.frame - 2));
        if old.is_dir() {
            let _ = std::fs::remove_dir_all(old);
        }
    }
    Ok(done)
}

/// Restores `state` (freshly built with the same configuration) from checkpoint `dir`.
/// Reads a checkpoint's `state.json` (frame, configuration, history) without its tensors, so
/// that a resume can compare configurations before loading state of another shape.
pub fn read_meta(dir: &Path) -> Result<CheckpointMeta, TrainError> {
    let text =
        std::fs::read_to_string(dir.join("state.json")).map_err(|source| TrainError::Io {
            path: dir.join("state.json"),
            source,
        })?;
    serde_json::from_str(&text).map_err(|e| checkpoint_error(&dir.join("state.json"), e))
}

pub fn load(
    dir: &Path,
    state: TrainState,
    device: &Device,
) -> Result<(TrainState, CheckpointMeta), TrainError> {
    let meta = read_meta(dir)?;
    let record = |e: burn::store::RecordError| checkpoint_error(dir, e);
    let gaussians = state
        .gaussians
        .try_load_file(dir.join("gaussians.bpk"))
        .map_err(record)?;
    let phi = state
        .phi
        .try_load_file(dir.join("phi.bpk"))
        .map_err(record)?;
    let gaussian_optim = state
        .gaussian_optim
        .load(dir.join("gaussian_optim.bpk"))
        .map_err(record)?;
    let phi_optim = state
        .phi_optim
        .load(dir.join("phi_optim.bpk"))
        .map_err(record)?;
    let path = dir.join("velocity.safetensors");
    let mut arrays = read_arrays(&path)?;
    let shape = state.velocity.dims();
    let values = take_array(&mut arrays, "velocity", &shape, &path)?;
    let velocity = Tensor::<4>::from_data(TensorData::new(values, shape), device);
    Ok((
        TrainState {
            gaussians,
            velocity,
            phi,
            gaussian_optim,
            phi_optim,
        },
        meta,
    ))
}
