//! What a resume checks before it trains on: the same data, a compatible configuration, the
//! newest intact checkpoint, and the outputs the frames before it left.

use std::path::{Path, PathBuf};

use super::Run;
use crate::TrainError;
use crate::checkpoint::{self, CheckpointMeta};
use crate::config::{RESUMABLE_KEYS, is_resumable};

/// The settings that choose what a run reads of its data set (and so its fingerprint).
const DATA_KEYS: &[&str] = &["image_size", "train_views", "test_views", "first_frame"];

impl Run {
    /// Refuses to resume on other data than the run was trained on (the fingerprint: box,
    /// views, cameras, first images), wherever the data set now lives. The fingerprint is the
    /// one `in_checkpoint` recorded (the newest readable checkpoint's), else `run.json`'s; with
    /// neither, the resume is refused.
    fn check_same_data(
        &self,
        data: &Path,
        fingerprint: &str,
        in_checkpoint: Option<String>,
    ) -> Result<(), TrainError> {
        let info = self.folder.read_run_info();
        let run_data = match &info {
            Ok(info) => info.data.display().to_string(),
            Err(_) => "its data".into(),
        };
        let trained = match (in_checkpoint, &info) {
            (Some(recorded), _) => Some(recorded),
            (None, Ok(info)) => info.data_fingerprint.clone(),
            (None, Err(err)) => {
                return Err(TrainError::Config {
                    origin: "--resume".into(),
                    reason: format!(
                        "cannot check that --data is the data set this run was trained on: \
                         {err}, and its checkpoints predate recording the data's fingerprint; \
                         put the run's run.json back or start a new --out"
                    ),
                });
            }
        };
        match &trained {
            Some(trained) if trained != fingerprint => {
                // Settings that choose what is read of the data change its fingerprint too:
                // name them rather than blame the data.
                if let Ok(run_config) = self.folder.read_config() {
                    let changed: Vec<String> = run_config
                        .differences(&self.trainer.config)
                        .into_iter()
                        .filter(|(key, _, _)| DATA_KEYS.contains(&key.as_str()))
                        .map(|(key, was, now)| format!("{key} = {was} in the run, {now} now"))
                        .collect();
                    if !changed.is_empty() {
                        return Err(TrainError::Config {
                            origin: "configuration".into(),
                            reason: format!(
                                "{}: these settings choose what the run reads of its data and \
                                 cannot change on resume; resume with the run's values (its \
                                 config.toml) or start a new --out",
                                changed.join("; ")
                            ),
                        });
                    }
                }
                Err(TrainError::Config {
                    origin: "--data".into(),
                    reason: format!(
                        "{} is not the data set this run was trained on ({}): its cameras, views, \
                     box or first images differ (fingerprint {fingerprint}, the run's {trained}); \
                     resume with the original --data or start a new --out",
                        data.display(),
                        run_data
                    ),
                })
            }
            Some(_) => Ok(()),
            None => {
                tracing::warn!(
                    run_data,
                    data = %data.display(),
                    "this run predates data fingerprints: cannot check that --data is the data \
                     set it was trained on"
                );
                Ok(())
            }
        }
    }

    /// After a restore: refuses a run missing a frame file it trained before its checkpoint
    /// (`--resume` trains only the frames after it, so the run would end with a gap), and
    /// names the exports missing up to the checkpoint.
    pub(super) fn check_outputs_before_resume(&self) -> Result<(), TrainError> {
        let Some(frame) = self.frame else {
            return Ok(());
        };
        if let Some(t) = (0..=frame).find(|&t| !self.folder.frame_state_path(t).is_file()) {
            return Err(TrainError::Dataset {
                path: self.folder.frame_state_path(t),
                reason: format!(
                    "missing: the run trained frame {t} before its checkpoint of frame {frame}, \
                     and --resume trains only the frames after that; put the file back, or \
                     start a new --out"
                ),
            });
        }
        let every = self.trainer.config.output.every;
        let exports = self.folder.exports_dir();
        let missing: Vec<String> = (0..=frame)
            .filter(|t| t.is_multiple_of(every))
            .flat_map(|t| [format!("gaussians_{t:03}.ply"), format!("grid_{t:03}.npz")])
            .filter(|name| !exports.join(name).is_file())
            .collect();
        if !missing.is_empty() {
            tracing::warn!(
                folder = %exports.display(),
                files = missing.join(", "),
                "exports of frames trained before the checkpoint are missing; --resume does \
                 not write them again"
            );
        }
        Ok(())
    }

