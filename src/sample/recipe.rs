//! The deterministic sample recipe: from an address (dataset fingerprint, seed, index) to a
//! finished [`Sample`].
//!
//! # The recipe
//!
//! 1. **Source.** Item `(index / motions_per_image) mod len` of the loader: consecutive indices
//!    share a source (its scene is computed once and reused from the [`SceneCache`]), and a
//!    collection of `len` images gives `len * motions_per_image` consecutive samples before the
//!    first source comes round again (with new motions, since the index differs). No random
//!    number is used for this ([`Purpose::SourceChoice`] is left for a future shuffled order).
//! 2. **Motions.** The camera motion from the `Purpose::CameraMotion` stream; the moving objects
//!    from `Purpose::ObjectChoice` ([`choose_objects`]); object slot `j`'s motion from
//!    `Purpose::ObjectMotion(j)`. Every stream is keyed by (fingerprint, seed, index, purpose), so
//!    the same address gives the same numbers on any run, thread count or machine, and one
//!    purpose never shifts another's numbers.
//! 3. **Renders** (exact mode by default): the scene under the camera motion (whole frame, work
//!    skipping with the scene's tile occupancy, which the [`Generator`] keeps per cached scene);
//!    with objects, the union mask's channel under the camera motion and each object under its
//!    own motion, each rendered only over the window of the frame where its channel can be
//!    non-zero, straight from the shared MPI ([`super::object`]: the same values as full-frame
//!    renders, bit-identical in the tests). With `windowed = false`, or in the reference mode,
//!    full-frame renders of MPI copies with the mask channel attached (the reference's way,
//!    slower). Without objects (`max_objects = 0`, no instances, none large enough) there is no
//!    mask channel and no second render: the object stage costs nothing.
//! 4. **Merge** ([`super::merge`]) by the configured rule, then **inpainting** of the holes with
//!    Telea's method in u8 ([`InpaintMethod`], radius 3 by default, as the reference's radius),
//!    on crops around the holes ([`inpaint_holes`]: the whole-frame result, bit for bit).
//!
//! Per-pixel work runs on the current rayon pool; every output is independent of the pool's size
//! (the renderer is bit-identical to a serial run, merging is per pixel, each inpainting crop is
//! sequential and independent of the others). [`StageTimings`] are measurements and not part of
//! the sample's bytes: `scene_ms` (cache lookup or load, and the scene's tile occupancy the first
//! time the generator sees the scene), `render_ms` (the scene render, and the occupancy when
//! [`assemble`] had to build it), `objects_ms` (choosing and rendering objects and the
//! scene mask), `merge_ms` (merge and image1), `inpaint_ms`, `total_ms`.
//!
//! **Bad sources** ([`Generator::sample`]): when the address's source item fails to load because
//! of its data (corrupt, truncated or too large image, bad depth, masks or MPI), the next items
//! (mod the collection's length) are tried in order and the first good one is used with the
//! address's own motions; failed items are remembered and counted by their [`FailureKind`]
//! ([`Generator::skip_counts`]), [`Sample::skipped_sources`] says how many were passed over. The
//! result depends only on which items are bad, not on what was asked before. Runtime, model,
//! configuration and render errors are not the item's and are returned.
//!
//! Besides the images and flow, a sample carries `depth1` (the scene's `1 / disparity`, the
//! source frame's depth in the scene scale) and `depth2` (the merge's depth of what image2 shows;
//! 0 in holes), both taken from what the recipe computes anyway.
//!
//! An object's motion is by default its own rigid motion from the source camera to the target
//! camera (the reference script renders the object with its own small pose, independent of the
//! camera's); with `objects_follow_camera` it is composed with the camera's
//! (`X_tgt = R_c (R_o X + t_o) + t_c`: the object moves, then the camera).

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, Weak};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::inpaint::{inpaint_telea_opencv_u8, inpaint_telea_u8_with, GradientTerm, TeleaOptions};
use super::merge::{merge, unit_to_u8, MergeRule, ObjectView, SceneView};
use super::motion::{MotionError, MotionPreset, MotionRanges};
use super::object::{
    choose_objects, object_window, render_full_with_mask, render_mask_window, scene_mask_window, support_rect,
    ObjectChoice, Rect, WindowRender,
};
use super::preblend::{preblend, PreblendError};
use super::rng::{Purpose, SampleRng};
use super::{ObjectRecord, Sample, SampleAddress, StageTimings};
use crate::render::{render, Fields, Mode, Occupancy, RenderError, RenderOutput, RenderParams, Skip};
use crate::scene::cache::{SceneCache, SceneKey};
use crate::scene::{Scene, SceneError, SceneLoader};
use crate::source::FailureKind;

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

