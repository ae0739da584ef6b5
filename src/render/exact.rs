//! Exact-mode rendering: every target ray is intersected with the planes analytically.
//!
//! For a target pixel p let u = K_t^-1 p (unit z), v = R^T u (the ray direction in source
//! coordinates), s = v_z, C = -R^T t (the target centre in source coordinates) and k = -C_z.
//! The ray C + lambda v meets plane Z = d_i at lambda_i = (d_i + k) / s, which is also the
//! point's depth in the target camera. With g_i = lambda_i / d_i = (1 + k disp_i) / s the source
//! pixel is q_i = (fx_s (C_x disp_i + v_x g_i) + cx_s, fy_s (C_y disp_i + v_y g_i) + cy_s),
//! finite even for disparity 0. Planes with g_i <= 0 lie behind the target camera and are not
//! seen; planes are composited in increasing lambda (source order when s > 0, reversed when the
//! camera has passed the planes and looks back, s < 0); the gap between consecutive planes along
//! the ray is (lambda_{i+1} - lambda_i) |u|, the last one [`DELTA_LAST`]. A ray that leaves the
//! source image (q outside [-0.5, W-0.5] x [-0.5, H-0.5]) sees nothing on that plane, so holes
//! show as coverage < 1 instead of smeared borders.
//!
//! The source view uses H_i p = K_t R K_s^-1 p + K_t t disp_i (homogeneous): planes whose point
//! is behind the target camera (third coordinate <= 0) carry no flow; flow is the weight-
//! normalised mean over the planes in front.
//!
//! This is the only implementation of these loops (the tile width [`TILE`], the per-plane
//! constants, [`tile_activity`]); [`SourceLanes`] and [`TargetLanes`] run the same loops for
//! four adjacent pixels at once in `f32` lanes, operation for operation, so with the same bits
//! (the scalar loops are their reference and take the rest). Every exact render goes through
//! it: the full frame, and windows of it (`render_window`). Both passes take a
//! window `win` of the frame and write window-sized buffers (pixel (x, y) of them is frame pixel
//! (win.x0 + x, win.y0 + y)); rays, sampling and the "leaves the source image" test always use
//! the whole frame, so a pixel's value does not depend on the window it is rendered in. Tiles
//! start at `win.x0` and bands at `win.y0`; tile skipping only drops planes whose density is
//! at most the occupancy's `sigma_eps` over the tile's footprint, which with `sigma_eps = 0`
//! (the default) contribute nothing, so tile alignment does not change values either. Extra
//! channels are sampled per plane from the MPI or from one H x W mask shared by every plane
//! ([`Channels`]); the source view can be restricted to the pixels where a mask is positive.
//!
//! The band loops run on the vector path chosen at start-up ([`crate::isa`]): each band is a
//! job ([`TargetBandJob`], [`SourceBandJob`]) whose loop is inlined into a function compiled for
//! AVX-512, AVX2 or the SSE2 baseline; the source view then takes 16, 8 or 4 pixels per plane
//! step ([`SourceLanes::wide`], [`SourceLanes::four`]), and on AVX-512 the target view takes a
//! tile row of 16 pixels reading packed planes in registers ([`super::row16`]; four pixels at
//! a time on the other paths and for the other samplers), the same bits on every path.
//!
//! Two things here stay large on purpose. The file (over 1,100 lines) keeps the scalar loops and
//! their lane twins ([`TargetLanes`], [`SourceLanes`]) together with the per-plane constants
//! they share, since each twin must follow its loop operation for operation. And
//! `TargetBand::band` (about 190 lines) is the target view's band loop, which the compiler must
//! see whole: its set-up is outside it ([`TargetGeometry`], [`TargetLanes::new`]), but the
//! tile's planes, the edge clamp, the link sums or the pixel's writes as inlined functions of
//! their own cost 1.9% more instructions in the band loop of the bilinear target pass
//! (cachegrind, `mpiflow bench render --threads 1 --pass target --resample bilinear`).

use super::band::{for_each_band, mark_valid};
use super::mip::{mip_planes, missing_levels, plane_lods, MipPlane};
use super::occupancy::Occupancy;
use super::real::Real;
use super::resample::{
    bspline_bricks, sample_rgb_bricks_weighted, sample_rgb_weighted, Bspline3, Bspline5, Kernel, Keys, Lanczos3,
};
use super::row16::{Blocks16, TargetLanes, KERNEL_MIN_WEIGHT};
use super::store::Rgba;
use super::tap::Tap;
use super::types::{Channels, DensityCut, RenderOutput, RenderParams, RenderStats, Resample, View};
use super::window::Rect;
use crate::mpi::bricks::Bricks;
use crate::mpi::planes::{plane_depth, plane_gaps, DELTA_LAST, DEPTH_MAX};
use crate::mpi::Mpi;

/// Width of a target tile for plane skipping (its height is the band height).
const TILE: usize = 16;

struct PlaneConst<T> {
    /// 1 + k disp
    a: T,
    depth: T,
    disp: T,
    ox: T,
    oy: T,
}

#[inline(always)]
fn cap<T: Real>(v: T, max: f64) -> T {
    if v > T::of(max) {
        T::of(max)
    } else {
        v
    }
}

