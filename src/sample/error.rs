//! [`SampleError`], the one error of sample generation, and which failures make a source item
//! bad ([`SampleError::bad_source_kind`]).

use super::motion::MotionError;
use super::preblend::PreblendError;
use crate::render::RenderError;
use crate::scene::SceneError;
use crate::source::FailureKind;

/// Errors of sample generation; each names the source it concerns.
#[derive(Debug, thiserror::Error)]
pub enum SampleError {
    /// A configuration field out of range: `field` names it (`max_objects`,
    /// `skip.tile_sigma_eps`, ...), `message` gives the value and what was expected.
    #[error("invalid sample configuration: {field} = {message}")]
    Config { field: &'static str, message: String },
    #[error("invalid sample configuration: {0}")]
    Motion(#[from] MotionError),
    #[error("the source collection is empty: there is nothing to make samples from")]
    EmptySource,
    #[error("source item {item} ({id}): {source}")]
    Scene {
        item: usize,
        id: String,
        #[source]
        source: Box<SceneError>,
    },
    #[error("scene {id}: {message}")]
    InvalidScene { id: String, message: String },
    #[error("scene {id}: the {stage} render failed: {source}")]
    Render {
        id: String,
        stage: &'static str,
        #[source]
        source: Box<RenderError>,
    },
    #[error("scene {id}: {source}")]
    Preblend {
        id: String,
        #[source]
        source: PreblendError,
    },
    /// The collection as a whole cannot make scenes (e.g. [`SceneError::NoDepthModel`]): a
    /// configuration problem, found before any sample is made.
    #[error("{0}")]
    Unusable(SceneError),
    /// A request's crop larger than the rendered frame (never shrunk to fit).
    #[error("{0}")]
    Crop(CropTooLarge),
    /// Every source item failed to load (see `Generator::sample`).
    #[error("all {items} source items failed to load (first: {first})")]
    NoGoodSource { items: usize, first: String },
}

/// A crop that does not fit the rendered frame (never shrunk to fit).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{want_w}x{want_h} is larger than the rendered frame {w}x{h}")]
pub struct CropTooLarge {
    pub want_w: usize,
    pub want_h: usize,
    pub w: usize,
    pub h: usize,
}

impl SampleError {
    /// The failure kind when the error makes its source item bad (skipped: the item's data is
    /// corrupt, truncated, too large, or its depth, masks, MPI or scene are unusable), or `None`
    /// for failures that are not the item's (the runtime, a model, the configuration, a render):
    /// those are returned to the caller.
    pub fn bad_source_kind(&self) -> Option<FailureKind> {
        match self {
            SampleError::Scene { source, .. } => source.failure_kind(),
            SampleError::InvalidScene { .. } => Some(FailureKind::Scene),
            _ => None,
        }
    }
}
