//! The run folder: every path a run writes and every file format in it, in one place. The
//! trainer writes through it and `eval` reads through it, so the two cannot disagree on a key.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use gausmoke_model::GridSpec;
use gausmoke_render::HostGaussians;
use serde::{Deserialize, Serialize};

use crate::arrays::{HostArrays, read_arrays, take_array, write_arrays};
use crate::config::{PlyAxes, TrainConfig};
use crate::export::{self, write_atomic};
use crate::slices::{GridSlice, SliceScale};
pub use crate::state::PhaseSeconds;
use crate::state::{FrameReport, LossRow, RefineMoveField};
use crate::visuals::{self, Picture};
use crate::{TrainError, checkpoint};

/// `run.json`: what the run was trained on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunInfo {
    /// The data set's absolute path (as given where it could not be resolved).
    pub data: PathBuf,
    /// [`crate::sequence::Sequence::fingerprint`] of the data the run was trained on
    /// (absent in runs written before it existed).
    #[serde(default)]
    pub data_fingerprint: Option<String>,
    pub frames: usize,
    pub grid_resolution: [usize; 3],
    pub box_lo: [f32; 3],
    pub box_hi: [f32; 3],
    pub device: String,
    pub version: String,
}

impl RunInfo {
    /// Refuses data whose fingerprint (`found`, [`crate::sequence::Sequence::fingerprint`])
    /// is not the one the run was trained on: a data set regenerated or replaced at the same
    /// path would be scored or rendered against the wrong pictures.
    pub fn check_data(&self, found: &str) -> Result<(), TrainError> {
        match &self.data_fingerprint {
            Some(trained) if trained != found => Err(TrainError::Dataset {
                path: self.data.clone(),
                reason: format!(
                    "this is no longer the data set the run was trained on: its cameras, views, \
                     box or first images differ (fingerprint {found}, the run's {trained})"
                ),
            }),
            _ => Ok(()),
        }
    }
}

/// `metrics.json`: per-frame reports and their means.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    pub frames: usize,
    pub gaussians: usize,
    pub grid_resolution: [usize; 3],
    pub test_l1_mean: Option<f64>,
    pub test_psnr_mean: Option<f64>,
    pub test_ssim_mean: Option<f64>,
    pub mean_abs_divergence: Option<f64>,
    pub train_l1_mean: Option<f64>,
    pub training_seconds: f64,
    pub device: String,
    /// Wall time per phase in this session (a resumed run counts from the resume). Nested:
    /// "backward (all ops)" includes the ops' own backward phases, "density splat" counts
    /// every splatting call (U-Net input and physics losses).
    pub phase_seconds: BTreeMap<String, PhaseSeconds>,
    pub per_frame: Vec<FrameReport>,
}

/// What one frame leaves for evaluation: the Gaussians and the grids (`frames/frame_TTT`).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameState {
    /// The smoke's Gaussians.
    pub gaussians: HostGaussians,
    /// The static Gaussians, when the run has them (`static_gaussians`).
    pub statics: Option<HostGaussians>,
    /// `[nx, ny, nz, 3]`, world units per frame.
    pub velocity: Vec<f32>,
    /// `[nx, ny, nz]`.
    pub density: Vec<f32>,
}

impl FrameState {
    /// Everything a render of the frame composites: the smoke's Gaussians, then the static ones.
    pub fn rendered(&self) -> HostGaussians {
        let mut all = self.gaussians.clone();
        if let Some(statics) = &self.statics {
            all.append(statics);
        }
        all
    }
}

/// Array names of the static Gaussians' attributes in a frame file.
fn static_name(attribute: &str) -> String {
    format!("static_{attribute}")
}

