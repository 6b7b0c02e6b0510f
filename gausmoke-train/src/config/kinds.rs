//! The configuration's choices among named alternatives, spelled for TOML.

use serde::{Deserialize, Serialize};

/// Which form of the incompressibility projection `Pi` (paper Eq. 10) the run uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProjectionKind {
    /// Exact discrete Helmholtz projection (solid walls): a direct Poisson solve by separation
    /// of variables on the CPU backends, Jacobi-PCG on the device backends.
    Exact,
    /// The paper's penalty form: `penalty_steps` gradient steps on `|D u|^2 / 2`.
    Penalty,
}

/// The axes of the exported `.ply` files.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PlyAxes {
    /// The data set's world axes, as the grids and cameras use them.
    World,
    /// The world turned half a turn about x (y and z negated): the OpenCV/COLMAP camera
    /// frame that 3DGS training produces and splat viewers assume (SuperSplat shows such a
    /// file upright by turning it back), so a y-up world opens upright there.
    YDown,
}

/// The velocity a finished run ends with besides its grid's (see `velocity_estimate`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VelocityEstimate {
    /// None: the run's velocity is the grid the joint iterations fitted.
    None,
    /// The velocity that carries each frame's density grid onto the next, tracked through
    /// the frames (`gausmoke-train velocity`).
    Density,
    /// The same, each frame's fit started from a smoke solver's step with a source in
    /// `scene.inflow` (`gausmoke-train velocity --forces`); without an inflow, `density`.
    Forces,
}

/// What the training does with obstacles the data set describes (PINF `obstacles`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Obstacles {
    /// Their cells become solid in the exact projection: no velocity inside, no flow through
    /// their surface.
    Solid,
    /// Ignored: the flow is free to pass through them (the paper's behaviour, an ablation).
    Ignore,
}

/// When the GPU projection's host learns that a solve converged
/// ([`gausmoke_model::ConvergenceTests`], spelled for TOML); the CPU backends solve directly
/// and ignore it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SolverTests {
    /// Solves run a learnt budget of iterations with no read and are judged with the losses.
    Deferred,
    /// Each solve reads its residuals while it runs (about 1.5 reads per solve).
    Immediate,
}

impl From<SolverTests> for gausmoke_model::ConvergenceTests {
    fn from(tests: SolverTests) -> Self {
        match tests {
            SolverTests::Deferred => Self::Deferred,
            SolverTests::Immediate => Self::Immediate,
        }
    }
}

/// How the GPU backward pass sums one splat's gradients over the pixels of a tile
/// ([`gausmoke_render::GradientSums`], spelled for TOML); the CPU backends ignore it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GradientSums {
    /// Plane (subgroup) sums, one atomic add per float per tile; per pixel on devices without
    /// plane operations.
    Planes,
    /// Shared-memory sums, for GPUs without plane operations.
    SharedMemory,
    /// One atomic add per contributing pixel.
    PerPixel,
}

impl From<GradientSums> for gausmoke_render::GradientSums {
    fn from(sums: GradientSums) -> Self {
        match sums {
            GradientSums::Planes => Self::Planes,
            GradientSums::SharedMemory => Self::SharedMemory,
            GradientSums::PerPixel => Self::PerPixel,
        }
    }
}

/// How the GPU backends solve the projection's Poisson equation on a grid without obstacles
/// ([`gausmoke_model::DeviceSolve`], spelled for TOML); with obstacles, and on the CPU
/// backends, this changes nothing.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ProjectionSolve {
    /// In one step by separation of variables, as matrix products: no iteration, no read.
    Direct,
    /// Jacobi-PCG to `projection.tolerance`, as with obstacles.
    Iterative,
}

impl From<ProjectionSolve> for gausmoke_model::DeviceSolve {
    fn from(solve: ProjectionSolve) -> Self {
        match solve {
            ProjectionSolve::Direct => Self::Direct,
            ProjectionSolve::Iterative => Self::Iterative,
        }
    }
}
