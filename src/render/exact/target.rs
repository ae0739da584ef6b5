//! The target view: its entry points ([`target_view`], [`target_view_cut`]) and their set-up,
//! once per number of links and colour kernel, before the band loop runs band by band.

use super::geometry::TargetGeometry;
use super::kernel::{DenseColour, HighOrder};
use super::row16::TargetLanes;
use super::sampler::{Bilinear, CutSampler, PlaneSampler};
use super::target_band::{LinkConst, TargetBand, TargetBandJob};
use crate::mpi::bricks::Bricks;
use crate::mpi::Mpi;
use crate::render::band::{for_each_band, mark_valid};
use crate::render::mip::{mip_planes, missing_levels, plane_lods};
use crate::render::occupancy::Occupancy;
use crate::render::real::Real;
use crate::render::resample::{bspline_bricks, Bspline3, Bspline5, Keys, Lanczos3, Omoms3};
use crate::render::store::Rgba;
use crate::render::types::{Channels, DensityCut, Prefilter, RenderOutput, RenderParams, RenderStats, Resample};
use crate::render::window::Rect;

/// What the target view renders: the MPI with the render's parameters, its tile occupancy
/// (`None`: no tile skipping) and the window.
#[derive(Clone, Copy)]
struct Inputs<'a> {
    mpi: &'a Mpi,
    p: &'a RenderParams,
    occ: Option<&'a Occupancy>,
    win: &'a Rect,
}

/// The target view over the (non-empty) window `win`: image, depth, coverage, the extra
/// channels given by `channels` and the links of `p.links` (`out`'s buffers are window-sized,
/// allocated by the caller). The loop is specialised once, here, by the number of links (0, 1
/// or 2): without links it is the loop without any link work.
pub(in crate::render) fn target_view<T: Real>(
    mpi: &Mpi,
    p: &RenderParams,
    occ: Option<&Occupancy>,
    win: &Rect,
    channels: Channels<'_>,
    out: &mut RenderOutput,
) -> RenderStats {
    let inp = Inputs { mpi, p, occ, win };
    let slots: Vec<usize> = (0..2).filter(|&l| p.links[l].is_some()).collect();
    let consts: Vec<LinkConst<T>> = p.links.iter().flatten().map(|v| LinkConst::new(v, p)).collect();
    let mut links = std::mem::take(&mut out.links);
    let ww = win.width();
    let mut fronts: Vec<Vec<f32>> = slots.iter().map(|_| crate::buf::zeros::<f32>(ww * win.height())).collect();
    let stats = {
        let mut bufs: Vec<(&mut [f32], &mut [f32], &mut [f32])> = Vec::new();
        let mut lv = links.iter_mut();
        let mut fv = fronts.iter_mut();
        for _ in &slots {
            // the links of `slots`, in slot order (an unused slot's buffers are empty)
            let l = lv.by_ref().find(|l| !l.flow.is_empty()).expect("a link buffer per used slot");
            let f = fv.next().expect("a front buffer per link");
            bufs.push((&mut l.flow, &mut l.depth, f));
        }
        let mut it = bufs.into_iter();
        match (it.next(), it.next()) {
            (None, _) => target_view_n::<T, 0>(&inp, channels, out, &consts, [empty3(), empty3()]),
            (Some(a), None) => target_view_n::<T, 1>(&inp, channels, out, &consts, [a, empty3()]),
            (Some(a), Some(b)) => target_view_n::<T, 2>(&inp, channels, out, &consts, [a, b]),
        }
    };
    let (w, h) = (mpi.width, mpi.height);
    for (&slot, front) in slots.iter().zip(&mut fronts) {
        // holes (coverage < 1/2) are not valid
        for (f, &c) in front.iter_mut().zip(&out.coverage) {
            if c < 0.5 {
                *f = 0.0;
            }
        }
        links[slot].valid = mark_valid(win, w, h, &links[slot].flow, front);
    }
    out.links = links;
    stats
}

fn empty3<'a>() -> (&'a mut [f32], &'a mut [f32], &'a mut [f32]) {
    (&mut [], &mut [], &mut [])
}

