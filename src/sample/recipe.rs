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
//!    ([`Purpose::SourceChoice`] is left for a future shuffled order).
//! 2. **Motions.** The camera motion from the `Purpose::CameraMotion` stream; the moving objects
//!    from `Purpose::ObjectChoice` ([`choose_objects`]); object slot `j`'s motion from
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
//! pixel back into the source view ([`crate::render::Link`] into [`View::Source`]: every plane's
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

use std::borrow::Cow;
use std::sync::Arc;
use std::time::Instant;

use super::background::{cut_planes, fill_from_planes, Background, Frame};
use super::config::{InpaintMethod, SampleConfig};
use super::error::SampleError;
use super::holes::{fill_holes, label_continued, TextureSource};
use super::merge::{
    merge, merge_link, merge_target, units_to_u8, MergeRule, Merged, ObjectView, OtherFrame, SceneView, TargetSide,
};
use super::motion::{Motion, RotationKind};
use super::object::{
    choose_objects, object_window, render_full_with_mask, render_mask_window, scene_mask_window, support_rect,
};
use super::preblend::preblend;
use super::types::{ClipFrame, LinkFields, ObjectRecord, Sample, SampleAddress, StageTimings};
use crate::geometry::Pose;
use crate::raster::resize::crop;
use crate::render::{
    render, render_window, Channels, Fields, Link, Mode, Occupancy, Rect, RenderError, RenderOutput, RenderParams,
    View, WindowRender,
};
use crate::rng::{Purpose, SampleRng};
use crate::scene::Scene;

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
    let (w, h) = (sample.width, sample.height);
    let (method, radius) = (config.inpaint_method, config.inpaint_radius);
    let texture_fill = method == InpaintMethod::Exemplar
        && (sample.inpainted_pixels > 0 || sample.clip.iter().any(|f| f.holes.contains(&1)));
    // every object of image1, moved or not (the texture fill's sources are background)
    let objects: Vec<bool> = if texture_fill { objects_of(scene, &sample.mask1) } else { Vec::new() };
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
    Ok((sample, target_depth))
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
    let (sample, _) = assemble_merged_sample(scene, address, config, occupancy)?;
    let hole = sample.holes.clone();
    Ok((sample, hole))
}

/// [`assemble_merged`] without the copy of the hole mask (it is [`Sample::holes`]), with the
/// merge's target depth of every source pixel. The stages, in order: the draws
/// ([`draw_motions`]), the scene's tile occupancy, the union mask ([`union_mask`]), every
/// frame's renders ([`render_frames`]), the merges with the background fill ([`merge_frame2`],
/// [`merge_later_frames`]), the links ([`merge_links`]), image1 and depth1 ([`image1_depth1`]).
fn assemble_merged_sample(
    scene: &Scene,
    address: SampleAddress,
    config: &SampleConfig,
    occupancy: Option<&Occupancy>,
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

    let union = union_mask(scene, &draws.chosen);
    let chosen = draws.chosen.as_slice();

    let cam_traj = trajectory(&draws.cam_pose, config.frames);
    let ctx = FrameCtx { scene, config, windowed, occupancy, union: union.as_deref(), chosen };
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
    let (merged, coverage, frame2) = merge_frame2(&ctx, renders.remove(0), &fill, &cam_traj)?;
    let later = merge_later_frames(&ctx, &mut renders, &fill, &cam_traj)?;
    let (backward, clip) = merge_links(&ctx, &merged, &frame2, &renders, later);
    drop(frame2);
    let (image1, depth1) = image1_depth1(scene, coverage);
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
        intrinsics: scene.intrinsics,
        timings,
    };
    Ok((sample, merged.target_depth))
}

/// The draws of a sample: the camera's motion, the chosen objects and their motions.
struct Draws {
    camera: Motion,
    cam_pose: Pose,
    /// indices into the scene's instance masks, slot order
    chosen: Vec<usize>,
    records: Vec<ObjectRecord>,
    /// each chosen object's pose (composed with the camera's when objects follow it)
    poses: Vec<Pose>,
}

