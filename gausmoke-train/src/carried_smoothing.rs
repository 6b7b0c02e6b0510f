//! Letting the carried state forget what no view sees (`carried_smoothing`, ours; issue 18).
//!
//! Every camera of the synthetic plume (and of ScalarFlow) sits at the smoke's height, so a
//! horizontal slice of the smoke is seen from the same few directions in every frame. What
//! those directions cannot place in depth is fitted as streaks, and a sequential fit carries
//! the streaks up the column with the smoke: nothing in a frame's few iterations removes
//! them. The same seeds' held-out errors agree (correlation 0.6-0.8), so the streaks are the
//! data's and the method's, not an initialisation's noise.
//!
//! Before a frame's fit, each Gaussian's density moves a fraction `blend` of the way towards
//! the carried density smoothed horizontally around its centre. What the frame's views see,
//! its iterations can restore; what they do not see fades by `1 - blend` a frame.
//!
//! How: the density splatted on the velocity grid (`[nx, ny, nz]`, z fastest) is blurred by
//! a Gaussian of `std_cells` cells along x and z, not along y (the views see the column's
//! height). Each Gaussian's density is scaled by `1 - blend + blend * blurred / density`,
//! both read trilinearly at its centre. The factor is kept within `[1/2, 2]`, where the
//! density is too thin to divide by it is 1, and rows on a box face (left for recycling) are
//! left alone. Host-side and deterministic, so a resumed run matches an uninterrupted one.
//!
//! A second way to forget, `carried_growth`: each carried Gaussian's variance along each of
//! its axes grows by a set number of cells squared before the frame's fit, as smoke carried
//! by a solver that resamples it on its grid loses a little of its finest detail every
//! frame, while Gaussians carried as particles keep all of theirs.

use gausmoke_core::glam::Vec3;
use gausmoke_render::HostGaussians;
use gausmoke_render::math::softplus;

use crate::host_grid::{sample, smoothed};
use crate::respawn::{SpawnLattice, inverse_softplus, on_box_face};

/// Bounds on one frame's scaling of a Gaussian's density.
const FACTOR_RANGE: (f32, f32) = (0.5, 2.0);
/// Below this share of the peak, the grid's density is too thin to divide by.
const THIN: f32 = 1e-3;

/// What [`smooth_carried_densities`] did, for the log.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SmoothingReport {
    /// Gaussians whose density changed.
    pub changed: usize,
    /// Mean of `|factor - 1|` over them.
    pub mean_change: f32,
}

/// `density` (`[nx, ny, nz]`, z fastest) blurred along x and z by a Gaussian of `std` cells,
/// cut at three deviations and renormalised at the box's sides.
pub fn blur_horizontally(density: &[f32], resolution: [usize; 3], std: f32) -> Vec<f32> {
    smoothed(density, resolution, 1, std, [true, false, true])
}

/// `grid` (`[nx, ny, nz]`, z fastest, values at the cell centres of `lattice`) read
/// trilinearly at `point`, clamped to the outermost centres.
fn trilinear(grid: &[f32], lattice: &SpawnLattice, point: Vec3) -> f32 {
    let mut out = [0.0f64];
    let cell = lattice.cell_size();
    sample(
        lattice.lo,
        cell,
        lattice.resolution,
        grid,
        1,
        point,
        &mut out,
    );
    out[0] as f32
}

/// Moves each Gaussian's density a fraction `blend` of the way towards `density` (the
/// Gaussians' own, splatted on `lattice`) blurred horizontally by `std_cells` cells, as the
/// module describes.
pub fn smooth_carried_densities(
    gaussians: &mut HostGaussians,
    density: &[f32],
    lattice: &SpawnLattice,
    blend: f32,
    std_cells: f32,
) -> SmoothingReport {
    if blend <= 0.0 || gaussians.is_empty() {
        return SmoothingReport::default();
    }
    let blurred = blur_horizontally(density, lattice.resolution, std_cells);
    let peak = density.iter().copied().fold(0.0f32, f32::max);
    let mut report = SmoothingReport::default();
    let mut change = 0.0f64;
    for i in 0..gaussians.len() {
        let m = &gaussians.means[3 * i..3 * i + 3];
        let centre = Vec3::new(m[0], m[1], m[2]);
        if on_box_face(centre, lattice) {
            continue;
        }
        let here = trilinear(density, lattice, centre);
        if here <= THIN * peak {
            continue;
        }
        let around = trilinear(&blurred, lattice, centre);
        let factor = (1.0 - blend + blend * around / here).clamp(FACTOR_RANGE.0, FACTOR_RANGE.1);
        if factor == 1.0 {
            continue;
        }
        let sigma = softplus(gaussians.raw_densities[i]) * factor;
        gaussians.raw_densities[i] = inverse_softplus(sigma);
        report.changed += 1;
        change += f64::from((factor - 1.0).abs());
    }
    if report.changed > 0 {
        report.mean_change = (change / report.changed as f64) as f32;
    }
    report
}