/// Plane samples of the target view: the bilinear density of plane `i` at a tap (always
/// bilinear; with the bilinear colour where a sampler gets it for free) and its colour by the
/// render's [`Resample`] kernel, asked for only where the density is positive.
trait PlaneSampler<T: Real>: Sync {
    /// The bilinear density (`[3]`) of plane `i` at a tap; `[0..3]` is its bilinear colour for
    /// [`Bilinear`] (all four channels in one vector operation, [`Real::lerp4`]) and unused by
    /// the others.
    fn texel(&self, tap: &Tap<T>, i: usize) -> [T; 4];
    /// The colour at `q` of a sample that gets composite weight `wgt` (`texel`: the sample's
    /// [`Self::texel`] at `tap`).
    fn colour(&self, tap: &Tap<T>, texel: &[T; 4], qx: T, qy: T, i: usize, wgt: T) -> [T; 3];
    /// The four-lane loop's [`Self::colour`] of the lanes with density (`lanes.on`; the others
    /// 0): the lanes' taps and texels in `lanes`, `q` (x and y) and the tap fractions `f` (x and
    /// y) in lanes, the weights `wgt` per lane; `[lane][channel]`, each lane's colour written
    /// and read as scalars (no vector load of values stored one by one, which stalls the store
    /// forwarding). The same bits as `colour` lane by lane.
    #[inline(always)]
    fn colour4(
        &self,
        lanes: &LaneTaps<T>,
        q: [[f32; 4]; 2],
        _f: [wide::f32x4; 2],
        i: usize,
        wgt: [f32; 4],
    ) -> [[f32; 3]; 4] {
        colour_per_lane(self, lanes, q, i, wgt)
    }
    /// The blocks the sixteen-lane loop reads ([`super::row16`]) when this sampler is one it
    /// does (packed planes, the bilinear or cubic B-spline colour, no minified plane).
    fn blocks16(&self) -> Option<Blocks16<'_>> {
        None
    }
}

/// The taps of the four lanes that take a plane, by their parts (pixel and fractions,
/// [`Tap::from_parts`]), with their texels, and which of them have density (`on`: they get a
/// colour; the others' entries are not read).
struct LaneTaps<T> {
    x0: [i32; 4],
    y0: [i32; 4],
    fx: [f32; 4],
    fy: [f32; 4],
    texel: [[T; 4]; 4],
    /// bit k: lane k has density
    on: u32,
    /// the planes' width and height
    w: usize,
    h: usize,
}

/// The lanes whose bits are set in `bits` (bit k: lane k), in order.
#[inline(always)]
fn lanes_of(bits: u32) -> impl Iterator<Item = usize> {
    (0..4).filter(move |k| bits >> k & 1 == 1)
}

impl<T: Real> LaneTaps<T> {
    /// The tap of lane `k`.
    #[inline(always)]
    fn tap(&self, k: usize) -> Tap<T> {
        Tap::from_parts(
            self.x0[k] as usize,
            self.y0[k] as usize,
            self.w,
            self.h,
            T::of32(self.fx[k]),
            T::of32(self.fy[k]),
        )
    }
}

/// [`PlaneSampler::colour4`] lane by lane through [`PlaneSampler::colour`].
#[inline(always)]
fn colour_per_lane<T: Real, S: PlaneSampler<T> + ?Sized>(
    s: &S,
    lanes: &LaneTaps<T>,
    q: [[f32; 4]; 2],
    i: usize,
    wgt: [f32; 4],
) -> [[f32; 3]; 4] {
    let mut out = [[0.0f32; 3]; 4];
    for k in lanes_of(lanes.on) {
        let c = s.colour(&lanes.tap(k), &lanes.texel[k], T::of32(q[0][k]), T::of32(q[1][k]), i, T::of32(wgt[k]));
        out[k] = c.map(T::f32);
    }
    out
}

/// Bilinear colour and density (the reference's arithmetic, channel by channel).
struct Bilinear<'a> {
    rgba: Rgba<'a>,
    /// the pyramids of the minified planes (empty: none; [`super::mip`])
    mip: &'a [Option<MipPlane<'a>>],
}

impl<T: Real> PlaneSampler<T> for Bilinear<'_> {
    #[inline(always)]
    fn texel(&self, tap: &Tap<T>, i: usize) -> [T; 4] {
        self.rgba.texel(tap, i)
    }

    fn blocks16(&self) -> Option<Blocks16<'_>> {
        match &self.rgba {
            Rgba::Blocks(b) if self.mip.iter().all(Option::is_none) => Blocks16::new(b, None),
            _ => None,
        }
    }

    #[inline(always)]
    fn colour(&self, _: &Tap<T>, texel: &[T; 4], qx: T, qy: T, i: usize, _: T) -> [T; 3] {
        let base = || [texel[0], texel[1], texel[2]];
        match self.mip.get(i) {
            Some(Some(m)) => m.colour(qx, qy, base),
            _ => base(),
        }
    }
}

/// Where a [`HighOrder`] sampler's kernel reads colour: `Some` colour of plane `i` at (qx, qy)
/// by kernel `K`, `None` where the source holds nothing there (the sampler then takes the
/// bilinear colour).
trait KernelColour: Sync {
    /// The colour by kernel `K` at the tap's fractions ([`Self::rgb_weighted`] with its weights).
    #[inline(always)]
    fn rgb<T: Real, K: Kernel<N>, const N: usize>(&self, i: usize, tap: &Tap<T>) -> Option<[T; 3]> {
        self.rgb_weighted(i, tap, &K::weights(tap.wx), &K::weights(tap.wy))
    }
    /// The store itself when it is one of blocks ([`Bricks`]).
    fn as_bricks(&self) -> Option<&Bricks> {
        None
    }
    /// The colour with the kernel's weights at the tap's fractions given.
    fn rgb_weighted<T: Real, const N: usize>(&self, i: usize, tap: &Tap<T>, wx: &[T; N], wy: &[T; N])
        -> Option<[T; 3]>;
}

/// Dense planes of `S` values per pixel (the bicubic and Lanczos kernels read the MPI's rgba).
struct DenseColour<'a, const S: usize> {
    src: Vec<&'a [f32]>,
    w: usize,
    h: usize,
}

