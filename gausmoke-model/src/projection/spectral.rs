//! The exact projection's Poisson solve `D D^T p = D u` in one direct step, by separation of
//! variables.
//!
//! `D` acts on velocity component `a` along axis `a` only (`D = sum_a D_a`, each `D_a` the same
//! 1D operator `D1` on the lines of the grid along that axis), so `D D^T = sum_a D_a D_a^T` is
//! a Kronecker sum of three small symmetric matrices `T_a = D1_a D1_a^T` (`n_a x n_a`). With
//! `T_a = Q_a L_a Q_a^T`, the solve is three changes of basis, a division by
//! `l_x[i] + l_y[j] + l_z[k]`, and three changes back: `O(N (nx + ny + nz))`, no iteration, no
//! tolerance. The only null mode is the constant (every `T_a` is positive semi-definite with
//! the constants as its kernel), which gets zero, so `p` is the minimum-norm solution that
//! conjugate gradients from zero converges to; `u - D^T p` is the same projection either way.
//! Everything is in f64.

use std::sync::Arc;

use super::host::{Divergence, ProjectionReport};

/// `T = D1 D1^T` of one axis with `n` cells of size `h` (dense, row-major), its low and high
/// faces' flow (0 when solid, see `OpenFaces::face_flow`).
fn normal_matrix(n: usize, h: f64, flow_low: f64, flow_high: f64) -> Vec<f64> {
    // D1 (n x n): (D1 v)_i = (v_i + v_{i+1}) / 2h - (v_i + v_{i-1}) / 2h inside; at a
    // boundary face the face velocity is flow v_i (zero on a solid one).
    let mut d1 = vec![0.0f64; n * n];
    for i in 0..n {
        if i + 1 < n {
            d1[i * n + i] += 0.5 / h;
            d1[i * n + i + 1] += 0.5 / h;
        } else {
            d1[i * n + i] += flow_high / h;
        }
        if i > 0 {
            d1[i * n + i] -= 0.5 / h;
            d1[i * n + i - 1] -= 0.5 / h;
        } else {
            d1[i * n + i] -= flow_low / h;
        }
    }
    let mut t = vec![0.0f64; n * n];
    for i in 0..n {
        for j in 0..n {
            t[i * n + j] = (0..n).map(|k| d1[i * n + k] * d1[j * n + k]).sum();
        }
    }
    t
}

/// Eigen-decomposition of a symmetric matrix by cyclic Jacobi rotations: `(values, vectors)`,
/// the eigenvectors as the columns of `vectors` (row-major `n x n`).
fn symmetric_eigen(mut a: Vec<f64>, n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut v = vec![0.0f64; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    let scale: f64 = a
        .iter()
        .map(|x| x * x)
        .sum::<f64>()
        .sqrt()
        .max(f64::MIN_POSITIVE);
    for _sweep in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i * n + j] * a[i * n + j])
            .sum::<f64>()
            .sqrt();
        if off <= 1e-15 * scale {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[p * n + q];
                if apq.abs() <= 1e-300 {
                    continue;
                }
                let theta = (a[q * n + q] - a[p * n + p]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                // A <- J^T A J on rows/columns p and q.
                for k in 0..n {
                    let (akp, akq) = (a[k * n + p], a[k * n + q]);
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[p * n + k], a[q * n + k]);
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[k * n + p], v[k * n + q]);
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ((0..n).map(|i| a[i * n + i]).collect(), v)
}

/// A strided view of a matrix held in a slice.
#[derive(Clone, Copy)]
struct Matrix<'a> {
    data: &'a [f64],
    row_stride: usize,
    col_stride: usize,
}

impl<'a> Matrix<'a> {
    fn row_major(data: &'a [f64], cols: usize) -> Self {
        Self {
            data,
            row_stride: cols,
            col_stride: 1,
        }
    }
}

/// `lhs [m, k] rhs [k, n]`, row-major (`gemm`, f64: splits only the output, so the sums do not
/// depend on scheduling).
fn product(m: usize, n: usize, k: usize, lhs: Matrix, rhs: Matrix) -> Vec<f64> {
    let fits = |a: &Matrix, rows: usize, cols: usize| {
        rows == 0
            || cols == 0
            || (rows - 1) * a.row_stride + (cols - 1) * a.col_stride < a.data.len()
    };
    assert!(
        fits(&lhs, m, k) && fits(&rhs, k, n),
        "operands inside their slices"
    );
    let mut out = vec![0.0f64; m * n];
    if m == 0 || n == 0 || k == 0 {
        return out;
    }
    let parallelism = if m * n * k >= 1 << 18 {
        gemm::Parallelism::Rayon(0)
    } else {
        gemm::Parallelism::None
    };
    // SAFETY: the assert bounds every index of both operands; `out` holds m x n.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            out.as_mut_ptr(),
            1,
            n as isize,
            false,
            lhs.data.as_ptr(),
            lhs.col_stride as isize,
            lhs.row_stride as isize,
            rhs.data.as_ptr(),
            rhs.col_stride as isize,
            rhs.row_stride as isize,
            0.0,
            1.0,
            false,
            false,
            false,
            parallelism,
        );
    }
    out
}

