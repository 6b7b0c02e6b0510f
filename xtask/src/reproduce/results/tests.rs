use super::*;
use serde_json::json;

#[test]
fn long_runs_get_block_means_and_the_independent_baseline_its_rows() {
    // 25 frames: blocks 0-9 and 10-19 full, 20-24 partial; frame 3 has no held-out view.
    let psnr: Vec<Value> = (0..25)
        .map(|t| {
            if t == 3 {
                Value::Null
            } else {
                json!(40.0 - t as f64)
            }
        })
        .collect();
    let records = vec![
        json!({"key": "long", "test_psnr_per_frame": psnr, "independent": [
            {"frame": 0, "sequential_test_psnr": 40.0, "test_psnr": 40.0,
             "sequential_minus_independent_psnr": 0.0},
            {"frame": 20, "sequential_test_psnr": 20.0, "test_psnr": 21.5,
             "sequential_minus_independent_psnr": -1.5,
             "sequential_density_correlation": 0.8, "density_correlation": 0.75},
        ]}),
        json!({"key": "short", "test_psnr_per_frame": [30.0, 29.0], "independent": []}),
    ];
    let mut block = String::new();
    write_drift_tables(&mut block, &records).unwrap();
    // Block 0: frames 0-9 without frame 3, mean of 40, 39, 38, 36, ..., 31 = 318 / 9.
    assert!(
        block.contains("| run | 0-9 | 10-19 | 20-29 |\n|---|---:|---:|---:|\n| `long` | 35.33 | 25.50 | 18.00 |\n"),
        "{block}"
    );
    assert!(!block.contains("`short`"), "{block}");
    assert!(
        block.contains("| `long` | 0 | 40.00 | 40.00 | +0.00 | n/a | n/a |"),
        "{block}"
    );
    assert!(
        block.contains("| `long` | 20 | 20.00 | 21.50 | -1.50 | 0.800 | 0.750 |"),
        "{block}"
    );
}

#[test]
fn variants_name_the_preset_settings_that_their_label_does_not() {
    let record = |label: &str, faces: Value| {
        upgraded(json!({"variant": label, "config": {"open_faces": faces}}))
    };
    assert_eq!(
        variant(&record("full method", json!(["y-", "y+"]))),
        "full method, open faces y- y+"
    );
    assert_eq!(variant(&record("full method", json!([]))), "full method");
    assert_eq!(
        variant(&upgraded(json!({"variant": "full method", "config": {}}))),
        "full method"
    );
    let tagged = r#"full method, open_faces=["y-","y+"]"#;
    assert_eq!(variant(&record(tagged, json!(["y-", "y+"]))), tagged);
    let carried = upgraded(json!({"variant": "full method",
                         "config": {"open_faces": ["y+"], "transport_velocity": true}}));
    assert_eq!(
        variant(&carried),
        "full method, velocity transported, open faces y+"
    );
    let tagged = upgraded(json!({"variant": "full method, transport_velocity=true",
                        "config": {"transport_velocity": true}}));
    assert_eq!(variant(&tagged), "full method, transport_velocity=true");
    // The quick presets' update, as its records store it (f32 values widened to f64).
    let ours = upgraded(json!({"variant": "full method, respawn 0.02",
                      "config": {"open_faces": ["y+"], "transport_velocity": true,
                                 "lambda_lookahead": 1.0, "lookahead_velocity": "predicted",
                                 "lambda_increment": 0.009999999776482582,
                                 "respawn_region": [0.3499999940395355, 0.0, 0.3499999940395355,
                                                    0.6499999761581421, 0.15000000596046448,
                                                    0.6499999761581421]}}));
    assert_eq!(
        variant(&ours),
        "full method, respawn 0.02, velocity transported, look-ahead 1 along Phi's \
         prediction, inertia prior 0.01, recycled into [0.35, 0, 0.35, 0.65, 0.15, 0.65], \
         open faces y+"
    );
    // A half-open top: named when a preset sets it, not twice when --set did, not at 1.
    let top = |label: &str, flow: f64| {
        variant(&upgraded(json!({"variant": label,
                        "config": {"open_faces": ["y+"], "open_face_flow": flow}})))
    };
    assert_eq!(
        top("full method", 0.5),
        "full method, open faces y+, open-face flow 0.5"
    );
    assert_eq!(
        top("full method, open_face_flow=0.5", 0.5),
        "full method, open_face_flow=0.5, open faces y+"
    );
    assert_eq!(top("full method", 1.0), "full method, open faces y+");
    // The sizes' own learning rate: named when a preset sets it, not twice when --set did.
    let sizes = upgraded(json!({"variant": "full method", "config": {"lr_log_scales": 0.0005}}));
    assert_eq!(variant(&sizes), "full method, sizes at lr 0.0005");
    let tagged = upgraded(json!({"variant": "full method, lr_log_scales=5e-4",
                        "config": {"lr_log_scales": 0.0005}}));
    assert_eq!(variant(&tagged), "full method, lr_log_scales=5e-4");
    let split = upgraded(json!({"variant": "full method",
                       "config": {"split_fraction": 0.009999999776482582,
                                  "split_size_factor": 1.5}}));
    assert_eq!(
        variant(&split),
        "full method, split 0.01 a frame above 1.5x the initial size"
    );
    let none = upgraded(json!({"variant": "full method", "config": {"split_fraction": 0.0}}));
    assert_eq!(variant(&none), "full method");
    // The one-view refinement, its tie and the horizontal weight, as a preset sets them.
    let refined = upgraded(json!({"variant": "full method",
                         "config": {"refine_iterations": 40, "refine_views_per_step": 1,
                                    "lambda_refine_grid": 3.0,
                                    "increment_horizontal_weight": 3.0}}));
    assert_eq!(
        variant(&refined),
        "full method, K' = 40 of 1 view a step, grid-scale tie 3, horizontal increments x3"
    );
    let paper = upgraded(json!({"variant": "full method",
                       "config": {"refine_iterations": 5, "refine_views_per_step": 0,
                                  "lambda_refine_grid": 0.0,
                                  "increment_horizontal_weight": 1.0}}));
    assert_eq!(variant(&paper), "full method");
    // The statics' fit and layer (the Blender preset's fit; a recorded f32 depth).
    let statics = upgraded(json!({"variant": "full method",
                         "config": {"static_iterations": 1000,
                                    "static_shell": 0.01600000075995922}}));
    assert_eq!(
        variant(&statics),
        "full method, statics fitted 1000 steps, statics within 0.016 of the surfaces"
    );
}

