//! Stages 2 and 3 of the CPU path: compositing each pixel of a tile front to back, and its
//! back-to-front replay for the gradients.

// Loops over the RGB channel index touch several arrays at once; an index reads best there.
#![allow(clippy::needless_range_loop)]

use super::lanes::{LANES, Lanes, Mask, Rays, length_weight, sample};
use super::{IMAGE_CHANNELS, ViewFrame};
use crate::RasterOptions;
use crate::math::ViewSplat;

/// One rendered tile: [`IMAGE_CHANNELS`] values per pixel, row-major within the tile, and
/// how many entries of the tile's list each pixel walked before it stopped.
pub(super) struct TilePixels {
    pub values: Vec<f32>,
    pub walked: Vec<u32>,
}

/// What every tile of one render reads: the binned Gaussians and the camera.
pub(super) struct TileScene<'a> {
    pub splats: &'a [ViewSplat],
    pub cutoffs: &'a [f32],
    pub frame: &'a ViewFrame,
    pub options: &'a RasterOptions,
    pub background: [f32; 3],
}

/// Renders one tile, with AVX2 where the CPU has it. The arithmetic is the same with or
/// without it (no fused multiply-add, sums in lane order), so the pixels are identical.
pub(super) fn render_tile(tile: usize, list: &[u32], scene: &TileScene) -> TilePixels {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has just been found to support AVX2.
        return unsafe { render_tile_avx2(tile, list, scene) };
    }
    render_tile_lanes(tile, list, scene)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn render_tile_avx2(tile: usize, list: &[u32], scene: &TileScene) -> TilePixels {
    render_tile_lanes(tile, list, scene)
}

#[inline(always)]
fn render_tile_lanes(tile: usize, list: &[u32], scene: &TileScene) -> TilePixels {
    let TileScene {
        splats,
        cutoffs,
        frame,
        options,
        background,
    } = *scene;
    let (x0, x1, y0, y1) = frame.tile_pixels(tile);
    let pixels = (x1 - x0) * (y1 - y0);
    let mut out = TilePixels {
        values: Vec::with_capacity(pixels * IMAGE_CHANNELS),
        walked: Vec::with_capacity(pixels),
    };
    for py in y0..y1 {
        for packet_x in (x0..x1).step_by(LANES) {
            let (rays, mut live) = packet_rays(frame, packet_x, x1, py);
            let lanes = (x1 - packet_x).min(LANES);
            let mut transmittance: Lanes = [1.0; LANES];
            let mut color = [[0.0f32; LANES]; 3];
            let mut walked = [0u32; LANES];
            for (k, &gi) in list.iter().enumerate() {
                if !live.iter().any(|&l| l) {
                    break;
                }
                let splat = &splats[gi as usize];
                let Some(s) = sample(splat, cutoffs[gi as usize], &rays, &live, options) else {
                    continue;
                };
                for i in 0..LANES {
                    let alpha = s.raw_alpha[i].min(options.alpha_max);
                    let next = transmittance[i] * (1.0 - alpha);
                    let stops = s.hit[i] & (next < options.transmittance_min);
                    let adds = s.hit[i] & !stops;
                    let weight = if adds { transmittance[i] * alpha } else { 0.0 };
                    for c in 0..3 {
                        color[c][i] += weight * splat.color[c];
                    }
                    transmittance[i] = if adds { next } else { transmittance[i] };
                    walked[i] = if adds { k as u32 + 1 } else { walked[i] };
                    live[i] &= !stops;
                }
            }
            for i in 0..lanes {
                for c in 0..3 {
                    out.values
                        .push(color[c][i] + transmittance[i] * background[c]);
                }
                out.values.push(transmittance[i]);
                out.walked.push(walked[i]);
            }
        }
    }
    out
}

