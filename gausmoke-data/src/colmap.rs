//! A multi-camera rig calibrated with COLMAP: one COLMAP image per camera, and one folder of
//! frames per camera filmed over time.
//!
//! ```text
//! DATA/
//!   rig.json                 {"aabb": [[x, y, z], [x, y, z]],   the smoke box (required)
//!                             "test_cameras": ["cam02"],        held out (optional)
//!                             "up": [0, -1, 0]}                 the world's up (optional)
//!   sparse/0/cameras.txt     COLMAP's calibration, text or binary (.bin); also read from
//!   sparse/0/images.txt      sparse/ or from DATA/ itself
//!   images/cam00/000.png     each camera's frames (PNG or JPEG), in numeric order of the
//!   images/cam01/000.png     digits in their names; frame t of every camera is time t
//! ```
//!
//! A COLMAP image named `cam00/000.png` or `cam00.png` is the camera `cam00`, whose frames are
//! in `images/cam00/`. COLMAP's poses are world-to-camera in the OpenCV convention (x right, y
//! down, looking down +z); they become camera-to-world in ours (OpenGL: looking down -z, y
//! up). COLMAP's world has no up; with `up` (a direction in COLMAP's world) the world is
//! turned so that it points along +y, and `aabb` is given in the turned world. The camera
//! models read are the pinhole ones (`SIMPLE_PINHOLE`, `PINHOLE`) and those with distortion
//! parameters (`SIMPLE_RADIAL`, `RADIAL`, `OPENCV`) when every parameter is 0: the renderer
//! has no distortion, so the images must be undistorted first (`colmap image_undistorter`).

use std::path::{Path, PathBuf};

use gausmoke_core::glam::{DMat3, DQuat, DVec3, Mat4};

use crate::dataset::{Aabb, Dataset, Format, LoadOptions, PlannedView, Split};
use crate::error::{DataError, Result, io_err};
use crate::json::{Node, read_aabb, read_json};
use crate::nerfstudio::{Description, Item, load_described, plan_described};

/// The rig's description beside its calibration.
const RIG_FILE: &str = "rig.json";

/// Whether `dir` holds a COLMAP-calibrated rig (its `rig.json`).
pub fn is_colmap_rig(dir: &Path) -> bool {
    dir.join(RIG_FILE).is_file()
}

/// What [`load_colmap`] would load, without decoding an image.
pub fn plan_colmap(dir: &Path, options: &LoadOptions) -> Result<Vec<PlannedView>> {
    options.validate()?;
    plan_described(&describe(dir)?, options)
}

/// Loads a COLMAP-calibrated rig from its folder (see the module docs).
pub fn load_colmap(dir: &Path, options: &LoadOptions) -> Result<Dataset> {
    options.validate()?;
    load_described(dir, describe(dir)?, options, Format::Colmap)
}

/// One COLMAP camera: size and pinhole intrinsics.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Intrinsic {
    id: u32,
    width: u64,
    height: u64,
    /// fx, fy, cx, cy.
    pinhole: [f64; 4],
}

/// One COLMAP image: its world-to-camera rotation and translation, camera and name.
#[derive(Debug, Clone, PartialEq)]
struct Registered {
    rotation: [f64; 4],
    translation: [f64; 3],
    camera: u32,
    name: String,
}

