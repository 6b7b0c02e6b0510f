//! Recycling Gaussians between frames: smoke that leaves the box and primitives that became
//! invisible are moved to where the training views show smoke the reconstruction lacks.
//!
//! The paper keeps one fixed set of Gaussians and only advects it. On a real plume that set
//! runs out: smoke rises through the box's top face (where advection clamps it) while fresh
//! smoke enters at the source, where no Gaussian is. This is our design choice for the gap,
//! off by default (`population.recycle.fraction = 0`, the paper's method):
//!
//! - **Which to recycle.** Gaussians clamped onto a face of the box first, then those whose
//!   largest possible opacity `1 - exp(-sigma sqrt(2 pi) max_std)` is below 1/255 (they add
//!   nothing to any image), least visible first; at most `population.recycle.fraction` of all per frame.
//! - **When.** After frame t's joint iterations, before its refinement: the Gaussians have
//!   been carried from frame t-1 by the new velocity, so what frame t's views show and they
//!   do not is smoke that entered (or was never fitted), and the refinement fits the recycled
//!   ones. Measured right after a frame's own fit instead, the deficit is what that fit left
//!   over (at most 0.002-0.007 on ScalarReal), and the rule never fired.
//! - **Where to put them.** Every cell centre of the velocity grid is projected into every
//!   training view. Its score is the smallest, over the views, of the pixel's *smoke
//!   deficit*: how much further the observation is from the background than the render is
//!   (mean over channels, clamped at 0). A point missing from the reconstruction in every
//!   view is a visual-hull argument for smoke there. Cells above `population.recycle.threshold` are
//!   drawn without replacement with probability proportional to the score and jittered
//!   within the cell. An optional limit: cells inside a box (`scene.inflow`, such as the
//!   inflow where a source feeds the plume, where the views pin the depth down).
//! - **What they start as.** Isotropic, the initialisation's size, the mean colour of the
//!   visible Gaussians, and a density whose opacity through the centre supplies half of the
//!   cell's deficit (half, because neighbouring recycled Gaussians overlap along rays).
//!
//! The count stays fixed, so the optimisers' per-row state keeps its shape; the recycled rows
//! keep their Adam moments, which fade within ~10 steps (first moment) but may make the first
//! steps larger or smaller than `lr` (second moment). Everything here is host-side and
//! deterministic in its seed, so a resumed run matches an uninterrupted one.

use gausmoke_core::Camera;
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_render::HostGaussians;
use gausmoke_render::math::softplus;

/// Opacity below which a Gaussian cannot change an 8-bit pixel.
pub(crate) const INVISIBLE_OPACITY: f32 = 1.0 / 255.0;
const SQRT_TAU: f32 = 2.506_628_3;

/// One training view of the frame the Gaussians are fitted to.
#[derive(Debug, Clone, Copy)]
pub struct DeficitView<'a> {
    pub camera: &'a Camera,
    /// Observed and rendered images, `[H, W, 3]` row-major, values in `[0, 1]`.
    pub observed: &'a [f32],
    pub rendered: &'a [f32],
}

/// The box and lattice the recycled Gaussians are placed in (the velocity grid's cells).
#[derive(Debug, Clone, Copy)]
pub struct SpawnLattice {
    pub lo: Vec3,
    pub hi: Vec3,
    pub resolution: [usize; 3],
}

impl SpawnLattice {
    /// The unit box on an 8^3 lattice, for tests.
    #[cfg(test)]
    pub(crate) fn unit_box() -> Self {
        Self {
            lo: Vec3::ZERO,
            hi: Vec3::ONE,
            resolution: [8, 8, 8],
        }
    }

    pub(crate) fn cell_size(&self) -> Vec3 {
        let [nx, ny, nz] = self.resolution;
        (self.hi - self.lo) / Vec3::new(nx as f32, ny as f32, nz as f32)
    }

    pub(crate) fn cell_centre(&self, [i, j, k]: [usize; 3]) -> Vec3 {
        self.lo + self.cell_size() * Vec3::new(i as f32 + 0.5, j as f32 + 0.5, k as f32 + 0.5)
    }

