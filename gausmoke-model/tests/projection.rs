//! The exact Helmholtz projection: divergence removed, idempotent, gradient fields vanish,
//! wall-tangent divergence-free fields stay, self-adjoint backward.
#![allow(clippy::disallowed_methods)] // tests read tensors freely; the library counts its reads

use burn::tensor::{Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_model::projection::Divergence;
use gausmoke_model::{
    GridSpec, ProjectionOptions, grid_from_fn, project_velocity, project_with_report,
};
use gausmoke_render::backends::cpu_devices;

fn grid(n: [usize; 3]) -> GridSpec {
    GridSpec::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 1.2, 0.8), n, 2).unwrap()
}

fn random_field(cells: usize, seed: u64) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed);
    (0..3 * cells).map(|_| rng.range(-1.0, 1.0)).collect()
}

fn divergence_rms(g: &GridSpec, u: &[f32]) -> f64 {
    let d = Divergence::on_grid(g).of_velocity(u);
    (d.iter().map(|v| v * v).sum::<f64>() / d.len() as f64).sqrt()
}

/// The projection op on `device` (autodiff) applied to `random_field(cells, field_seed)`, and
/// the gradient of `<w, Pi u>` with `w = random_field(cells, weight_seed)`, both on the host.
fn op_and_gradient(
    g: &GridSpec,
    options: &ProjectionOptions,
    device: &burn::tensor::Device,
    field_seed: u64,
    weight_seed: u64,
) -> (Vec<f32>, Vec<f32>) {
    let [nx, ny, nz] = g.resolution();
    let cells = g.num_cells();
    let field = |seed| {
        Tensor::<4>::from_data(
            TensorData::new(random_field(cells, seed), [nx, ny, nz, 3]),
            device,
        )
    };
    let u = field(field_seed).require_grad();
    let projected = project_velocity(g, u.clone(), options.clone());
    let forward = projected
        .clone()
        .into_data()
        .try_into_vec_as::<f32>()
        .unwrap();
    let grads = (projected * field(weight_seed)).sum().backward();
    let gradient = u
        .grad(&grads)
        .unwrap()
        .into_data()
        .try_into_vec_as::<f32>()
        .unwrap();
    (forward, gradient)
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()))
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
    let op = Divergence::on_grid(&g);
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
        let (_, got) = op_and_gradient(&g, &options, &ad, 2, 3);
        // d/du <w, Pi u> = Pi^T w = Pi w.
        let mut expected = random_field(cells, 3);
        project_with_report(&g, &mut expected, &options);
        let err = max_abs_diff(&got, &expected);
        assert!(err < 1e-5, "gradient differs from Pi(w) by {err}");
        // And it is not the identity (the test would be vacuous otherwise).
        assert!(
            got.iter()
                .zip(random_field(cells, 3))
                .any(|(a, b)| (a - b).abs() > 1e-2)
        );
    }
}

mod penalty {
    use super::*;
    use gausmoke_model::penalty::{
        PenaltyOptions, grid_divergence, grid_divergence_transpose, penalty_projection,
        penalty_projection_with_report,
    };

    fn host(t: Tensor<4>) -> Vec<f32> {
        t.into_data().try_into_vec_as::<f32>().unwrap()
    }

    #[test]
    fn tensor_divergence_is_the_projection_operator_and_its_adjoint() {
        let g = grid([10, 12, 8]);
        let [nx, ny, nz] = g.resolution();
        let u = random_field(g.num_cells(), 3);
        let p = random_field(g.num_cells(), 4)[..g.num_cells()].to_vec();
        let op = Divergence::on_grid(&g);
        let u64: Vec<f64> = u.iter().map(|&v| v as f64).collect();
        let mut expected = vec![0.0; g.num_cells()];
        op.apply(&u64, &mut expected);
        let p64: Vec<f64> = p.iter().map(|&v| v as f64).collect();
        let mut expected_t = vec![0.0; 3 * g.num_cells()];
        op.apply_transpose(&p64, &mut expected_t);
        for (backend, device) in cpu_devices() {
            let ut = Tensor::<4>::from_data(TensorData::new(u.clone(), [nx, ny, nz, 3]), &device);
            let pt = Tensor::<4>::from_data(TensorData::new(p.clone(), [nx, ny, nz, 1]), &device);
            let d = host(grid_divergence(&g, &ut));
            let dt = host(grid_divergence_transpose(&g, &pt));
            for (what, got, want) in [("D u", &d, &expected), ("D^T p", &dt, &expected_t)] {
                let worst = got
                    .iter()
                    .zip(want.iter())
                    .fold(0.0f64, |m, (a, b)| m.max((*a as f64 - b).abs()));
                assert!(worst < 1e-4, "{what} on {backend}: differs by {worst}");
            }
        }
    }