/// Which Telea variant fills the holes (all in [`super::inpaint`]).
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
    /// The mask threshold of the merge (the reference's 0.99).
    pub mask_threshold: f32,
    /// Telea neighbourhood radius in pixels. Default 3 (the reference's inpainting radius).
    pub inpaint_radius: f32,
    /// Default `telea-known-only`.
    pub inpaint_method: InpaintMethod,
    /// Consecutive sample indices per source item (see the module documentation). Default 1.
    pub motions_per_image: u64,
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
            mask_threshold: 0.99,
            inpaint_radius: 3.0,
            inpaint_method: InpaintMethod::TeleaKnownOnly,
            motions_per_image: 1,
            mode: Mode::Exact,
            skip: Skip::DEFAULT,
            windowed: true,
            preblend: false,
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
        self.motion.ranges().validate()?;
        let bad = |field: &'static str, message: String| Err(SampleError::Config { field, message });
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
        if self.motions_per_image == 0 {
            return bad("motions_per_image", "0 (expected at least 1)".into());
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

    /// The word of the cache key for what [`prepare_scene`] changes.
    pub fn scene_variant(&self) -> u64 {
        u64::from(self.preblend)
    }

    /// The source item of sample `index` in a collection of `len` items.
    pub fn source_item(&self, index: u64, len: usize) -> Option<usize> {
        (len > 0).then(|| ((index / self.motions_per_image.max(1)) % len as u64) as usize)
    }
}

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
    /// Every source item failed to load (see [`Generator::sample`]).
    #[error("all {items} source items failed to load (first: {first})")]
    NoGoodSource { items: usize, first: String },
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

/// Applies what the configuration does to a freshly loaded scene (the pre-blend), once, before
/// it goes into the cache.
pub fn prepare_scene(mut scene: Scene, config: &SampleConfig) -> Result<Scene, SampleError> {
    if config.preblend {
        let mpi = Arc::make_mut(&mut scene.mpi);
        preblend(mpi, &scene.image.data, &scene.intrinsics)
            .map_err(|source| SampleError::Preblend { id: scene.id.clone(), source })?;
        scene.provenance.push("preblend: reference (T_src * photo + (1 - T_src) * rgb)".into());
    }
    Ok(scene)
}

