//! Named f32 arrays in one safetensors file: what checkpoints, per-frame states and the
//! synthetic ground truth are stored as.

use std::collections::BTreeMap;
use std::path::Path;

use safetensors::{Dtype, SafeTensors, serialize, tensor::TensorView};

use crate::TrainError;

fn array_error(path: &Path, reason: impl ToString) -> TrainError {
    TrainError::Arrays {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

/// Host f32 arrays by name, with shapes.
pub type HostArrays = BTreeMap<String, (Vec<usize>, Vec<f32>)>;

/// Writes f32 arrays as one safetensors file (atomically).
pub fn write_arrays(path: &Path, arrays: &HostArrays) -> Result<(), TrainError> {
    let bytes: Vec<(String, Vec<u8>, Vec<usize>)> = arrays
        .iter()
        .map(|(name, (shape, values))| {
            let raw = values.iter().flat_map(|v| v.to_le_bytes()).collect();
            (name.clone(), raw, shape.clone())
        })
        .collect();
    let views: Vec<(String, TensorView)> = bytes
        .iter()
        .map(|(name, raw, shape)| {
            let view = TensorView::new(Dtype::F32, shape.clone(), raw)
                .expect("shape matches the number of values");
            (name.clone(), view)
        })
        .collect();
    let data = serialize(views, None).map_err(|e| array_error(path, e))?;
    crate::export::write_atomic(path, &data)
}

/// Reads every f32 array of a safetensors file.
pub fn read_arrays(path: &Path) -> Result<HostArrays, TrainError> {
    let bytes = std::fs::read(path).map_err(|source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let file = SafeTensors::deserialize(&bytes).map_err(|e| array_error(path, e))?;
    let mut out = HostArrays::new();
    for (name, view) in file.tensors() {
        if view.dtype() != Dtype::F32 {
            return Err(array_error(path, format!("`{name}` is not f32")));
        }
        let values = view
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        out.insert(name, (view.shape().to_vec(), values));
    }
    Ok(out)
}

/// Takes array `name` out of `arrays`, checking its shape.
pub fn take_array(
    arrays: &mut HostArrays,
    name: &str,
    shape: &[usize],
    path: &Path,
) -> Result<Vec<f32>, TrainError> {
    let (found, values) = arrays
        .remove(name)
        .ok_or_else(|| array_error(path, format!("no array `{name}`")))?;
    if found != shape {
        return Err(array_error(
            path,
            format!("`{name}` has shape {found:?}, expected {shape:?}"),
        ));
    }
    Ok(values)
}
