//! Emission at a source (`emission_fraction`, ours): inside the inflow box, new Gaussians
//! replace the density that a frame's advection carried out of it.
//!
//! A plume's column is steady while the fluid rises through it, so Gaussians that ride the
//! flow leave the column's foot empty unless new ones enter at the rate the flow carries
//! smoke out. Recycling into the inflow (`respawn`) places Gaussians where the training
//! views miss smoke, at a fixed cap and half the missing opacity, whatever the flow did; on
//! the long plume the true velocity as the carrier then lost 2.5 dB to the fitted, slower
//! one (docs/RESULTS.md). A steady source holds the density of its inflow, so what advection
//! took from a cell of the inflow box between frames t-1 and t is what it emits there:
//!
//! - **How much.** The box's loss: over the cells of the velocity grid inside it
//!   (`respawn_region`), the density the Gaussians of frame t-1 splat minus what the
//!   carried ones splat, summed, times the cell volume; nothing when the box gained. Gains
//!   of some cells offset losses of others, since smoke moved within the box has not left
//!   it (a sum of the losses alone emitted about twice the loss under a slow carrier). A
//!   slow carrier empties the box slowly and so emits little; one at rest emits nothing.
//! - **How many.** That mass over the median mass of the visible Gaussians whose centres lie
//!   in the box (of all visible ones when none does), rounded up, at most `budget`: emitted
//!   Gaussians are as heavy as their neighbours, and the cap only makes them heavier.
//! - **Where.** Cells drawn with replacement in proportion to their loss, jittered
//!   uniformly within the cell, and kept one standard deviation inside the smoke box: a
//!   source on the floor must not put half of a new Gaussian under it, where no view sees
//!   smoke.
//! - **What.** Isotropic at the given size, the density-weighted mean colour of the
//!   Gaussians in the box (of the visible ones when none is), and an equal share of the mass
//!   as the grid sees it: each peak density is set so that the Gaussian's splat on the
//!   lattice (inside the splat's cutoff and the box) sums to its share, so the splatted
//!   density regains what it lost.
//! - **Which rows.** The `slots` the caller passes, in order (rows recycling would take: on
//!   a box face, or invisible), so the count stays fixed.
//!
//! Host-side and deterministic in its seed, like recycling, so a resumed run matches an
//! uninterrupted one.

use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_render::HostGaussians;
use gausmoke_render::math::softplus;

use crate::respawn::{
    INVISIBLE_OPACITY, SpawnLattice, draw_weighted, in_region, make_isotropic, peak_opacity,
};

/// `(2 pi)^(3/2)`: the integral of an unnormalised 3D Gaussian of unit standard deviations.
const GAUSSIAN_VOLUME: f32 = 15.749_61;
/// The squared Mahalanobis radius the density splat evaluates a Gaussian within
/// (`gausmoke_model::SplatOptions`'s default).
const SPLAT_CUTOFF: f32 = 9.0;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EmissionOptions {
    /// World-space box `[lo, hi]` of the inflow; only cells whose centre lies in it emit.
    pub region: [Vec3; 2],
    /// Most Gaussians emitted in one frame.
    pub budget: usize,
    /// Standard deviation of an emitted Gaussian (world units).
    pub std: f32,
    pub seed: u64,
}

/// What [`emit`] did, for the frame report.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EmissionReport {
    /// Rows that became emitted Gaussians, in the order they were taken.
    pub indices: Vec<usize>,
    /// The density mass the carrier took out of the inflow box's cells (density times world
    /// volume), which the emitted Gaussians share.
    pub mass: f32,
}

/// Mass of Gaussian `index`: its peak density times `(2 pi)^(3/2) s_x s_y s_z`.
pub(crate) fn mass(gaussians: &HostGaussians, index: usize) -> f32 {
    let log_volume: f32 = gaussians.log_scales[3 * index..3 * index + 3].iter().sum();
    softplus(gaussians.raw_densities[index]) * GAUSSIAN_VOLUME * log_volume.exp()
}

