//! Beer-Lambert volumetric Gaussian rasterizer (GauSmoke paper, Sec. 4.1 and Appendix B).
//!
//! Each Gaussian `i` is a density kernel `sigma_i k_i(x)` with covariance
//! `Sigma_i = R S S^T R^T`. For each pixel, the ray through its centre integrates every
//! kernel in closed form, `I_i = sqrt(2 pi) beta_i exp(-K_i / 2)`, its opacity is the
//! Beer-Lambert `alpha_i = 1 - exp(-sigma_i I_i)` (clamped below [`RasterOptions::alpha_max`])
//! and the Gaussians, sorted by the view depth of their centres, are composited front to back:
//! `C = sum_i T_{i-1} alpha_i c_i + T_N background`.
//!
//! [`render_volume`] is the checked public entry point; it works on every backend that
//! implements [`VolumeRenderBackend`] (the CPU backends NdArray and Flex here) and is
//! differentiable under `Autodiff` through a hand-written backward pass.
//!
//! Units: `sigma_i` is an extinction coefficient per world unit; the line integral is along
//! unit-length ray directions, so optical depth is dimensionless. Conventions of cameras and
//! images: see [`gausmoke_core`].

pub mod backends;
pub mod cpu;
#[cfg(feature = "cube")]
pub mod kernels;
pub mod math;
mod ops;
pub mod scenes;

pub use gausmoke_core::{Camera, CameraError, Intrinsics};
pub use ops::VolumeRenderBackend;

use burn::tensor::{Tensor, TensorData};

/// Beyond `|log_scale| > LOG_SCALE_LIMIT` a scale of `e^20 ~ 5e8` or `e^-20 ~ 2e-9` world
/// units squares out of f32's comfortable range in `Sigma^-1`; such input is an error.
pub const LOG_SCALE_LIMIT: f32 = 20.0;

/// How one Gaussian's opacity on one ray is computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum AlphaModel {
    /// The paper's Beer-Lambert alpha (Sec. 4.1): `1 - exp(-sigma I)`, `I` the Gaussian's
    /// line integral along the ray, `sigma = softplus(raw)` a physical density.
    #[default]
    BeerLambert,
    /// The "w/o volumetric rendering" ablation (paper Table 3): 3DGS's alpha, an opacity times
    /// the projected 2D Gaussian, `o exp(-K / 2)`. `K` is the exact perspective projection of
    /// the kernel (the squared Mahalanobis distance from the centre to the ray), not 3DGS's
    /// affine (EWA) approximation of it; the opacity is `o = 1 - exp(-softplus(raw))` in
    /// `[0, 1)`, so the same raw parameter drives both models.
    SplatOpacity,
}

/// Thresholds of the rasterizer. The CPU and GPU paths use identical values so they agree to
/// float tolerance; the torch reference reads them from the golden files.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RasterOptions {
    /// Gaussians with `alpha < alpha_min` on a ray are skipped (3DGS: 1/255).
    pub alpha_min: f32,
    /// Opacity clamp, so the backward pass can divide by `1 - alpha` (Talegaonkar et al.: 0.99).
    pub alpha_max: f32,
    /// A pixel stops compositing before the Gaussian that would take its transmittance below
    /// this value (3DGS: 1e-4).
    pub transmittance_min: f32,
    /// Support of each kernel: rays whose transverse term `K` (squared Mahalanobis distance
    /// from the centre to the ray) exceeds this are skipped. 9 is the 3-sigma ellipse.
    pub kernel_cutoff: f32,
    /// Gaussians whose centre is not at least this far in front of the camera (view depth,
    /// world units) contribute nothing.
    pub near_plane: f32,
    pub alpha_model: AlphaModel,
}

impl Default for RasterOptions {
    fn default() -> Self {
        Self {
            alpha_min: 1.0 / 255.0,
            alpha_max: 0.99,
            transmittance_min: 1e-4,
            kernel_cutoff: 9.0,
            near_plane: 0.01,
            alpha_model: AlphaModel::BeerLambert,
        }
    }
}

