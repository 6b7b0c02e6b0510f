//! Incompressibility projection `Pi` (paper Eq. 10), made exact.
//!
//! The paper describes a penalty; here `Pi` is the orthogonal projection onto the velocity
//! fields with zero discrete divergence and no flow through the box walls:
//!
//! * velocities live at cell centres (`[nx, ny, nz, 3]`, see [`crate::grid`]);
//! * the discrete divergence `D` takes face velocities as the mean of the two adjacent cells,
//!   zero on the solid box faces (no normal flow) and the inner cell's velocity (times the
//!   faces' `flow`) on open ones ([`OpenFaces`]), divided by the cell size;
//! * `Pi u = u - D^T p` with `D D^T p = D u`, solved matrix-free by conjugate gradients with a
//!   Jacobi preconditioner, in f64 on the host. (`-D^T` is the discrete gradient, so this is
//!   `u - grad p` with `p` solving the Poisson equation.) `D D^T` is singular (constants and
//!   the collocated grid's checkerboard modes), but `D u` lies in its range, so CG converges
//!   to the minimum-norm `p`.
//!
//! `Pi` is symmetric and idempotent, so its backward pass is `Pi` applied to the incoming
//! gradient; nothing is differentiated through the solver's iterations.
//!
//! * [`SolidCells`] inside the box (obstacles) hold no velocity, and a face between a fluid
//!   cell and a solid one is a wall like the box's. A fluid cell next to an obstacle along an
//!   axis has no velocity component along that axis either (it is *pinned*): a face flux of
//!   zero alone would leave the cell free to point into the obstacle, and an interpolated
//!   velocity would then carry smoke into it. `D` has no row for a solid cell and reads no
//!   pinned component, so `Pi = M - D^T (D D^T)^+ D` (`M` zeroing the solid cells and the
//!   pinned components) stays the orthogonal projection onto `{u = M u, D u = 0}`:
//!   symmetric and idempotent.
//!
//! Caveat (collocated grid): `D`'s central differences cannot see odd-even (checkerboard)
//! velocity modes, so `Pi` leaves them. The default Gaussian interpolation smooths them out
//! (`L_div` of a projected radial field drops 98.7%), but trilinear sampled at cell centres
//! still sees them (only 66%). A staggered (MAC) velocity, or a `D` defined through the
//! interpolant's own divergence, would remove the mismatch; see the issue 4 notes.

use std::sync::Arc;

use rayon::prelude::*;

/// The cells of a grid that an obstacle fills (see the module's notes): no flow enters
/// them. Cheap to clone (the flags are shared); two sets compare equal when they mark the
/// same cells.
#[derive(Debug, Clone)]
pub struct SolidCells {
    resolution: [usize; 3],
    solid: Arc<[bool]>,
    /// Per cell and axis (`[cells * 3]`), whether that velocity component is free (see
    /// [`Divergence::component_is_free`]), worked out once.
    free: Arc<[bool]>,
    count: usize,
    fingerprint: u64,
}

impl SolidCells {
    /// `solid` per cell, flat in the grid's order (x slowest, z fastest); `None` when its
    /// length is not the grid's cell count.
    pub fn new(resolution: [usize; 3], solid: Vec<bool>) -> Option<Self> {
        if solid.len() != resolution.iter().product::<usize>() {
            return None;
        }
        // FNV-1a over the flags: tells solves on different obstacles apart cheaply.
        let mut fingerprint = 0xcbf2_9ce4_8422_2325u64;
        for &flag in &solid {
            fingerprint = (fingerprint ^ flag as u64).wrapping_mul(0x0100_0000_01b3);
        }
        let [_, ny, nz] = resolution;
        let strides = [ny * nz, nz, 1];
        let free: Vec<bool> = (0..solid.len())
            .flat_map(|c| {
                let solid = &solid;
                (0..3).map(move |axis| {
                    let i = (c / strides[axis]) % resolution[axis];
                    let s = strides[axis];
                    !solid[c]
                        && (i + 1 >= resolution[axis] || !solid[c + s])
                        && (i == 0 || !solid[c - s])
                })
            })
            .collect();
        Some(Self {
            resolution,
            count: solid.iter().filter(|&&s| s).count(),
            solid: solid.into(),
            free: free.into(),
            fingerprint,
        })
    }

