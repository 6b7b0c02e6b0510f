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

/// The image-plane conic `f(x, y) = v^T P v - 2 b.v + q <= 0` (`v = (x, y)`, the ray
/// direction `(x, y, -1)`) of the rays a Gaussian reaches, and the image's pixel mapping.
#[derive(Debug, Clone, Copy)]
struct Conic {
    p00: f64,
    p01: f64,
    p11: f64,
    b0: f64,
    b1: f64,
    q: f64,
}

impl Conic {
    fn at(&self, x: f64, y: f64) -> f64 {
        self.p00 * x * x + 2.0 * self.p01 * x * y + self.p11 * y * y
            - 2.0 * (self.b0 * x + self.b1 * y)
            + self.q
    }

    /// Smallest value of `f` on the segment from `(x, y0)` to `(x, y1)`.
    fn min_on_vertical(&self, x: f64, y0: f64, y1: f64) -> f64 {
        // df/dy = 2 (p01 x + p11 y - b1) = 0.
        let y = ((self.b1 - self.p01 * x) / self.p11).clamp(y0, y1);
        self.at(x, y)
    }

    /// Smallest value of `f` on the segment from `(x0, y)` to `(x1, y)`.
    fn min_on_horizontal(&self, y: f64, x0: f64, x1: f64) -> f64 {
        let x = ((self.b0 - self.p01 * y) / self.p00).clamp(x0, x1);
        self.at(x, y)
    }

    /// Whether the ellipse `f <= 0` meets the rectangle `[x0, x1] x [y0, y1]`: `f` is convex,
    /// so its minimum over the rectangle is its centre's value when the centre is inside,
    /// else on an edge.
    fn meets(&self, x0: f64, x1: f64, y0: f64, y1: f64) -> bool {
        let det = self.p00 * self.p11 - self.p01 * self.p01;
        let cx = (self.p11 * self.b0 - self.p01 * self.b1) / det;
        let cy = (self.p00 * self.b1 - self.p01 * self.b0) / det;
        if (x0..=x1).contains(&cx) && (y0..=y1).contains(&cy) {
            return true;
        }
        let lowest = self
            .min_on_vertical(x0, y0, y1)
            .min(self.min_on_vertical(x1, y0, y1))
            .min(self.min_on_horizontal(y0, x0, x1))
            .min(self.min_on_horizontal(y1, x0, x1));
        lowest <= 0.0
    }
}

/// Where a Gaussian may be seen: the tile rectangle around its footprint, and the exact
/// footprint when it is a bounded ellipse (tiles of the rectangle it misses are skipped).
#[derive(Debug, Clone, Copy)]
struct Footprint {
    rect: TileRect,
    conic: Option<Conic>,
}

impl Footprint {
    /// Whether tile `(tx, ty)` may hold a pixel the Gaussian reaches: the tile's pixel
    /// centres, widened by the same pixel of slack as the rectangle, against the conic.
    fn touches(&self, tx: usize, ty: usize, frame: &ViewFrame) -> bool {
        let Some(conic) = &self.conic else {
            return true;
        };
        let k = frame.camera.intrinsics();
        let (fx, fy, cx, cy) = (k.fx as f64, k.fy as f64, k.cx as f64, k.cy as f64);
        let tile = TILE_SIZE as f64;
        // Pixel centres of the tile are `i + 0.5` for `i` in `[tx * T, (tx + 1) * T)`.
        let (u0, u1) = (tx as f64 * tile - 0.5, (tx + 1) as f64 * tile + 0.5);
        let (v0, v1) = (ty as f64 * tile - 0.5, (ty + 1) as f64 * tile + 0.5);
        let (x0, x1) = ((u0 - cx) / fx, (u1 - cx) / fx);
        let (y0, y1) = ((cy - v1) / fy, (cy - v0) / fy);
        conic.meets(x0, x1, y0, y1)
    }
}

