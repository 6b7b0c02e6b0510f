//! AlexNet LPIPS against the `lpips` Python package (golden written by
//! `xtask/reference/lpips_export.py golden tests/goldens`): the package's real linear heads
//! and scaling layer, the convolutions set to a formula both sides compute, on every CPU
//! backend. Also: a weights file with a missing or misshapen tensor is refused by name.

use std::collections::BTreeMap;
use std::path::PathBuf;

use gausmoke_render::backends::cpu_devices;
use gausmoke_train::lpips::Lpips;
use safetensors::{Dtype, SafeTensors, tensor::TensorView};

const CONVOLUTIONS: [(&str, [usize; 4]); 5] = [
    ("net.slice1.0", [64, 3, 11, 11]),
    ("net.slice2.3", [192, 64, 5, 5]),
    ("net.slice3.6", [384, 192, 3, 3]),
    ("net.slice4.8", [256, 384, 3, 3]),
    ("net.slice5.10", [256, 256, 3, 3]),
];

fn golden_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/goldens/lpips_alexnet.safetensors")
}

fn floats(file: &SafeTensors, name: &str) -> Vec<f32> {
    file.tensor(name)
        .unwrap()
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// `formula_weights` of lpips_export.py.
fn formula(shape: [usize; 4], layer: usize) -> (Vec<f32>, Vec<f32>) {
    let fan_in = (shape[1] * shape[2] * shape[3]) as f64;
    let count: usize = shape.iter().product();
    let weights = (0..count)
        .map(|j| {
            ((2.0 / fan_in).sqrt() * (12.9898 * j as f64 + 1.7 * (layer + 1) as f64).sin()) as f32
        })
        .collect();
    let biases = (0..shape[0])
        .map(|o| (0.01 * (o as f64).cos()) as f32)
        .collect();
    (weights, biases)
}

/// A weights file: the golden's heads and scaling, formula convolutions, minus `skip`.
fn weights_file(dir: &std::path::Path, skip: Option<&str>, bad_shape: Option<&str>) -> PathBuf {
    let bytes = std::fs::read(golden_path()).unwrap();
    let golden = SafeTensors::deserialize(&bytes).unwrap();
    let mut tensors: BTreeMap<String, (Vec<usize>, Vec<f32>)> = BTreeMap::new();
    for name in golden.names() {
        if name.starts_with("lin") || name.starts_with("scaling_layer") {
            let shape = golden.tensor(name).unwrap().shape().to_vec();
            tensors.insert(name.to_string(), (shape, floats(&golden, name)));
        }
    }
    for (layer, (prefix, shape)) in CONVOLUTIONS.iter().enumerate() {
        let (w, b) = formula(*shape, layer);
        tensors.insert(format!("{prefix}.weight"), (shape.to_vec(), w));
        tensors.insert(format!("{prefix}.bias"), (vec![shape[0]], b));
    }
    if let Some(name) = skip {
        tensors.remove(name);
    }
    if let Some(name) = bad_shape {
        let (shape, _) = tensors.get_mut(name).unwrap();
        shape.reverse();
    }
    let raw: Vec<(String, Vec<usize>, Vec<u8>)> = tensors
        .into_iter()
        .map(|(name, (shape, values))| {
            let bytes = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            (name, shape, bytes)
        })
        .collect();
    let views: Vec<(String, TensorView)> = raw
        .iter()
        .map(|(name, shape, bytes)| {
            (
                name.clone(),
                TensorView::new(Dtype::F32, shape.clone(), bytes).unwrap(),
            )
        })
        .collect();
    let path = dir.join(format!("weights-{skip:?}-{bad_shape:?}.safetensors"));
    std::fs::write(&path, safetensors::serialize(views, None).unwrap()).unwrap();
    path
}

#[test]
fn lpips_matches_the_python_package() {
    let dir = tempfile::tempdir().unwrap();
    let path = weights_file(dir.path(), None, None);
    let bytes = std::fs::read(golden_path()).unwrap();
    let golden = SafeTensors::deserialize(&bytes).unwrap();
    let [h, w, _]: [usize; 3] = golden
        .tensor("image_a")
        .unwrap()
        .shape()
        .try_into()
        .unwrap();
    let (a, b) = (floats(&golden, "image_a"), floats(&golden, "image_b"));
    let expected = floats(&golden, "distance")[0] as f64;
    for (backend, device) in cpu_devices() {
        let lpips = Lpips::load(&path, &device).unwrap();
        let distance = lpips.distance(&a, &b, w, h);
        let same = lpips.distance(&a, &a, w, h);
        eprintln!("{backend}: LPIPS {distance:.6} (lpips package {expected:.6}), same {same:.1e}");
        assert!(
            (distance - expected).abs() < 1e-4 * expected.max(1e-3),
            "{backend}: {distance} vs {expected}"
        );
        assert!(same.abs() < 1e-9, "{backend}: identical images give {same}");
    }
}

#[test]
fn bad_weight_files_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let (_, device) = cpu_devices().remove(0);
    let missing = weights_file(dir.path(), Some("lin3.model.1.weight"), None);
    let err = Lpips::load(&missing, &device).err().unwrap().to_string();
    assert!(
        err.contains("lin3.model.1.weight") && err.contains("missing"),
        "{err}"
    );
    let misshapen = weights_file(dir.path(), None, Some("net.slice2.3.weight"));
    let err = Lpips::load(&misshapen, &device).err().unwrap().to_string();
    assert!(
        err.contains("net.slice2.3.weight") && err.contains("shape"),
        "{err}"
    );
    let err = Lpips::load(&dir.path().join("nope.safetensors"), &device)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("nope.safetensors"), "{err}");
}
