//! The one shape of a set of `N` Gaussians, whatever holds it.
//!
//! [`Gaussians`] names the per-Gaussian attributes once. Every view of a set of Gaussians is
//! this struct with a different storage: tensors for the public API ([`GaussianTensors`]),
//! backend primitives at the op boundary and for their gradients ([`GaussianPrimitives`]),
//! flat host arrays ([`HostGaussians`]) and borrowed slices ([`GaussianSlices`]) for the CPU
//! path and for files. One Gaussian on its own is a [`Gaussian`].
//!
//! Adding an attribute means a field here, its entry in [`ATTRIBUTES`], the field in
//! [`Gaussian`], and the maths that uses it.

use burn::backend::tensor::FloatTensor;
use burn::backend::{
    Backend, BackendTensor, Dispatch, DispatchAutodiffContext, DispatchTensor, DispatchTensorKind,
    ExtensionType,
};
use burn::tensor::{Device, Tensor, TensorData};

/// The attributes of `N` Gaussians. `M` holds the `[N, k]` attributes and `V` the `[N]` one;
/// most storages use one type for both.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Gaussians<M, V = M> {
    /// Centres in world units, `[N, 3]`.
    pub means: M,
    /// Quaternions `(w, x, y, z)`, `[N, 4]`; normalised where used, so any non-zero value.
    pub rotations: M,
    /// Natural log of the per-axis standard deviations (world units), `[N, 3]`.
    pub log_scales: M,
    /// Raw densities, `[N]`; `sigma = softplus(raw) >= 0` per world unit.
    pub raw_densities: V,
    /// Linear RGB emitted colour, `[N, 3]`.
    pub colors: M,
}

/// Name and row width of one attribute, in field order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Attribute {
    pub name: &'static str,
    /// Values per Gaussian; the `[N]` attribute has 1.
    pub columns: usize,
}

impl Attribute {
    /// The tensor shape of this attribute for `n` Gaussians: `[n]` or `[n, columns]`.
    pub fn shape(&self, n: usize) -> Vec<usize> {
        if self.columns == 1 {
            vec![n]
        } else {
            vec![n, self.columns]
        }
    }
}

/// The attributes of [`Gaussians`] in field order (what `to_array` and `from_array` use).
pub const ATTRIBUTES: [Attribute; 5] = [
    Attribute {
        name: "means",
        columns: 3,
    },
    Attribute {
        name: "rotations",
        columns: 4,
    },
    Attribute {
        name: "log_scales",
        columns: 3,
    },
    Attribute {
        name: "raw_densities",
        columns: 1,
    },
    Attribute {
        name: "colors",
        columns: 3,
    },
];

/// The public tensor view (what [`crate::render_volume`] takes).
pub type GaussianTensors = Gaussians<Tensor<2>, Tensor<1>>;
/// Backend primitives, at the boundary of the custom ops (inputs and gradients alike).
pub type GaussianPrimitives<B> = Gaussians<FloatTensor<B>>;
/// Flat row-major host arrays (exports, checkpoints, the CPU path).
pub type HostGaussians = Gaussians<Vec<f32>>;
/// Borrowed flat arrays.
pub type GaussianSlices<'a> = Gaussians<&'a [f32]>;

impl<T> Gaussians<T> {
    /// The attributes in field order (see [`ATTRIBUTES`]).
    pub fn into_array(self) -> [T; 5] {
        [
            self.means,
            self.rotations,
            self.log_scales,
            self.raw_densities,
            self.colors,
        ]
    }

    pub fn from_array([means, rotations, log_scales, raw_densities, colors]: [T; 5]) -> Self {
        Self {
            means,
            rotations,
            log_scales,
            raw_densities,
            colors,
        }
    }

    pub fn as_ref(&self) -> Gaussians<&T> {
        Gaussians {
            means: &self.means,
            rotations: &self.rotations,
            log_scales: &self.log_scales,
            raw_densities: &self.raw_densities,
            colors: &self.colors,
        }
    }

    pub fn as_mut(&mut self) -> Gaussians<&mut T> {
        Gaussians {
            means: &mut self.means,
            rotations: &mut self.rotations,
            log_scales: &mut self.log_scales,
            raw_densities: &mut self.raw_densities,
            colors: &mut self.colors,
        }
    }

