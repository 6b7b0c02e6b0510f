//! The grid-scale part of a move of the Gaussians' centres (ours, for the refinement's tie).
//!
//! The refinement (Sec. 4.4) moves each centre away from where the velocity carried it. A
//! move the velocity grid could have made is smooth at the grid's scale: the Gaussians
//! around a cell move together. What is left is sub-grid: each Gaussian on its own, the
//! detail the paper meant the refinement for, and also the freedom that fits a few views
//! pixel by pixel. [`GridScale`] splits a move in two: its mass-weighted mean at each cell
//! centre, sampled back trilinearly (the grid part), and the rest (the sub-grid part).
//!
//! The weights come from the centres the moves start from and stay fixed while the moves
//! are fitted, so the split is linear in the move and differentiable through two indexing
//! ops (scatter-add to the cells, gather back). Everything stays on the device, but on the
//! cube backends burn's scatter-add along rows runs one thread per channel over all `8 n`
//! rows: cheap for the per-frame statistics, a serial cost per refinement step for the
//! ties (unmeasured on a GPU; a segmented sum over rows sorted by cell would remove it).

use burn::tensor::activation::softplus;
use burn::tensor::{IndexingUpdateOp, Int, Tensor, TensorData};
use gausmoke_render::GaussianTensors;

use crate::grid::GridSpec;

/// Corners of a trilinear stencil.
const CORNERS: usize = 8;

/// The split of a move of `n` Gaussians into a grid-scale and a sub-grid part.
#[derive(Debug, Clone)]
pub struct GridScale {
    /// Cell row of each Gaussian's eight stencil corners, `[8 n]`, Gaussian-major.
    corners: Tensor<1, Int>,
    /// Trilinear weight of each corner, `[8 n, 1]`.
    trilinear: Tensor<2>,
    /// Trilinear weight times the Gaussian's mass, `[8 n, 1]`.
    massed: Tensor<2>,
    /// One over each cell's summed `massed` weight (0 where nothing reaches it), `[cells, 1]`.
    inverse_cell_mass: Tensor<2>,
    /// The Gaussians' masses over their total, `[n, 1]`: the weights of [`Self::mean_square`].
    mass_share: Tensor<2>,
    points: usize,
    cells: usize,
}

impl GridScale {
    /// The split for Gaussians at `centres` (`[n, 3]`, world units; outside the box they use
    /// the nearest cells) with `masses` (`[n]`, any non-negative scale). Built on the
    /// tensors' device: nothing is read back.
    pub fn new(grid: &GridSpec, centres: Tensor<2>, masses: Tensor<1>) -> Self {
        let [n, _] = centres.dims();
        assert_eq!(masses.dims(), [n], "one mass per centre");
        let device = centres.device();
        let resolution = grid.resolution();
        let (lo, cell) = (grid.lo().to_array(), grid.cell_size().to_array());
        let mut rows = Tensor::<2, Int>::zeros([n, CORNERS], &device);
        let mut trilinear = Tensor::<2>::ones([n, CORNERS], &device);
        for axis in 0..3 {
            let size = resolution[axis];
            // Whether each corner takes the upper cell along this axis (x slowest).
            let upper: Vec<f32> = (0..CORNERS)
                .map(|corner| ((corner >> (2 - axis)) & 1) as f32)
                .collect();
            let upper = Tensor::<2>::from_data(TensorData::new(upper, [1, CORNERS]), &device);
            // Lower cell and fraction between the two cell centres, clamped to the box.
            let u = (centres.clone().slice([0..n, axis..axis + 1]) - lo[axis]) / cell[axis] - 0.5;
            let low = u.clone().floor().clamp(0.0, size.saturating_sub(2) as f32);
            let fraction = (u - low.clone()).clamp(0.0, 1.0);
            let index = (low + upper.clone()).clamp_max((size - 1) as f32).int();
            let weight =
                upper.clone() * fraction.clone() + (upper.neg() + 1.0) * (fraction.neg() + 1.0);
            rows = rows * (size as i64) + index;
            trilinear = trilinear * weight;
        }
        let massed = (trilinear.clone() * masses.clone().reshape([n, 1])).reshape([CORNERS * n, 1]);
        let corners = rows.reshape([CORNERS * n]);
        let cells = grid.num_cells();
        let cell_mass = Tensor::<2>::zeros([cells, 1], &device).select_assign(
            0,
            corners.clone(),
            massed.clone(),
            IndexingUpdateOp::Add,
        );
        let reached = cell_mass.clone().greater_elem(0.0).float();
        let inverse_cell_mass = reached / cell_mass.clamp_min(f32::MIN_POSITIVE);
        let mass_share =
            (masses.clone() / masses.sum().clamp_min(f32::MIN_POSITIVE)).reshape([n, 1]);
        // Constants of the split: none may hold a node of an autodiff graph, which one
        // backward pass would consume for every later one.
        Self {
            corners,
            trilinear: trilinear.reshape([CORNERS * n, 1]).detach(),
            massed: massed.detach(),
            inverse_cell_mass: inverse_cell_mass.detach(),
            mass_share: mass_share.detach(),
            points: n,
            cells,
        }
    }

