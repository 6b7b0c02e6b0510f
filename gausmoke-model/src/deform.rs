//! The Gaussians' shapes carried by the flow (ours; issue 18, hypothesis 3).
//!
//! Eq. 13 moves a Gaussian's centre and keeps its covariance, so a blob of smoke keeps its
//! shape however the flow strains it: a rising cap that spreads sideways has to be spread again
//! by each frame's fit. A material blob in a velocity field is carried by the flow map's
//! Jacobian `F` instead, `Sigma' = F Sigma F^T` (the deformation gradient of continuum
//! mechanics). The step's `F` is built from the velocity's Jacobian `J` at the centre by the
//! Cayley form `(I - dt J / 2)^-1 (I + dt J / 2)`: second order like the midpoint rule, a pure
//! rotation for a pure rotation (antisymmetric `J`), and made volume-preserving (`det F = 1`)
//! because the projected flow is divergence-free, so a carried Gaussian keeps its mass with its
//! density unchanged.

use gausmoke_core::glam::{DMat3, DQuat, DVec3};

type Mat = [[f64; 3]; 3];

/// The volume-preserving deformation gradient of one step `dt` (frames) of a flow whose
/// Jacobian is `jacobian` (`J[a][b] = d u_a / d x_b`, per frame); `None` where the step is
/// too large for the Cayley form (`I - dt J / 2` singular, or `F` not orientation-preserving).
pub fn flow_deformation(jacobian: &Mat, dt: f64) -> Option<DMat3> {
    // glam is column-major: column b holds J[.][b].
    let j = DMat3::from_cols_array_2d(jacobian).transpose();
    let half = j * (0.5 * dt);
    let behind = DMat3::IDENTITY - half;
    if behind.determinant().abs() < 1e-9 {
        return None;
    }
    let f = behind.inverse() * (DMat3::IDENTITY + half);
    let det = f.determinant();
    if !(det.is_finite() && det > 1e-9) {
        return None;
    }
    Some(f * det.powf(-1.0 / 3.0))
}

/// Gaussian `(rotation (w, x, y, z), log standard deviations)` after deformation `f`: the
/// eigen-decomposition of `f R S^2 R^T f^T`. Where that would leave the Gaussian longer than
/// `max_elongation` times its width and longer than it was, its log standard deviations are
/// drawn towards their mean (keeping its volume) until it is as long as the larger of the
/// two: the flow turns it and strains it that far, no further. A zero quaternion (which the
/// renderer refuses) is returned as it is.
pub fn deform_shape(
    rotation: [f32; 4],
    log_scale: [f32; 3],
    f: &DMat3,
    max_elongation: f64,
) -> ([f32; 4], [f32; 3]) {
    let [w, x, y, z] = rotation.map(f64::from);
    let q = DQuat::from_xyzw(x, y, z, w);
    if q.length_squared() == 0.0 || !q.is_finite() {
        return (rotation, log_scale);
    }
    let r = DMat3::from_quat(q.normalize());
    let variances = DVec3::from_array(log_scale.map(|s| (2.0 * f64::from(s)).exp()));
    let covariance = r * DMat3::from_diagonal(variances) * r.transpose();
    let deformed = *f * covariance * f.transpose();
    let (values, mut vectors) = symmetric_eigen(&deformed);
    if vectors.determinant() < 0.0 {
        vectors.z_axis = -vectors.z_axis;
    }
    let q = DQuat::from_mat3(&vectors).normalize();
    let mut log = values.map(|v| 0.5 * v.max(f64::MIN_POSITIVE).ln());
    let spread = |v: DVec3| v.max_element() - v.min_element();
    let before = DVec3::from_array(log_scale.map(f64::from));
    let allowed = max_elongation.ln().max(spread(before));
    if spread(log) > allowed {
        let mean = log.element_sum() / 3.0;
        log = DVec3::splat(mean) + (log - DVec3::splat(mean)) * (allowed / spread(log));
    }
    (
        [q.w as f32, q.x as f32, q.y as f32, q.z as f32],
        [log.x as f32, log.y as f32, log.z as f32],
    )
}

