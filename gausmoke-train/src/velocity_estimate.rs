//! A velocity estimated after training from the run's own density grids (`gausmoke-train
//! velocity --run DIR`, ours): for each frame t, the velocity whose semi-Lagrangian step
//! carries frame t-1's density grid onto frame t's ([`crate::density_motion`]), tracked
//! through the frames: frame t's fit starts from, and is tied to, frame t-1's estimate carried
//! along itself, lifted along +y where there is smoke by as much as frame t-1's fit rose there
//! beyond frame t-2's estimate carried along itself ([`buoyancy_coefficient`]; downward only
//! instead for sinking smoke, [`EstimateOptions::sinking`]), and its
//! smoothness is charged on the change from that start. Frame 1 starts from no motion, untied.
//!
//! With [`EstimateOptions::forces`] (`--forces`) each fit starts instead from a smoke solver's
//! step of frame t-1's fit, driven by frame t-1's density and the forces the densities'
//! motion chooses ([`crate::smoke_step`]), is tied to it, and is smoothed as a whole. What
//! the densities' motion does not show then comes from the forces' history: on the long plume
//! that errs 0.41-0.42 against the default's 0.57 (docs/RESULTS.md). It needs the smoke's
//! source, the run's inflow box or one given.
//!
//! The run's own velocity is what carried its Gaussians; it is left as it is. On the long
//! plume this estimate, read off the same run's densities, is truer than the run's velocity,
//! while the same fit used as the trainer's carrier costs the pictures (docs/RESULTS.md, "Why
//! we fall short", item 1): so it is an output beside the run's velocity, not a step of it.
//! `gausmoke-train eval` scores it against a synthetic scene's ground truth next to the run's.
//!
//! Written to `RUN/velocity_estimate/`: `frame_TTT.safetensors` (`velocity`, `[nx, ny, nz,
//! 3]`, world units per frame as the frame files keep theirs) and `estimate.json` (the
//! settings, and per frame the fit's misfits, its speed and the run's where the smoke is, and
//! a fingerprint of the two densities it was fitted to, so that an estimate of a run trained
//! again is not read as this one's); and grids, slices and charts to look at
//! ([`crate::estimate_outputs`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_model::{GridSpec, ProjectionOptions, project_velocity};
use gausmoke_render::device_traffic::read_floats;
use serde::{Deserialize, Serialize};

use crate::arrays::{HostArrays, read_arrays, take_array, write_arrays};
use crate::density_motion::{
    MotionGrid, MotionPriors, Smoothed, fit_density_motion, transport_cells, velocity_of_moves,
};
use crate::estimate_outputs::{EstimateOutputs, FrameFigures, smoke_speed};
use crate::export::write_atomic;
use crate::hash::Fnv1a;
use crate::run_folder::RunFolder;
use crate::smoke_step::{Forces, INFLOW_CHOICES, SmokeStep, TriedForces, choose_forces};
use crate::{TrainConfig, TrainError};

/// Conjugate-gradient iterations per Gauss-Newton pass, as the trainer's fit takes.
const CG_ITERATIONS: usize = 400;

/// The estimate's folder inside a run folder.
pub fn estimate_dir(run: &Path) -> PathBuf {
    run.join("velocity_estimate")
}

/// Frame `t`'s estimate file inside a run folder.
pub fn estimate_path(run: &Path, t: usize) -> PathBuf {
    estimate_dir(run).join(format!("frame_{t:03}.safetensors"))
}

/// The fit's weights (see [`crate::density_motion`]): the smoothness `A` of each frame's
/// change from its start (the previous frame's estimate carried along itself; no motion for
/// frame 1), the divergence `B` and the tie `G` to that start; and whether the start is also
/// lifted along y (the world's up) in proportion to the density (`buoyancy`, see
/// [`buoyancy_coefficient`]), upward only for rising smoke or, with `sinking`, downward only
/// for smoke heavier than the air (fog).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EstimateOptions {
    /// Charged on each frame's change from its start, not on the estimate itself (with
    /// `forces`, on the estimate itself).
    pub smoothness: f64,
    pub divergence: f64,
    pub inertia: f64,
    #[serde(default)]
    pub buoyancy: bool,
    #[serde(default)]
    pub sinking: bool,
    /// Start each frame's fit from a smoke solver's step of the frame before's fit instead of
    /// from that fit carried along itself ([`crate::smoke_step`]); `buoyancy` then says
    /// whether the step has a buoyancy force, and `sinking` which way it and the inflow act.
    #[serde(default)]
    pub forces: Option<ForceOptions>,
    /// The run's density below this fraction of its frame's maximum is taken as none: the
    /// haze of Gaussians the views hardly see, which a smoke step would lift and carry as
    /// smoke (0: every density as it is).
    #[serde(default)]
    pub density_floor: f64,
}

/// The smoke step of [`EstimateOptions::forces`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ForceOptions {
    /// The source's exit speed (cells per frame); `None`: chosen by the density's motion
    /// among [`INFLOW_CHOICES`].
    pub inflow: Option<f64>,
    /// The buoyancy (cells per frame per frame at the source's density); `None`: chosen by
    /// the density's motion.
    pub buoyancy: Option<f64>,
    pub vorticity: f64,
    pub substeps: usize,
    /// The frames (1 to this) whose misfit chooses the forces.
    pub fit_frames: usize,
    /// The source, as fractions of the box (x0, y0, z0, x1, y1, z1); `None`: the run's inflow
    /// box (`respawn_region`).
    pub source_box: Option<[f32; 6]>,
}

