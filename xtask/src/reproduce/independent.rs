//! The independent per-frame baseline: each sampled frame fitted alone, with the settings of
//! the sequential run's frame-0 fit, scored on the same held-out views. The physics is meant
//! to make the sequential reconstruction of frame t better than what frame t's views give on
//! their own; this is the yardstick for that claim.

use std::path::Path;

use anyhow::{Context, Result, bail};
use burn::tensor::Device;
use gausmoke_train::{Run, TrainConfig, eval, sequence::Sequence};
use serde::Serialize;

/// One sampled frame: the fit of that frame alone beside the sequential run's result there.
#[derive(Debug, Clone, Serialize)]
pub struct IndependentFrame {
    /// The frame within the sequential run (0 = its first frame).
    pub frame: usize,
    pub test_psnr: Option<f64>,
    pub test_ssim: Option<f64>,
    pub density_relative_error: Option<f64>,
    pub density_correlation: Option<f64>,
    pub sequential_test_psnr: Option<f64>,
    pub sequential_density_relative_error: Option<f64>,
    pub sequential_density_correlation: Option<f64>,
    /// Sequential minus independent held-out PSNR (dB): positive where the physics helps.
    pub sequential_minus_independent_psnr: Option<f64>,
    pub training_seconds: f64,
}

/// Refuses sampled frames the sequential run does not have, before anything trains.
pub fn check_frames(frames: &[usize], run_frames: usize) -> Result<()> {
    if let Some(&t) = frames.iter().find(|&&t| t >= run_frames) {
        bail!(
            "--independent {t}: the run has {run_frames} frames (0 to {})",
            run_frames - 1
        );
    }
    Ok(())
}

/// What the baseline fits: the sampled frames and where and how to fit them.
pub struct Baseline<'a> {
    pub frames: &'a [usize],
    pub data: &'a Path,
    pub device: &'a Device,
    pub resume: bool,
    pub lpips_weights: Option<&'a Path>,
}

impl Baseline<'_> {
    /// Fits each sampled frame alone into `<out>/frame_TTT` (`first_frame` moved to it,
    /// `frames = 1`, so only the frame-0 fit runs) and compares it with the sequential run's
    /// evaluation.
    pub fn fit(
        &self,
        config: &TrainConfig,
        sequential: &eval::EvalReport,
        out: &Path,
    ) -> Result<Vec<IndependentFrame>> {
        let Baseline {
            frames,
            data,
            device,
            resume,
            lpips_weights,
        } = *self;
        let mut rows = Vec::with_capacity(frames.len());
        for &t in frames {
            let config = TrainConfig {
                first_frame: config.first_frame + t,
                frames: Some(1),
                ..config.clone()
            };
            let dir = out.join(format!("frame_{t:03}"));
            eprintln!("   frame {t} alone -> {}", dir.display());
            let scene = Sequence::open(data, &config)
                .with_context(|| format!("loading frame {t} of {}", data.display()))?;
            let mut run = Run::new(scene, config, device.clone().autodiff(), &dir, resume)?;
            run.run()?;
            let training_seconds = run.reports.iter().map(|r| r.seconds).sum();
            drop(run);
            let alone = eval::evaluate(&dir, device, lpips_weights)?;
            let alone = alone
                .frames
                .first()
                .with_context(|| format!("{}: no frame evaluated", dir.display()))?;
            let there = sequential.frames.iter().find(|f| f.frame == t);
            let sequential_test_psnr = there.and_then(|f| f.test_psnr);
            rows.push(IndependentFrame {
                frame: t,
                test_psnr: alone.test_psnr,
                test_ssim: alone.test_ssim,
                density_relative_error: alone.density_relative_error,
                density_correlation: alone.density_correlation,
                sequential_test_psnr,
                sequential_density_relative_error: there.and_then(|f| f.density_relative_error),
                sequential_density_correlation: there.and_then(|f| f.density_correlation),
                sequential_minus_independent_psnr: sequential_test_psnr
                    .zip(alone.test_psnr)
                    .map(|(s, i)| s - i),
                training_seconds,
            });
        }
        Ok(rows)
    }
}
