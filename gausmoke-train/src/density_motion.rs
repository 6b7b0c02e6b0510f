//! The velocity that carries one density grid onto the next (ours; the engine of
//! [`crate::velocity_estimate`]): a velocity on the grid such that one semi-Lagrangian step of
//! it carries frame t-1's density onto frame t's, regularised as a velocity of ours is:
//!
//! ```text
//! sum over data cells (rho_{t-1}(x - d(x)) - rho_t(x))^2
//!     + A |grad d|^2   (forward differences, each component, no term across a wall)
//!     + B |div d|^2    (the exact projection's divergence, walls and open faces included)
//!     + G |d - d_prior|^2
//! ```
//!
//! `d` is the move per step in cells, `d_prior` where the fit starts (the previous frame's
//! estimate carried along itself, or a smoke solver's step of it). The densities are divided by frame t's largest value. With
//! [`Smoothed::Change`] the smoothness is `A |grad (d - d_prior)|^2` instead: what the densities
//! do not see is then carried on as it is, not smoothed again at every frame.
//! Solved by Gauss-Newton with warping: ten passes, each linearising the step's residual about
//! the current `d` and solving for the update by conjugate gradients, preconditioned by the
//! inverse of `c I + B D^T D` ([`Preconditioner`], one direct solve): the
//! weight B makes the system stiff, and without it 400 iterations stopped far short. The
//! densities are smoothed by 2, 1, 0.5 cells and then not at all (two passes each, four at
//! the end), so the linearisation holds for moves of a cell or more. Unlike the script, a step
//! is halved while it raises the objective, and the start is kept if the passes end above it.
//!
//! It is `xtask/reference/velocity_from_density.py`'s tracked fit. The pictures only ever see
//! how the density moves; this asks the velocity to explain that motion on the grid, where
//! the joint iterations fit it through the Gaussians' centres.

use gausmoke_model::projection::Divergence;
use gausmoke_model::projection::spectral::SpectralSolver;
use gausmoke_model::{GridSpec, OpenFaces};

use crate::host_grid::smoothed;
use crate::respawn::{SpawnLattice, in_region};

/// Width (cells) of the Gaussian smoothing of both densities at each Gauss-Newton pass.
const SMOOTHING_PASSES: [f32; 10] = [2.0, 2.0, 1.0, 1.0, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0];

/// A Gauss-Newton step that raises the objective is halved up to this many times, then
/// dropped.
const STEP_HALVINGS: usize = 6;

/// Conjugate gradients stop once the residual is this fraction of the right-hand side's norm.
const CG_TOLERANCE: f64 = 1e-6;

/// The weights of the fit's priors (`A`, `B`, `G` above), for densities divided by their
/// largest value and moves in cells per step, and what the smoothness acts on.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct MotionPriors {
    pub smoothness: f64,
    pub divergence: f64,
    pub inertia: f64,
    pub smoothed: Smoothed,
}

/// What the smoothness `A` is charged on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Smoothed {
    /// The move itself, `|grad d|^2`.
    Move,
    /// Its change from the prior, `|grad (d - d_prior)|^2`.
    Change,
}

/// The grid the densities live on and where the smoke may leave it: a departure point past an
/// open face samples clear air (zero density); past a wall it is clamped to the outermost
/// cell centres. Obstacles are not modelled here: the projection after the fit keeps the flow
/// out of them (modelling them in the fit erred more, docs/RESULTS.md).
#[derive(Debug, Clone, Copy)]
pub(crate) struct MotionGrid {
    pub resolution: [usize; 3],
    pub open: OpenFaces,
}

/// The cells whose density the fit asks transport to explain: all but those in the inflow box
/// `scene.inflow` (fractions of `grid`'s box), where a source sets the density.
pub(crate) fn transport_cells(grid: &GridSpec, inflow: Option<[f32; 6]>) -> Vec<bool> {
    let lattice = SpawnLattice {
        lo: grid.lo(),
        hi: grid.hi(),
        resolution: grid.resolution(),
    };
    let inflow = inflow.map(|fractions| lattice.region_from_fractions(fractions));
    grid.cells_where(|p| inflow.is_none_or(|region| !in_region(region, p)))
}

