//! Synthetic smoke scenes with ground truth (issue 7, item 2).
//!
//! A small 3D smoke solver (buoyant plume from a source disc near the floor, semi-Lagrangian
//! advection with trilinear sampling, vorticity confinement, pressure projection by Jacobi
//! iterations, seeded inflow noise) is rendered from cameras on an arc by an independent Beer-Lambert ray
//! marcher (not the Gaussian renderer), and written as a PINF / HyFluid data set:
//! `info.json`, one folder of PNG frames per camera (`view00/000.png`, ...), and the ground
//! truth per frame in `gt/frame_000.safetensors` (`density` `[n, n, n]` and `velocity`
//! `[n, n, n, 3]`, index order `[z][y][x]` with x fastest, cell centres at
//! `sim = (i + 0.5) / n`; velocity in world units per frame).
//!
//! World: the smoke box is `[-0.5, 0.5] x [0, 1] x [-0.5, 0.5]` (y up), written as
//! `voxel_scale = 1` and a `voxel_matrix` that becomes `[I | (-0.5, 0, -0.5)]` after the
//! PINF column swap. Cameras look at the box centre from a circle of radius
//! [`SynthConfig::camera_distance`] in the horizontal plane through it, spread over
//! [`SynthConfig::arc_degrees`] centred on +Z. The middle camera is the test view.
//!
//! Rendering (emission-absorption, grey smoke of albedo 1, [`SynthConfig::background`]): along each
//! pixel-centre ray, `sigma = density_scale * density`, `L = sum T_k (1 - exp(-sigma_k ds))`,
//! `T_{k+1} = T_k exp(-sigma_k ds)`, step `ds` = half a cell, pixel = `L + T * background`.
//! PNGs store it in 8 bits, so loaded pixels match the marcher to 0.5/255.
//!
//! Optional solids ([`SynthConfig::solids`], spheres and axis-aligned boxes) are solid in the
//! solver: their cells hold no velocity and no smoke, and the pressure solve treats their
//! faces as walls. Unless [`SynthSolid::visible`], a solid is not drawn (the renders show only
//! smoke), so what a reconstruction puts inside it is leaked smoke; a visible one is opaque,
//! lit from `(0.3, 1, 0.5)` plus 0.3 ambient, and checkered in albedos 0.35 and 0.75 (a sphere
//! in 8 x 4 tiles of longitude and latitude, a box in squares of [`BOX_TILE`] world units on
//! each face), and the smoke in front of it is composited over it. `info.json` describes every
//! solid under `obstacles` in world units.
//!
//! Nothing is partially written: the scene is built in a sibling `.partial` folder and
//! renamed into place at the end; an existing non-empty output folder is refused.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use gausmoke_core::glam::{Mat4, Vec3};
use gausmoke_core::{Camera, SplitMix64};
use rayon::prelude::*;
use serde_json::json;

use crate::dataset::Obstacle;
use crate::error::{DataError, Result, io_err};
use crate::image::Image;

/// Side of a box's checker squares, in world units (six across the unit box).
pub const BOX_TILE: f32 = 1.0 / 6.0;

/// Scene and solver settings.
#[derive(Debug, Clone, PartialEq)]
pub struct SynthConfig {
    /// Cells per axis of the cubic grid.
    pub grid: usize,
    pub views: usize,
    pub frames: usize,
    pub width: u32,
    pub height: u32,
    pub seed: u64,
    /// Solver substeps per frame.
    pub substeps: usize,
    /// Jacobi iterations per pressure solve.
    pub jacobi_iterations: usize,
    /// Upward acceleration per unit density, in cells per frame^2.
    pub buoyancy: f32,
    /// Upward inflow speed at the source, in cells per frame.
    pub inflow_speed: f32,
    /// Relative amplitude of the seeded inflow noise (density and horizontal velocity).
    pub noise: f32,
    /// Vorticity confinement strength (Fedkiw et al. 2001), in cells; 0 disables it.
    pub vorticity: f32,
    /// Extinction per unit density per world unit.
    pub density_scale: f32,
    pub camera_distance: f32,
    pub arc_degrees: f32,
    /// Horizontal field of view, radians.
    pub fov_x: f32,
    /// Solids in the box (world units).
    pub solids: Vec<SynthSolid>,
    /// Linear RGB behind the box.
    pub background: [f32; 3],
    pub layout: SynthLayout,
}

