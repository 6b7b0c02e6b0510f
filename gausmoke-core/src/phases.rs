//! Wall time per named phase of training (render, its backward, density splatting, the
//! projection, each GPU stage, ...), measured from `tracing` spans.
//!
//! A phase is a span whose target is [`TARGET`]; [`phase!`](crate::phase) opens one.
//! [`PhaseLayer`] sums the time between each entry into and exit from such a span by name, so
//! nested phases are counted both on their own and inside their parents. Without a
//! `PhaseLayer` in the subscriber the spans cost next to nothing and nothing is recorded.
//!
//! On the CPU backends the ops run eagerly, so a phase measures its work; on GPU backends
//! kernel launches return before the work ends, so a phase measures launch cost unless the
//! layer is given a device sync ([`PhaseTotals::set_sync`]): then every phase waits for the
//! device at its entry and exit and is charged with its own GPU work (slower).

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;

use tracing::span::Id;
use tracing::{Dispatch, Subscriber};
use tracing_subscriber::Layer;
use tracing_subscriber::layer::Context;
use tracing_subscriber::registry::LookupSpan;

/// The target of phase spans.
pub const TARGET: &str = "gausmoke::phase";

/// Enters a phase span named `$name` (a string literal) until the guard is dropped.
#[macro_export]
macro_rules! phase {
    ($name:literal) => {
        $crate::tracing::info_span!(target: "gausmoke::phase", $name).entered()
    };
}

/// Waits until the device has finished the work queued so far.
pub type SyncHook = Arc<dyn Fn() + Send + Sync>;

/// Total wall time and number of entries of one phase.
#[derive(Debug, Clone, PartialEq)]
pub struct PhaseTime {
    pub name: &'static str,
    pub seconds: f64,
    pub calls: u64,
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

#[derive(Default)]
struct Shared {
    totals: Vec<PhaseTime>,
    sync: Option<SyncHook>,
}

/// The totals a [`PhaseLayer`] records, shared with whoever reads them.
#[derive(Clone, Default)]
pub struct PhaseTotals(Arc<Mutex<Shared>>);

impl std::fmt::Debug for PhaseTotals {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("PhaseTotals").finish_non_exhaustive()
    }
}

impl PhaseTotals {
    fn lock(&self) -> std::sync::MutexGuard<'_, Shared> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The totals so far (in first-seen order), starting again from zero.
    pub fn take(&self) -> Vec<PhaseTime> {
        std::mem::take(&mut self.lock().totals)
    }

    /// Makes every phase wait for the device at its entry and exit (`None`: stop waiting).
    pub fn set_sync(&self, hook: Option<SyncHook>) {
        self.lock().sync = hook;
    }

    fn sync(&self) {
        let hook = self.lock().sync.clone();
        if let Some(hook) = hook {
            hook();
        }
    }

    fn add(&self, name: &'static str, seconds: f64) {
        accumulate(
            &mut self.lock().totals,
            PhaseTime {
                name,
                seconds,
                calls: 1,
            },
        );
    }

    /// The totals of the `PhaseLayer` in the current default subscriber, if it has one.
    pub fn current() -> Option<Self> {
        tracing::dispatcher::get_default(|dispatch: &Dispatch| {
            dispatch
                .downcast_ref::<PhaseLayer>()
                .map(|layer| layer.totals.clone())
        })
    }
}

/// A `tracing_subscriber` layer that sums the time spent in phase spans, by name.
#[derive(Debug, Clone, Default)]
pub struct PhaseLayer {
    totals: PhaseTotals,
}

impl PhaseLayer {
    pub fn new() -> Self {
        Self::default()
    }

    /// The totals this layer records into.
    pub fn totals(&self) -> PhaseTotals {
        self.totals.clone()
    }
}

/// When the current entry into a phase span began.
struct Entered(Instant);

impl<S: Subscriber + for<'a> LookupSpan<'a>> Layer<S> for PhaseLayer {
    fn on_enter(&self, id: &Id, ctx: Context<'_, S>) {
        let Some(span) = ctx.span(id) else { return };
        if span.metadata().target() != TARGET {
            return;
        }
        self.totals.sync();
        span.extensions_mut().replace(Entered(Instant::now()));
    }

    fn on_exit(&self, id: &Id, ctx: Context<'_, S>) {
        let Some(span) = ctx.span(id) else { return };
        let Some(Entered(start)) = span.extensions_mut().remove::<Entered>() else {
            return;
        };
        self.totals.sync();
        self.totals
            .add(span.metadata().name(), start.elapsed().as_secs_f64());
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tracing_subscriber::layer::SubscriberExt;

    fn with_layer<R>(layer: PhaseLayer, work: impl FnOnce() -> R) -> R {
        let subscriber = tracing_subscriber::registry().with(layer);
        tracing::subscriber::with_default(subscriber, work)
    }

    #[test]
    fn phases_add_up_per_name_and_nest() {
        let layer = PhaseLayer::new();
        let totals = layer.totals();
        with_layer(layer, || {
            assert!(PhaseTotals::current().is_some());
            for _ in 0..3 {
                let _outer = crate::phase!("outer");
                let _inner = crate::phase!("inner");
                std::thread::sleep(std::time::Duration::from_millis(2));
            }
            let _other = tracing::info_span!("not a phase").entered();
        });
        let recorded = totals.take();
        let names: Vec<_> = recorded.iter().map(|p| (p.name, p.calls)).collect();
        assert_eq!(names, [("inner", 3), ("outer", 3)]);
        assert!(recorded.iter().all(|p| p.seconds >= 0.006), "{recorded:?}");
        assert!(totals.take().is_empty());
    }

    #[test]
    fn nothing_is_recorded_without_the_layer() {
        assert!(PhaseTotals::current().is_none());
        let _phase = crate::phase!("unrecorded");
    }

    #[test]
    fn a_sync_hook_runs_at_both_ends_of_a_phase() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let layer = PhaseLayer::new();
        let totals = layer.totals();
        let waits = Arc::new(AtomicUsize::new(0));
        let counter = waits.clone();
        totals.set_sync(Some(Arc::new(move || {
            counter.fetch_add(1, Ordering::Relaxed);
        })));
        with_layer(layer, || drop(crate::phase!("synced")));
        assert_eq!(waits.load(Ordering::Relaxed), 2);
    }
}
