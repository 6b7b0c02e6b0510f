//! Support for the integration tests: golden files written by the torch reference
//! (`xtask/reference/torch_reference.py`) and comparisons with stated tolerances.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use gausmoke_core::glam::Mat4;
use gausmoke_render::{Camera, Intrinsics, RasterOptions};
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