/// How a scene is written.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SynthLayout {
    /// PINF / HyFluid: `info.json` and a folder of RGB frames per camera.
    Pinf,
    /// Blender-style multi-view D-NeRF: `transforms_train.json` (with our `aabb` and
    /// `obstacles`) and `transforms_test.json` (the middle camera), one line per camera and
    /// time (`time` from 0 to 1), straight-alpha RGBA frames whose transparent background is
    /// [`SynthConfig::background`] only once composited (the D-NeRF loader composites over
    /// black unless told otherwise).
    Blender,
}

/// A solid in world units (see [`world_box`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SynthSolid {
    pub shape: Obstacle,
    /// Drawn, opaque and textured (else only its effect on the smoke shows).
    pub visible: bool,
}

impl SynthSolid {
    /// The ray parameter where `origin + t dir` (unit `dir`, `origin` outside) first enters
    /// the solid.
    fn hit(&self, origin: Vec3, dir: Vec3) -> Option<f32> {
        let entry = match self.shape {
            Obstacle::Sphere { centre, radius } => {
                let offset = origin - centre;
                let b = offset.dot(dir);
                let c = offset.length_squared() - radius * radius;
                let discriminant = b * b - c;
                (discriminant >= 0.0).then(|| -b - discriminant.sqrt())
            }
            Obstacle::Box { min, max } => {
                let (near, far) = slab_interval(origin, dir, min, max);
                (near <= far).then_some(near)
            }
        };
        entry.filter(|&t| t > 0.0)
    }

    /// The lit, textured colour of the surface point `p` (see the module's notes).
    fn shade(&self, p: Vec3) -> f32 {
        let n = self.shape.outward_normal(p);
        let tile = match self.shape {
            Obstacle::Sphere { .. } => {
                let longitude = n.z.atan2(n.x);
                let latitude = n.y.clamp(-1.0, 1.0).asin();
                (longitude / std::f32::consts::TAU * 8.0).floor()
                    + (latitude / std::f32::consts::PI * 4.0).floor()
            }
            Obstacle::Box { .. } => {
                // The two coordinates along the face (the normal's axis left out).
                let across = p / BOX_TILE;
                let along = if n.x.abs() > 0.5 {
                    (across.y, across.z)
                } else if n.y.abs() > 0.5 {
                    (across.x, across.z)
                } else {
                    (across.x, across.y)
                };
                along.0.floor() + along.1.floor()
            }
        };
        let albedo = if (tile as i32).rem_euclid(2) == 0 {
            0.35
        } else {
            0.75
        };
        let light = Vec3::new(0.3, 1.0, 0.5).normalize();
        albedo * (0.3 + 0.7 * n.dot(light).max(0.0))
    }
}

/// Where the line `origin + t dir` enters and leaves the axis-aligned box `[lo, hi]` (it
/// misses when the first exceeds the second).
fn slab_interval(origin: Vec3, dir: Vec3, lo: Vec3, hi: Vec3) -> (f32, f32) {
    let (mut near, mut far) = (f32::NEG_INFINITY, f32::INFINITY);
    for a in 0..3 {
        let inv = 1.0 / dir[a];
        let (ta, tb) = ((lo[a] - origin[a]) * inv, (hi[a] - origin[a]) * inv);
        near = near.max(ta.min(tb));
        far = far.min(ta.max(tb));
    }
    (near, far)
}

impl SynthConfig {
    /// 24^3, 3 views, 8 frames at 64x96: for tests.
    pub fn tiny() -> Self {
        Self {
            grid: 24,
            views: 3,
            frames: 8,
            width: 64,
            height: 96,
            seed: 7,
            substeps: 2,
            jacobi_iterations: 40,
            // Fast enough that the plume crosses most of the box in 8 frames, so a few-frame
            // training run sees real motion.
            buoyancy: 0.4,
            inflow_speed: 2.0,
            noise: 0.3,
            vorticity: 0.3,
            density_scale: 5.0,
            camera_distance: 2.0,
            arc_degrees: 120.0,
            fov_x: 0.75,
            solids: Vec::new(),
            background: [0.0; 3],
            layout: SynthLayout::Pinf,
        }
    }

