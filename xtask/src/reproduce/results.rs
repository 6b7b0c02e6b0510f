//! The generated block of `docs/RESULTS.md`: tables of every recorded run, summaries across
//! seeds, ablations paired by seed, and the paper's figures beside them.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{Result, bail};

use super::ablation::Ablation;
use gausmoke_train::config::legacy;
use serde_json::Value;

/// The paper's reference figures (Table 1/2, ScalarFlow real capture).
const PAPER_SCALAR_REAL: &str = "34.83 dB PSNR, 0.955 SSIM, 0.0168 LPIPS; 0.8 h training on an \
                                 RTX 3090; 114 FPS rendering; 42 MB";

/// The paper's Table 3 (ablations; PSNR, SSIM, LPIPS, divergence; the table does not name
/// its scene).
const PAPER_ABLATIONS: &str = "full model 37.98 dB, 0.975, 0.0336, div 0.085; w/o L_div, L_adv \
                               30.12 dB, 0.925, 0.0810, div 0.402; w/o volumetric rendering \
                               30.45 dB, 0.932, 0.0825, div 0.127; w/o L_refine 33.87 dB, 0.964, \
                               0.0418, div 0.098";

fn number(value: &Value, digits: usize) -> String {
    value
        .as_f64()
        .map_or("n/a".into(), |v| format!("{v:.digits$}"))
}

fn mib(value: &Value) -> String {
    value
        .as_f64()
        .map_or("n/a".into(), |v| format!("{:.1}", v / (1024.0 * 1024.0)))
}

/// Mean and sample standard deviation.
fn mean_std(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (mean, var.sqrt())
}

/// Whether a label names the key `setting` (as `--set` spells it now, or before the keys had
/// tables).
fn names(label: &str, setting: &str) -> bool {
    label.contains(setting)
        || legacy::RENAMED_KEYS
            .iter()
            .any(|(old, now)| *now == setting && label.contains(old))
}

/// A record's variant label, naming the settings of [`preset_settings`] where the label does
/// not: a preset's settings are not in its label.
fn variant(record: &Value) -> String {
    let mut label = record["variant"].as_str().unwrap_or("?").to_string();
    for (setting, named) in preset_settings(record) {
        if !names(&label, setting) {
            label += &format!(", {named}");
        }
    }
    label
}