impl<const S: usize> KernelColour for DenseColour<'_, S> {
    #[inline(always)]
    fn rgb_weighted<T: Real, const N: usize>(
        &self,
        i: usize,
        tap: &Tap<T>,
        wx: &[T; N],
        wy: &[T; N],
    ) -> Option<[T; 3]> {
        Some(sample_rgb_weighted::<T, N, S>(self.src[i], tap.x0, tap.y0, wx, wy, self.w, self.h))
    }
}

/// The B-spline coefficients in blocks ([`crate::mpi::Mpi::bspline_rgb`]).
impl KernelColour for Bricks {
    fn as_bricks(&self) -> Option<&Bricks> {
        Some(self)
    }

    #[inline(always)]
    fn rgb_weighted<T: Real, const N: usize>(
        &self,
        i: usize,
        tap: &Tap<T>,
        wx: &[T; N],
        wy: &[T; N],
    ) -> Option<[T; 3]> {
        sample_rgb_bricks_weighted::<T, N>(self, i, tap.x0, tap.y0, wx, wy)
    }
}

/// Bilinear density; colour by kernel `K` from `src` for samples of weight at least
/// [`KERNEL_MIN_WEIGHT`], bilinear below (and where `src` holds nothing).
struct HighOrder<'a, K, const N: usize, C> {
    rgba: Rgba<'a>,
    src: &'a C,
    kernel: std::marker::PhantomData<K>,
    /// the pyramids of the minified planes (empty: none; [`super::mip`])
    mip: &'a [Option<MipPlane<'a>>],
}

impl<T: Real, K: Kernel<N>, const N: usize, C: KernelColour> PlaneSampler<T> for HighOrder<'_, K, N, C> {
    fn blocks16(&self) -> Option<Blocks16<'_>> {
        match (&self.rgba, self.src.as_bricks()) {
            (Rgba::Blocks(b), Some(c)) if K::BSPLINE3 && self.mip.iter().all(Option::is_none) => {
                Blocks16::new(b, Some(c))
            }
            _ => None,
        }
    }

    #[inline(always)]
    fn texel(&self, tap: &Tap<T>, i: usize) -> [T; 4] {
        // the bilinear colour too (the four channels in one vector operation, one block look-up):
        // it is the colour of faint samples, the kernel's elsewhere
        self.rgba.texel(tap, i)
    }

    #[inline(always)]
    fn colour(&self, tap: &Tap<T>, texel: &[T; 4], qx: T, qy: T, i: usize, wgt: T) -> [T; 3] {
        match self.mip.get(i) {
            Some(Some(m)) => m.colour(qx, qy, || self.level0(tap, texel, i, wgt)),
            _ => self.level0(tap, texel, i, wgt),
        }
    }

    /// The kernel's weights of the four lanes in lanes ([`Kernel::weights4`]); the rest as
    /// [`Self::level0`] per lane (minified planes: [`Self::colour`] per lane).
    #[inline(always)]
    fn colour4(
        &self,
        lanes: &LaneTaps<T>,
        q: [[f32; 4]; 2],
        f: [wide::f32x4; 2],
        i: usize,
        wgt: [f32; 4],
    ) -> [[f32; 3]; 4] {
        if matches!(self.mip.get(i), Some(Some(_))) {
            return colour_per_lane(self, lanes, q, i, wgt);
        }
        let (wx, wy) = (K::weights4(f[0]), K::weights4(f[1]));
        let mut out = [[0.0f32; 3]; 4];
        for k in lanes_of(lanes.on) {
            let texel = &lanes.texel[k];
            let bilinear = [texel[0], texel[1], texel[2]];
            let c = if T::of32(wgt[k]) < T::of32(KERNEL_MIN_WEIGHT) {
                bilinear
            } else {
                let (wxk, wyk): ([T; N], [T; N]) =
                    (std::array::from_fn(|j| T::of32(wx[j][k])), std::array::from_fn(|j| T::of32(wy[j][k])));
                self.src.rgb_weighted::<T, N>(i, &lanes.tap(k), &wxk, &wyk).unwrap_or(bilinear)
            };
            out[k] = c.map(T::f32);
        }
        out
    }
}

impl<K, const N: usize, C: KernelColour> HighOrder<'_, K, N, C> {
    /// The colour of plane `i` itself at `tap`: by the kernel, or bilinear for a faint sample
    /// and where the kernel's source holds nothing (a method, not a closure, so that it inlines
    /// into the pixel loops).
    #[inline(always)]
    fn level0<T: Real>(&self, tap: &Tap<T>, texel: &[T; 4], i: usize, wgt: T) -> [T; 3]
    where
        K: Kernel<N>,
    {
        let bilinear = [texel[0], texel[1], texel[2]];
        if wgt < T::of32(KERNEL_MIN_WEIGHT) {
            return bilinear;
        }
        self.src.rgb::<T, K, N>(i, tap).unwrap_or(bilinear)
    }
}

/// A link's projection: homogeneous h = m q + b disp for the source pixel q of a plane point
/// (m = K_v R_v K_s^-1, b = K_v t_v; exactly the identity and 0 for [`View::Source`], so the
/// backward flow is q - p without rounding).
struct LinkConst<T> {
    m: [[T; 3]; 3],
    b: [T; 3],
}