    #[test]
    fn penalty_reduces_divergence_monotonically_and_keeps_solenoidal_fields() {
        let g = grid([16, 20, 12]);
        let [nx, ny, nz] = g.resolution();
        let (_, device) = cpu_devices().remove(0);
        let u = Tensor::<4>::from_data(
            TensorData::new(random_field(g.num_cells(), 5), [nx, ny, nz, 3]),
            &device,
        );
        let mut previous = f64::INFINITY;
        for steps in [0, 5, 20, 80] {
            let options = PenaltyOptions {
                steps,
                ..PenaltyOptions::default()
            };
            let (_, report) = penalty_projection_with_report(&g, u.clone(), &options);
            eprintln!("penalty, {steps} steps: {report:?}");
            assert!(report.divergence_rms_after < previous, "{report:?}");
            previous = report.divergence_rms_after;
        }
        // 80 steps remove 99.7% (not all: smooth modes converge slowly) of a random field
        // divergence.
        assert!(previous < 0.01 * divergence_rms(&g, &host(u.clone())));

        // An exactly projected field is a fixed point.
        let mut solenoidal = random_field(g.num_cells(), 6);
        project_with_report(&g, &mut solenoidal, &ProjectionOptions::default());
        let s = Tensor::<4>::from_data(
            TensorData::new(solenoidal.clone(), [nx, ny, nz, 3]),
            &device,
        );
        let kept = host(penalty_projection(&g, s, &PenaltyOptions::default()));
        let change = kept
            .iter()
            .zip(&solenoidal)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(change < 1e-4, "a divergence-free field moved by {change}");
    }

    #[test]
    fn penalty_is_differentiable_and_self_adjoint() {
        // Each step is u - eta D^T D u, a symmetric linear map: <P a, b> = <a, P b>, and
        // autodiff's gradient of <P u, w> is P w.
        let g = grid([8, 10, 6]);
        let [nx, ny, nz] = g.resolution();
        let (_, device) = cpu_devices().remove(0);
        let ad = device.autodiff();
        let shape = [nx, ny, nz, 3];
        let a = Tensor::<4>::from_data(TensorData::new(random_field(g.num_cells(), 7), shape), &ad)
            .require_grad();
        let w = random_field(g.num_cells(), 8);
        let wt = Tensor::<4>::from_data(TensorData::new(w.clone(), shape), &ad);
        let options = PenaltyOptions::default();
        let grads = (penalty_projection(&g, a.clone(), &options) * wt.clone())
            .sum()
            .backward();
        let grad = host(a.grad(&grads).unwrap());
        let projected_w = host(penalty_projection(&g, wt, &options));
        let worst = grad
            .iter()
            .zip(&projected_w)
            .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
        assert!(worst < 1e-4, "gradient differs from P w by {worst}");
    }
}

#[test]
fn direct_solve_matches_converged_conjugate_gradients() {
    // Non-cubic, unequal cells: a wrong axis or cell size in the separated solve fails here.
    let g = grid([20, 24, 16]);
    let input = random_field(g.num_cells(), 5);
    let mut iterative = input.clone();
    project_with_report(
        &g,
        &mut iterative,
        &ProjectionOptions {
            rel_tolerance: 1e-9,
            max_iterations: 5000,
            ..Default::default()
        },
    );
    let mut direct = input.clone();
    let report = gausmoke_model::project_direct(&g, &mut direct, &Default::default());
    eprintln!("{report:?}");
    // f64 throughout: only the f32 storage of the result remains.
    assert!(report.relative_residual < 1e-9, "{report:?}");
    assert!(divergence_rms(&g, &direct) < 1e-6 * report.divergence_rms_before);
    let scale = input.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let worst = direct
        .iter()
        .zip(&iterative)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(
        worst < 1e-5 * scale,
        "direct vs PCG: {worst} (scale {scale})"
    );
}

