//! The target view's four-lane loop: [`TargetLanes::new`] (the lanes' constants) and
//! [`TargetLanes::four`] (four adjacent pixels of a row in `f32x4` lanes, the scalar band loop's
//! operations in its order).

use super::geometry::TargetGeometry;
use super::plane::{PlaneConst, SurfaceRay, SURFACE_STEPS};
use super::row16::TargetLanes;
use super::sampler::{lanes_of, LaneTaps, PlaneSampler};
use crate::mpi::planes::{DELTA_LAST, DEPTH_MAX};
use crate::render::real::Real;
use crate::render::simd::exp_neg4;
use crate::render::types::RenderStats;
use wide::f32x4;

/// The lanes of the bits of `on` (bit k: lane k) as an `f32x4` mask, computed in registers (an
/// array of flags stored one by one and loaded as a vector stalls the store forwarding: the
/// profile of the `bspline3` target pass put 8% of its samples on that load).
#[inline(always)]
fn lane_mask(on: u32) -> wide::f32x4 {
    use wide::i32x4;
    let bits = i32x4::from([1, 2, 4, 8]);
    wide::bytemuck::cast::<i32x4, wide::f32x4>((i32x4::splat(on as i32) & bits).simd_eq(bits))
}

/// The target view's per-pixel loop for four adjacent pixels of a row at once (`f32`, without
/// links, with no or one extra channel; the scalar band loop (`TargetBand::band`) stays the
/// reference and runs everything else). The ray set-up, the plane intersection, the "leaves the
/// source image" test, the clamps, the depth, the gap to the next plane, the exponential and the
/// compositing run in `f32x4` lanes with the scalar loop's operations in its order; the taps and
/// the colour kernel run per lane through the same [`PlaneSampler`] calls. A plane a lane does
/// not take is masked out, a lane whose transmittance fell below `t_eps` is done (counted as
/// the scalar loop counts its early exit), and the loop ends when all four are done, so every
/// pixel gets the scalar loop's bits (`tests/render/render_window.rs` compares the two).
impl TargetLanes {
    /// The lanes' copy of the scalar loop's constants ([`TargetGeometry`]) in `f32`.
    pub(super) fn new<T: Real>(g: &TargetGeometry<T>, w: usize, h: usize) -> Self {
        let f = |v: &[T]| v.iter().map(|x| x.f32()).collect::<Vec<f32>>();
        let planes = &g.planes;
        TargetLanes {
            rt: g.rt_t.map(|r| r.map(T::f32)),
            ux: f(&g.ux),
            uy: f(&g.uy),
            a: planes.iter().map(|p| p.a.f32()).collect(),
            depth: planes.iter().map(|p| p.depth.f32()).collect(),
            ox: planes.iter().map(|p| p.ox.f32()).collect(),
            oy: planes.iter().map(|p| p.oy.f32()).collect(),
            fxs: g.fxs.f32(),
            fys: g.fys.f32(),
            lo: g.lo.f32(),
            hix: g.hix.f32(),
            hiy: g.hiy.f32(),
            wm: g.wm.f32(),
            hm: g.hm.f32(),
            t_eps: g.t_eps.f32(),
            w,
            h,
        }
    }