fn check_scene(scene: &Scene) -> Result<(), SampleError> {
    let bad = |message: String| Err(SampleError::InvalidScene { id: scene.id.clone(), message });
    let (w, h) = (scene.mpi.width, scene.mpi.height);
    if w == 0 || h == 0 || scene.mpi.planes() == 0 {
        return bad(format!("the MPI is empty ({w} x {h}, {} planes)", scene.mpi.planes()));
    }
    if scene.image.width != w || scene.image.height != h || scene.image.data.len() != w * h * 3 {
        return bad(format!("the image is {} x {} but the MPI {w} x {h}", scene.image.width, scene.image.height));
    }
    let m = &scene.masks;
    if !m.masks.is_empty() && (m.width != w || m.height != h || m.masks.iter().any(|i| i.mask.len() != w * h)) {
        return bad(format!("the instance masks are {} x {} but the MPI {w} x {h}", m.width, m.height));
    }
    if !scene.intrinsics.is_valid() {
        return bad(format!("invalid intrinsics {:?}", scene.intrinsics));
    }
    let d = &scene.disparity;
    if d.width != w || d.height != h || d.data.len() != w * h {
        return bad(format!("the disparity is {} x {} but the MPI {w} x {h}", d.width, d.height));
    }
    Ok(())
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The sample at `address` made from `scene` (which must be the address's source item, prepared
/// with [`prepare_scene`]); pure: the same arguments give the same sample.
pub fn assemble(scene: &Scene, address: SampleAddress, config: &SampleConfig) -> Result<Sample, SampleError> {
    assemble_with_occupancy(scene, address, config, None)
}

/// [`assemble`] with the scene MPI's tile occupancy (built with `config.skip.tile_sigma_eps`)
/// computed beforehand; an occupancy built with another threshold is ignored (the renderer then
/// builds its own).
pub fn assemble_with_occupancy(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
) -> Result<Sample, SampleError> {
    let start = Instant::now();
    let (mut sample, hole) = assemble_merged(scene, address, config, occupancy)?;
    let t = Instant::now();
    if sample.inpainted_pixels > 0 {
        let (w, h) = (sample.width, sample.height);
        inpaint_holes(&mut sample.image2, w, h, &hole, config.inpaint_method, config.inpaint_radius, true);
    }
    sample.timings.inpaint_ms = ms(t);
    sample.timings.total_ms = ms(start);
    Ok(sample)
}

/// [`assemble_with_occupancy`] up to the merge: the sample with `image2` as merged, its holes not
/// yet inpainted, and the hole mask (H x W, 1 = hole; [`Sample::inpainted_pixels`] counts them).
/// [`assemble`] is this followed by [`inpaint_holes`] over the mask (windowed).
pub fn assemble_merged(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
) -> Result<(Sample, Vec<u8>), SampleError> {
    let start = Instant::now();
    config.validate()?;
    check_scene(scene)?;
    let ranges = config.motion.ranges();
    let mpi = &*scene.mpi;
    let (w, h) = (mpi.width, mpi.height);
    let k = scene.intrinsics;
    let rng = |p: Purpose| SampleRng::new(address.dataset, address.seed, address.index, p);
    let render_err = |stage: &'static str| {
        let id = scene.id.clone();
        move |source: RenderError| SampleError::Render { id, stage, source: Box::new(source) }
    };
    let mut timings = StageTimings::default();

    // ---- motions and objects
    let t = Instant::now();
    let camera = ranges.sample_camera_motion(&mut rng(Purpose::CameraMotion));
    let cam_pose = camera.to_pose();
    let chosen = if config.max_objects > 0 && !scene.masks.masks.is_empty() {
        choose_objects(
            &scene.masks,
            config.max_objects,
            config.min_object_area_fraction,
            config.object_choice,
            &mut rng(Purpose::ObjectChoice),
        )
    } else {
        Vec::new()
    };
    let mut records = Vec::with_capacity(chosen.len());
    let mut poses = Vec::with_capacity(chosen.len());
    for (slot, &idx) in chosen.iter().enumerate() {
        let inst = &scene.masks.masks[idx];
        let motion = ranges.sample_object_motion(&mut rng(Purpose::ObjectMotion(slot as u32)));
        let own = motion.to_pose();
        poses.push(if config.objects_follow_camera { cam_pose.compose(&own) } else { own });
        records.push(ObjectRecord {
            label: (slot + 1) as u8,
            instance: inst.id,
            score: inst.score,
            area: inst.area,
            motion,
        });
    }
    let mut objects_ms = ms(t);

    let windowed = config.windowed && config.mode == Mode::Exact;
    let mut params = RenderParams::new(k, cam_pose);
    params.mode = config.mode;
    params.skip = config.skip;
    params.fields = Fields { target: true, flow: true, occlusion: false };
    // the scene MPI's tile occupancy, shared by the scene render and the windowed renders
    let t = Instant::now();
    let built;
    let occupancy = match occupancy {
        Some(o) if o.sigma_eps == config.skip.tile_sigma_eps => Some(o),
        _ if config.mode == Mode::Exact && config.skip.tiles => {
            built = Occupancy::build(mpi, config.skip.tile_sigma_eps);
            Some(&built)
        }
        _ => None,
    };
    let occupancy_ms = ms(t);

    // ---- the scene render (and the scene mask channel)
    let union: Option<Cow<'_, [f32]>> = match chosen.as_slice() {
        [] => None,
        [one] => Some(Cow::Borrowed(&scene.masks.masks[*one].mask)),
        many => {
            let mut u = vec![0.0f32; w * h];
            for &idx in many {
                for (a, &b) in u.iter_mut().zip(&scene.masks.masks[idx].mask) {
                    *a = a.max(b);
                }
            }
            Some(Cow::Owned(u))
        }
    };
    let t = Instant::now();
    let (scene_out, full_mask): (_, Option<Vec<f32>>) = match (&union, windowed) {
        (Some(u), false) => {
            // the reference's scene render: a full copy with the channel 1 - U
            let inv: Vec<f32> = u.iter().map(|&v| 1.0 - v).collect();
            let r = render_full_with_mask(mpi, &k, &cam_pose, &inv, config.mode, config.skip, params.fields)
                .map_err(render_err("scene"))?;
            let mut out = r.out;
            let mask = std::mem::take(&mut out.extras);
            (out, Some(mask))
        }
        _ => (render::<f32>(mpi, &params, occupancy).map_err(render_err("scene"))?, None),
    };
    timings.render_ms = ms(t) + occupancy_ms;

    // render(1 - U) = coverage - render(U), and render(U) is 0 outside U's footprint: the scene
    // mask is the coverage except over that window
    let t = Instant::now();
    let mut mask_patch: Option<(Rect, Vec<f32>)> = None;
    if let (None, Some(u)) = (&full_mask, &union) {
        if let Some(support) = support_rect(u, w, h) {
            let win = scene_mask_window(mpi, &k, &cam_pose, &support);
            let r = render_mask_window(mpi, occupancy, &k, &cam_pose, &win, u, config.skip, false)
                .map_err(render_err("scene mask"))?;
            let patch = r.out.coverage.iter().zip(&r.out.extras).map(|(c, m)| c - m).collect();
            mask_patch = Some((win, patch));
        }
    }

    // ---- object renders
    let mut renders: Vec<WindowRender> = Vec::with_capacity(chosen.len());
    for (&idx, pose) in chosen.iter().zip(&poses) {
        let mask = &scene.masks.masks[idx].mask;
        let r = match (windowed, support_rect(mask, w, h)) {
            (true, Some(support)) => {
                let win = object_window(mpi, &k, pose, &support);
                render_mask_window(mpi, occupancy, &k, pose, &win, mask, config.skip, true)
            }
            _ => render_full_with_mask(mpi, &k, pose, mask, config.mode, config.skip, params.fields),
        }
        .map_err(render_err("object"))?;
        renders.push(r);
    }
    objects_ms += ms(t);
    timings.objects_ms = objects_ms;

    // ---- merge
    let t = Instant::now();
    let RenderOutput { image, depth, coverage, flow, source_depth_in_target, valid, .. } = scene_out;
    let view = SceneView {
        width: w,
        height: h,
        image: &image,
        depth,
        scene_mask: full_mask.as_deref().unwrap_or(&coverage),
        scene_mask_patch: mask_patch.as_ref().map(|(r, p)| (*r, p.as_slice())),
        flow,
        valid,
        source_depth: &source_depth_in_target,
    };
    let views: Vec<ObjectView<'_>> = chosen
        .iter()
        .zip(&renders)
        .enumerate()
        .map(|(slot, (&idx, r))| ObjectView {
            label: (slot + 1) as u8,
            source_mask: &scene.masks.masks[idx].mask,
            render: r,
        })
        .collect();
    let merged = merge(view, &views, config.merge, config.mask_threshold);
    let image1: Vec<u8> = scene.image.data.iter().map(|&v| unit_to_u8(v)).collect();
    // depth1 = 1 / disparity, written over the scene render's coverage (no longer needed; a
    // buffer already in memory costs no page faults)
    let mut depth1 = coverage;
    if depth1.len() != w * h {
        depth1 = vec![0.0; w * h];
    }
    {
        use rayon::prelude::*;
        depth1.par_chunks_mut(w).zip(scene.disparity.data.par_chunks(w)).for_each(|(out, disp)| {
            for (o, &d) in out.iter_mut().zip(disp) {
                *o = crate::scene::scale::depth_of_disparity(d);
            }
        });
    }
    timings.merge_ms = ms(t);

    timings.total_ms = ms(start);

    let sample = Sample {
        address,
        source_id: scene.id.clone(),
        width: w,
        height: h,
        image1,
        image2: merged.image2,
        flow: merged.flow,
        valid: merged.valid,
        occlusion: merged.occlusion,
        mask1: merged.mask1,
        mask2: merged.mask2,
        camera,
        objects: records,
        depth1,
        depth2: merged.depth2,
        inpainted_pixels: merged.holes,
        skipped_sources: 0,
        provenance: scene.provenance.clone(),
        intrinsics: scene.intrinsics,
        timings,
    };
    Ok((sample, merged.hole))
}

