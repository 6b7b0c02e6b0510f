//! `compare`: a variant's records against a control's, paired by seed (issue 18's yardstick).
//!
//! Reads `docs/results/<key>-s<seed>.json` for both keys and prints, per seed and as the mean
//! and sample standard deviation over the seeds: the held-out PSNR's difference over the
//! video and per block of frames, the 3D density's correlation and the velocity's relative
//! error against the ground truth where the records have them, and each sampled frame's
//! margin over the frame fitted alone (the records' `independent` fits), with the count of
//! cases at or above the margin issue 18 asks for. A variant that changes the frame-0 fit
//! (another Gaussian count or view size) changes that yardstick too: `--own-alone` scores it
//! against its own.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;
use serde_json::Value;

#[derive(Debug, Args)]
pub struct CompareArgs {
    /// The control's record key without its seed, e.g. `synthetic-long-quick-ref40-grid3-views1-hw3-flow05`.
    #[arg(long)]
    base: String,
    /// The variant's record key without its seed.
    #[arg(long)]
    variant: String,
    /// The seeds to pair, e.g. `1,2,3`.
    #[arg(long, value_delimiter = ',', required = true)]
    seeds: Vec<u64>,
    /// Record keys (without their seeds) to take the frames fitted alone from, where the
    /// control's own records have none: for each seed, the first of them that has a record
    /// with such fits.
    #[arg(long, value_delimiter = ',')]
    alone: Vec<String>,
    /// Score the variant against the frames fitted alone in its own records, for a variant
    /// whose frame-0 fit differs from the control's (another Gaussian count or view size), so
    /// whose yardstick differs too; the control keeps its own, or `--alone`'s.
    #[arg(long)]
    own_alone: bool,
    /// Frames per block of the per-block differences.
    #[arg(long, default_value_t = 12)]
    block: usize,
    /// The margin over the frame fitted alone, in dB, that counts a sampled frame as met.
    #[arg(long, default_value_t = 1.0)]
    margin: f64,
    /// The folder that holds `results/` (default: the workspace's `docs`).
    #[arg(long)]
    docs: Option<PathBuf>,
}

pub fn run(args: CompareArgs) -> Result<()> {
    if args.block == 0 {
        bail!("--block must be at least 1 frame");
    }
    let docs = args
        .docs
        .clone()
        .unwrap_or_else(|| crate::workspace_root().join("docs"));
    let pairs = args
        .seeds
        .iter()
        .map(|&seed| read_pair(&docs, &args, seed))
        .collect::<Result<Vec<_>>>()?;
    print!("{}", report(&args.base, &args.variant, &pairs, args.margin));
    Ok(())
}

/// Seed `seed`'s control and variant, scored against the frames fitted alone in the control's
/// record or else in the first of `--alone` that has them; with `--own-alone`, the variant
/// against its own record's.
fn read_pair(docs: &Path, args: &CompareArgs, seed: u64) -> Result<Pair> {
    let base = read_record(docs, &args.base, seed)?;
    let variant = read_record(docs, &args.variant, seed)?;
    let mut alone = frames_alone(&base);
    for key in &args.alone {
        if !alone.is_empty() {
            break;
        }
        if record_path(docs, key, seed).exists() {
            alone = frames_alone(&read_record(docs, key, seed)?);
        }
    }
    let own = args.own_alone.then(|| frames_alone(&variant));
    if own.as_ref().is_some_and(Vec::is_empty) {
        bail!(
            "--own-alone: {} has no frames fitted alone (train it with --independent)",
            record_path(docs, &args.variant, seed).display()
        );
    }
    let variant_alone = own.as_deref().unwrap_or(&alone);
    Pair::of(seed, &base, &variant, [&alone, variant_alone], args.block)
}

fn record_path(docs: &Path, key: &str, seed: u64) -> PathBuf {
    docs.join("results").join(format!("{key}-s{seed}.json"))
}