/// Takes one Gaussian set out of a frame file's arrays: the attribute `a` is stored as
/// `name(a)`, and its rows are counted by the densities.
fn take_gaussians(
    arrays: &mut HostArrays,
    name: impl Fn(&str) -> String,
    path: &Path,
) -> Result<HostGaussians, TrainError> {
    let n = arrays
        .get(&name("raw_densities"))
        .map(|(shape, _)| shape[0])
        .unwrap_or_default();
    let mut gaussians = HostGaussians::default();
    for (attribute, values) in gaussians
        .as_mut()
        .map(|attribute, values| (attribute, values))
        .into_array()
    {
        let key = name(attribute.name);
        *values = take_array(arrays, &key, &attribute.shape(n), path)?;
        refuse_non_finite(&key, values, path)?;
    }
    Ok(gaussians)
}

/// A frame file's array must be finite: training stops before it writes a non-finite value,
/// so one in a file is corruption, refused here rather than read into every figure after it.
fn refuse_non_finite(name: &str, values: &[f32], path: &Path) -> Result<(), TrainError> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(first) => Err(TrainError::Arrays {
            path: path.to_path_buf(),
            reason: format!(
                "`{name}` holds {} non-finite value(s) (the first at index {first}): the \
                 file is corrupt and is not read",
                values.iter().filter(|v| !v.is_finite()).count()
            ),
        }),
    }
}

/// The smoke Gaussians of a frame file a run wrote (`RUN/frames/frame_TTT.safetensors`),
/// whatever its grid: what `init_gaussians` starts a fit from.
pub fn read_frame_gaussians(path: &Path) -> Result<HostGaussians, TrainError> {
    take_gaussians(&mut read_arrays(path)?, str::to_string, path)
}

/// A run folder on disk.
#[derive(Debug, Clone)]
pub struct RunFolder {
    root: PathBuf,
}

fn frame_file(t: usize, extension: &str) -> String {
    format!("frame_{t:03}.{extension}")
}

