//! The U-Net's convolution op on a GPU backend (wgpu; in CI on Mesa's lavapipe) against the
//! same op on the CPU (Flex, whose im2col path `conv.rs` checks against burn's own layers):
//! outputs and the gradients of the input, weights and bias for every layer shape the U-Net
//! uses, and for the shapes that take the GPU backward's other branches (a stride that leaves
//! input cells unreached; a grid plane over 8192 cells; im2col slices split into groups to
//! bound their memory).
//!
//! Like the other GPU tests this FAILS without a GPU adapter rather than skip.
//!
//! Tolerance: both sum the same products in different orders; measured on lavapipe
//! (2026-11-26, `GAUSMOKE_PRINT_ERRORS=1`) within 7e-6 of each tensor's largest magnitude;
//! bound 2e-5.

use gausmoke_render::backends::{device_by_name, gpu_devices};
use gausmoke_tests::assert_close;
use gausmoke_tests::conv::{Arithmetic, Layer, RESULTS, UNET_LAYERS, outputs_and_gradients};

fn compare(cases: &[([usize; 5], Layer)]) {
    let (backend, gpu) = gpu_devices()
        .into_iter()
        .next()
        .expect("this test binary is built with gausmoke-model's wgpu feature");
    let cpu = device_by_name("flex").unwrap().autodiff();
    let gpu = gpu.autodiff();
    for &(input, layer) in cases {
        let expected = outputs_and_gradients(input, layer, Arithmetic::Ours, &cpu);
        let actual = outputs_and_gradients(input, layer, Arithmetic::Ours, &gpu);
        for (name, (a, e)) in RESULTS.iter().zip(actual.iter().zip(&expected)) {
            assert!(e.iter().any(|v| *v != 0.0), "{name}: vacuous");
            assert_close(
                &format!("{backend}, {layer:?} on {input:?}: {name}"),
                a,
                e,
                0.0,
                2e-5,
            );
        }
    }
}

/// The U-Net's layers, and a stride that leaves the last input cells unreached by the
/// forward pass (their gradient is zero).
#[test]
fn the_unet_layers_match_the_cpu_on_the_gpu() {
    let mut cases = UNET_LAYERS.to_vec();
    cases.push(([1, 3, 5, 7, 6], Layer::conv([3, 4], 2, 2, 0)));
    compare(&cases);
}

/// A grid plane of more than 8192 cells (the weight gradient's batches are then rows, not
/// planes), and a 3^3 kernel whose im2col slices exceed the 64 MiB budget together (32
/// channels of a 48^3 grid: split into groups of taps).
#[test]
fn the_large_shapes_of_the_gpu_backward_match_the_cpu() {
    compare(&[
        ([1, 2, 3, 96, 96], Layer::conv([2, 3], 3, 1, 1)),
        ([1, 32, 48, 48, 48], Layer::conv([32, 4], 3, 1, 1)),
    ]);
}