/// Deforms the rows `rows` of flat `[N, 4]` rotations and `[N, 3]` log-scales by one step `dt`
/// of the flow whose Jacobians at their centres are `jacobians` (`[N, 3, 3]`, row-major),
/// straining none beyond `max_elongation` (see [`deform_shape`]); a row whose step is too
/// large keeps its shape. Returns how many rows kept it that way.
pub fn deform_shapes(
    rotations: &mut [f32],
    log_scales: &mut [f32],
    jacobians: &[f32],
    dt: f32,
    max_elongation: f32,
    rows: impl Iterator<Item = usize>,
) -> usize {
    let mut kept = 0;
    for row in rows {
        let j = &jacobians[row * 9..row * 9 + 9];
        let jacobian = [0, 1, 2].map(|a| [0, 1, 2].map(|b| f64::from(j[a * 3 + b])));
        let Some(f) = flow_deformation(&jacobian, f64::from(dt)) else {
            kept += 1;
            continue;
        };
        let rotation: [f32; 4] = rotations[row * 4..row * 4 + 4].try_into().expect("4 wide");
        let log_scale: [f32; 3] = log_scales[row * 3..row * 3 + 3].try_into().expect("3 wide");
        let (rotation, log_scale) =
            deform_shape(rotation, log_scale, &f, f64::from(max_elongation));
        rotations[row * 4..row * 4 + 4].copy_from_slice(&rotation);
        log_scales[row * 3..row * 3 + 3].copy_from_slice(&log_scale);
    }
    kept
}

