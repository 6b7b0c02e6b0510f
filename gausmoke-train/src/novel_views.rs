//! `gausmoke-train render --run DIR`: the reconstruction of a run seen from any camera, as
//! MP4 videos (and PNG pictures on request), with the grid slices as a video beside them.
//!
//! Cameras ([`CameraPath`]):
//! * the data set's own views (train and held-out), one video per view;
//! * an orbit around the smoke box: `steps` cameras evenly spaced on a circle about the box
//!   centre, at the data set cameras' mean elevation and up direction, starting at the
//!   held-out camera's bearing, with its field of view, and as far from the centre as frames
//!   the box (its bounding sphere fills [`ORBIT_FILL`] of the narrower side of the picture);
//!   the picture is the held-out camera's shape, [`ORBIT_LONG_SIDE`] pixels on its long side,
//!   unless a size is given;
//! * a camera-path file (see [`gausmoke_data::read_camera_path`]).
//!
//! A moving camera and a moving scene go together like this: with `len` frames and `cameras`
//! cameras there are `P = max(len, cameras)` pictures, and picture `i` shows time frame
//! `frames[i * len / P]` through camera `i * cameras / P`: time and camera both span the
//! video. So 120 frames with a 120-step orbit make one turn while the smoke evolves, 8 frames
//! with a 60-step orbit one turn with each frame held for 7 or 8 pictures, and a single frame
//! with a 90-step orbit a frozen-time turn. The data set's own views pair frame `t` with the
//! view's camera at `t`.

use std::ops::Range;
use std::path::{Path, PathBuf};

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::glam::Vec3;
use gausmoke_core::{Camera, Intrinsics};
use gausmoke_data::video_writer::VideoWriter;
use gausmoke_render::render_volume;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use crate::TrainError;
use crate::run_folder::RunFolder;
use crate::sequence::Sequence;
use crate::slices::{GridSlice, SliceScale};
use crate::visuals::Picture;

/// Where the cameras come from.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraPath {
    /// Every train and held-out view of the run's data set, one video each.
    DatasetViews,
    /// `steps` cameras on a circle around the smoke box.
    Orbit { steps: usize },
    /// A NeRF-style camera-path file.
    File(PathBuf),
}

/// What [`render_run`] renders.
#[derive(Debug, Clone)]
pub struct RenderRequest {
    pub cameras: CameraPath,
    /// Time frames to show; `None`: every frame the run has finished.
    pub frames: Option<Range<usize>>,
    /// Picture size for orbits, width then height (default: the held-out camera's shape,
    /// [`ORBIT_LONG_SIDE`] pixels on its long side).
    pub size: Option<[u32; 2]>,
    /// Pictures per second of the videos.
    pub fps: u32,
    /// Also write every picture as a PNG.
    pub png: bool,
    /// Show a progress bar.
    pub progress: bool,
}

/// One written video.
#[derive(Debug, Clone, Serialize)]
pub struct RenderedVideo {
    pub name: String,
    pub video: PathBuf,
    pub pictures: usize,
    /// Time frame of each picture.
    pub frames: Vec<usize>,
    /// Camera centre of each picture (world units).
    pub camera_positions: Vec<[f32; 3]>,
    /// On an orbit, each picture's angle about the box's vertical axis from the held-out
    /// camera's bearing, in degrees.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub orbit_degrees: Option<Vec<f32>>,
}

/// Everything [`render_run`] wrote, also saved as `OUT/render.json`.
#[derive(Debug, Clone, Serialize)]
pub struct RenderSummary {
    pub run: PathBuf,
    pub videos: Vec<RenderedVideo>,
    /// Middle-z slices, one picture per frame: density | the grid velocity's speed, and with
    /// the run's velocity estimate | the estimate's speed (one colour scale per picture).
    pub slices_video: PathBuf,
    /// Whether the slices show the velocity estimate.
    pub slices_show_estimate: bool,
}

fn config_error(origin: &str, reason: impl Into<String>) -> TrainError {
    TrainError::Config {
        origin: origin.into(),
        reason: reason.into(),
    }
}