/// Adds `variance` (world units squared) to each Gaussian's variance along each of its axes,
/// growing no log-scale past `max_log_scale` (one already past it is left as it is).
pub fn grow_carried_sizes(gaussians: &mut HostGaussians, variance: f32, max_log_scale: f32) {
    if variance <= 0.0 {
        return;
    }
    for log_scale in &mut gaussians.log_scales {
        let grown = 0.5 * ((2.0 * *log_scale).exp() + variance).ln();
        *log_scale = grown.min(max_log_scale).max(*log_scale);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn growth_adds_the_variance_to_every_axis_up_to_the_cap() {
        let sizes = [0.1f32, 0.2, 0.3, 0.1, 1.0, 2.0];
        let mut host = HostGaussians {
            means: vec![0.0; 6],
            rotations: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            log_scales: sizes.iter().map(|s| s.ln()).collect(),
            raw_densities: vec![0.0; 2],
            colors: vec![1.0; 6],
        };
        grow_carried_sizes(&mut host, 0.01, f32::INFINITY);
        for (log_scale, was) in host.log_scales.iter().zip(sizes) {
            let got = log_scale.exp();
            assert!(
                (got * got - (was * was + 0.01)).abs() < 1e-5,
                "{got} from {was}"
            );
        }
        // Capped at the bound, and a size already over it is left as it was, not shrunk.
        let cap = 1.5f32.ln();
        grow_carried_sizes(&mut host, 2.0, cap);
        assert!(
            host.log_scales[..4].iter().all(|l| *l < cap),
            "{:?}",
            host.log_scales
        );
        assert!(
            (host.log_scales[4] - cap).abs() < 1e-6,
            "{}",
            host.log_scales[4]
        );
        assert!((host.log_scales[5].exp() - (4.0f32 + 0.01).sqrt()).abs() < 1e-5);
        let before = host.clone();
        grow_carried_sizes(&mut host, 0.0, cap);
        assert_eq!(host, before);
    }

    fn lattice(n: usize) -> SpawnLattice {
        SpawnLattice {
            lo: Vec3::ZERO,
            hi: Vec3::ONE,
            resolution: [n, n, n],
        }
    }

    #[test]
    fn the_blur_keeps_a_constant_and_smooths_only_across_the_horizontal() {
        let n = 8;
        let index = |i: usize, j: usize, k: usize| (i * n + j) * n + k;
        let constant = vec![0.7f32; n * n * n];
        for v in blur_horizontally(&constant, [n, n, n], 1.0) {
            assert!((v - 0.7).abs() < 1e-6, "{v}");
        }
        // A wall at x = 3 spreads along x, a layer at y = 3 does not spread along y.
        let mut wall = vec![0.0f32; n * n * n];
        let mut layer = vec![0.0f32; n * n * n];
        for a in 0..n {
            for b in 0..n {
                wall[index(3, a, b)] = 1.0;
                layer[index(a, 3, b)] = 1.0;
            }
        }
        let wall = blur_horizontally(&wall, [n, n, n], 1.0);
        assert!(wall[index(3, 5, 5)] < 0.5 && wall[index(4, 5, 5)] > 0.2);
        let layer = blur_horizontally(&layer, [n, n, n], 1.0);
        assert!((layer[index(5, 3, 5)] - 1.0).abs() < 1e-6);
        assert_eq!(layer[index(5, 4, 5)], 0.0);
    }

    #[test]
    fn streaks_fade_and_an_even_slab_stays() {
        // Gaussians in two columns side by side, one heavy and one light (a streak pair),
        // and one in an even slab: the pair's densities move towards each other, by `blend`
        // of the way to their blurred neighbourhood; the slab's does not change.
        let n = 16;
        let lattice = lattice(n);
        let index = |i: usize, j: usize, k: usize| (i * n + j) * n + k;
        let mut density = vec![0.0f32; n * n * n];
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    density[index(i, j, k)] = if k < 8 {
                        1.0
                    } else if i % 2 == 0 {
                        2.0
                    } else {
                        0.2
                    };
                }
            }
        }
        let centre = |i: usize, j: usize, k: usize| lattice.cell_centre([i, j, k]).to_array();
        let mut gaussians = HostGaussians::default();
        for (mean, raw) in [
            (centre(6, 8, 12), inverse_softplus(2.0)),
            (centre(7, 8, 12), inverse_softplus(0.2)),
            (centre(6, 8, 3), inverse_softplus(1.0)),
        ] {
            gaussians.push(&gausmoke_render::Gaussian {
                mean,
                rotation: [1.0, 0.0, 0.0, 0.0],
                log_scale: [-3.0; 3],
                raw_density: raw,
                color: [1.0; 3],
            });
        }
        let report = smooth_carried_densities(&mut gaussians, &density, &lattice, 0.5, 1.0);
        let sigma: Vec<f32> = gaussians
            .raw_densities
            .iter()
            .map(|&r| softplus(r))
            .collect();
        assert!(sigma[0] < 2.0 * 0.8 && sigma[0] > 2.0 * 0.5, "{sigma:?}");
        assert!(
            sigma[1] > 0.2 * 1.5 && sigma[1] <= 0.2 * 2.0 + 1e-5,
            "{sigma:?}"
        );
        assert!((sigma[2] - 1.0).abs() < 1e-4, "{sigma:?}");
        assert_eq!(report.changed, 2, "{report:?}");
        // Nothing changes with blend 0.
        let before = gaussians.clone();
        smooth_carried_densities(&mut gaussians, &density, &lattice, 0.0, 1.0);
        assert_eq!(gaussians, before);
    }
}
