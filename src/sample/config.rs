//! The sample configuration: everything that defines how a sample is made from its address
//! (motion laws, objects, merge and inpainting, render mode and work skipping). Serialisable; its
//! JSON is part of the dataset fingerprint, so every option that changes a sample changes it.

use serde::{Deserialize, Serialize};

use super::background::Background;
use super::error::SampleError;
use super::merge::{LabelRule, MergeRule};
use super::motion::{MotionPreset, MotionRanges};
use super::object::ObjectChoice;
use crate::render::{Mode, Resample, Skip};

/// The motion laws: a preset name or explicit ranges. In JSON: `"paper-kitti"` or a
/// [`MotionRanges`] object.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum MotionSpec {
    Preset(MotionPreset),
    Ranges(Box<MotionRanges>),
}

impl Default for MotionSpec {
    fn default() -> Self {
        MotionSpec::Preset(MotionPreset::Reference)
    }
}

impl MotionSpec {
    pub fn ranges(&self) -> MotionRanges {
        match self {
            MotionSpec::Preset(p) => p.ranges(),
            MotionSpec::Ranges(r) => (**r).clone(),
        }
    }
}

/// What fills the holes: a Telea variant ([`super::inpaint`]) or the texture fill.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum InpaintMethod {
    /// The paper's first-order method with propagated gradients (exact on linear images).
    Telea,
    /// First order from known pixels only (less overshoot on textured photos with large holes,
    /// which disocclusions are; see the measurements in [`super::inpaint`]).
    #[default]
    TeleaKnownOnly,
    /// No gradient term (a convex combination of the available values).
    TeleaZeroOrder,
    /// OpenCV's `cv2.inpaint(..., INPAINT_TELEA)`, bit-compatible.
    TeleaOpencv,
    /// Texture: patches of image1's background at the hole's depth, copied by exemplar
    /// synthesis (`sample::holes`, "Texture"); Telea for what it cannot reach.
    Exemplar,
}

impl InpaintMethod {
    /// Every method with its name (the serde and command-line spelling).
    pub const ALL: [(InpaintMethod, &'static str); 5] = [
        (InpaintMethod::Telea, "telea"),
        (InpaintMethod::TeleaKnownOnly, "telea-known-only"),
        (InpaintMethod::TeleaZeroOrder, "telea-zero-order"),
        (InpaintMethod::TeleaOpencv, "telea-opencv"),
        (InpaintMethod::Exemplar, "exemplar"),
    ];
}

impl std::fmt::Display for InpaintMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = Self::ALL.iter().find(|(m, _)| m == self).map_or("?", |(_, n)| n);
        f.write_str(name)
    }
}

impl std::str::FromStr for InpaintMethod {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL.iter().find(|(_, n)| *n == s).map(|(m, _)| *m).ok_or_else(|| {
            let names: Vec<&str> = Self::ALL.iter().map(|(_, n)| *n).collect();
            format!("unknown inpainting method `{s}` (expected one of {})", names.join(", "))
        })
    }
}

#[derive(Serialize, Deserialize)]
#[serde(remote = "Mode", rename_all = "kebab-case")]
enum ModeDef {
    Reference,
    Exact,
}

#[derive(Serialize, Deserialize)]
#[serde(remote = "Skip", deny_unknown_fields)]
struct SkipDef {
    transmittance_eps: f32,
    tiles: bool,
    tile_sigma_eps: f32,
}

