//! The merges of every frame (frame 2 on both sides, later frames on their target side), the
//! background fill from the planes behind the moved objects, the links (backward fields and the
//! clip's forward flows), image1 and depth1.

use crate::geometry::Pose;
use crate::raster::Grid;
use std::borrow::Cow;

use crate::raster::resize::crop;
use crate::render::{Link, Mode, Occupancy, Rect, RenderOutput, WindowRender};
use crate::sample::background::{cut_planes, fill_from_planes, Background, Frame, PlanesBehind};
use crate::sample::config::SampleConfig;
use crate::sample::error::SampleError;
use crate::sample::merge::{
    merge, merge_link, merge_target, units_to_u8, MergeRule, Merged, OtherFrame, SceneTarget, SceneView, TargetFrame,
    TargetSide,
};
use crate::sample::types::{ClipFrame, LinkFields};
use crate::scene::Scene;

use super::frames::{object_views, views_of, FrameCtx, FrameRender};

/// The MPI's planes behind the moved objects, which fill what they can of a frame's holes
/// ([`crate::sample::background`]); nothing unless the configuration asks for it and the scene allows.
pub(super) struct BackgroundFill<'a> {
    scene: &'a Scene,
    config: &'a SampleConfig,
    occupancy: Option<&'a Occupancy>,
    /// the union mask and the cut planes
    cut: Option<(&'a [f32], Vec<u8>)>,
}

