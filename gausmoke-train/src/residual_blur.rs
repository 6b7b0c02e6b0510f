//! Losses on the image residual blurred by a Gaussian (ours; issue 18).
//!
//! The refinement's (`refine_loss_blur`): with four views, what a view's residual asks for at
//! a scale finer than the views can place in depth goes back along its rays as stripes. The
//! carried state holds that detail from the frames before; fitting only the residual's coarse
//! part leaves it there.
//!
//! The joint iterations' (`joint_loss_blur`), coarse to fine: the velocity is fitted first to
//! the residual's coarse part, whose gradient reaches smoke that moved further than the
//! Gaussians' own size.
//!
//! The blur is separable: two matrix products per image, differentiable through burn's own ops.

use burn::tensor::{Device, Tensor, TensorData};
use gausmoke_core::Camera;

/// The row-normalised blur matrices for one image size.
#[derive(Debug, Clone)]
pub struct ResidualBlur {
    /// Mixes the image's rows (the vertical blur); `None` when it blurs along rows alone.
    rows: Option<Tensor<2>>,
    /// Mixes the image's columns (the horizontal blur).
    columns: Tensor<2>,
}

impl ResidualBlur {
    /// The blur of standard deviation `sigma` pixels for `[height, width, 3]` images, along
    /// both axes, or with `horizontal_only` along each row alone.
    pub fn new(
        height: usize,
        width: usize,
        sigma: f32,
        horizontal_only: bool,
        device: &Device,
    ) -> Self {
        let matrix = |n: usize, sigma: f32| {
            Tensor::<2>::from_data(TensorData::new(blur_matrix(n, sigma), [n, n]), device)
        };
        Self {
            rows: (!horizontal_only).then(|| matrix(height, sigma)),
            columns: matrix(width, sigma),
        }
    }

    /// One blur of `sigma` pixels per view, sized to its image; `None` for `sigma = 0`.
    pub fn for_views(
        views: &[Camera],
        sigma: f32,
        horizontal_only: bool,
        device: &Device,
    ) -> Option<Vec<Self>> {
        (sigma > 0.0).then(|| {
            views
                .iter()
                .map(|c| {
                    let [h, w] = [c.height() as usize, c.width() as usize];
                    Self::new(h, w, sigma, horizontal_only, device)
                })
                .collect()
        })
    }

    /// `image` `[H, W, C]` blurred along the image axes this blur acts on.
    pub fn apply(&self, image: Tensor<3>) -> Tensor<3> {
        let [h, w, c] = image.dims();
        let image = match &self.rows {
            Some(rows) => rows
                .clone()
                .matmul(image.reshape([h, w * c]))
                .reshape([h, w, c]),
            None => image,
        };
        let by_column = image.swap_dims(0, 1).reshape([w, h * c]);
        let both = self.columns.clone().matmul(by_column);
        both.reshape([w, h, c]).swap_dims(0, 1)
    }
}

/// The blur, in pixels, of joint iteration `iteration` of `iterations` when the first is
/// blurred by `first`: linearly down to none at the last.
pub fn coarse_to_fine(first: f32, iteration: usize, iterations: usize) -> f32 {
    if iterations < 2 {
        return 0.0;
    }
    first * (iterations - 1 - iteration.min(iterations - 1)) as f32 / (iterations - 1) as f32
}

/// An `n x n` matrix whose row `i` holds the Gaussian weights of pixel `i`'s neighbours within
/// three standard deviations, normalised over the pixels inside the image (so a constant
/// image stays constant up to its borders); the identity for `sigma = 0`.
pub fn blur_matrix(n: usize, sigma: f32) -> Vec<f32> {
    if sigma <= 0.0 {
        return (0..n * n)
            .map(|k| if k / n == k % n { 1.0 } else { 0.0 })
            .collect();
    }
    let reach = (3.0 * sigma).ceil() as isize;
    let mut matrix = vec![0.0f32; n * n];
    for i in 0..n as isize {
        let row = &mut matrix[i as usize * n..(i as usize + 1) * n];
        let mut total = 0.0f32;
        for j in (i - reach).max(0)..(i + reach + 1).min(n as isize) {
            let d = (j - i) as f32 / sigma;
            let w = (-0.5 * d * d).exp();
            row[j as usize] = w;
            total += w;
        }
        row.iter_mut().for_each(|w| *w /= total);
    }
    matrix
}

#[cfg(test)]
mod tests {
    use super::*;
    use gausmoke_render::backends::device_by_name;
    use gausmoke_render::device_traffic::read_floats;