impl Default for ForceOptions {
    /// As the long plume's generator steps (two substeps, confinement 0.3); the forces
    /// chosen over its first 36 frames.
    fn default() -> Self {
        Self {
            inflow: None,
            buoyancy: None,
            vorticity: 0.3,
            substeps: 2,
            fit_frames: 36,
            source_box: None,
        }
    }
}

impl Default for EstimateOptions {
    /// The weights that erred least on the long plume: the divergence and the tie on the
    /// scene's exact density (`xtask/reference/velocity_from_density.py`), the smoothness on
    /// the preset runs' own densities (0.003 against 0.0001 to 0.1, three seeds; no less
    /// true on the obstacle scene; docs/RESULTS.md).
    fn default() -> Self {
        Self {
            smoothness: 0.003,
            divergence: 1000.0,
            inertia: 0.01,
            buoyancy: true,
            sinking: false,
            forces: None,
            density_floor: 0.0,
        }
    }
}

impl EstimateOptions {
    /// The weights that erred least on the long plume with the smoke step as each fit's
    /// start (`xtask/reference/velocity_from_forces.py --assimilate`): a tie of 0.03 (against
    /// 1, 0.1 and 0.01) and the smoothness on the velocity itself.
    pub fn forced() -> Self {
        Self {
            smoothness: 0.001,
            inertia: 0.03,
            forces: Some(ForceOptions::default()),
            ..Self::default()
        }
    }

    /// Where each frame's fit starts, as the CLI and the misfit chart name it.
    pub fn fits_start(&self) -> &'static str {
        if self.forces.is_some() {
            "smoke step"
        } else {
            "carried estimate"
        }
    }

    fn validate(&self) -> Result<(), TrainError> {
        for (name, value) in [
            ("smoothness", self.smoothness),
            ("divergence", self.divergence),
            ("inertia", self.inertia),
        ] {
            if !(0.0..=1e6).contains(&value) {
                return Err(TrainError::Config {
                    origin: format!("velocity estimate --{name}"),
                    reason: format!("{value} is outside [0, 1e6]"),
                });
            }
        }
        if !(0.0..1.0).contains(&self.density_floor) {
            return Err(TrainError::Config {
                origin: "velocity estimate --density-floor".into(),
                reason: format!(
                    "{} is not a fraction of the frame's largest density in [0, 1)",
                    self.density_floor
                ),
            });
        }
        if let Some(forces) = &self.forces {
            let bad = |name: &str, reason: String| {
                Err(TrainError::Config {
                    origin: format!("velocity estimate --{name}"),
                    reason,
                })
            };
            if !(1..=16).contains(&forces.substeps) {
                return bad(
                    "substeps",
                    format!("{} is outside 1 to 16", forces.substeps),
                );
            }
            if forces.fit_frames == 0 {
                return bad("fit-frames", "the forces need at least one frame".into());
            }
            for (name, value) in [
                ("inflow", forces.inflow),
                ("force-buoyancy", forces.buoyancy),
                ("vorticity", Some(forces.vorticity)),
            ] {
                if let Some(v) = value
                    && !(0.0..=100.0).contains(&v)
                {
                    return bad(name, format!("{v} is outside [0, 100] cells per frame"));
                }
            }
            if let Some(b) = forces.source_box
                && !crate::config::is_box_of_fractions(&b)
            {
                return bad(
                    "source-box",
                    format!("{b:?} is not x0,y0,z0,x1,y1,z1 with 0 <= x0 < x1 <= 1 per axis"),
                );
            }
        }
        if self.sinking && !self.buoyancy && self.forces.is_none() {
            return Err(TrainError::Config {
                origin: "velocity estimate --sinking".into(),
                reason: "it sets which way the lift is read, and --no-buoyancy leaves the lift \
                         out: give one of them"
                    .into(),
            });
        }
        Ok(())
    }
}

/// One frame's fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameEstimate {
    pub frame: usize,
    /// The data residual of the start (the carried estimate) and of the fit, each relative to
    /// that of no motion.
    pub misfit_prior: f64,
    pub misfit_fitted: f64,
    /// Whether the fit ended worse than its start, which was kept.
    pub kept_start: bool,
    /// The lift the start was given along +y, per unit density (cells per frame per frame,
    /// densities divided by frame t-1's largest): what frame t-1's fit showed, if upward (0
    /// without `buoyancy`, and for frames 1 and 2).
    #[serde(default)]
    pub buoyancy: f64,
    /// The coefficient this frame's fit showed ([`buoyancy_coefficient`]), of either sign,
    /// before the one-way rule makes it the next frame's lift (`None` without `buoyancy`,
    /// and for frame 1, which has no carried start).
    #[serde(default)]
    pub buoyancy_read: Option<f64>,
    /// The fit's conjugate-gradient iterations, and the largest residual one of its linear
    /// solves ended on, relative to its right-hand side (1e-6 when all converged).
    #[serde(default)]
    pub solver_iterations: usize,
    #[serde(default)]
    pub solver_residual: f64,
    /// The density-weighted mean speed (world units per frame) of the estimate and of the
    /// run's own velocity: their speeds where the smoke is.
    #[serde(default)]
    pub smoke_speed: f64,
    #[serde(default)]
    pub run_smoke_speed: f64,
    /// Fingerprints of frames t-1 and t's density grids as fitted.
    pub density_fingerprints: [String; 2],
    pub seconds: f64,
}

/// A solve that ends above this residual (relative to its right-hand side; the fit asks for
/// 1e-6) stopped at its iteration cap far from the fit's minimum.
const UNCONVERGED_RESIDUAL: f64 = 1e-3;

impl FrameEstimate {
    /// Whether one of the fit's linear solves stopped short of convergence, so that this
    /// frame's estimate is not the fit's minimum.
    pub fn stopped_short(&self) -> bool {
        self.solver_residual > UNCONVERGED_RESIDUAL
    }
}

