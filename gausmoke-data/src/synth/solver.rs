//! The small smoke solver behind the synthetic scenes: a buoyant plume from a source disc,
//! semi-Lagrangian advection, vorticity confinement, an optional swirl, Jacobi pressure
//! projection, solids.

use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use rayon::prelude::*;

use super::{SynthConfig, world_box};
use crate::error::Result;

/// A cubic grid of cell-centred values, `[z][y][x]`, x fastest.
#[derive(Debug, Clone)]
pub struct Grid {
    pub n: usize,
    pub data: Vec<f32>,
}

impl Grid {
    fn zeros(n: usize) -> Self {
        Self {
            n,
            data: vec![0.0; n * n * n],
        }
    }

    #[inline]
    fn idx(&self, x: usize, y: usize, z: usize) -> usize {
        (z * self.n + y) * self.n + x
    }

    /// Trilinear sample at grid coordinates (cell centres at integers), clamped to the box.
    pub fn sample(&self, p: Vec3) -> f32 {
        let max = (self.n - 1) as f32;
        let p = p.clamp(Vec3::ZERO, Vec3::splat(max));
        let (x0, y0, z0) = (
            p.x.floor() as usize,
            p.y.floor() as usize,
            p.z.floor() as usize,
        );
        let (x1, y1, z1) = (
            (x0 + 1).min(self.n - 1),
            (y0 + 1).min(self.n - 1),
            (z0 + 1).min(self.n - 1),
        );
        let (fx, fy, fz) = (p.x - x0 as f32, p.y - y0 as f32, p.z - z0 as f32);
        let d = &self.data;
        let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
        let c00 = lerp(d[self.idx(x0, y0, z0)], d[self.idx(x1, y0, z0)], fx);
        let c10 = lerp(d[self.idx(x0, y1, z0)], d[self.idx(x1, y1, z0)], fx);
        let c01 = lerp(d[self.idx(x0, y0, z1)], d[self.idx(x1, y0, z1)], fx);
        let c11 = lerp(d[self.idx(x0, y1, z1)], d[self.idx(x1, y1, z1)], fx);
        lerp(lerp(c00, c10, fy), lerp(c01, c11, fy), fz)
    }
}

/// Uniform in `[-1, 1)`.
fn signed(rng: &mut SplitMix64) -> f32 {
    2.0 * rng.uniform() - 1.0
}

/// State of the smoke solver (grid units: cells, velocities in cells per frame).
pub struct Solver {
    cfg: SynthConfig,
    pub density: Grid,
    pub velocity: [Grid; 3],
    /// Per cell, whether a solid fills it (cell centre inside it).
    pub solid: Vec<bool>,
    rng: SplitMix64,
}

impl Solver {
    pub fn new(cfg: &SynthConfig) -> Result<Self> {
        cfg.validate()?;
        let n = cfg.grid;
        let (lo, hi) = world_box();
        let cell = (hi - lo) / n as f32;
        let mut solid = vec![false; n * n * n];
        if !cfg.solids.is_empty() {
            for z in 0..n {
                for y in 0..n {
                    for x in 0..n {
                        let centre = lo
                            + cell * (Vec3::new(x as f32, y as f32, z as f32) + Vec3::splat(0.5));
                        solid[(z * n + y) * n + x] =
                            cfg.solids.iter().any(|s| s.shape.contains(centre));
                    }
                }
            }
        }
        Ok(Self {
            cfg: cfg.clone(),
            density: Grid::zeros(n),
            velocity: [Grid::zeros(n), Grid::zeros(n), Grid::zeros(n)],
            solid,
            rng: SplitMix64::new(cfg.seed),
        })
    }

    /// Advances one frame.
    pub fn step_frame(&mut self) {
        let dt = 1.0 / self.cfg.substeps as f32;
        for _ in 0..self.cfg.substeps {
            self.inflow(dt);
            self.add_buoyancy(dt);
            self.add_swirl(dt);
            self.confine_vorticity(dt);
            let vel = self.velocity.clone();
            for c in 0..3 {
                self.velocity[c] = advect(&vel[c], &vel, dt);
            }
            self.project();
            self.density = advect(&self.density, &self.velocity, dt);
            for (d, &solid) in self.density.data.iter_mut().zip(&self.solid) {
                if solid {
                    *d = 0.0;
                }
            }
        }
    }

