//! The cubecl kernels of the renderer (wgpu / Vulkan; in CI on Mesa's lavapipe, a software
//! Vulkan device) against the torch goldens, against the CPU path on thousands of random
//! Gaussians, and against finite differences.
//!
//! These tests need a GPU adapter. Where none exists they FAIL (burn's wgpu runtime panics
//! with "no adapter"): CI installs `mesa-vulkan-drivers` and sets
//! `CUBECL_WGPU_DEFAULT_DEVICE=Cpu`, so a green run means the real kernels ran.
//!
//! Tolerances (measured on lavapipe, 2026-11-22, `GAUSMOKE_PRINT_ERRORS=1`): the kernels use
//! the device's exp/sqrt/division, which on GPUs are not correctly rounded (a few ulp), and the
//! backward adds per-pixel contributions atomically in no fixed order. Forward: 2e-5 absolute.
//! Gradients: the CPU bounds relaxed by 4x.

use burn::backend::DispatchDevice;
use burn::backend::ops::FloatTensorOps;
use burn::tensor::{Device, Tensor, TensorData};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::features::Plane;
use burn_cubecl::cubecl::prelude::Client;
use gausmoke_core::SplitMix64;
use gausmoke_render::backends::{cpu_devices, gpu_devices};
use gausmoke_render::kernels::backward::rasterize::resolve;
use gausmoke_render::{
    Camera, FloatAtomics, Gaussians, GradientSums, InputCheck, Intrinsics, RasterOptions,
    RenderError, list_buffer_lengths, render_volume, render_volume_deferred,
};
use gausmoke_tests::{
    Golden, RenderTolerance, assert_close, check_render_golden, check_render_golden_with, to_vec,
};

const GPU_TOLERANCE: RenderTolerance = RenderTolerance {
    forward_atol: 2e-5,
    grad_case_atol: 4e-5,
    grad_rtol: 2e-4,
};

fn gpu() -> Vec<(&'static str, Device)> {
    let devices = gpu_devices();
    assert!(
        !devices.is_empty(),
        "this test binary must be built with a GPU feature of gausmoke-render"
    );
    devices
}

#[test]
fn kernels_match_torch_goldens() {
    let goldens = Golden::load_all("render_");
    assert!(goldens.len() >= 7);
    for (backend, device) in gpu() {
        for golden in &goldens {
            check_render_golden(golden, backend, &device, &GPU_TOLERANCE);
        }
    }
}

#[test]
fn other_atomics_and_tile_sums_match_torch_goldens() {
    // The compare-and-swap fallback for devices without f32 atomic add, forced on a device
    // that may have it, and the backward's shared-memory and per-pixel tile sums.
    let goldens = Golden::load_all("render_");
    let (backend, device) = gpu().remove(0);
    for (float_atomics, gradient_sums) in [
        (FloatAtomics::CompareAndSwap, GradientSums::SharedMemory),
        (FloatAtomics::Native, GradientSums::SharedMemory),
        (FloatAtomics::CompareAndSwap, GradientSums::PerPixel),
        (FloatAtomics::Native, GradientSums::PerPixel),
    ] {
        for golden in &goldens {
            let options = RasterOptions {
                float_atomics,
                gradient_sums,
                ..golden.options()
            };
            check_render_golden_with(golden, &options, backend, &device, &GPU_TOLERANCE);
        }
    }
}

#[test]
fn backward_runs_the_requested_tile_sums_where_the_device_allows() {
    // What the other tests check on this device: the shared-memory sums run wherever asked
    // (lavapipe has room for them); the plane sums only with plane operations, which wgpu
    // does not give lavapipe (their WGSL is validated in `render_wgsl.rs`).
    for (backend, device) in gpu() {
        let client = cube_client(&device);
        let planes = client.properties().features.plane.contains(Plane::Ops);
        println!("{backend}: plane operations {planes}");
        assert_eq!(
            resolve(&client, GradientSums::SharedMemory),
            GradientSums::SharedMemory
        );
        assert_eq!(
            resolve(&client, GradientSums::PerPixel),
            GradientSums::PerPixel
        );
        let expected = if planes {
            GradientSums::Planes
        } else {
            GradientSums::PerPixel
        };
        assert_eq!(resolve(&client, GradientSums::Planes), expected);
    }
}

/// The compute client behind a cube device.
fn cube_client(device: &Device) -> Client {
    let DispatchDevice::Cube(device) = device.as_dispatch() else {
        panic!("not a cube device: {device:?}");
    };
    CubeBackend::float_from_data(TensorData::new(vec![0.0f32], [1]), device).client
}