/// With the top and bottom open, a uniform upward flow (a plume's net flux) is divergence-free
/// and `Pi` keeps it; with every face solid `Pi` must turn it back inside the box. The host
/// PCG twin and the direct solve agree with open faces, and both leave no divergence.
#[test]
fn open_faces_let_the_flow_through() {
    use gausmoke_model::projection::{OpenFaces, spectral};
    let g = grid([12, 16, 10]);
    let cells = g.num_cells();
    let upward: Vec<f32> = (0..cells).flat_map(|_| [0.0, 0.3, 0.0]).collect();
    let top_and_bottom = OpenFaces::from_names(&["y-", "y+"]).unwrap();
    for (open, kept) in [(top_and_bottom, true), (OpenFaces::NONE, false)] {
        let op = Divergence::on_grid(&g).with_open_faces(open);
        let mut u = upward.clone();
        spectral::project(&op, &spectral::SpectralSolver::for_grid(&op), &mut u);
        let change = u
            .iter()
            .zip(&upward)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert_eq!(change < 1e-6, kept, "{open:?}: max change {change}");
    }

    // Only the top open: what enters nowhere cannot leave, but a random field's divergence is
    // removed and the two solvers agree, with the faces fully or half open.
    for (names, flow) in [
        (&["y+"][..], 1.0),
        (&["x-", "y+", "z+"], 1.0),
        (&["y+"], 0.5),
        (&["x-", "y+", "z+"], 0.5),
    ] {
        let open = OpenFaces::from_names(names).unwrap().with_flow(flow);
        let op = Divergence::on_grid(&g).with_open_faces(open);
        let input = random_field(cells, 9);
        let mut direct = input.clone();
        let report = spectral::project(&op, &spectral::SpectralSolver::for_grid(&op), &mut direct);
        assert!(
            report.divergence_rms_after < 1e-6 * report.divergence_rms_before,
            "{names:?}: {report:?}"
        );
        let mut iterative = input.clone();
        let options = ProjectionOptions {
            rel_tolerance: 1e-10,
            max_iterations: 5000,
            open_faces: open,
            ..Default::default()
        };
        gausmoke_model::projection::host::project(&op, &mut iterative, &options);
        let gap = direct
            .iter()
            .zip(&iterative)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(
            gap < 1e-5,
            "{names:?} {flow}: direct and PCG differ by {gap}"
        );
        // Pi is an orthogonal projection with open faces too: idempotent.
        let mut again = direct.clone();
        spectral::project(&op, &spectral::SpectralSolver::for_grid(&op), &mut again);
        let change = again
            .iter()
            .zip(&direct)
            .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(change < 1e-5, "{names:?}: Pi(Pi(u)) moved by {change}");
        // Flow crosses the open top; with no other open face, what leaves there comes back
        // in there (no net flux), while with three open faces a net flux may leave.
        let top: Vec<f32> = (0..cells)
            .filter(|c| (c / 10) % 16 == 15)
            .map(|c| direct[3 * c + 1])
            .collect();
        let crossing = top.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        let net: f32 = top.iter().sum();
        assert!(crossing > 1e-2, "{names:?}: no flow through the top");
        if names.len() == 1 {
            assert!(
                net.abs() < 1e-4 * top.len() as f32,
                "{names:?}: net flux {net}"
            );
        } else {
            assert!(
                net.abs() > 1e-3,
                "{names:?}: no net flux through three open faces"
            );
        }
    }
}

