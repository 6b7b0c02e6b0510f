//! Pictures a person looks at: PNG frames, side-by-side comparisons, grid slices, line plots
//! and animations (GIF, and H.264 MP4 for players and slides). Plots carry no text (no font rendering here); what each colour means
//! is in the run's `README.txt`.

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

    fn put(&mut self, x: i64, y: i64, colour: [u8; 3]) {
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

/// A perceptually ordered dark-blue -> green -> yellow ramp (viridis-like, 5 stops).
pub fn colour_ramp(t: f32) -> [u8; 3] {
    const STOPS: [[f32; 3]; 5] = [
        [0.267, 0.005, 0.329],
        [0.229, 0.322, 0.546],
        [0.128, 0.567, 0.551],
        [0.369, 0.789, 0.383],
        [0.993, 0.906, 0.144],
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    } * 4.0;
    let i = (t.floor() as usize).min(3);
    let f = t - i as f32;
    let c = |a: usize| to_u8(STOPS[i][a] * (1.0 - f) + STOPS[i + 1][a] * f);
    [c(0), c(1), c(2)]
}

/// The middle z-slice of the density (grey, left) and of the speed |u| (colour ramp, right),
/// +y up, each cell `scale` pixels wide. Returns the picture and the slice's largest speed.
pub fn grid_slices(
    grid: &GridSpec,
    density: &[f32],
    velocity: &[f32],
    scale: u32,
) -> (Picture, f32) {
    let [nx, ny, nz] = grid.resolution();
    let k = nz / 2;
    let cell = |i: usize, j: usize| (i * ny + j) * nz + k;
    let speed = |i: usize, j: usize| {
        let c = cell(i, j);
        (velocity[3 * c].powi(2) + velocity[3 * c + 1].powi(2) + velocity[3 * c + 2].powi(2)).sqrt()
    };
    let mut max_density = 1e-12f32;
    let mut max_speed = 1e-12f32;
    for i in 0..nx {
        for j in 0..ny {
            max_density = max_density.max(density[cell(i, j)]);
            max_speed = max_speed.max(speed(i, j));
        }
    }
    let (w, h) = (nx as u32 * scale, ny as u32 * scale);
    let mut left = Picture::blank(w, h, [0, 0, 0]);
    let mut right = Picture::blank(w, h, [0, 0, 0]);
    for y in 0..h {
        for x in 0..w {
            let (i, j) = ((x / scale) as usize, ny - 1 - (y / scale) as usize);
            let d = to_u8(density[cell(i, j)] / max_density);
            left.put(x as i64, y as i64, [d, d, d]);
            right.put(x as i64, y as i64, colour_ramp(speed(i, j) / max_speed));
        }
    }
    (Picture::side_by_side(&[&left, &right]), max_speed)
}

/// Distinct colours of the curves of [`line_plot`], in series order.
pub const SERIES_COLOURS: [[u8; 3]; 6] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [214, 39, 40],
    [148, 103, 189],
    [140, 86, 75],
];

/// Curves over a shared x axis on a white canvas with a light grid. With `log_y` the y axis
/// is logarithmic (non-positive values are skipped). Each series is scaled to the common
/// range of all series.
pub fn line_plot(series: &[Vec<f64>], width: u32, height: u32, log_y: bool) -> Picture {
    let mut picture = Picture::blank(width, height, [255, 255, 255]);
    let margin = 20i64;
    let (plot_w, plot_h) = (width as i64 - 2 * margin, height as i64 - 2 * margin);
    for g in 0..=4 {
        let y = margin + plot_h * g / 4;
        for x in margin..margin + plot_w {
            picture.put(x, y, [225, 225, 225]);
        }
    }
    let transform = |v: f64| if log_y { v.log10() } else { v };
    let values = series
        .iter()
        .flatten()
        .filter(|v| v.is_finite() && (!log_y || **v > 0.0))
        .map(|&v| transform(v));
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if !lo.is_finite() {
        return picture;
    }
    let span = (hi - lo).max(1e-12);
    let longest = series.iter().map(Vec::len).max().unwrap_or(0).max(2);
    for (s, values) in series.iter().enumerate() {
        let colour = SERIES_COLOURS[s % SERIES_COLOURS.len()];
        let mut previous: Option<(i64, i64)> = None;
        for (n, &v) in values.iter().enumerate() {
            if !v.is_finite() || (log_y && v <= 0.0) {
                previous = None;
                continue;
            }
            let x = margin + (n as i64 * (plot_w - 1)) / (longest as i64 - 1);
            let y = margin + plot_h - 1 - ((transform(v) - lo) / span * (plot_h - 1) as f64) as i64;
            if let Some((px, py)) = previous {
                let steps = (x - px).abs().max((y - py).abs()).max(1);
                for t in 0..=steps {
                    picture.put(px + (x - px) * t / steps, py + (y - py) * t / steps, colour);
                }
            } else {
                picture.put(x, y, colour);
            }
            previous = Some((x, y));
        }
    }
    picture
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
