//! Checkpoints after every frame: the Gaussians, the velocity grid, Phi's weights, both
//! optimisers' state, the frame index and the loss history. A checkpoint is written into a
//! hidden `.frame_TTT.partial` folder, flushed to the disk and renamed when complete, so a
//! folder named `frame_TTT` is always whole; the two newest are kept, so that a damaged newest
//! one can fall back to the one before.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::optim::ModuleOptimizer;
use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::TrainError;
use crate::arrays::{HostArrays, read_arrays, take_array, write_arrays};
use crate::config::TrainConfig;
use crate::export::sync_to_disk;
use crate::hash::Fnv1a;
use crate::state::{FrameReport, LossRow, PhaseSeconds, StaticGaussians, TrainState};

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
    /// Per-phase wall times up to this checkpoint (across resumed sessions), so that a
    /// resumed run's `metrics.json` accounts for all of its training.
    #[serde(default)]
    pub phase_seconds: BTreeMap<String, PhaseSeconds>,
    /// Each tensor file's FNV-1a hash, checked on load, so that a damaged file is refused
    /// rather than trained on. Filled in by [`save`].
    #[serde(default)]
    pub checksums: BTreeMap<String, String>,
    /// The frames of the run that wrote this (its sequence's length), which Phi's time input
    /// `t / (frames - 1)` depends on.
    #[serde(default)]
    pub run_frames: Option<usize>,
    /// The data set's fingerprint (as `run.json`'s), so that a resume checks its data even
    /// when `run.json` is gone.
    #[serde(default)]
    pub data_fingerprint: Option<String>,
    /// FNV-1a of this `state.json` as written with this field empty, so that an edited or
    /// damaged frame number, configuration or history is refused. Filled in by [`save`].
    #[serde(default)]
    pub state_checksum: Option<String>,
}

impl CheckpointMeta {
    /// The hash of `state.json`'s JSON with [`Self::state_checksum`] empty.
    fn unsealed_checksum(&self) -> Result<String, serde_json::Error> {
        let mut unsealed = self.clone();
        unsealed.state_checksum = None;
        let mut hash = Fnv1a::default();
        hash.write(serde_json::to_string_pretty(&unsealed)?.as_bytes());
        Ok(hash.hex())
    }
}

const GAUSSIANS_FILE: &str = "gaussians.bpk";
const PHI_FILE: &str = "phi.bpk";
const GAUSSIAN_OPTIM_FILE: &str = "gaussian_optim.bpk";
const PHI_OPTIM_FILE: &str = "phi_optim.bpk";
const VELOCITY_FILE: &str = "velocity.safetensors";
const META_FILE: &str = "state.json";
const STATICS_FILE: &str = "statics.bpk";
const STATIC_OPTIM_FILE: &str = "static_optim.bpk";
/// Host arrays a trainer carries from frame to frame besides its modules (the last frame's
/// refinement moves), when it has any.
const EXTRAS_FILE: &str = "extras.safetensors";
const TENSOR_FILES: [&str; 5] = [
    GAUSSIANS_FILE,
    PHI_FILE,
    GAUSSIAN_OPTIM_FILE,
    PHI_OPTIM_FILE,
    VELOCITY_FILE,
];

pub fn checkpoint_root(run: &Path) -> PathBuf {
    run.join("checkpoints")
}

/// The complete checkpoint folders of a run, newest first.
pub fn complete(run: &Path) -> Result<Vec<PathBuf>, TrainError> {
    let root = checkpoint_root(run);
    if !root.is_dir() {
        return Ok(Vec::new());
    }
    let entries = std::fs::read_dir(&root).map_err(|source| TrainError::Io {
        path: root.clone(),
        source,
    })?;
    let mut found: Vec<(usize, PathBuf)> = entries
        .flatten()
        .filter_map(|entry| {
            let name = entry.file_name().to_string_lossy().into_owned();
            let frame = name.strip_prefix("frame_")?.parse::<usize>().ok()?;
            Some((frame, entry.path()))
        })
        .collect();
    found.sort_by_key(|(frame, _)| std::cmp::Reverse(*frame));
    Ok(found.into_iter().map(|(_, path)| path).collect())
}

/// The newest complete checkpoint folder of a run, if any.
pub fn latest(run: &Path) -> Result<Option<PathBuf>, TrainError> {
    Ok(complete(run)?.into_iter().next())
}

