//! Plain-Rust implementation of the volumetric Gaussian rasterizer over host slices,
//! parallel over 16x16 screen tiles with rayon. Every CPU backend (NdArray, Flex) calls it.
//!
//! Pipeline: project every Gaussian into the camera's whitened frame and bound its footprint
//! (`project`), sort by view depth of the centre and bin into tiles (`bin`), composite each
//! pixel front to back (`render_tile`); the backward pass replays each pixel back to front from
//! its saved final transmittance (`backward_tile`) and chains per-Gaussian gradients back to
//! the world-space parameters (`math::view_vjp`).

// Loops over the RGB channel index touch several arrays at once; an index reads best there.
#![allow(clippy::needless_range_loop)]

use rayon::prelude::*;

use crate::math::{RaySample, ViewContext, ViewSplat, WorldGaussian, WorldGaussianGrad};
use crate::{AlphaModel, RasterOptions};
use gausmoke_core::Camera;

/// Tile edge in pixels (shared with the GPU kernels so both bin identically).
pub const TILE_SIZE: usize = 16;
/// Channels of the op's packed output: RGB, final transmittance, and the number of tile-list
/// entries each pixel walked before stopping (what the backward pass replays).
pub const OUTPUT_CHANNELS: usize = 5;

/// Borrowed, flat (row-major) parameters of `N` Gaussians plus the background colour.
#[derive(Debug, Clone, Copy)]
pub struct SceneRef<'a> {
    pub means: &'a [f32],
    pub quats: &'a [f32],
    pub log_scales: &'a [f32],
    pub raw_densities: &'a [f32],
    pub colors: &'a [f32],
    pub background: [f32; 3],
}

impl SceneRef<'_> {
    pub fn len(&self) -> usize {
        self.raw_densities.len()
    }

    pub fn is_empty(&self) -> bool {
        self.raw_densities.is_empty()
    }

    fn check_shapes(&self) {
        let n = self.len();
        assert_eq!(self.means.len(), 3 * n, "means must be [N, 3]");
        assert_eq!(self.quats.len(), 4 * n, "rotations must be [N, 4]");
        assert_eq!(self.log_scales.len(), 3 * n, "log_scales must be [N, 3]");
        assert_eq!(self.colors.len(), 3 * n, "colors must be [N, 3]");
    }

    fn gaussian(&self, i: usize) -> WorldGaussian {
        let v3 = |s: &[f32]| [s[3 * i], s[3 * i + 1], s[3 * i + 2]];
        WorldGaussian {
            mean: v3(self.means),
            quat: [
                self.quats[4 * i],
                self.quats[4 * i + 1],
                self.quats[4 * i + 2],
                self.quats[4 * i + 3],
            ],
            log_scale: v3(self.log_scales),
            raw_density: self.raw_densities[i],
            color: v3(self.colors),
        }
    }
}

/// Gradients of every input of the op, flat like [`SceneRef`].
#[derive(Debug, Clone, PartialEq)]
pub struct SceneGrads {
    pub means: Vec<f32>,
    pub quats: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub raw_densities: Vec<f32>,
    pub colors: Vec<f32>,
    pub background: [f32; 3],
}

/// The camera in the form the inner loops use.
#[derive(Debug, Clone, Copy)]
struct ViewFrame {
    world_to_cam: [[f32; 3]; 3],
    origin: [f32; 3],
    camera: Camera,
    tiles_x: usize,
    tiles_y: usize,
}

impl ViewFrame {
    fn new(camera: &Camera) -> Self {
        let w2c = camera.rotation_world_to_camera();
        // glam is column-major: row i of W is (col0[i], col1[i], col2[i]).
        let world_to_cam = [
            [w2c.x_axis.x, w2c.y_axis.x, w2c.z_axis.x],
            [w2c.x_axis.y, w2c.y_axis.y, w2c.z_axis.y],
            [w2c.x_axis.z, w2c.y_axis.z, w2c.z_axis.z],
        ];
        let width = camera.width() as usize;
        let height = camera.height() as usize;
        Self {
            world_to_cam,
            origin: camera.position().to_array(),
            camera: *camera,
            tiles_x: width.div_ceil(TILE_SIZE),
            tiles_y: height.div_ceil(TILE_SIZE),
        }
    }

    fn width(&self) -> usize {
        self.camera.width() as usize
    }

    fn height(&self) -> usize {
        self.camera.height() as usize
    }

