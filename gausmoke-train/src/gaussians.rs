//! The Gaussians as a trainable burn module, their initialisation inside the smoke box, and
//! host copies for exports.

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::glam::Vec3;
use gausmoke_render::GaussianTensors;
pub use gausmoke_render::scenes::HostGaussians;
use gausmoke_render::scenes::SplitMix64;

/// Trainable Gaussian parameters, in the renderer's parameterisation (see
/// [`GaussianTensors`]): world-space centres, quaternions (w first), log standard
/// deviations, raw densities (`sigma = softplus(raw)`), linear RGB colours.
#[derive(Module, Debug)]
pub struct GaussianModel {
    pub means: Param<Tensor<2>>,
    pub rotations: Param<Tensor<2>>,
    pub log_scales: Param<Tensor<2>>,
    pub raw_densities: Param<Tensor<1>>,
    pub colors: Param<Tensor<2>>,
}

fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data()
        .try_into_vec_as::<f32>()
        .expect("float tensors read back as f32")
}

impl GaussianModel {
    /// `count` Gaussians spread uniformly inside `[lo, hi]`, isotropic, with a size that
    /// tiles the box (`std = 0.5 * (volume / count)^(1/3)`), a low density so the initial
    /// render is translucent, grey colour, random orientation.
    pub fn init_in_box(count: usize, lo: Vec3, hi: Vec3, seed: u64, device: &Device) -> Self {
        let mut rng = SplitMix64::new(seed);
        let extent = hi - lo;
        let spacing = (extent.x * extent.y * extent.z / count as f32).cbrt();
        let log_std = (0.5 * spacing).ln();
        let mut host = HostGaussians {
            means: Vec::with_capacity(count * 3),
            rotations: Vec::with_capacity(count * 4),
            log_scales: vec![log_std; count * 3],
            // softplus(-2) = 0.13 per world unit: a 0.5-unit box starts mostly transparent.
            raw_densities: vec![-2.0; count],
            colors: vec![0.5; count * 3],
        };
        for _ in 0..count {
            for axis in 0..3 {
                host.means.push(rng.range(lo[axis], hi[axis]));
            }
            let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
            let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-6);
            host.rotations.extend(q.iter().map(|v| v / norm));
        }
        Self::from_host(&host, device)
    }

    pub fn from_host(host: &HostGaussians, device: &Device) -> Self {
        let n = host.len();
        let t2 = |v: &[f32], cols: usize| {
            Param::from_tensor(Tensor::<2>::from_data(
                TensorData::new(v.to_vec(), [n, cols]),
                device,
            ))
        };
        Self {
            means: t2(&host.means, 3),
            rotations: t2(&host.rotations, 4),
            log_scales: t2(&host.log_scales, 3),
            raw_densities: Param::from_tensor(Tensor::<1>::from_data(
                TensorData::new(host.raw_densities.clone(), [n]),
                device,
            )),
            colors: t2(&host.colors, 3),
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
        GaussianTensors {
            means: self.means.val(),
            rotations: self.rotations.val(),
            log_scales: self.log_scales.val(),
            raw_densities: self.raw_densities.val(),
            colors: self.colors.val(),
        }
    }

    /// The same Gaussians with their centres replaced (e.g. by advected ones).
    pub fn tensors_at(&self, means: Tensor<2>) -> GaussianTensors {
        GaussianTensors {
            means,
            ..self.tensors()
        }
    }

    pub fn to_host(&self) -> HostGaussians {
        HostGaussians {
            means: to_vec(self.means.val()),
            rotations: to_vec(self.rotations.val()),
            log_scales: to_vec(self.log_scales.val()),
            raw_densities: to_vec(self.raw_densities.val()),
            colors: to_vec(self.colors.val()),
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
        assert_eq!(host.len(), self.len(), "recycling keeps the Gaussian count");
        let device = self.means.val().device();
        let fresh = Self::from_host(host, &device);
        let keep = |id, tensor: Tensor<2>| Param::initialized(id, tensor.require_grad());
        Self {
            means: keep(self.means.id, fresh.means.val()),
            rotations: keep(self.rotations.id, fresh.rotations.val()),
            log_scales: keep(self.log_scales.id, fresh.log_scales.val()),
            raw_densities: Param::initialized(
                self.raw_densities.id,
                fresh.raw_densities.val().require_grad(),
            ),
            colors: keep(self.colors.id, fresh.colors.val()),
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
            .clamp(-12.0, 4.0)
            .detach()
            .require_grad();
        Self {
            colors: Param::initialized(colors_id, colors),
            log_scales: Param::initialized(scales_id, log_scales),
            ..self
        }
    }
}
