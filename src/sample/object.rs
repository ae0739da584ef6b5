//! Independent object motion: which objects move, and rendering an MPI with one mask channel
//! (an object's mask, or the union of the moved objects' masks) cheaply, over a window of the
//! image instead of the whole frame.
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
//! MPI (no copy), only the target pixels of a window that holds that footprint, with the exact
//! renderer's formulas and sampling (rays that leave the frame see nothing, planes in the order
//! the ray meets them, early ray termination, tile skipping with the scene's occupancy). Every
//! value it computes equals the full-frame render's at the same pixel up to f32 rounding; the
//! pixels it leaves out are those where the mask channel is exactly 0, which the merge never
//! reads there (an object is a candidate only where its channel reaches the threshold, and the
//! scene mask is the coverage where the union's channel is 0). So the windowed path changes
//! nothing but the cost (tested against full-frame renders of MPI copies in
//! `tests/sample_merge.rs`):
//!
//! - **Scene mask** (the union `U` of the moved objects' masks, under the camera motion): the
//!   window is [`scene_mask_window`], the target footprint of `U`'s support.
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
use crate::render::{
    render, Fields, Mode, Occupancy, Real, RenderError, RenderOutput, RenderParams, Skip, DELTA_LAST, DEPTH_MAX,
};
use crate::scene::masks::InstanceMasks;

use super::rng::SampleRng;

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

/// A pixel rectangle `[x0, x1) x [y0, y1)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Rect {
    pub x0: usize,
    pub y0: usize,
    pub x1: usize,
    pub y1: usize,
}

impl Rect {
    pub fn full(width: usize, height: usize) -> Self {
        Rect { x0: 0, y0: 0, x1: width, y1: height }
    }

    pub fn width(&self) -> usize {
        self.x1.saturating_sub(self.x0)
    }

    pub fn height(&self) -> usize {
        self.y1.saturating_sub(self.y0)
    }

    pub fn area(&self) -> usize {
        self.width() * self.height()
    }

    pub fn is_empty(&self) -> bool {
        self.area() == 0
    }

    pub fn contains(&self, x: usize, y: usize) -> bool {
        x >= self.x0 && x < self.x1 && y >= self.y0 && y < self.y1
    }

    /// The smallest rectangle holding both (an empty one is ignored).
    pub fn union(&self, o: &Rect) -> Rect {
        if self.is_empty() {
            return *o;
        }
        if o.is_empty() {
            return *self;
        }
        Rect { x0: self.x0.min(o.x0), y0: self.y0.min(o.y0), x1: self.x1.max(o.x1), y1: self.y1.max(o.y1) }
    }

    /// Grown by `m` pixels on every side, clipped to `width` x `height`.
    pub fn grow(&self, m: usize, width: usize, height: usize) -> Rect {
        if self.is_empty() {
            return *self;
        }
        Rect {
            x0: self.x0.saturating_sub(m),
            y0: self.y0.saturating_sub(m),
            x1: (self.x1 + m).min(width),
            y1: (self.y1 + m).min(height),
        }
    }

    /// The pixels of the continuous box `[x0, x1] x [y0, y1]` (rounded outwards), clipped to the
    /// image; `None` for non-finite input.
    fn from_box(b: [f64; 4], width: usize, height: usize) -> Option<Rect> {
        if !b.iter().all(|v| v.is_finite()) {
            return None;
        }
        let (wf, hf) = (width as f64, height as f64);
        let x0 = b[0].floor().clamp(0.0, wf) as usize;
        let y0 = b[1].floor().clamp(0.0, hf) as usize;
        let x1 = (b[2].ceil() + 1.0).clamp(0.0, wf) as usize;
        let y1 = (b[3].ceil() + 1.0).clamp(0.0, hf) as usize;
        if x1 <= x0 || y1 <= y0 {
            return Some(Rect { x0: 0, y0: 0, x1: 0, y1: 0 });
        }
        Some(Rect { x0, y0, x1, y1 })
    }

