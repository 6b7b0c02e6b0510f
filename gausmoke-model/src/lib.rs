//! GauSmoke's model and physics (paper Sec. 4.2-4.4, Appendix A), building on the renderer:
//! the trainable Gaussians ([`GaussianModel`]), the Eulerian grid, density splatting to it
//! (a custom op with hand-written backward passes, with the density's analytic spatial
//! gradient), continuous velocity interpolation with its closed-form divergence, advection of
//! Gaussian centres, the exact Helmholtz projection `Pi` (a custom op whose backward is `Pi`
//! itself) and the paper's penalty form of it ([`penalty`]), the update network Phi (a small
//! 3D U-Net), the losses `L_div`, `L_adv` and `L_refine` (plain tensor functions), and the split of the
//! refinement's move into its grid-scale and sub-grid parts ([`GridScale`]).

pub mod advect;
pub mod conv;
pub mod density;
pub mod gaussians;
pub mod grid;
pub mod interp;
pub mod losses;
pub mod moves;
pub mod penalty;
pub mod projection;
pub mod unet;

pub use advect::{Advected, Integrator, advect, transport_velocity};
pub use density::{
    DensityBackend, DensityField, SplatOptions, density_and_gradient_grid, density_field,
    density_gradient_grid, density_grid,
};
pub use gaussians::{GaussianModel, INITIAL_RAW_DENSITY};
pub use grid::{GridError, GridSpec};
pub use interp::{Interpolation, VelocitySample, grid_from_fn, sample_velocity};
pub use losses::{advection_loss, divergence_loss, divergence_loss_of, refine_loss};
pub use moves::GridScale;
pub use penalty::{PenaltyOptions, penalty_projection};
pub use projection::{
    ConvergenceTests, DeferredSolves, DeviceSolve, OpenFaces, ProjectionBackend, ProjectionOptions,
    ProjectionReport, ProjectionSpec, SolidCells, project_direct, project_velocity,
    project_with_report, settle_deferred_solves,
};
pub use unet::{UNetConfig, UNetError, VelocityUNet};
