//! The renderer's GPU stages one at a time against their CPU twins, so a kernel bug is found at
//! its stage rather than in the final image: the projection (splats, depths, tile rectangles),
//! the tile lists (binning), and the chain rule back to the world-space parameters.
//!
//! Like the other GPU tests these FAIL without a GPU adapter rather than skip (CI runs them on
//! Mesa's lavapipe).
//!
//! Tolerances (measured on lavapipe, 2026-11-23, `GAUSMOKE_PRINT_ERRORS=1 cargo test ... --
//! --nocapture`): splats within 4e-7 of each field's largest magnitude and view-backward
//! gradients within 4e-7 of each tensor's (the device's exp, sqrt and division are a few ulp
//! off); depths and colours exact. Bounds 1e-5 and 2e-5.

use burn::backend::DispatchDevice;
use burn::backend::ops::FloatTensorOps;
use burn::tensor::{Device, TensorData};
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::tensor::CubeTensor;
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::{Mat4, Vec3};
use gausmoke_render::backends::gpu_devices;
use gausmoke_render::cpu::{TILE_SIZE, ViewFrame, project_and_bin};
use gausmoke_render::kernels::splat::{SPLAT_FLOATS, view_params};
use gausmoke_render::kernels::{bin, list_buffer_length, project, view_backward};
use gausmoke_render::math::{ViewSplat, dot3, view_vjp};
use gausmoke_render::{Camera, Gaussian, Gaussians, HostGaussians, Intrinsics, RasterOptions};
use gausmoke_tests::assert_close;

/// The cube device behind the first GPU device of this build.
fn cube_device() -> burn_cubecl::CubeDevice {
    let devices = gpu_devices();
    let (_, device): &(&str, Device) = devices
        .first()
        .expect("this test binary must be built with a GPU feature of gausmoke-render");
    match device.as_dispatch() {
        DispatchDevice::Cube(device) => device.clone(),
        #[allow(unreachable_patterns)]
        other => panic!("not a cube device: {other:?}"),
    }
}

fn upload(values: &[f32], device: &burn_cubecl::CubeDevice) -> CubeTensor {
    CubeBackend::float_from_data(TensorData::new(values.to_vec(), [values.len()]), device)
}

fn read_f32(tensor: &CubeTensor, len: usize) -> Vec<f32> {
    let bytes = tensor.client.read_one(tensor.handle.clone()).unwrap();
    f32::from_bytes(&bytes)[..len].to_vec()
}

fn read_u32(tensor: &CubeTensor, len: usize) -> Vec<u32> {
    let bytes = tensor.client.read_one(tensor.handle.clone()).unwrap();
    u32::from_bytes(&bytes)[..len].to_vec()
}

/// `n` Gaussians in front of the camera, mixed sizes and orientations.
fn random_gaussians(n: usize, seed: u64) -> HostGaussians {
    let mut rng = SplitMix64::new(seed);
    let mut gaussians = HostGaussians::with_capacity(n);
    for _ in 0..n {
        let base = rng.range(-3.5, -1.8);
        gaussians.push(&Gaussian {
            mean: [0; 3].map(|_| rng.range(-1.0, 1.0)),
            rotation: [
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(-1.0, 1.0),
                rng.range(0.2, 1.0),
            ],
            log_scale: [0; 3].map(|_| base + rng.range(-0.5, 0.5)),
            raw_density: rng.range(-1.0, 4.0),
            color: [0; 3].map(|_| rng.uniform()),
        });
    }
    gaussians
}

fn camera() -> Camera {
    let eye = Vec3::new(0.4, 0.3, 3.2);
    let c2w = Mat4::look_at_rh(eye, Vec3::ZERO, Vec3::Y).inverse();
    Camera::new(
        200,
        150,
        Intrinsics {
            fx: 220.0,
            fy: 220.0,
            cx: 100.0,
            cy: 75.0,
        },
        c2w,
    )
    .unwrap()
}

/// The world-to-camera rotation, row-major, as the CPU maths takes it.
fn world_to_camera(camera: &Camera) -> [[f32; 3]; 3] {
    let w2c = camera.rotation_world_to_camera();
    [0, 1, 2].map(|row| [w2c.x_axis[row], w2c.y_axis[row], w2c.z_axis[row]])
}

/// The Gaussians and the view uploaded to the cube device.
struct OnDevice {
    device: burn_cubecl::CubeDevice,
    gaussians: Gaussians<CubeTensor>,
    view: CubeTensor,
}