fn read_record(docs: &Path, key: &str, seed: u64) -> Result<Value> {
    let path = record_path(docs, key, seed);
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

/// The held-out PSNR of each frame fitted alone in `record`, by frame.
fn frames_alone(record: &Value) -> Vec<(usize, f64)> {
    record["independent"]
        .as_array()
        .map(|fits| {
            fits.iter()
                .filter_map(|fit| {
                    Some((fit["frame"].as_u64()? as usize, fit["test_psnr"].as_f64()?))
                })
                .collect()
        })
        .unwrap_or_default()
}

fn per_frame(record: &Value, key: &str) -> Vec<f64> {
    record[key]
        .as_array()
        .map(|values| values.iter().filter_map(Value::as_f64).collect())
        .unwrap_or_default()
}

/// One seed's control and variant side by side.
#[derive(Debug, Clone, PartialEq)]
struct Pair {
    seed: u64,
    psnr: [f64; 2],
    density: Option<[f64; 2]>,
    velocity_error: Option<[f64; 2]>,
    /// The variant's mean per-frame PSNR minus the control's, per block of frames.
    blocks: Vec<f64>,
    /// Sampled frames (after frame 0): the frame, and each run's PSNR minus the frame fitted
    /// alone.
    over_alone: Vec<(usize, [f64; 2])>,
}

impl Pair {
    fn of(
        seed: u64,
        base: &Value,
        variant: &Value,
        alone: [&[(usize, f64)]; 2],
        block: usize,
    ) -> Result<Self> {
        let both = |key: &str| Some([base[key].as_f64()?, variant[key].as_f64()?]);
        let psnr =
            both("test_psnr").with_context(|| format!("seed {seed}: a record has no test_psnr"))?;
        let (b, v) = (
            per_frame(base, "test_psnr_per_frame"),
            per_frame(variant, "test_psnr_per_frame"),
        );
        if b.len() != v.len() {
            bail!(
                "seed {seed}: the records have {} and {} frames; pair runs of one length",
                b.len(),
                v.len()
            );
        }
        let blocks = b
            .chunks(block)
            .zip(v.chunks(block))
            .map(|(b, v)| mean(v) - mean(b))
            .collect();
        // The frames both yardsticks have.
        let over_alone = alone[0]
            .iter()
            .filter(|&&(frame, _)| frame > 0 && frame < b.len())
            .filter_map(|&(frame, control)| {
                let (_, variant) = alone[1].iter().find(|(f, _)| *f == frame)?;
                Some((frame, [b[frame] - control, v[frame] - variant]))
            })
            .collect();
        Ok(Self {
            seed,
            psnr,
            density: both("density_correlation"),
            velocity_error: both("velocity_relative_error"),
            blocks,
            over_alone,
        })
    }
}

fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len().max(1) as f64
}

/// The mean, the sample standard deviation (0 for one value) and how many are positive.
fn summary(values: &[f64]) -> (f64, f64, usize) {
    let m = mean(values);
    let sd = if values.len() > 1 {
        let square: f64 = values.iter().map(|v| (v - m).powi(2)).sum();
        (square / (values.len() - 1) as f64).sqrt()
    } else {
        0.0
    };
    (m, sd, values.iter().filter(|&&v| v > 0.0).count())
}

fn signed(values: &[f64], digits: usize) -> String {
    values
        .iter()
        .map(|v| format!("{v:+.digits$}"))
        .collect::<Vec<_>>()
        .join(" ")
}

