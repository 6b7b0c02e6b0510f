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
//! The grid velocity training fitted is what carried the run's Gaussians; it stays in the
//! frame files. On the long plume this estimate, read off the same run's densities, is truer,
//! while the same fit used as the trainer's carrier costs the pictures (docs/EXPERIMENTS.md):
//! so it is the run's last stage (`velocity_estimate` in the configuration), not a step of
//! each frame. It becomes the velocity of the run's exports (the grid velocity beside it as
//! `grid_velocity`), and `eval` scores both against a synthetic scene's ground truth.
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

mod options;
pub use options::{EstimateOptions, ForceOptions};

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
    /// Cells left out of the data term: the run's inflow box (`scene.inflow`), where a
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
    folder.require_whole()?;
    let config: TrainConfig = folder.read_config()?;
    let info = folder.read_run_info()?;
    let grid = config.grid(info.box_lo.into(), info.box_hi.into())?;
    // The data set says where its solids are, which the projection keeps the flow out of.
    let obstacles = gausmoke_data::read_obstacles(&info.data)?;
    let projection = ProjectionOptions {
        rel_tolerance: config.projection.tolerance,
        max_iterations: config.projection.max_iterations,
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
    let in_data = transport_cells(&grid, config.scene.inflow);
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
    let mut outputs = EstimateOutputs::new(
        &dir,
        &folder.exports_dir(),
        &grid,
        config.output.every,
        total,
    );
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
        .or(config.scene.inflow)
        .ok_or_else(|| TrainError::Config {
            origin: "velocity --forces".into(),
            reason: "the smoke step needs the smoke's source, and this run has no inflow box \
                     (scene.inflow): give it as --source-box x0,y0,z0,x1,y1,z1 (fractions \
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
                 {last}: the step needs smoke there (check --source-box or scene.inflow)"
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
mod tests;
