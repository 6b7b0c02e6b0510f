//! Deferred solves (`ConvergenceTests::Deferred`): each solve's iteration budget learnt
//! from the last ones of its kind, and the solves judged later, all in one read.

use burn_cubecl::tensor::CubeTensor;

use super::super::DeferredSolves;
use super::super::host::{OpenFaces, SolveKind};
use super::{StoppingRule, read_scalars, report_after};

/// Iterations between two convergence tests (each one is a device-to-host read) once the
/// first test, at the hinted count, found the solve unconverged.
pub const CHECK_EVERY: usize = 10;

/// Iterations added to the previous solve's count for the first test: two wasted iterations
/// (some ten launches) are cheaper than a second read when a solve needs one more.
pub(super) const HINT_MARGIN: usize = 2;

/// A deferred solve's budget is the most the last two solves of its kind needed, times this,
/// plus [`BUDGET_EXTRA`]: the counts drift slowly from step to step, and an iteration past
/// convergence costs five launches that do no work, where running short leaves a solve
/// less converged than asked.
pub(super) const BUDGET_FACTOR: f64 = 1.25;
pub(super) const BUDGET_EXTRA: usize = 4;

/// Deferred solves of a kind still test their convergence (at the end of their budget, and
/// on until converged) until this many in a row needed no more than their budget: a training
/// run's first steps, where Phi's update grows from nothing and the counts with it, and the
/// steps after a deferred solve ran short.
pub(super) const TRUST_AFTER: usize = 8;

/// Deferred solves kept at most before they are judged anyway (their scalar buffers stay
/// allocated until then).
pub(super) const MAX_PENDING: usize = 64;

/// How many iterations the last two solves of each kind on each grid needed. A training step
/// solves twice on one grid, the forward projection and its backward (measured on the reduced
/// ScalarReal preset: ~40-55 and ~75-80 iterations), with counts that change slowly from step
/// to step, so a solve first tests convergence after the count of the last one of its kind
/// and usually reads back once. Only *when* the host looks depends on this: the step kernel
/// stops stepping on the device once converged, so the result and its report are the same
/// whatever the hint.
pub(super) struct IterationHints;

/// Grid resolution, open faces, obstacles (their fingerprint), stopping rule and kind of a
/// solve.
pub(super) type HintKey = ([u32; 3], OpenFaces, u64, u64, usize, SolveKind);

/// What the solves of one key needed.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct History {
    /// The counts of the solve before the last one and of the last one.
    counts: [Option<usize>; 2],
    /// Solves in a row that needed no more than a deferred budget would have given them.
    trusted: usize,
}

static HINTS: std::sync::Mutex<Vec<(HintKey, History)>> = std::sync::Mutex::new(Vec::new());

impl IterationHints {
    fn history(key: HintKey) -> History {
        let hints = HINTS
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        hints
            .iter()
            .find(|(k, _)| *k == key)
            .map_or_else(History::default, |&(_, history)| history)
    }

    pub(super) fn first_check(key: HintKey, max_iterations: usize) -> usize {
        let hint = Self::history(key).counts[1].map_or(CHECK_EVERY, |n| n + HINT_MARGIN);
        hint.clamp(1, max_iterations.max(1))
    }

    /// The iteration budget of a deferred solve, and whether it may run without testing; `None`
    /// without a history to size it from.
    pub(super) fn budget(key: HintKey, max_iterations: usize) -> Option<(usize, bool)> {
        if max_iterations == 0 {
            return None;
        }
        let history = Self::history(key);
        let most = history.counts.into_iter().flatten().max()?;
        let budget = (most as f64 * BUDGET_FACTOR).ceil() as usize + BUDGET_EXTRA;
        Some((
            budget.clamp(1, max_iterations),
            history.trusted >= TRUST_AFTER,
        ))
    }

