//! PINF / HyFluid `info.json` data sets (ScalarReal and the PINF synthetic scenes).
//!
//! Format (see `shared/datasets/scalar_real/README.md`): `train_videos`, `test_videos`,
//! `val_videos` list one entry per camera with `file_name`, `frame_num`, `camera_angle_x`,
//! `camera_hw` (`[height, width]`), `frame_rate` (optional) and either `transform_matrix`
//! (camera-to-world, OpenGL, rows) or `transform_matrix_list` (one per frame).
//! `frame_bkg_color` (optional, default black), `voxel_scale` (3 numbers or one) and
//! `voxel_matrix`: HyFluid swaps columns 0 and 2 of `voxel_matrix` before use, then
//! `sim = inverse(M) * world / voxel_scale` lies in `[0, 1]^3`; so
//! `sim_to_world = M_swapped * diag(voxel_scale)`, and the world box is the bounding box of
//! the 8 mapped cube corners.
//!
//! Frames come from the video named by `file_name` (H.264 MP4, decoded in-process), or from a
//! folder of PNG or JPEG frames: `file_name` itself when it is a folder, else the folder named
//! like the file without its extension (`train00.mp4` -> `train00/`). Frames are taken in
//! numeric order of the digits in their names (`000.png`, `001.png`, ... or `000.jpg`, ...).

use std::path::{Path, PathBuf};

use gausmoke_core::glam::{Mat4, Vec3};
use gausmoke_core::{Camera, Intrinsics};
use rayon::prelude::*;

use crate::dataset::{
    Aabb, Dataset, Format, Frame, LoadOptions, Obstacle, PlannedView, Split, View, resize_to,
    scale_intrinsics, time_indices,
};
use crate::error::{DataError, Result, io_err};
use crate::image::read_image_over;
use crate::json::{Node, read_json, read_obstacles};
use crate::video;

/// A camera entry of `info.json`, before its frames are read.
struct Entry {
    field: String,
    name: String,
    split: Split,
    source: Source,
    frame_num: usize,
    frame_rate: Option<f32>,
    native: (u32, u32),
    intrinsics: Intrinsics,
    /// One pose, or one per frame.
    poses: Vec<Mat4>,
}

enum Source {
    Video(PathBuf),
    Pngs(PathBuf),
}

/// `info.json` itself, given it or the folder holding it.
fn info_file(path: &Path) -> PathBuf {
    if path.is_dir() {
        path.join("info.json")
    } else {
        path.to_path_buf()
    }
}

/// The solids `info.json` describes (`obstacles`), without reading a camera or a frame.
pub(crate) fn obstacles(path: &Path) -> Result<Vec<Obstacle>> {
    let info = info_file(path);
    let value = read_json(&info)?;
    read_obstacles(Node::root(&info, &value))
}

/// Loads a PINF / HyFluid data set. `path` is the `info.json` file or the folder holding it.
pub fn load_pinf(path: &Path, options: &LoadOptions) -> Result<Dataset> {
    options.validate()?;
    let info = info_file(path);
    let root_dir = info.parent().unwrap_or(Path::new(".")).to_path_buf();
    let value = read_json(&info)?;
    let root = Node::root(&info, &value);

    let background = match options.background {
        Some(bg) => bg,
        None => match root.get_opt("frame_bkg_color")? {
            Some(node) => {
                let node = node.node();
                let c = node.f64_array::<3>()?;
                if c.iter().any(|v| !(0.0..=1.0).contains(v)) {
                    return Err(node.err("3 numbers in [0, 1]"));
                }
                c.map(|v| v as f32)
            }
            None => [0.0; 3],
        },
    };
    let sim_to_world = read_volume(root)?;
    let bbox = Aabb::from_points(
        Aabb {
            min: Vec3::ZERO,
            max: Vec3::ONE,
        }
        .corners()
        .map(|c| sim_to_world.transform_point3(c)),
    );

    let entries = read_entries(root, &root_dir)?;
    let obstacles = read_obstacles(root)?;

    let views: Vec<View> = entries
        .par_iter()
        .map(|e| load_entry(e, &info, options, background))
        .collect::<Result<_>>()?;

    let all_times: Vec<f32> = views
        .iter()
        .flat_map(|v| v.frames.iter().map(|f| f.time))
        .collect();
    let (times, idx) = time_indices(&all_times);
    let mut views = views;
    let mut k = 0;
    for v in &mut views {
        for f in &mut v.frames {
            f.time_index = idx[k];
            k += 1;
        }
    }
    Ok(Dataset {
        format: Format::Pinf,
        source: info,
        views,
        times,
        background,
        bbox,
        sim_to_world: Some(sim_to_world),
        obstacles,
    })
}

