//! The fused Gaussian-kernel interpolation op (closed-form backward) against the same
//! interpolation composed of burn tensor ops (differentiated by autodiff), on every CPU
//! backend: velocity, Jacobian, and the gradients with respect to the grid and the points,
//! with points inside the box, near its faces and outside it.
//!
//! Measured (2026-11-23, `GAUSMOKE_PRINT_ERRORS=1 ... -- --nocapture`): velocity, Jacobian and
//! grid gradient within 2e-6, point gradient within 5e-6 of each tensor's largest magnitude
//! (points outside the box amplify rounding); bound 2e-5.
#![allow(clippy::disallowed_methods)] // tests read tensors freely; the library counts its reads

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_model::interp::composed;
use gausmoke_model::{GridSpec, Interpolation, sample_velocity};
use gausmoke_render::backends::cpu_devices;

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

fn close(what: &str, fused: &[f32], reference: &[f32]) {
    let scale = reference.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let worst = fused
        .iter()
        .zip(reference)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    if std::env::var_os("GAUSMOKE_PRINT_ERRORS").is_some() {
        eprintln!("{what}: max |diff| {worst:.2e} of {scale:.2e}");
    }
    assert!(scale > 0.0, "{what}: vacuous");
    assert!(worst <= 2e-5 * scale, "{what}: {worst} vs scale {scale}");
}

/// Velocity, Jacobian, and the gradients of `sum(u w_u) + sum(J w_j)`.
fn run(fused: bool, device: &Device) -> [Vec<f32>; 4] {
    let grid = GridSpec::new(
        Vec3::new(-1.0, 0.0, -0.5),
        Vec3::new(1.0, 1.5, 0.7),
        [12, 16, 8],
        4,
    )
    .unwrap();
    let mut rng = SplitMix64::new(5);
    let cells = grid.num_cells();
    let field: Vec<f32> = (0..3 * cells).map(|_| rng.range(-1.0, 1.0)).collect();
    // Inside, near the faces and outside the box.
    let m = 300;
    let points: Vec<f32> = (0..m)
        .flat_map(|_| {
            [
                rng.range(-1.2, 1.2),
                rng.range(-0.2, 1.7),
                rng.range(-0.7, 0.9),
            ]
        })
        .collect();
    let weights: Vec<f32> = (0..12 * m).map(|_| rng.range(-1.0, 1.0)).collect();
    let velocity =
        Tensor::<4>::from_data(TensorData::new(field, [12, 16, 8, 3]), device).require_grad();
    let points = Tensor::<2>::from_data(TensorData::new(points, [m, 3]), device).require_grad();
    let kind = Interpolation::default();
    let sample = if fused {
        sample_velocity(&grid, &velocity, &points, kind)
    } else {
        composed::sample(&grid, &velocity, &points, kind)
    };
    let w = |offset: usize, columns: usize| -> Vec<f32> {
        weights
            .chunks(12)
            .flat_map(|row| row[offset..offset + columns].to_vec())
            .collect()
    };
    let w_u = Tensor::<2>::from_data(TensorData::new(w(0, 3), [m, 3]), device);
    let w_j = Tensor::<3>::from_data(TensorData::new(w(3, 9), [m, 3, 3]), device);
    let loss = (sample.velocity.clone() * w_u).sum() + (sample.jacobian.clone() * w_j).sum();
    let grads = loss.backward();
    [
        host(sample.velocity),
        host(sample.jacobian),
        host(velocity.grad(&grads).unwrap()),
        host(points.grad(&grads).unwrap()),
    ]
}

#[test]
fn fused_op_matches_the_composed_interpolation() {
    for (backend, device) in cpu_devices() {
        let device = device.autodiff();
        let fused = run(true, &device);
        let reference = run(false, &device);
        for (name, (a, b)) in ["velocity", "jacobian", "grad velocity", "grad points"]
            .iter()
            .zip(fused.iter().zip(&reference))
        {
            close(&format!("{backend}: {name}"), a, b);
        }
    }
}
