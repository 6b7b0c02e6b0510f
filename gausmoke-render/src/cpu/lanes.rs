//! A packet of [`LANES`] pixels evaluated against one Gaussian at a time, written as plain
//! loops over fixed-size arrays with no calls and no branches inside, so that the compiler
//! turns each loop into SIMD instructions. The exponentials are our own for that reason
//! (a libm call cannot be vectorised); both are accurate to about one ulp on the ranges used.
//! No fused multiply-add is used anywhere, so results do not depend on the CPU's features.

// Loops over the lane index touch several arrays at once; an index reads best there.
#![allow(clippy::needless_range_loop)]

use std::f32::consts::{LOG2_E, TAU};

use crate::math::ViewSplat;
use crate::{AlphaModel, RasterOptions};

/// Pixels per packet: one row of half a tile.
pub const LANES: usize = 8;

pub type Lanes = [f32; LANES];
pub type Mask = [bool; LANES];

/// `exp(x)` for `x <= 0`, branch-free: `x = n ln 2 + r`, `|r| <= ln 2 / 2`, a degree-7 Taylor
/// polynomial for `e^r` (truncation below 6e-9 relative), and `2^n` built from its bits.
/// Inputs below -87 give `exp(-87)` rather than a subnormal; every caller either multiplies
/// that by a bounded factor or compares it with a threshold far above it.
#[inline(always)]
pub fn exp_nonpositive(x: f32) -> f32 {
    // ln 2 split so that `n * LN2_HI` is exact for |n| < 2^9.
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Adding and subtracting 1.5 * 2^23 rounds to the nearest integer in round-to-nearest.
    const ROUND: f32 = 12_582_912.0;
    let x = x.clamp(-87.0, 0.0);
    let n = (x * LOG2_E + ROUND) - ROUND;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let p = 1.0
        + r * (1.0
            + r * (1.0 / 2.0
                + r * (1.0 / 6.0
                    + r * (1.0 / 24.0
                        + r * (1.0 / 120.0 + r * (1.0 / 720.0 + r * (1.0 / 5040.0)))))));
    let scale = f32::from_bits(((n as i32 + 127) as u32) << 23);
    p * scale
}

/// `(1 - exp(-d), exp(-d))` for an optical depth `d >= 0`: below 0.35 the first from its
/// alternating series (error below 2e-8 relative), so that a thin Gaussian's opacity keeps its
/// relative precision; above, from the exponential, where no digits cancel.
#[inline(always)]
pub fn absorbed_and_transmitted(d: f32) -> (f32, f32) {
    let transmitted = exp_nonpositive(-d);
    let series = d
        * (1.0
            - d * (1.0 / 2.0)
                * (1.0
                    - d * (1.0 / 3.0)
                        * (1.0
                            - d * (1.0 / 4.0)
                                * (1.0
                                    - d * (1.0 / 5.0)
                                        * (1.0 - d * (1.0 / 6.0) * (1.0 - d * (1.0 / 7.0)))))));
    let absorbed = if d < 0.35 { series } else { 1.0 - transmitted };
    (absorbed, transmitted)
}

/// Camera-space unit directions of the packet's rays.
#[derive(Debug, Clone, Copy)]
pub struct Rays {
    pub dir: [Lanes; 3],
}

/// One Gaussian on every ray of a packet (see [`crate::math::RaySample`] for the scalar
/// twin): the transverse term `K`, the line integral and what the gradient reuses. `hit` says
/// where the Gaussian counts: its peak in front of the camera, `K` within its cutoff and
/// `alpha >= alpha_min`.
pub struct PacketSample {
    pub hit: Mask,
    pub dir_whitened: [Lanes; 3],
    pub dir_norm_sq: Lanes,
    pub peak_depth: Lanes,
    pub residual: [Lanes; 3],
    pub raw_alpha: Lanes,
    /// `d raw_alpha / d sigma`.
    pub d_alpha_d_sigma: Lanes,
    /// `d raw_alpha / d ln(kernel)`.
    pub d_alpha_d_log_kernel: Lanes,
}