impl<'a> BackgroundFill<'a> {
    pub(super) fn new(
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
    fn fill(
        &self,
        pose: Pose,
        at: Rect,
        image: &mut [u8],
        hole: &mut [u8],
        depth: &mut [f32],
    ) -> Result<u64, SampleError> {
        let Some((u, last)) = &self.cut else { return Ok(0) };
        let scene = self.scene;
        let planes = PlanesBehind {
            scene,
            occupancy: self.occupancy,
            skip: self.config.skip,
            union: u,
            last,
            threshold: self.config.mask_threshold,
        };
        fill_from_planes(&planes, Frame { pose, at, image, hole, depth }).map_err(|source| SampleError::Render {
            id: scene.id.clone(),
            stage: "background",
            source: Box::new(source),
        })
    }
}

/// What the links read of frame 2 besides its merged fields.
pub(super) struct Frame2 {
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
/// links read. With a `window` (the crop the sample is cut to), only its holes are holes.
pub(super) fn merge_frame2(
    c: &FrameCtx<'_>,
    mut first: FrameRender,
    fill: &BackgroundFill<'_>,
    cam_traj: &[Pose],
    window: Option<Rect>,
) -> Result<(Merged, Frame2), SampleError> {
    let (scene, config) = (c.scene, c.config);
    // the frame the renders cover: the crop (windowed) or the whole frame
    let at = c.covered();
    let (w, h) = (at.width(), at.height());
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
    // the objects' source masks over the frame the renders cover
    let fw = scene.mpi.width;
    let masks: Vec<Cow<'_, [f32]>> = c
        .chosen
        .iter()
        .map(|&idx| {
            let m = &scene.masks.masks[idx].mask;
            if at.is_full(fw, scene.mpi.height) {
                Cow::Borrowed(m.as_slice())
            } else {
                Cow::Owned(crop(m, fw, 1, at.x0, at.y0, w, h))
            }
        })
        .collect();
    let views1 = views_of(masks.iter().map(|m| &**m), &first.objects);
    let mut merged = merge(view, &views1, config.merge, config.label_rule, config.mask_threshold, config.occlusion);
    drop(views1);
    drop(image);
    drop(coverage);
    if let Some(r) = window.filter(|_| c.window.is_none()) {
        // whole-frame renders for a crop: only the crop's holes are the sample's
        for (y, row) in merged.hole.chunks_mut(w).enumerate() {
            for (x, o) in row.iter_mut().enumerate() {
                if !r.contains(x, y) {
                    *o = 0;
                }
            }
        }
        merged.holes = merged.hole.iter().map(|&o| u64::from(o != 0)).sum();
    }
    let rendered_hole = fill.cut.as_ref().map(|_| merged.hole.clone());
    let filled = fill.fill(cam_traj[1], at, &mut merged.image2, &mut merged.hole, &mut merged.depth2)?;
    merged.holes -= filled;
    let shown: Vec<f32> = if config.frames > 2 {
        merged.depth2.iter().zip(&merged.hole).map(|(&d, &o)| if o != 0 { f32::INFINITY } else { d }).collect()
    } else {
        Vec::new()
    };
    let frame2 = Frame2 { links: scene_links, source_depth, rendered_hole, shown, objects: first.objects };
    Ok((merged, frame2))
}

/// A later frame (3, 4, ...) merged on its target side and filled from the planes, with its
/// scene render's links and its holes as the renders left them (for the links).
pub(super) struct LaterFrame {
    target: TargetSide,
    links: [Link; 2],
    rendered_hole: Vec<u8>,
}

/// The target sides of the frames after frame 2 (`renders`, frame 3 first).
pub(super) fn merge_later_frames(
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
        let scene_target = SceneTarget {
            grid: Grid::new(w, h),
            image: &r.scene.image,
            depth,
            scene_mask: r.full_mask.as_deref().unwrap_or(&r.scene.coverage),
            scene_mask_patch: r.mask_patch.as_ref().map(|(rc, p)| (*rc, p.as_slice())),
        };
        let target = merge_target(scene_target, &views, config.merge, config.mask_threshold);
        let mut target = target;
        let rendered_hole = target.hole.clone();
        let full = Rect::full(c.scene.mpi.width, c.scene.mpi.height);
        let n = fill.fill(cam_traj[j + 2], full, &mut target.image, &mut target.hole, &mut target.shown_depth)?;
        target.holes -= n;
        later.push(LaterFrame { target, links, rendered_hole });
    }
    Ok(later)
}

/// The links: the backward fields of every frame and the forward flows from frame 2 on; returns
/// the pair's backward fields and the clip's later frames.
pub(super) fn merge_links(
    c: &FrameCtx<'_>,
    merged: &Merged,
    frame2: &Frame2,
    renders: &[FrameRender],
    later: Vec<LaterFrame>,
) -> (LinkFields, Vec<ClipFrame>) {
    let (scene, config, chosen) = (c.scene, c.config, c.chosen);
    let grid = Grid::new(scene.mpi.width, scene.mpi.height);
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
        let frame = TargetFrame { grid, labels: &merged.mask2, hole: hole2_for_links };
        merge_link(0, &frame2.links[0], &views1, frame, other, config.label_rule)
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
        let prev = TargetFrame { grid, labels: prev_mask, hole: prev_hole };
        let forward = merge_link(1, &prev_links[1], &prev_views, prev, frame_of(f), config.label_rule);
        let backward = if config.backward {
            let views = object_views(scene, chosen, &renders[j].objects);
            let (links, target) = (&lf.links, &lf.target);
            let frame = TargetFrame { grid, labels: &target.mask, hole: &lf.rendered_hole };
            merge_link(0, &links[0], &views, frame, frame_of(f - 1), config.label_rule)
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
pub(super) fn image1_depth1(scene: &Scene, at: Rect) -> (Vec<u8>, Vec<f32>) {
    let (fw, w, h) = (scene.mpi.width, at.width(), at.height());
    let mut image1 = crate::buf::zeros::<u8>(3 * w * h);
    let mut depth1 = crate::buf::zeros::<f32>(w * h);
    {
        use rayon::prelude::*;
        image1.par_chunks_mut(3 * w).zip(depth1.par_chunks_mut(w)).enumerate().for_each(|(y, (img, dep))| {
            let row = (at.y0 + y) * fw + at.x0;
            units_to_u8(&scene.image.data[3 * row..3 * (row + w)], img);
            if let Some(disp) = scene.disparity.data.get(row..row + w) {
                for (o, &d) in dep.iter_mut().zip(disp) {
                    *o = crate::scene::scale::depth_of_disparity(d);
                }
            }
        });
    }
    (image1, depth1)
}
