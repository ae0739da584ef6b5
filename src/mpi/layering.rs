//! Built-in RGB-D layering (being written).

use super::{Mpi, MpiError};

/// How pixels are assigned to planes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Layering {
    /// Each pixel goes to its nearest plane (in disparity).
    Hard,
    /// Each pixel is split between the two neighbouring planes, linearly in disparity.
    #[default]
    Soft,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LayeringOptions {
    pub planes: usize,
    pub layering: Layering,
    /// (nearest, farthest) plane disparities; None = the scene's own disparity range.
    pub disparity_range: Option<(f64, f64)>,
}

/// Builds an MPI from an image (H x W x 3 in [0, 1]) and a depth map (H x W, in the unit of the
/// translation; non-finite or <= 0 means unknown).
pub fn build_mpi(_rgb: &[f32], _depth: &[f32], _width: usize, _height: usize, _opts: &LayeringOptions) -> Result<Mpi, MpiError> {
    Err(MpiError::Invalid("built-in layering is not written yet".into()))
}
