//! Reproducible synthetic Gaussian scenes for demos, tests and benchmarks (not data sets:
//! those live in `gausmoke-data`).

use burn::tensor::Device;
use gausmoke_core::glam::Vec3;

use crate::{GaussianTensors, RenderError};

/// Flat host arrays of `N` Gaussians, laid out as [`GaussianTensors`] expects.
#[derive(Debug, Clone, PartialEq)]
pub struct HostGaussians {
    pub means: Vec<f32>,
    pub rotations: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub raw_densities: Vec<f32>,
    pub colors: Vec<f32>,
}

impl HostGaussians {
    pub fn len(&self) -> usize {
        self.raw_densities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.raw_densities.is_empty()
    }

    pub fn to_tensors(&self, device: &Device) -> Result<GaussianTensors, RenderError> {
        GaussianTensors::from_host(
            &self.means,
            &self.rotations,
            &self.log_scales,
            &self.raw_densities,
            &self.colors,
            device,
        )
    }
}

/// SplitMix64: a tiny, well-mixed deterministic generator (fixtures need no RNG crate).
#[derive(Debug, Clone)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn uniform(&mut self) -> f32 {
        (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.uniform()
    }

    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f32 {
        let u1 = self.uniform().max(1e-7);
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }
}

/// A rising smoke plume of `n` Gaussians inside the axis-aligned box `[lo, hi]` (+Y up): a
/// column that widens and sways with height, grey albedo, thin near its edges. Scales follow
/// the mean spacing of `n` points in the box, as a 3DGS initialisation would.
pub fn smoke_plume(n: usize, lo: Vec3, hi: Vec3, seed: u64) -> HostGaussians {
    let mut rng = SplitMix64::new(seed);
    let extent = hi - lo;
    let centre = 0.5 * (lo + hi);
    let spacing = (extent.x * extent.y * extent.z / n.max(1) as f32).cbrt();
    let mut g = HostGaussians {
        means: Vec::with_capacity(3 * n),
        rotations: Vec::with_capacity(4 * n),
        log_scales: Vec::with_capacity(3 * n),
        raw_densities: Vec::with_capacity(n),
        colors: Vec::with_capacity(3 * n),
    };
    while g.len() < n {
        let height = rng.uniform();
        let radius = extent.x.min(extent.z) * (0.04 + 0.16 * height);
        let sway = 0.12 * extent.x * (6.0 * height).sin();
        let p = Vec3::new(
            centre.x + sway + radius * rng.normal(),
            lo.y + extent.y * height,
            centre.z + 0.5 * sway + radius * rng.normal(),
        );
        if p.cmplt(lo).any() || p.cmpgt(hi).any() {
            continue;
        }
        let q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
        g.means.extend(p.to_array());
        g.rotations.extend(q);
        for _ in 0..3 {
            g.log_scales.push((spacing * rng.range(0.6, 1.6)).ln());
        }
        // Extinction per world unit such that the optical depth through one Gaussian's centre
        // (sqrt(2 pi) * scale * sigma) is about 0.01 to 0.1: many overlap along a ray.
        g.raw_densities.push(rng.range(0.004, 0.04) / spacing);
        let grey = rng.range(0.6, 1.0);
        g.colors.extend([grey, grey, grey]);
    }
    g
}
