//! Merging the scene render (camera motion) with the object renders (each object's own motion)
//! into image2, the forward flow, `valid`, `occlusion` and the object label masks, and finding
//! the holes that inpainting fills.
//!
//! # Inputs
//!
//! - The scene render of the whole frame: image (premultiplied by coverage), depth `D_t`,
//!   coverage, flow, `valid` and expected target depth of every source pixel, and the **scene
//!   mask** `s` = the reference's scene mask channel `1 - U` rendered under the camera motion
//!   (`U` = union of the moved objects' source masks; with the depth-aware merge their footprint,
//!   the masks grown past soft edges and fringes, [`super::object::object_footprint`]), i.e. how
//!   much of each target pixel shows background rather than a moved object's original place or
//!   a hole. `M_t = 1 - s` in the
//!   paper's notation. Without objects `s` is the coverage.
//! - Per object `j` (label `j + 1`): its source mask `M_j` and its render under its own motion,
//!   over a window of the frame ([`WindowRender`]): image, depth `D_t^obj`, the rendered mask
//!   channel `m_j` (`M_j` under the object's motion), flow, `valid`, expected target depth.
//!
//! With threshold `tau` (the reference's 0.99), a target pixel is a **candidate** of object `j`
//! when `m_j >= tau`. (As in the reference, the channel is the mask on *every* plane, so the
//! planes behind the object at the object's pixels move with the object: where the object
//! moves away from its place, its render shows those planes, counted as the object.)
//!
//! # [`MergeRule::Reference`] (the public script, for one object; several: see below)
//!
//! - image2 = scene image; where some object is a candidate, that object's image (the
//!   object is always on top); among several candidates the largest `m_j` (ties: lower slot);
//! - holes = `s < tau` and no candidate;
//! - images are converted to u8 before merging ([`unit_to_u8`]), as the reference does.
//!
//! # [`MergeRule::DepthAware`] (the paper's module; the default)
//!
//! Background nearer than a moved object stays in front: object `j` is hidden at a candidate
//! pixel where `M_occ = s' * m_j * [D_t' (1 + tol) < D_t^obj_j] >= 1/2` (`s = 1 - M_t`, `tol` =
//! [`OCCLUSION_TOLERANCE`]; `s'` and `D_t'` are `s` and `D_t` with one-pixel dips filled: a
//! pixel lower in `s` or farther in `D_t` than both its vertical, or both its horizontal,
//! neighbours takes the nearer of the two; so a one-pixel dip of the scene render where a soft
//! layer's two planes part under the camera's motion does not let a hidden object through as a
//! one-pixel line, while edges stay where they are).
//! Among the candidates not hidden, the nearest (`D_t^obj` smallest; ties: lower slot) is
//! drawn.
//!
//! The tolerance is what keeps touching surfaces from striping: a mask that spans many depths
//! (an object with part of the floor it stands on) moves that floor with the object, so the
//! object render and the scene render show the same surface at nearly the same depth, and the
//! paper's exact comparison `D_t < D_t^obj` flips from row to row with the renders' rounding:
//! image2 showed one-pixel rows of the object's render across the scene's ("thin lines";
//! `tests/samples/labels.rs` counts them). Within the tolerance the object is drawn, as
//! where it is nearer, so the decision changes only at a real depth step.
//!
//! **Seams.** A pixel with `s < tau` and no candidate, where some object's `m_j < tau` is not
//! hidden (`D_t (1 + tol) < D_t^obj_j` is false) and `s + m_j >= tau`, is covered by the two
//! renders together: the edge of an object that moved with (or close to) the scene, where the
//! scene's cut-out and the object's matte both fall off over a pixel or two. The larger share
//! shows: object `j` (largest such `m_j`) when `m_j > s`, else the scene. Holes = `s < tau`,
//! nothing drawn and no seam (scene holes include rays that left the source frustum, coverage
//! < tau); before seams, an object moving exactly with the scene left its whole outline, one
//! to three pixels wide, to inpainting.
//!
//! The depth of what image2 shows (the drawn object's `D_t^obj`, else the scene's `D_t`; 0 in
//! holes) is returned as [`Merged::depth2`].
//!
//! # Both rules, source side
//!
//! - flow, `valid` and the expected target depth come from the scene render, except where some
//!   `M_j >= tau` (the source-frame mask, as the reference's `flow[M_src >= 0.99] = object flow`):
//!   there from object `j` (the largest `M_j`, ties: lower slot): an object pixel's `valid`
//!   is the object render's (flow target inside the frame, point in front of the camera).
//! - `mask1` = label `j + 1` where `M_j >= 1/2` (largest `M_j`, ties: lower slot), else 0;
//!   `mask2` = the label of the object drawn at each image2 pixel.
//! - `occlusion` by the [`LabelRule`]. What image2 shows at a pixel: the drawn object's
//!   `D_t^obj` and label, else the scene's `D_t` and label 0, or a hole. Let `z` be a valid
//!   source pixel's expected target depth (the object's where the object owns its flow), `l`
//!   its `mask1` label and `N` the four bilinear neighbours of where it lands (clamped to the
//!   frame, as the renderer's occlusion test).
//!   - [`LabelRule::Honest`] (the default): the pixel is **not** occluded only when image2
//!     really shows it there: no pixel of `N` is a hole (it would show an inpainted guess), and
//!     some pixel of `N` shows label `l` at a depth `d` with `z / d` in
//!     `[1 / (1 + tol), 1 + tol]` (`tol` = [`OCCLUSION_TOLERANCE`]). Every pixel that breaks one of
//!     these laws is occluded: scene self-occlusion, scene points covered by a drawn object or
//!     landing on an object's place, object points hidden by nearer background or another
//!     object, an object's self-occlusion, points whose surface image2 does not show (it shows
//!     something farther), and points that land on or next to a hole. So the label never says
//!     "this surface moved here" where image2 shows another surface or an inpainted smudge
//!     (tested as laws in `tests/samples/labels.rs`).
//!   - [`LabelRule::DepthOnly`] (the renderer's rule, for comparison): occluded when `z` exceeds `d` by more
//!     than `tol` relative at all four pixels of `N` (the renderer's rule applied to the merged
//!     frame); holes never occlude.

