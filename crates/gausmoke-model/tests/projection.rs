//! The exact Helmholtz projection: divergence removed, idempotent, gradient fields vanish,
//! wall-tangent divergence-free fields stay, self-adjoint backward.

use burn::tensor::{Tensor, TensorData};
use gausmoke_core::glam::Vec3;
use gausmoke_model::projection::Divergence;
use gausmoke_model::{
    GridSpec, ProjectionOptions, grid_from_fn, project_velocity, project_with_report,
};
use gausmoke_render::backends::cpu_devices;
use gausmoke_render::scenes::SplitMix64;

fn grid(n: [usize; 3]) -> GridSpec {
    GridSpec::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 1.2, 0.8), n, 2).unwrap()
}

fn random_field(cells: usize, seed: u64) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed);
    (0..3 * cells).map(|_| rng.range(-1.0, 1.0)).collect()
}

fn divergence_rms(g: &GridSpec, u: &[f32]) -> f64 {
    let c = g.cell_size();
    let op = Divergence {
        resolution: g.resolution(),
        cell: [c.x as f64, c.y as f64, c.z as f64],
    };
    let u64: Vec<f64> = u.iter().map(|&v| v as f64).collect();
    let mut d = vec![0.0; g.num_cells()];
    op.apply(&u64, &mut d);
    (d.iter().map(|v| v * v).sum::<f64>() / d.len() as f64).sqrt()
}

#[test]
fn projection_removes_divergence_and_is_idempotent() {
    let g = grid([20, 24, 16]);
    let mut u = random_field(g.num_cells(), 1);
    let options = ProjectionOptions::default();
    let report = project_with_report(&g, &mut u, &options);
    eprintln!("{report:?}");
    assert!(
        report.relative_residual <= options.rel_tolerance,
        "{report:?}"
    );
    assert!(
        report.divergence_rms_after < 1e-5 * report.divergence_rms_before,
        "{report:?}"
    );
    assert!(divergence_rms(&g, &u) < 1e-5 * report.divergence_rms_before);
    let once = u.clone();
    let again = project_with_report(&g, &mut u, &options);
    // What is left is the f32 rounding of the stored field.
    assert!(
        again.divergence_rms_before < 1e-5 * report.divergence_rms_before,
        "{again:?}"
    );
    let change = once
        .iter()
        .zip(&u)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(change < 1e-5, "Pi(Pi(u)) = Pi(u): max change {change}");
}

#[test]
fn gradient_fields_project_to_zero_and_solenoidal_fields_stay() {
    let device = cpu_devices()[0].1.clone();
    let g = grid([24, 24, 24]);
    let options = ProjectionOptions {
        rel_tolerance: 1e-8,
        ..Default::default()
    };
    // A discrete gradient D^T phi is in the range of D^T, so Pi removes it exactly.
    let c = g.cell_size();
    let op = Divergence {
        resolution: g.resolution(),
        cell: [c.x as f64, c.y as f64, c.z as f64],
    };
    let centres = g.cell_centres();
    let phi: Vec<f64> = centres
        .chunks(3)
        .map(|p| ((3.0 * p[0]).sin() * (2.0 * p[1]).cos() + p[2] * p[2]) as f64)
        .collect();
    let mut grad = vec![0.0; 3 * g.num_cells()];
    op.apply_transpose(&phi, &mut grad);
    let mut u: Vec<f32> = grad.iter().map(|&v| v as f32).collect();
    let size = u.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    project_with_report(&g, &mut u, &options);
    let left = u.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    assert!(
        left < 1e-4 * size,
        "gradient field leaves {left} (of {size})"
    );

    // A smooth field that is divergence-free and tangent to the walls changes only by the
    // O(h^2) discretisation error of the central differences.
    let pi = std::f32::consts::PI;
    let (lx, ly) = (1.0, 1.2);
    // From the stream function psi = sin(pi x / lx) sin(pi y / ly): u = dpsi/dy, v = -dpsi/dx.
    let field = |x: [f32; 3]| {
        let (a, b) = (pi * x[0] / lx, pi * x[1] / ly);
        [
            pi / ly * a.sin() * b.cos(),
            -pi / lx * a.cos() * b.sin(),
            0.0,
        ]
    };
    let u = grid_from_fn(&g, &device, field);
    let before = u.clone().into_data().try_into_vec_as::<f32>().unwrap();
    let after = project_velocity(&g, u, options)
        .into_data()
        .try_into_vec_as::<f32>()
        .unwrap();
    let change = before
        .iter()
        .zip(&after)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    let size = before.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    // Central differences over 2h: relative truncation error ~ (pi h / l)^2 / 6 per derivative.
    let h = 1.2 / 24.0;
    let bound = (pi * h).powi(2);
    eprintln!("solenoidal field: max change {change:.2e} of max |u| {size:.2}, bound {bound:.2e}");
    assert!(
        change < bound * size,
        "solenoidal field changed by {change}"
    );
}

#[test]
fn backward_is_the_projection_of_the_gradient() {
    for (_, device) in cpu_devices() {
        let ad = device.autodiff();
        let g = grid([8, 10, 6]);
        let cells = g.num_cells();
        let options = ProjectionOptions {
            rel_tolerance: 1e-9,
            ..Default::default()
        };
        let u = Tensor::<4>::from_data(TensorData::new(random_field(cells, 2), [8, 10, 6, 3]), &ad)
            .require_grad();
        let weights_host = random_field(cells, 3);
        let weights =
            Tensor::<4>::from_data(TensorData::new(weights_host.clone(), [8, 10, 6, 3]), &ad);
        let loss = (project_velocity(&g, u.clone(), options) * weights).sum();
        let grads = loss.backward();
        let got = u
            .grad(&grads)
            .unwrap()
            .into_data()
            .try_into_vec_as::<f32>()
            .unwrap();
        // d/du <w, Pi u> = Pi^T w = Pi w.
        let mut expected = weights_host;
        project_with_report(&g, &mut expected, &options);
        let err = got
            .iter()
            .zip(&expected)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(err < 1e-5, "gradient differs from Pi(w) by {err}");
        // And it is not the identity (the test would be vacuous otherwise).
        assert!(
            got.iter()
                .zip(random_field(cells, 3))
                .any(|(a, b)| (a - b).abs() > 1e-2)
        );
    }
}
