//! Host-side helpers for launching kernels on burn's cube tensors: contiguous f32 inputs,
//! scratch buffers, flat results reshaped, and grid sizes.

use burn::backend::ops::FloatTensorOps;
use burn::tensor::{DType, TensorData};
use burn_cubecl::CubeBackend;
use burn_cubecl::kernel::into_contiguous;
use burn_cubecl::ops::numeric::{empty_device_contiguous_dtype, zeros_client};
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;

use crate::gaussians::Gaussians;

/// Units per cube of the per-Gaussian (and per-cell) kernels.
pub const GAUSSIAN_BLOCK: u32 = 256;

/// A device buffer argument covering all of `tensor` (which must be contiguous).
pub fn buffer(tensor: &CubeTensor) -> BufferArg {
    tensor.clone().into_buffer_arg()
}

/// `tensor` as a contiguous f32 buffer; panics naming `name` for another dtype (the kernels
/// are f32 only).
pub fn contiguous_f32(tensor: CubeTensor, name: &str) -> CubeTensor {
    assert_eq!(
        tensor.dtype,
        DType::F32,
        "the GPU kernels work in f32; `{name}` is {:?}",
        tensor.dtype
    );
    into_contiguous(tensor)
}

/// Every attribute contiguous f32, named in a panic otherwise.
pub fn contiguous_gaussians(gaussians: Gaussians<CubeTensor>) -> Gaussians<CubeTensor> {
    gaussians.map(|attribute, tensor| contiguous_f32(tensor, attribute.name))
}

/// Number of cubes of [`GAUSSIAN_BLOCK`] units covering `n` items.
pub fn linear_cubes(n: usize) -> CubeCount {
    let cubes = n.div_ceil(GAUSSIAN_BLOCK as usize).max(1);
    assert!(
        cubes <= u16::MAX as usize,
        "{n} items exceed the per-launch limit of these kernels ({} items)",
        u16::MAX as usize * GAUSSIAN_BLOCK as usize
    );
    CubeCount::Static(cubes as u32, 1, 1)
}

/// Where new buffers go: the client and device of an existing tensor.
#[derive(Clone)]
pub struct Allocator {
    pub client: Client,
    pub device: burn_cubecl::CubeDevice,
}

impl Allocator {
    pub fn like(tensor: &CubeTensor) -> Self {
        Self {
            client: tensor.client.clone(),
            device: tensor.device.clone(),
        }
    }

    /// An uninitialised flat buffer of `len` elements (at least one: zero-sized allocations
    /// are avoided).
    pub fn empty(&self, len: usize, dtype: DType) -> CubeTensor {
        self.empty_shaped(vec![len.max(1)], dtype)
    }

    pub fn empty_shaped(&self, shape: Vec<usize>, dtype: DType) -> CubeTensor {
        empty_device_contiguous_dtype(
            self.client.clone(),
            self.device.clone(),
            shape.into(),
            dtype,
        )
    }

    /// A zeroed flat buffer of `len` elements (at least one).
    pub fn zeros(&self, len: usize, dtype: DType) -> CubeTensor {
        zeros_client(
            self.client.clone(),
            self.device.clone(),
            [len.max(1)].into(),
            dtype,
        )
    }

    /// `values` uploaded as a flat f32 buffer.
    pub fn f32s(&self, values: &[f32]) -> CubeTensor {
        CubeBackend::float_from_data(
            TensorData::new(values.to_vec(), [values.len()]),
            &self.device,
        )
    }
}

/// The leading `shape.product()` values of a flat buffer (kernel buffers hold at least one
/// element), reshaped to `shape`.
pub fn leading(tensor: CubeTensor, shape: Vec<usize>) -> CubeTensor {
    let len: usize = shape.iter().product();
    let flat = burn_cubecl::ops::reshape(tensor.clone(), [tensor.meta.num_elements()].into());
    let flat = if len == flat.meta.num_elements() {
        flat
    } else {
        #[allow(clippy::single_range_in_vec_init)] // one range per dimension
        burn_cubecl::kernel::slice(flat, &[0..len])
    };
    burn_cubecl::ops::reshape(flat, shape.into())
}

/// Flat per-attribute gradient buffers, as tensors of the attributes' shapes.
pub fn gradient_shapes(grads: Gaussians<CubeTensor>, n: usize) -> Gaussians<CubeTensor> {
    grads.map(|attribute, tensor| leading(tensor, attribute.shape(n)))
}
