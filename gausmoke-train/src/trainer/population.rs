//! Stage 3 of a frame (ours; the paper's set is fixed, only advected): after the joint step,
//! Gaussians the training views leave unused are recycled to where the views show missing
//! smoke (`respawn_*`, [`crate::respawn`]), in the inflow box when the scene has one, and the
//! largest opaque Gaussians are split in two (`population.split.fraction`, [`crate::split`]), so that
//! the refinement fits the new rows.

use gausmoke_core::phase;
use gausmoke_render::HostGaussians;

use super::Trainer;
use crate::TrainError;
use crate::respawn::{
    DeficitView, RespawnOptions, RespawnReport, SpawnLattice, recycling_candidates, respawn,
};
use crate::split::{SplitReport, split_largest};

/// Only Gaussians whose longest standard deviation exceeds this multiple of the
/// initialisation's (`0.5 (V / N)^(1/3)` for a box of volume `V` and `N` Gaussians) are
/// split.
const SPLIT_SIZE_FACTOR: f32 = 1.0;

/// What [`Trainer::renew_population`] did to the rows in one frame.
#[derive(Debug, Default)]
pub(super) struct Renewal {
    pub recycled: RespawnReport,
    pub split: SplitReport,
}

impl Renewal {
    /// Rows that jumped this frame (left out of the refinement moves' persistence).
    pub fn moved_rows(&self) -> Vec<usize> {
        [
            &self.recycled.indices,
            &self.split.parents,
            &self.split.children,
        ]
        .into_iter()
        .flatten()
        .copied()
        .collect()
    }
}

impl Trainer {
    /// Recycles, then splits, on the host: one read from the device and a write back when
    /// rows changed. No row is taken twice.
    pub(super) fn renew_population(&mut self, t: usize) -> Result<Renewal, TrainError> {
        if self.config.population.recycle.fraction <= 0.0
            && self.config.population.split.fraction <= 0.0
        {
            return Ok(Renewal::default());
        }
        let mut host = self.state.gaussians.to_host();
        let recycled = self.recycle(t, &mut host)?;
        let split = self.split(&mut host, &recycled.indices);
        if !recycled.indices.is_empty() || !split.parents.is_empty() {
            self.state.gaussians = self.state.gaussians.clone().with_host_values(&host);
        }
        if !split.parents.is_empty() {
            // A half may land in an obstacle, as an advected centre may.
            self.keep_out_of_obstacles();
        }
        Ok(Renewal { recycled, split })
    }

    /// Recycles rows of `host` (see [`crate::respawn`]) against frame `t`'s training views,
    /// after the Gaussians were carried to frame `t`; nothing happens with
    /// `population.recycle.fraction = 0`.
    fn recycle(&self, t: usize, host: &mut HostGaussians) -> Result<RespawnReport, TrainError> {
        if self.config.population.recycle.fraction <= 0.0 {
            return Ok(RespawnReport::default());
        }
        let _phase = phase!("respawn");
        let observations = &self.sequence.train[t];
        let renders = self.render_host(observations)?;
        let views: Vec<DeficitView> = observations
            .iter()
            .zip(&renders)
            .map(|(observation, rendered)| DeficitView {
                camera: &observation.camera,
                observed: observation.image.data(),
                rendered,
            })
            .collect();
        let lattice = self.spawn_lattice();
        let options = RespawnOptions {
            fraction: self.config.population.recycle.fraction,
            threshold: self.config.population.recycle.threshold,
            std: self.initial_std(),
            background: self.sequence.background,
            // A per-frame stream, so a resumed run draws what an uninterrupted one did.
            seed: self.config.seed ^ (t as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15),
            region: self
                .config
                .scene
                .inflow
                .map(|fractions| lattice.region_from_fractions(fractions)),
        };
        let report = respawn(host, &views, &lattice, &options, &[]);
        tracing::debug!(
            frame = t,
            recycled = report.indices.len(),
            from_box_faces = report.from_box_faces,
            deficit_cells = report.deficit_cells,
            max_deficit = report.max_deficit,
            "respawn"
        );
        Ok(report)
    }

    /// Splits the largest rows of `host` (see [`crate::split`]) into rows recycling would
    /// take, other than the `taken` ones (recycled this frame); nothing happens with
    /// `population.split.fraction = 0`.
    fn split(&self, host: &mut HostGaussians, taken: &[usize]) -> SplitReport {
        if self.config.population.split.fraction <= 0.0 {
            return SplitReport::default();
        }
        let _phase = phase!("split");
        let lattice = self.spawn_lattice();
        let min_std = SPLIT_SIZE_FACTOR * self.initial_std();
        let budget = (self.config.population.split.fraction * host.len() as f32).floor() as usize;
        let (slots, _) = recycling_candidates(host, &lattice, taken);
        let report = split_largest(host, &slots, budget, min_std, &lattice);
        tracing::debug!(split = report.parents.len(), slots = slots.len(), "split");
        report
    }

    /// The box and lattice recycled and split Gaussians are placed in: the velocity grid's.
    fn spawn_lattice(&self) -> SpawnLattice {
        SpawnLattice {
            lo: self.grid.lo(),
            hi: self.grid.hi(),
            resolution: self.grid.resolution(),
        }
    }

    /// The Gaussians' standard deviation at initialisation (see `GaussianModel::init_in_box`).
    fn initial_std(&self) -> f32 {
        let extent = self.grid.hi() - self.grid.lo();
        let [count, _] = self.state.gaussians.means.val().dims();
        0.5 * (extent.x * extent.y * extent.z / count as f32).cbrt()
    }
}
