//! The burn devices this build can render on, by name (what tests, benchmarks and `--device`
//! iterate over).

use burn::tensor::Device;

/// CPU devices compiled into this build (cargo features `flex`, `ndarray`), by name, the
/// preferred one first (Flex: burn's maintained pure-Rust CPU backend).
pub fn cpu_devices() -> Vec<(&'static str, Device)> {
    #[allow(deprecated)] // NdArray is deprecated upstream; see ops.rs
    Vec::from([
        #[cfg(feature = "flex")]
        ("flex", Device::flex()),
        #[cfg(feature = "ndarray")]
        ("ndarray", Device::ndarray()),
    ])
}

/// GPU devices compiled into this build (cargo features `wgpu`, `vulkan`, `cuda`), by name.
/// Creating a device does not touch the hardware; the first tensor on it does, and fails there
/// when no adapter exists. `wgpu` picks the best adapter (override with
/// `CUBECL_WGPU_DEFAULT_DEVICE`, e.g. `Cpu` for Mesa's lavapipe); `vulkan` pins the Vulkan API
/// and its SPIR-V compiler (native float atomics).
#[allow(clippy::vec_init_then_push)] // the pushes are feature-gated
pub fn gpu_devices() -> Vec<(&'static str, Device)> {
    #[allow(unused_mut)]
    let mut devices = Vec::new();
    #[cfg(feature = "wgpu")]
    devices.push((
        "wgpu",
        Device::wgpu(burn::tensor::DeviceKind::DefaultDevice),
    ));
    #[cfg(feature = "vulkan")]
    devices.push((
        "vulkan",
        Device::vulkan(burn::tensor::DeviceKind::DefaultDevice),
    ));
    #[cfg(feature = "cuda")]
    devices.push(("cuda", Device::cuda(0)));
    devices
}

/// Every device compiled into this build: GPUs first, then CPUs.
pub fn all_devices() -> Vec<(&'static str, Device)> {
    let mut devices = gpu_devices();
    devices.extend(cpu_devices());
    devices
}

/// The compiled device called `name`, or the list of names to choose from.
pub fn device_by_name(name: &str) -> Result<Device, String> {
    let devices = all_devices();
    let names: Vec<&str> = devices.iter().map(|(n, _)| *n).collect();
    devices
        .into_iter()
        .find(|(n, _)| *n == name)
        .map(|(_, d)| d)
        .ok_or_else(|| {
            format!(
                "device `{name}` is not compiled into this build; available: {}",
                names.join(", ")
            )
        })
}