//!
//! # Links (backward flow, clip flows), target side
//!
//! [`merge_link`] merges the renders' [`Link`]s (slot `l`, e.g. into the source view: the
//! backward flow) the way image2 was merged: at an image2 pixel that shows object `j`
//! (`mask2 = j + 1`) from object `j`'s render (its inverse motion), at one that shows the scene
//! from the scene render, and at holes nothing (flow 0, not valid). Its occlusion asks the
//! same question as the forward one, of the other frame: with `z` the point's expected depth in
//! the other camera, `l` its `mask2` label and `N` the bilinear neighbours of where it lands,
//! [`LabelRule::Honest`] calls it visible only when no pixel of `N` is a hole of the other
//! frame and some pixel of `N` shows label `l` at a depth within the tolerance of `z`;
//! [`LabelRule::DepthOnly`] calls it occluded when every pixel of `N` is nearer than `z` by more
//! than the tolerance. Into the source view the other frame is image1: its depth is the
//! source view's rendered depth, its labels `mask1`, and it has no holes.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::types::LinkFields;
use crate::raster::grid::{interleaved, pixel_values};
use crate::raster::Grid;
use crate::render::{Link, Rect, WindowRender, OCCLUSION_TOLERANCE};

/// How scene and object renders are merged.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum MergeRule {
    /// The public reference script: object on top, no depth test.
    Reference,
    /// The paper's depth-aware merge: nearer background stays in front, objects by depth.
    #[default]
    DepthAware,
}

impl std::str::FromStr for MergeRule {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "reference" => Ok(MergeRule::Reference),
            "depth-aware" => Ok(MergeRule::DepthAware),
            _ => Err(format!("unknown merge rule `{s}` (expected reference or depth-aware)")),
        }
    }
}

