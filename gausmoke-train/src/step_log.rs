//! The losses and checks of the optimisation steps, kept on the device and read back together
//! every `output.log_every` steps: a read-back makes the host wait until the GPU has drained its
//! queue, so reading four loss terms, the largest speed and the renderer's input checks at
//! every step would stall the loop once per number.
//!
//! Each step queues a few one-element tensors (its losses, optionally one named diagnostic)
//! and the renderer's [`InputCheck`]s; [`StepLog::flush`] concatenates everything pending into
//! one tensor, reads it once and judges the steps in order, so the first bad step is the one
//! reported, as if it had been checked when it ran.

use burn::tensor::Tensor;
use gausmoke_render::device_traffic::read_floats;
use gausmoke_render::{InputCheck, RenderError};

use crate::TrainError;
use crate::state::{LossRow, Phase};

/// The loss terms of one step, as detached one-element tensors (`None`: the term is absent
/// from this step's loss and logged as 0).
pub struct StepLosses {
    pub total: Tensor<1>,
    pub render: Tensor<1>,
    pub divergence: Option<Tensor<1>>,
    pub advection: Option<Tensor<1>>,
    pub refine: Option<Tensor<1>>,
}

/// Where a step's numbers sit in the concatenated read.
struct Pending {
    frame: usize,
    phase: Phase,
    iteration: usize,
    present: [bool; 3],
    diagnostic: Option<&'static str>,
    /// The step's input checks, in order (their values are in the queue).
    checks: Vec<InputCheck>,
}

impl Pending {
    fn len(&self) -> usize {
        2 + self.present.iter().filter(|&&p| p).count()
            + usize::from(self.diagnostic.is_some())
            + self.checks.iter().map(InputCheck::len).sum::<usize>()
    }
}

/// Steps queued since the last read.
pub struct StepLog {
    every: usize,
    pending: Vec<Pending>,
    values: Vec<Tensor<1>>,
}

/// What a read returned: the judged rows, and the values of the `tail` tensor if one was given.
pub struct Flushed {
    pub rows: Vec<LossRow>,
    pub tail: Vec<f32>,
}

impl StepLog {
    /// Reads every `every` steps (at least 1).
    pub fn new(every: usize) -> Self {
        Self {
            every: every.max(1),
            pending: Vec::new(),
            values: Vec::new(),
        }
    }

