//! The mean of the Gaussians over a fit's last steps (`refine_average_steps`, ours; issue 18).
//!
//! With one training view a refinement step, the views take turns, so the state after the
//! last step leans towards the last view fitted, and towards the same view at every frame.
//! The mean over a whole turn of steps weighs every view alike. Every attribute is averaged
//! in the parameters' own terms (raw quaternions, which the renderer normalises; log-scales;
//! raw densities), on the device, outside the autodiff graph.

use burn::tensor::Tensor;
use gausmoke_render::{GaussianTensors, Gaussians};

/// A running sum of Gaussian states with the same rows.
#[derive(Debug, Default)]
pub struct IterateMean {
    sum: Option<GaussianTensors>,
    count: usize,
}

impl IterateMean {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds one state (detached here).
    pub fn add(&mut self, state: GaussianTensors) {
        let state = state.detach();
        self.sum = Some(match self.sum.take() {
            None => state,
            Some(sum) => Gaussians {
                means: sum.means + state.means,
                rotations: sum.rotations + state.rotations,
                log_scales: sum.log_scales + state.log_scales,
                raw_densities: sum.raw_densities + state.raw_densities,
                colors: sum.colors + state.colors,
            },
        });
        self.count += 1;
    }

    /// How many states were added.
    pub fn count(&self) -> usize {
        self.count
    }

    /// The mean of the states added; `None` when there were none.
    pub fn mean(self) -> Option<GaussianTensors> {
        let scale = 1.0 / self.count as f32;
        let mean2 = |sum: Tensor<2>| sum * scale;
        self.sum.map(|sum| Gaussians {
            means: mean2(sum.means),
            rotations: mean2(sum.rotations),
            log_scales: mean2(sum.log_scales),
            raw_densities: sum.raw_densities * scale,
            colors: mean2(sum.colors),
        })
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use burn::tensor::{Device, TensorData};
    use gausmoke_render::backends::device_by_name;
    use gausmoke_render::device_traffic::read_floats;

    /// Two Gaussians with every value `value`.
    pub(crate) fn state(value: f32, device: &Device) -> GaussianTensors {
        let rows = |columns: usize| {
            Tensor::<2>::from_data(
                TensorData::new(vec![value; 2 * columns], [2, columns]),
                device,
            )
        };
        Gaussians {
            means: rows(3),
            rotations: rows(4),
            log_scales: rows(3),
            raw_densities: Tensor::<1>::from_data(TensorData::new(vec![value; 2], [2]), device),
            colors: rows(3),
        }
    }

    #[test]
    fn the_mean_of_states_is_their_elementwise_mean() {
        let device = device_by_name("flex").expect("the default build has Flex");
        let mut mean = IterateMean::new();
        for value in [1.0, 2.0, 6.0] {
            mean.add(state(value, &device));
        }
        assert_eq!(mean.count(), 3);
        let mean = mean.mean().expect("three states were added");
        let values = |t: Tensor<1>| read_floats(t);
        for attribute in [mean.means, mean.rotations, mean.log_scales, mean.colors] {
            let flat = attribute.flatten::<1>(0, 1);
            assert!(values(flat).iter().all(|&v| (v - 3.0).abs() < 1e-6));
        }
        assert!(
            values(mean.raw_densities)
                .iter()
                .all(|&v| (v - 3.0).abs() < 1e-6)
        );
    }

    #[test]
    fn no_states_have_no_mean() {
        assert!(IterateMean::new().mean().is_none());
    }
}
