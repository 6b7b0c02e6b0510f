//! The data set's obstacles: solid cells for the projection, and smoke kept out of them.

use burn::tensor::{Tensor, TensorData};
use gausmoke_core::glam::Vec3;
use gausmoke_data::Obstacle;
use gausmoke_model::{GridSpec, SolidCells};

use super::Trainer;
use crate::TrainError;
use crate::config::{Obstacles, ProjectionKind, TrainConfig};

impl Trainer {
    /// Moves the Gaussians whose centre lies inside a solid obstacle onto its surface: smoke
    /// has no business there, and the velocity, zero inside, would never carry it out.
    pub(super) fn keep_out_of_obstacles(&mut self) {
        if self.solids.is_none() {
            return;
        }
        let means = self.state.gaussians.means.val().detach();
        let outside = outside_obstacles(means, &self.sequence.obstacles);
        self.state.gaussians = self.state.gaussians.clone().with_means(outside);
    }
}

/// `means` `[N, 3]` with every centre inside one of `obstacles` moved onto its surface (a hair
/// outside; radially for a sphere, through the nearest face for a box), in tensor operations
/// (no read).
pub(super) fn outside_obstacles(means: Tensor<2>, obstacles: &[Obstacle]) -> Tensor<2> {
    let device = means.device();
    let [n, _] = means.dims();
    obstacles
        .iter()
        .fold(means, |means, obstacle| match *obstacle {
            Obstacle::Sphere { centre, radius } => {
                let centre = Tensor::<2>::from_data(
                    TensorData::new(centre.to_array().to_vec(), [1, 3]),
                    &device,
                );
                let offset = means.clone() - centre.clone();
                let squared = offset.clone().powi_scalar(2).sum_dim(1);
                let inside = squared.clone().lower_elem(radius * radius).expand([n, 3]);
                let distance = squared.sqrt().clamp_min(1e-12);
                let surface = centre + offset / distance * (radius * 1.001);
                means.mask_where(inside, surface)
            }
            Obstacle::Box { min, max } => {
                let row = |v: Vec3| {
                    Tensor::<2>::from_data(TensorData::new(v.to_array().to_vec(), [1, 3]), &device)
                        .expand([n, 3])
                };
                let offset = means.clone() - row(0.5 * (min + max));
                // Per axis, how far outside the nearer face (negative inside).
                let q = offset.clone().abs() - row(0.5 * (max - min));
                let deepest = q.clone().max_dim(1);
                let inside = deepest.clone().lower_elem(0.0).expand([n, 3]);
                // Out through the nearest face, a hair beyond it.
                let nearest = q.clone().equal(deepest.expand([n, 3])).float();
                let hair = 5e-4 * (max - min).max_element();
                let surface = means.clone() + nearest * offset.sign() * (q.neg() + hair);
                means.mask_where(inside, surface)
            }
        })
}

/// The data set's obstacles as solid cells of `grid` (cell centre inside), when there are any
/// and `config.projection.obstacles` makes them solid; refused with the penalty form of `Pi`, which has no
/// notion of them, and when they cover no cell (a sphere smaller than the grid can see).
pub(crate) fn solid_cells(
    obstacles: &[Obstacle],
    config: &TrainConfig,
    grid: &GridSpec,
) -> Result<Option<SolidCells>, TrainError> {
    if obstacles.is_empty() || config.projection.obstacles == Obstacles::Ignore {
        return Ok(None);
    }
    let refuse = |reason: String| TrainError::Config {
        origin: "projection.obstacles".into(),
        reason,
    };
    if config.projection.kind != ProjectionKind::Exact {
        return Err(refuse(format!(
            "the data set describes {} obstacle(s), which only projection.kind = \"exact\" \
             keeps the flow out of: use it, or set projection.obstacles = \"ignore\"",
            obstacles.len()
        )));
    }
    let flags = grid.cells_where(|p| obstacles.iter().any(|o| o.contains(p)));
    let solids = SolidCells::new(grid.resolution(), flags).expect("one flag per cell");
    if solids.count() == 0 {
        return Err(refuse(format!(
            "the data set's obstacles cover no cell centre of the {:?} grid: refine \
             grid_resolution, or set projection.obstacles = \"ignore\"",
            grid.resolution()
        )));
    }
    tracing::info!(
        cells = solids.count(),
        of = grid.num_cells(),
        "obstacle cells are solid in the projection"
    );
    Ok(Some(solids))
}
