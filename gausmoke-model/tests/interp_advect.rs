//! Interpolation, closed-form derivatives and advection against analytic fields.
#![allow(clippy::disallowed_methods)] // tests read tensors freely; the library counts its reads

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_model::{
    GridError, GridSpec, Integrator, Interpolation, advect, grid_from_fn, sample_velocity,
    transport_velocity,
};
use gausmoke_render::backends::cpu_devices;

const GAUSSIAN: Interpolation = Interpolation::Gaussian {
    stencil: 4,
    std_cells: 0.6,
};

fn unit_grid(n: usize) -> GridSpec {
    GridSpec::new(Vec3::ZERO, Vec3::ONE, [n, n, n], 4).unwrap()
}

fn host(t: Tensor<2>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

fn host1(t: Tensor<1>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

/// `m` random points at least `margin` (world units) inside the unit box.
fn interior_points(m: usize, margin: f32, seed: u64, device: &Device) -> Tensor<2> {
    let mut rng = SplitMix64::new(seed);
    let v: Vec<f32> = (0..3 * m)
        .map(|_| rng.range(margin, 1.0 - margin))
        .collect();
    Tensor::from_data(TensorData::new(v, [m, 3]), device)
}

#[test]
fn constant_fields_are_reproduced_exactly() {
    for (_, device) in cpu_devices() {
        let grid = unit_grid(8);
        let u = grid_from_fn(&grid, &device, |_| [0.3, -1.2, 0.7]);
        // Points everywhere, including outside the box (extrapolation keeps constants too).
        let mut rng = SplitMix64::new(1);
        let p: Vec<f32> = (0..300).map(|_| rng.range(-0.2, 1.2)).collect();
        let p = Tensor::from_data(TensorData::new(p, [100, 3]), &device);
        for kind in [GAUSSIAN, Interpolation::Trilinear] {
            let s = sample_velocity(&grid, &u, &p, kind);
            for px in host(s.velocity.clone()).chunks(3) {
                assert!(
                    (px[0] - 0.3).abs() < 1e-5
                        && (px[1] + 1.2).abs() < 1e-5
                        && (px[2] - 0.7).abs() < 1e-5
                );
            }
            let j = s.jacobian.into_data().try_into_vec_as::<f32>().unwrap();
            assert!(
                j.iter().all(|v| v.abs() < 1e-4),
                "constant field has zero Jacobian"
            );
        }
    }
}

#[test]
fn radial_field_has_divergence_three() {
    for (_, device) in cpu_devices() {
        let grid = unit_grid(12);
        let u = grid_from_fn(&grid, &device, |x| [x[0] - 0.5, x[1] - 0.5, x[2] - 0.5]);
        let p = interior_points(200, 0.2, 2, &device);
        // Trilinear is exact for linear fields.
        let div = host1(sample_velocity(&grid, &u, &p, Interpolation::Trilinear).divergence());
        assert!(div.iter().all(|d| (d - 3.0).abs() < 1e-3), "{div:?}");
        // The default Gaussian kernel: per-axis slope within [0.95, 1.02] (module docs).
        let div = host1(sample_velocity(&grid, &u, &p, GAUSSIAN).divergence());
        let (lo, hi) = div
            .iter()
            .fold((f32::MAX, f32::MIN), |(a, b), &d| (a.min(d), b.max(d)));
        assert!(
            lo > 3.0 * 0.95 - 1e-3 && hi < 3.0 * 1.02 + 1e-3,
            "divergence in [{lo}, {hi}]"
        );
    }
}

#[test]
fn divergence_free_fields_have_near_zero_divergence() {
    for (_, device) in cpu_devices() {
        let grid = unit_grid(24);
        let p = interior_points(300, 0.15, 3, &device);
        // Rigid rotation about +Y through the box centre: linear, so trilinear is exact; the
        // Gaussian kernel's per-axis slope bias cancels in the trace by symmetry.
        let rotation = grid_from_fn(&grid, &device, |x| [-(x[2] - 0.5), 0.0, x[0] - 0.5]);
        for kind in [GAUSSIAN, Interpolation::Trilinear] {
            let div = host1(sample_velocity(&grid, &rotation, &p, kind).divergence());
            let worst = div.iter().fold(0.0f32, |m, d| m.max(d.abs()));
            assert!(worst < 5e-3, "{kind:?}: rotation divergence up to {worst}");
        }
        // Taylor-Green vortex (divergence-free, non-linear).
        // Trilinear: inside a cell du/dx is a one-sided difference, first-order accurate:
        // error <= h/2 |u_xx| = h/2 (2 pi)^2 per axis (0.82 here; measured 0.70).
        // Gaussian: each axis's slope is biased by -5%..+2% depending on where the point sits
        // in its cell (module docs), and du/dx, dv/dy (magnitude up to 2 pi) cancel only when
        // both biases agree: up to ~7% of 2 pi, bound 8% (0.50; measured 0.32).
        let tau = std::f32::consts::TAU;
        let taylor_green = grid_from_fn(&grid, &device, |x| {
            let (a, b, c) = (tau * x[0], tau * x[1], tau * x[2]);
            [
                a.sin() * b.cos() * c.cos(),
                -a.cos() * b.sin() * c.cos(),
                0.0,
            ]
        });
        let h = 1.0 / 24.0;
        for (kind, bound) in [
            (GAUSSIAN, 0.08 * tau),
            (Interpolation::Trilinear, 0.5 * h * tau * tau),
        ] {
            let div = host1(sample_velocity(&grid, &taylor_green, &p, kind).divergence());
            let worst = div.iter().fold(0.0f32, |m, d| m.max(d.abs()));
            eprintln!("{kind:?}: Taylor-Green max |div| {worst:.4}, bound {bound:.4}");
            assert!(
                worst < bound,
                "{kind:?}: Taylor-Green divergence up to {worst}"
            );
        }
    }
}

#[test]
fn closed_form_jacobian_matches_finite_differences_of_the_interpolant() {
    let device = cpu_devices()[0].1.clone();
    let grid = GridSpec::new(
        Vec3::new(-0.3, 0.0, 0.1),
        Vec3::new(0.5, 0.9, 0.7),
        [7, 9, 6],
        4,
    )
    .unwrap();
    let mut rng = SplitMix64::new(4);
    let values: Vec<f32> = (0..7 * 9 * 6 * 3).map(|_| rng.range(-1.0, 1.0)).collect();
    let u = Tensor::<4>::from_data(TensorData::new(values, [7, 9, 6, 3]), &device);
    // Keep each coordinate at least 5% of a cell away from a cell centre, where the stencil
    // moves (Gaussian: small jump; trilinear: kink); see the module docs.
    let (lo, cell) = (grid.lo(), grid.cell_size());
    let away_from_switch = |p: &[f32; 3]| {
        (0..3).all(|a| {
            let c = (p[a] - lo[a]) / cell[a] - 0.5;
            let frac = c - c.floor();
            (0.05..0.95).contains(&frac)
        })
    };
    let points: Vec<[f32; 3]> = (0..200)
        .map(|_| {
            [
                rng.range(-0.15, 0.35),
                rng.range(0.15, 0.75),
                rng.range(0.25, 0.55),
            ]
        })
        .filter(away_from_switch)
        .take(20)
        .collect();
    assert_eq!(points.len(), 20);
    let h = 1e-3f32;
    for kind in [GAUSSIAN, Interpolation::Trilinear] {
        for p in &points {
            let at = |q: [f32; 3]| {
                let t = Tensor::from_data(TensorData::new(q.to_vec(), [1, 3]), &device);
                sample_velocity(&grid, &u, &t, kind)
            };
            let s = at(*p);
            let jac = s.jacobian.into_data().try_into_vec_as::<f32>().unwrap();
            for b in 0..3 {
                let (mut plus, mut minus) = (*p, *p);
                plus[b] += h;
                minus[b] -= h;
                let up = host(at(plus).velocity);
                let um = host(at(minus).velocity);
                for a in 0..3 {
                    let fd = (up[a] - um[a]) / (2.0 * h);
                    let cf = jac[3 * a + b];
                    assert!(
                        (fd - cf).abs() < 1e-2 * cf.abs().max(1.0),
                        "{kind:?} at {p:?}: dU{a}/dx{b} closed form {cf} vs finite difference {fd}"
                    );
                }
            }
        }
    }
}

#[test]
fn rk2_keeps_points_on_circles_with_the_predicted_error() {
    for (_, device) in cpu_devices() {
        let grid = GridSpec::new(Vec3::splat(-1.0), Vec3::splat(1.0), [16, 16, 16], 4).unwrap();
        let omega = 0.1f32; // radians per frame about +Y
        let u = grid_from_fn(&grid, &device, |x| [-omega * x[2], 0.0, omega * x[0]]);
        let r0 = 0.5f32;
        let p0 = Tensor::<2>::from_data(TensorData::new(vec![r0, 0.1, 0.0], [1, 3]), &device);
        let steps = 60;
        let radius_after = |integrator| {
            let mut p = p0.clone();
            for _ in 0..steps {
                p = advect(&grid, &u, &p, 1.0, integrator, Interpolation::Trilinear).positions;
            }
            let v = host(p);
            (v[0] * v[0] + v[2] * v[2]).sqrt()
        };
        // One step multiplies the radius by sqrt(1 + (w dt)^2) (Euler) or
        // sqrt(1 + (w dt)^4 / 4) (explicit midpoint) for a rigid rotation.
        let euler_pred = r0 * (1.0 + omega * omega).powf(steps as f32 / 2.0);
        let rk2_pred = r0 * (1.0 + omega.powi(4) / 4.0).powf(steps as f32 / 2.0);
        let euler = radius_after(Integrator::Euler);
        let rk2 = radius_after(Integrator::Rk2);
        assert!(
            (euler - euler_pred).abs() < 1e-3 * euler_pred,
            "Euler {euler} vs {euler_pred}"
        );
        assert!((rk2 - rk2_pred).abs() < 2e-4, "RK2 {rk2} vs {rk2_pred}");
        assert!(
            (rk2 - r0).abs() < 1e-3 && (euler - r0) > 0.1,
            "RK2 stays on the circle, Euler drifts out"
        );
    }
}

#[test]
fn centres_leaving_the_box_are_clamped_and_flagged() {
    let device = cpu_devices()[0].1.clone();
    let grid = unit_grid(8);
    let u = grid_from_fn(&grid, &device, |_| [0.5, 0.0, 0.0]);
    let p = Tensor::<2>::from_data(
        TensorData::new(vec![0.2, 0.5, 0.5, 0.8, 0.5, 0.5], [2, 3]),
        &device,
    );
    let out = advect(&grid, &u, &p, 1.0, Integrator::Euler, GAUSSIAN);
    let pos = host(out.positions);
    assert!(
        (pos[0] - 0.7).abs() < 1e-5 && (pos[3] - 1.0).abs() < 1e-6,
        "{pos:?}"
    );
    let flags = out.left_box.into_data().try_to_vec::<bool>().unwrap();
    assert_eq!(flags, vec![false, true]);
}

#[test]
fn transporting_the_velocity_moves_its_pattern_downstream() {
    for (_, device) in cpu_devices() {
        let n = 16;
        let grid = unit_grid(n);
        let h = 1.0 / n as f32;
        // A uniform stream along x carrying a shear: the y component, linear in x, must come
        // out shifted downstream by the stream's distance per frame.
        let (stream, shear, dt) = (1.5 * h, 0.2, 1.0);
        let u = grid_from_fn(&grid, &device, |x| [stream, shear * x[0], 0.0]);
        let carried = transport_velocity(&grid, &u, dt);
        assert_eq!(carried.dims(), [n, n, n, 3]);
        let values = carried.into_data().try_into_vec_as::<f32>().unwrap();
        let centres = grid.cell_centres();
        let mut interior = 0;
        for (c, v) in centres.chunks_exact(3).zip(values.chunks_exact(3)) {
            assert!(
                (v[0] - stream).abs() < 1e-6,
                "the stream itself is uniform: {v:?}"
            );
            assert!(v[2].abs() < 1e-6);
            // Departure points inside the outermost cell centres: trilinear is exact there.
            if c[0] - stream * dt >= 0.5 * h {
                let expected = shear * (c[0] - stream * dt);
                assert!(
                    (v[1] - expected).abs() < 1e-5,
                    "at {c:?}: {} against {expected}",
                    v[1]
                );
                interior += 1;
            }
        }
        assert_eq!(
            interior,
            n * n * (n - 2),
            "cells with departure points inside"
        );
        // The pattern did move: a field carried by zero time is the field itself.
        let still = transport_velocity(&grid, &u, 0.0);
        let before = u.into_data().try_into_vec_as::<f32>().unwrap();
        let after = still.into_data().try_into_vec_as::<f32>().unwrap();
        let largest = before
            .iter()
            .zip(&after)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(largest < 1e-6, "dt = 0 changed the field by {largest}");
    }
}

#[test]
fn transported_departure_points_stay_in_the_box() {
    let device = cpu_devices()[0].1.clone();
    let grid = unit_grid(8);
    // Flow towards x+ in a field that grows towards x-: the departure points of cells near
    // x- lie outside the box; they take the outermost cell's value, not an extrapolation
    // beyond it.
    let u = grid_from_fn(&grid, &device, |x| [0.5, 1.0 - x[0], 0.0]);
    let carried = transport_velocity(&grid, &u, 1.0);
    let values = carried.into_data().try_into_vec_as::<f32>().unwrap();
    let largest = values
        .chunks_exact(3)
        .map(|v| v[1])
        .fold(f32::MIN, f32::max);
    assert!(
        largest <= 1.0 - 0.5 / 8.0 + 1e-5,
        "a value beyond the field's own ({largest})"
    );
}

#[test]
fn kernel_bias_table() {
    // Interpolated slope of a linear field along x at many positions: the numbers quoted in
    // the `interp` module docs.
    let device = cpu_devices()[0].1.clone();
    let grid = GridSpec::new(Vec3::ZERO, Vec3::new(16.0, 16.0, 16.0), [16, 16, 16], 4).unwrap();
    let u = grid_from_fn(&grid, &device, |x| [x[0], 0.0, 0.0]);
    let xs: Vec<f32> = (0..=40)
        .flat_map(|i| [7.5 + i as f32 / 40.0, 8.3, 8.6])
        .collect();
    let p = Tensor::from_data(TensorData::new(xs, [41, 3]), &device);
    let slope = |kind| {
        let j = sample_velocity(&grid, &u, &p, kind)
            .jacobian
            .into_data()
            .try_into_vec_as::<f32>()
            .unwrap();
        j.chunks(9)
            .fold((f32::MAX, f32::MIN), |(a, b), m| (a.min(m[0]), b.max(m[0])))
    };
    let two = slope(Interpolation::Gaussian {
        stencil: 2,
        std_cells: 1.0,
    });
    let four = slope(GAUSSIAN);
    eprintln!("slope 2x2x2 std 1.0: {two:?}; 4x4x4 std 0.6: {four:?}");
    assert!(
        two.1 < 0.26,
        "2x2x2 / 1-cell kernel underestimates gradients ~4x: {two:?}"
    );
    assert!(
        four.0 > 0.94 && four.1 < 1.03,
        "default kernel within a few percent: {four:?}"
    );
}

#[test]
fn bad_grids_are_refused() {
    assert!(matches!(
        GridSpec::new(Vec3::ZERO, Vec3::new(1.0, 0.0, 1.0), [8, 8, 8], 1),
        Err(GridError::BadBox { .. })
    ));
    assert!(matches!(
        GridSpec::new(Vec3::ZERO, Vec3::ONE, [8, 0, 8], 1),
        Err(GridError::TooFewCells { .. })
    ));
    assert!(matches!(
        GridSpec::new(Vec3::ZERO, Vec3::ONE, [3, 8, 8], 4),
        Err(GridError::TooFewCells { min: 4, .. })
    ));
    let err = GridSpec::new(Vec3::ZERO, Vec3::ONE, [100_000, 100_000, 100_000], 4).unwrap_err();
    assert!(matches!(err, GridError::TooLarge { .. }), "{err}");
}
