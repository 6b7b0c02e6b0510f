//! The held-out views' PSNR through a frame (`held_out_trace`, ours; issue 18).
//!
//! A diagnostic: where in a frame the held-out view is won or lost, which the frame's one
//! figure after its last step cannot tell: what the frame before's state gives where it
//! stands, what each joint iteration's carried state gives, and what the refinement's steps
//! add. The views are rendered outside the autodiff graph and nothing is fed back; the errors
//! stay on the device until the frame ends and are read once.

use burn::tensor::Tensor;
use gausmoke_render::device_traffic::read_floats;
use serde::{Deserialize, Serialize};

use crate::metrics::psnr_of_mse;

/// Where in a frame a trace point was taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    /// The frame before's state, not moved (step 0).
    Still,
    /// The state joint iteration `step` renders: carried by that iteration's velocity, its
    /// appearance as the iterations before left it.
    Joint,
    /// The refinement's state after `step` steps.
    Refine,
}

/// The held-out views' mean PSNR at one point of a frame (in `metrics.json`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TracePoint {
    pub stage: Stage,
    pub step: usize,
    pub psnr: f64,
}

/// Each point's mean squared error per held-out view, on the device.
#[derive(Default)]
pub struct HeldOutTrace {
    points: Vec<(Stage, usize)>,
    errors: Vec<Tensor<1>>,
}

impl HeldOutTrace {
    pub fn new() -> Self {
        Self::default()
    }

    /// Records the held-out views' mean squared errors `[views]` at `(stage, step)`.
    pub fn record(&mut self, point: (Stage, usize), errors: Tensor<1>) {
        self.points.push(point);
        self.errors.push(errors.detach());
    }

    /// The mean over views of each point's PSNR (as the frame's `test_psnr` averages it).
    pub fn finish(self) -> Vec<TracePoint> {
        let Some(first) = self.errors.first() else {
            return Vec::new();
        };
        let [views] = first.dims();
        let errors = read_floats(Tensor::cat(self.errors, 0));
        self.points
            .into_iter()
            .zip(errors.chunks(views))
            .map(|((stage, step), errors)| TracePoint {
                stage,
                step,
                psnr: errors
                    .iter()
                    .map(|&mse| psnr_of_mse(f64::from(mse)))
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
    fn each_point_reads_as_the_mean_of_its_views_psnr() {
        let device = device_by_name("flex").expect("the default build has Flex");
        let mut trace = HeldOutTrace::new();
        assert!(HeldOutTrace::new().finish().is_empty());
        for (point, errors) in [
            ((Stage::Still, 0), [1e-2, 1e-4]),
            ((Stage::Refine, 4), [1e-3, 1e-3]),
        ] {
            let errors = Tensor::<1>::from_data(TensorData::new(errors.to_vec(), [2]), &device);
            trace.record(point, errors);
        }
        let trace = trace.finish();
        assert_eq!(trace.len(), 2);
        assert_eq!((trace[0].stage, trace[0].step), (Stage::Still, 0));
        assert_eq!((trace[1].stage, trace[1].step), (Stage::Refine, 4));
        assert!((trace[0].psnr - 30.0).abs() < 1e-4, "{trace:?}");
        assert!((trace[1].psnr - 30.0).abs() < 1e-4, "{trace:?}");
    }
}
