//! Building one training sample: random motions, object motion and merging, inpainting of
//! holes, and the deterministic recipe that ties a sample to its address.

pub mod inpaint;
pub mod motion;
pub mod rng;
