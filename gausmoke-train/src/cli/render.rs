//! `render`: videos of a trained reconstruction from new viewpoints, or the procedural plume.

use super::*;

#[derive(Debug, Args)]
pub(super) struct RenderArgs {
    /// A run folder written by `train`: render its reconstruction. Without it, a procedural
    /// plume is rendered once (a check of the build and the renderer).
    #[arg(long)]
    pub(super) run: Option<PathBuf>,
    /// Cameras: N steps of an orbit around the smoke box (the default, with 120 steps).
    #[arg(long, value_name = "N", conflicts_with_all = ["views", "cameras"], requires = "run")]
    pub(super) orbit: Option<usize>,
    /// Cameras: every train and held-out view of the run's data set, one video each.
    #[arg(long, conflicts_with = "cameras", requires = "run")]
    pub(super) views: bool,
    /// Cameras: a camera-path JSON, NeRF-style (camera_angle_x, w, h,
    /// frames[].transform_matrix camera-to-world, OpenGL axes) or nerfstudio's
    /// camera_path.json (what ns-render reads).
    #[arg(long, value_name = "FILE", requires = "run")]
    pub(super) cameras: Option<PathBuf>,
    /// Time frames to show: `T`, `A-B` or `A..=B` (both ends), `A:B` or `A..B` (B excluded);
    /// default all finished frames.
    #[arg(long, value_name = "RANGE", requires = "run")]
    pub(super) frames: Option<String>,
    /// Picture size WIDTHxHEIGHT, each side 1 to 8192 (orbit: default the held-out
    /// camera's shape at 720 pixels on its long side; demo: 270x480).
    #[arg(long, value_name = "WxH")]
    pub(super) size: Option<String>,
    /// Pictures per second of the videos, 1 to 240.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=240), requires = "run")]
    pub(super) fps: u32,
    /// Also write every picture as a PNG.
    #[arg(long, requires = "run")]
    pub(super) png: bool,
    /// Output folder (default: RUN/render, or out/demo for the procedural plume). One that
    /// holds an earlier render is refused unless --overwrite is given.
    #[arg(long)]
    pub(super) out: Option<PathBuf>,
    /// Replace the render already in the output folder.
    #[arg(long, requires = "run")]
    pub(super) overwrite: bool,
    #[arg(long, default_value = "flex", value_parser = compiled_device, help = device_help())]
    pub(super) device: String,
    /// Procedural plume only: number of Gaussians.
    #[arg(long, default_value_t = 30_000, conflicts_with = "run")]
    pub(super) gaussians: usize,
    /// Hide the progress bar.
    #[arg(long)]
    pub(super) quiet: bool,
}
/// The largest side `--size` accepts: beyond what H.264 encoders and players take.
const MAX_SIDE: u32 = 8192;

/// `--size WIDTHxHEIGHT`, as everywhere on the command line.
pub(super) fn parse_size(text: &str) -> Result<[u32; 2]> {
    let parsed = text.split_once('x').and_then(|(w, h)| {
        let (w, h) = (w.trim().parse::<u32>().ok()?, h.trim().parse::<u32>().ok()?);
        (w > 0 && h > 0).then_some([w, h])
    });
    let [w, h] =
        parsed.with_context(|| format!("--size `{text}`: expected WIDTHxHEIGHT, e.g. 480x270"))?;
    if w.max(h) > MAX_SIDE {
        bail!("--size `{text}`: at most {MAX_SIDE} pixels a side");
    }
    Ok([w, h])
}

/// Refuses an output folder that holds an earlier render (unless `overwrite`), or that is a
/// data set or a run folder itself, whose files a render would mix with.
fn check_render_out(out: &Path, overwrite: bool) -> Result<()> {
    let holds = |name: &str| out.join(name).exists();
    if ["info.json", "transforms.json", "transforms_train.json"]
        .iter()
        .any(|name| holds(name))
    {
        bail!(
            "--out {}: this is a data set's folder; render into a folder of its own",
            out.display()
        );
    }
    if holds("run.json") {
        bail!(
            "--out {}: this is a run folder; render into a folder of its own (the default is \
             RUN/render)",
            out.display()
        );
    }
    if holds("render.json") && !overwrite {
        bail!(
            "--out {} holds an earlier render (render.json); pass --overwrite to replace it, or \
             choose another --out",
            out.display()
        );
    }
    Ok(())
}

/// `--frames T`, `A-B` or `A..=B` (both ends shown), `A:B` or `A..B` (B excluded, as Python
/// and Rust slice), as a half-open range.
pub(super) fn parse_frames(text: &str) -> Result<std::ops::Range<usize>> {
    let number = |s: &str| {
        s.trim()
            .parse::<usize>()
            .with_context(|| format!("--frames `{text}`: `{s}` is not a frame number"))
    };
    let inclusive = text.split_once("..=").or_else(|| text.split_once('-'));
    let exclusive = text.split_once("..").or_else(|| text.split_once(':'));
    let range = match (inclusive, exclusive) {
        (Some((a, b)), _) => number(a)?..number(b)? + 1,
        (None, Some((a, b))) => number(a)?..number(b)?,
        (None, None) => {
            let t = number(text)?;
            t..t + 1
        }
    };
    if range.is_empty() {
        bail!("--frames `{text}` is empty");
    }
    Ok(range)
}

