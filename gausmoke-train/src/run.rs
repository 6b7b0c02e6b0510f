//! A training run: the [`Trainer`] frame by frame, each frame evaluated on the held-out views,
//! written to its [`RunFolder`] and checkpointed, so an interrupted run resumes where it
//! stopped.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Instant;

use burn::tensor::Device;
use gausmoke_core::phases::{self, PhaseTime, PhaseTotals};
use gausmoke_model::GridSpec;
use gausmoke_model::projection::{OpenFaces, SolidCells};

use crate::checkpoint::{self, CheckpointMeta};
use crate::run_folder::{FrameState, Metrics, RunFolder, RunInfo, ViewRender};
use crate::run_lock::{LOCK_FILE, RunLock};
use crate::sequence::{Observation, Sequence};
use crate::state::{FrameReport, LossRow, PhaseSeconds};
use crate::tensorboard::EventWriter;
use crate::trainer::{FrameOutcome, Trainer};
use crate::velocity_estimate::StoredEstimate;
use crate::{TrainConfig, TrainError, metrics};

mod resume;

/// Algorithm 1 over a whole sequence, with its outputs.
pub struct Run {
    pub trainer: Trainer,
    pub folder: RunFolder,
    /// The last complete frame, `None` before frame 0 is fitted.
    pub frame: Option<usize>,
    pub losses: Vec<LossRow>,
    pub reports: Vec<FrameReport>,
    elapsed_before: f64,
    session_start: Instant,
    /// Wall time per phase in this session, from the `PhaseLayer` of the current subscriber
    /// (empty without one).
    phase_times: Vec<PhaseTime>,
    /// Phase totals of earlier sessions of a resumed run.
    phases_before: BTreeMap<String, PhaseSeconds>,
    /// TensorBoard events (`output.tensorboard = true`), opened at the first frame of this session.
    events: Option<EventWriter>,
    /// Keeps a second process from training into the same folder.
    _lock: RunLock,
}

impl Run {
    /// Prepares a run in `out`. With `resume`, continues from the newest complete
    /// checkpoint there (the configuration must match the one it was trained with);
    /// without, refuses a folder that already holds a run, so no work is overwritten.
    pub fn new(
        sequence: Sequence,
        config: TrainConfig,
        device: Device,
        out: &Path,
        resume: bool,
    ) -> Result<Self, TrainError> {
        // run.json keeps the data set's resolved path as text, and resuming compares it: a
        // path that is not text is refused before the run folder is touched.
        let resolved = std::fs::canonicalize(&sequence.path).unwrap_or(sequence.path.clone());
        if resolved.to_str().is_none() {
            return Err(TrainError::Dataset {
                path: resolved,
                reason: "the path is not valid UTF-8, which the run's run.json cannot record; \
                         rename the folder"
                    .into(),
            });
        }
        let trainer = Trainer::new(sequence, config, device)?;
        let folder = RunFolder::at(out);
        let existing = checkpoint::complete(out)?;
        if !existing.is_empty() && !resume {
            return Err(TrainError::Config {
                origin: out.display().to_string(),
                reason: "this folder already holds a run; pass --resume to continue it or \
                         choose another --out"
                    .into(),
            });
        }
        if existing.is_empty() {
            refuse_foreign_folder(out)?;
        }
        folder.create()?;
        let lock = RunLock::acquire(out)?;
        checkpoint::remove_partials(out)?;
        if let Some(totals) = PhaseTotals::current() {
            let _ = totals.take();
            totals.set_sync(trainer.config.device.sync_phase_timings.then(|| {
                let device = trainer.device.clone();
                let hook: phases::SyncHook = std::sync::Arc::new(move || {
                    // A failed wait only blurs the phase boundaries; the work itself reports
                    // its own errors.
                    let _ = device.sync();
                });
                hook
            }));
        }
        let mut run = Self {
            trainer,
            folder,
            frame: None,
            losses: Vec::new(),
            reports: Vec::new(),
            elapsed_before: 0.0,
            session_start: Instant::now(),
            phase_times: Vec::new(),
            phases_before: BTreeMap::new(),
            events: None,
            _lock: lock,
        };
        let sequence = &run.trainer.sequence;
        let fingerprint = sequence.fingerprint();
        let data = resolved;
        if resume && !existing.is_empty() {
            run.restore(&existing, &data, &fingerprint)?;
            run.check_outputs_before_resume()?;
        }
        run.folder.write_config(&run.trainer.config)?;
        let grid = &run.trainer.grid;
        run.folder.write_run_info(&RunInfo {
            data,
            data_fingerprint: Some(fingerprint),
            frames: run.trainer.sequence.frames(),
            grid_resolution: grid.resolution(),
            box_lo: grid.lo().to_array(),
            box_hi: grid.hi().to_array(),
            device: format!("{:?}", run.trainer.device),
            version: env!("CARGO_PKG_VERSION").into(),
        })?;
        Ok(run)
    }

