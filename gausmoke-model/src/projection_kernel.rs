//! The exact projection `Pi` ([`crate::projection`]) on the device, for the cube backends.
//!
//! The same Jacobi-preconditioned conjugate gradients on `D D^T p = D u` as the host solver,
//! with the same discrete operators, but in f32 and without leaving the GPU: the velocity grid
//! is never read back. Every CG scalar (`r.z`, `d.A d`, `|r|^2`) lives in a device buffer, one
//! slot per iteration, so the step sizes are computed by the kernels themselves; the host
//! reads that small buffer only every [`CHECK_EVERY`] iterations to test convergence.
//!
//! Dot products are summed in two fixed-order stages (per-cube shared-memory trees, then one
//! cube over the partial sums), so a solve is deterministic, unlike an atomic sum.
//!
//! One iteration `k` is seven launches over the cells:
//! `D^T d`, `A d = D (D^T d)`, `d.A d`, the step (`p += a d`, `r -= a A d`, `z = M^-1 r`),
//! `|r|^2`, `r.z`, and the new direction `d = z + b d`.

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use burn::tensor::DType;
use burn_cubecl::ops::numeric::{empty_device_contiguous_dtype, zeros_client};
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;
use gausmoke_render::kernels::{buffer, contiguous_f32};

use crate::projection::{ProjectionOptions, ProjectionReport};
use crate::projection_op::ProjectionSpec;

/// Units per cube of every kernel here (one unit per cell).
pub const CELL_BLOCK: usize = 256;

/// Iterations between two convergence tests (each one is a device-to-host read).
pub const CHECK_EVERY: usize = 10;

/// Slots of the CG scalar buffer: `|b|^2` and `|u|^2` first, then three per iteration.
struct Slot;

impl Slot {
    const RHS_NORM_SQUARED: usize = 0;
    const VELOCITY_NORM_SQUARED: usize = 1;

    /// `r_k . z_k` (slot of iteration `k`; iteration `k + 1` finds its own in `rz(k + 1)`).
    fn rz(k: usize) -> usize {
        2 + 3 * k
    }

    /// `d_k . A d_k`.
    fn curvature(k: usize) -> usize {
        3 + 3 * k
    }

    /// `|r_{k+1}|^2`, after the step of iteration `k`.
    fn residual_squared(k: usize) -> usize {
        4 + 3 * k
    }

    /// `|r_k|^2`, before the step of iteration `k` (`|b|^2` for the first).
    fn residual_before(k: usize) -> usize {
        match k {
            0 => Self::RHS_NORM_SQUARED,
            k => Self::residual_squared(k - 1),
        }
    }

    fn count(max_iterations: usize) -> usize {
        Self::rz(max_iterations + 1)
    }
}

/// Coordinate of flat cell `cell` along `axis` (x slowest, as [`crate::grid`]).
#[cube]
fn axis_coordinate(cell: u32, axis: u32, ny: u32, nz: u32) -> u32 {
    let mut coordinate = cell % nz;
    if axis == 0 {
        coordinate = cell / (ny * nz);
    } else if axis == 1 {
        coordinate = (cell / nz) % ny;
    }
    coordinate
}

/// Flat-index step to the next cell along `axis`.
#[cube]
fn axis_stride(axis: u32, ny: u32, nz: u32) -> u32 {
    let mut stride = 1u32;
    if axis == 0 {
        stride = ny * nz;
    } else if axis == 1 {
        stride = nz;
    }
    stride
}

/// Number of cells along `axis`.
#[cube]
fn axis_cells(axis: u32, nx: u32, ny: u32, nz: u32) -> u32 {
    let mut cells = nz;
    if axis == 0 {
        cells = nx;
    } else if axis == 1 {
        cells = ny;
    }
    cells
}