    /// ScalarFlow-sized: 64^3, 5 views over 120 degrees, 120 frames at 270x480.
    pub fn scalarflow() -> Self {
        Self {
            grid: 64,
            views: 5,
            frames: 120,
            width: 270,
            height: 480,
            substeps: 2,
            jacobi_iterations: 80,
            buoyancy: 0.08,
            inflow_speed: 1.0,
            ..Self::tiny()
        }
    }

    /// The drift test (issue 18): 32^3, 5 views, 72 frames at 64x96. The plume reaches the
    /// top within the first third and then leaves through it while the source keeps feeding
    /// it, so most frames hold smoke that entered after frame 0 and smoke is lost through
    /// the top: what a fixed set of advected Gaussians cannot follow.
    pub fn long_plume() -> Self {
        Self {
            grid: 32,
            views: 5,
            frames: 72,
            buoyancy: 0.2,
            inflow_speed: 1.0,
            ..Self::tiny()
        }
    }

    /// The obstacle test (issue 20): the long plume's settings for 48 frames, with a solid
    /// sphere of radius 0.14 a little off the source's axis at 0.4 height, so the plume splits
    /// around it and flows past on one side more than the other.
    pub fn obstacle_plume() -> Self {
        Self {
            frames: 48,
            solids: vec![SynthSolid {
                shape: Obstacle::Sphere {
                    centre: Vec3::new(0.04, 0.4, 0.0),
                    radius: 0.14,
                },
                visible: false,
            }],
            ..Self::long_plume()
        }
    }

    /// The static-primitives test (issue 20): the obstacle plume with the sphere drawn as a
    /// textured ball, over a grey-blue background.
    pub fn ball_plume() -> Self {
        let obstacle = Self::obstacle_plume();
        Self {
            solids: obstacle
                .solids
                .iter()
                .map(|solid| SynthSolid {
                    visible: true,
                    ..*solid
                })
                .collect(),
            background: [0.12, 0.14, 0.18],
            ..obstacle
        }
    }

    /// Boxes and a textured backdrop (issue 20): the obstacle plume's settings with a block
    /// in the plume's way, off its axis so most of the smoke passes on one side, and a wall
    /// across the back of the box that every camera sees behind the smoke; both drawn
    /// checkered, over the grey-blue background. Static primitives have to carry the wall's
    /// texture, seen through varying smoke, for the smoke to be fitted where it passes in
    /// front of it.
    pub fn blocks_plume() -> Self {
        Self {
            solids: vec![
                SynthSolid {
                    shape: Obstacle::Box {
                        min: Vec3::new(-0.04, 0.36, -0.12),
                        max: Vec3::new(0.2, 0.46, 0.12),
                    },
                    visible: true,
                },
                SynthSolid {
                    shape: Obstacle::Box {
                        min: Vec3::new(-0.5, 0.0, -0.5),
                        max: Vec3::new(0.5, 1.0, -0.42),
                    },
                    visible: true,
                },
            ],
            ..Self::ball_plume()
        }
    }

    /// The blocks scene as a Blender-style multi-view set (issue 20, the paper's synthetic
    /// scenes: "fewer than 15 viewpoints and more than 120 frames at a resolution of
    /// 800x800"): a 64^3 solver grid, 12 cameras 15 degrees apart on the half ring in front
    /// of the wall (the middle one held out), 120 frames at 800x800, D-NeRF files.
    pub fn blender_blocks() -> Self {
        Self {
            views: 12,
            width: 800,
            height: 800,
            arc_degrees: 165.0,
            layout: SynthLayout::Blender,
            solids: Self::blocks_plume().solids,
            background: Self::blocks_plume().background,
            ..Self::scalarflow()
        }
    }