/// Eigenvalues and eigenvectors (as the columns) of a symmetric matrix, by cyclic Jacobi
/// rotations; for 3x3 a handful of sweeps reach double precision.
fn symmetric_eigen(m: &DMat3) -> (DVec3, DMat3) {
    let mut a: Mat = m.transpose().to_cols_array_2d(); // rows of m
    let mut v: Mat = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..32 {
        let off = a[0][1].powi(2) + a[0][2].powi(2) + a[1][2].powi(2);
        let scale = a[0][0].powi(2) + a[1][1].powi(2) + a[2][2].powi(2);
        if off <= 1e-30 * scale.max(f64::MIN_POSITIVE) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            // a <- G^T a G with G the rotation in the (p, q) plane.
            let turn_columns = |m: &mut Mat| {
                for row in m.iter_mut() {
                    let (mp, mq) = (row[p], row[q]);
                    row[p] = c * mp - s * mq;
                    row[q] = s * mp + c * mq;
                }
            };
            turn_columns(&mut a);
            let (row_p, row_q) = (a[p], a[q]);
            for k in 0..3 {
                a[p][k] = c * row_p[k] - s * row_q[k];
                a[q][k] = s * row_p[k] + c * row_q[k];
            }
            turn_columns(&mut v);
        }
    }
    let values = DVec3::new(a[0][0], a[1][1], a[2][2]);
    // v's columns are the eigenvectors; glam takes columns.
    let vectors = DMat3::from_cols_array_2d(&v).transpose();
    (values, vectors)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn covariance(rotation: [f32; 4], log_scale: [f32; 3]) -> DMat3 {
        let [w, x, y, z] = rotation.map(f64::from);
        let r = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize());
        let d = DVec3::from_array(log_scale.map(|s| (2.0 * f64::from(s)).exp()));
        r * DMat3::from_diagonal(d) * r.transpose()
    }

    fn assert_close(a: &DMat3, b: &DMat3, tolerance: f64) {
        let (a, b) = (a.to_cols_array(), b.to_cols_array());
        let largest = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() <= tolerance * largest, "{a:?} against {b:?}");
        }
    }

    const SHAPE: ([f32; 4], [f32; 3]) = ([0.9, 0.1, -0.3, 0.2], [-3.0, -3.5, -2.6]);

    #[test]
    fn the_deformed_shape_is_f_sigma_f_transposed() {
        let jacobian = [[0.1, 0.4, -0.2], [0.05, -0.3, 0.25], [-0.15, 0.1, 0.2]];
        let f = flow_deformation(&jacobian, 1.0).expect("a small step");
        assert!((f.determinant() - 1.0).abs() < 1e-12);
        let (rotation, log_scale) = deform_shape(SHAPE.0, SHAPE.1, &f, f64::INFINITY);
        let before = covariance(SHAPE.0, SHAPE.1);
        assert_close(
            &covariance(rotation, log_scale),
            &(f * before * f.transpose()),
            1e-5,
        );
        // Volume kept: the product of the standard deviations.
        let volume = |s: [f32; 3]| s.iter().sum::<f32>();
        assert!((volume(log_scale) - volume(SHAPE.1)).abs() < 1e-5);
        // A strain changes the shape (the test is not of the identity).
        assert!(
            log_scale
                .iter()
                .zip(&SHAPE.1)
                .any(|(a, b)| (a - b).abs() > 0.05)
        );
    }

    #[test]
    fn a_still_flow_keeps_every_shape() {
        let f = flow_deformation(&[[0.0; 3]; 3], 1.0).expect("no step");
        let (rotation, log_scale) = deform_shape(SHAPE.0, SHAPE.1, &f, f64::INFINITY);
        assert_close(
            &covariance(rotation, log_scale),
            &covariance(SHAPE.0, SHAPE.1),
            1e-6,
        );
    }

    #[test]
    fn a_turning_flow_turns_the_shape_without_stretching_it() {
        // Rigid rotation about y at 0.3 radians a frame: u = w x r.
        let w = 0.3;
        let jacobian = [[0.0, 0.0, w], [0.0, 0.0, 0.0], [-w, 0.0, 0.0]];
        let f = flow_deformation(&jacobian, 1.0).expect("a small step");
        assert_close(&(f * f.transpose()), &DMat3::IDENTITY, 1e-12);
        let (rotation, log_scale) = deform_shape(SHAPE.0, SHAPE.1, &f, f64::INFINITY);
        let sorted = |mut s: [f32; 3]| {
            s.sort_by(f32::total_cmp);
            s
        };
        let (after, before) = (sorted(log_scale), sorted(SHAPE.1));
        for (a, b) in after.iter().zip(&before) {
            assert!((a - b).abs() < 1e-5, "{after:?} against {before:?}");
        }
        let turned = covariance(rotation, log_scale);
        assert_close(
            &turned,
            &(f * covariance(SHAPE.0, SHAPE.1) * f.transpose()),
            1e-5,
        );
        // The turn is visible: the covariance is not the one it started from.
        let moved = (turned - covariance(SHAPE.0, SHAPE.1)).to_cols_array();
        assert!(moved.iter().any(|v| v.abs() > 1e-4));
    }

    #[test]
    fn a_strain_stops_at_the_elongation_cap_and_keeps_the_volume() {
        let round = ([1.0, 0.0, 0.0, 0.0], [-3.0, -3.0, -3.0]);
        // Stretch along x, squeeze along y: e^0.8 = 2.2 times as long as wide, uncapped.
        let jacobian = [[0.4, 0.0, 0.0], [0.0, -0.4, 0.0], [0.0, 0.0, 0.0]];
        let f = flow_deformation(&jacobian, 1.0).expect("a small step");
        let elongation = |s: [f32; 3]| {
            let (lo, hi) = s
                .iter()
                .fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
            (hi - lo).exp()
        };
        let (_, free) = deform_shape(round.0, round.1, &f, f64::INFINITY);
        assert!(elongation(free) > 2.1, "{free:?}");
        let (_, capped) = deform_shape(round.0, round.1, &f, 1.5);
        assert!((elongation(capped) - 1.5).abs() < 1e-4, "{capped:?}");
        assert!((capped.iter().sum::<f32>() - round.1.iter().sum::<f32>()).abs() < 1e-5);
        // A Gaussian already longer than the cap is not shortened by it.
        let long = ([1.0, 0.0, 0.0, 0.0], [-2.0, -3.0, -3.0]);
        let still = flow_deformation(&[[0.0; 3]; 3], 1.0).expect("no step");
        let (_, kept) = deform_shape(long.0, long.1, &still, 1.5);
        assert!((elongation(kept) - 1.0f32.exp()).abs() < 1e-4, "{kept:?}");
    }

    #[test]
    fn a_step_too_large_keeps_the_shape_and_is_counted() {
        // I - J / 2 is singular for J = 2 I.
        let mut jacobians = vec![0.0f32; 18];
        for k in 0..3 {
            jacobians[k * 4] = 2.0;
            jacobians[9 + k * 4] = 0.1 * (k as f32 - 1.0);
        }
        let mut rotations = [SHAPE.0, SHAPE.0].concat();
        let mut log_scales = [SHAPE.1, SHAPE.1].concat();
        let kept = deform_shapes(
            &mut rotations,
            &mut log_scales,
            &jacobians,
            1.0,
            f32::INFINITY,
            0..2,
        );
        assert_eq!(kept, 1);
        assert_eq!(&rotations[..4], &SHAPE.0);
        assert_eq!(&log_scales[..3], &SHAPE.1);
        assert_ne!(&log_scales[3..], &SHAPE.1);
    }

    #[test]
    fn the_eigen_decomposition_rebuilds_its_matrix() {
        let m = DMat3::from_cols_array_2d(&[[4.0, 1.0, -0.5], [1.0, 3.0, 0.2], [-0.5, 0.2, 1.0]]);
        let (values, vectors) = symmetric_eigen(&m);
        assert_close(
            &(vectors * DMat3::from_diagonal(values) * vectors.transpose()),
            &m,
            1e-12,
        );
        assert_close(&(vectors.transpose() * vectors), &DMat3::IDENTITY, 1e-12);
    }
}
