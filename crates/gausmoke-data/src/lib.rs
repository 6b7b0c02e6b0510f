//! Smoke data sets in their published formats and the synthetic scene generator.
//!
//! Empty until the data issue lands; it depends only on `gausmoke-core` (cameras), never on
//! the renderer or on training.