    /// Hides the progress bars (tests, notebooks).
    pub fn quiet(mut self, quiet: bool) -> Self {
        self.trainer = self.trainer.quiet(quiet);
        self
    }

    fn elapsed(&self) -> f64 {
        self.elapsed_before + self.session_start.elapsed().as_secs_f64()
    }

    /// Per-phase totals of all sessions: the checkpoint's and this session's.
    fn phase_seconds(&self) -> BTreeMap<String, PhaseSeconds> {
        let mut totals = self.phases_before.clone();
        for p in &self.phase_times {
            let entry = totals.entry(p.name.to_string()).or_insert(PhaseSeconds {
                calls: 0,
                seconds: 0.0,
            });
            entry.calls += p.calls;
            entry.seconds += p.seconds;
        }
        totals
    }

    /// Adds the phase times recorded since the last call.
    fn collect_phase_times(&mut self) {
        if let Some(totals) = PhaseTotals::current() {
            for time in totals.take() {
                phases::accumulate(&mut self.phase_times, time);
            }
        }
    }

    /// Trains every remaining frame, writes the summary outputs and returns the reports.
    pub fn run(&mut self) -> Result<&[FrameReport], TrainError> {
        let first = self.frame.map_or(0, |done| done + 1);
        for t in first..self.trainer.sequence.frames() {
            self.train_frame(t)?;
        }
        self.write_summary()?;
        // A finished run resumed trains nothing new: its estimate stands, if it was finished
        // (its summary is written last).
        let trained_now = first < self.trainer.sequence.frames();
        if trained_now || StoredEstimate::open(self.folder.root())?.is_none() {
            self.estimate_velocity()?;
        }
        Ok(&self.reports)
    }

    /// The last stage (`velocity_estimate`): the run's velocity read off its density grids,
    /// written to `RUN/velocity_estimate/` beside the grid's.
    fn estimate_velocity(&self) -> Result<(), TrainError> {
        use crate::config::VelocityEstimate;
        use crate::velocity_estimate::{EstimateOptions, estimate_run_velocity};
        let config = &self.trainer.config;
        if self.trainer.sequence.frames() < 2 {
            // A velocity carries one frame onto the next: one frame has none to estimate.
            return Ok(());
        }
        let options = match (config.velocity_estimate, config.scene.inflow) {
            (VelocityEstimate::None, _) => return Ok(()),
            (VelocityEstimate::Forces, Some(_)) => EstimateOptions::forced(),
            (VelocityEstimate::Forces, None) => {
                tracing::warn!(
                    "velocity_estimate = \"forces\" needs the scene's inflow (scene.inflow), \
                     which is unset: estimating without the smoke step"
                );
                EstimateOptions::default()
            }
            (VelocityEstimate::Density, _) => EstimateOptions::default(),
        };
        let bar = self.trainer.progress_bar(0);
        bar.set_prefix("velocity");
        let start = Instant::now();
        let summary = estimate_run_velocity(
            self.folder.root(),
            &options,
            &self.trainer.device,
            |done, total| {
                bar.set_length(total as u64);
                bar.set_position(done as u64);
            },
        )?;
        bar.finish_and_clear();
        tracing::info!(
            frames = summary.frames.len(),
            seconds = format!("{:.1}", start.elapsed().as_secs_f64()),
            start = summary.options.fits_start(),
            "velocity estimated from the density grids (RUN/velocity_estimate/)"
        );
        Ok(())
    }

