//! Every frame's renders: the scene under the camera's trajectory with its scene mask (a full
//! channel, or the coverage with a patch over the moved objects' window), and each moved object
//! under its own; what every frame's renders share, and their timing.

use std::borrow::Cow;
use std::time::Instant;

use crate::geometry::Pose;
use crate::raster::resize::crop;
use crate::render::{
    render, render_window, Channels, Fields, Occupancy, Rect, RenderError, RenderOutput, RenderParams, View,
    WindowRender,
};
use crate::sample::config::SampleConfig;
use crate::sample::error::SampleError;
use crate::sample::merge::ObjectView;
use crate::sample::object::{
    object_footprint, object_window, render_full_with_mask, render_mask_window, scene_mask_window, support_rect,
};
use crate::scene::Scene;

/// Milliseconds since `t`.
pub(crate) fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// The union mask of the moved objects (the scene mask channel is 1 - U); none without objects.
/// With `footprint` (the depth-aware merge) the moved objects' footprint instead
/// ([`object_footprint`]: the masks grown past their soft edges and fringes).
pub(super) fn union_mask<'a>(scene: &'a Scene, chosen: &[usize], footprint: bool) -> Option<Cow<'a, [f32]>> {
    let (w, h) = (scene.mpi.width, scene.mpi.height);
    match chosen {
        [] => None,
        _ if footprint => {
            let masks = chosen.iter().map(|&idx| scene.masks.masks[idx].mask.as_slice());
            Some(Cow::Owned(object_footprint(masks, w, h)))
        }
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
pub(super) fn render_frames(
    c: &FrameCtx<'_>,
    cam_traj: &[Pose],
    poses: &[Pose],
) -> Result<Vec<FrameRender>, SampleError> {
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
pub(super) struct FrameCtx<'a> {
    pub(super) scene: &'a Scene,
    pub(super) config: &'a SampleConfig,
    pub(super) windowed: bool,
    pub(super) occupancy: Option<&'a Occupancy>,
    pub(super) union: Option<&'a [f32]>,
    pub(super) chosen: &'a [usize],
    /// The crop the sample is made for: the renders cover only it (windowed renders of frame 2
    /// without links; None = the whole frame).
    pub(super) window: Option<Rect>,
}

impl FrameCtx<'_> {
    /// The frame's rectangle the renders cover: the crop, or the whole frame.
    pub(super) fn covered(&self) -> Rect {
        let mpi = &*self.scene.mpi;
        self.window.unwrap_or(Rect::full(mpi.width, mpi.height))
    }
}

/// One frame's renders: the scene (whole frame), its scene mask (a full channel, or the
/// coverage with a patch), the objects.
pub(super) struct FrameRender {
    pub(super) scene: RenderOutput,
    pub(super) full_mask: Option<Vec<f32>>,
    pub(super) mask_patch: Option<(Rect, Vec<f32>)>,
    pub(super) objects: Vec<WindowRender>,
    pub(super) render_ms: f64,
    pub(super) objects_ms: f64,
}

pub(super) fn object_views<'a>(scene: &'a Scene, chosen: &[usize], renders: &'a [WindowRender]) -> Vec<ObjectView<'a>> {
    views_of(chosen.iter().map(|&idx| scene.masks.masks[idx].mask.as_slice()), renders)
}

/// The moved objects' views from their source masks (in order, slot 0 first) and renders.
pub(super) fn views_of<'a>(masks: impl Iterator<Item = &'a [f32]>, renders: &'a [WindowRender]) -> Vec<ObjectView<'a>> {
    masks
        .zip(renders)
        .enumerate()
        .map(|(slot, (source_mask, render))| ObjectView { label: (slot + 1) as u8, source_mask, render })
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
    let (mut scene_out, full_mask) = render_scene(c, &params, mask_win)?;
    let render_ms = ms(t);

    // render(1 - U) = coverage - render(U), and render(U) is 0 outside U's footprint: the scene
    // mask is the coverage except over that window (in the coordinates of the frame rendered)
    let t = Instant::now();
    let at = c.covered();
    let mut mask_patch: Option<(Rect, Vec<f32>)> = None;
    if let Some(win) = mask_win.map(|m| m.intersect(&at)).filter(|m| !m.is_empty()).map(|m| m.local_to(&at)) {
        let u_render = std::mem::take(&mut scene_out.extras);
        let window = |v: &[f32]| crop(v, at.width(), 1, win.x0, win.y0, win.width(), win.height());
        let patch = window(&scene_out.coverage).iter().zip(window(&u_render)).map(|(c, m)| c - m).collect();
        mask_patch = Some((win, patch));
    }
    let renders = render_objects(c, objects, &params)?;
    Ok(FrameRender { scene: scene_out, full_mask, mask_patch, objects: renders, render_ms, objects_ms: ms(t) })
}

