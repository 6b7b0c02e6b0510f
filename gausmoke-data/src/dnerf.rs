//! D-NeRF / 4D-GS / Deformable-GS / NeuSmoke style data sets: `transforms_train.json`
//! (required), `transforms_val.json` and `transforms_test.json` (optional), each with
//! `camera_angle_x` and `frames[{file_path, time, transform_matrix}]`. `file_path` is relative
//! to the folder and, as in D-NeRF, given without the `.png` extension (`.jpg` is tried next,
//! and a path that already names an existing file is accepted too). RGBA PNGs are composited over the background
//! (black unless [`LoadOptions::background`] says otherwise, as 4D-GS does without
//! `--white_background`). In D-NeRF's own layout every frame has its own pose and time, and
//! each split becomes one [`View`]. Blender-style multi-view sets (fixed cameras filmed
//! together: several frames per time in one file) become one view per camera pose instead,
//! named `{split}_{k:02}` in order of first appearance, and `frames` then selects time steps,
//! not lines. The format has no smoke box; ours, `transforms_train.json` may give one as
//! `aabb` (`[[min x, y, z], [max x, y, z]]`, as nerfstudio's) and solids as `obstacles` (as
//! the PINF loader reads them); without `aabb` [`Dataset::bbox`] is `None`.

use std::path::{Path, PathBuf};

use gausmoke_core::glam::Mat4;
use gausmoke_core::{Camera, Intrinsics};
use rayon::prelude::*;

use crate::dataset::{
    Dataset, Format, Frame, LoadOptions, Obstacle, PlannedView, Split, View, resize_to,
    scale_intrinsics, time_indices,
};
use crate::error::{DataError, Result};
use crate::image::read_image_over;
use crate::json::{Node, read_aabb, read_json, read_obstacles};

struct Item {
    field: String,
    image: PathBuf,
    time: f32,
    pose: Mat4,
}

/// The views of one split's `items`, as (name, indices into `items`) after `options`' frame
/// selection: one named `split` when no two frames share a time (D-NeRF's layout), else one
/// per camera pose (see the module's notes).
fn split_views(
    items: &[Item],
    split: &str,
    options: &LoadOptions,
    origin: &str,
) -> Result<Vec<(String, Vec<usize>)>> {
    let mut times: Vec<f32> = items.iter().map(|it| it.time).collect();
    times.sort_by(f32::total_cmp);
    times.dedup();
    if times.len() == items.len() {
        let range = options.frame_range(items.len(), origin)?;
        return Ok(vec![(split.to_string(), range.collect())]);
    }
    let range = options.frame_range(times.len(), &format!("the time steps of {origin}"))?;
    let kept = &times[range];
    let mut poses: Vec<[u32; 16]> = Vec::new();
    let mut views: Vec<(String, Vec<usize>)> = Vec::new();
    for (index, item) in items.iter().enumerate() {
        let pose = item.pose.to_cols_array().map(f32::to_bits);
        let k = match poses.iter().position(|p| *p == pose) {
            Some(k) => k,
            None => {
                poses.push(pose);
                views.push((format!("{split}_{:02}", poses.len() - 1), Vec::new()));
                poses.len() - 1
            }
        };
        if kept.iter().any(|t| t.to_bits() == item.time.to_bits()) {
            views[k].1.push(index);
        }
    }
    Ok(views)
}

/// Every frame item of the transforms file `root` (paths checked, images not read).
fn read_items(root: Node<'_>, dir: &Path) -> Result<Vec<Item>> {
    let frames_owned = root.get("frames")?;
    let list = frames_owned.node().array()?;
    if list.is_empty() {
        return Err(frames_owned.node().err("a non-empty array of frames"));
    }
    list.iter().map(|f| read_item(f.node(), dir)).collect()
}

/// What [`load_dnerf`] would load from the transforms files and the first image's header,
/// without decoding an image.
pub fn plan_dnerf(dir: &Path, options: &LoadOptions) -> Result<Vec<PlannedView>> {
    options.validate()?;
    let mut planned = Vec::new();
    let mut native: Option<(u32, u32)> = None;
    for (stem, split) in [
        ("transforms_train", Split::Train),
        ("transforms_val", Split::Val),
        ("transforms_test", Split::Test),
    ] {
        let json = dir.join(format!("{stem}.json"));
        if split != Split::Train && !json.exists() {
            continue;
        }
        let value = read_json(&json)?;
        let root = Node::root(&json, &value);
        let items = read_items(root, dir)?;
        let (width, height) = match (options.resolution, native) {
            (Some(size), _) | (None, Some(size)) => size,
            (None, None) => {
                let image = items[0].image.clone();
                let size =
                    ::image::image_dimensions(&image).map_err(|source| DataError::Image {
                        action: "read",
                        path: image,
                        source,
                    })?;
                *native.insert(size)
            }
        };
        let name = stem.trim_start_matches("transforms_");
        for (name, indices) in split_views(&items, name, options, &format!("{stem}.json"))? {
            planned.push(PlannedView {
                name,
                split,
                frames: indices.len(),
                width,
                height,
            });
        }
    }
    Ok(planned)
}

