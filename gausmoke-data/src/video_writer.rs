//! Writing H.264 video in MP4 files, the counterpart of [`crate::video`]: RGB pictures are
//! converted to 8-bit YCbCr 4:2:0 (BT.601 matrix, limited range: what a stream without a VUI
//! colour description is read as by ffmpeg, browsers and our decoder), encoded by
//! `rusty_h264-encoder` as Constrained Baseline (CAVLC, no B-frames: the profile every browser
//! and phone decodes) at a constant quantiser, and put in an MP4 container by `mp4`, one
//! sample per picture with SPS/PPS in the avcC box.
//!
//! H.264 4:2:0 needs even picture sizes: an odd width or height gets one more column or row,
//! a copy of the last one.
//!
//! The file is written under a temporary name and renamed by [`VideoWriter::finish`], so an
//! interrupted render never leaves a truncated `.mp4` under the final name.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use rusty_h264_common::YuvFrame;
use rusty_h264_encoder::{Encoder, EncoderConfig};

use crate::error::{DataError, Result, io_err};

/// Quantiser of the constant-QP encode: 18 keeps smoke gradients free of visible banding
/// (about 45 dB on the test pattern) at a few hundred kB per second of 270x480 video.
const QP: u8 = 18;

/// NAL unit types (H.264 Table 7-1) the muxer needs to tell apart.
const NAL_IDR: u8 = 5;
const NAL_SPS: u8 = 7;
const NAL_PPS: u8 = 8;

fn video_err(path: &Path, reason: impl Into<String>) -> DataError {
    DataError::Video {
        path: path.to_path_buf(),
        reason: reason.into(),
    }
}

/// A video being written; pictures go in with [`VideoWriter::push_rgb`] and the file appears
/// under its name with [`VideoWriter::finish`].
pub struct VideoWriter {
    path: PathBuf,
    partial: PathBuf,
    muxer: mp4::Mp4Writer<BufWriter<File>>,
    encoder: Encoder,
    /// Picture size given by the caller.
    width: u32,
    height: u32,
    /// Coded size (even).
    frame: YuvFrame,
    /// Track time units per picture (the track's timescale is `fps * TICKS`).
    ticks: u32,
    pictures: u64,
    track_added: bool,
}

impl VideoWriter {
    /// Starts `path` for `width` x `height` pictures shown at `fps` per second.
    pub fn create(path: &Path, width: u32, height: u32, fps: u32) -> Result<Self> {
        if width == 0 || height == 0 || fps == 0 {
            return Err(video_err(
                path,
                format!("cannot write a {width}x{height} video at {fps} frames per second"),
            ));
        }
        let (coded_w, coded_h) = (width.div_ceil(2) * 2, height.div_ceil(2) * 2);
        if coded_w > u16::MAX as u32 || coded_h > u16::MAX as u32 {
            return Err(video_err(
                path,
                format!("{width}x{height} is larger than MP4 allows"),
            ));
        }
        let mut config = EncoderConfig::baseline(coded_w as usize, coded_h as usize);
        config.qp = QP;
        config.bitrate = 0;
        config.framerate = fps as f32;
        // An IDR every two seconds: players can seek, files stay small.
        config.gop_size = 2 * fps;
        let encoder = Encoder::new(config)
            .map_err(|e| video_err(path, format!("H.264 encoder refused the settings: {e}")))?;
        let partial = path.with_extension("partial.mp4");
        let file = File::create(&partial).map_err(io_err(&partial))?;
        let ticks = 1000;
        let muxer = mp4::Mp4Writer::write_start(
            BufWriter::new(file),
            &mp4::Mp4Config {
                major_brand: "isom".parse().expect("four characters"),
                minor_version: 512,
                compatible_brands: ["isom", "iso2", "avc1", "mp41"]
                    .iter()
                    .map(|b| b.parse().expect("four characters"))
                    .collect(),
                timescale: 1000,
            },
        )
        .map_err(|e| video_err(&partial, e.to_string()))?;
        Ok(Self {
            path: path.to_path_buf(),
            partial,
            muxer,
            encoder,
            width,
            height,
            frame: YuvFrame::black(coded_w as usize, coded_h as usize),
            ticks,
            pictures: 0,
            track_added: false,
        })
    }