/// A half-open face (`flow` 0.5) is the top of a collocated solver that reads zero velocity
/// past it: `D`'s central difference there takes a still ghost cell outside the box.
#[test]
fn a_half_open_face_is_a_still_ghost_cell_outside_the_box() {
    use gausmoke_model::projection::{OpenFaces, spectral};
    let g = grid([6, 8, 5]);
    let [nx, ny, nz] = g.resolution();
    let h = g.cell_size().y as f64;
    let cells = g.num_cells();
    // Only the vertical component, so `D u` is its central difference along y.
    let vertical: Vec<f32> = random_field(cells, 3)
        .chunks(3)
        .flat_map(|c| [0.0, c[1], 0.0])
        .collect();
    let top = OpenFaces::from_names(&["y+"]).unwrap().with_flow(0.5);
    let divergence = Divergence::on_grid(&g)
        .with_open_faces(top)
        .of_velocity(&vertical);
    let v = |x: usize, y: usize, z: usize| vertical[3 * ((x * ny + y) * nz + z) + 1] as f64;
    for x in 0..nx {
        for z in 0..nz {
            let c = (x * ny + ny - 1) * nz + z;
            let ghost = (0.0 - v(x, ny - 2, z)) / (2.0 * h);
            assert!(
                (divergence[c] - ghost).abs() < 1e-9,
                "({x}, {z}): {} vs {ghost}",
                divergence[c]
            );
        }
    }
    // Mean flux through the middle face of rows (the mean of the two rows beside it) after
    // projecting a uniform upward stream, top and bottom open: all of it when fully open,
    // none when solid. Half open, a net flux `q` needs the rows to alternate between `2 q`
    // and 0 from the bottom up (every face's flux the same), and 2 q again in the top row:
    // possible with an odd count of rows only. So half-open faces pass part of a stream
    // through an odd grid and none through an even one, a partial lid either way.
    for (rows, passes) in [(7, true), (8, false)] {
        let g = grid([6, rows, 5]);
        let cells = g.num_cells();
        let upward: Vec<f32> = (0..cells).flat_map(|_| [0.0, 0.3, 0.0]).collect();
        let middle_flux = |open: OpenFaces| {
            let op = Divergence::on_grid(&g).with_open_faces(open);
            let mut u = upward.clone();
            spectral::project(&op, &spectral::SpectralSolver::for_grid(&op), &mut u);
            (0..cells)
                .filter(|c| [rows / 2 - 1, rows / 2].contains(&((c / nz) % rows)))
                .map(|c| u[3 * c + 1] as f64)
                .sum::<f64>()
                / (2 * nx * nz) as f64
        };
        let both = OpenFaces::from_names(&["y-", "y+"]).unwrap();
        let (open, half, solid) = (
            middle_flux(both),
            middle_flux(both.with_flow(0.5)),
            middle_flux(OpenFaces::NONE),
        );
        assert!((open - 0.3).abs() < 1e-6, "{rows} rows, fully open: {open}");
        assert!(solid.abs() < 1e-6, "{rows} rows, solid: {solid}");
        if passes {
            assert!(0.02 < half && half < 0.28, "{rows} rows, half open: {half}");
        } else {
            assert!(half.abs() < 1e-6, "{rows} rows, half open: {half}");
        }
    }
}

/// Obstacle cells inside the box (`SolidCells`): `Pi` leaves no velocity in them nor towards
/// them in the cells touching them, no divergence in the fluid, keeps its algebra (symmetric, idempotent, backward = `Pi` of the
/// gradient), and makes a uniform stream go around the obstacle instead of through it.
mod obstacles {
    use super::*;
    use gausmoke_model::{OpenFaces, SolidCells};

    fn sphere_cells(g: &GridSpec, centre: Vec3, radius: f32) -> SolidCells {
        let flags = g.cells_where(|p| p.distance(centre) <= radius);
        SolidCells::new(g.resolution(), flags).unwrap()
    }

    fn options(solids: &SolidCells, open: &[&str]) -> ProjectionOptions {
        ProjectionOptions {
            rel_tolerance: 1e-10,
            max_iterations: 5000,
            open_faces: OpenFaces::from_names(open).unwrap(),
            solids: Some(solids.clone()),
            ..Default::default()
        }
    }

