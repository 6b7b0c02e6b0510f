//! Pictures a person looks at: PNG frames, side-by-side comparisons, grid slices and
//! animations (GIF, and H.264 MP4 for players and slides); charts are in [`crate::chart`].

use std::path::Path;

use gausmoke_model::GridSpec;

use crate::TrainError;

/// An 8-bit RGB picture.
pub struct Picture {
    pub width: u32,
    pub height: u32,
    pub pixels: Vec<u8>,
}

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

impl Picture {
    pub fn blank(width: u32, height: u32, colour: [u8; 3]) -> Self {
        Self {
            width,
            height,
            pixels: colour.repeat((width * height) as usize),
        }
    }

    /// From an `[H, W, 3]` f32 image in `[0, 1]`.
    pub fn from_rgb(rgb: &[f32], width: u32, height: u32) -> Self {
        assert_eq!(rgb.len(), (width * height * 3) as usize, "image size");
        Self {
            width,
            height,
            pixels: rgb.iter().map(|&v| to_u8(v)).collect(),
        }
    }

    /// Pictures next to each other, separated by a 4-pixel grey gap, top-aligned.
    pub fn side_by_side(parts: &[&Picture]) -> Self {
        let gap = 4;
        let width = parts.iter().map(|p| p.width).sum::<u32>() + gap * (parts.len() as u32 - 1);
        let height = parts.iter().map(|p| p.height).max().unwrap_or(0);
        let mut out = Self::blank(width, height, [64, 64, 64]);
        let mut x0 = 0;
        for part in parts {
            for y in 0..part.height {
                let src = (y * part.width * 3) as usize;
                let dst = ((y * width + x0) * 3) as usize;
                out.pixels[dst..dst + (part.width * 3) as usize]
                    .copy_from_slice(&part.pixels[src..src + (part.width * 3) as usize]);
            }
            x0 += part.width + gap;
        }
        out
    }

    /// Sets one pixel; coordinates outside the picture are ignored.
    pub fn put(&mut self, x: i64, y: i64, colour: [u8; 3]) {
        if x >= 0 && y >= 0 && (x as u32) < self.width && (y as u32) < self.height {
            let at = ((y as u32 * self.width + x as u32) * 3) as usize;
            self.pixels[at..at + 3].copy_from_slice(&colour);
        }
    }

    /// A PNG written by [`Picture::save_png`]; `None` when it is missing or unreadable.
    pub fn open_png(path: &Path) -> Option<Self> {
        let rgb = image::open(path).ok()?.to_rgb8();
        Some(Self {
            width: rgb.width(),
            height: rgb.height(),
            pixels: rgb.into_raw(),
        })
    }

    pub fn save_png(&self, path: &Path) -> Result<(), TrainError> {
        let image = image::RgbImage::from_raw(self.width, self.height, self.pixels.clone())
            .expect("pixel buffer matches the picture size");
        let tmp = path.with_extension("partial.png");
        image.save(&tmp).map_err(|e| TrainError::Export {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })?;
        std::fs::rename(&tmp, path).map_err(|source| TrainError::Io {
            path: path.to_path_buf(),
            source,
        })
    }
}

/// The middle z-slice of the density (grey, left) and of the speed |u| of each of
/// `velocities` (viridis, to its right, in order, all on one colour scale: the largest speed in
/// any of them), +y up, each cell `scale` pixels wide. Returns the picture and that largest
/// speed.
pub fn grid_slices(
    grid: &GridSpec,
    density: &[f32],
    velocities: &[&[f32]],
    scale: u32,
) -> (Picture, f32) {
    let [nx, ny, nz] = grid.resolution();
    let k = nz / 2;
    let cell = |i: usize, j: usize| (i * ny + j) * nz + k;
    let speed = |velocity: &[f32], i: usize, j: usize| {
        let c = cell(i, j);
        (velocity[3 * c].powi(2) + velocity[3 * c + 1].powi(2) + velocity[3 * c + 2].powi(2)).sqrt()
    };
    let mut max_density = 1e-12f32;
    let mut max_speed = 1e-12f32;
    for i in 0..nx {
        for j in 0..ny {
            max_density = max_density.max(density[cell(i, j)]);
            for velocity in velocities {
                max_speed = max_speed.max(speed(velocity, i, j));
            }
        }
    }
    let (w, h) = (nx as u32 * scale, ny as u32 * scale);
    let mut panels: Vec<Picture> = (0..=velocities.len())
        .map(|_| Picture::blank(w, h, [0, 0, 0]))
        .collect();
    for y in 0..h {
        for x in 0..w {
            let (i, j) = ((x / scale) as usize, ny - 1 - (y / scale) as usize);
            let d = to_u8(density[cell(i, j)] / max_density);
            panels[0].put(x as i64, y as i64, [d, d, d]);
            for (panel, velocity) in panels[1..].iter_mut().zip(velocities) {
                let colour = crate::viridis::viridis(speed(velocity, i, j) / max_speed);
                panel.put(x as i64, y as i64, colour);
            }
        }
    }
    let parts: Vec<&Picture> = panels.iter().collect();
    (Picture::side_by_side(&parts), max_speed)
}

/// An H.264 MP4 of equally sized pictures at `fps` per second (see
/// [`gausmoke_data::video_writer`]).
pub fn save_mp4(path: &Path, frames: &[Picture], fps: u32) -> Result<(), TrainError> {
    let Some(first) = frames.first() else {
        return Ok(());
    };
    let mut writer =
        gausmoke_data::video_writer::VideoWriter::create(path, first.width, first.height, fps)?;
    for picture in frames {
        writer.push_rgb(&picture.pixels)?;
    }
    writer.finish()?;
    Ok(())
}

/// An animated GIF of equally sized pictures, `delay_ms` per frame, looping.
pub fn save_gif(path: &Path, frames: &[Picture], delay_ms: u32) -> Result<(), TrainError> {
    use image::codecs::gif::{GifEncoder, Repeat};
    let export = |e: image::ImageError| TrainError::Export {
        path: path.to_path_buf(),
        reason: e.to_string(),
    };
    let tmp = path.with_extension("partial.gif");
    let file = std::fs::File::create(&tmp).map_err(|source| TrainError::Io {
        path: tmp.clone(),
        source,
    })?;
    {
        let mut encoder = GifEncoder::new_with_speed(std::io::BufWriter::new(file), 20);
        encoder.set_repeat(Repeat::Infinite).map_err(export)?;
        for picture in frames {
            let rgba: Vec<u8> = picture
                .pixels
                .chunks(3)
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect();
            let buffer = image::RgbaImage::from_raw(picture.width, picture.height, rgba)
                .expect("pixel buffer matches the picture size");
            let delay = image::Delay::from_numer_denom_ms(delay_ms, 1);
            encoder
                .encode_frame(image::Frame::from_parts(buffer, 0, 0, delay))
                .map_err(export)?;
        }
    }
    std::fs::rename(&tmp, path).map_err(|source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    })
}
