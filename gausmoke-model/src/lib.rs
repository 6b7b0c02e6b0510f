//! GauSmoke's physics half (paper Sec. 4.2-4.4, Appendix A): the Eulerian grid, continuous
//! velocity interpolation with its closed-form divergence, advection of Gaussian centres, and
//! the exact Helmholtz projection `Pi` (a custom op whose backward is `Pi` itself).
//!
//! Density splatting to the grid is a custom op with a hand-written backward.
//!
//! The update network Phi is a small 3D U-Net module.
//!
//! The density's analytic spatial gradient comes from the same op; the losses `L_div`,
//! `L_adv` and `L_refine` are plain tensor functions.
//!
//! `Pi` also comes in the paper's penalty form ([`penalty`]), for comparison.

pub mod advect;
pub mod density;
#[cfg(feature = "cube")]
mod density_kernel;
mod density_op;
pub mod grid;
pub mod interp;
pub mod losses;
pub mod penalty;
pub mod projection;
#[cfg(feature = "cube")]
mod projection_kernel;
mod projection_op;
pub mod unet;

pub use advect::{Advected, Integrator, advect};
pub use density_op::{DensityBackend, DensityField, density_gradient_grid, density_grid};
pub use grid::{GridError, GridSpec};
pub use interp::{Interpolation, VelocitySample, grid_from_fn, sample_velocity};
pub use losses::{advection_loss, divergence_loss, refine_loss};
pub use penalty::{PenaltyOptions, penalty_projection};
pub use projection::{ProjectionOptions, ProjectionReport};
pub use projection_op::{ProjectionBackend, ProjectionSpec, project_velocity, project_with_report};
pub use unet::{UNetConfig, UNetError, VelocityUNet};
