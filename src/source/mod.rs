//! Where source photos come from (directories of images or the reference's input layout, the
//! bundled default scenes), with what they carry (given depth, disparity, masks, MPI), under
//! size limits.

use crate::geometry::Intrinsics;
use crate::io::image::RgbImage;
use crate::mpi::Mpi;
use crate::scene::masks::InstanceMasks;

/// Depth information shipped with a source, as read from disk (not yet in the scene scale).
#[derive(Clone, Debug, PartialEq)]
pub enum GivenDepth {
    /// Metric (or any linear-unit) depth, H x W; non-finite or <= 0 = unknown.
    Depth(Vec<f32>),
    /// Disparity already in [0, 1] as the reference reads it (8-bit PNG / 255, 16-bit / 65535).
    Disparity(Vec<f32>),
}

/// One source photo and whatever it carries.
#[derive(Clone, Debug)]
pub struct SourceItem {
    /// Stable id (the file stem, or the generator's name for built-in scenes).
    pub id: String,
    pub image: RgbImage,
    pub depth: Option<GivenDepth>,
    pub masks: Option<InstanceMasks>,
    /// A whole precomputed MPI (skips depth and the MPI step).
    pub mpi: Option<Mpi>,
    pub intrinsics: Option<Intrinsics>,
}

#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error("{path}: {message}")]
    File { path: String, message: String },
    #[error("{0}")]
    Invalid(String),
}

/// An indexed, immutable collection of sources.
pub trait Source: Send + Sync {
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The id of item `i` without loading it.
    fn id(&self, i: usize) -> String;
    fn load(&self, i: usize) -> Result<SourceItem, SourceError>;
    /// A 64-bit fingerprint of the collection's content identity (ids and file sizes/hashes), part
    /// of every sample address: same fingerprint, same samples.
    fn fingerprint(&self) -> u64;
    /// A short human description (`dir:/data/photos (120 images)`).
    fn describe(&self) -> String;
}
