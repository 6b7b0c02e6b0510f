use std::ops::Range;
use std::path::{Path, PathBuf};

use gausmoke_core::glam::{Mat4, Vec3};
use gausmoke_core::{Camera, Intrinsics};

use crate::error::{DataError, Result};
use crate::image::Image;

/// Which part of the evaluation protocol a view belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Split {
    Train,
    Val,
    Test,
}

/// The format a data set was read from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// PINF / HyFluid `info.json` with videos or frame folders.
    Pinf,
    /// D-NeRF / 4D-GS `transforms_*.json`.
    DNerf,
    /// nerfstudio `transforms.json`.
    Nerfstudio,
    /// A COLMAP-calibrated rig: `rig.json`, COLMAP's `cameras` and `images`, a frame folder
    /// per camera.
    Colmap,
}

impl Format {
    /// The format of the data set in the folder `path`, from the file that describes it: PINF
    /// for `info.json`, D-NeRF for `transforms_train.json`, nerfstudio for `transforms.json`,
    /// a COLMAP rig for `rig.json`; the first that the folder holds, in that order.
    pub fn detect(path: &Path) -> Option<Self> {
        if path.join("info.json").is_file() {
            Some(Self::Pinf)
        } else if path.join("transforms_train.json").is_file() {
            Some(Self::DNerf)
        } else if path.join("transforms.json").is_file() {
            Some(Self::Nerfstudio)
        } else if path.join("rig.json").is_file() {
            Some(Self::Colmap)
        } else {
            None
        }
    }
}

/// A solid the smoke flows around, inside the smoke box (world units). The training's
/// projection turns it into obstacle cells of its grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Obstacle {
    Sphere {
        centre: Vec3,
        radius: f32,
    },
    /// An axis-aligned box (a table, a wall, a chimney block).
    Box {
        min: Vec3,
        max: Vec3,
    },
}

impl Obstacle {
    /// Whether the world point `p` lies inside the solid.
    pub fn contains(&self, p: Vec3) -> bool {
        self.signed_distance(p) <= 0.0
    }

    /// Distance from `p` to the surface, negative inside.
    pub fn signed_distance(&self, p: Vec3) -> f32 {
        match *self {
            Obstacle::Sphere { centre, radius } => p.distance(centre) - radius,
            Obstacle::Box { min, max } => {
                // Per axis, how far outside the nearer face (negative inside).
                let q = (p - 0.5 * (min + max)).abs() - 0.5 * (max - min);
                q.max(Vec3::ZERO).length() + q.max_element().min(0.0)
            }
        }
    }

    /// The solid's bounding box and volume (world units).
    pub fn bounds(&self) -> (Vec3, Vec3, f32) {
        match *self {
            Obstacle::Sphere { centre, radius } => (
                centre - Vec3::splat(radius),
                centre + Vec3::splat(radius),
                4.0 / 3.0 * std::f32::consts::PI * radius.powi(3),
            ),
            Obstacle::Box { min, max } => (min, max, (max - min).element_product()),
        }
    }

    /// The unit normal pointing out of the solid at the surface point nearest `p`.
    pub fn outward_normal(&self, p: Vec3) -> Vec3 {
        match *self {
            Obstacle::Sphere { centre, .. } => (p - centre).normalize_or(Vec3::Y),
            Obstacle::Box { min, max } => {
                let offset = p - 0.5 * (min + max);
                let q = offset.abs() - 0.5 * (max - min);
                if q.max_element() > 0.0 {
                    // Outside: towards p from the nearest surface point.
                    (q.max(Vec3::ZERO) * offset.signum()).normalize_or(Vec3::Y)
                } else {
                    // Inside: out through the nearest face.
                    let axis = if q.x >= q.y && q.x >= q.z {
                        Vec3::X
                    } else if q.y >= q.z {
                        Vec3::Y
                    } else {
                        Vec3::Z
                    };
                    axis * offset.dot(axis).signum()
                }
            }
        }
    }

    /// The point a hair outside the surface nearest `p`, for a `p` inside (else `p`).
    pub fn pushed_out(&self, p: Vec3) -> Vec3 {
        let depth = self.signed_distance(p);
        if depth > 0.0 {
            return p;
        }
        let (lo, hi, _) = self.bounds();
        let hair = 5e-4 * (hi - lo).max_element();
        p + self.outward_normal(p) * (hair - depth)
    }
}