/// Removes the `.frame_TTT.partial` folders a killed or failed write left behind, naming
/// each: they never hold anything a resume could use.
pub fn remove_partials(run: &Path) -> Result<(), TrainError> {
    let root = checkpoint_root(run);
    let Ok(entries) = std::fs::read_dir(&root) else {
        return Ok(());
    };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with(".frame_") && name.ends_with(".partial") {
            let path = entry.path();
            tracing::warn!(folder = %path.display(), "removing an incomplete checkpoint");
            std::fs::remove_dir_all(&path).map_err(|source| TrainError::Io { path, source })?;
        }
    }
    Ok(())
}

/// Writes the checkpoint of `meta.frame`: into a hidden partial folder, every file and the
/// folder flushed to the disk, then renamed, so that `frame_TTT` is whole even after a power
/// loss. A failed write removes its partial folder and leaves the older checkpoints alone.
pub fn save(
    run: &Path,
    state: &TrainState,
    extras: &HostArrays,
    meta: &CheckpointMeta,
) -> Result<PathBuf, TrainError> {
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
    if let Err(err) = write_files(&partial, state, extras, meta) {
        // The error is the one worth reporting; a leftover is removed on the next start.
        let _ = std::fs::remove_dir_all(&partial);
        return Err(err);
    }
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
    sync_to_disk(&root)?;
    // Keep the newest two complete checkpoints.
    if meta.frame >= 2 {
        let old = root.join(format!("frame_{:03}", meta.frame - 2));
        if old.is_dir() {
            let _ = std::fs::remove_dir_all(old);
        }
    }
    Ok(done)
}