/// Moves per step in cells (`[cells, 3]`) as a velocity in world units per time unit, for
/// cells of size `cell` (per axis) and a step of `dt`.
pub(crate) fn velocity_of_moves(moves: &[f64], cell: [f64; 3], dt: f64) -> Vec<f32> {
    moves
        .iter()
        .enumerate()
        .map(|(i, &m)| (m * cell[i % 3] / dt) as f32)
        .collect()
}

/// The inverse of [`velocity_of_moves`].
pub(crate) fn moves_of_velocity(velocity: &[f32], cell: [f64; 3], dt: f64) -> Vec<f64> {
    velocity
        .iter()
        .enumerate()
        .map(|(i, &u)| f64::from(u) * dt / cell[i % 3])
        .collect()
}

/// What the fit found.
#[derive(Debug, Clone)]
pub(crate) struct MotionFit {
    /// The move per step, cells, `[nx, ny, nz, 3]`, z fastest.
    pub moves: Vec<f64>,
    /// The data residual of the start (the prior) and of the fit, each
    /// relative to that of no move at all (`|rho_t - rho_{t-1}|` over the data cells).
    pub misfit_prior: f64,
    pub misfit_fitted: f64,
    /// Whether the passes ended worse than they started (unsmoothed), so the start was kept.
    pub kept_start: bool,
    /// Conjugate-gradient iterations over all passes, and the largest residual a pass's solve
    /// ended on, relative to its right-hand side ([`CG_TOLERANCE`] when every solve
    /// converged).
    pub solver_iterations: usize,
    pub solver_residual: f64,
}

impl MotionGrid {
    pub(crate) fn cells(&self) -> usize {
        self.resolution.iter().product()
    }

    pub(crate) fn index(&self, [i, j, k]: [usize; 3]) -> usize {
        let [_, ny, nz] = self.resolution;
        (i * ny + j) * nz + k
    }

    pub(crate) fn coordinates(&self, cell: usize) -> [usize; 3] {
        let [_, ny, nz] = self.resolution;
        [cell / (ny * nz), (cell / nz) % ny, cell % nz]
    }