/// The settings of ours that set one preset's runs apart from another's, from a record's
/// configuration: each as its configuration key and as a table names it.
fn preset_settings(record: &Value) -> Vec<(&'static str, String)> {
    let config = &record["config"];
    // Records keep the configuration's f32 values; printed as f32 they read as written.
    let weight = |key: &str| {
        at(config, key)
            .as_f64()
            .filter(|&w| w > 0.0)
            .map(|w| w as f32)
    };
    let mut settings = Vec::new();
    if transported(record) {
        settings.push(("transport_velocity", "velocity transported".to_string()));
    }
    if let Some(w) = weight("joint.look_ahead.weight") {
        // Since the scene has its table, the look-ahead always follows Phi's prediction.
        let predicted = config["lookahead_velocity"].as_str() == Some("predicted")
            || config["scene"].is_object();
        let along = if predicted {
            " along Phi's prediction"
        } else {
            ""
        };
        settings.push(("joint.look_ahead.weight", format!("look-ahead {w}{along}")));
    }
    if let Some(w) = weight("joint.inertia.weight") {
        settings.push(("joint.inertia.weight", format!("inertia prior {w}")));
    }
    // Records made before the scene had its table held the box only when they recycled.
    let recycling =
        weight("population.recycle.fraction").is_some() || config["respawn_region"].is_array();
    if let Some(region) = scene_value(config, "inflow", "respawn_region")
        .as_array()
        .filter(|_| recycling)
    {
        let corners: Vec<String> = region
            .iter()
            .filter_map(Value::as_f64)
            .map(|v| (v as f32).to_string())
            .collect();
        settings.push((
            "respawn_region",
            format!("recycled into [{}]", corners.join(", ")),
        ));
    }
    for (key, attribute) in [
        ("lr_means", "refined centres"),
        ("learning_rates.log_scales", "sizes"),
        ("lr_colors", "colours"),
        ("lr_raw_densities", "densities"),
    ] {
        if let Some(lr) = at(config, key).as_f64() {
            settings.push((key, format!("{attribute} at lr {}", lr as f32)));
        }
    }
    if let Some(fraction) = weight("population.split.fraction") {
        let factor = config["split_size_factor"].as_f64().unwrap_or(1.0) as f32;
        let above = if factor == 1.0 {
            String::new()
        } else {
            format!(" above {factor}x the initial size")
        };
        settings.push((
            "population.split.fraction",
            format!("split {fraction} a frame{above}"),
        ));
    }
    if let Some(share) = weight("shape_transport") {
        let of = if share == 1.0 {
            String::new()
        } else {
            format!(" ({share} of the step)")
        };
        settings.push(("shape_transport", format!("shapes carried by the flow{of}")));
    }
    if let Some(cells) = weight("velocity_smoothing_cells") {
        settings.push((
            "velocity_smoothing_cells",
            format!("carried velocity smoothed over {cells} cells"),
        ));
    }
    if let Some(blend) = weight("carried_smoothing") {
        let cells = config["carried_smoothing_cells"].as_f64().unwrap_or(1.0) as f32;
        settings.push((
            "carried_smoothing",
            format!("carried densities smoothed {blend} over {cells} cells"),
        ));
    }
    if let Some(views) = at(config, "refine.views_per_step")
        .as_u64()
        .filter(|&n| n > 0)
    {
        let steps = at(config, "refine.iterations").as_u64().unwrap_or(0);
        let per = if views == 1 { "view" } else { "views" };
        settings.push((
            "refine.views_per_step",
            format!("K' = {steps} of {views} {per} a step"),
        ));
    }
    if let Some(steps) = config["refine_average_steps"].as_u64().filter(|&n| n > 1) {
        settings.push((
            "refine_average_steps",
            format!("mean of the refinement's last {steps} steps"),
        ));
    }
    if let Some(share) = weight("refine_view_agreement") {
        let what = match config["refine_view_agreement_attributes"].as_str() {
            Some("densities") => "densities",
            _ => "refinement",
        };
        settings.push((
            "refine_view_agreement",
            format!("{what} where the views agree ({share})"),
        ));
    }
    if let Some(sigma) = weight("refine_loss_blur") {
        settings.push((
            "refine_loss_blur",
            match config["refine_loss_blur_axes"].as_str() {
                Some("horizontal") => {
                    format!("refinement on residuals blurred by {sigma} px along rows")
                }
                _ => format!("refinement on residuals blurred by {sigma} px"),
            },
        ));
    }
    if let Some(sigma) = weight("joint_loss_blur") {
        settings.push((
            "joint_loss_blur",
            if config["joint_loss_blur_velocity_only"].as_bool() == Some(true) {
                format!("velocity fitted coarse to fine from {sigma} px")
            } else {
                format!("joint iterations coarse to fine from {sigma} px")
            },
        ));
    }
    if let Some(w) = weight("refine.lambda_grid") {
        settings.push(("refine.lambda_grid", format!("grid-scale tie {w}")));
    }
    if let Some(w) = weight("lambda_refine_density") {
        settings.push(("lambda_refine_density", format!("density tie {w}")));
    }
    if let Some(w) = at(config, "joint.inertia.horizontal_weight")
        .as_f64()
        .map(|w| w as f32)
        .filter(|&w| w != 1.0)
    {
        settings.push((
            "joint.inertia.horizontal_weight",
            format!("horizontal increments x{w}"),
        ));
    }
    if let Some(steps) = config["static_iterations"].as_u64() {
        settings.push(("static_iterations", format!("statics fitted {steps} steps")));
    }
    if let Some(depth) = config["static_shell"].as_f64().map(|d| d as f32) {
        settings.push((
            "static_shell",
            format!("statics within {depth} of the surfaces"),
        ));
    }
    let faces = open_faces(record);
    if !faces.is_empty() {
        settings.push(("open_faces", format!("open faces {}", faces.join(" "))));
    }
    if let Some(flow) = scene_value(config, "open_face_flow", "open_face_flow")
        .as_f64()
        .map(|f| f as f32)
        .filter(|&f| f != 1.0)
    {
        settings.push(("open_face_flow", format!("open-face flow {flow}")));
    }
    settings
}