fn on_device(gaussians: &HostGaussians, camera: &Camera) -> OnDevice {
    let device = cube_device();
    let uploaded = gaussians.as_ref().map(|_, values| upload(values, &device));
    let view = upload(&view_params(camera, &RasterOptions::default()), &device);
    OnDevice {
        device,
        gaussians: uploaded,
        view,
    }
}

/// Every field of a CPU splat, flat in the kernels' order.
fn splat_floats(splat: &ViewSplat) -> [f32; SPLAT_FLOATS] {
    let mut out = [0.0; SPLAT_FLOATS];
    for (k, row) in splat.whiten.iter().enumerate() {
        out[3 * k..3 * k + 3].copy_from_slice(row);
    }
    out[9..12].copy_from_slice(&splat.center);
    out[12] = splat.sigma;
    out[13..16].copy_from_slice(&splat.color);
    out
}

#[test]
fn projection_stage_matches_the_cpu_view_of_every_gaussian() {
    let n = 2000;
    let gaussians = random_gaussians(n, 5);
    let camera = camera();
    let gpu = on_device(&gaussians, &camera);
    let projection = project::project(&gpu.gaussians, &gpu.view, camera.width(), camera.height());
    let splats = read_f32(&projection.splats, n * SPLAT_FLOATS);
    let depths = read_f32(&projection.depths, n);

    let w2c = world_to_camera(&camera);
    let origin = camera.position().to_array();
    let mut expected_splats = Vec::with_capacity(n * SPLAT_FLOATS);
    let mut expected_depths = Vec::with_capacity(n);
    for i in 0..n {
        let (splat, ctx) = gaussians.get(i).view(&w2c, origin);
        expected_splats.extend(splat_floats(&splat));
        expected_depths.push(-dot3(w2c[2], ctx.offset));
    }
    // Field by field: L, m, sigma and colour have different scales.
    for (field, range) in [
        ("whitening", 0..9),
        ("centre", 9..12),
        ("sigma", 12..13),
        ("colour", 13..16),
    ] {
        let pick = |values: &[f32]| -> Vec<f32> {
            values
                .chunks(SPLAT_FLOATS)
                .flat_map(|s| s[range.clone()].to_vec())
                .collect()
        };
        assert_close(
            &format!("splat {field}"),
            &pick(&splats),
            &pick(&expected_splats),
            0.0,
            1e-5,
        );
    }
    assert_close("centre depths", &depths, &expected_depths, 0.0, 1e-6);
}

#[test]
fn tile_lists_hold_every_gaussian_the_cpu_bins_in_depth_order() {
    let n = 2000;
    let gaussians = random_gaussians(n, 6);
    let camera = camera();
    let gpu = on_device(&gaussians, &camera);
    let projection = project::project(&gpu.gaussians, &gpu.view, camera.width(), camera.height());
    let tiles = bin(&projection, n, camera.width(), camera.height(), None);
    let num_tiles = (tiles.tiles_x * tiles.tiles_y) as usize;
    let offsets = read_u32(&tiles.offsets, num_tiles + 1);
    let list = read_u32(&tiles.list, offsets[num_tiles] as usize);
    let depths = read_f32(&projection.depths, n);

    let cpu = project_and_bin(
        &gaussians.slices(),
        &ViewFrame::new(&camera),
        &RasterOptions::default(),
    );
    assert_eq!(cpu.tiles.len(), num_tiles);
    assert_eq!(
        (tiles.tiles_x as usize, tiles.tiles_y as usize),
        (
            (camera.width() as usize).div_ceil(TILE_SIZE),
            (camera.height() as usize).div_ceil(TILE_SIZE)
        )
    );
    let mut binned = 0;
    for (t, expected) in cpu.tiles.iter().enumerate() {
        let entries = &list[offsets[t] as usize..offsets[t + 1] as usize];
        // The GPU bounds each footprint by tangent planes (never tighter than the CPU's
        // exact conic): a superset, but every Gaussian the CPU bins must be there.
        for gaussian in expected {
            assert!(
                entries.contains(gaussian),
                "tile {t}: Gaussian {gaussian} is missing from the GPU list"
            );
        }
        // Sorted by (centre depth, index), the order the CPU composites in.
        for pair in entries.windows(2) {
            let key = |i: u32| (depths[i as usize], i);
            assert!(
                key(pair[0]).0 < key(pair[1]).0
                    || (key(pair[0]).0 == key(pair[1]).0 && pair[0] < pair[1]),
                "tile {t}: {pair:?} out of order"
            );
        }
        binned += expected.len();
    }
    assert!(
        binned > 10 * num_tiles,
        "the scene must cover the image ({binned} entries)"
    );
}