    /// Central differences inside, one-sided at the walls, per axis, `[cells, 3]`.
    fn gradient(&self, field: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; 3 * field.len()];
        for cell in 0..field.len() {
            let at = self.coordinates(cell);
            for axis in 0..3 {
                let (low, high) = central(at[axis], self.resolution[axis]);
                if low == high {
                    continue;
                }
                let mut lower = at;
                lower[axis] = low;
                let mut upper = at;
                upper[axis] = high;
                out[3 * cell + axis] =
                    (field[self.index(upper)] - field[self.index(lower)]) / (high - low) as f64;
            }
        }
        out
    }

    /// Trilinear sample of `values` (`channels` per cell) at `point`, in cell-index
    /// coordinates inside `[0, n - 1]` per axis, into `out`.
    fn sample(&self, values: &[f64], channels: usize, point: [f64; 3], out: &mut [f64]) {
        let mut base = [0usize; 3];
        let mut fraction = [0.0f64; 3];
        for axis in 0..3 {
            let n = self.resolution[axis];
            base[axis] = (point[axis].floor() as usize).min(n.saturating_sub(2));
            fraction[axis] = point[axis] - base[axis] as f64;
        }
        out.iter_mut().for_each(|o| *o = 0.0);
        for corner in 0..8 {
            let offset = [(corner >> 2) & 1, (corner >> 1) & 1, corner & 1];
            let mut weight = 1.0;
            let mut at = [0usize; 3];
            for axis in 0..3 {
                at[axis] = (base[axis] + offset[axis]).min(self.resolution[axis] - 1);
                weight *= if offset[axis] == 1 {
                    fraction[axis]
                } else {
                    1.0 - fraction[axis]
                };
            }
            let cell = self.index(at);
            for (c, o) in out.iter_mut().enumerate() {
                *o += weight * values[channels * cell + c];
            }
        }
    }

    /// Where cell `cell` came from over `fraction` of its move (cell-index coordinates,
    /// clamped to the outermost cell centres), and whether that lies past an open face, where
    /// clear air comes in.
    fn departure(&self, cell: usize, moves: &[f64], fraction: f64) -> ([f64; 3], bool) {
        let at = self.coordinates(cell);
        let mut departure = [0.0; 3];
        let mut from_outside = false;
        for axis in 0..3 {
            let n = self.resolution[axis] as f64;
            let x = at[axis] as f64 - fraction * moves[3 * cell + axis];
            from_outside |=
                (self.open.low[axis] && x < -0.5) || (self.open.high[axis] && x > n - 0.5);
            departure[axis] = x.clamp(0.0, n - 1.0);
        }
        (departure, from_outside)
    }

    /// One semi-Lagrangian step of `density` by `moves`: each cell's value at its departure
    /// point, and the density's gradient there (`d value / d move = -gradient`).
    fn carried(&self, density: &[f64], moves: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let slope_field = self.gradient(density);
        let mut value = vec![0.0; density.len()];
        let mut slope = vec![0.0; 3 * density.len()];
        let mut one = [0.0];
        for cell in 0..density.len() {
            let (departure, from_outside) = self.departure(cell, moves, 1.0);
            if from_outside {
                continue;
            }
            self.sample(density, 1, departure, &mut one);
            value[cell] = one[0];
            self.sample(
                &slope_field,
                3,
                departure,
                &mut slope[3 * cell..3 * cell + 3],
            );
        }
        (value, slope)
    }

    /// `values` (`channels` per cell) carried by `fraction` of `moves` in one semi-Lagrangian
    /// step: each cell takes the value at its departure point, zero from past an open face.
    pub(crate) fn advected(
        &self,
        values: &[f64],
        channels: usize,
        moves: &[f64],
        fraction: f64,
    ) -> Vec<f64> {
        let mut out = vec![0.0; values.len()];
        for cell in 0..self.cells() {
            let (departure, from_outside) = self.departure(cell, moves, fraction);
            if !from_outside {
                let range = channels * cell..channels * (cell + 1);
                self.sample(values, channels, departure, &mut out[range]);
            }
        }
        out
    }

    /// `moves` carried along themselves by one semi-Lagrangian step, as a velocity is carried
    /// from one frame to the next: each cell takes the move found at its departure point,
    /// clamped to the outermost cell centres.
    pub(crate) fn self_carried(&self, moves: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; moves.len()];
        for cell in 0..self.cells() {
            let (departure, _) = self.departure(cell, moves, 1.0);
            self.sample(moves, 3, departure, &mut out[3 * cell..3 * cell + 3]);
        }
        out
    }

    /// `out = (A L + B D^T D + G) moves`: `L` the forward differences' normal matrix (a
    /// Laplacian with no flux through the walls), `D` the projection's own divergence (faces
    /// the mean of their two cells, no flow through a wall, `flow` times the inner cell's
    /// through an open face), so that what the fit counts as divergence-free is what `Pi`
    /// leaves alone.
    fn regularise(&self, priors: &MotionPriors, moves: &[f64], out: &mut [f64]) {
        let cells = self.cells();
        out.iter_mut()
            .zip(moves)
            .for_each(|(o, m)| *o = priors.inertia * m);
        for cell in 0..cells {
            let at = self.coordinates(cell);
            for axis in 0..3 {
                if at[axis] + 1 < self.resolution[axis] {
                    let mut next = at;
                    next[axis] += 1;
                    let other = self.index(next);
                    for c in 0..3 {
                        let difference =
                            priors.smoothness * (moves[3 * cell + c] - moves[3 * other + c]);
                        out[3 * cell + c] += difference;
                        out[3 * other + c] -= difference;
                    }
                }
            }
        }
        let operator = self.divergence();
        let mut divergence = vec![0.0; cells];
        operator.apply(moves, &mut divergence);
        divergence.iter_mut().for_each(|d| *d *= priors.divergence);
        let mut back = vec![0.0; 3 * cells];
        operator.apply_transpose(&divergence, &mut back);
        out.iter_mut().zip(&back).for_each(|(o, b)| *o += b);
    }

    /// The projection's divergence on unit cells (moves are in cells).
    fn divergence(&self) -> Divergence {
        Divergence {
            resolution: self.resolution,
            cell: [1.0; 3],
            open: self.open,
            solids: None,
        }
    }
}

