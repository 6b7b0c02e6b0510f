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
//! implements [`VolumeRenderBackend`] and is differentiable under `Autodiff` through a
//! hand-written backward pass. A set of Gaussians is one [`Gaussians`] bundle, whatever holds
//! it (tensors, backend primitives, host arrays).
//!
//! Units: `sigma_i` is an extinction coefficient per world unit; the line integral is along
//! unit-length ray directions, so optical depth is dimensionless. Conventions of cameras and
//! images: see [`gausmoke_core`].

pub mod backends;
pub mod cpu;
pub mod device_traffic;
pub mod gaussians;
#[cfg(feature = "cube")]
pub mod kernels;
pub mod math;
mod op;
mod options;
pub mod primitives;
pub mod procedural;

pub use gausmoke_core::{Camera, CameraError, Intrinsics};
pub use gaussians::{
    ATTRIBUTES, Attribute, Gaussian, GaussianPrimitives, GaussianSlices, GaussianTensors,
    Gaussians, HostGaussians,
};
pub use op::{RenderGrads, RenderPasses, Rendered, VolumeRenderBackend};
pub use options::{
    AlphaModel, FloatAtomics, GradientSums, LOG_SCALE_LIMIT, RasterOptions, RenderError,
};

use burn::backend::Dispatch;
use burn::tensor::Tensor;

/// A rendered view.
#[derive(Debug, Clone)]
pub struct RenderOutput {
    /// Composited colour over the background, `[H, W, 3]`.
    pub rgb: Tensor<3>,
    /// Final transmittance `T_N` per pixel, `[H, W]`; `1 - T_N` is the smoke's alpha mask.
    pub transmittance: Tensor<2>,
}

/// Checks the shapes on the host (no device work).
fn check_shapes(gaussians: &GaussianTensors, background: &Tensor<1>) -> Result<(), RenderError> {
    let n = gaussians.len();
    for (attribute, got) in gaussians.shapes().map(|a, shape| (a, shape)).into_array() {
        let expected = attribute.shape(n);
        if got != expected {
            return Err(RenderError::Shape {
                name: attribute.name,
                expected: format!("{expected:?}"),
                got,
            });
        }
    }
    if background.dims() != [3] {
        return Err(RenderError::Shape {
            name: "background",
            expected: "[3]".into(),
            got: background.dims().to_vec(),
        });
    }
    Ok(())
}

/// The renderer's input checks that need the values (finiteness of every attribute and the
/// background, quaternion norms, scale range), computed on the device by one backend op into
/// [`InputCheck::STATS`] numbers and judged on the host by [`InputCheck::judge`]. A caller that
/// must not wait for the device keeps [`InputCheck::values`] with its other diagnostics and
/// reads them all at once. (Composing this from ~20 burn tensor ops cost 11 ms per render on an
/// H100 through wgpu, four times the render itself.)
#[derive(Debug, Clone)]
pub struct InputCheck {
    values: Tensor<1>,
    gaussians: usize,
    /// The tile-list buffer sizes the views were rendered with, whose needed lengths follow
    /// the statistics in `values` (see [`InputCheck::with_list_capacities`]).
    list_capacities: Vec<u32>,
}

impl InputCheck {
    /// How many statistics of the inputs [`InputCheck::values`] starts with.
    pub const STATS: usize = 8;

    /// Shapes checked now; the value checks queued on the device.
    pub fn new(gaussians: &GaussianTensors, background: &Tensor<1>) -> Result<Self, RenderError> {
        check_shapes(gaussians, background)?;
        let values = Tensor::<1>::from_dispatch(
            <Dispatch as VolumeRenderBackend>::volume_render_input_stats(
                gaussians.clone().into_dispatch(),
                background.clone().into_dispatch(),
            ),
        );
        Ok(Self {
            values,
            gaussians: gaussians.len(),
            list_capacities: Vec::new(),
        })
    }

    /// Also checks that the views rendered with these tile-list buffer sizes
    /// ([`RasterOptions::tile_list_capacity`], one per view) had room: `lengths` is what
    /// [`list_buffer_lengths`] gave for the same Gaussians and views.
    pub fn with_list_capacities(
        mut self,
        lengths: Tensor<1>,
        capacities: Vec<u32>,
    ) -> Result<Self, RenderError> {
        if lengths.dims() != [capacities.len()] {
            return Err(RenderError::Shape {
                name: "tile-list lengths",
                expected: format!("[{}] (one per view with a capacity)", capacities.len()),
                got: lengths.dims().to_vec(),
            });
        }
        self.values = Tensor::cat(vec![self.values, lengths], 0);
        self.list_capacities.extend(capacities);
        Ok(self)
    }

    /// How many Gaussians were checked.
    pub fn gaussians(&self) -> usize {
        self.gaussians
    }

    /// How many numbers [`InputCheck::values`] holds.
    pub fn len(&self) -> usize {
        Self::STATS + self.list_capacities.len()
    }