/// [`target_view`] with `NL` links (`consts[..NL]`, their flow, depth and front-fraction buffers
/// in `lb[..NL]`).
fn target_view_n<T: Real, const NL: usize>(
    inp: &Inputs<'_>,
    channels: Channels<'_>,
    out: &mut RenderOutput,
    consts: &[LinkConst<T>],
    lb: [(&mut [f32], &mut [f32], &mut [f32]); 2],
) -> RenderStats {
    let Inputs { mpi, p, .. } = *inp;
    let rgba = Rgba::of(mpi);
    // the bicubic and Lanczos kernels read colour around the density too: dense planes
    let unpacked = matches!(p.resample, Resample::Bicubic | Resample::Lanczos3).then(|| mpi.unpacked());
    fn dense(m: &Mpi) -> DenseColour<'_, 4> {
        DenseColour { src: (0..m.planes()).map(|i| m.plane_rgba(i)).collect(), w: m.width, h: m.height }
    }
    let lods = plane_lods(mpi, p);
    let built = missing_levels(mpi, &lods);
    let levels = built.as_ref().or(mpi.mip.as_deref());
    let mips = levels.map(|l| mip_planes(&lods, l)).unwrap_or_default();
    let mip = mips.as_slice();
    match p.resample {
        Resample::Bilinear => target_view_with::<T, _, NL>(inp, channels, out, consts, lb, &Bilinear { rgba, mip }),
        Resample::Bicubic => {
            let m = unpacked.as_deref().unwrap_or(mpi);
            let s =
                HighOrder::<Keys, 4, _> { rgba: Rgba::of(m), src: &dense(m), kernel: std::marker::PhantomData, mip };
            target_view_with::<T, _, NL>(inp, channels, out, consts, lb, &s)
        }
        Resample::Lanczos3 => {
            let m = unpacked.as_deref().unwrap_or(mpi);
            let s = HighOrder::<Lanczos3, 6, _> {
                rgba: Rgba::of(m),
                src: &dense(m),
                kernel: std::marker::PhantomData,
                mip,
            };
            target_view_with::<T, _, NL>(inp, channels, out, consts, lb, &s)
        }
        Resample::Bspline3 | Resample::Bspline5 | Resample::Omoms3 => {
            let prefilter = p.resample.prefilter().expect("a prefiltered kernel");
            let owned;
            let coef: &Bricks = match &mpi.bspline_rgb {
                Some(c) if c.prefilter == prefilter => &c.coefficients,
                _ => {
                    owned = bspline_bricks(mpi, prefilter, true);
                    &owned
                }
            };
            match prefilter {
                Prefilter::Bspline3 => {
                    let s = HighOrder::<Bspline3, 4, _> { rgba, src: coef, kernel: std::marker::PhantomData, mip };
                    target_view_with::<T, _, NL>(inp, channels, out, consts, lb, &s)
                }
                Prefilter::Omoms3 => {
                    let s = HighOrder::<Omoms3, 4, _> { rgba, src: coef, kernel: std::marker::PhantomData, mip };
                    target_view_with::<T, _, NL>(inp, channels, out, consts, lb, &s)
                }
                Prefilter::Bspline5 => {
                    let s = HighOrder::<Bspline5, 6, _> { rgba, src: coef, kernel: std::marker::PhantomData, mip };
                    target_view_with::<T, _, NL>(inp, channels, out, consts, lb, &s)
                }
            }
        }
    }
}

/// [`target_view_n`] with the plane sampler of the render's kernel: the set-up, then the band
/// loop (`TargetBand::band`) on the dispatched instruction set ([`crate::isa`]).
fn target_view_with<T: Real, S: PlaneSampler<T>, const NL: usize>(
    inp: &Inputs<'_>,
    channels: Channels<'_>,
    out: &mut RenderOutput,
    consts: &[LinkConst<T>],
    lb: [(&mut [f32], &mut [f32], &mut [f32]); 2],
    sampler: &S,
) -> RenderStats {
    let Inputs { mpi, p, occ, win } = *inp;
    let (w, h, n) = (mpi.width, mpi.height, mpi.planes());
    let ww = win.width();
    // the extra channels' source on every plane: the MPI's own, or one mask for all (computed
    // in every tile, or only in the tiles that meet `ex_rect`)
    let (c, ex_planes, ex_rect): (usize, Vec<&[f32]>, _) = match channels {
        Channels::PerPlane => (mpi.extra_channels, (0..n).map(|i| mpi.plane_extras(i)).collect(), None),
        Channels::Broadcast(mask) => (1, vec![mask; n], None),
        Channels::BroadcastWithin(mask, r) => (1, vec![mask; n], Some(r)),
    };
    let geo = TargetGeometry::new(mpi, p, win);
    let g = &geo;
    // four pixels at a time where T is f32, without links and with at most one extra channel
    let surface = mpi.surface.as_deref().map(|s| geo.surface_ray(&s.disparity, w, h));
    let lanes = (T::LANES && NL == 0 && c <= 1).then(|| TargetLanes::new(g, w, h));
    let band = TargetBand::<T, S, NL> {
        geo: &geo,
        sampler,
        occ,
        win,
        consts,
        lanes: lanes.as_ref(),
        ex_planes: &ex_planes,
        surface,
        ex_rect,
        c,
        w,
        h,
    };
    let (image, depth, coverage, extras) = (&mut out.image, &mut out.depth, &mut out.coverage, &mut out.extras);
    let [(f0, d0, r0), (f1, d1, r1)] = lb;
    let ls = |l: usize, k: usize| if l < NL { k } else { 0 };
    // y0 is the band's first row in the window, fy0 in the frame
    let bufs = [image, depth, coverage, extras, f0, d0, r0, f1, d1, r1];
    let strides = [3, 1, 1, c, ls(0, 2), ls(0, 1), ls(0, 1), ls(1, 2), ls(1, 1), ls(1, 1)];
    for_each_band(ww, win.height(), bufs, strides, |y0, rows, b| {
        crate::isa::dispatch(TargetBandJob { band: &band, y0, rows, b })
    })
}

/// The target view of `mpi` with the density cut `cut`, bilinear, without links or extra
/// channels (image, depth and coverage of `out`, window-sized).
pub(in crate::render) fn target_view_cut<T: Real>(
    mpi: &Mpi,
    p: &RenderParams,
    occ: Option<&Occupancy>,
    win: &Rect,
    cut: &DensityCut<'_>,
    out: &mut RenderOutput,
) -> RenderStats {
    let sampler = CutSampler { inner: Bilinear { rgba: Rgba::of(mpi), mip: &[] }, cut };
    let none: [LinkConst<T>; 0] = [];
    let inp = Inputs { mpi, p, occ, win };
    target_view_with::<T, _, 0>(&inp, Channels::Broadcast(cut.mask), out, &none, [empty3(), empty3()], &sampler)
}
