//! Fits to still images (the static Gaussians' before frame 0, and frame 0's), the Adam
//! steps every stage takes, and the state Algorithm 1 starts from.

use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Gradients, Tensor, TensorData};
use gausmoke_core::glam::Vec3;
use gausmoke_core::{Camera, phase};
use gausmoke_model::{GaussianModel, GridSpec, INITIAL_RAW_DENSITY, UNetConfig, VelocityUNet};
use gausmoke_render::Gaussians;

use super::Trainer;
use super::losses::{ListCapacities, read_log};
use crate::TrainError;
use crate::config::TrainConfig;
use crate::sequence::{Observation, Sequence};
use crate::state::{LossRow, Phase, StaticGaussians, TrainState};
use crate::step_log::{StepLog, StepLosses};

/// One Adam step per attribute of `model` with its own learning rate (0 skips it), the
/// gradients taken from `grads`; every log-scale ends within the renderer's range.
fn adam_per_attribute(
    mut model: GaussianModel,
    optim: &mut ModuleOptimizer,
    grads: &mut Gradients,
    learning_rates: Gaussians<f64>,
) -> GaussianModel {
    let steps = model
        .param_ids()
        .zip(learning_rates)
        .zip(
            model
                .param_ids()
                .map(|_, id| GradientsParams::from_params(grads, &model, &[id])),
        )
        .into_array();
    for ((_, lr), params) in steps {
        if lr > 0.0 && !params.is_empty() {
            let _phase = phase!("optimizer");
            model = optim.step(lr, model, params);
        }
    }
    model.clamped()
}

/// Which Gaussians a fit to still images trains (see [`Trainer::fit_to_images`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum StillFit {
    /// The static Gaussians alone, before frame 0.
    Statics,
    /// Frame 0's smoke, in front of the (fixed) static Gaussians.
    FirstFrame,
}

impl Trainer {
    /// One Adam step of the static Gaussians' shape, density and colour at `lr`, if there are
    /// any. Their centres stay where their own fit put them: Adam moves every parameter by
    /// about `lr` per step whatever its gradient, which would make a still object jitter.
    pub(super) fn step_statics(&mut self, grads: &mut Gradients, lr: f64) {
        let Some(statics) = &mut self.state.statics else {
            return;
        };
        statics.gaussians = adam_per_attribute(
            statics.gaussians.clone(),
            &mut statics.optim,
            grads,
            Gaussians {
                means: 0.0,
                rotations: lr,
                log_scales: lr,
                raw_densities: lr,
                colors: lr,
            },
        );
    }

    /// Fits the static Gaussians alone to the training views' per-pixel minimum over the
    /// loaded frames: smoke only adds light (emission over what it attenuates), so the minimum
    /// is what each pixel shows when the smoke in front of it is thinnest, the static scene
    /// wherever smoke is absent at least once. Frame 0's settings (iterations, learning rates).
    pub(super) fn fit_statics(&mut self) -> Result<Vec<LossRow>, TrainError> {
        if self.state.statics.is_none() {
            return Ok(Vec::new());
        }
        let observations = self.sequence.train[0].clone();
        let targets: Vec<Tensor<3>> = (0..observations.len())
            .map(|view| {
                let mut least = observations[view].image.data().to_vec();
                for frame in &self.sequence.train[1..] {
                    for (l, v) in least.iter_mut().zip(frame[view].image.data()) {
                        *l = l.min(*v);
                    }
                }
                let image = &observations[view].image;
                Tensor::from_data(
                    TensorData::new(least, [image.height() as usize, image.width() as usize, 3]),
                    &self.device,
                )
            })
            .collect();
        self.fit_to_images(StillFit::Statics, &observations, &targets)
    }