/// Fills the pixels where `hole` is non-zero in the u8 RGB image (`w` x `h` x 3) with `method`.
///
/// With `windowed` (what the recipe uses) the Telea variants of the paper (`telea`,
/// `telea-known-only`, `telea-zero-order`) run on crops instead of the whole frame: the holes'
/// connected components, grouped where their bounding boxes grown by a margin overlap, each on
/// its box grown by the margin, the groups in parallel. The margin (`ceil(1.5 ceil(r) + 2) + 2`
/// pixels for radius `r`) holds everything the method reads for a hole pixel: the known pixels
/// within the radius, their one-pixel gradient stencils, and the outward arrival times, which
/// the method computes only up to `1.5 ceil(r) + 2` from the hole. The result is therefore the
/// whole-frame result, bit for bit (tested), at a cost that follows the holes instead of the
/// frame (the method allocates and scans several full-frame arrays per call). The OpenCV variant
/// treats the image border specially and always runs on the whole frame.
pub fn inpaint_holes(
    image: &mut [u8],
    w: usize,
    h: usize,
    hole: &[u8],
    method: InpaintMethod,
    radius: f32,
    windowed: bool,
) {
    use rayon::prelude::*;
    let gradient = match method {
        InpaintMethod::Telea => GradientTerm::Propagated,
        InpaintMethod::TeleaKnownOnly => GradientTerm::KnownOnly,
        InpaintMethod::TeleaZeroOrder => GradientTerm::Off,
        InpaintMethod::TeleaOpencv => {
            inpaint_telea_opencv_u8(image, w, h, 3, hole, radius);
            return;
        }
    };
    let options = TeleaOptions { radius, gradient };
    if !windowed {
        inpaint_telea_u8_with(image, w, h, 3, hole, &options);
        return;
    }
    let r = if radius >= 1.0 { radius.min(super::inpaint::MAX_RADIUS) } else { 1.0 };
    let margin = (1.5 * r.ceil() + 2.0).ceil() as usize + 2;
    let groups = hole_groups(hole, w, h, margin);
    let results: Vec<(Rect, Vec<u8>)> = groups
        .par_iter()
        .map(|win| {
            let (cw, ch) = (win.width(), win.height());
            let mut img = Vec::with_capacity(cw * ch * 3);
            let mut sub = Vec::with_capacity(cw * ch);
            for y in win.y0..win.y1 {
                img.extend_from_slice(&image[3 * (y * w + win.x0)..3 * (y * w + win.x1)]);
                sub.extend_from_slice(&hole[y * w + win.x0..y * w + win.x1]);
            }
            inpaint_telea_u8_with(&mut img, cw, ch, 3, &sub, &options);
            (*win, img)
        })
        .collect();
    for (win, img) in results {
        let cw = win.width();
        for y in win.y0..win.y1 {
            for x in win.x0..win.x1 {
                if hole[y * w + x] != 0 {
                    let o = 3 * ((y - win.y0) * cw + (x - win.x0));
                    image[3 * (y * w + x)..3 * (y * w + x) + 3].copy_from_slice(&img[o..o + 3]);
                }
            }
        }
    }
}