/// Whether the run carried its velocity along itself (`joint.transport_velocity`).
fn transported(record: &Value) -> bool {
    at(&record["config"], "joint.transport_velocity")
        .as_bool()
        .unwrap_or(false)
}

/// The value at a dotted key of a record's configuration (`Null` when absent).
pub(super) fn at<'a>(config: &'a Value, dotted: &str) -> &'a Value {
    dotted.split('.').fold(config, |node, key| &node[key])
}

/// The records of `docs/results`, by key, their configurations read at their current keys
/// (records made before the keys had tables are moved to them).
pub(super) fn read_records(docs: &Path) -> Result<Vec<Value>> {
    let mut records: Vec<Value> = std::fs::read_dir(docs.join("results"))?
        .flatten()
        .filter(|e| e.path().extension().is_some_and(|x| x == "json"))
        .map(|e| -> Result<Value> {
            let mut record: Value = serde_json::from_str(&std::fs::read_to_string(e.path())?)?;
            legacy::upgrade(&mut record["config"]);
            Ok(record)
        })
        .collect::<Result<_>>()?;
    records.sort_by(|a, b| a["key"].as_str().cmp(&b["key"].as_str()));
    Ok(records)
}

/// A scene key of a configuration: under `[scene]`, or (in records made before the scene
/// had its table) at the top level as `old`.
fn scene_value<'a>(config: &'a Value, key: &str, old: &str) -> &'a Value {
    match &config["scene"][key] {
        Value::Null => &config[old],
        value => value,
    }
}

/// The box faces the run left open.
fn open_faces(record: &Value) -> Vec<&str> {
    scene_value(&record["config"], "open_faces", "open_faces")
        .as_array()
        .map(|faces| faces.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default()
}

/// The seed of a record's Gaussians' initialisation.
fn seed_of(record: &Value) -> u64 {
    record["seed"]
        .as_u64()
        .or(record["config"]["seed"].as_u64())
        .unwrap_or(2026)
}

/// A metric summarised over seeds.
struct SeedMetric {
    /// Its name in the records.
    name: &'static str,
    higher_is_better: bool,
    format: fn(f64) -> String,
}

const SEED_METRICS: [SeedMetric; 4] = [
    SeedMetric {
        name: "test_psnr",
        higher_is_better: true,
        format: |v| format!("{v:.2}"),
    },
    SeedMetric {
        name: "velocity_relative_error",
        higher_is_better: false,
        format: |v| format!("{v:.3}"),
    },
    SeedMetric {
        name: "density_relative_error",
        higher_is_better: false,
        format: |v| format!("{v:.3}"),
    },
    SeedMetric {
        name: "mean_abs_divergence",
        higher_is_better: false,
        format: |v| format!("{v:.2e}"),
    },
];

/// A group of runs: the group name they were recorded under, and the settings of ours that
/// set presets apart ([`preset_settings`], not in a preset's keys).
type GroupKey<'a> = (&'a str, Vec<String>);

