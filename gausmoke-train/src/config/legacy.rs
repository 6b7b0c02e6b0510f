//! Configurations written before the keys had tables (runs' `config.toml`, records' `config`)
//! still read: each flat key is moved to where it lives now, and the moves are reported.

use serde_json::{Map, Value};

/// Each flat key of the configuration before its tables, and the dotted key it became.
pub const RENAMED_KEYS: &[(&str, &str)] = &[
    ("init_iterations", "init.iterations"),
    ("init_learning_rates", "init.learning_rates"),
    ("lr_velocity", "learning_rates.velocity"),
    ("lr_gaussians", "learning_rates.gaussians"),
    ("lr_log_scales", "learning_rates.log_scales"),
    ("lr_decay", "learning_rates.decay"),
    ("lr_decay_every", "learning_rates.decay_every"),
    ("advect_iterations", "joint.iterations"),
    ("lambda_div", "joint.lambda_div"),
    ("lambda_adv", "joint.lambda_adv"),
    ("transport_velocity", "joint.transport_velocity"),
    ("lambda_lookahead", "joint.look_ahead.weight"),
    ("lambda_increment", "joint.inertia.weight"),
    (
        "increment_horizontal_weight",
        "joint.inertia.horizontal_weight",
    ),
    ("refine_iterations", "refine.iterations"),
    ("lambda_refine", "refine.lambda"),
    ("lambda_refine_grid", "refine.lambda_grid"),
    ("refine_views_per_step", "refine.views_per_step"),
    ("respawn_fraction", "population.recycle.fraction"),
    ("respawn_threshold", "population.recycle.threshold"),
    ("split_fraction", "population.split.fraction"),
    ("projection", "projection.kind"),
    ("projection_tolerance", "projection.tolerance"),
    ("projection_max_iterations", "projection.max_iterations"),
    ("penalty_steps", "projection.penalty_steps"),
    ("obstacles", "projection.obstacles"),
    ("output_every", "output.every"),
    ("log_every", "output.log_every"),
    ("ply_axes", "output.ply_axes"),
    ("tensorboard", "output.tensorboard"),
    ("gradient_sums", "device.gradient_sums"),
    ("tile_list_headroom", "device.tile_list_headroom"),
    ("solver_tests", "device.solver_tests"),
    ("sync_phase_timings", "device.sync_phase_timings"),
];

/// The dotted key a flat key of the older configuration became, if it was renamed.
pub fn renamed(old: &str) -> Option<&'static str> {
    RENAMED_KEYS
        .iter()
        .find(|(flat, _)| *flat == old)
        .map(|(_, dotted)| *dotted)
}

/// What an older key is now, for a message: `` `dotted.key` ``, or the setting that replaced a
/// retired switch.
pub fn replacement(old: &str) -> Option<String> {
    match old {
        "physics_losses" => Some("`joint.lambda_div = 0` with `joint.lambda_adv = 0`".into()),
        "refinement" => Some("`refine.iterations = 0`".into()),
        _ => renamed(old).map(|dotted| format!("`{dotted}`")),
    }
}

/// Moves the older keys of `config` (a configuration as JSON) to their tables: the renamed
/// ones, and the two retired ablation switches as the settings that replaced them
/// (`physics_losses = false`: both physical weights 0; `refinement = false`: no refinement
/// iterations). Returns each older key with what it became, empty for a current
/// configuration.
pub fn upgrade(config: &mut Value) -> Vec<(String, String)> {
    let Some(table) = config.as_object_mut() else {
        return Vec::new();
    };
    // `projection` is a table now and was a string: only the string is the older key.
    let older: Vec<String> = table
        .iter()
        .filter(|(key, value)| {
            (renamed(key).is_some() && !(key.as_str() == "projection" && value.is_object()))
                || matches!(key.as_str(), "physics_losses" | "refinement")
        })
        .map(|(key, _)| key.clone())
        .collect();
    // All out first: `projection` is both an older key and the table others move into.
    let older: Vec<(String, Value)> = older
        .into_iter()
        .map(|key| {
            let value = table.remove(&key).expect("listed above");
            (key, value)
        })
        .collect();
    let mut moves = Vec::new();
    for (key, value) in older {
        match key.as_str() {
            "physics_losses" => {
                if value == Value::Bool(false) {
                    insert(table, "joint.lambda_div", Value::from(0.0));
                    insert(table, "joint.lambda_adv", Value::from(0.0));
                }
                moves.push((key, "joint.lambda_div = joint.lambda_adv = 0".into()));
            }
            "refinement" => {
                if value == Value::Bool(false) {
                    insert(table, "refine.iterations", Value::from(0));
                }
                moves.push((key, "refine.iterations = 0".into()));
            }
            _ => {
                let dotted = renamed(&key).expect("listed above");
                // A retired switch's `false` overrides the iterations it carried.
                if !(dotted == "refine.iterations" && lookup(table, dotted).is_some()) {
                    insert(table, dotted, value);
                }
                moves.push((key, dotted.to_string()));
            }
        }
    }
    moves
}

