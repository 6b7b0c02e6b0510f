//! The reproduction's presets: the library's `paper` and `ours` at each scene's sizes, with the
//! scene where its data does not declare one.

use gausmoke_train::TrainConfig;
use gausmoke_train::preset::{Preset, Scale};
use gausmoke_train::scene::SceneConfig;

use super::Target;

/// The scenes whose quick presets train with our update (`Preset::Ours`): the real capture and
/// the plume itself, turning, past a sphere (undrawn or drawn as a ball) and past a block
/// before a checkered wall, where it gains +3.80 / +0.90 / +0.64 dB held out and a truer
/// velocity over the paper's update (three paired seeds each, docs/RESULTS.md). The Blender
/// set keeps the paper's update (ours cost it 0.52 dB held out there, docs/EXPERIMENTS.md).
pub(super) fn trains_with_our_update(target: Target) -> bool {
    matches!(
        target,
        Target::ScalarReal
            | Target::SyntheticLong
            | Target::Turning
            | Target::Obstacle
            | Target::Ball
            | Target::Blocks
    )
}

/// Around ScalarFlow's inflow, where the smoke leaves the generator at the bottom of the box,
/// measured by hand on its pictures (the capture ships no scene.toml).
pub(super) const SCALAR_REAL_INFLOW: [f32; 6] = [0.4, 0.0, 0.4, 0.66, 0.15, 0.66];

/// The ScalarFlow capture's scene: the plume rises through the box's top and draws air in at
/// the bottom (with these two faces solid the quick preset fell below fitting each frame alone
/// after frame 60, three paired seeds), and its inflow box.
pub(super) fn scalar_real_scene() -> SceneConfig {
    SceneConfig {
        open_faces: Some(vec!["y-".into(), "y+".into()]),
        open_face_flow: Some(1.0),
        inflow: Some(SCALAR_REAL_INFLOW),
    }
}

/// On ScalarReal, our update without its one-view refinement (which costs 0.23 dB held out
/// there over 120 frames, three seeds) and with a quarter of `learning_rates.gaussians` for the sizes
/// after frame 0 (+0.21 +- 0.09 dB there; on the long plume the same costs 1.0 dB): the two
/// settings where the library's one recipe is not ScalarReal's best (docs/RESULTS.md).
pub(super) fn for_scalar_real(ours: TrainConfig, paper: &TrainConfig) -> TrainConfig {
    {
        let mut config = ours;
        config.refine.iterations = paper.refine.iterations;
        config.refine.views_per_step = paper.refine.views_per_step;
        config.refine.lambda_grid = paper.refine.lambda_grid;
        config.joint.inertia.horizontal_weight = paper.joint.inertia.horizontal_weight;
        config.learning_rates.log_scales = Some(5e-4);
        config
    }
}

/// `config` with as many static Gaussians as smoke ones, for the blocks scene's and the
/// Blender set's quick presets, whose wall fills most of every view (with half as many,
/// frame 0's smoke paints the wall's checker; docs/RESULTS.md, "Obstacles and static solids").
pub(super) fn with_statics_for_a_wall(config: TrainConfig) -> TrainConfig {
    TrainConfig {
        static_gaussians: config.gaussians,
        ..config
    }
}

/// The paper's method at the sizes of `target`'s preset: the library's scale, and what the
/// scene's data asks for (views, image size, static Gaussians).
pub(super) fn sizes(target: Target, quick: bool) -> TrainConfig {
    let scale = Preset::Paper.config(if quick { Scale::Quick } else { Scale::Paper });
    // The synthetic scenes at the quick scale: 4000 Gaussians for their 64x96 views (the
    // scale's 8000 are ScalarReal's, for 90x160).
    let plume = TrainConfig {
        gaussians: if quick { 4000 } else { scale.gaussians },
        ..scale.clone()
    };
    let scalar_real = TrainConfig {
        train_views: Some(
            ["train00", "train01", "train03", "train04"]
                .map(String::from)
                .into(),
        ),
        test_views: Some(vec!["train02".into()]),
        scene: scalar_real_scene(),
        ..scale.clone()
    };
    // The tiny scene's records ran with closed walls.
    let walls = SceneConfig {
        open_faces: Some(Vec::new()),
        open_face_flow: Some(1.0),
        ..SceneConfig::default()
    };
    match (target, quick) {
        (Target::ScalarReal, true) => TrainConfig {
            image_size: Some([90, 160]),
            frames: Some(8),
            ..scalar_real
        },
        (Target::ScalarReal, false) => {
            let mut config = TrainConfig {
                image_size: Some([270, 480]),
                ..scalar_real
            };
            config.output.every = 10;
            config
        }
        (Target::Synthetic, true) => TrainConfig {
            scene: walls,
            ..TrainConfig::quick_demo()
        },
        (Target::Synthetic, false) => TrainConfig {
            scene: walls,
            ..scale
        },
        (Target::SyntheticLong | Target::Turning | Target::Obstacle, _) => plume,
        // A quarter as many static Gaussians as smoke ones.
        (Target::Ball, true) => TrainConfig {
            static_gaussians: 1000,
            ..plume
        },
        (Target::Ball, false) => TrainConfig {
            static_gaussians: 7500,
            ..plume
        },
        (Target::Blocks, true) => with_statics_for_a_wall(plume),
        // Eleven training views, each loaded from 800x800 down to 100x100; the top an
        // outflow, as its records ran.
        (Target::Blender, true) => TrainConfig {
            image_size: Some([100, 100]),
            scene: SceneConfig {
                open_face_flow: Some(1.0),
                ..SceneConfig::default()
            },
            ..with_statics_for_a_wall(plume)
        },
        (Target::Blocks | Target::Blender, false) => TrainConfig {
            static_gaussians: 15000,
            ..plume
        },
    }
}
