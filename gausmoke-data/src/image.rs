//! Host images (`[height, width, 3]` f32, row-major) and the area (box) resampling filter.

use std::path::Path;

use crate::error::{DataError, Result};

/// An RGB image, f32 values in `[0, 1]`, laid out `[height, width, 3]` row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    width: u32,
    height: u32,
    data: Vec<f32>,
}

impl Image {
    /// Wraps `data` (`height * width * 3` values). Returns `None` when the length does not
    /// match or the size is empty.
    pub fn from_vec(width: u32, height: u32, data: Vec<f32>) -> Option<Self> {
        (width > 0 && height > 0 && data.len() == width as usize * height as usize * 3).then_some(
            Self {
                width,
                height,
                data,
            },
        )
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    /// `[height, width, 3]` row-major values.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    pub fn into_vec(self) -> Vec<f32> {
        self.data
    }

    /// RGB of pixel column `x`, row `y` (panics when out of range, like slice indexing).
    pub fn pixel(&self, x: u32, y: u32) -> [f32; 3] {
        let i = (y as usize * self.width as usize + x as usize) * 3;
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }

    /// Bytes held by the pixel buffer.
    pub fn byte_size(&self) -> usize {
        self.data.len() * std::mem::size_of::<f32>()
    }

    /// Area-resampled copy at `width x height` (see [`resize_area`]); `None` for an empty
    /// size.
    pub fn resized(&self, width: u32, height: u32) -> Option<Image> {
        if width == self.width && height == self.height {
            return Some(self.clone());
        }
        let data = resize_area(
            &self.data,
            self.width as usize,
            self.height as usize,
            3,
            width as usize,
            height as usize,
        );
        Image::from_vec(width, height, data)
    }

    /// Writes an 8-bit straight-alpha RGBA PNG: this image's colours with `alpha` (one value
    /// per pixel), both clamped to `[0, 1]` and rounded.
    pub fn save_png_with_alpha(&self, alpha: &[f32], path: &Path) -> Result<()> {
        assert_eq!(alpha.len(), self.data.len() / 3, "one alpha per pixel");
        let bytes: Vec<u8> = self
            .data
            .chunks(3)
            .zip(alpha)
            .flat_map(|(rgb, &a)| [to_u8(rgb[0]), to_u8(rgb[1]), to_u8(rgb[2]), to_u8(a)])
            .collect();
        self.write_png(path, &bytes, image::ExtendedColorType::Rgba8)
    }

    /// This image with straight `alpha` (one per pixel) composited over `background`, as
    /// [`read_image_over`] does.
    pub fn over(&self, alpha: &[f32], background: [f32; 3]) -> Image {
        assert_eq!(alpha.len(), self.data.len() / 3, "one alpha per pixel");
        let data = self
            .data
            .chunks(3)
            .zip(alpha)
            .flat_map(|(rgb, &a)| (0..3).map(move |c| rgb[c] * a + background[c] * (1.0 - a)))
            .collect();
        Image {
            width: self.width,
            height: self.height,
            data,
        }
    }

    /// Writes an 8-bit RGB PNG (values clamped to `[0, 1]`, rounded).
    pub fn save_png(&self, path: &Path) -> Result<()> {
        let bytes: Vec<u8> = self.data.iter().map(|&v| to_u8(v)).collect();
        self.write_png(path, &bytes, image::ExtendedColorType::Rgb8)
    }

    /// Writes `bytes`, this image's pixels in `layout`, as an 8-bit PNG.
    fn write_png(&self, path: &Path, bytes: &[u8], layout: image::ExtendedColorType) -> Result<()> {
        image::save_buffer(path, bytes, self.width, self.height, layout).map_err(|source| {
            DataError::Image {
                action: "write",
                path: path.to_path_buf(),
                source,
            }
        })
    }
}

