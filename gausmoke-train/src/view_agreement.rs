//! A refinement step that moves the Gaussians only where the training views agree
//! (`refine_view_agreement`, ours; issue 18).
//!
//! With every camera at the smoke's height, each horizontal slice of the smoke is a few-view
//! tomography problem. One view's residual, followed back along its rays, asks every Gaussian
//! on a ray for the same change, wherever it sits in depth: summed over the views, those
//! requests leave streaks along the views' directions where only one view asked. Each view's
//! gradient is taken on its own here, and each element of the mean gradient is kept only
//! where the views' signs agree: `|sum_v sign(g_v)| >= threshold * V`. A Gaussian at the
//! smoke's true depth is asked for the same change by every view that sees it; one that only
//! a single view's rays cross is asked by that view alone and stays where it is. Excess
//! density that one view placed is seen as excess by the others, which agree to remove it.
//!
//! The ties of the refinement (to the advected centres, the grid-scale moves, the
//! densities) are not views: their gradient is added in full.

use burn::tensor::Tensor;
use gausmoke_render::Gaussians;

use crate::attribute_grads::AttributeGrads;
use crate::config::AgreementAttributes;

/// The attributes `which` masks.
pub fn masked_attributes(which: AgreementAttributes) -> Gaussians<bool> {
    match which {
        AgreementAttributes::All => Gaussians::default().map(|_, ()| true),
        AgreementAttributes::Densities => Gaussians {
            raw_densities: true,
            ..Gaussians::default()
        },
    }
}

/// The mean of `per_view`, element by element, kept where `|sum_v sign(g_v)|` is at least
/// `threshold` times the number of views (a view that did not reach the element counts as 0).
pub fn agreed_mean<const D: usize>(per_view: Vec<Tensor<D>>, threshold: f32) -> Tensor<D> {
    let views = per_view.len();
    assert!(views > 0, "at least one view's gradient");
    let signs = per_view
        .iter()
        .map(|g| g.clone().sign())
        .reduce(|a, b| a + b)
        .expect("at least one view");
    let sum = per_view
        .into_iter()
        .reduce(|a, b| a + b)
        .expect("at least one view");
    if threshold <= 0.0 {
        return sum / views as f32;
    }
    // The sums of signs are whole numbers: half a vote below the bar is still below it.
    let bar = threshold * views as f32 - 0.5;
    let keep = signs.abs().greater_equal_elem(bar.max(0.5)).float();
    sum * keep / views as f32
}

/// Each attribute's mean over the views, kept where they agree (`masked` attributes only; the
/// others keep the whole mean), plus the ties' gradient; `None` where neither reached it.
pub fn combine(
    per_view: Vec<AttributeGrads>,
    ties: AttributeGrads,
    threshold: f32,
    masked: Gaussians<bool>,
) -> AttributeGrads {
    fn one<const D: usize>(
        views: Vec<Option<Tensor<D>>>,
        tie: Option<Tensor<D>>,
        threshold: f32,
        masked: bool,
    ) -> Option<Tensor<D>> {
        let reached: Vec<Tensor<D>> = views.into_iter().flatten().collect();
        // A threshold of 0 keeps every element: the plain mean.
        let threshold = if masked { threshold } else { 0.0 };
        let agreed = (!reached.is_empty()).then(|| agreed_mean(reached, threshold));
        match (agreed, tie) {
            (Some(a), Some(t)) => Some(a + t),
            (a, t) => a.or(t),
        }
    }
    let mut means = Vec::new();
    let mut rotations = Vec::new();
    let mut log_scales = Vec::new();
    let mut raw_densities = Vec::new();
    let mut colors = Vec::new();
    for view in per_view {
        means.push(view.means);
        rotations.push(view.rotations);
        log_scales.push(view.log_scales);
        raw_densities.push(view.raw_densities);
        colors.push(view.colors);
    }
    Gaussians {
        means: one(means, ties.means, threshold, masked.means),
        rotations: one(rotations, ties.rotations, threshold, masked.rotations),
        log_scales: one(log_scales, ties.log_scales, threshold, masked.log_scales),
        raw_densities: one(
            raw_densities,
            ties.raw_densities,
            threshold,
            masked.raw_densities,
        ),
        colors: one(colors, ties.colors, threshold, masked.colors),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;
    use gausmoke_render::backends::device_by_name;
    use gausmoke_render::device_traffic::read_floats;

    fn values(t: Tensor<1>) -> Vec<f32> {
        read_floats(t)
    }

    /// Four views, five elements: all agree; three agree and one is silent; three agree and
    /// one disagrees; one asks alone; two and two.
    #[test]
    fn only_what_the_views_agree_on_is_kept() {
        let device = device_by_name("flex").expect("the default build has Flex");
        let view = |v: [f32; 5]| Tensor::<1>::from_data(TensorData::new(v.to_vec(), [5]), &device);
        let per_view = || {
            vec![
                view([1.0, 1.0, 1.0, 4.0, 1.0]),
                view([1.0, 1.0, 1.0, 0.0, 1.0]),
                view([2.0, 1.0, 1.0, 0.0, -1.0]),
                view([4.0, 0.0, -1.0, 0.0, -1.0]),
            ]
        };
        // Every view must agree (silence breaks it).
        assert_eq!(
            values(agreed_mean(per_view(), 1.0)),
            [2.0, 0.0, 0.0, 0.0, 0.0]
        );
        // Three of four: a silent fourth is fine, a disagreeing one is not.
        assert_eq!(
            values(agreed_mean(per_view(), 0.75)),
            [2.0, 0.75, 0.0, 0.0, 0.0]
        );
        // Any net majority, a lone view included.
        assert_eq!(
            values(agreed_mean(per_view(), 0.25)),
            [2.0, 0.75, 0.5, 1.0, 0.0]
        );
    }

    #[test]
    fn the_ties_are_added_in_full() {
        let device = device_by_name("flex").expect("the default build has Flex");
        let one = |v: f32| Tensor::<1>::from_data(TensorData::new(vec![v], [1]), &device);
        let view = |v: Option<f32>| Gaussians {
            means: None,
            rotations: None,
            log_scales: None,
            raw_densities: v.map(one),
            colors: None,
        };
        let all = Gaussians::default().map(|_, ()| true);
        let combined = combine(
            vec![view(Some(1.0)), view(Some(-1.0))],
            view(Some(0.25)),
            1.0,
            all,
        );
        // The views cancel; the tie's gradient stays.
        assert_eq!(values(combined.raw_densities.unwrap()), [0.25]);
        assert!(combined.means.is_none());
        let alone = combine(vec![view(Some(2.0)), view(Some(2.0))], view(None), 1.0, all);
        assert_eq!(values(alone.raw_densities.unwrap()), [2.0]);
        // An attribute left unmasked takes the plain mean.
        let unmasked = Gaussians {
            raw_densities: false,
            ..all
        };
        let mean = combine(
            vec![view(Some(3.0)), view(Some(-1.0))],
            view(None),
            1.0,
            unmasked,
        );
        assert_eq!(values(mean.raw_densities.unwrap()), [1.0]);
    }
}