fn layout(path: &Path, reason: impl Into<String>) -> DataError {
    DataError::Layout {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

/// The number of parameters of COLMAP's camera model `model` and, for those with
/// distortion, the pinhole part: the parameters that are fx, fy, cx, cy (a shared focal
/// length twice). `None` for a model the renderer cannot stand for.
fn model(name: &str) -> Option<(usize, [usize; 4])> {
    Some(match name {
        "SIMPLE_PINHOLE" => (3, [0, 0, 1, 2]),
        "PINHOLE" => (4, [0, 1, 2, 3]),
        "SIMPLE_RADIAL" => (4, [0, 0, 1, 2]),
        "RADIAL" => (5, [0, 0, 1, 2]),
        "OPENCV" => (8, [0, 1, 2, 3]),
        _ => return None,
    })
}

/// COLMAP's binary model ids, by position.
const MODEL_IDS: [&str; 11] = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "OPENCV_FISHEYE",
    "FULL_OPENCV",
    "FOV",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "THIN_PRISM_FISHEYE",
];

/// A camera of model `name` with `params`, checked: a pinhole one, or one whose distortion
/// parameters are all 0.
fn intrinsic(
    path: &Path,
    at: &str,
    id: u32,
    name: &str,
    size: [u64; 2],
    params: &[f64],
) -> Result<Intrinsic> {
    let Some((count, pinhole)) = model(name) else {
        return Err(layout(
            path,
            format!(
                "{at}: camera model {name} is not a pinhole one; undistort the images first \
                 (`colmap image_undistorter` writes PINHOLE cameras)"
            ),
        ));
    };
    if params.len() != count {
        return Err(layout(
            path,
            format!(
                "{at}: {name} has {count} parameters, found {}",
                params.len()
            ),
        ));
    }
    let distortion = &params[pinhole.iter().max().map_or(0, |m| m + 1)..];
    if distortion.iter().any(|&k| k != 0.0) {
        return Err(layout(
            path,
            format!(
                "{at}: {name} has distortion parameters {distortion:?}; the renderer has pinhole \
                 cameras only, so undistort the images first (`colmap image_undistorter`)"
            ),
        ));
    }
    if size.contains(&0) || params.iter().any(|v| !v.is_finite()) {
        return Err(layout(
            path,
            format!("{at}: a camera needs a size and finite parameters"),
        ));
    }
    Ok(Intrinsic {
        id,
        width: size[0],
        height: size[1],
        pinhole: pinhole.map(|i| params[i]),
    })
}

/// The lines of a COLMAP text file that are not comments or blank, with their line numbers.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim()))
        .filter(|(_, line)| !line.is_empty() && !line.starts_with('#'))
}

fn parse<T: std::str::FromStr>(path: &Path, at: &str, word: Option<&str>, what: &str) -> Result<T> {
    word.and_then(|w| w.parse().ok())
        .ok_or_else(|| layout(path, format!("{at}: expected {what}")))
}

fn cameras_text(path: &Path, text: &str) -> Result<Vec<Intrinsic>> {
    data_lines(text)
        .map(|(number, line)| {
            let at = format!("line {number}");
            let mut words = line.split_whitespace();
            let id = parse(path, &at, words.next(), "a camera id")?;
            let name: String = parse(path, &at, words.next(), "a camera model")?;
            let width = parse(path, &at, words.next(), "a width")?;
            let height = parse(path, &at, words.next(), "a height")?;
            let params = words
                .map(|w| parse(path, &at, Some(w), "a number"))
                .collect::<Result<Vec<f64>>>()?;
            intrinsic(path, &at, id, &name, [width, height], &params)
        })
        .collect()
}

fn images_text(path: &Path, text: &str) -> Result<Vec<Registered>> {
    // Each image takes two lines, its pose and its 2D points; only the first is read.
    let mut lines: Vec<(usize, &str)> = Vec::new();
    let mut expect_pose = true;
    for (number, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.starts_with('#') {
            continue;
        }
        if expect_pose && !line.is_empty() {
            lines.push((number + 1, line));
        }
        if expect_pose && line.is_empty() {
            continue;
        }
        expect_pose = !expect_pose;
    }
    lines
        .into_iter()
        .map(|(number, line)| {
            let at = format!("line {number}");
            let mut words = line.split_whitespace();
            let _id: u32 = parse(path, &at, words.next(), "an image id")?;
            let mut number = |what| parse::<f64>(path, &at, words.next(), what);
            let rotation = [number("QW")?, number("QX")?, number("QY")?, number("QZ")?];
            let translation = [number("TX")?, number("TY")?, number("TZ")?];
            let camera = parse(path, &at, words.next(), "a camera id")?;
            let name = words.collect::<Vec<_>>().join(" ");
            if name.is_empty() {
                return Err(layout(path, format!("{at}: expected an image name")));
            }
            Ok(Registered {
                rotation,
                translation,
                camera,
                name,
            })
        })
        .collect()
}

/// A little-endian reader over a COLMAP binary file, naming the file on a short read.
struct Binary<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    at: usize,
}

