//! The density-splatting kernels (wgpu; in CI on Mesa's lavapipe) against the CPU path on a
//! few thousand random Gaussians: the density and its analytic spatial gradient, values and
//! gradients of every parameter, with native float atomics where the device has them and
//! with the compare-and-swap fallback.
//!
//! Like `render_gpu.rs`, these FAIL without a GPU adapter rather than skip.
//!
//! Tolerances (measured on lavapipe, 2026-11-22, `GAUSMOKE_PRINT_ERRORS=1`: values 4e-6 and
//! gradients 4e-6 of the largest magnitude): values within `2e-5 * max|cpu|` (a cell sums up
//! to hundreds of Gaussians in atomic order; device exp is a few ulp); gradients within
//! `5e-5 * max|cpu grad|` of the same tensor (per-Gaussian sums over up to thousands of cells,
//! in the same order on both paths, but every term carries the device's exp).

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_model::{DensityField, GridSpec, SplatOptions, density_field};
use gausmoke_render::backends::{cpu_devices, gpu_devices};
use gausmoke_render::{FloatAtomics, GaussianTensors};
use gausmoke_tests::{assert_close, to_vec};

struct Scene {
    means: Vec<f32>,
    quats: Vec<f32>,
    log_scales: Vec<f32>,
    raw: Vec<f32>,
}

/// `n` Gaussians in and around the box `[-1, 1]^3` (some straddle its faces), sizes from a
/// fraction of a cell to several cells, random orientations.
fn random_scene(n: usize, seed: u64) -> Scene {
    let mut rng = SplitMix64::new(seed);
    let mut uniform = |lo: f32, hi: f32| lo + (hi - lo) * rng.uniform();
    let mut scene = Scene {
        means: Vec::new(),
        quats: Vec::new(),
        log_scales: Vec::new(),
        raw: Vec::new(),
    };
    for _ in 0..n {
        scene
            .means
            .extend([uniform(-1.1, 1.1), uniform(-1.1, 1.1), uniform(-1.1, 1.1)]);
        scene.quats.extend([
            uniform(-1.0, 1.0),
            uniform(-1.0, 1.0),
            uniform(-1.0, 1.0),
            uniform(0.2, 1.0),
        ]);
        let base = uniform(-3.5, -2.0);
        scene.log_scales.extend([
            base + uniform(-0.4, 0.4),
            base + uniform(-0.4, 0.4),
            base + uniform(-0.4, 0.4),
        ]);
        scene.raw.push(uniform(-2.0, 3.0));
    }
    scene
}

fn gaussians(scene: &Scene, device: &Device) -> GaussianTensors {
    let n = scene.raw.len();
    let t2 = |v: &[f32], c: usize| {
        Tensor::<2>::from_data(TensorData::new(v.to_vec(), [n, c]), device).require_grad()
    };
    GaussianTensors {
        means: t2(&scene.means, 3),
        rotations: t2(&scene.quats, 4),
        log_scales: t2(&scene.log_scales, 3),
        raw_densities: Tensor::<1>::from_data(TensorData::new(scene.raw.clone(), [n]), device)
            .require_grad(),
        colors: Tensor::zeros([n, 3], device),
    }
}

/// Field values and the gradients of `sum(field * weight)` for (means, rotations, log-scales,
/// raw densities).
fn run(
    scene: &Scene,
    grid: &GridSpec,
    field: DensityField,
    weight: &[f32],
    device: &Device,
    float_atomics: FloatAtomics,
) -> (Vec<f32>, [Vec<f32>; 4]) {
    let ad = device.clone().autodiff();
    let g = gaussians(scene, &ad);
    let [nx, ny, nz] = grid.resolution();
    let options = SplatOptions {
        cutoff: 9.0,
        float_atomics,
    };
    let grads = if field != DensityField::Density {
        let channels = field.channels();
        let field: Tensor<4> = density_field(&g, grid, &options, field);
        let w = Tensor::<4>::from_data(
            TensorData::new(weight.to_vec(), [nx, ny, nz, channels]),
            &ad,
        );
        let values = to_vec(field.clone());
        ((field * w).sum().backward(), values)
    } else {
        let field: Tensor<3> = density_field(&g, grid, &options, DensityField::Density);
        let w = Tensor::<3>::from_data(TensorData::new(weight.to_vec(), [nx, ny, nz]), &ad);
        let values = to_vec(field.clone());
        ((field * w).sum().backward(), values)
    };
    let (grads, values) = grads;
    (
        values,
        [
            to_vec(g.means.grad(&grads).unwrap()),
            to_vec(g.rotations.grad(&grads).unwrap()),
            to_vec(g.log_scales.grad(&grads).unwrap()),
            to_vec(g.raw_densities.grad(&grads).unwrap()),
        ],
    )
}