    /// Pixels `o .. o + 4` of the band's buffers `b` (image, depth, coverage, the extra channel
    /// when `ex` is given), the window's columns `at[0] .. at[0] + 4` of its row `at[1]` (`px`),
    /// the planes of `fwd` (or `rev` when the rays look back), searched for a true-depth MPI's
    /// texels with `srf` ([`surface4`]): false, with nothing written, when
    /// the four rays do not all meet the planes in the same order (the scalar loop then takes
    /// them). Per plane: the rays' lanes that stop ([`Self::rays`] set them up), the source
    /// pixels and the "leaves the source image" test, the taps and densities
    /// ([`Self::samples`]), the depth and the gap to the next plane ([`Self::gap`]), the
    /// compositing ([`Sums4::add`]); then the writes ([`Sums4::write`]).
    #[inline(always)]
    pub(super) fn four<T: Real, S: PlaneSampler<T>>(
        &self,
        sampler: &S,
        ex: Option<&[&[f32]]>,
        ([fwd, rev], srf): ([&[usize]; 2], Surfaced<'_, T>),
        px: Quad,
        b: &mut [&mut [f32]; 10],
        stats: &mut RenderStats,
    ) -> bool {
        let Some(rays) = self.rays(px.at) else {
            return false;
        };
        let sp = f32x4::splat;
        let zero = sp(0.0);
        let (lo, hix, hiy) = (sp(self.lo), sp(self.hix), sp(self.hiy));
        let t_eps = sp(self.t_eps);
        let order = if rays.forward { fwd } else { rev };
        let mut sums = Sums4::new();
        // lanes done (bit k: lane k)
        let mut done = 0u32;
        for (j, &i) in order.iter().enumerate() {
            let g = sp(self.a[i]) * rays.inv_s;
            let front = !g.simd_le(zero);
            // a lane in front of the plane with its transmittance below t_eps stops here
            let stop = (front & sums.tr.simd_lt(t_eps)).to_bitmask() & !done;
            if stop != 0 {
                stats.skipped_early += u64::from(stop.count_ones()) * (order.len() - j) as u64;
                done |= stop;
                if done == 0b1111 {
                    break;
                }
            }
            let qx = sp(self.ox[i]) + sp(self.fxs) * rays.v[0] * g;
            let qy = sp(self.oy[i]) + sp(self.fys) * rays.v[1] * g;
            let lambda = cap4(g * sp(self.depth[i]), sp(DEPTH_MAX as f32));
            // a true-depth MPI: each lane's texel searched as the scalar loop searches it
            let (qx, qy, lambda_z, in_front) = match srf {
                None => (qx, qy, lambda, 0b1111),
                Some((sr, pls)) => surface4(sr, &pls[i], &rays, [qx, qy], front.to_bitmask() & !done),
            };
            let inside = qx.simd_ge(lo) & qx.simd_lt(hix) & qy.simd_ge(lo) & qy.simd_lt(hiy);
            let take = (front & inside).to_bitmask() & in_front & !done;
            if take == 0 {
                continue;
            }
            let smp = self.samples(sampler, i, take, [qx, qy], stats);
            if smp.lt.on == 0 {
                continue;
            }
            let delta = self.gap(i, &rays, lambda);
            sums.add(sampler, ex, i, &smp, [lambda_z, delta]);
        }
        sums.write(px.o, ex.is_some(), b);
        true
    }

    /// The rays of the window's columns `at[0] .. at[0] + 4` of its row `at[1]` in lanes
    /// (direction v = R^T u, |u|, with the scalar loop's `ray_u` operations); `None` unless all
    /// four meet the planes in the same order.
    #[inline(always)]
    fn rays(&self, at: [usize; 2]) -> Option<Rays4> {
        let sp = f32x4::splat;
        let one = sp(1.0);
        let ux: &[f32; 4] = self.ux[at[0]..at[0] + 4].try_into().expect("four columns");
        let (ux, uy) = (f32x4::from(*ux), sp(self.uy[at[1]]));
        let rt = &self.rt;
        let [v0, v1, v2] = [0, 1, 2].map(|i| sp(rt[i][0]) * ux + sp(rt[i][1]) * uy + sp(rt[i][2]));
        let norm_u = (ux * ux + uy * uy + one).sqrt();
        let s = v2.to_array();
        let forward = s[0] > 0.0;
        if !s.iter().all(|&s| s.abs() > 1e-12_f64 as f32 && (s > 0.0) == forward) {
            return None;
        }
        Some(Rays4 { v: [v0, v1], inv_s: one / v2, norm_u, forward })
    }

    /// The taps of plane `i` for the lanes of `take` at the source pixels `q` (inside the
    /// image, clamped onto the edge pixels here), then their densities; the lanes with density
    /// are the taps' `on`.
    #[inline(always)]
    fn samples<T: Real, S: PlaneSampler<T>>(
        &self,
        sampler: &S,
        i: usize,
        take: u32,
        [qx, qy]: [f32x4; 2],
        stats: &mut RenderStats,
    ) -> Samples4<T> {
        let sp = f32x4::splat;
        let zero = sp(0.0);
        let (wm, hm) = (sp(self.wm), sp(self.hm));
        let qx = qx.simd_lt(zero).select(zero, qx.simd_gt(wm).select(wm, qx));
        let qy = qy.simd_lt(zero).select(zero, qy.simd_gt(hm).select(hm, qy));
        // `Tap::new` in lanes: q >= 0, so truncation is floor; at most the last pixel
        let x0 = qx.trunc_int().min(wide::i32x4::splat(self.w as i32 - 1));
        let y0 = qy.trunc_int().min(wide::i32x4::splat(self.h as i32 - 1));
        let f = [qx - x0.round_float(), qy - y0.round_float()];
        let mut lt = LaneTaps {
            x0: x0.to_array(),
            y0: y0.to_array(),
            fx: f[0].to_array(),
            fy: f[1].to_array(),
            texel: [[T::zero(); 4]; 4],
            on: 0,
            w: self.w,
            h: self.h,
        };
        // the densities in lanes, each blended into its lane in registers
        let mut sig = zero;
        for k in lanes_of(take) {
            let texel = sampler.texel(&lt.tap(k), i);
            stats.samples += 1;
            // the scalar loop goes on with this plane unless sigma <= 0
            if !matches!(texel[3].partial_cmp(&T::zero()), Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)) {
                lt.on |= 1 << k;
                sig = lane_mask(1 << k).select(sp(texel[3].f32()), sig);
            }
            lt.texel[k] = texel;
        }
        Samples4 { lt, sig, q: [qx.to_array(), qy.to_array()], f }
    }