    /// Trains frame `t` (the next one), evaluates it, writes its outputs and checkpoints it.
    pub fn train_frame(&mut self, t: usize) -> Result<&FrameReport, TrainError> {
        let start = Instant::now();
        let outcome = self.trainer.train_frame(t)?;
        if t == 0 {
            // Frame 0 may have settled the scene (see `crate::scene`).
            self.folder.write_config(&self.trainer.config)?;
        }
        // The optimisation's phase times so far; the evaluation and outputs below render too,
        // and their time goes to "outputs and evaluation" instead.
        self.collect_phase_times();
        let outputs_start = Instant::now();
        self.finish_frame(outcome, start)?;
        if let Some(totals) = PhaseTotals::current() {
            let _ = totals.take();
        }
        phases::accumulate(
            &mut self.phase_times,
            PhaseTime {
                name: "outputs and evaluation",
                seconds: outputs_start.elapsed().as_secs_f64(),
                calls: 1,
            },
        );
        Ok(self.reports.last().expect("a frame was just reported"))
    }

    /// Frame `t`'s metrics, its optimisation steps' losses (numbered after the steps before)
    /// and its comparison picture, when one was written, as TensorBoard events.
    fn log_events(
        &mut self,
        t: usize,
        losses: &[LossRow],
        report: &FrameReport,
    ) -> Result<(), TrainError> {
        if self.events.is_none() {
            self.events = Some(EventWriter::create(
                &self.folder.root().join("tensorboard"),
            )?);
        }
        let events = self.events.as_mut().expect("opened above");
        let first_step = self.losses.len();
        for (k, row) in losses.iter().enumerate() {
            events.scalars(
                (first_step + k) as i64,
                &[
                    ("loss/total", row.total as f64),
                    ("loss/render", row.render as f64),
                    ("loss/divergence", row.divergence as f64),
                    ("loss/advection", row.advection as f64),
                    ("loss/refine", row.refine as f64),
                ],
            )?;
        }
        events.scalars(
            t as i64,
            &[
                (
                    "frame/held_out_psnr_db",
                    report.test_psnr.unwrap_or(f64::NAN),
                ),
                ("frame/held_out_ssim", report.test_ssim.unwrap_or(f64::NAN)),
                ("frame/train_l1", report.train_l1),
                ("frame/mean_abs_divergence", report.mean_abs_divergence),
                ("frame/mean_speed", report.mean_speed),
                ("frame/max_speed", report.max_speed),
                ("frame/clamped_to_box", report.clamped_to_box as f64),
                ("frame/respawned", report.respawned as f64),
                ("frame/split", report.split as f64),
                ("frame/seconds", report.seconds),
            ],
        )?;
        let comparison = self
            .folder
            .root()
            .join("comparison")
            .join(format!("frame_{t:03}.png"));
        if let Some(picture) = crate::visuals::Picture::open_png(&comparison) {
            events.image(t as i64, "held_out/reference_vs_render", &picture)?;
        }
        events.flush()
    }

