//! The backward passes of the renderer's stages, one file each (see [`super`] for how
//! [`super::backward`] chains them).

pub mod background;
pub mod rasterize;
pub mod view;
