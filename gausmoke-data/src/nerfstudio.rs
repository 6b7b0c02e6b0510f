//! nerfstudio `transforms.json` data sets (the layout `ns-process-data` writes): shared
//! intrinsics at the top level (`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`), any of which a frame may
//! override, and `frames[{file_path, transform_matrix}]` with camera-to-world poses in the
//! OpenGL convention (as NeRF's), `file_path` relative to the folder. Pixel centres are at
//! `+0.5` and `cx = w / 2` is a centred principal point, as in our cameras.
//!
//! Smoke is filmed by fixed cameras over time, which the format does not spell out, so:
//! * a frame's **time** is its `time` member (as in nerfstudio's dynamic data parsers);
//!   without any `time`, the capture is one instant;
//! * frames whose pose and intrinsics are identical are one **view** (one camera of the rig),
//!   named `cam00`, `cam01`, ... in order of first appearance, or by the frames' common
//!   `camera` member when they have one;
//! * the **split** comes from the optional `train_filenames`, `val_filenames` and
//!   `test_filenames` lists (nerfstudio's own names): a view is held out when all its frames
//!   are listed under test (or val); a view split across lists is refused;
//! * the **smoke box** comes from an optional `aabb`, `[[min x, y, z], [max x, y, z]]` in
//!   world units; without it [`Dataset::bbox`] is `None` (training asks for one).
//!
//! Lens distortion is not modelled by the renderer: non-zero `k1..k4`, `p1`, `p2` and camera
//! models other than `OPENCV`/`PINHOLE` (fisheye, equirectangular) are refused, naming the
//! field, rather than silently producing wrong rays. Undistort the images first
//! (`ns-process-data` can).

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use gausmoke_core::glam::Mat4;
use gausmoke_core::{Camera, Intrinsics};
use rayon::prelude::*;

use crate::dataset::{
    Aabb, Dataset, Format, Frame, LoadOptions, PlannedView, Split, View, resize_to,
    scale_intrinsics, time_indices,
};
use crate::error::{DataError, Result};
use crate::image::read_image_over;
use crate::json::{Node, read_aabb, read_json};

const DISTORTION: [&str; 6] = ["k1", "k2", "k3", "k4", "p1", "p2"];
const INTRINSICS: [&str; 6] = ["fl_x", "fl_y", "cx", "cy", "w", "h"];

/// One picture of a camera rig as a description lists it (also COLMAP's, see
/// [`crate::colmap`]).
pub(crate) struct Item {
    pub(crate) image: PathBuf,
    pub(crate) relative: String,
    pub(crate) time: f32,
    /// Camera-to-world, OpenGL convention.
    pub(crate) pose: Mat4,
    /// fl_x, fl_y, cx, cy, w, h.
    pub(crate) intrinsics: [f64; 6],
    pub(crate) camera: Option<String>,
    /// Where the picture is described, for messages (a JSON field path, a line).
    pub(crate) field: String,
}

/// A rig's views and box as a description gives them, before any picture is read.
pub(crate) struct Description {
    /// The file the description came from, named in messages.
    pub(crate) json: PathBuf,
    pub(crate) views: Vec<(String, Split, Vec<Item>)>,
    pub(crate) bbox: Option<Aabb>,
}

/// Whether `dir` holds a nerfstudio data set.
pub fn is_nerfstudio(dir: &Path) -> bool {
    dir.join("transforms.json").is_file()
}

