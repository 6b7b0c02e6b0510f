//! The Gaussians as a trainable burn module, and their initialisation inside the smoke box.

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_render::{Gaussian, GaussianTensors, Gaussians, HostGaussians};

/// The raw density [`GaussianModel::init_in_box`] gives: softplus(-2) = 0.13 per world unit,
/// so a 0.5-unit box starts mostly transparent.
pub const INITIAL_RAW_DENSITY: f32 = -2.0;

/// The log-scales an optimiser step may leave: the renderer's accepted range.
const MIN_LOG_SCALE: f32 = -12.0;
const MAX_LOG_SCALE: f32 = 4.0;

/// Trainable Gaussian parameters, in the renderer's parameterisation (see [`Gaussians`]):
/// world-space centres, quaternions (w first), log standard deviations, raw densities
/// (`sigma = softplus(raw)`), linear RGB colours.
#[derive(Module, Debug)]
pub struct GaussianModel {
    pub means: Param<Tensor<2>>,
    pub rotations: Param<Tensor<2>>,
    pub log_scales: Param<Tensor<2>>,
    pub raw_densities: Param<Tensor<1>>,
    pub colors: Param<Tensor<2>>,
}

impl GaussianModel {
    /// `count` Gaussians spread uniformly inside `[lo, hi]`, isotropic, with a size that
    /// tiles the box (`std = 0.5 * (volume / count)^(1/3)`), a low density so the initial
    /// render is translucent, grey colour, random orientation.
    pub fn init_in_box(count: usize, lo: Vec3, hi: Vec3, seed: u64, device: &Device) -> Self {
        let extent = hi - lo;
        Self::init_where(
            count,
            (lo, hi),
            extent.x * extent.y * extent.z,
            |_| true,
            INITIAL_RAW_DENSITY,
            seed,
            device,
        )
        .expect("every point of the box is inside it")
    }

    /// As [`GaussianModel::init_in_box`], with the centres drawn uniformly from the points of
    /// `bounds` where `inside` holds (a region of `volume` world units cubed, which sizes the
    /// Gaussians) and raw density `raw_density`; `None` when a thousand draws per Gaussian
    /// found too few such points.
    pub fn init_where(
        count: usize,
        (lo, hi): (Vec3, Vec3),
        volume: f32,
        inside: impl Fn(Vec3) -> bool,
        raw_density: f32,
        seed: u64,
        device: &Device,
    ) -> Option<Self> {
        let mut rng = SplitMix64::new(seed);
        let spacing = (volume / count as f32).cbrt();
        let log_std = (0.5 * spacing).ln();
        let mut host = HostGaussians::with_capacity(count);
        let mut draws = 0usize;
        while host.len() < count {
            draws += 1;
            if draws > 1000 * count.max(1) {
                return None;
            }
            let mean = [0, 1, 2].map(|axis| rng.range(lo[axis], hi[axis]));
            if !inside(Vec3::from_array(mean)) {
                continue;
            }
            let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
            let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-6);
            host.push(&Gaussian {
                mean,
                rotation: q.map(|v| v / norm),
                log_scale: [log_std; 3],
                raw_density,
                color: [0.5; 3],
            });
        }
        Some(Self::from_host(&host, device))
    }

    pub fn from_host(host: &HostGaussians, device: &Device) -> Self {
        Self::from_tensors(
            host.to_tensors(device)
                .expect("host Gaussians hold N rows of every attribute"),
        )
    }

    /// New parameters holding `tensors`.
    pub fn from_tensors(tensors: GaussianTensors) -> Self {
        Self {
            means: Param::from_tensor(tensors.means),
            rotations: Param::from_tensor(tensors.rotations),
            log_scales: Param::from_tensor(tensors.log_scales),
            raw_densities: Param::from_tensor(tensors.raw_densities),
            colors: Param::from_tensor(tensors.colors),
        }
    }

    pub fn len(&self) -> usize {
        self.raw_densities.dims()[0]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The renderer's view of the parameters (tracked for autodiff).
    pub fn tensors(&self) -> GaussianTensors {
        Gaussians {
            means: self.means.val(),
            rotations: self.rotations.val(),
            log_scales: self.log_scales.val(),
            raw_densities: self.raw_densities.val(),
            colors: self.colors.val(),
        }
    }

    /// The same Gaussians with their centres replaced (e.g. by advected ones).
    pub fn tensors_at(&self, means: Tensor<2>) -> GaussianTensors {
        Gaussians {
            means,
            ..self.tensors()
        }
    }

    pub fn to_host(&self) -> HostGaussians {
        self.tensors().to_host()
    }

    /// The ids of the parameters, attribute by attribute (what per-attribute optimiser steps
    /// select).
    pub fn param_ids(&self) -> Gaussians<burn::module::ParamId> {
        Gaussians {
            means: self.means.id,
            rotations: self.rotations.id,
            log_scales: self.log_scales.id,
            raw_densities: self.raw_densities.id,
            colors: self.colors.id,
        }
    }

    /// Replaces the centres, keeping the parameter's id so its optimiser state carries over.
    pub fn with_means(self, means: Tensor<2>) -> Self {
        let id = self.means.id;
        Self {
            means: Param::initialized(id, means.detach().require_grad()),
            ..self
        }
    }

    /// Replaces every parameter's values with `host`'s (same count), keeping the parameter
    /// ids so the optimiser's state carries over (used when Gaussians are recycled).
    pub fn with_host_values(self, host: &HostGaussians) -> Self {
        let device = self.means.val().device();
        let fresh = host
            .to_tensors(&device)
            .expect("host Gaussians hold N rows of every attribute");
        self.with_values(fresh)
    }

    /// Replaces every parameter's values with `values` (same count, detached), keeping the
    /// parameter ids so the optimiser's state carries over.
    pub fn with_values(self, values: GaussianTensors) -> Self {
        assert_eq!(
            values.raw_densities.dims()[0],
            self.len(),
            "new values keep the Gaussian count"
        );
        let values = values.detach();
        Self {
            means: Param::initialized(self.means.id, values.means.require_grad()),
            rotations: Param::initialized(self.rotations.id, values.rotations.require_grad()),
            log_scales: Param::initialized(self.log_scales.id, values.log_scales.require_grad()),
            raw_densities: Param::initialized(
                self.raw_densities.id,
                values.raw_densities.require_grad(),
            ),
            colors: Param::initialized(self.colors.id, values.colors.require_grad()),
        }
    }

    /// Keeps colours in `[0, 1]` and log-scales in the renderer's accepted range after an
    /// optimiser step (a projection onto the feasible set, not a reparameterisation).
    pub fn clamped(self) -> Self {
        let colors_id = self.colors.id;
        let scales_id = self.log_scales.id;
        let colors = self.colors.val().clamp(0.0, 1.0).detach().require_grad();
        let log_scales = self
            .log_scales
            .val()
            .clamp(MIN_LOG_SCALE, MAX_LOG_SCALE)
            .detach()
            .require_grad();
        Self {
            colors: Param::initialized(colors_id, colors),
            log_scales: Param::initialized(scales_id, log_scales),
            ..self
        }
    }
}
