//! An explicit buoyancy force (ours): an upward change of velocity in proportion to the
//! density, `b * sigma / max(sigma)` on the y (up) component, with one coefficient `b` fitted
//! to the pictures. A plume's velocity is such a force accumulated and carried along; without
//! it, Phi has to produce that push anew at every frame, against the inertia prior.

use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};

/// The coefficient `b` of the force, a module so that its optimiser and checkpoint are
/// burn's.
#[derive(Module, Debug)]
pub struct BuoyancyForce {
    /// The upward change of velocity per frame at the densest cell, world units per frame.
    pub coefficient: Param<Tensor<1>>,
}

impl BuoyancyForce {
    pub fn new(coefficient: f32, device: &Device) -> Self {
        Self {
            coefficient: Param::from_tensor(Tensor::from_data(
                TensorData::new(vec![coefficient], [1]),
                device,
            )),
        }
    }

    /// The force's change of velocity over one frame, `[nx, ny, nz, 3]`, for `density`
    /// `[nx, ny, nz]`. The density is scaled by its largest value (held constant for the
    /// gradient), so that `b` has the velocity's units whatever the density's are; the
    /// gradient reaches `b` alone, not the density.
    pub fn velocity_change(&self, density: Tensor<3>) -> Tensor<4> {
        let [nx, ny, nz] = density.dims();
        let density = density.detach();
        let largest = density.clone().max().clamp_min(1e-12).reshape([1, 1, 1, 1]);
        let upward = density.reshape([nx, ny, nz, 1]) / largest
            * self.coefficient.val().reshape([1, 1, 1, 1]);
        Tensor::cat(
            vec![upward.zeros_like(), upward.clone(), upward.zeros_like()],
            3,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use gausmoke_render::backends::cpu_devices;
    use gausmoke_render::device_traffic::read_floats;

    /// Densities 0, 1, 2, 4 on a 2x2x1 grid.
    fn density(device: &Device) -> Tensor<3> {
        Tensor::from_data(
            TensorData::new(vec![0.0f32, 1.0, 2.0, 4.0], [2, 2, 1]),
            device,
        )
    }

    #[test]
    fn the_force_pushes_up_in_proportion_to_the_density() {
        let device = cpu_devices()[0].1.clone();
        let force = BuoyancyForce::new(0.5, &device);
        let change = read_floats(force.velocity_change(density(&device)));
        let upward = [0.0, 0.125, 0.25, 0.5];
        for (cell, want) in upward.iter().enumerate() {
            let got = &change[cell * 3..cell * 3 + 3];
            assert_eq!(got[0], 0.0, "cell {cell}: x");
            assert!((got[1] - want).abs() < 1e-7, "cell {cell}: y {}", got[1]);
            assert_eq!(got[2], 0.0, "cell {cell}: z");
        }
    }

    /// The coefficient's gradient is the upstream gradient's y part weighed by the scaled
    /// density; the density gets none.
    #[test]
    fn the_gradient_reaches_the_coefficient_alone() {
        let device = cpu_devices()[0].1.clone().autodiff();
        let force = BuoyancyForce::new(0.3, &device);
        let density = density(&device).require_grad();
        let weights: Vec<f32> = (0..12).map(|i| 0.1 * i as f32 - 0.4).collect();
        let upstream =
            Tensor::<4>::from_data(TensorData::new(weights.clone(), [2, 2, 1, 3]), &device);
        let grads = (force.velocity_change(density.clone()) * upstream)
            .sum()
            .backward();
        let got = read_floats(force.coefficient.val().grad(&grads).unwrap())[0];
        let want: f32 = [0.0f32, 0.25, 0.5, 1.0]
            .iter()
            .enumerate()
            .map(|(cell, scaled)| scaled * weights[cell * 3 + 1])
            .sum();
        assert!((got - want).abs() < 1e-6, "{got} against {want}");
        assert!(density.grad(&grads).is_none(), "the density is held");
    }
}