/// Draws the camera motion, the moved objects and their motions, each from its own stream.
fn draw_motions(scene: &Scene, address: SampleAddress, config: &SampleConfig) -> Draws {
    let ranges = config.motion.ranges();
    let rng = |p: Purpose| SampleRng::new(address.dataset, address.seed, address.index, p);
    let camera = ranges.sample_camera_motion(&mut rng(Purpose::CameraMotion));
    let cam_pose = camera.to_pose();
    // stereo laws move no object: a rectified pair is one rigid camera motion
    let chosen = if config.max_objects > 0 && !ranges.stereo && !scene.masks.masks.is_empty() {
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
        let mut stream = rng(Purpose::ObjectMotion(slot as u32));
        let mut motion = ranges.sample_object_motion(&mut stream);
        let mut pose = object_pose(&motion.to_pose(), &cam_pose, config.objects_follow_camera);
        if let Some(budget) = ranges.sample_reveal_budget(&mut stream) {
            (motion, pose) = within_budget(scene, &inst.mask, &cam_pose, (motion, pose), budget, config);
        }
        poses.push(pose);
        records.push(ObjectRecord {
            label: (slot + 1) as u8,
            instance: inst.id,
            score: inst.score,
            area: inst.area,
            motion,
        });
    }
    Draws { camera, cam_pose, chosen, records, poses }
}

/// The pose image2 shows an object under: its own motion, after the camera's when objects
/// follow it.
fn object_pose(own: &Pose, cam_pose: &Pose, follow: bool) -> Pose {
    if follow {
        cam_pose.compose(own)
    } else {
        *own
    }
}

/// An object's motion and pose moved by less when it would uncover more than `budget` of the
/// frame ([`super::reveal`]); the record is the motion applied (as an axis-angle law when
/// scaled).
fn within_budget(
    scene: &Scene,
    mask: &[f32],
    cam_pose: &Pose,
    (motion, pose): (Motion, Pose),
    budget: f64,
    config: &SampleConfig,
) -> (Motion, Pose) {
    use super::reveal::{fit_scale, scaled_pose, MaskSamples};
    let (w, h) = (scene.mpi.width, scene.mpi.height);
    if scene.disparity.data.len() != w * h || mask.len() != w * h {
        return (motion, pose);
    }
    let samples = MaskSamples::new(mask, &scene.disparity.data, w, h, scene.intrinsics);
    let s = fit_scale(&samples, cam_pose, &pose, budget);
    if s == 1.0 {
        return (motion, pose);
    }
    let scaled = scaled_pose(cam_pose, &pose, s);
    let own = if config.objects_follow_camera { cam_pose.inverse().compose(&scaled) } else { scaled };
    let aa = super::motion::axis_angle_from_matrix(&own.rotation).to_array();
    let record = Motion::new(&motion.law, own.translation.to_array(), RotationKind::AxisAngle, aa);
    // the pose of the record, so that the sample's metadata reproduces the render exactly
    let applied = object_pose(&record.to_pose(), cam_pose, config.objects_follow_camera);
    (record, applied)
}

/// Where image1 shows an object: a moved one (`mask1`) or any instance of the scene (>= 0.5).
fn objects_of(scene: &Scene, mask1: &[u8]) -> Vec<bool> {
    let mut out: Vec<bool> = mask1.iter().map(|&m| m != 0).collect();
    for inst in &scene.masks.masks {
        for (o, &m) in out.iter_mut().zip(&inst.mask) {
            *o |= m >= 0.5;
        }
    }
    out
}

/// The union mask of the moved objects (the scene mask channel is 1 - U); none without objects.
fn union_mask<'a>(scene: &'a Scene, chosen: &[usize]) -> Option<Cow<'a, [f32]>> {
    let (w, h) = (scene.mpi.width, scene.mpi.height);
    match chosen {
        [] => None,
        [one] => Some(Cow::Borrowed(&scene.masks.masks[*one].mask)),
        many => {
            let mut u = crate::buf::zeros::<f32>(w * h);
            for &idx in many {
                for (a, &b) in u.iter_mut().zip(&scene.masks.masks[idx].mask) {
                    *a = a.max(b);
                }
            }
            Some(Cow::Owned(u))
        }
    }
}

