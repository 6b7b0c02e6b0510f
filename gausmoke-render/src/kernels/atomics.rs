//! Float addition into buffers that many threads write at once: a native `f32` atomic add
//! where the device has one, else a compare-and-swap loop on the bits. Launchers pick one with
//! [`native_float_atomics`].

use burn_cubecl::cubecl::features::AtomicUsage;
use burn_cubecl::cubecl::ir::{FloatKind, Type};
use cubecl::prelude::*;

use crate::FloatAtomics;

#[cube]
pub trait GradientAdd: Send + Sync + 'static {
    type Cell: Numeric;
    fn add(cells: &mut [Atomic<Self::Cell>], index: usize, value: f32);
}

/// Native `f32` atomic add.
#[derive(CubeType)]
pub struct NativeAdd;

/// Compare-and-swap on the `u32` bits of an `f32`.
#[derive(CubeType)]
pub struct CasAdd;

#[cube]
impl GradientAdd for NativeAdd {
    type Cell = f32;
    fn add(cells: &mut [Atomic<f32>], index: usize, value: f32) {
        cells[index].fetch_add(value);
    }
}

#[cube]
impl GradientAdd for CasAdd {
    type Cell = u32;
    fn add(cells: &mut [Atomic<u32>], index: usize, value: f32) {
        if value != 0.0 {
            let mut current = cells[index].load();
            loop {
                let expected = current;
                let updated = (f32::from_bits(expected) + value).to_bits();
                current = cells[index].compare_exchange_weak(expected, updated);
                if current == expected {
                    break;
                }
            }
        }
    }
}

/// Whether kernels on `client` should add floats natively: the device has `f32` atomic add in
/// storage buffers and `choice` does not ask for the fallback.
pub fn native_float_atomics(client: &Client, choice: FloatAtomics) -> bool {
    choice == FloatAtomics::Native
        && client
            .properties()
            .atomic_type_usage(Type::atomic(FloatKind::F32))
            .contains(AtomicUsage::Add)
}
