//! An up-front estimate of a run's peak memory, so that a configuration too large for the
//! machine is refused naming the settings that drive it, before any frame is decoded or any
//! Gaussian allocated, instead of aborting in the allocator minutes later.
//!
//! The coefficients are peak resident sizes measured on the CPU backend (flex) by varying one
//! setting at a time on the tiny synthetic scene and checked on ScalarReal (see
//! `docs/BENCHMARKS.md`, "Memory estimate"); each part is rounded up, and the parts add,
//! which over-estimates slightly since they do not all peak at once.

use gausmoke_data::{PlannedView, Split};

use crate::{TrainConfig, TrainError};

/// Resident size of the process before any data or state (code, allocator, thread stacks).
const BASE_BYTES: f64 = 32e6;
/// Per loaded picture pixel: RGB as f32.
const PICTURE_BYTES_PER_PIXEL: f64 = 12.0;
/// Per training-view pixel: rendered images, transmittance and per-pixel backward state.
const RENDER_BYTES_PER_PIXEL_AND_VIEW: f64 = 120.0;
/// Per Gaussian: parameters, gradients, Adam moments, projected splats and tile lists.
const BYTES_PER_GAUSSIAN: f64 = 1200.0;
/// Per grid cell: velocity, density, divergence and projection arrays.
const GRID_BYTES_PER_CELL: f64 = 410.0;
/// Per grid cell and U-Net channel: activations kept for the backward, and their gradients.
const UNET_BYTES_PER_CELL_AND_CHANNEL: f64 = 87.0;

/// One part of the estimate and the settings that drive it.
#[derive(Debug, Clone, PartialEq)]
pub struct MemoryPart {
    pub what: &'static str,
    pub bytes: f64,
    /// The settings to lower to shrink this part, with their values.
    pub settings: String,
}

/// The estimated peak memory of a run, by part.
#[derive(Debug, Clone, PartialEq)]
pub struct MemoryEstimate {
    pub parts: Vec<MemoryPart>,
}

impl MemoryEstimate {
    /// The estimate for training `config` on the views `plan` describes (see
    /// [`crate::sequence::Sequence::plan`]). With `state_on_host` false (a GPU backend) only
    /// the loaded pictures count: the training state lives in device memory.
    pub fn new(config: &TrainConfig, plan: &[PlannedView], state_on_host: bool) -> Self {
        let chosen = |names: &Option<Vec<String>>, split: Split| -> Vec<&PlannedView> {
            plan.iter()
                .filter(|view| match names {
                    Some(names) => names.contains(&view.name),
                    None => view.split == split,
                })
                .collect()
        };
        let train = chosen(&config.train_views, Split::Train);
        let mut test = chosen(&config.test_views, Split::Test);
        if config.test_views.is_none() && test.is_empty() {
            test = chosen(&None, Split::Val);
        }
        let pixels = |view: &PlannedView| f64::from(view.width) * f64::from(view.height);
        let pictures: f64 = train
            .iter()
            .chain(&test)
            .map(|view| pixels(view) * view.frames as f64)
            .sum();
        let (width, height) = train
            .first()
            .map_or((0, 0), |view| (view.width, view.height));
        let size = format!("image_size = [{width}, {height}]");
        let mut parts = vec![
            MemoryPart {
                what: "process",
                bytes: BASE_BYTES,
                settings: String::new(),
            },
            MemoryPart {
                what: "loaded pictures",
                bytes: pictures * PICTURE_BYTES_PER_PIXEL,
                settings: format!(
                    "{size}, frames = {}, {} views",
                    train.iter().map(|v| v.frames).max().unwrap_or(0),
                    train.len() + test.len()
                ),
            },
        ];
        if state_on_host {
            let cells = (config.grid_resolution as f64).powi(3);
            let train_pixels: f64 = train.iter().map(|view| pixels(view)).sum();
            parts.extend([
                MemoryPart {
                    what: "rendering",
                    bytes: train_pixels * RENDER_BYTES_PER_PIXEL_AND_VIEW,
                    settings: format!("{size}, {} training views", train.len()),
                },
                MemoryPart {
                    what: "Gaussians",
                    // The static ones are rendered, optimised and kept as the smoke's are.
                    bytes: (config.gaussians as f64 + config.static_gaussians as f64)
                        * BYTES_PER_GAUSSIAN,
                    settings: format!(
                        "gaussians = {}, static_gaussians = {}",
                        config.gaussians, config.static_gaussians
                    ),
                },
                MemoryPart {
                    what: "velocity grid and U-Net",
                    bytes: cells
                        * (GRID_BYTES_PER_CELL
                            + config.unet_channels as f64 * UNET_BYTES_PER_CELL_AND_CHANNEL),
                    settings: format!(
                        "grid_resolution = {}, unet_channels = {}",
                        config.grid_resolution, config.unet_channels
                    ),
                },
            ]);
        }
        Self { parts }
    }

    pub fn total(&self) -> f64 {
        self.parts.iter().map(|part| part.bytes).sum()
    }