impl Binary<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8]> {
        let slice = self
            .bytes
            .get(self.at..self.at.saturating_add(n))
            .ok_or_else(|| layout(self.path, format!("ends early at byte {}", self.at)))?;
        self.at += n;
        Ok(slice)
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }
    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }
    /// A count of records at least `each` bytes long, checked against what is left.
    fn count(&mut self, each: usize) -> Result<usize> {
        let n = self.u64()?;
        let left = (self.bytes.len() - self.at) as u64;
        if n.saturating_mul(each as u64) > left {
            return Err(layout(
                self.path,
                format!("announces {n} records, more than its {left} bytes can hold"),
            ));
        }
        Ok(n as usize)
    }
}

fn cameras_binary(path: &Path, bytes: &[u8]) -> Result<Vec<Intrinsic>> {
    let mut file = Binary { path, bytes, at: 0 };
    let count = file.count(24)?;
    (0..count)
        .map(|k| {
            let at = format!("camera record {k}");
            let id = file.u32()?;
            let model_id = file.u32()? as usize;
            let name = MODEL_IDS
                .get(model_id)
                .ok_or_else(|| layout(path, format!("{at}: unknown camera model id {model_id}")))?;
            let size = [file.u64()?, file.u64()?];
            let params = match model(name) {
                Some((n, _)) => (0..n).map(|_| file.f64()).collect::<Result<Vec<_>>>()?,
                None => Vec::new(),
            };
            intrinsic(path, &at, id, name, size, &params)
        })
        .collect()
}

fn images_binary(path: &Path, bytes: &[u8]) -> Result<Vec<Registered>> {
    let mut file = Binary { path, bytes, at: 0 };
    let count = file.count(64)?;
    (0..count)
        .map(|k| {
            let _id = file.u32()?;
            let rotation = [file.f64()?, file.f64()?, file.f64()?, file.f64()?];
            let translation = [file.f64()?, file.f64()?, file.f64()?];
            let camera = file.u32()?;
            let mut name = Vec::new();
            loop {
                match file.take(1)?[0] {
                    0 => break,
                    byte => name.push(byte),
                }
            }
            let name = String::from_utf8(name)
                .map_err(|_| layout(path, format!("image record {k}: its name is not UTF-8")))?;
            let points = file.count(24)?;
            file.take(points * 24)?;
            Ok(Registered {
                rotation,
                translation,
                camera,
                name,
            })
        })
        .collect()
}

/// The folder holding `cameras.*` and `images.*`, and whether they are text.
fn calibration(dir: &Path) -> Result<(PathBuf, bool)> {
    for folder in [
        dir.join("sparse").join("0"),
        dir.join("sparse"),
        dir.to_path_buf(),
    ] {
        for text in [true, false] {
            let ext = if text { "txt" } else { "bin" };
            if folder.join(format!("cameras.{ext}")).is_file()
                && folder.join(format!("images.{ext}")).is_file()
            {
                return Ok((folder, text));
            }
        }
    }
    Err(layout(
        dir,
        "no COLMAP calibration: expected cameras.txt and images.txt (or .bin) in sparse/0/, \
         sparse/ or the folder itself",
    ))
}

/// The camera-to-world pose (OpenGL convention) of COLMAP's world-to-camera rotation
/// (w, x, y, z) and translation (OpenCV convention), turned by `world`.
fn pose(rotation: [f64; 4], translation: [f64; 3], world: DQuat) -> Mat4 {
    let [w, x, y, z] = rotation;
    let to_camera = DQuat::from_xyzw(x, y, z, w).normalize();
    let to_world = to_camera.inverse();
    let centre = -(to_world * DVec3::from_array(translation));
    // OpenCV's camera axes (x right, y down, z forward) to OpenGL's (y up, looking down -z).
    let axes = DMat3::from_cols(
        to_world * DVec3::X,
        to_world * DVec3::NEG_Y,
        to_world * DVec3::NEG_Z,
    );
    let turn = DMat3::from_quat(world);
    let axes = turn * axes;
    let centre = turn * centre;
    let column = |v: DVec3| v.as_vec3().extend(0.0);
    Mat4::from_cols(
        column(axes.x_axis),
        column(axes.y_axis),
        column(axes.z_axis),
        centre.as_vec3().extend(1.0),
    )
}

