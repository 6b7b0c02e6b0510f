use super::*;

/// A frame file with a non-finite value is refused by name, wherever it sits; frames
/// after a gap are not counted as finished.
#[test]
fn a_frame_file_with_a_non_finite_value_or_after_a_gap_is_not_read() {
    let dir = tempfile::tempdir().unwrap();
    let folder = RunFolder::at(dir.path());
    folder.create().unwrap();
    let grid = TrainConfig {
        grid_resolution: 4,
        ..TrainConfig::default()
    }
    .grid([0.0; 3].into(), [1.0; 3].into())
    .unwrap();
    let cells = grid.num_cells();
    let gaussians = HostGaussians {
        means: vec![0.5; 6],
        rotations: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        log_scales: vec![-3.0; 6],
        raw_densities: vec![0.0; 2],
        colors: vec![0.8; 6],
    };
    let state = FrameState {
        gaussians,
        statics: None,
        velocity: vec![0.1; 3 * cells],
        density: vec![0.2; cells],
    };
    folder.write_frame_state(0, &grid, &state).unwrap();
    assert!(folder.read_frame_state(0, &grid).unwrap().is_some());
    // A gap: frames 0 and 2 written, 1 missing, so only frame 0 counts as finished.
    folder.write_frame_state(2, &grid, &state).unwrap();
    assert_eq!(folder.finished_frames(), 1);
    let error = folder.require_whole().unwrap_err().to_string();
    assert!(
        error.contains("frame_001.safetensors") && error.contains("up to frame 2"),
        "{error}"
    );
    std::fs::remove_file(folder.frame_state_path(2)).unwrap();
    let spoilt = |name: &str, value: f32| {
        let mut bad = FrameState {
            gaussians: state.gaussians.clone(),
            statics: None,
            velocity: state.velocity.clone(),
            density: state.density.clone(),
        };
        match name {
            "density" => bad.density[5] = value,
            "velocity" => bad.velocity[7] = value,
            _ => bad.gaussians.means[1] = value,
        }
        folder.write_frame_state(1, &grid, &bad).unwrap();
        folder.read_frame_state(1, &grid).unwrap_err().to_string()
    };
    for (name, value, index) in [
        ("density", f32::NAN, 5),
        ("velocity", f32::INFINITY, 7),
        ("means", f32::NEG_INFINITY, 1),
    ] {
        let error = spoilt(name, value);
        assert!(
            error.contains(&format!("`{name}`"))
                && error.contains(&format!("index {index}"))
                && error.contains("frame_001"),
            "{error}"
        );
    }
}