    fn validate(&self) -> Result<()> {
        let bad = |option: &'static str, reason: String| Err(DataError::Options { option, reason });
        if !(4..=512).contains(&self.grid) {
            return bad(
                "grid",
                format!("{} cells per axis, expected 4..=512", self.grid),
            );
        }
        if self.layout == SynthLayout::Blender && self.views < 2 {
            return bad(
                "views",
                "the Blender layout holds one camera out: at least 2".into(),
            );
        }
        if self.views == 0 || self.frames == 0 || self.substeps == 0 {
            return bad("views/frames/substeps", "must be at least 1".into());
        }
        if self.width == 0 || self.height == 0 {
            return bad("width/height", "empty image".into());
        }
        let finite = [
            self.vorticity,
            self.buoyancy,
            self.inflow_speed,
            self.noise,
            self.density_scale,
            self.camera_distance,
            self.arc_degrees,
            self.fov_x,
        ];
        if finite.iter().any(|v| !v.is_finite()) {
            return bad("config", "non-finite value".into());
        }
        if self.background.iter().any(|v| !(0.0..=1.0).contains(v)) {
            return bad("background", "3 values in [0, 1]".into());
        }
        let (lo, hi) = world_box();
        for (k, solid) in self.solids.iter().enumerate() {
            let (min, max, volume) = solid.shape.bounds();
            let inside = (0..3).all(|a| min[a] >= lo[a] && max[a] <= hi[a]);
            if !(volume > 0.0 && min.is_finite() && max.is_finite() && inside) {
                return bad(
                    "solids",
                    format!("solid {k} ({:?}): not a solid inside the box", solid.shape),
                );
            }
        }
        if self.camera_distance <= 1.0 {
            return bad(
                "camera_distance",
                "cameras must stay outside the unit box (> 1)".into(),
            );
        }
        Ok(())
    }
}

/// The smoke box in world space and the map from the unit simulation cube to it.
pub fn world_box() -> (Vec3, Vec3) {
    (Vec3::new(-0.5, 0.0, -0.5), Vec3::new(0.5, 1.0, 0.5))
}

