//! What training changes and what it reports: shared by the trainer, the run folder and the
//! checkpoints.

use burn::optim::ModuleOptimizer;
use burn::tensor::Tensor;
use gausmoke_model::{GaussianModel, VelocityUNet};
use serde::{Deserialize, Serialize};

/// Everything the optimisation changes; what a checkpoint stores.
pub struct TrainState {
    pub gaussians: GaussianModel,
    /// The static Gaussians (`static_gaussians > 0`), and their optimiser.
    pub statics: Option<StaticGaussians>,
    /// The velocity grid `u` at the current frame, `[nx, ny, nz, 3]`, world units per frame.
    pub velocity: Tensor<4>,
    pub phi: VelocityUNet,
    pub gaussian_optim: ModuleOptimizer,
    pub phi_optim: ModuleOptimizer,
}

/// Gaussians that are the same in every frame (solids, background): never advected.
pub struct StaticGaussians {
    pub gaussians: GaussianModel,
    pub optim: ModuleOptimizer,
}

/// Wall time of one phase (see `gausmoke_core::phases`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PhaseSeconds {
    pub calls: u64,
    pub seconds: f64,
}

/// Which part of Algorithm 1 a step belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// The fit of the static Gaussians, before frame 0's (`static_gaussians > 0`).
    Statics,
    /// The static fit of frame 0.
    Init,
    /// The K joint iterations (lines 3-9).
    Advect,
    /// The K' refinement iterations (lines 11-13).
    Refine,
}

impl Phase {
    pub fn name(self) -> &'static str {
        match self {
            Phase::Statics => "statics",
            Phase::Init => "init",
            Phase::Advect => "advect",
            Phase::Refine => "refine",
        }
    }
}

/// Device-to-host reads and kernel launches of one of a frame's optimisation loops (see
/// `gausmoke_render::device_traffic`; launches are 0 on the CPU backends).
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct LoopTraffic {
    pub phase: Phase,
    pub iterations: usize,
    /// Reads of every kind, and of them the renderer's tile-list lengths and the projection
    /// solver's convergence tests.
    pub reads: u64,
    pub tile_list_reads: u64,
    pub solver_reads: u64,
    pub launches: u64,
}

impl LoopTraffic {
    /// The traffic since `start` of a loop of `iterations` steps.
    pub fn of(
        phase: Phase,
        iterations: usize,
        start: gausmoke_render::device_traffic::Traffic,
    ) -> Self {
        let counted = gausmoke_render::device_traffic::Traffic::now().since(start);
        Self {
            phase,
            iterations,
            reads: counted.reads,
            tile_list_reads: counted.tile_list_reads,
            solver_reads: counted.solver_reads,
            launches: counted.launches,
        }
    }
}

/// One optimisation step's losses (the CSV row of `losses.csv`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct LossRow {
    pub frame: usize,
    pub phase: Phase,
    pub iteration: usize,
    pub total: f32,
    pub render: f32,
    pub divergence: f32,
    pub advection: f32,
    pub refine: f32,
}