impl RasterOptions {
    fn validate(&self) -> Result<(), RenderError> {
        let bad = |name: &'static str, value: f32, expected: &'static str| {
            Err(RenderError::BadOption {
                name,
                value,
                expected,
            })
        };
        if !(self.alpha_min > 0.0 && self.alpha_min < 1.0) {
            return bad("alpha_min", self.alpha_min, "in (0, 1)");
        }
        if !(self.alpha_max > self.alpha_min && self.alpha_max < 1.0) {
            return bad("alpha_max", self.alpha_max, "in (alpha_min, 1)");
        }
        if !(self.transmittance_min >= 0.0 && self.transmittance_min < 1.0) {
            return bad("transmittance_min", self.transmittance_min, "in [0, 1)");
        }
        if !(self.kernel_cutoff > 0.0 && self.kernel_cutoff.is_finite()) {
            return bad("kernel_cutoff", self.kernel_cutoff, "finite and > 0");
        }
        if !(self.near_plane > 0.0 && self.near_plane.is_finite()) {
            return bad("near_plane", self.near_plane, "finite and > 0");
        }
        Ok(())
    }
}

/// `GAUSMOKE_KERNEL_TIMINGS` is set: print the time of validation and of each GPU stage to
/// stderr (read once per process; renders are a hot path).
pub(crate) fn timings_enabled() -> bool {
    static ENABLED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ENABLED.get_or_init(|| std::env::var_os("GAUSMOKE_KERNEL_TIMINGS").is_some())
}

/// Why a render was refused. Every variant names the offending argument.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    #[error("`{name}` must have shape {expected}, got {got:?}")]
    Shape {
        name: &'static str,
        expected: String,
        got: Vec<usize>,
    },
    #[error("`{name}` contains a non-finite value (NaN or infinity)")]
    NonFinite { name: &'static str },
    #[error(
        "`rotations` contains a zero quaternion (smallest |q|^2 = {min_norm_sq:e}); every Gaussian needs a non-zero rotation"
    )]
    ZeroQuaternion { min_norm_sq: f32 },
    #[error(
        "`log_scales` holds a value of magnitude {max_abs}, beyond the supported {LOG_SCALE_LIMIT} (scales from e^-{LOG_SCALE_LIMIT} to e^{LOG_SCALE_LIMIT} world units)"
    )]
    ScaleOutOfRange { max_abs: f32 },
    #[error("render option `{name}` = {value} is invalid: expected {expected}")]
    BadOption {
        name: &'static str,
        value: f32,
        expected: &'static str,
    },
}

/// Parameters of `N` Gaussians as tensors (the model owns them as parameters; the renderer
/// only borrows them).
#[derive(Debug, Clone)]
pub struct GaussianTensors {
    /// Centres in world units, `[N, 3]`.
    pub means: Tensor<2>,
    /// Quaternions `(w, x, y, z)`, `[N, 4]`; normalised inside the op, so any non-zero value.
    pub rotations: Tensor<2>,
    /// Natural log of the per-axis standard deviations (world units), `[N, 3]`.
    pub log_scales: Tensor<2>,
    /// Raw densities, `[N]`; `sigma = softplus(raw) >= 0` per world unit.
    pub raw_densities: Tensor<1>,
    /// Linear RGB emitted colour, `[N, 3]`.
    pub colors: Tensor<2>,
}

impl GaussianTensors {
    pub fn len(&self) -> usize {
        self.raw_densities.dims()[0]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Builds the tensors on `device` from flat host arrays (row-major, as in the field docs).
    pub fn from_host(
        means: &[f32],
        rotations: &[f32],
        log_scales: &[f32],
        raw_densities: &[f32],
        colors: &[f32],
        device: &burn::tensor::Device,
    ) -> Result<Self, RenderError> {
        let n = raw_densities.len();
        let tensor2 = |name: &'static str, values: &[f32], cols: usize| {
            if values.len() != n * cols {
                return Err(RenderError::Shape {
                    name,
                    expected: format!("[{n}, {cols}] (N from raw_densities)"),
                    got: vec![values.len()],
                });
            }
            Ok(Tensor::<2>::from_data(
                TensorData::new(values.to_vec(), [n, cols]),
                device,
            ))
        };
        Ok(Self {
            means: tensor2("means", means, 3)?,
            rotations: tensor2("rotations", rotations, 4)?,
            log_scales: tensor2("log_scales", log_scales, 3)?,
            raw_densities: Tensor::<1>::from_data(
                TensorData::new(raw_densities.to_vec(), [n]),
                device,
            ),
            colors: tensor2("colors", colors, 3)?,
        })
    }
}

/// A rendered view.
#[derive(Debug, Clone)]
pub struct RenderOutput {
    /// Composited colour over the background, `[H, W, 3]`.
    pub rgb: Tensor<3>,
    /// Final transmittance `T_N` per pixel, `[H, W]`; `1 - T_N` is the smoke's alpha mask.
    pub transmittance: Tensor<2>,
}