pub(crate) fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Reads a PNG (8 or 16 bit, grey, grey+alpha, RGB or RGBA) or a JPEG (8-bit, opaque) and
/// composites it over `background`: `rgb * alpha + background * (1 - alpha)`. Files without
/// alpha are opaque.
pub fn read_image_over(path: &Path, background: [f32; 3]) -> Result<Image> {
    let decoded = image::ImageReader::open(path)
        .map_err(crate::error::io_err(path))?
        .with_guessed_format()
        .map_err(crate::error::io_err(path))?
        .decode()
        .map_err(|source| DataError::Image {
            action: "decode",
            path: path.to_path_buf(),
            source,
        })?;
    let rgba = decoded.into_rgba32f();
    let (width, height) = rgba.dimensions();
    let mut data = Vec::with_capacity(width as usize * height as usize * 3);
    for px in rgba.pixels() {
        let a = px.0[3].clamp(0.0, 1.0);
        for (&v, &bg) in px.0.iter().zip(&background) {
            data.push(v.clamp(0.0, 1.0) * a + bg * (1.0 - a));
        }
    }
    Image::from_vec(width, height, data).ok_or_else(|| DataError::Layout {
        path: path.to_path_buf(),
        reason: "image has no pixels".into(),
    })
}

/// Weights of a 1-D area filter from `src` to `dst` samples: output sample `i` covers the
/// source interval `[i * s, (i + 1) * s)` with `s = src / dst`; source sample `j` (covering
/// `[j, j + 1)`) gets the length of the overlap divided by `s`, so weights sum to one.
pub(crate) struct AreaAxis {
    /// For output `i`: first source index and the range of its weights in `weights`.
    taps: Vec<(usize, usize, usize)>,
    weights: Vec<f32>,
}

impl AreaAxis {
    pub(crate) fn new(src: usize, dst: usize) -> Self {
        let scale = src as f64 / dst as f64;
        let mut taps = Vec::with_capacity(dst);
        let mut weights = Vec::new();
        for i in 0..dst {
            let lo = i as f64 * scale;
            let hi = ((i + 1) as f64 * scale).min(src as f64);
            let first = (lo.floor() as usize).min(src - 1);
            let last = (hi.ceil() as usize).clamp(first + 1, src);
            let begin = weights.len();
            for j in first..last {
                let overlap = (hi.min(j as f64 + 1.0) - lo.max(j as f64)).max(0.0);
                weights.push((overlap / scale) as f32);
            }
            taps.push((first, begin, weights.len()));
        }
        Self { taps, weights }
    }

    /// Resamples one row of `channels`-interleaved values.
    pub(crate) fn apply_row(&self, src: &[f32], dst: &mut [f32], channels: usize) {
        for (out, &(first, begin, end)) in dst.chunks_exact_mut(channels).zip(&self.taps) {
            out.fill(0.0);
            let ws = &self.weights[begin..end];
            let px = &src[first * channels..(first + ws.len()) * channels];
            for (w, p) in ws.iter().zip(px.chunks_exact(channels)) {
                for (o, v) in out.iter_mut().zip(p) {
                    *o += w * v;
                }
            }
        }
    }

    /// For every source sample, the outputs it contributes to and with which weight.
    pub(crate) fn contributions(&self, src: usize) -> Vec<Vec<(usize, f32)>> {
        let mut out = vec![Vec::new(); src];
        for (i, &(first, begin, end)) in self.taps.iter().enumerate() {
            for (k, &w) in self.weights[begin..end].iter().enumerate() {
                if w > 0.0 {
                    out[first + k].push((i, w));
                }
            }
        }
        out
    }
}

/// Row-by-row area resampler: feed source rows in order with [`RowResampler::push_row`],
/// then take the image. Only the output (and one resampled row) is held.
pub(crate) struct RowResampler {
    channels: usize,
    dst_w: usize,
    x: AreaAxis,
    y_contrib: Vec<Vec<(usize, f32)>>,
    row: Vec<f32>,
    out: Vec<f32>,
}

