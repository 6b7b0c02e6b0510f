//! The device projection (cubecl PCG in f32, `projection_kernel.rs`; wgpu, in CI on Mesa's
//! lavapipe) against the host solver (the same PCG in f64): converged solutions, the same
//! truncated iterations, the backward pass, and a grid with no divergence to remove.
//!
//! Like the other GPU tests these FAIL without a GPU adapter rather than skip.
//!
//! Tolerances (measured on lavapipe, 2026-11-23, `GAUSMOKE_PRINT_ERRORS=1`): converged
//! solutions and gradients differ from the f64 solve by 3e-6 of the largest value (bound
//! 2e-5 of the largest input); the 5-iteration solve by 4e-7 (bound 1e-5).

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_model::projection::Divergence;
use gausmoke_model::{GridSpec, ProjectionOptions, project_velocity, project_with_report};
use gausmoke_render::backends::gpu_devices;
use gausmoke_tests::{assert_close, to_vec};

/// Non-cubic, with unequal cell sizes per axis: a wrong stride, axis or cell size in the
/// kernels fails here.
fn grid() -> GridSpec {
    GridSpec::new(
        Vec3::new(-1.0, -0.5, 0.0),
        Vec3::new(1.0, 1.3, 0.7),
        [18, 13, 11],
        1,
    )
    .unwrap()
}

/// A smooth divergent field (a source and a sink) plus noise, `[nx, ny, nz, 3]` flat.
fn velocity(grid: &GridSpec, seed: u64) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed);
    let centres = grid.cell_centres();
    centres
        .chunks(3)
        .flat_map(|c| {
            let p = Vec3::from_slice(c);
            let source = (p - Vec3::new(-0.3, 0.2, 0.3)) * (-(p.length_squared()) * 2.0).exp();
            let sink = (Vec3::new(0.4, 0.6, 0.4) - p) * 0.5;
            let v = source + sink;
            [v.x, v.y, v.z]
        })
        .map(|v| v + 0.2 * (rng.uniform() - 0.5))
        .collect()
}

fn device() -> (&'static str, Device) {
    let mut devices = gpu_devices();
    assert!(
        !devices.is_empty(),
        "this test binary must be built with a GPU feature of gausmoke-model"
    );
    devices.remove(0)
}

fn tensor(values: &[f32], grid: &GridSpec, device: &Device) -> Tensor<4> {
    let [nx, ny, nz] = grid.resolution();
    Tensor::from_data(TensorData::new(values.to_vec(), [nx, ny, nz, 3]), device)
}

fn host_projection(values: &[f32], grid: &GridSpec, options: &ProjectionOptions) -> Vec<f32> {
    let mut projected = values.to_vec();
    project_with_report(grid, &mut projected, options);
    projected
}

fn device_projection(
    values: &[f32],
    grid: &GridSpec,
    device: &Device,
    options: ProjectionOptions,
) -> Vec<f32> {
    to_vec(project_velocity(
        grid,
        tensor(values, grid, device),
        options,
    ))
}

/// RMS of the discrete divergence of a velocity grid (host, f64).
fn divergence_rms(values: &[f32], grid: &GridSpec) -> f64 {
    let divergence = Divergence::on_grid(grid).of_velocity(values);
    (divergence.iter().map(|d| d * d).sum::<f64>() / divergence.len() as f64).sqrt()
}

fn max_abs(values: &[f32]) -> f32 {
    values.iter().fold(0.0f32, |m, v| m.max(v.abs()))
}

#[test]
fn device_projection_matches_the_host_solver() {
    let grid = grid();
    let (backend, device) = device();
    let options = ProjectionOptions::default();
    let input = velocity(&grid, 3);
    let expected = host_projection(&input, &grid, &options);
    let actual = device_projection(&input, &grid, &device, options);
    let scale = max_abs(&input);
    assert_close(
        &format!("projected velocity on {backend}"),
        &actual,
        &expected,
        2e-5 * scale,
        0.0,
    );
    let before = divergence_rms(&input, &grid);
    let after = divergence_rms(&actual, &grid);
    assert!(
        before > 0.1,
        "the test field must be divergent (rms {before})"
    );
    assert!(
        after < 1e-4 * before,
        "device projection left divergence rms {after} of {before}"
    );
}