    /// Unit camera-space direction of the ray through the centre of pixel `(px, py)`.
    #[inline]
    fn pixel_direction(&self, px: usize, py: usize) -> [f32; 3] {
        let d = self
            .camera
            .ray_direction_camera(px as f32 + 0.5, py as f32 + 0.5)
            .normalize();
        d.to_array()
    }

    /// Pixel range `[x0, x1) x [y0, y1)` of the tile `tile`.
    fn tile_pixels(&self, tile: usize) -> (usize, usize, usize, usize) {
        let tx = tile % self.tiles_x;
        let ty = tile / self.tiles_x;
        let x0 = tx * TILE_SIZE;
        let y0 = ty * TILE_SIZE;
        (
            x0,
            (x0 + TILE_SIZE).min(self.width()),
            y0,
            (y0 + TILE_SIZE).min(self.height()),
        )
    }
}

/// Inclusive-exclusive tile rectangle a Gaussian may touch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct TileRect {
    x0: usize,
    x1: usize,
    y0: usize,
    y1: usize,
}

/// Largest transverse term `K` at which this Gaussian can still reach `alpha_min` on some ray:
/// Beer-Lambert: `I <= sqrt(2 pi) s_max exp(-K/2)` because `beta <= s_max` for unit
/// directions; splat opacity: `alpha = o exp(-K/2)`.
fn effective_cutoff(splat: &ViewSplat, max_scale: f32, options: &RasterOptions) -> f32 {
    let alpha_bound = match options.alpha_model {
        AlphaModel::BeerLambert => {
            let needed_optical_depth = -(1.0 - options.alpha_min).ln();
            let peak = splat.sigma * (std::f32::consts::TAU).sqrt() * max_scale;
            2.0 * (peak / needed_optical_depth).ln()
        }
        AlphaModel::SplatOpacity => 2.0 * (splat_opacity(splat.sigma) / options.alpha_min).ln(),
    };
    // Slightly generous so rounding never culls a pixel that the exact test keeps.
    options.kernel_cutoff.min(alpha_bound * 1.001 + 1e-3)
}

/// Screen tiles touched by the cone of rays whose transverse term is at most `cutoff`.
///
/// `K(d) <= tau` is the quadric `d^T L^T [(c - tau) I - m m^T] L d <= 0` (`c = m.m`), a cone
/// with its apex at the camera; on the image plane `z = -1` it is an exact conic. When the
/// camera lies inside the Gaussian's `tau` ellipsoid, or the conic is not a bounded ellipse,
/// the whole image is returned (rare, conservative). Computed in f64: the entries cancel.
fn footprint(splat: &ViewSplat, cutoff: f32, frame: &ViewFrame) -> Option<TileRect> {
    let full = TileRect {
        x0: 0,
        x1: frame.tiles_x,
        y0: 0,
        y1: frame.tiles_y,
    };
    let tau = cutoff as f64;
    let m = splat.center.map(f64::from);
    let l = splat.whiten.map(|row| row.map(f64::from));
    let c = m[0] * m[0] + m[1] * m[1] + m[2] * m[2];
    if c <= tau {
        return Some(full);
    }
    // N = (c - tau) I - m m^T;  M = L^T N L.
    let mut n = [[0.0f64; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            n[i][j] = if i == j { c - tau } else { 0.0 } - m[i] * m[j];
        }
    }
    let mut quad = [[0.0f64; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let mut acc = 0.0;
            for a in 0..3 {
                for b in 0..3 {
                    acc += l[a][i] * n[a][b] * l[b][j];
                }
            }
            quad[i][j] = acc;
        }
    }
    // With d = (x, y, -1): f(x, y) = v^T P v - 2 b.v + quad[2][2], v = (x, y).
    let (p00, p01, p11) = (quad[0][0], quad[0][1], quad[1][1]);
    let det = p00 * p11 - p01 * p01;
    if !(p00 > 0.0 && det > 0.0) {
        return Some(full);
    }
    let (b0, b1) = (quad[0][2], quad[1][2]);
    let (inv00, inv01, inv11) = (p11 / det, -p01 / det, p00 / det);
    let (x0, y0) = (inv00 * b0 + inv01 * b1, inv01 * b0 + inv11 * b1);
    let radius = b0 * x0 + b1 * y0 - quad[2][2];
    if radius <= 0.0 {
        return None;
    }
    let half_x = (radius * inv00).sqrt();
    let half_y = (radius * inv11).sqrt();
    let k = frame.camera.intrinsics();
    let (fx, fy, cx, cy) = (k.fx as f64, k.fy as f64, k.cx as f64, k.cy as f64);
    // Pixel centres u = i + 0.5 inside [u_min, u_max]; one pixel of slack for rounding.
    let u_min = cx + fx * (x0 - half_x);
    let u_max = cx + fx * (x0 + half_x);
    let v_min = cy - fy * (y0 + half_y);
    let v_max = cy - fy * (y0 - half_y);
    let width = frame.width() as f64;
    let height = frame.height() as f64;
    if !(u_min.is_finite() && u_max.is_finite() && v_min.is_finite() && v_max.is_finite()) {
        return Some(full);
    }
    let px0 = (u_min - 1.5).ceil().max(0.0);
    let px1 = (u_max + 0.5).floor().min(width - 1.0);
    let py0 = (v_min - 1.5).ceil().max(0.0);
    let py1 = (v_max + 0.5).floor().min(height - 1.0);
    if px0 > px1 || py0 > py1 {
        return None;
    }
    let tile = TILE_SIZE as f64;
    Some(TileRect {
        x0: (px0 / tile) as usize,
        x1: (px1 / tile) as usize + 1,
        y0: (py0 / tile) as usize,
        y1: (py1 / tile) as usize + 1,
    })
}

