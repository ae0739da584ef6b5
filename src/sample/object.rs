//! Independent object motion: which objects move, and where to render an MPI with one mask
//! channel (an object's mask, or the union of the moved objects' masks): the windows of the
//! frame that hold the channel's footprint. The rendering itself is the renderer's
//! ([`render_window`] with a broadcast channel); this module owns the object choice, the
//! footprints and windows, and the reference's full-copy construction.
//!
//! # Choosing objects
//!
//! [`choose_objects`] takes the instances [`InstanceMasks::select_objects`] accepts (area at
//! least `min_area_fraction` of the image, not empty), ranked by decreasing score, then area,
//! then id. With [`ObjectChoice::Top`] the first `k` move; with [`ObjectChoice::Random`] (the
//! default, like the reference script, which picks an instance uniformly) `k` distinct ones are
//! drawn uniformly from the `Purpose::ObjectChoice` stream by a partial Fisher-Yates shuffle
//! (`below(n - j)` for draw `j`), then put back in rank order; slot `j` of that order is object
//! label `j + 1` and draws its motion from `Purpose::ObjectMotion(j)`.
//!
//! # Windowed renders (exact mode)
//!
//! A mask channel is the same 2-D mask on every plane. Rendering it the reference's way needs a
//! full copy of the MPI with the channel attached (N x H x W x 5 floats, 196 MB at
//! 640 x 480 x 32) and a full-frame render, while the channel is non-zero only where some plane
//! of the mask's support lands. [`render_mask_window`] renders instead, directly from the shared
//! MPI (no copy), only the target pixels of a window that holds that footprint: it is the exact
//! renderer itself ([`render_window`] with [`Channels::Broadcast`], the scene's occupancy for
//! tile skipping, the non-finite guard), so every value it computes equals the full-frame
//! render's at the same pixel, bit for bit (`tests/render/render_window.rs`); the pixels it leaves out are those where the mask channel is exactly 0, which the merge never
//! reads there (an object is a candidate only where its channel reaches the threshold, and the
//! scene mask is the coverage where the union's channel is 0). So the windowed path changes
//! nothing but the cost (tested against full-frame renders of MPI copies in
//! `tests/samples/sample_merge.rs`):
//!
//! - **Scene mask** (the union `U` of the moved objects' masks, under the camera motion): the
//!   window is [`scene_mask_window`], the target footprint of `U`'s support. The recipe does not
//!   render it apart: the scene's own full-frame render carries `U` as its channel, computed in
//!   the tiles that meet this window ([`crate::render::Channels::BroadcastWithin`]; the same
//!   values, since a channel's weights are the density's whatever the colour kernel), which
//!   saves a second render of the window's image, depth and coverage.
//! - **Object render** (object `j`'s mask under its own motion): [`object_window`], the mask's
//!   support (whose source view gives the object's flow, `valid` and depth) united with its
//!   target footprint.
//!
//! Footprints: for a source rectangle and the planes' disparity range `[far, near]`, the target
//! point `K (R K^-1 p + t disp)` (homogeneous) is affine in `disp`, so the footprint over all
//! planes lies in the convex hull of the 8 images of the rectangle's corners on the nearest and
//! farthest plane, as long as every one of them is in front of the camera; otherwise the
//! window is the whole frame (always correct). Windows are grown by [`WINDOW_PAD`] pixels.
//!
//! The reference mode (border-clamped sampling, the `+1e-6` transmittance) is not reproduced by
//! the windowed renderer; there, and with `windowed = false`, the recipe renders full frames of
//! MPI copies with the mask channel ([`render_full_with_mask`]).

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::geometry::{Intrinsics, Pose};
use crate::mpi::Mpi;
use crate::raster::InstanceMasks;
use crate::render::{
    render, render_window, Channels, Fields, Mode, Occupancy, Rect, RenderError, RenderParams, WindowRender,
};
use crate::rng::SampleRng;

/// Pixels added around every window (bilinear support and rounding).
pub const WINDOW_PAD: usize = 3;

/// How the moving objects are picked among the eligible instances.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ObjectChoice {
    /// `k` distinct eligible instances drawn uniformly (`Purpose::ObjectChoice` stream).
    #[default]
    Random,
    /// The `k` best-ranked (score, then area).
    Top,
}

