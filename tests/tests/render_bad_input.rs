//! Bad input to the renderer gets a clear, typed error naming the argument — never a panic
//! inside burn and never a silent NaN image.

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::glam::{Mat4, Vec3};
use gausmoke_render::{
    Camera, CameraError, GaussianSlices, GaussianTensors, Gaussians, Intrinsics, RasterOptions,
    RenderError, backends::all_devices, procedural::smoke_plume, render_volume,
};

fn camera() -> Camera {
    Camera::look_at(
        Vec3::new(0.0, 0.3, 2.0),
        Vec3::new(0.0, 0.3, 0.0),
        Vec3::Y,
        24,
        16,
        0.8,
    )
    .unwrap()
}

fn scene(device: &Device) -> GaussianTensors {
    smoke_plume(20, Vec3::new(-0.2, 0.0, -0.2), Vec3::new(0.2, 0.6, 0.2), 1)
        .to_tensors(device)
        .unwrap()
}

fn black(device: &Device) -> Tensor<1> {
    Tensor::from_data(TensorData::new(vec![0.0f32; 3], [3]), device)
}

/// Replaces element `index` of a `[N, C]` tensor.
fn poke(t: &Tensor<2>, index: usize, value: f32) -> Tensor<2> {
    let dims = t.dims();
    let mut v = t.to_data().try_into_vec_as::<f32>().unwrap();
    v[index] = value;
    Tensor::from_data(TensorData::new(v, dims), &t.device())
}

fn render_err(g: &GaussianTensors, bg: &Tensor<1>, options: &RasterOptions) -> RenderError {
    render_volume(g, &camera(), bg, options).expect_err("bad input must be refused")
}

#[test]
fn non_finite_parameters_are_named() {
    for (backend, device) in all_devices() {
        for device in [device.clone(), device.autodiff()] {
            let ok = scene(&device);
            let bg = black(&device);
            let opts = RasterOptions::default();
            let mut g = ok.clone();
            g.means = poke(&g.means, 4, f32::NAN);
            assert_eq!(
                render_err(&g, &bg, &opts),
                RenderError::NonFinite { name: "means" },
                "{backend}"
            );
            let mut g = ok.clone();
            g.rotations = poke(&g.rotations, 0, f32::INFINITY);
            assert_eq!(
                render_err(&g, &bg, &opts),
                RenderError::NonFinite { name: "rotations" }
            );
            let mut g = ok.clone();
            g.log_scales = poke(&g.log_scales, 1, f32::NEG_INFINITY);
            assert_eq!(
                render_err(&g, &bg, &opts),
                RenderError::NonFinite { name: "log_scales" }
            );
            let mut g = ok.clone();
            g.colors = poke(&g.colors, 2, f32::NAN);
            assert_eq!(
                render_err(&g, &bg, &opts),
                RenderError::NonFinite { name: "colors" }
            );
            let mut g = ok.clone();
            let mut raw = g.raw_densities.to_data().try_into_vec_as::<f32>().unwrap();
            raw[3] = f32::NAN;
            g.raw_densities = Tensor::from_data(TensorData::new(raw, [20]), &device);
            assert_eq!(
                render_err(&g, &bg, &opts),
                RenderError::NonFinite {
                    name: "raw_densities"
                }
            );
            let nan_bg =
                Tensor::from_data(TensorData::new(vec![0.0f32, f32::NAN, 0.0], [3]), &device);
            assert_eq!(
                render_err(&ok, &nan_bg, &opts),
                RenderError::NonFinite { name: "background" }
            );
        }
    }
}

#[test]
fn zero_quaternion_and_extreme_scales_are_refused() {
    for (_, device) in all_devices() {
        let ok = scene(&device);
        let bg = black(&device);
        let opts = RasterOptions::default();
        let mut g = ok.clone();
        for i in 4..8 {
            g.rotations = poke(&g.rotations, i, 0.0);
        }
        assert!(matches!(
            render_err(&g, &bg, &opts),
            RenderError::ZeroQuaternion { .. }
        ));
        let mut g = ok.clone();
        g.log_scales = poke(&g.log_scales, 0, 50.0);
        assert_eq!(
            render_err(&g, &bg, &opts),
            RenderError::ScaleOutOfRange { max_abs: 50.0 }
        );
        let msg = render_err(&g, &bg, &opts).to_string();
        assert!(msg.contains("log_scales"), "{msg}");
    }
}