    /// The split for `gaussians` as they are, each weighted by its mass (density times the
    /// product of its standard deviations: what it splats into the grid, up to a constant),
    /// so that invisible Gaussians neither pull on the cells' means nor count in them.
    pub fn of(grid: &GridSpec, gaussians: &GaussianTensors) -> Self {
        let [n, _] = gaussians.means.dims();
        // Detached before any op, so that nothing joins the training's autodiff graph.
        let masses = softplus(gaussians.raw_densities.clone().detach(), 1.0)
            * gaussians
                .log_scales
                .clone()
                .detach()
                .sum_dim(1)
                .exp()
                .reshape([n]);
        Self::new(grid, gaussians.means.clone().detach(), masses)
    }

    /// At each cell centre the mass-weighted mean of the `moves` (`[n, c]`) of the Gaussians
    /// around it (trilinear weights), 0 where none reaches: `[cells, c]`, cells in the grid's
    /// row-major order (x slowest).
    pub fn cell_means(&self, moves: Tensor<2>) -> Tensor<2> {
        let [n, c] = moves.dims();
        assert_eq!(n, self.points, "moves must have one row per Gaussian");
        let per_corner = moves
            .reshape([n, 1, c])
            .expand([n, CORNERS, c])
            .reshape([CORNERS * n, c]);
        let sums = Tensor::<2>::zeros([self.cells, c], &per_corner.device()).select_assign(
            0,
            self.corners.clone(),
            per_corner * self.massed.clone(),
            IndexingUpdateOp::Add,
        );
        sums * self.inverse_cell_mass.clone()
    }

    /// The grid-scale part of `moves` (`[n, c]`): [`Self::cell_means`] sampled back at each
    /// Gaussian.
    pub fn grid_part(&self, moves: Tensor<2>) -> Tensor<2> {
        self.sampled(self.cell_means(moves))
    }

    /// A cell field (`[cells, c]`, as [`Self::cell_means`] gives it) sampled trilinearly at
    /// each Gaussian: `[n, c]`.
    pub fn sampled(&self, field: Tensor<2>) -> Tensor<2> {
        let [cells, c] = field.dims();
        assert_eq!(cells, self.cells, "the field must have one row per cell");
        (field.select(0, self.corners.clone()) * self.trilinear.clone())
            .reshape([self.points, CORNERS, c])
            .sum_dim(1)
            .reshape([self.points, c])
    }