    fn dot(a: &[f32], b: &[f32]) -> f64 {
        a.iter().zip(b).map(|(a, b)| *a as f64 * *b as f64).sum()
    }

    #[test]
    fn solid_cells_hold_no_velocity_and_the_fluid_no_divergence() {
        let g = grid([14, 16, 12]);
        let solids = sphere_cells(&g, Vec3::new(0.45, 0.6, 0.4), 0.22);
        assert!(solids.count() > 50, "{} solid cells", solids.count());
        for open in [&[][..], &["y-", "y+"]] {
            let options = options(&solids, open);
            let mut u = random_field(g.num_cells(), 7);
            let report = project_with_report(&g, &mut u, &options);
            assert!(report.relative_residual <= 1e-10, "{open:?}: {report:?}");
            // What the CPU backends run: CG preconditioned by the obstacle-free direct solve,
            // the same projection in a fraction of the Jacobi-preconditioned iterations.
            let mut direct = random_field(g.num_cells(), 7);
            let fast = gausmoke_model::project_direct(&g, &mut direct, &options);
            eprintln!("{open:?}: Jacobi {report:?}, direct-preconditioned {fast:?}");
            assert!(fast.relative_residual <= 1e-10, "{open:?}: {fast:?}");
            assert!(
                4 * fast.iterations < report.iterations,
                "{open:?}: {} iterations against {}",
                fast.iterations,
                report.iterations
            );
            let apart = direct
                .iter()
                .zip(&u)
                .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(apart < 1e-5, "{open:?}: the two solves differ by {apart}");
            let op = Divergence::on_grid(&g)
                .with_open_faces(options.open_faces)
                .with_solids(Some(solids.clone()));
            // No velocity in the obstacle, none towards it from the cells touching it.
            let mut pinned = 0;
            for c in 0..g.num_cells() {
                if solids.is_solid(c) {
                    assert_eq!(&u[3 * c..3 * c + 3], &[0.0; 3], "{open:?}: solid cell {c}");
                }
                for a in 0..3 {
                    if !solids.is_solid(c) && !op.component_is_free(c, a) {
                        assert_eq!(u[3 * c + a], 0.0, "{open:?}: cell {c} axis {a}");
                        pinned += 1;
                    }
                }
            }
            assert!(pinned > 30, "{pinned} pinned components");
            let after = op.of_velocity(&u);
            let worst = after.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(worst < 1e-4, "{open:?}: max |D u| {worst:.2e} after Pi");
            // With no flow in or towards the obstacle, the operator that does not know of it
            // finds no divergence either: nothing crosses the obstacle's faces.
            let unaware = Divergence::on_grid(&g)
                .with_open_faces(options.open_faces)
                .of_velocity(&u);
            let worst_unaware = unaware.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(worst_unaware < 1e-4, "{open:?}: {worst_unaware:.2e}");
            // And the obstacle matters: the projection without it differs.
            let mut without = random_field(g.num_cells(), 7);
            project_with_report(
                &g,
                &mut without,
                &ProjectionOptions {
                    solids: None,
                    ..options.clone()
                },
            );
            let moved = without
                .iter()
                .zip(&u)
                .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(moved > 0.5, "{open:?}: the obstacle changed {moved}");

            // Symmetric and idempotent.
            let once = u.clone();
            project_with_report(&g, &mut u, &options);
            let change = once
                .iter()
                .zip(&u)
                .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
            assert!(change < 1e-5, "{open:?}: Pi(Pi u) moved by {change}");
            let (a, b) = (
                random_field(g.num_cells(), 8),
                random_field(g.num_cells(), 9),
            );
            let (mut pa, mut pb) = (a.clone(), b.clone());
            project_with_report(&g, &mut pa, &options);
            project_with_report(&g, &mut pb, &options);
            let (left, right) = (dot(&pa, &b), dot(&a, &pb));
            assert!(
                (left - right).abs() < 1e-4 * left.abs().max(1.0),
                "{open:?}: <Pi a, b> {left} vs <a, Pi b> {right}"
            );
        }
    }

