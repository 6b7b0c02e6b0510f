//! One training view held back from a frame's refinement (`refine_held_view`, ours; issue 18).
//!
//! On the long plume every start tried, the scene's true density included, lands near the
//! frame fitted alone once the refinement has fitted it to the four views: past some step the
//! fit undoes carried structure that the views leave open. A view the refinement does not fit
//! shows when that begins, as the held-out view would. Its L1 is checked before the first step
//! and after each turn of the other views; the states are kept on the device and their L1s
//! read once, at the end. The view rotates with the frame, so each view is fitted by most
//! frames' refinements.

use burn::tensor::Tensor;
use gausmoke_render::GaussianTensors;
use gausmoke_render::device_traffic::read_floats;
use serde::{Deserialize, Serialize};

/// The view frame `t`'s refinement holds back out of `views`.
pub fn held_view(t: usize, views: usize) -> usize {
    t % views
}

/// The views the refinement fits when `held` is held back, in order.
pub fn fitted_views(views: usize, held: usize) -> Vec<usize> {
    (0..views).filter(|&v| v != held).collect()
}

/// Refinement steps in one turn of `views` fitted views at `per_step` a step (0: all of them
/// each step).
pub fn steps_per_turn(views: usize, per_step: usize) -> usize {
    if per_step == 0 || per_step >= views {
        1
    } else {
        views.div_ceil(per_step)
    }
}

/// What the held view's checks found at one frame (in `metrics.json`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HeldViewReport {
    /// The training view held back.
    pub view: usize,
    /// Refinement steps done at the state where the held view's L1 was lowest.
    pub best_step: usize,
    /// Whether the frame kept that state (`early_stop`) or the last one (`left_out`).
    pub kept_best: bool,
    /// The held view's L1 before the first step, at the best state and after the last step.
    pub l1_before: f64,
    pub l1_best: f64,
    pub l1_last: f64,
}

/// A refinement state and what it was checked at.
struct Check {
    step: usize,
    l1: Tensor<1>,
    smoke: GaussianTensors,
    statics: Option<GaussianTensors>,
}

/// The states checked over one frame's refinement.
pub struct HeldViewChecks {
    view: usize,
    checks: Vec<Check>,
}

/// The state a frame's refinement ends on, when it is not the last one.
pub struct KeptState {
    pub smoke: GaussianTensors,
    pub statics: Option<GaussianTensors>,
}

impl HeldViewChecks {
    pub fn new(view: usize) -> Self {
        Self {
            view,
            checks: Vec::new(),
        }
    }

    /// The training view held back.
    pub fn view(&self) -> usize {
        self.view
    }

    /// Records the state after `step` refinement steps, whose held view's L1 is `l1`
    /// (detached here).
    pub fn record(
        &mut self,
        step: usize,
        l1: Tensor<1>,
        smoke: GaussianTensors,
        statics: Option<GaussianTensors>,
    ) {
        self.checks.push(Check {
            step,
            l1: l1.detach(),
            smoke: smoke.detach(),
            statics: statics.map(GaussianTensors::detach),
        });
    }

    /// The report, and the best state when `keep_best` and it is not the last one checked;
    /// `None` without checks. Ties go to the earlier state.
    pub fn finish(self, keep_best: bool) -> Option<(HeldViewReport, Option<KeptState>)> {
        let last = self.checks.len().checked_sub(1)?;
        let l1s = read_floats(Tensor::cat(
            self.checks.iter().map(|c| c.l1.clone()).collect(),
            0,
        ));
        let best = lowest(&l1s);
        let report = HeldViewReport {
            view: self.view,
            best_step: self.checks[best].step,
            kept_best: keep_best,
            l1_before: f64::from(l1s[0]),
            l1_best: f64::from(l1s[best]),
            l1_last: f64::from(l1s[last]),
        };
        let kept = (keep_best && best != last).then(|| {
            let check = self
                .checks
                .into_iter()
                .nth(best)
                .expect("an index of the checks");
            KeptState {
                smoke: check.smoke,
                statics: check.statics,
            }
        });
        Some((report, kept))
    }
}

/// The index of the first smallest value (not-a-number never is).
fn lowest(values: &[f32]) -> usize {
    let mut best = 0;
    for (i, &v) in values.iter().enumerate() {
        if v < values[best] || values[best].is_nan() {
            best = i;
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;
    use gausmoke_render::backends::device_by_name;

    use crate::iterate_mean::tests::state;

    #[test]
    fn the_views_rotate_and_each_turn_fits_the_others() {
        assert_eq!(held_view(0, 4), 0);
        assert_eq!(held_view(5, 4), 1);
        assert_eq!(fitted_views(4, 1), vec![0, 2, 3]);
        assert_eq!(steps_per_turn(3, 1), 3);
        assert_eq!(steps_per_turn(3, 2), 2);
        assert_eq!(steps_per_turn(3, 0), 1);
        assert_eq!(steps_per_turn(3, 3), 1);
    }

    #[test]
    fn the_lowest_check_is_kept_and_ties_go_to_the_earlier() {
        assert_eq!(lowest(&[3.0, 1.0, 2.0, 1.0]), 1);
        assert_eq!(lowest(&[f32::NAN, 2.0, 1.0]), 2);
        assert_eq!(lowest(&[1.0, f32::NAN]), 0);
    }

    #[test]
    fn early_stop_returns_the_best_state_and_left_out_reports_it() {
        let device = device_by_name("flex").expect("the default build has Flex");
        let checks = |l1s: &[f32]| {
            let mut checks = HeldViewChecks::new(2);
            for (i, &l1) in l1s.iter().enumerate() {
                let l1 = Tensor::<1>::from_data(TensorData::new(vec![l1], [1]), &device);
                checks.record(3 * i, l1, state(i as f32, &device), None);
            }
            checks
        };
        let (report, kept) = checks(&[0.5, 0.25, 0.75]).finish(true).expect("checks");
        assert_eq!(report.view, 2);
        assert_eq!(report.best_step, 3);
        assert_eq!(
            [report.l1_before, report.l1_best, report.l1_last],
            [0.5, 0.25, 0.75]
        );
        let kept = kept.expect("the best is not the last");
        assert_eq!(
            read_floats(kept.smoke.means.flatten::<1>(0, 1)),
            vec![1.0; 6]
        );

        let (report, kept) = checks(&[0.5, 0.25, 0.75]).finish(false).expect("checks");
        assert!(!report.kept_best && report.best_step == 3 && kept.is_none());
        // The last state is already the frame's: nothing to restore.
        let (report, kept) = checks(&[0.5, 0.25, 0.125]).finish(true).expect("checks");
        assert!(report.best_step == 6 && kept.is_none());
        assert!(HeldViewChecks::new(0).finish(true).is_none());
    }
}