/// Which valid source pixels the merge marks occluded (see the module documentation).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LabelRule {
    /// Visible only where image2 shows the pixel's label at its depth, with no hole next to the
    /// target.
    #[default]
    Honest,
    /// Occluded only when hidden behind by depth (holes never occlude): the renderer's rule applied to the merged frame.
    DepthOnly,
}

impl std::str::FromStr for LabelRule {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "honest" => Ok(LabelRule::Honest),
            "depth-only" => Ok(LabelRule::DepthOnly),
            _ => Err(format!("unknown label rule `{s}` (expected honest or depth-only)")),
        }
    }
}

/// The scene render, full frame (see the module documentation). `depth`, `flow` and `valid` are
/// taken by value: the merge reuses them as buffers of its result (they are the largest arrays
/// of a sample, and fresh memory costs page faults).
#[derive(Clone, Debug)]
pub struct SceneView<'a> {
    pub width: usize,
    pub height: usize,
    /// H x W x 3, premultiplied by coverage.
    pub image: &'a [f32],
    /// `D_t`, H x W.
    pub depth: Vec<f32>,
    /// The scene mask channel `s` (H x W), except inside `scene_mask_patch`'s rectangle, whose
    /// values (row-major over the rectangle) take precedence there.
    pub scene_mask: &'a [f32],
    pub scene_mask_patch: Option<(Rect, &'a [f32])>,
    /// H x W x 2.
    pub flow: Vec<f32>,
    pub valid: Vec<u8>,
    /// The expected target depth of every source pixel (H x W); reused as
    /// [`Merged::target_depth`].
    pub source_depth: Vec<f32>,
}

/// One moved object (see the module documentation).
#[derive(Clone, Copy, Debug)]
pub struct ObjectView<'a> {
    /// The value in mask1 / mask2.
    pub label: u8,
    /// `M_j`, H x W, in the source frame.
    pub source_mask: &'a [f32],
    /// Its render under its motion; the window's extra channel 0 is `m_j`.
    pub render: &'a WindowRender,
}

/// The merged sample before inpainting.
#[derive(Clone, Debug, PartialEq)]
pub struct Merged {
    /// H x W x 3, holes not yet filled.
    pub image2: Vec<u8>,
    pub flow: Vec<f32>,
    pub valid: Vec<u8>,
    pub occlusion: Vec<u8>,
    pub mask1: Vec<u8>,
    pub mask2: Vec<u8>,
    /// 1 = to be inpainted.
    pub hole: Vec<u8>,
    /// Number of hole pixels.
    pub holes: u64,
    /// H x W, the depth (z in the target camera) of what image2 shows: the drawn object's, else
    /// the scene's; 0 in holes and where it is not a positive finite number.
    pub depth2: Vec<f32>,
    /// H x W, the expected target depth of each source pixel as the occlusion test used it (the
    /// owning object's where an object owns the flow, else the scene's); 0 where not a positive
    /// finite number.
    pub target_depth: Vec<f32>,
}

/// `floor(255 v + 1/2)` with `v` clamped to [0, 1], NaN to 0 (round half up; the same as
/// `io::image::rgb_to_u8` except for values within f32 rounding of a half level, and without a
/// libm call on baseline x86-64).
#[inline(always)]
pub fn unit_to_u8(v: f32) -> u8 {
    // `as` truncates (the value is >= 0.5 here) and maps NaN to 0
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

/// [`unit_to_u8`] of every value of `src` into `dst` (of the same length), on the chosen vector
/// path ([`crate::isa`]): blocks of the path's lanes, each value by [`unit_to_u8`]'s own
/// operations, which the compiler vectorises for the path, so the same bytes on every path
/// (tested against the scalar function).
pub fn units_to_u8(src: &[f32], dst: &mut [u8]) {
    assert_eq!(src.len(), dst.len());
    crate::isa::dispatch(ToU8 { src, dst });
}

/// [`units_to_u8`] as a job for [`crate::isa::dispatch`].
struct ToU8<'a> {
    src: &'a [f32],
    dst: &'a mut [u8],
}