/// Up to `k` instances of `masks` to move (indices into `masks.masks`), in rank order; see the
/// module documentation. `rng` is read only when there are more eligible instances than `k`.
pub fn choose_objects(
    masks: &InstanceMasks,
    k: usize,
    min_area_fraction: f64,
    choice: ObjectChoice,
    rng: &mut SampleRng,
) -> Vec<usize> {
    if k == 0 {
        return Vec::new();
    }
    let ranked = masks.select_objects(usize::MAX, min_area_fraction);
    if ranked.len() <= k || choice == ObjectChoice::Top {
        return ranked.into_iter().take(k).collect();
    }
    // partial Fisher-Yates over rank positions
    let mut pos: Vec<usize> = (0..ranked.len()).collect();
    for j in 0..k {
        let r = j + rng.below((ranked.len() - j) as u64) as usize;
        pos.swap(j, r);
    }
    let mut picked: Vec<usize> = pos[..k].to_vec();
    picked.sort_unstable();
    picked.into_iter().map(|p| ranked[p]).collect()
}

/// How far past a moved object's mask its footprint in the scene reaches (pixels, chessboard):
/// the soft edge and the fringe the mask misses (mixed pixels, hair) go with the object.
pub const OBJECT_MARGIN: usize = 3;
/// A mask value above this is part of the object's footprint (however uncertain).
pub const FOOTPRINT_EPSILON: f32 = 0.01;

/// The moved objects' footprint in the scene (H x W, 1 or 0): every pixel within
/// [`OBJECT_MARGIN`] of a pixel where some mask exceeds [`FOOTPRINT_EPSILON`]. The scene's
/// render carries it as its mask channel (with the depth-aware merge), so the object's colour and
/// density leave every plane there, its soft edge and fringe included; what the footprint
/// uncovers is a hole (or the planes behind, `background = "planes"`), filled from the
/// background around it.
pub fn object_footprint<'a>(masks: impl IntoIterator<Item = &'a [f32]>, width: usize, height: usize) -> Vec<f32> {
    let mut set = vec![false; width * height];
    for m in masks {
        for (s, &v) in set.iter_mut().zip(m) {
            *s |= v > FOOTPRINT_EPSILON;
        }
    }
    let grown = crate::raster::morph::dilate(width, height, &set, OBJECT_MARGIN);
    grown.into_iter().map(|g| if g { 1.0 } else { 0.0 }).collect()
}

/// The bounding rectangle of the pixels where `mask > 0`, grown by one pixel (the bilinear
/// support of the samples that can read them); `None` when the mask is 0 everywhere.
pub fn support_rect(mask: &[f32], width: usize, height: usize) -> Option<Rect> {
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for y in 0..height {
        let row = &mask[y * width..(y + 1) * width];
        let Some(first) = row.iter().position(|&v| v > 0.0) else { continue };
        let last = row.iter().rposition(|&v| v > 0.0).unwrap_or(first);
        x0 = x0.min(first);
        x1 = x1.max(last + 1);
        y0 = y0.min(y);
        y1 = y + 1;
    }
    (x0 != usize::MAX).then(|| Rect { x0, y0, x1, y1 }.grow(1, width, height))
}

/// The disparities of the nearest and farthest plane.
fn disparity_range(mpi: &Mpi) -> (f64, f64) {
    (mpi.disparity[0], mpi.disparity[mpi.planes() - 1])
}

/// The target pixels where the source pixels of `rect` land on any plane with disparity in
/// `[far, near]` under `pose` (same intrinsics both sides), clipped to the image (possibly
/// empty); `None` when some corner point lies behind or on the target camera's plane (the
/// footprint is then unbounded: use the whole frame).
pub fn target_footprint(
    rect: &Rect,
    k: &Intrinsics,
    pose: &Pose,
    near: f64,
    far: f64,
    w: usize,
    h: usize,
) -> Option<Rect> {
    if rect.is_empty() {
        return Some(*rect);
    }
    let m = crate::geometry::pixel_rotation(k, k, &pose.rotation);
    let b = k.matrix() * pose.translation;
    let mut bx = [f64::MAX, f64::MAX, f64::MIN, f64::MIN];
    for (x, y) in rect.corners() {
        let a = m * glam::DVec3::new(x, y, 1.0);
        for disp in [near, far] {
            let p = a + b * disp;
            if p.z.is_nan() || p.z <= 1e-9 * (a.z.abs() + 1.0) {
                return None;
            }
            let (u, v) = (p.x / p.z, p.y / p.z);
            bx = [bx[0].min(u), bx[1].min(v), bx[2].max(u), bx[3].max(v)];
        }
    }
    Rect::from_box(bx, w, h)
}

/// The window of the scene mask (where the scene render carries the union mask as its channel):
/// the target footprint of the union mask's
/// [`support_rect`] under the camera motion, grown by [`WINDOW_PAD`].
pub fn scene_mask_window(mpi: &Mpi, k: &Intrinsics, pose: &Pose, support: &Rect) -> Rect {
    let (w, h) = (mpi.width, mpi.height);
    let (near, far) = disparity_range(mpi);
    match target_footprint(support, k, pose, near, far, w, h) {
        Some(t) => t.grow(WINDOW_PAD, w, h),
        None => Rect::full(w, h),
    }
}

