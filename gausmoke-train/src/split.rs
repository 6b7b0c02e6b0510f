//! Splitting the largest Gaussians under a fixed count (`population.split.fraction`, ours).
//!
//! Over a video the mass gathers into fewer, larger Gaussians (on the long synthetic plume
//! 90% of it sits in 544 of 4000 by frame 71, against 1404 in a frame fitted alone), and a
//! few refinement steps a frame cannot draw the detail a large Gaussian smooths over. 3DGS
//! densifies by splitting; with a fixed count (the optimisers' per-row state keeps its
//! shape) a split must take a row that no longer describes smoke:
//!
//! - **Which to split.** Visible Gaussians larger than the initialisation's size, by their
//!   longest standard deviation times their peak opacity (large and opaque first).
//! - **Into which rows.** The rows recycling would take (on a box face, or invisible), after
//!   recycling has taken its own; none left, no split. `split_into_faces_only` keeps to the
//!   face ones.
//! - **How.** The parent becomes two Gaussians along its longest axis `a` (standard
//!   deviation `s`): centres at `+-0.6 s`, that axis' deviation `0.8 s`, the density times
//!   `1 / 1.6`, everything else kept. The pair has the parent's mass, mean and covariance
//!   (`0.8^2 + 0.6^2 = 1`), so the frame's render barely changes until the refinement moves
//!   the halves apart where the views ask for it.
//!
//! Host-side and deterministic, like recycling, so a resumed run matches an uninterrupted one.

use gausmoke_render::HostGaussians;
use gausmoke_render::math::{quat_to_rotation, softplus};

use crate::respawn::{
    INVISIBLE_OPACITY, SpawnLattice, inverse_softplus, largest_log_std, peak_opacity,
};

/// The halves' offset along the split axis, in the parent's standard deviations.
const OFFSET: f32 = 0.6;
/// The halves' standard deviation along the split axis, in the parent's
/// (`OFFSET^2 + SHRINK^2 = 1` keeps the covariance).
const SHRINK: f32 = 0.8;

/// What [`split_largest`] did, for the frame report.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SplitReport {
    /// Split rows, largest first.
    pub parents: Vec<usize>,
    /// The row each parent's second half went into, in the same order.
    pub children: Vec<usize>,
}

/// Splits up to `budget` of the largest opaque Gaussians whose longest standard deviation
/// exceeds `min_std`, each into one of `slots` (taken in order; rows recycling would take).
/// The halves stay inside the lattice's box.
pub fn split_largest(
    gaussians: &mut HostGaussians,
    slots: &[usize],
    budget: usize,
    min_std: f32,
    lattice: &SpawnLattice,
) -> SplitReport {
    let count = budget.min(slots.len());
    if count == 0 {
        return SplitReport::default();
    }
    let mut is_slot = vec![false; gaussians.len()];
    for &slot in slots {
        is_slot[slot] = true;
    }
    let mut ranked: Vec<(f32, usize)> = (0..gaussians.len())
        .filter(|&i| !is_slot[i])
        .filter_map(|i| {
            let longest = largest_log_std(gaussians, i).exp();
            let opacity = peak_opacity(gaussians, i);
            (longest > min_std && opacity >= INVISIBLE_OPACITY).then_some((longest * opacity, i))
        })
        .collect();
    ranked.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));

    let mut report = SplitReport::default();
    for (&(_, parent), &child) in ranked.iter().zip(slots).take(count) {
        let scales = &gaussians.log_scales[3 * parent..3 * parent + 3];
        let axis = (0..3)
            .max_by(|&a, &b| scales[a].total_cmp(&scales[b]).then(b.cmp(&a)))
            .expect("three axes");
        let std = scales[axis].exp();
        let q = &gaussians.rotations[4 * parent..4 * parent + 4];
        let norm = q
            .iter()
            .map(|v| v * v)
            .sum::<f32>()
            .sqrt()
            .max(f32::MIN_POSITIVE);
        let rotation = quat_to_rotation([q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm]);
        let mean: [f32; 3] = std::array::from_fn(|i| gaussians.means[3 * parent + i]);
        let half = |sign: f32| -> [f32; 3] {
            std::array::from_fn(|i| {
                (mean[i] + sign * OFFSET * std * rotation[i][axis])
                    .clamp(lattice.lo[i], lattice.hi[i])
            })
        };
        let (first, second) = (half(1.0), half(-1.0));
        let raw_density =
            inverse_softplus(softplus(gaussians.raw_densities[parent]) * 0.5 / SHRINK);

        gaussians.log_scales[3 * parent + axis] += SHRINK.ln();
        gaussians.raw_densities[parent] = raw_density;
        copy_row(gaussians, parent, child);
        gaussians.means[3 * parent..3 * parent + 3].copy_from_slice(&first);
        gaussians.means[3 * child..3 * child + 3].copy_from_slice(&second);
        report.parents.push(parent);
        report.children.push(child);
    }
    report
}