/// Screen tiles touched by the cone of rays whose transverse term is at most `cutoff`.
///
/// `K(d) <= tau` is the quadric `d^T L^T [(c - tau) I - m m^T] L d <= 0` (`c = m.m`), a cone
/// with its apex at the camera; on the image plane `z = -1` it is an exact conic. When the
/// camera lies inside the Gaussian's `tau` ellipsoid, or the conic is not a bounded ellipse,
/// the whole image is returned (rare, conservative). Computed in f64: the entries cancel.
fn footprint(splat: &ViewSplat, cutoff: f32, frame: &ViewFrame) -> Option<Footprint> {
    let full = Footprint {
        rect: TileRect {
            x0: 0,
            x1: frame.tiles_x,
            y0: 0,
            y1: frame.tiles_y,
        },
        conic: None,
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
    let rect = TileRect {
        x0: (px0 / tile) as usize,
        x1: (px1 / tile) as usize + 1,
        y0: (py0 / tile) as usize,
        y1: (py1 / tile) as usize + 1,
    };
    // A rectangle of one or two tiles a side gains nothing from the per-tile test.
    let conic = (rect.x1 - rect.x0 > 2 || rect.y1 - rect.y0 > 2).then_some(Conic {
        p00,
        p01,
        p11,
        b0,
        b1,
        q: quad[2][2],
    });
    Some(Footprint { rect, conic })
}

/// Every Gaussian as the camera sees it, and the depth-sorted per-tile lists.
#[derive(Debug, Clone)]
pub struct Binning {
    pub splats: Vec<ViewSplat>,
    /// Per Gaussian, the largest transverse term `K` at which it can still reach `alpha_min`
    /// on some ray (at most `kernel_cutoff`): past it a pixel skips the Gaussian before any
    /// exponential is evaluated.
    pub cutoffs: Vec<f32>,
    /// For each tile, the indices of the Gaussians touching it, nearest centre first.
    pub tiles: Vec<Vec<u32>>,
}

/// One Gaussian after projection: its view, its cutoff on `K`, and its depth and footprint
/// when the camera can see it.
type Projected = (ViewSplat, f32, Option<(f32, Footprint)>);

/// Projects every Gaussian into `frame` and bins the visible ones into tiles.
pub fn project_and_bin(
    gaussians: &GaussianSlices,
    frame: &ViewFrame,
    options: &RasterOptions,
) -> Binning {
    let projected: Vec<Projected> = (0..gaussians.len())
        .into_par_iter()
        .map(|i| {
            let g = gaussians.get(i);
            let (splat, ctx) = g.view(&frame.world_to_cam, frame.origin);
            let depth = -dot3(frame.world_to_cam[2], ctx.offset);
            if depth <= options.near_plane || splat.sigma <= 0.0 {
                return (splat, 0.0, None);
            }
            let max_scale = g.log_scale.iter().fold(f32::MIN, |a, &b| a.max(b)).exp();
            let cutoff = effective_cutoff(&splat, max_scale, options);
            if cutoff <= 0.0 {
                return (splat, 0.0, None);
            }
            let rect = footprint(&splat, cutoff, frame);
            (splat, cutoff, rect.map(|r| (depth, r)))
        })
        .collect();

    let mut order: Vec<(f32, u32)> = projected
        .iter()
        .enumerate()
        .filter_map(|(i, (_, _, vis))| vis.map(|(depth, _)| (depth, i as u32)))
        .collect();
    // Ties broken by index so every backend composites in the same order.
    order.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));

    let mut tiles = vec![Vec::new(); frame.tiles_x * frame.tiles_y];
    for &(_, i) in &order {
        let footprint = projected[i as usize]
            .2
            .expect("sorted Gaussians are visible")
            .1;
        let rect = footprint.rect;
        for ty in rect.y0..rect.y1 {
            for tx in rect.x0..rect.x1 {
                if footprint.touches(tx, ty, frame) {
                    tiles[ty * frame.tiles_x + tx].push(i);
                }
            }
        }
    }
    let (splats, cutoffs) = projected.into_iter().map(|(s, c, _)| (s, c)).unzip();
    Binning {
        splats,
        cutoffs,
        tiles,
    }
}

#[cfg(test)]
mod tests {
    use gausmoke_core::Camera;
    use gausmoke_core::glam::Vec3;

    use super::*;
    use crate::procedural::smoke_plume;

    /// Every (pixel, Gaussian) pair that passes the per-pixel test lies in a tile whose list
    /// holds the Gaussian: the rectangle, the per-tile ellipse test and the per-Gaussian
    /// cutoff only ever skip pairs that could not contribute. Also checks that the ellipse
    /// test does skip tiles, so that it is exercised.
    #[test]
    fn binning_keeps_every_contributing_pair() {
        let (lo, hi) = (Vec3::new(-0.3, -0.4, -0.3), Vec3::new(0.3, 0.4, 0.3));
        // Few, hence large, Gaussians: footprints many tiles wide, some of them elongated.
        let plume = smoke_plume(300, lo, hi, 3);
        let (width, height) = (96, 128);
        let camera = Camera::look_at(
            Vec3::new(0.4, 0.2, 1.1),
            Vec3::ZERO,
            Vec3::Y,
            width,
            height,
            0.9,
        )
        .unwrap();
        let frame = ViewFrame::new(&camera);
        let options = RasterOptions::default();
        let binning = project_and_bin(&plume.slices(), &frame, &options);

        let mut rect_entries = 0usize;
        let mut kept_entries = 0usize;
        for i in 0..plume.len() {
            let g = plume.get(i);
            let (splat, _) = g.view(&frame.world_to_cam, frame.origin);
            let kept: Vec<usize> = (0..binning.tiles.len())
                .filter(|&t| binning.tiles[t].contains(&(i as u32)))
                .collect();
            kept_entries += kept.len();
            if let Some(rect) = footprint(&splat, binning.cutoffs[i], &frame).map(|f| f.rect)
                && binning.cutoffs[i] > 0.0
            {
                rect_entries += (rect.x1 - rect.x0) * (rect.y1 - rect.y0);
            }
            for py in 0..height as usize {
                for px in 0..width as usize {
                    let dir = frame.pixel_direction(px, py);
                    let Some(sample) = splat.sample(dir, options.kernel_cutoff) else {
                        continue;
                    };
                    let depth = splat.sigma * sample.integral;
                    if -(-depth).exp_m1() < options.alpha_min {
                        continue;
                    }
                    let tile = (py / TILE_SIZE) * frame.tiles_x + px / TILE_SIZE;
                    assert!(
                        kept.contains(&tile),
                        "Gaussian {i} reaches pixel ({px}, {py}) but tile {tile} does not list it"
                    );
                    assert!(
                        sample.transverse <= binning.cutoffs[i],
                        "Gaussian {i}: pixel ({px}, {py}) has K = {} past its cutoff {}",
                        sample.transverse,
                        binning.cutoffs[i]
                    );
                }
            }
        }
        assert!(
            kept_entries < rect_entries,
            "the ellipse test skipped no tile ({kept_entries} of {rect_entries} kept)"
        );
    }
}