/// Runs grouped by what they share apart from the seed (records written before groups existed
/// are their own group; runs whose presets differ in [`preset_settings`] are never in one
/// group).
fn seed_groups(records: &[Value]) -> std::collections::BTreeMap<GroupKey<'_>, Vec<&Value>> {
    let mut groups: std::collections::BTreeMap<GroupKey<'_>, Vec<&Value>> = Default::default();
    for r in records {
        let group = r["group"].as_str().or(r["key"].as_str()).unwrap_or("?");
        let settings = preset_settings(r).into_iter().map(|(_, named)| named);
        groups
            .entry((group, settings.collect()))
            .or_default()
            .push(r);
    }
    groups
}

/// For every group of runs that differ only in their seed (two or more), the mean and
/// standard deviation of the held-out metrics; then, for every ablation, its per-seed
/// differences from the full method run with the same seed.
fn write_seed_summary(block: &mut String, records: &[Value]) -> Result<()> {
    let groups = seed_groups(records);
    let repeated: Vec<_> = groups.iter().filter(|(_, runs)| runs.len() >= 2).collect();
    if repeated.is_empty() {
        return Ok(());
    }
    writeln!(
        block,
        "\nAcross seeds (mean +- sample standard deviation over the runs of a group):\n"
    )?;
    writeln!(
        block,
        "| group | variant | seeds | held-out PSNR (dB) | SSIM | velocity rel. error | velocity cosine | density rel. error | density correlation | mean abs div u (1/frame) |"
    )?;
    writeln!(block, "|---|---|---|---:|---:|---:|---:|---:|---:|---:|")?;
    for ((group, _), runs) in &repeated {
        let column = |name: &str, format: fn(f64) -> String| {
            let values: Vec<f64> = runs.iter().filter_map(|r| r[name].as_f64()).collect();
            if values.len() < 2 {
                return "n/a".to_string();
            }
            let (mean, std) = mean_std(&values);
            format!("{} +- {}", format(mean), format(std))
        };
        let seeds: Vec<String> = runs.iter().map(|r| seed_of(r).to_string()).collect();
        writeln!(
            block,
            "| `{group}` | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
            variant(runs[0]),
            seeds.join(", "),
            column("test_psnr", SEED_METRICS[0].format),
            column("test_ssim", |v| format!("{v:.4}")),
            column("velocity_relative_error", SEED_METRICS[1].format),
            column("velocity_cosine", |v| format!("{v:.3}")),
            column("density_relative_error", SEED_METRICS[2].format),
            column("density_correlation", |v| format!("{v:.3}")),
            column("mean_abs_divergence", SEED_METRICS[3].format),
        )?;
    }
    write_paired_ablations(block, &groups)
}

/// Each ablation against the full method with the same seed: the mean +- standard deviation
/// of the per-seed difference (full minus ablation) and in how many seeds the full method
/// is the better of the two. Pairing removes the spread that the initialisation puts into
/// both runs alike.
fn write_paired_ablations(
    block: &mut String,
    groups: &std::collections::BTreeMap<GroupKey<'_>, Vec<&Value>>,
) -> Result<()> {
    let mut rows = Vec::new();
    for ((group, settings), runs) in groups {
        let Some(ablation) = Ablation::KNOWN
            .into_iter()
            .find(|a| group.ends_with(a.suffix()))
        else {
            continue;
        };
        let full_group = &group[..group.len() - ablation.suffix().len()];
        let Some(full_runs) = groups.get(&(full_group, settings.clone())) else {
            continue;
        };
        let pairs: Vec<(&Value, &Value)> = runs
            .iter()
            .filter_map(|r| {
                full_runs
                    .iter()
                    .find(|f| seed_of(f) == seed_of(r))
                    .map(|f| (*f, *r))
            })
            .collect();
        if pairs.len() < 2 {
            continue;
        }
        let mut row = format!(
            "| `{full_group}` | {} | {} |",
            ablation.label(),
            pairs.len()
        );
        for SeedMetric {
            name,
            higher_is_better,
            format,
        } in SEED_METRICS
        {
            let differences: Vec<f64> = pairs
                .iter()
                .filter_map(|(full, ablated)| Some(full[name].as_f64()? - ablated[name].as_f64()?))
                .collect();
            if differences.len() < 2 {
                row += " n/a |";
                continue;
            }
            let (mean, std) = mean_std(&differences);
            let full_better = differences
                .iter()
                .filter(|&&d| if higher_is_better { d > 0.0 } else { d < 0.0 })
                .count();
            row += &format!(
                " {}{} +- {} ({}/{}) |",
                if mean >= 0.0 { "+" } else { "" },
                format(mean),
                format(std),
                full_better,
                differences.len()
            );
        }
        rows.push(row);
    }
    if rows.is_empty() {
        return Ok(());
    }
    writeln!(
        block,
        "\nAblations paired by seed (full method minus ablation, mean +- sample standard deviation \
         over seeds; in brackets, the seeds in which the full method is better: higher PSNR, \
         lower errors and divergence):\n"
    )?;
    writeln!(
        block,
        "| full-method group | ablation | seeds | PSNR (dB) | velocity rel. error | density rel. error | mean abs div u (1/frame) |"
    )?;
    writeln!(block, "|---|---|---:|---:|---:|---:|---:|")?;
    for row in rows {
        writeln!(block, "{row}")?;
    }
    Ok(())
}