/// The neighbours a central difference at `i` of `n` reads.
fn central(i: usize, n: usize) -> (usize, usize) {
    (i.saturating_sub(1), (i + 1).min(n - 1))
}

/// The move per step (cells) that carries `before` onto `after` (`[nx, ny, nz]`, z fastest),
/// starting from and tied to `prior` (cells per step, `[nx, ny, nz, 3]`). Only cells marked
/// in `in_data` enter the data term (a source sets the others, not transport). With no
/// density in `after`, the prior is returned as it is.
pub(crate) fn fit_density_motion(
    grid: &MotionGrid,
    before: &[f32],
    after: &[f32],
    in_data: &[bool],
    prior: &[f64],
    priors: MotionPriors,
    cg_iterations: usize,
) -> MotionFit {
    let cells = grid.cells();
    assert_eq!(
        (before.len(), after.len(), in_data.len(), prior.len()),
        (cells, cells, cells, 3 * cells),
        "density-motion fit: the grids' sizes"
    );
    let scale = after.iter().fold(0.0f32, |m, &v| m.max(v));
    if scale.is_nan() || scale <= 0.0 || scale.is_infinite() {
        return MotionFit {
            moves: prior.to_vec(),
            misfit_prior: 0.0,
            misfit_fitted: 0.0,
            kept_start: true,
            solver_iterations: 0,
            solver_residual: 0.0,
        };
    }
    let normalised = |field: &[f32]| -> Vec<f32> { field.iter().map(|&v| v / scale).collect() };
    let (before_unit, after_unit) = (normalised(before), normalised(after));
    let as_f64 = |field: &[f32]| -> Vec<f64> { field.iter().map(|&v| f64::from(v)).collect() };
    let (source_plain, target_plain) = (as_f64(&before_unit), as_f64(&after_unit));
    let operator = grid.divergence();
    let spectral = SpectralSolver::for_grid(&operator);
    let mut moves = prior.to_vec();
    let mut operator_out = vec![0.0; 3 * cells];
    let (mut solver_iterations, mut solver_residual) = (0, 0.0f64);
    let pull = pull_of(grid, &priors, prior);
    let problem = Problem {
        grid,
        priors: &priors,
        in_data,
        pull: &pull,
    };
    for &sigma in &SMOOTHING_PASSES {
        let blurred =
            |field: &[f32]| as_f64(&smoothed(field, grid.resolution, 1, sigma, [true; 3]));
        let smoothed_pair;
        let (source, target): (&[f64], &[f64]) = if sigma > 0.0 {
            smoothed_pair = (blurred(&before_unit), blurred(&after_unit));
            (&smoothed_pair.0, &smoothed_pair.1)
        } else {
            (&source_plain, &target_plain)
        };
        let (value, slope) = grid.carried(source, &moves);
        // The residual's Jacobian with respect to the move is minus the slope.
        let mut jacobian = vec![0.0; 3 * cells];
        let mut rhs = vec![0.0; 3 * cells];
        grid.regularise(&priors, &moves, &mut operator_out);
        for cell in 0..cells {
            for c in 0..3 {
                rhs[3 * cell + c] = pull[3 * cell + c] - operator_out[3 * cell + c];
            }
            if !in_data[cell] {
                continue;
            }
            let residual = value[cell] - target[cell];
            for c in 0..3 {
                jacobian[3 * cell + c] = -slope[3 * cell + c];
                rhs[3 * cell + c] -= jacobian[3 * cell + c] * residual;
            }
        }
        let mut preconditioner = Preconditioner::new(
            &operator,
            &spectral,
            // Positive even with no tie, smoothness or slope (all weights may be 0).
            (priors.inertia
                + 6.0 * priors.smoothness
                + jacobian.iter().map(|j| j * j).sum::<f64>() / cells as f64)
                .max(1e-12),
            priors.divergence,
        );
        let apply = |x: &[f64], out: &mut [f64]| {
            grid.regularise(&priors, x, out);
            for cell in 0..cells {
                let j = &jacobian[3 * cell..3 * cell + 3];
                let along = j[0] * x[3 * cell] + j[1] * x[3 * cell + 1] + j[2] * x[3 * cell + 2];
                for c in 0..3 {
                    out[3 * cell + c] += j[c] * along;
                }
            }
        };
        let precondition = |r: &[f64], z: &mut [f64]| preconditioner.apply(r, z);
        let solve = conjugate_gradients(apply, precondition, &rhs, cg_iterations);
        solver_iterations += solve.iterations;
        solver_residual = solver_residual.max(solve.relative_residual);
        let step = solve.x;
        // Damped: where the densities pin the move down only weakly, a full step can leave the
        // range where the linearisation holds and fit worse than no step at all.
        let start = objective(&problem, source, target, &moves, &mut operator_out);
        let mut length = 1.0;
        for _ in 0..STEP_HALVINGS {
            let tried: Vec<f64> = moves
                .iter()
                .zip(&step)
                .map(|(m, s)| m + length * s)
                .collect();
            if objective(&problem, source, target, &tried, &mut operator_out) < start {
                moves = tried;
                break;
            }
            length *= 0.5;
        }
    }
    // The smoothed passes can lead into a basin the unsmoothed objective likes less than the
    // start: then the start is kept.
    let (source, target) = (&source_plain, &target_plain);
    let kept_start = objective(&problem, source, target, &moves, &mut operator_out)
        >= objective(&problem, source, target, prior, &mut operator_out);
    if kept_start {
        moves = prior.to_vec();
    }
    // No move carries each cell's own value: the misfit's yardstick.
    let still = data_term(&problem, source, target, &vec![0.0; 3 * cells]);
    let misfit = |moves: &[f64]| {
        if still > 0.0 {
            (data_term(&problem, source, target, moves) / still).sqrt()
        } else {
            0.0
        }
    };
    MotionFit {
        misfit_prior: misfit(prior),
        misfit_fitted: misfit(&moves),
        moves,
        kept_start,
        solver_iterations,
        solver_residual,
    }
}

