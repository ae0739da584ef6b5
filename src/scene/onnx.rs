//! The scene models through ONNX Runtime (`ort` with `load-dynamic`): [`OnnxDepth`],
//! [`OnnxMpi`], [`OnnxSegmenter`] and [`OnnxDetr`], implementing the scene traits with the default contracts
//! of `docs/models.md` (tensor names, normalisation and input size configurable).
//!
//! # Life cycle
//! * The ONNX Runtime library is loaded once per process by the first constructor (or
//!   [`init_runtime`]) from the configured path or `ORT_DYLIB_PATH`; see [`runtime`] for the
//!   errors. Nothing in this module panics on a missing or wrong library.
//! * Each constructor loads its model once, checks its tensors against the contract (names,
//!   element type, declared rank), and makes one warm-up run on a grey dummy image (which also
//!   checks the output shapes); so a wrong model fails at start-up, not at the first sample.
//! * The models are `Send + Sync` and meant to be shared (e.g. in an `Arc`) by all workers.
//!   `ort`'s `Session::run` takes `&mut self`, so each model holds its session in a `Mutex`:
//!   inferences on one model are serialised, ONNX Runtime parallelising inside each one
//!   (`intra_threads`, default one thread per core).
//! * Each model times its `Session::run` calls ([`InferenceStats`]), so a bench can report
//!   inference separately from the rest.
//!
//! # Errors
//! A [`SceneError::Runtime`](crate::scene::SceneError::Runtime) for the library (missing, not a library, older than 1.31, already
//! loaded from another path); a [`SceneError::Model`](crate::scene::SceneError::Model) naming the model file and the tensor for
//! everything else: missing file, unknown input or output name (listing the model's real
//! tensors with their types and shapes), wrong rank or shape, an input the contract does not
//! feed, NaN or infinite outputs, failed inference (with ONNX Runtime's message).
//!
//! # Resizing
//! Image, disparity and outputs are resized with [`crate::raster::resize_bilinear`]
//! (pixel centres aligned, i.e. PyTorch's `align_corners=False`, no antialiasing). AdaMPI's own
//! scripts resize with `align_corners=True`; the difference is below half a pixel.

mod depth;
mod detr;
mod model;
mod mpi;
pub mod runtime;
mod segment;

pub(crate) use depth::normalize_disparity;
pub use depth::{OnnxDepth, OnnxDepthConfig, RawDepth, DEFAULT_DISPARITY_FLOOR};
pub use detr::{detr_instances, DetrOutputs, DetrSelection, OnnxDetr, OnnxDetrConfig};
pub use model::{InferenceStats, Normalization, SizePolicy};
pub use mpi::{OnnxMpi, OnnxMpiConfig};
pub use runtime::{init_runtime, runtime_info, RuntimeInfo, ORT_DYLIB_ENV};
pub use segment::{OnnxSegmenter, OnnxSegmenterConfig};

#[cfg(test)]
mod tests {
    use super::*;

    fn assert_send_sync<T: Send + Sync>() {}

    #[test]
    fn models_are_send_and_sync() {
        assert_send_sync::<OnnxDepth>();
        assert_send_sync::<OnnxMpi>();
        assert_send_sync::<OnnxSegmenter>();
        assert_send_sync::<OnnxDetr>();
    }
}