/// Most separate crops [`inpaint_holes`] makes; beyond, one crop holds all holes.
const MAX_HOLE_GROUPS: usize = 256;

/// The crops of [`inpaint_holes`]: bounding boxes of the holes' 4-connected components, grown by
/// `margin` and clipped to the frame, merged until no two overlap.
fn hole_groups(hole: &[u8], w: usize, h: usize, margin: usize) -> Vec<Rect> {
    let mut seen = vec![false; w * h];
    let mut rects: Vec<Rect> = Vec::new();
    let mut stack: Vec<usize> = Vec::new();
    let mut too_many = false;
    let mut all = Rect { x0: w, y0: h, x1: 0, y1: 0 };
    for start in 0..w * h {
        if hole[start] == 0 || seen[start] {
            continue;
        }
        let mut r = Rect { x0: start % w, y0: start / w, x1: start % w + 1, y1: start / w + 1 };
        seen[start] = true;
        stack.push(start);
        while let Some(i) = stack.pop() {
            let (x, y) = (i % w, i / w);
            r = r.union(&Rect { x0: x, y0: y, x1: x + 1, y1: y + 1 });
            let mut visit = |j: usize| {
                if hole[j] != 0 && !seen[j] {
                    seen[j] = true;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
            }
        }
        all = all.union(&r);
        if rects.len() < MAX_HOLE_GROUPS {
            rects.push(r.grow(margin, w, h));
        } else {
            too_many = true;
        }
    }
    if too_many {
        return vec![all.grow(margin, w, h)];
    }
    let overlap = |a: &Rect, b: &Rect| a.x0 < b.x1 && b.x0 < a.x1 && a.y0 < b.y1 && b.y0 < a.y1;
    loop {
        let mut merged = false;
        let mut i = 0;
        while i < rects.len() {
            let mut j = i + 1;
            while j < rects.len() {
                if overlap(&rects[i], &rects[j]) {
                    let b = rects.swap_remove(j);
                    rects[i] = rects[i].union(&b);
                    merged = true;
                } else {
                    j += 1;
                }
            }
            i += 1;
        }
        if !merged {
            break;
        }
    }
    rects
}

/// Most scene occupancies the generator keeps (those of scenes no longer alive are dropped
/// first).
const MAX_OCCUPANCIES: usize = 256;

/// A cached tile occupancy: the scene's key, the scene it was built from, the occupancy.
type OccupancyEntry = (SceneKey, Weak<Scene>, Arc<Occupancy>);

/// Makes samples by address from a scene loader, through a shared scene cache.
pub struct Generator {
    loader: Arc<dyn SceneLoader>,
    cache: Arc<SceneCache>,
    config: SampleConfig,
    /// The dataset word of the addresses (the loader's fingerprint, or one given).
    fingerprint: u64,
    /// The loader's fingerprint: the dataset word of the scene cache keys.
    loader_fingerprint: u64,
    /// Tile occupancy of each cached scene's MPI (small: N x (W/8) x (H/8) counts), keyed by the
    /// scene's cache key and checked against the scene itself.
    occupancies: Mutex<Vec<OccupancyEntry>>,
    /// Source items known to fail, by item: (id, failure kind, reason).
    bad: Mutex<BTreeMap<usize, BadItem>>,
}

/// A source item that failed to load: its id, failure kind and reason.
#[derive(Clone, Debug)]
struct BadItem {
    id: String,
    kind: FailureKind,
    reason: String,
}

impl std::fmt::Debug for Generator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Generator")
            .field("fingerprint", &self.fingerprint)
            .field("items", &self.loader.len())
            .field("config", &self.config)
            .finish()
    }
}

