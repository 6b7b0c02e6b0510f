//! The velocity fields and grid the device projection tests share (`projection_gpu.rs`,
//! `projection_deferred_gpu.rs`).

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::SplitMix64;
use gausmoke_core::glam::Vec3;
use gausmoke_model::{GridSpec, ProjectionOptions, project_velocity};
use gausmoke_render::backends::gpu_devices;

use crate::to_vec;

/// Non-cubic, with unequal cell sizes per axis: a wrong stride, axis or cell size in the
/// kernels fails here.
pub fn grid() -> GridSpec {
    GridSpec::new(
        Vec3::new(-1.0, -0.5, 0.0),
        Vec3::new(1.0, 1.3, 0.7),
        [18, 13, 11],
        1,
    )
    .unwrap()
}

/// A smooth divergent field (a source and a sink) plus noise, `[nx, ny, nz, 3]` flat.
pub fn velocity(grid: &GridSpec, seed: u64) -> Vec<f32> {
    let mut rng = SplitMix64::new(seed);
    let centres = grid.cell_centres();
    centres
        .chunks(3)
        .flat_map(|c| {
            let p = Vec3::from_slice(c);
            let source = (p - Vec3::new(-0.3, 0.2, 0.3)) * (-(p.length_squared()) * 2.0).exp();
            let sink = (Vec3::new(0.4, 0.6, 0.4) - p) * 0.5;
            let v = source + sink;
            [v.x, v.y, v.z]
        })
        .map(|v| v + 0.2 * (rng.uniform() - 0.5))
        .collect()
}

/// The first GPU device of this build, by name.
pub fn gpu_device() -> (&'static str, Device) {
    let mut devices = gpu_devices();
    assert!(
        !devices.is_empty(),
        "this test binary must be built with a GPU feature of gausmoke-model"
    );
    devices.remove(0)
}

/// `values` as a `[nx, ny, nz, 3]` velocity tensor on `device`.
pub fn velocity_tensor(values: &[f32], grid: &GridSpec, device: &Device) -> Tensor<4> {
    let [nx, ny, nz] = grid.resolution();
    Tensor::from_data(TensorData::new(values.to_vec(), [nx, ny, nz, 3]), device)
}

/// `Pi(values)` on `device`, read back.
pub fn device_projection(
    values: &[f32],
    grid: &GridSpec,
    device: &Device,
    options: ProjectionOptions,
) -> Vec<f32> {
    to_vec(project_velocity(
        grid,
        velocity_tensor(values, grid, device),
        options,
    ))
}