    /// Appends one picture: `rgb` holds `height * width * 3` bytes, rows top to bottom.
    pub fn push_rgb(&mut self, rgb: &[u8]) -> Result<()> {
        let expected = self.width as usize * self.height as usize * 3;
        if rgb.len() != expected {
            return Err(video_err(
                &self.path,
                format!(
                    "picture {} has {} bytes, a {}x{} RGB picture has {expected}",
                    self.pictures,
                    rgb.len(),
                    self.width,
                    self.height
                ),
            ));
        }
        rgb_to_yuv420(
            rgb,
            self.width as usize,
            self.height as usize,
            &mut self.frame,
        );
        let access_unit = self
            .encoder
            .try_encode(&self.frame)
            .map_err(|e| video_err(&self.path, format!("H.264 encoding failed: {e}")))?;
        self.write_access_unit(&access_unit)
    }

    fn write_access_unit(&mut self, access_unit: &[u8]) -> Result<()> {
        let mut sps = None;
        let mut pps = None;
        let mut sample = Vec::with_capacity(access_unit.len());
        let mut is_sync = false;
        for nal in annex_b_units(access_unit) {
            match nal[0] & 0x1f {
                NAL_SPS => sps = Some(nal.to_vec()),
                NAL_PPS => pps = Some(nal.to_vec()),
                kind => {
                    is_sync |= kind == NAL_IDR;
                    sample.extend_from_slice(&(nal.len() as u32).to_be_bytes());
                    sample.extend_from_slice(nal);
                }
            }
        }
        if sample.is_empty() {
            return Err(video_err(
                &self.path,
                format!(
                    "the encoder returned no picture for input {} (it should code every picture \
                     as it arrives)",
                    self.pictures
                ),
            ));
        }
        if !self.track_added {
            let (Some(sps), Some(pps)) = (sps, pps) else {
                return Err(video_err(
                    &self.path,
                    "the first coded picture carries no SPS/PPS",
                ));
            };
            let fps = self.encoder.config().framerate.round() as u32;
            self.muxer
                .add_track(&mp4::TrackConfig {
                    track_type: mp4::TrackType::Video,
                    timescale: fps * self.ticks,
                    language: "und".into(),
                    media_conf: mp4::MediaConfig::AvcConfig(mp4::AvcConfig {
                        width: self.frame.width as u16,
                        height: self.frame.height as u16,
                        seq_param_set: sps,
                        pic_param_set: pps,
                    }),
                })
                .map_err(|e| video_err(&self.partial, e.to_string()))?;
            self.track_added = true;
        }
        self.muxer
            .write_sample(
                1,
                &mp4::Mp4Sample {
                    start_time: self.pictures * self.ticks as u64,
                    duration: self.ticks,
                    rendering_offset: 0,
                    is_sync,
                    bytes: bytes::Bytes::from(sample),
                },
            )
            .map_err(|e| video_err(&self.partial, e.to_string()))?;
        self.pictures += 1;
        Ok(())
    }

    /// Pictures written so far.
    pub fn pictures(&self) -> u64 {
        self.pictures
    }

    /// Completes the file and gives it its name. A video without pictures is refused.
    pub fn finish(mut self) -> Result<PathBuf> {
        let tail = self
            .encoder
            .try_flush()
            .map_err(|e| video_err(&self.path, format!("H.264 encoding failed: {e}")))?;
        if !tail.is_empty() {
            return Err(video_err(
                &self.path,
                "the encoder held pictures back (the baseline configuration has no lookahead)",
            ));
        }
        if self.pictures == 0 {
            let _ = std::fs::remove_file(&self.partial);
            return Err(video_err(&self.path, "no pictures to write"));
        }
        self.muxer
            .write_end()
            .map_err(|e| video_err(&self.partial, e.to_string()))?;
        let file = self
            .muxer
            .into_writer()
            .into_inner()
            .map_err(|e| io_err(&self.partial)(e.into_error()))?;
        file.sync_all().map_err(io_err(&self.partial))?;
        std::fs::rename(&self.partial, &self.path).map_err(io_err(&self.path))?;
        Ok(self.path)
    }
}