/// What an isotropic Gaussian of unit peak density and standard deviation `std` at
/// `centre` adds to the lattice's density, summed over the cells and times the cell volume.
fn lattice_mass(centre: Vec3, std: f32, lattice: &SpawnLattice) -> f32 {
    let cell = lattice.cell_size();
    let reach = SPLAT_CUTOFF.sqrt() * std;
    // The cells whose centre lies within `reach` of `centre` along `axis`.
    let range = |axis: usize| {
        let index = |x: f32| ((x - lattice.lo[axis]) / cell[axis] - 0.5) as i64;
        let first = index(centre[axis] - reach).max(0) as usize;
        let end = (index(centre[axis] + reach) + 2).clamp(0, lattice.resolution[axis] as i64);
        first..end as usize
    };
    let mut sum = 0.0;
    for i in range(0) {
        for j in range(1) {
            for k in range(2) {
                let d = (lattice.cell_centre([i, j, k]) - centre) / std;
                let m = d.length_squared();
                if m <= SPLAT_CUTOFF {
                    sum += (-0.5 * m).exp();
                }
            }
        }
    }
    sum * cell.x * cell.y * cell.z
}

fn median(mut values: Vec<f32>) -> Option<f32> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f32::total_cmp);
    Some(values[values.len() / 2])
}

