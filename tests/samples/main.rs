//! Scenes and samples: sources and users' photos, the ONNX models, the scene cache and its stages,
//! labels, masks, the merge, inpainting, recipes, export and bake.
//! One test binary per group (each file beside this one is a module), so that the suite links a
//! handful of binaries.

mod augment;
mod background;
mod bad_sources;
mod bake;
mod export;
mod inpaint;
mod io_formats;
mod labels;
mod masks;
mod named_models;
mod named_segmenter;
mod onnx_scene;
mod phone_photos;
mod phone_sizes;
mod recipe;
mod sample_merge;
mod scene_cache;
mod scene_prefetch;
mod scene_stage;
mod sources;
mod user_photos;