    /// The cell of flat index `cell` (`[nx, ny, nz]`, z fastest).
    pub(crate) fn cell_of(&self, cell: usize) -> [usize; 3] {
        let [_, ny, nz] = self.resolution;
        [cell / (ny * nz), (cell / nz) % ny, cell % nz]
    }

    /// A point drawn uniformly in the cell of flat index `cell`.
    pub(crate) fn point_in_cell(&self, cell: usize, rng: &mut SplitMix64) -> Vec3 {
        let jitter = Vec3::new(
            rng.range(-0.5, 0.5),
            rng.range(-0.5, 0.5),
            rng.range(-0.5, 0.5),
        );
        self.cell_centre(self.cell_of(cell)) + jitter * self.cell_size()
    }

    /// The world-space box `[lo, hi]` of `[x0, y0, z0, x1, y1, z1]` given as fractions of
    /// this lattice's box (`scene.inflow`).
    pub fn region_from_fractions(&self, r: [f32; 6]) -> [Vec3; 2] {
        let extent = self.hi - self.lo;
        [
            self.lo + extent * Vec3::new(r[0], r[1], r[2]),
            self.lo + extent * Vec3::new(r[3], r[4], r[5]),
        ]
    }
}

/// Whether `p` lies in the world-space box `[lo, hi]` (bounds included), as a region such as
/// `scene.inflow` holds cell centres.
pub fn in_region([lo, hi]: [Vec3; 2], p: Vec3) -> bool {
    p.cmpge(lo).all() && p.cmple(hi).all()
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RespawnOptions {
    /// Most Gaussians recycled per frame, as a fraction of all.
    pub fraction: f32,
    /// Smallest smoke deficit (in `[0, 1]` image units) a cell must show in every view.
    pub threshold: f32,
    /// Standard deviation of a recycled Gaussian (world units).
    pub std: f32,
    pub background: [f32; 3],
    pub seed: u64,
    /// World-space box `[lo, hi]` the cell centres must lie in (`scene.inflow`: where smoke
    /// enters); `None` admits every cell.
    pub region: Option<[Vec3; 2]>,
}

/// What [`respawn`] did, for the frame report.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RespawnReport {
    /// Recycled rows, in the order they were chosen.
    pub indices: Vec<usize>,
    /// Of those, the ones taken from a face of the box.
    pub from_box_faces: usize,
    /// Lattice cells whose deficit exceeded the threshold in every view.
    pub deficit_cells: usize,
    /// The largest cell score (smallest deficit over the views) of any cell.
    pub max_deficit: f32,
}

/// The log of a Gaussian's longest standard deviation.
pub(crate) fn largest_log_std(gaussians: &HostGaussians, index: usize) -> f32 {
    gaussians.log_scales[3 * index..3 * index + 3]
        .iter()
        .cloned()
        .fold(f32::NEG_INFINITY, f32::max)
}

/// Largest opacity a Gaussian can give a ray (through its centre, along its longest axis).
pub(crate) fn peak_opacity(gaussians: &HostGaussians, index: usize) -> f32 {
    let sigma = softplus(gaussians.raw_densities[index]);
    1.0 - (-sigma * SQRT_TAU * largest_log_std(gaussians, index).exp()).exp()
}

/// The raw density whose softplus is `sigma > 0`.
pub(crate) fn inverse_softplus(sigma: f32) -> f32 {
    if sigma > 20.0 {
        sigma
    } else {
        sigma.exp_m1().max(f32::MIN_POSITIVE).ln()
    }
}

pub(crate) fn on_box_face(position: Vec3, lattice: &SpawnLattice) -> bool {
    let tolerance = 1e-5 * (lattice.hi - lattice.lo).max_element();
    (position - lattice.lo).min_element() <= tolerance
        || (lattice.hi - position).min_element() <= tolerance
}

/// The position in `cells` (`(cell, weight)` pairs, weights >= 0, not all 0) drawn with
/// probability proportional to its weight (a linear scan: callers draw a few hundred).
pub(crate) fn draw_weighted(cells: &[(usize, f32)], rng: &mut SplitMix64) -> usize {
    let total: f32 = cells.iter().map(|(_, w)| w).sum();
    let mut pick = rng.uniform() * total;
    for (position, (_, weight)) in cells.iter().enumerate() {
        if pick < *weight {
            return position;
        }
        pick -= weight;
    }
    cells.len() - 1
}