/// Transverse terms of the packet, and where the Gaussian's support holds the ray: the cheap
/// half of [`sample`], enough to skip a Gaussian that no ray of the packet meets.
#[inline(always)]
fn geometry(splat: &ViewSplat, cutoff: f32, rays: &Rays, live: &Mask) -> PacketSample {
    let l = &splat.whiten;
    let m = &splat.center;
    let mut s = PacketSample {
        hit: [false; LANES],
        dir_whitened: [[0.0; LANES]; 3],
        dir_norm_sq: [0.0; LANES],
        peak_depth: [0.0; LANES],
        residual: [[0.0; LANES]; 3],
        raw_alpha: [0.0; LANES],
        d_alpha_d_sigma: [0.0; LANES],
        d_alpha_d_log_kernel: [0.0; LANES],
    };
    for i in 0..LANES {
        let d = [rays.dir[0][i], rays.dir[1][i], rays.dir[2][i]];
        let e = [0, 1, 2].map(|k| l[k][0] * d[0] + l[k][1] * d[1] + l[k][2] * d[2]);
        let a = e[0] * e[0] + e[1] * e[1] + e[2] * e[2];
        let gamma = (m[0] * e[0] + m[1] * e[1] + m[2] * e[2]) / a;
        let r = [0, 1, 2].map(|k| gamma * e[k] - m[k]);
        let transverse = r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
        for k in 0..3 {
            s.dir_whitened[k][i] = e[k];
            s.residual[k][i] = r[k];
        }
        s.dir_norm_sq[i] = a;
        s.peak_depth[i] = gamma;
        s.hit[i] = live[i] & (gamma > 0.0) & (transverse <= cutoff);
    }
    s
}

/// The opacity of one Gaussian on every ray of a packet, or `None` when it counts on none of
/// them. `live` masks rays that have stopped or lie outside the tile. The one place that
/// decides whether a Gaussian contributes to a ray: forward and backward both call it.
#[inline(always)]
pub fn sample(
    splat: &ViewSplat,
    cutoff: f32,
    rays: &Rays,
    live: &Mask,
    options: &RasterOptions,
) -> Option<PacketSample> {
    let mut s = geometry(splat, cutoff, rays, live);
    if !s.hit.iter().any(|&h| h) {
        return None;
    }
    match options.alpha_model {
        AlphaModel::BeerLambert => {
            for i in 0..LANES {
                let transverse = s.residual[0][i] * s.residual[0][i]
                    + s.residual[1][i] * s.residual[1][i]
                    + s.residual[2][i] * s.residual[2][i];
                let integral = (TAU / s.dir_norm_sq[i]).sqrt() * exp_nonpositive(-0.5 * transverse);
                // alpha = 1 - exp(-sigma I): d alpha / d(sigma I) = exp(-sigma I).
                let optical_depth = splat.sigma * integral;
                let (absorbed, transmitted) = absorbed_and_transmitted(optical_depth);
                s.raw_alpha[i] = absorbed;
                s.d_alpha_d_sigma[i] = transmitted * integral;
                s.d_alpha_d_log_kernel[i] = transmitted * optical_depth;
            }
        }
        AlphaModel::SplatOpacity => {
            let (opacity, transparency) = absorbed_and_transmitted(splat.sigma);
            for i in 0..LANES {
                let transverse = s.residual[0][i] * s.residual[0][i]
                    + s.residual[1][i] * s.residual[1][i]
                    + s.residual[2][i] * s.residual[2][i];
                let kernel = exp_nonpositive(-0.5 * transverse);
                s.raw_alpha[i] = opacity * kernel;
                s.d_alpha_d_sigma[i] = transparency * kernel;
                s.d_alpha_d_log_kernel[i] = opacity * kernel;
            }
        }
    }
    for i in 0..LANES {
        s.hit[i] &= s.raw_alpha[i] >= options.alpha_min;
    }
    s.hit.iter().any(|&h| h).then_some(s)
}

/// 1 when the kernel is the line integral `I` (its `-ln(a)/2` term counts in the gradient of
/// `ln kernel`), 0 for the projected kernel `exp(-K/2)`.
pub fn length_weight(model: AlphaModel) -> f32 {
    match model {
        AlphaModel::BeerLambert => 1.0,
        AlphaModel::SplatOpacity => 0.0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ulps(a: f32, b: f32) -> u32 {
        (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs() as u32
    }

    #[test]
    fn exp_is_within_two_ulps_of_libm() {
        let mut worst = 0;
        for i in 0..=200_000 {
            let x = -80.0 * i as f32 / 200_000.0;
            worst = worst.max(ulps(exp_nonpositive(x), (x as f64).exp() as f32));
        }
        assert!(worst <= 2, "worst error {worst} ulps");
        assert_eq!(exp_nonpositive(0.0), 1.0);
    }

    #[test]
    fn absorbed_keeps_relative_precision_for_thin_gaussians() {
        let mut worst = 0;
        for i in 1..=200_000 {
            let d = 1e-6 * (1.0f32 + 1e-4).powi(i);
            if d > 80.0 {
                break;
            }
            let (absorbed, transmitted) = absorbed_and_transmitted(d);
            let exact = -(-(d as f64)).exp_m1();
            worst = worst.max(ulps(absorbed, exact as f32));
            assert!(
                ulps(transmitted, (-(d as f64)).exp() as f32) <= 2,
                "d = {d}"
            );
        }
        assert!(worst <= 3, "worst error {worst} ulps");
    }
}