/// What happened at one frame (in `metrics.json`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct FrameReport {
    pub frame: usize,
    /// Mean absolute error over the training views after the frame's last step.
    pub train_l1: f64,
    /// Mean absolute error, PSNR and SSIM on the held-out views (`None` without any).
    pub test_l1: Option<f64>,
    pub test_psnr: Option<f64>,
    pub test_ssim: Option<f64>,
    /// Mean |div u| over the grid cells after `Pi` (1/frame).
    pub mean_abs_divergence: f64,
    /// The projection's solve at this frame's last step: iterations, relative residual and
    /// RMS divergence before and after.
    pub projection_iterations: usize,
    pub projection_residual: f64,
    pub divergence_rms_before: f64,
    pub divergence_rms_after: f64,
    /// Gaussians whose advected centre left the box and was clamped back onto it.
    pub clamped_to_box: usize,
    /// Gaussians recycled in this frame, between its joint iterations and its refinement
    /// (`population.recycle.fraction`).
    #[serde(default)]
    pub respawned: usize,
    /// Gaussians split in this frame, after recycling (`population.split.fraction`).
    #[serde(default)]
    pub split: usize,
    /// The refinement's move of the centres (mass-weighted; `None` without refinement):
    /// its RMS length in cells of the velocity grid, the share of its mean square in its
    /// grid-scale part (a move the velocity could have made), and that share with the moves
    /// shuffled among the Gaussians (the floor a move without spatial order reaches).
    #[serde(default)]
    pub refine_move_cells: Option<f64>,
    #[serde(default)]
    pub refine_move_grid_share: Option<f64>,
    #[serde(default)]
    pub refine_move_grid_share_shuffled: Option<f64>,
    /// Mass-weighted correlation of each Gaussian's move with its move at the frame before,
    /// and the same for the grid-scale parts (`None` at the first frame refined after a
    /// start or a resume, and without refinement).
    #[serde(default)]
    pub refine_move_persistence: Option<f64>,
    #[serde(default)]
    pub refine_move_grid_persistence: Option<f64>,
    /// Share of the moves' grid-scale field that the projection keeps (the part a
    /// divergence-free velocity can make).
    #[serde(default)]
    pub refine_move_flow_share: Option<f64>,
    /// Correlation over the cells of the move field's flow part with the frame before's,
    /// and of its gathering part (the rest) with the frame before's (`None` at the first
    /// frame refined after a start or a resume, and without refinement).
    #[serde(default)]
    pub refine_move_flow_persistence: Option<f64>,
    #[serde(default)]
    pub refine_move_gathering_persistence: Option<f64>,
    /// Mean and largest speed of the velocity grid (world units per frame).
    pub mean_speed: f64,
    pub max_speed: f64,
    pub seconds: f64,
    /// Device reads and kernel launches of the frame's optimisation loops.
    #[serde(default)]
    pub device_traffic: Vec<LoopTraffic>,
}

/// The refinement's grid-scale move field at one frame, on the host, in cells of the
/// velocity grid per frame (`[nx, ny, nz, 3]`, see `MoveField` in the trainer): the whole field and the
/// part the exact projection keeps (a flow); the rest gathers or spreads the Gaussians.
#[derive(Debug, Clone, PartialEq)]
pub struct RefineMoveField {
    pub moves: Vec<f32>,
    pub flow: Vec<f32>,
}

impl RefineMoveField {
    /// The field less its flow part.
    pub fn gathering(&self) -> Vec<f32> {
        self.moves
            .iter()
            .zip(&self.flow)
            .map(|(m, f)| m - f)
            .collect()
    }

    /// The share of the field's sum of squares in its flow part.
    pub(crate) fn flow_share(&self) -> f64 {
        let whole = dot(&self.moves, &self.moves);
        if whole > 0.0 {
            dot(&self.flow, &self.flow) / whole
        } else {
            0.0
        }
    }

    /// Correlations over the cells of the flow parts and of the gathering parts with
    /// `before`'s (0 where a part is zero).
    pub(crate) fn persistence(&self, before: &Self) -> [f64; 2] {
        [
            correlation(&self.flow, &before.flow),
            correlation(&self.gathering(), &before.gathering()),
        ]
    }
}

fn dot(a: &[f32], b: &[f32]) -> f64 {
    a.iter().zip(b).map(|(&x, &y)| x as f64 * y as f64).sum()
}

/// `a . b / (|a| |b|)`, 0 where either is zero.
fn correlation(a: &[f32], b: &[f32]) -> f64 {
    let norms = (dot(a, a) * dot(b, b)).sqrt();
    if norms > 0.0 { dot(a, b) / norms } else { 0.0 }
}

#[cfg(test)]
mod tests {
    /// Checkpoints keep the per-frame metrics in `state.json`; a resumed run writes them back
    /// into `metrics.json`, which must then equal an uninterrupted run's bit for bit. serde_json
    /// parses floats exactly only with its `float_roundtrip` feature.
    #[test]
    fn floats_survive_a_json_round_trip_bit_for_bit() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let values: Vec<f64> = (0..100_000)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                // Metrics-like magnitudes: PSNRs, L1s, seconds, divergences.
                let mantissa = (state >> 11) as f64 / (1u64 << 53) as f64;
                mantissa * 10f64.powi((state % 24) as i32 - 16)
            })
            .collect();
        let text = serde_json::to_string(&values).unwrap();
        let back: Vec<f64> = serde_json::from_str(&text).unwrap();
        let differing = values
            .iter()
            .zip(&back)
            .filter(|(a, b)| a.to_bits() != b.to_bits())
            .count();
        assert_eq!(
            differing,
            0,
            "{differing} of {} values changed",
            values.len()
        );
    }
}
