//! The render loss every stage fits, what the renders composite, and the step logs' reads.

use burn::tensor::Tensor;
use gausmoke_core::Camera;
use gausmoke_model::settle_deferred_solves;
use gausmoke_render::cpu::TILE_SIZE;
use gausmoke_render::device_traffic::{ReadKind, read_floats_for};
use gausmoke_render::{
    GaussianTensors, InputCheck, RasterOptions, list_buffer_lengths, render_volume_deferred,
};
use indicatif::ProgressBar;

use super::Trainer;
use crate::TrainError;
use crate::state::{LossRow, Phase};
use crate::step_log::StepLog;

/// Reads `log` (and `tail` with it), appends its rows to `losses` and shows the last one on
/// `bar`; returns `tail`'s values.
pub(super) fn read_log(
    log: &mut StepLog,
    losses: &mut Vec<LossRow>,
    bar: &ProgressBar,
    tail: Option<Tensor<1>>,
) -> Result<Vec<f32>, TrainError> {
    let flushed = log.flush(tail)?;
    // The steps' deferred projection solves are judged with their losses.
    let solves = settle_deferred_solves();
    if solves.unconverged > 0 {
        tracing::warn!(
            unconverged = solves.unconverged,
            of = solves.solves,
            worst_relative_residual = solves.worst_relative_residual,
            "projection solves ran out of their iteration budget before converging (the next \
             budgets are raised from what they needed)"
        );
    }
    if let Some(row) = flushed.rows.last() {
        bar.set_message(match row.phase {
            Phase::Statics | Phase::Init => format!("L1 {:.5}", row.render),
            Phase::Advect => format!(
                "L1 {:.5} div {:.2e} adv {:.2e}",
                row.render, row.divergence, row.advection
            ),
            Phase::Refine => format!("L1 {:.5} refine {:.2e}", row.render, row.refine),
        });
    }
    losses.extend(flushed.rows);
    Ok(flushed.tail)
}

/// Fewest entries a tile-list buffer is given, so that a view with almost nothing in it at
/// the loop's first step still has room when the smoke moves in.
const MIN_TILE_LIST_CAPACITY: u32 = 4096;

/// The tile-list buffer sizes of one loop's renders of one set of views (one per view), so
/// that no GPU render reads its list length back: measured (one read for all the views) at the
/// loop's first step and again after each read of the loop's log, so they follow the
/// Gaussians as they grow or move (frame 0's fit changes them most), and given `headroom`;
/// every step checks on the device, with its other checks, that its renders had room (see
/// [`InputCheck::with_list_capacities`]).
pub(super) struct ListCapacities {
    headroom: f32,
    views: Option<Vec<u32>>,
}

impl ListCapacities {
    pub(super) fn new(headroom: f32) -> Self {
        Self {
            headroom,
            views: None,
        }
    }

    /// The next step measures again.
    pub(super) fn expire(&mut self) {
        self.views = None;
    }

    /// The capacities, measured from `lengths` (`[views]`, on the device) on the first call
    /// after [`ListCapacities::new`] or [`ListCapacities::expire`]; none above `most`, the
    /// length if every Gaussian touched every tile.
    fn for_lengths(&mut self, lengths: &Tensor<1>, most: &[u64]) -> Vec<u32> {
        let headroom = self.headroom as f64;
        self.views
            .get_or_insert_with(|| {
                read_floats_for(lengths.clone(), ReadKind::TileListLength)
                    .into_iter()
                    .zip(most)
                    .map(|(length, &most)| {
                        let room = (length as f64 * headroom).ceil() as u64;
                        let room = room.max(u64::from(MIN_TILE_LIST_CAPACITY)).min(most);
                        u32::try_from(room).unwrap_or(u32::MAX)
                    })
                    .collect()
            })
            .clone()
    }
}

impl Trainer {
    /// Mean L1 of the Gaussians' renders from `cameras` against `targets`, their tile-list
    /// buffers sized by `lists`.
    pub(super) fn render_loss(
        &self,
        gaussians: &GaussianTensors,
        cameras: &[Camera],
        targets: &[Tensor<3>],
        lists: &mut ListCapacities,
    ) -> Result<(Tensor<1>, InputCheck), TrainError> {
        let lengths = list_buffer_lengths(gaussians, cameras, &self.raster);
        let most: Vec<u64> = cameras
            .iter()
            .map(|c| {
                let tiles =
                    c.width().div_ceil(TILE_SIZE as u32) * c.height().div_ceil(TILE_SIZE as u32);
                (gaussians.len() as u64 * u64::from(tiles)).max(1)
            })
            .collect();
        let capacities = lists.for_lengths(&lengths, &most);
        // Every view renders the same Gaussians: one check covers them.
        let check = InputCheck::new(gaussians, &self.background)?
            .with_list_capacities(lengths, capacities.clone())?;
        let mut total: Option<Tensor<1>> = None;
        for ((camera, target), capacity) in cameras.iter().zip(targets).zip(capacities) {
            let options = RasterOptions {
                tile_list_capacity: Some(capacity),
                ..self.raster
            };
            let out =
                render_volume_deferred(gaussians, camera, &self.background, &options, &check)?;
            let l1 = (out.rgb - target.clone()).abs().mean();
            total = Some(match total {
                Some(t) => t + l1,
                None => l1,
            });
        }
        Ok((
            total.expect("at least one training view") / cameras.len() as f32,
            check,
        ))
    }

    /// What the renders composite: the smoke Gaussians `smoke` and, when there are any, the
    /// static ones after them, tracked for their optimiser when `learn_statics`.
    pub(super) fn scene(&self, smoke: GaussianTensors, learn_statics: bool) -> GaussianTensors {
        match &self.state.statics {
            Some(statics) => {
                let fixed = statics.gaussians.tensors();
                let fixed = if learn_statics { fixed } else { fixed.detach() };
                smoke.concat(fixed)
            }
            None => smoke,
        }
    }
}
