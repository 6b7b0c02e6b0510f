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
    ("init.iterations", false),
    ("init.learning_rates.means", true),
    ("init.learning_rates.rotations", true),
    ("init.learning_rates.log_scales", true),
    ("init.learning_rates.raw_densities", true),
    ("init.learning_rates.colors", true),
    ("joint.iterations", false),
    ("refine.iterations", false),
    ("refine.views_per_step", true),
    ("learning_rates.velocity", true),
    ("learning_rates.gaussians", true),
    ("learning_rates.log_scales", true),
    ("learning_rates.decay", true),
    ("learning_rates.decay_every", true),
    ("joint.lambda_div", true),
    ("joint.lambda_adv", true),
    ("refine.lambda", true),
    ("refine.lambda_grid", true),
    ("joint.look_ahead.weight", true),
    ("joint.inertia.weight", true),
    ("joint.inertia.horizontal_weight", true),
    ("dt", true),
    ("unet_channels", false),
    ("time_frequencies", true),
    ("projection.tolerance", true),
    ("projection.max_iterations", false),
    ("projection.penalty_steps", false),
    ("scene.open_face_flow", true),
    ("population.recycle.fraction", true),
    ("population.recycle.threshold", true),
    ("population.split.fraction", true),
    ("seed", true),
    ("output.every", true),
    ("output.log_every", true),
    ("device.tile_list_headroom", true),
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
    {
        let mut config = TrainConfig {
            gaussians: 200,
            grid_resolution: 8,
            frames: Some(2),
            unet_channels: 4,
            time_frequencies: 2,
            ..TrainConfig::default()
        };
        config.init.iterations = 3;
        config.joint.iterations = 2;
        config.refine.iterations = 1;
        config
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