/// `estimate.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EstimateSummary {
    pub options: EstimateOptions,
    /// Cells left out of the data term: the run's inflow box (`respawn_region`), where a
    /// source sets the density, not transport.
    pub inflow_cells: usize,
    /// The smoke step's forces as chosen, with [`EstimateOptions::forces`].
    #[serde(default)]
    pub forces: Option<ChosenForces>,
    pub frames: Vec<FrameEstimate>,
}

/// The smoke step's forces and what chose them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChosenForces {
    pub forces: Forces,
    /// The step's density misfit over frames 1 to `fit_frames` with them, relative to no
    /// motion's ([`crate::smoke_step::SmokeStep`]'s `misfit`).
    #[serde(alias = "mean_misfit")]
    pub misfit: f64,
    pub fit_frames: usize,
    /// The source's cells, and its density in the run's units (the mean of the run's density
    /// there over those frames): the step's unit of density.
    pub source_cells: usize,
    pub density_unit: f64,
    /// One pair per inflow tried, with the buoyancy that fitted it best.
    pub tried: Vec<TriedForces>,
    /// The choice's time (the frames' own are in each frame's `seconds`).
    pub seconds: f64,
}

/// A chosen step's misfit at or above this fraction of no motion's explains the density's
/// motion scarcely at all. On the obstacle preset's runs trained with the paper's update,
/// whose densities are far from the scene's, it was 0.87 and the estimate 0.04 less true than
/// without `forces`; on runs with our update 0.31-0.41 on the plumes and 0.69-0.81 on the
/// obstacle scene, where the estimate is 0.15-0.16 truer than without (docs/RESULTS.md): a
/// thin margin, measured on few runs.
const STEP_MISFIT_WARNING: f64 = 0.85;

impl ChosenForces {
    /// Whether even the chosen step carried the density scarcely better than no motion: the
    /// run's density does not move as a plume from that source would, and the estimate
    /// without `forces` may be truer.
    pub fn scarcely_explains(&self) -> bool {
        self.misfit >= STEP_MISFIT_WARNING
    }
}

/// The coefficients the fits read, summed by sign: how much of the lift went the way it is
/// kept ([`EstimateOptions::sinking`]: down, else up) and how much the other way.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LiftReadings {
    pub along: f64,
    pub against: f64,
}

impl EstimateSummary {
    /// The lift's readings when the fits mostly accelerated the smoke against the way the
    /// lift is kept (rising smoke estimated with `sinking`, or sinking smoke without): the
    /// one-way lift then drops most of what the data shows, and on the long plume turned
    /// upside down that erred more than no lift at all (docs/RESULTS.md). `None` otherwise,
    /// and without the lift.
    pub fn lift_against_data(&self) -> Option<LiftReadings> {
        let sign = if self.options.sinking { -1.0 } else { 1.0 };
        let mut readings = LiftReadings {
            along: 0.0,
            against: 0.0,
        };
        for read in self.frames.iter().filter_map(|f| f.buoyancy_read) {
            if sign * read > 0.0 {
                readings.along += read.abs();
            } else {
                readings.against += read.abs();
            }
        }
        (readings.against > readings.along).then_some(readings)
    }
}

/// How strongly a fit's moves rose where there was smoke, beyond `start` (the previous
/// estimate carried along itself, without the lift): the least-squares `b` in `moves_y -
/// start_y ~ b density` over all cells (`[cells, 3]` moves, `[cells]` density). A buoyant
/// plume accelerates upward in proportion to its density, and smoke heavier than the air
/// downward; the next frame's start is lifted by it where it has the expected sign
/// ([`EstimateOptions::buoyancy`], [`EstimateOptions::sinking`]), so the lift is read off the
/// data, not assumed.
pub fn buoyancy_coefficient(moves: &[f64], start: &[f64], density: &[f64]) -> f64 {
    let (mut along, mut squared) = (0.0, 0.0);
    for (c, rho) in density.iter().enumerate() {
        along += (moves[3 * c + 1] - start[3 * c + 1]) * rho;
        squared += rho * rho;
    }
    if squared > 0.0 { along / squared } else { 0.0 }
}

/// `density` divided by its largest value (all zeros for an empty grid).
fn unit_density(density: &[f32]) -> Vec<f64> {
    let largest = density.iter().fold(0.0f32, |m, &v| m.max(v));
    if largest > 0.0 && largest.is_finite() {
        density.iter().map(|&v| f64::from(v / largest)).collect()
    } else {
        vec![0.0; density.len()]
    }
}

/// A fingerprint of a density grid's values.
pub fn density_fingerprint(density: &[f32]) -> String {
    let mut hash = Fnv1a::default();
    for v in density {
        hash.write(&v.to_le_bytes());
    }
    hash.hex()
}

/// Sets the cells of `density` below `fraction` of its largest value to zero.
fn floor_density(density: &mut [f32], fraction: f64) {
    if fraction <= 0.0 {
        return;
    }
    let floor = (fraction * f64::from(density.iter().copied().fold(0.0, f32::max))) as f32;
    for d in density.iter_mut().filter(|d| **d < floor) {
        *d = 0.0;
    }
}

