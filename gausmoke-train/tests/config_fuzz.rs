//! Every configuration key set to zero, negative, huge, not-a-number and the wrong type: the
//! value is either refused by `validate` with a message naming the key, or a short training
//! run on the tiny scene ends without a panic (an error is fine, a panic is not).

use std::panic::{AssertUnwindSafe, catch_unwind};

use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_render::backends::device_by_name;
use gausmoke_train::sequence::Sequence;
use gausmoke_train::{Run, TrainConfig};

/// Numeric keys, and whether a huge value of it may be trained (counts of work or memory are
/// not: a huge one is a request for that much work).
const KEYS: &[(&str, bool)] = &[
    ("gaussians", false),
    ("grid_resolution", false),
    ("frames", false),
    ("init_iterations", false),
    ("init_learning_rates.means", true),
    ("init_learning_rates.rotations", true),
    ("init_learning_rates.log_scales", true),
    ("init_learning_rates.raw_densities", true),
    ("init_learning_rates.colors", true),
    ("advect_iterations", false),
    ("refine_iterations", false),
    ("refine_views_per_step", true),
    ("lr_velocity", true),
    ("lr_gaussians", true),
    ("lr_log_scales", true),
    ("lr_decay", true),
    ("lr_decay_every", true),
    ("lambda_div", true),
    ("lambda_adv", true),
    ("lambda_refine", true),
    ("lambda_refine_grid", true),
    ("lambda_lookahead", true),
    ("lambda_increment", true),
    ("increment_horizontal_weight", true),
    ("dt", true),
    ("unet_channels", false),
    ("time_frequencies", true),
    ("projection_tolerance", true),
    ("projection_max_iterations", false),
    ("penalty_steps", false),
    ("scene.open_face_flow", true),
    ("respawn_fraction", true),
    ("respawn_threshold", true),
    ("split_fraction", true),
    ("seed", true),
    ("output_every", true),
    ("log_every", true),
    ("tile_list_headroom", true),
];

const VALUES: &[&str] = &[
    "0",
    "-1",
    "-0.5",
    "1e30",
    "18446744073709551615",
    "nan",
    "inf",
    "abc",
];

fn tiny_config() -> TrainConfig {
    TrainConfig {
        gaussians: 200,
        grid_resolution: 8,
        frames: Some(2),
        init_iterations: 3,
        advect_iterations: 2,
        refine_iterations: 1,
        unet_channels: 4,
        time_frequencies: 2,
        ..TrainConfig::default()
    }
}

#[test]
fn no_configuration_value_panics() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    generate(&SynthConfig::tiny(), &data).unwrap();
    let device = device_by_name("flex").unwrap().autodiff();
    let mut refused = 0;
    let mut trained = 0;
    for &(key, huge_may_train) in KEYS {
        for &value in VALUES {
            let set = format!("{key}={value}");
            let config = match tiny_config().with_overrides(std::slice::from_ref(&set)) {
                Ok(config) => config,
                Err(err) => {
                    // A value of the wrong type: refused while parsing, naming the setting.
                    assert!(err.to_string().contains(key), "`{set}`: {err}");
                    refused += 1;
                    continue;
                }
            };
            if let Err(err) = config.validate() {
                assert!(
                    err.to_string().contains(key.rsplit('.').next().unwrap()),
                    "`{set}` refused without naming the key: {err}"
                );
                refused += 1;
                continue;
            }
            let huge = value.contains("e30") || value.len() > 10 || value == "inf";
            if huge && !huge_may_train {
                continue;
            }
            let out = dir.path().join(format!("run-{trained}"));
            let outcome = catch_unwind(AssertUnwindSafe(|| {
                let scene = Sequence::open(&data, &config)?;
                let mut run =
                    Run::new(scene, config.clone(), device.clone(), &out, false)?.quiet(true);
                run.run().map(|_| ())
            }));
            assert!(outcome.is_ok(), "`{set}` panicked");
            trained += 1;
        }
    }
    eprintln!("{refused} values refused up front, {trained} trained without a panic");
    assert!(
        refused > 50 && trained > 20,
        "{refused} refused, {trained} trained"
    );
}