/// Makes row `index` of `gaussians` an isotropic Gaussian at `position` of log standard
/// deviation `log_std`, peak density `sigma` and `colour`.
pub(crate) fn make_isotropic(
    gaussians: &mut HostGaussians,
    index: usize,
    position: Vec3,
    log_std: f32,
    sigma: f32,
    colour: [f32; 3],
) {
    gaussians.means[3 * index..3 * index + 3].copy_from_slice(&position.to_array());
    gaussians.rotations[4 * index..4 * index + 4].copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
    gaussians.log_scales[3 * index..3 * index + 3].fill(log_std);
    gaussians.raw_densities[index] = inverse_softplus(sigma);
    gaussians.colors[3 * index..3 * index + 3].copy_from_slice(&colour);
}

/// Rows to recycle, best candidates first: on a box face, then invisible by ascending
/// opacity; never the `taken` rows (renewed otherwise this frame). Also how many of them are
/// on a face.
pub(crate) fn recycling_candidates(
    gaussians: &HostGaussians,
    lattice: &SpawnLattice,
    taken: &[usize],
) -> (Vec<usize>, usize) {
    let mut free = vec![true; gaussians.len()];
    for &row in taken {
        free[row] = false;
    }
    let mut on_faces = Vec::new();
    let mut invisible = Vec::new();
    for index in (0..gaussians.len()).filter(|&index| free[index]) {
        let m = &gaussians.means[3 * index..3 * index + 3];
        let opacity = peak_opacity(gaussians, index);
        if on_box_face(Vec3::new(m[0], m[1], m[2]), lattice) {
            on_faces.push(index);
        } else if opacity < INVISIBLE_OPACITY {
            invisible.push((opacity, index));
        }
    }
    invisible.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let faces = on_faces.len();
    on_faces.extend(invisible.into_iter().map(|(_, index)| index));
    (on_faces, faces)
}

/// Per-pixel smoke deficit of one view: how much further from the background the
/// observation is than the render (mean over channels, at least 0).
fn deficit_image(view: &DeficitView, background: [f32; 3]) -> Vec<f32> {
    view.observed
        .chunks_exact(3)
        .zip(view.rendered.chunks_exact(3))
        .map(|(observed, rendered)| {
            let distance = |pixel: &[f32]| {
                pixel
                    .iter()
                    .zip(background)
                    .map(|(v, b)| (v - b).abs())
                    .sum::<f32>()
                    / 3.0
            };
            (distance(observed) - distance(rendered)).max(0.0)
        })
        .collect()
}

/// Score of every lattice cell: its smallest deficit over the views (0 where a view misses it).
fn cell_scores(views: &[DeficitView], lattice: &SpawnLattice, background: [f32; 3]) -> Vec<f32> {
    let [nx, ny, nz] = lattice.resolution;
    let mut scores = vec![f32::INFINITY; nx * ny * nz];
    for view in views {
        let (width, height) = (view.camera.width() as usize, view.camera.height() as usize);
        assert_eq!(
            view.observed.len(),
            width * height * 3,
            "observed image does not match its camera"
        );
        assert_eq!(
            view.rendered.len(),
            width * height * 3,
            "rendered image does not match its camera"
        );
        let deficit = deficit_image(view, background);
        for i in 0..nx {
            for j in 0..ny {
                for k in 0..nz {
                    let cell = (i * ny + j) * nz + k;
                    let value = view
                        .camera
                        .project(lattice.cell_centre([i, j, k]))
                        .filter(|p| {
                            p.x >= 0.0 && p.y >= 0.0 && p.x < width as f32 && p.y < height as f32
                        })
                        .map_or(0.0, |p| deficit[p.y as usize * width + p.x as usize]);
                    scores[cell] = scores[cell].min(value);
                }
            }
        }
    }
    if views.is_empty() {
        scores.fill(0.0);
    }
    scores
}