/// Axis-aligned box in world space.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub fn center(&self) -> Vec3 {
        0.5 * (self.min + self.max)
    }

    pub fn size(&self) -> Vec3 {
        self.max - self.min
    }

    /// The 8 corners, index bits (x, y, z) = (1, 2, 4).
    pub fn corners(&self) -> [Vec3; 8] {
        std::array::from_fn(|i| {
            Vec3::new(
                if i & 1 == 0 { self.min.x } else { self.max.x },
                if i & 2 == 0 { self.min.y } else { self.max.y },
                if i & 4 == 0 { self.min.z } else { self.max.z },
            )
        })
    }

    /// Bounding box of points (`None` for an empty iterator).
    pub fn from_points(points: impl IntoIterator<Item = Vec3>) -> Option<Self> {
        points.into_iter().fold(None, |acc, p| {
            Some(match acc {
                None => Aabb { min: p, max: p },
                Some(b) => Aabb {
                    min: b.min.min(p),
                    max: b.max.max(p),
                },
            })
        })
    }
}

/// One image of one camera at one time.
#[derive(Debug, Clone)]
pub struct Frame {
    /// Index into [`Dataset::times`].
    pub time_index: usize,
    /// Time as the format gives it (PINF: frame index / frame_rate in seconds, or the frame
    /// index when no frame rate is given; D-NeRF: the `time` field, usually in `[0, 1]`).
    pub time: f32,
    /// Camera at the loaded resolution (intrinsics already scaled).
    pub camera: Camera,
    pub image: Image,
}

/// What a loader would load for one view, read from the data set's description alone (see
/// [`crate::plan`]): enough to tell the memory the frames will take before decoding any.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlannedView {
    pub name: String,
    pub split: Split,
    /// Frames that would be loaded (after `LoadOptions::frames`).
    pub frames: usize,
    /// Size of the loaded images (after `LoadOptions::resolution`).
    pub width: u32,
    pub height: u32,
}

/// One camera's sequence (PINF), or one split's frames (D-NeRF, a moving camera).
#[derive(Debug, Clone)]
pub struct View {
    /// The video or folder name (PINF) or the split's JSON file stem (D-NeRF).
    pub name: String,
    pub split: Split,
    /// Source of the frames (a video, a frame folder or a JSON file).
    pub source: PathBuf,
    /// Frames in time order.
    pub frames: Vec<Frame>,
}

/// A loaded data set.
#[derive(Debug, Clone)]
pub struct Dataset {
    pub format: Format,
    /// The file the data set was read from (`info.json`, or the D-NeRF folder).
    pub source: PathBuf,
    pub views: Vec<View>,
    /// Distinct time stamps of the loaded frames, ascending.
    pub times: Vec<f32>,
    /// Background colour the images are composited over (linear RGB).
    pub background: [f32; 3],
    /// World-space bounding box of the smoke volume, when the format gives one.
    pub bbox: Option<Aabb>,
    /// Affine map from the simulation unit cube `[0, 1]^3` to world space (PINF:
    /// column-swapped `voxel_matrix` times `diag(voxel_scale)`), when the format gives one.
    pub sim_to_world: Option<Mat4>,
    /// Solids inside the smoke box, when the data set describes them (PINF `obstacles`).
    pub obstacles: Vec<Obstacle>,
}

impl Dataset {
    pub fn views_in(&self, split: Split) -> impl Iterator<Item = &View> {
        self.views.iter().filter(move |v| v.split == split)
    }

    pub fn view(&self, name: &str) -> Option<&View> {
        self.views.iter().find(|v| v.name == name)
    }

    /// Bytes held by all loaded images.
    pub fn image_bytes(&self) -> usize {
        self.views
            .iter()
            .flat_map(|v| &v.frames)
            .map(|f| f.image.byte_size())
            .sum()
    }
}

/// What to load.
#[derive(Debug, Clone, Default)]
pub struct LoadOptions {
    /// Resize every image to `(width, height)` with the area filter; `None` keeps the native
    /// size. Intrinsics are scaled to match.
    pub resolution: Option<(u32, u32)>,
    /// Frame indices (PINF: positions in each video in presentation order; D-NeRF: positions
    /// in each split's frame list) to load; `None` loads all announced frames.
    pub frames: Option<Range<usize>>,
    /// Overrides the background colour (D-NeRF default: black; PINF: `frame_bkg_color`).
    pub background: Option<[f32; 3]>,
}

impl LoadOptions {
    pub(crate) fn validate(&self) -> Result<()> {
        if let Some((w, h)) = self.resolution
            && (w == 0 || h == 0)
        {
            return Err(DataError::Options {
                option: "resolution",
                reason: format!("{w}x{h} is empty"),
            });
        }
        if let Some(r) = &self.frames
            && r.start >= r.end
        {
            return Err(DataError::Options {
                option: "frames",
                reason: format!("range {r:?} is empty"),
            });
        }
        if let Some(bg) = self.background
            && bg.iter().any(|c| !(0.0..=1.0).contains(c))
        {
            return Err(DataError::Options {
                option: "background",
                reason: format!("{bg:?} is not in [0, 1]"),
            });
        }
        Ok(())
    }

