//! The renderer and the layering: reference vectors, render windows, label and depth laws, resampling,
//! stability, texture, noise, stereo, motion and the backward fields.
//! One test binary per group (each file beside this one is a module), so that the suite links a
//! handful of binaries.

mod accuracy;
mod backward;
mod crop_window;
mod laws;
mod layering;
mod motion;
mod noise;
mod packed;
mod pipeline;
mod realism;
mod reference_vectors;
mod render_window;
mod resample;
mod stability;
mod stereo;
mod texture;