#[test]
fn mismatched_shapes_are_named() {
    for (_, device) in all_devices() {
        let ok = scene(&device);
        let bg = black(&device);
        let opts = RasterOptions::default();
        let mut g = ok.clone();
        g.means = Tensor::zeros([20, 2], &device);
        let err = render_err(&g, &bg, &opts);
        assert!(
            matches!(err, RenderError::Shape { name: "means", .. }),
            "{err}"
        );
        let mut g = ok.clone();
        g.colors = Tensor::zeros([21, 3], &device);
        assert!(matches!(
            render_err(&g, &bg, &opts),
            RenderError::Shape { name: "colors", .. }
        ));
        let mut g = ok.clone();
        g.rotations = Tensor::zeros([20, 3], &device);
        assert!(matches!(
            render_err(&g, &bg, &opts),
            RenderError::Shape {
                name: "rotations",
                ..
            }
        ));
        let bg4: Tensor<1> = Tensor::zeros([4], &device);
        assert!(matches!(
            render_err(&ok, &bg4, &opts),
            RenderError::Shape {
                name: "background",
                ..
            }
        ));
        let err = host(
            &[0.0; 5],
            &[1.0, 0.0, 0.0, 0.0],
            &[0.0; 3],
            &[1.0],
            &[0.5; 3],
        )
        .to_tensors(&device)
        .expect_err("5 values are not [1, 3]");
        assert!(matches!(err, RenderError::Shape { name: "means", .. }));
    }
}

/// Borrowed host arrays of Gaussians, attribute by attribute.
fn host<'a>(
    means: &'a [f32],
    rotations: &'a [f32],
    log_scales: &'a [f32],
    raw_densities: &'a [f32],
    colors: &'a [f32],
) -> GaussianSlices<'a> {
    Gaussians {
        means,
        rotations,
        log_scales,
        raw_densities,
        colors,
    }
}

#[test]
fn invalid_options_are_named() {
    let device = all_devices()[0].1.clone();
    let g = scene(&device);
    let bg = black(&device);
    let cases = [
        (
            RasterOptions {
                alpha_max: 1.0,
                ..Default::default()
            },
            "alpha_max",
        ),
        (
            RasterOptions {
                alpha_min: 0.0,
                ..Default::default()
            },
            "alpha_min",
        ),
        (
            RasterOptions {
                transmittance_min: 1.0,
                ..Default::default()
            },
            "transmittance_min",
        ),
        (
            RasterOptions {
                kernel_cutoff: f32::NAN,
                ..Default::default()
            },
            "kernel_cutoff",
        ),
        (
            RasterOptions {
                near_plane: -1.0,
                ..Default::default()
            },
            "near_plane",
        ),
    ];
    for (opts, name) in cases {
        match render_err(&g, &bg, &opts) {
            RenderError::BadOption { name: got, .. } => assert_eq!(got, name),
            other => panic!("expected BadOption for {name}, got {other}"),
        }
    }
}

#[test]
fn bad_cameras_cannot_be_built() {
    let k = Intrinsics::from_fov_x(0.8, 16, 16);
    assert_eq!(
        Camera::new(0, 16, k, Mat4::IDENTITY),
        Err(CameraError::EmptyImage {
            width: 0,
            height: 16
        })
    );
    assert!(matches!(
        Camera::new(16, 16, k, Mat4::from_scale(Vec3::new(1.0, 2.0, 1.0))),
        Err(CameraError::NotRigid { .. })
    ));
    let nan_k = Intrinsics { cx: f32::NAN, ..k };
    assert!(matches!(
        Camera::new(16, 16, nan_k, Mat4::IDENTITY),
        Err(CameraError::BadIntrinsics { .. })
    ));
}

#[test]
fn empty_scene_renders_the_background() {
    for (_, device) in all_devices() {
        let g = host(&[], &[], &[], &[], &[]).to_tensors(&device).unwrap();
        let bg = Tensor::from_data(TensorData::new(vec![0.2f32, 0.4, 0.6], [3]), &device);
        let out = render_volume(&g, &camera(), &bg, &RasterOptions::default()).unwrap();
        let rgb = out.rgb.into_data().try_into_vec_as::<f32>().unwrap();
        assert_eq!(rgb.len(), 24 * 16 * 3);
        for px in rgb.chunks(3) {
            assert_eq!(px, [0.2, 0.4, 0.6]);
        }
        let t = out
            .transmittance
            .into_data()
            .try_into_vec_as::<f32>()
            .unwrap();
        assert!(t.iter().all(|&v| v == 1.0));
    }
}

#[test]
fn gaussians_behind_the_camera_contribute_nothing() {
    for (_, device) in all_devices() {
        // A dense Gaussian 1 unit behind the camera (camera at z = 2 looking down -Z).
        let g = host(
            &[0.0, 0.3, 3.0],
            &[1.0, 0.0, 0.0, 0.0],
            &[-1.0, -1.0, -1.0],
            &[10.0],
            &[1.0, 1.0, 1.0],
        )
        .to_tensors(&device)
        .unwrap();
        let out = render_volume(&g, &camera(), &black(&device), &RasterOptions::default()).unwrap();
        let t = out
            .transmittance
            .into_data()
            .try_into_vec_as::<f32>()
            .unwrap();
        assert!(t.iter().all(|&v| v == 1.0), "nothing may be drawn");
    }
}