/// `render --run DIR`: videos of a trained reconstruction.
pub(super) fn render_trained(run: &Path, args: RenderArgs) -> Result<()> {
    use gausmoke_train::novel_views::{CameraPath, RenderRequest, render_run};
    let device = backends::device_by_name(&args.device).map_err(anyhow::Error::msg)?;
    let cameras = if args.views {
        CameraPath::DatasetViews
    } else if let Some(file) = args.cameras {
        CameraPath::File(file)
    } else {
        CameraPath::Orbit {
            steps: args.orbit.unwrap_or(120),
        }
    };
    let request = RenderRequest {
        cameras,
        frames: args.frames.as_deref().map(parse_frames).transpose()?,
        size: args.size.as_deref().map(parse_size).transpose()?,
        fps: args.fps,
        png: args.png,
        progress: !args.quiet,
    };
    let out = args.out.unwrap_or_else(|| run.join("render"));
    check_render_out(&out, args.overwrite)?;
    let start = Instant::now();
    let summary = render_run(run, &out, &request, &device)?;
    for video in &summary.videos {
        println!(
            "{}: {} pictures -> {}",
            video.name,
            video.pictures,
            video.video.display()
        );
    }
    println!("grid slices -> {}", summary.slices_video.display());
    println!(
        "rendered in {:.1} s; list of pictures: {}",
        start.elapsed().as_secs_f64(),
        out.join("render.json").display()
    );
    Ok(())
}

/// Renders the procedural plume from the front and writes render.png and alpha.png.
pub(super) fn render_demo(args: RenderArgs) -> Result<()> {
    let [width, height] = match args.size.as_deref() {
        Some(text) => parse_size(text)?,
        None => [270, 480],
    };
    let out_dir = args.out.unwrap_or_else(|| PathBuf::from("out/demo"));
    let device = backends::device_by_name(&args.device).map_err(anyhow::Error::msg)?;
    tracing::info!(device = %args.device, "rendering on");
    let lo = Vec3::new(-0.25, 0.0, -0.25);
    let hi = Vec3::new(0.25, 0.8, 0.25);
    let gaussians = procedural::smoke_plume(args.gaussians, lo, hi, 2026);
    let camera = Camera::look_at(
        Vec3::new(0.0, 0.4, 2.2),
        Vec3::new(0.0, 0.4, 0.0),
        Vec3::Y,
        width,
        height,
        0.45,
    )
    .context("building the demo camera")?;
    let tensors = gaussians.to_tensors(&device)?;
    let background = Tensor::<1>::from_data(TensorData::new(vec![0.0f32; 3], [3]), &device);
    let start = Instant::now();
    let out = render_volume(&tensors, &camera, &background, &RasterOptions::default())?;
    let rgb = gausmoke_render::device_traffic::read_floats(out.rgb);
    let transmittance = gausmoke_render::device_traffic::read_floats(out.transmittance);
    let elapsed = start.elapsed();
    std::fs::create_dir_all(&out_dir)
        .with_context(|| format!("creating output directory {}", out_dir.display()))?;
    let (w, h) = (width, height);
    let to_u8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let rgb_path = out_dir.join("render.png");
    image::RgbImage::from_raw(w, h, rgb.iter().map(|&v| to_u8(v)).collect())
        .expect("buffer matches the image size")
        .save(&rgb_path)
        .with_context(|| format!("writing {}", rgb_path.display()))?;
    let alpha_path = out_dir.join("alpha.png");
    image::GrayImage::from_raw(
        w,
        h,
        transmittance.iter().map(|&t| to_u8(1.0 - t)).collect(),
    )
    .expect("buffer matches the image size")
    .save(&alpha_path)
    .with_context(|| format!("writing {}", alpha_path.display()))?;
    println!(
        "rendered {} Gaussians at {w}x{h} in {:.1} ms: {} and {}",
        args.gaussians,
        elapsed.as_secs_f64() * 1e3,
        rgb_path.display(),
        alpha_path.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::parse_frames;

    /// The forms users type: a frame, Rust's ranges, a dash (both ends) and Python's colon
    /// (end excluded); nonsense and empty ranges are refused naming the text.
    #[test]
    fn frames_are_read_as_users_type_them() {
        for (text, range) in [
            ("7", 7..8),
            ("0..60", 0..60),
            ("0..=59", 0..60),
            ("0-59", 0..60),
            ("0:60", 0..60),
            (" 3 - 5 ", 3..6),
        ] {
            assert_eq!(parse_frames(text).unwrap(), range, "{text}");
        }
        for text in ["a-b", "5:5", "-1", "9-3"] {
            let err = parse_frames(text).unwrap_err().to_string();
            assert!(err.contains(text.trim()), "{text}: {err}");
        }
    }
}
