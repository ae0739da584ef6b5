//! The target view's samplers for the higher-order colour kernels ([`HighOrder`]): bilinear
//! density, colour by the kernel from dense planes ([`DenseColour`]) or B-spline coefficients in
//! blocks.

use super::row16::{Blocks16, KERNEL_MIN_WEIGHT};
use super::sampler::{colour_per_lane, lanes_of, LaneTaps, PlaneSampler};
use crate::mpi::bricks::Bricks;
use crate::render::mip::MipPlane;
use crate::render::real::Real;
use crate::render::resample::{sample_rgb_bricks_weighted, sample_rgb_weighted, Kernel};
use crate::render::store::Rgba;
use crate::render::tap::Tap;

/// Where a [`HighOrder`] sampler's kernel reads colour: `Some` colour of plane `i` at (qx, qy)
/// by kernel `K`, `None` where the source holds nothing there (the sampler then takes the
/// bilinear colour).
pub(super) trait KernelColour: Sync {
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
pub(super) struct DenseColour<'a, const S: usize> {
    pub(super) src: Vec<&'a [f32]>,
    pub(super) w: usize,
    pub(super) h: usize,
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
pub(super) struct HighOrder<'a, K, const N: usize, C> {
    pub(super) rgba: Rgba<'a>,
    pub(super) src: &'a C,
    pub(super) kernel: std::marker::PhantomData<K>,
    /// the pyramids of the minified planes (empty: none; [`crate::render::mip`])
    pub(super) mip: &'a [Option<MipPlane<'a>>],
}

impl<T: Real, K: Kernel<N>, const N: usize, C: KernelColour> PlaneSampler<T> for HighOrder<'_, K, N, C> {
    fn blocks16(&self) -> Option<Blocks16<'_>> {
        match (&self.rgba, self.src.as_bricks()) {
            (Rgba::Blocks(b), Some(c)) if self.mip.iter().all(Option::is_none) => {
                K::ROW16.and_then(|cubic| Blocks16::new(b, Some((c, cubic))))
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
