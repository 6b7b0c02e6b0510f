//! Wall-time totals per named phase of training (render, its backward, density splatting,
//! projection, ...), process-wide, so the slowest phase of a run is known.
//!
//! Off by default (one relaxed atomic load per scope). The custom ops record their own forward
//! and backward calls; the trainer records the rest. On the CPU backends the ops run eagerly,
//! so a scope measures the work; on GPU backends kernel launches return before the work ends
//! unless the device is synchronised, so there a scope measures launch cost only. A sync hook
//! (`set_sync_hook`) makes every scope wait for the device at its start and end: slower, but
//! each phase is then charged with its own GPU work.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::Instant;

/// Waits until the device has finished the work queued so far.
pub type SyncHook = Arc<dyn Fn() + Send + Sync>;

static ENABLED: AtomicBool = AtomicBool::new(false);
static TOTALS: Mutex<Vec<PhaseTime>> = Mutex::new(Vec::new());
static SYNC_HOOK: RwLock<Option<SyncHook>> = RwLock::new(None);

/// Total wall time and number of calls of one phase.
#[derive(Debug, Clone, PartialEq)]
pub struct PhaseTime {
    pub name: &'static str,
    pub seconds: f64,
    pub calls: u64,
}

/// Turns recording on or off for the whole process.
pub fn set_enabled(enabled: bool) {
    ENABLED.store(enabled, Ordering::Relaxed);
}

pub fn enabled() -> bool {
    ENABLED.load(Ordering::Relaxed)
}

/// Sets (or clears) the hook every scope calls at its start and end while recording is on.
pub fn set_sync_hook(hook: Option<SyncHook>) {
    *SYNC_HOOK
        .write()
        .unwrap_or_else(|poisoned| poisoned.into_inner()) = hook;
}

fn wait_for_device() {
    let hook = SYNC_HOOK
        .read()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
        .clone();
    if let Some(hook) = hook {
        hook();
    }
}

/// Adds `time` to the entry of the same name in `totals` (or appends it).
pub fn accumulate(totals: &mut Vec<PhaseTime>, time: PhaseTime) {
    match totals.iter_mut().find(|p| p.name == time.name) {
        Some(phase) => {
            phase.seconds += time.seconds;
            phase.calls += time.calls;
        }
        None => totals.push(time),
    }
}

/// Adds `seconds` (one call) to `name`'s process-wide total.
pub fn record(name: &'static str, seconds: f64) {
    let mut totals = TOTALS
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    accumulate(
        &mut totals,
        PhaseTime {
            name,
            seconds,
            calls: 1,
        },
    );
}

/// Returns the totals so far (in first-seen order) and starts again from zero.
pub fn take() -> Vec<PhaseTime> {
    std::mem::take(
        &mut *TOTALS
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner()),
    )
}

/// Times the scope it lives in (when recording is on) and adds it to `name` on drop.
#[must_use = "the scope is timed until this guard is dropped"]
pub struct Scope {
    name: &'static str,
    start: Option<Instant>,
}

pub fn scope(name: &'static str) -> Scope {
    let start = enabled().then(|| {
        wait_for_device();
        Instant::now()
    });
    Scope { name, start }
}

impl Drop for Scope {
    fn drop(&mut self) {
        if let Some(start) = self.start {
            wait_for_device();
            record(self.name, start.elapsed().as_secs_f64());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The recorder is process-wide: tests that switch it on take turns.
    static SERIAL: Mutex<()> = Mutex::new(());

    #[test]
    fn scopes_add_up_per_name_only_when_enabled() {
        let _serial = SERIAL
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        let _ = take();
        drop(scope("off"));
        assert!(take().is_empty());
        set_enabled(true);
        for _ in 0..3 {
            let _timed = scope("phase");
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        set_enabled(false);
        let totals = take();
        assert_eq!(totals.len(), 1);
        assert_eq!(totals[0].calls, 3);
        assert!(totals[0].seconds >= 0.006, "{totals:?}");
        assert!(take().is_empty());
    }

    #[test]
    fn a_sync_hook_runs_at_both_ends_of_a_recorded_scope() {
        let _serial = SERIAL
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        use std::sync::atomic::AtomicUsize;
        let waits = Arc::new(AtomicUsize::new(0));
        let counter = waits.clone();
        set_sync_hook(Some(Arc::new(move || {
            counter.fetch_add(1, Ordering::Relaxed);
        })));
        drop(scope("not recorded"));
        assert_eq!(waits.load(Ordering::Relaxed), 0);
        set_enabled(true);
        drop(scope("synced"));
        set_enabled(false);
        set_sync_hook(None);
        assert_eq!(waits.load(Ordering::Relaxed), 2);
        let _ = take();
    }
}
