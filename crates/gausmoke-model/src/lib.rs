//! GauSmoke's physics half (paper Sec. 4.2-4.4, Appendix A): the Eulerian grid, continuous
//! velocity interpolation with its closed-form divergence, and advection of Gaussian centres.
//!
//! Still to come (issue 4): density splatting to the grid as a custom op, the U-Net Phi, the
//! Helmholtz projection, and the physical losses.

pub mod advect;
pub mod grid;
pub mod interp;

pub use advect::{Advected, Integrator, advect};
pub use grid::{GridError, GridSpec};
pub use interp::{Interpolation, VelocitySample, grid_from_fn, sample_velocity};
