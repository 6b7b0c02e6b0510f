//! What a record holds besides the metrics: memory, wall time, machine, date and the command.

use std::ops::Not as _;
use std::path::Path;

use serde_json::{Value, json};

use super::ReproduceArgs;

/// Starts the peak-resident-memory count again (Linux: writing 5 to `/proc/self/clear_refs`
/// resets `VmHWM`), so each variant of one invocation reports its own peak.
pub(super) fn reset_peak_memory() {
    if let Err(e) = std::fs::write("/proc/self/clear_refs", "5") {
        eprintln!("warning: cannot reset the peak memory count ({e}); it includes earlier runs");
    }
}

/// Peak resident memory since the last [`reset_peak_memory`] (Linux `VmHWM`), in MiB.
pub(super) fn peak_memory_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// The record this run folder wrote before, if any (the same key and `run`).
pub(super) fn previous_record(path: &Path, run_dir: &Path) -> Option<Value> {
    let record: Value = serde_json::from_str(&std::fs::read_to_string(path).ok()?).ok()?;
    (record["run"].as_str() == Some(&*run_dir.display().to_string())).then_some(record)
}

/// Wall time and peak memory for a record. This process measured only its own session, so
/// a resumed run adds the earlier sessions from the run's previous record, or records
/// neither (null) where there is none, rather than a session's part as the whole.
pub(super) fn session_totals(
    previous: Option<Value>,
    resumed: bool,
    wall_seconds: f64,
    peak_memory: Option<f64>,
) -> (Value, Value) {
    if !resumed {
        return (json!(wall_seconds), json!(peak_memory));
    }
    let Some(previous) = previous else {
        eprintln!(
            "warning: resumed without this run's earlier record: its wall time and peak \
             memory are recorded as unknown"
        );
        return (Value::Null, Value::Null);
    };
    let wall = previous["wall_seconds_with_outputs"]
        .as_f64()
        .map(|before| before + wall_seconds);
    let peak = previous["peak_memory_mib"]
        .as_f64()
        .zip(peak_memory)
        .map(|(a, b)| a.max(b));
    (json!(wall), json!(peak))
}

/// The CPU, and for GPU devices the NVIDIA adapter and driver where `nvidia-smi` exists.
pub(super) fn machine(device: &str) -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|info| {
            info.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let gpu = ["flex", "ndarray"]
        .contains(&device)
        .not()
        .then(|| {
            std::process::Command::new("nvidia-smi")
                .args(["--query-gpu=name,driver_version", "--format=csv,noheader"])
                .output()
                .ok()
                .filter(|o| o.status.success())
                .and_then(|o| String::from_utf8(o.stdout).ok())
                .and_then(|s| s.lines().next().map(|l| l.trim().to_string()))
        })
        .flatten()
        .map(|line| match line.split_once(", ") {
            Some((name, driver)) => format!("{name} (driver {driver}), "),
            None => format!("{line}, "),
        })
        .unwrap_or_default();
    format!("{gpu}{cpu}, {threads} threads")
}

pub(super) fn utc_now() -> String {
    std::process::Command::new("date")
        .args(["-u", "+%Y-%m-%d %H:%M UTC"])
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|| "unknown date".into())
}

pub(super) fn file_size(path: &Path) -> u64 {
    std::fs::metadata(path).map_or(0, |m| m.len())
}

/// `value` as one POSIX shell word: as is when it holds no character the shell treats
/// specially, else in single quotes.
pub(super) fn shell_quoted(value: &str) -> String {
    let plain = |c: char| c.is_ascii_alphanumeric() || "-_=.,/:+@%".contains(c);
    if !value.is_empty() && value.chars().all(plain) {
        value.to_string()
    } else {
        format!("'{}'", value.replace('\'', r"'\''"))
    }
}

pub(super) fn command_line(args: &ReproduceArgs) -> String {
    let mut line = format!(
        "cargo run --release -p xtask -- reproduce {}",
        args.target.cli_name()
    );
    if args.quick {
        line += " --quick";
    }
    if args.device != "flex" {
        line += &format!(" --device {}", args.device);
    }
    if let Some(frames) = args.frames {
        line += &format!(" --frames {frames}");
    }
    if let Some(seed) = args.seed {
        line += &format!(" --seed {seed}");
    }
    if let Some(fraction) = args.respawn {
        line += &format!(" --respawn {fraction}");
    }
    if let Some(degrees) = args.swirl {
        line += &format!(" --swirl {degrees}");
    }
    if args.paper_update {
        line += " --paper-update";
    }
    for entry in &args.overrides {
        line += &format!(" --set {}", shell_quoted(entry));
    }
    if let Some(tag) = &args.tag {
        line += &format!(" --tag {}", shell_quoted(tag));
    }
    if let Some(key) = &args.config_of {
        line += &format!(" --config-of {}", shell_quoted(key));
    }
    if args.no_ablations {
        line += " --no-ablations";
    }
    if args.velocity_estimate {
        line += " --velocity-estimate";
    }
    if args.velocity_estimate_forces {
        line += " --velocity-estimate-forces";
    }
    if let Some(data) = &args.data {
        line += &format!(" --data {}", shell_quoted(&data.display().to_string()));
    }
    if let Some(weights) = &args.lpips_weights {
        line += &format!(
            " --lpips-weights {}",
            shell_quoted(&weights.display().to_string())
        );
    }
    if !args.independent.is_empty() {
        let frames: Vec<String> = args.independent.iter().map(|t| t.to_string()).collect();
        line += &format!(" --independent {}", frames.join(","));
    }
    line
}
