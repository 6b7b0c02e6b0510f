//! Our SSIM and PSNR against scikit-image's on fixed image pairs
//! (`tests/goldens/metrics_skimage.safetensors`, written by xtask/reference/metrics_golden.py
//! with scikit-image 0.25.2).

use std::path::Path;

use gausmoke_train::arrays::read_arrays;
use gausmoke_train::metrics::{psnr, ssim};

#[test]
fn ssim_and_psnr_match_scikit_image() {
    let path =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/goldens/metrics_skimage.safetensors");
    let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let meta = header.metadata().as_ref().expect("golden metadata");
    let arrays = read_arrays(&path).unwrap();
    let image = |name: &str| -> (&[f32], usize, usize) {
        let (shape, values) = &arrays[name];
        (values, shape[1], shape[0])
    };
    let pairs: Vec<&str> = meta["pairs"].split(',').collect();
    assert_eq!(pairs.len(), 4);
    for pair in pairs {
        let (a, width, height) = image(&format!("{pair}.a"));
        let (b, _, _) = image(&format!("{pair}.b"));
        let expected_ssim: f64 = meta[&format!("{pair}.ssim")].parse().unwrap();
        let expected_psnr: f64 = meta[&format!("{pair}.psnr")].parse().unwrap();
        let ours_ssim = ssim(a, b, width, height);
        let ours_psnr = psnr(a, b);
        eprintln!(
            "{pair}: SSIM {ours_ssim:.10} vs {expected_ssim:.10}, PSNR {ours_psnr:.8} vs {expected_psnr:.8}"
        );
        assert!(
            (ours_ssim - expected_ssim).abs() < 1e-6,
            "{pair}: SSIM {ours_ssim} vs scikit-image {expected_ssim}"
        );
        assert!(
            (ours_psnr - expected_psnr).abs() < 1e-5,
            "{pair}: PSNR {ours_psnr} vs scikit-image {expected_psnr}"
        );
    }
}