    pub fn resolution(&self) -> [usize; 3] {
        self.resolution
    }

    pub fn is_solid(&self, cell: usize) -> bool {
        self.solid[cell]
    }

    /// The flags, one per cell.
    pub fn flags(&self) -> &[bool] {
        &self.solid
    }

    /// How many cells are solid.
    pub fn count(&self) -> usize {
        self.count
    }

    /// A hash of the flags (equal sets have equal fingerprints).
    pub fn fingerprint(&self) -> u64 {
        self.fingerprint
    }

    /// `sum |u_x| + |u_y| + |u_z|` of `velocity` (`[cells * 3]`, the grid's order) over the
    /// solid cells: what flows inside the obstacles, zero after the exact projection.
    pub fn speed_inside(&self, velocity: &[f32]) -> f32 {
        assert_eq!(
            velocity.len(),
            3 * self.solid.len(),
            "velocity per cell and axis"
        );
        velocity
            .chunks_exact(3)
            .zip(self.solid.iter())
            .filter(|(_, solid)| **solid)
            .map(|(u, _)| u.iter().map(|v| v.abs()).sum::<f32>())
            .sum()
    }
}

impl PartialEq for SolidCells {
    fn eq(&self, other: &Self) -> bool {
        self.resolution == other.resolution
            && self.fingerprint == other.fingerprint
            && (Arc::ptr_eq(&self.solid, &other.solid) || self.solid == other.solid)
    }
}

/// Which faces of the box let the flow through, and how freely. A solid face (the default)
/// has zero normal velocity; an open face takes its face velocity from the cell inside it,
/// times `flow` (1: zero normal gradient, outflow or inflow, which makes the pressure zero
/// there in effect, so a plume can leave through it instead of recirculating).
#[derive(Debug, Clone, Copy)]
pub struct OpenFaces {
    /// Per axis (x, y, z): the low face (`x-`, at the box's minimum) and the high face.
    pub low: [bool; 3],
    pub high: [bool; 3],
    /// The velocity on an open face as a fraction of the cell's inside it, in (0, 1]: 1 a
    /// zero-gradient outflow; 0.5 the mean of the cell and a still cell outside the box, which
    /// is what a collocated solver that reads zero velocity past an open face (with zero
    /// pressure there) has, the synthetic generator's top among them.
    pub flow: f32,
}

impl PartialEq for OpenFaces {
    fn eq(&self, other: &Self) -> bool {
        self.low == other.low
            && self.high == other.high
            && self.flow.to_bits() == other.flow.to_bits()
    }
}

impl Eq for OpenFaces {}

impl std::hash::Hash for OpenFaces {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        (self.low, self.high, self.flow.to_bits()).hash(state);
    }
}

impl Default for OpenFaces {
    fn default() -> Self {
        Self::NONE
    }
}

impl OpenFaces {
    /// Every face solid.
    pub const NONE: Self = Self {
        low: [false; 3],
        high: [false; 3],
        flow: 1.0,
    };

    /// The same faces with `flow` (see the field).
    pub fn with_flow(self, flow: f32) -> Self {
        Self { flow, ..self }
    }

    /// The face velocity on the low (`high == false`) or high face of `axis` as a fraction of
    /// the cell inside it: `flow` when the face is open, 0 when solid.
    pub fn face_flow(&self, axis: usize, high: bool) -> f64 {
        let open = if high {
            self.high[axis]
        } else {
            self.low[axis]
        };
        if open { f64::from(self.flow) } else { 0.0 }
    }

    /// Parses names such as `y+` (the high y face) and `x-`.
    pub fn from_names<S: AsRef<str>>(names: &[S]) -> Result<Self, String> {
        let mut faces = Self::NONE;
        for name in names {
            let name = name.as_ref();
            let mut chars = name.chars();
            let axis = match chars.next() {
                Some('x') => 0,
                Some('y') => 1,
                Some('z') => 2,
                _ => {
                    return Err(format!(
                        "unknown face `{name}`: use x-, x+, y-, y+, z- or z+"
                    ));
                }
            };
            match (chars.next(), chars.next()) {
                (Some('-'), None) => faces.low[axis] = true,
                (Some('+'), None) => faces.high[axis] = true,
                _ => {
                    return Err(format!(
                        "unknown face `{name}`: use x-, x+, y-, y+, z- or z+"
                    ));
                }
            }
        }
        Ok(faces)
    }