impl RowResampler {
    pub(crate) fn new(
        src_w: usize,
        src_h: usize,
        channels: usize,
        dst_w: usize,
        dst_h: usize,
    ) -> Self {
        Self {
            channels,
            dst_w,
            x: AreaAxis::new(src_w, dst_w),
            y_contrib: AreaAxis::new(src_h, dst_h).contributions(src_h),
            row: vec![0.0; dst_w * channels],
            out: vec![0.0; dst_w * dst_h * channels],
        }
    }

    /// Adds source row `j` (`src_w * channels` values).
    pub(crate) fn push_row(&mut self, j: usize, src_row: &[f32]) {
        self.x.apply_row(src_row, &mut self.row, self.channels);
        let len = self.dst_w * self.channels;
        for &(i, w) in &self.y_contrib[j] {
            for (o, &v) in self.out[i * len..(i + 1) * len].iter_mut().zip(&self.row) {
                *o += w * v;
            }
        }
    }

    pub(crate) fn finish(self) -> Vec<f32> {
        self.out
    }
}

/// Area (box) resampling of a `[src_h, src_w, channels]` row-major buffer to
/// `[dst_h, dst_w, channels]`. Each output pixel is the exact average of the source area it
/// covers (partial source pixels weighted by overlap), so an integer downscale is a plain box
/// average and the mean of the image is preserved. Pixel edges map to pixel edges, which is
/// why intrinsics scale by the size ratio (`fx`, `cx` by `dst_w / src_w`, `fy`, `cy` by
/// `dst_h / src_h`). Empty sizes or a buffer of the wrong length give an empty result.
pub fn resize_area(
    src: &[f32],
    src_w: usize,
    src_h: usize,
    channels: usize,
    dst_w: usize,
    dst_h: usize,
) -> Vec<f32> {
    if src_w == 0 || src_h == 0 || dst_w == 0 || dst_h == 0 || channels == 0 {
        return Vec::new();
    }
    if src.len() != src_w * src_h * channels {
        return Vec::new();
    }
    let mut r = RowResampler::new(src_w, src_h, channels, dst_w, dst_h);
    for (j, row) in src.chunks_exact(src_w * channels).enumerate() {
        r.push_row(j, row);
    }
    r.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integer_downscale_is_box_average() {
        // 4x2 single channel -> 2x1.
        let src = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0];
        let out = resize_area(&src, 4, 2, 1, 2, 1);
        assert_eq!(
            out,
            vec![(0.0 + 1.0 + 4.0 + 5.0) / 4.0, (2.0 + 3.0 + 6.0 + 7.0) / 4.0]
        );
    }

    #[test]
    fn fractional_downscale_weights_partial_pixels() {
        // 3 -> 2: output 0 covers [0, 1.5): src0 fully, half of src1.
        let out = resize_area(&[3.0, 6.0, 9.0], 3, 1, 1, 2, 1);
        let expected = [(3.0 + 0.5 * 6.0) / 1.5, (0.5 * 6.0 + 9.0) / 1.5];
        for (o, e) in out.iter().zip(expected) {
            assert!((o - e).abs() < 1e-5, "{out:?}");
        }
    }

    #[test]
    fn resize_preserves_mean_and_constants() {
        let (w, h) = (37, 23);
        let src: Vec<f32> = (0..w * h * 3)
            .map(|i| ((i * 7919) % 101) as f32 / 100.0)
            .collect();
        let out = resize_area(&src, w, h, 3, 10, 7);
        let mean = |v: &[f32]| v.iter().map(|&x| x as f64).sum::<f64>() / v.len() as f64;
        assert!((mean(&src) - mean(&out)).abs() < 1e-4);
        let flat = resize_area(&vec![0.25; w * h * 3], w, h, 3, 9, 4);
        assert!(flat.iter().all(|&v| (v - 0.25).abs() < 1e-6));
        // Upscaling by an integer factor replicates pixels.
        let up = resize_area(&[1.0, 2.0], 2, 1, 1, 4, 2);
        assert_eq!(up, vec![1.0, 1.0, 2.0, 2.0, 1.0, 1.0, 2.0, 2.0]);
    }
}