impl<T: Real> LinkConst<T> {
    fn new(view: &View, p: &RenderParams) -> Self {
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

/// The target view over the (non-empty) window `win`: image, depth, coverage, the extra
/// channels given by `channels` and the links of `p.links` (`out`'s buffers are window-sized,
/// allocated by the caller). The loop is specialised once, here, by the number of links (0, 1
/// or 2): without links it is the loop without any link work.
pub(super) fn target_view<T: Real>(
    mpi: &Mpi,
    p: &RenderParams,
    occ: Option<&Occupancy>,
    win: &Rect,
    channels: Channels<'_>,
    out: &mut RenderOutput,
) -> RenderStats {
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
            (None, _) => target_view_n::<T, 0>(mpi, p, occ, win, channels, out, &consts, [empty3(), empty3()]),
            (Some(a), None) => target_view_n::<T, 1>(mpi, p, occ, win, channels, out, &consts, [a, empty3()]),
            (Some(a), Some(b)) => target_view_n::<T, 2>(mpi, p, occ, win, channels, out, &consts, [a, b]),
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
#[allow(clippy::too_many_arguments)]
fn target_view_n<T: Real, const NL: usize>(
    mpi: &Mpi,
    p: &RenderParams,
    occ: Option<&Occupancy>,
    win: &Rect,
    channels: Channels<'_>,
    out: &mut RenderOutput,
    consts: &[LinkConst<T>],
    lb: [(&mut [f32], &mut [f32], &mut [f32]); 2],
) -> RenderStats {
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
        Resample::Bilinear => {
            target_view_with::<T, _, NL>(mpi, p, occ, win, channels, out, consts, lb, &Bilinear { rgba, mip })
        }
        Resample::Bicubic => {
            let m = unpacked.as_deref().unwrap_or(mpi);
            let s =
                HighOrder::<Keys, 4, _> { rgba: Rgba::of(m), src: &dense(m), kernel: std::marker::PhantomData, mip };
            target_view_with::<T, _, NL>(mpi, p, occ, win, channels, out, consts, lb, &s)
        }
        Resample::Lanczos3 => {
            let m = unpacked.as_deref().unwrap_or(mpi);
            let s = HighOrder::<Lanczos3, 6, _> {
                rgba: Rgba::of(m),
                src: &dense(m),
                kernel: std::marker::PhantomData,
                mip,
            };
            target_view_with::<T, _, NL>(mpi, p, occ, win, channels, out, consts, lb, &s)
        }
        Resample::Bspline3 | Resample::Bspline5 => {
            let degree = if p.resample == Resample::Bspline3 { 3 } else { 5 };
            let owned;
            let coef: &Bricks = match &mpi.bspline_rgb {
                Some(c) if c.degree == degree => &c.coefficients,
                _ => {
                    owned = bspline_bricks(mpi, degree, true);
                    &owned
                }
            };
            if degree == 3 {
                let s = HighOrder::<Bspline3, 4, _> { rgba, src: coef, kernel: std::marker::PhantomData, mip };
                target_view_with::<T, _, NL>(mpi, p, occ, win, channels, out, consts, lb, &s)
            } else {
                let s = HighOrder::<Bspline5, 6, _> { rgba, src: coef, kernel: std::marker::PhantomData, mip };
                target_view_with::<T, _, NL>(mpi, p, occ, win, channels, out, consts, lb, &s)
            }
        }
    }
}

/// [`target_view_n`] with the plane sampler of the render's kernel: the set-up, then the band
/// loop ([`TargetBand::band`]) on the dispatched instruction set ([`crate::isa`]).
#[allow(clippy::too_many_arguments)]
fn target_view_with<T: Real, S: PlaneSampler<T>, const NL: usize>(
    mpi: &Mpi,
    p: &RenderParams,
    occ: Option<&Occupancy>,
    win: &Rect,
    channels: Channels<'_>,
    out: &mut RenderOutput,
    consts: &[LinkConst<T>],
    lb: [(&mut [f32], &mut [f32], &mut [f32]); 2],
    sampler: &S,
) -> RenderStats {
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
    let lanes = (T::LANES && NL == 0 && c <= 1).then(|| TargetLanes::new(g, w, h));
    let band = TargetBand::<T, S, NL> {
        geo: &geo,
        sampler,
        occ,
        win,
        consts,
        lanes: lanes.as_ref(),
        ex_planes: &ex_planes,
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

/// What the target view's band loop reads ([`TargetBand::band`]).
struct TargetBand<'a, T, S, const NL: usize> {
    geo: &'a TargetGeometry<T>,
    sampler: &'a S,
    occ: Option<&'a Occupancy>,
    win: &'a Rect,
    consts: &'a [LinkConst<T>],
    lanes: Option<&'a TargetLanes>,
    ex_planes: &'a [&'a [f32]],
    /// where the extra channel is needed (`None`: everywhere); tiles that do not meet it leave 0
    ex_rect: Option<[usize; 4]>,
    /// extra channels per pixel
    c: usize,
    w: usize,
    h: usize,
}

/// One band of the target view, as a job for [`crate::isa::dispatch`].
struct TargetBandJob<'a, 'b, 'c, T, S, const NL: usize> {
    band: &'a TargetBand<'a, T, S, NL>,
    y0: usize,
    rows: usize,
    b: &'b mut [&'c mut [f32]; 10],
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
        let TargetBand { geo, sampler, occ, win, consts, lanes, ex_planes, ex_rect, c, w, h } = *self;
        let TargetGeometry { kt, planes, rt_t, fxs, fys, lo, hix, hiy, wm, hm, t_eps, delta_last, ux, uy } = geo;
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
                Some(o) => tile_activity(o, planes, &ray, &source_px, [tx0, fy0, tx1, ty1], &mut active),
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
                rows16 = super::row16::rows16(v4, l, src, ex_lanes, [tx0 - win.x0, y0], rows, [&fwd, &rev], out);
            }
            for ry in (0..rows).filter(|ry| rows16 >> ry & 1 == 0) {
                let uy_y = uy[y0 + ry];
                let mut x = tx0;
                while x <= tx1 {
                    if let Some(l) = lanes.filter(|_| x + 3 <= tx1) {
                        let o = ry * ww + (x - win.x0);
                        if l.four(sampler, ex_lanes, [x - win.x0, y0 + ry], &fwd, &rev, o, b, &mut stats) {
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
                            sum_z += wgt * lambda;
                            for (acc, lc) in lacc.iter_mut().zip(consts) {
                                let m = &lc.m;
                                let (qx, qy) = q_raw;
                                let hz = m[2][0] * qx + m[2][1] * qy + m[2][2];
                                let hzb = hz + lc.b[2] * pl.disp;
                                if hzb > z_min * (hz.abs() + T::one()) {
                                    let hx = m[0][0] * qx + m[0][1] * qy + m[0][2] + lc.b[0] * pl.disp;
                                    let hy = m[1][0] * qx + m[1][1] * qy + m[1][2] + lc.b[1] * pl.disp;
                                    acc[0] += wgt * (hx / hzb - px);
                                    acc[1] += wgt * (hy / hzb - py);
                                    acc[2] += wgt * cap(hzb * pl.depth, DEPTH_MAX);
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

/// The per-render constants of the target view: the target intrinsics, the planes' constants,
/// R^T, the source focal lengths, the bounds of the "leaves the source image" test and of the
/// edge clamp, the early-termination threshold, the last gap, and the window's columns and rows
/// as u = K_t^-1 p.
struct TargetGeometry<T> {
    kt: crate::geometry::Intrinsics,
    planes: Vec<PlaneConst<T>>,
    rt_t: [[T; 3]; 3],
    fxs: T,
    fys: T,
    lo: T,
    hix: T,
    hiy: T,
    wm: T,
    hm: T,
    t_eps: T,
    delta_last: T,
    ux: Vec<T>,
    uy: Vec<T>,
}

impl<T: Real> TargetGeometry<T> {
    fn new(mpi: &Mpi, p: &RenderParams, win: &Rect) -> Self {
        let (w, h) = (mpi.width, mpi.height);
        let (ks, kt) = (p.k_src, p.k_tgt);
        let rt = p.pose.rotation.transpose();
        let centre = p.pose.target_centre_in_source();
        let k = -centre.z;
        let planes: Vec<PlaneConst<T>> = mpi
            .disparity
            .iter()
            .map(|&disp| PlaneConst {
                a: T::of(1.0 + k * disp),
                depth: T::of(plane_depth(disp)),
                disp: T::of(disp),
                ox: T::of(ks.fx * centre.x * disp + ks.cx),
                oy: T::of(ks.fy * centre.y * disp + ks.cy),
            })
            .collect();
        let r = |i: usize| [T::of(rt.row(i).x), T::of(rt.row(i).y), T::of(rt.row(i).z)];
        Self {
            kt,
            planes,
            rt_t: [r(0), r(1), r(2)],
            fxs: T::of(ks.fx),
            fys: T::of(ks.fy),
            lo: T::of(-0.5),
            hix: T::of(w as f64 - 0.5),
            hiy: T::of(h as f64 - 0.5),
            wm: T::of((w - 1) as f64),
            hm: T::of((h - 1) as f64),
            t_eps: T::of32(p.skip.transmittance_eps),
            delta_last: T::of(DELTA_LAST),
            ux: (win.x0..win.x1).map(|x| T::of((x as f64 - kt.cx) / kt.fx)).collect(),
            uy: (win.y0..win.y1).map(|y| T::of((y as f64 - kt.cy) / kt.fy)).collect(),
        }
    }
}

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
/// links, with no or one extra channel; the scalar loop of [`target_view_with`] stays the
/// reference and runs everything else). The ray set-up, the plane intersection, the "leaves the
/// source image" test, the clamps, the depth, the gap to the next plane, the exponential and the
/// compositing run in `f32x4` lanes with the scalar loop's operations in its order; the taps and
/// the colour kernel run per lane through the same [`PlaneSampler`] calls. A plane a lane does
/// not take is masked out, a lane whose transmittance fell below `t_eps` is done (counted as
/// the scalar loop counts its early exit), and the loop ends when all four are done, so every
/// pixel gets the scalar loop's bits (`tests/render_window.rs` compares the two).
impl TargetLanes {
    /// The lanes' copy of the scalar loop's constants ([`TargetGeometry`]) in `f32`.
    fn new<T: Real>(g: &TargetGeometry<T>, w: usize, h: usize) -> Self {
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
    /// when `ex` is given), the window's columns `at[0] .. at[0] + 4` of its row `at[1]`: false,
    /// with nothing written, when the four rays do not all meet the planes in the same order
    /// (the scalar loop then takes them). The rays (direction v = R^T u, |u|) are set up in lanes
    /// with the scalar loop's `ray_u` operations.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn four<T: Real, S: PlaneSampler<T>>(
        &self,
        sampler: &S,
        ex: Option<&[&[f32]]>,
        at: [usize; 2],
        fwd: &[usize],
        rev: &[usize],
        o: usize,
        b: &mut [&mut [f32]; 10],
        stats: &mut RenderStats,
    ) -> bool {
        use super::simd::exp_neg4;
        use wide::f32x4;
        let sp = f32x4::splat;
        let (zero, one) = (sp(0.0), sp(1.0));
        let ux: &[f32; 4] = self.ux[at[0]..at[0] + 4].try_into().expect("four columns");
        let (ux, uy) = (f32x4::from(*ux), sp(self.uy[at[1]]));
        let rt = &self.rt;
        let [v0, v1, v2] = [0, 1, 2].map(|i| sp(rt[i][0]) * ux + sp(rt[i][1]) * uy + sp(rt[i][2]));
        let norm_u = (ux * ux + uy * uy + one).sqrt();
        let s = v2.to_array();
        let forward = s[0] > 0.0;
        if !s.iter().all(|&s| s.abs() > 1e-12_f64 as f32 && (s > 0.0) == forward) {
            return false;
        }
        let inv_s = one / v2;
        let (lo, hix, hiy, wm, hm) = (sp(self.lo), sp(self.hix), sp(self.hiy), sp(self.wm), sp(self.hm));
        let (t_eps, depth_max, delta_last) = (sp(self.t_eps), sp(DEPTH_MAX as f32), sp(DELTA_LAST as f32));
        let cap = |v: f32x4, max: f32x4| v.simd_gt(max).select(max, v);
        let order = if forward { fwd } else { rev };
        let (mut tr, mut sum_w, mut sum_z) = (one, zero, zero);
        // per lane: colour and the extra channel
        let mut rgb = [[0.0f32; 3]; 4];
        let mut acc1 = [0.0f32; 4];
        // lanes done (bit k: lane k)
        let mut done = 0u32;
        for (j, &i) in order.iter().enumerate() {
            let g = sp(self.a[i]) * inv_s;
            let front = !g.simd_le(zero);
            // a lane in front of the plane with its transmittance below t_eps stops here
            let stop = (front & tr.simd_lt(t_eps)).to_bitmask() & !done;
            if stop != 0 {
                stats.skipped_early += u64::from(stop.count_ones()) * (order.len() - j) as u64;
                done |= stop;
                if done == 0b1111 {
                    break;
                }
            }
            let qx = sp(self.ox[i]) + sp(self.fxs) * v0 * g;
            let qy = sp(self.oy[i]) + sp(self.fys) * v1 * g;
            let inside = qx.simd_ge(lo) & qx.simd_lt(hix) & qy.simd_ge(lo) & qy.simd_lt(hiy);
            let take = (front & inside).to_bitmask() & !done;
            if take == 0 {
                continue;
            }
            let qx = qx.simd_lt(zero).select(zero, qx.simd_gt(wm).select(wm, qx));
            let qy = qy.simd_lt(zero).select(zero, qy.simd_gt(hm).select(hm, qy));
            // `Tap::new` in lanes: q >= 0, so truncation is floor; at most the last pixel
            let x0 = qx.trunc_int().min(wide::i32x4::splat(self.w as i32 - 1));
            let y0 = qy.trunc_int().min(wide::i32x4::splat(self.h as i32 - 1));
            let f = [qx - x0.round_float(), qy - y0.round_float()];
            let (qx, qy) = (qx.to_array(), qy.to_array());
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
                if !matches!(
                    texel[3].partial_cmp(&T::zero()),
                    Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
                ) {
                    lt.on |= 1 << k;
                    sig = lane_mask(1 << k).select(sp(texel[3].f32()), sig);
                }
                lt.texel[k] = texel;
            }
            if lt.on == 0 {
                continue;
            }
            let m = lane_mask(lt.on);
            let lambda = cap(g * sp(self.depth[i]), depth_max);
            let next = if forward { i + 1 } else { i.wrapping_sub(1) };
            let delta = match self.a.get(next) {
                Some(&an) => {
                    let an = sp(an) * inv_s;
                    let d = cap((cap(an * sp(self.depth[next]), depth_max) - lambda) * norm_u, delta_last);
                    an.simd_gt(zero).select(d, delta_last)
                }
                None => delta_last,
            };
            let e = exp_neg4(sig * delta);
            let wgt = tr * (one - e);
            tr = m.select(tr * e, tr);
            let wa = wgt.to_array();
            // the colours and the extra channel come lane by lane: they are summed lane by lane
            let smp = sampler.colour4(&lt, [qx, qy], f, i, wa);
            for k in lanes_of(lt.on) {
                for ch in 0..3 {
                    rgb[k][ch] += wa[k] * smp[k][ch];
                }
                if let Some(ex) = ex {
                    acc1[k] += wa[k] * lt.tap(k).sample1(ex[i]).f32();
                }
            }
            sum_w = m.select(sum_w + wgt, sum_w);
            sum_z = m.select(sum_z + wgt * lambda, sum_z);
        }
        // the scalar loop's T::of(1e-6)
        const EPS: f32 = 1e-6_f64 as f32;
        let [sum_w, sum_z] = [sum_w, sum_z].map(f32x4::to_array);
        for k in 0..4 {
            let o = o + k;
            b[0][3 * o..3 * o + 3].copy_from_slice(&rgb[k]);
            b[1][o] = if sum_w[k] > EPS { sum_z[k] / sum_w[k] } else { 0.0 };
            b[2][o] = sum_w[k];
            if ex.is_some() {
                b[3][o] = acc1[k];
            }
        }
        true
    }
}

/// Marks which planes can contribute inside the target tile [x0, x1] x [y0, y1]: a plane is
/// skipped when its source footprint over the tile (the bounding box of the four corner
/// samples, grown by one pixel for the bilinear support) holds no occupied block. The footprint
/// is exact only when the plane is in front of the camera over the whole tile, so a tile where
/// some corner sees the plane from behind keeps the plane active.
fn tile_activity<T: Real>(
    occ: &Occupancy,
    planes: &[PlaneConst<T>],
    ray: &impl Fn(f64, f64) -> ([T; 3], T),
    source_px: &impl Fn(&PlaneConst<T>, &[T; 3], T) -> (T, T),
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
            if v[2] <= T::zero() {
                exact = false;
                break;
            }
            let g = pl.a / v[2];
            if g <= T::zero() {
                exact = false;
                break;
            }
            let (qx, qy) = source_px(pl, v, g);
            let (qx, qy) = (qx.f64(), qy.f64());
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

/// The source view over the (non-empty) window `win`: flow, expected target depth and `valid`
/// (window-sized buffers allocated by the caller). With `flow_where` (H x W) only the pixels
/// where it is > 0 are computed; the others keep flow 0, depth 0 and `valid` 0.
pub(super) fn source_view<T: Real>(
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
    // four pixels at a time where T is f32 and every pixel is asked for (the same bits)
    let lanes = (T::LANES && flow_where.is_none()).then(|| SourceLanes {
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
        let SourceBand { win, occ, flow_where, lanes, m_t, b_t, disp, depth_t, gap, t_eps, rgba, ks, w, want_sd } =
            *self;
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
                    while L > 4 && x0 + L - 1 <= tx1 {
                        l.wide::<L>(x0, yy, &active, ry * ww + (x0 - win.x0), b);
                        x0 += L;
                    }
                    while x0 + 3 <= tx1 {
                        l.four(x0, yy, &active, ry * ww + (x0 - win.x0), b);
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
                        if want_sd {
                            sd += wgt * depth_t[i];
                        }
                        let hz = a[2] + b_t[2] * disp[i];
                        if hz > z_min * (a[2].abs() + T::one()) {
                            let hx = a[0] + b_t[0] * disp[i];
                            let hy = a[1] + b_t[1] * disp[i];
                            fu += wgt * (hx / hz - xf);
                            fv += wgt * (hy / hz - y);
                            sw += wgt;
                            sz += wgt * cap(hz * depth_t[i], DEPTH_MAX);
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

/// The source view's per-pixel loop for four adjacent pixels of a row at once (f32 only, the
/// scalar loop of [`source_view`] stays the reference): every lane does the scalar loop's
/// operations in its order on its own pixel, planes a lane does not take (density 0, or the
/// lane done because its transmittance fell below `t_eps`) are masked out instead of skipped,
/// and the plane loop ends when every lane is done. So each pixel gets the scalar loop's bits
/// (`tests/render_window.rs` compares the two: a `flow_where` mask makes the scalar loop run).
struct SourceLanes<'a> {
    m: [[f32; 3]; 3],
    b: [f32; 3],
    disp: Vec<f32>,
    depth: Vec<f32>,
    gap: Vec<f32>,
    t_eps: f32,
    z_min: f32,
    rgba: Rgba<'a>,
    /// the frame's columns as f32, and its columns and rows as u = K_s^-1 p (the scalar loop's
    /// values, computed once)
    xs: Vec<f32>,
    ux: Vec<f32>,
    uy: Vec<f32>,
    want_sd: bool,
}

impl SourceLanes<'_> {
    /// Pixels `x .. x + 4` of row `yy`, written at `o .. o + 4` of the band's buffers `b`
    /// (flow, expected target depth, front fraction, source depth).
    #[inline(always)]
    fn four(&self, x: usize, yy: usize, active: &[usize], o: usize, b: &mut [&mut [f32]; 4]) {
        use super::simd::exp_neg4;
        use wide::f32x4;
        let sp = f32x4::splat;
        let (zero, one) = (sp(0.0), sp(1.0));
        let four = |v: &[f32]| f32x4::from(*<&[f32; 4]>::try_from(&v[x..x + 4]).expect("four columns"));
        let (xf, ux) = (four(&self.xs), four(&self.ux));
        let y = yy as f64 as f32;
        let uy = sp(self.uy[yy]);
        let norm_u = (ux * ux + uy * uy + one).sqrt();
        let a: [f32x4; 3] = std::array::from_fn(|r| sp(self.m[r][0]) * xf + sp(self.m[r][1] * y) + sp(self.m[r][2]));
        let (mut tr, mut fu, mut fv, mut sw, mut sz, mut sall, mut sd) = (one, zero, zero, zero, zero, zero, zero);
        let (t_eps, z_lim) = (sp(self.t_eps), sp(self.z_min) * (a[2].abs() + one));
        let depth_max = sp(DEPTH_MAX as f32);
        for &i in active {
            // a lane is done once its transmittance is below t_eps (it only falls)
            let live = !tr.simd_lt(t_eps);
            if !live.any() {
                break;
            }
            let sigma = self.rgba.sigma4(i, x, yy);
            let take = live & !sigma.simd_le(zero);
            if !take.any() {
                continue;
            }
            let e = exp_neg4(sigma * sp(self.gap[i]) * norm_u);
            let wgt = tr * (one - e);
            tr = take.select(tr * e, tr);
            sall = take.select(sall + wgt, sall);
            if self.want_sd {
                sd = take.select(sd + wgt * sp(self.depth[i]), sd);
            }
            let d = sp(self.disp[i]);
            let hz = a[2] + sp(self.b[2]) * d;
            let front = take & hz.simd_gt(z_lim);
            if front.any() {
                let hx = a[0] + sp(self.b[0]) * d;
                let hy = a[1] + sp(self.b[1]) * d;
                fu = front.select(fu + wgt * (hx / hz - xf), fu);
                fv = front.select(fv + wgt * (hy / hz - sp(y)), fv);
                sw = front.select(sw + wgt, sw);
                let z = hz * sp(self.depth[i]);
                let z = z.simd_gt(depth_max).select(depth_max, z);
                sz = front.select(sz + wgt * z, sz);
            }
        }
        let [fu, fv, sw, sz, sall, sd] = [fu, fv, sw, sz, sall, sd].map(f32x4::to_array);
        self.write(o, [fu, fv, sw, sz, sall, sd], b);
    }
}

impl SourceLanes<'_> {
    /// Writes the `L` pixels `o .. o + L` of the band from their sums `[fu, fv, sw, sz, sall,
    /// sd]`: flow and depth normalised by the weight in front, `valid` the share in front, the
    /// expected depth (the scalar loop's divisions, pixel by pixel).
    #[inline(always)]
    fn write<const L: usize>(&self, o: usize, [fu, fv, sw, sz, sall, sd]: [[f32; L]; 6], b: &mut [&mut [f32]; 4]) {
        // the scalar loop's T::of(1e-6)
        const EPS: f32 = 1e-6_f64 as f32;
        for k in 0..L {
            let o = o + k;
            if sw[k] > EPS {
                b[0][2 * o] = fu[k] / sw[k];
                b[0][2 * o + 1] = fv[k] / sw[k];
                b[1][o] = sz[k] / sw[k];
            }
            b[2][o] = if sall[k] > 0.0 { sw[k] / sall[k] } else { 0.0 };
            if self.want_sd && sall[k] > EPS {
                b[3][o] = sd[k] / sall[k];
            }
        }
    }

    /// [`Self::four`] for the `L` pixels `x .. x + L` (the paths whose registers hold 8 or 16
    /// values, [`crate::isa`]) in plain arrays: lane by lane the same operations in the same
    /// order, which LLVM turns into the path's vector instructions, so the same bits (the
    /// negated compares are the scalar loop's: NaN densities are taken, as there).
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    #[inline(always)]
    fn wide<const L: usize>(&self, x: usize, yy: usize, active: &[usize], o: usize, b: &mut [&mut [f32]; 4]) {
        use std::array::from_fn;
        let ld = |v: &[f32]| -> [f32; L] { v[x..x + L].try_into().expect("L columns") };
        let (xf, ux) = (ld(&self.xs), ld(&self.ux));
        let y = yy as f64 as f32;
        let uy = self.uy[yy];
        let norm_u: [f32; L] = from_fn(|k| (ux[k] * ux[k] + uy * uy + 1.0).sqrt());
        let m = &self.m;
        let a: [[f32; L]; 3] = from_fn(|r| from_fn(|k| m[r][0] * xf[k] + m[r][1] * y + m[r][2]));
        let z_lim: [f32; L] = from_fn(|k| self.z_min * (a[2][k].abs() + 1.0));
        let mut tr = [1.0f32; L];
        let (mut fu, mut fv, mut sw, mut sz, mut sall, mut sd) =
            ([0.0f32; L], [0.0; L], [0.0; L], [0.0; L], [0.0; L], [0.0; L]);
        let depth_max = DEPTH_MAX as f32;
        let sel = |m: bool, a: f32, b: f32| if m { a } else { b };
        for &i in active {
            // a lane is done once its transmittance is below t_eps (it only falls)
            if tr.iter().all(|&t| t < self.t_eps) {
                break;
            }
            let sigma = self.rgba.sigma_n::<L>(i, x, yy);
            let take: [bool; L] = from_fn(|k| !(tr[k] < self.t_eps) & !(sigma[k] <= 0.0));
            if !take.iter().any(|&t| t) {
                continue;
            }
            let (gap, depth, d) = (self.gap[i], self.depth[i], self.disp[i]);
            let e: [f32; L] = from_fn(|k| f32::exp_neg(sigma[k] * gap * norm_u[k]));
            let wgt: [f32; L] = from_fn(|k| tr[k] * (1.0 - e[k]));
            tr = from_fn(|k| sel(take[k], tr[k] * e[k], tr[k]));
            sall = from_fn(|k| sel(take[k], sall[k] + wgt[k], sall[k]));
            if self.want_sd {
                sd = from_fn(|k| sel(take[k], sd[k] + wgt[k] * depth, sd[k]));
            }
            let hz: [f32; L] = from_fn(|k| a[2][k] + self.b[2] * d);
            let front: [bool; L] = from_fn(|k| take[k] & (hz[k] > z_lim[k]));
            if front.iter().any(|&f| f) {
                let (bx, by) = (self.b[0] * d, self.b[1] * d);
                fu = from_fn(|k| sel(front[k], fu[k] + wgt[k] * ((a[0][k] + bx) / hz[k] - xf[k]), fu[k]));
                fv = from_fn(|k| sel(front[k], fv[k] + wgt[k] * ((a[1][k] + by) / hz[k] - y), fv[k]));
                sw = from_fn(|k| sel(front[k], sw[k] + wgt[k], sw[k]));
                sz = from_fn(|k| {
                    let z = hz[k] * depth;
                    let z = if z > depth_max { depth_max } else { z };
                    sel(front[k], sz[k] + wgt[k] * z, sz[k])
                });
            }
        }
        self.write(o, [fu, fv, sw, sz, sall, sd], b);
    }
}

/// A density cut ([`DensityCut`]) over a bilinear sampler: plane `i`'s
/// density at a tap is scaled by `1 - c`, `c` the bilinear mean of the cut's mask over the tap's
/// four pixels, each counted only where plane `i` is one it cuts there.
struct CutSampler<'a> {
    inner: Bilinear<'a>,
    cut: &'a DensityCut<'a>,
}

impl<T: Real> PlaneSampler<T> for CutSampler<'_> {
    #[inline(always)]
    fn texel(&self, tap: &Tap<T>, i: usize) -> [T; 4] {
        let [r, g, b, sigma]: [T; 4] = self.inner.texel(tap, i);
        if sigma <= T::zero() {
            return [r, g, b, sigma];
        }
        let cut = tap.sample_where(self.cut.mask, |p| usize::from(self.cut.last[p]) >= i && self.cut.mask[p] > 0.0);
        [r, g, b, sigma * (T::one() - cut).max(T::zero())]
    }

    #[inline(always)]
    fn colour(&self, tap: &Tap<T>, texel: &[T; 4], qx: T, qy: T, i: usize, wgt: T) -> [T; 3] {
        self.inner.colour(tap, texel, qx, qy, i, wgt)
    }
}

/// The target view of `mpi` with the density cut `cut`, bilinear, without links or extra
/// channels (image, depth and coverage of `out`, window-sized).
pub(super) fn target_view_cut<T: Real>(
    mpi: &Mpi,
    p: &RenderParams,
    occ: Option<&Occupancy>,
    win: &Rect,
    cut: &DensityCut<'_>,
    out: &mut RenderOutput,
) -> RenderStats {
    let sampler = CutSampler { inner: Bilinear { rgba: Rgba::of(mpi), mip: &[] }, cut };
    let none: [LinkConst<T>; 0] = [];
    target_view_with::<T, _, 0>(
        mpi,
        p,
        occ,
        win,
        Channels::Broadcast(cut.mask),
        out,
        &none,
        [empty3(), empty3()],
        &sampler,
    )
}
