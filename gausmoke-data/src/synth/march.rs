//! The independent ray marcher: Beer-Lambert emission and absorption through the density
//! grid, composited over the nearest visible solid or the background.

use gausmoke_core::Camera;
use gausmoke_core::glam::Vec3;
use rayon::prelude::*;

use super::{Grid, world_box};
use crate::dataset::Obstacle;
use crate::error::{DataError, Result};
use crate::image::Image;

/// Side of a box's checker squares, in world units (six across the unit box).
pub const BOX_TILE: f32 = 1.0 / 6.0;

/// A solid in world units (see [`world_box`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SynthSolid {
    pub shape: Obstacle,
    /// Drawn, opaque and textured (else only its effect on the smoke shows).
    pub visible: bool,
}

impl SynthSolid {
    /// The ray parameter where `origin + t dir` (unit `dir`, `origin` outside) first enters
    /// the solid.
    fn hit(&self, origin: Vec3, dir: Vec3) -> Option<f32> {
        let entry = match self.shape {
            Obstacle::Sphere { centre, radius } => {
                let offset = origin - centre;
                let b = offset.dot(dir);
                let c = offset.length_squared() - radius * radius;
                let discriminant = b * b - c;
                (discriminant >= 0.0).then(|| -b - discriminant.sqrt())
            }
            Obstacle::Box { min, max } => {
                let (near, far) = slab_interval(origin, dir, min, max);
                (near <= far).then_some(near)
            }
        };
        entry.filter(|&t| t > 0.0)
    }

    /// The lit, textured colour of the surface point `p` (see the module's notes).
    fn shade(&self, p: Vec3) -> f32 {
        let n = self.shape.outward_normal(p);
        let tile = match self.shape {
            Obstacle::Sphere { .. } => {
                let longitude = n.z.atan2(n.x);
                let latitude = n.y.clamp(-1.0, 1.0).asin();
                (longitude / std::f32::consts::TAU * 8.0).floor()
                    + (latitude / std::f32::consts::PI * 4.0).floor()
            }
            Obstacle::Box { .. } => {
                // The two coordinates along the face (the normal's axis left out).
                let across = p / BOX_TILE;
                let along = if n.x.abs() > 0.5 {
                    (across.y, across.z)
                } else if n.y.abs() > 0.5 {
                    (across.x, across.z)
                } else {
                    (across.x, across.y)
                };
                along.0.floor() + along.1.floor()
            }
        };
        let albedo = if (tile as i32).rem_euclid(2) == 0 {
            0.35
        } else {
            0.75
        };
        let light = Vec3::new(0.3, 1.0, 0.5).normalize();
        albedo * (0.3 + 0.7 * n.dot(light).max(0.0))
    }
}

/// Where the line `origin + t dir` enters and leaves the axis-aligned box `[lo, hi]` (it
/// misses when the first exceeds the second).
fn slab_interval(origin: Vec3, dir: Vec3, lo: Vec3, hi: Vec3) -> (f32, f32) {
    let (mut near, mut far) = (f32::NEG_INFINITY, f32::INFINITY);
    for a in 0..3 {
        let inv = 1.0 / dir[a];
        let (ta, tb) = ((lo[a] - origin[a]) * inv, (hi[a] - origin[a]) * inv);
        near = near.max(ta.min(tb));
        far = far.min(ta.max(tb));
    }
    (near, far)
}

/// Beer-Lambert emission-absorption ray marcher over a density grid filling the world box:
/// the picture over `background`.
pub fn render(
    density: &Grid,
    camera: &Camera,
    density_scale: f32,
    background: [f32; 3],
    solids: &[SynthSolid],
) -> Result<Image> {
    let (light, reach) = march(density, camera, density_scale, solids)?;
    let data = light
        .data()
        .chunks(3)
        .zip(&reach)
        .flat_map(|(rgb, &t)| (0..3).map(move |c| rgb[c] + t * background[c]))
        .collect();
    image_of(camera, data)
}

/// [`render`] as straight-alpha RGBA, as Blender writes a transparent background: alpha is
/// the share of the background a pixel hides (1 wherever a visible solid is hit), the colour
/// what lies in front of the background divided by it, so that compositing over
/// `background` gives [`render`]'s picture.
pub fn render_rgba(
    density: &Grid,
    camera: &Camera,
    density_scale: f32,
    solids: &[SynthSolid],
) -> Result<(Image, Vec<f32>)> {
    let (light, reach) = march(density, camera, density_scale, solids)?;
    let alpha: Vec<f32> = reach.iter().map(|t| 1.0 - t).collect();
    let data = light
        .data()
        .chunks(3)
        .zip(&alpha)
        .flat_map(|(rgb, &a)| {
            (0..3).map(move |c| if a > 0.0 { (rgb[c] / a).min(1.0) } else { 0.0 })
        })
        .collect();
    Ok((image_of(camera, data)?, alpha))
}

fn image_of(camera: &Camera, data: Vec<f32>) -> Result<Image> {
    Image::from_vec(camera.width(), camera.height(), data).ok_or_else(|| DataError::Options {
        option: "camera",
        reason: "empty image".into(),
    })
}