/// The rays of the packet starting at pixel `(packet_x, py)`, and which lanes lie inside the
/// tile (the others repeat the first ray and stay masked).
fn packet_rays(frame: &ViewFrame, packet_x: usize, x1: usize, py: usize) -> (Rays, Mask) {
    let mut rays = Rays {
        dir: [[0.0; LANES]; 3],
    };
    let mut inside = [false; LANES];
    for i in 0..LANES {
        let px = packet_x + i;
        inside[i] = px < x1;
        let d = frame.pixel_direction(if inside[i] { px } else { packet_x }, py);
        for k in 0..3 {
            rays.dir[k][i] = d[k];
        }
    }
    (rays, inside)
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
    scene: &TileScene,
    inputs: &TileInputs,
) -> (Vec<SplatGrad>, [f32; 3]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has just been found to support AVX2.
        return unsafe { backward_tile_avx2(tile, list, scene, inputs) };
    }
    backward_tile_lanes(tile, list, scene, inputs)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn backward_tile_avx2(
    tile: usize,
    list: &[u32],
    scene: &TileScene,
    inputs: &TileInputs,
) -> (Vec<SplatGrad>, [f32; 3]) {
    backward_tile_lanes(tile, list, scene, inputs)
}

#[inline(always)]
fn backward_tile_lanes(
    tile: usize,
    list: &[u32],
    scene: &TileScene,
    inputs: &TileInputs,
) -> (Vec<SplatGrad>, [f32; 3]) {
    let TileScene {
        splats,
        cutoffs,
        frame,
        options,
        background,
    } = *scene;
    let (x0, x1, y0, y1) = frame.tile_pixels(tile);
    let mut grads = vec![SplatGrad::default(); list.len()];
    let mut grad_background = [0.0f32; 3];
    let length_weight = length_weight(options.alpha_model);
    for py in y0..y1 {
        for packet_x in (x0..x1).step_by(LANES) {
            let (rays, inside) = packet_rays(frame, packet_x, x1, py);
            let mut grad_color = [[0.0f32; LANES]; 3];
            let mut grad_final_t: Lanes = [0.0; LANES];
            let mut final_t: Lanes = [0.0; LANES];
            let mut walked = [0usize; LANES];
            for i in 0..LANES {
                if !inside[i] {
                    continue;
                }
                let pixel = py * frame.width() + packet_x + i;
                let base = pixel * IMAGE_CHANNELS;
                for c in 0..3 {
                    grad_color[c][i] = inputs.grad_image[base + c];
                    grad_background[c] += grad_color[c][i] * inputs.image[base + 3];
                }
                grad_final_t[i] = inputs.grad_image[base + 3];
                final_t[i] = inputs.image[base + 3];
                walked[i] = inputs.walked[pixel] as usize;
            }
            let deepest = walked.iter().copied().max().unwrap_or(0);
            // Colour composited behind the current Gaussian, background included.
            let mut behind = [0, 1, 2].map(|c| final_t.map(|t| background[c] * t));
            let mut transmittance_after = final_t;
            for k in (0..deepest).rev() {
                let gi = list[k] as usize;
                let splat = &splats[gi];
                let live: Mask = std::array::from_fn(|i| k < walked[i]);
                let Some(s) = sample(splat, cutoffs[gi], &rays, &live, options) else {
                    continue;
                };
                // Per lane, then summed over the packet in lane order.
                let mut color_grad = [[0.0f32; LANES]; 3];
                let mut sigma_grad: Lanes = [0.0; LANES];
                let mut log_kernel_grad: Lanes = [0.0; LANES];
                for i in 0..LANES {
                    let alpha = s.raw_alpha[i].min(options.alpha_max);
                    let one_minus = 1.0 - alpha;
                    let before = transmittance_after[i] / one_minus;
                    let mut grad_alpha = -grad_final_t[i] * final_t[i] / one_minus;
                    for c in 0..3 {
                        let weight = before * alpha;
                        color_grad[c][i] = if s.hit[i] {
                            grad_color[c][i] * weight
                        } else {
                            0.0
                        };
                        grad_alpha +=
                            grad_color[c][i] * (before * splat.color[c] - behind[c][i] / one_minus);
                        let behind_next = behind[c][i] + weight * splat.color[c];
                        behind[c][i] = if s.hit[i] { behind_next } else { behind[c][i] };
                    }
                    transmittance_after[i] = if s.hit[i] {
                        before
                    } else {
                        transmittance_after[i]
                    };
                    // Where alpha is clamped it is constant: no gradient reaches sigma or shape.
                    let varies = s.hit[i] & (s.raw_alpha[i] < options.alpha_max);
                    sigma_grad[i] = if varies {
                        grad_alpha * s.d_alpha_d_sigma[i]
                    } else {
                        0.0
                    };
                    log_kernel_grad[i] = if varies {
                        grad_alpha * s.d_alpha_d_log_kernel[i]
                    } else {
                        0.0
                    };
                }
                // `sample_vjp` across the packet: d lnI/de = -w e/a - gamma r, d lnI/dm = r.
                let mut whiten_grad = [[[0.0f32; LANES]; 3]; 3];
                let mut center_grad = [[0.0f32; LANES]; 3];
                for i in 0..LANES {
                    let g_ln = log_kernel_grad[i];
                    for a in 0..3 {
                        let g_e = g_ln
                            * (-length_weight * s.dir_whitened[a][i] / s.dir_norm_sq[i]
                                - s.peak_depth[i] * s.residual[a][i]);
                        for j in 0..3 {
                            whiten_grad[a][j][i] = g_e * rays.dir[j][i];
                        }
                        center_grad[a][i] = g_ln * s.residual[a][i];
                    }
                }
                let g = &mut grads[k];
                for c in 0..3 {
                    g.color[c] += color_grad[c].iter().sum::<f32>();
                }
                g.sigma += sigma_grad.iter().sum::<f32>();
                for a in 0..3 {
                    for j in 0..3 {
                        g.whiten[a][j] += whiten_grad[a][j].iter().sum::<f32>();
                    }
                    g.center[a] += center_grad[a].iter().sum::<f32>();
                }
            }
        }
    }
    (grads, grad_background)
}