fn check_shape<const D: usize>(
    name: &'static str,
    tensor: &Tensor<D>,
    expected: [usize; D],
) -> Result<(), RenderError> {
    let got = tensor.dims();
    if got != expected {
        return Err(RenderError::Shape {
            name,
            expected: format!("{expected:?}"),
            got: got.to_vec(),
        });
    }
    Ok(())
}

/// Checks shapes on the host, then finiteness, quaternion norms and scale range with one
/// backend op and one small device read-back (8 numbers), so a bad parameter is named instead
/// of becoming a NaN image or a panic inside a backend. (Composing this from ~20 burn tensor
/// ops cost 11 ms per render on an H100 through wgpu, four times the render itself.)
fn validate(gaussians: &GaussianTensors, background: &Tensor<1>) -> Result<(), RenderError> {
    let n = gaussians.raw_densities.dims()[0];
    check_shape("means", &gaussians.means, [n, 3])?;
    check_shape("rotations", &gaussians.rotations, [n, 4])?;
    check_shape("log_scales", &gaussians.log_scales, [n, 3])?;
    check_shape("colors", &gaussians.colors, [n, 3])?;
    check_shape("background", background, [3])?;

    use burn::backend::Dispatch;
    let stats = Tensor::<1>::from_dispatch(
        <Dispatch as VolumeRenderBackend>::volume_render_input_stats(
            gaussians.means.clone().into_dispatch(),
            gaussians.rotations.clone().into_dispatch(),
            gaussians.log_scales.clone().into_dispatch(),
            gaussians.raw_densities.clone().into_dispatch(),
            gaussians.colors.clone().into_dispatch(),
            background.clone().into_dispatch(),
        ),
    )
    .into_data()
    .try_into_vec_as::<f32>()
    .expect("validation statistics are floats");
    let names = [
        "background",
        "means",
        "rotations",
        "log_scales",
        "raw_densities",
        "colors",
    ];
    for (name, &ok) in names.iter().zip(&stats) {
        if ok < 0.5 {
            return Err(RenderError::NonFinite { name });
        }
    }
    if n > 0 {
        let min_norm_sq = stats[6];
        if min_norm_sq.is_nan() || min_norm_sq <= 1e-12 {
            return Err(RenderError::ZeroQuaternion { min_norm_sq });
        }
        let max_abs = stats[7];
        if max_abs > LOG_SCALE_LIMIT {
            return Err(RenderError::ScaleOutOfRange { max_abs });
        }
    }
    Ok(())
}

/// Renders `gaussians` seen by `camera` over `background` (`[3]`, linear RGB).
///
/// Differentiable with respect to every Gaussian tensor and the background when they are
/// tracked by `Autodiff`. Inputs are validated first; see [`RenderError`].
pub fn render_volume(
    gaussians: &GaussianTensors,
    camera: &Camera,
    background: &Tensor<1>,
    options: &RasterOptions,
) -> Result<RenderOutput, RenderError> {
    options.validate()?;
    let started = std::time::Instant::now();
    validate(gaussians, background)?;
    if timings_enabled() {
        eprintln!(
            "gausmoke input validation: {:.3} ms",
            started.elapsed().as_secs_f64() * 1e3
        );
    }
    let packed = render_volume_unchecked(gaussians, camera, background, options);
    let [h, w, _] = packed.dims();
    let rgb = packed.clone().slice([0..h, 0..w, 0..3]);
    let transmittance = packed.slice([0..h, 0..w, 3..4]).reshape([h, w]);
    Ok(RenderOutput { rgb, transmittance })
}

/// The raw op without validation: `[H, W, 5]` (RGB, final transmittance, walked-list length).
/// Callers must uphold what [`render_volume`] checks.
pub fn render_volume_unchecked(
    gaussians: &GaussianTensors,
    camera: &Camera,
    background: &Tensor<1>,
    options: &RasterOptions,
) -> Tensor<3> {
    use burn::backend::Dispatch;
    Tensor::from_dispatch(<Dispatch as VolumeRenderBackend>::volume_render(
        gaussians.means.clone().into_dispatch(),
        gaussians.rotations.clone().into_dispatch(),
        gaussians.log_scales.clone().into_dispatch(),
        gaussians.raw_densities.clone().into_dispatch(),
        gaussians.colors.clone().into_dispatch(),
        background.clone().into_dispatch(),
        *camera,
        *options,
    ))
}