/// `n` random Gaussians in a unit-ish box in front of a camera, mixed sizes, densities and
/// orientations (some dense enough to saturate pixels and trigger early termination).
fn random_scene(n: usize, seed: u64) -> [Vec<f32>; 5] {
    let mut rng = SplitMix64::new(seed);
    let mut uniform = |lo: f32, hi: f32| lo + (hi - lo) * rng.uniform();
    let mut means = Vec::with_capacity(3 * n);
    let mut quats = Vec::with_capacity(4 * n);
    let mut log_scales = Vec::with_capacity(3 * n);
    let mut raw = Vec::with_capacity(n);
    let mut colors = Vec::with_capacity(3 * n);
    for _ in 0..n {
        means.extend([uniform(-1.0, 1.0), uniform(-1.0, 1.0), uniform(-1.0, 1.0)]);
        quats.extend([
            uniform(-1.0, 1.0),
            uniform(-1.0, 1.0),
            uniform(-1.0, 1.0),
            uniform(0.2, 1.0),
        ]);
        let base = uniform(-3.5, -1.8);
        log_scales.extend([
            base + uniform(-0.5, 0.5),
            base + uniform(-0.5, 0.5),
            base + uniform(-0.5, 0.5),
        ]);
        raw.push(uniform(-1.0, 4.0));
        colors.extend([uniform(0.0, 1.0), uniform(0.0, 1.0), uniform(0.0, 1.0)]);
    }
    [means, quats, log_scales, raw, colors]
}

fn camera(width: u32, height: u32) -> Camera {
    let eye = gausmoke_core::glam::Vec3::new(0.4, 0.3, 3.2);
    let c2w = gausmoke_core::glam::Mat4::look_at_rh(
        eye,
        gausmoke_core::glam::Vec3::ZERO,
        gausmoke_core::glam::Vec3::Y,
    )
    .inverse();
    Camera::new(
        width,
        height,
        Intrinsics {
            fx: 1.1 * width as f32,
            fy: 1.1 * width as f32,
            cx: 0.5 * width as f32,
            cy: 0.5 * height as f32,
        },
        c2w,
    )
    .unwrap()
}

struct Rendered {
    rgb: Vec<f32>,
    transmittance: Vec<f32>,
    grads: Vec<Vec<f32>>,
}

fn render_with_grads(
    scene: &[Vec<f32>; 5],
    camera: &Camera,
    options: &RasterOptions,
    device: &Device,
) -> Rendered {
    let device = device.clone().autodiff();
    let g = Gaussians::from_array(scene.clone())
        .to_tensors(&device)
        .unwrap()
        .require_grad();
    let background = Tensor::<1>::from_data(TensorData::new(vec![0.1f32, 0.2, 0.3], [3]), &device)
        .require_grad();
    let out = render_volume(&g, camera, &background, options).unwrap();
    let [h, w, _] = out.rgb.dims();
    // A fixed, non-uniform weighting so every pixel's gradient matters differently.
    let weights: Vec<f32> = (0..h * w * 3)
        .map(|i| ((i * 7919) % 101) as f32 / 101.0 - 0.3)
        .collect();
    let weights = Tensor::<3>::from_data(TensorData::new(weights, [h, w, 3]), &device);
    let loss = (out.rgb.clone() * weights).sum() + out.transmittance.clone().sum() * 0.5;
    let grads = loss.backward();
    Rendered {
        rgb: to_vec(out.rgb),
        transmittance: to_vec(out.transmittance),
        grads: vec![
            to_vec(g.means.grad(&grads).unwrap()),
            to_vec(g.rotations.grad(&grads).unwrap()),
            to_vec(g.log_scales.grad(&grads).unwrap()),
            to_vec(g.raw_densities.grad(&grads).unwrap()),
            to_vec(g.colors.grad(&grads).unwrap()),
            to_vec(background.grad(&grads).unwrap()),
        ],
    }
}

