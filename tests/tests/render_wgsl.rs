//! The backward rasterisation kernel compiled to WGSL and validated by naga, as wgpu does
//! before it runs a shader, in each of its three forms ([`GradientSums`]), including the plane
//! sums that lavapipe (CI's device) cannot run because wgpu does not give it subgroups.
//! `render_gpu.rs` runs the other two forms against the torch goldens and the CPU path.
//!
//! Needs a GPU adapter only for the compute client the kernel is expanded with (lavapipe in
//! CI); fails without one.

use std::sync::Arc;

use burn::backend::DispatchDevice;
use burn::backend::ops::FloatTensorOps;
use burn::tensor::TensorData;
use burn_cubecl::CubeBackend;
use burn_cubecl::cubecl::Compiler;
use burn_cubecl::cubecl::features::Plane;
use burn_cubecl::cubecl::prelude::*;
use burn_cubecl::cubecl::wgpu::WgslCompiler;
use gausmoke_render::GradientSums;
use gausmoke_render::backends::gpu_devices;
use gausmoke_render::kernels::atomics::CasAdd;
use gausmoke_render::kernels::backward::rasterize::rasterize_backward_kernel;
use gausmoke_render::kernels::buffers::buffer;
use gausmoke_render::kernels::rasterize::TILE_THREADS;

/// WGSL of the backward kernel in form `sums`, expanded for the first GPU device with plane
/// operations switched on in its properties when `planes`.
fn backward_wgsl(sums: GradientSums, planes: bool) -> String {
    let devices = gpu_devices();
    let (_, device) = devices
        .first()
        .expect("this test binary must be built with a GPU feature of gausmoke-render");
    let DispatchDevice::Cube(device) = device.as_dispatch() else {
        panic!("not a cube device");
    };
    let tensor = CubeBackend::float_from_data(TensorData::new(vec![0.0f32; 64], [64]), device);
    let client = tensor.client.clone();
    let mut properties = client.properties().clone();
    if planes {
        properties.features.plane.insert(Plane::Ops);
    }
    let arg = || buffer(&tensor);
    let kernel = rasterize_backward_kernel::create_dummy_kernel::<CasAdd>(
        Arc::new(properties),
        client.target_properties_shared(),
        CubeCount::Static(1, 1, 1),
        CubeDim::new_1d(TILE_THREADS as u32),
        arg(),
        arg(),
        arg(),
        arg(),
        arg(),
        arg(),
        arg(),
        arg(),
        arg(),
        16u32,
        16u32,
        sums,
    );
    let shader = WgslCompiler
        .compile(kernel.define(), &Default::default())
        .unwrap_or_else(|e| panic!("{sums:?}: cubecl could not compile the kernel: {e:?}"));
    shader.to_string()
}

/// naga's parse and validation of `source`, with the subgroup capability when `subgroups`.
fn validate(source: &str, subgroups: bool) -> Result<(), String> {
    let module = naga::front::wgsl::parse_str(source).map_err(|e| e.emit_to_string(source))?;
    let capabilities = if subgroups {
        naga::valid::Capabilities::SUBGROUP
    } else {
        naga::valid::Capabilities::empty()
    };
    naga::valid::Validator::new(naga::valid::ValidationFlags::all(), capabilities)
        .subgroup_stages(naga::valid::ShaderStages::COMPUTE)
        .subgroup_operations(naga::valid::SubgroupOperationSet::all())
        .validate(&module)
        .map(|_| ())
        .map_err(|e| e.emit_to_string(source))
}

#[test]
fn plane_sums_pass_naga_with_subgroups_and_only_with_them() {
    let source = backward_wgsl(GradientSums::Planes, true);
    assert!(
        source.contains("subgroupAdd") && source.contains("subgroupAny"),
        "the plane form should sum with subgroup operations:\n{source}"
    );
    if let Err(e) = validate(&source, true) {
        panic!("naga rejects the plane-sum kernel:\n{e}");
    }
    assert!(
        validate(&source, false).is_err(),
        "naga should refuse subgroup operations without the capability (the check is live)"
    );
}

#[test]
fn shared_and_per_pixel_forms_pass_naga_without_subgroups() {
    for sums in [GradientSums::SharedMemory, GradientSums::PerPixel] {
        let source = backward_wgsl(sums, false);
        assert!(!source.contains("subgroup"), "{sums:?} uses no subgroups");
        if let Err(e) = validate(&source, false) {
            panic!("naga rejects the {sums:?} kernel:\n{e}");
        }
    }
}
