//! Stages 2 and 3 of the CPU path: compositing each pixel of a tile front to back, and its
//! back-to-front replay for the gradients.

// Loops over the RGB channel index touch several arrays at once; an index reads best there.
#![allow(clippy::needless_range_loop)]

use super::project::splat_opacity;
use super::{IMAGE_CHANNELS, ViewFrame};
use crate::math::{RaySample, ViewSplat, sample_vjp};
use crate::{AlphaModel, RasterOptions};

/// Opacity of one Gaussian on one ray, with the unclamped value and its partial derivatives
/// for the gradient.
#[derive(Debug, Clone, Copy)]
struct Opacity {
    sample: RaySample,
    /// Alpha before the `alpha_max` clamp (see [`AlphaModel`]).
    raw_alpha: f32,
    /// Composited opacity, `min(raw_alpha, alpha_max)`.
    alpha: f32,
    /// `d raw_alpha / d sigma`.
    d_alpha_d_sigma: f32,
    /// `d raw_alpha / d ln(kernel)`: the kernel is `I` (Beer-Lambert) or `exp(-K/2)`.
    d_alpha_d_log_kernel: f32,
    /// 1 when the kernel is the line integral `I` (its `-ln(a)/2` term counts), else 0.
    length_weight: f32,
}

/// The one place that decides whether a Gaussian contributes to a ray; forward and backward
/// both call it so their decisions cannot diverge.
#[inline]
fn opacity(splat: &ViewSplat, dir: [f32; 3], options: &RasterOptions) -> Option<Opacity> {
    let sample = splat.sample(dir, options.kernel_cutoff)?;
    let (raw_alpha, d_alpha_d_sigma, d_alpha_d_log_kernel, length_weight) =
        match options.alpha_model {
            AlphaModel::BeerLambert => {
                // alpha = 1 - exp(-sigma I): d alpha / d(sigma I) = exp(-sigma I).
                let optical_depth = splat.sigma * sample.integral;
                let transmitted = (-optical_depth).exp();
                (
                    -(-optical_depth).exp_m1(),
                    transmitted * sample.integral,
                    transmitted * optical_depth,
                    1.0,
                )
            }
            AlphaModel::SplatOpacity => {
                let kernel = (-0.5 * sample.transverse).exp();
                let raw_alpha = splat_opacity(splat.sigma) * kernel;
                (raw_alpha, (-splat.sigma).exp() * kernel, raw_alpha, 0.0)
            }
        };
    if raw_alpha < options.alpha_min {
        return None;
    }
    Some(Opacity {
        sample,
        raw_alpha,
        alpha: raw_alpha.min(options.alpha_max),
        d_alpha_d_sigma,
        d_alpha_d_log_kernel,
        length_weight,
    })
}

/// One rendered tile: [`IMAGE_CHANNELS`] values per pixel, row-major within the tile, and
/// how many entries of the tile's list each pixel walked before it stopped.
pub(super) struct TilePixels {
    pub values: Vec<f32>,
    pub walked: Vec<u32>,
}

pub(super) fn render_tile(
    tile: usize,
    list: &[u32],
    splats: &[ViewSplat],
    frame: &ViewFrame,
    options: &RasterOptions,
    background: [f32; 3],
) -> TilePixels {
    let (x0, x1, y0, y1) = frame.tile_pixels(tile);
    let pixels = (x1 - x0) * (y1 - y0);
    let mut out = TilePixels {
        values: Vec::with_capacity(pixels * IMAGE_CHANNELS),
        walked: Vec::with_capacity(pixels),
    };
    for py in y0..y1 {
        for px in x0..x1 {
            let dir = frame.pixel_direction(px, py);
            let mut transmittance = 1.0f32;
            let mut color = [0.0f32; 3];
            let mut walked = 0usize;
            for (k, &gi) in list.iter().enumerate() {
                let splat = &splats[gi as usize];
                let Some(op) = opacity(splat, dir, options) else {
                    continue;
                };
                let next = transmittance * (1.0 - op.alpha);
                if next < options.transmittance_min {
                    break;
                }
                let weight = transmittance * op.alpha;
                for c in 0..3 {
                    color[c] += weight * splat.color[c];
                }
                transmittance = next;
                walked = k + 1;
            }
            for c in 0..3 {
                out.values.push(color[c] + transmittance * background[c]);
            }
            out.values.push(transmittance);
            out.walked.push(walked as u32);
        }
    }
    out
}