    #[test]
    fn the_joint_blur_shrinks_linearly_to_none_at_the_last_iteration() {
        let sigmas: Vec<f32> = (0..5).map(|k| coarse_to_fine(2.0, k, 5)).collect();
        assert_eq!(sigmas, [2.0, 1.5, 1.0, 0.5, 0.0]);
        assert_eq!(
            coarse_to_fine(2.0, 0, 1),
            0.0,
            "one iteration is the plain loss"
        );
        assert_eq!(coarse_to_fine(0.0, 0, 10), 0.0);
    }

    #[test]
    fn the_blur_matrix_keeps_constants_and_spreads_a_point_symmetrically() {
        let m = blur_matrix(9, 1.0);
        for i in 0..9 {
            let sum: f32 = m[i * 9..(i + 1) * 9].iter().sum();
            assert!((sum - 1.0).abs() < 1e-6, "row {i} sums to {sum}");
        }
        // Away from the borders the weights are the Gaussian's: symmetric, falling,
        // exp(-1/2) between the centre and its neighbour, and none beyond three sigma.
        let row = &m[4 * 9..5 * 9];
        assert_eq!(row[3], row[5]);
        assert!((row[3] / row[4] - (-0.5f32).exp()).abs() < 1e-6);
        assert!(row[2] < row[3] && row[1] > 0.0 && row[0] == 0.0);
    }

    #[test]
    fn the_blur_acts_on_each_axis_and_channel_alone() {
        let device = device_by_name("flex").expect("the default build has Flex");
        let (h, w) = (5, 7);
        // One bright pixel in channel 1; channels 0 and 2 are a constant and zero.
        let mut data = vec![0.0f32; h * w * 3];
        for p in 0..h * w {
            data[p * 3] = 0.25;
        }
        data[(2 * w + 3) * 3 + 1] = 1.0;
        let image = Tensor::<3>::from_data(TensorData::new(data, [h, w, 3]), &device);
        let blurred = read_floats(ResidualBlur::new(h, w, 1.0, false, &device).apply(image));
        let (rows, columns) = (blur_matrix(h, 1.0), blur_matrix(w, 1.0));
        for y in 0..h {
            for x in 0..w {
                let at = |c: usize| blurred[(y * w + x) * 3 + c];
                assert!((at(0) - 0.25).abs() < 1e-6, "constant kept at ({y}, {x})");
                assert_eq!(at(2), 0.0);
                // A point blurs into the outer product of the two axes' weights.
                let expected = rows[y * h + 2] * columns[x * w + 3];
                assert!((at(1) - expected).abs() < 1e-6, "({y}, {x}): {}", at(1));
            }
        }
    }

    #[test]
    fn a_pixel_scale_pattern_leaves_little_residual_and_a_smooth_one_stays() {
        let device = device_by_name("flex").expect("the default build has Flex");
        let (h, w) = (16, 16);
        let blur = ResidualBlur::new(h, w, 1.0, false, &device);
        let mean_abs = |f: &dyn Fn(usize, usize) -> f32| {
            let data: Vec<f32> = (0..h * w * 3).map(|i| f(i / 3 / w, i / 3 % w)).collect();
            let image = Tensor::<3>::from_data(TensorData::new(data, [h, w, 3]), &device);
            let blurred = read_floats(blur.apply(image));
            blurred.iter().map(|v| v.abs()).sum::<f32>() / blurred.len() as f32
        };
        // Stripes one pixel wide, as a view's fine residual: under a tenth survives (the
        // borders keep a little).
        let stripes = mean_abs(&|_, x| if x % 2 == 0 { 1.0 } else { -1.0 });
        assert!(stripes < 0.1, "stripes keep {stripes}");
        // A residual that changes over the whole image keeps nearly all of its L1.
        let ramp = |_: usize, x: usize| x as f32 / w as f32 - 0.5;
        let plain: f32 = (0..w).map(|x| ramp(0, x).abs()).sum::<f32>() / w as f32;
        let smooth = mean_abs(&ramp);
        assert!(
            (smooth - plain).abs() < 0.05 * plain,
            "{smooth} against {plain}"
        );
        // Along the rows alone, horizontal stripes (one pixel high) are left as they are.
        let rows_only = ResidualBlur::new(h, w, 1.0, true, &device);
        let data: Vec<f32> = (0..h * w * 3)
            .map(|i| if (i / 3 / w) % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let image = Tensor::<3>::from_data(TensorData::new(data.clone(), [h, w, 3]), &device);
        let kept = read_floats(rows_only.apply(image));
        assert!(kept.iter().zip(&data).all(|(a, b)| (a - b).abs() < 1e-6));
    }
}