/// Jacobi preconditioner `1 / (D D^T)_cc` of one cell (as `Divergence::normal_diagonal`).
#[cube]
fn inverse_diagonal(cell: u32, inverse_cell: &[f32], nx: u32, ny: u32, nz: u32) -> f32 {
    let mut diagonal = 0.0f32;
    let mut axis = 0u32;
    while axis < 3 {
        let i = axis_coordinate(cell, axis, ny, nz);
        let n = axis_cells(axis, nx, ny, nz);
        let mut interior = 0.0f32;
        if i + 1 < n {
            interior += 1.0;
        }
        if i > 0 {
            interior += 1.0;
        }
        let mut own = 0.0f32;
        if interior == 1.0 {
            own = 0.25;
        }
        let h_inv = inverse_cell[axis as usize];
        diagonal += (0.25 * interior + own) * h_inv * h_inv;
        axis += 1;
    }
    1.0 / diagonal.max(1e-30)
}

/// `(D u)_c`: face velocity = mean of its two cells, zero on the walls, over the cell size.
#[cube(launch)]
pub fn divergence_kernel(
    velocity: &[f32],
    divergence: &mut [f32],
    inverse_cell: &[f32],
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    if cell >= nx * ny * nz {
        terminate!();
    }
    let mut total = 0.0f32;
    let mut axis = 0u32;
    while axis < 3 {
        let i = axis_coordinate(cell, axis, ny, nz);
        let n = axis_cells(axis, nx, ny, nz);
        let stride = axis_stride(axis, ny, nz);
        let own = velocity[(3 * cell + axis) as usize];
        let mut flux = 0.0f32;
        if i + 1 < n {
            flux += 0.5 * (own + velocity[(3 * (cell + stride) + axis) as usize]);
        }
        if i > 0 {
            flux -= 0.5 * (own + velocity[(3 * (cell - stride) + axis) as usize]);
        }
        total += flux * inverse_cell[axis as usize];
        axis += 1;
    }
    divergence[cell as usize] = total;
}

/// `(D^T p)_c`, three components per cell (`-D^T` is the discrete gradient).
#[cube(launch)]
pub fn divergence_transpose_kernel(
    pressure: &[f32],
    output: &mut [f32],
    inverse_cell: &[f32],
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    if cell >= nx * ny * nz {
        terminate!();
    }
    let own = pressure[cell as usize];
    let mut axis = 0u32;
    while axis < 3 {
        let i = axis_coordinate(cell, axis, ny, nz);
        let n = axis_cells(axis, nx, ny, nz);
        let stride = axis_stride(axis, ny, nz);
        let mut value = 0.0f32;
        if i + 1 < n {
            value += 0.5 * (own - pressure[(cell + stride) as usize]);
        }
        if i > 0 {
            value -= 0.5 * (own - pressure[(cell - stride) as usize]);
        }
        output[(3 * cell + axis) as usize] = value * inverse_cell[axis as usize];
        axis += 1;
    }
}

/// Tree sum of one value per unit into `sums[0]` (every unit must call it: it synchronises
/// the cube; `CUBE_DIM` is a power of two).
#[cube]
fn sum_over_cube(sums: &mut Shared<[f32]>) {
    sync_cube();
    let mut stride = CUBE_DIM / 2;
    while stride > 0 {
        if UNIT_POS < stride {
            let other = sums[(UNIT_POS + stride) as usize];
            sums[UNIT_POS as usize] += other;
        }
        sync_cube();
        stride /= 2;
    }
}

/// Per-cube sums of `a * b` over `len` entries into `partials[CUBE_POS]`.
#[cube(launch)]
pub fn dot_partials_kernel(a: &[f32], b: &[f32], partials: &mut [f32], len: u32) {
    let mut sums = Shared::<[f32]>::new_slice(CELL_BLOCK);
    let index = ABSOLUTE_POS as u32;
    let mut product = 0.0f32;
    if index < len {
        product = a[index as usize] * b[index as usize];
    }
    sums[UNIT_POS as usize] = product;
    sum_over_cube(&mut sums);
    if UNIT_POS == 0 {
        partials[CUBE_POS] = sums[0];
    }
}

