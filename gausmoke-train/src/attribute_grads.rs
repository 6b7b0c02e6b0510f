//! A loss's gradients with respect to the Gaussians, one per attribute: as burn's
//! [`GradientsParams`] (what the per-attribute Adam steps take) and as tensors (what
//! `view_agreement` combines), and back.

use burn::module::ParamId;
use burn::optim::GradientsParams;
use burn::tensor::{Gradients, Tensor};
use gausmoke_model::GaussianModel;
use gausmoke_render::Gaussians;

/// One loss's gradient with respect to each Gaussian attribute (`None` where it did not reach
/// the attribute).
pub type AttributeGrads = Gaussians<Option<Tensor<2>>, Option<Tensor<1>>>;

/// `model`'s gradients taken out of `grads`, one [`GradientsParams`] per attribute.
pub fn attribute_params(
    grads: &mut Gradients,
    model: &GaussianModel,
) -> Gaussians<GradientsParams> {
    model
        .param_ids()
        .map(|_, id| GradientsParams::from_params(grads, model, &[id]))
}

/// `model`'s gradients taken out of `grads`, as tensors.
pub fn attribute_grads(grads: &mut Gradients, model: &GaussianModel) -> AttributeGrads {
    let ids = model.param_ids();
    let mut params = attribute_params(grads, model);
    Gaussians {
        means: params.means.remove::<2>(ids.means),
        rotations: params.rotations.remove::<2>(ids.rotations),
        log_scales: params.log_scales.remove::<2>(ids.log_scales),
        raw_densities: params.raw_densities.remove::<1>(ids.raw_densities),
        colors: params.colors.remove::<2>(ids.colors),
    }
}

/// `grads` back as one [`GradientsParams`] per attribute of `model` (empty where `None`).
pub fn per_attribute_params(
    grads: AttributeGrads,
    model: &GaussianModel,
) -> Gaussians<GradientsParams> {
    let ids = model.param_ids();
    fn params<const D: usize>(id: ParamId, grad: Option<Tensor<D>>) -> GradientsParams {
        let mut params = GradientsParams::new();
        if let Some(grad) = grad {
            params.register(id, grad);
        }
        params
    }
    Gaussians {
        means: params(ids.means, grads.means),
        rotations: params(ids.rotations, grads.rotations),
        log_scales: params(ids.log_scales, grads.log_scales),
        raw_densities: params(ids.raw_densities, grads.raw_densities),
        colors: params(ids.colors, grads.colors),
    }
}

/// Each attribute's gradient divided by its root mean square over all its entries, so that
/// an absolute epsilon in Adam is one relative to the step's typical gradient.
pub fn grads_over_their_rms(
    mut grads: Gaussians<GradientsParams>,
    model: &GaussianModel,
) -> Gaussians<GradientsParams> {
    fn scaled<const D: usize>(params: &mut GradientsParams, id: ParamId) {
        if let Some(grad) = params.remove::<D>(id) {
            // The tiny floor keeps an all-zero gradient at zero rather than NaN.
            let rms = grad.clone().powi_scalar(2).mean().sqrt().add_scalar(1e-30);
            params.register(id, grad / rms.reshape([1; D]));
        }
    }
    let ids = model.param_ids();
    scaled::<2>(&mut grads.means, ids.means);
    scaled::<2>(&mut grads.rotations, ids.rotations);
    scaled::<2>(&mut grads.log_scales, ids.log_scales);
    scaled::<1>(&mut grads.raw_densities, ids.raw_densities);
    scaled::<2>(&mut grads.colors, ids.colors);
    grads
}

#[cfg(test)]
mod tests {
    #![allow(clippy::disallowed_methods)] // tests read tensors freely

    use super::*;
    use burn::tensor::TensorData;
    use gausmoke_core::glam::Vec3;
    use gausmoke_render::backends::cpu_devices;

    fn values<const D: usize>(tensor: Tensor<D>) -> Vec<f32> {
        tensor.into_data().try_into_vec_as::<f32>().unwrap()
    }

    /// Each attribute's gradient comes back with a root mean square of 1 and its entries in
    /// the same proportions; a gradient of zeros stays zeros, and an attribute the loss did
    /// not reach stays absent.
    #[test]
    fn gradients_are_divided_by_their_root_mean_square() {
        for (_, device) in cpu_devices() {
            let device = device.autodiff();
            let model = GaussianModel::init_in_box(4, Vec3::ZERO, Vec3::ONE, 7, &device);
            let weights = Tensor::<2>::from_data(
                TensorData::new(
                    vec![
                        1.0f32, -2.0, 3.0, 0.001, 0.0, 0.0, 5.0, 1.0, 1.0, 0.5, 0.5, -0.5,
                    ],
                    [4, 3],
                ),
                &device,
            );
            let loss =
                (model.means.val() * weights.clone()).sum() + model.raw_densities.val().sum() * 0.0;
            let mut grads = loss.backward();
            let ids = model.param_ids();
            let mut scaled = grads_over_their_rms(attribute_params(&mut grads, &model), &model);

            let means = values(scaled.means.remove::<2>(ids.means).unwrap());
            let expected = values(weights);
            let rms = (expected.iter().map(|w| w * w).sum::<f32>() / 12.0).sqrt();
            for (got, want) in means.iter().zip(&expected) {
                assert!(
                    (got - want / rms).abs() < 1e-5,
                    "{got} against {}",
                    want / rms
                );
            }
            let densities = values(scaled.raw_densities.remove::<1>(ids.raw_densities).unwrap());
            assert!(densities.iter().all(|&d| d == 0.0), "{densities:?}");
            assert!(scaled.colors.remove::<2>(ids.colors).is_none());
        }
    }
}