    /// Applies `f` to every attribute, with its [`Attribute`].
    pub fn map<U>(self, mut f: impl FnMut(Attribute, T) -> U) -> Gaussians<U> {
        let mut attributes = ATTRIBUTES.into_iter();
        Gaussians::from_array(
            self.into_array()
                .map(|value| f(attributes.next().expect("one per field"), value)),
        )
    }

    /// Pairs every attribute with the same one of `other`.
    pub fn zip<U>(self, other: Gaussians<U>) -> Gaussians<(T, U)> {
        let mut other = other.into_array().into_iter();
        Gaussians::from_array(
            self.into_array()
                .map(|value| (value, other.next().expect("one per field"))),
        )
    }
}

/// One Gaussian's parameters (or the gradient of a loss with respect to them: same shape).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Gaussian {
    pub mean: [f32; 3],
    /// Raw (not normalised) quaternion `(w, x, y, z)`.
    pub rotation: [f32; 4],
    pub log_scale: [f32; 3],
    pub raw_density: f32,
    pub color: [f32; 3],
}

fn row<const K: usize>(values: &[f32], i: usize) -> [f32; K] {
    values[K * i..K * (i + 1)]
        .try_into()
        .expect("a row of K values")
}

impl<S: AsRef<[f32]>> Gaussians<S> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.raw_densities.as_ref().len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Gaussian `i`.
    pub fn get(&self, i: usize) -> Gaussian {
        Gaussian {
            mean: row(self.means.as_ref(), i),
            rotation: row(self.rotations.as_ref(), i),
            log_scale: row(self.log_scales.as_ref(), i),
            raw_density: self.raw_densities.as_ref()[i],
            color: row(self.colors.as_ref(), i),
        }
    }

    /// Tensors on `device`; the shapes must hold `N` rows (see [`Self::mismatched`]).
    pub fn to_tensors(&self, device: &Device) -> Result<GaussianTensors, crate::RenderError> {
        if let Some((attribute, len)) = self.mismatched() {
            return Err(crate::RenderError::Shape {
                name: attribute.name,
                expected: format!(
                    "[{}, {}] (N from raw_densities)",
                    self.len(),
                    attribute.columns
                ),
                got: vec![len],
            });
        }
        let n = self.len();
        let matrix = |values: &S, columns: usize| {
            Tensor::<2>::from_data(
                TensorData::new(values.as_ref().to_vec(), [n, columns]),
                device,
            )
        };
        Ok(Gaussians {
            means: matrix(&self.means, 3),
            rotations: matrix(&self.rotations, 4),
            log_scales: matrix(&self.log_scales, 3),
            raw_densities: Tensor::<1>::from_data(
                TensorData::new(self.raw_densities.as_ref().to_vec(), [n]),
                device,
            ),
            colors: matrix(&self.colors, 3),
        })
    }

    /// Borrowed view.
    pub fn slices(&self) -> GaussianSlices<'_> {
        self.as_ref().map(|_, values| values.as_ref())
    }

    /// The attribute whose length does not match `N` Gaussians, if any.
    pub fn mismatched(&self) -> Option<(Attribute, usize)> {
        let n = self.len();
        self.as_ref()
            .map(|attribute, values| (attribute, values.as_ref().len()))
            .into_array()
            .into_iter()
            .find(|(attribute, len)| *len != attribute.columns * n)
    }
}

impl HostGaussians {
    /// Appends `other`'s Gaussians after these.
    pub fn append(&mut self, other: &HostGaussians) {
        for (mine, theirs) in self.as_mut().zip(other.as_ref()).into_array() {
            mine.extend_from_slice(theirs);
        }
    }

    pub fn with_capacity(n: usize) -> Self {
        Self::default().map(|attribute, _| Vec::with_capacity(attribute.columns * n))
    }

    pub fn push(&mut self, g: &Gaussian) {
        self.means.extend(g.mean);
        self.rotations.extend(g.rotation);
        self.log_scales.extend(g.log_scale);
        self.raw_densities.push(g.raw_density);
        self.colors.extend(g.color);
    }

    pub fn set(&mut self, i: usize, g: &Gaussian) {
        self.means[3 * i..3 * i + 3].copy_from_slice(&g.mean);
        self.rotations[4 * i..4 * i + 4].copy_from_slice(&g.rotation);
        self.log_scales[3 * i..3 * i + 3].copy_from_slice(&g.log_scale);
        self.raw_densities[i] = g.raw_density;
        self.colors[3 * i..3 * i + 3].copy_from_slice(&g.color);
    }
}

