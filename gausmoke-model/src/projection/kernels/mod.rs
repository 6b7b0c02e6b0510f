//! The exact projection `Pi` ([`super`]) on the device, for the cube backends.
//!
//! Without obstacles (and with [`DeviceSolve::Direct`], the default) the Poisson solve is
//! direct, as matrix products ([`direct`]). Otherwise it is the same Jacobi-preconditioned conjugate gradients on `D D^T p = D u` as the host solver,
//! with the same discrete operators, but in f32 and without leaving the GPU: the velocity grid
//! is never read back. Every CG scalar (`r.z`, `d.A d`, `|r|^2`) lives in a device buffer, one
//! slot per iteration, so the step sizes are computed by the kernels themselves, and once the
//! solve has converged the kernels take no step (the iterations after it are no-ops). The
//! host reads that small buffer to test convergence first after as many iterations as the
//! last solve of the same kind on the same grid needed (see `IterationHints`), then every
//! [`CHECK_EVERY`]; or, with [`ConvergenceTests::Deferred`], it launches a budget of
//! iterations from that history without reading, and [`settle_deferred_solves`] judges the
//! solves later, all in one read.
//!
//! Dot products are summed in two fixed-order stages (per-cube shared-memory trees, then one
//! cube over the partial sums), so a solve is deterministic, unlike an atomic sum.
//!
//! One iteration `k` is five launches: `A d = D (D^T d)` (one stencil, `D^T d` not stored)
//! with the per-cube sums of `d.A d`; their total; the step (`p += a d`, `r -= a A d`, `z = M^-1 r`) with the per-cube
//! sums of `|r|^2` and `r.z`; their totals (two cubes); the new direction `d = z + b d`.

// `div_ceil` is not available inside cubecl kernels; the manual form is what they compile.
#![allow(clippy::manual_div_ceil)]

use burn::tensor::DType;
use burn_cubecl::ops::numeric::{empty_device_contiguous_dtype, zeros_client};
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;
use gausmoke_render::kernels::buffers::{buffer, contiguous_f32};

use super::host::{
    ConvergenceTests, DeviceSolve, ProjectionOptions, ProjectionReport, ProjectionSpec,
};
use cg::{
    CELL_BLOCK, direction_kernel, dot_partials_kernel, finish_sums_kernel,
    operator_direction_kernel, step_kernel, subtract_kernel,
};
use operators::{divergence_kernel, divergence_transpose_kernel, precondition_kernel};

mod cg;
mod deferred;
mod direct;
mod operators;

pub use deferred::{CHECK_EVERY, settle_deferred_solves};
use deferred::{IterationHints, PendingSolve, defer};

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

/// Device buffers and launch shapes of one solve.
struct Solver {
    /// Any tensor on the solve's device (for its client and device).
    like: CubeTensor,
    inverse_cell: CubeTensor,
    /// `OpenFaces::face_flows` of the box (6 values).
    face_flow: CubeTensor,
    /// Per cell 1 (fluid) or 0 (obstacle); read only when `has_solids` is 1.
    fluid: CubeTensor,
    has_solids: u32,
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
            buffer(&self.face_flow),
            buffer(&self.fluid),
            self.has_solids,
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
            buffer(&self.face_flow),
            buffer(&self.fluid),
            self.has_solids,
            nx,
            ny,
            nz,
        );
    }

    /// `u - D^T p`, shaped `shape` (the velocity's).
    fn subtract_gradient(
        &self,
        velocity: &CubeTensor,
        pressure: &CubeTensor,
        shape: burn::tensor::Shape,
    ) -> CubeTensor {
        let [nx, ny, nz] = self.dims;
        let gradient = self.new_buffer(3 * self.cells, false);
        self.divergence_transpose(pressure, &gradient);
        let output = self.new_buffer(3 * self.cells, false);
        subtract_kernel::launch(
            &self.like.client,
            self.cubes(3 * self.cells),
            Self::block(),
            buffer(velocity),
            buffer(&gradient),
            buffer(&output),
            buffer(&self.fluid),
            self.has_solids,
            nx,
            ny,
            nz,
        );
        CubeTensor::new_contiguous(
            output.client,
            output.device,
            shape,
            output.handle,
            DType::F32,
        )
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
        self.finish_sums(partials, scalars, count, [slot, slot], 1);
    }

    /// `scalars[slots[i]]` = the sum of `partials[i * count..(i + 1) * count]`, for the first
    /// `sums` of the two.
    fn finish_sums(
        &self,
        partials: &CubeTensor,
        scalars: &CubeTensor,
        count: usize,
        slots: [usize; 2],
        sums: u32,
    ) {
        finish_sums_kernel::launch(
            &self.like.client,
            CubeCount::Static(sums, 1, 1),
            Self::block(),
            buffer(partials),
            buffer(scalars),
            count as u32,
            slots[0] as u32,
            slots[1] as u32,
        );
    }
}