/// Sums `count` partial sums in a fixed order (one cube) into `scalars[slot]`.
#[cube(launch)]
pub fn finish_sum_kernel(partials: &[f32], scalars: &mut [f32], count: u32, slot: u32) {
    let mut sums = Shared::<[f32]>::new_slice(CELL_BLOCK);
    let mut total = 0.0f32;
    let mut index = UNIT_POS;
    while index < count {
        total += partials[index as usize];
        index += CUBE_DIM;
    }
    sums[UNIT_POS as usize] = total;
    sum_over_cube(&mut sums);
    if UNIT_POS == 0 {
        scalars[slot as usize] = sums[0];
    }
}

/// Start of CG from `p = 0`: `z = M^-1 r` and `d = z`.
#[cube(launch)]
pub fn precondition_kernel(
    residual: &[f32],
    preconditioned: &mut [f32],
    direction: &mut [f32],
    inverse_cell: &[f32],
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    if cell >= nx * ny * nz {
        terminate!();
    }
    let z = residual[cell as usize] * inverse_diagonal(cell, inverse_cell, nx, ny, nz);
    preconditioned[cell as usize] = z;
    direction[cell as usize] = z;
}

/// Whether a residual `|r|^2` meets the stopping rule: under `tolerance^2 |b|^2` (the
/// requested relative residual) or `floor^2 |u|^2` (what f32 can resolve; see
/// [`F32_RESOLVABLE`]). The host's [`converged`] applies the same rule in the same arithmetic.
#[cube]
fn has_converged(
    residual_squared: f32,
    scalars: &[f32],
    tolerance_squared: f32,
    floor_squared: f32,
) -> bool {
    let relative = tolerance_squared * scalars[0];
    let absolute = floor_squared * scalars[1];
    residual_squared <= relative.max(absolute)
}

/// Step of iteration `k`: `a = (r.z) / (d.A d)` read from the scalar buffer, then
/// `p += a d`, `r -= a A d`, `z = M^-1 r`.
///
/// No step is taken once the solve has converged (`|r_k|^2` at `residual_slot` under
/// `tolerance^2 |b|^2` or `floor^2 |u|^2`, see [`has_converged`]): the iterations the host launches
/// before its next convergence test are then no-ops, and the result is the first converged
/// iterate. Nor when the curvature is not positive and finite (the direction lies in the
/// operator's null space).
#[cube(launch)]
#[allow(clippy::too_many_arguments)]
pub fn step_kernel(
    pressure: &mut [f32],
    residual: &mut [f32],
    preconditioned: &mut [f32],
    direction: &[f32],
    operator_direction: &[f32],
    scalars: &[f32],
    inverse_cell: &[f32],
    residual_slot: u32,
    rz_slot: u32,
    curvature_slot: u32,
    tolerance_squared: f32,
    floor_squared: f32,
    nx: u32,
    ny: u32,
    nz: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    if cell >= nx * ny * nz {
        terminate!();
    }
    let converged = has_converged(
        scalars[residual_slot as usize],
        scalars,
        tolerance_squared,
        floor_squared,
    );
    let curvature = scalars[curvature_slot as usize];
    let mut step = 0.0f32;
    if !converged && curvature > 0.0 && curvature < f32::MAX {
        step = scalars[rz_slot as usize] / curvature;
    }
    let c = cell as usize;
    pressure[c] += step * direction[c];
    let r = residual[c] - step * operator_direction[c];
    residual[c] = r;
    preconditioned[c] = r * inverse_diagonal(cell, inverse_cell, nx, ny, nz);
}

/// New direction of iteration `k`: `d = z + b d`, `b = (r.z)_{k+1} / (r.z)_k` (zero when the
/// old product is zero).
#[cube(launch)]
pub fn direction_kernel(
    preconditioned: &[f32],
    direction: &mut [f32],
    scalars: &[f32],
    rz_slot: u32,
    next_rz_slot: u32,
    cells: u32,
) {
    let cell = ABSOLUTE_POS as u32;
    if cell >= cells {
        terminate!();
    }
    let previous = scalars[rz_slot as usize];
    let mut beta = 0.0f32;
    if previous != 0.0 {
        beta = scalars[next_rz_slot as usize] / previous;
    }
    let c = cell as usize;
    direction[c] = preconditioned[c] + beta * direction[c];
}