    /// A uniform upward stream through open top and bottom: with the obstacle, the cells right
    /// under it slow down and their neighbours turn sideways, while the flux through every
    /// horizontal layer stays the inflow's (what enters leaves).
    #[test]
    fn a_stream_goes_around_the_obstacle() {
        let g = grid([16, 20, 16]);
        let centre = Vec3::new(0.5, 0.6, 0.4);
        let solids = sphere_cells(&g, centre, 0.2);
        let options = options(&solids, &["y-", "y+"]);
        let [nx, ny, nz] = g.resolution();
        let index = |i: usize, j: usize, k: usize| (i * ny + j) * nz + k;
        let mut u = vec![0.0f32; 3 * g.num_cells()];
        for c in 0..g.num_cells() {
            u[3 * c + 1] = 1.0;
        }
        project_with_report(&g, &mut u, &options);
        // Below the sphere's lowest solid cell on the axis.
        let (ci, ck) = (nx / 2, (0.4 / 0.8 * nz as f32) as usize);
        let lowest = (0..ny)
            .find(|&j| solids.is_solid(index(ci, j, ck)))
            .unwrap();
        let under = u[3 * index(ci, lowest - 1, ck) + 1];
        let far = u[3 * index(0, lowest - 1, 0) + 1];
        assert!(
            under < 0.7 * far,
            "under the obstacle {under}, far from it {far}"
        );
        let sideways: f32 = (0..g.num_cells())
            .map(|c| u[3 * c].abs() + u[3 * c + 2].abs())
            .sum();
        assert!(sideways > 1.0, "no sideways flow: {sideways}");
        for j in 0..ny {
            let flux: f32 = (0..nx)
                .flat_map(|i| (0..nz).map(move |k| (i, k)))
                .map(|(i, k)| u[3 * index(i, j, k) + 1])
                .sum();
            let expected = (nx * nz) as f32;
            // Layers through the obstacle carry it in fewer cells.
            assert!(
                (flux - expected).abs() < 0.15 * expected,
                "layer {j}: flux {flux} of {expected}"
            );
        }
    }

    /// The op on the CPU backends (a PCG solve, since obstacles defeat the direct one) and its
    /// backward, `Pi` of the incoming gradient.
    #[test]
    fn the_op_and_its_backward_keep_the_flow_out() {
        for (name, device) in cpu_devices() {
            let ad = device.autodiff();
            let g = grid([10, 12, 8]);
            let solids = sphere_cells(&g, Vec3::new(0.5, 0.6, 0.4), 0.25);
            let options = options(&solids, &["y+"]);
            let cells = g.num_cells();
            let (forward, got) = op_and_gradient(&g, &options, &ad, 11, 12);
            let mut expected = random_field(cells, 11);
            project_with_report(&g, &mut expected, &options);
            let err = max_abs_diff(&forward, &expected);
            assert!(err < 1e-5, "{name}: forward differs by {err}");
            let mut expected = random_field(cells, 12);
            project_with_report(&g, &mut expected, &options);
            let err = max_abs_diff(&got, &expected);
            assert!(err < 1e-5, "{name}: gradient differs from Pi(w) by {err}");
            assert!(
                (0..cells)
                    .filter(|&c| solids.is_solid(c))
                    .all(|c| got[3 * c..3 * c + 3] == [0.0; 3]),
                "{name}: gradient inside the obstacle"
            );
        }
    }

    #[test]
    fn a_flag_list_of_the_wrong_length_is_refused() {
        assert!(SolidCells::new([2, 2, 2], vec![false; 7]).is_none());
        let a = SolidCells::new([2, 2, 2], vec![false; 8]).unwrap();
        let mut flags = vec![false; 8];
        flags[3] = true;
        let b = SolidCells::new([2, 2, 2], flags).unwrap();
        assert_ne!(a, b);
        assert_ne!(a.fingerprint(), b.fingerprint());
        assert_eq!(b.count(), 1);
    }
}
