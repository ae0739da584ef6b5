//! What a sample is: its address ([`SampleAddress`]), its fields ([`Sample`]: the images, the
//! flows and their masks, the clip's later frames, the moved objects, the stage timings) and the
//! stereo disparity of a flow ([`disparity_of`]).

use serde::{Deserialize, Serialize};

use super::motion::Motion;

/// Where a sample lives: same address, same bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct SampleAddress {
    /// The source collection's fingerprint ([`crate::source::Source::fingerprint`]).
    pub dataset: u64,
    pub seed: u64,
    pub index: u64,
}

/// One moved object, as recorded in the sample.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObjectRecord {
    /// The value of this object in `mask1` / `mask2` (1, 2, ...).
    pub label: u8,
    /// The instance id in the source's masks.
    pub instance: u32,
    pub score: f32,
    /// Source-frame area in pixels (mask >= 0.5).
    pub area: f64,
    pub motion: Motion,
}

/// A flow between two frames with its masks, on the grid of the frame it starts from (the
/// backward flow: image2 -> image1 on image2's grid). Empty when not computed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LinkFields {
    /// H x W x 2 (u, v) in pixels; always finite, 0 where nothing is rendered (holes).
    pub flow: Vec<f32>,
    /// H x W, 1 = the target lies inside the other frame and in front of its camera, and the
    /// pixel is rendered (not a hole).
    pub valid: Vec<u8>,
    /// H x W, 1 = the pixel's point is not visible in the other frame (e.g. disoccluded
    /// background, for the backward flow).
    pub occlusion: Vec<u8>,
}

/// Frame `k + 3` of a clip (k = 0, 1, ...; frames 1 and 2 are image1 and image2) with the pair
/// that ends in it. Every frame is a render of the same MPI (see `sample::recipe`, "Clips").
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ClipFrame {
    /// H x W x 3, merged and inpainted like image2.
    pub image: Vec<u8>,
    /// The previous frame -> this frame, on the previous frame's grid.
    pub forward: LinkFields,
    /// This frame -> the previous frame, on this frame's grid (empty without the backward
    /// fields).
    pub backward: LinkFields,
    /// H x W object labels as visible in this frame.
    pub mask: Vec<u8>,
    /// H x W, the depth (z in this frame's camera) of what it shows; 0 in holes.
    pub depth: Vec<f32>,
    /// H x W, 1 = filled by inpainting.
    pub holes: Vec<u8>,
}

/// Milliseconds spent per stage of one sample.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StageTimings {
    /// Getting the scene (0-ish on a cache hit).
    pub scene_ms: f64,
    /// Rendering the scene under the camera motion.
    pub render_ms: f64,
    /// Rendering the moving objects.
    pub objects_ms: f64,
    /// Merging scene and objects.
    pub merge_ms: f64,
    /// Inpainting the holes.
    pub inpaint_ms: f64,
    pub total_ms: f64,
}

/// A finished training sample. All images are `height` x `width`, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    pub address: SampleAddress,
    /// The source's id.
    pub source_id: String,
    pub width: usize,
    pub height: usize,
    /// H x W x 3.
    pub image1: Vec<u8>,
    /// H x W x 3.
    pub image2: Vec<u8>,
    /// H x W x 2 (u, v), forward flow on image1's pixels; always finite.
    pub flow: Vec<f32>,
    /// H x W, 1 = the flow is valid (target inside image2, point in front of the camera).
    pub valid: Vec<u8>,
    /// H x W, 1 = the image1 point is hidden in image2 (all 0 when the configuration's
    /// `occlusion` is off: the service computes it only for requests that ask for it).
    pub occlusion: Vec<u8>,
    /// H x W object labels in image1's frame (0 = background, else `ObjectRecord::label`).
    pub mask1: Vec<u8>,
    /// H x W object labels as visible in image2.
    pub mask2: Vec<u8>,
    pub camera: Motion,
    pub objects: Vec<ObjectRecord>,
    /// H x W, the source frame's depth in the scene scale: `1 / disparity` of the scene
    /// (nearest content ~1), as the MPI was built from.
    pub depth1: Vec<f32>,
    /// H x W, the target frame's depth after the merge: the rendered depth (z in the target
    /// camera) of what image2 shows, objects where they win the merge; 0 in holes (the pixels
    /// that were inpainted) and where invalid.
    pub depth2: Vec<f32>,
    /// H x W, 1 = image2 was filled there by 2-D inpainting (no render covers the pixel); the
    /// merge's hole mask. Trainers can mask or down-weight these pixels.
    pub holes: Vec<u8>,
    /// Pixels of image2 that were inpainted (the ones of `holes`).
    pub inpainted_pixels: u64,
    /// The backward flow image2 -> image1 on image2's grid, its `valid` and `occlusion`
    /// (empty unless asked for: `SampleConfig::backward`).
    pub backward: LinkFields,
    /// Frames 3.. of a clip (`SampleConfig::frames` > 2); empty for a pair.
    pub clip: Vec<ClipFrame>,
    /// Bad source items passed over to make this sample (see
    /// `Generator::sample`); 0 when its own source item loaded.
    pub skipped_sources: u32,
    /// Which implementation produced the scene's depth, MPI and masks.
    pub provenance: Vec<String>,
    /// The camera of image1 (the scene's; image2 uses the same).
    pub intrinsics: crate::geometry::Intrinsics,
    pub timings: StageTimings,
}

impl Sample {
    /// The stereo disparity of a rectified pair (stereo motion laws): `d = x1 - x2 = -u`, H x W,
    /// on image1's (the left view's) grid; `valid` and `occlusion` say where it holds.
    pub fn disparity(&self) -> Vec<f32> {
        disparity_of(&self.flow)
    }
}

/// The disparity `d = -u` of an H x W x 2 flow (`0.0 - u`, not `-u`: a zero flow gives +0.0,
/// never -0.0).
pub fn disparity_of(flow: &[f32]) -> Vec<f32> {
    flow.chunks_exact(2).map(|uv| 0.0 - uv[0]).collect()
}
