//! Smoke data sets in their published formats and the synthetic scene generator.
//!
//! Depends only on `gausmoke-core` (cameras), never on the renderer or on training.
//!
//! * [`Dataset`]: views (one per camera, or one per split for monocular formats), each a list
//!   of [`Frame`]s (time, camera, RGB image), plus background colour and smoke box.
//! * [`load_pinf`]: PINF / HyFluid `info.json` with per-camera `.mp4` videos (decoded
//!   in-process, see [`video`]) or folders of PNG frames.
//! * [`load_dnerf`]: D-NeRF / 4D-GS `transforms_{train,val,test}.json` with RGBA PNGs.
//! * [`load_nerfstudio`]: nerfstudio `transforms.json` (per-frame or shared `fl_x`, `fl_y`,
//!   `cx`, `cy`; fixed cameras over time).
//! * [`load_colmap`]: a camera rig calibrated with COLMAP (`cameras` and `images`, text or
//!   binary) with a folder of frames per camera and a `rig.json` giving the smoke box.
//! * [`load`]: whichever of these the folder holds ([`Format::detect`]).
//! * [`synth`]: a synthetic smoke scene generator with ground-truth density and velocity,
//!   written in the PINF format.
//!
//! Images follow the workspace conventions: f32 in `[0, 1]`, `[height, width, 3]` row-major,
//! no sRGB conversion. Resizing ([`LoadOptions::resolution`]) uses an area filter and scales
//! the intrinsics by the size ratio.

mod camera_file;
mod colmap;
mod dataset;
mod dnerf;
mod error;
mod image;
use std::path::Path;

pub mod inspect;
mod json;
mod nerfstudio;
mod pinf;
pub mod synth;
pub mod video;
pub mod video_writer;

pub use camera_file::read_camera_path;
pub use colmap::{is_colmap_rig, load_colmap, plan_colmap};
pub use dataset::{Aabb, Dataset, Format, Frame, LoadOptions, Obstacle, PlannedView, Split, View};
pub use dnerf::{load_dnerf, plan_dnerf};
pub use error::{DataError, Result};
pub use image::{Image, read_image_over, resize_area};
pub use nerfstudio::{is_nerfstudio, load_nerfstudio, plan_nerfstudio};
pub use pinf::{load_pinf, plan_pinf};

pub use gausmoke_core::{Camera, Intrinsics, glam};

/// The data set at `path` (a PINF/HyFluid folder or `info.json`, a D-NeRF or a nerfstudio
/// folder, a COLMAP rig; see [`Format::detect`]) loaded with `options`.
pub fn load(path: &Path, options: &LoadOptions) -> Result<Dataset> {
    match Format::detect(path) {
        Some(Format::DNerf) => load_dnerf(path, options),
        Some(Format::Nerfstudio) => load_nerfstudio(path, options),
        Some(Format::Colmap) => load_colmap(path, options),
        // Without a known description, PINF's reader names the `info.json` it looked for.
        Some(Format::Pinf) | None => load_pinf(path, options),
    }
}

/// What [`load`] would produce, per view, without decoding a frame.
pub fn plan(path: &Path, options: &LoadOptions) -> Result<Vec<PlannedView>> {
    match Format::detect(path) {
        Some(Format::DNerf) => plan_dnerf(path, options),
        Some(Format::Nerfstudio) => plan_nerfstudio(path, options),
        Some(Format::Colmap) => plan_colmap(path, options),
        // Without a known description, PINF's reader names the `info.json` it looked for.
        Some(Format::Pinf) | None => plan_pinf(path, options),
    }
}

/// The solids the data set at `path` describes (its `obstacles`; see [`Format::detect`]),
/// read from its description alone, without decoding a frame. nerfstudio's format and COLMAP
/// rigs have none.
pub fn read_obstacles(path: &Path) -> Result<Vec<Obstacle>> {
    match Format::detect(path) {
        Some(Format::DNerf) => dnerf::obstacles(path),
        Some(Format::Nerfstudio | Format::Colmap) => Ok(Vec::new()),
        Some(Format::Pinf) | None => pinf::obstacles(path),
    }
}
