//! The deterministic sample recipe: from an address (dataset fingerprint, seed, index) to a
//! finished [`Sample`].
//!
//! # The recipe
//!
//! 1. **Source.** Item [`SampleConfig::source_item`] of the loader: the index space is cut into
//!    windows of `scene_window x motions_per_image` samples; a window interleaves the motions of
//!    `scene_window` items (sample `p` of window `b` uses item `b K + p mod K`), so consecutive
//!    samples come from different items while each item's scene, computed once and reused from
//!    the [`SceneCache`], serves `motions_per_image` samples. No random number is used for this
//!    ([`Purpose::SourceChoice`](crate::rng::Purpose::SourceChoice) is left for a future shuffled order).
//! 2. **Motions.** The camera motion from the `Purpose::CameraMotion` stream; the moving objects
//!    from `Purpose::ObjectChoice` ([`choose_objects`](super::object::choose_objects)); object slot `j`'s motion from
//!    `Purpose::ObjectMotion(j)`. Every stream is keyed by (fingerprint, seed, index, purpose), so
//!    the same address gives the same numbers on any run, thread count or machine, and one
//!    purpose never shifts another's numbers.
//! 3. **Renders** (exact mode by default): the scene under the camera motion (whole frame, work
//!    skipping with the scene's tile occupancy, which `Generator` (`pipeline.rs`) keeps per cached
//!    scene);
//!    with objects, the union mask's channel under the camera motion and each object under its
//!    own motion, each rendered only over the window of the frame where its channel can be
//!    non-zero, straight from the shared MPI ([`super::object`]: the same values as full-frame
//!    renders, bit-identical in the tests). With `windowed = false`, or in the reference mode,
//!    full-frame renders of MPI copies with the mask channel attached (the reference's way,
//!    slower). Without objects (`max_objects = 0`, no instances, none large enough) there is no
//!    mask channel and no second render: the object stage costs nothing.
//! 4. **Merge** ([`super::merge`]) by the configured rule, then **inpainting** of the holes with
//!    Telea's method in u8 ([`InpaintMethod`](super::config::InpaintMethod), radius 3 by default, as the reference's radius),
//!    on crops around the holes ([`fill_holes`]: the whole-frame result, bit for bit).
//!
//! **A cropped sample** ([`assemble_cropped`], a request's [`CropSpec`]) is made over its window
//! only: the renders of a pair without backward fields cover the window (each pixel the
//! whole frame's, bit for bit), the holes are those inside it, and the merged sample is cut to
//! the window before the hole filling and the noise, which see only the window (pixels near the
//! window's edge are filled from the window alone). Image1, the flow, `valid`, the masks and
//! the depths are the whole frame's cut to the window, and so is image2 wherever it is rendered;
//! a clip, the backward fields and the reference mode render whole frames and are cut alike.
//!
//! Per-pixel work runs on the current rayon pool; every output is independent of the pool's size
//! (the renderer is bit-identical to a serial run, merging is per pixel, each inpainting crop is
//! sequential and independent of the others). [`StageTimings`] are measurements and not part of
//! the sample's bytes: `scene_ms` (cache lookup or load, and the scene's tile occupancy the first
//! time the generator sees the scene), `render_ms` (the scene render with, in windowed renders,
//! the union of the moved objects' masks as its channel over that mask's footprint, and the
//! occupancy when [`assemble`] had to build it), `objects_ms` (choosing and rendering objects,
//! and the scene mask from the union's channel), `merge_ms` (merge and image1), `inpaint_ms`,
//! `total_ms`.
//!
//! **Bad sources** (`Generator::sample`): when the address's source item fails to load because
//! of its data (corrupt, truncated or too large image, bad depth, masks or MPI), the next items
//! (mod the collection's length) are tried in order and the first good one is used with the
//! address's own motions; failed items are remembered and counted by their
//! [`FailureKind`](crate::source::FailureKind) (`Generator::skip_counts`), [`Sample::skipped_sources`] says how many were passed over. The
//! result depends only on which items are bad, not on what was asked before. Runtime, model,
//! configuration and render errors are not the item's and are returned.
//!
//! Besides the images and flow, a sample carries `depth1` (the scene's `1 / disparity`, the
//! source frame's depth in the scene scale) and `depth2` (the merge's depth of what image2 shows;
//! 0 in holes), both taken from what the recipe computes anyway.
//!
//! # Backward fields and clips
//!
//! With [`SampleConfig::backward`] the image2 renders (scene and objects) also follow each target
//! pixel back into the source view ([`crate::render::Link`] into [`View::Source`](crate::render::View::Source): every plane's
//! inverse displacement composited with the target weights), merged like image2 itself
//! ([`super::merge::merge_link`]: an object's pixels carry its inverse motion, holes are not
//! valid) into [`Sample::backward`]. Without it no link is rendered at all.
//!
//! **Clips** ([`SampleConfig::frames`] = K > 2) follow the constant-velocity model: the camera and
//! every moving object repeat their drawn frame-1 -> frame-2 rigid motion each frame, so frame
//! f + 1 (f = 0 is the photo) is the same MPI rendered under `pose^f` ([`trajectory`];
//! `pose^(f+1) = pose o pose^f`, which composes exactly). Every frame is one render of the
//! cached scene's MPI (one per object too); frame f's renders carry a link into frame f + 1
//! (`pose^(f+1)`, the forward flow f -> f + 1 on frame f's grid, exact per plane: no lookup in
//! another frame) and, with the backward fields, one into frame f - 1. The flow 1 -> 2 is the
//! pair's (the source view), so a clip's first pair is byte for byte the pair of the same
//! address and configuration, and frames = 2 adds nothing to the address (the fingerprint).
//! Occlusion of a link is tested against what the frame it lands in shows (its merged depth and
//! labels, holes included), the forward rule of the pair applied to that frame.
//!
//! An object's motion is by default its own rigid motion from the source camera to the target
//! camera (the reference script renders the object with its own small pose, independent of the
//! camera's); with `objects_follow_camera` it is composed with the camera's
//! (`X_tgt = R_c (R_o X + t_o) + t_c`: the object moves, then the camera).