/// `(c I + B D^T D)^-1`, `D` the divergence on unit cells: the fit's normal matrix with its
/// data and smoothness terms as one scale `c` (their mean diagonal), whose large divergence
/// part it inverts exactly. By Woodbury's identity it is
/// `(I - D^T (D D^T + c/B I)^-1 D) / c`, one shifted direct solve.
/// It is applied at every conjugate-gradient iteration, so it keeps its two scratch fields.
struct Preconditioner<'a> {
    operator: &'a Divergence,
    solver: &'a SpectralSolver,
    scale: f64,
    divergence: f64,
    pressure: Vec<f64>,
    gradient: Vec<f64>,
}

impl<'a> Preconditioner<'a> {
    fn new(
        operator: &'a Divergence,
        solver: &'a SpectralSolver,
        scale: f64,
        divergence: f64,
    ) -> Self {
        let cells: usize = operator.resolution.iter().product();
        Self {
            operator,
            solver,
            scale,
            divergence,
            pressure: vec![0.0; cells],
            gradient: vec![0.0; 3 * cells],
        }
    }

    fn apply(&mut self, r: &[f64], z: &mut [f64]) {
        z.copy_from_slice(r);
        if self.divergence > 0.0 {
            self.operator.apply(r, &mut self.pressure);
            self.solver
                .solve_shifted(&mut self.pressure, self.scale / self.divergence);
            self.operator
                .apply_transpose(&self.pressure, &mut self.gradient);
            z.iter_mut().zip(&self.gradient).for_each(|(z, g)| *z -= g);
        }
        z.iter_mut().for_each(|z| *z /= self.scale);
    }
}

