//! Stage 1 of the CPU path: every Gaussian seen by the camera, its screen footprint, and the
//! depth-sorted list of Gaussians per tile.

use rayon::prelude::*;

use super::{TILE_SIZE, ViewFrame};
use crate::gaussians::GaussianSlices;
use crate::math::{ViewSplat, dot3};
use crate::{AlphaModel, RasterOptions};

/// Inclusive-exclusive tile rectangle a Gaussian may touch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct TileRect {
    x0: usize,
    x1: usize,
    y0: usize,
    y1: usize,
}

/// `o = 1 - exp(-sigma)`: the opacity of [`AlphaModel::SplatOpacity`].
pub(super) fn splat_opacity(sigma: f32) -> f32 {
    -(-sigma).exp_m1()
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
    for (i, row) in n.iter_mut().enumerate() {
        for (j, value) in row.iter_mut().enumerate() {
            *value = if i == j { c - tau } else { 0.0 } - m[i] * m[j];
        }
    }
    let mut quad = [[0.0f64; 3]; 3];
    for (i, row) in quad.iter_mut().enumerate() {
        for (j, value) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            for a in 0..3 {
                for b in 0..3 {
                    acc += l[a][i] * n[a][b] * l[b][j];
                }
            }
            *value = acc;
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

/// Every Gaussian as the camera sees it, and the depth-sorted per-tile lists.
#[derive(Debug, Clone)]
pub struct Binning {
    pub splats: Vec<ViewSplat>,
    /// For each tile, the indices of the Gaussians touching it, nearest centre first.
    pub tiles: Vec<Vec<u32>>,
}

/// Projects every Gaussian into `frame` and bins the visible ones into tiles.
pub fn project_and_bin(
    gaussians: &GaussianSlices,
    frame: &ViewFrame,
    options: &RasterOptions,
) -> Binning {
    let projected: Vec<(ViewSplat, Option<(f32, TileRect)>)> = (0..gaussians.len())
        .into_par_iter()
        .map(|i| {
            let g = gaussians.get(i);
            let (splat, ctx) = g.view(&frame.world_to_cam, frame.origin);
            let depth = -dot3(frame.world_to_cam[2], ctx.offset);
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