/// The window of an object render: the mask's support and its target footprint under the
/// object's motion, grown by [`WINDOW_PAD`].
pub fn object_window(mpi: &Mpi, k: &Intrinsics, pose: &Pose, support: &Rect) -> Rect {
    let (w, h) = (mpi.width, mpi.height);
    let (near, far) = disparity_range(mpi);
    match target_footprint(support, k, pose, near, far, w, h) {
        Some(t) => support.union(&t).grow(WINDOW_PAD, w, h),
        None => Rect::full(w, h),
    }
}

/// A full copy of `mpi` with one extra channel holding `mask` (H x W) on every plane: the
/// reference's construction, used in the reference mode and with `windowed = false`.
pub fn mpi_with_mask(mpi: &Mpi, mask: &[f32]) -> Mpi {
    let mut out = Mpi { rgba: Vec::new(), extras: Vec::new(), extra_channels: 1, ..mpi.clone_without_planes() };
    if !mpi.is_packed() {
        out.rgba = crate::buf::zeros(mpi.rgba.len());
        out.rgba.par_chunks_mut(1 << 16).zip(mpi.rgba.par_chunks(1 << 16)).for_each(|(d, s)| d.copy_from_slice(s));
    }
    out.extras = crate::buf::zeros(mpi.plane_len() * mpi.planes());
    out.extras.par_chunks_mut(mpi.plane_len()).for_each(|dst| dst.copy_from_slice(mask));
    out
}

/// The full-frame render of `mpi` with `mask` as its one extra channel, through a full copy
/// ([`mpi_with_mask`]) and [`render`]: the reference's way. `params` gives the camera (one
/// intrinsics for source and target), the motion, the mode, work skipping, colour kernel,
/// minification, fields (no occlusion field) and links.
pub fn render_full_with_mask(mpi: &Mpi, params: &RenderParams, mask: &[f32]) -> Result<WindowRender, RenderError> {
    let copy = mpi_with_mask(mpi, mask);
    let p = RenderParams { fields: Fields { occlusion: false, ..params.fields }, ..*params };
    let out = render::<f32>(&copy, &p, None)?;
    Ok(WindowRender { win: Rect::full(mpi.width, mpi.height), out })
}

/// Renders, in exact mode and directly from the shared `mpi` (no copy), the target view over
/// `win` (image, depth, coverage and the channel `mask` broadcast on every plane) and, with
/// `params.fields.flow`, the source view (flow, expected target depth, `valid`) of the pixels of `win` where
/// `mask > 0`: [`render_window`] with [`Channels::Broadcast`], so every value equals the
/// full-frame render's at the same pixel (tested against [`render_full_with_mask`] in
/// `tests/samples/sample_merge.rs`, and the renderer's window laws in `tests/render/render_window.rs`); only
/// the pixels outside `win` are not computed. `occupancy` (built with `skip.tile_sigma_eps`)
/// serves tile skipping when `skip.tiles` is set (the renderer builds one when it is missing).
/// `params` gives the camera (one intrinsics for source and target), the motion, work skipping,
/// colour kernel, alias-free minification ([`crate::render::RenderParams::minify`]) and links;
/// its mode is taken as exact and its fields as the target view with the source view where
/// `params.fields.flow`. No occlusion field.
pub fn render_mask_window(
    mpi: &Mpi,
    occupancy: Option<&Occupancy>,
    params: &RenderParams,
    win: &Rect,
    mask: &[f32],
) -> Result<WindowRender, RenderError> {
    let source = params.fields.flow;
    let fields = Fields { target: true, flow: source, occlusion: false };
    let p = RenderParams { mode: Mode::Exact, fields, ..*params };
    render_window::<f32>(mpi, &p, occupancy, win, Channels::Broadcast(mask), source.then_some(mask))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_footprint_grows_every_uncertain_mask_pixel_by_the_margin() {
        let (w, h) = (16, 12);
        let mut a = vec![0.0f32; w * h];
        let mut b = vec![0.0f32; w * h];
        a[5 * w + 4] = 1.0;
        b[2 * w + 12] = 2.0 * FOOTPRINT_EPSILON; // a faint, uncertain edge
        b[9 * w + 12] = FOOTPRINT_EPSILON; // at the threshold: not the object
        let f = object_footprint([a.as_slice(), b.as_slice()], w, h);
        for y in 0..h {
            for x in 0..w {
                let near_a = x.abs_diff(4) <= OBJECT_MARGIN && y.abs_diff(5) <= OBJECT_MARGIN;
                let near_b = x.abs_diff(12) <= OBJECT_MARGIN && y.abs_diff(2) <= OBJECT_MARGIN;
                assert_eq!(f[y * w + x], if near_a || near_b { 1.0 } else { 0.0 }, "({x}, {y})");
            }
        }
    }
}