#[test]
fn an_atomic_write_replaces_the_file_and_leaves_nothing_beside_it() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("RESULTS.md");
    std::fs::write(&path, "old").unwrap();
    write_atomically(&path, "new").unwrap();
    assert_eq!(std::fs::read_to_string(&path).unwrap(), "new");
    let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert_eq!(names.len(), 1, "{names:?}");
}

#[test]
fn runs_whose_presets_differ_are_not_summarised_together() {
    let record = |seed: u64, faces: Value| {
        upgraded(
            json!({"key": format!("g-s{seed}"), "group": "g", "seed": seed, "variant": "full method",
               "test_psnr": 30.0 + seed as f64, "config": {"open_faces": faces}}),
        )
    };
    let mut records = vec![
        record(1, json!([])),
        record(2, json!([])),
        record(3, json!(["y-", "y+"])),
        record(4, json!(["y-", "y+"])),
    ];
    // Two more seeds of the open-faced preset with the velocity transported: their own group.
    for seed in [5, 6] {
        let mut carried = record(seed, json!(["y-", "y+"]));
        carried["config"]["joint"]["transport_velocity"] = json!(true);
        records.push(carried);
    }
    // And two with the look-ahead on top: a preset changed under the same keys.
    for seed in [7, 8] {
        let mut ahead = record(seed, json!(["y-", "y+"]));
        ahead["config"]["joint"]["transport_velocity"] = json!(true);
        ahead["config"]["joint"]["look_ahead"]["weight"] = json!(1.0);
        records.push(ahead);
    }
    let mut block = String::new();
    write_seed_summary(&mut block, &records).unwrap();
    assert!(
        block.contains(
            "| `g` | full method, velocity transported, look-ahead 1, open faces y- y+ | 7, 8 | 37.50 +- 0.71 |"
        ),
        "{block}"
    );
    assert!(
        block.contains(
            "| `g` | full method, velocity transported, open faces y- y+ | 5, 6 | 35.50 +- 0.71 |"
        ),
        "{block}"
    );
    assert!(
        block.contains("| `g` | full method | 1, 2 | 31.50 +- 0.71 |"),
        "{block}"
    );
    assert!(
        block.contains("| `g` | full method, open faces y- y+ | 3, 4 | 33.50 +- 0.71 |"),
        "{block}"
    );
}

#[test]
fn ablations_are_paired_with_the_full_method_of_the_same_seed() {
    let record = |group: &str, seed: u64, psnr: f64, divergence: f64| {
        json!({
            "key": format!("{group}-s{seed}"),
            "group": group,
            "seed": seed,
            "variant": "v",
            "test_psnr": psnr,
            "test_ssim": 0.9,
            "velocity_relative_error": 0.5,
            "density_relative_error": 0.5,
            "mean_abs_divergence": divergence,
        })
    };
    let records = vec![
        record("synthetic-quick", 1, 40.0, 0.01),
        record("synthetic-quick", 2, 44.0, 0.01),
        // No ablation ran with seed 3: it is left out of the pairs.
        record("synthetic-quick", 3, 10.0, 0.01),
        record("synthetic-quick-no-physics", 1, 39.0, 0.1),
        record("synthetic-quick-no-physics", 2, 42.0, 0.2),
    ];
    let mut block = String::new();
    write_seed_summary(&mut block, &records).unwrap();
    // PSNR differences 1 and 2 dB: mean 1.5, sample sd 0.71, the full method better in
    // both; divergence differences -0.09 and -0.19: lower with the full method in both.
    assert!(
        block.contains(
            "| `synthetic-quick` | w/o physical losses | 2 | +1.50 +- 0.71 (2/2) \
             | +0.000 +- 0.000 (0/2) | +0.000 +- 0.000 (0/2) | -1.40e-1 +- 7.07e-2 (2/2) |"
        ),
        "{block}"
    );
}

/// A record as [`read_records`] gives it: its configuration at the current keys.
fn upgraded(mut record: Value) -> Value {
    legacy::upgrade(&mut record["config"]);
    record
}