fn describe(dir: &Path) -> Result<Description> {
    let json = dir.join("transforms.json");
    let value = read_json(&json)?;
    let root = Node::root(&json, &value);
    if let Some(model) = root.get_opt("camera_model")? {
        let name = model.node().str()?;
        if !matches!(name, "OPENCV" | "PINHOLE") {
            return Err(model.node().err(format!(
                "`OPENCV` or `PINHOLE` (got `{name}`: the renderer has pinhole cameras only; \
                 undistort the images first)"
            )));
        }
    }
    // Top-level values every frame inherits unless it gives its own.
    let read_number = |node: Node<'_>, key: &str| -> Result<Option<f64>> {
        node.get_opt(key)?.map(|v| v.node().f64()).transpose()
    };
    let check_no_distortion = |node: Node<'_>| -> Result<()> {
        for key in DISTORTION {
            if let Some(v) = node.get_opt(key)? {
                let k = v.node().f64()?;
                if k != 0.0 {
                    return Err(v.node().err(format!(
                        "0 (got {k}): lens distortion is not modelled; undistort the images \
                         first"
                    )));
                }
            }
        }
        Ok(())
    };
    check_no_distortion(root)?;
    let mut shared = [None; 6];
    for (slot, key) in shared.iter_mut().zip(INTRINSICS) {
        *slot = read_number(root, key)?;
    }
    let listed = |key: &str| -> Result<Vec<String>> {
        match root.get_opt(key)? {
            None => Ok(Vec::new()),
            Some(list) => list
                .node()
                .array()?
                .iter()
                .map(|v| v.node().str().map(normalise))
                .collect(),
        }
    };
    let (train_list, val_list, test_list) = (
        listed("train_filenames")?,
        listed("val_filenames")?,
        listed("test_filenames")?,
    );
    let bbox = read_aabb(root)?;
    let frames_owned = root.get("frames")?;
    let list = frames_owned.node().array()?;
    if list.is_empty() {
        return Err(frames_owned.node().err("a non-empty array of frames"));
    }
    let mut items = Vec::with_capacity(list.len());
    for owned in &list {
        let node = owned.node();
        check_no_distortion(node)?;
        let mut intrinsics = [0.0; 6];
        for (k, key) in INTRINSICS.iter().enumerate() {
            intrinsics[k] = match (read_number(node, key)?, shared[k]) {
                (Some(v), _) | (None, Some(v)) => v,
                (None, None) => {
                    return Err(node.err(format!(
                        "`{key}` here or at the top level of the file (camera intrinsics)"
                    )));
                }
            };
        }
        let path_owned = node.get("file_path")?;
        let relative = path_owned.node().str()?;
        let image = dir.join(relative);
        if !image.is_file() {
            return Err(path_owned.node().err(format!(
                "the path of an existing image ({} does not exist)",
                image.display()
            )));
        }
        let time = match node.get_opt("time")? {
            Some(t) => t.node().f64()? as f32,
            None => 0.0,
        };
        let camera = match node.get_opt("camera")? {
            Some(c) => Some(c.node().str()?.to_string()),
            None => None,
        };
        items.push(Item {
            image,
            relative: normalise(relative),
            time,
            pose: node.get("transform_matrix")?.node().mat4_rows()?,
            intrinsics,
            camera,
            field: node.field_path().to_string(),
        });
    }

    // Group frames into views by identical camera (pose and intrinsics bit for bit).
    let key = |it: &Item| -> Vec<u32> {
        let mut k: Vec<u32> = it
            .pose
            .to_cols_array()
            .iter()
            .map(|v| v.to_bits())
            .collect();
        k.extend(it.intrinsics.iter().map(|v| (*v as f32).to_bits()));
        k
    };
    let mut order: Vec<Vec<u32>> = Vec::new();
    let mut groups: HashMap<Vec<u32>, Vec<Item>> = HashMap::new();
    for item in items {
        let k = key(&item);
        if !groups.contains_key(&k) {
            order.push(k.clone());
        }
        groups.entry(k).or_default().push(item);
    }
    let mut views = Vec::with_capacity(order.len());
    for (index, k) in order.iter().enumerate() {
        let mut frames = groups.remove(k).expect("grouped above");
        frames.sort_by(|a, b| a.time.total_cmp(&b.time));
        let name = match frames[0].camera.clone() {
            Some(name) if frames.iter().all(|f| f.camera.as_deref() == Some(&name)) => name,
            _ => format!("cam{index:02}"),
        };
        let listed_in =
            |list: &[String]| frames.iter().filter(|f| list.contains(&f.relative)).count();
        let (test, val, train) = (
            listed_in(&test_list),
            listed_in(&val_list),
            listed_in(&train_list),
        );
        let split = if test == frames.len() {
            Split::Test
        } else if val == frames.len() {
            Split::Val
        } else if test + val == 0 || train == frames.len() {
            Split::Train
        } else {
            return Err(DataError::Field {
                path: json.clone(),
                field: frames[0].field.clone(),
                expected: format!(
                    "all frames of view `{name}` in one of train_filenames / val_filenames / \
                     test_filenames (its {} frames: {train} listed for train, {val} for val, \
                     {test} for test)",
                    frames.len()
                ),
            });
        };
        views.push((name, split, frames));
    }
    Ok(Description { json, views, bbox })
}