/// `u - D^T p`, the projected velocity.
#[cube(launch)]
pub fn subtract_kernel(velocity: &[f32], gradient: &[f32], output: &mut [f32], len: u32) {
    let index = ABSOLUTE_POS as u32;
    if index >= len {
        terminate!();
    }
    output[index as usize] = velocity[index as usize] - gradient[index as usize];
}

/// Device buffers and launch shapes of one solve.
struct Solver {
    /// Any tensor on the solve's device (for its client and device).
    like: CubeTensor,
    inverse_cell: CubeTensor,
    dims: [u32; 3],
    cells: usize,
}

impl Solver {
    fn cubes(&self, len: usize) -> CubeCount {
        CubeCount::Static(len.div_ceil(CELL_BLOCK) as u32, 1, 1)
    }

    fn block() -> CubeDim {
        CubeDim::new_1d(CELL_BLOCK as u32)
    }

    fn new_buffer(&self, len: usize, zeroed: bool) -> CubeTensor {
        let like = &self.like;
        if zeroed {
            zeros_client(
                like.client.clone(),
                like.device.clone(),
                [len.max(1)].into(),
                DType::F32,
            )
        } else {
            empty_device_contiguous_dtype(
                like.client.clone(),
                like.device.clone(),
                [len.max(1)].into(),
                DType::F32,
            )
        }
    }

    fn divergence(&self, velocity: &CubeTensor, output: &CubeTensor) {
        let [nx, ny, nz] = self.dims;
        divergence_kernel::launch(
            &self.like.client,
            self.cubes(self.cells),
            Self::block(),
            buffer(velocity),
            buffer(output),
            buffer(&self.inverse_cell),
            nx,
            ny,
            nz,
        );
    }

    fn divergence_transpose(&self, pressure: &CubeTensor, output: &CubeTensor) {
        let [nx, ny, nz] = self.dims;
        divergence_transpose_kernel::launch(
            &self.like.client,
            self.cubes(self.cells),
            Self::block(),
            buffer(pressure),
            buffer(output),
            buffer(&self.inverse_cell),
            nx,
            ny,
            nz,
        );
    }

    /// `scalars[slot] = a . b` over the cells (`a`, `b` one value per cell).
    fn dot(
        &self,
        a: &CubeTensor,
        b: &CubeTensor,
        partials: &CubeTensor,
        scalars: &CubeTensor,
        slot: usize,
    ) {
        self.dot_over(self.cells, a, b, partials, scalars, slot);
    }

    /// `scalars[slot] = a . b` over the first `len` entries (`partials` holds
    /// `len / CELL_BLOCK` values, rounded up).
    fn dot_over(
        &self,
        len: usize,
        a: &CubeTensor,
        b: &CubeTensor,
        partials: &CubeTensor,
        scalars: &CubeTensor,
        slot: usize,
    ) {
        let client = &self.like.client;
        let count = len.div_ceil(CELL_BLOCK);
        dot_partials_kernel::launch(
            client,
            self.cubes(len),
            Self::block(),
            buffer(a),
            buffer(b),
            buffer(partials),
            len as u32,
        );
        finish_sum_kernel::launch(
            client,
            CubeCount::Static(1, 1, 1),
            Self::block(),
            buffer(partials),
            buffer(scalars),
            count as u32,
            slot as u32,
        );
    }
}

/// Reads the CG scalar buffer back (the only device-to-host traffic of a solve).
fn read_scalars(scalars: &CubeTensor) -> Vec<f32> {
    let bytes = scalars
        .client
        .read_one(scalars.handle.clone())
        .expect("reading the projection solver's scalars back from the GPU failed (device lost?)");
    f32::from_bytes(&bytes).to_vec()
}