/// The share of the picture's narrower side the smoke box's bounding sphere fills on an orbit.
pub const ORBIT_FILL: f32 = 0.9;
/// An orbit's picture size on its long side, unless one is given.
pub const ORBIT_LONG_SIDE: u32 = 720;

/// The orbit described in the module docs.
pub fn orbit_cameras(
    reference: &Camera,
    all: &[&Camera],
    lo: Vec3,
    hi: Vec3,
    steps: usize,
    size: Option<[u32; 2]>,
) -> Result<Vec<Camera>, TrainError> {
    let centre = (lo + hi) * 0.5;
    let mut up = all
        .iter()
        .map(|c| c.camera_to_world().y_axis.truncate())
        .sum::<Vec3>();
    if up.length() < 1e-6 {
        return Err(config_error(
            "--orbit",
            "the data set's cameras have no common up direction to orbit about",
        ));
    }
    up = up.normalize();
    let offsets: Vec<Vec3> = all.iter().map(|c| c.position() - centre).collect();
    let height = offsets.iter().map(|o| o.dot(up)).sum::<f32>() / offsets.len() as f32;
    let across = offsets
        .iter()
        .map(|o| (*o - up * o.dot(up)).length())
        .sum::<f32>()
        / offsets.len() as f32;
    let bearing = reference.position() - centre;
    let mut e1 = bearing - up * bearing.dot(up);
    if e1.length() < 1e-6 || across < 1e-6 {
        return Err(config_error(
            "--orbit",
            "the held-out camera sits on the box's vertical axis; no circle to orbit on",
        ));
    }
    e1 = e1.normalize();
    let e2 = up.cross(e1);
    let [width, height_px] = size.unwrap_or_else(|| {
        let (w, h) = (reference.width() as f32, reference.height() as f32);
        let scale = ORBIT_LONG_SIDE as f32 / w.max(h);
        // Even sides, as H.264 players expect.
        [w, h].map(|side| ((side * scale / 2.0).round() as u32 * 2).max(2))
    });
    let Intrinsics { fx, .. } = reference.intrinsics();
    let fov_x = 2.0 * (reference.width() as f32 / (2.0 * fx)).atan();
    // The narrower half-angle of the picture the orbit renders (square pixels).
    let focal = width as f32 / 2.0 / (fov_x / 2.0).tan();
    let half_angle = (width.min(height_px) as f32 / 2.0 / focal).atan();
    let sphere = (hi - lo).length() / 2.0;
    let distance = sphere / (ORBIT_FILL * half_angle.tan()).atan().sin();
    // The data set cameras' elevation, at the distance that frames the box.
    let elevation = height.atan2(across);
    let (along, rise) = (distance * elevation.cos(), distance * elevation.sin());
    (0..steps)
        .map(|k| {
            let angle = std::f32::consts::TAU * k as f32 / steps as f32;
            let eye = centre + up * rise + (e1 * angle.cos() + e2 * angle.sin()) * along;
            Camera::look_at(eye, centre, up, width, height_px, fov_x)
                .map_err(|e| config_error("--orbit", e.to_string()))
        })
        .collect()
}

/// Picture `i` of a video of `frames` time frames through `cameras` cameras: its frame's index
/// into `frames` and its camera's, both spanning the video (see the module docs).
pub fn schedule(frames: usize, cameras: usize) -> Vec<(usize, usize)> {
    let pictures = frames.max(cameras);
    (0..pictures)
        .map(|i| (i * frames / pictures, i * cameras / pictures))
        .collect()
}

