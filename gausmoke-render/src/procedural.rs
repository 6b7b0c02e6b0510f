//! Procedural sets of Gaussians for demos, tests and benchmarks (data sets live in
//! `gausmoke-data`).

use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;

use crate::gaussians::{Gaussian, HostGaussians};

/// A rising smoke plume of `n` Gaussians inside the axis-aligned box `[lo, hi]` (+Y up): a
/// column that widens and sways with height, grey albedo, thin near its edges. Scales follow
/// the mean spacing of `n` points in the box, as a 3DGS initialisation would.
pub fn smoke_plume(n: usize, lo: Vec3, hi: Vec3, seed: u64) -> HostGaussians {
    let mut rng = SplitMix64::new(seed);
    let extent = hi - lo;
    let centre = 0.5 * (lo + hi);
    let spacing = (extent.x * extent.y * extent.z / n.max(1) as f32).cbrt();
    let mut plume = HostGaussians::with_capacity(n);
    while plume.len() < n {
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
        let rotation = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
        let log_scale = [0; 3].map(|_| (spacing * rng.range(0.6, 1.6)).ln());
        // Extinction per world unit such that the optical depth through one Gaussian's centre
        // (sqrt(2 pi) * scale * sigma) is about 0.01 to 0.1: many overlap along a ray.
        let raw_density = rng.range(0.004, 0.04) / spacing;
        let grey = rng.range(0.6, 1.0);
        plume.push(&Gaussian {
            mean: p.to_array(),
            rotation,
            log_scale,
            raw_density,
            color: [grey; 3],
        });
    }
    plume
}
