//! The burn devices this build can render on, by name (what tests, benchmarks and `--device`
//! iterate over).

use burn::tensor::Device;

/// CPU devices compiled into this build (cargo features `ndarray`, `flex`), by name.
pub fn cpu_devices() -> Vec<(&'static str, Device)> {
    #[allow(unused_mut)]
    let mut devices = Vec::new();
    #[cfg(feature = "ndarray")]
    #[allow(deprecated)] // NdArray is deprecated upstream; see ops.rs
    devices.push(("ndarray", Device::ndarray()));
    #[cfg(feature = "flex")]
    devices.push(("flex", Device::flex()));
    devices
}