/// One axis's eigen-decomposition of `T_a`.
#[derive(Debug)]
struct AxisBasis {
    n: usize,
    values: Vec<f64>,
    /// Eigenvectors as columns, row-major.
    vectors: Vec<f64>,
}

/// The eigenbases of the three axes of one grid (cached: they depend on the grid only).
#[derive(Debug, Clone)]
pub struct SpectralSolver {
    axes: Arc<[AxisBasis; 3]>,
    resolution: [usize; 3],
}

impl SpectralSolver {
    /// The solver of `op`'s grid, computed once per grid (a few recent grids are kept: the
    /// bases depend on the resolution and cell size only).
    pub fn for_grid(op: &Divergence) -> Self {
        type Key = ([usize; 3], [u64; 3], super::host::OpenFaces);
        static RECENT: std::sync::Mutex<Vec<(Key, SpectralSolver)>> =
            std::sync::Mutex::new(Vec::new());
        let key = (op.resolution, op.cell.map(f64::to_bits), op.open);
        let mut recent = RECENT
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some((_, solver)) = recent.iter().find(|(k, _)| *k == key) {
            return solver.clone();
        }
        let solver = Self::new(op);
        if recent.len() >= 4 {
            recent.remove(0);
        }
        recent.push((key, solver.clone()));
        solver
    }

    pub fn new(op: &Divergence) -> Self {
        let axes = [0, 1, 2].map(|a| {
            let n = op.resolution[a];
            let matrix = normal_matrix(
                n,
                op.cell[a],
                op.open.face_flow(a, false),
                op.open.face_flow(a, true),
            );
            let (values, vectors) = symmetric_eigen(matrix, n);
            AxisBasis { n, values, vectors }
        });
        Self {
            axes: Arc::new(axes),
            resolution: op.resolution,
        }
    }

    /// Multiplies every line of `x` (`[nx, ny, nz]`, flat) along `axis` by the axis's
    /// eigenvectors: by `Q^T` (into the eigenbasis) or by `Q` (back).
    fn change_basis(&self, x: &mut [f64], axis: usize, into: bool) {
        let basis = &self.axes[axis];
        let n = basis.n;
        let [nx, ny, nz] = self.resolution;
        // M = Q^T or Q as a strided view of the row-major Q.
        let q = &basis.vectors;
        let m = if into {
            Matrix {
                data: q,
                row_stride: 1,
                col_stride: n,
            }
        } else {
            Matrix {
                data: q,
                row_stride: n,
                col_stride: 1,
            }
        };
        match axis {
            // [n, ny nz]: M X.
            0 => {
                let out = product(n, ny * nz, n, m, Matrix::row_major(x, ny * nz));
                x.copy_from_slice(&out);
            }
            // nx blocks of [n, nz]: M X each.
            1 => {
                for block in x.chunks_mut(ny * nz) {
                    let out = product(n, nz, n, m, Matrix::row_major(block, nz));
                    block.copy_from_slice(&out);
                }
            }
            // [nx ny, n]: X M^T.
            _ => {
                let mt = Matrix {
                    data: m.data,
                    row_stride: m.col_stride,
                    col_stride: m.row_stride,
                };
                let out = product(nx * ny, n, n, Matrix::row_major(x, n), mt);
                x.copy_from_slice(&out);
            }
        }
    }

    /// The minimum-norm `p` with `D D^T p = b` (`b` orthogonal to the constants, as `D u`
    /// is), in place.
    pub fn solve(&self, b: &mut [f64]) {
        self.solve_shifted(b, 0.0);
    }

    /// `p` with `(D D^T + shift I) p = b`, in place; with `shift` 0 the minimum-norm solution
    /// of [`SpectralSolver::solve`].
    pub fn solve_shifted(&self, b: &mut [f64], shift: f64) {
        let [nx, ny, nz] = self.resolution;
        assert_eq!(b.len(), nx * ny * nz, "one value per cell");
        assert!(
            shift >= 0.0,
            "a shift of {shift} can make the system singular"
        );
        for axis in 0..3 {
            self.change_basis(b, axis, true);
        }
        let [lx, ly, lz] = [0, 1, 2].map(|a| &self.axes[a].values);
        let largest = lx.iter().cloned().fold(0.0, f64::max)
            + ly.iter().cloned().fold(0.0, f64::max)
            + lz.iter().cloned().fold(0.0, f64::max);
        for (cell, value) in b.iter_mut().enumerate() {
            let (i, j, k) = (cell / (ny * nz), (cell / nz) % ny, cell % nz);
            let eigenvalue = lx[i] + ly[j] + lz[k] + shift;
            *value = if eigenvalue > 1e-12 * largest {
                *value / eigenvalue
            } else {
                0.0
            };
        }
        for axis in 0..3 {
            self.change_basis(b, axis, false);
        }
    }
}