    /// Evaluates the frame `outcome` reports, writes its outputs and checkpoints it.
    fn finish_frame(&mut self, outcome: FrameOutcome, start: Instant) -> Result<(), TrainError> {
        let t = outcome.frame;
        let trainer = &self.trainer;
        let grid = trainer.grid;
        let state = FrameState {
            gaussians: trainer.state.gaussians.to_host(),
            statics: trainer
                .state
                .statics
                .as_ref()
                .map(|s| s.gaussians.to_host()),
            velocity: gausmoke_render::device_traffic::read_floats(trainer.state.velocity.clone()),
            density: trainer.density_host(),
        };
        let test = &trainer.sequence.test[t];
        let train = &trainer.sequence.train[t];
        let test_renders = trainer.render_host(test)?;
        let open = self.trainer.config.open_faces()?;
        let report = frame_report(
            &outcome,
            &state,
            test,
            &test_renders,
            (&grid, open, trainer.solid_cells()),
            start,
        );

        self.folder.write_frame_state(t, &grid, &state)?;
        let frames = trainer.sequence.frames();
        if t.is_multiple_of(trainer.config.output.every) || t + 1 == frames {
            let train_renders = trainer.render_host(train)?;
            let views: Vec<ViewRender> = train
                .iter()
                .zip(&train_renders)
                .map(|(o, r)| (o, r, false))
                .chain(test.iter().zip(&test_renders).map(|(o, r)| (o, r, true)))
                .map(|(observation, render, held_out)| ViewRender {
                    name: &observation.view,
                    held_out,
                    width: observation.image.width(),
                    height: observation.image.height(),
                    reference: observation.image.data(),
                    render,
                })
                .collect();
            self.folder.write_frame_outputs(
                t,
                &grid,
                &state,
                &views,
                self.trainer.config.output.ply_axes,
                outcome.refine_move_field.as_ref(),
            )?;
        }

        tracing::info!(
            frame = t,
            train_l1 = format!("{:.5}", report.train_l1),
            test_psnr = format!("{:.2}", report.test_psnr.unwrap_or(f64::NAN)),
            test_ssim = format!("{:.4}", report.test_ssim.unwrap_or(f64::NAN)),
            mean_abs_div = format!("{:.3e}", report.mean_abs_divergence),
            seconds = format!("{:.1}", report.seconds),
            eta_seconds = format!("{:.0}", report.seconds * (frames - 1 - t) as f64),
            "frame done"
        );
        if self.trainer.config.output.tensorboard {
            self.log_events(t, &outcome.losses, &report)?;
        }
        self.losses.extend(outcome.losses);
        self.reports.push(report);
        self.frame = Some(t);
        let meta = CheckpointMeta {
            frame: t,
            config: self.trainer.config.clone(),
            losses: self.losses.clone(),
            reports: self.reports.clone(),
            elapsed_seconds: self.elapsed(),
            phase_seconds: self.phase_seconds(),
            checksums: Default::default(),
            run_frames: Some(self.trainer.sequence.frames()),
            data_fingerprint: Some(self.trainer.sequence.fingerprint()),
            state_checksum: None,
        };
        checkpoint::save(
            self.folder.root(),
            &self.trainer.state,
            &self.trainer.checkpoint_extras(),
            &meta,
        )?;
        self.folder.write_losses(&self.losses)
    }

    /// Loss and speed plots, the comparison GIF, `losses.csv` and `metrics.json`.
    pub fn write_summary(&self) -> Result<(), TrainError> {
        self.folder.write_losses(&self.losses)?;
        self.folder.write_summary_pictures(
            &self.trainer.grid,
            &self.losses,
            &self.reports,
            self.trainer.sequence.frames(),
        )?;
        let mean = |f: fn(&FrameReport) -> Option<f64>| {
            let values: Vec<f64> = self
                .reports
                .iter()
                .filter_map(f)
                .filter(|v| v.is_finite())
                .collect();
            (!values.is_empty()).then(|| values.iter().sum::<f64>() / values.len() as f64)
        };
        self.folder.write_metrics(&Metrics {
            frames: self.reports.len(),
            gaussians: self.trainer.state.gaussians.len(),
            grid_resolution: self.trainer.grid.resolution(),
            test_l1_mean: mean(|r| r.test_l1),
            test_psnr_mean: mean(|r| r.test_psnr),
            test_ssim_mean: mean(|r| r.test_ssim),
            mean_abs_divergence: mean(|r| Some(r.mean_abs_divergence)),
            train_l1_mean: mean(|r| Some(r.train_l1)),
            training_seconds: self.elapsed(),
            device: format!("{:?}", self.trainer.device),
            phase_seconds: self.phase_seconds(),
            per_frame: self.reports.clone(),
        })
    }
}