impl crate::isa::Wide for ToU8<'_> {
    type Output = ();
    #[inline(always)]
    fn run<const LANES: usize>(self) {
        // fixed-size blocks are what the compiler vectorises: a plain loop over the whole slices
        // made the merge stage 6.4 ms instead of 3.9 (`bench sample`, no object)
        let mut s = self.src.chunks_exact(LANES);
        let mut d = self.dst.chunks_exact_mut(LANES);
        for (s, d) in (&mut s).zip(&mut d) {
            for (d, &v) in d.iter_mut().zip(s) {
                *d = unit_to_u8(v);
            }
        }
        for (d, &v) in d.into_remainder().iter_mut().zip(s.remainder()) {
            *d = unit_to_u8(v);
        }
    }
}

/// What one object shows at a frame pixel.
#[derive(Clone, Copy)]
struct Hit {
    slot: usize,
    m: f32,
    depth: f32,
    idx: usize,
}

/// Merges (see the module documentation). `tau` is the mask threshold (0.99 in the reference).
/// Without `with_occlusion` the occlusion mask is left all 0 (nothing else changes).
///
/// # Panics
/// If a buffer's size disagrees with `scene.width` x `scene.height`, or there are more than 255
/// objects.
pub fn merge(
    scene: SceneView<'_>,
    objects: &[ObjectView<'_>],
    rule: MergeRule,
    labels: LabelRule,
    tau: f32,
    with_occlusion: bool,
) -> Merged {
    let (w, h) = (scene.width, scene.height);
    let n = w * h;
    assert!(objects.len() < 256, "at most 255 objects");
    assert!(scene.image.len() == 3 * n && scene.depth.len() == n && scene.scene_mask.len() == n);
    assert!(scene.flow.len() == 2 * n && scene.valid.len() == n && scene.source_depth.len() == n);
    if let Some((r, patch)) = scene.scene_mask_patch {
        assert!(r.x1 <= w && r.y1 <= h && patch.len() == r.area());
    }
    for o in objects {
        assert_eq!(o.source_mask.len(), n);
        assert_eq!(o.render.out.extra_channels, 1);
    }

    let g = Grid::new(w, h);
    let SceneView { image, depth, scene_mask, scene_mask_patch, flow, valid, source_depth, .. } = scene;
    let target = SceneTarget { grid: g, image, depth, scene_mask, scene_mask_patch };
    let TargetSide { image: image2, mask: mask2, shown_depth, hole, holes } = merge_target(target, objects, rule, tau);
    let shown = OtherFrame { depth: &shown_depth, labels: &mask2 };

    // ---- source side: mask1, flow, valid, occlusion
    // the scene's flow and valid are read and then replaced, pixel by pixel
    let (mut flow, mut valid, mut target_depth) = (flow, valid, source_depth);
    let mut occlusion = crate::buf::zeros::<u8>(n);
    let mut mask1 = crate::buf::zeros::<u8>(n);
    flow.par_chunks_mut(2 * w)
        .zip(valid.par_chunks_mut(w))
        .zip(occlusion.par_chunks_mut(w))
        .zip(mask1.par_chunks_mut(w))
        .zip(target_depth.par_chunks_mut(w))
        .enumerate()
        .for_each(|(y, ((((fl, va), oc), m1), zs))| {
            for x in 0..w {
                let i = g.index(x, y);
                let (mut label_m, mut flow_m) = (0.5f32, tau);
                let mut owner: Option<usize> = None;
                for (slot, o) in objects.iter().enumerate() {
                    let m = o.source_mask[i];
                    if m >= label_m && (m > label_m || m1[x] == 0) {
                        label_m = m;
                        m1[x] = o.label;
                    }
                    if m >= flow_m && (m > flow_m || owner.is_none()) {
                        flow_m = m;
                        owner = Some(slot);
                    }
                }
                let (f, v, z) = match owner.and_then(|s| objects[s].render.index(x, y).map(|idx| (s, idx))) {
                    Some((s, idx)) => {
                        let r = &objects[s].render.out;
                        ([r.flow[2 * idx], r.flow[2 * idx + 1]], r.valid[idx], r.source_depth_in_target[idx])
                    }
                    None => ([fl[2 * x], fl[2 * x + 1]], va[x], zs[x]),
                };
                let f = [finite_or_zero(f[0]), finite_or_zero(f[1])];
                fl[2 * x] = f[0];
                fl[2 * x + 1] = f[1];
                va[x] = v;
                zs[x] = if z.is_finite() && z > 0.0 { z } else { 0.0 };
                if v != 0 && with_occlusion {
                    let (tx, ty) = (x as f32 + f[0], y as f32 + f[1]);
                    oc[x] = u8::from(match labels {
                        LabelRule::Honest => !shown_there(shown, g, (tx, ty), z, m1[x]),
                        LabelRule::DepthOnly => hidden(shown.depth, g, (tx, ty), z),
                    });
                }
            }
        });
    // what image2 shows, with holes (inf) and anything not positive and finite as 0
    let mut depth2 = shown_depth;
    depth2.par_chunks_mut(w.max(1)).for_each(|row| {
        for d in row {
            if !(d.is_finite() && *d > 0.0) {
                *d = 0.0;
            }
        }
    });
    Merged { image2, flow, valid, occlusion, mask1, mask2, hole, holes, depth2, target_depth }
}

/// The target side of one frame (see [`merge_target`]).
#[derive(Clone, Debug, PartialEq)]
pub struct TargetSide {
    /// H x W x 3, holes not yet filled.
    pub image: Vec<u8>,
    /// The object labels shown (0 = background).
    pub mask: Vec<u8>,
    /// The depth of what is shown; `f32::INFINITY` at holes.
    pub shown_depth: Vec<f32>,
    /// 1 = hole.
    pub hole: Vec<u8>,
    pub holes: u64,
}

/// What [`merge_target`] reads of the scene render: its target view (the fields of
/// [`SceneView`] of the same names).
pub struct SceneTarget<'a> {
    pub grid: Grid,
    /// H x W x 3, premultiplied by coverage.
    pub image: &'a [f32],
    /// `D_t`, H x W, taken by value and reused as the shown depth.
    pub depth: Vec<f32>,
    /// The scene mask channel `s` (H x W), except inside `scene_mask_patch`'s rectangle.
    pub scene_mask: &'a [f32],
    pub scene_mask_patch: Option<(Rect, &'a [f32])>,
}

/// The target side of [`merge`] for one frame (image, labels, shown depth, holes): the scene
/// render's target view and the objects' renders. [`merge`] is this followed by the source side;
/// the later frames of a clip are this alone.
pub fn merge_target(scene: SceneTarget<'_>, objects: &[ObjectView<'_>], rule: MergeRule, tau: f32) -> TargetSide {
    let SceneTarget { grid: g, image, depth, scene_mask, scene_mask_patch } = scene;
    let (w, n) = (g.w, g.len());
    assert!(image.len() == 3 * n && depth.len() == n && scene_mask.len() == n);
    // ---- target side: image2, mask2, depth of what is shown (inf = hole), holes
    let mut image2 = crate::buf::zeros::<u8>(3 * n);
    let mut mask2 = crate::buf::zeros::<u8>(n);
    // D_t is read and then replaced, pixel by pixel, by the depth of what image2 shows
    let mut shown_depth = depth;
    let mut hole = crate::buf::zeros::<u8>(n);
    let scene_s = |x: usize, y: usize| match scene_mask_patch {
        Some((r, patch)) if r.contains(x, y) => patch[Grid::new(r.width(), r.height()).index(x - r.x0, y - r.y0)],
        _ => scene_mask[g.index(x, y)],
    };
    // the occlusion test's view of the scene (depth-aware rule): scene mask and depth with
    // one-pixel dips filled, so a dip of either (where a soft layer's planes part under the
    // camera's motion) does not let a hidden object through as a one-pixel line
    // (computed at candidate pixels only, from a copy of the scene depth: the rows below are
    // overwritten with what image2 shows as they are merged)
    let scene_depth =
        if rule == MergeRule::DepthAware && !objects.is_empty() { shown_depth.clone() } else { Vec::new() };
    let near = |x: usize, y: usize| dip_filled(g, &scene_depth, &scene_s, x, y);
    let holes: u64 = image2
        .par_chunks_mut(3 * w)
        .zip(mask2.par_chunks_mut(w))
        .zip(shown_depth.par_chunks_mut(w))
        .zip(hole.par_chunks_mut(w))
        .enumerate()
        .map(|(y, (((img, lab), dep), hol))| {
            let mut row_holes = 0u64;
            // the scene's colours, overwritten below where an object is drawn
            units_to_u8(&image[interleaved(g.row(y), 3)], img);
            for x in 0..w {
                let s = scene_s(x, y);
                let (best, seam) = shown_object(objects, rule, tau, (x, y), s, dep[x], &near);
                match best {
                    Some(b) => {
                        let src = &objects[b.slot].render.out.image[pixel_values(b.idx, 3)];
                        for (d, &v) in img[pixel_values(x, 3)].iter_mut().zip(src) {
                            *d = unit_to_u8(v);
                        }
                        lab[x] = objects[b.slot].label;
                        dep[x] = b.depth;
                    }
                    None => {
                        // the row's scene colours are converted before the loop
                        if s < tau && !seam {
                            hol[x] = 1;
                            dep[x] = f32::INFINITY;
                            row_holes += 1;
                        }
                    }
                }
            }
            row_holes
        })
        .sum();

    TargetSide { image: image2, mask: mask2, shown_depth, hole, holes }
}

