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

/// The compiled device called `name`, or the list of names to choose from.
pub fn device_by_name(name: &str) -> Result<Device, String> {
    let devices = cpu_devices();
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
