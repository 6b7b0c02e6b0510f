//! What the velocity estimate leaves to look at. It becomes the run's velocity in the run's
//! own exports: at the run's output cadence (`output.every`, and the last frame)
//! `RUN/exports/grid_TTT.vti` and `.npz` are rewritten with `velocity` the estimate and
//! `grid_velocity` the grid velocity training fitted (the `.npz`'s other arrays kept), so
//! ParaView's `grid.pvd` and NumPy read the estimate by the same names as before. Beside its
//! frame files in `RUN/velocity_estimate/`: `slices/frame_TTT.png`, the middle z slice, density
//! | the grid velocity's speed | the estimate's speed, both speeds on one colour scale,
//! animated by `slices.mp4`; and over all frames, two charts: `speed.png` (the two velocities'
//! speed where the smoke is) and `misfit.png` (how well the start and the fit carry one
//! density onto the next).

use std::path::{Path, PathBuf};

use gausmoke_model::GridSpec;

use crate::TrainError;
use crate::chart::{self, Chart, Series};
use crate::export::{rewrite_npz, write_vti};
use crate::slices::{GridSlice, SliceScale};
use crate::visuals;

/// Pictures per second of `slices.mp4`, as the run's own `slices.mp4`.
const FPS: u32 = 10;

/// One frame's figures for the charts.
pub(crate) struct FrameFigures {
    pub frame: usize,
    /// The data residual of the start and of the fit, relative to that of no motion.
    pub misfit_start: f64,
    pub misfit_fitted: f64,
    /// Density-weighted mean speeds (world units per frame) of the estimate and of the run's
    /// own velocity ([`smoke_speed`]).
    pub speed: f64,
    pub run_speed: f64,
}

/// The mean speed of `velocity` (`[cells, 3]`) weighted by `density` (`[cells]`): the speed
/// where the smoke is, which the still air around it does not dilute. 0 with no density.
pub(crate) fn smoke_speed(density: &[f32], velocity: &[f32]) -> f64 {
    let (mut weighted, mut mass) = (0.0f64, 0.0f64);
    for (rho, u) in density.iter().zip(velocity.chunks_exact(3)) {
        let rho = f64::from(rho.max(0.0));
        let speed = u.iter().map(|&v| f64::from(v).powi(2)).sum::<f64>().sqrt();
        weighted += rho * speed;
        mass += rho;
    }
    if mass > 0.0 { weighted / mass } else { 0.0 }
}

/// The estimate's outputs, written frame by frame and finished once.
pub(crate) struct EstimateOutputs<'a> {
    dir: PathBuf,
    exports: PathBuf,
    grid: &'a GridSpec,
    every: usize,
    last: usize,
    /// Each output frame's number and slice, drawn on one scale at the end.
    slices: Vec<(usize, GridSlice)>,
}

impl<'a> EstimateOutputs<'a> {
    /// Outputs in `dir` and the run's `exports` folder for a run whose frames go up to
    /// `last`, written every `every` frames.
    pub(crate) fn new(
        dir: &Path,
        exports: &Path,
        grid: &'a GridSpec,
        every: usize,
        last: usize,
    ) -> Self {
        Self {
            dir: dir.to_path_buf(),
            exports: exports.to_path_buf(),
            grid,
            every: every.max(1),
            last,
            slices: Vec::new(),
        }
    }

    /// Whether frame `t` gets grids and a slice (the run's cadence, and the last frame).
    pub(crate) fn wants(&self, t: usize) -> bool {
        t.is_multiple_of(self.every) || t == self.last
    }

    /// Frame `t`'s grids and slice: the run's `density` and `grid_velocity` and the
    /// `estimate` (`[nx, ny, nz]` and `[nx, ny, nz, 3]`, world units per frame).
    pub(crate) fn frame(
        &mut self,
        t: usize,
        density: &[f32],
        grid_velocity: &[f32],
        estimate: &[f32],
    ) -> Result<(), TrainError> {
        std::fs::create_dir_all(&self.exports).map_err(|source| TrainError::Io {
            path: self.exports.clone(),
            source,
        })?;
        let grid_field = [("grid_velocity", grid_velocity)];
        write_vti(
            &self.exports.join(format!("grid_{t:03}.vti")),
            self.grid,
            density,
            estimate,
            &grid_field,
        )?;
        rewrite_npz(
            &self.exports.join(format!("grid_{t:03}.npz")),
            self.grid,
            density,
            estimate,
            &grid_field,
        )?;
        self.slices.push((
            t,
            GridSlice::middle(self.grid, density, &[grid_velocity, estimate]),
        ));
        Ok(())
    }

    /// The animation, the time series and the charts over `frames`; `start` names where
    /// each fit started (the misfit chart's legend).
    pub(crate) fn finish(self, frames: &[FrameFigures], start: &str) -> Result<(), TrainError> {
        if !self.slices.is_empty() {
            let dir = self.dir.join("slices");
            std::fs::create_dir_all(&dir).map_err(|source| TrainError::Io {
                path: dir.clone(),
                source,
            })?;
            let scale = SliceScale::over(self.slices.iter().map(|(_, slice)| slice));
            let note = scale.video_note();
            let mut pictures = Vec::with_capacity(self.slices.len());
            for (t, slice) in &self.slices {
                let picture = crate::slices::figure(
                    *t,
                    slice,
                    &scale,
                    &["density", "speed: grid velocity", "speed: the estimate"],
                    &note,
                );
                picture.save_png(&dir.join(format!("frame_{t:03}.png")))?;
                pictures.push(picture);
            }
            visuals::save_mp4(&self.dir.join("slices.mp4"), &pictures, FPS)?;
        }
        let series = |label: &str, value: fn(&FrameFigures) -> f64| Series {
            label: label.into(),
            points: frames.iter().map(|f| (f.frame as f64, value(f))).collect(),
        };
        let charts = [
            (
                "speed",
                Chart {
                    title: "Speed where the smoke is (density-weighted mean)".into(),
                    x_label: "frame".into(),
                    y_label: "speed (world units / frame)".into(),
                    log_y: false,
                    series: vec![
                        series("the run's velocity", |f| f.run_speed),
                        series("the estimate", |f| f.speed),
                    ],
                    marks: Vec::new(),
                },
            ),
            (
                "misfit",
                Chart {
                    title: "Frame t-1's density carried onto frame t's: residual".into(),
                    x_label: "frame".into(),
                    y_label: "residual / residual with no motion".into(),
                    log_y: false,
                    series: vec![
                        series(&format!("start ({start})"), |f| f.misfit_start),
                        series("fit", |f| f.misfit_fitted),
                    ],
                    marks: Vec::new(),
                },
            ),
        ];
        for (name, figure) in &charts {
            chart::save(figure, 960, 480, &self.dir.join(name))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The speed where the smoke is ignores the still air's cells and weighs by density.
    #[test]
    fn the_smoke_speed_is_density_weighted() {
        let density = [0.0, 1.0, 3.0];
        let velocity = [9.0, 9.0, 9.0, 3.0, 4.0, 0.0, 0.0, 0.0, 1.0];
        let speed = smoke_speed(&density, &velocity);
        assert!((speed - (5.0 + 3.0) / 4.0).abs() < 1e-12, "{speed}");
        assert_eq!(smoke_speed(&[0.0; 3], &velocity), 0.0);
    }
}
