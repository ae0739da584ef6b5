//! The target view's band loop ([`TargetBand::band`]): tile by tile the planes that may
//! contribute, then per pixel (sixteen or four at a time in lanes where they can) the plane
//! loop; a band is a job for [`crate::isa::dispatch`] ([`TargetBandJob`]).
//! `TargetBand::band` is about 180 lines on purpose: the compiler must see the band loop whole
//! (the front door gives the measurement).

use super::activity::tile_activity;
use super::geometry::TargetGeometry;
use super::lanes::Quad;
use super::plane::{cap, PlaneConst, SurfaceRay, TILE};
use super::row16::TargetLanes;
use super::sampler::PlaneSampler;
use crate::mpi::planes::{DELTA_LAST, DEPTH_MAX};
use crate::render::occupancy::Occupancy;
use crate::render::real::Real;
use crate::render::tap::Tap;
use crate::render::types::{RenderParams, RenderStats, View};
use crate::render::window::Rect;

/// A link's projection: homogeneous h = m q + b disp for the source pixel q of a plane point
/// (m = K_v R_v K_s^-1, b = K_v t_v; exactly the identity and 0 for [`View::Source`], so the
/// backward flow is q - p without rounding).
pub(super) struct LinkConst<T> {
    m: [[T; 3]; 3],
    b: [T; 3],
}

impl<T: Real> LinkConst<T> {
    pub(super) fn new(view: &View, p: &RenderParams) -> Self {
        match view {
            View::Source => {
                let (o, z) = (T::one(), T::zero());
                Self { m: [[o, z, z], [z, o, z], [z, z, o]], b: [z; 3] }
            }
            View::Pose(pose) => {
                let m = p.k_tgt.matrix() * pose.rotation * p.k_src.inverse_matrix();
                let b = p.k_tgt.matrix() * pose.translation;
                let r = |i: usize| [T::of(m.row(i).x), T::of(m.row(i).y), T::of(m.row(i).z)];
                Self { m: [r(0), r(1), r(2)], b: [T::of(b.x), T::of(b.y), T::of(b.z)] }
            }
        }
    }
}

/// What the target view's band loop reads ([`TargetBand::band`]).
pub(super) struct TargetBand<'a, T, S, const NL: usize> {
    pub(super) geo: &'a TargetGeometry<T>,
    pub(super) sampler: &'a S,
    pub(super) occ: Option<&'a Occupancy>,
    pub(super) win: &'a Rect,
    pub(super) consts: &'a [LinkConst<T>],
    pub(super) lanes: Option<&'a TargetLanes>,
    pub(super) ex_planes: &'a [&'a [f32]],
    /// the search of a true-depth MPI's texels ([`crate::mpi::Surface`]): each plane's texels
    /// at their own disparity
    pub(super) surface: Option<SurfaceRay<'a, T>>,
    /// where the extra channel is needed (`None`: everywhere); tiles that do not meet it leave 0
    pub(super) ex_rect: Option<[usize; 4]>,
    /// extra channels per pixel
    pub(super) c: usize,
    pub(super) w: usize,
    pub(super) h: usize,
}

/// One band of the target view, as a job for [`crate::isa::dispatch`].
pub(super) struct TargetBandJob<'a, 'b, 'c, T, S, const NL: usize> {
    pub(super) band: &'a TargetBand<'a, T, S, NL>,
    pub(super) y0: usize,
    pub(super) rows: usize,
    pub(super) b: &'b mut [&'c mut [f32]; 10],
}

impl<T: Real, S: PlaneSampler<T>, const NL: usize> crate::isa::Wide for TargetBandJob<'_, '_, '_, T, S, NL> {
    type Output = RenderStats;
    #[inline(always)]
    fn run<const LANES: usize>(self) -> RenderStats {
        self.band.band(self.y0, self.rows, self.b, None)
    }
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn run_v4(self, v4: pulp::x86::V4) -> RenderStats {
        self.band.band(self.y0, self.rows, self.b, Some(v4))
    }
}

/// The AVX-512 token where the band runs on that path (the sixteen-lane loop needs it).
#[cfg(target_arch = "x86_64")]
type Token = pulp::x86::V4;
#[cfg(not(target_arch = "x86_64"))]
type Token = std::convert::Infallible;