/// The direct solve in the form the device runs it, in f32: per axis the change of basis
/// into the eigenbasis, `Q^T` (row-major `[n, n]`), and back, `Q`; and per cell (`[nx, ny,
/// nz]`, z fastest) the inverse of its eigenvalue, 0 for the null mode, as
/// [`SpectralSolver::solve`] divides.
#[derive(Debug, Clone)]
pub struct DeviceFactors {
    pub into: [Vec<f32>; 3],
    pub back: [Vec<f32>; 3],
    pub inverse: Vec<f32>,
}

impl SpectralSolver {
    /// [`DeviceFactors`] of this grid.
    pub fn device_factors(&self) -> DeviceFactors {
        let [nx, ny, nz] = self.resolution;
        let transpose = |q: &[f64], n: usize| -> Vec<f32> {
            (0..n * n).map(|e| q[(e % n) * n + e / n] as f32).collect()
        };
        let into = [0, 1, 2].map(|a| transpose(&self.axes[a].vectors, self.axes[a].n));
        let back = [0, 1, 2].map(|a| self.axes[a].vectors.iter().map(|&v| v as f32).collect());
        let [lx, ly, lz] = [0, 1, 2].map(|a| &self.axes[a].values);
        let largest = lx.iter().cloned().fold(0.0, f64::max)
            + ly.iter().cloned().fold(0.0, f64::max)
            + lz.iter().cloned().fold(0.0, f64::max);
        let inverse = (0..nx * ny * nz)
            .map(|cell| {
                let (i, j, k) = (cell / (ny * nz), (cell / nz) % ny, cell % nz);
                let eigenvalue = lx[i] + ly[j] + lz[k];
                if eigenvalue > 1e-12 * largest {
                    (1.0 / eigenvalue) as f32
                } else {
                    0.0
                }
            })
            .collect();
        DeviceFactors {
            into,
            back,
            inverse,
        }
    }
}