    /// [`Self::face_flow`] of every face (`2 a` the low face of axis `a`, `2 a + 1` the
    /// high), for the kernels.
    pub fn face_flows(&self) -> [f32; 6] {
        std::array::from_fn(|i| self.face_flow(i / 2, i % 2 == 1) as f32)
    }
}

/// When the device solver's host learns that a solve converged (the CPU backends solve
/// directly and ignore it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ConvergenceTests {
    /// The host reads the solve's residuals while it runs (about 1.5 reads per solve) and stops
    /// at convergence or `max_iterations`.
    #[default]
    Immediate,
    /// The solve runs, with no read, as many iterations as the last solves of its kind on the
    /// same grid needed plus a margin (the iterations after convergence are no-ops on the
    /// device), and is judged later, with every other such solve, in one read by
    /// `settle_deferred_solves`, which also sets the next solves' budgets. A solve with no such
    /// history tests immediately; one that runs out of budget returns that iterate, as at
    /// `max_iterations`, and is counted by the settlement.
    Deferred,
}

/// How the device solver of the cube backends solves a grid without obstacles (with
/// obstacles it always iterates: the operator no longer separates).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DeviceSolve {
    /// In one step by separation of variables, as the CPU backends do: three changes of
    /// basis as matrix products, a division, three changes back, in f32, with no read and no
    /// iteration.
    #[default]
    Direct,
    /// Jacobi-PCG to `rel_tolerance`, as with obstacles.
    Iterative,
}

/// Solver controls and what it reached.
#[derive(Debug, Clone, PartialEq)]
pub struct ProjectionOptions {
    /// Stop when `|D u - D D^T p| <= rel_tolerance * |D u|`.
    pub rel_tolerance: f64,
    pub max_iterations: usize,
    /// The box faces the flow may cross.
    pub open_faces: OpenFaces,
    /// Obstacles inside the box, if any.
    pub solids: Option<SolidCells>,
    pub convergence_tests: ConvergenceTests,
    pub device_solve: DeviceSolve,
}

impl Default for ProjectionOptions {
    fn default() -> Self {
        Self {
            rel_tolerance: 1e-6,
            max_iterations: 2000,
            open_faces: OpenFaces::NONE,
            solids: None,
            convergence_tests: ConvergenceTests::Immediate,
            device_solve: DeviceSolve::Direct,
        }
    }
}

/// What a projection solves for: the velocity (the op's forward pass) or the gradient that
/// flows back through it (its backward pass). They need different iteration counts, so the
/// device solver keeps its iteration history per kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum SolveKind {
    #[default]
    Velocity,
    Gradient,
}

#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ProjectionReport {
    pub iterations: usize,
    /// Final `|r| / |D u|` (0 when `D u = 0`).
    pub relative_residual: f64,
    /// RMS of `D u` per cell before and after the projection (units: 1 / frame).
    pub divergence_rms_before: f64,
    pub divergence_rms_after: f64,
}

/// What the op needs to know about the grid (plain data, so it can cross the dispatch).
#[derive(Debug, Clone, PartialEq)]
pub struct ProjectionSpec {
    pub resolution: [usize; 3],
    pub cell: [f64; 3],
    pub options: ProjectionOptions,
    pub kind: SolveKind,
}

impl ProjectionSpec {
    pub fn new(grid: &crate::grid::GridSpec, options: ProjectionOptions) -> Self {
        let Divergence {
            resolution, cell, ..
        } = Divergence::on_grid(grid);
        Self {
            resolution,
            cell,
            options,
            kind: SolveKind::Velocity,
        }
    }

    pub fn operator(&self) -> Divergence {
        Divergence {
            resolution: self.resolution,
            cell: self.cell,
            open: self.options.open_faces,
            solids: self.options.solids.clone(),
        }
    }
}