#[test]
fn renders_sized_by_the_caller_read_nothing_back_and_a_short_buffer_is_reported() {
    let scene = random_scene(3000, 11);
    let cameras = [camera(200, 150), camera(96, 64)];
    let background_values = TensorData::new(vec![0.1f32, 0.2, 0.3], [3]);
    for (_, device) in cpu_devices() {
        let g = Gaussians::from_array(scene.clone())
            .to_tensors(&device)
            .unwrap();
        let lengths = to_vec(list_buffer_lengths(&g, &cameras, &RasterOptions::default()));
        assert_eq!(lengths, [0.0, 0.0], "the CPU path has no list buffer");
    }
    for (backend, device) in gpu() {
        let g = Gaussians::from_array(scene.clone())
            .to_tensors(&device)
            .unwrap();
        let background = Tensor::<1>::from_data(background_values.clone(), &device);
        let lengths = list_buffer_lengths(&g, &cameras, &RasterOptions::default());
        let measured = to_vec(lengths.clone());
        assert!(
            measured.iter().all(|&l| l > 1000.0),
            "{backend}: {measured:?}"
        );
        let camera = &cameras[0];
        let exact = to_vec(
            render_volume(&g, camera, &background, &RasterOptions::default())
                .unwrap()
                .rgb,
        );
        let with_capacity = |capacity: u32| RasterOptions {
            tile_list_capacity: Some(capacity),
            ..RasterOptions::default()
        };

        // Room for the measured length: the same image, and a check that passes.
        let fitted = measured[0] as u32;
        let check = InputCheck::new(&g, &background)
            .unwrap()
            .with_list_capacities(lengths.clone(), vec![fitted, measured[1] as u32])
            .unwrap();
        let out = render_volume_deferred(&g, camera, &background, &with_capacity(fitted), &check)
            .unwrap();
        assert_eq!(to_vec(out.rgb), exact, "{backend}: exact capacity");
        check.verify_now().unwrap();

        // Half the room: the last tiles lose splats, and the check says which view and by
        // how much.
        let half = fitted / 2;
        let check = InputCheck::new(&g, &background)
            .unwrap()
            .with_list_capacities(lengths.clone(), vec![half, measured[1] as u32])
            .unwrap();
        let out =
            render_volume_deferred(&g, camera, &background, &with_capacity(half), &check).unwrap();
        assert_ne!(to_vec(out.rgb), exact, "{backend}: half the capacity");
        assert_eq!(
            check.verify_now(),
            Err(RenderError::TileListOverflow {
                view: 0,
                length: measured[0],
                capacity: half,
            })
        );
    }
}

#[test]
fn kernels_agree_with_the_cpu_path_on_thousands_of_random_gaussians() {
    let scene = random_scene(3000, 7);
    let camera = camera(200, 150);
    let options = RasterOptions::default();
    let (_, cpu) = cpu_devices().remove(0);
    let reference = render_with_grads(&scene, &camera, &options, &cpu);
    let min_t = reference
        .transmittance
        .iter()
        .cloned()
        .fold(1.0f32, f32::min);
    assert!(
        min_t < 0.01,
        "the scene should saturate some pixels (min T {min_t})"
    );
    let variants = [GradientSums::Planes, GradientSums::SharedMemory];
    for ((backend, device), gradient_sums) in gpu()
        .into_iter()
        .flat_map(|d| variants.map(|s| (d.clone(), s)))
    {
        let options = RasterOptions {
            gradient_sums,
            ..options
        };
        let backend = format!("{backend} ({gradient_sums:?})");
        let gpu = render_with_grads(&scene, &camera, &options, &device);
        assert_close(
            &format!("{backend}: rgb"),
            &gpu.rgb,
            &reference.rgb,
            2e-4,
            0.0,
        );
        assert_close(
            &format!("{backend}: transmittance"),
            &gpu.transmittance,
            &reference.transmittance,
            2e-4,
            0.0,
        );
        let names = [
            "means",
            "rotations",
            "log_scales",
            "raw_densities",
            "colors",
            "background",
        ];
        for ((name, g), r) in names.iter().zip(&gpu.grads).zip(&reference.grads) {
            // Sums of up to ~30k per-pixel terms in different orders: relative to the
            // tensor's largest gradient.
            assert_close(&format!("{backend}: grad {name}"), g, r, 0.0, 2e-3);
        }
    }
}

