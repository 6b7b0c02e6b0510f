//! Synthetic smoke scenes with ground truth (issue 7, item 2).
//!
//! A small 3D smoke solver (buoyant plume from a source disc near the floor, semi-Lagrangian
//! advection with trilinear sampling, vorticity confinement, pressure projection by Jacobi
//! iterations, seeded inflow noise, optionally a swirl that turns the smoke about the
//! source's vertical axis) is rendered from cameras on an arc by an independent Beer-Lambert ray
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
//! renamed into place at the end; an existing non-empty output folder is refused. A sibling
//! `.lock` file serialises processes that generate into the same folder.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use gausmoke_core::Camera;
use gausmoke_core::glam::{Mat4, Vec3};
use serde_json::json;

use crate::dataset::Obstacle;
use crate::error::{DataError, Result, io_err};
use crate::image::Image;

mod march;
mod solver;

pub use march::{BOX_TILE, SynthSolid, render, render_rgba};
pub use solver::{Grid, Solver};

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
    /// Turning of the smoke about the source's vertical axis, in degrees per frame
    /// (counter-clockwise seen from above): each substep the smoke's tangential velocity
    /// relaxes towards this solid-body rotation, in proportion to its density (capped at 1).
    /// 0 (every preset but [`SynthConfig::turning_plume`]) leaves the solver as it was.
    pub swirl_degrees: f32,
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

/// The largest image side [`SynthConfig::validate`] accepts.
const MAX_SIDE: u32 = 8192;

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
            swirl_degrees: 0.0,
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

    /// The long plume turning about its vertical axis (relaxed towards 5 degrees per frame,
    /// it turns about 3 by frame 20), so that what the cameras saw of a rising structure they
    /// later see from other directions (some 75 degrees over the 25 frames a structure takes
    /// to rise through the box): a scene on which transport can carry what earlier frames'
    /// views saw to where no view of the present frame looks (issue 18).
    pub fn turning_plume() -> Self {
        Self {
            swirl_degrees: 5.0,
            ..Self::long_plume()
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
        // Each view's frame is rendered and written whole: past this it would not fit in memory.
        if self.width > MAX_SIDE || self.height > MAX_SIDE {
            return bad(
                "width/height",
                format!(
                    "{}x{}: at most {MAX_SIDE} pixels a side",
                    self.width, self.height
                ),
            );
        }
        let finite = [
            self.vorticity,
            self.swirl_degrees,
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
    let name = out
        .file_name()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene".into());
    // Two processes asked for the same scene (two `reproduce` runs started together) would
    // otherwise build it in the same partial folder at once; the lock makes the second wait
    // and then find the first one's scene in place. The lock is released when the file closes,
    // also when the process dies.
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(io_err(parent))?;
    }
    let lock_path = out.with_file_name(format!(".{name}.lock"));
    let lock = std::fs::File::options()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&lock_path)
        .map_err(io_err(&lock_path))?;
    lock.lock().map_err(io_err(&lock_path))?;
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
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, SCENE_TOML).map_err(io_err(&scene))?;
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

/// The solver's boundary and source, as `gausmoke-train` reads a data set's `scene.toml`: its
/// top is open (and its divergence reads a still cell above it: half the top cell's velocity
/// on the face), and the source disc (radius 0.12, up to 0.1 of the box's height, at the floor's
/// centre) lies in the inflow box, a margin of about a cell around it at 32^3.
pub const SCENE_TOML: &str = "\
# The scene's boundary and source (gausmoke-train reads this beside the cameras).
open_faces = [\"y+\"]
open_face_flow = 0.5
inflow = [0.35, 0.0, 0.35, 0.65, 0.15, 0.65]
";

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