/// The object pixel (x, y) of the target shows by `rule` (scene mask `s`, scene depth `d_t`,
/// `near`: both with one-pixel dips filled), and whether an object's partial share not hidden
/// makes the pixel a seam.
fn shown_object(
    objects: &[ObjectView<'_>],
    rule: MergeRule,
    tau: f32,
    (x, y): (usize, usize),
    s: f32,
    d_t: f32,
    near: &impl Fn(usize, usize) -> (f32, f32),
) -> (Option<Hit>, bool) {
    let mut filled: Option<(f32, f32)> = None;
    let mut best: Option<Hit> = None;
    // the largest partial share not hidden (depth-aware rule): the seam's other half
    let mut partial: Option<Hit> = None;
    for (slot, o) in objects.iter().enumerate() {
        let Some(idx) = o.render.index(x, y) else { continue };
        let m = o.render.out.extras[idx];
        if m.is_nan() || (m < tau && (rule == MergeRule::Reference || s >= tau || s + m < tau)) {
            continue;
        }
        let depth = o.render.out.depth[idx];
        let hit = Hit { slot, m, depth, idx };
        match rule {
            MergeRule::Reference => {
                if best.is_none_or(|b| m > b.m) {
                    best = Some(hit);
                }
            }
            MergeRule::DepthAware if m < tau => {
                let hidden = d_t * (1.0 + OCCLUSION_TOLERANCE) < depth;
                if !hidden && partial.is_none_or(|p| m > p.m) {
                    partial = Some(hit);
                }
            }
            MergeRule::DepthAware => {
                let hidden = |s: f32, d_t: f32| d_t * (1.0 + OCCLUSION_TOLERANCE) < depth && s * m >= 0.5;
                // filling dips only raises s and lowers D_t: hidden as the pixel is,
                // hidden after filling (so only the others need their neighbours)
                if hidden(s, d_t) {
                    continue; // nearer background stays in front
                }
                let (s_near, d_near) = *filled.get_or_insert_with(|| near(x, y));
                if hidden(s_near, d_near) {
                    continue;
                }
                if best.is_none_or(|b| depth < b.depth) {
                    best = Some(hit);
                }
            }
        }
    }
    // a seam: the scene and an object cover the pixel together; the larger share shows
    let best = best.or_else(|| partial.filter(|p| p.m > s));
    let seam = partial.is_some();
    (best, seam)
}

/// The scene mask `s` and depth `D_t` of pixel (x, y) with one-pixel dips filled: `s` raised
/// to the smaller of its two vertical (or two horizontal) neighbours when both are larger, `D_t`
/// lowered to the larger of its two vertical (or horizontal) neighbours when both are nearer
/// (finite and positive). A dip one pixel wide between two higher neighbours is filled; an edge
/// (a higher neighbour on one side only) is kept, so no occluder grows. Non-finite `s` reads 0,
/// unknown `D_t` infinity.
fn dip_filled(g: Grid, depth: &[f32], s: &impl Fn(usize, usize) -> f32, x: usize, y: usize) -> (f32, f32) {
    let known = |d: f32| d.is_finite() && d > 0.0;
    let (mut sv, mut dv) = (s(x, y), depth[g.index(x, y)]);
    let pairs = [
        (y > 0 && y + 1 < g.h).then(|| ((x, y - 1), (x, y + 1))),
        (x > 0 && x + 1 < g.w).then(|| ((x - 1, y), (x + 1, y))),
    ];
    for ((xa, ya), (xb, yb)) in pairs.into_iter().flatten() {
        let (sa, sb) = (s(xa, ya), s(xb, yb));
        if !sv.is_nan() && sa.min(sb) > sv {
            sv = sa.min(sb);
        }
        let (da, db) = (depth[g.index(xa, ya)], depth[g.index(xb, yb)]);
        if known(da) && known(db) && known(dv) && da.max(db) < dv {
            dv = da.max(db);
        }
    }
    (if sv.is_nan() { 0.0 } else { sv }, if known(dv) { dv } else { f32::INFINITY })
}

#[inline]
fn finite_or_zero(v: f32) -> f32 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

/// The frame indices of the four bilinear neighbours of `(tx, ty)`, clamped to the frame.
#[inline]
fn neighbours(g: Grid, (tx, ty): (f32, f32)) -> [usize; 4] {
    let tx = tx.clamp(0.0, (g.w - 1) as f32);
    let ty = ty.clamp(0.0, (g.h - 1) as f32);
    // in [0, w - 1] x [0, h - 1]: the i32 conversion is exact (and cheaper than usize's)
    let (x0, y0) = (tx as i32 as usize, ty as i32 as usize);
    let (x1, y1) = ((x0 + 1).min(g.w - 1), (y0 + 1).min(g.h - 1));
    [g.index(x0, y0), g.index(x1, y0), g.index(x0, y1), g.index(x1, y1)]
}

/// The renderer's occlusion test against the merged frame's shown depth (inf = hole) at the
/// point `t` a source point of expected depth `z` lands on.
#[inline]
fn hidden(shown: &[f32], g: Grid, t: (f32, f32), z: f32) -> bool {
    neighbours(g, t).iter().all(|&n| {
        let d = shown[n];
        d.is_finite() && z > d * (1.0 + OCCLUSION_TOLERANCE)
    })
}

/// [`LabelRule::Honest`]: `frame` (of size `g`) shows the source point (expected target depth
/// `z`, label `label`) at `t`: no bilinear neighbour is a hole (shown depth inf), and some
/// neighbour shows `label` at a depth within the tolerance of `z`.
#[inline]
fn shown_there(frame: OtherFrame<'_>, g: Grid, t: (f32, f32), z: f32, label: u8) -> bool {
    let nb = neighbours(g, t);
    if nb.iter().any(|&n| frame.depth[n] == f32::INFINITY) {
        return false;
    }
    let tol = 1.0 + OCCLUSION_TOLERANCE;
    nb.iter().any(|&n| {
        let d = frame.depth[n];
        frame.labels[n] == label && d.is_finite() && d > 0.0 && z <= d * tol && d <= z * tol
    })
}

/// The frame a link lands in: what it shows (H x W each).
#[derive(Clone, Copy, Debug)]
pub struct OtherFrame<'a> {
    /// The depth of what it shows (z in its camera); `f32::INFINITY` at holes.
    pub depth: &'a [f32],
    /// Its object labels (0 = background).
    pub labels: &'a [u8],
}