fn report(base: &str, variant: &str, pairs: &[Pair], margin: f64) -> String {
    let mut out = format!("{variant} against {base}, paired by seed\n");
    for p in pairs {
        out += &format!(
            "seed {}: {:.2} -> {:.2} dB ({:+.2})",
            p.seed,
            p.psnr[0],
            p.psnr[1],
            p.psnr[1] - p.psnr[0]
        );
        if let Some([b, v]) = p.density {
            out += &format!("; density correlation {:+.4}", v - b);
        }
        if let Some([b, v]) = p.velocity_error {
            out += &format!("; velocity error {:+.4}", v - b);
        }
        out += &format!("\n  per block: {}\n", signed(&p.blocks, 2));
        if p.over_alone.is_empty() {
            out += "  no frames fitted alone to score against (see --alone)\n";
        } else {
            let cases: Vec<String> = p
                .over_alone
                .iter()
                .map(|(frame, [b, v])| format!("{frame}: {b:+.2} / {v:+.2}"))
                .collect();
            out += &format!(
                "  over the frame fitted alone (control / variant): {}\n",
                cases.join(", ")
            );
        }
    }
    let line = |name: &str, values: Vec<f64>, digits: usize| {
        let (m, sd, positive) = summary(&values);
        format!(
            "{name}: {m:+.digits$} +- {sd:.digits$} (positive in {positive} of {})\n",
            values.len()
        )
    };
    out += &line(
        "held-out PSNR (dB)",
        pairs.iter().map(|p| p.psnr[1] - p.psnr[0]).collect(),
        2,
    );
    let blocks = pairs.iter().map(|p| p.blocks.len()).min().unwrap_or(0);
    for k in 0..blocks {
        out += &line(
            &format!("  block {}", k + 1),
            pairs.iter().map(|p| p.blocks[k]).collect(),
            2,
        );
    }
    // Against the ground truth: only where every seed's records have it.
    type Truth = fn(&Pair) -> Option<[f64; 2]>;
    let truth: [(&str, Truth); 2] = [
        ("density correlation", |p| p.density),
        ("velocity error", |p| p.velocity_error),
    ];
    for (name, of) in truth {
        let differences: Option<Vec<f64>> =
            pairs.iter().map(|p| of(p).map(|[b, v]| v - b)).collect();
        if let Some(differences) = differences {
            out += &line(name, differences, 4);
        }
    }
    let cases: Vec<[f64; 2]> = pairs
        .iter()
        .flat_map(|p| p.over_alone.iter().map(|c| c.1))
        .collect();
    if !cases.is_empty() {
        let met = |i: usize| cases.iter().filter(|c| c[i] >= margin).count();
        out += &format!(
            "sampled frames at least {margin} dB above the frame fitted alone: control {} of {n}, variant {} of {n}\n",
            met(0),
            met(1),
            n = cases.len()
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn record(psnr: &[f64], density: f64) -> Value {
        json!({
            "test_psnr": mean(psnr),
            "test_psnr_per_frame": psnr,
            "density_correlation": density,
            "independent": [{"frame": 0, "test_psnr": 50.0}, {"frame": 2, "test_psnr": 40.0}],
        })
    }

    #[test]
    fn a_pair_holds_the_differences_per_block_and_over_the_frames_alone() {
        let base = record(&[50.0, 44.0, 41.0, 40.0], 0.9);
        let variant = record(&[50.0, 46.0, 40.0, 42.0], 0.95);
        let alone = frames_alone(&base);
        let pair = Pair::of(3, &base, &variant, [&alone, &alone], 2).unwrap();
        assert_eq!(pair.blocks, [1.0, 0.5]);
        // Frame 0 is the frame-0 fit in both: it is not a case.
        assert_eq!(pair.over_alone, [(2, [1.0, 0.0])]);
        assert_eq!(pair.density, Some([0.9, 0.95]));
        assert_eq!(pair.velocity_error, None);
        let text = report("b", "v", &[pair], 1.0);
        assert!(text.contains("control 1 of 1, variant 0 of 1"), "{text}");
        assert!(text.contains("density correlation: +0.0500"), "{text}");
        assert!(!text.contains("velocity error"), "{text}");
    }

    #[test]
    fn the_frames_alone_come_from_the_first_alone_key_that_has_them_or_the_variants_own() {
        let docs = tempfile::tempdir().unwrap();
        std::fs::create_dir(docs.path().join("results")).unwrap();
        let write = |key: &str, value: Value| {
            let path = record_path(docs.path(), key, 1);
            std::fs::write(path, value.to_string()).unwrap();
        };
        let mut plain = record(&[50.0, 44.0, 41.0], 0.9);
        plain["independent"] = json!([]);
        write("base", plain.clone());
        write("variant", plain.clone());
        write("empty", plain);
        let mut fits = record(&[50.0, 44.0, 41.0], 0.9);
        fits["independent"] = json!([{"frame": 1, "test_psnr": 43.0}]);
        write("fits", fits);
        let args = |alone: &[&str]| CompareArgs {
            base: "base".into(),
            variant: "variant".into(),
            seeds: vec![1],
            alone: alone.iter().map(|k| k.to_string()).collect(),
            own_alone: false,
            block: 12,
            margin: 1.0,
            docs: None,
        };
        let pair = read_pair(docs.path(), &args(&["missing", "empty", "fits"]), 1).unwrap();
        assert_eq!(pair.over_alone, [(1, [1.0, 1.0])]);
        let pair = read_pair(docs.path(), &args(&[]), 1).unwrap();
        assert!(pair.over_alone.is_empty());
        let err = read_pair(
            docs.path(),
            &CompareArgs {
                seeds: vec![2],
                ..args(&[])
            },
            2,
        );
        assert!(format!("{:#}", err.unwrap_err()).contains("base-s2.json"));

        // A variant with a yardstick of its own (another Gaussian count) is scored against it;
        // one without is refused, by its record's path.
        let mut own = record(&[50.0, 46.0, 44.0], 0.95);
        own["independent"] =
            json!([{"frame": 1, "test_psnr": 44.5}, {"frame": 2, "test_psnr": 40.0}]);
        write("own", own);
        let with_own = |variant: &str| CompareArgs {
            variant: variant.into(),
            own_alone: true,
            ..args(&["fits"])
        };
        let pair = read_pair(docs.path(), &with_own("own"), 1).unwrap();
        assert_eq!(pair.over_alone, [(1, [1.0, 1.5])]);
        let err = read_pair(docs.path(), &with_own("variant"), 1).unwrap_err();
        assert!(err.to_string().contains("variant-s1.json"), "{err}");
    }

    #[test]
    fn runs_of_different_lengths_are_refused() {
        let base = record(&[50.0, 44.0, 41.0], 0.9);
        let variant = record(&[50.0, 44.0], 0.9);
        let err = Pair::of(1, &base, &variant, [&[], &[]], 12).unwrap_err();
        assert!(err.to_string().contains("3 and 2 frames"), "{err}");
    }

    #[test]
    fn the_summary_is_the_mean_the_sample_deviation_and_the_positive_count() {
        let (m, sd, positive) = summary(&[1.0, -1.0, 3.0]);
        assert!((m - 1.0).abs() < 1e-12);
        assert!((sd - 2.0).abs() < 1e-12);
        assert_eq!(positive, 2);
        assert_eq!(summary(&[0.5]), (0.5, 0.0, 1));
    }
}