/// `Pi(u)` for `velocity [nx, ny, nz, 3]` on the device; the report of what the solve reached
/// (its residual is the CG recurrence's, in f32).
pub fn project_velocity(
    velocity: CubeTensor,
    spec: &ProjectionSpec,
) -> (CubeTensor, ProjectionReport) {
    let velocity = contiguous_f32(velocity, "velocity grid");
    let cells: usize = spec.resolution.iter().product();
    assert_eq!(
        velocity.meta.num_elements(),
        3 * cells,
        "velocity must be [nx, ny, nz, 3] on the grid {:?}",
        spec.resolution
    );
    let shape = velocity.meta.shape().clone();
    let ProjectionOptions {
        rel_tolerance,
        max_iterations,
    } = spec.options;
    let inverse_cell = {
        use burn::backend::ops::FloatTensorOps;
        let values: Vec<f32> = spec.cell.iter().map(|h| (1.0 / h) as f32).collect();
        burn_cubecl::CubeBackend::float_from_data(
            burn::tensor::TensorData::new(values, [3]),
            &velocity.device,
        )
    };
    let dims = spec.resolution.map(|n| {
        u32::try_from(n).expect("grid resolution checked by GridSpec (under 8 GiB per tensor)")
    });
    let solver = Solver {
        like: velocity.clone(),
        inverse_cell,
        dims,
        cells,
    };
    let [nx, ny, nz] = dims;
    let client = velocity.client.clone();

    let residual = solver.new_buffer(cells, false);
    solver.divergence(&velocity, &residual);
    let partials = solver.new_buffer((3 * cells).div_ceil(CELL_BLOCK), false);
    let scalars = solver.new_buffer(Slot::count(max_iterations), true);
    solver.dot_over(
        3 * cells,
        &velocity,
        &velocity,
        &partials,
        &scalars,
        Slot::VELOCITY_NORM_SQUARED,
    );
    solver.dot(
        &residual,
        &residual,
        &partials,
        &scalars,
        Slot::RHS_NORM_SQUARED,
    );
    let pressure = solver.new_buffer(cells, true);
    let preconditioned = solver.new_buffer(cells, false);
    let direction = solver.new_buffer(cells, false);
    let gradient = solver.new_buffer(3 * cells, false);
    let operator_direction = solver.new_buffer(cells, false);
    precondition_kernel::launch(
        &client,
        solver.cubes(cells),
        Solver::block(),
        buffer(&residual),
        buffer(&preconditioned),
        buffer(&direction),
        buffer(&solver.inverse_cell),
        nx,
        ny,
        nz,
    );
    solver.dot(&residual, &preconditioned, &partials, &scalars, Slot::rz(0));

    // What f32 can resolve: `D u` carries round-off of about `eps |D| |u|` (`|D|^2 <= sum_a
    // h_a^-2`, see `penalty`), so residuals below a few times that are noise. Without this floor
    // an already projected field (the trainer's case whenever Phi's update is small) makes CG
    // chase round-off into the operator's near-null space and return garbage.
    let stopping = StoppingRule::new(rel_tolerance, spec.cell);
    let mut report = ProjectionReport::default();
    let mut iteration = 0;
    while iteration < max_iterations {
        let k = iteration;
        solver.divergence_transpose(&direction, &gradient);
        solver.divergence(&gradient, &operator_direction);
        solver.dot(
            &direction,
            &operator_direction,
            &partials,
            &scalars,
            Slot::curvature(k),
        );
        step_kernel::launch(
            &client,
            solver.cubes(cells),
            Solver::block(),
            buffer(&pressure),
            buffer(&residual),
            buffer(&preconditioned),
            buffer(&direction),
            buffer(&operator_direction),
            buffer(&scalars),
            buffer(&solver.inverse_cell),
            Slot::residual_before(k) as u32,
            Slot::rz(k) as u32,
            Slot::curvature(k) as u32,
            stopping.tolerance_squared,
            stopping.floor_squared,
            nx,
            ny,
            nz,
        );
        solver.dot(
            &residual,
            &residual,
            &partials,
            &scalars,
            Slot::residual_squared(k),
        );
        solver.dot(
            &residual,
            &preconditioned,
            &partials,
            &scalars,
            Slot::rz(k + 1),
        );
        direction_kernel::launch(
            &client,
            solver.cubes(cells),
            Solver::block(),
            buffer(&preconditioned),
            buffer(&direction),
            buffer(&scalars),
            Slot::rz(k) as u32,
            Slot::rz(k + 1) as u32,
            cells as u32,
        );
        iteration += 1;
        if iteration % CHECK_EVERY == 0 || iteration == max_iterations {
            let values = read_scalars(&scalars);
            if let Some(done) = stopping.first_converged(&values, iteration, cells) {
                report = done;
                break;
            }
            report = report_after(&values, iteration, cells);
        }
    }
    if max_iterations == 0 {
        report = report_after(&read_scalars(&scalars), 0, cells);
    }

    solver.divergence_transpose(&pressure, &gradient);
    let output = solver.new_buffer(3 * cells, false);
    subtract_kernel::launch(
        &client,
        solver.cubes(3 * cells),
        Solver::block(),
        buffer(&velocity),
        buffer(&gradient),
        buffer(&output),
        (3 * cells) as u32,
    );
    let output = CubeTensor::new_contiguous(
        output.client,
        output.device,
        shape,
        output.handle,
        DType::F32,
    );
    (output, report)
}

