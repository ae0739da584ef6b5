//! Where source photos come from (directories of images or the reference's input layout,
//! WebDataset tar shards, uploaded bytes, the bundled default scenes), with what they carry
//! (given depth, disparity, masks, MPI), under size limits; [`open_source`] picks the kind for a
//! path.

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

/// Why a source item is bad (or was left out of its collection): the reason class of a skip, set
/// where the failure happens. [`as_str`](Self::as_str) is the `reason` of the skip counts in
/// `GetInfo` and of the `mpiflow_skipped_sources{dataset,reason}` metric.
#[non_exhaustive]
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum FailureKind {
    /// `decode`: a corrupt or unsupported image, a missing or unreadable file, bad JSON.
    Decode,
    /// `truncated`: the data ends early (a truncated JPEG, PNG or PFM, a shard member or a shard
    /// cut short).
    Truncated,
    /// `too-large`: over a byte or dimension limit.
    TooLarge,
    /// `depth`: a depth or disparity file that is malformed, or depth that is missing (no depth
    /// and no depth model) or cannot be brought to the scene scale.
    Depth,
    /// `mask`: a malformed instance-mask file.
    Mask,
    /// `mpi`: a malformed given MPI (or one of the wrong size).
    Mpi,
    /// `scene`: a scene that does not fit the recipe (sizes, intrinsics).
    Scene,
    /// `no-image`: a shard sample without an image field (left out when opened).
    NoImage,
    /// `duplicate`: a shard key whose members are not adjacent (the later run is left out).
    Duplicate,
    /// `unnamed`: a shard member without a key or field.
    Unnamed,
}

impl FailureKind {
    /// The reason string (`decode`, `truncated`, `too-large`, `depth`, `mask`, `mpi`, `scene`,
    /// `no-image`, `duplicate`, `unnamed`).
    pub const fn as_str(self) -> &'static str {
        match self {
            FailureKind::Decode => "decode",
            FailureKind::Truncated => "truncated",
            FailureKind::TooLarge => "too-large",
            FailureKind::Depth => "depth",
            FailureKind::Mask => "mask",
            FailureKind::Mpi => "mpi",
            FailureKind::Scene => "scene",
            FailureKind::NoImage => "no-image",
            FailureKind::Duplicate => "duplicate",
            FailureKind::Unnamed => "unnamed",
        }
    }

    /// The kind of this failure in a file that plays `part` ([`Depth`](Self::Depth),
    /// [`Mask`](Self::Mask), [`Mpi`](Self::Mpi)): a file that does not decode is the part's
    /// failure; too large and truncated stay what they are.
    pub fn in_part(self, part: FailureKind) -> FailureKind {
        match self {
            FailureKind::Decode => part,
            other => other,
        }
    }
}

impl std::fmt::Display for FailureKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// A file (a shard member, an upload part) that cannot be read or decoded; `kind` says why.
    #[error("{path}: {message}")]
    File { path: String, kind: FailureKind, message: String },
    #[error("{0}")]
    Invalid(String),
    /// Over a size or count limit (an upload too large for the store, too many datasets).
    #[error("{0}")]
    Limit(String),
    /// A malformed upload stream; `field` is the `SourceChunk` field at fault (`dataset`, `name`).
    #[error("{field}: {message}")]
    Upload { field: &'static str, message: String },
}

impl SourceError {
    /// A [`SourceError::File`].
    pub fn file(path: impl Into<String>, kind: FailureKind, message: impl Into<String>) -> Self {
        SourceError::File { path: path.into(), kind, message: message.into() }
    }

    /// The failure kind of a file error (`None` for the others).
    pub fn failure_kind(&self) -> Option<FailureKind> {
        match self {
            SourceError::File { kind, .. } => Some(*kind),
            _ => None,
        }
    }
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
    /// What was found but left out of the collection when it was opened (e.g. a truncated shard's
    /// last sample), with reasons. Items that fail later, when loaded, are not listed here (the
    /// sample generator skips and counts those).
    fn skipped(&self) -> Vec<SkippedItem> {
        Vec::new()
    }
}

/// Something left out of a collection, and why.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SkippedItem {
    /// What it is (`shard.tar:key`, a file name, ...).
    pub item: String,
    /// The reason class ([`FailureKind::Truncated`], [`FailureKind::NoImage`],
    /// [`FailureKind::Duplicate`], ...).
    pub kind: FailureKind,
    /// The full reason.
    pub reason: String,
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
pub mod encoded;
pub mod pfm;
pub mod shard;
pub mod upload;

pub use builtin::{BuiltinOptions, BuiltinSource};
pub use dir::{DirSource, IntrinsicsSpec, SourceOptions};
pub use shard::ShardSource;
pub use upload::{UploadLimits, UploadSession, UploadStore, UploadSummary};

/// Opens what a path holds, as a source:
///
/// - a `.tar` file: a WebDataset shard ([`ShardSource`]);
/// - another file: a single image ([`DirSource`]);
/// - a directory with an `images/` folder: the reference layout ([`DirSource`]);
/// - a directory with `.png` / `.jpg` / `.jpeg` files: the plain layout ([`DirSource`]);
/// - a directory with `.tar` files (and no images): its shards ([`ShardSource`]).
///
/// A directory holding both images and `.tar` files is refused as ambiguous (open it with
/// [`DirSource::open`] or [`ShardSource::open`] to choose).
pub fn open_source(path: &std::path::Path, options: &SourceOptions) -> Result<std::sync::Arc<dyn Source>, SourceError> {
    use std::sync::Arc;
    let meta = std::fs::metadata(path).map_err(|e| {
        let message = if e.kind() == std::io::ErrorKind::NotFound { "not found".into() } else { e.to_string() };
        SourceError::file(path.display().to_string(), FailureKind::Decode, message)
    })?;
    let ext_is = |p: &std::path::Path, exts: &[&str]| {
        p.extension().and_then(|e| e.to_str()).is_some_and(|e| exts.iter().any(|x| e.eq_ignore_ascii_case(x)))
    };
    if meta.is_file() {
        return if ext_is(path, &["tar"]) {
            Ok(Arc::new(ShardSource::open(path, options)?))
        } else {
            Ok(Arc::new(DirSource::open(path, options)?))
        };
    }
    if path.join("images").is_dir() {
        return Ok(Arc::new(DirSource::open(path, options)?));
    }
    let (mut images, mut tars) = (false, false);
    let rd = std::fs::read_dir(path)
        .map_err(|e| SourceError::file(path.display().to_string(), FailureKind::Decode, e.to_string()))?;
    for ent in rd.flatten() {
        let p = ent.path();
        if !std::fs::metadata(&p).is_ok_and(|m| m.is_file()) {
            continue;
        }
        images |= ext_is(&p, &["png", "jpg", "jpeg"]);
        tars |= ext_is(&p, &["tar"]);
    }
    match (images, tars) {
        (true, true) => Err(SourceError::file(
            path.display().to_string(),
            FailureKind::Decode,
            "holds both images and .tar shards; give the images or the shards a folder of their own",
        )),
        (false, true) => Ok(Arc::new(ShardSource::open(path, options)?)),
        _ => Ok(Arc::new(DirSource::open(path, options)?)),
    }
}
