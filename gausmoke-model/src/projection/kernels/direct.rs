//! The direct solve on the device, for grids without obstacles: `D D^T p = D u` by separation
//! of variables, as the CPU backends solve it ([`crate::projection::spectral`]), written as
//! matrix products so that the GPU's matmul does the work. Into each axis's eigenbasis (three
//! products), a division by the eigenvalue sums, and back (three products): no iteration, no
//! read, a few launches per product where Jacobi-PCG takes five per iteration over tens of
//! iterations. f32 throughout; its error against the host's f64 solve is measured by the
//! tests. The factors are uploaded once per grid and device.

use std::sync::{Mutex, PoisonError};

use burn::backend::ops::FloatTensorOps;
use burn::tensor::{Shape, TensorData};
use burn_cubecl::CubeBackend;
use burn_cubecl::tensor::CubeTensor;

use crate::projection::host::{OpenFaces, ProjectionSpec};
use crate::projection::spectral::SpectralSolver;

/// The factors of one grid on one device: `Q^T` and `Q` per axis, the inverse eigenvalues.
#[derive(Clone)]
struct Uploaded {
    into: [CubeTensor; 3],
    back: [CubeTensor; 3],
    inverse: CubeTensor,
}

/// The factors of `spec`'s grid on `like`'s device, uploaded once (a few recent grids and
/// devices are kept: a run projects on one grid, forward and backward).
fn factors(spec: &ProjectionSpec, like: &CubeTensor) -> Uploaded {
    type Key = ([usize; 3], [u64; 3], OpenFaces, String);
    static RECENT: Mutex<Vec<(Key, Uploaded)>> = Mutex::new(Vec::new());
    let op = spec.operator();
    let key = (
        op.resolution,
        op.cell.map(f64::to_bits),
        op.open,
        format!("{:?}", like.device),
    );
    let mut recent = RECENT.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some((_, uploaded)) = recent.iter().find(|(k, _)| *k == key) {
        return uploaded.clone();
    }
    let [nx, ny, nz] = op.resolution;
    let factors = SpectralSolver::for_grid(&op).device_factors();
    let upload = |values: &[f32], shape: Vec<usize>| {
        CubeBackend::float_from_data(TensorData::new(values.to_vec(), shape), &like.device)
    };
    // Along y the lines are the middle axis: one [ny, ny] matrix for each of the nx blocks.
    let along_y = |m: &[f32]| {
        CubeBackend::float_expand(upload(m, vec![1, ny, ny]), Shape::from(vec![nx, ny, ny]))
    };
    let uploaded = Uploaded {
        into: [
            upload(&factors.into[0], vec![nx, nx]),
            along_y(&factors.into[1]),
            // Along z (the rows' last index) X Q_z applies Q_z^T to every line.
            upload(&factors.back[2], vec![nz, nz]),
        ],
        back: [
            upload(&factors.back[0], vec![nx, nx]),
            along_y(&factors.back[1]),
            upload(&factors.into[2], vec![nz, nz]),
        ],
        inverse: upload(&factors.inverse, vec![nx, ny, nz]),
    };
    if recent.len() >= 4 {
        recent.remove(0);
    }
    recent.push((key, uploaded.clone()));
    uploaded
}

/// The minimum-norm `p` (`[cells]`) with `D D^T p = rhs` for `rhs = D u` (`[cells]`, cells in
/// `[nx, ny, nz]` order, z fastest).
pub(super) fn pressure(rhs: CubeTensor, spec: &ProjectionSpec) -> CubeTensor {
    let [nx, ny, nz] = spec.resolution;
    let Uploaded {
        into,
        back,
        inverse,
    } = factors(spec, &rhs);
    let reshape =
        |t: CubeTensor, shape: Vec<usize>| CubeBackend::float_reshape(t, Shape::from(shape));
    let [into_x, into_y, into_z] = into;
    let [back_x, back_y, back_z] = back;
    // Into the eigenbasis along x, y and z.
    let x = CubeBackend::float_matmul(into_x, reshape(rhs, vec![nx, ny * nz]));
    let x = CubeBackend::float_matmul(into_y, reshape(x, vec![nx, ny, nz]));
    let x = CubeBackend::float_matmul(reshape(x, vec![nx * ny, nz]), into_z);
    // The division (0 for the null mode, the constants).
    let x = CubeBackend::float_mul(reshape(x, vec![nx, ny, nz]), inverse);
    // And back.
    let x = CubeBackend::float_matmul(reshape(x, vec![nx * ny, nz]), back_z);
    let x = CubeBackend::float_matmul(back_y, reshape(x, vec![nx, ny, nz]));
    let x = CubeBackend::float_matmul(back_x, reshape(x, vec![nx, ny * nz]));
    reshape(x, vec![nx * ny * nz])
}