/// Every frame's renders: frame f (0-based; f = 1 is image2) under pose^f of the camera
/// (`cam_traj`) and of each object (`poses`); links: slot 0 the previous frame (backward
/// fields), slot 1 the next.
fn render_frames(c: &FrameCtx<'_>, cam_traj: &[Pose], poses: &[Pose]) -> Result<Vec<FrameRender>, SampleError> {
    let config = c.config;
    let frames = config.frames;
    let obj_traj: Vec<Vec<Pose>> = poses.iter().map(|p| trajectory(p, frames)).collect();
    let links_of = |traj: &[Pose], f: usize| -> [Option<View>; 2] {
        let prev = config.backward.then(|| if f == 1 { View::Source } else { View::Pose(traj[f - 1]) });
        [prev, (f + 1 < frames).then(|| View::Pose(traj[f + 1]))]
    };
    let mut renders: Vec<FrameRender> = Vec::with_capacity(frames - 1);
    for f in 1..frames {
        let obj_poses: Vec<(Pose, [Option<View>; 2])> =
            obj_traj.iter().map(|traj| (traj[f], links_of(traj, f))).collect();
        let r = render_frame(c, (cam_traj[f], links_of(cam_traj, f)), &obj_poses, f == 1)?;
        renders.push(r);
    }
    Ok(renders)
}

/// The MPI's planes behind the moved objects, which fill what they can of a frame's holes
/// ([`super::background`]); nothing unless the configuration asks for it and the scene allows.
struct BackgroundFill<'a> {
    scene: &'a Scene,
    config: &'a SampleConfig,
    occupancy: Option<&'a Occupancy>,
    /// the union mask and the cut planes
    cut: Option<(&'a [f32], Vec<u8>)>,
}

impl<'a> BackgroundFill<'a> {
    fn new(
        scene: &'a Scene,
        config: &'a SampleConfig,
        occupancy: Option<&'a Occupancy>,
        union: Option<&'a [f32]>,
    ) -> Self {
        let (w, h) = (scene.mpi.width, scene.mpi.height);
        let cut = match union {
            Some(u)
                if config.background == Background::Planes
                    && config.merge == MergeRule::DepthAware
                    && config.mode == Mode::Exact
                    && scene.disparity.data.len() == w * h =>
            {
                Some((u, cut_planes(scene, u)))
            }
            _ => None,
        };
        Self { scene, config, occupancy, cut }
    }

    /// Fills the holes of the frame at camera `pose`; returns how many it filled.
    fn fill(&self, pose: Pose, image: &mut [u8], hole: &mut [u8], depth: &mut [f32]) -> Result<u64, SampleError> {
        let Some((u, last)) = &self.cut else { return Ok(0) };
        let scene = self.scene;
        fill_from_planes(
            scene,
            &scene.intrinsics,
            self.occupancy,
            self.config.skip,
            u,
            last,
            self.config.mask_threshold,
            Frame { pose, image, hole, depth },
        )
        .map_err(|source| SampleError::Render {
            id: scene.id.clone(),
            stage: "background",
            source: Box::new(source),
        })
    }
}

/// What the links read of frame 2 besides its merged fields.
struct Frame2 {
    /// the scene render's links
    links: [Link; 2],
    /// the source camera's depth of each source pixel (the backward occlusion test)
    source_depth: Vec<f32>,
    /// the holes as the renders left them (the links keep them), when the fill changed them
    rendered_hole: Option<Vec<u8>>,
    /// what frame 2 shows (inf at holes), for the links that land in it (clips only)
    shown: Vec<f32>,
    objects: Vec<WindowRender>,
}