impl RunFolder {
    /// The folder at `root` (nothing is read or created).
    pub fn at(root: &Path) -> Self {
        Self {
            root: root.to_path_buf(),
        }
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn config_path(&self) -> PathBuf {
        self.root.join("config.toml")
    }

    pub fn run_info_path(&self) -> PathBuf {
        self.root.join("run.json")
    }

    pub fn metrics_path(&self) -> PathBuf {
        self.root.join("metrics.json")
    }

    pub fn eval_path(&self) -> PathBuf {
        self.root.join("eval.json")
    }

    pub fn frame_state_path(&self, t: usize) -> PathBuf {
        self.root.join("frames").join(frame_file(t, "safetensors"))
    }

    /// The frame numbers of `frames/frame_TTT.safetensors` present.
    fn frame_files(&self) -> std::collections::BTreeSet<usize> {
        std::fs::read_dir(self.root.join("frames"))
            .into_iter()
            .flatten()
            .flatten()
            .filter_map(|entry| {
                let name = entry.file_name().into_string().ok()?;
                let t = name.strip_prefix("frame_")?.strip_suffix(".safetensors")?;
                t.parse::<usize>().ok()
            })
            .collect()
    }

    /// Frames `0..n` whose state the run has written without a gap: what eval, render and
    /// the velocity estimate read ([`Self::require_whole`] refuses a folder with a gap).
    pub fn finished_frames(&self) -> usize {
        (0..)
            .take_while(|&t| self.frame_state_path(t).is_file())
            .count()
    }

    /// Refuses a run folder missing a frame file that the run wrote: one below a frame file
    /// that exists, or below the frames `metrics.json` reports trained. What reads the frames
    /// would otherwise score or show fewer frames than the run has, without saying so.
    pub fn require_whole(&self) -> Result<(), TrainError> {
        let finished = self.finished_frames();
        let present = self.frame_files();
        let reported = self
            .read_metrics()
            .ok()
            .and_then(|m| m.per_frame.iter().map(|f| f.frame + 1).max())
            .unwrap_or(0);
        let later = present.range(finished + 1..).next_back().copied();
        let why = match (later, reported > finished) {
            (Some(last), _) => format!("frame files up to frame {last} exist"),
            (None, true) => format!(
                "metrics.json reports {reported} trained frame(s) (frames 0-{})",
                reported - 1
            ),
            (None, false) => return Ok(()),
        };
        Err(TrainError::Dataset {
            path: self.frame_state_path(finished),
            reason: format!(
                "missing, while {why}: reading the frames would leave frames from {finished} on \
                 out; put the file back, or train the run again (--resume trains only frames \
                 after its checkpoint)"
            ),
        })
    }

    pub fn checkpoints(&self) -> PathBuf {
        checkpoint::checkpoint_root(&self.root)
    }

    fn create_dir(dir: &Path) -> Result<(), TrainError> {
        std::fs::create_dir_all(dir).map_err(|source| TrainError::Io {
            path: dir.to_path_buf(),
            source,
        })
    }

    /// Creates the folder (and its parents).
    pub fn create(&self) -> Result<(), TrainError> {
        Self::create_dir(&self.root)
    }

    fn write_json(path: &Path, value: &impl Serialize) -> Result<(), TrainError> {
        let text = serde_json::to_string_pretty(value).map_err(|e| TrainError::Export {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
        write_atomic(path, text.as_bytes())
    }

    fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T, TrainError> {
        let text = std::fs::read_to_string(path).map_err(|source| TrainError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        serde_json::from_str(&text).map_err(|e| TrainError::Config {
            origin: path.display().to_string(),
            reason: e.to_string(),
        })
    }

    pub fn write_config(&self, config: &TrainConfig) -> Result<(), TrainError> {
        let text = crate::config_docs::annotated_toml(config);
        write_atomic(&self.config_path(), text.as_bytes())
    }

    pub fn read_config(&self) -> Result<TrainConfig, TrainError> {
        TrainConfig::from_toml_file(&self.config_path())
    }

    pub fn write_run_info(&self, info: &RunInfo) -> Result<(), TrainError> {
        Self::write_json(&self.run_info_path(), info)
    }

    pub fn read_run_info(&self) -> Result<RunInfo, TrainError> {
        Self::read_json(&self.run_info_path())
    }

    /// `metrics.json` as the run last wrote it.
    pub fn read_metrics(&self) -> Result<Metrics, TrainError> {
        let path = self.metrics_path();
        let text = std::fs::read_to_string(&path).map_err(|source| TrainError::Io {
            path: path.clone(),
            source,
        })?;
        serde_json::from_str(&text).map_err(|e| TrainError::Dataset {
            path,
            reason: format!("not a run's metrics: {e}"),
        })
    }

    pub fn write_metrics(&self, metrics: &Metrics) -> Result<(), TrainError> {
        Self::write_json(&self.metrics_path(), metrics)
    }

    pub fn write_eval(&self, report: &impl Serialize) -> Result<(), TrainError> {
        Self::write_json(&self.eval_path(), report)
    }

    /// `frames/frame_TTT.safetensors`.
    pub fn write_frame_state(
        &self,
        t: usize,
        grid: &GridSpec,
        state: &FrameState,
    ) -> Result<(), TrainError> {
        let [nx, ny, nz] = grid.resolution();
        let n = state.gaussians.len();
        let mut arrays: HostArrays = state
            .gaussians
            .clone()
            .map(|attribute, values| (attribute.name.to_string(), (attribute.shape(n), values)))
            .into_array()
            .into_iter()
            .collect();
        if let Some(statics) = &state.statics {
            let m = statics.len();
            arrays.extend(
                statics
                    .clone()
                    .map(|attribute, values| {
                        (static_name(attribute.name), (attribute.shape(m), values))
                    })
                    .into_array(),
            );
        }
        arrays.insert(
            "velocity".into(),
            (vec![nx, ny, nz, 3], state.velocity.clone()),
        );
        arrays.insert("density".into(), (vec![nx, ny, nz], state.density.clone()));
        let path = self.frame_state_path(t);
        Self::create_dir(path.parent().expect("frames/ is inside the run"))?;
        write_arrays(&path, &arrays)
    }

    /// Frame `t`'s state, `None` when the run has not finished that frame.
    pub fn read_frame_state(
        &self,
        t: usize,
        grid: &GridSpec,
    ) -> Result<Option<FrameState>, TrainError> {
        let path = self.frame_state_path(t);
        if !path.is_file() {
            return Ok(None);
        }
        let mut arrays = read_arrays(&path)?;
        let [nx, ny, nz] = grid.resolution();
        let gaussians = take_gaussians(&mut arrays, str::to_string, &path)?;
        let statics = if arrays.contains_key(&static_name("raw_densities")) {
            Some(take_gaussians(&mut arrays, static_name, &path)?)
        } else {
            None
        };
        let velocity = take_array(&mut arrays, "velocity", &[nx, ny, nz, 3], &path)?;
        let density = take_array(&mut arrays, "density", &[nx, ny, nz], &path)?;
        refuse_non_finite("velocity", &velocity, &path)?;
        refuse_non_finite("density", &density, &path)?;
        Ok(Some(FrameState {
            gaussians,
            statics,
            velocity,
            density,
        }))
    }

    /// Per-frame pictures and exports: renders of every view, the held-out comparison,
    /// grid slices, `.ply`, `.vti` and `.npz`.
    pub fn write_frame_outputs(
        &self,
        t: usize,
        grid: &GridSpec,
        state: &FrameState,
        renders: &[ViewRender],
        ply_axes: PlyAxes,
        refine_moves: Option<&RefineMoveField>,
    ) -> Result<(), TrainError> {
        for view in renders {
            let dir = self.root.join("renders").join(view.name);
            Self::create_dir(&dir)?;
            Picture::from_rgb(view.render, view.width, view.height)
                .save_png(&dir.join(frame_file(t, "png")))?;
        }
        // Held-out (or first training) view: reference | render, for the GIF.
        if let Some(view) = renders.iter().find(|v| v.held_out).or(renders.first()) {
            let comparison = visuals::labelled_pair(
                &Picture::from_rgb(view.reference, view.width, view.height),
                &Picture::from_rgb(view.render, view.width, view.height),
                [&format!("{}: reference", view.name), "ours"],
                &format!("frame {t}"),
            );
            let dir = self.root.join("comparison");
            Self::create_dir(&dir)?;
            comparison.save_png(&dir.join(frame_file(t, "png")))?;
        }
        let dir = self.root.join("slices");
        Self::create_dir(&dir)?;
        let slice = GridSlice::middle(grid, &state.density, &[&state.velocity]);
        crate::slices::figure(
            t,
            &slice,
            &SliceScale::over([&slice]),
            &RUN_SLICE_LABELS,
            "colour scales: this frame's own, until training ends and redraws every frame on \
             one scale",
        )
        .save_png(&dir.join(frame_file(t, "png")))?;
        let dir = self.exports_dir();
        Self::create_dir(&dir)?;
        export::write_ply(
            &dir.join(format!("gaussians_{t:03}.ply")),
            &state.gaussians,
            ply_axes,
        )?;
        if let Some(statics) = &state.statics {
            export::write_ply(&dir.join(format!("statics_{t:03}.ply")), statics, ply_axes)?;
        }
        export::write_vti(
            &dir.join(format!("grid_{t:03}.vti")),
            grid,
            &state.density,
            &state.velocity,
            &[],
        )?;
        let vectors: Vec<(&str, &[f32])> = refine_moves
            .map(|m| {
                vec![
                    ("refine_move", &m.moves[..]),
                    ("refine_move_flow", &m.flow[..]),
                ]
            })
            .unwrap_or_default();
        export::write_npz(
            &dir.join(format!("grid_{t:03}.npz")),
            grid,
            &state.density,
            &state.velocity,
            &vectors,
        )
    }

    /// `exports/`: the `.ply`, `.vti` and `.npz` files other tools open.
    pub fn exports_dir(&self) -> PathBuf {
        self.root.join("exports")
    }

    pub fn write_losses(&self, losses: &[LossRow]) -> Result<(), TrainError> {
        let mut csv =
            String::from("step,frame,phase,iteration,total,render,divergence,advection,refine\n");
        for (step, r) in losses.iter().enumerate() {
            csv += &format!(
                "{step},{},{},{},{},{},{},{},{}\n",
                r.frame,
                r.phase.name(),
                r.iteration,
                r.total,
                r.render,
                r.divergence,
                r.advection,
                r.refine
            );
        }
        write_atomic(&self.root.join("losses.csv"), csv.as_bytes())
    }

    /// Every finished frame's slice redrawn on one colour scale (the largest density and
    /// speed of the run), as `slices/frame_TTT.png` and `slices.mp4`.
    fn write_slices(&self, grid: &GridSpec, frames: usize) -> Result<(), TrainError> {
        let mut slices = Vec::new();
        for t in 0..frames.min(self.finished_frames()) {
            let Some(state) = self.read_frame_state(t, grid)? else {
                break;
            };
            slices.push(GridSlice::middle(grid, &state.density, &[&state.velocity]));
        }
        if slices.is_empty() {
            return Ok(());
        }
        let scale = SliceScale::over(&slices);
        let note = scale.video_note();
        let dir = self.root.join("slices");
        Self::create_dir(&dir)?;
        let mut pictures = Vec::with_capacity(slices.len());
        for (t, slice) in slices.iter().enumerate() {
            let picture = crate::slices::figure(t, slice, &scale, &RUN_SLICE_LABELS, &note);
            picture.save_png(&dir.join(frame_file(t, "png")))?;
            pictures.push(picture);
        }
        visuals::save_mp4(&self.root.join("slices.mp4"), &pictures, 10)
    }

    /// Loss, speed and PSNR charts, the comparison and slice videos, the ParaView series and
    /// the folder's `README.txt`.
    pub fn write_summary_pictures(
        &self,
        grid: &GridSpec,
        losses: &[LossRow],
        reports: &[FrameReport],
        frames: usize,
    ) -> Result<(), TrainError> {
        use crate::chart::{self, Chart, Series};
        let loss = |label: &str, f: fn(&LossRow) -> f32| Series {
            label: label.into(),
            points: losses
                .iter()
                .enumerate()
                .map(|(step, r)| (step as f64, f(r) as f64))
                .collect(),
        };
        let per_frame = |label: &str, f: fn(&FrameReport) -> Option<f64>| Series {
            label: label.into(),
            points: reports
                .iter()
                .map(|r| (r.frame as f64, f(r).unwrap_or(f64::NAN)))
                .collect(),
        };
        // Where each frame's steps begin, marked on the loss chart.
        let frame_starts: Vec<f64> = losses
            .iter()
            .enumerate()
            .filter(|(step, r)| *step == 0 || losses[step - 1].frame != r.frame)
            .map(|(step, _)| step as f64)
            .collect();
        let chart = |title: &str, x: &str, y: &str, log_y: bool, series: Vec<Series>| Chart {
            title: title.into(),
            x_label: x.into(),
            y_label: y.into(),
            log_y,
            series,
            marks: Vec::new(),
        };
        let losses_chart = Chart {
            marks: frame_starts,
            ..chart(
                "Training losses (frame 0's fit, then K joint and K' refinement steps a frame)",
                "optimisation step (light lines: where each frame begins)",
                "loss (log scale)",
                true,
                vec![
                    loss("total", |r| r.total),
                    loss("L_render", |r| r.render),
                    loss("L_div", |r| r.divergence),
                    loss("L_adv", |r| r.advection),
                    loss("L_refine", |r| r.refine),
                ],
            )
        };
        let speed = chart(
            "Recovered velocity (the grid's)",
            "frame",
            "speed (world units / frame)",
            false,
            vec![
                per_frame("mean", |r| Some(r.mean_speed)),
                per_frame("max", |r| Some(r.max_speed)),
            ],
        );
        // Shares and correlations are different quantities: one chart each.
        let move_shares = chart(
            "Refinement's moves: shares",
            "frame",
            "share of the moves' mean square",
            false,
            vec![
                per_frame("grid-scale share", |r| r.refine_move_grid_share),
                per_frame("same moves shuffled", |r| r.refine_move_grid_share_shuffled),
                per_frame("share a flow can make", |r| r.refine_move_flow_share),
            ],
        );
        let move_persistence = chart(
            "Refinement's moves: persistence (correlation with the frame before's)",
            "frame",
            "correlation",
            false,
            vec![
                per_frame("moves", |r| r.refine_move_persistence),
                per_frame("grid-scale part", |r| r.refine_move_grid_persistence),
                per_frame("field's flow part", |r| r.refine_move_flow_persistence),
                per_frame("field's gathering part", |r| {
                    r.refine_move_gathering_persistence
                }),
            ],
        );
        let psnr = chart(
            "Held-out view",
            "frame",
            "PSNR (dB)",
            false,
            vec![per_frame("held-out PSNR", |r| r.test_psnr)],
        );
        // Each chart as a PNG and, for papers and slides, an SVG of the same layout; the
        // refinement's two charts as SVGs, and one above the other in refine_moves.png.
        for (name, figure, [width, height]) in [
            ("losses", &losses_chart, [1400, 640]),
            ("speed", &speed, [960, 480]),
            ("psnr", &psnr, [960, 480]),
        ] {
            chart::save(figure, width, height, &self.root.join(name))?;
        }
        for (name, figure) in [
            ("refine_moves_shares.svg", &move_shares),
            ("refine_moves_persistence.svg", &move_persistence),
        ] {
            write_atomic(
                &self.root.join(name),
                chart::svg(figure, 960, 420).as_bytes(),
            )?;
        }
        Picture::stacked(&[
            &chart::draw(&move_shares, 960, 420),
            &chart::draw(&move_persistence, 960, 420),
        ])
        .save_png(&self.root.join("refine_moves.png"))?;
        let pictures: Vec<Picture> = (0..frames)
            .filter_map(|t| {
                Picture::open_png(&self.root.join("comparison").join(frame_file(t, "png")))
            })
            .collect();
        if !pictures.is_empty() {
            visuals::save_gif(&self.root.join("comparison.gif"), &pictures, 100)?;
            visuals::save_mp4(&self.root.join("comparison.mp4"), &pictures, 10)?;
        }
        self.write_slices(grid, frames)?;
        // Frame t of the run is time step t (the data set's frame first_frame + t).
        let grids: Vec<(f64, String)> = (0..frames)
            .map(|t| (t as f64, format!("grid_{t:03}.vti")))
            .filter(|(_, name)| self.exports_dir().join(name).is_file())
            .collect();
        if !grids.is_empty() {
            export::write_pvd(&self.exports_dir().join("grid.pvd"), &grids)?;
        }
        write_atomic(&self.root.join("README.txt"), RUN_README.as_bytes())
    }
}

/// The panels of a run's slices.
const RUN_SLICE_LABELS: [&str; 2] = ["density", "speed of the grid velocity"];

/// One camera's render of a frame, for the pictures of [`RunFolder::write_frame_outputs`].
pub struct ViewRender<'a> {
    pub name: &'a str,
    pub held_out: bool,
    pub width: u32,
    pub height: u32,
    /// `[H, W, 3]`.
    pub reference: &'a [f32],
    pub render: &'a [f32],
}

/// What the files of a run folder are (written into it).
const RUN_README: &str = include_str!("run_folder/README.txt");

#[cfg(test)]
mod tests;
