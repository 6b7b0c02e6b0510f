//! Stage 2 of a frame: the joint step (Algorithm 1, lines 3-9), K iterations of
//! `u^t = Pi(u' + Phi(u', sigma, PE(t)))`, the centres advected from `p^{t-1}` through `u^t`,
//! and a loss that is a sum of named terms: `L_render`, `lambda_div L_div`,
//! `lambda_adv L_adv` (the paper's), and ours, [`LookAhead`] and [`InertiaPrior`].
//! Adam steps on Phi and on the Gaussians' shape, density and colour (the centres are the
//! advected ones, so `p^{t-1}` stays).

use burn::tensor::{Tensor, TensorData};
use gausmoke_core::phase;
use gausmoke_model::{GridSpec, SplatOptions, advection_loss, divergence_loss_of};
use gausmoke_render::device_traffic::Traffic;
use gausmoke_render::{GaussianTensors, Gaussians, InputCheck};
use indicatif::ProgressBar;

use super::losses::{ListCapacities, read_log};
use super::{FrameStart, Trainer, ViewTargets};
use crate::TrainError;
use crate::config::InertiaConfig;
use crate::state::{LoopTraffic, LossRow, Phase};
use crate::step_log::{StepLog, StepLosses};

/// What the joint step leaves for the rest of the frame.
pub(super) struct JointResult {
    /// `u^t` of the last iteration, projected, and before `Pi` (for the frame's report).
    pub velocity: Tensor<4>,
    pub unprojected: Tensor<4>,
    /// The centres advected through `u^t`: where the refinement starts.
    pub advected: Tensor<2>,
    /// Centres that left the box at the last iteration and were clamped back onto it.
    pub clamped: usize,
    pub traffic: LoopTraffic,
}

/// Ours (`[joint.look_ahead]`): the Gaussians carried to frame t are carried one frame
/// further, along Phi's projected prediction for frame t+1 from their density there, and
/// rendered against frame t+1's training views with their other attributes held: `u^t` must
/// also explain the next frame's pictures. Not applied at the last frame.
pub(super) struct LookAhead {
    weight: f32,
    /// Phi's time input at frame t+1.
    time: f32,
    views: ViewTargets,
    lists: ListCapacities,
}

impl LookAhead {
    pub fn for_frame(trainer: &Trainer, frame: &FrameStart) -> Option<Self> {
        let config = &trainer.config;
        let next = frame.t + 1;
        (config.joint.look_ahead.weight > 0.0 && next < trainer.sequence.frames()).then(|| Self {
            weight: config.joint.look_ahead.weight,
            time: next as f32 / (trainer.sequence.frames() - 1) as f32,
            views: trainer.training_views(next),
            lists: ListCapacities::new(config.device.tile_list_headroom),
        })
    }

    /// The term, weighted, for the carried Gaussians `next` and `u^t` (`projected`).
    fn loss(
        &mut self,
        trainer: &Trainer,
        projected: Tensor<4>,
        next: &GaussianTensors,
    ) -> Result<(Tensor<1>, InputCheck), TrainError> {
        let carrier = trainer.predicted_velocity(projected, next, self.time)?;
        // Only the velocity learns here: the other attributes are held.
        let carried = Gaussians {
            means: trainer.carry(&carrier, &next.means).positions,
            ..trainer.state.gaussians.tensors().detach()
        };
        let (cameras, targets) = &self.views;
        let (loss, check) = trainer.render_loss(
            &trainer.scene(carried, false),
            cameras,
            targets,
            &mut self.lists,
        )?;
        Ok((loss * self.weight, check))
    }
}

/// Ours (`[joint.inertia]`): its weight times the mean over the grid's cells of `|Phi's
/// increment|^2` in cells per frame, the horizontal components (x and z, across the upward y)
/// weighted by its `horizontal_weight`: the velocity keeps what it had unless the pictures ask
/// for a change.
pub(super) struct InertiaPrior {
    weight: f32,
    /// `[x, y, z]`: `sqrt(component weight) / cell size`, `[1, 1, 1, 3]`.
    scale: Tensor<4>,
}

impl InertiaPrior {
    pub fn of(
        config: &InertiaConfig,
        grid: &GridSpec,
        device: &burn::tensor::Device,
    ) -> Option<Self> {
        (config.weight > 0.0).then(|| {
            let cell = grid.cell_size();
            let across = config.horizontal_weight.sqrt();
            Self {
                weight: config.weight,
                scale: Tensor::<1>::from_data(
                    TensorData::new(vec![across / cell.x, 1.0 / cell.y, across / cell.z], [3]),
                    device,
                )
                .reshape([1, 1, 1, 3]),
            }
        })
    }

    pub fn loss(&self, delta: Tensor<4>) -> Tensor<1> {
        (delta * self.scale.clone())
            .powi_scalar(2)
            .sum_dim(3)
            .mean()
            * self.weight
    }
}