/// The marcher: per pixel, the light in front of the background (smoke emission, and the
/// nearest visible solid's shade seen through the smoke) and the transmittance to the
/// background (0 where a visible solid is hit).
fn march(
    density: &Grid,
    camera: &Camera,
    density_scale: f32,
    solids: &[SynthSolid],
) -> Result<(Image, Vec<f32>)> {
    let (lo, hi) = world_box();
    let n = density.n as f32;
    let cell = (hi - lo) / n;
    let ds = 0.5 * cell.min_element();
    let (w, h) = (camera.width() as usize, camera.height() as usize);
    let c2w = camera.camera_to_world();
    let origin = camera.position();
    let mut data = vec![0.0f32; w * h * 3];
    let mut reach = vec![0.0f32; w * h];
    data.par_chunks_mut(w * 3)
        .zip(reach.par_chunks_mut(w))
        .enumerate()
        .for_each(|(j, (row, row_reach))| {
            for i in 0..w {
                let d_cam = camera.ray_direction_camera(i as f32 + 0.5, j as f32 + 0.5);
                let dir = c2w.transform_vector3(d_cam).normalize();
                let (t0, mut t1) = slab_interval(origin, dir, lo, hi);
                let t0 = t0.max(0.0);
                let (mut light, mut trans) = (0.0f32, 1.0f32);
                // The nearest visible solid hides what lies behind it: march up to it, then
                // show it.
                let hit = solids
                    .iter()
                    .filter(|s| s.visible)
                    .filter_map(|s| s.hit(origin, dir).map(|t| (t, s)))
                    .min_by(|a, b| a.0.total_cmp(&b.0));
                if let Some((t, _)) = hit {
                    t1 = t1.min(t);
                }
                if t1 > t0 {
                    let steps = ((t1 - t0) / ds).ceil() as usize;
                    let step = (t1 - t0) / steps.max(1) as f32;
                    for k in 0..steps {
                        let p = origin + dir * (t0 + (k as f32 + 0.5) * step);
                        let g = (p - lo) / cell - Vec3::splat(0.5);
                        let sigma = density_scale * density.sample(g).max(0.0);
                        let a = 1.0 - (-sigma * step).exp();
                        light += trans * a;
                        trans *= 1.0 - a;
                    }
                }
                let (shade, to_background) = match hit {
                    Some((t, solid)) => (trans * solid.shade(origin + dir * t), 0.0),
                    None => (0.0, trans),
                };
                row[i * 3..i * 3 + 3].fill(light + shade);
                row_reach[i] = to_background;
            }
        });
    Ok((image_of(camera, data)?, reach))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::SynthConfig;

    fn blocks() -> (SynthSolid, SynthSolid) {
        let solids = SynthConfig::blocks_plume().solids;
        (solids[0], solids[1])
    }

    /// Entry points worked by hand: straight down -z onto the wall (face at z = -0.42), past
    /// the block (y = 0.5 is above its top at 0.46), and onto the sphere (|x| = 0.04 off its
    /// centre line, so it enters at z = sqrt(0.14^2 - 0.04^2)).
    #[test]
    fn rays_enter_boxes_and_spheres_where_worked_by_hand() {
        let (block, wall) = blocks();
        let down = Vec3::new(0.0, 0.0, -1.0);
        let from = Vec3::new(0.05, 0.5, 2.0);
        assert!(block.hit(from, down).is_none());
        let t = wall.hit(from, down).unwrap();
        assert!((t - 2.42).abs() < 1e-5, "{t}");
        let through_block = Vec3::new(0.05, 0.4, 2.0);
        let t = block.hit(through_block, down).unwrap();
        assert!((t - 1.88).abs() < 1e-5, "{t}");
        // Pointing away, or starting past it: no hit.
        assert!(wall.hit(from, -down).is_none());
        let sphere = SynthConfig::obstacle_plume().solids[0];
        let t = sphere.hit(Vec3::new(0.0, 0.4, 2.0), down).unwrap();
        let expected = 2.0 - (0.14f32 * 0.14 - 0.04 * 0.04).sqrt();
        assert!((t - expected).abs() < 1e-5, "{t} against {expected}");
    }

    /// The wall's face (normal +z) is lit by `0.3 + 0.7 (n . l)` with `l = (0.3, 1, 0.5) /
    /// |.|`, so its squares are 0.35 or 0.75 of 0.6023; squares alternate every sixth of a
    /// unit, along x and along y.
    #[test]
    fn box_faces_are_checkered_in_squares_of_a_sixth() {
        let (_, wall) = blocks();
        let lit = 0.3 + 0.7 * 0.5 / 1.34f32.sqrt();
        let at = |x: f32, y: f32| wall.shade(Vec3::new(x, y, -0.42));
        // floor(0.05 * 6) + floor(0.5 * 6) = 3: odd, the light squares.
        assert!((at(0.05, 0.5) - 0.75 * lit).abs() < 1e-6);
        assert!((at(-0.1, 0.5) - 0.35 * lit).abs() < 1e-6);
        assert!((at(0.05, 0.7) - 0.35 * lit).abs() < 1e-6);
        assert!((at(0.2, 0.7) - 0.75 * lit).abs() < 1e-6);
        // The top face of the block: normal +y, lit by 0.3 + 0.7 / |l|.
        let (block, _) = blocks();
        let top = block.shade(Vec3::new(0.05, 0.46, 0.05));
        let lit_top = 0.3 + 0.7 / 1.34f32.sqrt();
        assert!(
            (top - 0.75 * lit_top).abs() < 1e-6 || (top - 0.35 * lit_top).abs() < 1e-6,
            "{top}"
        );
    }

    #[test]
    fn solids_outside_the_box_are_refused_naming_the_setting() {
        let config = SynthConfig {
            solids: vec![SynthSolid {
                shape: Obstacle::Box {
                    min: Vec3::new(-0.6, 0.0, -0.5),
                    max: Vec3::new(0.0, 0.1, 0.0),
                },
                visible: true,
            }],
            ..SynthConfig::tiny()
        };
        let err = config.validate().unwrap_err().to_string();
        assert!(err.contains("solids") && err.contains("solid 0"), "{err}");
    }
}