/// Everything that defines how a sample is made from its address. Serialisable (every field
/// optional in JSON, defaults below).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SampleConfig {
    /// Camera and object motion laws. Default: the `reference` preset.
    pub motion: MotionSpec,
    /// Most objects moved per sample (0 = none). Default 1 (the reference moves one).
    pub max_objects: usize,
    /// How objects are picked among the eligible ones. Default `random`.
    pub object_choice: ObjectChoice,
    /// Smallest object area (mask >= 0.5) as a fraction of the image. Default 0.002.
    pub min_object_area_fraction: f64,
    /// Compose each object's motion with the camera's. Default false (the reference's law).
    pub objects_follow_camera: bool,
    /// Default `depth-aware`.
    pub merge: MergeRule,
    /// Which valid pixels are marked occluded ([`LabelRule`]). Default `honest`.
    pub label_rule: LabelRule,
    /// What fills image2's holes before 2-D inpainting with the depth-aware merge
    /// ([`Background`]: the MPI's planes behind the moved objects, or Telea alone); the reference
    /// merge always inpaints, as the paper. Default `inpaint`: `planes` leaves few holes to Telea
    /// with the completed background, but its render over the holes leaves thin lines where a
    /// mask spans many depths (docs/quality.md, "The default, and the realistic scene"). Part of the fingerprint when not
    /// `inpaint`.
    #[serde(skip_serializing_if = "is_inpaint")]
    pub background: Background,
    /// The mask threshold of the merge (the reference's 0.99).
    pub mask_threshold: f32,
    /// Telea neighbourhood radius in pixels. Default 3 (the reference's inpainting radius).
    pub inpaint_radius: f32,
    /// Default `telea-known-only`.
    pub inpaint_method: InpaintMethod,
    /// Motions drawn from each source item in one pass of its window ([`source_item`]): its scene
    /// is built once for them. Default [`DEFAULT_MOTIONS_PER_IMAGE`].
    ///
    /// [`source_item`]: SampleConfig::source_item
    pub motions_per_image: u64,
    /// Source items whose motions are interleaved ([`source_item`]): consecutive samples come from
    /// different items, each item's scene stays warm for its `motions_per_image` samples. Default
    /// [`DEFAULT_SCENE_WINDOW`]; 1 gives runs of `motions_per_image` consecutive samples per item.
    ///
    /// [`source_item`]: SampleConfig::source_item
    pub scene_window: u64,
    /// Render mode. Default `exact`.
    #[serde(with = "ModeDef")]
    pub mode: Mode,
    /// Work skipping of the exact mode. Default [`Skip::DEFAULT`].
    #[serde(with = "SkipDef")]
    pub skip: Skip,
    /// Render mask channels and objects over windows (exact mode). Default true.
    pub windowed: bool,
    /// Pre-blend the MPI with the source photo when the scene is loaded (for network MPIs;
    /// [`super::preblend`]). Default false.
    pub preblend: bool,
    /// Frames per sample, [`MIN_FRAMES`] to [`MAX_FRAMES`]: 2 = a pair (image1, image2), more =
    /// a clip along the constant-velocity trajectory (`sample::recipe`, "Clips"). Default 2.
    /// Part of the fingerprint when not 2 (so pairs keep the addresses they always had).
    #[serde(skip_serializing_if = "is_pair")]
    pub frames: usize,
    /// Also make the backward fields (flow image2 -> image1 and its masks, for every pair of a
    /// clip). An output selection, not an option of the sample: it changes no other byte of a
    /// sample and is not part of the fingerprint (nor of the configuration's JSON), like the
    /// fields a request asks for. Default false (none of their work is done).
    #[serde(skip)]
    pub backward: bool,
    /// Compute the forward occlusion mask of the first pair ([`Sample::occlusion`](super::types::Sample::occlusion); all 0
    /// without it). An output selection like `backward`: it changes no other byte and is not
    /// part of the fingerprint. Default true; the service turns it off for requests that do not
    /// ask for the occlusion field.
    #[serde(skip, default = "yes")]
    pub occlusion: bool,
    /// Colour kernel of the exact-mode target renders ([`crate::render::resample`]; the
    /// reference mode is always bilinear). Default `bspline3` (measurements in docs/quality.md).
    pub resample: Resample,
    /// Restore image1's sensor-noise level in image2 and every later frame
    /// ([`super::noise`]: per channel, the variance the render lost, deterministic by address).
    /// Default false; part of the fingerprint when true (so samples keep the addresses they had
    /// before the option).
    #[serde(skip_serializing_if = "is_false")]
    pub restore_noise: bool,
    /// Alias-free minification of the target renders' colour ([`crate::render::mip`]: planes the
    /// view shrinks are sampled from prefiltered levels). Default false; part of the fingerprint
    /// when true.
    #[serde(skip_serializing_if = "is_false")]
    pub minify: bool,
}

/// Fewest frames per sample (a pair).
pub const MIN_FRAMES: usize = 2;

/// The default `motions_per_image`: each scene serves 8 samples per pass, so a collection
/// larger than the scene cache builds a scene every 8 samples (docs/performance.md).
pub const DEFAULT_MOTIONS_PER_IMAGE: u64 = 8;

/// Most `motions_per_image`.
pub const MAX_MOTIONS_PER_IMAGE: u64 = 1_000_000;

/// The default `scene_window`: 11 items interleaved. Prime, so that the ranks of any world size
/// that is not a multiple of 11 each see 8 different photos in any 8 consecutive samples; 11
/// scenes at the working size (about 45 MiB each at 640 x 480, 32 planes) stay warm together.
pub const DEFAULT_SCENE_WINDOW: u64 = 11;

/// Most `scene_window`.
pub const MAX_SCENE_WINDOW: u64 = 4096;
/// Most frames per sample.
pub const MAX_FRAMES: usize = 8;

#[allow(clippy::trivially_copy_pass_by_ref)]
fn is_inpaint(b: &Background) -> bool {
    *b == Background::Inpaint
}

#[allow(clippy::trivially_copy_pass_by_ref)]
fn is_false(b: &bool) -> bool {
    !*b
}

fn yes() -> bool {
    true
}

fn is_pair(frames: &usize) -> bool {
    *frames == MIN_FRAMES
}

impl Default for SampleConfig {
    fn default() -> Self {
        Self {
            motion: MotionSpec::default(),
            max_objects: 1,
            object_choice: ObjectChoice::Random,
            min_object_area_fraction: 0.002,
            objects_follow_camera: false,
            merge: MergeRule::DepthAware,
            label_rule: LabelRule::Honest,
            background: Background::Inpaint,
            mask_threshold: 0.99,
            inpaint_radius: 3.0,
            inpaint_method: InpaintMethod::TeleaKnownOnly,
            motions_per_image: DEFAULT_MOTIONS_PER_IMAGE,
            scene_window: DEFAULT_SCENE_WINDOW,
            mode: Mode::Exact,
            skip: Skip::DEFAULT,
            windowed: true,
            preblend: false,
            frames: MIN_FRAMES,
            backward: false,
            occlusion: true,
            resample: Resample::default(),
            restore_noise: false,
            minify: false,
        }
    }
}

