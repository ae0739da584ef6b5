//! The per-source scene stage: depth, MPI and instance masks, from ONNX models, given with the
//! source, or built in, behind three small traits; and the scene every sample of a source reuses.
//!
//! Scale convention (binding for every implementation): a scene's `disparity` is normalised to
//! the reference generator's scale, values in [0, 1] with 1 = the nearest content (depth 1) and
//! smaller = farther (depth = 1 / disparity); motion presets are defined in that scale. See
//! [`scale`] for how each kind of depth input is brought to it.

pub mod builtin;
pub mod cache;
pub mod hub;
pub mod matte;
pub mod models;
pub mod onnx;
pub mod registry;
pub mod scale;
pub mod stage;

use std::sync::Arc;

use crate::geometry::Intrinsics;
use crate::io::image::RgbImage;
use crate::mpi::Mpi;
use crate::raster::InstanceMasks;
use crate::source::FailureKind;

/// A disparity map in the scene scale: H x W values in [0, 1], 1 = nearest (depth 1), every
/// value finite (unknown pixels are filled by whoever produced the map).
#[derive(Clone, Debug, PartialEq)]
pub struct Disparity {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

/// Errors of the scene stage. Each names the model (or file) and, for models, the tensor.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// ONNX Runtime itself could not be loaded (missing, too old, ORT_DYLIB_PATH wrong).
    #[error("ONNX Runtime: {0}")]
    Runtime(String),
    /// A model file or its tensors do not fit the contract, or inference failed / gave NaN.
    #[error("{kind} model {model}: {message}")]
    Model { kind: &'static str, model: String, message: String },
    /// A source file (image, depth, masks, MPI) is missing or malformed; `kind` says how.
    #[error("{path}: {message}")]
    Given { path: String, kind: FailureKind, message: String },
    /// The item's data does not make a scene (no depth and no depth model, depth or disparity
    /// without a usable value, a given MPI of the wrong size); `kind` says which part.
    #[error("{message}")]
    Data { kind: FailureKind, message: String },
    #[error(transparent)]
    Mask(#[from] crate::raster::MaskError),
    #[error(transparent)]
    Mpi(#[from] crate::mpi::MpiError),
    /// A whole collection cannot make scenes: none of its items carries depth (or an MPI) and no
    /// depth model is configured. The message names the fix.
    #[error(
        "photos carry no depth and no depth model is configured: pass --depth-model NAME|FILE (see \
         docs/models.md), or ship depths/ beside images/"
    )]
    NoDepthModel,
    /// Anything else that makes this item's scene unusable (reported as [`FailureKind::Scene`]).
    #[error("{0}")]
    Invalid(String),
}

impl SceneError {
    /// The failure kind when the error is the item's (its data is bad: the item is skipped), or
    /// `None` when it is not (the runtime, a model).
    pub fn failure_kind(&self) -> Option<FailureKind> {
        match self {
            SceneError::Runtime(_) | SceneError::Model { .. } | SceneError::NoDepthModel => None,
            SceneError::Given { kind, .. } | SceneError::Data { kind, .. } => Some(*kind),
            SceneError::Mask(m) => Some(m.failure_kind()),
            SceneError::Mpi(_) => Some(FailureKind::Mpi),
            SceneError::Invalid(_) => Some(FailureKind::Scene),
        }
    }
}

/// Estimates disparity (scene scale, see the module docs) from an image.
pub trait DepthEstimator: Send + Sync {
    /// A short name for logs and sample metadata (e.g. `onnx:model.onnx`).
    fn name(&self) -> String;
    /// Everything that makes this estimator's output what it is, for fingerprints (for a model:
    /// the content hash of its file and its contract). Default: [`Self::name`].
    fn identity(&self) -> String {
        self.name()
    }
    fn estimate(&self, image: &RgbImage) -> Result<Disparity, SceneError>;
    /// Inferences run so far (warm-up excluded), or `None` when this is not a model (a built-in
    /// rule that costs no inference): what `mpiflow_model_runs_total` counts.
    fn inference_runs(&self) -> Option<u64> {
        None
    }
    /// The FNV-1a 64 ([`crate::hash::Fnv64`]) of the model file's bytes, `None` when not a model
    /// file (bake provenance, `bake-report.json`).
    fn content_hash(&self) -> Option<u64> {
        None
    }
}

/// Lifts an image with its disparity into an MPI (planes near to far).
pub trait MpiBuilder: Send + Sync {
    fn name(&self) -> String;
    /// What makes the output what it is, for fingerprints (see [`DepthEstimator::identity`]).
    fn identity(&self) -> String {
        self.name()
    }
    fn build(&self, image: &RgbImage, disparity: &Disparity, k: &Intrinsics) -> Result<Mpi, SceneError>;
    /// [`MpiBuilder::build`] knowing the scene's instance masks (the objects that may move), for
    /// a builder that completes the background behind them; the default ignores them.
    fn build_with_masks(
        &self,
        image: &RgbImage,
        disparity: &Disparity,
        _masks: &InstanceMasks,
        k: &Intrinsics,
    ) -> Result<Mpi, SceneError> {
        self.build(image, disparity, k)
    }
    /// Whether the scene's object masks are aligned with their depth edges before the build
    /// ([`matte::align_to_depth`]); the builder's name says so when they are.
    fn aligns_masks(&self) -> bool {
        false
    }
    /// Inferences run so far (warm-up excluded), or `None` when this is not a model (a built-in
    /// rule that costs no inference): what `mpiflow_model_runs_total` counts.
    fn inference_runs(&self) -> Option<u64> {
        None
    }
    /// The FNV-1a 64 ([`crate::hash::Fnv64`]) of the model file's bytes, `None` when not a model
    /// file (bake provenance, `bake-report.json`).
    fn content_hash(&self) -> Option<u64> {
        None
    }
}

/// Finds object instances in an image.
pub trait Segmenter: Send + Sync {
    fn name(&self) -> String;
    /// What makes the output what it is, for fingerprints (see [`DepthEstimator::identity`]).
    fn identity(&self) -> String {
        self.name()
    }
    fn segment(&self, image: &RgbImage) -> Result<InstanceMasks, SceneError>;
    /// Inferences run so far (warm-up excluded), or `None` when this is not a model (a built-in
    /// rule that costs no inference): what `mpiflow_model_runs_total` counts.
    fn inference_runs(&self) -> Option<u64> {
        None
    }
    /// The FNV-1a 64 ([`crate::hash::Fnv64`]) of the model file's bytes, `None` when not a model
    /// file (bake provenance, `bake-report.json`).
    fn content_hash(&self) -> Option<u64> {
        None
    }
}

/// Everything a source's samples reuse, computed once per source (and cached).
#[derive(Clone, Debug)]
pub struct Scene {
    /// The source's id (file stem, shard key, ...).
    pub id: String,
    pub image: RgbImage,
    pub disparity: Disparity,
    pub mpi: Arc<Mpi>,
    /// Instances (possibly none) on the image grid.
    pub masks: InstanceMasks,
    pub intrinsics: Intrinsics,
    /// Which implementation produced each part, e.g. `["depth: given npy", "mpi: builtin soft 32"]`.
    pub provenance: Vec<String>,
}

impl Scene {
    /// Bytes held by the scene (for the cache's budget).
    pub fn byte_size(&self) -> usize {
        self.mpi.byte_size()
            + self.image.data.len() * 4
            + self.disparity.data.len() * 4
            + self.masks.masks.iter().map(|m| m.mask.len() * 4).sum::<usize>()
    }
}

/// Produces the scene of source item `i` of a collection (loading the source and running or
/// skipping each model). Implemented by the scene stage; the sample generator caches its output.
pub trait SceneLoader: Send + Sync {
    /// Number of source items.
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The id of item `i` without loading it.
    fn id(&self, i: usize) -> String;
    /// The collection's fingerprint (see [`crate::source::Source::fingerprint`]) combined with
    /// everything in the stage's configuration that changes the scene (models, planes).
    fn fingerprint(&self) -> u64;
    fn load_scene(&self, i: usize) -> Result<Scene, SceneError>;
}