    /// Never empty: the statistics are always there.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// The `[len]` numbers on the device, for a caller that reads them later.
    pub fn values(&self) -> Tensor<1> {
        self.values.clone()
    }

    /// Reads the numbers back (one device read) and judges them.
    pub fn verify_now(self) -> Result<(), RenderError> {
        self.judge(&device_traffic::read_floats(self.values.clone()))
    }

    /// Judges numbers read from [`InputCheck::values`]: a bad parameter is named instead of
    /// becoming a NaN image, and a tile-list buffer that was too short is reported.
    pub fn judge(&self, values: &[f32]) -> Result<(), RenderError> {
        assert_eq!(values.len(), self.len(), "input check layout");
        let (stats, lengths) = values.split_at(Self::STATS);
        let names = ["background"]
            .into_iter()
            .chain(ATTRIBUTES.iter().map(|attribute| attribute.name));
        for (name, &ok) in names.zip(stats) {
            if ok < 0.5 {
                return Err(RenderError::NonFinite { name });
            }
        }
        if self.gaussians > 0 {
            let min_norm_sq = stats[6];
            if min_norm_sq.is_nan() || min_norm_sq <= 1e-12 {
                return Err(RenderError::ZeroQuaternion { min_norm_sq });
            }
            let max_abs = stats[7];
            if max_abs > LOG_SCALE_LIMIT {
                return Err(RenderError::ScaleOutOfRange { max_abs });
            }
        }
        for (view, (&length, &capacity)) in lengths.iter().zip(&self.list_capacities).enumerate() {
            if length > capacity as f32 {
                return Err(RenderError::TileListOverflow {
                    view,
                    length,
                    capacity,
                });
            }
        }
        Ok(())
    }
}

/// How many tile-list entries renders of `gaussians` seen by each of `cameras` need (see
/// [`RasterOptions::tile_list_capacity`]): `[cameras.len()]` on the device, nothing read back.
/// 0 on the CPU backends, which have no list buffer to size.
pub fn list_buffer_lengths(
    gaussians: &GaussianTensors,
    cameras: &[Camera],
    options: &RasterOptions,
) -> Tensor<1> {
    if cameras.is_empty() {
        return Tensor::<1>::zeros([0], &gaussians.means.device());
    }
    let lengths = cameras
        .iter()
        .map(|camera| {
            Tensor::<1>::from_dispatch(
                <Dispatch as VolumeRenderBackend>::volume_render_list_buffer_length(
                    gaussians.clone().into_dispatch(),
                    *camera,
                    *options,
                ),
            )
        })
        .collect();
    Tensor::cat(lengths, 0)
}

/// Renders `gaussians` seen by `camera` over `background` (`[3]`, linear RGB).
///
/// Differentiable with respect to every Gaussian tensor and the background when they are
/// tracked by `Autodiff`. Inputs are validated first, which reads 8 numbers back from the
/// device (see [`RenderError`]); [`render_volume_deferred`] leaves that read to the caller.
pub fn render_volume(
    gaussians: &GaussianTensors,
    camera: &Camera,
    background: &Tensor<1>,
    options: &RasterOptions,
) -> Result<RenderOutput, RenderError> {
    options.validate()?;
    {
        let _phase = gausmoke_core::phase!("render input validation");
        InputCheck::new(gaussians, background)?.verify_now()?;
    }
    Ok(render_unverified(gaussians, camera, background, options))
}

/// [`render_volume`] without waiting for the value checks: the caller made `check` for these
/// Gaussians and background with [`InputCheck::new`] (shapes checked there) and reads its
/// values later with its other diagnostics, so a training loop reads nothing back per step
/// and checks once for all the views it renders. Until then, a bad parameter makes a NaN image
/// instead of an error.
pub fn render_volume_deferred(
    gaussians: &GaussianTensors,
    camera: &Camera,
    background: &Tensor<1>,
    options: &RasterOptions,
    check: &InputCheck,
) -> Result<RenderOutput, RenderError> {
    options.validate()?;
    if check.gaussians() != gaussians.len() {
        return Err(RenderError::Shape {
            name: "input check",
            expected: format!("a check of {} Gaussians", gaussians.len()),
            got: vec![check.gaussians()],
        });
    }
    Ok(render_unverified(gaussians, camera, background, options))
}

fn render_unverified(
    gaussians: &GaussianTensors,
    camera: &Camera,
    background: &Tensor<1>,
    options: &RasterOptions,
) -> RenderOutput {
    let image = Tensor::<3>::from_dispatch(<Dispatch as VolumeRenderBackend>::volume_render(
        gaussians.clone().into_dispatch(),
        background.clone().into_dispatch(),
        *camera,
        *options,
    ));
    let [h, w, _] = image.dims();
    RenderOutput {
        rgb: image.clone().slice([0..h, 0..w, 0..3]),
        transmittance: image.slice([0..h, 0..w, 3..4]).reshape([h, w]),
    }
}