/// Projection result of every Gaussian, and the depth-sorted per-tile lists.
struct Binning {
    splats: Vec<ViewSplat>,
    /// For each tile, the indices of the Gaussians touching it, nearest centre first.
    tiles: Vec<Vec<u32>>,
}

fn project_and_bin(scene: &SceneRef, frame: &ViewFrame, options: &RasterOptions) -> Binning {
    let projected: Vec<(ViewSplat, Option<(f32, TileRect)>)> = (0..scene.len())
        .into_par_iter()
        .map(|i| {
            let g = scene.gaussian(i);
            let (splat, ctx) = g.view(&frame.world_to_cam, frame.origin);
            let depth = -crate::math::dot3(frame.world_to_cam[2], ctx.offset);
            if depth <= options.near_plane || splat.sigma <= 0.0 {
                return (splat, None);
            }
            let max_scale = g.log_scale.iter().fold(f32::MIN, |a, &b| a.max(b)).exp();
            let cutoff = effective_cutoff(&splat, max_scale, options);
            if cutoff <= 0.0 {
                return (splat, None);
            }
            let rect = footprint(&splat, cutoff, frame);
            (splat, rect.map(|r| (depth, r)))
        })
        .collect();

    let mut order: Vec<(f32, u32)> = projected
        .iter()
        .enumerate()
        .filter_map(|(i, (_, vis))| vis.map(|(depth, _)| (depth, i as u32)))
        .collect();
    // Ties broken by index so every backend composites in the same order.
    order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));

    let mut tiles = vec![Vec::new(); frame.tiles_x * frame.tiles_y];
    for &(_, i) in &order {
        let rect = projected[i as usize]
            .1
            .expect("sorted Gaussians are visible")
            .1;
        for ty in rect.y0..rect.y1 {
            for tx in rect.x0..rect.x1 {
                tiles[ty * frame.tiles_x + tx].push(i);
            }
        }
    }
    Binning {
        splats: projected.into_iter().map(|(s, _)| s).collect(),
        tiles,
    }
}

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

/// `o = 1 - exp(-sigma)`: the opacity of [`AlphaModel::SplatOpacity`].
fn splat_opacity(sigma: f32) -> f32 {
    -(-sigma).exp_m1()
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

fn render_tile(
    tile: usize,
    list: &[u32],
    splats: &[ViewSplat],
    frame: &ViewFrame,
    options: &RasterOptions,
    background: [f32; 3],
) -> Vec<f32> {
    let (x0, x1, y0, y1) = frame.tile_pixels(tile);
    let mut out = Vec::with_capacity((x1 - x0) * (y1 - y0) * OUTPUT_CHANNELS);
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
                out.push(color[c] + transmittance * background[c]);
            }
            out.push(transmittance);
            out.push(walked as f32);
        }
    }
    out
}

/// Renders the scene; returns `[H, W, OUTPUT_CHANNELS]` row-major.
pub fn forward(scene: &SceneRef, camera: &Camera, options: &RasterOptions) -> Vec<f32> {
    scene.check_shapes();
    let frame = ViewFrame::new(camera);
    let binning = project_and_bin(scene, &frame, options);
    let tiles: Vec<Vec<f32>> = binning
        .tiles
        .par_iter()
        .enumerate()
        .map(|(t, list)| render_tile(t, list, &binning.splats, &frame, options, scene.background))
        .collect();
    let width = frame.width();
    // Poisoned so that a pixel no tile wrote shows up as NaN in tests.
    let mut image = vec![f32::NAN; width * frame.height() * OUTPUT_CHANNELS];
    for (t, values) in tiles.iter().enumerate() {
        let (x0, x1, y0, y1) = frame.tile_pixels(t);
        let row_len = (x1 - x0) * OUTPUT_CHANNELS;
        for (r, py) in (y0..y1).enumerate() {
            let start = (py * width + x0) * OUTPUT_CHANNELS;
            image[start..start + row_len].copy_from_slice(&values[r * row_len..(r + 1) * row_len]);
        }
    }
    image
}

