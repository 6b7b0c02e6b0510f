//! Backend primitives to host arrays and back, for the CPU implementations of the custom ops
//! (these backends hold their tensors in host memory, so reading one is a copy).

use burn::backend::Backend;
use burn::backend::tensor::FloatTensor;
use burn::tensor::{TensorData, read_sync};

use crate::gaussians::{GaussianPrimitives, HostGaussians};

pub fn to_vec<B: Backend>(tensor: FloatTensor<B>) -> Vec<f32> {
    let data = read_sync(B::float_into_data(tensor)).expect("reading a CPU tensor cannot fail");
    data.try_into_vec_as::<f32>()
        .expect("CPU backends hold float tensors")
}

pub fn from_vec<B: Backend>(
    values: Vec<f32>,
    shape: Vec<usize>,
    device: &B::Device,
) -> FloatTensor<B> {
    B::float_from_data(TensorData::new(values, shape), device)
}

/// Host copies of the Gaussians.
pub fn host_gaussians<B: Backend>(gaussians: GaussianPrimitives<B>) -> HostGaussians {
    gaussians.map(|_, t| to_vec::<B>(t))
}

/// Host gradients as tensors of the attributes' shapes.
pub fn gradient_tensors<B: Backend>(
    grads: HostGaussians,
    device: &B::Device,
) -> GaussianPrimitives<B> {
    let n = grads.len();
    grads.map(|attribute, values| from_vec::<B>(values, attribute.shape(n), device))
}
