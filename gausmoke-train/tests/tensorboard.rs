//! `output.tensorboard = true`: the run's event file reads back as TFRecords with valid CRCs holding
//! Event protocol buffers with the scalars and the comparison picture TensorBoard shows.
//! Decoded here independently of the writer (protobuf wire format by hand).

use std::collections::BTreeMap;

use gausmoke_data::synth::{SynthConfig, generate};
use gausmoke_render::backends::device_by_name;
use gausmoke_train::sequence::Sequence;
use gausmoke_train::tensorboard::crc32c;
use gausmoke_train::{Run, TrainConfig};

fn masked(bytes: &[u8]) -> u32 {
    crc32c(bytes).rotate_right(15).wrapping_add(0xA282_EAD8)
}

/// (field number, wire type, value bytes or varint) of one protobuf message.
fn fields(mut bytes: &[u8]) -> Vec<(u64, u8, Vec<u8>, u64)> {
    fn varint(bytes: &mut &[u8]) -> u64 {
        let mut v = 0u64;
        for shift in (0..64).step_by(7) {
            let b = bytes[0];
            *bytes = &bytes[1..];
            v |= ((b & 0x7f) as u64) << shift;
            if b & 0x80 == 0 {
                break;
            }
        }
        v
    }
    let mut out = Vec::new();
    while !bytes.is_empty() {
        let key = varint(&mut bytes);
        let (field, wire) = (key >> 3, (key & 7) as u8);
        match wire {
            0 => out.push((field, 0, Vec::new(), varint(&mut bytes))),
            1 => {
                out.push((field, 1, bytes[..8].to_vec(), 0));
                bytes = &bytes[8..];
            }
            2 => {
                let n = varint(&mut bytes) as usize;
                out.push((field, 2, bytes[..n].to_vec(), 0));
                bytes = &bytes[n..];
            }
            5 => {
                out.push((field, 5, bytes[..4].to_vec(), 0));
                bytes = &bytes[4..];
            }
            other => panic!("unexpected wire type {other}"),
        }
    }
    out
}

#[test]
fn a_runs_event_file_holds_its_scalars_and_pictures() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    generate(&SynthConfig::tiny(), &data).unwrap();
    let config = {
        let mut config = TrainConfig {
            gaussians: 400,
            grid_resolution: 8,
            frames: Some(2),
            unet_channels: 4,
            time_frequencies: 2,
            ..TrainConfig::default()
        };
        config.init.iterations = 10;
        config.joint.iterations = 3;
        config.refine.iterations = 1;
        config.output.tensorboard = true;
        config
    };
    let scene = Sequence::open(&data, &config).unwrap();
    let device = device_by_name("flex").unwrap().autodiff();
    let run = dir.path().join("run");
    let reports = Run::new(scene, config, device, &run, false)
        .unwrap()
        .quiet(true)
        .run()
        .unwrap()
        .to_vec();

    let files: Vec<_> = std::fs::read_dir(run.join("tensorboard"))
        .unwrap()
        .flatten()
        .collect();
    assert_eq!(files.len(), 1);
    let name = files[0].file_name().into_string().unwrap();
    assert!(name.starts_with("events.out.tfevents."), "{name}");
    let bytes = std::fs::read(files[0].path()).unwrap();

    let mut at = 0;
    let mut scalars: BTreeMap<String, Vec<(u64, f32)>> = BTreeMap::new();
    let mut images = Vec::new();
    let mut first = true;
    while at < bytes.len() {
        let length = &bytes[at..at + 8];
        let n = u64::from_le_bytes(length.try_into().unwrap()) as usize;
        let crc = u32::from_le_bytes(bytes[at + 8..at + 12].try_into().unwrap());
        assert_eq!(crc, masked(length), "length CRC at byte {at}");
        let data = &bytes[at + 12..at + 12 + n];
        let crc = u32::from_le_bytes(bytes[at + 12 + n..at + 16 + n].try_into().unwrap());
        assert_eq!(crc, masked(data), "data CRC at byte {at}");
        at += 16 + n;
        let event = fields(data);
        let step = event.iter().find(|f| f.0 == 2).map_or(0, |f| f.3);
        if first {
            let version = event.iter().find(|f| f.0 == 3).expect("file_version first");
            assert_eq!(version.2, b"brain.Event:2");
            first = false;
            continue;
        }
        let summary = event.iter().find(|f| f.0 == 5).expect("a summary");
        for value in fields(&summary.2).into_iter().filter(|f| f.0 == 1) {
            let value = fields(&value.2);
            let tag =
                String::from_utf8(value.iter().find(|f| f.0 == 1).unwrap().2.clone()).unwrap();
            if let Some(simple) = value.iter().find(|f| f.0 == 2) {
                let v = f32::from_le_bytes(simple.2[..4].try_into().unwrap());
                scalars.entry(tag).or_default().push((step, v));
            } else {
                let image = fields(&value.iter().find(|f| f.0 == 4).unwrap().2);
                let png = &image.iter().find(|f| f.0 == 4).unwrap().2;
                let decoded = image::load_from_memory(png).unwrap();
                let (h, w) = (image[0].3 as u32, image[1].3 as u32);
                assert_eq!((decoded.width(), decoded.height()), (w, h));
                images.push((tag, step));
            }
        }
    }
    // One loss event per optimisation step: 10 fitting frame 0, 3 + 1 for frame 1.
    assert_eq!(scalars["loss/total"].len(), 14);
    assert_eq!(scalars["loss/total"].last().unwrap().0, 13);
    let psnr = &scalars["frame/held_out_psnr_db"];
    assert_eq!(psnr.len(), 2);
    for (t, report) in reports.iter().enumerate() {
        assert_eq!(psnr[t].0, t as u64);
        assert!((psnr[t].1 as f64 - report.test_psnr.unwrap()).abs() < 1e-3);
    }
    assert_eq!(
        images,
        [
            ("held_out/reference_vs_render".to_string(), 0),
            ("held_out/reference_vs_render".to_string(), 1)
        ]
    );
}
