//! TensorBoard event files, so `tensorboard --logdir RUN/tensorboard` (and W&B's
//! `wandb sync`) show a run's curves and comparison pictures. Written by hand, no protobuf or
//! TensorFlow dependency: a file of TFRecords (`u64` length, masked CRC-32C of the length,
//! the bytes, masked CRC-32C of the bytes) each holding one `Event` protocol buffer
//! (`wall_time` 1, `step` 2, `file_version` 3, `summary` 5), whose `Summary.Value`s carry a
//! `tag` (1) and either a `simple_value` (2, float) or an `image` (4: `height` 1, `width` 2,
//! `colorspace` 3, `encoded_image_string` 4, a PNG).

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use image::ImageEncoder;

use crate::TrainError;
use crate::visuals::Picture;

/// CRC-32C (Castagnoli), reflected, as TFRecord uses it.
pub fn crc32c(bytes: &[u8]) -> u32 {
    const POLY: u32 = 0x82F6_3B78;
    let mut crc = !0u32;
    for &byte in bytes {
        crc ^= byte as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ POLY
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

fn masked_crc(bytes: &[u8]) -> u32 {
    let crc = crc32c(bytes);
    (crc.rotate_right(15)).wrapping_add(0xA282_EAD8)
}

fn varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

fn key(out: &mut Vec<u8>, field: u32, wire: u8) {
    varint(out, ((field as u64) << 3) | wire as u64);
}

fn bytes_field(out: &mut Vec<u8>, field: u32, bytes: &[u8]) {
    key(out, field, 2);
    varint(out, bytes.len() as u64);
    out.extend_from_slice(bytes);
}

/// What one summary value holds.
enum Value<'a> {
    Scalar(f32),
    Png {
        width: u32,
        height: u32,
        png: &'a [u8],
    },
}

fn summary_value(tag: &str, value: Value) -> Vec<u8> {
    let mut out = Vec::new();
    bytes_field(&mut out, 1, tag.as_bytes());
    match value {
        Value::Scalar(v) => {
            key(&mut out, 2, 5);
            out.extend_from_slice(&v.to_le_bytes());
        }
        Value::Png { width, height, png } => {
            let mut image = Vec::new();
            key(&mut image, 1, 0);
            varint(&mut image, height as u64);
            key(&mut image, 2, 0);
            varint(&mut image, width as u64);
            key(&mut image, 3, 0);
            varint(&mut image, 3); // RGB
            bytes_field(&mut image, 4, png);
            bytes_field(&mut out, 4, &image);
        }
    }
    out
}

fn event(step: i64, body: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let wall_time = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    let mut out = Vec::new();
    key(&mut out, 1, 1);
    out.extend_from_slice(&wall_time.to_le_bytes());
    key(&mut out, 2, 0);
    varint(&mut out, step as u64);
    body(&mut out);
    out
}

/// An event file being written.
pub struct EventWriter {
    path: PathBuf,
    file: BufWriter<File>,
}

impl EventWriter {
    /// Starts a new event file in `dir` (created if missing).
    pub fn create(dir: &Path) -> Result<Self, TrainError> {
        let io = |path: &Path| {
            let path = path.to_path_buf();
            move |source| TrainError::Io { path, source }
        };
        std::fs::create_dir_all(dir).map_err(io(dir))?;
        let seconds = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        // TensorBoard finds files by this prefix; the suffix keeps concurrent files apart.
        let path = dir.join(format!(
            "events.out.tfevents.{seconds}.gausmoke.{}",
            std::process::id()
        ));
        let file = File::create(&path).map_err(io(&path))?;
        let mut writer = Self {
            path,
            file: BufWriter::new(file),
        };
        writer.record(&event(0, |out| bytes_field(out, 3, b"brain.Event:2")))?;
        Ok(writer)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn record(&mut self, data: &[u8]) -> Result<(), TrainError> {
        let length = (data.len() as u64).to_le_bytes();
        let mut bytes = Vec::with_capacity(data.len() + 16);
        bytes.extend_from_slice(&length);
        bytes.extend_from_slice(&masked_crc(&length).to_le_bytes());
        bytes.extend_from_slice(data);
        bytes.extend_from_slice(&masked_crc(data).to_le_bytes());
        self.file
            .write_all(&bytes)
            .map_err(|source| TrainError::Io {
                path: self.path.clone(),
                source,
            })
    }

    /// Scalars `(tag, value)` at `step`, one event.
    pub fn scalars(&mut self, step: i64, values: &[(&str, f64)]) -> Result<(), TrainError> {
        let data = event(step, |out| {
            let mut summary = Vec::new();
            for (tag, v) in values.iter().filter(|(_, v)| v.is_finite()) {
                bytes_field(
                    &mut summary,
                    1,
                    &summary_value(tag, Value::Scalar(*v as f32)),
                );
            }
            bytes_field(out, 5, &summary);
        });
        self.record(&data)
    }

    /// A picture under `tag` at `step`.
    pub fn image(&mut self, step: i64, tag: &str, picture: &Picture) -> Result<(), TrainError> {
        let mut png = Vec::new();
        image::codecs::png::PngEncoder::new(&mut png)
            .write_image(
                &picture.pixels,
                picture.width,
                picture.height,
                image::ExtendedColorType::Rgb8,
            )
            .map_err(|e| TrainError::Export {
                path: self.path.clone(),
                reason: e.to_string(),
            })?;
        let data = event(step, |out| {
            let value = summary_value(
                tag,
                Value::Png {
                    width: picture.width,
                    height: picture.height,
                    png: &png,
                },
            );
            let mut summary = Vec::new();
            bytes_field(&mut summary, 1, &value);
            bytes_field(out, 5, &summary);
        });
        self.record(&data)
    }

    /// Pushes what is written to the file (TensorBoard reads files as they grow).
    pub fn flush(&mut self) -> Result<(), TrainError> {
        self.file.flush().map_err(|source| TrainError::Io {
            path: self.path.clone(),
            source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32c_matches_the_standard_check_value() {
        // The CRC catalogue's check value for CRC-32C over "123456789".
        assert_eq!(crc32c(b"123456789"), 0xE306_9283);
    }

    #[test]
    fn varints_are_little_endian_base_128() {
        let mut out = Vec::new();
        varint(&mut out, 300);
        assert_eq!(out, [0xAC, 0x02]);
    }
}
