//! Stage 4 of a frame: the refinement step (Algorithm 1, lines 11-13), K' iterations in
//! which the centres are free parameters, with `L_render` and ties: `refine.lambda L_refine`
//! (the paper's) and ours, [`GridTie`]. Ours too: each step may render some of the training
//! views in turn (`refine.views_per_step`).

use burn::tensor::Tensor;
use gausmoke_core::Camera;
use gausmoke_model::{GridScale, refine_loss};
use gausmoke_render::GaussianTensors;
use gausmoke_render::device_traffic::Traffic;
use indicatif::ProgressBar;

use super::losses::{ListCapacities, read_log};
use super::{FrameStart, Trainer, ViewTargets};
use crate::TrainError;
use crate::state::{LoopTraffic, LossRow, Phase};
use crate::step_log::{StepLog, StepLosses};

/// What the refinement step leaves for the frame's report.
pub(super) struct RefineResult {
    /// The moves' grid scale and where they started (`None` without refinement).
    pub moves: Option<(GridScale, Tensor<2>)>,
    pub traffic: LoopTraffic,
}

/// Ours (`refine.lambda_grid`): a tie on the refinement's move at the velocity grid's
/// scale, the mass-weighted mean move around each cell (a move the velocity could have
/// made), as a mass-weighted mean of squared lengths in world units (see
/// [`gausmoke_model::GridScale`]). What is left to the refinement is the sub-grid rest.
pub(super) struct GridTie {
    weight: f32,
}

impl GridTie {
    pub fn of(weight: f32) -> Option<Self> {
        (weight > 0.0).then_some(Self { weight })
    }

    fn loss(&self, scale: &GridScale, moves: Tensor<2>) -> Tensor<1> {
        scale.mean_square(scale.grid_part(moves)) * self.weight
    }
}

/// The views of `group` (indices into `views`), in its order.
fn views_of(group: &[usize], (cameras, targets): (&[Camera], &[Tensor<3>])) -> ViewTargets {
    group
        .iter()
        .map(|&v| (cameras[v], targets[v].clone()))
        .unzip()
}

impl Trainer {
    /// The refinement step's K' iterations, from the Gaussians as the joint step and the
    /// population left them.
    pub(super) fn refine_step(
        &mut self,
        frame: &FrameStart,
        losses: &mut Vec<LossRow>,
        bar: &ProgressBar,
    ) -> Result<RefineResult, TrainError> {
        let iterations = frame.refine_iterations;
        let views = frame.cameras.len();
        let per_step = self.config.refine.views_per_step;
        let lambda_refine = self.config.refine.lambda;
        let anchor = self.state.gaussians.means.val().detach();
        // The split of the moves is fixed by where they start.
        let scale =
            (iterations > 0).then(|| GridScale::of(&self.grid, &self.state.gaussians.tensors()));
        let grid_tie = GridTie::of(self.config.refine.lambda_grid);
        // One set of list capacities per group of views a step renders (keyed by its first).
        let mut group_lists: Vec<ListCapacities> = (0..views)
            .map(|_| ListCapacities::new(self.config.device.tile_list_headroom))
            .collect();
        let mut log = StepLog::new(self.config.output.log_every);
        let start = Traffic::now();
        for iteration in 0..iterations {
            let gaussians = self.state.gaussians.tensors();
            let group = refinement_views(iteration, views, per_step);
            let (cameras, targets) = views_of(&group, (&frame.cameras, &frame.targets));
            let (render, check) = self.render_loss(
                &self.scene(gaussians.clone(), true),
                &cameras,
                &targets,
                &mut group_lists[group[0]],
            )?;
            let refine = refine_loss(&gaussians.means, &anchor);
            let mut ties = refine.clone() * lambda_refine;
            if let (Some(tie), Some(scale)) = (&grid_tie, &scale) {
                ties = ties + tie.loss(scale, moves_from(&gaussians, &anchor));
            }
            let loss = render.clone() + ties;
            log.push(
                (frame.t, Phase::Refine, iteration),
                StepLosses {
                    total: loss.clone(),
                    render,
                    divergence: None,
                    advection: None,
                    refine: Some(refine),
                },
                None,
                vec![check],
            );
            let mut grads = {
                let _phase = gausmoke_core::phase!("backward (all ops)");
                loss.backward()
            };
            self.step_gaussians(&mut grads, frame.rates);
            self.step_statics(&mut grads, frame.lr_gaussians);
            if log.due() || iteration + 1 == iterations {
                read_log(&mut log, losses, bar, None)?;
                group_lists.iter_mut().for_each(ListCapacities::expire);
            }
            bar.inc(1);
        }
        Ok(RefineResult {
            moves: scale.map(|scale| (scale, anchor)),
            traffic: LoopTraffic::of(Phase::Refine, iterations, start),
        })
    }
}

fn moves_from(gaussians: &GaussianTensors, anchor: &Tensor<2>) -> Tensor<2> {
    gaussians.means.clone() - anchor.clone()
}

/// The frame's L1 on its training views after its loops: the last step's, or, when that step
/// was a refinement step rendering some of the `views` (`per_step`), the mean of the last
/// `views` refinement steps' (one turn in which each view is rendered equally often).
pub(super) fn last_turn_l1(losses: &[LossRow], views: usize, per_step: usize) -> f64 {
    let Some(last) = losses.last() else {
        return f64::NAN;
    };
    if last.phase != Phase::Refine || per_step == 0 || per_step >= views {
        return last.render as f64;
    }
    let turn: Vec<f32> = losses
        .iter()
        .rev()
        .take_while(|row| row.phase == Phase::Refine)
        .take(views)
        .map(|row| row.render)
        .collect();
    turn.iter().map(|&l1| l1 as f64).sum::<f64>() / turn.len() as f64
}

/// The training views (indices into the frame's `views`) that refinement step `step`
/// renders: `per_step` of them in turn from view `step * per_step`, wrapping around, so that
/// every view is rendered equally often over `views` steps; all of them when `per_step` is 0
/// or not below `views`. The first index names the group (a group's views are fixed by it).
pub(super) fn refinement_views(step: usize, views: usize, per_step: usize) -> Vec<usize> {
    if per_step == 0 || per_step >= views {
        return (0..views).collect();
    }
    let first = step * per_step % views;
    (0..per_step).map(|i| (first + i) % views).collect()
}