/// Frame 2 merged on both sides (image2 and the forward flow) and filled from the planes;
/// returns the merge, the scene render's coverage (the buffer depth1 reuses) and what the
/// links read.
fn merge_frame2(
    c: &FrameCtx<'_>,
    mut first: FrameRender,
    fill: &BackgroundFill<'_>,
    cam_traj: &[Pose],
) -> Result<(Merged, Vec<f32>, Frame2), SampleError> {
    let (scene, config) = (c.scene, c.config);
    let (w, h) = (scene.mpi.width, scene.mpi.height);
    let scene_links = std::mem::take(&mut first.scene.links);
    let source_depth = std::mem::take(&mut first.scene.source_depth);
    let RenderOutput { image, depth, coverage, flow, source_depth_in_target, valid, .. } = first.scene;
    let view = SceneView {
        width: w,
        height: h,
        image: &image,
        depth,
        scene_mask: first.full_mask.as_deref().unwrap_or(&coverage),
        scene_mask_patch: first.mask_patch.as_ref().map(|(r, p)| (*r, p.as_slice())),
        flow,
        valid,
        source_depth: source_depth_in_target,
    };
    let views1 = object_views(scene, c.chosen, &first.objects);
    let mut merged = merge(view, &views1, config.merge, config.label_rule, config.mask_threshold, config.occlusion);
    drop(views1);
    drop(image);
    let rendered_hole = fill.cut.as_ref().map(|_| merged.hole.clone());
    let filled = fill.fill(cam_traj[1], &mut merged.image2, &mut merged.hole, &mut merged.depth2)?;
    merged.holes -= filled;
    let shown: Vec<f32> = if config.frames > 2 {
        merged.depth2.iter().zip(&merged.hole).map(|(&d, &o)| if o != 0 { f32::INFINITY } else { d }).collect()
    } else {
        Vec::new()
    };
    let frame2 = Frame2 { links: scene_links, source_depth, rendered_hole, shown, objects: first.objects };
    Ok((merged, coverage, frame2))
}

/// A later frame (3, 4, ...) merged on its target side and filled from the planes, with its
/// scene render's links and its holes as the renders left them (for the links).
struct LaterFrame {
    target: TargetSide,
    links: [Link; 2],
    rendered_hole: Vec<u8>,
}

/// The target sides of the frames after frame 2 (`renders`, frame 3 first).
fn merge_later_frames(
    c: &FrameCtx<'_>,
    renders: &mut [FrameRender],
    fill: &BackgroundFill<'_>,
    cam_traj: &[Pose],
) -> Result<Vec<LaterFrame>, SampleError> {
    let (scene, config) = (c.scene, c.config);
    let (w, h) = (scene.mpi.width, scene.mpi.height);
    let mut later = Vec::with_capacity(renders.len());
    for (j, r) in renders.iter_mut().enumerate() {
        let links = std::mem::take(&mut r.scene.links);
        let views = object_views(scene, c.chosen, &r.objects);
        let depth = std::mem::take(&mut r.scene.depth);
        let target = merge_target(
            w,
            h,
            &r.scene.image,
            depth,
            r.full_mask.as_deref().unwrap_or(&r.scene.coverage),
            r.mask_patch.as_ref().map(|(rc, p)| (*rc, p.as_slice())),
            &views,
            config.merge,
            config.mask_threshold,
        );
        let mut target = target;
        let rendered_hole = target.hole.clone();
        let n = fill.fill(cam_traj[j + 2], &mut target.image, &mut target.hole, &mut target.shown_depth)?;
        target.holes -= n;
        later.push(LaterFrame { target, links, rendered_hole });
    }
    Ok(later)
}