/// Gradient of the loss with respect to the camera-dependent quantities of one Gaussian.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct SplatGrad {
    pub whiten: [[f32; 3]; 3],
    pub center: [f32; 3],
    pub sigma: f32,
    pub color: [f32; 3],
}

impl SplatGrad {
    pub fn add(&mut self, other: &SplatGrad) {
        for k in 0..3 {
            for j in 0..3 {
                self.whiten[k][j] += other.whiten[k][j];
            }
            self.center[k] += other.center[k];
            self.color[k] += other.color[k];
        }
        self.sigma += other.sigma;
    }
}

/// What the backward pass of one tile reads: the forward image and walked counts, and the
/// gradient of the image (all full-image, row-major).
pub(super) struct TileInputs<'a> {
    pub image: &'a [f32],
    pub walked: &'a [u32],
    pub grad_image: &'a [f32],
}

/// Back-to-front replay of one tile. Returns gradients per tile-list entry and for the
/// background.
pub(super) fn backward_tile(
    tile: usize,
    list: &[u32],
    splats: &[ViewSplat],
    frame: &ViewFrame,
    options: &RasterOptions,
    background: [f32; 3],
    inputs: &TileInputs,
) -> (Vec<SplatGrad>, [f32; 3]) {
    let (x0, x1, y0, y1) = frame.tile_pixels(tile);
    let mut grads = vec![SplatGrad::default(); list.len()];
    let mut grad_background = [0.0f32; 3];
    for py in y0..y1 {
        for px in x0..x1 {
            let pixel = py * frame.width() + px;
            let base = pixel * IMAGE_CHANNELS;
            let grad_color = [
                inputs.grad_image[base],
                inputs.grad_image[base + 1],
                inputs.grad_image[base + 2],
            ];
            let grad_final_t = inputs.grad_image[base + 3];
            let final_t = inputs.image[base + 3];
            let walked = inputs.walked[pixel] as usize;
            for c in 0..3 {
                grad_background[c] += grad_color[c] * final_t;
            }
            if walked == 0 {
                continue;
            }
            let dir = frame.pixel_direction(px, py);
            // Colour composited behind the current Gaussian, background included.
            let mut behind = background.map(|b| b * final_t);
            let mut transmittance_after = final_t;
            for k in (0..walked).rev() {
                let splat = &splats[list[k] as usize];
                let Some(op) = opacity(splat, dir, options) else {
                    continue;
                };
                let one_minus = 1.0 - op.alpha;
                let transmittance_before = transmittance_after / one_minus;
                let g = &mut grads[k];
                let mut grad_alpha = -grad_final_t * final_t / one_minus;
                for c in 0..3 {
                    g.color[c] += grad_color[c] * transmittance_before * op.alpha;
                    grad_alpha += grad_color[c]
                        * (transmittance_before * splat.color[c] - behind[c] / one_minus);
                    behind[c] += transmittance_before * op.alpha * splat.color[c];
                }
                transmittance_after = transmittance_before;
                if op.raw_alpha >= options.alpha_max {
                    continue; // clamped: alpha is constant here
                }
                g.sigma += grad_alpha * op.d_alpha_d_sigma;
                sample_vjp(
                    &op.sample,
                    dir,
                    grad_alpha * op.d_alpha_d_log_kernel,
                    op.length_weight,
                    &mut g.whiten,
                    &mut g.center,
                );
            }
        }
    }
    (grads, grad_background)
}
