//! Stage 5 of a frame: how far and how coherently the refinement moved the centres, for the
//! frame's report (`refine_move_*` in metrics.json, refine_moves.png).

use burn::tensor::{Device, Int, Tensor, TensorData};
use gausmoke_model::{GridScale, GridSpec, ProjectionOptions, project_direct};
use gausmoke_render::device_traffic::read_floats;

use super::Trainer;
use crate::arrays::HostArrays;
use crate::state::RefineMoveField;

/// The refinement's move of the centres at one frame, mass-weighted (see
/// [`gausmoke_model::GridScale`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineMoves {
    /// RMS length of the move, in cells of the velocity grid.
    pub rms_cells: f64,
    /// Share of the move's mean square in its grid-scale part.
    pub grid_share: f64,
    /// The same share with the moves shuffled among the Gaussians: what a move without
    /// spatial order gets, the floor to read `grid_share` against.
    pub shuffled_grid_share: f64,
    /// Mass-weighted correlation of each Gaussian's move with its own move at the frame
    /// before, and the same for the moves' grid-scale parts: near 1 the refinement supplies
    /// the same motion frame after frame (motion the velocity keeps missing), near 0 its
    /// moves do not persist. Gaussians that jumped this frame are left out; `None` at the
    /// first frame the trainer refines (a resume takes the frame before's from the
    /// checkpoint).
    pub persistence: Option<[f64; 2]>,
    /// Share of the grid-scale move field (at each cell the mass-weighted mean move around
    /// it) that the projection keeps: the part a divergence-free velocity can make; the rest
    /// gathers or spreads the Gaussians.
    pub flow_share: f64,
    /// Correlation over the cells of the move field's flow part with the frame before's,
    /// and the same for the rest (the gathering part): which of the two the refinement
    /// asks for again. `None` at the first frame the trainer refines (after a start or a
    /// resume); unlike `persistence`, kept when the number of Gaussians changed.
    pub field_persistence: Option<[f64; 2]>,
}

/// The refinement's moves as a field on the velocity grid and how to project it, for
/// [`RefineMoves::flow_share`].
pub(super) struct MoveField<'a> {
    /// At each cell the mass-weighted mean move around it, world units, `[nx, ny, nz, 3]`.
    pub(super) field: Tensor<4>,
    pub(super) grid: &'a GridSpec,
    pub(super) projection: ProjectionOptions,
}

impl MoveField<'_> {
    /// `values`, this field read back, and the part the exact projection keeps, both in
    /// cells (projected in world units: the divergence is the world's).
    pub(super) fn split(&self, values: Vec<f32>) -> RefineMoveField {
        let mut flow = values.clone();
        project_direct(self.grid, &mut flow, &self.projection);
        let in_cells = |values| per_axis(values, self.grid, |x, cell| x / cell);
        RefineMoveField {
            moves: in_cells(values),
            flow: in_cells(flow),
        }
    }
}

/// `values` (rows of 3, one per cell) with `f(value, cell size along its axis)` applied to
/// each: world lengths to cells and back.
fn per_axis(mut values: Vec<f32>, grid: &GridSpec, f: impl Fn(f32, f32) -> f32) -> Vec<f32> {
    let cell = grid.cell_size().to_array();
    values
        .chunks_exact_mut(3)
        .for_each(|u| u.iter_mut().zip(cell).for_each(|(x, c)| *x = f(*x, c)));
    values
}

/// `1 / cell size` per axis, `[3]`: world lengths to cell lengths.
fn cells_per_world_unit(grid: &GridSpec, device: &Device) -> Tensor<1> {
    let cell = grid.cell_size();
    Tensor::<1>::from_data(
        TensorData::new(vec![1.0 / cell.x, 1.0 / cell.y, 1.0 / cell.z], [3]),
        device,
    )
}

/// 1 for each of `n` rows listed in `rows`, 0 for the others.
fn marked_rows(n: usize, rows: &[usize]) -> Vec<f32> {
    let mut marked = vec![0.0; n];
    for &i in rows {
        marked[i] = 1.0;
    }
    marked
}

/// One frame's refinement moves (in cells), their grid-scale parts and their field, kept for
/// the next frame's [`RefineMoves::persistence`] and [`RefineMoves::field_persistence`].
#[derive(Debug, Clone)]
pub(super) struct FrameMoves {
    pub(super) moves: Tensor<2>,
    pub(super) grid_part: Tensor<2>,
    pub(super) field: RefineMoveField,
}

/// The names of [`FrameMoves`]' arrays in a checkpoint's extras.
const SAVED: [&str; 4] = [
    "refine_moves",
    "refine_moves_grid_part",
    "refine_move_field",
    "refine_move_field_flow",
];

impl FrameMoves {
    /// As host arrays, for a checkpoint (one read).
    pub(super) fn to_arrays(&self) -> HostArrays {
        let [n, _] = self.moves.dims();
        let both = read_floats(Tensor::cat(
            vec![self.moves.clone(), self.grid_part.clone()],
            0,
        ));
        let (moves, grid_part) = both.split_at(3 * n);
        let field = |values: &Vec<f32>| (vec![values.len()], values.clone());
        HostArrays::from([
            (SAVED[0].into(), (vec![n, 3], moves.to_vec())),
            (SAVED[1].into(), (vec![n, 3], grid_part.to_vec())),
            (SAVED[2].into(), field(&self.field.moves)),
            (SAVED[3].into(), field(&self.field.flow)),
        ])
    }