    fn inflow(&mut self, dt: f32) {
        let n = self.cfg.grid;
        let nf = n as f32;
        let (cx, cz) = (0.5 * nf, 0.5 * nf);
        let radius = 0.12 * nf;
        let y_top = (0.1 * nf).ceil() as usize;
        for z in 0..n {
            for y in 1..y_top.max(2) {
                for x in 0..n {
                    let (dx, dz) = (x as f32 + 0.5 - cx, z as f32 + 0.5 - cz);
                    if dx * dx + dz * dz > radius * radius {
                        continue;
                    }
                    let i = self.density.idx(x, y, z);
                    let amount = 1.0 + self.cfg.noise * signed(&mut self.rng);
                    self.density.data[i] = self.density.data[i].max(amount);
                    self.velocity[1].data[i] = self.cfg.inflow_speed;
                    self.velocity[0].data[i] += self.cfg.noise * dt * signed(&mut self.rng);
                    self.velocity[2].data[i] += self.cfg.noise * dt * signed(&mut self.rng);
                }
            }
        }
    }

    fn add_buoyancy(&mut self, dt: f32) {
        let b = self.cfg.buoyancy * dt;
        for (v, d) in self.velocity[1].data.iter_mut().zip(&self.density.data) {
            *v += b * d;
        }
    }