    /// Queues one step: its losses, a named diagnostic that must be finite (e.g. the largest
    /// speed), and the renderer's input checks of the Gaussians it rendered.
    pub fn push(
        &mut self,
        (frame, phase, iteration): (usize, Phase, usize),
        losses: StepLosses,
        diagnostic: Option<(&'static str, Tensor<1>)>,
        checks: Vec<InputCheck>,
    ) {
        let StepLosses {
            total,
            render,
            divergence,
            advection,
            refine,
        } = losses;
        let present = [divergence.is_some(), advection.is_some(), refine.is_some()];
        self.values.push(total.detach());
        self.values.push(render.detach());
        self.values.extend(
            [divergence, advection, refine]
                .into_iter()
                .flatten()
                .map(|t| t.detach()),
        );
        let diagnostic = diagnostic.map(|(name, value)| {
            self.values.push(value.detach());
            name
        });
        self.values
            .extend(checks.iter().map(|c| c.values().detach()));
        self.pending.push(Pending {
            frame,
            phase,
            iteration,
            present,
            diagnostic,
            checks,
        });
    }

    /// Whether enough steps are queued to read them.
    pub fn due(&self) -> bool {
        self.pending.len() >= self.every
    }

    /// Reads everything queued, and `tail` with it, in one device read; judges the steps in
    /// order (input checks first, so a bad parameter is named before the NaN loss it causes,
    /// then the diagnostic, then the losses).
    pub fn flush(&mut self, tail: Option<Tensor<1>>) -> Result<Flushed, TrainError> {
        let tail_len = tail.as_ref().map_or(0, |t| t.dims()[0]);
        let mut values = std::mem::take(&mut self.values);
        values.extend(tail.map(|t| t.detach()));
        let pending = std::mem::take(&mut self.pending);
        if values.is_empty() {
            return Ok(Flushed {
                rows: Vec::new(),
                tail: Vec::new(),
            });
        }
        let host = read_floats(Tensor::cat(values, 0));
        let expected: usize = pending.iter().map(Pending::len).sum::<usize>() + tail_len;
        assert_eq!(host.len(), expected, "step log layout");
        let mut at = 0;
        let mut take = |n: usize| {
            let slice = &host[at..at + n];
            at += n;
            slice
        };
        let mut rows = Vec::with_capacity(pending.len());
        for step in &pending {
            let head = take(2);
            let (total, render) = (head[0], head[1]);
            let mut optional = [0.0f32; 3];
            for (slot, present) in optional.iter_mut().zip(step.present) {
                if present {
                    *slot = take(1)[0];
                }
            }
            let diagnostic = step.diagnostic.map(|name| (name, take(1)[0]));
            for check in &step.checks {
                check
                    .judge(take(check.len()))
                    .map_err(|error| match error {
                        RenderError::TileListOverflow { .. } => TrainError::TileListOverflow {
                            source: error,
                            frame: step.frame,
                            phase: step.phase.name(),
                            iteration: step.iteration,
                        },
                        RenderError::NonFinite { name } => TrainError::NonFinite {
                            quantity: format!("the Gaussians' `{name}`"),
                            value: "non-finite (NaN or infinity)".into(),
                            frame: step.frame,
                            phase: step.phase.name(),
                            iteration: step.iteration,
                        },
                        other => other.into(),
                    })?;
            }
            let row = LossRow {
                frame: step.frame,
                phase: step.phase,
                iteration: step.iteration,
                total,
                render,
                divergence: optional[0],
                advection: optional[1],
                refine: optional[2],
            };
            check_finite(&row, diagnostic)?;
            rows.push(row);
        }
        let tail = take(tail_len).to_vec();
        Ok(Flushed { rows, tail })
    }
}

/// Refuses a step whose losses, or `diagnostic` (a named quantity such as the largest
/// velocity, checked first so the report names the earliest thing that went wrong), are not
/// finite.
fn check_finite(row: &LossRow, diagnostic: Option<(&'static str, f32)>) -> Result<(), TrainError> {
    let terms = [
        ("the render loss", row.render),
        ("L_div", row.divergence),
        ("L_adv", row.advection),
        ("L_refine", row.refine),
        ("the total loss", row.total),
    ];
    if let Some((quantity, value)) = diagnostic
        .into_iter()
        .chain(terms)
        .find(|(_, v)| !v.is_finite())
    {
        return Err(TrainError::NonFinite {
            quantity: quantity.into(),
            value: value.to_string(),
            frame: row.frame,
            phase: row.phase.name(),
            iteration: row.iteration,
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use burn::tensor::{Device, Tensor, TensorData};
    use gausmoke_render::backends::device_by_name;
    use gausmoke_render::{GaussianTensors, Gaussians, InputCheck, RenderError};

    use super::{StepLog, StepLosses};
    use crate::TrainError;
    use crate::state::Phase;

    fn one(value: f32, device: &Device) -> Tensor<1> {
        Tensor::from_data(TensorData::new(vec![value], [1]), device)
    }

    fn losses(value: f32, device: &Device) -> StepLosses {
        StepLosses {
            total: one(value, device),
            render: one(value, device),
            divergence: Some(one(value / 2.0, device)),
            advection: None,
            refine: None,
        }
    }

    /// One Gaussian whose first centre coordinate is `x`.
    fn check(x: f32, device: &Device) -> InputCheck {
        let t = |values: Vec<f32>, n: usize| {
            Tensor::<2>::from_data(TensorData::new(values, [1, n]), device)
        };
        let gaussians: GaussianTensors = Gaussians {
            means: t(vec![x, 0.0, 0.0], 3),
            rotations: t(vec![1.0, 0.0, 0.0, 0.0], 4),
            log_scales: t(vec![-2.0; 3], 3),
            raw_densities: Tensor::<1>::from_data(TensorData::new(vec![0.0], [1]), device),
            colors: t(vec![0.5; 3], 3),
        };
        InputCheck::new(&gaussians, &one(0.0, device).repeat_dim(0, 3)).unwrap()
    }

    #[test]
    fn rows_come_back_in_order_and_the_first_bad_step_is_named() {
        let device = device_by_name("flex").unwrap();
        let mut log = StepLog::new(3);
        for i in 0..3 {
            log.push(
                (1, Phase::Advect, i),
                losses(i as f32, &device),
                Some(("the largest speed", one(2.0, &device))),
                vec![check(0.1, &device)],
            );
        }
        assert!(log.due());
        let flushed = log.flush(Some(one(7.0, &device))).unwrap();
        let rows: Vec<(usize, f32, f32, f32)> = flushed
            .rows
            .iter()
            .map(|r| (r.iteration, r.total, r.divergence, r.advection))
            .collect();
        assert_eq!(
            rows,
            [(0, 0.0, 0.0, 0.0), (1, 1.0, 0.5, 0.0), (2, 2.0, 1.0, 0.0)]
        );
        assert_eq!(flushed.tail, [7.0]);
        assert!(!log.due());

        // Step 4's diagnostic, step 5's loss and step 5's parameters go bad: step 4 is named.
        log.push(
            (1, Phase::Advect, 3),
            losses(1.0, &device),
            Some(("the largest speed", one(f32::INFINITY, &device))),
            vec![check(0.1, &device)],
        );
        log.push(
            (1, Phase::Advect, 4),
            losses(f32::NAN, &device),
            None,
            vec![check(f32::NAN, &device)],
        );
        match log.flush(None) {
            Err(TrainError::NonFinite {
                quantity,
                iteration: 3,
                ..
            }) => assert_eq!(quantity, "the largest speed"),
            other => panic!("{:?}", other.map(|f| f.rows)),
        }

        // A bad parameter is named before the NaN loss it causes.
        log.push(
            (2, Phase::Refine, 0),
            losses(f32::NAN, &device),
            None,
            vec![check(f32::NAN, &device)],
        );
        match log.flush(None) {
            Err(TrainError::NonFinite {
                quantity, frame: 2, ..
            }) => assert_eq!(quantity, "the Gaussians' `means`"),
            other => panic!("{:?}", other.map(|f| f.rows)),
        }
    }

    #[test]
    fn a_tile_list_longer_than_its_buffer_names_the_step_and_the_view() {
        let device = device_by_name("flex").unwrap();
        let lengths = |values: Vec<f32>| {
            let n = values.len();
            Tensor::<1>::from_data(TensorData::new(values, [n]), &device)
        };
        let mut log = StepLog::new(10);
        let fits = check(0.1, &device)
            .with_list_capacities(lengths(vec![4096.0, 5000.0]), vec![4096, 6000])
            .unwrap();
        assert_eq!(fits.len(), InputCheck::STATS + 2);
        log.push(
            (3, Phase::Advect, 0),
            losses(1.0, &device),
            None,
            vec![fits],
        );
        let overflows = check(0.1, &device)
            .with_list_capacities(lengths(vec![100.0, 6001.0]), vec![4096, 6000])
            .unwrap();
        log.push(
            (3, Phase::Advect, 1),
            losses(1.0, &device),
            None,
            vec![overflows],
        );
        match log.flush(None) {
            Err(TrainError::TileListOverflow {
                source:
                    RenderError::TileListOverflow {
                        view: 1,
                        length,
                        capacity: 6000,
                    },
                frame: 3,
                iteration: 1,
                ..
            }) => assert_eq!(length, 6001.0),
            other => panic!("{:?}", other.map(|f| f.rows)),
        }
        // One capacity per length.
        assert!(
            check(0.1, &device)
                .with_list_capacities(lengths(vec![1.0]), vec![1, 2])
                .is_err()
        );
    }
}