/// Estimates the velocity of every frame of the run folder `run` from its density grids and
/// writes it to [`estimate_dir`], each frame's fit made divergence-free by the exact `Pi` with
/// the run's open faces and the data set's solids (on `device`); `on_frame(done, total)`
/// reports progress.
pub fn estimate_run_velocity(
    run: &Path,
    options: &EstimateOptions,
    device: &Device,
    mut on_frame: impl FnMut(usize, usize),
) -> Result<EstimateSummary, TrainError> {
    options.validate()?;
    let folder = RunFolder::at(run);
    if !folder.run_info_path().is_file() {
        return Err(TrainError::Config {
            origin: run.display().to_string(),
            reason: "this folder is not a GauSmoke run (it has no run.json); pass the --out \
                     folder of a `gausmoke-train train`"
                .into(),
        });
    }
    let config: TrainConfig = folder.read_config()?;
    let info = folder.read_run_info()?;
    let grid = config.grid(info.box_lo.into(), info.box_hi.into())?;
    // The data set says where its solids are, which the projection keeps the flow out of.
    let obstacles = gausmoke_data::read_obstacles(&info.data)?;
    let projection = ProjectionOptions {
        rel_tolerance: config.projection_tolerance,
        max_iterations: config.projection_max_iterations,
        open_faces: config.open_faces()?,
        solids: crate::trainer::solid_cells(&obstacles, &config, &grid)?,
        ..ProjectionOptions::default()
    };
    let (mut densities, mut run_speeds) = (Vec::new(), Vec::new());
    for t in 0..folder.finished_frames() {
        let Some(state) = folder.read_frame_state(t, &grid)? else {
            break;
        };
        run_speeds.push(smoke_speed(&state.density, &state.velocity));
        densities.push(state.density);
    }
    if densities.len() < 2 {
        return Err(TrainError::Dataset {
            path: run.to_path_buf(),
            reason: format!(
                "{} finished frame(s) in frames/: a velocity needs two",
                densities.len()
            ),
        });
    }
    let motion_grid = MotionGrid {
        resolution: grid.resolution(),
        open: projection.open_faces,
    };
    let in_data = transport_cells(&grid, config.respawn_region);
    let dt = f64::from(config.dt);
    let cell = grid.cell_size().to_array().map(f64::from);
    // Of the densities as the run wrote them, which eval compares with the frames.
    let fingerprints: Vec<String> = densities.iter().map(|d| density_fingerprint(d)).collect();
    for density in &mut densities {
        floor_density(density, options.density_floor);
    }
    let source = match &options.forces {
        Some(forces) => source_cells(forces, &config, &grid)?,
        None => Vec::new(),
    };
    let forced = match &options.forces {
        Some(forces) => {
            let step = SmokeStep {
                grid: motion_grid,
                spec: &grid,
                projection: &projection,
                cell,
                dt,
                source: &source,
                substeps: forces.substeps,
                vorticity: forces.vorticity,
                up: if options.sinking { -1.0 } else { 1.0 },
            };
            let chosen = choose_run_forces(&step, forces, options.buoyancy, &densities, run)?;
            tracing::info!(
                inflow = chosen.forces.inflow,
                buoyancy = format!("{:.4}", chosen.forces.buoyancy),
                misfit = format!("{:.4}", chosen.misfit),
                "smoke step's forces chosen"
            );
            Some((step, chosen))
        }
        None => None,
    };

    let dir = estimate_dir(run);
    std::fs::create_dir_all(&dir).map_err(|source| TrainError::Io {
        path: dir.clone(),
        source,
    })?;
    // Without its summary no frame file is read, so an estimate stopped part way is not
    // taken for the one before it.
    let summary_path = dir.join("estimate.json");
    if summary_path.is_file() {
        std::fs::remove_file(&summary_path).map_err(|source| TrainError::Io {
            path: summary_path.clone(),
            source,
        })?;
    }
    let [nx, ny, nz] = grid.resolution();
    let total = densities.len() - 1;
    let mut outputs = EstimateOutputs::new(&dir, &grid, config.output_every, total);
    let mut frames = Vec::new();
    let mut previous: Option<Vec<f64>> = forced
        .as_ref()
        .map(|(step, chosen)| step.velocity_at_frame_zero(chosen.forces));
    let mut lift = 0.0;
    for t in 1..densities.len() {
        let start = Instant::now();
        let carried = match forced {
            Some(_) => None,
            None => previous
                .as_ref()
                .map(|moves| motion_grid.self_carried(moves)),
        };
        // The density the lift is in proportion to, and regressed on after the fit.
        let lift_density =
            (options.buoyancy && forced.is_none()).then(|| unit_density(&densities[t - 1]));
        let (prior, inertia, smoothed) = match (&forced, &carried) {
            (Some((step, chosen)), _) => {
                let unit = chosen.density_unit;
                let before: Vec<f64> = densities[t - 1]
                    .iter()
                    .map(|&d| f64::from(d) / unit)
                    .collect();
                let moves = previous.as_ref().expect("the step starts from rest");
                let (stepped, _) = step.frame(chosen.forces, moves, &before);
                (stepped, options.inertia, Smoothed::Move)
            }
            (None, Some(carried)) => {
                let mut prior = carried.clone();
                for (c, rho) in lift_density.iter().flatten().enumerate() {
                    prior[3 * c + 1] += lift * rho;
                }
                // What the densities do not see is carried on, not smoothed away frame by
                // frame.
                (prior, options.inertia, Smoothed::Change)
            }
            (None, None) => (vec![0.0; 3 * motion_grid.cells()], 0.0, Smoothed::Change),
        };
        let priors = MotionPriors {
            smoothness: options.smoothness,
            divergence: options.divergence,
            inertia,
            smoothed,
        };
        let fit = fit_density_motion(
            &motion_grid,
            &densities[t - 1],
            &densities[t],
            &in_data,
            &prior,
            priors,
            CG_ITERATIONS,
        );
        let world = velocity_of_moves(&fit.moves, cell, dt);
        let world = Tensor::from_data(TensorData::new(world, [nx, ny, nz, 3]), device);
        let velocity = read_floats(project_velocity(&grid, world, projection.clone()));
        let speed = smoke_speed(&densities[t], &velocity);
        let read = match (&carried, &lift_density) {
            (Some(carried), Some(density)) => {
                Some(buoyancy_coefficient(&fit.moves, carried, density))
            }
            _ => None,
        };
        if outputs.wants(t) {
            // Read again rather than kept from the first pass: that holds one velocity grid
            // at a time, not one per output frame.
            let run_velocity = folder
                .read_frame_state(t, &grid)?
                .ok_or_else(|| TrainError::Dataset {
                    path: run.to_path_buf(),
                    reason: format!("frame {t}'s state vanished from frames/ while estimating"),
                })?
                .velocity;
            outputs.frame(t, &densities[t], &run_velocity, &velocity)?;
        }
        let mut arrays = HostArrays::new();
        arrays.insert("velocity".into(), (vec![nx, ny, nz, 3], velocity));
        write_arrays(&estimate_path(run, t), &arrays)?;
        tracing::info!(
            frame = t,
            misfit_prior = format!("{:.3}", fit.misfit_prior),
            misfit_fitted = format!("{:.3}", fit.misfit_fitted),
            kept_start = fit.kept_start,
            solver_iterations = fit.solver_iterations,
            solver_residual = format!("{:.1e}", fit.solver_residual),
            "velocity estimated"
        );
        frames.push(FrameEstimate {
            frame: t,
            misfit_prior: fit.misfit_prior,
            misfit_fitted: fit.misfit_fitted,
            kept_start: fit.kept_start,
            buoyancy: lift,
            buoyancy_read: read,
            solver_iterations: fit.solver_iterations,
            solver_residual: fit.solver_residual,
            smoke_speed: speed,
            run_smoke_speed: run_speeds[t],
            density_fingerprints: [fingerprints[t - 1].clone(), fingerprints[t].clone()],
            seconds: start.elapsed().as_secs_f64(),
        });
        if let Some(coefficient) = read {
            // One way only: where the smoke slows (a rising cap meeting the top), the slowing
            // is not in proportion to its density, and carrying it on erred more.
            lift = if options.sinking {
                coefficient.min(0.0)
            } else {
                coefficient.max(0.0)
            };
        }
        previous = Some(fit.moves);
        on_frame(t, total);
    }
    let figures: Vec<FrameFigures> = frames
        .iter()
        .map(|f| FrameFigures {
            frame: f.frame,
            misfit_start: f.misfit_prior,
            misfit_fitted: f.misfit_fitted,
            speed: f.smoke_speed,
            run_speed: f.run_smoke_speed,
        })
        .collect();
    outputs.finish(&figures, options.fits_start())?;
    let summary = EstimateSummary {
        options: options.clone(),
        inflow_cells: in_data.iter().filter(|&&inside| !inside).count(),
        forces: forced.map(|(_, chosen)| chosen),
        frames,
    };
    let text = serde_json::to_string_pretty(&summary).expect("the summary serialises");
    write_atomic(&summary_path, text.as_bytes())?;
    Ok(summary)
}

