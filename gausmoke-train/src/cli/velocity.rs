//! `velocity`: a run's velocity estimated from its density grids.

use super::*;

/// `velocity --run DIR`: the velocity estimated from a run's density grids.
pub(super) fn estimate_velocity(
    run: &Path,
    options: &EstimateOptions,
    device: &burn::tensor::Device,
    quiet: bool,
) -> Result<()> {
    use gausmoke_train::velocity_estimate::{estimate_dir, estimate_run_velocity};
    let bar = if quiet {
        indicatif::ProgressBar::hidden()
    } else {
        indicatif::ProgressBar::new(0)
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template("[{bar:40}] {pos}/{len} frames, eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    let start = Instant::now();
    let summary = estimate_run_velocity(run, options, device, |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    let kept = summary.frames.iter().filter(|f| f.kept_start).count();
    let mean = |f: fn(&gausmoke_train::velocity_estimate::FrameEstimate) -> f64| {
        summary.frames.iter().map(f).sum::<f64>() / summary.frames.len() as f64
    };
    let start_name = summary.options.fits_start();
    println!(
        "{} frames in {:.1} s; misfit (relative to no motion) {:.3} {start_name}, {:.3} fitted; \
         {kept} frame(s) kept the {start_name} start",
        summary.frames.len(),
        start.elapsed().as_secs_f64(),
        mean(|f| f.misfit_prior),
        mean(|f| f.misfit_fitted),
    );
    if let Some(chosen) = &summary.forces {
        println!(
            "smoke step: inflow {} cells a frame, buoyancy {:.4} cells a frame per frame at the \
             source's density ({} source cells, density {:.3}); chosen over frames 1-{} in \
             {:.1} s, step misfit {:.3}",
            chosen.forces.inflow,
            chosen.forces.buoyancy,
            chosen.source_cells,
            chosen.density_unit,
            chosen.fit_frames,
            chosen.seconds,
            chosen.misfit,
        );
        if chosen.scarcely_explains() {
            eprintln!(
                "warning: even the chosen smoke step carries the run's density scarcely better \
                 than no motion (misfit {:.2} of no motion's): the run's density does not move \
                 as a plume from that source would (is the source box right? is the run's \
                 density close to the smoke's?), and the estimate without --forces may be \
                 truer",
                chosen.misfit
            );
        }
    }
    let unconverged: Vec<_> = summary
        .frames
        .iter()
        .filter(|f| f.stopped_short())
        .collect();
    if let Some(worst) = unconverged
        .iter()
        .max_by(|a, b| a.solver_residual.total_cmp(&b.solver_residual))
    {
        eprintln!(
            "warning: the fit's linear solves stopped short of convergence in {} frame(s) \
             (worst: frame {}, residual {:.1e} of its start): those frames are not the fit's \
             minimum",
            unconverged.len(),
            worst.frame,
            worst.solver_residual
        );
    }
    if let Some(readings) = summary.lift_against_data() {
        let (kept, other, flag) = if summary.options.sinking {
            ("downward", "upward", "without --sinking")
        } else {
            ("upward", "downward", "with --sinking")
        };
        eprintln!(
            "warning: the lift is read {kept} only, but the fits accelerated the smoke mostly \
             {other} (their coefficients summed {:.3} {other} against {:.3} {kept}): if the \
             smoke moves {other}, run it again {flag}",
            readings.against, readings.along
        );
    }
    println!(
        "wrote {}; `gausmoke-train eval --run {}` scores it",
        estimate_dir(run).display(),
        run.display()
    );
    Ok(())
}