    /// Relaxes the smoke's velocity about the source's vertical axis towards the solid-body
    /// rotation of [`SynthConfig::swirl_degrees`]: `u += min(d, 1) dt (omega r - u_t) t`, with
    /// `t` the unit tangent and `u_t` the velocity along it. Radial and vertical flow are left
    /// alone; the projection that follows keeps the whole divergence-free.
    fn add_swirl(&mut self, dt: f32) {
        if self.cfg.swirl_degrees == 0.0 {
            return;
        }
        let n = self.cfg.grid;
        let omega = self.cfg.swirl_degrees.to_radians();
        let centre = 0.5 * n as f32;
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let i = self.density.idx(x, y, z);
                    let weight = self.density.data[i].min(1.0) * dt;
                    if weight <= 0.0 || self.solid[i] {
                        continue;
                    }
                    let (dx, dz) = (x as f32 + 0.5 - centre, z as f32 + 0.5 - centre);
                    let r = (dx * dx + dz * dz).sqrt();
                    if r < 1e-6 {
                        continue;
                    }
                    // Counter-clockwise seen from +y: the tangent of (dx, dz) is (dz, -dx)/r.
                    let (tx, tz) = (dz / r, -dx / r);
                    let along = self.velocity[0].data[i] * tx + self.velocity[2].data[i] * tz;
                    let push = weight * (omega * r - along);
                    self.velocity[0].data[i] += push * tx;
                    self.velocity[2].data[i] += push * tz;
                }
            }
        }
    }

    /// Vorticity confinement: `f = eps * (N x omega)` with `omega = curl u` and
    /// `N = grad |omega| / |grad |omega||` (central differences, interior cells).
    fn confine_vorticity(&mut self, dt: f32) {
        let eps = self.cfg.vorticity;
        if eps == 0.0 {
            return;
        }
        let n = self.cfg.grid;
        let [u, v, w] = &self.velocity;
        let g = |f: &Grid, x: usize, y: usize, z: usize| f.data[(z * n + y) * n + x];
        let mut omega = vec![Vec3::ZERO; n * n * n];
        for z in 1..n - 1 {
            for y in 1..n - 1 {
                for x in 1..n - 1 {
                    let dwdy = 0.5 * (g(w, x, y + 1, z) - g(w, x, y - 1, z));
                    let dvdz = 0.5 * (g(v, x, y, z + 1) - g(v, x, y, z - 1));
                    let dudz = 0.5 * (g(u, x, y, z + 1) - g(u, x, y, z - 1));
                    let dwdx = 0.5 * (g(w, x + 1, y, z) - g(w, x - 1, y, z));
                    let dvdx = 0.5 * (g(v, x + 1, y, z) - g(v, x - 1, y, z));
                    let dudy = 0.5 * (g(u, x, y + 1, z) - g(u, x, y - 1, z));
                    omega[(z * n + y) * n + x] = Vec3::new(dwdy - dvdz, dudz - dwdx, dvdx - dudy);
                }
            }
        }
        let mag = |x: usize, y: usize, z: usize| omega[(z * n + y) * n + x].length();
        for z in 1..n - 1 {
            for y in 1..n - 1 {
                for x in 1..n - 1 {
                    let grad = 0.5
                        * Vec3::new(
                            mag(x + 1, y, z) - mag(x - 1, y, z),
                            mag(x, y + 1, z) - mag(x, y - 1, z),
                            mag(x, y, z + 1) - mag(x, y, z - 1),
                        );
                    let len = grad.length();
                    if len < 1e-8 {
                        continue;
                    }
                    let i = (z * n + y) * n + x;
                    let f = eps * dt * (grad / len).cross(omega[i]);
                    self.velocity[0].data[i] += f.x;
                    self.velocity[1].data[i] += f.y;
                    self.velocity[2].data[i] += f.z;
                }
            }
        }
    }

    /// Projects the velocity towards divergence-free: collocated central differences, the
    /// matching wide-stencil Poisson equation solved by Jacobi iterations, closed walls on
    /// the sides and floor (zero normal velocity, zero-gradient pressure), a half-open top
    /// (pressure 0 above it, and the divergence reads zero velocity there: a still cell past
    /// the face, `open_face_flow = 0.5` in the trainer's terms, which lets only part of the
    /// flow through); obstacle cells hold no velocity and their faces are walls like the
    /// sides. A fixed number of Jacobi iterations leaves a residual; the generator records
    /// the mean |div u| per frame.
    fn project(&mut self) {
        let n = self.cfg.grid;
        // Closed walls: zero the normal component in the boundary cells, and all of it in
        // the obstacle.
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let i = self.density.idx(x, y, z);
                    if self.solid[i] {
                        for c in 0..3 {
                            self.velocity[c].data[i] = 0.0;
                        }
                    }
                    if x == 0 || x == n - 1 {
                        self.velocity[0].data[i] = 0.0;
                    }
                    if y == 0 {
                        self.velocity[1].data[i] = 0.0;
                    }
                    if z == 0 || z == n - 1 {
                        self.velocity[2].data[i] = 0.0;
                    }
                }
            }
        }
        let [u, v, w] = &self.velocity;
        let at = |g: &Grid, x: isize, y: isize, z: isize| -> f32 {
            if x < 0 || y < 0 || z < 0 || x >= n as isize || y >= n as isize || z >= n as isize {
                0.0
            } else {
                g.data[g.idx(x as usize, y as usize, z as usize)]
            }
        };
        let mut div = vec![0.0f32; n * n * n];
        div.par_chunks_mut(n * n).enumerate().for_each(|(z, slab)| {
            for y in 0..n {
                for x in 0..n {
                    let (xi, yi, zi) = (x as isize, y as isize, z as isize);
                    slab[y * n + x] = 0.5
                        * (at(u, xi + 1, yi, zi) - at(u, xi - 1, yi, zi) + at(v, xi, yi + 1, zi)
                            - at(v, xi, yi - 1, zi)
                            + at(w, xi, yi, zi + 1)
                            - at(w, xi, yi, zi - 1));
                }
            }
        });
        let mut p = vec![0.0f32; n * n * n];
        let mut next = vec![0.0f32; n * n * n];
        let solid = &self.solid;
        // The pressure at cell (x, y, z) as the stencil of cell (xc, yc, zc) sees it:
        // zero-gradient at the walls, the floor and a neighbour inside an obstacle (the cell's
        // own value), p = 0 above the open top.
        let pressure_at =
            |p: &[f32], x: isize, y: isize, z: isize, xc: usize, yc: usize, zc: usize| -> f32 {
                let inside = |v: isize| (0..n as isize).contains(&v);
                if y >= n as isize {
                    return 0.0;
                }
                if inside(x)
                    && inside(y)
                    && inside(z)
                    && solid[(z as usize * n + y as usize) * n + x as usize]
                {
                    return p[(zc * n + yc) * n + xc];
                }
                let cx = if inside(x) { x as usize } else { xc };
                let cy = if y < 0 { yc } else { y as usize };
                let cz = if inside(z) { z as usize } else { zc };
                p[(cz * n + cy) * n + cx]
            };
        for _ in 0..self.cfg.jacobi_iterations {
            let get = |x, y, z, xc, yc, zc| pressure_at(&p, x, y, z, xc, yc, zc);
            next.par_chunks_mut(n * n)
                .enumerate()
                .for_each(|(z, slab)| {
                    for y in 0..n {
                        for x in 0..n {
                            let (xi, yi, zi) = (x as isize, y as isize, z as isize);
                            let sum = get(xi + 2, yi, zi, x, y, z)
                                + get(xi - 2, yi, zi, x, y, z)
                                + get(xi, yi + 2, zi, x, y, z)
                                + get(xi, yi - 2, zi, x, y, z)
                                + get(xi, yi, zi + 2, x, y, z)
                                + get(xi, yi, zi - 2, x, y, z);
                            // div(grad p) with the same central differences is the wide
                            // stencil (sum of p two cells away - 6 p) / 4, so the projected
                            // field is divergence-free in the sense the metric measures.
                            slab[y * n + x] = (sum - 4.0 * div[(z * n + y) * n + x]) / 6.0;
                        }
                    }
                });
            std::mem::swap(&mut p, &mut next);
        }
        let pg = |x, y, z, xc, yc, zc| pressure_at(&p, x, y, z, xc, yc, zc);
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let (xi, yi, zi) = (x as isize, y as isize, z as isize);
                    let i = (z * n + y) * n + x;
                    if solid[i] {
                        continue;
                    }
                    self.velocity[0].data[i] -=
                        0.5 * (pg(xi + 1, yi, zi, x, y, z) - pg(xi - 1, yi, zi, x, y, z));
                    self.velocity[1].data[i] -=
                        0.5 * (pg(xi, yi + 1, zi, x, y, z) - pg(xi, yi - 1, zi, x, y, z));
                    self.velocity[2].data[i] -=
                        0.5 * (pg(xi, yi, zi + 1, x, y, z) - pg(xi, yi, zi - 1, x, y, z));
                }
            }
        }
    }

    /// Mean |div u| over the interior fluid cells (central differences, cells per frame per
    /// cell).
    pub fn mean_abs_divergence(&self) -> f32 {
        let n = self.cfg.grid;
        let [u, v, w] = &self.velocity;
        let at = |g: &Grid, x: usize, y: usize, z: usize| g.data[g.idx(x, y, z)];
        let mut sum = 0.0f64;
        let mut count = 0usize;
        for z in 1..n - 1 {
            for y in 1..n - 1 {
                for x in 1..n - 1 {
                    if self.solid[(z * n + y) * n + x] {
                        continue;
                    }
                    let d = 0.5
                        * (at(u, x + 1, y, z) - at(u, x - 1, y, z) + at(v, x, y + 1, z)
                            - at(v, x, y - 1, z)
                            + at(w, x, y, z + 1)
                            - at(w, x, y, z - 1));
                    sum += d.abs() as f64;
                    count += 1;
                }
            }
        }
        (sum / count.max(1) as f64) as f32
    }
}

/// Semi-Lagrangian advection of `field` by `vel` over `dt` frames (grid units).
fn advect(field: &Grid, vel: &[Grid; 3], dt: f32) -> Grid {
    let n = field.n;
    let mut out = Grid::zeros(n);
    out.data
        .par_chunks_mut(n * n)
        .enumerate()
        .for_each(|(z, slab)| {
            for y in 0..n {
                for x in 0..n {
                    let i = (z * n + y) * n + x;
                    let v = Vec3::new(vel[0].data[i], vel[1].data[i], vel[2].data[i]);
                    let back = Vec3::new(x as f32, y as f32, z as f32) - dt * v;
                    // Above the open top nothing comes back in.
                    slab[y * n + x] = if back.y > (n - 1) as f32 + 0.5 {
                        0.0
                    } else {
                        field.sample(back)
                    };
                }
            }
        });
    out
}