    fn corners(&self) -> [(f64, f64); 4] {
        let (x0, y0) = (self.x0 as f64, self.y0 as f64);
        let (x1, y1) = ((self.x1 - 1) as f64, (self.y1 - 1) as f64);
        [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
    }
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
    let m = k.matrix() * pose.rotation * k.inverse_matrix();
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

/// The window of the scene-mask render: the target footprint of the union mask's
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
    let mut out = Mpi::new(mpi.width, mpi.height, mpi.disparity.clone(), 1);
    out.rgba.par_chunks_mut(1 << 16).zip(mpi.rgba.par_chunks(1 << 16)).for_each(|(d, s)| d.copy_from_slice(s));
    out.extras.par_chunks_mut(mpi.plane_len()).for_each(|dst| dst.copy_from_slice(mask));
    out.intrinsics = mpi.intrinsics;
    out.pose = mpi.pose;
    out
}

/// A render over a window of the frame: `out`'s per-pixel buffers are `win.width()` x
/// `win.height()`, pixel (x, y) of them is frame pixel (win.x0 + x, win.y0 + y), in the target
/// view as in the source view. `out.extras` (one channel) is the rendered mask channel.
#[derive(Clone, Debug)]
pub struct WindowRender {
    pub win: Rect,
    pub out: RenderOutput,
}

impl WindowRender {
    /// Index into the window's per-pixel buffers of frame pixel (x, y), if inside.
    #[inline]
    pub fn index(&self, x: usize, y: usize) -> Option<usize> {
        self.win.contains(x, y).then(|| (y - self.win.y0) * self.win.width() + (x - self.win.x0))
    }
}

/// The full-frame render of `mpi` with `mask` as its one extra channel, through a full copy
/// ([`mpi_with_mask`]) and [`render`]: the reference's way.
pub fn render_full_with_mask(
    mpi: &Mpi,
    k: &Intrinsics,
    pose: &Pose,
    mask: &[f32],
    mode: Mode,
    skip: Skip,
    fields: Fields,
) -> Result<WindowRender, RenderError> {
    let copy = mpi_with_mask(mpi, mask);
    let mut p = RenderParams::new(*k, *pose);
    p.mode = mode;
    p.skip = skip;
    p.fields = Fields { occlusion: false, ..fields };
    let out = render::<f32>(&copy, &p, None)?;
    Ok(WindowRender { win: Rect::full(mpi.width, mpi.height), out })
}

/// Width of a target tile for plane skipping (its height is [`TILE_ROWS`]), as in the renderer.
const TILE: usize = 16;
const TILE_ROWS: usize = 16;

/// Per-plane constants of the target view (see `render::exact`): `a = 1 + k disp`, the plane's
/// depth, and the source pixel offsets.
struct PlaneConst {
    a: f32,
    depth: f32,
    ox: f32,
    oy: f32,
}

#[inline(always)]
fn cap(v: f32, max: f64) -> f32 {
    if v > max as f32 {
        max as f32
    } else {
        v
    }
}

#[inline(always)]
fn exp_neg(x: f32) -> f32 {
    <f32 as Real>::exp_neg(x)
}

/// Renders, in exact mode and directly from the shared `mpi` (no copy), the target view over
/// `win` (image, depth, coverage and the channel `mask` broadcast on every plane) and, with
/// `source`, the source view (flow, expected target depth, `valid`) of the pixels of `win` where
/// `mask > 0`. The formulas, the sampling (rays that leave the *frame* see nothing), the plane
/// order, early ray termination and tile skipping are those of the exact renderer
/// (`render::exact`), so every value equals the full-frame render's at the same pixel up to f32
/// rounding (tested against [`render_full_with_mask`]); only the pixels outside `win` are not
/// computed. `occupancy` (built with `skip.tile_sigma_eps`) enables tile skipping when
/// `skip.tiles` is set. `pose` is the motion, `k` the intrinsics of source and target.
#[allow(clippy::too_many_arguments)]
pub fn render_mask_window(
    mpi: &Mpi,
    occupancy: Option<&Occupancy>,
    k: &Intrinsics,
    pose: &Pose,
    win: &Rect,
    mask: &[f32],
    skip: Skip,
    source: bool,
) -> Result<WindowRender, RenderError> {
    mpi.validate()?;
    if !k.is_valid() {
        return Err(RenderError::Intrinsics { which: "source", k: *k });
    }
    if !pose.is_finite() {
        return Err(RenderError::Pose);
    }
    let (ww, wh) = (win.width(), win.height());
    let mut out = RenderOutput { width: ww, height: wh, extra_channels: 1, ..Default::default() };
    if win.is_empty() {
        return Ok(WindowRender { win: *win, out });
    }
    let occ = occupancy.filter(|o| skip.tiles && o.sigma_eps == skip.tile_sigma_eps);
    out.image = vec![0.0; ww * wh * 3];
    out.depth = vec![0.0; ww * wh];
    out.coverage = vec![0.0; ww * wh];
    out.extras = vec![0.0; ww * wh];
    target_window(mpi, occ, k, pose, win, mask, skip, &mut out);
    if source {
        out.flow = vec![0.0; ww * wh * 2];
        out.source_depth_in_target = vec![0.0; ww * wh];
        out.valid = vec![0; ww * wh];
        source_window(mpi, k, pose, win, mask, skip, &mut out);
    }
    Ok(WindowRender { win: *win, out })
}

#[allow(clippy::too_many_arguments)]
fn target_window(
    mpi: &Mpi,
    occ: Option<&Occupancy>,
    k: &Intrinsics,
    pose: &Pose,
    win: &Rect,
    mask: &[f32],
    skip: Skip,
    out: &mut RenderOutput,
) {
    let (w, h, n) = (mpi.width, mpi.height, mpi.planes());
    let ww = win.width();
    let rt = pose.rotation.transpose();
    let centre = pose.target_centre_in_source();
    let kk = -centre.z;
    let planes: Vec<PlaneConst> = mpi
        .disparity
        .iter()
        .map(|&disp| PlaneConst {
            a: (1.0 + kk * disp) as f32,
            depth: (1.0 / disp).min(DEPTH_MAX) as f32,
            ox: (k.fx * centre.x * disp + k.cx) as f32,
            oy: (k.fy * centre.y * disp + k.cy) as f32,
        })
        .collect();
    let r = |i: usize| [rt.row(i).x as f32, rt.row(i).y as f32, rt.row(i).z as f32];
    let rt_t = [r(0), r(1), r(2)];
    let (fx, fy) = (k.fx as f32, k.fy as f32);
    let (lo, hix, hiy) = (-0.5f32, w as f32 - 0.5, h as f32 - 0.5);
    let (wm, hm) = ((w - 1) as f32, (h - 1) as f32);
    let t_eps = skip.transmittance_eps;
    let ux: Vec<f32> = (win.x0..win.x1).map(|x| ((x as f64 - k.cx) / k.fx) as f32).collect();
    let ray_u = |ux: f32, uy: f32| -> ([f32; 3], f32) {
        let v = [0, 1, 2].map(|i| rt_t[i][0] * ux + rt_t[i][1] * uy + rt_t[i][2]);
        (v, (ux * ux + uy * uy + 1.0).sqrt())
    };
    let ray = |x: f64, y: f64| ray_u(((x - k.cx) / k.fx) as f32, ((y - k.cy) / k.fy) as f32);
    let source_px = |pl: &PlaneConst, v: &[f32; 3], g: f32| (pl.ox + fx * v[0] * g, pl.oy + fy * v[1] * g);
    let rgba: Vec<&[f32]> = (0..n).map(|i| mpi.plane_rgba(i)).collect();

    let band = TILE_ROWS * ww;
    out.image
        .par_chunks_mut(3 * band)
        .zip(out.depth.par_chunks_mut(band))
        .zip(out.coverage.par_chunks_mut(band))
        .zip(out.extras.par_chunks_mut(band))
        .enumerate()
        .for_each(|(b, (((img, dep), cov), ext))| {
            let y0 = win.y0 + b * TILE_ROWS;
            let rows = dep.len() / ww;
            let mut active = vec![true; n];
            let mut fwd: Vec<usize> = Vec::with_capacity(n);
            let mut rev: Vec<usize> = Vec::with_capacity(n);
            for tx0 in (win.x0..win.x1).step_by(TILE) {
                let tx1 = (tx0 + TILE).min(win.x1) - 1;
                let ty1 = y0 + rows - 1;
                match occ {
                    Some(o) => tile_activity(o, &planes, &ray, &source_px, [tx0, y0, tx1, ty1], &mut active),
                    None => active.iter_mut().for_each(|a| *a = true),
                }
                fwd.clear();
                fwd.extend((0..n).filter(|&i| active[i]));
                rev.clear();
                rev.extend(fwd.iter().rev());
                for ry in 0..rows {
                    let yy = y0 + ry;
                    let uy = ((yy as f64 - k.cy) / k.fy) as f32;
                    for x in tx0..=tx1 {
                        let (v, norm_u) = ray_u(ux[x - win.x0], uy);
                        let s = v[2];
                        let (mut tr, mut sum_w, mut sum_z, mut sum_m) = (1.0f32, 0.0f32, 0.0f32, 0.0f32);
                        let mut rgb = [0.0f32; 3];
                        if s.abs() > 1e-12 {
                            let inv_s = 1.0 / s;
                            let forward = s > 0.0;
                            let order = if forward { &fwd } else { &rev };
                            for &i in order.iter() {
                                let pl = &planes[i];
                                let g = pl.a * inv_s;
                                if g <= 0.0 {
                                    continue;
                                }
                                if tr < t_eps {
                                    break;
                                }
                                let (qx, qy) = source_px(pl, &v, g);
                                if !(qx >= lo && qx < hix && qy >= lo && qy < hiy) {
                                    continue;
                                }
                                let qx = qx.clamp(0.0, wm);
                                let qy = qy.clamp(0.0, hm);
                                let x0 = (qx as usize).min(w - 1);
                                let y0 = (qy as usize).min(h - 1);
                                let (wx, wy) = (qx - x0 as f32, qy - y0 as f32);
                                let x1 = (x0 + 1).min(w - 1);
                                let y1 = (y0 + 1).min(h - 1);
                                let idx = [y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1];
                                let plane = rgba[i];
                                let at = |c: usize| {
                                    let (a, b) = (plane[4 * idx[0] + c], plane[4 * idx[1] + c]);
                                    let (cc, d) = (plane[4 * idx[2] + c], plane[4 * idx[3] + c]);
                                    let top = a + wx * (b - a);
                                    let bot = cc + wx * (d - cc);
                                    top + wy * (bot - top)
                                };
                                let sigma = at(3);
                                if sigma <= 0.0 {
                                    continue;
                                }
                                let lambda = cap(g * pl.depth, DEPTH_MAX);
                                let next = if forward { i + 1 } else { i.wrapping_sub(1) };
                                let delta = match planes.get(next) {
                                    Some(pn) if pn.a * inv_s > 0.0 => {
                                        cap((cap(pn.a * inv_s * pn.depth, DEPTH_MAX) - lambda) * norm_u, DELTA_LAST)
                                    }
                                    _ => DELTA_LAST as f32,
                                };
                                let e = exp_neg(sigma * delta);
                                let wgt = tr * (1.0 - e);
                                tr *= e;
                                for (c, acc) in rgb.iter_mut().enumerate() {
                                    *acc += wgt * at(c);
                                }
                                sum_w += wgt;
                                sum_z += wgt * lambda;
                                let m = {
                                    let top = mask[idx[0]] + wx * (mask[idx[1]] - mask[idx[0]]);
                                    let bot = mask[idx[2]] + wx * (mask[idx[3]] - mask[idx[2]]);
                                    top + wy * (bot - top)
                                };
                                sum_m += wgt * m;
                            }
                        }
                        let o = ry * ww + (x - win.x0);
                        img[3 * o..3 * o + 3].copy_from_slice(&rgb);
                        dep[o] = if sum_w > 1e-6 { sum_z / sum_w } else { 0.0 };
                        cov[o] = sum_w;
                        ext[o] = sum_m;
                    }
                }
            }
        });
}

/// Which planes can contribute inside the target tile (the renderer's rule, see
/// `render::exact::tile_activity`).
fn tile_activity(
    occ: &Occupancy,
    planes: &[PlaneConst],
    ray: &impl Fn(f64, f64) -> ([f32; 3], f32),
    source_px: &impl Fn(&PlaneConst, &[f32; 3], f32) -> (f32, f32),
    [x0, y0, x1, y1]: [usize; 4],
    active: &mut [bool],
) {
    let corners = [(x0, y0), (x1, y0), (x0, y1), (x1, y1)].map(|(x, y)| ray(x as f64, y as f64).0);
    for (i, pl) in planes.iter().enumerate() {
        if !occ.plane_any[i] {
            active[i] = false;
            continue;
        }
        let (mut bx0, mut by0, mut bx1, mut by1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        let mut exact = true;
        for v in &corners {
            if v[2] <= 0.0 {
                exact = false;
                break;
            }
            let g = pl.a / v[2];
            if g <= 0.0 {
                exact = false;
                break;
            }
            let (qx, qy) = source_px(pl, v, g);
            let (qx, qy) = (qx as f64, qy as f64);
            bx0 = bx0.min(qx);
            by0 = by0.min(qy);
            bx1 = bx1.max(qx);
            by1 = by1.max(qy);
        }
        active[i] = !exact
            || ![bx0, bx1, by0, by1].iter().all(|v| v.is_finite())
            || occ.any_in(i, bx0 - 1.0, by0 - 1.0, bx1 + 1.0, by1 + 1.0);
    }
}

/// The source view (the renderer's `exact::source_view`) of the pixels of `win` with `mask > 0`.
fn source_window(mpi: &Mpi, k: &Intrinsics, pose: &Pose, win: &Rect, mask: &[f32], skip: Skip, out: &mut RenderOutput) {
    let (w, h, n) = (mpi.width, mpi.height, mpi.planes());
    let ww = win.width();
    let m = k.matrix() * pose.rotation * k.inverse_matrix();
    let bt = k.matrix() * pose.translation;
    let mr = |i: usize| [m.row(i).x as f32, m.row(i).y as f32, m.row(i).z as f32];
    let m_t = [mr(0), mr(1), mr(2)];
    let b_t = [bt.x as f32, bt.y as f32, bt.z as f32];
    let disp: Vec<f32> = mpi.disparity.iter().map(|&d| d as f32).collect();
    let depth: Vec<f64> = mpi.disparity.iter().map(|&d| (1.0 / d).min(DEPTH_MAX)).collect();
    let depth_t: Vec<f32> = depth.iter().map(|&d| d as f32).collect();
    let gap: Vec<f32> =
        (0..n).map(|i| if i + 1 < n { (depth[i + 1] - depth[i]).min(DELTA_LAST) } else { DELTA_LAST } as f32).collect();
    let t_eps = skip.transmittance_eps;
    let z_min = 1e-9f32;
    let rgba: Vec<&[f32]> = (0..n).map(|i| mpi.plane_rgba(i)).collect();
    out.flow
        .par_chunks_mut(2 * ww)
        .zip(out.source_depth_in_target.par_chunks_mut(ww))
        .zip(out.valid.par_chunks_mut(ww))
        .enumerate()
        .for_each(|(ry, ((fl, zs), va))| {
            let yy = win.y0 + ry;
            let y = yy as f32;
            let uy = ((yy as f64 - k.cy) / k.fy) as f32;
            for x in win.x0..win.x1 {
                let mv = mask[yy * w + x];
                if mv.is_nan() || mv <= 0.0 {
                    continue;
                }
                let xf = x as f32;
                let ux = ((x as f64 - k.cx) / k.fx) as f32;
                let norm_u = (ux * ux + uy * uy + 1.0).sqrt();
                let a = [0, 1, 2].map(|r| m_t[r][0] * xf + m_t[r][1] * y + m_t[r][2]);
                let (mut tr, mut fu, mut fv, mut sw, mut sz, mut sall) =
                    (1.0f32, 0.0f32, 0.0f32, 0.0f32, 0.0f32, 0.0f32);
                let pix = 4 * (yy * w + x) + 3;
                for i in 0..n {
                    if tr < t_eps {
                        break;
                    }
                    let sigma = rgba[i][pix];
                    if sigma <= 0.0 {
                        continue;
                    }
                    let e = exp_neg(sigma * gap[i] * norm_u);
                    let wgt = tr * (1.0 - e);
                    tr *= e;
                    sall += wgt;
                    let hz = a[2] + b_t[2] * disp[i];
                    if hz > z_min * (a[2].abs() + 1.0) {
                        let hx = a[0] + b_t[0] * disp[i];
                        let hy = a[1] + b_t[1] * disp[i];
                        fu += wgt * (hx / hz - xf);
                        fv += wgt * (hy / hz - y);
                        sw += wgt;
                        sz += wgt * cap(hz * depth_t[i], DEPTH_MAX);
                    }
                }
                let o = x - win.x0;
                let (mut f0, mut f1) = (0.0f32, 0.0f32);
                if sw > 1e-6 {
                    f0 = fu / sw;
                    f1 = fv / sw;
                    zs[o] = sz / sw;
                }
                let f0 = if f0.is_finite() { f0 } else { 0.0 };
                let f1 = if f1.is_finite() { f1 } else { 0.0 };
                fl[2 * o] = f0;
                fl[2 * o + 1] = f1;
                let front = if sall > 0.0 { sw / sall } else { 0.0 };
                let (tx, ty) = (xf + f0, y + f1);
                let inside = tx >= 0.0 && tx <= (w - 1) as f32 && ty >= 0.0 && ty <= (h - 1) as f32;
                va[o] = u8::from(inside && front >= 0.5);
            }
        });
}