/// Gradient of the loss with respect to the camera-dependent quantities of one Gaussian.
#[derive(Debug, Clone, Copy, Default)]
struct SplatGrad {
    whiten: [[f32; 3]; 3],
    center: [f32; 3],
    sigma: f32,
    color: [f32; 3],
}

impl SplatGrad {
    fn add(&mut self, other: &SplatGrad) {
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

/// Back-to-front replay of one tile. Returns gradients per tile-list entry and for the
/// background.
#[allow(clippy::too_many_arguments)]
fn backward_tile(
    tile: usize,
    list: &[u32],
    splats: &[ViewSplat],
    frame: &ViewFrame,
    options: &RasterOptions,
    background: [f32; 3],
    output: &[f32],
    grad_output: &[f32],
) -> (Vec<SplatGrad>, [f32; 3]) {
    let (x0, x1, y0, y1) = frame.tile_pixels(tile);
    let mut grads = vec![SplatGrad::default(); list.len()];
    let mut grad_background = [0.0f32; 3];
    for py in y0..y1 {
        for px in x0..x1 {
            let base = (py * frame.width() + px) * OUTPUT_CHANNELS;
            let grad_color = [
                grad_output[base],
                grad_output[base + 1],
                grad_output[base + 2],
            ];
            let grad_final_t = grad_output[base + 3];
            let final_t = output[base + 3];
            let walked = output[base + 4] as usize;
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
                crate::math::sample_vjp(
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

/// Gradients of a loss with respect to every input, given `output` (the forward result) and
/// `grad_output` (its gradient), both `[H, W, OUTPUT_CHANNELS]`.
pub fn backward(
    scene: &SceneRef,
    camera: &Camera,
    options: &RasterOptions,
    output: &[f32],
    grad_output: &[f32],
) -> SceneGrads {
    scene.check_shapes();
    let frame = ViewFrame::new(camera);
    let pixels = frame.width() * frame.height() * OUTPUT_CHANNELS;
    assert_eq!(
        output.len(),
        pixels,
        "saved render output has the wrong size"
    );
    assert_eq!(
        grad_output.len(),
        pixels,
        "render gradient has the wrong size"
    );
    let binning = project_and_bin(scene, &frame, options);
    let per_tile: Vec<(Vec<SplatGrad>, [f32; 3])> = binning
        .tiles
        .par_iter()
        .enumerate()
        .map(|(t, list)| {
            backward_tile(
                t,
                list,
                &binning.splats,
                &frame,
                options,
                scene.background,
                output,
                grad_output,
            )
        })
        .collect();

    // Sequential scatter in tile order: deterministic sums, run after run.
    let n = scene.len();
    let mut splat_grads = vec![SplatGrad::default(); n];
    let mut background = [0.0f32; 3];
    for ((grads, grad_bg), list) in per_tile.iter().zip(&binning.tiles) {
        for (g, &gi) in grads.iter().zip(list) {
            splat_grads[gi as usize].add(g);
        }
        for c in 0..3 {
            background[c] += grad_bg[c];
        }
    }

    let world: Vec<WorldGaussianGrad> = (0..n)
        .into_par_iter()
        .map(|i| {
            let g = scene.gaussian(i);
            let sg = &splat_grads[i];
            let (_, ctx): (ViewSplat, ViewContext) = g.view(&frame.world_to_cam, frame.origin);
            crate::math::view_vjp(
                &g,
                &ctx,
                &frame.world_to_cam,
                &sg.whiten,
                sg.center,
                sg.sigma,
                sg.color,
            )
        })
        .collect();

    SceneGrads {
        means: world.iter().flat_map(|g| g.mean).collect(),
        quats: world.iter().flat_map(|g| g.quat).collect(),
        log_scales: world.iter().flat_map(|g| g.log_scale).collect(),
        raw_densities: world.iter().map(|g| g.raw_density).collect(),
        colors: world.iter().flat_map(|g| g.color).collect(),
        background,
    }
}