/// Emits into `slots` of `gaussians` the density the carrier took out of the inflow box:
/// `before` and `after` are the Gaussians' density on `lattice` (`[nx, ny, nz]`, z fastest)
/// at frame t-1 and once carried to frame t (see the module docs).
pub fn emit(
    gaussians: &mut HostGaussians,
    before: &[f32],
    after: &[f32],
    lattice: &SpawnLattice,
    slots: &[usize],
    options: &EmissionOptions,
) -> EmissionReport {
    let [nx, ny, nz] = lattice.resolution;
    assert_eq!(
        before.len(),
        nx * ny * nz,
        "density before does not match the lattice"
    );
    assert_eq!(
        after.len(),
        nx * ny * nz,
        "density after does not match the lattice"
    );
    let cell_volume = lattice.cell_size().x * lattice.cell_size().y * lattice.cell_size().z;
    // The cells that lost density, with their loss, and the box's net loss.
    let mut cells: Vec<(usize, f32)> = Vec::new();
    let mut net_loss = 0.0;
    for i in 0..nx {
        for j in 0..ny {
            for k in 0..nz {
                let cell = (i * ny + j) * nz + k;
                if !in_region(options.region, lattice.cell_centre([i, j, k])) {
                    continue;
                }
                let loss = before[cell] - after[cell];
                net_loss += loss;
                if loss > 0.0 {
                    cells.push((cell, loss));
                }
            }
        }
    }
    let total_mass = net_loss * cell_volume;
    let report = EmissionReport {
        indices: Vec::new(),
        mass: total_mass,
    };
    if !total_mass.is_finite() || total_mass <= 0.0 || options.budget == 0 || slots.is_empty() {
        return report;
    }

    let visible: Vec<usize> = (0..gaussians.len())
        .filter(|&i| peak_opacity(gaussians, i) >= INVISIBLE_OPACITY)
        .collect();
    let centre = |i: usize| Vec3::from_slice(&gaussians.means[3 * i..3 * i + 3]);
    let in_box: Vec<usize> = visible
        .iter()
        .copied()
        .filter(|&i| in_region(options.region, centre(i)))
        .collect();
    let neighbours = if in_box.is_empty() { &visible } else { &in_box };
    let typical = median(neighbours.iter().map(|&i| mass(gaussians, i)).collect());
    let wanted = match typical {
        Some(m) if m > 0.0 => (total_mass / m).ceil() as usize,
        _ => options.budget,
    };
    let count = wanted.clamp(1, options.budget).min(slots.len());

    let mut colour = [0.5f32; 3];
    let weights: Vec<(usize, f32)> = neighbours
        .iter()
        .map(|&i| (i, softplus(gaussians.raw_densities[i])))
        .collect();
    let weight: f32 = weights.iter().map(|(_, w)| w).sum();
    if weight > 0.0 {
        for (channel, value) in colour.iter_mut().enumerate() {
            *value = weights
                .iter()
                .map(|&(i, w)| w * gaussians.colors[3 * i + channel])
                .sum::<f32>()
                / weight;
        }
    }

    let share = total_mass / count as f32;
    let log_std = options.std.ln();
    // One standard deviation inside the box where it is wide enough.
    let margin = Vec3::splat(options.std).min(0.5 * (lattice.hi - lattice.lo));
    let mut rng = SplitMix64::new(options.seed);
    let mut report = report;
    for &index in slots.iter().take(count) {
        // With replacement.
        let (cell, _) = cells[draw_weighted(&cells, &mut rng)];
        let position = lattice
            .point_in_cell(cell, &mut rng)
            .clamp(lattice.lo + margin, lattice.hi - margin);
        let seen = lattice_mass(position, options.std, lattice);
        let sigma = share / seen.max(f32::MIN_POSITIVE);
        make_isotropic(gaussians, index, position, log_std, sigma, colour);
        report.indices.push(index);
    }
    report
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The inflow: the bottom-centre quarter of the unit box (lattice 8^3).
    fn inflow() -> [Vec3; 2] {
        [Vec3::new(0.25, 0.0, 0.25), Vec3::new(0.75, 0.25, 0.75)]
    }

    fn cell(i: usize, j: usize, k: usize) -> usize {
        (i * 8 + j) * 8 + k
    }

    /// `n` rows: the first `visible` in the inflow (grey 0.4 and 0.8 alternating, density
    /// `softplus(2)` and `softplus(4)` alternating), the rest invisible at the top.
    fn gaussians(n: usize, visible: usize) -> HostGaussians {
        let mut g = HostGaussians {
            means: [0.5, 0.9, 0.5].repeat(n),
            rotations: [1.0, 0.0, 0.0, 0.0].repeat(n),
            log_scales: vec![(0.05f32).ln(); 3 * n],
            raw_densities: vec![-14.0; n],
            colors: vec![0.5; 3 * n],
        };
        for i in 0..visible {
            g.means[3 * i..3 * i + 3].copy_from_slice(&[0.5, 0.1, 0.5]);
            let heavy = i % 2 == 1;
            g.raw_densities[i] = if heavy { 4.0 } else { 2.0 };
            g.colors[3 * i..3 * i + 3].fill(if heavy { 0.8 } else { 0.4 });
        }
        g
    }

    /// What Gaussian `index` adds to the lattice's density, summed times the cell volume,
    /// by a direct sum over every cell (the splat's cutoff included).
    fn seen_mass(g: &HostGaussians, index: usize) -> f32 {
        let p = Vec3::from_slice(&g.means[3 * index..3 * index + 3]);
        let std = g.log_scales[3 * index].exp();
        let lattice = SpawnLattice::unit_box();
        let mut sum = 0.0;
        for i in 0..8 {
            for j in 0..8 {
                for k in 0..8 {
                    let m = ((lattice.cell_centre([i, j, k]) - p) / std).length_squared();
                    if m <= 9.0 {
                        sum += (-0.5 * m).exp();
                    }
                }
            }
        }
        softplus(g.raw_densities[index]) * sum * 0.125f32.powi(3)
    }

    /// [`emit`] on the unit box's lattice into `slots`, at most `budget`.
    fn emitted(
        g: &mut HostGaussians,
        before: &[f32],
        after: &[f32],
        slots: &[usize],
        budget: usize,
    ) -> EmissionReport {
        emit(
            g,
            before,
            after,
            &SpawnLattice::unit_box(),
            slots,
            &options(budget),
        )
    }

    fn options(budget: usize) -> EmissionOptions {
        EmissionOptions {
            region: inflow(),
            budget,
            std: 0.1,
            seed: 11,
        }
    }

    /// Frame t-1 held density 2 in four inflow cells and 1 in a cell above the box; the
    /// carrier left 0.5 in two of them and took the rest.
    fn densities() -> (Vec<f32>, Vec<f32>) {
        let mut before = vec![0.0; 512];
        let mut after = vec![0.0; 512];
        for (i, k) in [(3, 3), (3, 4), (4, 3), (4, 4)] {
            before[cell(i, 0, k)] = 2.0;
        }
        after[cell(3, 0, 3)] = 0.5;
        after[cell(4, 0, 4)] = 0.5;
        // Outside the inflow box: a loss there is not the source's.
        before[cell(4, 6, 4)] = 1.0;
        (before, after)
    }

    #[test]
    fn the_mass_carried_out_of_the_inflow_is_emitted_inside_it() {
        let (before, after) = densities();
        let mut g = gaussians(100, 6);
        let slots: Vec<usize> = (50..100).collect();
        let report = emitted(&mut g, &before, &after, &slots, 40);
        let cell_volume = 0.125f32.powi(3);
        let expected_mass = (2.0 * 1.5 + 2.0 * 2.0) * cell_volume;
        assert!((report.mass - expected_mass).abs() < 1e-6 * expected_mass.max(1.0));
        // As many as the mass over the median mass of the inflow's visible Gaussians.
        let median = mass(&g, 1).max(mass(&g, 0));
        let count = (expected_mass / median).ceil() as usize;
        assert!(
            count > 1 && count < 40,
            "{count}: the test cannot tell the rule"
        );
        assert_eq!(report.indices, (50..50 + count).collect::<Vec<_>>());
        let emitted: f32 = report.indices.iter().map(|&i| seen_mass(&g, i)).sum();
        assert!(
            (emitted - expected_mass).abs() < 1e-3 * expected_mass,
            "emitted {emitted}, carried out {expected_mass}"
        );
        // The density-weighted colour of the inflow's Gaussians.
        let (light, heavy) = (softplus(2.0), softplus(4.0));
        let grey = (0.4 * light + 0.8 * heavy) / (light + heavy);
        for &index in &report.indices {
            let p = Vec3::from_slice(&g.means[3 * index..3 * index + 3]);
            // Only the four cells that lost density, never the one above the box.
            assert!(
                p.x >= 0.375 && p.x <= 0.625 && p.z >= 0.375 && p.z <= 0.625 && p.y <= 0.125,
                "emitted {index} at {p:?}"
            );
            // A standard deviation above the floor.
            assert!(p.y >= 0.1 - 1e-6, "emitted {index} at {p:?}");
            for c in &g.colors[3 * index..3 * index + 3] {
                assert!((c - grey).abs() < 1e-5, "colour {c}, expected {grey}");
            }
            assert_eq!(&g.log_scales[3 * index..3 * index + 3], &[0.1f32.ln(); 3]);
        }
        // Rows outside the slots are untouched.
        let fresh = gaussians(100, 6);
        assert_eq!(g.means[..150], fresh.means[..150]);
        assert_eq!(g.raw_densities[..50], fresh.raw_densities[..50]);
    }

    #[test]
    fn smoke_moved_within_the_inflow_has_not_left_it() {
        let (before, mut after) = densities();
        // Of the eight units the four cells held, 3 stay in one of them: the box lost 4.
        after[cell(3, 0, 4)] = 3.0;
        let mut g = gaussians(100, 6);
        let slots: Vec<usize> = (50..100).collect();
        let report = emitted(&mut g, &before, &after, &slots, 40);
        let cell_volume = 0.125f32.powi(3);
        assert!((report.mass - 4.0 * cell_volume).abs() < 1e-6);
        let emitted: f32 = report.indices.iter().map(|&i| seen_mass(&g, i)).sum();
        assert!((emitted - report.mass).abs() < 1e-3 * report.mass);
        // Only into the three cells that lost density.
        for &index in &report.indices {
            let p = Vec3::from_slice(&g.means[3 * index..3 * index + 3]);
            let gained = p.x < 0.5 && p.z >= 0.5;
            assert!(!gained, "emitted {index} at {p:?}, in the cell that gained");
        }
    }

    #[test]
    fn the_budget_caps_the_count_and_keeps_the_mass() {
        let (before, after) = densities();
        let mut g = gaussians(100, 6);
        let slots: Vec<usize> = (50..100).collect();
        let report = emitted(&mut g, &before, &after, &slots, 1);
        assert_eq!(report.indices, vec![50]);
        assert!((seen_mass(&g, 50) - report.mass).abs() < 1e-3 * report.mass);
        // Fewer free rows than the budget: all of them.
        let mut g = gaussians(100, 6);
        let report = emitted(&mut g, &before, &after, &[70], 40);
        assert_eq!(report.indices, vec![70]);
    }

    #[test]
    fn a_carrier_that_empties_nothing_emits_nothing() {
        let (before, _) = densities();
        let mut g = gaussians(100, 6);
        let fresh = g.clone();
        let slots: Vec<usize> = (50..100).collect();
        // At rest.
        let report = emitted(&mut g, &before, &before, &slots, 40);
        assert!(report.indices.is_empty() && report.mass == 0.0);
        // Density gained in the box (smoke carried in from elsewhere), lost only outside it.
        let mut after = before.clone();
        after[cell(3, 0, 3)] = 3.0;
        after[cell(4, 6, 4)] = 0.0;
        let report = emitted(&mut g, &before, &after, &slots, 40);
        assert!(report.indices.is_empty());
        assert_eq!(g, fresh);
    }
}
