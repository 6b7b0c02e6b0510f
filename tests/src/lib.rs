//! Support for the integration tests: golden files written by the torch reference
//! (`xtask/reference/torch_reference.py`) and comparisons with stated tolerances.

pub mod conv;
pub mod projection;

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::glam::Mat4;
use gausmoke_render::{
    AlphaModel, Camera, GaussianTensors, Intrinsics, RasterOptions, render_volume,
};
use safetensors::{Dtype, SafeTensors};

/// Directory of the committed golden files.
pub fn goldens_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("goldens")
}

/// A golden file: named f32 tensors with their shapes.
pub struct Golden {
    pub name: String,
    tensors: HashMap<String, (Vec<usize>, Vec<f32>)>,
}

impl Golden {
    pub fn load(file_stem: &str) -> Self {
        let path = goldens_dir().join(format!("{file_stem}.safetensors"));
        let bytes = std::fs::read(&path)
            .unwrap_or_else(|e| panic!("cannot read golden {}: {e}", path.display()));
        let st = SafeTensors::deserialize(&bytes)
            .unwrap_or_else(|e| panic!("golden {} is not safetensors: {e}", path.display()));
        let tensors = st
            .tensors()
            .into_iter()
            .map(|(name, view)| {
                assert_eq!(
                    view.dtype(),
                    Dtype::F32,
                    "{name} in {} is not f32",
                    path.display()
                );
                let values = view
                    .data()
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect();
                (name, (view.shape().to_vec(), values))
            })
            .collect();
        Self {
            name: file_stem.to_string(),
            tensors,
        }
    }

    /// All golden files whose name starts with `prefix`, sorted.
    pub fn load_all(prefix: &str) -> Vec<Self> {
        let mut stems: Vec<String> = std::fs::read_dir(goldens_dir())
            .expect("goldens directory exists")
            .filter_map(|e| {
                let name = e.ok()?.file_name().into_string().ok()?;
                let stem = name.strip_suffix(".safetensors")?;
                stem.starts_with(prefix).then(|| stem.to_string())
            })
            .collect();
        stems.sort();
        stems.iter().map(|s| Self::load(s)).collect()
    }

    pub fn get(&self, key: &str) -> &[f32] {
        &self.entry(key).1
    }

    pub fn shape(&self, key: &str) -> &[usize] {
        &self.entry(key).0
    }

    fn entry(&self, key: &str) -> &(Vec<usize>, Vec<f32>) {
        self.tensors
            .get(key)
            .unwrap_or_else(|| panic!("golden {} has no tensor `{key}`", self.name))
    }

    /// The camera stored as `[width, height, fx, fy, cx, cy, camera-to-world row-major]`.
    pub fn camera(&self) -> Camera {
        let v = self.get("camera");
        let c2w = Mat4::from_cols_array(&v[6..22].try_into().unwrap()).transpose();
        Camera::new(
            v[0] as u32,
            v[1] as u32,
            Intrinsics {
                fx: v[2],
                fy: v[3],
                cx: v[4],
                cy: v[5],
            },
            c2w,
        )
        .expect("golden camera is valid")
    }

    pub fn options(&self) -> RasterOptions {
        let v = self.get("options");
        RasterOptions {
            alpha_min: v[0],
            alpha_max: v[1],
            transmittance_min: v[2],
            kernel_cutoff: v[3],
            near_plane: v[4],
            // Files written before the ablation have five entries (Beer-Lambert).
            alpha_model: match v.get(5) {
                None | Some(0.0) => AlphaModel::BeerLambert,
                Some(_) => AlphaModel::SplatOpacity,
            },
            ..RasterOptions::default()
        }
    }
}

/// Largest absolute difference and the largest reference magnitude.
pub fn max_abs_diff(actual: &[f32], expected: &[f32]) -> (f32, f32) {
    assert_eq!(actual.len(), expected.len(), "length mismatch");
    let diff = actual
        .iter()
        .zip(expected)
        .fold(0.0f32, |m, (a, e)| m.max((a - e).abs()));
    let scale = expected.iter().fold(0.0f32, |m, e| m.max(e.abs()));
    (diff, scale)
}

