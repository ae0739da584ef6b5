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
use std::sync::Arc;
use std::time::Instant;

pub use super::config::{InpaintMethod, MotionSpec, SampleConfig};
pub use super::holes::inpaint_holes;
use super::merge::{merge, unit_to_u8, ObjectView, SceneView};
use super::motion::MotionError;
use super::object::{
    choose_objects, object_window, render_full_with_mask, render_mask_window, scene_mask_window, support_rect, Rect,
    WindowRender,
};
pub use super::pipeline::Generator;
use super::preblend::{preblend, PreblendError};
use super::rng::{Purpose, SampleRng};
use super::{ObjectRecord, Sample, SampleAddress, StageTimings};
use crate::render::{render, Fields, Mode, Occupancy, RenderError, RenderOutput, RenderParams, Resample};
use crate::scene::{Scene, SceneError};
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
    if config.mode == Mode::Exact {
        // once per scene: the cached scene carries the coefficients every sample samples
        crate::render::resample::prefilter_arc(&mut scene.mpi, config.resample);
    }
    Ok(scene)
}

pub(crate) fn check_scene(scene: &Scene) -> Result<(), SampleError> {
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

pub(crate) fn ms(t: Instant) -> f64 {
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
    Ok(assemble_with_target_depth(scene, address, config, occupancy)?.0)
}

/// [`assemble_with_occupancy`], with the expected target depth of every image1 pixel (H x W, the
/// depth its point has in image2's camera under the motion that moves it; 0 where unknown): the
/// `z` of the merge's occlusion rule ([`super::merge::LabelRule`]), for checking the labels
/// (`tests/labels.rs`, `mpiflow bench quality`).
pub fn assemble_with_target_depth(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
) -> Result<(Sample, Vec<f32>), SampleError> {
    let start = Instant::now();
    let (mut sample, target_depth) = assemble_merged_sample(scene, address, config, occupancy)?;
    let t = Instant::now();
    if sample.inpainted_pixels > 0 {
        let (w, h) = (sample.width, sample.height);
        inpaint_holes(&mut sample.image2, w, h, &sample.holes, config.inpaint_method, config.inpaint_radius, true);
    }
    sample.timings.inpaint_ms = ms(t);
    sample.timings.total_ms = ms(start);
    Ok((sample, target_depth))
}

/// [`assemble_with_occupancy`] up to the merge: the sample with `image2` as merged, its holes not
/// yet inpainted, and the hole mask (H x W, 1 = hole; [`Sample::inpainted_pixels`] counts them).
/// [`assemble`] is this followed by [`inpaint_holes`] over the mask (windowed). The mask is
/// also the sample's [`Sample::holes`].
pub fn assemble_merged(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
) -> Result<(Sample, Vec<u8>), SampleError> {
    let (sample, _) = assemble_merged_sample(scene, address, config, occupancy)?;
    let hole = sample.holes.clone();
    Ok((sample, hole))
}

/// [`assemble_merged`] without the copy of the hole mask (it is [`Sample::holes`]), with the
/// merge's target depth of every source pixel.
fn assemble_merged_sample(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
) -> Result<(Sample, Vec<f32>), SampleError> {
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
    params.resample = config.resample;
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
            let r = render_full_with_mask(
                mpi,
                &k,
                &cam_pose,
                &inv,
                config.mode,
                config.skip,
                config.resample,
                params.fields,
            )
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
            // only coverage and the mask channel are used, which no colour kernel changes
            let r = render_mask_window(mpi, occupancy, &k, &cam_pose, &win, u, config.skip, Resample::Bilinear, false)
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
                render_mask_window(mpi, occupancy, &k, pose, &win, mask, config.skip, config.resample, true)
            }
            _ => render_full_with_mask(mpi, &k, pose, mask, config.mode, config.skip, config.resample, params.fields),
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
        source_depth: source_depth_in_target,
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
    let merged = merge(view, &views, config.merge, config.label_rule, config.mask_threshold);
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
        holes: merged.hole,
        inpainted_pixels: merged.holes,
        skipped_sources: 0,
        provenance: scene.provenance.clone(),
        intrinsics: scene.intrinsics,
        timings,
    };
    Ok((sample, merged.target_depth))
}