/// The links: the backward fields of every frame and the forward flows from frame 2 on; returns
/// the pair's backward fields and the clip's later frames.
fn merge_links(
    c: &FrameCtx<'_>,
    merged: &Merged,
    frame2: &Frame2,
    renders: &[FrameRender],
    later: Vec<LaterFrame>,
) -> (LinkFields, Vec<ClipFrame>) {
    let (scene, config, chosen) = (c.scene, c.config, c.chosen);
    let (w, h) = (scene.mpi.width, scene.mpi.height);
    let hole2_for_links: &[u8] = frame2.rendered_hole.as_deref().unwrap_or(&merged.hole);
    let image1_labels = &merged.mask1;
    // what frame f (>= 1) shows
    let frame_of = |f: usize| -> OtherFrame<'_> {
        if f == 1 {
            OtherFrame { depth: &frame2.shown, labels: &merged.mask2 }
        } else {
            OtherFrame { depth: &later[f - 2].target.shown_depth, labels: &later[f - 2].target.mask }
        }
    };
    let backward = if config.backward {
        let views1 = object_views(scene, chosen, &frame2.objects);
        let other = OtherFrame { depth: &frame2.source_depth, labels: image1_labels };
        merge_link(0, &frame2.links[0], &views1, &merged.mask2, hole2_for_links, other, w, h, config.label_rule)
    } else {
        LinkFields::default()
    };
    let mut clip = Vec::with_capacity(later.len());
    for (j, lf) in later.iter().enumerate() {
        // frame f = j + 2 (0-based): its previous frame is f - 1
        let f = j + 2;
        let (prev_links, prev_mask, prev_hole, prev_views) = if f == 2 {
            (&frame2.links, &merged.mask2, hole2_for_links, object_views(scene, chosen, &frame2.objects))
        } else {
            let pf = &later[j - 1];
            (
                &pf.links,
                &pf.target.mask,
                pf.rendered_hole.as_slice(),
                object_views(scene, chosen, &renders[j - 1].objects),
            )
        };
        let forward =
            merge_link(1, &prev_links[1], &prev_views, prev_mask, prev_hole, frame_of(f), w, h, config.label_rule);
        let backward = if config.backward {
            let views = object_views(scene, chosen, &renders[j].objects);
            let (links, target) = (&lf.links, &lf.target);
            merge_link(0, &links[0], &views, &target.mask, &lf.rendered_hole, frame_of(f - 1), w, h, config.label_rule)
        } else {
            LinkFields::default()
        };
        clip.push((forward, backward));
    }
    let clip = later
        .into_iter()
        .zip(clip)
        .map(|(LaterFrame { target: t, .. }, (forward, backward))| ClipFrame {
            image: t.image,
            forward,
            backward,
            mask: t.mask,
            depth: t.shown_depth.into_iter().map(|d| if d.is_finite() && d > 0.0 { d } else { 0.0 }).collect(),
            holes: t.hole,
        })
        .collect();
    (backward, clip)
}

/// image1 (the photo in u8) and depth1 = 1 / disparity, written over `coverage` (the scene
/// render's, no longer needed; a buffer already in memory costs no page faults).
fn image1_depth1(scene: &Scene, coverage: Vec<f32>) -> (Vec<u8>, Vec<f32>) {
    let (w, h) = (scene.mpi.width, scene.mpi.height);
    let mut image1 = crate::buf::zeros::<u8>(scene.image.data.len());
    units_to_u8(&scene.image.data, &mut image1);
    let mut depth1 = coverage;
    if depth1.len() != w * h {
        depth1 = crate::buf::zeros(w * h);
    }
    {
        use rayon::prelude::*;
        depth1.par_chunks_mut(w).zip(scene.disparity.data.par_chunks(w)).for_each(|(out, disp)| {
            for (o, &d) in out.iter_mut().zip(disp) {
                *o = crate::scene::scale::depth_of_disparity(d);
            }
        });
    }
    (image1, depth1)
}

/// `[identity, pose, pose^2, ..., pose^(frames - 1)]`: the constant-velocity trajectory (each
/// frame repeats the drawn frame-1 -> frame-2 motion, `pose^(f+1) = pose o pose^f`).
pub fn trajectory(pose: &Pose, frames: usize) -> Vec<Pose> {
    let mut out = vec![Pose::identity()];
    for f in 1..frames.max(1) {
        out.push(pose.compose(&out[f - 1]));
    }
    out
}

/// What every frame's renders share.
struct FrameCtx<'a> {
    scene: &'a Scene,
    config: &'a SampleConfig,
    windowed: bool,
    occupancy: Option<&'a Occupancy>,
    union: Option<&'a [f32]>,
    chosen: &'a [usize],
}

/// One frame's renders: the scene (whole frame), its scene mask (a full channel, or the
/// coverage with a patch), the objects.
struct FrameRender {
    scene: RenderOutput,
    full_mask: Option<Vec<f32>>,
    mask_patch: Option<(Rect, Vec<f32>)>,
    objects: Vec<WindowRender>,
    render_ms: f64,
    objects_ms: f64,
}

fn object_views<'a>(scene: &'a Scene, chosen: &[usize], renders: &'a [WindowRender]) -> Vec<ObjectView<'a>> {
    chosen
        .iter()
        .zip(renders)
        .enumerate()
        .map(|(slot, (&idx, r))| ObjectView {
            label: (slot + 1) as u8,
            source_mask: &scene.masks.masks[idx].mask,
            render: r,
        })
        .collect()
}

