//! Host copies of fields on the velocity grid's cells (`[nx, ny, nz, C]`, z fastest): a
//! Gaussian smoothing and a cell-centred trilinear sample.

use gausmoke_core::glam::Vec3;

/// `values` (`[nx, ny, nz, channels]`, z fastest) smoothed by a Gaussian of `sigma` cells
/// along each axis `axes` names, in turn, cut off at 3 sigma; near the walls the weights
/// inside the grid are renormalised, so a uniform field stays uniform.
pub(crate) fn smoothed(
    values: &[f32],
    resolution: [usize; 3],
    channels: usize,
    sigma: f32,
    axes: [bool; 3],
) -> Vec<f32> {
    let reach = (3.0 * sigma).ceil() as isize;
    let weights: Vec<f64> = (-reach..=reach)
        .map(|d| (-0.5 * (d as f64 / sigma as f64).powi(2)).exp())
        .collect();
    let [nx, ny, nz] = resolution;
    assert_eq!(values.len(), nx * ny * nz * channels, "grid size");
    // The stride of one step along each axis, in rows of `channels`.
    let strides = [ny * nz, nz, 1];
    let mut field = values.to_vec();
    let mut sum = vec![0.0f64; channels];
    for (axis, &stride) in strides.iter().enumerate().filter(|&(axis, _)| axes[axis]) {
        let size = resolution[axis] as isize;
        let mut next = vec![0.0f32; field.len()];
        for cell in 0..nx * ny * nz {
            let at = ((cell / stride) % resolution[axis]) as isize;
            sum.iter_mut().for_each(|s| *s = 0.0);
            let mut total = 0.0;
            for (d, &w) in (-reach..=reach).zip(&weights) {
                let j = at + d;
                if !(0..size).contains(&j) {
                    continue;
                }
                let other = (cell as isize + (j - at) * stride as isize) as usize;
                for (c, s) in sum.iter_mut().enumerate() {
                    *s += w * field[channels * other + c] as f64;
                }
                total += w;
            }
            for (c, s) in sum.iter().enumerate() {
                next[channels * cell + c] = (s / total) as f32;
            }
        }
        field = next;
    }
    field
}

/// Cell-centred trilinear sample of `values` (`[nx, ny, nz, channels]`, z fastest, cells of
/// size `cell` from `lo`) at world point `p`, clamped to the outermost cell centres, into
/// `out` (`channels` long).
pub(crate) fn sample(
    lo: Vec3,
    cell: Vec3,
    resolution: [usize; 3],
    values: &[f32],
    channels: usize,
    p: Vec3,
    out: &mut [f64],
) {
    let res = resolution;
    let local = (p - lo) / cell - Vec3::splat(0.5);
    let mut base = [0usize; 3];
    let mut frac = [0f32; 3];
    for a in 0..3 {
        let x = local[a].clamp(0.0, (res[a] - 1) as f32);
        base[a] = (x.floor() as usize).min(res[a].saturating_sub(2));
        frac[a] = x - base[a] as f32;
    }
    out.iter_mut().for_each(|o| *o = 0.0);
    for corner in 0..8 {
        let offset = [(corner >> 2) & 1, (corner >> 1) & 1, corner & 1];
        let mut weight = 1.0f32;
        let mut index = [0usize; 3];
        for a in 0..3 {
            index[a] = (base[a] + offset[a]).min(res[a] - 1);
            weight *= if offset[a] == 1 {
                frac[a]
            } else {
                1.0 - frac[a]
            };
        }
        let cell_index = (index[0] * res[1] + index[1]) * res[2] + index[2];
        for c in 0..channels {
            out[c] += (weight * values[cell_index * channels + c]) as f64;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::smoothed;

    /// The smoothing keeps a uniform field, keeps an impulse's sum away from the walls and
    /// spreads it by sigma along each axis, each component on its own.
    #[test]
    fn the_move_field_is_smoothed_by_a_gaussian_of_sigma_cells() {
        // Wide enough that no cell the impulse reaches has a wall within reach.
        let resolution = [23, 23, 23];
        let cells = 23 * 23 * 23;
        let uniform: Vec<f32> = (0..cells).flat_map(|_| [0.5, -1.0, 2.0]).collect();
        let smooth = smoothed(&uniform, resolution, 3, 2.0, [true; 3]);
        assert!(
            smooth
                .iter()
                .zip(&uniform)
                .all(|(a, b)| (a - b).abs() < 1e-5)
        );
        let index = |x: usize, y: usize, z: usize| (x * 23 + y) * 23 + z;
        let mut impulse = vec![0.0f32; 3 * cells];
        impulse[3 * index(11, 11, 11) + 1] = 1.0;
        let sigma = 1.5;
        let smooth = smoothed(&impulse, resolution, 3, sigma, [true; 3]);
        let mut sum = 0.0f64;
        let mut second = [0.0f64; 3];
        for x in 0..23 {
            for y in 0..23 {
                for z in 0..23 {
                    let v = smooth[3 * index(x, y, z) + 1] as f64;
                    assert_eq!(smooth[3 * index(x, y, z)], 0.0);
                    assert_eq!(smooth[3 * index(x, y, z) + 2], 0.0);
                    sum += v;
                    let d = [x as f64 - 11.0, y as f64 - 11.0, z as f64 - 11.0];
                    second.iter_mut().zip(d).for_each(|(m, d)| *m += v * d * d);
                }
            }
        }
        assert!((sum - 1.0).abs() < 1e-5, "sum {sum}");
        // A sampled Gaussian cut at 3 sigma has a variance a little under sigma^2.
        for m in second {
            assert!(
                (m - 2.25).abs() < 0.1,
                "variance {m} against {}",
                sigma * sigma
            );
        }
    }
}
