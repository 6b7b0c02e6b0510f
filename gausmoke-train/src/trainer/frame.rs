//! Stage 1 of a frame: what its later stages share.

use burn::tensor::Tensor;
use gausmoke_core::{Camera, phase};
use gausmoke_model::transport_velocity;
use gausmoke_render::Gaussians;

use super::Trainer;

/// Frame t's training views, learning rates and starting point, fixed for the whole frame.
pub struct FrameStart {
    pub t: usize,
    /// Phi's time input, `t / (frames - 1)`.
    pub time: f32,
    pub cameras: Vec<Camera>,
    pub targets: Vec<Tensor<3>>,
    pub lr_velocity: f64,
    pub lr_gaussians: f64,
    /// Per attribute, after the decay; the centres' applies to the refinement alone (the
    /// joint iterations leave them to the advection).
    pub rates: Gaussians<f64>,
    /// `u'`: frame t-1's velocity, carried along itself with `joint.transport_velocity` (ours).
    pub previous_velocity: Tensor<4>,
    /// Frame t-1's centres, `p^{t-1}`.
    pub previous_means: Tensor<2>,
    /// K and K'.
    pub joint_iterations: usize,
    pub refine_iterations: usize,
}

impl FrameStart {
    pub fn new(trainer: &Trainer, t: usize) -> Self {
        let config = &trainer.config;
        let (cameras, targets) = trainer.training_views(t);
        let factor = config.lr_factor(t);
        let lr_gaussians = config.learning_rates.gaussians * factor;
        let velocity = trainer.state.velocity.clone().detach();
        let previous_velocity = if config.joint.transport_velocity {
            let _phase = phase!("velocity transport");
            transport_velocity(&trainer.grid, &velocity, config.dt)
        } else {
            velocity
        };
        Self {
            t,
            time: t as f32 / (trainer.sequence.frames() - 1).max(1) as f32,
            cameras,
            targets,
            lr_velocity: config.learning_rates.velocity * factor,
            lr_gaussians,
            rates: Gaussians {
                log_scales: config
                    .learning_rates
                    .log_scales
                    .map_or(lr_gaussians, |lr| lr * factor),
                ..Gaussians::default().map(|_, ()| lr_gaussians)
            },
            previous_velocity,
            previous_means: trainer.state.gaussians.means.val().detach(),
            joint_iterations: config.joint.iterations,
            refine_iterations: config.refine.iterations,
        }
    }

    /// The frame's optimisation steps, for its progress bar.
    pub fn iterations(&self) -> usize {
        self.joint_iterations + self.refine_iterations
    }
}