#[test]
fn a_list_buffer_of_given_capacity_is_filled_as_far_as_it_goes_and_never_past_its_end() {
    let n = 2000;
    let gaussians = random_gaussians(n, 6);
    let camera = camera();
    let gpu = on_device(&gaussians, &camera);
    let (width, height) = (camera.width(), camera.height());
    let projection = project::project(&gpu.gaussians, &gpu.view, width, height);
    let exact = bin(&projection, n, width, height, None);
    let num_tiles = (exact.tiles_x * exact.tiles_y) as usize;
    let offsets = read_u32(&exact.offsets, num_tiles + 2);
    let total = offsets[num_tiles];
    assert_eq!(offsets[num_tiles + 1], total, "unclamped total");
    let list = read_u32(&exact.list, total as usize);

    // The length the caller sizes buffers from is the same total, as a float on the device.
    let length = list_buffer_length(gpu.gaussians.clone(), &camera, &RasterOptions::default());
    assert_eq!(read_f32(&length, 1), [total as f32]);

    // Room for exactly the total: the same lists.
    let fitted = bin(&projection, n, width, height, Some(total));
    assert_eq!(read_u32(&fitted.offsets, num_tiles + 2), offsets);
    assert_eq!(read_u32(&fitted.list, total as usize), list);

    // Room for half: offsets clamped to it, the true total still told, the tiles that fit
    // complete, the one that straddles the end holding only its own Gaussians, and the tiles
    // past it empty (so the kernels never index beyond the buffer).
    let half = total / 2;
    let clamped = bin(&projection, n, width, height, Some(half));
    let clamped_offsets = read_u32(&clamped.offsets, num_tiles + 2);
    assert_eq!(clamped_offsets[num_tiles], half);
    assert_eq!(clamped_offsets[num_tiles + 1], total);
    let clamped_list = read_u32(&clamped.list, half as usize);
    let mut complete = 0;
    for t in 0..num_tiles {
        assert_eq!(clamped_offsets[t], offsets[t].min(half), "tile {t}'s start");
        let exact_entries = &list[offsets[t] as usize..offsets[t + 1] as usize];
        let kept = &clamped_list[clamped_offsets[t] as usize..clamped_offsets[t + 1] as usize];
        if offsets[t + 1] <= half {
            assert_eq!(kept, exact_entries, "tile {t}");
            complete += 1;
        } else {
            assert!(
                kept.iter().all(|i| exact_entries.contains(i)),
                "tile {t} holds a Gaussian that is not its own"
            );
        }
    }
    assert!(
        complete > 0 && complete < num_tiles,
        "{complete} complete tiles"
    );
}

#[test]
fn view_backward_stage_matches_the_cpu_chain_rule() {
    let n = 1500;
    let gaussians = random_gaussians(n, 7);
    let camera = camera();
    let gpu = on_device(&gaussians, &camera);
    let mut rng = SplitMix64::new(8);
    let splat_grads: Vec<f32> = (0..n * SPLAT_FLOATS)
        .map(|_| rng.range(-1.0, 1.0))
        .collect();
    let grads = view_backward(
        &gpu.gaussians,
        &gpu.view,
        &upload(&splat_grads, &gpu.device),
    );

    let w2c = world_to_camera(&camera);
    let origin = camera.position().to_array();
    let mut expected = HostGaussians::with_capacity(n);
    for (i, g) in splat_grads.chunks(SPLAT_FLOATS).enumerate() {
        let gaussian = gaussians.get(i);
        let (_, ctx) = gaussian.view(&w2c, origin);
        let whiten = [0, 1, 2].map(|k| [g[3 * k], g[3 * k + 1], g[3 * k + 2]]);
        expected.push(&view_vjp(
            &gaussian,
            &ctx,
            &w2c,
            &whiten,
            [g[9], g[10], g[11]],
            g[12],
            [g[13], g[14], g[15]],
        ));
    }
    let device_grads = grads.map(|attribute, tensor| read_f32(&tensor, n * attribute.columns));
    for (attribute, (actual, wanted)) in device_grads
        .zip(expected)
        .map(|attribute, pair| (attribute, pair))
        .into_array()
    {
        assert_close(
            &format!("grad {}", attribute.name),
            &actual,
            &wanted,
            0.0,
            2e-5,
        );
    }
}
