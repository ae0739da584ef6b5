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

/// The 64-bit FNV-1a hash, written out so that fingerprints are the same on every machine, build
/// and Rust version (std's `DefaultHasher` promises none of that). Multi-byte values are fed
/// little-endian; strings are fed with their length first, so `("ab", "c")` and `("a", "bc")`
/// differ.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Fnv64(u64);

impl Default for Fnv64 {
    fn default() -> Self {
        Self::new()
    }
}

impl Fnv64 {
    const OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
    const PRIME: u64 = 0x0000_0100_0000_01b3;

    pub fn new() -> Self {
        Fnv64(Self::OFFSET)
    }

    pub fn bytes(&mut self, bytes: &[u8]) -> &mut Self {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(Self::PRIME);
        }
        self
    }

    pub fn u64(&mut self, v: u64) -> &mut Self {
        self.bytes(&v.to_le_bytes())
    }

    pub fn f64(&mut self, v: f64) -> &mut Self {
        self.u64(v.to_bits())
    }

    pub fn str(&mut self, s: &str) -> &mut Self {
        self.u64(s.len() as u64).bytes(s.as_bytes())
    }

    pub fn finish(&self) -> u64 {
        self.0
    }
}

/// The FNV-1a hash of a byte string ([`Fnv64`]).
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    Fnv64::new().bytes(bytes).finish()
}

pub mod builtin;
pub mod dir;
pub mod pfm;

pub use builtin::{BuiltinOptions, BuiltinSource};
pub use dir::{DirSource, IntrinsicsSpec, SourceOptions};