/// Reads the CG scalar buffer back (the only device-to-host traffic of a solve).
fn read_scalars(scalars: &CubeTensor) -> Vec<f32> {
    gausmoke_render::device_traffic::note_read(
        gausmoke_render::device_traffic::ReadKind::SolverConvergence,
    );
    let bytes = scalars
        .client
        .read_one(scalars.handle.clone())
        .expect("reading the projection solver's scalars back from the GPU failed (device lost?)");
    f32::from_bytes(&bytes).to_vec()
}

/// `Pi(u)` for `velocity [nx, ny, nz, 3]` on the device; the report of what the solve reached
/// (its residual is the CG recurrence's, in f32), or `None` for a deferred solve (judged later
/// by [`settle_deferred_solves`]).
pub fn project_velocity(
    velocity: CubeTensor,
    spec: &ProjectionSpec,
) -> (CubeTensor, Option<ProjectionReport>) {
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
        open_faces,
        ref solids,
        convergence_tests,
        device_solve,
    } = spec.options;
    let upload = |values: Vec<f32>| {
        use burn::backend::ops::FloatTensorOps;
        let len = values.len();
        burn_cubecl::CubeBackend::float_from_data(
            burn::tensor::TensorData::new(values, [len]),
            &velocity.device,
        )
    };
    let inverse_cell = upload(spec.cell.iter().map(|h| (1.0 / h) as f32).collect());
    let face_flow = upload(open_faces.face_flows().to_vec());
    let dims = spec.resolution.map(|n| {
        u32::try_from(n).expect("grid resolution checked by GridSpec (under 8 GiB per tensor)")
    });
    // One flag per cell, uploaded with the solve (a write, not a read); a placeholder the
    // kernels never read without obstacles.
    let fluid = upload(match solids {
        Some(solids) => {
            assert_eq!(
                solids.resolution(),
                spec.resolution,
                "obstacle cells must be on the projected grid"
            );
            solids
                .flags()
                .iter()
                .map(|&s| if s { 0.0 } else { 1.0 })
                .collect()
        }
        None => vec![1.0],
    });
    let solver = Solver {
        like: velocity.clone(),
        inverse_cell,
        face_flow,
        fluid,
        has_solids: solids.is_some() as u32,
        dims,
        cells,
    };
    let [nx, ny, nz] = dims;
    let client = velocity.client.clone();

    let residual = solver.new_buffer(cells, false);
    solver.divergence(&velocity, &residual);
    if solids.is_none() && device_solve == DeviceSolve::Direct {
        let pressure = contiguous_f32(direct::pressure(residual, spec), "pressure");
        return (solver.subtract_gradient(&velocity, &pressure, shape), None);
    }
    // Per-cube partial sums: of the velocity's norm (3 values per cell), or of two dot
    // products over the cells at once (the step's `|r|^2` and `r.z`).
    let cell_cubes = cells.div_ceil(CELL_BLOCK);
    let partials = solver.new_buffer((3 * cells).div_ceil(CELL_BLOCK).max(2 * cell_cubes), false);
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
    let operator_direction = solver.new_buffer(cells, false);
    precondition_kernel::launch(
        &client,
        solver.cubes(cells),
        Solver::block(),
        buffer(&residual),
        buffer(&preconditioned),
        buffer(&direction),
        buffer(&solver.inverse_cell),
        buffer(&solver.face_flow),
        buffer(&solver.fluid),
        solver.has_solids,
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
    let hint_key = (
        dims,
        open_faces,
        solids.as_ref().map_or(0, |s| s.fingerprint()),
        rel_tolerance.to_bits(),
        max_iterations,
        spec.kind,
    );
    // A trusted deferred solve runs its budget and reads nothing; an untrusted one tests at
    // the end of its budget and on until converged, like an immediate one.
    let sized = IterationHints::budget(hint_key, max_iterations);
    let planned = match convergence_tests {
        ConvergenceTests::Deferred => sized,
        ConvergenceTests::Immediate => None,
    };
    let (budget, mut next_check) = match planned {
        Some((budget, true)) => (Some(budget), usize::MAX),
        Some((budget, false)) => (None, budget),
        None => (None, IterationHints::first_check(hint_key, max_iterations)),
    };
    let mut report = Some(ProjectionReport::default());
    let last = budget.unwrap_or(max_iterations);
    let mut iteration = 0;
    while iteration < last {
        let k = iteration;
        let residual_slot = Slot::residual_before(k) as u32;
        operator_direction_kernel::launch(
            &client,
            solver.cubes(cells),
            Solver::block(),
            buffer(&direction),
            buffer(&operator_direction),
            buffer(&partials),
            buffer(&scalars),
            residual_slot,
            stopping.tolerance_squared,
            stopping.floor_squared,
            buffer(&solver.inverse_cell),
            buffer(&solver.face_flow),
            buffer(&solver.fluid),
            solver.has_solids,
            nx,
            ny,
            nz,
        );
        let curvature = Slot::curvature(k);
        solver.finish_sums(&partials, &scalars, cell_cubes, [curvature, curvature], 1);
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
            buffer(&partials),
            residual_slot,
            Slot::rz(k) as u32,
            curvature as u32,
            stopping.tolerance_squared,
            stopping.floor_squared,
            buffer(&solver.face_flow),
            buffer(&solver.fluid),
            solver.has_solids,
            nx,
            ny,
            nz,
        );
        solver.finish_sums(
            &partials,
            &scalars,
            cell_cubes,
            [Slot::residual_squared(k), Slot::rz(k + 1)],
            2,
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
            residual_slot,
            stopping.tolerance_squared,
            stopping.floor_squared,
            cells as u32,
        );
        iteration += 1;
        if iteration == next_check || (budget.is_none() && iteration == max_iterations) {
            let values = read_scalars(&scalars);
            if let Some(done) = stopping.first_converged(&values, iteration, cells) {
                report = Some(done);
                break;
            }
            report = Some(report_after(&values, iteration, cells));
            next_check = iteration + CHECK_EVERY;
        }
    }
    match (budget, report) {
        (Some(budget), _) => {
            defer(PendingSolve {
                key: hint_key,
                budget,
                max_iterations,
                scalars: scalars.clone(),
                stopping,
                cells,
            });
            report = None;
        }
        (None, Some(done)) => {
            // Tested as it went: trusted if a deferred budget would have sufficed.
            let within_budget = sized.is_some_and(|(budget, _)| done.iterations <= budget);
            IterationHints::record(hint_key, done.iterations, within_budget);
        }
        (None, None) => {}
    }
    if max_iterations == 0 {
        report = Some(report_after(&read_scalars(&scalars), 0, cells));
    }

    (
        solver.subtract_gradient(&velocity, &pressure, shape),
        report,
    )
}