impl Trainer {
    /// The joint step's K iterations (none: the centres carried along `u'`).
    pub(super) fn joint_step(
        &mut self,
        frame: &FrameStart,
        losses: &mut Vec<LossRow>,
        bar: &ProgressBar,
    ) -> Result<JointResult, TrainError> {
        let config = self.config.clone();
        let splat = SplatOptions::default();
        let mut look_ahead = LookAhead::for_frame(self, frame);
        let inertia = InertiaPrior::of(&config.joint.inertia, &self.grid, &self.device);
        let previous_means = &frame.previous_means;
        let mut velocity = frame.previous_velocity.clone();
        let mut unprojected = frame.previous_velocity.clone();
        let mut advected = None;
        let mut clamped = 0;
        let mut log = StepLog::new(config.output.log_every);
        let mut lists = ListCapacities::new(config.device.tile_list_headroom);
        let start = Traffic::now();
        for iteration in 0..frame.joint_iterations {
            let previous = self.state.gaussians.tensors_at(previous_means.clone());
            // The density and (for L_adv) its gradient, in one pass over the Gaussians.
            let (sigma_previous, gradient_previous) = if config.joint.has_physics_losses() {
                let (sigma, gradient) = self.splat_density_and_gradient(&previous, splat.cutoff);
                (sigma, Some(gradient))
            } else {
                (self.splat_density(&previous, splat.cutoff), None)
            };
            let delta = {
                let _phase = phase!("U-Net forward");
                self.state.phi.forward(
                    frame.previous_velocity.clone(),
                    sigma_previous.clone().detach(),
                    frame.time,
                )?
            };
            let update = frame.previous_velocity.clone() + delta.clone();
            let projected = self.project(update.clone());
            let moved = self.carry(&projected, previous_means);
            let next = self.state.gaussians.tensors_at(moved.positions.clone());

            // The loss, term by term.
            let (render, check) = self.render_loss(
                &self.scene(next.clone(), true),
                &frame.cameras,
                &frame.targets,
                &mut lists,
            )?;
            let mut checks = vec![check];
            let mut loss = render.clone();
            if let Some(look_ahead) = look_ahead.as_mut() {
                let (term, check) = look_ahead.loss(self, projected.clone(), &next)?;
                checks.push(check);
                loss = loss + term;
            }
            if let Some(inertia) = &inertia {
                loss = loss + inertia.loss(delta);
            }
            let mut physical = None;
            if let Some(gradient_previous) = gradient_previous {
                let divergence = divergence_loss_of(&moved.start);
                let (sigma_next, gradient_next) =
                    self.splat_density_and_gradient(&next, splat.cutoff);
                let advection = advection_loss(
                    &sigma_previous,
                    &sigma_next,
                    &gradient_previous,
                    &gradient_next,
                    &projected,
                    config.dt,
                );
                physical = Some((divergence.clone(), advection.clone()));
                loss = loss
                    + divergence * config.joint.lambda_div
                    + advection * config.joint.lambda_adv;
            }
            let (divergence, advection) = physical.unzip();
            log.push(
                (frame.t, Phase::Advect, iteration),
                StepLosses {
                    total: loss.clone(),
                    render,
                    divergence,
                    advection,
                    refine: None,
                },
                Some((
                    "the velocity grid (max |u|)",
                    projected.clone().abs().max().reshape([1]),
                )),
                checks,
            );

            velocity = projected.detach();
            unprojected = update.detach();
            advected = Some(moved.positions.detach());
            let left_box = moved.left_box.float().sum().reshape([1]);

            let mut grads = {
                let _phase = phase!("backward (all ops)");
                loss.backward()
            };
            self.step_phi(&mut grads, frame.lr_velocity);
            let rates = Gaussians {
                means: 0.0,
                ..frame.rates
            };
            self.step_gaussians(&mut grads, rates);
            self.step_statics(&mut grads, frame.lr_gaussians);
            let last = iteration + 1 == frame.joint_iterations;
            if log.due() || last {
                // The clamped count of the last step is read with its losses.
                let tail = last.then_some(left_box);
                if let Some(&count) = read_log(&mut log, losses, bar, tail)?.first() {
                    clamped = count as usize;
                }
                lists.expire();
                if let Some(look_ahead) = look_ahead.as_mut() {
                    look_ahead.lists.expire();
                }
            }
            bar.inc(1);
        }
        let traffic = LoopTraffic::of(Phase::Advect, frame.joint_iterations, start);
        // No joint iterations: carry the Gaussians along the previous velocity.
        let advected =
            advected.unwrap_or_else(|| self.carry(&velocity, previous_means).positions.detach());
        Ok(JointResult {
            velocity,
            unprojected,
            advected,
            clamped,
            traffic,
        })
    }
}