    /// The gap along the rays from plane `i` (at depth `lambda`) to the next plane they meet:
    /// the last gap where there is none or the rays meet it behind the camera.
    #[inline(always)]
    fn gap(&self, i: usize, rays: &Rays4, lambda: f32x4) -> f32x4 {
        let sp = f32x4::splat;
        let (depth_max, delta_last) = (sp(DEPTH_MAX as f32), sp(DELTA_LAST as f32));
        let next = if rays.forward { i + 1 } else { i.wrapping_sub(1) };
        match self.a.get(next) {
            Some(&an) => {
                let an = sp(an) * rays.inv_s;
                let d = cap4((cap4(an * sp(self.depth[next]), depth_max) - lambda) * rays.norm_u, delta_last);
                an.simd_gt(sp(0.0)).select(d, delta_last)
            }
            None => delta_last,
        }
    }
}

/// The four pixels of a [`TargetLanes::four`] call: the window's columns `at[0] .. at[0] + 4`
/// of its row `at[1]`, at `o .. o + 4` of the band's buffers.
pub(super) struct Quad {
    pub(super) at: [usize; 2],
    pub(super) o: usize,
}

/// The four rays in lanes: their directions' x and y (v = R^T u), 1 / v_z, |u|, and whether
/// they meet the planes in source order (v_z > 0).
struct Rays4 {
    v: [f32x4; 2],
    inv_s: f32x4,
    norm_u: f32x4,
    forward: bool,
}

/// One plane's samples for the four lanes: the taps with their texels (`lt.on`: the lanes with
/// density), the densities in lanes (0 in the others), the clamped source pixels per lane and
/// the taps' fractions in lanes.
struct Samples4<T> {
    lt: LaneTaps<T>,
    sig: f32x4,
    q: [[f32; 4]; 2],
    f: [f32x4; 2],
}

/// What the four pixels gather over the planes: transmittance, weight and weighted depth in
/// lanes, the colour and the extra channel per lane.
struct Sums4 {
    tr: f32x4,
    sum_w: f32x4,
    sum_z: f32x4,
    rgb: [[f32; 3]; 4],
    acc1: [f32; 4],
}

impl Sums4 {
    #[inline(always)]
    fn new() -> Self {
        let (zero, one) = (f32x4::splat(0.0), f32x4::splat(1.0));
        Sums4 { tr: one, sum_w: zero, sum_z: zero, rgb: [[0.0; 3]; 4], acc1: [0.0; 4] }
    }

    /// Composites plane `i`'s samples `s` of the lanes with density, at depth and gap
    /// `[lambda, delta]`: the exponential and the weights in lanes, the colours (and the extra
    /// channel of `ex`) lane by lane, since they are summed lane by lane.
    #[inline(always)]
    fn add<T: Real, S: PlaneSampler<T>>(
        &mut self,
        sampler: &S,
        ex: Option<&[&[f32]]>,
        i: usize,
        s: &Samples4<T>,
        [lambda, delta]: [f32x4; 2],
    ) {
        let m = lane_mask(s.lt.on);
        let e = exp_neg4(s.sig * delta);
        let wgt = self.tr * (f32x4::splat(1.0) - e);
        self.tr = m.select(self.tr * e, self.tr);
        let wa = wgt.to_array();
        let smp = sampler.colour4(&s.lt, s.q, s.f, i, wa);
        for k in lanes_of(s.lt.on) {
            for (c, s) in self.rgb[k].iter_mut().zip(smp[k]) {
                *c += wa[k] * s;
            }
            if let Some(ex) = ex {
                self.acc1[k] += wa[k] * s.lt.tap(k).sample1(ex[i]).f32();
            }
        }
        self.sum_w = m.select(self.sum_w + wgt, self.sum_w);
        self.sum_z = m.select(self.sum_z + wgt * lambda, self.sum_z);
    }

    /// Writes pixels `o .. o + 4` of the band's buffers `b`: colour, depth (0 without weight),
    /// coverage and, with `ex`, the extra channel.
    #[inline(always)]
    fn write(&self, o: usize, ex: bool, b: &mut [&mut [f32]; 10]) {
        // the scalar loop's T::of(1e-6)
        const EPS: f32 = 1e-6_f64 as f32;
        let [sum_w, sum_z] = [self.sum_w, self.sum_z].map(f32x4::to_array);
        for k in 0..4 {
            let o = o + k;
            b[0][3 * o..3 * o + 3].copy_from_slice(&self.rgb[k]);
            b[1][o] = if sum_w[k] > EPS { sum_z[k] / sum_w[k] } else { 0.0 };
            b[2][o] = sum_w[k];
            if ex {
                b[3][o] = self.acc1[k];
            }
        }
    }
}

