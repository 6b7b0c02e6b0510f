//! The normalised Gaussian-kernel interpolation (Eq. 11) with its Jacobian (Eq. 22), fused, on
//! host slices: the CPU twin of the kernels and what the CPU backends run. Per point, with
//! cell coordinates `c` (cell centre `(i, j, k)` at exactly `(i, j, k)`), stencil nodes `n_g`,
//! `delta_g = n_g - c` (cells), weights `w_g = exp(-|delta_g|^2 / 2 s^2)`, `p_g = w_g / W`:
//!
//! * `u = sum_g p_g u_g`;
//! * `J_ab = sum_g p_g (u_ga - u_a) k_gb / h_b` with `k_g = delta_g / s^2`.
//!
//! The backward pass is closed-form: with `kbar = sum_g p_g k_g`,
//!
//! * `dL/du_ga = p_g (ubar_a + sum_b Jbar_ab (k_gb - kbar_b) / h_b)`;
//! * `dL/dc_e = sum_a ubar_a J_ae h_e + sum_ab Jbar_ab / h_b (sum_g p_g (u_ga - u_a) k_gb
//!   (k_ge - kbar_e) - J_ae h_e kbar_b)`, and `dL/dx_e = dL/dc_e / h_e`
//!
//! (`dp_g/dc_e = p_g (k_ge - kbar_e)`, and the `dk/dc` term vanishes because
//! `sum_g p_g (u_g - u) = 0`).

use rayon::prelude::*;

/// The grid and kernel of the interpolation (plain data, so it can cross burn's dispatch).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KernelGrid {
    pub lo: [f32; 3],
    pub cell: [f32; 3],
    pub resolution: [usize; 3],
    /// Nodes per axis (4 by default).
    pub stencil: usize,
    /// Standard deviation of the kernel in cells.
    pub std_cells: f32,
}

/// Values per point of the fused op: `u` (3) then `J` row by row (9).
pub const SAMPLE_FLOATS: usize = 12;

/// One point's stencil: per node the normalised weight, `k_g` and the node's flat cell index.
struct Stencil {
    weights: Vec<f32>,
    k: Vec<[f32; 3]>,
    cells: Vec<usize>,
}

impl KernelGrid {
    fn nodes(&self) -> usize {
        self.stencil.pow(3)
    }

    fn stencil_of(&self, point: [f32; 3]) -> Stencil {
        let s = self.stencil;
        let inv_var = 1.0 / (self.std_cells * self.std_cells);
        let first = (s / 2 - 1) as f32;
        let c: [f32; 3] = [0, 1, 2].map(|a| (point[a] - self.lo[a]) / self.cell[a] - 0.5);
        let base: [usize; 3] = [0, 1, 2].map(|a| {
            (c[a].floor() - first)
                .max(0.0)
                .min((self.resolution[a] - s) as f32) as usize
        });
        let [_, ny, nz] = self.resolution;
        let mut stencil = Stencil {
            weights: Vec::with_capacity(self.nodes()),
            k: Vec::with_capacity(self.nodes()),
            cells: Vec::with_capacity(self.nodes()),
        };
        let mut dist = Vec::with_capacity(self.nodes());
        for i in 0..s {
            for j in 0..s {
                for l in 0..s {
                    let node = [base[0] + i, base[1] + j, base[2] + l];
                    let delta: [f32; 3] = [0, 1, 2].map(|a| node[a] as f32 - c[a]);
                    dist.push(delta[0] * delta[0] + delta[1] * delta[1] + delta[2] * delta[2]);
                    stencil.k.push(delta.map(|d| d * inv_var));
                    stencil.cells.push((node[0] * ny + node[1]) * nz + node[2]);
                }
            }
        }
        // Shifted by the nearest node's distance so far points do not underflow to 0/0; the
        // shift cancels in every normalised ratio.
        let nearest = dist.iter().fold(f32::INFINITY, |m, &d| m.min(d));
        stencil.weights = dist
            .iter()
            .map(|d| ((d - nearest) * (-0.5 * inv_var)).exp())
            .collect();
        let total: f32 = stencil.weights.iter().sum();
        stencil.weights.iter_mut().for_each(|w| *w /= total);
        stencil
    }
}

/// `u` and `J` of one point from its stencil.
fn evaluate(grid: &KernelGrid, stencil: &Stencil, velocity: &[f32]) -> ([f32; 3], [[f32; 3]; 3]) {
    let mut u = [0.0f32; 3];
    for (p, &cell) in stencil.weights.iter().zip(&stencil.cells) {
        for a in 0..3 {
            u[a] += p * velocity[3 * cell + a];
        }
    }
    let mut j = [[0.0f32; 3]; 3];
    for ((p, k), &cell) in stencil.weights.iter().zip(&stencil.k).zip(&stencil.cells) {
        for a in 0..3 {
            let du = p * (velocity[3 * cell + a] - u[a]);
            for b in 0..3 {
                j[a][b] += du * k[b];
            }
        }
    }
    for row in &mut j {
        for (b, value) in row.iter_mut().enumerate() {
            *value /= grid.cell[b];
        }
    }
    (u, j)
}