/// nerfstudio writes `./images/x.png` or `images/x.png`; the lists use either.
fn normalise(path: &str) -> String {
    path.trim_start_matches("./").to_string()
}

/// The distinct times of all views and the range of them `options.frames` keeps.
fn kept_times(description: &Description, options: &LoadOptions) -> Result<(Vec<f32>, Vec<f32>)> {
    let all: Vec<f32> = description
        .views
        .iter()
        .flat_map(|(_, _, frames)| frames.iter().map(|f| f.time))
        .collect();
    let (times, _) = time_indices(&all);
    let origin = format!("the distinct times of {}", description.json.display());
    let range = options.frame_range(times.len(), &origin)?;
    let kept = times[range].to_vec();
    Ok((times, kept))
}

/// What [`load_nerfstudio`] would load, without decoding an image.
pub fn plan_nerfstudio(dir: &Path, options: &LoadOptions) -> Result<Vec<PlannedView>> {
    options.validate()?;
    plan_described(&describe(dir)?, options)
}

/// The views `description` holds, as [`crate::plan`] gives them.
pub(crate) fn plan_described(
    description: &Description,
    options: &LoadOptions,
) -> Result<Vec<PlannedView>> {
    let (_, kept) = kept_times(description, options)?;
    Ok(description
        .views
        .iter()
        .map(|(name, split, frames)| {
            let native = (
                frames[0].intrinsics[4] as u32,
                frames[0].intrinsics[5] as u32,
            );
            let (width, height) = options.resolution.unwrap_or(native);
            PlannedView {
                name: name.clone(),
                split: *split,
                frames: frames.iter().filter(|f| kept.contains(&f.time)).count(),
                width,
                height,
            }
        })
        .collect())
}

/// Loads a nerfstudio data set from its folder (see the module docs).
pub fn load_nerfstudio(dir: &Path, options: &LoadOptions) -> Result<Dataset> {
    options.validate()?;
    load_described(dir, describe(dir)?, options, Format::Nerfstudio)
}

/// Reads the pictures `description` lists (a rig's, in the `format` it came from).
pub(crate) fn load_described(
    dir: &Path,
    description: Description,
    options: &LoadOptions,
    format: Format,
) -> Result<Dataset> {
    let background = options.background.unwrap_or([0.0; 3]);
    let (_, kept) = kept_times(&description, options)?;
    let (times, _) = time_indices(&kept);
    let mut views = Vec::new();
    for (name, split, items) in &description.views {
        let selected: Vec<&Item> = items.iter().filter(|f| kept.contains(&f.time)).collect();
        let images = selected
            .par_iter()
            .map(|it| read_image_over(&it.image, background))
            .collect::<Result<Vec<_>>>()?;
        let mut frames = Vec::with_capacity(selected.len());
        for (it, image) in selected.iter().zip(images) {
            let [fx, fy, cx, cy, w, h] = it.intrinsics;
            let native = (w as u32, h as u32);
            if (image.width(), image.height()) != native {
                return Err(DataError::FrameSize {
                    path: it.image.clone(),
                    frame: frames.len(),
                    found_width: image.width(),
                    found_height: image.height(),
                    expected_width: native.0,
                    expected_height: native.1,
                    origin: format!(
                        "`w` and `h` of {} in {}",
                        it.field,
                        description.json.display()
                    ),
                });
            }
            let target = options.resolution.unwrap_or(native);
            let k = Intrinsics {
                fx: fx as f32,
                fy: fy as f32,
                cx: cx as f32,
                cy: cy as f32,
            };
            let camera = Camera::new(
                target.0,
                target.1,
                scale_intrinsics(k, native, target),
                it.pose,
            )
            .map_err(|source| DataError::Camera {
                path: description.json.clone(),
                field: format!("{}.transform_matrix", it.field),
                source,
            })?;
            frames.push(Frame {
                time_index: times.partition_point(|t| *t < it.time),
                time: it.time,
                camera,
                image: resize_to(image, target)?,
            });
        }
        views.push(View {
            name: name.clone(),
            split: *split,
            source: description.json.clone(),
            frames,
        });
    }
    Ok(Dataset {
        format,
        source: dir.to_path_buf(),
        views,
        times,
        background,
        bbox: description.bbox,
        sim_to_world: None,
        obstacles: Vec::new(),
    })
}
