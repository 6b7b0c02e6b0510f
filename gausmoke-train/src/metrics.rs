//! Image and flow metrics of the evaluation protocol (docs: design notes, "Evaluation").
//!
//! Images are `[H, W, 3]` row-major f32 in `[0, 1]`.

use gausmoke_model::GridSpec;
use gausmoke_model::projection::{Divergence, OpenFaces, SolidCells};

/// Peak signal-to-noise ratio in dB for images in `[0, 1]` (inputs are clamped first, as a
/// saved PNG would be). Identical images give `f64::INFINITY`.
pub fn psnr(rendered: &[f32], reference: &[f32]) -> f64 {
    assert_eq!(rendered.len(), reference.len(), "images differ in size");
    let mse = rendered
        .iter()
        .zip(reference)
        .map(|(&a, &b)| {
            let d = a.clamp(0.0, 1.0) as f64 - b.clamp(0.0, 1.0) as f64;
            d * d
        })
        .sum::<f64>()
        / rendered.len().max(1) as f64;
    psnr_of_mse(mse)
}

/// PSNR in dB of a mean squared error of images in `[0, 1]`.
pub fn psnr_of_mse(mse: f64) -> f64 {
    -10.0 * mse.log10()
}

/// Mean absolute error, the L1 of Eq. 15 per pixel and channel.
pub fn mean_abs_error(rendered: &[f32], reference: &[f32]) -> f64 {
    assert_eq!(rendered.len(), reference.len(), "images differ in size");
    rendered
        .iter()
        .zip(reference)
        .map(|(&a, &b)| (a as f64 - b as f64).abs())
        .sum::<f64>()
        / rendered.len().max(1) as f64
}

/// SSIM as scikit-image computes it with `gaussian_weights=True, sigma=1.5,
/// use_sample_covariance=False, data_range=1`: an 11-tap Gaussian window (truncate 3.5),
/// statistics per channel, the mean taken over the pixels whose window lies inside the
/// image (a 5-pixel border is cropped), then over channels.
pub fn ssim(rendered: &[f32], reference: &[f32], width: usize, height: usize) -> f64 {
    assert_eq!(rendered.len(), width * height * 3, "rendered image size");
    assert_eq!(reference.len(), width * height * 3, "reference image size");
    const RADIUS: usize = 5;
    if width <= 2 * RADIUS || height <= 2 * RADIUS {
        return f64::NAN;
    }
    let sigma = 1.5f64;
    let taps: Vec<f64> = (0..=2 * RADIUS)
        .map(|i| {
            let x = i as f64 - RADIUS as f64;
            (-x * x / (2.0 * sigma * sigma)).exp()
        })
        .collect();
    let norm: f64 = taps.iter().sum();
    let taps: Vec<f64> = taps.iter().map(|t| t / norm).collect();
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    // Separable filtering of one plane, keeping only the valid region.
    let filter = |plane: &[f64]| -> Vec<f64> {
        let valid_w = width - 2 * RADIUS;
        let valid_h = height - 2 * RADIUS;
        let mut rows = vec![0.0; valid_w * height];
        for y in 0..height {
            for x in 0..valid_w {
                rows[y * valid_w + x] = taps
                    .iter()
                    .enumerate()
                    .map(|(k, t)| t * plane[y * width + x + k])
                    .sum();
            }
        }
        let mut out = vec![0.0; valid_w * valid_h];
        for y in 0..valid_h {
            for x in 0..valid_w {
                out[y * valid_w + x] = taps
                    .iter()
                    .enumerate()
                    .map(|(k, t)| t * rows[(y + k) * valid_w + x])
                    .sum();
            }
        }
        out
    };
    let mut total = 0.0;
    for channel in 0..3 {
        let a: Vec<f64> = rendered[channel..]
            .iter()
            .step_by(3)
            .map(|&v| v.clamp(0.0, 1.0) as f64)
            .collect();
        let b: Vec<f64> = reference[channel..]
            .iter()
            .step_by(3)
            .map(|&v| v.clamp(0.0, 1.0) as f64)
            .collect();
        let product =
            |p: &[f64], q: &[f64]| p.iter().zip(q).map(|(x, y)| x * y).collect::<Vec<_>>();
        let mu_a = filter(&a);
        let mu_b = filter(&b);
        let aa = filter(&product(&a, &a));
        let bb = filter(&product(&b, &b));
        let ab = filter(&product(&a, &b));
        let mut sum = 0.0;
        for i in 0..mu_a.len() {
            let (ma, mb) = (mu_a[i], mu_b[i]);
            let var_a = aa[i] - ma * ma;
            let var_b = bb[i] - mb * mb;
            let cov = ab[i] - ma * mb;
            sum += ((2.0 * ma * mb + c1) * (2.0 * cov + c2))
                / ((ma * ma + mb * mb + c1) * (var_a + var_b + c2));
        }
        total += sum / mu_a.len() as f64;
    }
    total / 3.0
}

/// Mean over cells of |div u| of a velocity grid (`[nx, ny, nz, 3]` flat, world units per
/// frame), with the same face-averaged discrete divergence (and the same open faces) the
/// projection makes zero, and its obstacle cells (which hold no divergence); in 1/frame.
/// This is the paper's Table 3 quantity on our grid.
pub fn mean_abs_divergence(
    grid: &GridSpec,
    open: OpenFaces,
    solids: Option<&SolidCells>,
    velocity: &[f32],
) -> f64 {
    let divergence = Divergence::on_grid(grid)
        .with_open_faces(open)
        .with_solids(solids.cloned())
        .of_velocity(velocity);
    divergence.iter().map(|d| d.abs()).sum::<f64>() / divergence.len().max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(width: usize, height: usize) -> Vec<f32> {
        (0..width * height * 3)
            .map(|i| ((i * 7919) % 251) as f32 / 250.0)
            .collect()
    }

    #[test]
    fn psnr_of_a_uniform_error_matches_the_formula() {
        let a = vec![0.5f32; 300];
        let b = vec![0.6f32; 300];
        assert!((psnr(&a, &b) - 20.0).abs() < 1e-4);
        assert_eq!(psnr(&a, &a), f64::INFINITY);
    }

    #[test]
    fn ssim_is_one_for_identical_images_and_drops_with_noise() {
        let (w, h) = (32, 24);
        let a = ramp(w, h);
        assert!((ssim(&a, &a, w, h) - 1.0).abs() < 1e-12);
        let b: Vec<f32> = a.iter().map(|v| (v + 0.05).min(1.0)).collect();
        let shifted = ssim(&a, &b, w, h);
        assert!(shifted < 1.0 && shifted > 0.9, "{shifted}");
        let c = vec![0.5f32; w * h * 3];
        assert!(ssim(&a, &c, w, h) < 0.1);
    }

    #[test]
    fn ssim_matches_a_hand_computed_constant_image_pair() {
        // Constant images: variances and covariance vanish, so SSIM is the luminance term.
        let (w, h) = (16, 16);
        let a = vec![0.2f32; w * h * 3];
        let b = vec![0.4f32; w * h * 3];
        let (ma, mb, c1) = (0.2f64, 0.4f64, 1e-4);
        let expected = (2.0 * ma * mb + c1) / (ma * ma + mb * mb + c1);
        assert!((ssim(&a, &b, w, h) - expected).abs() < 1e-6);
    }
}
