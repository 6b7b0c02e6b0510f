//! Density of the Gaussians sampled at the grid's cell centres (paper Sec. 4.2):
//! `sigma_grid(x) = sum_i sigma_i k_i(x)`, `k_i(x) = exp(-|S^-1 R^T (x - mu_i)|^2 / 2)`,
//! evaluated only inside each Gaussian's `cutoff` support (`|.|^2 <= 9`: 3 sigma).
//!
//! Host implementation over flat slices (shared by the CPU backends, and the twin the kernels
//! are tested against), with the backward pass to means, quaternions, log-scales and raw
//! densities. It uses the renderer's whitening of a Gaussian (`L = S^-1 R^T`, in the world
//! frame: no rotation, origin at zero) and its chain rule [`gausmoke_render::math::view_vjp`],
//! so both ops differentiate the same parameterisation.

// Small fixed loops index several 3-vectors and matrices at once; an index reads best.
#![allow(clippy::needless_range_loop)]

use gausmoke_render::math::{ViewSplat, dot3, view_vjp};
use gausmoke_render::{Gaussian, GaussianSlices, HostGaussians};
use rayon::prelude::*;

/// The world frame as a viewer: no rotation (the origin is at zero).
const WORLD: [[f32; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Which of the two fields an op evaluates.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DensityField {
    /// `sigma_grid`, `[nx, ny, nz]`.
    Density,
    /// `grad sigma_grid`, `[nx, ny, nz, 3]` (per world unit).
    SpatialGradient,
    /// Both in one pass, `[nx, ny, nz, 4]`: `sigma` then its gradient.
    Both,
}

impl DensityField {
    /// Whether the field holds the density (its channel 0).
    pub fn has_density(self) -> bool {
        self != DensityField::SpatialGradient
    }

    /// Whether the field holds the spatial gradient (its last three channels).
    pub fn has_gradient(self) -> bool {
        self != DensityField::Density
    }

    /// Values per cell.
    pub fn channels(self) -> usize {
        usize::from(self.has_density()) + 3 * usize::from(self.has_gradient())
    }

    /// The field's tensor shape on `grid`.
    pub fn shape(self, grid: &SplatGrid) -> Vec<usize> {
        let mut shape = grid.resolution.to_vec();
        if self != DensityField::Density {
            shape.push(self.channels());
        }
        shape
    }
}

/// Grid geometry for the op: `resolution` cells over a box starting at `lo`, cell `cell`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplatGrid {
    pub lo: [f32; 3],
    pub cell: [f32; 3],
    pub resolution: [usize; 3],
    /// Squared Mahalanobis radius of the support (9 = 3 sigma).
    pub cutoff: f32,
}

impl SplatGrid {
    pub fn cells(&self) -> usize {
        self.resolution.iter().product()
    }

    fn centre(&self, i: usize, a: usize) -> f32 {
        self.lo[a] + (i as f32 + 0.5) * self.cell[a]
    }

    /// Cell index range per axis of the box `mean +- sqrt(cutoff) * max_scale` (the support
    /// is inside it), or `None` when it misses the grid.
    fn support(&self, mean: [f32; 3], radius: f32) -> Option<[(usize, usize); 3]> {
        let mut out = [(0, 0); 3];
        for a in 0..3 {
            let lo = ((mean[a] - radius - self.lo[a]) / self.cell[a] - 0.5)
                .ceil()
                .max(0.0);
            let hi = ((mean[a] + radius - self.lo[a]) / self.cell[a] - 0.5)
                .floor()
                .min(self.resolution[a] as f32 - 1.0);
            if lo.is_nan() || hi.is_nan() || lo > hi {
                return None;
            }
            out[a] = (lo as usize, hi as usize + 1);
        }
        Some(out)
    }
}

/// Calls `visit(flat_cell, whitened_offset)` for every cell centre inside the support of the
/// Gaussian whose whitening (camera at the origin) is `splat`.
fn for_each_cell(
    grid: &SplatGrid,
    g: &Gaussian,
    splat: &ViewSplat,
    mut visit: impl FnMut(usize, [f32; 3], [f32; 3]),
) {
    let radius = grid.cutoff.sqrt() * g.log_scale.iter().fold(f32::MIN, |m, &s| m.max(s)).exp();
    let Some(range) = grid.support(g.mean, radius) else {
        return;
    };
    let [_, ny, nz] = grid.resolution;
    let l = &splat.whiten;
    for i in range[0].0..range[0].1 {
        let x = grid.centre(i, 0);
        for j in range[1].0..range[1].1 {
            let y = grid.centre(j, 1);
            for k in range[2].0..range[2].1 {
                let p = [x, y, grid.centre(k, 2)];
                // m = L x - L mu: the whitened offset of the cell centre.
                let m = [
                    dot3(l[0], p) - splat.center[0],
                    dot3(l[1], p) - splat.center[1],
                    dot3(l[2], p) - splat.center[2],
                ];
                if dot3(m, m) <= grid.cutoff {
                    visit((i * ny + j) * nz + k, p, m);
                }
            }
        }
    }
}

/// Sums, over all Gaussians in parallel, `cell_value(splat, m, out)` into the `channels`
/// values of every cell inside each Gaussian's support (`m`: whitened offset of the centre).
fn accumulate_field(
    gaussians: &GaussianSlices,
    grid: &SplatGrid,
    channels: usize,
    cell_value: impl Fn(&ViewSplat, [f32; 3], &mut [f32]) + Sync,
) -> Vec<f32> {
    // Fixed chunks of Gaussians, each summed in order into its own buffer, then the buffers
    // summed in chunk order: the result does not depend on rayon's work stealing, so a run
    // (and a resumed run) is bit-for-bit reproducible.
    const CHUNKS: usize = 16;
    let len = channels * grid.cells();
    let n = gaussians.len();
    let chunk = n.div_ceil(CHUNKS).max(1);
    let partials: Vec<Vec<f32>> = (0..n)
        .step_by(chunk)
        .collect::<Vec<_>>()
        .into_par_iter()
        .map(|start| {
            let mut acc = vec![0.0f32; len];
            for i in start..(start + chunk).min(n) {
                let g = gaussians.get(i);
                let (splat, _) = g.view(&WORLD, [0.0; 3]);
                for_each_cell(grid, &g, &splat, |c, _, m| {
                    cell_value(&splat, m, &mut acc[channels * c..channels * (c + 1)]);
                });
            }
            acc
        })
        .collect();
    let mut out = vec![0.0f32; len];
    out.par_chunks_mut(4096)
        .enumerate()
        .for_each(|(block, values)| {
            let offset = block * 4096;
            for partial in &partials {
                let part = &partial[offset..offset + values.len()];
                values.iter_mut().zip(part).for_each(|(x, y)| *x += y);
            }
        });
    out
}

/// Gradient of a loss with respect to one Gaussian's whitening `L`, whitened centre `L mu`
/// and density `sigma`, accumulated cell by cell.
#[derive(Debug, Default)]
struct WhitenedGrad {
    whiten: [[f32; 3]; 3],
    center: [f32; 3],
    sigma: f32,
}

impl WhitenedGrad {
    /// Adds `dLoss/dm` for the cell at `p` (through `m = L p - L mu`).
    fn add_offset_grad(&mut self, grad_m: [f32; 3], p: [f32; 3]) {
        for r in 0..3 {
            for col in 0..3 {
                self.whiten[r][col] += grad_m[r] * p[col];
            }
            self.center[r] -= grad_m[r];
        }
    }
}

/// Per Gaussian in parallel: `cell_grad(splat, cell, p, m, grad)` accumulates the cell's
/// contribution, then [`view_vjp`] chains it back to the world-space parameters. Returns the
/// gradient of every attribute (zero for the colours, which splatting does not read).
fn gaussian_gradients(
    gaussians: &GaussianSlices,
    grid: &SplatGrid,
    cell_grad: impl Fn(&ViewSplat, usize, [f32; 3], [f32; 3], &mut WhitenedGrad) + Sync,
) -> HostGaussians {
    let grads: Vec<_> = (0..gaussians.len())
        .into_par_iter()
        .map(|i| {
            let g = gaussians.get(i);
            let (splat, ctx) = g.view(&WORLD, [0.0; 3]);
            let mut acc = WhitenedGrad::default();
            for_each_cell(grid, &g, &splat, |c, p, m| {
                cell_grad(&splat, c, p, m, &mut acc)
            });
            view_vjp(
                &g,
                &ctx,
                &WORLD,
                &acc.whiten,
                acc.center,
                acc.sigma,
                [0.0; 3],
            )
        })
        .collect();
    let mut out = HostGaussians::with_capacity(grads.len());
    for g in &grads {
        out.push(g);
    }
    out
}

/// `field` of the Gaussians, `[cells * field.channels()]` in the grid's flat order: the
/// density `sum_i sigma_i k_i(x)` and/or its analytic spatial gradient
/// `sum_i sigma_i k_i(x) (-Sigma_i^-1 (x - mu_i))`, with `Sigma^-1 (x - mu) = L^T m`.
pub fn splat_field_forward(
    gaussians: &GaussianSlices,
    grid: &SplatGrid,
    field: DensityField,
) -> Vec<f32> {
    let offset = usize::from(field.has_density());
    accumulate_field(gaussians, grid, field.channels(), |splat, m, out| {
        let density = splat.sigma * (-0.5 * dot3(m, m)).exp();
        if field.has_density() {
            out[0] += density;
        }
        if field.has_gradient() {
            let l = &splat.whiten;
            let weight = -density;
            for a in 0..3 {
                out[offset + a] += weight * (l[0][a] * m[0] + l[1][a] * m[1] + l[2][a] * m[2]);
            }
        }
    })
}

/// Gradients of every attribute of [`splat_field_forward`] given the gradient of its output
/// (`[cells * field.channels()]`).
///
/// Density channel: `d(sigma k)/dm = -sigma k m`, `d(sigma k)/dsigma = k`. Gradient channels:
/// per cell the output is `f = -sigma k m.(L g)` for upstream `g`; with `v = L g`, `s = m.v`:
/// `df/dm = sigma k (s m - v)`, `df/dL = -sigma k m g^T` directly plus `(df/dm) x^T` through
/// `m = L x - L mu`, and `df/dsigma = -k s`.
pub fn splat_field_backward(
    gaussians: &GaussianSlices,
    grid: &SplatGrid,
    field: DensityField,
    grad_field: &[f32],
) -> HostGaussians {
    let channels = field.channels();
    assert_eq!(
        grad_field.len(),
        channels * grid.cells(),
        "gradient must be [cells, {channels}]"
    );
    let offset = usize::from(field.has_density());
    gaussian_gradients(gaussians, grid, |splat, c, p, m, acc| {
        let kernel = (-0.5 * dot3(m, m)).exp();
        let mut grad_m = [0.0f32; 3];
        if field.has_density() {
            let up = grad_field[channels * c];
            acc.sigma += up * kernel;
            let scale = -up * splat.sigma * kernel;
            grad_m = [scale * m[0], scale * m[1], scale * m[2]];
        }
        if field.has_gradient() {
            let l = &splat.whiten;
            let base = channels * c + offset;
            let up = [grad_field[base], grad_field[base + 1], grad_field[base + 2]];
            let v = [dot3(l[0], up), dot3(l[1], up), dot3(l[2], up)];
            let s = dot3(m, v);
            acc.sigma -= kernel * s;
            let sk = splat.sigma * kernel;
            for r in 0..3 {
                for col in 0..3 {
                    acc.whiten[r][col] -= sk * m[r] * up[col];
                }
                grad_m[r] += sk * (s * m[r] - v[r]);
            }
        }
        acc.add_offset_grad(grad_m, p);
    })
}

/// `sigma_grid`, `[nx * ny * nz]`.
pub fn splat_forward(gaussians: &GaussianSlices, grid: &SplatGrid) -> Vec<f32> {
    splat_field_forward(gaussians, grid, DensityField::Density)
}

/// Gradients of every attribute given `dLoss/dsigma_grid`.
pub fn splat_backward(
    gaussians: &GaussianSlices,
    grid: &SplatGrid,
    grad_grid: &[f32],
) -> HostGaussians {
    splat_field_backward(gaussians, grid, DensityField::Density, grad_grid)
}

/// Analytic spatial gradient `grad sigma_grid`, `[nx * ny * nz * 3]`.
pub fn splat_gradient_forward(gaussians: &GaussianSlices, grid: &SplatGrid) -> Vec<f32> {
    splat_field_forward(gaussians, grid, DensityField::SpatialGradient)
}

/// Gradients of every attribute of [`splat_gradient_forward`] given `dLoss/d(grad sigma)`.
pub fn splat_gradient_backward(
    gaussians: &GaussianSlices,
    grid: &SplatGrid,
    grad_field: &[f32],
) -> HostGaussians {
    splat_field_backward(gaussians, grid, DensityField::SpatialGradient, grad_field)
}
