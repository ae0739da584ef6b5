//! Building one training sample: random motions, object motion and merging, inpainting of
//! holes, and the deterministic recipe that ties a sample to its address.
//!
//! # The rooms
//!
//! This file is the front door: the module list and the names of what a sample is (from the
//! room `types.rs`). The rooms name only rooms under them (`tests/server/layers.rs` holds the order):
//! `inpaint` (Telea), `motion` (motion laws and draws), `object` (object choice and windowed
//! renders), `preblend` < `types` (the sample's fields), `error` ([`error::SampleError`]) <
//! `merge`, `noise` < `background` (the planes behind moved objects) < `config`
//! ([`config::SampleConfig`]) < `holes` (inpainting over crops), `augment` < `crop` (a request's
//! crop: its window and cut) < `recipe` (one address -> one sample) < `pipeline` (`Pipeline`,
//! `Generator`, the dataset fingerprint).

pub mod augment;
pub mod background;
pub mod config;
pub mod crop;
pub mod error;
pub mod holes;
pub mod inpaint;
pub mod merge;
pub mod motion;
pub mod noise;
pub mod object;
pub mod pipeline;
pub mod preblend;
pub mod recipe;
pub mod reveal;
mod types;

pub use types::{disparity_of, ClipFrame, LinkFields, ObjectRecord, Sample, SampleAddress, StageTimings};