    /// What [`Self::to_arrays`] wrote, `None` when `arrays` holds none of it.
    pub(super) fn from_arrays(arrays: &HostArrays, device: &Device) -> Option<Self> {
        let [moves, grid_part, field, flow] = SAVED.map(|name| arrays.get(name));
        let tensor = |(shape, values): &(Vec<usize>, Vec<f32>)| {
            Tensor::<2>::from_data(TensorData::new(values.clone(), [shape[0], 3]), device)
        };
        Some(Self {
            moves: tensor(moves?),
            grid_part: tensor(grid_part?),
            field: RefineMoveField {
                moves: field?.1.clone(),
                flow: flow?.1.clone(),
            },
        })
    }
}

/// [`RefineMoves`] of `moves` (`[n, 3]`, in cells), against the frame before's where there
/// is one, leaving out the rows `jumped` marks (`[n]`, 1 for a row that jumped), in one read.
/// `field` is the same moves' grid-scale field in world units (its grid part is sampled
/// from it), read with the rest and projected on the host (a device solve would read its
/// residuals). Returns the frame's moves too, for the next frame.
pub(super) fn refine_moves(
    scale: &GridScale,
    moves: Tensor<2>,
    before: Option<&FrameMoves>,
    jumped: &Tensor<1>,
    field: &MoveField,
) -> (RefineMoves, FrameMoves) {
    let [n, _] = moves.dims();
    let field_before = before.map(|b| &b.field);
    // A stride coprime to n shuffles the rows deterministically.
    let stride = [7919usize, 7927, 7933, 7937]
        .into_iter()
        .find(|p| n % p != 0)
        .unwrap_or(1);
    let order: Vec<i64> = (0..n).map(|i| ((i * stride) % n.max(1)) as i64).collect();
    let order = Tensor::<1, Int>::from_data(TensorData::new(order, [n]), &moves.device());
    let shuffled = moves.clone().select(0, order);
    let per_cell = cells_per_world_unit(field.grid, &moves.device()).reshape([1, 3]);
    let cells = field.grid.num_cells();
    let grid_part = scale.sampled(field.field.clone().reshape([cells, 3]) * per_cell);
    let mut parts = vec![
        scale.mean_square(moves.clone()),
        scale.mean_square(grid_part.clone()),
        scale.mean_square(shuffled.clone()),
        scale.mean_square(scale.grid_part(shuffled)),
    ];
    let before = before.filter(|b| b.moves.dims() == [n, 3]);
    if let Some(before) = before {
        // Weighted dot products from mean squares: a.b = (|a + b|^2 - |a - b|^2) / 4.
        let kept = (jumped.clone().neg() + 1.0).reshape([n, 1]);
        for (now, then) in [
            (moves.clone(), before.moves.clone()),
            (grid_part.clone(), before.grid_part.clone()),
        ] {
            let (now, then) = (now * kept.clone(), then * kept.clone());
            parts.extend([
                scale.mean_square(now.clone() + then.clone()),
                scale.mean_square(now.clone() - then.clone()),
                scale.mean_square(now),
                scale.mean_square(then),
            ]);
        }
    }
    let scalars = parts.len();
    let field_len = field.field.shape().num_elements();
    parts.push(field.field.clone().reshape([field_len]));
    let mut v = read_floats(Tensor::cat(parts, 0));
    let field = field.split(v.split_off(scalars));
    let share = |part: f32, whole: f32| {
        if whole > 0.0 {
            (part / whole) as f64
        } else {
            0.0
        }
    };
    let weighted_correlation = |w: &[f32]| {
        let norms = (w[2] as f64 * w[3] as f64).sqrt();
        if norms > 0.0 {
            (w[0] as f64 - w[1] as f64) / 4.0 / norms
        } else {
            0.0
        }
    };
    let persistence = (scalars == 12).then(|| {
        [
            weighted_correlation(&v[4..8]),
            weighted_correlation(&v[8..12]),
        ]
    });
    (
        RefineMoves {
            rms_cells: (v[0] as f64).sqrt(),
            grid_share: share(v[1], v[0]),
            shuffled_grid_share: share(v[3], v[2]),
            persistence,
            flow_share: field.flow_share(),
            field_persistence: field_before.map(|b| field.persistence(b)),
        },
        FrameMoves {
            moves,
            grid_part,
            field,
        },
    )
}

impl Trainer {
    /// The refinement's moves since `anchor`, measured against the frame before's (the rows
    /// in `jumped_rows`, recycled or split this frame, left out of the persistence); the
    /// frame's moves are kept for the next frame's.
    pub(super) fn measure_moves(
        &mut self,
        scale: &GridScale,
        anchor: Tensor<2>,
        jumped_rows: &[usize],
    ) -> (RefineMoves, RefineMoveField) {
        let moves = self.state.gaussians.means.val().detach() - anchor;
        let [nx, ny, nz] = self.grid.resolution();
        let field = MoveField {
            field: scale.cell_means(moves.clone()).reshape([nx, ny, nz, 3]),
            grid: &self.grid,
            projection: self.projection(),
        };
        let moves = moves * cells_per_world_unit(&self.grid, &self.device).reshape([1, 3]);
        let [n, _] = moves.dims();
        let jumped = marked_rows(n, jumped_rows);
        let jumped = Tensor::<1>::from_data(TensorData::new(jumped, [n]), &self.device);
        let (report, frame_moves) =
            refine_moves(scale, moves, self.last_moves.as_ref(), &jumped, &field);
        let field = frame_moves.field.clone();
        self.last_moves = Some(frame_moves);
        (report, field)
    }
}