/// The solids `transforms_train.json` describes (`obstacles`), without reading a frame.
pub(crate) fn obstacles(dir: &Path) -> Result<Vec<Obstacle>> {
    let json = dir.join("transforms_train.json");
    let value = read_json(&json)?;
    read_obstacles(Node::root(&json, &value))
}

/// Loads a D-NeRF style data set from its folder.
pub fn load_dnerf(dir: &Path, options: &LoadOptions) -> Result<Dataset> {
    options.validate()?;
    let background = options.background.unwrap_or([0.0; 3]);
    let mut views = Vec::new();
    // Native size: the first frame of the first split; every frame must match it.
    let mut native: Option<(u32, u32, PathBuf)> = None;
    let (mut bbox, mut obstacles) = (None, Vec::new());
    for (stem, split) in [
        ("transforms_train", Split::Train),
        ("transforms_val", Split::Val),
        ("transforms_test", Split::Test),
    ] {
        let json = dir.join(format!("{stem}.json"));
        if split != Split::Train && !json.exists() {
            continue;
        }
        let value = read_json(&json)?;
        let root = Node::root(&json, &value);
        let fov_owned = root.get("camera_angle_x")?;
        let fov = fov_owned.node().positive_f64()?;
        if fov >= std::f64::consts::PI {
            return Err(fov_owned.node().err(format!(
                "a horizontal field of view in (0, pi) radians (got {fov})"
            )));
        }
        if split == Split::Train {
            bbox = read_aabb(root)?;
            obstacles = read_obstacles(root)?;
        }
        let items = read_items(root, dir)?;
        let name = stem.trim_start_matches("transforms_");
        for (name, indices) in split_views(&items, name, options, &format!("{stem}.json"))? {
            let selected: Vec<&Item> = indices.iter().map(|&i| &items[i]).collect();
            let images = selected
                .par_iter()
                .map(|it| read_image_over(&it.image, background))
                .collect::<Result<Vec<_>>>()?;
            let mut frames = Vec::with_capacity(images.len());
            for (it, image) in selected.iter().zip(images) {
                let (nw, nh, first) = native
                    .get_or_insert_with(|| (image.width(), image.height(), it.image.clone()))
                    .clone();
                if (image.width(), image.height()) != (nw, nh) {
                    return Err(DataError::FrameSize {
                        path: it.image.clone(),
                        frame: frames.len(),
                        found_width: image.width(),
                        found_height: image.height(),
                        expected_width: nw,
                        expected_height: nh,
                        origin: format!("the first frame, {}", first.display()),
                    });
                }
                let target = options.resolution.unwrap_or((nw, nh));
                let k =
                    scale_intrinsics(Intrinsics::from_fov_x(fov as f32, nw, nh), (nw, nh), target);
                let camera = Camera::new(target.0, target.1, k, it.pose).map_err(|source| {
                    DataError::Camera {
                        path: json.clone(),
                        field: format!("{}.transform_matrix", it.field),
                        source,
                    }
                })?;
                let image = resize_to(image, target)?;
                frames.push(Frame {
                    time_index: 0,
                    time: it.time,
                    camera,
                    image,
                });
            }
            views.push(View {
                name,
                split,
                source: json.clone(),
                frames,
            });
        }
    }
    let all: Vec<f32> = views
        .iter()
        .flat_map(|v| v.frames.iter().map(|f| f.time))
        .collect();
    let (times, idx) = time_indices(&all);
    let mut k = 0;
    for v in &mut views {
        for f in &mut v.frames {
            f.time_index = idx[k];
            k += 1;
        }
    }
    Ok(Dataset {
        format: Format::DNerf,
        source: dir.to_path_buf(),
        views,
        times,
        background,
        bbox,
        sim_to_world: None,
        obstacles,
    })
}

fn read_item(node: Node<'_>, dir: &Path) -> Result<Item> {
    let path_owned = node.get("file_path")?;
    let rel = path_owned.node().str()?;
    let with_png = dir.join(format!("{rel}.png"));
    let with_jpg = dir.join(format!("{rel}.jpg"));
    let as_is = dir.join(rel);
    let image = if with_png.is_file() {
        with_png
    } else if with_jpg.is_file() {
        with_jpg
    } else if !rel.is_empty() && as_is.is_file() {
        as_is
    } else {
        return Err(path_owned.node().err(format!(
            "the path of an existing image (none of {}, {} and {} exists)",
            with_png.display(),
            with_jpg.display(),
            as_is.display()
        )));
    };
    let time = node.get("time")?.node().f64()? as f32;
    let pose_owned = node.get("transform_matrix")?;
    let pose = pose_owned.node().mat4_rows()?;
    Ok(Item {
        field: node.field_path().to_string(),
        image,
        time,
        pose,
    })
}
