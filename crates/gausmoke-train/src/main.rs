//! `gausmoke-train`: the GauSmoke-rs command line.
//!
//! Today it renders a built-in synthetic smoke scene with the volumetric Gaussian renderer and
//! writes the image, so a new user can check that the build and the renderer work. Training
//! (Algorithm 1), evaluation and exports arrive with the training issue.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use burn::tensor::{Tensor, TensorData};
use clap::Parser;
use gausmoke_core::glam::Vec3;
use gausmoke_render::{Camera, RasterOptions, backends, render_volume, scenes};

/// Render the built-in synthetic smoke plume with the Beer-Lambert Gaussian renderer.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Args {
    /// Directory for the output images.
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Compiled backend to render on (see the error message for the list).
    #[arg(long, default_value = "flex")]
    device: String,
    /// Number of Gaussians in the plume.
    #[arg(long, default_value_t = 30_000)]
    gaussians: usize,
    /// Image width in pixels (ScalarFlow at the paper's resolution: 270).
    #[arg(long, default_value_t = 270)]
    width: u32,
    /// Image height in pixels (ScalarFlow at the paper's resolution: 480).
    #[arg(long, default_value_t = 480)]
    height: u32,
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    let args = Args::parse();
    let device = backends::device_by_name(&args.device).map_err(anyhow::Error::msg)?;
    tracing::info!(device = %args.device, "rendering on");

    // A 0.5 x 0.8 x 0.5 box with the plume rising along +Y, seen from the front.
    let lo = Vec3::new(-0.25, 0.0, -0.25);
    let hi = Vec3::new(0.25, 0.8, 0.25);
    let gaussians = scenes::smoke_plume(args.gaussians, lo, hi, 2026);
    let camera = Camera::look_at(
        Vec3::new(0.0, 0.4, 2.2),
        Vec3::new(0.0, 0.4, 0.0),
        Vec3::Y,
        args.width,
        args.height,
        0.45,
    )
    .context("building the demo camera")?;
    let tensors = gaussians.to_tensors(&device)?;
    let background = Tensor::<1>::from_data(TensorData::new(vec![0.0f32; 3], [3]), &device);

    let start = Instant::now();
    let out = render_volume(&tensors, &camera, &background, &RasterOptions::default())?;
    let rgb = out.rgb.into_data().try_into_vec_as::<f32>()?;
    let transmittance = out.transmittance.into_data().try_into_vec_as::<f32>()?;
    let elapsed = start.elapsed();

    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating output directory {}", args.out.display()))?;
    let (w, h) = (args.width, args.height);
    let to_u8 = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let rgb_path = args.out.join("render.png");
    image::RgbImage::from_raw(w, h, rgb.iter().map(|&v| to_u8(v)).collect())
        .expect("buffer matches the image size")
        .save(&rgb_path)
        .with_context(|| format!("writing {}", rgb_path.display()))?;
    let alpha_path = args.out.join("alpha.png");
    image::GrayImage::from_raw(
        w,
        h,
        transmittance.iter().map(|&t| to_u8(1.0 - t)).collect(),
    )
    .expect("buffer matches the image size")
    .save(&alpha_path)
    .with_context(|| format!("writing {}", alpha_path.display()))?;

    println!(
        "Rendered {} Gaussians at {w}x{h} on {} in {:.1} ms.",
        gaussians.len(),
        args.device,
        elapsed.as_secs_f64() * 1e3
    );
    println!("Image: {}", rgb_path.display());
    println!("Alpha: {}", alpha_path.display());
    Ok(())
}
