//! What the renderer can be asked to do, and why it refuses.

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

/// How GPU kernels add floats that many threads write at once (the backward pass, density
/// splatting). Either way the sums agree to float tolerance; the order is not fixed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FloatAtomics {
    /// Native `f32` atomic add where the device has it, else compare-and-swap.
    #[default]
    Native,
    /// Always the compare-and-swap loop (what devices without float atomics run); tests use
    /// it to check that path on a device that has native atomics.
    CompareAndSwap,
}

/// How the GPU backward pass sums one splat's gradients over the pixels of a tile. Every form
/// agrees with the others to float tolerance; the order of the additions is not fixed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum GradientSums {
    /// Plane (subgroup) sums, then the planes' partial sums in shared memory: one atomic add
    /// per float per tile and one barrier per splat. Devices without plane operations run
    /// [`GradientSums::PerPixel`] instead.
    #[default]
    Planes,
    /// The same sums through shared memory alone (groups of 16 units, then across groups), for
    /// devices without plane operations: one atomic add per float per tile, two barriers per
    /// splat. Not the fallback for [`GradientSums::Planes`]: on lavapipe, the one such device
    /// measured, barriers cost more than the atomics they save (`docs/BENCHMARKS.md`).
    SharedMemory,
    /// Every contributing pixel adds its own gradient atomically.
    PerPixel,
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
    /// GPU kernels only; the CPU path sums in a fixed order.
    pub float_atomics: FloatAtomics,
    /// GPU kernels only.
    pub gradient_sums: GradientSums,
    /// GPU kernels only: entries of the tile-list buffer. `None` reads the exact length back
    /// from the device (one read per render, which makes the host wait for the GPU); a caller
    /// that sizes the buffer itself (from [`crate::list_buffer_lengths`], with headroom) reads
    /// nothing, and checks afterwards that it was long enough ([`crate::InputCheck`]): a
    /// buffer too short drops the splats of the last tiles instead of overrunning.
    pub tile_list_capacity: Option<u32>,
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
            float_atomics: FloatAtomics::Native,
            gradient_sums: GradientSums::Planes,
            tile_list_capacity: None,
        }
    }
}

impl RasterOptions {
    pub(crate) fn validate(&self) -> Result<(), RenderError> {
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
    #[error(
        "the tile-list buffer of view {view} held {capacity} entries but the render needed {length}: its last tiles lost splats (the buffer is sized from a length measured earlier, with headroom; the Gaussians grew or moved more than that allows)"
    )]
    TileListOverflow {
        view: usize,
        length: f32,
        capacity: u32,
    },
    #[error("render option `{name}` = {value} is invalid: expected {expected}")]
    BadOption {
        name: &'static str,
        value: f32,
        expected: &'static str,
    },
}
