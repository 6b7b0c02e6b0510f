//! Finite-difference check of the renderer's hand-written backward pass.
//!
//! The thresholds of the rasterizer (kernel cutoff, alpha_min, early termination) make the
//! image piecewise smooth; a central difference straddling a threshold measures a jump, not a
//! derivative. Here they are opened up (huge cutoff, tiny alpha_min, no termination) so the
//! function is smooth and every term of the backward is exercised; the thresholds themselves
//! are covered by the torch goldens, which apply the same masks. The alpha_max clamp stays on
//! (at densities where it is not reached) since the backward divides by `1 - alpha`.

use gausmoke_core::glam::Vec3;
use gausmoke_render::Camera;
use gausmoke_render::RasterOptions;
use gausmoke_render::cpu::{self, IMAGE_CHANNELS};
use gausmoke_render::{Gaussians, HostGaussians};

/// Channels per pixel of the op's output before the walked-list length left the image: the
/// random weights below are drawn for that layout, so the inputs stay what they were.
const DRAWN_CHANNELS: usize = 5;

/// Deterministic pseudo-random numbers in [0, 1) (no RNG dependency for one test).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }
    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.next()
    }
}

struct Params {
    gaussians: HostGaussians,
    background: [f32; 3],
}

impl Params {
    fn field(&mut self, which: usize) -> &mut Vec<f32> {
        self.gaussians
            .as_mut()
            .into_array()
            .into_iter()
            .nth(which)
            .unwrap()
    }

    fn forward(&self, camera: &Camera, options: &RasterOptions) -> Vec<f32> {
        cpu::forward(&self.gaussians.slices(), self.background, camera, options).image
    }
}

fn random_gaussians(rng: &mut Lcg, n: usize, ranges: [(f32, f32); 5]) -> HostGaussians {
    let mut columns = [3, 4, 3, 1, 3].into_iter().zip(ranges);
    Gaussians::default().map(|_, ()| {
        let (width, (lo, hi)) = columns.next().unwrap();
        (0..width * n).map(|_| rng.range(lo, hi)).collect()
    })
}

fn smooth_options() -> RasterOptions {
    RasterOptions {
        alpha_min: 1e-12,
        transmittance_min: 0.0,
        kernel_cutoff: 1e6,
        ..RasterOptions::default()
    }
}

fn weighted_loss(image: &[f32], weights: &[f32]) -> f64 {
    image
        .iter()
        .zip(weights)
        .map(|(v, w)| *v as f64 * *w as f64)
        .sum()
}

#[test]
fn backward_matches_central_differences() {
    let mut rng = Lcg(42);
    let n = 5;
    let mut params = Params {
        gaussians: random_gaussians(
            &mut rng,
            n,
            [
                (-0.4, 0.4),
                (-1.0, 1.0),
                (-1.8, -0.9),
                (-0.5, 1.0),
                (0.0, 1.0),
            ],
        ),
        background: [0.2, 0.3, 0.4],
    };
    let camera = Camera::look_at(Vec3::new(0.4, 0.6, 3.0), Vec3::ZERO, Vec3::Y, 20, 16, 0.9)
        .expect("valid camera");
    let options = smooth_options();
    let weights: Vec<f32> = (0..20 * 16 * DRAWN_CHANNELS)
        .map(|_| rng.range(-1.0, 1.0))
        .enumerate()
        .filter(|(i, _)| i % DRAWN_CHANNELS < IMAGE_CHANNELS)
        .map(|(_, w)| w)
        .collect();

    let rendered = cpu::forward(
        &params.gaussians.slices(),
        params.background,
        &camera,
        &options,
    );
    let output = rendered.image.clone();
    assert!(output.iter().all(|v| v.is_finite()), "every pixel written");
    let (grads, grad_background) = cpu::backward(
        &params.gaussians.slices(),
        params.background,
        &camera,
        &options,
        &rendered,
        &weights,
    );
    let analytic = grads.into_array();
    let names = ["means", "quats", "log_scales", "raw_densities", "colors"];

    let step = 5e-3f32;
    let mut worst = 0.0f64;
    for (which, name) in names.iter().enumerate() {
        let scale = analytic[which].iter().fold(0.0f32, |m, g| m.max(g.abs())) as f64;
        assert!(
            scale > 1e-3,
            "{name}: gradient is (nearly) all zero, the test would be vacuous"
        );
        for (i, &a) in analytic[which].iter().enumerate() {
            let original = params.field(which)[i];
            params.field(which)[i] = original + step;
            let plus = weighted_loss(&params.forward(&camera, &options), &weights);
            params.field(which)[i] = original - step;
            let minus = weighted_loss(&params.forward(&camera, &options), &weights);
            params.field(which)[i] = original;
            let numeric = (plus - minus) / (2.0 * step as f64);
            let a = a as f64;
            let err = (numeric - a).abs();
            worst = worst.max(err / scale);
            // Central differences: O(h^2) truncation plus f32 rounding of the loss (~1e-6 / h).
            // Measured worst with h = 5e-3: 3.4e-4 of the gradient scale (h = 1e-2: 1.3e-3).
            assert!(
                err <= 1e-3 * scale + 5e-3 * a.abs(),
                "{name}[{i}]: analytic {a:.6} vs numeric {numeric:.6} (gradient scale {scale:.3})"
            );
        }
    }
    // Background: the loss is linear in it, so compare exactly.
    for (c, &analytic) in grad_background.iter().enumerate() {
        let mut fd_params = params_clone(&params);
        fd_params.background[c] += 1.0;
        let plus = weighted_loss(&fd_params.forward(&camera, &options), &weights);
        let base = weighted_loss(&output, &weights);
        let numeric = plus - base;
        assert!(
            (numeric - analytic as f64).abs() < 1e-3 * numeric.abs().max(1.0),
            "background[{c}]: analytic {analytic} vs numeric {numeric}"
        );
    }
    eprintln!("worst finite-difference error relative to gradient scale: {worst:.2e}");
}

fn params_clone(p: &Params) -> Params {
    Params {
        gaussians: p.gaussians.clone(),
        background: p.background,
    }
}

#[test]
fn backward_is_deterministic() {
    let mut rng = Lcg(7);
    let n = 200;
    let params = Params {
        gaussians: random_gaussians(
            &mut rng,
            n,
            [
                (-0.6, 0.6),
                (-1.0, 1.0),
                (-3.0, -1.5),
                (-1.0, 2.0),
                (0.0, 1.0),
            ],
        ),
        background: [0.0; 3],
    };
    let camera =
        Camera::look_at(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y, 64, 48, 0.9).unwrap();
    let options = RasterOptions::default();
    let slices = params.gaussians.slices();
    let rendered = cpu::forward(&slices, params.background, &camera, &options);
    let grad_output: Vec<f32> = (0..rendered.image.len())
        .map(|_| rng.range(-1.0, 1.0))
        .collect();
    let a = cpu::backward(
        &slices,
        params.background,
        &camera,
        &options,
        &rendered,
        &grad_output,
    );
    let b = cpu::backward(
        &slices,
        params.background,
        &camera,
        &options,
        &rendered,
        &grad_output,
    );
    assert_eq!(
        a, b,
        "two backward passes on the same input must agree bit for bit"
    );
}