#[cfg(test)]
mod tests {
    use gausmoke_core::Camera;
    use gausmoke_core::glam::Vec3;

    use super::*;
    use crate::cpu::project_and_bin;
    use crate::procedural::smoke_plume;

    /// The dispatched tile functions (AVX2 where this CPU has it) give bit-identical results
    /// to the portable build of the same code.
    #[test]
    fn simd_dispatch_changes_no_bit() {
        let plume = smoke_plume(2000, Vec3::splat(-0.3), Vec3::splat(0.3), 5);
        let camera =
            Camera::look_at(Vec3::new(0.3, 0.1, 1.0), Vec3::ZERO, Vec3::Y, 45, 37, 0.8).unwrap();
        let frame = ViewFrame::new(&camera);
        let options = RasterOptions::default();
        let binning = project_and_bin(&plume.slices(), &frame, &options);
        let scene = TileScene {
            splats: &binning.splats,
            cutoffs: &binning.cutoffs,
            frame: &frame,
            options: &options,
            background: [0.1, 0.2, 0.3],
        };
        let mut walked_any = false;
        for (t, list) in binning.tiles.iter().enumerate() {
            let fast = render_tile(t, list, &scene);
            let plain = render_tile_lanes(t, list, &scene);
            assert_eq!(fast.values, plain.values, "tile {t}");
            assert_eq!(fast.walked, plain.walked, "tile {t}");
            walked_any |= plain.walked.iter().any(|&w| w > 0);
        }
        assert!(walked_any, "the scene must cover some pixel");

        let rendered = crate::cpu::forward(&plume.slices(), scene.background, &camera, &options);
        let grad_image: Vec<f32> = (0..rendered.image.len())
            .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.5)
            .collect();
        let inputs = TileInputs {
            image: &rendered.image,
            walked: &rendered.walked,
            grad_image: &grad_image,
        };
        for (t, list) in binning.tiles.iter().enumerate() {
            let (fast, fast_bg) = backward_tile(t, list, &scene, &inputs);
            let (plain, plain_bg) = backward_tile_lanes(t, list, &scene, &inputs);
            assert_eq!(fast_bg, plain_bg, "tile {t}");
            for (a, b) in fast.iter().zip(&plain) {
                assert_eq!(
                    (a.whiten, a.center, a.sigma, a.color),
                    (b.whiten, b.center, b.sigma, b.color),
                    "tile {t}"
                );
            }
        }
    }
}