/// Rebuilds the generated block of `docs/RESULTS.md` from `docs/results/*.json`.
/// A run is long enough to show drift from this many frames on.
const DRIFT_MIN_FRAMES: usize = 20;
const DRIFT_BLOCK: usize = 10;

/// The held-out PSNR of every long run per 10-frame block, and every sampled frame of the
/// independent baseline (`--independent`) beside the sequential run's result there.
fn write_drift_tables(block: &mut String, records: &[Value]) -> Result<()> {
    let per_frame = |r: &Value| -> Vec<Option<f64>> {
        r["test_psnr_per_frame"]
            .as_array()
            .map(|a| a.iter().map(Value::as_f64).collect())
            .unwrap_or_default()
    };
    let long: Vec<(&Value, Vec<Option<f64>>)> = records
        .iter()
        .map(|r| (r, per_frame(r)))
        .filter(|(_, psnr)| psnr.len() >= DRIFT_MIN_FRAMES)
        .collect();
    if let Some(blocks) = long
        .iter()
        .map(|(_, psnr)| psnr.len().div_ceil(DRIFT_BLOCK))
        .max()
    {
        writeln!(
            block,
            "\nHeld-out PSNR (dB) per block of {DRIFT_BLOCK} frames:\n"
        )?;
        let mut header = "| run |".to_string();
        let mut rule = "|---|".to_string();
        for b in 0..blocks {
            header += &format!(" {}-{} |", b * DRIFT_BLOCK, (b + 1) * DRIFT_BLOCK - 1);
            rule += "---:|";
        }
        writeln!(block, "{header}\n{rule}")?;
        for (r, psnr) in &long {
            let mut row = format!("| `{}` |", r["key"].as_str().unwrap_or("?"));
            for chunk in psnr.chunks(DRIFT_BLOCK) {
                let values: Vec<f64> = chunk.iter().flatten().copied().collect();
                if values.is_empty() {
                    row += " n/a |";
                } else {
                    row += &format!(" {:.2} |", mean_std(&values).0);
                }
            }
            row += &" |".repeat(blocks - psnr.len().div_ceil(DRIFT_BLOCK));
            writeln!(block, "{row}")?;
        }
    }
    let baselines: Vec<(&Value, &Vec<Value>)> = records
        .iter()
        .filter_map(|r| r["independent"].as_array().map(|rows| (r, rows)))
        .filter(|(_, rows)| !rows.is_empty())
        .collect();
    if !baselines.is_empty() {
        writeln!(
            block,
            "\nThe sequential run against each sampled frame fitted on its own (`--independent`; same settings as the run's frame-0 fit): held-out PSNR (dB), and on data with ground truth the 3D density's correlation with the true density:\n"
        )?;
        writeln!(
            block,
            "| run | frame | sequential | frame alone | sequential minus alone | density corr., sequential | density corr., alone |"
        )?;
        writeln!(block, "|---|---:|---:|---:|---:|---:|---:|")?;
        for (r, rows) in baselines {
            for row in rows {
                writeln!(
                    block,
                    "| `{}` | {} | {} | {} | {} | {} | {} |",
                    r["key"].as_str().unwrap_or("?"),
                    row["frame"],
                    number(&row["sequential_test_psnr"], 2),
                    number(&row["test_psnr"], 2),
                    row["sequential_minus_independent_psnr"]
                        .as_f64()
                        .map_or("n/a".into(), |d| format!("{d:+.2}")),
                    number(&row["sequential_density_correlation"], 3),
                    number(&row["density_correlation"], 3),
                )?;
            }
        }
    }
    Ok(())
}

