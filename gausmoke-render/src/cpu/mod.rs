//! Plain-Rust implementation of the volumetric Gaussian rasterizer over host slices,
//! parallel over 16x16 screen tiles with rayon. Every CPU backend (NdArray, Flex) runs it; it
//! is also the twin each GPU stage is tested against.
//!
//! Stages: project every Gaussian into the camera's whitened frame, bound its footprint by
//! the exact image-plane ellipse and bin it into the tiles that ellipse meets, nearest centre
//! first ([`project`]); composite the pixels front to back, eight at a time as SIMD lanes
//! ([`composite`], [`lanes`]). The backward pass reuses the forward's [`Binning`], replays
//! each pixel back to front from its final transmittance and chains per-Gaussian gradients
//! back to the world-space parameters ([`crate::math::view_vjp`]).

mod composite;
mod lanes;
mod project;

use rayon::prelude::*;

use crate::RasterOptions;
use crate::gaussians::{GaussianSlices, HostGaussians};
use crate::math::ViewContext;
use composite::{SplatGrad, TileInputs, TileScene, backward_tile, render_tile};
use gausmoke_core::Camera;
pub use project::{Binning, project_and_bin};

/// Tile edge in pixels (shared with the GPU kernels so both bin identically).
pub const TILE_SIZE: usize = 16;
/// Channels of the rendered image: RGB over the background, then the final transmittance.
pub const IMAGE_CHANNELS: usize = 4;

/// The camera in the form the inner loops use.
#[derive(Debug, Clone, Copy)]
pub struct ViewFrame {
    world_to_cam: [[f32; 3]; 3],
    origin: [f32; 3],
    camera: Camera,
    tiles_x: usize,
    tiles_y: usize,
}

impl ViewFrame {
    pub fn new(camera: &Camera) -> Self {
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

/// A forward render and what its backward pass reuses.
#[derive(Debug, Clone)]
pub struct Rendered {
    /// `[H, W, IMAGE_CHANNELS]`, row-major.
    pub image: Vec<f32>,
    /// Per pixel, how many entries of its tile's list it walked before stopping.
    pub walked: Vec<u32>,
    pub binning: Binning,
}

/// Renders `gaussians` over `background`.
pub fn forward(
    gaussians: &GaussianSlices,
    background: [f32; 3],
    camera: &Camera,
    options: &RasterOptions,
) -> Rendered {
    assert!(
        gaussians.mismatched().is_none(),
        "every attribute must hold N rows"
    );
    let frame = ViewFrame::new(camera);
    let binning = project_and_bin(gaussians, &frame, options);
    let scene = TileScene {
        splats: &binning.splats,
        cutoffs: &binning.cutoffs,
        frame: &frame,
        options,
        background,
    };
    let tiles: Vec<_> = binning
        .tiles
        .par_iter()
        .enumerate()
        .map(|(t, list)| render_tile(t, list, &scene))
        .collect();
    let width = frame.width();
    let pixels = width * frame.height();
    // Poisoned so that a pixel no tile wrote shows up as NaN in tests.
    let mut image = vec![f32::NAN; pixels * IMAGE_CHANNELS];
    let mut walked = vec![u32::MAX; pixels];
    for (t, tile) in tiles.iter().enumerate() {
        let (x0, x1, y0, y1) = frame.tile_pixels(t);
        let row = x1 - x0;
        for (r, py) in (y0..y1).enumerate() {
            let start = py * width + x0;
            image[start * IMAGE_CHANNELS..(start + row) * IMAGE_CHANNELS].copy_from_slice(
                &tile.values[r * row * IMAGE_CHANNELS..(r + 1) * row * IMAGE_CHANNELS],
            );
            walked[start..start + row].copy_from_slice(&tile.walked[r * row..(r + 1) * row]);
        }
    }
    Rendered {
        image,
        walked,
        binning,
    }
}

/// Gradients of a loss with respect to every Gaussian attribute and the background, given the
/// forward pass `rendered` of the same inputs and the gradient of its image.
pub fn backward(
    gaussians: &GaussianSlices,
    background: [f32; 3],
    camera: &Camera,
    options: &RasterOptions,
    rendered: &Rendered,
    grad_image: &[f32],
) -> (HostGaussians, [f32; 3]) {
    let frame = ViewFrame::new(camera);
    let pixels = frame.width() * frame.height();
    assert_eq!(
        rendered.image.len(),
        pixels * IMAGE_CHANNELS,
        "saved render has the wrong size"
    );
    assert_eq!(
        grad_image.len(),
        pixels * IMAGE_CHANNELS,
        "render gradient has the wrong size"
    );
    let binning = &rendered.binning;
    let scene = TileScene {
        splats: &binning.splats,
        cutoffs: &binning.cutoffs,
        frame: &frame,
        options,
        background,
    };
    let inputs = TileInputs {
        image: &rendered.image,
        walked: &rendered.walked,
        grad_image,
    };
    let per_tile: Vec<(Vec<SplatGrad>, [f32; 3])> = binning
        .tiles
        .par_iter()
        .enumerate()
        .map(|(t, list)| backward_tile(t, list, &scene, &inputs))
        .collect();

    // Sequential scatter in tile order: deterministic sums, run after run.
    let n = gaussians.len();
    let mut splat_grads = vec![SplatGrad::default(); n];
    let mut grad_background = [0.0f32; 3];
    for ((grads, grad_bg), list) in per_tile.iter().zip(&binning.tiles) {
        for (g, &gi) in grads.iter().zip(list) {
            splat_grads[gi as usize].add(g);
        }
        for (total, value) in grad_background.iter_mut().zip(grad_bg) {
            *total += value;
        }
    }

    let world: Vec<_> = (0..n)
        .into_par_iter()
        .map(|i| {
            let g = gaussians.get(i);
            let sg = &splat_grads[i];
            let (_, ctx): (_, ViewContext) = g.view(&frame.world_to_cam, frame.origin);
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
    let mut grads = HostGaussians::with_capacity(n);
    for g in &world {
        grads.push(g);
    }
    (grads, grad_background)
}
