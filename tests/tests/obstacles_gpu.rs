//! Scenes with solid obstacles (a sphere; two boxes) and static Gaussians train on a GPU
//! backend (wgpu; lavapipe in CI) as on the CPU: the obstacles' cells hold no velocity after
//! the device projection, no smoke centre stays inside one, and the static Gaussians render
//! with the smoke in one pass and keep their place.
//!
//! Like the other GPU tests this FAILS without a GPU adapter rather than skip.

use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_render::backends::gpu_devices;
use gausmoke_render::device_traffic::read_floats;
use gausmoke_train::sequence::Sequence;
use gausmoke_train::{TrainConfig, Trainer};

#[test]
fn the_ball_scene_trains_on_the_device() {
    trains_on_the_device(SynthConfig::ball_plume());
}

/// A block in the plume's way and a wall behind it: boxes in the device projection and in the
/// push-out of smoke centres.
#[test]
fn the_blocks_scene_trains_on_the_device() {
    trains_on_the_device(SynthConfig::blocks_plume());
}

fn trains_on_the_device(preset: SynthConfig) {
    let (backend, device) = gpu_devices()
        .into_iter()
        .next()
        .expect("this test binary is built with gausmoke-train's wgpu feature");
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let scene = SynthConfig {
        frames: 3,
        grid: 16,
        views: 3,
        ..preset
    };
    generate(&scene, &data).unwrap();
    let config = {
        let mut config = TrainConfig {
            gaussians: 400,
            static_gaussians: 100,
            grid_resolution: 16,
            frames: Some(3),
            unet_channels: 4,
            time_frequencies: 2,
            scene: gausmoke_train::scene::SceneConfig {
                open_faces: Some(vec!["y+".into()]),
                ..Default::default()
            },
            ..TrainConfig::default()
        };
        config.init.iterations = 10;
        config.joint.iterations = 4;
        config.refine.iterations = 2;
        config
    };
    let sequence = Sequence::open(&data, &config).unwrap();
    let mut trainer = Trainer::new(sequence, config, device.autodiff())
        .unwrap()
        .quiet(true);
    let solids = trainer
        .solid_cells()
        .cloned()
        .expect("the obstacles are solid");
    let statics_at = |trainer: &Trainer| {
        read_floats(
            trainer
                .state
                .statics
                .as_ref()
                .expect("static Gaussians")
                .gaussians
                .means
                .val(),
        )
    };
    trainer.train_frame(0).unwrap();
    let fitted = statics_at(&trainer);
    for t in 1..3 {
        let outcome = trainer.train_frame(t).unwrap();
        assert!(outcome.train_l1.is_finite(), "{backend}: frame {t}");
    }
    assert_eq!(statics_at(&trainer), fitted, "{backend}: the statics moved");
    let velocity = read_floats(trainer.state.velocity.clone());
    assert_eq!(
        solids.speed_inside(&velocity),
        0.0,
        "{backend}: velocity inside the obstacle"
    );
    assert!(
        velocity.iter().any(|&v| v != 0.0),
        "{backend}: no flow at all"
    );
    let means = read_floats(trainer.state.gaussians.means.val());
    let inside = means
        .chunks(3)
        .filter(|m| {
            let p = gausmoke_data::glam::Vec3::from_slice(m);
            scene
                .solids
                .iter()
                .any(|s| s.shape.signed_distance(p) < 0.0)
        })
        .count();
    assert_eq!(inside, 0, "{backend}: smoke centres inside an obstacle");
}