/// The cameras of a configuration (index order = view order).
pub fn cameras(cfg: &SynthConfig) -> Result<Vec<Camera>> {
    let (lo, hi) = world_box();
    let centre = 0.5 * (lo + hi);
    (0..cfg.views)
        .map(|k| {
            let a = if cfg.views == 1 {
                0.0
            } else {
                (k as f32 / (cfg.views - 1) as f32 - 0.5) * cfg.arc_degrees.to_radians()
            };
            let eye = centre + cfg.camera_distance * Vec3::new(a.sin(), 0.0, a.cos());
            Camera::look_at(eye, centre, Vec3::Y, cfg.width, cfg.height, cfg.fov_x).map_err(|e| {
                DataError::Options {
                    option: "cameras",
                    reason: e.to_string(),
                }
            })
        })
        .collect()
}

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
    /// the sides and floor (zero normal velocity, zero-gradient pressure), open top
    /// (pressure 0 above); obstacle cells hold no velocity and their faces are walls like
    /// the sides. A fixed number of Jacobi iterations leaves a residual; the generator records
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
        // A neighbour inside the obstacle mirrors the cell (zero gradient, as at the walls).
        let solid_at = |x: isize, y: isize, z: isize| -> bool {
            x >= 0
                && y >= 0
                && z >= 0
                && x < n as isize
                && y < n as isize
                && z < n as isize
                && solid[(z as usize * n + y as usize) * n + x as usize]
        };
        for _ in 0..self.cfg.jacobi_iterations {
            let pr = &p;
            let get = |x: isize, y: isize, z: isize, xc: usize, yc: usize, zc: usize| -> f32 {
                // Zero-gradient at walls and floor, p = 0 above the open top.
                if y >= n as isize {
                    return 0.0;
                }
                if solid_at(x, y, z) {
                    return pr[(zc * n + yc) * n + xc];
                }
                let cx = if x < 0 || x >= n as isize {
                    xc
                } else {
                    x as usize
                };
                let cy = if y < 0 { yc } else { y as usize };
                let cz = if z < 0 || z >= n as isize {
                    zc
                } else {
                    z as usize
                };
                pr[(cz * n + cy) * n + cx]
            };
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
        let pg = |x: isize, y: isize, z: isize, xc: usize, yc: usize, zc: usize| -> f32 {
            if y >= n as isize {
                return 0.0;
            }
            if solid_at(x, y, z) {
                return p[(zc * n + yc) * n + xc];
            }
            let cx = if x < 0 || x >= n as isize {
                xc
            } else {
                x as usize
            };
            let cy = if y < 0 { yc } else { y as usize };
            let cz = if z < 0 || z >= n as isize {
                zc
            } else {
                z as usize
            };
            p[(cz * n + cy) * n + cx]
        };
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

/// Beer-Lambert emission-absorption ray marcher over a density grid filling the world box:
/// the picture over `background`.
pub fn render(
    density: &Grid,
    camera: &Camera,
    density_scale: f32,
    background: [f32; 3],
    solids: &[SynthSolid],
) -> Result<Image> {
    let (light, reach) = march(density, camera, density_scale, solids)?;
    let data = light
        .data()
        .chunks(3)
        .zip(&reach)
        .flat_map(|(rgb, &t)| (0..3).map(move |c| rgb[c] + t * background[c]))
        .collect();
    image_of(camera, data)
}

/// [`render`] as straight-alpha RGBA, as Blender writes a transparent background: alpha is
/// the share of the background a pixel hides (1 wherever a visible solid is hit), the colour
/// what lies in front of the background divided by it, so that compositing over
/// `background` gives [`render`]'s picture.
pub fn render_rgba(
    density: &Grid,
    camera: &Camera,
    density_scale: f32,
    solids: &[SynthSolid],
) -> Result<(Image, Vec<f32>)> {
    let (light, reach) = march(density, camera, density_scale, solids)?;
    let alpha: Vec<f32> = reach.iter().map(|t| 1.0 - t).collect();
    let data = light
        .data()
        .chunks(3)
        .zip(&alpha)
        .flat_map(|(rgb, &a)| {
            (0..3).map(move |c| if a > 0.0 { (rgb[c] / a).min(1.0) } else { 0.0 })
        })
        .collect();
    Ok((image_of(camera, data)?, alpha))
}

fn image_of(camera: &Camera, data: Vec<f32>) -> Result<Image> {
    Image::from_vec(camera.width(), camera.height(), data).ok_or_else(|| DataError::Options {
        option: "camera",
        reason: "empty image".into(),
    })
}

/// The marcher: per pixel, the light in front of the background (smoke emission, and the
/// nearest visible solid's shade seen through the smoke) and the transmittance to the
/// background (0 where a visible solid is hit).
fn march(
    density: &Grid,
    camera: &Camera,
    density_scale: f32,
    solids: &[SynthSolid],
) -> Result<(Image, Vec<f32>)> {
    let (lo, hi) = world_box();
    let n = density.n as f32;
    let cell = (hi - lo) / n;
    let ds = 0.5 * cell.min_element();
    let (w, h) = (camera.width() as usize, camera.height() as usize);
    let c2w = camera.camera_to_world();
    let origin = camera.position();
    let mut data = vec![0.0f32; w * h * 3];
    let mut reach = vec![0.0f32; w * h];
    data.par_chunks_mut(w * 3)
        .zip(reach.par_chunks_mut(w))
        .enumerate()
        .for_each(|(j, (row, row_reach))| {
            for i in 0..w {
                let d_cam = camera.ray_direction_camera(i as f32 + 0.5, j as f32 + 0.5);
                let dir = c2w.transform_vector3(d_cam).normalize();
                let (t0, mut t1) = slab_interval(origin, dir, lo, hi);
                let t0 = t0.max(0.0);
                let (mut light, mut trans) = (0.0f32, 1.0f32);
                // The nearest visible solid hides what lies behind it: march up to it, then
                // show it.
                let hit = solids
                    .iter()
                    .filter(|s| s.visible)
                    .filter_map(|s| s.hit(origin, dir).map(|t| (t, s)))
                    .min_by(|a, b| a.0.total_cmp(&b.0));
                if let Some((t, _)) = hit {
                    t1 = t1.min(t);
                }
                if t1 > t0 {
                    let steps = ((t1 - t0) / ds).ceil() as usize;
                    let step = (t1 - t0) / steps.max(1) as f32;
                    for k in 0..steps {
                        let p = origin + dir * (t0 + (k as f32 + 0.5) * step);
                        let g = (p - lo) / cell - Vec3::splat(0.5);
                        let sigma = density_scale * density.sample(g).max(0.0);
                        let a = 1.0 - (-sigma * step).exp();
                        light += trans * a;
                        trans *= 1.0 - a;
                    }
                }
                let (shade, to_background) = match hit {
                    Some((t, solid)) => (trans * solid.shade(origin + dir * t), 0.0),
                    None => (0.0, trans),
                };
                row[i * 3..i * 3 + 3].fill(light + shade);
                row_reach[i] = to_background;
            }
        });
    Ok((image_of(camera, data)?, reach))
}

/// What [`generate`] wrote.
#[derive(Debug, Clone)]
pub struct SynthScene {
    pub dir: PathBuf,
    pub cameras: Vec<Camera>,
    /// Rendered frames `[view][frame]` as f32 before PNG quantisation (in the Blender
    /// layout, composited over the configuration's background).
    pub frames: Vec<Vec<Image>>,
    /// Mean |div u| after projection, per frame.
    pub divergence: Vec<f32>,
}

/// Simulates, renders and writes a scene into `out` (which must not exist or be empty).
pub fn generate(cfg: &SynthConfig, out: &Path) -> Result<SynthScene> {
    generate_with_progress(cfg, out, |_| {})
}

/// [`generate`], calling `frame_done(t)` after each frame is written (for a progress bar:
/// an 800x800 preset takes minutes).
pub fn generate_with_progress(
    cfg: &SynthConfig,
    out: &Path,
    frame_done: impl FnMut(usize),
) -> Result<SynthScene> {
    cfg.validate()?;
    if out.exists() {
        let mut entries = std::fs::read_dir(out).map_err(io_err(out))?;
        if entries.next().is_some() {
            return Err(DataError::Layout {
                path: out.to_path_buf(),
                reason: "output folder exists and is not empty".into(),
            });
        }
        std::fs::remove_dir(out).map_err(io_err(out))?;
    }
    let name = out
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into());
    let partial = out.with_file_name(format!(".{name}.partial"));
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(io_err(&partial))?;
    }
    let result = write_scene(cfg, &partial, frame_done);
    match result {
        Ok(mut scene) => {
            std::fs::rename(&partial, out).map_err(io_err(out))?;
            scene.dir = out.to_path_buf();
            Ok(scene)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&partial);
            Err(e)
        }
    }
}

