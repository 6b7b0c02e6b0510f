//! What a convolution of the U-Net is (plain data, so it can cross burn's dispatch).

use burn::tensor::ops::{ConvOptions, ConvTransposeOptions};

/// A 3D convolution or transposed convolution: no dilation, no groups, batch 1.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConvSpec {
    pub kernel: [usize; 3],
    pub stride: [usize; 3],
    pub padding: [usize; 3],
    pub transposed: bool,
}

impl ConvSpec {
    /// burn's options for the same convolution.
    pub fn options(&self) -> ConvOptions<3> {
        ConvOptions::new(self.stride, self.padding, [1; 3], 1)
    }

    /// burn's options for the same transposed convolution.
    pub fn transpose_options(&self) -> ConvTransposeOptions<3> {
        ConvTransposeOptions::new(self.stride, self.padding, [0; 3], [1; 3], 1)
    }

    /// Output cells per axis of the transposed convolution of `input` cells.
    pub fn transposed_output(&self, input: [usize; 3]) -> [usize; 3] {
        [0, 1, 2].map(|a| (input[a] - 1) * self.stride[a] + self.kernel[a] - 2 * self.padding[a])
    }
}