    /// The frame range to load out of the `available` frames that `origin` (a view, a file)
    /// announces: a range reaching past them is an error naming it, not a silent truncation.
    pub(crate) fn frame_range(&self, available: usize, origin: &str) -> Result<Range<usize>> {
        match &self.frames {
            Some(r) if r.end > available => Err(DataError::Options {
                option: "frames",
                reason: format!("range {r:?} reaches past the {available} frames of {origin}"),
            }),
            Some(r) => Ok(r.clone()),
            None => Ok(0..available),
        }
    }
}

/// Intrinsics scaled from a `native` image size to `target`: `fx, cx` by the width ratio,
/// `fy, cy` by the height ratio (pixel edges map to pixel edges under the area filter).
pub(crate) fn scale_intrinsics(
    k: Intrinsics,
    native: (u32, u32),
    target: (u32, u32),
) -> Intrinsics {
    let sx = target.0 as f32 / native.0 as f32;
    let sy = target.1 as f32 / native.1 as f32;
    Intrinsics {
        fx: k.fx * sx,
        fy: k.fy * sy,
        cx: k.cx * sx,
        cy: k.cy * sy,
    }
}

/// Sorted distinct times and, for each input time, its index in that list.
pub(crate) fn time_indices(times: &[f32]) -> (Vec<f32>, Vec<usize>) {
    let mut distinct: Vec<f32> = times.to_vec();
    distinct.sort_by(f32::total_cmp);
    distinct.dedup();
    let idx = times
        .iter()
        .map(|t| distinct.partition_point(|d| d < t))
        .collect();
    (distinct, idx)
}

/// `image` resampled to `target` (width, height) with the area filter, unchanged when it
/// already has that size.
pub(crate) fn resize_to(image: Image, target: (u32, u32)) -> Result<Image> {
    if (image.width(), image.height()) == target {
        return Ok(image);
    }
    image
        .resized(target.0, target.1)
        .ok_or_else(|| DataError::Options {
            option: "resolution",
            reason: format!("{}x{} is empty", target.0, target.1),
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Signed distance, outward normal and the pushed-out point of a box against the
    /// distances worked out by hand.
    #[test]
    fn a_box_obstacle_knows_its_inside_and_its_faces() {
        let cuboid = Obstacle::Box {
            min: Vec3::new(-1.0, 0.0, -0.5),
            max: Vec3::new(1.0, 1.0, 0.5),
        };
        let cases = [
            // (point, signed distance, outward normal)
            (Vec3::new(0.0, 0.5, 0.0), -0.5, Vec3::Y), // centre: nearest faces y and z tie
            (Vec3::new(0.9, 0.5, 0.0), -0.1, Vec3::X),
            (Vec3::new(0.0, 0.5, -0.45), -0.05, Vec3::NEG_Z),
            (Vec3::new(0.0, 1.3, 0.0), 0.3, Vec3::Y),
            (Vec3::new(-1.3, -0.4, 0.0), 0.5, Vec3::new(-0.6, -0.8, 0.0)),
        ];
        for (p, distance, normal) in cases {
            assert!(
                (cuboid.signed_distance(p) - distance).abs() < 1e-6,
                "{p}: {}",
                cuboid.signed_distance(p)
            );
            assert_eq!(cuboid.contains(p), distance <= 0.0);
            if p != Vec3::new(0.0, 0.5, 0.0) {
                assert!(
                    cuboid.outward_normal(p).distance(normal) < 1e-6,
                    "{p}: {}",
                    cuboid.outward_normal(p)
                );
            }
            let out = cuboid.pushed_out(p);
            assert!(!cuboid.contains(out), "{p} -> {out}");
            if distance <= 0.0 {
                let hair = cuboid.signed_distance(out);
                assert!(hair < 3e-3, "{p} -> {out} is {hair} from the surface");
            } else {
                assert_eq!(out, p, "a point outside stays");
            }
        }
        assert_eq!(cuboid.bounds().2, 2.0);
        let ball = Obstacle::Sphere {
            centre: Vec3::ZERO,
            radius: 0.5,
        };
        let out = ball.pushed_out(Vec3::new(0.1, 0.0, 0.0));
        assert!(out.distance(Vec3::new(0.5005, 0.0, 0.0)) < 1e-6, "{out}");
    }
}
