//! The physical operators as this run configures them: advection, `Pi`, Phi's prediction and
//! the density splat.

use burn::optim::GradientsParams;
use burn::tensor::{Gradients, Tensor};
use gausmoke_core::phase;
use gausmoke_model::penalty::penalty_projection_with_report;
use gausmoke_model::{
    Advected, Integrator, Interpolation, PenaltyOptions, ProjectionOptions, ProjectionReport,
    SplatOptions, advect, density_and_gradient_grid, density_grid, penalty_projection,
    project_direct, project_velocity,
};
use gausmoke_render::GaussianTensors;
use gausmoke_render::device_traffic::read_floats;

use super::Trainer;
use crate::TrainError;
use crate::config::ProjectionKind;

impl Trainer {
    /// `means` carried one step of `dt` by `velocity`, Euler (Eq. 13) through the Gaussian
    /// interpolation (Eq. 11): how the trainer moves Gaussians from frame to frame.
    pub(super) fn carry(&self, velocity: &Tensor<4>, means: &Tensor<2>) -> Advected {
        advect(
            &self.grid,
            velocity,
            means,
            self.config.dt,
            Integrator::Euler,
            Interpolation::default(),
        )
    }

    pub(super) fn projection(&self) -> ProjectionOptions {
        ProjectionOptions {
            rel_tolerance: self.config.projection.tolerance,
            max_iterations: self.config.projection.max_iterations,
            // Validated with the configuration.
            open_faces: self.config.open_faces().unwrap_or_default(),
            solids: self.solids.clone(),
            // Deferred solves are judged when the steps' losses are read (`read_log`).
            convergence_tests: self.config.device.solver_tests.into(),
            device_solve: self.config.device.projection_solve.into(),
        }
    }

    fn penalty(&self) -> PenaltyOptions {
        PenaltyOptions {
            steps: self.config.projection.penalty_steps,
            ..PenaltyOptions::default()
        }
    }

    /// `Pi(velocity)` in the configured form (differentiable either way).
    pub(super) fn project(&self, velocity: Tensor<4>) -> Tensor<4> {
        match self.config.projection.kind {
            ProjectionKind::Exact => project_velocity(&self.grid, velocity, self.projection()),
            ProjectionKind::Penalty => penalty_projection(&self.grid, velocity, &self.penalty()),
        }
    }

    /// What the configured `Pi` does to `velocity` (for the frame's metrics).
    pub(super) fn projection_report(&self, velocity: Tensor<4>) -> ProjectionReport {
        match self.config.projection.kind {
            ProjectionKind::Exact => {
                project_direct(&self.grid, &mut read_floats(velocity), &self.projection())
            }
            ProjectionKind::Penalty => {
                penalty_projection_with_report(&self.grid, velocity, &self.penalty()).1
            }
        }
    }

    /// The velocity Phi predicts at `time` from `velocity` and the density of `gaussians`
    /// (not differentiated through), projected: one step of Eq. 9 with no fitting.
    pub(super) fn predicted_velocity(
        &self,
        velocity: Tensor<4>,
        gaussians: &GaussianTensors,
        time: f32,
    ) -> Result<Tensor<4>, TrainError> {
        let sigma = self
            .splat_density(gaussians, SplatOptions::default().cutoff)
            .detach();
        let delta = self.state.phi.forward(velocity.clone(), sigma, time)?;
        Ok(self.project(velocity + delta))
    }

    /// One optimizer step of Phi on the gradients of a loss.
    pub(super) fn step_phi(&mut self, grads: &mut Gradients, lr: f64) {
        let phi_grads = GradientsParams::from_module(grads, &self.state.phi);
        let phi = self.state.phi.clone();
        self.state.phi = {
            let _phase = phase!("optimizer");
            self.state.phi_optim.step(lr, phi, phi_grads)
        };
    }

    /// The density grid of `gaussians`.
    pub(super) fn splat_density(&self, gaussians: &GaussianTensors, cutoff: f32) -> Tensor<3> {
        density_grid(gaussians, &self.grid, cutoff)
    }

    /// [`Self::splat_density`] with the density's gradient, in one pass.
    pub(super) fn splat_density_and_gradient(
        &self,
        gaussians: &GaussianTensors,
        cutoff: f32,
    ) -> (Tensor<3>, Tensor<4>) {
        density_and_gradient_grid(gaussians, &self.grid, cutoff)
    }
}
