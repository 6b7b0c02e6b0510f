#![allow(clippy::disallowed_methods)] // tests read tensors freely

use burn::tensor::{Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_data::Obstacle;
use gausmoke_model::{GridScale, GridSpec, ProjectionOptions};
use gausmoke_render::backends::cpu_devices;
use gausmoke_render::device_traffic::{read_floats, read_scalar};

use super::Trainer;
use super::joint::InertiaPrior;
use super::moves::{FrameMoves, MoveField, refine_moves};
use super::obstacles::outside_obstacles;
use super::refine::{last_turn_l1, refinement_views};
use crate::config::TrainConfig;
use crate::sequence::Sequence;
use crate::state::{LossRow, Phase};

fn tiny_scene() -> (tempfile::TempDir, std::path::PathBuf) {
    use gausmoke_data::synth::{SynthConfig, generate};
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    generate(&SynthConfig::tiny(), &data).unwrap();
    (dir, data)
}

/// `joint.inertia.horizontal_weight` scales what a sideways increment pays in the inertia
/// prior and leaves what an upward one pays.
#[test]
fn the_inertia_prior_weighs_horizontal_increments_apart() {
    use gausmoke_render::backends::device_by_name;
    let (_dir, data) = tiny_scene();
    let device = device_by_name("flex").unwrap();
    let prior = |weight: f32, component: usize| {
        let config = {
            let mut config = TrainConfig {
                gaussians: 100,
                grid_resolution: 8,
                frames: Some(2),
                ..TrainConfig::default()
            };
            config.joint.inertia.weight = 0.5;
            config.joint.inertia.horizontal_weight = weight;
            config
        };
        let sequence = Sequence::open(&data, &config).unwrap();
        let trainer = Trainer::new(sequence, config, device.clone()).unwrap();
        let prior =
            InertiaPrior::of(&trainer.config.joint.inertia, &trainer.grid, &device).unwrap();
        let cell = trainer.grid.cell_size().to_array()[component];
        let mut values = vec![0.0f32; 8 * 8 * 8 * 3];
        // One cell moves one cell's length along `component`.
        values[component] = cell;
        let delta = Tensor::<4>::from_data(TensorData::new(values, [8, 8, 8, 3]), &device);
        read_scalar(prior.loss(delta))
    };
    let one = 0.5 / 512.0;
    for (component, weight, want) in [
        (0, 1.0, one),
        (0, 10.0, 10.0 * one),
        (2, 10.0, 10.0 * one),
        (1, 10.0, one),
        (2, 0.0, 0.0),
    ] {
        let got = prior(weight, component);
        assert!(
            (got - want).abs() < 1e-6 * want.max(1.0),
            "component {component}, weight {weight}: {got} against {want}"
        );
    }
}

/// The persistence of the refinement's moves is their correlation with the frame
/// before's: 1 for the same moves, -1 for reversed ones, about 0 for unrelated ones,
/// and rows that jumped this frame do not count.
#[test]
fn the_persistence_of_the_moves_is_their_correlation_with_the_frame_before() {
    let (_, device) = cpu_devices().into_iter().next().unwrap();
    let grid = GridSpec::new(Vec3::ZERO, Vec3::ONE, [8, 8, 8], 1).unwrap();
    let mut rng = SplitMix64::new(3);
    let n = 500;
    let mut random = |lo: f32, hi: f32| -> Tensor<2> {
        let values: Vec<f32> = (0..3 * n).map(|_| rng.range(lo, hi)).collect();
        Tensor::from_data(TensorData::new(values, [n, 3]), &device)
    };
    let centres = random(0.05, 0.95);
    let moves = random(-1.0, 1.0);
    let unrelated = random(-1.0, 1.0);
    let masses = Tensor::<1>::ones([n], &device);
    let scale = GridScale::new(&grid, centres, masses);
    let none = Tensor::<1>::zeros([n], &device);
    // Each frame's grid-scale field, in world units (a cell is an eighth of the box).
    let field_of = |m: Tensor<2>| MoveField {
        field: scale.cell_means(m / 8.0).reshape([8, 8, 8, 3]),
        grid: &grid,
        projection: ProjectionOptions::default(),
    };
    let field = field_of(moves.clone());
    // The field's share is the swirl test's business; still moves have none.
    let still = moves.clone() * 0.0;
    assert_eq!(
        refine_moves(&scale, still.clone(), None, &none, &field_of(still))
            .0
            .flow_share,
        0.0
    );
    let frame = |m: Tensor<2>| {
        let before = field_of(m.clone());
        FrameMoves {
            grid_part: scale.grid_part(m.clone()),
            moves: m,
            field: before.split(read_floats(before.field.clone())),
        }
    };
    let persistence = |before: Option<&FrameMoves>, jumped: &Tensor<1>| {
        refine_moves(&scale, moves.clone(), before, jumped, &field)
            .0
            .persistence
    };
    assert_eq!(persistence(None, &none), None);
    let field_persistence = |before: Option<&FrameMoves>| {
        refine_moves(&scale, moves.clone(), before, &none, &field)
            .0
            .field_persistence
    };
    assert_eq!(field_persistence(None), None);
    let close = |got: Option<[f64; 2]>, want: f64, tolerance: f64| {
        let got = got.expect("a frame before");
        assert!(
            got.iter().all(|g| (g - want).abs() < tolerance),
            "{got:?} against {want}"
        );
    };
    close(persistence(Some(&frame(moves.clone())), &none), 1.0, 1e-4);
    close(persistence(Some(&frame(-moves.clone())), &none), -1.0, 1e-4);
    // Both parts of the field, the flow and the gathering, follow the moves.
    close(field_persistence(Some(&frame(moves.clone()))), 1.0, 1e-4);
    close(field_persistence(Some(&frame(-moves.clone()))), -1.0, 1e-4);
    close(
        persistence(Some(&frame(unrelated.clone())), &none),
        0.0,
        0.15,
    );
    // The first half jumped, and only there did the moves change.
    let half: Vec<f32> = (0..n).map(|i| if i < n / 2 { 1.0 } else { 0.0 }).collect();
    let jumped = Tensor::<1>::from_data(TensorData::new(half.clone(), [n]), &device);
    let first_half = Tensor::<2>::from_data(TensorData::new(half, [n, 1]), &device);
    let changed = moves.clone() * (first_half.clone().neg() + 1.0) + unrelated * first_half;
    let persistence_of = |jumped: &Tensor<1>| {
        refine_moves(
            &scale,
            moves.clone(),
            Some(&frame(changed.clone())),
            jumped,
            &field,
        )
        .0
        .persistence
        .expect("a frame before")[0]
    };
    assert!((persistence_of(&jumped) - 1.0).abs() < 1e-4);
    assert!(persistence_of(&none) < 0.8);
}

#[test]
fn refinement_steps_take_the_views_in_turn() {
    for views in 1..=5 {
        for per_step in 0..=views + 1 {
            let all = per_step == 0 || per_step >= views;
            let mut seen = vec![0; views];
            let mut groups = std::collections::HashMap::new();
            for step in 0..3 * views {
                let group = refinement_views(step, views, per_step);
                assert_eq!(group.len(), if all { views } else { per_step });
                // A group is fixed by its first view (it keys the list capacities).
                let known = groups.entry(group[0]).or_insert_with(|| group.clone());
                assert_eq!(*known, group, "{views} views, {per_step} per step");
                for v in group {
                    seen[v] += 1;
                }
            }
            // Over any whole number of turns every view is rendered equally often.
            let want = if all { 3 * views } else { 3 * per_step };
            assert!(
                seen.iter().all(|&n| n == want),
                "{views} views, {per_step} per step: {seen:?}"
            );
        }
    }
    assert_eq!(refinement_views(1, 4, 1), vec![1]);
    assert_eq!(refinement_views(1, 4, 3), vec![3, 0, 1]);
}

#[test]
fn the_train_l1_of_a_frame_covers_every_view() {
    let row = |phase, render| LossRow {
        frame: 1,
        phase,
        iteration: 0,
        total: render,
        render,
        divergence: 0.0,
        advection: 0.0,
        refine: 0.0,
    };
    let rows = [
        row(Phase::Advect, 9.0),
        row(Phase::Refine, 1.0),
        row(Phase::Refine, 2.0),
        row(Phase::Refine, 4.0),
        row(Phase::Refine, 6.0),
    ];
    // All views per step: the last step's.
    assert_eq!(last_turn_l1(&rows, 3, 0), 6.0);
    assert_eq!(last_turn_l1(&rows, 3, 3), 6.0);
    // One of three per step: the last three steps'.
    assert_eq!(last_turn_l1(&rows, 3, 1), 4.0);
    // Fewer refinement steps than a turn: those there are, never the joint step's.
    assert_eq!(last_turn_l1(&rows[..3], 4, 1), 1.5);
    assert_eq!(last_turn_l1(&rows[..1], 4, 1), 9.0);
    assert!(last_turn_l1(&[], 4, 1).is_nan());
}

#[test]
fn centres_inside_obstacles_are_pushed_out_like_the_host_twin() {
    let obstacles = [
        Obstacle::Sphere {
            centre: Vec3::new(0.3, 0.5, 0.0),
            radius: 0.2,
        },
        Obstacle::Box {
            min: Vec3::new(-0.6, 0.1, -0.2),
            max: Vec3::new(-0.1, 0.4, 0.3),
        },
    ];
    let mut rng = SplitMix64::new(7);
    let points: Vec<Vec3> = (0..2000)
        .map(|_| {
            Vec3::new(
                rng.range(-0.8, 0.8),
                rng.range(0.0, 0.8),
                rng.range(-0.4, 0.4),
            )
        })
        .collect();
    let expected: Vec<Vec3> = points
        .iter()
        .map(|&p| obstacles.iter().fold(p, |p, o| o.pushed_out(p)))
        .collect();
    let inside = points
        .iter()
        .filter(|p| obstacles.iter().any(|o| o.contains(**p)))
        .count();
    assert!(inside > 150, "only {inside} points inside");
    for (_, device) in cpu_devices() {
        let flat: Vec<f32> = points.iter().flat_map(|p| p.to_array()).collect();
        let means = Tensor::<2>::from_data(TensorData::new(flat, [points.len(), 3]), &device);
        let moved = outside_obstacles(means, &obstacles)
            .into_data()
            .try_into_vec_as::<f32>()
            .unwrap();
        for ((p, want), got) in points.iter().zip(&expected).zip(moved.chunks_exact(3)) {
            let got = Vec3::from_slice(got);
            assert!(
                got.distance(*want) < 1e-5,
                "{p} -> {got}, the host twin says {want}"
            );
            assert!(obstacles.iter().all(|o| !o.contains(got)), "{p} -> {got}");
        }
    }
}