impl<T: Real, S: PlaneSampler<T>, const NL: usize> TargetBand<'_, T, S, NL> {
    /// The band of `rows` rows from window row `y0`: tile by tile, the planes that may
    /// contribute, then per pixel (four at a time in lanes where they can) the plane loop.
    #[inline(always)]
    fn band(&self, y0: usize, rows: usize, b: &mut [&mut [f32]; 10], v4: Option<Token>) -> RenderStats {
        let TargetBand { geo, sampler, occ, win, consts, lanes, ex_planes, surface, ex_rect, c, w, h } = *self;
        let TargetGeometry { kt, planes, rt_t, fxs, fys, lo, hix, hiy, wm, hm, t_eps, delta_last, ux, uy, .. } = geo;
        let (fxs, fys, lo, hix, hiy, wm, hm, t_eps, delta_last) =
            (*fxs, *fys, *lo, *hix, *hiy, *wm, *hm, *t_eps, *delta_last);
        let (n, ww) = (planes.len(), win.width());
        let ray_u = |ux: T, uy: T| -> ([T; 3], T) {
            let v = [0, 1, 2].map(|i| rt_t[i][0] * ux + rt_t[i][1] * uy + rt_t[i][2]);
            (v, (ux * ux + uy * uy + T::one()).sqrt())
        };
        let ray = |x: f64, y: f64| ray_u(T::of((x - kt.cx) / kt.fx), T::of((y - kt.cy) / kt.fy));
        let source_px = |pl: &PlaneConst<T>, v: &[T; 3], g: T| (pl.ox + fxs * v[0] * g, pl.oy + fys * v[1] * g);
        let z_min = T::of(1e-9);
        let fy0 = win.y0 + y0;
        let mut stats = RenderStats::default();
        let mut active = vec![true; n];
        // planes that may contribute in this tile, in the order a ray with s > 0 (fwd) or
        // s < 0 (rev) meets them
        let mut fwd: Vec<usize> = Vec::with_capacity(n);
        let mut rev: Vec<usize> = Vec::with_capacity(n);
        let mut acc_ex = vec![T::zero(); c];
        let mut ex = vec![T::zero(); c];
        // sixteen pixels at a time on AVX-512 where the planes are blocks it reads
        let blocks16 = v4.zip(lanes).and_then(|_| sampler.blocks16());
        for tx0 in (win.x0..win.x1).step_by(TILE) {
            let tx1 = (tx0 + TILE).min(win.x1) - 1;
            let ty1 = fy0 + rows - 1;
            match occ {
                Some(o) => {
                    tile_activity(o, planes, &ray, &source_px, surface.as_ref(), [tx0, fy0, tx1, ty1], &mut active);
                }
                None => active.iter_mut().for_each(|a| *a = true),
            }
            fwd.clear();
            fwd.extend((0..n).filter(|&i| active[i]));
            rev.clear();
            rev.extend(fwd.iter().rev());
            stats.skipped_tile += ((n - fwd.len()) * rows * (tx1 + 1 - tx0)) as u64;
            // the extra channel in this tile: everywhere, or where the tile meets `ex_rect`
            let ex_here = ex_rect.is_none_or(|[x0, y0, x1, y1]| tx0 < x1 && tx1 >= x0 && fy0 < y1 && fy0 + rows > y0);
            let ex_lanes = (c == 1 && ex_here).then_some(ex_planes);
            // the rows the sixteen-lane loop renders (bit r: row r of the band)
            #[allow(unused_mut)]
            let mut rows16 = 0u32;
            #[cfg(target_arch = "x86_64")]
            if let (Some(v4), Some(l), Some(src)) = (v4, lanes, blocks16.filter(|_| tx1 + 1 - tx0 == TILE)) {
                let out = super::row16::TileOut { b: &mut *b, stats: &mut stats, o: tx0 - win.x0, row_len: ww };
                let srf = surface.as_ref().map(|sr| (sr, planes.as_slice()));
                rows16 = super::row16::rows16(v4, l, (src, srf), ex_lanes, [tx0 - win.x0, y0], rows, [&fwd, &rev], out);
            }
            for ry in (0..rows).filter(|ry| rows16 >> ry & 1 == 0) {
                let uy_y = uy[y0 + ry];
                let mut x = tx0;
                while x <= tx1 {
                    if let Some(l) = lanes.filter(|_| x + 3 <= tx1) {
                        let o = ry * ww + (x - win.x0);
                        let px = Quad { at: [x - win.x0, y0 + ry], o };
                        let srf = surface.as_ref().map(|sr| (sr, planes.as_slice()));
                        if l.four(sampler, ex_lanes, ([&fwd, &rev], srf), px, b, &mut stats) {
                            x += 4;
                            continue;
                        }
                    }
                    let ux_x = ux[x - win.x0];
                    let (v, norm_u) = ray_u(ux_x, uy_y);
                    let s = v[2];
                    let (mut tr, mut sum_w, mut sum_z) = (T::one(), T::zero(), T::zero());
                    let mut rgb = [T::zero(); 3];
                    // one channel (a broadcast mask) in a register, more in acc_ex
                    let mut acc1 = T::zero();
                    acc_ex.iter_mut().for_each(|a| *a = T::zero());
                    // per link: flow u, v, depth and weight of the planes in front of its view
                    let mut lacc = [[T::zero(); 4]; NL];
                    let (px, py) = (T::of(x as f64), T::of((fy0 + ry) as f64));
                    if s.abs() > T::of(1e-12) {
                        let inv_s = T::one() / s;
                        let forward = s > T::zero();
                        let order = if forward { &fwd } else { &rev };
                        for (j, &i) in order.iter().enumerate() {
                            let pl = &planes[i];
                            let g = pl.a * inv_s;
                            if g <= T::zero() {
                                continue; // behind the target camera
                            }
                            if tr < t_eps {
                                stats.skipped_early += (order.len() - j) as u64;
                                break;
                            }
                            let (qx, qy) = source_px(pl, &v, g);
                            // a true-depth texel: where the ray meets the surface within the
                            // plane's slab, by fixed-point steps from the plane's point
                            let (qx, qy, g_t, disp_t, depth_t) = match &surface {
                                None => (qx, qy, g, pl.disp, pl.depth),
                                Some(sr) => {
                                    let ([qx, qy], d, depth, g_t) = sr.search(pl, [v[0], v[1]], inv_s, (qx, qy));
                                    (qx, qy, g_t, d, depth)
                                }
                            };
                            if g_t <= T::zero() {
                                continue; // the texel is behind the target camera
                            }
                            if !(qx >= lo && qx < hix && qy >= lo && qy < hiy) {
                                continue; // the ray leaves the source image on this plane
                            }
                            let q_raw = (qx, qy);
                            // inside [-0.5, W-0.5) x [-0.5, H-0.5): clamp the half-pixel border onto the edge pixels
                            let qx = if qx < T::zero() {
                                T::zero()
                            } else if qx > wm {
                                wm
                            } else {
                                qx
                            };
                            let qy = if qy < T::zero() {
                                T::zero()
                            } else if qy > hm {
                                hm
                            } else {
                                qy
                            };
                            let tap = Tap::new(qx, qy, w, h);
                            let texel = sampler.texel(&tap, i);
                            let sigma = texel[3];
                            stats.samples += 1;
                            if sigma <= T::zero() {
                                continue;
                            }
                            let lambda = cap(g * pl.depth, DEPTH_MAX);
                            let lambda_t = if surface.is_some() { cap(g_t * depth_t, DEPTH_MAX) } else { lambda };
                            // the next plane along the ray (in front of the camera whenever this one is)
                            let next = if forward { i + 1 } else { i.wrapping_sub(1) };
                            let delta = match planes.get(next) {
                                Some(pn) if pn.a * inv_s > T::zero() => {
                                    cap((cap(pn.a * inv_s * pn.depth, DEPTH_MAX) - lambda) * norm_u, DELTA_LAST)
                                }
                                _ => delta_last,
                            };
                            let e = T::exp_neg(sigma * delta);
                            let wgt = tr * (T::one() - e);
                            tr *= e;
                            let smp = sampler.colour(&tap, &texel, qx, qy, i, wgt);
                            for k in 0..3 {
                                rgb[k] += wgt * smp[k];
                            }
                            sum_w += wgt;
                            sum_z += wgt * lambda_t;
                            for (acc, lc) in lacc.iter_mut().zip(consts) {
                                let m = &lc.m;
                                let (qx, qy) = q_raw;
                                let hz = m[2][0] * qx + m[2][1] * qy + m[2][2];
                                let hzb = hz + lc.b[2] * disp_t;
                                if hzb > z_min * (hz.abs() + T::one()) {
                                    let hx = m[0][0] * qx + m[0][1] * qy + m[0][2] + lc.b[0] * disp_t;
                                    let hy = m[1][0] * qx + m[1][1] * qy + m[1][2] + lc.b[1] * disp_t;
                                    acc[0] += wgt * (hx / hzb - px);
                                    acc[1] += wgt * (hy / hzb - py);
                                    acc[2] += wgt * cap(hzb * depth_t, DEPTH_MAX);
                                    acc[3] += wgt;
                                }
                            }
                            if c == 1 && ex_here {
                                acc1 += wgt * tap.sample1(ex_planes[i]);
                            } else if c > 1 {
                                tap.sample_c(ex_planes[i], c, &mut ex);
                                for (a, e) in acc_ex.iter_mut().zip(&ex) {
                                    *a += wgt * *e;
                                }
                            }
                        }
                    }
                    let o = ry * ww + (x - win.x0);
                    for k in 0..3 {
                        b[0][3 * o + k] = rgb[k].f32();
                    }
                    b[1][o] = if sum_w > T::of(1e-6) { (sum_z / sum_w).f32() } else { 0.0 };
                    b[2][o] = sum_w.f32();
                    if c == 1 {
                        b[3][o] = acc1.f32();
                    } else {
                        for k in 0..c {
                            b[3][c * o + k] = acc_ex[k].f32();
                        }
                    }
                    for (l, acc) in lacc.iter().enumerate() {
                        let j = 4 + 3 * l;
                        if acc[3] > T::of(1e-6) {
                            b[j][2 * o] = (acc[0] / acc[3]).f32();
                            b[j][2 * o + 1] = (acc[1] / acc[3]).f32();
                            b[j + 1][o] = (acc[2] / acc[3]).f32();
                        }
                        b[j + 2][o] = if sum_w > T::zero() { (acc[3] / sum_w).f32() } else { 0.0 };
                    }
                    x += 1;
                }
            }
        }
        stats
    }
}