impl SampleConfig {
    /// The default configuration with the motion laws of `preset`.
    pub fn with_preset(preset: MotionPreset) -> Self {
        Self { motion: MotionSpec::Preset(preset), ..Self::default() }
    }

    /// Checks every field; the error names the field.
    pub fn validate(&self) -> Result<(), SampleError> {
        let ranges = self.motion.ranges();
        ranges.validate()?;
        let bad = |field: &'static str, message: String| Err(SampleError::Config { field, message });
        if ranges.stereo && self.frames > MIN_FRAMES {
            return bad(
                "frames",
                format!("{} with a stereo motion law (a stereo sample is one rectified pair)", self.frames),
            );
        }
        if self.max_objects > 255 {
            return bad("max_objects", format!("{} (at most 255 objects fit the u8 label masks)", self.max_objects));
        }
        if !(0.0..=1.0).contains(&self.min_object_area_fraction) {
            return bad("min_object_area_fraction", format!("{} (expected 0 to 1)", self.min_object_area_fraction));
        }
        if !(self.mask_threshold > 0.0 && self.mask_threshold <= 1.0) {
            return bad("mask_threshold", format!("{} (expected in (0, 1])", self.mask_threshold));
        }
        if !(self.inpaint_radius.is_finite() && self.inpaint_radius > 0.0) {
            return bad("inpaint_radius", format!("{} (expected a positive number of pixels)", self.inpaint_radius));
        }
        if !(MIN_FRAMES..=MAX_FRAMES).contains(&self.frames) {
            return bad("frames", format!("{} (expected {MIN_FRAMES} to {MAX_FRAMES})", self.frames));
        }
        if (self.backward || self.frames > MIN_FRAMES) && self.mode != Mode::Exact {
            return bad("mode", "reference: the backward fields and clips need the exact mode".into());
        }
        if !(1..=MAX_MOTIONS_PER_IMAGE).contains(&self.motions_per_image) {
            return bad(
                "motions_per_image",
                format!("{} (expected 1 to {MAX_MOTIONS_PER_IMAGE})", self.motions_per_image),
            );
        }
        if !(1..=MAX_SCENE_WINDOW).contains(&self.scene_window) {
            return bad("scene_window", format!("{} (expected 1 to {MAX_SCENE_WINDOW})", self.scene_window));
        }
        let s = self.skip;
        if !(s.transmittance_eps.is_finite() && (0.0..1.0).contains(&s.transmittance_eps)) {
            return bad("skip.transmittance_eps", format!("{} (expected in [0, 1))", s.transmittance_eps));
        }
        if !(s.tile_sigma_eps.is_finite() && s.tile_sigma_eps >= 0.0) {
            return bad("skip.tile_sigma_eps", format!("{} (expected >= 0)", s.tile_sigma_eps));
        }
        Ok(())
    }

    /// The word of the cache key for what [`prepare_scene`] changes (the pre-blend, the
    /// prefiltered coefficients a `bspline3` render needs, the minification levels).
    pub fn scene_variant(&self) -> u64 {
        let degree = match self.mode {
            Mode::Exact => self.resample.prefilter().map_or(0, crate::mpi::Prefilter::id),
            Mode::Reference => 0,
        };
        u64::from(self.preblend) | u64::from(degree) << 1 | u64::from(self.minify && self.mode == Mode::Exact) << 8
    }

    /// The source item of sample `index` in a collection of `len` items: the index space is cut
    /// into windows of `K M` samples (`K` = `scene_window`, at most `len`; `M` =
    /// `motions_per_image`); window `b` draws from items `b K .. b K + K` (mod `len`), and its
    /// sample `p` from item `b K + p mod K`. So consecutive samples come from `K` different items
    /// in turn, each item gives `M` motions while its scene is warm, and `len / K` windows pass
    /// over every item before the first comes round again with new motions. With `K` = 1, `M`
    /// consecutive samples share an item; with `M` = 1, sample `I` uses item `I mod len`.
    ///
    /// For a rank of `R` consumers (indices `r, r + R, r + 2R, ...`) with `K` prime and `R` not a
    /// multiple of it, any `K` consecutive samples of the rank come from different items when
    /// `len` is at least `K` times the number of windows they span (within a window the slot
    /// steps by `R mod K`, which returns to a slot only after `K` steps; the items of the windows
    /// spanned are distinct numbers below that span).
    pub fn source_item(&self, index: u64, len: usize) -> Option<usize> {
        if len == 0 {
            return None;
        }
        let k = self.scene_window.clamp(1, len as u64);
        let m = self.motions_per_image.max(1);
        // window * k + slot <= index / m: no overflow
        let window = index / k.saturating_mul(m);
        Some(((window * k + index % k) % len as u64) as usize)
    }
}