fn compare(field: DensityField) {
    let gpu = gpu_devices();
    assert!(
        !gpu.is_empty(),
        "this test binary must be built with a GPU feature of gausmoke-model"
    );
    let (_, cpu) = cpu_devices().remove(0);
    // Non-cubic on purpose: a wrong axis order in the kernel's flat index fails here.
    let grid = GridSpec::new(Vec3::splat(-1.0), Vec3::new(1.0, 1.2, 0.9), [20, 24, 18], 1).unwrap();
    let scene = random_scene(3000, 7);
    let channels = field.channels();
    let mut rng = SplitMix64::new(11);
    let weight: Vec<f32> = (0..grid.num_cells() * channels)
        .map(|_| rng.uniform() * 2.0 - 1.0)
        .collect();
    let (cpu_values, cpu_grads) = run(&scene, &grid, field, &weight, &cpu, FloatAtomics::Native);
    let what = format!("{field:?}");
    for atomics in [FloatAtomics::Native, FloatAtomics::CompareAndSwap] {
        for (backend, device) in &gpu {
            let label = format!("{what} on {backend} ({atomics:?} float atomics)");
            let (values, grads) = run(&scene, &grid, field, &weight, device, atomics);
            let scale = cpu_values.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            assert!(scale > 1.0, "the scene must put real density on the grid");
            assert_close(&label, &values, &cpu_values, 2e-5 * scale, 0.0);
            for ((name, actual), expected) in ["means", "rotations", "log_scales", "raw_densities"]
                .iter()
                .zip(&grads)
                .zip(&cpu_grads)
            {
                let tensor_scale = expected.iter().fold(0.0f32, |m, v| m.max(v.abs()));
                assert!(tensor_scale > 0.0, "{label}: grad {name} is all zero");
                assert_close(
                    &format!("{label}: grad {name}"),
                    actual,
                    expected,
                    0.0,
                    5e-5,
                );
            }
        }
    }
}

#[test]
fn density_kernel_matches_cpu() {
    compare(DensityField::Density);
}

#[test]
fn density_gradient_kernel_matches_cpu() {
    compare(DensityField::SpatialGradient);
}

#[test]
fn density_and_gradient_kernel_matches_cpu() {
    compare(DensityField::Both);
}

/// The fused interpolation's kernels against its CPU path: velocity, Jacobian and the
/// gradients with respect to the grid and the points (points in, near and out of the box).
/// Measured on lavapipe (2026-11-23): within 2e-6 of each tensor's largest magnitude; bound
/// 2e-5 (the grid gradient is summed atomically, in no fixed order).
#[test]
fn interpolation_kernels_match_cpu() {
    use gausmoke_model::{Interpolation, sample_velocity};
    let grid = GridSpec::new(
        Vec3::new(-1.0, 0.0, -0.5),
        Vec3::new(1.0, 1.5, 0.7),
        [12, 16, 8],
        4,
    )
    .unwrap();
    let mut rng = SplitMix64::new(21);
    let field: Vec<f32> = (0..3 * grid.num_cells())
        .map(|_| rng.range(-1.0, 1.0))
        .collect();
    let m = 2000;
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
    let run = |device: &Device| -> [Vec<f32>; 4] {
        let ad = device.clone().autodiff();
        let velocity = Tensor::<4>::from_data(TensorData::new(field.clone(), [12, 16, 8, 3]), &ad)
            .require_grad();
        let p = Tensor::<2>::from_data(TensorData::new(points.clone(), [m, 3]), &ad).require_grad();
        let s = sample_velocity(&grid, &velocity, &p, Interpolation::default());
        let w_u: Vec<f32> = weights.chunks(12).flat_map(|r| r[..3].to_vec()).collect();
        let w_j: Vec<f32> = weights.chunks(12).flat_map(|r| r[3..].to_vec()).collect();
        let loss = (s.velocity.clone() * Tensor::<2>::from_data(TensorData::new(w_u, [m, 3]), &ad))
            .sum()
            + (s.jacobian.clone() * Tensor::<3>::from_data(TensorData::new(w_j, [m, 3, 3]), &ad))
                .sum();
        let grads = loss.backward();
        [
            to_vec(s.velocity),
            to_vec(s.jacobian),
            to_vec(velocity.grad(&grads).unwrap()),
            to_vec(p.grad(&grads).unwrap()),
        ]
    };
    let (_, cpu) = cpu_devices().remove(0);
    let reference = run(&cpu);
    for (backend, device) in gpu_devices() {
        let ours = run(&device);
        for (name, (a, b)) in ["velocity", "jacobian", "grad velocity", "grad points"]
            .iter()
            .zip(ours.iter().zip(&reference))
        {
            assert_close(&format!("{backend}: {name}"), a, b, 0.0, 2e-5);
        }
    }
}

/// The split of a move into its grid-scale and sub-grid parts (`GridScale`, built on the
/// device from the Gaussians) against the CPU: the grid part of a random move and the
/// gradient of both parts' mass-weighted mean squares.
#[test]
fn move_split_matches_cpu() {
    use gausmoke_model::GridScale;
    let scene = random_scene(3000, 11);
    let grid = GridSpec::new(Vec3::splat(-1.0), Vec3::ONE, [16, 12, 14], 4).unwrap();
    let mut rng = SplitMix64::new(5);
    let moves: Vec<f32> = (0..3 * 3000)
        .map(|_| 0.05 * (rng.uniform() - 0.5))
        .collect();
    let run = |device: &Device| {
        let ad = device.clone().autodiff();
        let g = gaussians(&scene, &ad);
        let scale = GridScale::of(&grid, &g);
        let m =
            Tensor::<2>::from_data(TensorData::new(moves.clone(), [3000, 3]), &ad).require_grad();
        let part = scale.grid_part(m.clone());
        let loss =
            scale.mean_square(part.clone()) * 2.0 + scale.mean_square(m.clone() - part.clone());
        let grads = loss.backward();
        (to_vec(part), to_vec(m.grad(&grads).unwrap()))
    };
    let (cpu_part, cpu_grad) = run(&cpu_devices()[0].1);
    let gpus = gpu_devices();
    assert!(
        !gpus.is_empty(),
        "no GPU adapter: this test needs one (lavapipe in CI)"
    );
    for (name, device) in gpus {
        let (part, grad) = run(&device);
        assert_close(&format!("{name}: grid part"), &part, &cpu_part, 1e-7, 1e-5);
        assert_close(&format!("{name}: gradient"), &grad, &cpu_grad, 1e-7, 1e-4);
    }
}