/// A true-depth MPI's search and the planes' constants ([`TargetLanes::four`]; `None`: texels on
/// their planes).
pub(super) type Surfaced<'a, T> = Option<(&'a SurfaceRay<'a, T>, &'a [PlaneConst<T>])>;

/// The texels of a true-depth MPI's plane `pl` that the lanes of `lanes` meet, from the plane's
/// points `q`: [`SurfaceRay::search`] in `f32x4` lanes, its operations in its order (the clamp,
/// the tap's pixel and fractions, the four surface reads per lane, [`super::plane::slab_offset`] and the
/// bilinear blend, the ray's point at that disparity; `T` is `f32` wherever the lanes run, so
/// every lane gets the scalar loop's bits, `tests/render/render_window.rs` compares the two): the
/// points, their depths along the rays (the depth sums' `lambda`) and the lanes whose texel is in
/// front of the camera (bit k: lane k; the other lanes keep `q` and are not taken).
#[inline(always)]
fn surface4<T: Real>(
    sr: &SurfaceRay<'_, T>,
    pl: &PlaneConst<T>,
    rays: &Rays4,
    q: [f32x4; 2],
    lanes: u32,
) -> (f32x4, f32x4, f32x4, u32) {
    use wide::i32x4;
    let sp = f32x4::splat;
    let (zero, one, depth_max) = (sp(0.0), sp(1.0), sp(DEPTH_MAX as f32));
    let (disp, lo, hi) = (sp(pl.disp.f32()), sp(pl.lo.f32()), sp(pl.hi.f32()));
    let (lo2, hi2) = (sp(pl.lo.f32() + pl.lo.f32()), sp(pl.hi.f32() + pl.hi.f32()));
    let (wm, hm, k) = (sp(sr.wm.f32()), sp(sr.hm.f32()), sp(sr.k.f32()));
    let [fx, fy] = sr.fs.map(|v| sp(v.f32()));
    let [cx, cy] = sr.cs.map(|v| sp(v.f32()));
    let [ox, oy] = sr.centre.map(|v| sp(v.f32()));
    let (w, h) = (sr.w as i32, sr.h as i32);
    let (wl, hl, ww) = (i32x4::splat(w - 1), i32x4::splat(h - 1), i32x4::splat(w));
    let [v0, v1] = rays.v;
    let inv_s = rays.inv_s;
    // `slab_offset` in lanes
    let offset = |s: f32x4| {
        let o = s - disp;
        (o.simd_ge(lo2) & o.simd_le(hi2)).select(o.max(lo).min(hi), zero)
    };
    let (mut qx, mut qy, mut d) = (q[0], q[1], disp);
    for _ in 0..SURFACE_STEPS {
        // `Tap::new` at the clamped point (q >= 0 there, so truncation is floor)
        let (px, py) = (qx.max(zero).min(wm), qy.max(zero).min(hm));
        let x0 = px.trunc_int().max(i32x4::splat(0)).min(wl);
        let y0 = py.trunc_int().max(i32x4::splat(0)).min(hl);
        let (wx, wy) = (px - x0.round_float(), py - y0.round_float());
        let x1 = (x0 + i32x4::splat(1)).min(wl);
        let (r0, r1) = (y0 * ww, (y0 + i32x4::splat(1)).min(hl) * ww);
        let idx = [r0 + x0, r0 + x1, r1 + x0, r1 + x1].map(i32x4::to_array);
        let at = |c: usize| f32x4::from(idx[c].map(|i| sr.surface[i as usize]));
        let [a00, a10, a01, a11] = [0, 1, 2, 3].map(|c| offset(at(c)));
        let top = a00 + wx * (a10 - a00);
        let bot = a01 + wx * (a11 - a01);
        d = disp + (top + wy * (bot - top));
        // `SurfaceRay::at`
        let g = (one + k * d) * inv_s;
        qx = fx * (ox * d + v0 * g) + cx;
        qy = fy * (oy * d + v1 * g) + cy;
    }
    // `texel_depth`
    let depth = d.simd_gt(zero).select(cap4(one / d, depth_max), depth_max);
    let g = (one + k * d) * inv_s;
    let front = g.simd_gt(zero);
    let in_front = front.to_bitmask() & lanes;
    let keep = lane_mask(lanes);
    let lambda = lane_mask(in_front).select(cap4(g * depth, depth_max), zero);
    (keep.select(qx, q[0]), keep.select(qy, q[1]), lambda, in_front)
}

/// `v`, at most `max` (lane by lane, the scalar loop's `cap`).
#[inline(always)]
fn cap4(v: f32x4, max: f32x4) -> f32x4 {
    v.simd_gt(max).select(max, v)
}