/// Multiple of f32's epsilon under which `|r| / (|D| |u|)` is round-off.
const F32_RESOLVABLE: f64 = 8.0 * f32::EPSILON as f64;

/// The solve's stopping rule, in the f32 form the step kernel tests (`cg::has_converged`).
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

    /// Iterations an unconverged solve would have needed, estimated from its residual after
    /// `done` iterations as if it kept shrinking at its mean rate so far (CG's is roughly
    /// geometric); `max_iterations` when it did not shrink.
    fn extrapolate(&self, values: &[f32], done: usize, max_iterations: usize) -> usize {
        let start = values[Slot::RHS_NORM_SQUARED] as f64;
        let reached = match done {
            0 => start,
            k => values[Slot::residual_squared(k - 1)] as f64,
        };
        let target = (self.tolerance_squared as f64 * start)
            .max(self.floor_squared as f64 * values[Slot::VELOCITY_NORM_SQUARED] as f64);
        if done == 0 || !(reached > 0.0 && reached < start && target > 0.0) {
            return max_iterations;
        }
        let rate = (reached / start).ln() / done as f64;
        let needed = ((target / start).ln() / rate).ceil();
        if needed.is_finite() && needed > 0.0 {
            (needed as usize).clamp(done + 1, max_iterations.max(done + 1))
        } else {
            max_iterations
        }
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
