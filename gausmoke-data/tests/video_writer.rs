//! Videos written by `VideoWriter` decode with our own decoder to the pictures put in.

use gausmoke_data::video::{decode_mp4, probe_mp4};
use gausmoke_data::video_writer::VideoWriter;

/// A moving pattern: smooth colour gradients and a disc with a sharp edge in brightness only,
/// as smoke over a background is (4:2:0 would blur a sharp edge in colour).
fn picture(width: u32, height: u32, t: u32) -> Vec<u8> {
    let mut rgb = Vec::with_capacity((width * height * 3) as usize);
    for y in 0..height {
        for x in 0..width {
            let disc = {
                let (dx, dy) = (
                    x as f32 - (8 + 2 * t) as f32,
                    y as f32 - height as f32 / 2.0,
                );
                dx * dx + dy * dy < 64.0
            };
            let lift = if disc { 100 } else { 0 };
            let r = (x * 150 / width + lift) as u8;
            let g = (y * 150 / height + lift) as u8;
            rgb.extend_from_slice(&[r, g, (60 + lift) as u8]);
        }
    }
    rgb
}

fn psnr(a: &[u8], b: &[f32]) -> f64 {
    let mse = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 / 255.0 - y as f64).powi(2))
        .sum::<f64>()
        / a.len() as f64;
    -10.0 * mse.log10()
}

fn round_trip(width: u32, height: u32, pictures: u32) -> Vec<f64> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("clip.mp4");
    let mut writer = VideoWriter::create(&path, width, height, 24).unwrap();
    for t in 0..pictures {
        writer.push_rgb(&picture(width, height, t)).unwrap();
    }
    assert!(
        !path.exists(),
        "the final name appears only when the video is complete"
    );
    assert_eq!(writer.finish().unwrap(), path);
    let info = probe_mp4(&path).unwrap();
    let (coded_w, coded_h) = (width.div_ceil(2) * 2, height.div_ceil(2) * 2);
    assert_eq!((info.width, info.height), (coded_w, coded_h));
    assert_eq!(info.frame_count, pictures as usize);
    let decoded = decode_mp4(&path, 0..pictures as usize, None).unwrap();
    decoded
        .frames
        .iter()
        .enumerate()
        .map(|(t, frame)| {
            let source = picture(width, height, t as u32);
            // Compare the picture's own pixels (an odd size is padded by one column/row).
            let cropped: Vec<f32> = (0..height as usize)
                .flat_map(|y| {
                    let row = y * coded_w as usize * 3;
                    frame.data()[row..row + width as usize * 3].to_vec()
                })
                .collect();
            psnr(&source, &cropped)
        })
        .collect()
}

#[test]
fn a_written_video_decodes_to_its_pictures() {
    // 60 pictures at 24 fps: three IDRs (every 48) and P-frames between.
    let psnr = round_trip(96, 64, 60);
    let worst = psnr.iter().cloned().fold(f64::INFINITY, f64::min);
    assert!(worst > 40.0, "worst picture {worst:.2} dB: {psnr:?}");
}

#[test]
fn odd_sizes_are_padded_to_even() {
    let psnr = round_trip(45, 31, 3);
    assert!(psnr.iter().all(|&p| p > 40.0), "{psnr:?}");
}

#[test]
fn wrong_sizes_and_empty_videos_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.mp4");
    let mut writer = VideoWriter::create(&path, 16, 16, 24).unwrap();
    let err = writer.push_rgb(&[0; 10]).unwrap_err().to_string();
    assert!(err.contains("bad.mp4") && err.contains("16x16"), "{err}");
    let err = writer.finish().unwrap_err().to_string();
    assert!(err.contains("no pictures"), "{err}");
    assert!(!path.exists());
    assert!(VideoWriter::create(&path, 0, 16, 24).is_err());
}
