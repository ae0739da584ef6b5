//! The source view: flow, expected target depth and `valid` of every source pixel
//! ([`source_view`]), band by band on the dispatched instruction set ([`SourceBandJob`]).

use super::plane::{cap, TILE};
use super::source_lanes::{texel_disparity, SourceLanes};
use crate::mpi::planes::{plane_depth, plane_gaps, DEPTH_MAX};
use crate::mpi::Mpi;
use crate::render::band::{for_each_band, mark_valid};
use crate::render::occupancy::Occupancy;
use crate::render::real::Real;
use crate::render::store::Rgba;
use crate::render::types::{RenderOutput, RenderParams, RenderStats};
use crate::render::window::Rect;

/// The source view over the (non-empty) window `win`: flow, expected target depth and `valid`
/// (window-sized buffers allocated by the caller). With `flow_where` (H x W) only the pixels
/// where it is > 0 are computed; the others keep flow 0, depth 0 and `valid` 0.
pub(in crate::render) fn source_view<T: Real>(
    mpi: &Mpi,
    p: &RenderParams,
    occ: Option<&Occupancy>,
    win: &Rect,
    flow_where: Option<&[f32]>,
    out: &mut RenderOutput,
) {
    let (w, h) = (mpi.width, mpi.height);
    let ww = win.width();
    let (ks, kt) = (p.k_src, p.k_tgt);
    let m = crate::geometry::pixel_rotation(&ks, &kt, &p.pose.rotation);
    let bt = kt.matrix() * p.pose.translation;
    let mr = |i: usize| [T::of(m.row(i).x), T::of(m.row(i).y), T::of(m.row(i).z)];
    let m_t = [mr(0), mr(1), mr(2)];
    let b_t = [T::of(bt.x), T::of(bt.y), T::of(bt.z)];
    let disp: Vec<T> = mpi.disparity.iter().map(|&d| T::of(d)).collect();
    let depth_t: Vec<T> = mpi.disparity.iter().map(|&d| T::of(plane_depth(d))).collect();
    // gap to the next plane along a source ray of unit-z direction, before the |u| factor
    let gap: Vec<T> = plane_gaps(&mpi.disparity).into_iter().map(T::of).collect();
    let t_eps = T::of32(p.skip.transmittance_eps);
    let rgba = Rgba::of(mpi);
    let mut flow = std::mem::take(&mut out.flow);
    let mut zexp = std::mem::take(&mut out.source_depth_in_target);
    let mut front = crate::buf::zeros::<f32>(ww * win.height());
    // the source camera's own depth, only when a link needs it (allocated by the caller)
    let mut src_depth = std::mem::take(&mut out.source_depth);
    let want_sd = !src_depth.is_empty();
    // four pixels at a time where T is f32 (the same bits); with `flow_where`, lanes that are
    // not asked for are computed but not written, and groups with none asked for are skipped
    // a true-depth surface: each texel at its own disparity within its plane's slab
    let surface = mpi.surface.as_deref().map(|s| s.disparity.as_slice());
    let slab: Vec<(T, T)> = (0..mpi.planes())
        .map(|i| crate::mpi::Surface::slab(&mpi.disparity, i))
        .map(|(lo, hi)| (T::of(lo), T::of(hi)))
        .collect();
    let lanes = T::LANES.then(|| SourceLanes {
        m: std::array::from_fn(|r| [m.row(r).x as f32, m.row(r).y as f32, m.row(r).z as f32]),
        b: [bt.x as f32, bt.y as f32, bt.z as f32],
        disp: mpi.disparity.iter().map(|&d| d as f32).collect(),
        depth: mpi.disparity.iter().map(|&d| plane_depth(d) as f32).collect(),
        gap: plane_gaps(&mpi.disparity).into_iter().map(|g| g as f32).collect(),
        t_eps: p.skip.transmittance_eps,
        z_min: 1e-9_f64 as f32,
        rgba: rgba.clone(),
        xs: (0..w).map(|x| x as f64 as f32).collect(),
        ux: (0..w).map(|x| ((x as f64 - ks.cx) / ks.fx) as f32).collect(),
        uy: (0..h).map(|y| ((y as f64 - ks.cy) / ks.fy) as f32).collect(),
        want_sd,
        surface,
        slab: slab.iter().map(|&(lo, hi)| (lo.f32(), hi.f32())).collect(),
        w,
    });
    let band = SourceBand {
        win,
        occ,
        flow_where,
        lanes: lanes.as_ref(),
        m_t,
        b_t,
        disp: &disp,
        depth_t: &depth_t,
        surface,
        slab: &slab,
        gap: &gap,
        t_eps,
        rgba: &rgba,
        ks,
        w,
        want_sd,
    };
    let bufs: [&mut [f32]; 4] = [&mut flow, &mut zexp, &mut front, &mut src_depth];
    for_each_band(ww, win.height(), bufs, [2, 1, 1, usize::from(want_sd)], |y0, rows, b| {
        crate::isa::dispatch(SourceBandJob { band: &band, y0, rows, b });
        RenderStats::default()
    });
    out.valid = mark_valid(win, w, h, &flow, &front);
    out.flow = flow;
    out.source_depth_in_target = zexp;
    out.source_depth = src_depth;
}

/// What the source view's band loop reads ([`SourceBand::band`]).
struct SourceBand<'a, T> {
    win: &'a Rect,
    occ: Option<&'a Occupancy>,
    flow_where: Option<&'a [f32]>,
    lanes: Option<&'a SourceLanes<'a>>,
    m_t: [[T; 3]; 3],
    b_t: [T; 3],
    disp: &'a [T],
    depth_t: &'a [T],
    surface: Option<&'a [f32]>,
    slab: &'a [(T, T)],
    gap: &'a [T],
    t_eps: T,
    rgba: &'a Rgba<'a>,
    ks: crate::geometry::Intrinsics,
    w: usize,
    want_sd: bool,
}

