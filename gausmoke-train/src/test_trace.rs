//! The held-out views' PSNR along a frame's refinement (`refine_test_trace`, ours; issue 18).
//!
//! A diagnostic: whether the refinement's steps bring a frame's held-out view closer or take
//! it further away, which the frame's one figure after its last step cannot tell. The views
//! are rendered outside the autodiff graph and nothing is fed back; the errors stay on the
//! device until the frame ends and are read once.

use burn::tensor::Tensor;
use gausmoke_render::device_traffic::read_floats;
use serde::{Deserialize, Serialize};

/// The held-out views' mean PSNR after `step` refinement steps (in `metrics.json`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StepPsnr {
    pub step: usize,
    pub psnr: f64,
}

/// Each check's mean squared error per held-out view, on the device.
#[derive(Default)]
pub struct TestTrace {
    steps: Vec<usize>,
    errors: Vec<Tensor<1>>,
}

impl TestTrace {
    pub fn new() -> Self {
        Self::default()
    }

    /// Records the held-out views' mean squared errors `[views]` after `step` steps.
    pub fn record(&mut self, step: usize, errors: Tensor<1>) {
        self.steps.push(step);
        self.errors.push(errors.detach());
    }

    /// The mean over views of each check's PSNR (as the frame's `test_psnr` averages it).
    pub fn finish(self) -> Vec<StepPsnr> {
        let Some(first) = self.errors.first() else {
            return Vec::new();
        };
        let [views] = first.dims();
        let errors = read_floats(Tensor::cat(self.errors, 0));
        self.steps
            .into_iter()
            .zip(errors.chunks(views))
            .map(|(step, errors)| StepPsnr {
                step,
                psnr: errors
                    .iter()
                    .map(|&mse| -10.0 * f64::from(mse).log10())
                    .sum::<f64>()
                    / views as f64,
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;
    use gausmoke_render::backends::device_by_name;

    #[test]
    fn each_check_reads_as_the_mean_of_its_views_psnr() {
        let device = device_by_name("flex").expect("the default build has Flex");
        let mut trace = TestTrace::new();
        assert!(TestTrace::new().finish().is_empty());
        for (step, errors) in [(0, [1e-2, 1e-4]), (4, [1e-3, 1e-3])] {
            let errors = Tensor::<1>::from_data(TensorData::new(errors.to_vec(), [2]), &device);
            trace.record(step, errors);
        }
        let trace = trace.finish();
        assert_eq!(trace.len(), 2);
        assert_eq!((trace[0].step, trace[1].step), (0, 4));
        assert!((trace[0].psnr - 30.0).abs() < 1e-4, "{trace:?}");
        assert!((trace[1].psnr - 30.0).abs() < 1e-4, "{trace:?}");
    }
}