fn write_files(
    dir: &Path,
    state: &TrainState,
    extras: &HostArrays,
    meta: &CheckpointMeta,
) -> Result<(), TrainError> {
    std::fs::create_dir_all(dir).map_err(|source| TrainError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    save_with_optim(
        dir,
        &state.gaussians,
        &state.gaussian_optim,
        GAUSSIANS_FILE,
        GAUSSIAN_OPTIM_FILE,
    )?;
    save_with_optim(dir, &state.phi, &state.phi_optim, PHI_FILE, PHI_OPTIM_FILE)?;
    let mut files = TENSOR_FILES.to_vec();
    if let Some(statics) = &state.statics {
        save_with_optim(
            dir,
            &statics.gaussians,
            &statics.optim,
            STATICS_FILE,
            STATIC_OPTIM_FILE,
        )?;
        files.extend([STATICS_FILE, STATIC_OPTIM_FILE]);
    }
    let velocity = state.velocity.clone();
    let shape = velocity.dims().to_vec();
    let values = gausmoke_render::device_traffic::read_floats(velocity);
    write_arrays(
        &dir.join(VELOCITY_FILE),
        &HostArrays::from([("velocity".to_string(), (shape, values))]),
    )?;
    if !extras.is_empty() {
        write_arrays(&dir.join(EXTRAS_FILE), extras)?;
        files.push(EXTRAS_FILE);
    }
    let mut meta = meta.clone();
    meta.checksums.clear();
    for &file in &files {
        meta.checksums
            .insert(file.into(), checksum(&dir.join(file))?);
    }
    let sum = meta
        .unsealed_checksum()
        .map_err(|e| checkpoint_error(dir, e))?;
    meta.state_checksum = Some(sum);
    let json = serde_json::to_string_pretty(&meta).map_err(|e| checkpoint_error(dir, e))?;
    std::fs::write(dir.join(META_FILE), json).map_err(|source| TrainError::Io {
        path: dir.join(META_FILE),
        source,
    })?;
    for file in files.iter().chain(&[META_FILE]) {
        sync_to_disk(&dir.join(file))?;
    }
    sync_to_disk(dir)
}

/// Turns a burn record error on `file` in `dir` into ours, naming the file.
fn file_error(dir: &Path, file: &str) -> impl FnOnce(burn::store::RecordError) -> TrainError {
    let path = dir.join(file);
    move |e| checkpoint_error(&path, e)
}

/// Writes a part of the state, a module and its optimiser, into `dir`.
fn save_with_optim<M: Module>(
    dir: &Path,
    module: &M,
    optim: &ModuleOptimizer,
    module_file: &str,
    optim_file: &str,
) -> Result<(), TrainError> {
    module
        .clone()
        .save_file(dir.join(module_file))
        .map_err(file_error(dir, module_file))?;
    optim
        .save(dir.join(optim_file))
        .map_err(file_error(dir, optim_file))
}

/// Reads a part of the state, a module and its optimiser, from `dir`.
fn load_with_optim<M: Module>(
    dir: &Path,
    module: M,
    optim: ModuleOptimizer,
    module_file: &str,
    optim_file: &str,
) -> Result<(M, ModuleOptimizer), TrainError> {
    let module = module
        .try_load_file(dir.join(module_file))
        .map_err(file_error(dir, module_file))?;
    let optim = optim
        .load(dir.join(optim_file))
        .map_err(file_error(dir, optim_file))?;
    Ok((module, optim))
}

fn checksum(path: &Path) -> Result<String, TrainError> {
    let bytes = std::fs::read(path).map_err(|source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let mut hash = Fnv1a::default();
    hash.write(&bytes);
    Ok(hash.hex())
}

/// Refuses a checkpoint whose files do not hash to what its `state.json` recorded.
fn verify(dir: &Path, meta: &CheckpointMeta) -> Result<(), TrainError> {
    for (file, recorded) in &meta.checksums {
        let path = dir.join(file);
        let found = checksum(&path)?;
        if &found != recorded {
            return Err(checkpoint_error(
                &path,
                format!("the file is damaged: its checksum is {found}, {recorded} when written"),
            ));
        }
    }
    Ok(())
}

/// Reads a checkpoint's `state.json` (frame, configuration, history) without its tensors, so
/// that a resume can compare configurations before loading state of another shape.
pub fn read_meta(dir: &Path) -> Result<CheckpointMeta, TrainError> {
    let path = dir.join(META_FILE);
    let text = std::fs::read_to_string(&path).map_err(|source| TrainError::Io {
        path: path.clone(),
        source,
    })?;
    let meta: CheckpointMeta =
        serde_json::from_str(&text).map_err(|e| checkpoint_error(&path, e))?;
    match &meta.state_checksum {
        Some(recorded) => {
            let found = meta
                .unsealed_checksum()
                .map_err(|e| checkpoint_error(&path, e))?;
            if &found != recorded {
                return Err(checkpoint_error(
                    &path,
                    format!(
                        "the file was changed after it was written (its checksum is {found}, \
                         {recorded} when written); resume from the checkpoint before it, or \
                         train again"
                    ),
                ));
            }
        }
        None => tracing::warn!(
            path = %path.display(),
            "this checkpoint predates state.json checksums; read as it is"
        ),
    }
    let named = format!("frame_{:03}", meta.frame);
    if dir.file_name().is_some_and(|name| name != named.as_str()) {
        return Err(checkpoint_error(
            &path,
            format!(
                "it says frame {} but its folder is {}",
                meta.frame,
                dir.file_name().unwrap_or_default().to_string_lossy()
            ),
        ));
    }
    Ok(meta)
}

/// What [`load`] restores.
pub struct Restored {
    pub state: TrainState,
    /// The extras [`save`] was given (empty when it had none).
    pub extras: HostArrays,
    pub meta: CheckpointMeta,
}

/// Restores `state` (freshly built with the same configuration) from checkpoint `dir`, whose
/// `state.json` [`read_meta`] read as `meta`.
pub fn load(
    dir: &Path,
    meta: CheckpointMeta,
    state: TrainState,
    device: &Device,
) -> Result<Restored, TrainError> {
    verify(dir, &meta)?;
    let (gaussians, gaussian_optim) = load_with_optim(
        dir,
        state.gaussians,
        state.gaussian_optim,
        GAUSSIANS_FILE,
        GAUSSIAN_OPTIM_FILE,
    )?;
    let (phi, phi_optim) =
        load_with_optim(dir, state.phi, state.phi_optim, PHI_FILE, PHI_OPTIM_FILE)?;
    let statics = match state.statics {
        Some(StaticGaussians { gaussians, optim }) => {
            let (gaussians, optim) =
                load_with_optim(dir, gaussians, optim, STATICS_FILE, STATIC_OPTIM_FILE)?;
            Some(StaticGaussians { gaussians, optim })
        }
        None => None,
    };
    let path = dir.join(VELOCITY_FILE);
    let mut arrays = read_arrays(&path)?;
    let shape = state.velocity.dims();
    let values = take_array(&mut arrays, "velocity", &shape, &path)?;
    let velocity = Tensor::<4>::from_data(TensorData::new(values, shape), device);
    let extras = if meta.checksums.contains_key(EXTRAS_FILE) {
        read_arrays(&dir.join(EXTRAS_FILE))?
    } else {
        HostArrays::new()
    };
    Ok(Restored {
        state: TrainState {
            gaussians,
            statics,
            velocity,
            phi,
            gaussian_optim,
            phi_optim,
        },
        extras,
        meta,
    })
}