/// The merged frame whose pixels a link follows: its size, object labels and holes (H x W each).
#[derive(Clone, Copy, Debug)]
pub struct TargetFrame<'a> {
    pub grid: Grid,
    /// Its object labels (0 = background; the frame's mask).
    pub labels: &'a [u8],
    /// 1 = hole.
    pub hole: &'a [u8],
}

/// Merges link slot `slot` of the scene render (`scene`, full frame) and of the objects' renders
/// into the target frame `target` (see the module documentation); the occlusion is tested
/// against `other`.
///
/// # Panics
/// If a buffer's size disagrees with the target's grid, or a render lacks the link.
pub fn merge_link(
    slot: usize,
    scene: &Link,
    objects: &[ObjectView<'_>],
    target: TargetFrame<'_>,
    other: OtherFrame<'_>,
    labels: LabelRule,
) -> LinkFields {
    let TargetFrame { grid: g, labels: mask2, hole } = target;
    let (w, n) = (g.w, g.len());
    assert!(scene.flow.len() == 2 * n && scene.depth.len() == n && scene.valid.len() == n);
    assert!(mask2.len() == n && hole.len() == n && other.depth.len() == n && other.labels.len() == n);
    let mut flow = crate::buf::zeros::<f32>(2 * n);
    let mut valid = crate::buf::zeros::<u8>(n);
    let mut occlusion = crate::buf::zeros::<u8>(n);
    flow.par_chunks_mut(2 * w).zip(valid.par_chunks_mut(w)).zip(occlusion.par_chunks_mut(w)).enumerate().for_each(
        |(y, ((fl, va), oc))| {
            for x in 0..w {
                let i = g.index(x, y);
                if hole[i] != 0 {
                    continue;
                }
                let label = mask2[i];
                let src = if label == 0 {
                    Some((scene, i))
                } else {
                    objects.iter().find(|o| o.label == label).and_then(|o| {
                        let link = &o.render.out.links[slot];
                        o.render.index(x, y).filter(|_| !link.valid.is_empty()).map(|idx| (link, idx))
                    })
                };
                let Some((link, j)) = src else { continue };
                let f = [finite_or_zero(link.flow[2 * j]), finite_or_zero(link.flow[2 * j + 1])];
                let v = link.valid[j];
                let z = link.depth[j];
                fl[2 * x] = f[0];
                fl[2 * x + 1] = f[1];
                va[x] = v;
                if v != 0 {
                    let (tx, ty) = (x as f32 + f[0], y as f32 + f[1]);
                    oc[x] = u8::from(match labels {
                        LabelRule::Honest => !shown_there(other, g, (tx, ty), z, label),
                        LabelRule::DepthOnly => hidden(other.depth, g, (tx, ty), z),
                    });
                }
            }
        },
    );
    LinkFields { flow, valid, occlusion }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The vector conversion gives the scalar function's byte for every value: the edges, the
    /// half levels and their f32 neighbours, NaN and the infinities, any length (the tail).
    #[test]
    fn units_to_u8_is_unit_to_u8_byte_for_byte() {
        let mut v =
            vec![f32::NAN, -f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -0.0, 0.0, 1.0, -1e-30, 1.0 + 1e-7, 7.5];
        for k in 0..=255u32 {
            let half = (k as f32 + 0.5) / 255.0;
            v.extend([half, f32::from_bits(half.to_bits() - 1), f32::from_bits(half.to_bits() + 1), k as f32 / 255.0]);
        }
        for len in 0..v.len() {
            let mut out = vec![7u8; len];
            units_to_u8(&v[..len], &mut out);
            let want: Vec<u8> = v[..len].iter().map(|&x| unit_to_u8(x)).collect();
            assert_eq!(out, want, "length {len}");
        }
    }

    proptest! {
        #[test]
        fn units_to_u8_agrees_on_any_bits(bits in proptest::collection::vec(any::<u32>(), 0..64)) {
            let v: Vec<f32> = bits.iter().map(|&b| f32::from_bits(b)).collect();
            let mut out = vec![0u8; v.len()];
            units_to_u8(&v, &mut out);
            let want: Vec<u8> = v.iter().map(|&x| unit_to_u8(x)).collect();
            prop_assert_eq!(out, want);
        }
    }
}