/// The discrete operators on one grid.
#[derive(Debug, Clone)]
pub struct Divergence {
    pub resolution: [usize; 3],
    /// Cell size per axis, world units.
    pub cell: [f64; 3],
    pub open: OpenFaces,
    /// Obstacle cells (no velocity, no flow through their faces).
    pub solids: Option<SolidCells>,
}

impl Divergence {
    /// The operator on `grid`'s cells, every face solid.
    pub fn on_grid(grid: &crate::grid::GridSpec) -> Self {
        let cell = grid.cell_size();
        Self {
            resolution: grid.resolution(),
            cell: [cell.x as f64, cell.y as f64, cell.z as f64],
            open: OpenFaces::NONE,
            solids: None,
        }
    }

    /// The same operator with `open` faces.
    pub fn with_open_faces(self, open: OpenFaces) -> Self {
        Self { open, ..self }
    }

    /// The same operator with obstacle cells.
    pub fn with_solids(self, solids: Option<SolidCells>) -> Self {
        Self { solids, ..self }
    }

    fn is_solid(&self, cell: usize) -> bool {
        self.solids.as_ref().is_some_and(|s| s.is_solid(cell))
    }

    /// Whether cell `c`'s neighbour along `axis` on the high (`+`) or low side exists and
    /// holds fluid: the face between them is interior (neither a box face nor an obstacle's).
    fn fluid_neighbour(&self, c: usize, axis: usize, high: bool) -> bool {
        let i = self.coord(c, axis);
        let s = self.stride(axis);
        if high {
            i + 1 < self.resolution[axis] && !self.is_solid(c + s)
        } else {
            i > 0 && !self.is_solid(c - s)
        }
    }

    /// Whether the velocity component `axis` of cell `c` is free: the cell holds fluid and
    /// has no obstacle cell next to it along `axis` (else it is zero, see the module's notes).
    pub fn component_is_free(&self, c: usize, axis: usize) -> bool {
        self.solids
            .as_ref()
            .is_none_or(|solids| solids.free[3 * c + axis])
    }

    /// Component `axis` of cell `c` of `u`, or 0 where it is pinned.
    fn free_component(&self, u: &[f64], c: usize, axis: usize) -> f64 {
        if self.component_is_free(c, axis) {
            u[3 * c + axis]
        } else {
            0.0
        }
    }

    /// Row `c` of `D` along `axis`: the coefficient (times `h`) on the cell's own velocity
    /// (0 when pinned), and how many free neighbour components it reaches across interior
    /// faces (each with `+-1/2`). An interior face adds `+-1/2` to the own coefficient, an
    /// open boundary face `+-flow`, a solid one (a box wall or an obstacle's face) nothing.
    fn axis_row(&self, axis: usize, c: usize) -> (f64, usize) {
        let i = self.coord(c, axis);
        let n = self.resolution[axis];
        let s = self.stride(axis);
        let after = self.fluid_neighbour(c, axis, true);
        let before = self.fluid_neighbour(c, axis, false);
        let (after_box, before_box) = (i + 1 >= n, i == 0);
        let plus = match (after, after_box) {
            (true, _) => 0.5,
            (false, true) => self.open.face_flow(axis, true),
            (false, false) => 0.0,
        };
        let minus = match (before, before_box) {
            (true, _) => 0.5,
            (false, true) => self.open.face_flow(axis, false),
            (false, false) => 0.0,
        };
        let own = if self.component_is_free(c, axis) {
            plus - minus
        } else {
            0.0
        };
        let reached = (after && self.component_is_free(c + s, axis)) as usize
            + (before && self.component_is_free(c - s, axis)) as usize;
        (own, reached)
    }

    /// `D u` per cell (1 / frame) of a velocity grid `[nx, ny, nz, 3]`, flat, in f64.
    pub fn of_velocity(&self, velocity: &[f32]) -> Vec<f64> {
        let u: Vec<f64> = velocity.iter().map(|&v| v as f64).collect();
        let mut divergence = vec![0.0; self.resolution.iter().product()];
        self.apply(&u, &mut divergence);
        divergence
    }

    fn stride(&self, axis: usize) -> usize {
        let [_, ny, nz] = self.resolution;
        [ny * nz, nz, 1][axis]
    }

