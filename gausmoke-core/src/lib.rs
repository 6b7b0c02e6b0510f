//! Conventions shared by every GauSmoke-rs crate, stated once.
//!
//! * **World frame**: right-handed, units as the data set gives them, +Y up.
//! * **Cameras** ([`Camera`]): pinhole, camera-to-world rigid transform in the **OpenGL
//!   convention** (as in NeRF / Blender data): in camera space the camera looks down -Z, +X is
//!   right and +Y is up.
//! * **Pixels**: column `u` grows to the right, row `v` grows downwards, pixel `(i, j)` has its
//!   centre at `(i + 0.5, j + 0.5)`. Intrinsics `fx, fy, cx, cy` are in pixels.
//! * **Images**: f32 linear values in `[0, 1]`, `[height, width, channels]` on the host.
//!
//! Also the pieces every crate uses: a seeded generator ([`SplitMix64`]) and the per-phase
//! wall times of training, measured from `tracing` spans ([`phases`]). This crate has no
//! tensor dependency so the data loaders can use it without pulling a deep-learning framework.

mod camera;
pub mod phases;
mod rng;

pub use camera::{Camera, CameraError, Intrinsics};
pub use glam;
pub use rng::SplitMix64;
/// Re-exported for [`phase!`].
pub use tracing;