/// Projects `u` (`[cells * 3]`, f32) in place with the direct solve; the report's
/// `iterations` is 1 and its residual what f64 arithmetic left.
///
/// Obstacles make the operator inseparable: with [`Divergence::solids`] set this panics;
/// callers solve those with [`super::host::project`] (see `super::project_on_host`).
pub fn project(op: &Divergence, solver: &SpectralSolver, u: &mut [f32]) -> ProjectionReport {
    assert!(
        op.solids.is_none(),
        "the direct solve separates the axes, which obstacle cells prevent"
    );
    let cells: usize = op.resolution.iter().product();
    assert_eq!(u.len(), 3 * cells, "velocity must be [nx, ny, nz, 3]");
    let u64: Vec<f64> = u.iter().map(|&v| v as f64).collect();
    let mut b = vec![0.0; cells];
    op.apply(&u64, &mut b);
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let b_norm = norm(&b);
    let mut p = b.clone();
    solver.solve(&mut p);
    let mut grad = vec![0.0; 3 * cells];
    op.apply_transpose(&p, &mut grad);
    let projected: Vec<f64> = u64.iter().zip(&grad).map(|(u, g)| u - g).collect();
    let mut after = vec![0.0; cells];
    op.apply(&projected, &mut after);
    for (dst, src) in u.iter_mut().zip(&projected) {
        *dst = *src as f32;
    }
    let after_norm = norm(&after);
    ProjectionReport {
        iterations: 1,
        relative_residual: if b_norm > 0.0 {
            after_norm / b_norm
        } else {
            0.0
        },
        divergence_rms_before: b_norm / (cells as f64).sqrt(),
        divergence_rms_after: after_norm / (cells as f64).sqrt(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::projection::OpenFaces;

    #[test]
    fn eigen_decomposition_reconstructs_the_matrix() {
        for n in [1, 2, 5, 16] {
            let t = normal_matrix(n, 0.3, 0.0, 0.0);
            let (values, vectors) = symmetric_eigen(t.clone(), n);
            for i in 0..n {
                for j in 0..n {
                    let rebuilt: f64 = (0..n)
                        .map(|k| vectors[i * n + k] * values[k] * vectors[j * n + k])
                        .sum();
                    assert!((rebuilt - t[i * n + j]).abs() < 1e-9, "n {n} ({i}, {j})");
                }
            }
            // One null direction (the constants), every other eigenvalue positive.
            let zeros = values.iter().filter(|v| v.abs() < 1e-9).count();
            assert_eq!(zeros, 1, "n {n}: {values:?}");
        }
    }

    #[test]
    fn the_solve_inverts_the_normal_operator() {
        let op = Divergence {
            resolution: [6, 5, 7],
            cell: [0.2, 0.3, 0.25],
            open: OpenFaces::NONE,
            solids: None,
        };
        let cells = 6 * 5 * 7;
        let mut rng = gausmoke_core::SplitMix64::new(4);
        let u: Vec<f64> = (0..3 * cells)
            .map(|_| rng.range(-1.0, 1.0) as f64)
            .collect();
        let mut b = vec![0.0; cells];
        op.apply(&u, &mut b);
        let mut p = b.clone();
        SpectralSolver::new(&op).solve(&mut p);
        let mut grad = vec![0.0; 3 * cells];
        op.apply_transpose(&p, &mut grad);
        let mut again = vec![0.0; cells];
        op.apply(&grad, &mut again);
        let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (x, y) in again.iter().zip(&b) {
            assert!((x - y).abs() < 1e-10 * scale, "{x} vs {y}");
        }
        // Minimum norm: no constant component.
        let mean = p.iter().sum::<f64>() / cells as f64;
        assert!(mean.abs() < 1e-10 * scale, "mean {mean}");
    }

    /// The shifted solve inverts `D D^T + shift I`, constants included.
    #[test]
    fn the_shifted_solve_inverts_the_shifted_operator() {
        let op = Divergence {
            resolution: [6, 5, 7],
            cell: [1.0; 3],
            open: OpenFaces::from_names(&["y+"]).unwrap(),
            solids: None,
        };
        let cells = 6 * 5 * 7;
        let mut rng = gausmoke_core::SplitMix64::new(6);
        let b: Vec<f64> = (0..cells).map(|_| rng.range(-1.0, 1.0) as f64).collect();
        let shift = 0.03;
        let mut p = b.clone();
        SpectralSolver::new(&op).solve_shifted(&mut p, shift);
        let mut grad = vec![0.0; 3 * cells];
        op.apply_transpose(&p, &mut grad);
        let mut again = vec![0.0; cells];
        op.apply(&grad, &mut again);
        for ((x, y), p) in again.iter().zip(&b).zip(&p) {
            assert!(
                (x + shift * p - y).abs() < 1e-10,
                "{x} + {shift} {p} vs {y}"
            );
        }
    }

    /// One open face removes an axis's null direction (the constants); two open faces leave
    /// at most the collocated grid's odd-even pressure mode, which `D u` never excites. The
    /// direct solve reproduces `D u` for one open face, a pair and all six, with the faces
    /// fully open and half open.
    #[test]
    fn open_faces_are_solved_exactly() {
        for n in [5, 6] {
            for flow in [1.0, 0.5] {
                for (low, high, most) in [(flow, 0.0, 0), (0.0, flow, 0), (flow, flow, 1)] {
                    let (values, _) = symmetric_eigen(normal_matrix(n, 0.3, low, high), n);
                    let zeros = values.iter().filter(|v| v.abs() < 1e-9).count();
                    assert!(zeros <= most, "n {n}, flow {low} {high}: {values:?}");
                }
            }
        }
        for (names, flow) in [
            (&["y+"][..], 1.0),
            (&["y+"][..], 0.5),
            (&["y-", "y+"], 1.0),
            (&["y-", "y+"], 0.5),
            (&["x-", "x+", "y-", "y+", "z-", "z+"], 1.0),
            (&["x-", "x+", "y-", "y+", "z-", "z+"], 0.25),
        ] {
            let open = OpenFaces::from_names(names).unwrap().with_flow(flow);
            let op = Divergence {
                resolution: [6, 5, 7],
                cell: [0.2, 0.3, 0.25],
                open,
                solids: None,
            };
            let cells = 6 * 5 * 7;
            let mut rng = gausmoke_core::SplitMix64::new(5);
            let u: Vec<f64> = (0..3 * cells)
                .map(|_| rng.range(-1.0, 1.0) as f64)
                .collect();
            let mut b = vec![0.0; cells];
            op.apply(&u, &mut b);
            let mut p = b.clone();
            SpectralSolver::new(&op).solve(&mut p);
            let mut grad = vec![0.0; 3 * cells];
            op.apply_transpose(&p, &mut grad);
            let mut again = vec![0.0; cells];
            op.apply(&grad, &mut again);
            for (x, y) in again.iter().zip(&b) {
                assert!((x - y).abs() < 1e-9, "{names:?} {flow}: {x} vs {y}");
            }
        }
    }
}
