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

/// The header metadata key of the checksum every file written here carries, so a damaged
/// file is refused when read rather than trained on or scored.
const CHECKSUM_KEY: &str = "gausmoke_fnv1a";

/// FNV-1a over each array's name, shape and little-endian bytes, in name order.
fn checksum<'a>(arrays: impl IntoIterator<Item = (&'a str, &'a [usize], &'a [u8])>) -> String {
    let mut hash = crate::hash::Fnv1a::default();
    for (name, shape, bytes) in arrays {
        hash.write(name.as_bytes());
        for &dim in shape {
            hash.write(&(dim as u64).to_le_bytes());
        }
        hash.write(bytes);
    }
    hash.hex()
}

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
    let sum = checksum(
        bytes
            .iter()
            .map(|(name, raw, shape)| (name.as_str(), &shape[..], &raw[..])),
    );
    let metadata = std::collections::HashMap::from([(CHECKSUM_KEY.to_string(), sum)]);
    let data = serialize(views, Some(metadata)).map_err(|e| array_error(path, e))?;
    crate::export::write_atomic(path, &data)
}

/// Reads every f32 array of a safetensors file.
pub fn read_arrays(path: &Path) -> Result<HostArrays, TrainError> {
    let bytes = std::fs::read(path).map_err(|source| TrainError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let file = SafeTensors::deserialize(&bytes).map_err(|e| array_error(path, e))?;
    let (_, metadata) = SafeTensors::read_metadata(&bytes).map_err(|e| array_error(path, e))?;
    // Files other tools wrote (a data set's ground truth) carry none.
    if let Some(recorded) = metadata
        .metadata()
        .as_ref()
        .and_then(|m| m.get(CHECKSUM_KEY))
    {
        let mut tensors = file.tensors();
        tensors.sort_by(|a, b| a.0.cmp(&b.0));
        let found = checksum(
            tensors
                .iter()
                .map(|(name, view)| (name.as_str(), view.shape(), view.data())),
        );
        if &found != recorded {
            return Err(array_error(
                path,
                format!("the file is damaged: its arrays hash to {found}, {recorded} when written"),
            ));
        }
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// One flipped bit in a value is refused by name; a file without a checksum (another
    /// tool's) is read as it is.
    #[test]
    fn a_damaged_file_is_refused_and_one_without_a_checksum_is_read() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.safetensors");
        let arrays = HostArrays::from([
            ("density".to_string(), (vec![2], vec![0.25, 0.5])),
            ("velocity".to_string(), (vec![1, 3], vec![1.0, 2.0, 3.0])),
        ]);
        write_arrays(&path, &arrays).unwrap();
        assert_eq!(read_arrays(&path).unwrap(), arrays);
        let mut bytes = std::fs::read(&path).unwrap();
        let last = bytes.len() - 2;
        // An exponent bit of the last value: 3.0 becomes a huge finite number.
        bytes[last + 1] ^= 0x20;
        std::fs::write(&path, &bytes).unwrap();
        let error = read_arrays(&path).unwrap_err().to_string();
        assert!(
            error.contains("damaged") && error.contains("a.safetensors"),
            "{error}"
        );
        let plain = dir.path().join("plain.safetensors");
        let raw: Vec<u8> = [0.25f32, 0.5]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let view = TensorView::new(Dtype::F32, vec![2], &raw).unwrap();
        std::fs::write(&plain, serialize([("density", view)], None).unwrap()).unwrap();
        assert_eq!(read_arrays(&plain).unwrap()["density"].1, [0.25, 0.5]);
    }
}