    /// Refuses an estimate above `limit` bytes, listing the largest parts and their settings.
    /// `limit_origin` says where the limit comes from.
    pub fn check(&self, limit: u64, limit_origin: &str) -> Result<(), TrainError> {
        let total = self.total();
        if total <= limit as f64 {
            return Ok(());
        }
        let mut parts: Vec<&MemoryPart> = self
            .parts
            .iter()
            .filter(|part| !part.settings.is_empty())
            .collect();
        parts.sort_by(|a, b| b.bytes.total_cmp(&a.bytes));
        let listed: Vec<String> = parts
            .iter()
            .take(3)
            .map(|part| {
                format!(
                    "{} {} ({})",
                    part.what,
                    format_bytes(part.bytes),
                    part.settings
                )
            })
            .collect();
        Err(TrainError::Config {
            origin: "memory".into(),
            reason: format!(
                "this configuration needs about {} at its peak, more than the {} {limit_origin}; \
                 the largest parts: {}. Lower those settings, or raise the limit with \
                 --max-memory if the machine has the memory",
                format_bytes(total),
                format_bytes(limit as f64),
                listed.join("; ")
            ),
        })
    }
}

/// `bytes` as GiB or MiB with one decimal.
pub fn format_bytes(bytes: f64) -> String {
    const GIB: f64 = 1024.0 * 1024.0 * 1024.0;
    if bytes >= GIB / 10.0 {
        format!("{:.1} GiB", bytes / GIB)
    } else {
        format!("{:.1} MiB", bytes / (1024.0 * 1024.0))
    }
}

/// Memory the system can give a new process without swapping (Linux's `MemAvailable`), or
/// `None` where that is not known.
pub fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text
        .lines()
        .find(|line| line.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// Parses a size such as `24G`, `512M`, `1.5GiB` or a plain number of bytes.
pub fn parse_size(text: &str) -> Result<u64, String> {
    let trimmed = text.trim();
    let split = trimmed
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(trimmed.len());
    let (number, unit) = trimmed.split_at(split);
    let value: f64 = number
        .parse()
        .map_err(|_| format!("`{text}` is not a size such as 24G or 512M"))?;
    let scale = match unit.trim().to_ascii_uppercase().as_str() {
        "" | "B" => 1.0,
        "K" | "KB" | "KIB" => 1024.0,
        "M" | "MB" | "MIB" => 1024.0 * 1024.0,
        "G" | "GB" | "GIB" => 1024.0 * 1024.0 * 1024.0,
        "T" | "TB" | "TIB" => 1024.0 * 1024.0 * 1024.0 * 1024.0,
        other => {
            return Err(format!(
                "unknown unit `{other}` in `{text}`: use K, M, G or T"
            ));
        }
    };
    let bytes = value * scale;
    if !bytes.is_finite() || bytes < 1.0 {
        return Err(format!("`{text}` is not a positive size"));
    }
    Ok(bytes as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn view(name: &str, split: Split) -> PlannedView {
        PlannedView {
            name: name.into(),
            split,
            frames: 120,
            width: 270,
            height: 480,
        }
    }

    #[test]
    fn sizes_parse_with_and_without_units() {
        assert_eq!(parse_size("24G").unwrap(), 24 << 30);
        assert_eq!(parse_size("512 MiB").unwrap(), 512 << 20);
        assert_eq!(parse_size("1000").unwrap(), 1000);
        assert!(parse_size("lots").is_err());
        assert!(parse_size("0").is_err());
        assert!(parse_size("3X").unwrap_err().contains("unknown unit"));
    }

    #[test]
    fn the_largest_part_is_named_with_its_setting() {
        let plan: Vec<PlannedView> = (0..4)
            .map(|i| view(&format!("train{i}"), Split::Train))
            .chain([view("test", Split::Test)])
            .collect();
        let config = TrainConfig::default();
        let paper = MemoryEstimate::new(&config, &plan, true);
        assert!(
            paper.total() < 2e9,
            "the paper's configuration fits: {}",
            format_bytes(paper.total())
        );
        paper.check(4 << 30, "allowed").unwrap();
        let huge = TrainConfig {
            gaussians: 100_000_000,
            ..config.clone()
        };
        let err = MemoryEstimate::new(&huge, &plan, true)
            .check(24 << 30, "available")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("Gaussians 111.8 GiB (gaussians = 100000000, static_gaussians = 0)"),
            "{err}"
        );
        // Static Gaussians count as the smoke's do.
        let statics = TrainConfig {
            static_gaussians: 100_000_000,
            ..config.clone()
        };
        let err = MemoryEstimate::new(&statics, &plan, true)
            .check(24 << 30, "available")
            .unwrap_err()
            .to_string();
        assert!(err.contains("static_gaussians = 100000000"), "{err}");
        let grid = TrainConfig {
            grid_resolution: 512,
            ..config.clone()
        };
        let err = MemoryEstimate::new(&grid, &plan, true)
            .check(24 << 30, "available")
            .unwrap_err()
            .to_string();
        assert!(err.contains("grid_resolution = 512"), "{err}");
        // On a GPU backend the state is not host memory: only the pictures count.
        assert!(MemoryEstimate::new(&huge, &plan, false).total() < 1e9);
    }
}
