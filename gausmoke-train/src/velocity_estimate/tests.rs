use gausmoke_core::glam::Vec3;

use super::*;
use crate::run_folder::{FrameState, RunInfo};

fn device() -> Device {
    gausmoke_render::backends::device_by_name("flex").unwrap()
}

/// A run folder (beside the tiny synthetic scene, its data set) of `frames` frames whose
/// density is a smooth blob centred at `centre(t)` (world units), on a 16^3 grid over the
/// unit box.
fn blob_run(dir: &Path, centre: impl Fn(f32) -> Vec3, frames: usize) -> (RunFolder, TrainConfig) {
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
                    estimate_run_velocity(folder.root(), options, &device(), |_, _| {}).unwrap();
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
    // Exports as training leaves them, with an array the estimate does not write.
    let grid = config.grid(Vec3::ZERO, Vec3::ONE).unwrap();
    std::fs::create_dir_all(folder.exports_dir()).unwrap();
    for t in 1..3 {
        let state = folder.read_frame_state(t, &grid).unwrap().unwrap();
        let moves = vec![t as f32; state.velocity.len()];
        crate::export::write_npz(
            &folder.exports_dir().join(format!("grid_{t:03}.npz")),
            &grid,
            &state.density,
            &state.velocity,
            &[("refine_move", &moves)],
        )
        .unwrap();
    }
    let mut reported = Vec::new();
    let summary = estimate_run_velocity(run, &EstimateOptions::default(), &device(), |d, n| {
        reported.push((d, n))
    })
    .unwrap();
    assert_eq!(reported, [(1, 2), (2, 2)]);
    assert_eq!(summary.frames.len(), 2);
    // What a person looks at: frame 2 is the last (the default cadence writes all), the
    // charts span both frames, and the run's velocity (zero here) is slower than the blob.
    // The run's exports carry the estimate as their velocity, the grid velocity beside it,
    // and keep their other arrays.
    let dir = estimate_dir(run);
    for t in 1..3 {
        assert!(dir.join(format!("slices/frame_{t:03}.png")).is_file());
        let exports = folder.exports_dir();
        let vti = std::fs::read(exports.join(format!("grid_{t:03}.vti"))).unwrap();
        assert!(String::from_utf8_lossy(&vti).contains("Name=\"grid_velocity\""));
        let npz = crate::export::read_npz(&exports.join(format!("grid_{t:03}.npz")));
        let estimate = read_arrays(&estimate_path(run, t)).unwrap();
        assert_eq!(
            crate::export::floats(&npz["velocity"].1),
            estimate["velocity"].1
        );
        assert!(
            crate::export::floats(&npz["grid_velocity"].1)
                .iter()
                .all(|&v| v == 0.0)
        );
        assert_eq!(
            crate::export::floats(&npz["refine_move"].1),
            vec![t as f32; estimate["velocity"].1.len()],
        );
    }
    for file in ["slices.mp4", "speed.png", "misfit.png"] {
        assert!(dir.join(file).is_file(), "{file}");
    }
    let slice = crate::visuals::Picture::open_png(&dir.join("slices/frame_002.png")).unwrap();
    // Three 256-pixel panels (density and two speeds) with the margins and gaps between
    // them, and room above and below for the title, labels, colour bars and the note.
    assert!((768..860).contains(&slice.width) && slice.height > 256 + 60);
    for frame in &summary.frames {
        assert_eq!(frame.run_smoke_speed, 0.0);
        let speed = frame.smoke_speed / shift.length() as f64;
        assert!(
            (0.7..1.3).contains(&speed),
            "frame {}: {speed}",
            frame.frame
        );
    }
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