/// Recycles up to `options.fraction` of `gaussians` in place (see the module docs), never
/// the `taken` rows (renewed otherwise this frame).
pub fn respawn(
    gaussians: &mut HostGaussians,
    views: &[DeficitView],
    lattice: &SpawnLattice,
    options: &RespawnOptions,
    taken: &[usize],
) -> RespawnReport {
    let budget = (options.fraction.max(0.0) * gaussians.len() as f32).floor() as usize;
    if budget == 0 || views.is_empty() {
        return RespawnReport::default();
    }
    let mut scores = cell_scores(views, lattice, options.background);
    if let Some(region) = options.region {
        for (cell, score) in scores.iter_mut().enumerate() {
            if !in_region(region, lattice.cell_centre(lattice.cell_of(cell))) {
                *score = 0.0;
            }
        }
    }
    let mut cells: Vec<(usize, f32)> = scores
        .iter()
        .enumerate()
        .filter(|(_, s)| **s > options.threshold)
        .map(|(cell, s)| (cell, *s))
        .collect();
    let deficit_cells = cells.len();
    let max_deficit = scores.iter().cloned().fold(0.0, f32::max);
    let (candidates, faces) = recycling_candidates(gaussians, lattice, taken);
    let count = budget.min(cells.len()).min(candidates.len());
    if count == 0 {
        return RespawnReport {
            deficit_cells,
            max_deficit,
            ..Default::default()
        };
    }

    // The colour the reconstruction already gives smoke: the visible Gaussians' mean.
    let visible: Vec<usize> = (0..gaussians.len())
        .filter(|&i| peak_opacity(gaussians, i) >= INVISIBLE_OPACITY)
        .collect();
    let mut colour = [0.5f32; 3];
    if !visible.is_empty() {
        for (channel, value) in colour.iter_mut().enumerate() {
            *value = visible
                .iter()
                .map(|&i| gaussians.colors[3 * i + channel])
                .sum::<f32>()
                / visible.len() as f32;
        }
    }
    let contrast = colour
        .iter()
        .zip(options.background)
        .map(|(c, b)| (c - b).abs())
        .sum::<f32>()
        / 3.0;

    let mut rng = SplitMix64::new(options.seed);
    let log_std = options.std.ln();
    let mut report = RespawnReport {
        indices: Vec::with_capacity(count),
        from_box_faces: faces.min(count),
        deficit_cells,
        max_deficit,
    };
    for &index in candidates.iter().take(count) {
        // Without replacement.
        let (cell, score) = cells.swap_remove(draw_weighted(&cells, &mut rng));
        let position = lattice.point_in_cell(cell, &mut rng);
        let opacity = (0.5 * score / contrast.max(0.05)).clamp(INVISIBLE_OPACITY, 0.5);
        let sigma = -(1.0 - opacity).ln() / (SQRT_TAU * options.std);
        make_isotropic(gaussians, index, position, log_std, sigma, colour);
        report.indices.push(index);
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;
    use gausmoke_core::Camera;

    fn lattice() -> SpawnLattice {
        SpawnLattice::unit_box()
    }

    /// Two cameras looking at the unit box's centre along -Z and along -X.
    fn cameras() -> [Camera; 2] {
        let target = Vec3::splat(0.5);
        [Vec3::new(0.5, 0.5, 3.0), Vec3::new(3.0, 0.5, 0.5)]
            .map(|eye| Camera::look_at(eye, target, Vec3::Y, 64, 64, 0.9).unwrap())
    }

    /// An image that is black except a bright disc around the projection of `point`.
    fn spot_image(camera: &Camera, point: Vec3, radius: f32) -> Vec<f32> {
        let centre = camera.project(point).unwrap();
        let mut image = vec![0.0; 64 * 64 * 3];
        for y in 0..64 {
            for x in 0..64 {
                let d = (centre - gausmoke_core::glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5))
                    .length();
                if d < radius {
                    image[(y * 64 + x) * 3..(y * 64 + x) * 3 + 3].fill(0.8);
                }
            }
        }
        image
    }

    /// `n` Gaussians: the first on the top face, the second visible, the rest invisible.
    fn gaussians(n: usize) -> HostGaussians {
        let mut g = HostGaussians {
            means: vec![0.3; 3 * n],
            rotations: [1.0, 0.0, 0.0, 0.0].repeat(n),
            log_scales: vec![(0.05f32).ln(); 3 * n],
            raw_densities: vec![-12.0; n],
            colors: vec![0.6; 3 * n],
        };
        g.means[1] = 1.0;
        g.raw_densities[1] = 3.0;
        // Give the invisible ones distinct, increasing opacities.
        for i in 2..n {
            g.raw_densities[i] = -14.0 + 0.01 * i as f32;
        }
        g
    }

    fn options(fraction: f32) -> RespawnOptions {
        RespawnOptions {
            fraction,
            threshold: 0.05,
            std: 0.03,
            background: [0.0; 3],
            seed: 7,
            region: None,
        }
    }

    /// Each camera's observed picture against the same rendered one.
    fn deficit_views<'a>(
        cameras: &'a [Camera],
        observed: &'a [Vec<f32>],
        rendered: &'a [f32],
    ) -> Vec<DeficitView<'a>> {
        cameras
            .iter()
            .zip(observed)
            .map(|(camera, observed)| DeficitView {
                camera,
                observed,
                rendered,
            })
            .collect()
    }

    #[test]
    fn gaussians_go_where_every_view_misses_smoke_face_ones_first() {
        let cameras = cameras();
        let smoke = Vec3::new(0.3, 0.7, 0.6);
        let observed: Vec<Vec<f32>> = cameras.iter().map(|c| spot_image(c, smoke, 4.0)).collect();
        let rendered = vec![0.0; 64 * 64 * 3];
        let views = deficit_views(&cameras, &observed, &rendered);
        let mut g = gaussians(100);
        let before = g.clone();
        let report = respawn(&mut g, &views, &lattice(), &options(0.05), &[]);

        assert_eq!(report.indices.len(), 5);
        assert_eq!(report.from_box_faces, 1);
        assert_eq!(
            report.indices[0], 0,
            "the Gaussian on the top face goes first"
        );
        assert!(
            !report.indices.contains(&1),
            "a visible Gaussian is never recycled"
        );
        // Then the least visible: rows 2, 3, 4, 5 have the lowest densities.
        assert_eq!(&report.indices[1..], &[2, 3, 4, 5]);
        assert!(report.deficit_cells > 0);
        for &index in &report.indices {
            let p = Vec3::from_slice(&g.means[3 * index..3 * index + 3]);
            // Only cells near the smoke's point project into the spot in both views.
            assert!(
                (p - smoke).length() < 0.25,
                "recycled Gaussian {index} at {p:?}, smoke at {smoke:?}"
            );
            let opacity = peak_opacity(&g, index);
            assert!(opacity > INVISIBLE_OPACITY && opacity <= 0.5 + 1e-4);
            // The mean colour of the visible Gaussians (there is one: 0.6 grey).
            assert_eq!(&g.colors[3 * index..3 * index + 3], &[0.6; 3]);
        }
        // Rows not recycled are untouched.
        for i in (6..100).chain([1]) {
            assert_eq!(g.means[3 * i..3 * i + 3], before.means[3 * i..3 * i + 3]);
            assert_eq!(g.raw_densities[i], before.raw_densities[i]);
        }
        // Rows renewed otherwise this frame are passed over, the face one included.
        let mut g = before.clone();
        let report = respawn(&mut g, &views, &lattice(), &options(0.05), &[0, 3]);
        assert_eq!(report.indices, vec![2, 4, 5, 6, 7]);
        assert_eq!(report.from_box_faces, 0);
        assert_eq!(g.means[..3], before.means[..3]);
    }

    #[test]
    fn a_region_admits_only_the_cells_inside_it() {
        // Two missing spots, one low (where a source would be) and one high.
        let cameras = cameras();
        let low = Vec3::new(0.5, 0.1, 0.5);
        let high = Vec3::new(0.3, 0.7, 0.6);
        let observed: Vec<Vec<f32>> = cameras
            .iter()
            .map(|c| {
                let a = spot_image(c, low, 4.0);
                let b = spot_image(c, high, 4.0);
                a.iter().zip(&b).map(|(a, b)| a.max(*b)).collect()
            })
            .collect();
        let rendered = vec![0.0; 64 * 64 * 3];
        let views = deficit_views(&cameras, &observed, &rendered);
        let bottom = RespawnOptions {
            region: Some([Vec3::new(0.25, 0.0, 0.25), Vec3::new(0.75, 0.25, 0.75)]),
            ..options(0.05)
        };
        let mut g = gaussians(100);
        let report = respawn(&mut g, &views, &lattice(), &bottom, &[]);
        assert_eq!(report.indices.len(), 5);
        for &index in &report.indices {
            let p = Vec3::from_slice(&g.means[3 * index..3 * index + 3]);
            assert!(
                (p - low).length() < 0.25,
                "recycled Gaussian {index} at {p:?}, the low spot at {low:?}"
            );
        }
        // Without the region both spots receive some.
        let mut g = gaussians(100);
        let report = respawn(&mut g, &views, &lattice(), &options(0.05), &[]);
        let highs = report
            .indices
            .iter()
            .filter(|&&i| (Vec3::from_slice(&g.means[3 * i..3 * i + 3]) - high).length() < 0.25)
            .count();
        assert!(
            highs > 0 && highs < report.indices.len(),
            "{highs} of {report:?}"
        );
        // A region that holds neither spot receives nothing.
        let corner = RespawnOptions {
            region: Some([Vec3::new(0.8, 0.8, 0.0), Vec3::ONE]),
            ..options(0.05)
        };
        let mut g = gaussians(100);
        let report = respawn(&mut g, &views, &lattice(), &corner, &[]);
        assert!(report.indices.is_empty(), "{report:?}");
    }

    #[test]
    fn a_region_in_fractions_of_the_box_is_placed_in_the_world() {
        let lattice = SpawnLattice {
            lo: Vec3::new(-1.0, 0.0, 2.0),
            hi: Vec3::new(1.0, 4.0, 3.0),
            resolution: [8, 8, 8],
        };
        assert_eq!(
            lattice.region_from_fractions([0.0, 0.0, 0.0, 1.0, 1.0, 1.0]),
            [lattice.lo, lattice.hi]
        );
        assert_eq!(
            lattice.region_from_fractions([0.25, 0.0, 0.5, 0.75, 0.125, 1.0]),
            [Vec3::new(-0.5, 0.0, 2.5), Vec3::new(0.5, 0.5, 3.0)]
        );
    }

    #[test]
    fn nothing_moves_without_a_deficit_or_a_budget() {
        let cameras = cameras();
        let smoke = Vec3::new(0.3, 0.7, 0.6);
        let image = spot_image(&cameras[0], smoke, 4.0);
        // The render already shows the smoke: no deficit anywhere.
        let views = [DeficitView {
            camera: &cameras[0],
            observed: &image,
            rendered: &image,
        }];
        let mut g = gaussians(100);
        let before = g.clone();
        assert!(
            respawn(&mut g, &views, &lattice(), &options(0.05), &[])
                .indices
                .is_empty()
        );
        // A deficit, but a budget of zero (the paper's method).
        let dark = vec![0.0; 64 * 64 * 3];
        let views = [DeficitView {
            camera: &cameras[0],
            observed: &image,
            rendered: &dark,
        }];
        assert!(
            respawn(&mut g, &views, &lattice(), &options(0.0), &[])
                .indices
                .is_empty()
        );
        assert_eq!(g, before);
    }

    #[test]
    fn a_deficit_seen_by_one_view_only_is_not_smoke() {
        // The second view shows nothing there: the visual hull excludes the point.
        let cameras = cameras();
        let smoke = Vec3::new(0.3, 0.7, 0.6);
        let observed = spot_image(&cameras[0], smoke, 4.0);
        let dark = vec![0.0; 64 * 64 * 3];
        let views = [
            DeficitView {
                camera: &cameras[0],
                observed: &observed,
                rendered: &dark,
            },
            DeficitView {
                camera: &cameras[1],
                observed: &dark,
                rendered: &dark,
            },
        ];
        let mut g = gaussians(100);
        let report = respawn(&mut g, &views, &lattice(), &options(0.05), &[]);
        assert_eq!(report.deficit_cells, 0);
        assert!(report.indices.is_empty());
    }

    #[test]
    fn softplus_round_trips() {
        for sigma in [1e-4f32, 0.01, 0.5, 3.0, 30.0] {
            let back = softplus(inverse_softplus(sigma));
            assert!(
                (back - sigma).abs() <= 1e-4 * sigma.max(1.0),
                "{sigma} {back}"
            );
        }
    }
}