/// Runs on data with obstacles: how much smoke and flow the reconstruction puts into them.
fn write_obstacle_table(block: &mut String, records: &[Value]) -> Result<()> {
    let with: Vec<&Value> = records
        .iter()
        .filter(|r| r["obstacle_density_fraction"].is_number())
        .collect();
    if with.is_empty() {
        return Ok(());
    }
    writeln!(
        block,
        "\nObstacles (runs on data that describes them; means over frames): the share of the \
         reconstructed density inside the obstacles (0 is right), and over the fluid cells \
         within one cell of their surface the RMS velocity along the surface normal relative \
         to RMS speed (0: the flow slides along the surface; 0.58: as if there were no \
         obstacle; 1: straight through):\n"
    )?;
    writeln!(
        block,
        "| run | variant | seed | held-out PSNR (dB) | density inside | normal flow at the surface | velocity rel. error | density correlation |"
    )?;
    writeln!(block, "|---|---|---:|---:|---:|---:|---:|---:|")?;
    for r in with {
        writeln!(
            block,
            "| `{}` | {} | {} | {} | {} | {} | {} | {} |",
            r["key"].as_str().unwrap_or("?"),
            variant(r),
            seed_of(r),
            number(&r["test_psnr"], 2),
            number(&r["obstacle_density_fraction"], 4),
            number(&r["obstacle_normal_flow"], 3),
            number(&r["velocity_relative_error"], 3),
            number(&r["density_correlation"], 3),
        )?;
    }
    Ok(())
}