/// `[M, SAMPLE_FLOATS]`: `u` and `J` at every point of `points [M, 3]` of `velocity
/// [nx, ny, nz, 3]`.
pub fn forward(grid: &KernelGrid, velocity: &[f32], points: &[f32]) -> Vec<f32> {
    check(grid, velocity);
    points
        .par_chunks(3)
        .flat_map_iter(|point| {
            let stencil = grid.stencil_of([point[0], point[1], point[2]]);
            let (u, j) = evaluate(grid, &stencil, velocity);
            u.into_iter().chain(j.into_iter().flatten())
        })
        .collect()
}

fn check(grid: &KernelGrid, velocity: &[f32]) {
    assert!(
        grid.resolution.iter().all(|&n| n >= grid.stencil) && grid.stencil >= 2,
        "every axis must hold the {}-node stencil",
        grid.stencil
    );
    assert_eq!(
        velocity.len(),
        3 * grid.resolution.iter().product::<usize>(),
        "velocity must be [nx, ny, nz, 3]"
    );
}

/// Points per fixed chunk of the backward pass: each chunk adds into its own copy of the grid
/// gradient, and the copies are summed in chunk order, so the result does not depend on
/// scheduling.
const CHUNKS: usize = 8;

/// Gradients `(velocity [nx, ny, nz, 3], points [M, 3])` given `grad [M, SAMPLE_FLOATS]`.
pub fn backward(
    grid: &KernelGrid,
    velocity: &[f32],
    points: &[f32],
    grad: &[f32],
) -> (Vec<f32>, Vec<f32>) {
    check(grid, velocity);
    let m = points.len() / 3;
    assert_eq!(grad.len(), m * SAMPLE_FLOATS, "gradient must be [M, 12]");
    let chunk = m.div_ceil(CHUNKS).max(1);
    let partial: Vec<(Vec<f32>, Vec<f32>)> = (0..m)
        .step_by(chunk)
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|start| {
            let mut grad_velocity = vec![0.0f32; velocity.len()];
            let mut grad_points = Vec::with_capacity(3 * chunk);
            for i in start..(start + chunk).min(m) {
                let g = &grad[SAMPLE_FLOATS * i..SAMPLE_FLOATS * (i + 1)];
                let stencil =
                    grid.stencil_of([points[3 * i], points[3 * i + 1], points[3 * i + 2]]);
                grad_points.extend(point_backward(
                    grid,
                    &stencil,
                    velocity,
                    g,
                    &mut grad_velocity,
                ));
            }
            (grad_velocity, grad_points)
        })
        .collect();
    let mut grad_velocity = vec![0.0f32; velocity.len()];
    let mut grad_points = Vec::with_capacity(3 * m);
    for (part, points) in partial {
        grad_velocity
            .iter_mut()
            .zip(part)
            .for_each(|(total, v)| *total += v);
        grad_points.extend(points);
    }
    (grad_velocity, grad_points)
}

/// One point's backward: adds into `grad_velocity`, returns the point's gradient.
fn point_backward(
    grid: &KernelGrid,
    stencil: &Stencil,
    velocity: &[f32],
    g: &[f32],
    grad_velocity: &mut [f32],
) -> [f32; 3] {
    let (u, j) = evaluate(grid, stencil, velocity);
    let h = grid.cell;
    let ubar = [g[0], g[1], g[2]];
    let jbar = [[g[3], g[4], g[5]], [g[6], g[7], g[8]], [g[9], g[10], g[11]]];
    let mut kbar = [0.0f32; 3];
    for (p, k) in stencil.weights.iter().zip(&stencil.k) {
        for b in 0..3 {
            kbar[b] += p * k[b];
        }
    }
    // sum_g p_g (u_ga - u_a) k_gb (k_ge - kbar_e), [a][b][e].
    let mut second = [[[0.0f32; 3]; 3]; 3];
    for ((p, k), &cell) in stencil.weights.iter().zip(&stencil.k).zip(&stencil.cells) {
        for a in 0..3 {
            let du = p * (velocity[3 * cell + a] - u[a]);
            // Grid gradient of this node, channel a.
            let mut gu = ubar[a];
            for b in 0..3 {
                gu += jbar[a][b] * (k[b] - kbar[b]) / h[b];
                for e in 0..3 {
                    second[a][b][e] += du * k[b] * (k[e] - kbar[e]);
                }
            }
            grad_velocity[3 * cell + a] += p * gu;
        }
    }
    let mut grad_c = [0.0f32; 3];
    for e in 0..3 {
        let mut total = 0.0f32;
        for a in 0..3 {
            total += ubar[a] * j[a][e] * h[e];
            for b in 0..3 {
                total += jbar[a][b] / h[b] * (second[a][b][e] - j[a][e] * h[e] * kbar[b]);
            }
        }
        grad_c[e] = total;
    }
    [0, 1, 2].map(|e| grad_c[e] / h[e])
}