impl GaussianTensors {
    /// These Gaussians followed by `other`'s, as one set (what one render composites in a
    /// single depth-sorted pass).
    pub fn concat(self, other: GaussianTensors) -> GaussianTensors {
        Gaussians {
            means: Tensor::cat(vec![self.means, other.means], 0),
            rotations: Tensor::cat(vec![self.rotations, other.rotations], 0),
            log_scales: Tensor::cat(vec![self.log_scales, other.log_scales], 0),
            raw_densities: Tensor::cat(vec![self.raw_densities, other.raw_densities], 0),
            colors: Tensor::cat(vec![self.colors, other.colors], 0),
        }
    }

    pub fn len(&self) -> usize {
        self.raw_densities.dims()[0]
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The shape of every attribute.
    pub fn shapes(&self) -> Gaussians<Vec<usize>> {
        Gaussians {
            means: self.means.dims().to_vec(),
            rotations: self.rotations.dims().to_vec(),
            log_scales: self.log_scales.dims().to_vec(),
            raw_densities: self.raw_densities.dims().to_vec(),
            colors: self.colors.dims().to_vec(),
        }
    }

    /// The same Gaussians outside the autodiff graph.
    pub fn detach(self) -> Self {
        Gaussians {
            means: self.means.detach(),
            rotations: self.rotations.detach(),
            log_scales: self.log_scales.detach(),
            raw_densities: self.raw_densities.detach(),
            colors: self.colors.detach(),
        }
    }

    /// Every attribute tracked for gradients.
    pub fn require_grad(self) -> Self {
        Gaussians {
            means: self.means.require_grad(),
            rotations: self.rotations.require_grad(),
            log_scales: self.log_scales.require_grad(),
            raw_densities: self.raw_densities.require_grad(),
            colors: self.colors.require_grad(),
        }
    }

    /// Reads every attribute back to the host.
    pub fn to_host(&self) -> HostGaussians {
        fn host<const D: usize>(t: &Tensor<D>) -> Vec<f32> {
            crate::device_traffic::read_floats(t.clone())
        }
        Gaussians {
            means: host(&self.means),
            rotations: host(&self.rotations),
            log_scales: host(&self.log_scales),
            raw_densities: host(&self.raw_densities),
            colors: host(&self.colors),
        }
    }

    /// The dispatch primitives, for the custom ops.
    pub fn into_dispatch(self) -> GaussianPrimitives<Dispatch> {
        Gaussians {
            means: self.means.into_dispatch(),
            rotations: self.rotations.into_dispatch(),
            log_scales: self.log_scales.into_dispatch(),
            raw_densities: self.raw_densities.into_dispatch(),
            colors: self.colors.into_dispatch(),
        }
    }
}

/// Carries the bundle across burn's dispatch boundary, field by field, as
/// `#[derive(ExtensionType)]` does for a struct of primitives (the derive needs the struct to
/// be generic over the backend itself; this one is generic over its storage).
impl<B: Backend> ExtensionType<B> for GaussianPrimitives<B> {
    type Target = GaussianPrimitives<Dispatch>;

    fn map_to_dispatch<F>(self, map_kind: F, autodiff: DispatchAutodiffContext) -> Self::Target
    where
        F: Fn(BackendTensor<B>) -> DispatchTensorKind,
    {
        self.map(|_, tensor| DispatchTensor {
            kind: map_kind(BackendTensor::Float(tensor)),
            autodiff,
        })
    }

    fn map_from_dispatch<F>(target: Self::Target, unwrap_kind: F) -> Self
    where
        F: Fn(DispatchTensor) -> BackendTensor<B>,
    {
        target.map(|_, tensor| unwrap_kind(tensor).float())
    }

    fn routing_tensor(target: &Self::Target) -> Option<&DispatchTensor> {
        Some(&target.means)
    }

    fn routing_float_tensor(target: &Self::Target) -> Option<&DispatchTensor> {
        Some(&target.means)
    }

    fn autodiff_context(target: &Self::Target) -> DispatchAutodiffContext {
        target
            .as_ref()
            .into_array()
            .into_iter()
            .fold(DispatchAutodiffContext::Disabled, |context, tensor| {
                context.merge(tensor.autodiff)
            })
    }
}