impl Generator {
    /// A generator over `loader`'s items; the configuration is checked here.
    pub fn new(
        loader: Arc<dyn SceneLoader>,
        cache: Arc<SceneCache>,
        config: SampleConfig,
    ) -> Result<Self, SampleError> {
        let fingerprint = loader.fingerprint();
        Self::with_fingerprint(loader, cache, config, fingerprint)
    }

    /// [`Generator::new`] with an explicit dataset word for the sample addresses (e.g. one that
    /// also covers the configuration, as the service's dataset fingerprint does). Scenes are still
    /// cached under the loader's fingerprint, so generators with different configurations over one
    /// loader share the cache.
    pub fn with_fingerprint(
        loader: Arc<dyn SceneLoader>,
        cache: Arc<SceneCache>,
        config: SampleConfig,
        fingerprint: u64,
    ) -> Result<Self, SampleError> {
        config.validate()?;
        let loader_fingerprint = loader.fingerprint();
        Ok(Self {
            loader,
            cache,
            config,
            fingerprint,
            loader_fingerprint,
            occupancies: Mutex::new(Vec::new()),
            bad: Mutex::new(BTreeMap::new()),
        })
    }

    pub fn config(&self) -> &SampleConfig {
        &self.config
    }

    /// The dataset word of every address this generator makes (the loader's fingerprint, unless
    /// given to [`Generator::with_fingerprint`]).
    pub fn fingerprint(&self) -> u64 {
        self.fingerprint
    }