fn write_scene(
    cfg: &SynthConfig,
    dir: &Path,
    mut frame_done: impl FnMut(usize),
) -> Result<SynthScene> {
    let cams = cameras(cfg)?;
    let middle = cfg.views / 2;
    std::fs::create_dir_all(dir.join("gt")).map_err(io_err(dir))?;
    // Where each view's frame t goes, without the extension.
    let (folders, stems): (Vec<String>, Vec<String>) = match cfg.layout {
        SynthLayout::Pinf => (0..cfg.views)
            .map(|k| (format!("view{k:02}"), format!("view{k:02}/")))
            .unzip(),
        SynthLayout::Blender => (0..cfg.views)
            .map(|k| {
                let split = if k == middle { "test" } else { "train" };
                (split.to_string(), format!("{split}/view{k:02}_"))
            })
            .unzip(),
    };
    for folder in &folders {
        std::fs::create_dir_all(dir.join(folder)).map_err(io_err(dir.join(folder)))?;
    }
    let mut solver = Solver::new(cfg)?;
    let mut frames: Vec<Vec<Image>> = vec![Vec::new(); cfg.views];
    let mut divergence = Vec::new();
    let cell = 1.0 / cfg.grid as f32;
    for t in 0..cfg.frames {
        solver.step_frame();
        divergence.push(solver.mean_abs_divergence());
        for (k, cam) in cams.iter().enumerate() {
            let path = dir.join(format!("{}{t:03}.png", stems[k]));
            let picture = match cfg.layout {
                SynthLayout::Pinf => {
                    let picture = render(
                        &solver.density,
                        cam,
                        cfg.density_scale,
                        cfg.background,
                        &cfg.solids,
                    )?;
                    picture.save_png(&path)?;
                    picture
                }
                SynthLayout::Blender => {
                    let (colour, alpha) =
                        render_rgba(&solver.density, cam, cfg.density_scale, &cfg.solids)?;
                    colour.save_png_with_alpha(&alpha, &path)?;
                    colour.over(&alpha, cfg.background)
                }
            };
            frames[k].push(picture);
        }
        // Ground truth: density, and velocity in world units per frame.
        let n = cfg.grid;
        let mut vel = Vec::with_capacity(n * n * n * 3);
        for i in 0..n * n * n {
            for c in 0..3 {
                vel.push(solver.velocity[c].data[i] * cell);
            }
        }
        write_gt(
            &dir.join("gt").join(format!("frame_{t:03}.safetensors")),
            n,
            &solver.density.data,
            &vel,
        )?;
        frame_done(t);
    }
    let pose = |k: usize| -> Vec<Vec<f32>> {
        let m = cams[k].camera_to_world();
        (0..4).map(|r| m.row(r).to_array().to_vec()).collect()
    };
    let obstacles: Vec<serde_json::Value> = cfg
        .solids
        .iter()
        .map(|s| match s.shape {
            Obstacle::Sphere { centre, radius } => {
                json!({"sphere": {"centre": centre.to_array(), "radius": radius}})
            }
            Obstacle::Box { min, max } => {
                json!({"box": {"min": min.to_array(), "max": max.to_array()}})
            }
        })
        .collect();
    let synth = json!({
        "generator": "gausmoke-data synth",
        "grid": cfg.grid,
        "seed": cfg.seed,
        "substeps": cfg.substeps,
        "jacobi_iterations": cfg.jacobi_iterations,
        "vorticity": cfg.vorticity,
        "buoyancy": cfg.buoyancy,
        "inflow_speed": cfg.inflow_speed,
        "noise": cfg.noise,
        "density_scale": cfg.density_scale,
        "background": cfg.background,
        "ground_truth": "gt/frame_TTT.safetensors: density [n,n,n], velocity [n,n,n,3] (world units per frame), [z][y][x] x fastest, cell centres at (i+0.5)/n of the box"
    });
    let files: Vec<(PathBuf, serde_json::Value)> = match cfg.layout {
        SynthLayout::Pinf => {
            let entry = |k: usize| {
                json!({
                    "file_name": folders[k],
                    "frame_rate": 30,
                    "frame_num": cfg.frames,
                    "camera_angle_x": cfg.fov_x,
                    "camera_hw": [cfg.height, cfg.width],
                    "transform_matrix": pose(k),
                })
            };
            let train: Vec<_> = (0..cfg.views).filter(|&k| k != middle).map(entry).collect();
            // PINF swaps columns 0 and 2 of voxel_matrix on load; store the swapped form of
            // [I | (-0.5, 0, -0.5)].
            let (lo, _) = world_box();
            let mut stored = Mat4::from_translation(lo);
            std::mem::swap(&mut stored.x_axis, &mut stored.z_axis);
            let voxel_rows: Vec<Vec<f32>> =
                (0..4).map(|r| stored.row(r).to_array().to_vec()).collect();
            vec![(
                dir.join("info.json"),
                json!({
                    "obstacles": obstacles,
                    "train_videos": train,
                    "test_videos": [entry(middle)],
                    "frame_bkg_color": cfg.background,
                    "voxel_scale": [1.0, 1.0, 1.0],
                    "voxel_matrix": voxel_rows,
                    "synth": synth,
                }),
            )]
        }
        SynthLayout::Blender => {
            let last = (cfg.frames - 1).max(1) as f32;
            let entries = |test: bool| -> Vec<serde_json::Value> {
                (0..cfg.frames)
                    .flat_map(|t| {
                        (0..cfg.views)
                            .filter(move |&k| (k == middle) == test)
                            .map(move |k| (t, k))
                    })
                    .map(|(t, k)| {
                        json!({
                            "file_path": format!("./{}{t:03}", stems[k]),
                            "time": t as f32 / last,
                            "transform_matrix": pose(k),
                        })
                    })
                    .collect()
            };
            let (lo, hi) = world_box();
            vec![
                (
                    dir.join("transforms_train.json"),
                    json!({
                        "camera_angle_x": cfg.fov_x,
                        "aabb": [lo.to_array(), hi.to_array()],
                        "obstacles": obstacles,
                        "synth": synth,
                        "frames": entries(false),
                    }),
                ),
                (
                    dir.join("transforms_test.json"),
                    json!({"camera_angle_x": cfg.fov_x, "frames": entries(true)}),
                ),
            ]
        }
    };
    for (path, value) in files {
        let text = serde_json::to_string_pretty(&value).map_err(|source| DataError::Json {
            path: path.clone(),
            source,
        })?;
        std::fs::write(&path, text).map_err(io_err(&path))?;
    }
    Ok(SynthScene {
        dir: dir.to_path_buf(),
        cameras: cams,
        frames,
        divergence,
    })
}