/// Five iterations, far from converged: the device runs the host's recurrence step for step.
#[test]
fn truncated_device_solve_follows_the_host_iterations() {
    let grid = grid();
    let (backend, device) = device();
    let options = ProjectionOptions {
        rel_tolerance: 0.0,
        max_iterations: 5,
        ..Default::default()
    };
    let input = velocity(&grid, 5);
    let expected = host_projection(&input, &grid, &options);
    let converged = host_projection(&input, &grid, &ProjectionOptions::default());
    let actual = device_projection(&input, &grid, &device, options);
    let scale = max_abs(&input);
    let distance = expected
        .iter()
        .zip(&converged)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(
        distance > 1e-2 * scale,
        "five iterations must be measurably short of convergence for this test to mean anything"
    );
    assert_close(
        &format!("5-iteration projection on {backend}"),
        &actual,
        &expected,
        1e-5 * scale,
        0.0,
    );
}

/// The backward pass is the projection of the incoming gradient (`Pi` is self-adjoint).
#[test]
fn device_projection_backward_projects_the_gradient() {
    let grid = grid();
    let (backend, device) = device();
    let options = ProjectionOptions::default();
    let input = velocity(&grid, 7);
    let mut rng = SplitMix64::new(13);
    let weight: Vec<f32> = (0..input.len())
        .map(|_| rng.uniform() * 2.0 - 1.0)
        .collect();
    let ad = device.autodiff();
    let u = tensor(&input, &grid, &ad).require_grad();
    let loss = (project_velocity(&grid, u.clone(), options) * tensor(&weight, &grid, &ad)).sum();
    let grads = loss.backward();
    let actual = to_vec(u.grad(&grads).expect("the velocity takes a gradient"));
    let expected = host_projection(&weight, &grid, &options);
    assert_close(
        &format!("gradient through the projection on {backend}"),
        &actual,
        &expected,
        2e-5 * max_abs(&weight),
        0.0,
    );
}

/// A divergence-free input comes back unchanged (no NaN from a zero right-hand side, no
/// garbage from chasing f32 round-off), and a small divergent change to it is still removed.
#[test]
fn device_projection_leaves_a_divergence_free_field() {
    let grid = grid();
    let (backend, device) = device();
    let options = ProjectionOptions::default();
    let zero = vec![0.0f32; 3 * grid.num_cells()];
    let actual = device_projection(&zero, &grid, &device, options);
    assert_close(&format!("Pi(0) on {backend}"), &actual, &zero, 0.0, 0.0);
    // A projected field is a fixed point (to the solver's tolerance).
    let projected = host_projection(&velocity(&grid, 9), &grid, &options);
    let again = device_projection(&projected, &grid, &device, options);
    assert_close(
        &format!("Pi(Pi(u)) on {backend}"),
        &again,
        &projected,
        1e-5 * max_abs(&projected),
        0.0,
    );
    // A small divergent change to a projected field (the trainer's case: Phi's update to last
    // frame's velocity) is still projected, not taken for round-off.
    let perturbation = velocity(&grid, 11);
    let nudged: Vec<f32> = projected
        .iter()
        .zip(&perturbation)
        .map(|(u, w)| u + 1e-3 * w)
        .collect();
    let expected = host_projection(&nudged, &grid, &options);
    let actual = device_projection(&nudged, &grid, &device, options);
    assert!(divergence_rms(&nudged, &grid) > 1e-4);
    assert!(divergence_rms(&actual, &grid) < 1e-2 * divergence_rms(&nudged, &grid));
    assert_close(
        &format!("Pi(Pi(u) + 1e-3 w) on {backend}"),
        &actual,
        &expected,
        1e-5 * max_abs(&expected),
        0.0,
    );
}

/// Open faces on the device: converged and truncated solves match the host twin step for step.
#[test]
fn device_projection_with_open_faces_matches_the_host() {
    use gausmoke_model::projection::OpenFaces;
    let grid = grid();
    let (backend, device) = device();
    let open_faces = OpenFaces::from_names(&["x-", "y+", "z+"]).unwrap();
    let input = velocity(&grid, 11);
    let scale = max_abs(&input);
    for (max_iterations, rel_tolerance, tolerance) in [(5, 0.0, 1e-5), (400, 1e-6, 2e-5)] {
        let options = ProjectionOptions {
            rel_tolerance,
            max_iterations,
            open_faces,
            ..Default::default()
        };
        let expected = host_projection(&input, &grid, &options);
        let actual = device_projection(&input, &grid, &device, options);
        assert_close(
            &format!("{max_iterations}-iteration projection, open faces, on {backend}"),
            &actual,
            &expected,
            tolerance * scale,
            0.0,
        );
    }
}