    pub fn cache(&self) -> &Arc<SceneCache> {
        &self.cache
    }

    /// The source item of sample `index` (None for an empty collection).
    pub fn source_item(&self, index: u64) -> Option<usize> {
        self.config.source_item(index, self.loader.len())
    }

    fn key(&self, item: usize) -> SceneKey {
        SceneKey::new(self.loader_fingerprint, item as u64, self.config.scene_variant())
    }

    /// The prepared scene of source item `item`, from the cache or loaded into it.
    pub fn scene(&self, item: usize) -> Result<Arc<Scene>, SampleError> {
        self.cache.get_or_load(self.key(item), || {
            let scene = self.loader.load_scene(item).map_err(|e| SampleError::Scene {
                item,
                id: self.loader.id(item),
                source: Box::new(e),
            })?;
            prepare_scene(scene, &self.config)
        })
    }

    fn occupancy(&self, key: SceneKey, scene: &Arc<Scene>) -> Option<Arc<Occupancy>> {
        if self.config.mode != Mode::Exact || !self.config.skip.tiles {
            return None;
        }
        let found = {
            let list = self.occupancies.lock().unwrap_or_else(|e| e.into_inner());
            list.iter()
                .find(|(k, s, _)| *k == key && s.upgrade().is_some_and(|s| Arc::ptr_eq(&s, scene)))
                .map(|(_, _, o)| o.clone())
        };
        if found.is_some() {
            return found;
        }
        let occ = Arc::new(Occupancy::build(&scene.mpi, self.config.skip.tile_sigma_eps));
        let mut list = self.occupancies.lock().unwrap_or_else(|e| e.into_inner());
        list.retain(|(k, s, _)| s.strong_count() > 0 && *k != key);
        if list.len() >= MAX_OCCUPANCIES {
            list.remove(0);
        }
        list.push((key, Arc::downgrade(scene), occ.clone()));
        Some(occ)
    }