    fn coord(&self, cell: usize, axis: usize) -> usize {
        let [_, ny, nz] = self.resolution;
        match axis {
            0 => cell / (ny * nz),
            1 => (cell / nz) % ny,
            _ => cell % nz,
        }
    }

    /// `(D u)_c = sum_axis (u_face+ - u_face-) / h`, face velocity = mean of its two cells,
    /// zero on solid walls and obstacle faces, the inner cell's on open faces; 0 in obstacle
    /// cells; pinned components read as 0. `u` is `[cells * 3]`.
    pub fn apply(&self, u: &[f64], out: &mut [f64]) {
        let n = self.resolution;
        out.par_iter_mut().enumerate().for_each(|(c, o)| {
            if self.is_solid(c) {
                *o = 0.0;
                return;
            }
            let mut acc = 0.0;
            for (a, &cells) in n.iter().enumerate() {
                let i = self.coord(c, a);
                let s = self.stride(a);
                let own = self.free_component(u, c, a);
                let plus = if self.fluid_neighbour(c, a, true) {
                    0.5 * (own + self.free_component(u, c + s, a))
                } else if i + 1 >= cells {
                    self.open.face_flow(a, true) * own
                } else {
                    0.0
                };
                let minus = if self.fluid_neighbour(c, a, false) {
                    0.5 * (own + self.free_component(u, c - s, a))
                } else if i == 0 {
                    self.open.face_flow(a, false) * own
                } else {
                    0.0
                };
                acc += (plus - minus) / self.cell[a];
            }
            *o = acc;
        });
    }

    /// The adjoint `D^T p`, `[cells * 3]` (0 in obstacle cells and pinned components).
    pub fn apply_transpose(&self, p: &[f64], out: &mut [f64]) {
        let n = self.resolution;
        out.par_chunks_mut(3).enumerate().for_each(|(c, o)| {
            for a in 0..3 {
                if !self.component_is_free(c, a) {
                    o[a] = 0.0;
                    continue;
                }
                let i = self.coord(c, a);
                let s = self.stride(a);
                // u_c appears with weight +1/2h in D at c's + face and in the cell above, and
                // -1/2h at c's - face and in the cell below (interior faces); with +-1/h at
                // c's own open boundary faces (times their flow).
                let mut acc = 0.0;
                if self.fluid_neighbour(c, a, true) {
                    acc += 0.5 * (p[c] - p[c + s]);
                } else if i + 1 >= n[a] {
                    acc += self.open.face_flow(a, true) * p[c];
                }
                if self.fluid_neighbour(c, a, false) {
                    acc -= 0.5 * (p[c] - p[c - s]);
                } else if i == 0 {
                    acc -= self.open.face_flow(a, false) * p[c];
                }
                o[a] = acc / self.cell[a];
            }
        });
    }

    /// Diagonal of `D D^T` (the Jacobi preconditioner).
    fn normal_diagonal(&self) -> Vec<f64> {
        let n = self.resolution;
        (0..n.iter().product::<usize>())
            .into_par_iter()
            .map(|c| {
                if self.is_solid(c) {
                    // No row: the residual stays 0 there, any scale will do.
                    return 1.0;
                }
                (0..3)
                    .map(|a| {
                        let (own, interior) = self.axis_row(a, c);
                        (interior as f64 * 0.25 + own * own) / (self.cell[a] * self.cell[a])
                    })
                    .sum::<f64>()
                    .max(1e-30)
            })
            .collect()
    }
}

impl Divergence {
    /// `M u - D^T p`: the projected velocity from `u` and `D^T p`, obstacle cells and pinned
    /// components zeroed.
    pub fn subtract_gradient(&self, u: &[f64], gradient: &[f64]) -> Vec<f64> {
        u.par_chunks(3)
            .zip(gradient.par_chunks(3))
            .enumerate()
            .flat_map_iter(|(c, (u, g))| {
                (0..3).map(move |a| {
                    if self.component_is_free(c, a) {
                        u[a] - g[a]
                    } else {
                        0.0
                    }
                })
            })
            .collect()
    }
}

