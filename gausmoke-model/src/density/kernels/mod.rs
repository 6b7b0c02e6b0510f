//! Density splatting ([`crate::density`]) as cubecl kernels for the cube backends: the forward
//! pass scatters with float atomics (native where the device has them, else compare-and-swap),
//! the backward pass gathers per Gaussian. Both take one unit per Gaussian and walk exactly the
//! cells the host path visits; both whiten each Gaussian with the renderer's kernel maths
//! (`gausmoke_render::kernels::math`), in the world frame. The atomic sums are not ordered:
//! results agree with the CPU path to float tolerance, not bit for bit.

mod backward;
mod forward;
mod support;

use burn::tensor::DType;
use burn_cubecl::tensor::CubeTensor;
use cubecl::prelude::*;
use gausmoke_render::FloatAtomics;
use gausmoke_render::Gaussians;
use gausmoke_render::kernels::atomics::{CasAdd, NativeAdd, native_float_atomics};
use gausmoke_render::kernels::buffers::{
    Allocator, GAUSSIAN_BLOCK, buffer, contiguous_f32, contiguous_gaussians, leading, linear_cubes,
};

use crate::density::host::{DensityField, SplatGrid};
use support::grid_params;

fn resolution_u32(grid: &SplatGrid) -> [u32; 3] {
    grid.resolution.map(|n| {
        u32::try_from(n).expect("grid resolution checked by GridSpec (under 8 GiB per tensor)")
    })
}

/// `field` of the Gaussians at the grid's cell centres, on the device.
pub fn splat_field(
    gaussians: Gaussians<CubeTensor>,
    grid: &SplatGrid,
    field: DensityField,
    float_atomics: FloatAtomics,
) -> CubeTensor {
    let g = contiguous_gaussians(gaussians);
    let alloc = Allocator::like(&g.means);
    let n = g.raw_densities.meta.num_elements();
    let len = field.channels() * grid.cells();
    let output = alloc.zeros(len, DType::F32);
    let params = alloc.f32s(&grid_params(grid));
    let [nx, ny, nz] = resolution_u32(grid);
    let (density, gradient) = (field.has_density(), field.has_gradient());
    macro_rules! launch_forward {
        ($adder:ty) => {
            forward::splat_field_kernel::launch::<$adder>(
                &alloc.client,
                linear_cubes(n),
                CubeDim::new_1d(GAUSSIAN_BLOCK),
                buffer(&g.means),
                buffer(&g.rotations),
                buffer(&g.log_scales),
                buffer(&g.raw_densities),
                buffer(&params),
                buffer(&output),
                nx,
                ny,
                nz,
                n as u32,
                density,
                gradient,
            )
        };
    }
    if n > 0 && len > 0 {
        if native_float_atomics(&alloc.client, float_atomics) {
            launch_forward!(NativeAdd);
        } else {
            launch_forward!(CasAdd);
        }
    }
    leading(output, field.shape(grid))
}

/// Gradients of the geometric attributes (means, rotations, log-scales, raw densities; the
/// colour slot holds zeros) of [`splat_field`] given the gradient of its output.
pub fn splat_field_backward(
    gaussians: Gaussians<CubeTensor>,
    grid: &SplatGrid,
    field: DensityField,
    grad: CubeTensor,
) -> Gaussians<CubeTensor> {
    let g = contiguous_gaussians(gaussians);
    let grad = contiguous_f32(grad, "density grid gradient");
    assert_eq!(
        grad.meta.num_elements(),
        field.channels() * grid.cells(),
        "the gradient of the density field must match the field's shape {:?}",
        field.shape(grid)
    );
    let alloc = Allocator::like(&g.means);
    let n = g.raw_densities.meta.num_elements();
    let grads = Gaussians::default().map(|attribute, ()| {
        if attribute.name == "colors" {
            alloc.zeros(n * attribute.columns, DType::F32)
        } else {
            alloc.empty(n * attribute.columns, DType::F32)
        }
    });
    let params = alloc.f32s(&grid_params(grid));
    let [nx, ny, nz] = resolution_u32(grid);
    if n > 0 {
        backward::splat_field_backward_kernel::launch(
            &alloc.client,
            linear_cubes(n),
            CubeDim::new_1d(GAUSSIAN_BLOCK),
            buffer(&g.means),
            buffer(&g.rotations),
            buffer(&g.log_scales),
            buffer(&g.raw_densities),
            buffer(&params),
            buffer(&grad),
            buffer(&grads.means),
            buffer(&grads.rotations),
            buffer(&grads.log_scales),
            buffer(&grads.raw_densities),
            nx,
            ny,
            nz,
            n as u32,
            field.has_density(),
            field.has_gradient(),
        );
    }
    gausmoke_render::kernels::buffers::gradient_shapes(grads, n)
}