    fn bad_items(&self) -> std::sync::MutexGuard<'_, BTreeMap<usize, BadItem>> {
        self.bad.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Records a bad item (once).
    fn mark_bad(&self, item: usize, kind: FailureKind, error: &SampleError) {
        let mut bad = self.bad_items();
        bad.entry(item).or_insert_with(|| BadItem { id: self.loader.id(item), kind, reason: error.to_string() });
    }

    /// The scene of a source item that loads and fits the recipe, or the error.
    fn good_scene(&self, item: usize) -> Result<Arc<Scene>, SampleError> {
        let scene = self.scene(item)?;
        check_scene(&scene)?;
        Ok(scene)
    }

    /// The sample at (fingerprint, `seed`, `index`).
    ///
    /// **Bad sources are skipped deterministically.** If the address's source item `k` fails to
    /// load (a corrupt, truncated or too large image, bad depth or masks: an error of the item's
    /// data, not of the runtime, a model or the configuration), items `k + 1, k + 2, ...` (mod the
    /// number of items) are tried in turn and the first that loads makes the sample, with the
    /// address's own motions (the random streams stay keyed by (fingerprint, seed, index)), so a
    /// sample never depends on what was asked before. Failed items are remembered (not loaded
    /// again; failures are never cached as scenes) and recorded once each
    /// ([`skipped`](Self::skipped), [`skip_counts`](Self::skip_counts));
    /// [`Sample::skipped_sources`] counts the items passed over for this sample. When every
    /// item fails the error is [`SampleError::NoGoodSource`].
    pub fn sample(&self, seed: u64, index: u64) -> Result<Sample, SampleError> {
        let start = Instant::now();
        let first = self.source_item(index).ok_or(SampleError::EmptySource)?;
        let len = self.loader.len();
        let mut passed = 0u32;
        for step in 0..len {
            let item = (first + step) % len;
            if self.bad_items().contains_key(&item) {
                passed += 1;
                continue;
            }
            let scene = match self.good_scene(item) {
                Ok(scene) => scene,
                Err(e) => match e.bad_source_kind() {
                    Some(kind) => {
                        self.mark_bad(item, kind, &e);
                        passed += 1;
                        continue;
                    }
                    None => return Err(e),
                },
            };
            let occ = self.occupancy(self.key(item), &scene);
            let scene_ms = ms(start);
            let address = SampleAddress { dataset: self.fingerprint, seed, index };
            let mut s = assemble_with_occupancy(&scene, address, &self.config, occ.as_deref())?;
            s.skipped_sources = passed;
            s.timings.scene_ms = scene_ms;
            s.timings.total_ms += scene_ms;
            return Ok(s);
        }
        let bad = self.bad_items();
        let first_reason = bad.values().next().map(|b| b.reason.clone()).unwrap_or_default();
        Err(SampleError::NoGoodSource { items: len, first: first_reason })
    }

    /// The source items found bad so far, in item order: (item, id, reason).
    pub fn skipped(&self) -> Vec<(usize, String, String)> {
        self.bad_items().iter().map(|(&i, b)| (i, b.id.clone(), b.reason.clone())).collect()
    }

    /// How many source items were found bad so far, by failure kind (`decode`, `truncated`,
    /// `too-large`, `depth`, `mask`, `mpi`, `scene`: [`FailureKind::as_str`]), as set where each
    /// failure happened ([`SampleError::bad_source_kind`]).
    pub fn skip_counts(&self) -> BTreeMap<FailureKind, u64> {
        let mut out = BTreeMap::new();
        for b in self.bad_items().values() {
            *out.entry(b.kind).or_insert(0) += 1;
        }
        out
    }
}