/// The smoke step's source cells: `forces`' box, else the run's inflow box.
fn source_cells(
    forces: &ForceOptions,
    config: &TrainConfig,
    grid: &GridSpec,
) -> Result<Vec<bool>, TrainError> {
    let region = forces
        .source_box
        .or(config.respawn_region)
        .ok_or_else(|| TrainError::Config {
            origin: "velocity --forces".into(),
            reason: "the smoke step needs the smoke's source, and this run has no inflow box \
                     (respawn_region): give it as --source-box x0,y0,z0,x1,y1,z1 (fractions \
                     of the box)"
                .into(),
        })?;
    let source: Vec<bool> = transport_cells(grid, Some(region))
        .iter()
        .map(|inside| !inside)
        .collect();
    if !source.contains(&true) {
        return Err(TrainError::Config {
            origin: "velocity --source-box".into(),
            reason: format!("the source {region:?} holds no cell centre of the velocity grid"),
        });
    }
    Ok(source)
}

/// The step's unit of density (the run's mean density in the source over the frames that
/// choose the forces) and the forces, given or chosen ([`choose_forces`]).
fn choose_run_forces(
    step: &SmokeStep,
    forces: &ForceOptions,
    with_buoyancy: bool,
    densities: &[Vec<f32>],
    run: &Path,
) -> Result<ChosenForces, TrainError> {
    let start = Instant::now();
    let last = forces.fit_frames.min(densities.len() - 1);
    let source_cells = step.source.iter().filter(|&&inside| inside).count();
    let mut total = 0.0;
    for density in &densities[1..=last] {
        for (d, _) in density
            .iter()
            .zip(step.source)
            .filter(|(_, inside)| **inside)
        {
            total += f64::from(*d);
        }
    }
    let density_unit = total / (source_cells * last) as f64;
    if !(density_unit.is_finite() && density_unit > 0.0) {
        return Err(TrainError::Dataset {
            path: run.to_path_buf(),
            reason: format!(
                "the run's density is {density_unit} in the smoke step's source over frames 1 to \
                 {last}: the step needs smoke there (check --source-box or respawn_region)"
            ),
        });
    }
    let scaled: Vec<Vec<f64>> = densities[..=last]
        .iter()
        .map(|d| d.iter().map(|&v| f64::from(v) / density_unit).collect())
        .collect();
    let inflows = match forces.inflow {
        Some(inflow) => vec![inflow],
        None => INFLOW_CHOICES.to_vec(),
    };
    let buoyancy = if with_buoyancy {
        forces.buoyancy
    } else {
        Some(0.0)
    };
    let (best, tried) = choose_forces(step, &scaled, &inflows, buoyancy);
    Ok(ChosenForces {
        forces: best.forces,
        misfit: best.misfit,
        fit_frames: last,
        source_cells,
        density_unit,
        tried,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// A run's estimate as written by [`estimate_run_velocity`], its summary read once.
#[derive(Debug, Clone)]
pub struct StoredEstimate {
    run: PathBuf,
    summary: EstimateSummary,
}

impl StoredEstimate {
    /// The run's estimate, `None` when it has none (or one stopped before its summary was
    /// written).
    pub fn open(run: &Path) -> Result<Option<Self>, TrainError> {
        let summary_path = estimate_dir(run).join("estimate.json");
        if !summary_path.is_file() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&summary_path).map_err(|source| TrainError::Io {
            path: summary_path.clone(),
            source,
        })?;
        let summary = serde_json::from_str(&text).map_err(|e| TrainError::Arrays {
            path: summary_path.clone(),
            reason: format!("not a velocity estimate's summary: {e}"),
        })?;
        Ok(Some(Self {
            run: run.to_path_buf(),
            summary,
        }))
    }

    /// Frame `t`'s estimated velocity (`[nx, ny, nz, 3]`, world units per frame) when it was
    /// fitted to the densities the run holds now (`densities` = frames t-1 and t's); `Err` when
    /// it was fitted to other densities (the run was trained again since).
    pub fn frame(
        &self,
        t: usize,
        resolution: [usize; 3],
        densities: [&[f32]; 2],
    ) -> Result<Option<Vec<f32>>, TrainError> {
        let path = estimate_path(&self.run, t);
        if t == 0 || !path.is_file() {
            return Ok(None);
        }
        let stale = || TrainError::Arrays {
            path: path.clone(),
            reason: format!(
                "this estimate was fitted to other density grids than frames {} and {t} now \
                 hold (the run was trained again since); run `gausmoke-train velocity --run {}` \
                 again",
                t - 1,
                self.run.display()
            ),
        };
        let entry = self
            .summary
            .frames
            .iter()
            .find(|f| f.frame == t)
            .ok_or_else(stale)?;
        if entry.density_fingerprints != densities.map(density_fingerprint) {
            return Err(stale());
        }
        let [nx, ny, nz] = resolution;
        let mut arrays = read_arrays(&path)?;
        Ok(Some(take_array(
            &mut arrays,
            "velocity",
            &[nx, ny, nz, 3],
            &path,
        )?))
    }
}

#[cfg(test)]
mod tests {
    use gausmoke_core::glam::Vec3;

    use super::*;
    use crate::run_folder::{FrameState, RunInfo};

    fn device() -> Device {
        gausmoke_render::backends::device_by_name("flex").unwrap()
    }

    /// A run folder (beside the tiny synthetic scene, its data set) of `frames` frames whose
    /// density is a smooth blob centred at `centre(t)` (world units), on a 16^3 grid over the
    /// unit box.
    fn blob_run(
        dir: &Path,
        centre: impl Fn(f32) -> Vec3,
        frames: usize,
    ) -> (RunFolder, TrainConfig) {
        let data = dir.join("data");
        gausmoke_data::synth::generate(&gausmoke_data::synth::SynthConfig::tiny(), &data).unwrap();
        let folder = RunFolder::at(&dir.join("run"));
        folder.create().unwrap();
        let config = TrainConfig {
            grid_resolution: 16,
            ..TrainConfig::default()
        };
        folder.write_config(&config).unwrap();
        let (lo, hi) = ([0.0; 3], [1.0; 3]);
        folder
            .write_run_info(&RunInfo {
                data,
                data_fingerprint: None,
                frames,
                grid_resolution: [16; 3],
                box_lo: lo,
                box_hi: hi,
                device: "none".into(),
                version: "test".into(),
            })
            .unwrap();
        let grid = config.grid(lo.into(), hi.into()).unwrap();
        for t in 0..frames {
            let centre = centre(t as f32);
            let density = grid
                .cell_centres()
                .chunks(3)
                .map(|p| (-(Vec3::from_slice(p) - centre).length_squared() / 0.02).exp())
                .collect();
            let state = FrameState {
                gaussians: Default::default(),
                statics: None,
                velocity: vec![0.0; 3 * grid.num_cells()],
                density,
            };
            folder.write_frame_state(t, &grid, &state).unwrap();
        }
        (folder, config)
    }

    /// A blob moving by `shift` (world units) a frame.
    fn moving_blob_run(dir: &Path, shift: Vec3, frames: usize) -> (RunFolder, TrainConfig) {
        blob_run(dir, |t| Vec3::new(0.4, 0.35, 0.45) + shift * t, frames)
    }

    /// The lift is the least-squares coefficient of the vertical increment on the density.
    #[test]
    fn the_buoyancy_coefficient_is_the_increments_slope_on_the_density() {
        let density = [0.0, 0.5, 1.0, 0.25];
        let start = [0.1, -0.2, 0.3, 0.0, 0.4, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0];
        let mut moves = start;
        for (c, rho) in density.iter().enumerate() {
            moves[3 * c + 1] += 0.3 * rho;
            moves[3 * c] += 5.0 * rho;
        }
        let b = buoyancy_coefficient(&moves, &start, &density);
        assert!((b - 0.3).abs() < 1e-12, "{b}");
        assert_eq!(buoyancy_coefficient(&moves, &start, &[0.0; 4]), 0.0);
    }

    /// A blob rising faster each frame: its estimate's start is lifted from frame 3 on, by
    /// an upward coefficient; without `buoyancy` it never is, nor when the blob slows. A
    /// blob sinking faster each frame is lifted downward with `sinking`, and not without.
    #[test]
    fn an_accelerating_blob_lifts_the_start() {
        // Each frame's lift for a blob centred at `centre(t)`, under `options`, and whether
        // the summary finds the fits against the way the lift is kept.
        let lifts = |centre: fn(f32) -> Vec3, options: &[EstimateOptions]| {
            let dir = tempfile::tempdir().unwrap();
            let (folder, _) = blob_run(dir.path(), centre, 5);
            options
                .iter()
                .map(|options| {
                    let summary =
                        estimate_run_velocity(folder.root(), options, &device(), |_, _| {})
                            .unwrap();
                    let lifts: Vec<f64> = summary.frames.iter().map(|f| f.buoyancy).collect();
                    (lifts, summary.lift_against_data().is_some())
                })
                .collect::<Vec<_>>()
        };
        let rising = EstimateOptions::default();
        let sinking = EstimateOptions {
            sinking: true,
            ..rising.clone()
        };
        let none = EstimateOptions {
            buoyancy: false,
            ..rising.clone()
        };
        let zero = |lifts: &[f64]| lifts.iter().all(|&b| b == 0.0);
        let up = lifts(
            |t| Vec3::new(0.45, 0.3 + 0.02 * t * t, 0.5),
            &[rising.clone(), none],
        );
        assert_eq!(&up[0].0[..2], &[0.0, 0.0], "{up:?}");
        assert!(up[0].0[2..].iter().all(|&b| b > 0.0), "{up:?}");
        assert!(zero(&up[1].0));
        assert!(!up[0].1 && !up[1].1, "{up:?}");
        let slowing = lifts(
            |t| Vec3::new(0.45, 0.3 + 0.1 * t - 0.02 * t * t, 0.5),
            std::slice::from_ref(&rising),
        );
        assert!(zero(&slowing[0].0), "{slowing:?}");
        // Sinking faster each frame (fog): with `sinking` the lift is downward from frame 3
        // on; read upward only, as for rising smoke, it never is, and the summary says the
        // fits went the other way.
        let down = lifts(
            |t| Vec3::new(0.45, 0.7 - 0.02 * t * t, 0.5),
            &[sinking, rising],
        );
        assert_eq!(&down[0].0[..2], &[0.0, 0.0], "{down:?}");
        assert!(down[0].0[2..].iter().all(|&b| b < 0.0), "{down:?}");
        assert!(!down[0].1, "{down:?}");
        assert!(zero(&down[1].0) && down[1].1, "{down:?}");
    }

    /// A blob rising from a source: with `forces` the estimate asks for the source when the
    /// run has no inflow box, then chooses the buoyancy from the densities, records it, and
    /// moves the smoke upward.
    #[test]
    fn the_forced_estimate_needs_a_source_and_lifts_the_smoke() {
        let dir = tempfile::tempdir().unwrap();
        let (folder, _) = blob_run(dir.path(), |t| Vec3::new(0.5, 0.3 + 0.04 * t, 0.5), 5);
        let forces = ForceOptions {
            inflow: Some(0.5),
            ..ForceOptions::default()
        };
        let options = |source_box| EstimateOptions {
            forces: Some(ForceOptions {
                source_box,
                ..forces.clone()
            }),
            ..EstimateOptions::forced()
        };
        let error = estimate_run_velocity(folder.root(), &options(None), &device(), |_, _| {})
            .unwrap_err()
            .to_string();
        assert!(error.contains("--source-box"), "{error}");
        let summary = estimate_run_velocity(
            folder.root(),
            &options(Some([0.35, 0.15, 0.35, 0.65, 0.35, 0.65])),
            &device(),
            |_, _| {},
        )
        .unwrap();
        assert_eq!(summary.frames.len(), 4);
        let chosen = summary.forces.as_ref().expect("the chosen forces");
        assert_eq!(chosen.tried.len(), 1);
        assert_eq!(chosen.forces.inflow, 0.5);
        assert!(chosen.forces.buoyancy > 0.0, "{chosen:?}");
        assert!(
            chosen.source_cells > 0 && chosen.density_unit > 0.0,
            "{chosen:?}"
        );
        let grid = TrainConfig {
            grid_resolution: 16,
            ..TrainConfig::default()
        }
        .grid(Vec3::ZERO, Vec3::ONE)
        .unwrap();
        let state = folder.read_frame_state(3, &grid).unwrap().unwrap();
        let velocity = read_arrays(&estimate_path(folder.root(), 3)).unwrap();
        let velocity = &velocity["velocity"].1;
        let lift: f32 = state
            .density
            .iter()
            .enumerate()
            .map(|(c, rho)| rho * velocity[3 * c + 1])
            .sum();
        assert!(lift > 0.0, "the smoke's mean vertical velocity {lift}");
    }

    /// A blob moving a known distance each frame: the estimate, read back through the files
    /// eval reads, is that distance per frame in world units inside the smoke, and an
    /// estimate of densities that have changed since is refused.
    #[test]
    fn the_estimate_is_the_blobs_motion_and_a_stale_one_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let shift = Vec3::new(0.05, 0.07, -0.03);
        let (folder, config) = moving_blob_run(dir.path(), shift, 3);
        let run = folder.root();
        let mut reported = Vec::new();
        let summary = estimate_run_velocity(run, &EstimateOptions::default(), &device(), |d, n| {
            reported.push((d, n))
        })
        .unwrap();
        assert_eq!(reported, [(1, 2), (2, 2)]);
        assert_eq!(summary.frames.len(), 2);
        // What a person looks at: frame 2 is the last (the default cadence writes all), the
        // charts span both frames, and the run's velocity (zero here) is slower than the blob.
        let dir = estimate_dir(run);
        for t in 1..3 {
            for file in [
                format!("exports/grid_{t:03}.vti"),
                format!("exports/grid_{t:03}.npz"),
                format!("slices/frame_{t:03}.png"),
            ] {
                assert!(dir.join(&file).is_file(), "{file}");
            }
        }
        for file in ["exports/grid.pvd", "slices.mp4", "speed.png", "misfit.png"] {
            assert!(dir.join(file).is_file(), "{file}");
        }
        let pvd = std::fs::read_to_string(dir.join("exports/grid.pvd")).unwrap();
        assert!(
            pvd.contains("grid_001.vti") && pvd.contains("grid_002.vti"),
            "{pvd}"
        );
        let slice = crate::visuals::Picture::open_png(&dir.join("slices/frame_002.png")).unwrap();
        // Three 256-pixel panels (density and two speeds) and the gaps between them.
        assert!((768..800).contains(&slice.width) && slice.height == 256);
        for frame in &summary.frames {
            assert_eq!(frame.run_smoke_speed, 0.0);
            let speed = frame.smoke_speed / shift.length() as f64;
            assert!(
                (0.7..1.3).contains(&speed),
                "frame {}: {speed}",
                frame.frame
            );
        }
        let grid = config.grid(Vec3::ZERO, Vec3::ONE).unwrap();
        let state = |t| folder.read_frame_state(t, &grid).unwrap().unwrap().density;
        let stored = StoredEstimate::open(run).unwrap().expect("an estimate");
        for t in 1..3 {
            let (before, after) = (state(t - 1), state(t));
            let estimate = stored
                .frame(t, grid.resolution(), [&before, &after])
                .unwrap()
                .expect("an estimate for frame t");
            let (mut error, mut norm) = (0.0f64, 0.0f64);
            for (cell, &rho) in after.iter().enumerate() {
                if rho > 0.3 {
                    for a in 0..3 {
                        error += f64::from(estimate[3 * cell + a] - shift[a]).powi(2);
                        norm += f64::from(shift[a]).powi(2);
                    }
                }
            }
            let relative = (error / norm).sqrt();
            assert!(relative < 0.15, "frame {t}: relative error {relative}");
            assert!(summary.frames[t - 1].misfit_fitted < 0.2);
        }
        // Frame 0 has no estimate (its velocity is zero by construction).
        let zero = state(0);
        assert!(
            stored
                .frame(0, grid.resolution(), [&zero, &zero])
                .unwrap()
                .is_none()
        );
        // Frame 2 trained again: its estimate no longer belongs to the run; frame 1's still does.
        let mut changed = state(2);
        changed[100] += 0.5;
        let error = stored
            .frame(2, grid.resolution(), [&state(1), &changed])
            .unwrap_err()
            .to_string();
        assert!(error.contains("trained again"), "{error}");
        assert!(
            stored
                .frame(1, grid.resolution(), [&zero, &state(1)])
                .unwrap()
                .is_some()
        );
    }

    /// Settings outside their range and a run with one frame are refused by name.
    #[test]
    fn bad_settings_and_a_one_frame_run_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (folder, _) = moving_blob_run(dir.path(), Vec3::ZERO, 1);
        let refusal = |run: &Path, options: &EstimateOptions| {
            estimate_run_velocity(run, options, &device(), |_, _| {})
                .unwrap_err()
                .to_string()
        };
        let run = folder.root();
        let bad = EstimateOptions {
            inertia: -1.0,
            ..EstimateOptions::default()
        };
        let error = refusal(run, &bad);
        assert!(error.contains("--inertia"), "{error}");
        let contradictory = EstimateOptions {
            buoyancy: false,
            sinking: true,
            ..EstimateOptions::default()
        };
        let error = refusal(run, &contradictory);
        assert!(error.contains("--sinking"), "{error}");
        for floor in [-0.1, 1.0, f64::NAN] {
            let bad = EstimateOptions {
                density_floor: floor,
                ..EstimateOptions::default()
            };
            let error = refusal(run, &bad);
            assert!(error.contains("--density-floor"), "{floor}: {error}");
        }
        for (forces, flag) in [
            (
                ForceOptions {
                    substeps: 0,
                    ..ForceOptions::default()
                },
                "--substeps",
            ),
            (
                ForceOptions {
                    inflow: Some(-1.0),
                    ..ForceOptions::default()
                },
                "--inflow",
            ),
            (
                ForceOptions {
                    source_box: Some([0.6, 0.0, 0.3, 0.4, 0.2, 0.7]),
                    ..ForceOptions::default()
                },
                "--source-box",
            ),
        ] {
            let bad = EstimateOptions {
                forces: Some(forces),
                ..EstimateOptions::forced()
            };
            let error = refusal(run, &bad);
            assert!(error.contains(flag), "{error}");
        }
        let error = refusal(run, &EstimateOptions::default());
        assert!(error.contains("a velocity needs two"), "{error}");
        let empty = tempfile::tempdir().unwrap();
        let error = refusal(empty.path(), &EstimateOptions::default());
        assert!(error.contains("not a GauSmoke run"), "{error}");
    }

    #[test]
    fn the_floor_clears_only_the_cells_below_its_share_of_the_largest() {
        let mut density = vec![0.0, 0.04, 0.05, 0.5, 1.0, 2.0];
        floor_density(&mut density, 0.025);
        assert_eq!(density, [0.0, 0.0, 0.05, 0.5, 1.0, 2.0]);
        let mut untouched = vec![0.001, 2.0];
        floor_density(&mut untouched, 0.0);
        assert_eq!(untouched, [0.001, 2.0]);
    }
}