/// Multiple of f32's epsilon under which `|r| / (|D| |u|)` is round-off.
const F32_RESOLVABLE: f64 = 8.0 * f32::EPSILON as f64;

/// The solve's stopping rule, in the f32 form the step kernel tests ([`has_converged`]).
#[derive(Debug, Clone, Copy)]
struct StoppingRule {
    tolerance_squared: f32,
    /// `(F32_RESOLVABLE |D|)^2`, with `|D|^2 <= sum_a h_a^-2`.
    floor_squared: f32,
}

impl StoppingRule {
    fn new(rel_tolerance: f64, cell: [f64; 3]) -> Self {
        let operator_norm_squared: f64 = cell.iter().map(|h| h.powi(-2)).sum();
        Self {
            tolerance_squared: (rel_tolerance * rel_tolerance) as f32,
            floor_squared: (F32_RESOLVABLE * F32_RESOLVABLE * operator_norm_squared) as f32,
        }
    }

    fn met(&self, residual_squared: f32, values: &[f32]) -> bool {
        let relative = self.tolerance_squared * values[Slot::RHS_NORM_SQUARED];
        let absolute = self.floor_squared * values[Slot::VELOCITY_NORM_SQUARED];
        residual_squared <= relative.max(absolute)
    }

    /// The first iteration count up to `done` (0 included) after which the rule held: the
    /// step kernel took no step from there on, so that iterate is the result.
    fn first_converged(
        &self,
        values: &[f32],
        done: usize,
        cells: usize,
    ) -> Option<ProjectionReport> {
        (0..=done)
            .find(|&k| {
                let residual = match k {
                    0 => values[Slot::RHS_NORM_SQUARED],
                    k => values[Slot::residual_squared(k - 1)],
                };
                self.met(residual, values)
            })
            .map(|k| report_after(values, k, cells))
    }
}

/// The report after `iterations` steps. The CG residual is `r = D u - D D^T p = D (Pi u)`,
/// so `|r|` is also the divergence left after the projection (up to f32 recurrence drift).
fn report_after(values: &[f32], iterations: usize, cells: usize) -> ProjectionReport {
    let rhs_squared = values[Slot::RHS_NORM_SQUARED] as f64;
    let residual_squared = match iterations {
        0 => rhs_squared,
        k => values[Slot::residual_squared(k - 1)] as f64,
    };
    let relative_residual = if rhs_squared > 0.0 {
        (residual_squared / rhs_squared).sqrt()
    } else {
        0.0
    };
    ProjectionReport {
        iterations,
        relative_residual,
        divergence_rms_before: (rhs_squared / cells as f64).sqrt(),
        divergence_rms_after: (residual_squared / cells as f64).sqrt(),
    }
}