pub fn write_results_md(docs: &Path) -> Result<()> {
    let records = read_records(docs)?;

    let mut block = String::new();
    writeln!(
        block,
        "Generated by `cargo xtask reproduce` from `docs/results/*.json`; do not edit by hand.\n"
    )?;
    writeln!(
        block,
        "| run | variant | frames | Gaussians | held-out PSNR (dB) | SSIM | LPIPS | mean abs div u (1/frame) | velocity rel. error | density rel. error | training (s) | peak memory (MiB) | state per frame (MiB) | device, machine, date |"
    )?;
    writeln!(
        block,
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"
    )?;
    for r in &records {
        writeln!(
            block,
            "| `{}` | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {}, {}, {} |",
            r["key"].as_str().unwrap_or("?"),
            variant(r),
            r["frames"],
            r["gaussians"],
            number(&r["test_psnr"], 2),
            number(&r["test_ssim"], 4),
            number(&r["test_lpips"], 4),
            r["mean_abs_divergence"]
                .as_f64()
                .map_or("n/a".into(), |v| format!("{v:.2e}")),
            number(&r["velocity_relative_error"], 3),
            number(&r["density_relative_error"], 3),
            number(&r["training_seconds"], 0),
            number(&r["peak_memory_mib"], 0),
            mib(&r["state_bytes_per_frame"]),
            r["device"].as_str().unwrap_or("?"),
            r["machine"].as_str().unwrap_or("?"),
            r["date"].as_str().unwrap_or("?"),
        )?;
    }
    write_seed_summary(&mut block, &records)?;
    write_drift_tables(&mut block, &records)?;
    write_obstacle_table(&mut block, &records)?;
    writeln!(
        block,
        "\nPaper, ScalarFlow real capture (Table 1/2): {PAPER_SCALAR_REAL}.\n"
    )?;
    writeln!(block, "Paper, ablations (Table 3): {PAPER_ABLATIONS}.\n")?;
    writeln!(
        block,
        "Per-phase wall time (s) of each run's optimisation (calls in brackets; nested phases are inside \"backward (all ops)\"):\n"
    )?;
    for r in &records {
        // Records re-evaluated from a finished run by a build that did not keep phase
        // timings across sessions have none.
        let Some(phases) = r["phase_seconds"].as_object().filter(|p| !p.is_empty()) else {
            continue;
        };
        let mut phases: Vec<(&String, &Value)> = phases.iter().collect();
        phases.sort_by(|a, b| {
            b.1["seconds"]
                .as_f64()
                .partial_cmp(&a.1["seconds"].as_f64())
                .unwrap_or(std::cmp::Ordering::Equal)
        });
        let parts: Vec<String> = phases
            .iter()
            .map(|(name, v)| format!("{name} {} ({})", number(&v["seconds"], 1), v["calls"]))
            .collect();
        writeln!(
            block,
            "- `{}`: {}",
            r["key"].as_str().unwrap_or("?"),
            parts.join(", ")
        )?;
    }
    writeln!(block, "\nCommands:\n")?;
    let mut commands: Vec<&str> = records
        .iter()
        .filter_map(|r| r["command"].as_str())
        .collect();
    commands.sort();
    commands.dedup();
    for command in commands {
        writeln!(block, "- `{command}`")?;
    }

    // Every record's row goes to RUNS.md; RESULTS.md holds the summary of the current presets.
    let runs = docs.join("RUNS.md");
    let text = std::fs::read_to_string(&runs).unwrap_or_else(|_| {
        "# Every recorded run\n\n<!-- results:begin -->\n<!-- results:end -->\n".to_string()
    });
    let updated = between_markers(&runs, &text, "results", &block)?;
    write_atomically(&runs, &updated)?;
    eprintln!("wrote {}", runs.display());
    let path = docs.join("RESULTS.md");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|_| {
        "# Results\n\n<!-- summary:begin -->\n<!-- summary:end -->\n".to_string()
    });
    write_atomically(&path, &super::summary::fill(&text, &records)?)?;
    eprintln!("wrote {}", path.display());
    Ok(())
}

/// `text` (the file at `path`) with what lies between its `<!-- NAME:begin -->` and
/// `<!-- NAME:end -->` markers replaced by `block`.
fn between_markers(path: &Path, text: &str, name: &str, block: &str) -> Result<String> {
    let (begin, end) = (
        format!("<!-- {name}:begin -->"),
        format!("<!-- {name}:end -->"),
    );
    let (Some(start), Some(stop)) = (text.find(&begin), text.find(&end)) else {
        bail!(
            "{}: the {begin} / {end} markers are missing",
            path.display()
        );
    };
    Ok(format!(
        "{}{begin}\n{block}{}",
        &text[..start],
        &text[stop..]
    ))
}

/// Writes `contents` to `path` through a temporary file in the same folder and a rename, so
/// that a reader (another `reproduce` rebuilding the tables, say) never sees half a file.
pub(crate) fn write_atomically(path: &Path, contents: &str) -> std::io::Result<()> {
    let name = path
        .file_name()
        .map_or_else(Default::default, |n| n.to_string_lossy());
    let temporary = path.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    std::fs::write(&temporary, contents)?;
    std::fs::rename(&temporary, path)
}

#[cfg(test)]
mod tests;