/// Renders one frame: the scene under `cam` (with the source view when `source_view`: frame 2,
/// the forward flow), the scene mask, and each chosen object under its pose, each with its
/// links.
fn render_frame(
    c: &FrameCtx<'_>,
    cam: (Pose, [Option<View>; 2]),
    objects: &[(Pose, [Option<View>; 2])],
    source_view: bool,
) -> Result<FrameRender, SampleError> {
    let (scene, config) = (c.scene, c.config);
    let mpi = &*scene.mpi;
    let (w, h) = (mpi.width, mpi.height);
    let k = scene.intrinsics;
    let render_err = |stage: &'static str| {
        let id = scene.id.clone();
        move |source: RenderError| SampleError::Render { id, stage, source: Box::new(source) }
    };
    let (cam_pose, cam_links) = cam;
    let mut params = RenderParams::new(k, cam_pose);
    params.mode = config.mode;
    params.skip = config.skip;
    params.resample = config.resample;
    params.minify = config.minify;
    params.fields = Fields { target: true, flow: source_view, occlusion: false };
    params.links = cam_links;
    // the window of the union's footprint under the camera (windowed renders with moved objects)
    let mask_win = match (c.union, c.windowed) {
        (Some(u), true) => support_rect(u, w, h).map(|s| scene_mask_window(mpi, &k, &cam_pose, &s)),
        _ => None,
    };
    let t = Instant::now();
    let (mut scene_out, full_mask): (_, Option<Vec<f32>>) = match (c.union, c.windowed, mask_win) {
        (Some(u), false, _) => {
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
                config.minify,
                params.fields,
                cam_links,
            )
            .map_err(render_err("scene"))?;
            let mut out = r.out;
            let mask = std::mem::take(&mut out.extras);
            (out, Some(mask))
        }
        // with moved objects, the scene render carries the union U as its channel over U's
        // footprint (the same values as a render of U alone: the channel's weights are the
        // density's, whatever the colour kernel)
        (Some(u), true, Some(win)) => {
            let within = Channels::BroadcastWithin(u, [win.x0, win.y0, win.x1, win.y1]);
            let r = render_window::<f32>(mpi, &params, c.occupancy, &Rect::full(w, h), within, None);
            (r.map_err(render_err("scene"))?.out, None)
        }
        _ => (render::<f32>(mpi, &params, c.occupancy).map_err(render_err("scene"))?, None),
    };
    let render_ms = ms(t);

    // render(1 - U) = coverage - render(U), and render(U) is 0 outside U's footprint: the scene
    // mask is the coverage except over that window
    let t = Instant::now();
    let mut mask_patch: Option<(Rect, Vec<f32>)> = None;
    if let Some(win) = mask_win {
        let u_render = std::mem::take(&mut scene_out.extras);
        let window = |v: &[f32]| crop(v, w, 1, win.x0, win.y0, win.width(), win.height());
        let patch = window(&scene_out.coverage).iter().zip(window(&u_render)).map(|(c, m)| c - m).collect();
        mask_patch = Some((win, patch));
    }

    // ---- object renders
    let mut renders: Vec<WindowRender> = Vec::with_capacity(c.chosen.len());
    for (&idx, (pose, links)) in c.chosen.iter().zip(objects) {
        let mask = &scene.masks.masks[idx].mask;
        let r = match (c.windowed, support_rect(mask, w, h)) {
            (true, Some(support)) => {
                let win = object_window(mpi, &k, pose, &support);
                render_mask_window(
                    mpi,
                    c.occupancy,
                    &k,
                    pose,
                    &win,
                    mask,
                    config.skip,
                    config.resample,
                    config.minify,
                    source_view,
                    *links,
                )
            }
            _ => render_full_with_mask(
                mpi,
                &k,
                pose,
                mask,
                config.mode,
                config.skip,
                config.resample,
                config.minify,
                params.fields,
                *links,
            ),
        }
        .map_err(render_err("object"))?;
        renders.push(r);
    }
    Ok(FrameRender { scene: scene_out, full_mask, mask_patch, objects: renders, render_ms, objects_ms: ms(t) })
}
