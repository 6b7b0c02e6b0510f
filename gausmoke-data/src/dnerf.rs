//! D-NeRF / 4D-GS / Deformable-GS / NeuSmoke style data sets: `transforms_train.json`
//! (required), `transforms_val.json` and `transforms_test.json` (optional), each with
//! `camera_angle_x` and `frames[{file_path, time, transform_matrix}]`. `file_path` is relative
//! to the folder and, as in D-NeRF, given without the `.png` extension (a path that already
//! names an existing file is accepted too). RGBA PNGs are composited over the background
//! (black unless [`LoadOptions::background`] says otherwise, as 4D-GS does without
//! `--white_background`). Every frame has its own pose and time; each split becomes one
//! [`View`]. The format has no smoke box: [`Dataset::bbox`] is `None`.

use std::path::{Path, PathBuf};

use gausmoke_core::glam::Mat4;
use gausmoke_core::{Camera, Intrinsics};
use rayon::prelude::*;

use crate::dataset::{
    Dataset, Format, Frame, LoadOptions, PlannedView, Split, View, resize_to, scale_intrinsics,
    time_indices,
};
use crate::error::{DataError, Result};
use crate::image::read_png_over;
use crate::json::{Node, read_json};

struct Item {
    field: String,
    image: PathBuf,
    time: f32,
    pose: Mat4,
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
        let frames_owned = root.get("frames")?;
        let list = frames_owned.node().array()?;
        let Some(first) = list.first() else {
            return Err(frames_owned.node().err("a non-empty array of frames"));
        };
        let range = options.frame_range(list.len(), &format!("{stem}.json"))?;
        let (width, height) = match (options.resolution, native) {
            (Some(size), _) | (None, Some(size)) => size,
            (None, None) => {
                let image = read_item(first.node(), dir)?.image;
                let size =
                    ::image::image_dimensions(&image).map_err(|source| DataError::Image {
                        action: "read",
                        path: image,
                        source,
                    })?;
                *native.insert(size)
            }
        };
        planned.push(PlannedView {
            name: stem.trim_start_matches("transforms_").to_string(),
            split,
            frames: range.len(),
            width,
            height,
        });
    }
    Ok(planned)
}

/// Loads a D-NeRF style data set from its folder.
pub fn load_dnerf(dir: &Path, options: &LoadOptions) -> Result<Dataset> {
    options.validate()?;
    let background = options.background.unwrap_or([0.0; 3]);
    let mut views = Vec::new();
    // Native size: the first frame of the first split; every frame must match it.
    let mut native: Option<(u32, u32, PathBuf)> = None;
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
        let frames_owned = root.get("frames")?;
        let list = frames_owned.node().array()?;
        if list.is_empty() {
            return Err(frames_owned.node().err("a non-empty array of frames"));
        }
        let items = list
            .iter()
            .map(|f| read_item(f.node(), dir))
            .collect::<Result<Vec<_>>>()?;
        let range = options.frame_range(items.len(), &format!("{stem}.json"))?;
        let selected = &items[range];
        let images = selected
            .par_iter()
            .map(|it| read_png_over(&it.image, background))
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
            let k = scale_intrinsics(Intrinsics::from_fov_x(fov as f32, nw, nh), (nw, nh), target);
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
            name: stem.trim_start_matches("transforms_").to_string(),
            split,
            source: json,
            frames,
        });
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
        bbox: None,
        sim_to_world: None,
        obstacles: Vec::new(),
    })
}

fn read_item(node: Node<'_>, dir: &Path) -> Result<Item> {
    let path_owned = node.get("file_path")?;
    let rel = path_owned.node().str()?;
    let with_png = dir.join(format!("{rel}.png"));
    let as_is = dir.join(rel);
    let image = if with_png.is_file() {
        with_png
    } else if !rel.is_empty() && as_is.is_file() {
        as_is
    } else {
        return Err(path_owned.node().err(format!(
            "the path of an existing image (neither {} nor {} exists)",
            with_png.display(),
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
