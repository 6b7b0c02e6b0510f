//! Pictures a person looks at: PNG frames, side-by-side comparisons, grid slices and
//! animations (GIF, and H.264 MP4 for players and slides); charts are in [`crate::chart`].

use std::path::Path;

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

    /// Pictures one above the other on white, left-aligned.
    pub fn stacked(parts: &[&Picture]) -> Self {
        let width = parts.iter().map(|p| p.width).max().unwrap_or(0);
        let height = parts.iter().map(|p| p.height).sum::<u32>();
        let mut out = Self::blank(width, height, [255, 255, 255]);
        let mut y0 = 0;
        for part in parts {
            for y in 0..part.height {
                let src = (y * part.width * 3) as usize;
                let dst = (((y0 + y) * width) * 3) as usize;
                out.pixels[dst..dst + (part.width * 3) as usize]
                    .copy_from_slice(&part.pixels[src..src + (part.width * 3) as usize]);
            }
            y0 += part.height;
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

    /// Mixes `colour` into pixel `(x, y)` by `coverage` in [0, 1] (anti-aliased text).
    pub fn blend(&mut self, x: i64, y: i64, colour: [u8; 3], coverage: f32) {
        if x >= 0 && y >= 0 && (x as u32) < self.width && (y as u32) < self.height {
            let at = ((y as u32 * self.width + x as u32) * 3) as usize;
            let a = coverage.clamp(0.0, 1.0);
            for (old, new) in self.pixels[at..at + 3].iter_mut().zip(colour) {
                *old = (f32::from(*old) * (1.0 - a) + f32::from(new) * a).round() as u8;
            }
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

/// `left` and `right` side by side, each scaled up by a whole factor to about 256 pixels
/// high (nearest neighbour, so pixels stay pixels), under `title` and with `labels` above
/// them: a comparison a person can read.
pub fn labelled_pair(left: &Picture, right: &Picture, labels: [&str; 2], title: &str) -> Picture {
    let factor = (256 / left.height.max(right.height).max(1)).max(1);
    let grow = |p: &Picture| {
        let mut out = Picture::blank(p.width * factor, p.height * factor, [0, 0, 0]);
        for y in 0..out.height {
            for x in 0..out.width {
                let at = (((y / factor) * p.width + x / factor) * 3) as usize;
                out.put(
                    i64::from(x),
                    i64::from(y),
                    [p.pixels[at], p.pixels[at + 1], p.pixels[at + 2]],
                );
            }
        }
        out
    };
    let (left, right) = (grow(left), grow(right));
    let line = crate::text::line_height(crate::text::LABEL);
    let header = 6 + 2 * line + 8;
    let pair = Picture::side_by_side(&[&left, &right]);
    let mut out = Picture::blank(pair.width, pair.height + header as u32, [255, 255, 255]);
    let ink = [30, 30, 30];
    crate::text::draw(&mut out, 4, 4, title, ink, crate::text::LABEL, false);
    for (x, label) in [(0, labels[0]), (i64::from(left.width) + 4, labels[1])] {
        crate::text::draw(
            &mut out,
            x + 4,
            6 + line,
            label,
            ink,
            crate::text::LABEL,
            false,
        );
    }
    for y in 0..pair.height {
        let src = (y * pair.width * 3) as usize;
        let dst = (((y + header as u32) * pair.width) * 3) as usize;
        out.pixels[dst..dst + (pair.width * 3) as usize]
            .copy_from_slice(&pair.pixels[src..src + (pair.width * 3) as usize]);
    }
    out
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
