//! GauSmoke's physics half: Gaussians as burn modules, the Eulerian velocity grid, the U-Net
//! Phi, the incompressibility projection, interpolation, advection and the physical losses.
//!
//! Empty until the physics issue lands; the crate exists so the workspace's dependency arrows
//! (render -> model -> train) are fixed from the start.