#[test]
fn kernel_gradients_match_finite_differences() {
    // Smooth settings (as the CPU gradcheck): no cutoffs or termination to straddle.
    let options = RasterOptions {
        alpha_min: 1e-12,
        transmittance_min: 0.0,
        kernel_cutoff: 1e6,
        ..RasterOptions::default()
    };
    let scene = random_scene(12, 3);
    let camera = camera(48, 40);
    for (backend, device) in gpu() {
        let base = render_with_grads(&scene, &camera, &options, &device);
        let loss_at = |scene: &[Vec<f32>; 5]| -> f64 {
            let r = render_with_grads(scene, &camera, &options, &device);
            let [h, w] = [40usize, 48usize];
            let weights: Vec<f32> = (0..h * w * 3)
                .map(|i| ((i * 7919) % 101) as f32 / 101.0 - 0.3)
                .collect();
            r.rgb
                .iter()
                .zip(&weights)
                .map(|(v, w)| *v as f64 * *w as f64)
                .sum::<f64>()
                + 0.5 * r.transmittance.iter().map(|&t| t as f64).sum::<f64>()
        };
        // Directional derivative along a random direction per parameter tensor.
        let mut rng = SplitMix64::new(11);
        for field in 0..5 {
            let direction: Vec<f32> = (0..scene[field].len())
                .map(|_| rng.uniform() - 0.5)
                .collect();
            let step = 2e-3f32;
            let shifted = |sign: f32| {
                let mut s = scene.clone();
                for (v, d) in s[field].iter_mut().zip(&direction) {
                    *v += sign * step * d;
                }
                s
            };
            let numeric = (loss_at(&shifted(1.0)) - loss_at(&shifted(-1.0))) / (2.0 * step as f64);
            let analytic: f64 = base.grads[field]
                .iter()
                .zip(&direction)
                .map(|(g, d)| *g as f64 * *d as f64)
                .sum();
            let scale = numeric.abs().max(analytic.abs()).max(1e-3);
            assert!(
                (numeric - analytic).abs() <= 2e-2 * scale,
                "{backend}: field {field}: finite difference {numeric:.6} vs backward {analytic:.6}"
            );
        }
    }
}

/// A mixed scene (static Gaussians after the smoke's, `GaussianTensors::concat`, what the
/// trainer renders): the same image as the one set made on the host, and each set's gradients
/// the matching rows of that set's, on every backend. An opaque ball of static Gaussians sits
/// among translucent smoke ones, so the composite crosses both in depth.
#[test]
fn a_mixed_scene_renders_and_splits_its_gradients_like_one_set() {
    let smoke = random_scene(600, 21);
    let mut ball = random_scene(200, 22);
    // Dense and gathered near the centre: an opaque ball.
    for (i, raw) in ball[3].iter_mut().enumerate() {
        *raw = 6.0 + (i % 5) as f32;
    }
    for coordinate in ball[0].iter_mut() {
        *coordinate *= 0.3;
    }
    let joined: [Vec<f32>; 5] =
        std::array::from_fn(|k| [smoke[k].clone(), ball[k].clone()].concat());
    let camera = camera(120, 90);
    let options = RasterOptions::default();
    let devices = cpu_devices().into_iter().chain(gpu());
    for (backend, device) in devices {
        let whole = render_with_grads(&joined, &camera, &options, &device);
        let ad = device.clone().autodiff();
        let parts = [&smoke, &ball].map(|part| {
            Gaussians::from_array(part.clone())
                .to_tensors(&ad)
                .unwrap()
                .require_grad()
        });
        let background = Tensor::<1>::from_data(TensorData::new(vec![0.1f32, 0.2, 0.3], [3]), &ad);
        let mixed = parts[0].clone().concat(parts[1].clone());
        let out = render_volume(&mixed, &camera, &background, &options).unwrap();
        let [h, w, _] = out.rgb.dims();
        let weights: Vec<f32> = (0..h * w * 3)
            .map(|i| ((i * 7919) % 101) as f32 / 101.0 - 0.3)
            .collect();
        let weights = Tensor::<3>::from_data(TensorData::new(weights, [h, w, 3]), &ad);
        let loss = (out.rgb.clone() * weights).sum() + out.transmittance.clone().sum() * 0.5;
        let grads = loss.backward();
        assert_eq!(to_vec(out.rgb), whole.rgb, "{backend}: rgb");
        let min_t = whole.transmittance.iter().cloned().fold(1.0f32, f32::min);
        assert!(
            min_t < 0.01,
            "{backend}: the ball is not opaque (min T {min_t})"
        );
        let n = smoke[3].len();
        for (part, rows) in parts.iter().zip([0..n, n..n + ball[3].len()]) {
            let got = [
                to_vec(part.means.grad(&grads).unwrap()),
                to_vec(part.raw_densities.grad(&grads).unwrap()),
                to_vec(part.colors.grad(&grads).unwrap()),
            ];
            let expected = [
                &whole.grads[0][3 * rows.start..3 * rows.end],
                &whole.grads[3][rows.clone()],
                &whole.grads[4][3 * rows.start..3 * rows.end],
            ];
            for (name, (g, e)) in ["means", "raw_densities", "colors"]
                .iter()
                .zip(got.iter().zip(expected))
            {
                // The device backward sums with atomics, in no fixed order: the last bits differ
                // from run to run.
                assert_close(
                    &format!("{backend}: grad {name} rows {rows:?}"),
                    g,
                    e,
                    0.0,
                    1e-5,
                );
            }
        }
    }
}