    /// Restores the newest intact checkpoint of `checkpoints` (newest first), once the newest
    /// readable one has shown that `data` (fingerprinted `fingerprint`) is the run's
    /// ([`Run::check_same_data`]). A damaged one (unreadable, truncated, failing its checksums)
    /// is reported and the one before it used; it is replaced when its frame is trained again.
    pub(super) fn restore(
        &mut self,
        checkpoints: &[PathBuf],
        data: &Path,
        fingerprint: &str,
    ) -> Result<(), TrainError> {
        let mut damaged: Vec<String> = Vec::new();
        let mut data_checked = false;
        for dir in checkpoints {
            let trained = match checkpoint::read_meta(dir) {
                Ok(meta) => meta,
                Err(err) => {
                    tracing::warn!(%err, "damaged checkpoint, trying the one before");
                    damaged.push(err.to_string());
                    continue;
                }
            };
            if !data_checked {
                self.check_same_data(data, fingerprint, trained.data_fingerprint.clone())?;
                data_checked = true;
            }
            self.check_resumable(dir, &trained)?;
            let fresh = self.trainer.fresh_state_for_resume();
            match checkpoint::load(dir, trained, fresh, &self.trainer.device) {
                Ok(checkpoint::Restored {
                    state,
                    extras,
                    meta,
                }) => {
                    self.trainer.restore(state, extras)?;
                    self.frame = Some(meta.frame);
                    self.losses = meta.losses;
                    self.reports = meta.reports;
                    self.elapsed_before = meta.elapsed_seconds;
                    self.phases_before = meta.phase_seconds;
                    if damaged.is_empty() {
                        tracing::info!(checkpoint = %dir.display(), frame = meta.frame, "resumed");
                    } else {
                        tracing::warn!(
                            checkpoint = %dir.display(),
                            frame = meta.frame,
                            "resumed from an older checkpoint because the newer one is damaged; \
                             the frames after it are trained again"
                        );
                    }
                    return Ok(());
                }
                Err(err) => {
                    tracing::warn!(%err, "damaged checkpoint, trying the one before");
                    damaged.push(err.to_string());
                }
            }
        }
        Err(TrainError::Checkpoint {
            path: checkpoint::checkpoint_root(self.folder.root()),
            reason: format!(
                "no intact checkpoint to resume from: {}; start a new --out",
                damaged.join("; ")
            ),
        })
    }

    /// Refuses to resume checkpoint `dir` (its `state.json` read as `meta`) with a
    /// configuration that changes what was trained, naming every such key. Compared before
    /// any tensor is loaded, so that a different shape is named as the setting that caused it
    /// rather than failing inside the record loader.
    fn check_resumable(&mut self, dir: &Path, meta: &CheckpointMeta) -> Result<(), TrainError> {
        let trained = &meta.config;
        // What frame 0 estimated of the scene, the run keeps.
        self.trainer.config.scene.fill(trained.scene.clone());
        // Phi has been trained on times t / (frames - 1) from frame 1 on: another length
        // would give the frames trained so far other times.
        let frames = self.trainer.sequence.frames();
        let frames_were = match meta.run_frames {
            Some(was) => (was != frames).then(|| was.to_string()),
            None => (trained.frames != self.trainer.config.frames)
                .then(|| trained.frames.map_or("all".into(), |n| n.to_string())),
        };
        if let Some(was) = frames_were.filter(|_| meta.frame >= 1) {
            return Err(TrainError::Checkpoint {
                path: dir.to_path_buf(),
                reason: format!(
                    "it was trained as a run of {was} frames and this one has {frames}: Phi's \
                     time input is t / (frames - 1), so the frames trained so far would get \
                     other times. Resume with frames = {was}, or start a new --out (a run \
                     stopped early keeps every frame it finished)"
                ),
            });
        }
        let changes = trained.differences(&self.trainer.config);
        let (allowed, refused): (Vec<_>, Vec<_>) = changes
            .into_iter()
            .partition(|(key, _, _)| is_resumable(key));
        if !refused.is_empty() {
            let list: Vec<String> = refused
                .iter()
                .map(|(key, was, now)| format!("{key} = {was} in the run, {now} now"))
                .collect();
            return Err(TrainError::Checkpoint {
                path: dir.to_path_buf(),
                reason: format!(
                    "it was trained with a different configuration: {}. Only {} may change on \
                     resume; resume with the run's values (its config.toml) or start a new --out",
                    list.join("; "),
                    RESUMABLE_KEYS.join(", ")
                ),
            });
        }
        for (key, was, now) in &allowed {
            tracing::warn!(%key, run = %was, now = %now, "resuming with a changed setting");
        }
        Ok(())
    }
}