/// Renders the run in `run` as `request` asks, into the folder `out` (created if missing).
pub fn render_run(
    run: &Path,
    out: &Path,
    request: &RenderRequest,
    device: &Device,
) -> Result<RenderSummary, TrainError> {
    if request.fps == 0 {
        return Err(config_error("--fps", "must be at least 1"));
    }
    let folder = RunFolder::at(run);
    if !folder.run_info_path().is_file() {
        return Err(config_error(
            &run.display().to_string(),
            "this folder is not a GauSmoke run (it has no run.json); pass the --out folder of \
             a `gausmoke-train train`",
        ));
    }
    let mut config = folder.read_config()?;
    let info = folder.read_run_info()?;
    folder.require_whole()?;
    let finished = folder.finished_frames();
    if finished == 0 {
        return Err(TrainError::Dataset {
            path: run.to_path_buf(),
            reason: "no frames/frame_000.safetensors: the run has not finished a frame".into(),
        });
    }
    let frames = request.frames.clone().unwrap_or(0..finished);
    if frames.is_empty() || frames.end > finished {
        return Err(config_error(
            "--frames",
            format!(
                "frames {}..{} asked for, the run has finished frames 0..{finished}",
                frames.start, frames.end
            ),
        ));
    }
    // Only the dataset's own views need the pictures of every frame shown (a D-NeRF camera
    // moves); the others need the cameras and the box, which the first frame gives.
    let needed = match request.cameras {
        CameraPath::DatasetViews => frames.end,
        _ => 1,
    };
    config.frames = Some(needed);
    let scene = Sequence::open(&info.data, &config)?;
    info.check_data(&scene.fingerprint())?;
    let grid = config.grid(scene.lo, scene.hi)?;
    let background =
        Tensor::<1>::from_data(TensorData::new(scene.background.to_vec(), [3]), device);

    // (video name, camera for each picture index modulo its length)
    let mut paths: Vec<(String, Vec<Camera>)> = Vec::new();
    match &request.cameras {
        CameraPath::DatasetViews => {
            for observation in scene.train[0].iter().chain(&scene.test[0]) {
                // A D-NeRF camera moves: each frame has its own pose for the view.
                let cameras = frames
                    .clone()
                    .map(|t| {
                        scene.train[t]
                            .iter()
                            .chain(&scene.test[t])
                            .find(|o| o.view == observation.view)
                            .map(|o| o.camera)
                            .expect("Sequence checks that every view covers every frame")
                    })
                    .collect();
                paths.push((observation.view.clone(), cameras));
            }
        }
        CameraPath::Orbit { steps } => {
            if *steps == 0 {
                return Err(config_error("--orbit", "needs at least 1 step"));
            }
            let all: Vec<&Camera> = scene.train[0]
                .iter()
                .chain(&scene.test[0])
                .map(|o| &o.camera)
                .collect();
            let reference = scene.test[0]
                .first()
                .or(scene.train[0].first())
                .map(|o| &o.camera)
                .expect("a data set has a view");
            let cameras = orbit_cameras(reference, &all, scene.lo, scene.hi, *steps, request.size)?;
            paths.push(("orbit".into(), cameras));
        }
        CameraPath::File(path) => {
            let stem = path
                .file_stem()
                .map_or("cameras".into(), |s| s.to_string_lossy().into_owned());
            paths.push((stem, gausmoke_data::read_camera_path(path)?));
        }
    }

    std::fs::create_dir_all(out).map_err(|source| TrainError::Io {
        path: out.to_path_buf(),
        source,
    })?;
    let frame_list: Vec<usize> = frames.clone().collect();
    let total: usize = paths
        .iter()
        .map(|(_, c)| frame_list.len().max(c.len()))
        .sum::<usize>();
    let bar = if request.progress {
        ProgressBar::new(total as u64)
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template("{msg:>20} [{bar:40}] {pos}/{len}, eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );

    let mut loaded: Option<(usize, gausmoke_render::GaussianTensors)> = None;
    let mut videos = Vec::new();
    for (name, cameras) in &paths {
        bar.set_message(format!("{name} pictures"));
        let first = &cameras[0];
        let (width, height) = (first.width(), first.height());
        if let Some(other) = cameras
            .iter()
            .find(|c| (c.width(), c.height()) != (width, height))
        {
            return Err(config_error(
                name,
                format!(
                    "cameras of one video must share a picture size ({}x{} and {}x{})",
                    width,
                    height,
                    other.width(),
                    other.height()
                ),
            ));
        }
        let video_path = out.join(format!("{name}.mp4"));
        let png_dir = out.join(name);
        if request.png {
            std::fs::create_dir_all(&png_dir).map_err(|source| TrainError::Io {
                path: png_dir.clone(),
                source,
            })?;
        }
        let mut writer = VideoWriter::create(&video_path, width, height, request.fps)?;
        let mut shown = Vec::new();
        let mut positions = Vec::new();
        let mut degrees = Vec::new();
        for (i, (f, c)) in schedule(frame_list.len(), cameras.len())
            .into_iter()
            .enumerate()
        {
            let t = frame_list[f];
            if loaded.as_ref().is_none_or(|(f, _)| *f != t) {
                let state = folder.read_frame_state(t, &grid)?.ok_or_else(|| {
                    config_error(
                        &folder.frame_state_path(t).display().to_string(),
                        "missing: the run's frame state was removed while rendering",
                    )
                })?;
                loaded = Some((t, state.rendered().to_tensors(device)?));
            }
            let gaussians = &loaded.as_ref().expect("loaded above").1;
            let camera = &cameras[c];
            let rgb = gausmoke_render::device_traffic::read_floats(
                render_volume(gaussians, camera, &background, &config.raster_options())?.rgb,
            );
            let picture = Picture::from_rgb(&rgb, width, height);
            writer.push_rgb(&picture.pixels)?;
            if request.png {
                picture.save_png(&png_dir.join(format!("{i:04}.png")))?;
            }
            shown.push(t);
            positions.push(camera.position().to_array());
            degrees.push(360.0 * c as f32 / cameras.len() as f32);
            bar.inc(1);
        }
        let video = writer.finish()?;
        videos.push(RenderedVideo {
            name: name.clone(),
            video,
            pictures: shown.len(),
            frames: shown,
            camera_positions: positions,
            orbit_degrees: matches!(request.cameras, CameraPath::Orbit { .. }).then_some(degrees),
        });
    }

    // The slices count on a bar of their own: they are grid frames, not pictures.
    bar.set_length(frame_list.len() as u64);
    bar.set_position(0);
    bar.set_message("grid slices");
    let slices_video = out.join("slices.mp4");
    let estimate = crate::velocity_estimate::StoredEstimate::open(run)?;
    let mut slices = Vec::with_capacity(frame_list.len());
    // The density of the frame before, which the estimate of a frame is checked against: read
    // once, for the first frame shown, and carried from frame to frame after that.
    let mut before: Option<Vec<f32>> = None;
    for &t in &frame_list {
        let state = folder
            .read_frame_state(t, &grid)?
            .expect("frames before `finished` exist");
        slices.push(match &estimate {
            Some(estimate) => {
                if before.is_none() && t > 0 {
                    let previous = folder
                        .read_frame_state(t - 1, &grid)?
                        .expect("frames before `finished` exist");
                    before = Some(previous.density);
                }
                // Frame 0 has no estimate: the smoke starts at rest.
                let estimated = match &before {
                    Some(previous) => {
                        estimate.frame(t, grid.resolution(), [previous, &state.density])?
                    }
                    None => None,
                }
                .unwrap_or_else(|| vec![0.0; state.velocity.len()]);
                before = Some(state.density.clone());
                GridSlice::middle(&grid, &state.density, &[&state.velocity, &estimated])
            }
            None => GridSlice::middle(&grid, &state.density, &[&state.velocity]),
        });
        bar.inc(1);
    }
    let scale = SliceScale::over(&slices);
    let labels: &[&str] = if estimate.is_some() {
        &[
            "density",
            "speed: grid velocity",
            "speed: velocity estimate",
        ]
    } else {
        &["density", "speed: grid velocity"]
    };
    let note = scale.video_note();
    let mut writer: Option<VideoWriter> = None;
    for (slice, &t) in slices.iter().zip(&frame_list) {
        let picture = crate::slices::figure(t, slice, &scale, labels, &note);
        let writer = match &mut writer {
            Some(w) => w,
            None => writer.insert(VideoWriter::create(
                &slices_video,
                picture.width,
                picture.height,
                request.fps,
            )?),
        };
        writer.push_rgb(&picture.pixels)?;
    }
    writer.expect("at least one frame").finish()?;
    bar.finish_and_clear();
    let summary = RenderSummary {
        run: run.to_path_buf(),
        videos,
        slices_video,
        slices_show_estimate: estimate.is_some(),
    };
    let json = serde_json::to_string_pretty(&summary).expect("serialisable summary");
    crate::export::write_atomic(&out.join("render.json"), json.as_bytes())?;
    Ok(summary)
}
