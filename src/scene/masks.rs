//! The scene's instance masks: the [`crate::raster`] types, re-exported where the scene stage
//! and its users have always found them.

pub use crate::raster::*;
