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

#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error("{path}: {message}")]
    File { path: String, message: String },
    #[error("{0}")]
    Invalid(String),
    /// Over a size or count limit (an upload too large for the store, too many datasets).
    #[error("{0}")]
    Limit(String),
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
    /// A short reason class (`truncated`, `no-image`, `duplicate`, ...).
    pub class: String,
    /// The full reason.
    pub reason: String,
}

/// The reason class of a source item's load failure, from the failing file (`path`, empty when
/// none) and the message:
///
/// - `too-large`: over a byte or dimension limit (`... is larger than the limit ...`, `... is
///   too large ...`);
/// - `truncated`: the data ends early (a truncated JPEG, PNG or PFM, a shard member cut short);
/// - `depth`: a depth or disparity file (in `depths/` or `disps/`, a `depth.*` / `disp.*`
///   shard field, an upload's `DATASET/depth/NAME`) that is malformed, or a message about depth or disparity (no
///   depth, depth that cannot be brought to the scene scale);
/// - `mask`: an instance-mask file (`masks/`, a `mask.*` field, `DATASET/mask/NAME`);
/// - `mpi`: a given MPI (`mpis/`);
/// - `decode`: anything else (a corrupt or unsupported image, a missing file, bad JSON).
///
/// The checks run in that order, so a truncated depth file is `truncated`.
pub fn failure_class(path: &str, message: &str) -> &'static str {
    let m = message.to_ascii_lowercase();
    if m.contains("larger than the limit") || m.contains("is too large") || m.contains("empty or too large") {
        return "too-large";
    }
    // the image decoder's category name mentions truncation for every corrupt image
    let m2 = m.replace("corrupt or truncated image", "corrupt image");
    if m2.contains("truncated") || m2.contains("unexpected end of") {
        return "truncated";
    }
    let p = path.to_ascii_lowercase();
    let mut parts = p.rsplit(['/', ':']);
    let base = parts.next().unwrap_or("");
    let parent = parts.next().unwrap_or("");
    let field = base.split_once('.').map(|(_, f)| f).unwrap_or("");
    let is = |dirs: &[&str], fields: &[&str]| dirs.contains(&parent) || fields.iter().any(|f| field.starts_with(f));
    if is(&["depths", "disps", "depth"], &["depth", "disp"]) || m.contains("depth") || m.contains("disparity") {
        return "depth";
    }
    if is(&["masks", "mask"], &["mask"]) {
        return "mask";
    }
    if is(&["mpis"], &[]) {
        return "mpi";
    }
    "decode"
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
    let meta = std::fs::metadata(path).map_err(|e| SourceError::File {
        path: path.display().to_string(),
        message: if e.kind() == std::io::ErrorKind::NotFound { "not found".into() } else { e.to_string() },
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
        .map_err(|e| SourceError::File { path: path.display().to_string(), message: e.to_string() })?;
    for ent in rd.flatten() {
        let p = ent.path();
        if !std::fs::metadata(&p).is_ok_and(|m| m.is_file()) {
            continue;
        }
        images |= ext_is(&p, &["png", "jpg", "jpeg"]);
        tars |= ext_is(&p, &["tar"]);
    }
    match (images, tars) {
        (true, true) => Err(SourceError::File {
            path: path.display().to_string(),
            message: "holds both images and .tar shards; give the images or the shards a folder of their own".into(),
        }),
        (false, true) => Ok(Arc::new(ShardSource::open(path, options)?)),
        _ => Ok(Arc::new(DirSource::open(path, options)?)),
    }
}