/// What frame `outcome` achieved: the held-out views' errors against their renders
/// `test_renders`, the velocity's divergence and speed, and the outcome's own figures.
fn frame_report(
    outcome: &FrameOutcome,
    state: &FrameState,
    test: &[Observation],
    test_renders: &[Vec<f32>],
    (grid, open, solids): (&GridSpec, OpenFaces, Option<&SolidCells>),
    start: Instant,
) -> FrameReport {
    let (mut l1, mut psnr, mut ssim) = (0.0, 0.0, 0.0);
    for (observation, render) in test.iter().zip(test_renders) {
        let (w, h) = (
            observation.image.width() as usize,
            observation.image.height() as usize,
        );
        l1 += metrics::mean_abs_error(render, observation.image.data());
        psnr += metrics::psnr(render, observation.image.data());
        ssim += metrics::ssim(render, observation.image.data(), w, h);
    }
    let tests = test.len() as f64;
    let speeds: Vec<f64> = state
        .velocity
        .chunks(3)
        .map(|v| ((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) as f64).sqrt())
        .collect();
    let projection = outcome.projection.unwrap_or_default();
    FrameReport {
        frame: outcome.frame,
        train_l1: outcome.train_l1,
        test_l1: (tests > 0.0).then_some(l1 / tests),
        test_psnr: (tests > 0.0).then_some(psnr / tests),
        test_ssim: (tests > 0.0).then_some(ssim / tests),
        mean_abs_divergence: metrics::mean_abs_divergence(grid, open, solids, &state.velocity),
        projection_iterations: projection.iterations,
        projection_residual: projection.relative_residual,
        divergence_rms_before: projection.divergence_rms_before,
        divergence_rms_after: projection.divergence_rms_after,
        clamped_to_box: outcome.clamped_to_box,
        respawned: outcome.respawned,
        split: outcome.split,
        refine_move_cells: outcome.refine_moves.map(|m| m.rms_cells),
        refine_move_grid_share: outcome.refine_moves.map(|m| m.grid_share),
        refine_move_grid_share_shuffled: outcome.refine_moves.map(|m| m.shuffled_grid_share),
        refine_move_persistence: outcome
            .refine_moves
            .and_then(|m| m.persistence)
            .map(|[whole, _]| whole),
        refine_move_flow_share: outcome.refine_moves.map(|m| m.flow_share),
        refine_move_flow_persistence: outcome
            .refine_moves
            .and_then(|m| m.field_persistence)
            .map(|[flow, _]| flow),
        refine_move_gathering_persistence: outcome
            .refine_moves
            .and_then(|m| m.field_persistence)
            .map(|[_, gathering]| gathering),
        refine_move_grid_persistence: outcome
            .refine_moves
            .and_then(|m| m.persistence)
            .map(|[_, grid]| grid),
        mean_speed: speeds.iter().sum::<f64>() / speeds.len().max(1) as f64,
        max_speed: speeds.iter().cloned().fold(0.0, f64::max),
        seconds: start.elapsed().as_secs_f64(),
        device_traffic: outcome.traffic.clone(),
    }
}

/// Refuses an `--out` folder that holds files but no run of ours (no `run.json`), so that
/// training never writes over someone's data.
fn refuse_foreign_folder(out: &Path) -> Result<(), TrainError> {
    let Ok(entries) = std::fs::read_dir(out) else {
        return Ok(()); // absent: created below; unreadable: creating it reports why
    };
    let names: Vec<String> = entries
        .filter_map(Result::ok)
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|name| name != LOCK_FILE)
        .collect();
    if names.is_empty() || out.join("run.json").is_file() {
        return Ok(());
    }
    let mut shown: Vec<&str> = names.iter().map(String::as_str).collect();
    shown.sort_unstable();
    shown.truncate(3);
    Err(TrainError::Config {
        origin: out.display().to_string(),
        reason: format!(
            "this folder is not empty and holds no GauSmoke run (it has {}{}); choose an empty \
             or new --out",
            shown.join(", "),
            if names.len() > 3 { ", ..." } else { "" }
        ),
    })
}