/// One band of the source view, as a job for [`crate::isa::dispatch`].
struct SourceBandJob<'a, 'b, 'c, T> {
    band: &'a SourceBand<'a, T>,
    y0: usize,
    rows: usize,
    b: &'b mut [&'c mut [f32]; 4],
}

impl<T: Real> crate::isa::Wide for SourceBandJob<'_, '_, '_, T> {
    type Output = ();
    #[inline(always)]
    fn run<const LANES: usize>(self) {
        self.band.band::<LANES>(self.y0, self.rows, self.b);
    }
}

impl<T: Real> SourceBand<'_, T> {
    /// The band of `rows` rows from window row `y0` (flow, expected target depth, front
    /// fraction, source depth), tile by tile, `L` pixels at a time in lanes where they can (the
    /// path's vector width, [`crate::isa`]), then four.
    #[inline(always)]
    fn band<const L: usize>(&self, y0: usize, rows: usize, b: &mut [&mut [f32]; 4]) {
        let SourceBand {
            win,
            occ,
            flow_where,
            lanes,
            m_t,
            b_t,
            disp,
            depth_t,
            surface,
            slab,
            gap,
            t_eps,
            rgba,
            ks,
            w,
            want_sd,
        } = *self;
        let n = disp.len();
        let ww = win.width();
        let z_min = T::of(1e-9);
        let fy0 = win.y0 + y0;
        let mut active: Vec<usize> = Vec::with_capacity(n);
        for tx0 in (win.x0..win.x1).step_by(TILE) {
            let tx1 = (tx0 + TILE).min(win.x1) - 1;
            active.clear();
            match occ {
                Some(o) => active.extend(
                    (0..n).filter(|&i| o.any_in(i, tx0 as f64, fy0 as f64, tx1 as f64, (fy0 + rows - 1) as f64)),
                ),
                None => active.extend(0..n),
            }
            for ry in 0..rows {
                let yy = fy0 + ry;
                let y = T::of(yy as f64);
                let uy = T::of((yy as f64 - ks.cy) / ks.fy);
                let mut x0 = tx0;
                if let Some(l) = &lanes {
                    // the pixels of `x .. x + N` asked for (None: all), as the scalar loop asks
                    fn wanted<const N: usize>(m: Option<&[f32]>, at: usize) -> Option<[bool; N]> {
                        m.map(|m| std::array::from_fn(|k| m[at + k] > 0.0))
                    }
                    while L > 4 && x0 + L - 1 <= tx1 {
                        let want = wanted::<L>(flow_where, yy * w + x0);
                        if want.is_none_or(|m| m.contains(&true)) {
                            l.wide::<L>(x0, yy, &active, ry * ww + (x0 - win.x0), b, want.as_ref());
                        }
                        x0 += L;
                    }
                    while x0 + 3 <= tx1 {
                        let want = wanted::<4>(flow_where, yy * w + x0);
                        if want.is_none_or(|m| m.contains(&true)) {
                            l.four(x0, yy, &active, ry * ww + (x0 - win.x0), b, want.as_ref());
                        }
                        x0 += 4;
                    }
                }
                for x in x0..=tx1 {
                    if let Some(m) = flow_where {
                        let mv = m[yy * w + x];
                        if mv.is_nan() || mv <= 0.0 {
                            continue;
                        }
                    }
                    let xf = T::of(x as f64);
                    let ux = T::of((x as f64 - ks.cx) / ks.fx);
                    let norm_u = (ux * ux + uy * uy + T::one()).sqrt();
                    let a = [0, 1, 2].map(|r| m_t[r][0] * xf + m_t[r][1] * y + m_t[r][2]);
                    let (mut tr, mut fu, mut fv, mut sw, mut sz, mut sall) =
                        (T::one(), T::zero(), T::zero(), T::zero(), T::zero(), T::zero());
                    let mut sd = T::zero();
                    for &i in &active {
                        if tr < t_eps {
                            break;
                        }
                        let sigma = T::of32(rgba.sigma(i, x, yy));
                        if sigma <= T::zero() {
                            continue;
                        }
                        let e = T::exp_neg(sigma * gap[i] * norm_u);
                        let wgt = tr * (T::one() - e);
                        tr *= e;
                        sall += wgt;
                        // the texel's own disparity and depth (the plane's without a surface)
                        let (di, zi) = match surface {
                            None => (disp[i], depth_t[i]),
                            Some(srf) => texel_disparity(srf[yy * w + x], disp[i], slab[i]),
                        };
                        if want_sd {
                            sd += wgt * zi;
                        }
                        let hz = a[2] + b_t[2] * di;
                        if hz > z_min * (a[2].abs() + T::one()) {
                            let hx = a[0] + b_t[0] * di;
                            let hy = a[1] + b_t[1] * di;
                            fu += wgt * (hx / hz - xf);
                            fv += wgt * (hy / hz - y);
                            sw += wgt;
                            sz += wgt * cap(hz * zi, DEPTH_MAX);
                        }
                    }
                    let o = ry * ww + (x - win.x0);
                    if sw > T::of(1e-6) {
                        b[0][2 * o] = (fu / sw).f32();
                        b[0][2 * o + 1] = (fv / sw).f32();
                        b[1][o] = (sz / sw).f32();
                    }
                    b[2][o] = if sall > T::zero() { (sw / sall).f32() } else { 0.0 };
                    if want_sd && sall > T::of(1e-6) {
                        b[3][o] = (sd / sall).f32();
                    }
                }
            }
        }
    }
}