/// The linear term the quadratic priors pull the move towards: the objective's quadratic part
/// is `d . R d - 2 d . pull` (`R` as [`MotionGrid::regularise`] applies it), with `pull = G
/// d_prior`, and `+ A L d_prior` when the smoothness is on the change from the prior.
fn pull_of(grid: &MotionGrid, priors: &MotionPriors, prior: &[f64]) -> Vec<f64> {
    let mut pull: Vec<f64> = prior.iter().map(|p| priors.inertia * p).collect();
    if priors.smoothed == Smoothed::Change {
        let smoothness_only = MotionPriors {
            divergence: 0.0,
            inertia: 0.0,
            ..*priors
        };
        let mut smoothed_prior = vec![0.0; prior.len()];
        grid.regularise(&smoothness_only, prior, &mut smoothed_prior);
        pull.iter_mut()
            .zip(&smoothed_prior)
            .for_each(|(p, s)| *p += s);
    }
    pull
}

/// What stays fixed through the passes.
struct Problem<'a> {
    grid: &'a MotionGrid,
    priors: &'a MotionPriors,
    in_data: &'a [bool],
    pull: &'a [f64],
}

/// The fit's objective (up to a constant) for `moves` between `source` and `target`; `out` is
/// scratch.
fn objective(
    problem: &Problem,
    source: &[f64],
    target: &[f64],
    moves: &[f64],
    out: &mut [f64],
) -> f64 {
    let data = data_term(problem, source, target, moves);
    problem.grid.regularise(problem.priors, moves, out);
    let quadratic: f64 = (0..moves.len())
        .map(|i| moves[i] * out[i] - 2.0 * moves[i] * problem.pull[i])
        .sum();
    data + quadratic
}

/// The squared difference of `source` carried by `moves` from `target` over the data cells.
fn data_term(problem: &Problem, source: &[f64], target: &[f64], moves: &[f64]) -> f64 {
    let (value, _) = problem.grid.carried(source, moves);
    (0..target.len())
        .filter(|&c| problem.in_data[c])
        .map(|c| (value[c] - target[c]).powi(2))
        .sum()
}

/// Solves `A x = rhs` for a symmetric positive (semi-)definite `A`, from `x = 0`, with the
/// symmetric positive preconditioner `precondition(r, z)` (`z = M^-1 r`), until the residual
/// is [`CG_TOLERANCE`] of `rhs` or after `iterations`.
fn conjugate_gradients(
    apply: impl Fn(&[f64], &mut [f64]),
    mut precondition: impl FnMut(&[f64], &mut [f64]),
    rhs: &[f64],
    iterations: usize,
) -> Solve {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let mut x = vec![0.0; rhs.len()];
    let mut residual = rhs.to_vec();
    let mut preconditioned = vec![0.0; rhs.len()];
    precondition(&residual, &mut preconditioned);
    let mut direction = preconditioned.clone();
    let mut applied = vec![0.0; rhs.len()];
    let mut along = dot(&residual, &preconditioned);
    let first = dot(&residual, &residual);
    let stop = (CG_TOLERANCE * CG_TOLERANCE) * first;
    let mut squared = first;
    let mut used = 0;
    while used < iterations && squared > stop && squared > 0.0 {
        apply(&direction, &mut applied);
        let curvature = dot(&direction, &applied);
        if curvature.is_nan() || curvature <= 0.0 {
            break;
        }
        used += 1;
        let alpha = along / curvature;
        for i in 0..x.len() {
            x[i] += alpha * direction[i];
            residual[i] -= alpha * applied[i];
        }
        squared = dot(&residual, &residual);
        precondition(&residual, &mut preconditioned);
        let next = dot(&residual, &preconditioned);
        let beta = next / along;
        along = next;
        for i in 0..x.len() {
            direction[i] = preconditioned[i] + beta * direction[i];
        }
    }
    Solve {
        x,
        iterations: used,
        relative_residual: if first > 0.0 {
            (squared / first).sqrt()
        } else {
            0.0
        },
    }
}

/// What [`conjugate_gradients`] reached.
struct Solve {
    x: Vec<f64>,
    iterations: usize,
    /// The residual's norm relative to the right-hand side's.
    relative_residual: f64,
}

#[cfg(test)]
mod tests;