fn insert(table: &mut Map<String, Value>, dotted: &str, value: Value) {
    let mut node = table;
    let mut parts = dotted.split('.').peekable();
    while let Some(part) = parts.next() {
        if parts.peek().is_none() {
            node.insert(part.to_string(), value);
            return;
        }
        let next = node
            .entry(part.to_string())
            .or_insert_with(|| Value::Object(Map::new()));
        if !next.is_object() {
            *next = Value::Object(Map::new());
        }
        node = next.as_object_mut().expect("made an object above");
    }
}

fn lookup<'a>(table: &'a Map<String, Value>, dotted: &str) -> Option<&'a Value> {
    let (first, rest) = match dotted.split_once('.') {
        Some((first, rest)) => (first, Some(rest)),
        None => (dotted, None),
    };
    let value = table.get(first)?;
    match rest {
        None => Some(value),
        Some(rest) => lookup(value.as_object()?, rest),
    }
}

/// [`upgrade`] on a TOML table.
pub fn upgrade_toml(table: &mut toml::Table) -> Vec<(String, String)> {
    let mut json = serde_json::to_value(&*table).expect("TOML converts to JSON");
    let moves = upgrade(&mut json);
    if !moves.is_empty() {
        *table = serde_json::from_value(json).expect("moved TOML values convert back");
    }
    moves
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::TrainConfig;

    /// An older flat configuration reads as the tables it became, the retired switches as
    /// their replacements.
    #[test]
    fn an_older_flat_configuration_reads_into_the_tables() {
        let mut old = serde_json::json!({
            "gaussians": 500,
            "advect_iterations": 7,
            "lambda_lookahead": 1.0,
            "lambda_increment": 0.01,
            "increment_horizontal_weight": 3.0,
            "respawn_fraction": 0.02,
            "projection": "penalty",
            "penalty_steps": 5,
            "projection_tolerance": 1e-4,
            "output_every": 4,
            "physics_losses": false,
            "refinement": false,
            "refine_iterations": 40,
            "init_learning_rates": {"means": 0.01},
        });
        let moves = upgrade(&mut old);
        assert_eq!(moves.len(), 13);
        let config: TrainConfig = serde_json::from_value(old).unwrap();
        assert_eq!(config.gaussians, 500);
        assert_eq!(config.joint.iterations, 7);
        assert_eq!(config.joint.look_ahead.weight, 1.0);
        assert_eq!(config.joint.inertia.weight, 0.01);
        assert_eq!(config.joint.inertia.horizontal_weight, 3.0);
        assert_eq!(config.population.recycle.fraction, 0.02);
        assert_eq!(
            config.projection.kind,
            crate::config::ProjectionKind::Penalty
        );
        assert_eq!(config.output.every, 4);
        assert_eq!(
            (config.joint.lambda_div, config.joint.lambda_adv),
            (0.0, 0.0)
        );
        assert_eq!(config.refine.iterations, 0);
        assert_eq!(config.init.learning_rates.means, 0.01);
        // A current configuration is left as it is.
        let mut current = serde_json::to_value(&config).unwrap();
        assert!(upgrade(&mut current).is_empty());
    }

    /// A run folder's `config.toml` written before the tables resumes: read from its file, its
    /// keys land in their tables; and `--set` with an older name says what it is now.
    #[test]
    fn an_older_config_file_reads_and_an_older_set_says_the_new_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("config.toml");
        std::fs::write(
            &path,
            "gaussians = 300\nadvect_iterations = 4\nprojection = \"exact\"\n\
             [init_learning_rates]\nmeans = 0.002\n[scene]\nopen_faces = [\"y+\"]\n",
        )
        .unwrap();
        let config = TrainConfig::from_toml_file(&path).unwrap();
        assert_eq!(
            (config.gaussians, config.joint.iterations),
            (300, 4),
            "{config:?}"
        );
        assert_eq!(config.init.learning_rates.means, 0.002);
        assert_eq!(config.scene.open_faces, Some(vec!["y+".to_string()]));
        let err = TrainConfig::default()
            .with_overrides(&["advect_iterations=3".into()])
            .unwrap_err()
            .to_string();
        assert!(err.contains("is now `joint.iterations`"), "{err}");
        let err = TrainConfig::default()
            .with_overrides(&["physics_losses=false".into()])
            .unwrap_err()
            .to_string();
        assert!(err.contains("joint.lambda_div = 0"), "{err}");
    }
}
