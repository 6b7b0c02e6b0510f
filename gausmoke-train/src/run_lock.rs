//! One training process per run folder: an exclusive advisory lock on `<run>/.lock`, held
//! for the life of the [`RunLock`]. The operating system drops it when the process ends, so
//! a killed run never leaves a stale lock behind.

use std::fs::{File, TryLockError};
use std::io::{Read, Seek, Write};
use std::path::Path;

use crate::TrainError;

pub const LOCK_FILE: &str = ".lock";

/// Held while a process trains into a run folder.
#[derive(Debug)]
pub struct RunLock {
    _file: File,
}

impl RunLock {
    /// Takes the lock of the run folder `run` (which must exist), or refuses naming the
    /// process that holds it. On file systems without locks it warns and goes on.
    pub fn acquire(run: &Path) -> Result<Self, TrainError> {
        let path = run.join(LOCK_FILE);
        let io = |source| TrainError::Io {
            path: path.clone(),
            source,
        };
        // Never truncated before the lock is ours: the holder's process id stays readable.
        let mut file = File::options()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(io)?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                return Err(TrainError::Config {
                    origin: run.display().to_string(),
                    reason: format!(
                        "another process is training into this folder ({}); wait for it to \
                         finish or choose another --out",
                        holder(&mut file, &path)
                    ),
                });
            }
            Err(TryLockError::Error(err)) => {
                tracing::warn!(
                    lock = %path.display(),
                    %err,
                    "cannot lock the run folder: nothing stops a second run from writing into it"
                );
                return Ok(Self { _file: file });
            }
        }
        file.set_len(0).map_err(io)?;
        file.rewind().map_err(io)?;
        writeln!(file, "{}", std::process::id()).map_err(io)?;
        Ok(Self { _file: file })
    }
}

fn holder(file: &mut File, path: &Path) -> String {
    let mut text = String::new();
    match file.read_to_string(&mut text) {
        Ok(_) if !text.trim().is_empty() => {
            format!("process {}, see {}", text.trim(), path.display())
        }
        _ => format!("see {}", path.display()),
    }
}
