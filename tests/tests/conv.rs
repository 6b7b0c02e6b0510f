//! The U-Net's convolution op against burn's own Conv3d / ConvTranspose3d modules on every CPU
//! backend: outputs and the gradients of the input, weights and bias, for each layer shape
//! the U-Net uses (3^3 padded, 2^3 strided down, 2^3 transposed up, 1^3).
//!
//! Tolerance: both sum the same products in different orders (ours tiles im2col through
//! `gemm`): measured within 7e-7 of each tensor's largest magnitude (2026-11-26,
//! `GAUSMOKE_PRINT_ERRORS=1 ... -- --nocapture`); bound 1e-5.

use gausmoke_render::backends::cpu_devices;
use gausmoke_tests::assert_close;
use gausmoke_tests::conv::{Arithmetic, RESULTS, UNET_LAYERS, outputs_and_gradients};

#[test]
fn matches_burns_convolutions_and_their_gradients() {
    for (backend, device) in cpu_devices() {
        let device = device.autodiff();
        for (i, &(input, layer)) in UNET_LAYERS.iter().enumerate() {
            let burns = outputs_and_gradients(input, layer, Arithmetic::Burns, &device);
            let ours = outputs_and_gradients(input, layer, Arithmetic::Ours, &device);
            for (name, (a, b)) in RESULTS.iter().zip(ours.iter().zip(&burns)) {
                assert!(
                    b.iter().any(|v| *v != 0.0),
                    "{backend}, layer {i}: {name}: vacuous"
                );
                assert_close(&format!("{backend}, layer {i}: {name}"), a, b, 0.0, 1e-5);
            }
        }
    }
}