/// Copies every attribute of row `from` into row `to`.
fn copy_row(gaussians: &mut HostGaussians, from: usize, to: usize) {
    gaussians.means.copy_within(3 * from..3 * from + 3, 3 * to);
    gaussians
        .rotations
        .copy_within(4 * from..4 * from + 4, 4 * to);
    gaussians
        .log_scales
        .copy_within(3 * from..3 * from + 3, 3 * to);
    gaussians.raw_densities[to] = gaussians.raw_densities[from];
    gaussians.colors.copy_within(3 * from..3 * from + 3, 3 * to);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lattice() -> SpawnLattice {
        SpawnLattice::unit_box()
    }

    /// Row 0 large and opaque (longest along its local y, rotated), row 1 small, row 2 large
    /// but faint, row 3 invisible (a slot).
    fn gaussians() -> HostGaussians {
        let quarter_turn_about_z = [(0.5f32).sqrt(), 0.0, 0.0, (0.5f32).sqrt()];
        HostGaussians {
            means: vec![0.5, 0.5, 0.5, 0.2, 0.2, 0.2, 0.8, 0.8, 0.8, 0.3, 0.3, 0.3],
            rotations: [
                quarter_turn_about_z,
                [1.0, 0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0, 0.0],
            ]
            .concat(),
            log_scales: [
                [0.05f32.ln(), 0.1f32.ln(), 0.05f32.ln()],
                [0.01f32.ln(); 3],
                [0.1f32.ln(); 3],
                [0.05f32.ln(); 3],
            ]
            .concat(),
            raw_densities: vec![
                inverse_softplus(20.0),
                inverse_softplus(20.0),
                inverse_softplus(0.05),
                -14.0,
            ],
            colors: vec![0.7; 12],
        }
    }

    /// Mass, mean and covariance of a set of rows, from their attributes.
    fn moments(g: &HostGaussians, rows: &[usize]) -> (f32, [f32; 3], [[f32; 3]; 3]) {
        let mut mass = 0.0;
        let mut first = [0.0f32; 3];
        let mut second = [[0.0f32; 3]; 3];
        for &i in rows {
            let s: Vec<f32> = g.log_scales[3 * i..3 * i + 3]
                .iter()
                .map(|v| v.exp())
                .collect();
            let m = softplus(g.raw_densities[i]) * s[0] * s[1] * s[2];
            let q = &g.rotations[4 * i..4 * i + 4];
            let r = quat_to_rotation([q[0], q[1], q[2], q[3]]);
            let mu = &g.means[3 * i..3 * i + 3];
            mass += m;
            for a in 0..3 {
                first[a] += m * mu[a];
                for b in 0..3 {
                    let cov: f32 = (0..3).map(|k| r[a][k] * s[k] * s[k] * r[b][k]).sum();
                    second[a][b] += m * (cov + mu[a] * mu[b]);
                }
            }
        }
        let mean = first.map(|v| v / mass);
        let cov = std::array::from_fn(|a| {
            std::array::from_fn(|b| second[a][b] / mass - mean[a] * mean[b])
        });
        (mass, mean, cov)
    }

    #[test]
    fn the_largest_opaque_gaussian_splits_into_a_slot_keeping_its_moments() {
        let mut g = gaussians();
        let before = moments(&g, &[0]);
        let report = split_largest(&mut g, &[3], 5, 0.03, &lattice());
        assert_eq!(report.parents, vec![0]);
        assert_eq!(report.children, vec![3]);
        let after = moments(&g, &[0, 3]);
        assert!(
            (after.0 / before.0 - 1.0).abs() < 1e-4,
            "mass {after:?} {before:?}"
        );
        for a in 0..3 {
            assert!((after.1[a] - before.1[a]).abs() < 1e-6, "mean {after:?}");
            for b in 0..3 {
                assert!(
                    (after.2[a][b] - before.2[a][b]).abs() < 1e-6,
                    "covariance {:?} against {:?}",
                    after.2,
                    before.2
                );
            }
        }
        // The quarter turn about z sends the local y axis to world -x.
        assert!((g.means[0] - (0.5 - 0.06)).abs() < 1e-6 && (g.means[9] - 0.56).abs() < 1e-6);
        assert_eq!(&g.means[1..3], &[0.5, 0.5]);
        // The other rows are untouched.
        let fresh = gaussians();
        assert_eq!(g.means[3..9], fresh.means[3..9]);
        assert_eq!(g.raw_densities[1..3], fresh.raw_densities[1..3]);
    }

    #[test]
    fn no_slot_no_budget_or_nothing_large_splits_nothing() {
        for (slots, budget, min_std) in
            [(&[][..], 5, 0.03), (&[3][..], 0, 0.03), (&[3][..], 5, 0.2)]
        {
            let mut g = gaussians();
            let report = split_largest(&mut g, slots, budget, min_std, &lattice());
            assert_eq!(report, SplitReport::default());
            assert_eq!(g, gaussians());
        }
    }

    #[test]
    fn halves_stay_inside_the_box() {
        let mut g = gaussians();
        g.means[0] = 0.01;
        split_largest(&mut g, &[3], 1, 0.03, &lattice());
        assert!(
            g.means.iter().all(|v| (0.0..=1.0).contains(v)),
            "{:?}",
            g.means
        );
        assert_eq!(g.means[0], 0.0);
    }
}