/// The cameras of `train_videos`, `val_videos` and `test_videos`, at least one.
fn read_entries(root: Node<'_>, root_dir: &Path) -> Result<Vec<Entry>> {
    let mut entries = Vec::new();
    for (key, split) in [
        ("train_videos", Split::Train),
        ("val_videos", Split::Val),
        ("test_videos", Split::Test),
    ] {
        let Some(list) = root.get_opt(key)? else {
            continue;
        };
        for item in list.node().array()? {
            entries.push(read_entry(item.node(), split, root_dir)?);
        }
    }
    if entries.is_empty() {
        return Err(root.err(
            "at least one camera in `train_videos`, `val_videos` or `test_videos`".to_string(),
        ));
    }
    Ok(entries)
}

/// What [`load_pinf`] would load (views, frame counts, image sizes) from `info.json` alone,
/// without decoding a frame.
pub fn plan_pinf(path: &Path, options: &LoadOptions) -> Result<Vec<PlannedView>> {
    options.validate()?;
    let info = info_file(path);
    let root_dir = info.parent().unwrap_or(Path::new(".")).to_path_buf();
    let value = read_json(&info)?;
    let entries = read_entries(Node::root(&info, &value), &root_dir)?;
    entries
        .iter()
        .map(|e| {
            let range = options.frame_range(e.frame_num, &format!("view `{}`", e.name))?;
            let (width, height) = options.resolution.unwrap_or(e.native);
            Ok(PlannedView {
                name: e.name.clone(),
                split: e.split,
                frames: range.len(),
                width,
                height,
            })
        })
        .collect()
}

fn read_volume(root: Node<'_>) -> Result<Mat4> {
    let scale_owned = root.get("voxel_scale")?;
    let scale_node = scale_owned.node();
    let scale = if let Ok(s) = scale_node.f64() {
        [s; 3]
    } else {
        scale_node
            .f64_array::<3>()
            .map_err(|_| scale_node.err("one positive number or an array of 3"))?
    };
    if scale.iter().any(|&s| s <= 0.0) {
        return Err(scale_node.err(format!("positive scales (got {scale:?})")));
    }
    let m_owned = root.get("voxel_matrix")?;
    let m_node = m_owned.node();
    let mut m = m_node.mat4_rows()?;
    if (m.row(3) - gausmoke_core::glam::Vec4::W)
        .abs()
        .max_element()
        > 1e-6
    {
        return Err(m_node.err("an affine 4x4 matrix with last row (0, 0, 0, 1)"));
    }
    // HyFluid / PINF swap columns 0 and 2 before use.
    std::mem::swap(&mut m.x_axis, &mut m.z_axis);
    let sim_to_world = m * Mat4::from_scale(Vec3::from_array(scale.map(|s| s as f32)));
    let det = sim_to_world.determinant();
    if !det.is_finite() || det.abs() < 1e-12 {
        return Err(m_node.err("an invertible matrix (with voxel_scale)"));
    }
    Ok(sim_to_world)
}

fn read_entry(node: Node<'_>, split: Split, root_dir: &Path) -> Result<Entry> {
    let field = node.field_path().to_string();
    let file_name_owned = node.get("file_name")?;
    let file_name = file_name_owned.node().str()?;
    if file_name.is_empty() {
        return Err(file_name_owned.node().err("a non-empty file name"));
    }
    let frame_num_owned = node.get("frame_num")?;
    let frame_num = frame_num_owned.node().usize()?;
    if frame_num == 0 {
        return Err(frame_num_owned.node().err("at least 1 frame"));
    }
    let fov_owned = node.get("camera_angle_x")?;
    let fov = fov_owned.node().positive_f64()?;
    if fov >= std::f64::consts::PI {
        return Err(fov_owned.node().err(format!(
            "a horizontal field of view in (0, pi) radians (got {fov})"
        )));
    }
    let hw_owned = node.get("camera_hw")?;
    let hw = hw_owned.node().f64_array::<2>()?;
    let is_size = |v: f64| v >= 1.0 && v.fract() == 0.0 && v <= u32::MAX as f64;
    if !hw.iter().all(|&v| is_size(v)) {
        return Err(hw_owned
            .node()
            .err(format!("[height, width] as positive integers (got {hw:?})")));
    }
    let native = (hw[1] as u32, hw[0] as u32);
    let frame_rate = match node.get_opt("frame_rate")? {
        Some(n) => Some(n.node().positive_f64()? as f32),
        None => None,
    };
    let intrinsics = Intrinsics::from_fov_x(fov as f32, native.0, native.1);

    let poses = if let Some(list) = node.get_opt("transform_matrix_list")? {
        let items = list.node().array()?;
        if items.len() < frame_num {
            return Err(list.node().err(format!(
                "one matrix per frame ({frame_num}), got {}",
                items.len()
            )));
        }
        items
            .iter()
            .take(frame_num)
            .map(|m| checked_pose(m.node(), native, intrinsics))
            .collect::<Result<Vec<_>>>()?
    } else {
        let m = node
            .get("transform_matrix")
            .map_err(|_| node.err("a `transform_matrix` or a `transform_matrix_list` member"))?;
        vec![checked_pose(m.node(), native, intrinsics)?]
    };

    let named = root_dir.join(file_name);
    let folder = root_dir.join(Path::new(file_name).with_extension(""));
    let source = if named.is_dir() {
        Source::Pngs(named)
    } else if named.is_file() {
        Source::Video(named)
    } else if folder.is_dir() {
        Source::Pngs(folder)
    } else {
        return Err(file_name_owned.node().err(format!(
            "an existing video or frame folder (neither {} nor {} exists)",
            named.display(),
            folder.display()
        )));
    };
    let name = Path::new(file_name)
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| file_name.to_string());
    Ok(Entry {
        field,
        name,
        split,
        source,
        frame_num,
        frame_rate,
        native,
        intrinsics,
        poses,
    })
}