    /// Mass-weighted mean over the Gaussians of the squared length of each row of `x`
    /// (`[n, c]`).
    pub fn mean_square(&self, x: Tensor<2>) -> Tensor<1> {
        (x.powi_scalar(2).sum_dim(1) * self.mass_share.clone()).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;
    use gausmoke_core::glam::Vec3;
    use gausmoke_render::backends::cpu_devices;
    use gausmoke_render::device_traffic::{read_floats, read_scalar};

    fn device() -> Device {
        cpu_devices()[0].1.clone()
    }

    fn scale_of(centres: &[f32], masses: &[f32], device: &Device) -> GridScale {
        let n = masses.len();
        GridScale::new(
            &grid(),
            Tensor::<2>::from_data(TensorData::new(centres.to_vec(), [n, 3]), device),
            Tensor::<1>::from_data(TensorData::new(masses.to_vec(), [n]), device),
        )
    }

    fn grid() -> GridSpec {
        GridSpec::new(Vec3::ZERO, Vec3::ONE, [4, 4, 4], 2).unwrap()
    }

    /// Centres spread over the box, the same lattice for every test.
    fn spread(n: usize) -> Vec<f32> {
        (0..n)
            .flat_map(|i| {
                let f = |k: usize| ((i * k + 3) % 97) as f32 / 97.0;
                [f(7), f(13), f(29)]
            })
            .collect()
    }

    /// Also for centres outside the box, which use the nearest cells.
    #[test]
    fn a_uniform_move_is_all_grid_scale() {
        let device = device();
        let mut centres = spread(58);
        centres.extend([-0.3, 0.5, 1.4, 0.9, 2.0, -1.0]);
        let n = 60;
        let scale = scale_of(&centres, &vec![1.0; n], &device);
        let moves = Tensor::<2>::from_data(
            TensorData::new([0.01f32, -0.02, 0.03].repeat(n), [n, 3]),
            &device,
        );
        let part = read_floats(scale.grid_part(moves.clone()));
        for (got, want) in part.iter().zip(read_floats(moves)) {
            assert!((got - want).abs() < 1e-6, "{got} against {want}");
        }
    }

    /// Two Gaussians share every cell of their stencil (the same centre): their cell means
    /// are the mass-weighted mean of the two moves, and that is what each gets back.
    #[test]
    fn the_grid_part_is_the_mass_weighted_mean_of_neighbours() {
        let device = device();
        let centres = [0.4f32, 0.6, 0.3, 0.4, 0.6, 0.3];
        let scale = scale_of(&centres, &[3.0, 1.0], &device);
        let moves = Tensor::<2>::from_data(
            TensorData::new(vec![1.0f32, 0.0, 0.0, 0.0, 4.0, 0.0], [2, 3]),
            &device,
        );
        let part = read_floats(scale.grid_part(moves));
        let want = [0.75f32, 1.0, 0.0];
        for row in part.chunks(3) {
            for (got, want) in row.iter().zip(want) {
                assert!((got - want).abs() < 1e-6, "{row:?} against {want:?}");
            }
        }
        // Mass shares 3/4 and 1/4 of |(1,0,0)|^2 = 1 and |(0,4,0)|^2 = 16.
        let moves = Tensor::<2>::from_data(
            TensorData::new(vec![1.0f32, 0.0, 0.0, 0.0, 4.0, 0.0], [2, 3]),
            &device,
        );
        let ms = read_scalar(scale.mean_square(moves));
        assert!((ms - (0.75 + 4.0)).abs() < 1e-5, "{ms}");
    }

    /// A move that alternates from Gaussian to Gaussian within the cells is sub-grid: its
    /// grid part is far smaller than the move.
    #[test]
    fn an_alternating_move_is_mostly_sub_grid() {
        let device = device();
        let n = 400;
        let scale = scale_of(&spread(n), &vec![1.0; n], &device);
        let alternating: Vec<f32> = (0..n)
            .flat_map(|i| {
                if i % 2 == 0 {
                    [0.01, 0.0, 0.0]
                } else {
                    [-0.01, 0.0, 0.0]
                }
            })
            .collect();
        let moves = Tensor::<2>::from_data(TensorData::new(alternating, [n, 3]), &device);
        let part = scale.grid_part(moves.clone());
        let share = read_scalar(scale.mean_square(part)) / read_scalar(scale.mean_square(moves));
        assert!(share < 0.05, "grid share {share}");
    }

    /// The split is differentiable: the gradient of the grid part's mean square matches a
    /// central difference in one Gaussian's move.
    #[test]
    fn the_grid_part_has_the_finite_difference_gradient() {
        let device = device().autodiff();
        let n = 30;
        let centres = spread(n);
        let masses: Vec<f32> = (0..n).map(|i| 0.5 + (i % 5) as f32 * 0.3).collect();
        let scale = scale_of(&centres, &masses, &device);
        let raw: Vec<f32> = (0..3 * n)
            .map(|i| ((i * 37 % 11) as f32 - 5.0) * 0.01)
            .collect();
        let moves =
            Tensor::<2>::from_data(TensorData::new(raw.clone(), [n, 3]), &device).require_grad();
        let loss = scale.mean_square(scale.grid_part(moves.clone()));
        let grads = loss.backward();
        let analytic = read_floats(moves.grad(&grads).unwrap());
        let at = |delta: f32, index: usize| {
            let mut shifted = raw.clone();
            shifted[index] += delta;
            let t = Tensor::<2>::from_data(TensorData::new(shifted, [n, 3]), &device);
            read_scalar(scale.mean_square(scale.grid_part(t))) as f64
        };
        for index in [0, 7, 44, 89] {
            let h = 1e-3;
            let numeric = (at(h, index) - at(-h, index)) / (2.0 * h as f64);
            let got = analytic[index] as f64;
            assert!(
                (got - numeric).abs() < 1e-4 + 1e-2 * numeric.abs(),
                "d/d move[{index}]: {got} against {numeric}"
            );
        }
    }

    /// One split serves every step of a refinement: each step's backward pass leaves it
    /// usable for the next (built from tracked Gaussians, as training builds it).
    #[test]
    fn one_split_serves_many_backward_passes() {
        let device = device().autodiff();
        let n = 40;
        let tracked = |values: Vec<f32>, shape: [usize; 2]| {
            Tensor::<2>::from_data(TensorData::new(values, shape), &device).require_grad()
        };
        let gaussians = GaussianTensors {
            means: tracked(spread(n), [n, 3]),
            rotations: tracked([1.0, 0.0, 0.0, 0.0].repeat(n), [n, 4]),
            log_scales: tracked(vec![-3.0; 3 * n], [n, 3]),
            raw_densities: Tensor::<1>::from_data(TensorData::new(vec![0.5; n], [n]), &device)
                .require_grad(),
            colors: tracked(vec![0.5; 3 * n], [n, 3]),
        };
        let scale = GridScale::of(&grid(), &gaussians);
        for step in 0..3 {
            let moves = tracked(vec![0.01 * (step + 1) as f32; 3 * n], [n, 3]);
            let grads = scale.mean_square(scale.grid_part(moves.clone())).backward();
            assert!(moves.grad(&grads).is_some(), "step {step}");
        }
    }
}