fn write_gt(path: &Path, n: usize, density: &[f32], velocity: &[f32]) -> Result<()> {
    let err = |e: safetensors::SafeTensorError| DataError::Tensors {
        path: path.to_path_buf(),
        reason: e.to_string(),
    };
    let to_bytes = |v: &[f32]| -> Vec<u8> { v.iter().flat_map(|x| x.to_le_bytes()).collect() };
    let (db, vb) = (to_bytes(density), to_bytes(velocity));
    let d = safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![n, n, n], &db)
        .map_err(err)?;
    let v = safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![n, n, n, 3], &vb)
        .map_err(err)?;
    let meta = HashMap::from([
        ("layout".to_string(), "[z][y][x], x fastest".to_string()),
        (
            "velocity_units".to_string(),
            "world units per frame".to_string(),
        ),
    ]);
    safetensors::serialize_to_file([("density", d), ("velocity", v)], Some(meta), path).map_err(err)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blocks() -> (SynthSolid, SynthSolid) {
        let solids = SynthConfig::blocks_plume().solids;
        (solids[0], solids[1])
    }

    /// Entry points worked by hand: straight down -z onto the wall (face at z = -0.42), past
    /// the block (y = 0.5 is above its top at 0.46), and onto the sphere (|x| = 0.04 off its
    /// centre line, so it enters at z = sqrt(0.14^2 - 0.04^2)).
    #[test]
    fn rays_enter_boxes_and_spheres_where_worked_by_hand() {
        let (block, wall) = blocks();
        let down = Vec3::new(0.0, 0.0, -1.0);
        let from = Vec3::new(0.05, 0.5, 2.0);
        assert!(block.hit(from, down).is_none());
        let t = wall.hit(from, down).unwrap();
        assert!((t - 2.42).abs() < 1e-5, "{t}");
        let through_block = Vec3::new(0.05, 0.4, 2.0);
        let t = block.hit(through_block, down).unwrap();
        assert!((t - 1.88).abs() < 1e-5, "{t}");
        // Pointing away, or starting past it: no hit.
        assert!(wall.hit(from, -down).is_none());
        let sphere = SynthConfig::obstacle_plume().solids[0];
        let t = sphere.hit(Vec3::new(0.0, 0.4, 2.0), down).unwrap();
        let expected = 2.0 - (0.14f32 * 0.14 - 0.04 * 0.04).sqrt();
        assert!((t - expected).abs() < 1e-5, "{t} against {expected}");
    }

    /// The wall's face (normal +z) is lit by `0.3 + 0.7 (n . l)` with `l = (0.3, 1, 0.5) /
    /// |.|`, so its squares are 0.35 or 0.75 of 0.6023; squares alternate every sixth of a
    /// unit, along x and along y.
    #[test]
    fn box_faces_are_checkered_in_squares_of_a_sixth() {
        let (_, wall) = blocks();
        let lit = 0.3 + 0.7 * 0.5 / 1.34f32.sqrt();
        let at = |x: f32, y: f32| wall.shade(Vec3::new(x, y, -0.42));
        // floor(0.05 * 6) + floor(0.5 * 6) = 3: odd, the light squares.
        assert!((at(0.05, 0.5) - 0.75 * lit).abs() < 1e-6);
        assert!((at(-0.1, 0.5) - 0.35 * lit).abs() < 1e-6);
        assert!((at(0.05, 0.7) - 0.35 * lit).abs() < 1e-6);
        assert!((at(0.2, 0.7) - 0.75 * lit).abs() < 1e-6);
        // The top face of the block: normal +y, lit by 0.3 + 0.7 / |l|.
        let (block, _) = blocks();
        let top = block.shade(Vec3::new(0.05, 0.46, 0.05));
        let lit_top = 0.3 + 0.7 / 1.34f32.sqrt();
        assert!(
            (top - 0.75 * lit_top).abs() < 1e-6 || (top - 0.35 * lit_top).abs() < 1e-6,
            "{top}"
        );
    }

    #[test]
    fn solids_outside_the_box_are_refused_naming_the_setting() {
        let config = SynthConfig {
            solids: vec![SynthSolid {
                shape: Obstacle::Box {
                    min: Vec3::new(-0.6, 0.0, -0.5),
                    max: Vec3::new(0.0, 0.1, 0.0),
                },
                visible: true,
            }],
            ..SynthConfig::tiny()
        };
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("solids") && err.contains("solid 0"), "{err}");
    }
}