/// The camera a COLMAP image name stands for: its folder, or its file stem.
fn camera_name(name: &str) -> String {
    match name.split_once('/') {
        Some((folder, _)) => folder.to_string(),
        None => Path::new(name)
            .file_stem()
            .map_or_else(|| name.to_string(), |s| s.to_string_lossy().into_owned()),
    }
}

fn describe(dir: &Path) -> Result<Description> {
    let rig = dir.join(RIG_FILE);
    let value = read_json(&rig)?;
    let root = Node::root(&rig, &value);
    let bbox: Option<Aabb> = read_aabb(root)?;
    if bbox.is_none() {
        return Err(root.err("`aabb`: the smoke box, [[min x, y, z], [max x, y, z]]"));
    }
    let test: Vec<String> = match root.get_opt("test_cameras")? {
        Some(list) => list
            .node()
            .array()?
            .iter()
            .map(|v| v.node().str().map(str::to_string))
            .collect::<Result<_>>()?,
        None => Vec::new(),
    };
    let world = match root.get_opt("up")? {
        Some(owned) => {
            let up = DVec3::from_array(owned.node().f64_array::<3>()?);
            if up.length() < 1e-9 {
                return Err(owned.node().err("a non-zero direction"));
            }
            DQuat::from_rotation_arc(up.normalize(), DVec3::Y)
        }
        None => DQuat::IDENTITY,
    };
    let (folder, text) = calibration(dir)?;
    let ext = if text { "txt" } else { "bin" };
    let read = |path: &Path| -> Result<Vec<u8>> { std::fs::read(path).map_err(io_err(path)) };
    let cameras_path = folder.join(format!("cameras.{ext}"));
    let images_path = folder.join(format!("images.{ext}"));
    let (cameras, mut images) = if text {
        let as_text = |path: &Path, bytes: Vec<u8>| {
            String::from_utf8(bytes).map_err(|_| layout(path, "not UTF-8 text"))
        };
        (
            cameras_text(
                &cameras_path,
                &as_text(&cameras_path, read(&cameras_path)?)?,
            )?,
            images_text(&images_path, &as_text(&images_path, read(&images_path)?)?)?,
        )
    } else {
        (
            cameras_binary(&cameras_path, &read(&cameras_path)?)?,
            images_binary(&images_path, &read(&images_path)?)?,
        )
    };
    if images.is_empty() {
        return Err(layout(&images_path, "registers no image"));
    }
    images.sort_by_key(|image| camera_name(&image.name));
    let mut views = Vec::new();
    for image in &images {
        let name = camera_name(&image.name);
        if views.iter().any(|(seen, _, _)| *seen == name) {
            return Err(layout(
                &images_path,
                format!("camera `{name}` has more than one image; a rig has one per camera"),
            ));
        }
        let camera = cameras
            .iter()
            .find(|c| c.id == image.camera)
            .ok_or_else(|| {
                layout(
                    &images_path,
                    format!(
                        "image `{}` names camera {}, which cameras.{ext} lacks",
                        image.name, image.camera
                    ),
                )
            })?;
        let frames_dir = dir.join("images").join(&name);
        let files = crate::pinf::image_frames(&frames_dir)?;
        if files.is_empty() {
            return Err(layout(
                &frames_dir,
                format!("holds no PNG or JPEG frames of camera `{name}`"),
            ));
        }
        let [fx, fy, cx, cy] = camera.pinhole;
        let intrinsics = [fx, fy, cx, cy, camera.width as f64, camera.height as f64];
        let pose = pose(image.rotation, image.translation, world);
        let items = files
            .into_iter()
            .enumerate()
            .map(|(t, file)| Item {
                relative: file.display().to_string(),
                image: file,
                time: t as f32,
                pose,
                intrinsics,
                camera: Some(name.clone()),
                field: format!("image `{}`", image.name),
            })
            .collect();
        let split = if test.contains(&name) {
            Split::Test
        } else {
            Split::Train
        };
        views.push((name, split, items));
    }
    if let Some(missing) = test.iter().find(|t| !views.iter().any(|(n, _, _)| n == *t)) {
        return Err(root.err(format!(
            "`test_cameras`: names of the calibrated cameras (`{missing}` is not one)"
        )));
    }
    Ok(Description {
        json: images_path,
        views,
        bbox,
    })
}