/// The error of a render of `scene` at `stage`.
fn render_err(scene: &Scene, stage: &'static str) -> impl FnOnce(RenderError) -> SampleError {
    let id = scene.id.clone();
    move |source: RenderError| SampleError::Render { id, stage, source: Box::new(source) }
}

/// The scene render of one frame under `params` (its pose and links): with moved objects, the
/// union's channel over `mask_win` (windowed) or a full copy with the channel 1 - U (the full
/// scene mask, returned beside it); without, the plain render.
fn render_scene(
    c: &FrameCtx<'_>,
    params: &RenderParams,
    mask_win: Option<Rect>,
) -> Result<(RenderOutput, Option<Vec<f32>>), SampleError> {
    let scene = c.scene;
    let mpi = &*scene.mpi;
    Ok(match (c.union, c.windowed, mask_win) {
        (Some(u), false, _) => {
            // the reference's scene render: a full copy with the channel 1 - U
            let inv: Vec<f32> = u.iter().map(|&v| 1.0 - v).collect();
            let r = render_full_with_mask(mpi, params, &inv).map_err(render_err(scene, "scene"))?;
            let mut out = r.out;
            let mask = std::mem::take(&mut out.extras);
            (out, Some(mask))
        }
        // with moved objects, the scene render carries the union U as its channel over U's
        // footprint (the same values as a render of U alone: the channel's weights are the
        // density's, whatever the colour kernel)
        (Some(u), true, Some(win)) => {
            let within = Channels::BroadcastWithin(u, [win.x0, win.y0, win.x1, win.y1]);
            let r = render_window::<f32>(mpi, params, c.occupancy, &c.covered(), within, None);
            (r.map_err(render_err(scene, "scene"))?.out, None)
        }
        (_, true, _) if c.window.is_some() => {
            let r = render_window::<f32>(mpi, params, c.occupancy, &c.covered(), Channels::PerPlane, None);
            (r.map_err(render_err(scene, "scene"))?.out, None)
        }
        _ => (render::<f32>(mpi, params, c.occupancy).map_err(render_err(scene, "scene"))?, None),
    })
}

/// Each chosen object of one frame under its pose, with its links: over its window (windowed)
/// or a full copy with its mask as the channel. `frame` holds what the objects' renders share
/// with the frame's camera render (mode, skipping, colour kernel, minification, fields).
fn render_objects(
    c: &FrameCtx<'_>,
    objects: &[(Pose, [Option<View>; 2])],
    frame: &RenderParams,
) -> Result<Vec<WindowRender>, SampleError> {
    let scene = c.scene;
    let mpi = &*scene.mpi;
    let (w, h) = (mpi.width, mpi.height);
    let k = scene.intrinsics;
    let mut renders: Vec<WindowRender> = Vec::with_capacity(c.chosen.len());
    for (&idx, (pose, links)) in c.chosen.iter().zip(objects) {
        let mask = &scene.masks.masks[idx].mask;
        let params = RenderParams { pose: *pose, links: *links, ..*frame };
        let r = match (c.windowed, support_rect(mask, w, h)) {
            (true, Some(support)) => {
                let at = c.covered();
                let win = object_window(mpi, &k, pose, &support).intersect(&at);
                // the window in the coordinates of the frame rendered (the crop's)
                render_mask_window(mpi, c.occupancy, &params, &win, mask)
                    .map(|r| WindowRender { win: r.win.local_to(&at), out: r.out })
            }
            _ => render_full_with_mask(mpi, &params, mask),
        }
        .map_err(render_err(scene, "object"))?;
        renders.push(r);
    }
    Ok(renders)
}