/// The NAL units (header byte first, start codes removed) of an Annex-B byte stream.
fn annex_b_units(stream: &[u8]) -> Vec<&[u8]> {
    let mut starts = Vec::new();
    let mut i = 0;
    while i + 3 <= stream.len() {
        if stream[i] == 0 && stream[i + 1] == 0 && stream[i + 2] == 1 {
            starts.push((i, i + 3));
            i += 3;
        } else {
            i += 1;
        }
    }
    let mut units = Vec::with_capacity(starts.len());
    for (k, &(_, payload)) in starts.iter().enumerate() {
        let mut end = starts.get(k + 1).map_or(stream.len(), |&(code, _)| code);
        // A four-byte start code's leading zero belongs to the next code, not this unit.
        while end > payload && stream[end - 1] == 0 {
            end -= 1;
        }
        if end > payload {
            units.push(&stream[payload..end]);
        }
    }
    units
}

/// BT.601 limited-range YCbCr 4:2:0 of an RGB picture; chroma is the mean of each 2x2 block.
/// An odd last column or row of the coded frame repeats the picture's last one.
fn rgb_to_yuv420(rgb: &[u8], width: usize, height: usize, out: &mut YuvFrame) {
    let (cw, ch) = (out.width, out.height);
    let pixel = |x: usize, y: usize| {
        let i = (y.min(height - 1) * width + x.min(width - 1)) * 3;
        [rgb[i] as f32, rgb[i + 1] as f32, rgb[i + 2] as f32]
    };
    let luma = |[r, g, b]: [f32; 3]| 0.299 * r + 0.587 * g + 0.114 * b;
    for y in 0..ch {
        for x in 0..cw {
            let l = luma(pixel(x, y));
            out.y[y * cw + x] = (16.0 + l * (219.0 / 255.0)).round() as u8;
        }
    }
    let half_w = cw / 2;
    for cy in 0..ch / 2 {
        for cx in 0..half_w {
            let (mut cb, mut cr) = (0.0, 0.0);
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let p = pixel(2 * cx + dx, 2 * cy + dy);
                let l = luma(p);
                cb += (p[2] - l) / 1.772;
                cr += (p[0] - l) / 1.402;
            }
            let scale = 224.0 / 255.0 / 4.0;
            out.u[cy * half_w + cx] = (128.0 + cb * scale).round().clamp(16.0, 240.0) as u8;
            out.v[cy * half_w + cx] = (128.0 + cr * scale).round().clamp(16.0, 240.0) as u8;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn annex_b_units_split_on_three_and_four_byte_start_codes() {
        let stream = [
            0, 0, 0, 1, 0x67, 1, 2, 0, 0, 1, 0x68, 3, 0, 0, 0, 1, 0x65, 4, 0,
        ];
        let units = annex_b_units(&stream);
        assert_eq!(units, vec![&[0x67, 1, 2][..], &[0x68, 3], &[0x65, 4]]);
    }

    #[test]
    fn grey_maps_to_neutral_chroma_and_limited_luma() {
        let mut frame = YuvFrame::black(2, 2);
        rgb_to_yuv420(&[0; 12], 2, 2, &mut frame);
        assert_eq!((frame.y[0], frame.u[0], frame.v[0]), (16, 128, 128));
        rgb_to_yuv420(&[255; 12], 2, 2, &mut frame);
        assert_eq!((frame.y[3], frame.u[0], frame.v[0]), (235, 128, 128));
    }
}