/// Asserts `|actual - expected| <= atol + rtol * max|expected|` element-wise, reporting the
/// worst element.
pub fn assert_close(what: &str, actual: &[f32], expected: &[f32], atol: f32, rtol: f32) {
    let (diff, scale) = max_abs_diff(actual, expected);
    assert!(
        actual.iter().all(|v| v.is_finite()),
        "{what}: non-finite values in the result"
    );
    let bound = atol + rtol * scale;
    if std::env::var_os("GAUSMOKE_PRINT_ERRORS").is_some() {
        eprintln!("{what}: max |diff| {diff:.3e}, max |expected| {scale:.3e}, bound {bound:.3e}");
    }
    if diff > bound {
        let (i, _) = actual
            .iter()
            .zip(expected)
            .enumerate()
            .map(|(i, (a, e))| (i, (a - e).abs()))
            .fold(
                (0, 0.0f32),
                |best, cur| if cur.1 > best.1 { cur } else { best },
            );
        panic!(
            "{what}: max |diff| = {diff:.3e} > {bound:.3e} (max |expected| = {scale:.3e}); worst at flat index {i}: got {} expected {}",
            actual[i], expected[i]
        );
    }
}

pub fn to_vec<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec_as::<f32>().unwrap()
}

pub fn tensor<const D: usize>(golden: &Golden, key: &str, device: &Device) -> Tensor<D> {
    let shape: [usize; D] = golden.shape(key).try_into().expect("rank");
    Tensor::from_data(TensorData::new(golden.get(key).to_vec(), shape), device)
}

/// Tolerances of [`check_render_golden`]: forward values absolutely; each gradient against
/// `grad_rtol * max|g_ref|` of its tensor plus `grad_case_atol * (largest gradient of the case)`.
#[derive(Debug, Clone, Copy)]
pub struct RenderTolerance {
    pub forward_atol: f32,
    pub grad_case_atol: f32,
    pub grad_rtol: f32,
}

/// Renders a golden case on `device` under autodiff and checks the image, the transmittance
/// and the gradients of every input of the golden's weighted loss.
pub fn check_render_golden(golden: &Golden, backend: &str, device: &Device, tol: &RenderTolerance) {
    check_render_golden_with(golden, &golden.options(), backend, device, tol);
}

/// [`check_render_golden`] with `options` in place of the golden's own (which must agree with
/// them on everything the torch reference computes, e.g. to force a GPU atomics path).
pub fn check_render_golden_with(
    golden: &Golden,
    options: &RasterOptions,
    backend: &str,
    device: &Device,
    tol: &RenderTolerance,
) {
    let device = device.clone().autodiff();
    let gaussians = GaussianTensors {
        means: tensor::<2>(golden, "means", &device).require_grad(),
        rotations: tensor::<2>(golden, "rotations", &device).require_grad(),
        log_scales: tensor::<2>(golden, "log_scales", &device).require_grad(),
        raw_densities: tensor::<1>(golden, "raw_densities", &device).require_grad(),
        colors: tensor::<2>(golden, "colors", &device).require_grad(),
    };
    let background = tensor::<1>(golden, "background", &device).require_grad();
    let out = render_volume(&gaussians, &golden.camera(), &background, options)
        .expect("golden inputs are valid");
    let what = |s: &str| format!("{} on {backend}: {s}", golden.name);
    assert_close(
        &what("rgb"),
        &to_vec(out.rgb.clone()),
        golden.get("rgb"),
        tol.forward_atol,
        0.0,
    );
    assert_close(
        &what("transmittance"),
        &to_vec(out.transmittance.clone()),
        golden.get("transmittance"),
        tol.forward_atol,
        0.0,
    );

    let loss = (out.rgb * tensor::<3>(golden, "weight_rgb", &device)).sum()
        + (out.transmittance * tensor::<2>(golden, "weight_transmittance", &device)).sum();
    let grads = loss.backward();
    let grad2 = |t: &Tensor<2>| to_vec(t.grad(&grads).expect("tracked"));
    let grad1 = |t: &Tensor<1>| to_vec(t.grad(&grads).expect("tracked"));
    let checks = [
        ("means", grad2(&gaussians.means)),
        ("rotations", grad2(&gaussians.rotations)),
        ("log_scales", grad2(&gaussians.log_scales)),
        ("raw_densities", grad1(&gaussians.raw_densities)),
        ("colors", grad2(&gaussians.colors)),
        ("background", grad1(&background)),
    ];
    let case_scale = checks
        .iter()
        .flat_map(|(name, _)| golden.get(&format!("grad_{name}")))
        .fold(0.0f32, |m, g| m.max(g.abs()));
    for (name, actual) in checks {
        assert_close(
            &what(&format!("grad {name}")),
            &actual,
            golden.get(&format!("grad_{name}")),
            tol.grad_case_atol * case_scale,
            tol.grad_rtol,
        );
    }
}