/// Parallel dot product over fixed blocks summed in block order: reproducible bit for bit
/// (rayon's own `sum` splits by work stealing, so its rounding varies from run to run).
fn dot(a: &[f64], b: &[f64]) -> f64 {
    const BLOCK: usize = 8192;
    a.par_chunks(BLOCK)
        .zip(b.par_chunks(BLOCK))
        .map(|(x, y)| x.iter().zip(y).map(|(x, y)| x * y).sum::<f64>())
        .collect::<Vec<f64>>()
        .iter()
        .sum()
}

/// Projects `u` (`[cells * 3]`, f32) in place; returns what the solver reached.
pub fn project(op: &Divergence, u: &mut [f32], options: &ProjectionOptions) -> ProjectionReport {
    let inv_diag: Vec<f64> = op.normal_diagonal().iter().map(|d| 1.0 / d).collect();
    project_preconditioned(op, u, options, |r, z| {
        z.iter_mut()
            .zip(r)
            .zip(&inv_diag)
            .for_each(|((z, r), m)| *z = r * m)
    })
}

/// [`project`] with the preconditioner `precondition(r, z)`, which writes `z = M^-1 r` for a
/// symmetric positive (semi-)definite `M^-1`.
pub fn project_preconditioned(
    op: &Divergence,
    u: &mut [f32],
    options: &ProjectionOptions,
    precondition: impl Fn(&[f64], &mut [f64]),
) -> ProjectionReport {
    let cells: usize = op.resolution.iter().product();
    assert_eq!(u.len(), 3 * cells, "velocity must be [nx, ny, nz, 3]");
    let u64: Vec<f64> = u.iter().map(|&v| v as f64).collect();
    let mut b = vec![0.0; cells];
    op.apply(&u64, &mut b);
    let b_norm = dot(&b, &b).sqrt();
    let rms = |v: &[f64]| (dot(v, v) / cells as f64).sqrt();
    let divergence_rms_before = rms(&b);
    if b_norm == 0.0 {
        for (c, cell) in u.chunks_mut(3).enumerate() {
            for (a, value) in cell.iter_mut().enumerate() {
                if !op.component_is_free(c, a) {
                    *value = 0.0;
                }
            }
        }
        return ProjectionReport {
            iterations: 0,
            relative_residual: 0.0,
            divergence_rms_before,
            divergence_rms_after: 0.0,
        };
    }
    // Preconditioned CG on D D^T p = b, from p = 0.
    let mut p = vec![0.0; cells];
    let mut r = b.clone();
    let mut z = vec![0.0; cells];
    precondition(&r, &mut z);
    let mut dir = z.clone();
    let mut rz = dot(&r, &z);
    let mut grad = vec![0.0; 3 * cells];
    let mut a_dir = vec![0.0; cells];
    let mut iterations = 0;
    let mut residual = 1.0;
    while iterations < options.max_iterations {
        op.apply_transpose(&dir, &mut grad);
        op.apply(&grad, &mut a_dir);
        let curvature = dot(&dir, &a_dir);
        if curvature <= 0.0 {
            break; // direction in the null space: nothing left to remove
        }
        let step = rz / curvature;
        p.par_iter_mut().zip(&dir).for_each(|(p, d)| *p += step * d);
        r.par_iter_mut()
            .zip(&a_dir)
            .for_each(|(r, a)| *r -= step * a);
        iterations += 1;
        residual = dot(&r, &r).sqrt() / b_norm;
        if residual <= options.rel_tolerance {
            break;
        }
        precondition(&r, &mut z);
        let rz_next = dot(&r, &z);
        let beta = rz_next / rz;
        rz = rz_next;
        dir.par_iter_mut()
            .zip(&z)
            .for_each(|(d, z)| *d = z + beta * *d);
    }
    op.apply_transpose(&p, &mut grad);
    let projected = op.subtract_gradient(&u64, &grad);
    let mut after = vec![0.0; cells];
    op.apply(&projected, &mut after);
    for (dst, src) in u.iter_mut().zip(&projected) {
        *dst = *src as f32;
    }
    ProjectionReport {
        iterations,
        relative_residual: residual,
        divergence_rms_before,
        divergence_rms_after: rms(&after),
    }
}