    /// `init.iterations` steps of `L_render` against
    /// the still images `targets` of `observations`' cameras, every attribute learning at
    /// frame 0's rates.
    pub(super) fn fit_to_images(
        &mut self,
        fit: StillFit,
        observations: &[Observation],
        targets: &[Tensor<3>],
    ) -> Result<Vec<LossRow>, TrainError> {
        let mut learning_rates = self.init_learning_rates();
        if fit == StillFit::Statics && !self.sequence.obstacles.is_empty() {
            // Placed where the data set says the solids are: they stay there.
            learning_rates.means = 0.0;
        }
        let iterations = self.config.init.iterations;
        let bar = self.progress(0, iterations);
        let phase = match fit {
            StillFit::Statics => {
                bar.set_prefix("statics");
                Phase::Statics
            }
            StillFit::FirstFrame => Phase::Init,
        };
        let mut losses = Vec::with_capacity(iterations);
        let mut log = StepLog::new(self.config.output.log_every);
        let mut lists = ListCapacities::new(self.config.device.tile_list_headroom);
        let cameras: Vec<Camera> = observations.iter().map(|o| o.camera).collect();
        for iteration in 0..iterations {
            let gaussians = match (fit, &self.state.statics) {
                (StillFit::Statics, Some(statics)) => statics.gaussians.tensors(),
                _ => self.scene(self.state.gaussians.tensors(), false),
            };
            let (loss, check) = self.render_loss(&gaussians, &cameras, targets, &mut lists)?;
            log.push(
                (0, phase, iteration),
                StepLosses {
                    total: loss.clone(),
                    render: loss.clone(),
                    divergence: None,
                    advection: None,
                    refine: None,
                },
                None,
                vec![check],
            );
            let mut grads = {
                let _phase = phase!("backward (all ops)");
                loss.backward()
            };
            match (fit, &mut self.state.statics) {
                (StillFit::Statics, Some(statics)) => {
                    statics.gaussians = adam_per_attribute(
                        statics.gaussians.clone(),
                        &mut statics.optim,
                        &mut grads,
                        learning_rates,
                    );
                }
                _ => self.step_gaussians(&mut grads, learning_rates),
            }
            if log.due() || iteration + 1 == iterations {
                read_log(&mut log, &mut losses, &bar, None)?;
                lists.expire();
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        Ok(losses)
    }

    /// Frame 0's learning rates per attribute (the centres' scaled by the box's extent).
    fn init_learning_rates(&self) -> Gaussians<f64> {
        let rates = &self.config.init.learning_rates;
        let extent = (self.sequence.hi - self.sequence.lo).max_element() as f64;
        Gaussians {
            means: rates.means * extent,
            rotations: rates.rotations,
            log_scales: rates.log_scales,
            raw_densities: rates.raw_densities,
            colors: rates.colors,
        }
    }

    /// One Adam step per Gaussian attribute, each with its own learning rate (0 skips it).
    pub(super) fn step_gaussians(&mut self, grads: &mut Gradients, learning_rates: Gaussians<f64>) {
        self.state.gaussians = adam_per_attribute(
            self.state.gaussians.clone(),
            &mut self.state.gaussian_optim,
            grads,
            learning_rates,
        );
        // Only a step that moved the centres can have moved one into an obstacle.
        if learning_rates.means > 0.0 {
            self.keep_out_of_obstacles();
        }
    }
}

/// The static Gaussians before their fit: inside the obstacles the data set describes, if any
/// (where the solids are), else spread through the box like the smoke's.
fn static_gaussians_at_start(
    sequence: &Sequence,
    config: &TrainConfig,
    device: &Device,
) -> GaussianModel {
    // Their own stream: not the smoke's positions again.
    let seed = config.seed ^ 0x5747_4943;
    let count = config.static_gaussians;
    let mut bounds: Option<(Vec3, Vec3)> = None;
    let mut volume = 0.0;
    for obstacle in &sequence.obstacles {
        let (lo, hi, v) = obstacle.bounds();
        volume += v;
        bounds = Some(bounds.map_or((lo, hi), |(a, b)| (a.min(lo), b.max(hi))));
    }
    // Packed into a smaller volume, the Gaussians are smaller: as dense as the smoke's at
    // their start, a ray through one would see so little that the renderer skips it
    // (`alpha_min`) and it would never learn. Give them the optical depth through the centre
    // that a smoke Gaussian starts with instead (it scales with density times size).
    let size = |volume: f32, count: usize| (volume / count.max(1) as f32).cbrt();
    let extent = sequence.hi - sequence.lo;
    let softplus = |x: f32| x.exp().ln_1p();
    let depth_scale =
        softplus(INITIAL_RAW_DENSITY) * size(extent.x * extent.y * extent.z, config.gaussians);
    let placed = |p: Vec3| {
        sequence
            .obstacles
            .iter()
            .any(|o| o.signed_distance(p) <= 0.0)
    };
    match bounds {
        Some((lo, hi)) => {
            let within = (lo.max(sequence.lo), hi.min(sequence.hi));
            GaussianModel::init_where(
                count,
                within,
                volume,
                placed,
                // The raw value (softplus^-1) of the density that keeps density x size.
                (depth_scale / size(volume, count)).exp_m1().ln(),
                seed,
                device,
            )
            // An obstacle reaching outside the box: fall back to the box.
            .unwrap_or_else(|| {
                GaussianModel::init_in_box(count, sequence.lo, sequence.hi, seed, device)
            })
        }
        None => GaussianModel::init_in_box(count, sequence.lo, sequence.hi, seed, device),
    }
}

/// The state Algorithm 1 starts from: Gaussians spread in the box, zero velocity, Phi's
/// initial weights.
pub(super) fn fresh_state(
    sequence: &Sequence,
    config: &TrainConfig,
    grid: &GridSpec,
    device: &Device,
) -> TrainState {
    let [nx, ny, nz] = grid.resolution();
    let unet = UNetConfig {
        base_channels: config.unet_channels,
        time_frequencies: config.time_frequencies,
    };
    TrainState {
        gaussians: GaussianModel::init_in_box(
            config.gaussians,
            sequence.lo,
            sequence.hi,
            config.seed,
            device,
        ),
        statics: (config.static_gaussians > 0).then(|| StaticGaussians {
            gaussians: static_gaussians_at_start(sequence, config, device),
            optim: AdamConfig::new().with_epsilon(1e-15).init(),
        }),
        velocity: Tensor::zeros([nx, ny, nz, 3], device),
        phi: VelocityUNet::new(&unet, config.seed, device),
        gaussian_optim: gaussian_optimizer(),
        phi_optim: AdamConfig::new().init(),
    }
}

/// A fresh Adam state for the smoke Gaussians.
fn gaussian_optimizer() -> ModuleOptimizer {
    // 3DGS practice: a tiny epsilon, so rarely-seen Gaussians still move.
    AdamConfig::new().with_epsilon(1e-15).init()
}