//!
//! Rooms: `draws` (the motions and the moved objects), `frames` (every frame's renders), `merges`
//! (the merges, the background fill, the links, image1 and depth1); this front door holds the
//! entry points and the inpainting after the merge.

mod draws;
mod frames;
mod merges;

use std::sync::Arc;
use std::time::Instant;

use super::config::{InpaintMethod, SampleConfig};
use super::crop::{clear_outside, crop_plane, crop_sample, crop_window, window_intrinsics, CropSpec};
use super::error::SampleError;
use super::holes::{fill_holes, label_continued, TextureSource};
use super::merge::MergeRule;
use super::preblend::preblend;
use super::types::{Sample, SampleAddress, StageTimings};
use crate::render::{Mode, Occupancy, Rect};
use crate::scene::Scene;

use draws::draw_motions;
pub(crate) use frames::ms;
pub use frames::trajectory;
use frames::{render_frames, union_mask, FrameCtx};
use merges::{image1_depth1, merge_frame2, merge_later_frames, merge_links, BackgroundFill};

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
        if config.minify {
            crate::render::mip::prefilter_arc(&mut scene.mpi);
        }
    }
    if crate::render::store::packs(config.mode, config.resample, config.minify) {
        // the planes in blocks, only where there is density (the same renders, a third of the bytes)
        crate::render::store::pack_arc(&mut scene.mpi);
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
/// (`tests/samples/labels.rs`, `mpiflow bench quality`).
pub fn assemble_with_target_depth(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
) -> Result<(Sample, Vec<f32>), SampleError> {
    assemble_cropped(scene, address, config, occupancy, None).map(|(s, z, _)| (s, z))
}

/// A sample, its target depth and its window's corner in the frame ([`assemble_cropped`]).
pub type Cropped = (Sample, Vec<f32>, (usize, usize));

/// [`assemble_with_target_depth`] cut to `crop`'s window (see "A cropped sample" above), with the
/// window's corner in the frame ((0, 0) without a crop): the sample's intrinsics are the
/// window's, its target depth is cut alike. A crop larger than the frame is
/// [`SampleError::Crop`].
pub fn assemble_cropped(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
    crop: Option<&CropSpec>,
) -> Result<Cropped, SampleError> {
    let start = Instant::now();
    let (fw, fh) = (scene.mpi.width, scene.mpi.height);
    let window = match crop {
        Some(c) => {
            let (x0, y0, cw, ch) = crop_window(c, fw, fh, address).map_err(SampleError::Crop)?;
            let r = Rect { x0, y0, x1: x0 + cw, y1: y0 + ch };
            (!r.is_full(fw, fh)).then_some(r)
        }
        None => None,
    };
    let (merged, target_depth) = assemble_merged_sample(scene, address, config, occupancy, window)?;
    let (mut sample, target_depth, corner) = match window {
        // made over the window
        Some(r) if merged.width == r.width() && merged.height == r.height() => (merged, target_depth, (r.x0, r.y0)),
        Some(r) => {
            let (cw, ch) = (r.width(), r.height());
            let z = crop_plane(&target_depth, fw, 1, r.x0, r.y0, cw, ch);
            (crop_sample(&merged, r.x0, r.y0, cw, ch), z, (r.x0, r.y0))
        }
        None => (merged, target_depth, (0, 0)),
    };
    let t = Instant::now();
    let (w, h) = (sample.width, sample.height);
    let (method, radius) = (config.inpaint_method, config.inpaint_radius);
    let texture_fill = method == InpaintMethod::Exemplar
        && (sample.inpainted_pixels > 0 || sample.clip.iter().any(|f| f.holes.contains(&1)));
    // every object of image1, moved or not (the texture fill's sources are background)
    let objects: Vec<bool> = if texture_fill { objects_of(scene, &sample.mask1, w, corner) } else { Vec::new() };
    if sample.inpainted_pixels > 0 {
        let texture = TextureSource {
            image1: &sample.image1,
            depth1: &sample.depth1,
            objects: &objects,
            depth: &sample.depth2,
            mask: &sample.mask2,
            labels1: &sample.mask1,
            z_shift: sample.camera.translation[2] as f32,
        };
        let continued = fill_holes(&mut sample.image2, w, h, &sample.holes, method, radius, &texture);
        label_continued(&mut sample.mask2, &continued);
    }
    for (k, f) in sample.clip.iter_mut().enumerate() {
        if f.holes.contains(&1) {
            // frame k + 3 is pose^(k + 2) from image1 (constant velocity)
            let z_shift = (sample.camera.translation[2] * (k + 2) as f64) as f32;
            let texture = TextureSource {
                image1: &sample.image1,
                depth1: &sample.depth1,
                objects: &objects,
                depth: &f.depth,
                mask: &f.mask,
                labels1: &sample.mask1,
                z_shift,
            };
            let continued = fill_holes(&mut f.image, w, h, &f.holes, method, radius, &texture);
            label_continued(&mut f.mask, &continued);
        }
    }
    if config.restore_noise {
        use super::noise::{noise_key, restore_noise_to, NoiseTarget};
        // image1's level once for every frame
        if let Some(target) = NoiseTarget::of(&sample.image1, w, h) {
            let key = noise_key(sample.address);
            restore_noise_to(&target, &mut sample.image2, &sample.holes, w, h, key, 1);
            for (k, f) in sample.clip.iter_mut().enumerate() {
                restore_noise_to(&target, &mut f.image, &f.holes, w, h, key, k as u64 + 2);
            }
        }
    }
    sample.timings.inpaint_ms = ms(t);
    sample.timings.total_ms = ms(start);
    Ok((sample, target_depth, corner))
}

/// [`assemble_with_occupancy`] up to the merge: the sample with `image2` as merged, its holes not
/// yet inpainted, and the hole mask (H x W, 1 = hole; [`Sample::inpainted_pixels`] counts them).
/// [`assemble`] is this followed by [`fill_holes`] over the mask (windowed). The mask is
/// also the sample's [`Sample::holes`].
pub fn assemble_merged(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
) -> Result<(Sample, Vec<u8>), SampleError> {
    let (sample, _) = assemble_merged_sample(scene, address, config, occupancy, None)?;
    let hole = sample.holes.clone();
    Ok((sample, hole))
}

/// [`assemble_merged`] without the copy of the hole mask (it is [`Sample::holes`]), with the
/// merge's target depth of every source pixel. The stages, in order: the draws
/// ([`draw_motions`]), the scene's tile occupancy, the union mask ([`union_mask`]), every
/// frame's renders ([`render_frames`]), the merges with the background fill ([`merge_frame2`],
/// [`merge_later_frames`]), the links ([`merge_links`]), image1 and depth1 ([`image1_depth1`]).
///
/// With a `window` (a crop of the frame), the holes are those inside it; a pair without
/// backward fields in the windowed exact mode renders only the window.
fn assemble_merged_sample(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
    window: Option<Rect>,
) -> Result<(Sample, Vec<f32>), SampleError> {
    let start = Instant::now();
    config.validate()?;
    check_scene(scene)?;
    let mpi = &*scene.mpi;
    let (w, h) = (mpi.width, mpi.height);
    let mut timings = StageTimings::default();

    let t = Instant::now();
    let draws = draw_motions(scene, address, config);
    let mut objects_ms = ms(t);

    let windowed = config.windowed && config.mode == Mode::Exact;
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

    let union = union_mask(scene, &draws.chosen, config.merge == MergeRule::DepthAware);
    let chosen = draws.chosen.as_slice();

    let cam_traj = trajectory(&draws.cam_pose, config.frames);
    // the renders cover only the window where nothing reads outside it: frame 2 with no links
    let render_window = window.filter(|_| windowed && config.frames == 2 && !config.backward);
    let ctx = FrameCtx { scene, config, windowed, occupancy, union: union.as_deref(), chosen, window: render_window };
    let mut renders = render_frames(&ctx, &cam_traj, &draws.poses)?;
    let (mut render_ms, mut objects_extra_ms) = (occupancy_ms, 0.0);
    for r in &renders {
        render_ms += r.render_ms;
        objects_extra_ms += r.objects_ms;
    }
    timings.render_ms = render_ms;
    objects_ms += objects_extra_ms;
    timings.objects_ms = objects_ms;

    // merge: frame 2 both sides (image2 and the forward flow), later frames their target side
    let t = Instant::now();
    let fill = BackgroundFill::new(scene, config, occupancy, union.as_deref());
    let (merged, frame2) = merge_frame2(&ctx, renders.remove(0), &fill, &cam_traj, window)?;
    let later = merge_later_frames(&ctx, &mut renders, &fill, &cam_traj)?;
    let (backward, clip) = merge_links(&ctx, &merged, &frame2, &renders, later);
    drop(frame2);
    let at = ctx.covered();
    let (image1, depth1) = image1_depth1(scene, at);
    timings.merge_ms = ms(t);

    timings.total_ms = ms(start);

    // a windowed render is the crop's sample already: its own size, camera and crop rule
    let (mut valid, mut occlusion) = (merged.valid, merged.occlusion);
    let (w, h, intrinsics) = match ctx.window {
        Some(r) => {
            clear_outside(&merged.flow, &mut valid, &mut occlusion, r.width(), r.height());
            (r.width(), r.height(), window_intrinsics(scene.intrinsics, r.x0, r.y0))
        }
        None => (w, h, scene.intrinsics),
    };
    let sample = Sample {
        address,
        source_id: scene.id.clone(),
        width: w,
        height: h,
        image1,
        image2: merged.image2,
        flow: merged.flow,
        valid,
        occlusion,
        mask1: merged.mask1,
        mask2: merged.mask2,
        camera: draws.camera,
        objects: draws.records,
        depth1,
        depth2: merged.depth2,
        holes: merged.hole,
        inpainted_pixels: merged.holes,
        backward,
        clip,
        skipped_sources: 0,
        provenance: scene.provenance.clone(),
        intrinsics,
        timings,
    };
    Ok((sample, merged.target_depth))
}

/// Where image1 shows an object: a moved one (`mask1`, a window of the frame at `corner`) or any
/// instance of the scene (>= 0.5).
fn objects_of(scene: &Scene, mask1: &[u8], width: usize, corner: (usize, usize)) -> Vec<bool> {
    let fw = scene.mpi.width;
    let mut out: Vec<bool> = mask1.iter().map(|&m| m != 0).collect();
    for inst in &scene.masks.masks {
        for (y, row) in out.chunks_mut(width.max(1)).enumerate() {
            let at = (corner.1 + y) * fw + corner.0;
            let n = row.len();
            for (o, &m) in row.iter_mut().zip(&inst.mask[at..at + n]) {
                *o |= m >= 0.5;
            }
        }
    }
    out
}
