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
