//! What interpolation is asked for, and what it returns.

use burn::tensor::{Int, Tensor, TensorData};

/// How the grid is sampled between cell centres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Interpolation {
    /// Normalised isotropic Gaussian kernel (Eq. 11) over `stencil^3` nearest cell centres,
    /// standard deviation `std_cells` cell sizes along each axis.
    Gaussian { stencil: usize, std_cells: f32 },
    /// Trilinear over the 2x2x2 nearest cell centres (exact for linear fields).
    Trilinear,
}

impl Default for Interpolation {
    fn default() -> Self {
        Self::Gaussian {
            stencil: 4,
            std_cells: 0.6,
        }
    }
}

impl Interpolation {
    /// Nodes per axis the stencil reads.
    pub fn stencil(&self) -> usize {
        match self {
            Self::Gaussian { stencil, .. } => *stencil,
            Self::Trilinear => 2,
        }
    }
}

/// Velocity sampled at points, with its spatial derivatives.
#[derive(Debug, Clone)]
pub struct VelocitySample {
    /// `u(x)`, `[M, 3]`.
    pub velocity: Tensor<2>,
    /// `J[m, a, b] = d u_a / d x_b`, `[M, 3, 3]`.
    pub jacobian: Tensor<3>,
}

impl VelocitySample {
    /// `div u = trace(J)`, `[M]`.
    pub fn divergence(&self) -> Tensor<1> {
        let [m, _, _] = self.jacobian.dims();
        let j = self.jacobian.clone().reshape([m, 9]);
        let diagonal =
            Tensor::<1, Int>::from_data(TensorData::new(vec![0i32, 4, 8], [3]), &j.device());
        j.select(1, diagonal).sum_dim(1).reshape([m])
    }
}
