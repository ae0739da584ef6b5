//! Where source photos come from (directories of images or the reference's input layout,
//! WebDataset tar shards, uploaded bytes, the bundled default scenes), with what they carry
//! (given depth, disparity, masks, MPI), under size limits; [`open_source`] picks the kind for a
//! path.

use crate::geometry::Intrinsics;
use crate::io::image::RgbImage;
use crate::mpi::Mpi;
use crate::raster::InstanceMasks;

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

pub use crate::failure::FailureKind;

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
    /// What every item carries, known from the listing without loading (so which scene models
    /// its scenes can skip). Default: nothing known.
    fn carried(&self) -> Carried {
        Carried::default()
    }
    /// The provenance of a baked collection ([`baked::BakeManifest::describe`]), `None` when it
    /// was not made by `mpiflow bake`.
    fn baked_with(&self) -> Option<String> {
        None
    }
    /// How many items carry neither depth (or disparity) nor an MPI, known from the listing
    /// without loading; `None` when the listing does not say (such a collection is never refused
    /// for it before its items are loaded).
    fn items_without_depth(&self) -> Option<usize> {
        None
    }
}

/// What every item of a collection carries (each `true` only when all items do).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Carried {
    /// Depth or disparity.
    pub depth: bool,
    pub masks: bool,
    pub mpi: bool,
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

pub use crate::hash::Fnv64;

/// The FNV-1a hash of a byte string ([`Fnv64`]).
pub fn fnv1a64(bytes: &[u8]) -> u64 {
    Fnv64::new().bytes(bytes).finish()
}

pub mod baked;
pub mod builtin;
pub mod dir;
pub mod encoded;
pub mod given;
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
/// - a directory with `.png` / `.jpg` / `.jpeg` / `.webp` files: the plain layout ([`DirSource`]);
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
        images |= ext_is(&p, &["png", "jpg", "jpeg", "webp"]);
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
