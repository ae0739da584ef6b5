//! The target view's plane samplers: the density and colour of a plane at a tap
//! ([`PlaneSampler`]), bilinear ([`Bilinear`]) or with a density cut ([`CutSampler`]), and the
//! taps of the four-lane loop ([`LaneTaps`]).

use super::row16::Blocks16;
use crate::render::mip::MipPlane;
use crate::render::real::Real;
use crate::render::store::Rgba;
use crate::render::tap::Tap;
use crate::render::types::DensityCut;

/// Plane samples of the target view: the bilinear density of plane `i` at a tap (always
/// bilinear; with the bilinear colour where a sampler gets it for free) and its colour by the
/// render's [`Resample`](crate::render::types::Resample) kernel, asked for only where the
/// density is positive.
pub(super) trait PlaneSampler<T: Real>: Sync {
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
    /// The blocks the sixteen-lane loop reads ([`crate::render::row16`]) when this sampler is one it
    /// does (packed planes, the bilinear or cubic B-spline colour, no minified plane).
    fn blocks16(&self) -> Option<Blocks16<'_>> {
        None
    }
}

/// The taps of the four lanes that take a plane, by their parts (pixel and fractions,
/// [`Tap::from_parts`]), with their texels, and which of them have density (`on`: they get a
/// colour; the others' entries are not read).
pub(super) struct LaneTaps<T> {
    pub(super) x0: [i32; 4],
    pub(super) y0: [i32; 4],
    pub(super) fx: [f32; 4],
    pub(super) fy: [f32; 4],
    pub(super) texel: [[T; 4]; 4],
    /// bit k: lane k has density
    pub(super) on: u32,
    /// the planes' width and height
    pub(super) w: usize,
    pub(super) h: usize,
}

/// The lanes whose bits are set in `bits` (bit k: lane k), in order.
#[inline(always)]
pub(super) fn lanes_of(bits: u32) -> impl Iterator<Item = usize> {
    (0..4).filter(move |k| bits >> k & 1 == 1)
}

impl<T: Real> LaneTaps<T> {
    /// The tap of lane `k`.
    #[inline(always)]
    pub(super) fn tap(&self, k: usize) -> Tap<T> {
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
pub(super) fn colour_per_lane<T: Real, S: PlaneSampler<T> + ?Sized>(
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
pub(super) struct Bilinear<'a> {
    pub(super) rgba: Rgba<'a>,
    /// the pyramids of the minified planes (empty: none; [`crate::render::mip`])
    pub(super) mip: &'a [Option<MipPlane<'a>>],
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

/// A density cut ([`DensityCut`]) over a bilinear sampler: plane `i`'s
/// density at a tap is scaled by `1 - c`, `c` the bilinear mean of the cut's mask over the tap's
/// four pixels, each counted only where plane `i` is one it cuts there.
pub(super) struct CutSampler<'a> {
    pub(super) inner: Bilinear<'a>,
    pub(super) cut: &'a DensityCut<'a>,
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