    /// A solve needed `iterations`; `within_budget`: no more than the deferred budget sized
    /// from the history before it.
    pub(super) fn record(key: HintKey, iterations: usize, within_budget: bool) {
        let mut hints = HINTS
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let index = match hints.iter().position(|(k, _)| *k == key) {
            Some(index) => index,
            None => {
                hints.push((key, History::default()));
                hints.len() - 1
            }
        };
        let history = &mut hints[index].1;
        history.counts = [history.counts[1], Some(iterations)];
        history.trusted = if within_budget {
            history.trusted + 1
        } else {
            0
        };
    }
}

/// A solve run with `ConvergenceTests::Deferred`, not yet judged.
pub(super) struct PendingSolve {
    pub(super) key: HintKey,
    /// Iterations launched.
    pub(super) budget: usize,
    pub(super) max_iterations: usize,
    pub(super) scalars: CubeTensor,
    pub(super) stopping: StoppingRule,
    pub(super) cells: usize,
}

/// The deferred solves not judged yet, and the tally of those judged since the last
/// [`settle_deferred_solves`] (when [`MAX_PENDING`] forced a judgement in between).
static PENDING: std::sync::Mutex<(Vec<PendingSolve>, DeferredSolves)> = std::sync::Mutex::new((
    Vec::new(),
    DeferredSolves {
        solves: 0,
        unconverged: 0,
        worst_relative_residual: 0.0,
    },
));

pub(super) fn pending() -> std::sync::MutexGuard<'static, (Vec<PendingSolve>, DeferredSolves)> {
    PENDING
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Judges `solves` (one read per device they ran on) into `tally`, recording what each
/// needed as the next budgets' history.
pub(super) fn judge(solves: Vec<PendingSolve>, tally: &mut DeferredSolves) {
    use burn::backend::ops::FloatTensorOps;
    let mut groups: Vec<Vec<PendingSolve>> = Vec::new();
    for solve in solves {
        match groups
            .iter_mut()
            .find(|g| g[0].scalars.device == solve.scalars.device)
        {
            Some(group) => group.push(solve),
            None => groups.push(vec![solve]),
        }
    }
    for group in groups {
        let lengths: Vec<usize> = group
            .iter()
            .map(|s| s.scalars.meta.num_elements())
            .collect();
        let all = burn_cubecl::CubeBackend::float_cat(
            group.iter().map(|s| s.scalars.clone()).collect(),
            0,
        );
        let values = read_scalars(&all);
        let mut at = 0;
        for (solve, len) in group.into_iter().zip(lengths) {
            let scalars = &values[at..at + len];
            at += len;
            tally.solves += 1;
            match solve
                .stopping
                .first_converged(scalars, solve.budget, solve.cells)
            {
                Some(report) => IterationHints::record(solve.key, report.iterations, true),
                None => {
                    let report = report_after(scalars, solve.budget, solve.cells);
                    tally.unconverged += 1;
                    tally.worst_relative_residual =
                        tally.worst_relative_residual.max(report.relative_residual);
                    let needed =
                        solve
                            .stopping
                            .extrapolate(scalars, solve.budget, solve.max_iterations);
                    IterationHints::record(solve.key, needed, false);
                }
            }
        }
    }
}

/// See [`super::settle_deferred_solves`].
pub fn settle_deferred_solves() -> DeferredSolves {
    let (solves, mut tally) = {
        let mut pending = pending();
        (
            std::mem::take(&mut pending.0),
            std::mem::take(&mut pending.1),
        )
    };
    if !solves.is_empty() {
        judge(solves, &mut tally);
    }
    tally
}

/// Keeps `solve` for [`settle_deferred_solves`], judging the oldest ones now if too many wait.
pub(super) fn defer(solve: PendingSolve) {
    let mut pending = pending();
    pending.0.push(solve);
    if pending.0.len() > MAX_PENDING {
        let solves = std::mem::take(&mut pending.0);
        let mut tally = pending.1;
        judge(solves, &mut tally);
        pending.1 = tally;
    }
}