fn checked_pose(node: Node<'_>, native: (u32, u32), k: Intrinsics) -> Result<Mat4> {
    let m = node.mat4_rows()?;
    Camera::new(native.0, native.1, k, m).map_err(|source| DataError::Camera {
        path: node.file_buf(),
        field: node.field_path().to_string(),
        source,
    })?;
    Ok(m)
}

fn load_entry(e: &Entry, info: &Path, options: &LoadOptions, background: [f32; 3]) -> Result<View> {
    let target = options.resolution.unwrap_or(e.native);
    let k = scale_intrinsics(e.intrinsics, e.native, target);
    let range = options.frame_range(e.frame_num, &format!("view `{}`", e.name))?;
    let expected_size = |path: &Path, frame: usize, w: u32, h: u32| -> Result<()> {
        if (w, h) == e.native {
            Ok(())
        } else {
            Err(DataError::FrameSize {
                path: path.to_path_buf(),
                frame,
                found_width: w,
                found_height: h,
                expected_width: e.native.0,
                expected_height: e.native.1,
                origin: format!("`{}.camera_hw` in {}", e.field, info.display()),
            })
        }
    };
    let too_few = |path: &Path, found: usize| DataError::TooFewFrames {
        path: path.to_path_buf(),
        json: info.to_path_buf(),
        field: format!("{}.frame_num", e.field),
        found,
        expected: e.frame_num,
    };

    let (source, images) = match &e.source {
        Source::Video(path) => {
            let probe = video::probe_mp4(path)?;
            expected_size(path, 0, probe.width, probe.height)?;
            if probe.frame_count < e.frame_num {
                return Err(too_few(path, probe.frame_count));
            }
            let decoded = video::decode_mp4(path, range.clone(), options.resolution)?;
            (path.clone(), decoded.frames)
        }
        Source::Pngs(dir) => {
            let files = image_frames(dir)?;
            if files.len() < e.frame_num {
                return Err(too_few(dir, files.len()));
            }
            let images = files[range.clone()]
                .par_iter()
                .enumerate()
                .map(|(i, file)| {
                    let img = read_image_over(file, background)?;
                    expected_size(file, range.start + i, img.width(), img.height())?;
                    resize_to(img, target)
                })
                .collect::<Result<Vec<_>>>()?;
            (dir.clone(), images)
        }
    };

    let frames = images
        .into_iter()
        .enumerate()
        .map(|(i, image)| {
            let t = range.start + i;
            let pose = if e.poses.len() == 1 {
                e.poses[0]
            } else {
                e.poses[t]
            };
            let camera =
                Camera::new(target.0, target.1, k, pose).map_err(|source| DataError::Camera {
                    path: info.to_path_buf(),
                    field: e.field.clone(),
                    source,
                })?;
            Ok(Frame {
                time_index: 0,
                time: match e.frame_rate {
                    Some(fps) => t as f32 / fps,
                    None => t as f32,
                },
                camera,
                image,
            })
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(View {
        name: e.name.clone(),
        split: e.split,
        source,
        frames,
    })
}

/// PNG and JPEG files of a frame folder, in numeric order of the digits in their stems (ties
/// and names without digits: by name).
pub(crate) fn image_frames(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut files: Vec<(u64, String, PathBuf)> = std::fs::read_dir(dir)
        .map_err(io_err(dir))?
        .filter_map(|entry| entry.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension().is_some_and(|x| {
                    ["png", "jpg", "jpeg"]
                        .iter()
                        .any(|known| x.eq_ignore_ascii_case(known))
                })
        })
        .map(|p| {
            let stem = p
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            let digits: String = stem.chars().filter(|c| c.is_ascii_digit()).collect();
            (digits.parse().unwrap_or(u64::MAX), stem, p)
        })
        .collect();
    files.sort();
    Ok(files.into_iter().map(|(_, _, p)| p).collect())
}
