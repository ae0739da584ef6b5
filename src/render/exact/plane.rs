//! What both views' loops share: the tile width of plane skipping, the per-plane constants of
//! the target view's rays, and the cap on depths and gaps.

use crate::mpi::planes::DEPTH_MAX;
use crate::render::real::Real;
use crate::render::tap::Tap;

/// Width of a target tile for plane skipping (its height is the band height).
pub(super) const TILE: usize = 16;

/// The constants of one plane along the target view's rays (see the front door's formulas).
pub(super) struct PlaneConst<T> {
    /// 1 + k disp
    pub(super) a: T,
    pub(super) depth: T,
    pub(super) disp: T,
    pub(super) ox: T,
    pub(super) oy: T,
    /// the slab of the texels' disparity offsets ([`crate::mpi::Surface::slab`])
    pub(super) lo: T,
    pub(super) hi: T,
}

/// `v`, at most `max`.
#[inline(always)]
pub(super) fn cap<T: Real>(v: T, max: f64) -> T {
    if v > T::of(max) {
        T::of(max)
    } else {
        v
    }
}

/// Fixed-point steps of a true-depth texel's search along its ray ([`SurfaceRay::search`]).
pub(super) const SURFACE_STEPS: usize = 2;

/// What a true-depth texel's search needs of the target view's geometry (the front door's
/// formulas at any disparity): the source focal lengths and principal point, the target centre
/// in source coordinates (x, y), k = -C_z, and the edge clamp's bounds; with the surface
/// ([`crate::mpi::Surface`]) it searches.
#[derive(Clone, Copy)]
pub(super) struct SurfaceRay<'a, T> {
    pub(super) surface: &'a [f32],
    pub(super) fs: [T; 2],
    pub(super) cs: [T; 2],
    pub(super) centre: [T; 2],
    pub(super) k: T,
    pub(super) wm: T,
    pub(super) hm: T,
    pub(super) w: usize,
    pub(super) h: usize,
}

/// The disparity offset of a texel whose pixel's surface lies at disparity `s`, on a plane at
/// `disp` with slab `[lo, hi]`: `s - disp` kept within the slab where the pixel lies within two
/// slabs of the plane (its texel is the pixel itself, split onto this plane, or a neighbour of it
/// on the same smooth surface), 0 farther away (the texel is a fill, or the far plane's colour
/// behind a nearer pixel: it stays on its plane). A depth edge therefore never pulls a texel from
/// one side's depth to the other's, which made the search alternate across edges in stripes,
/// while a smooth surface's offsets stay continuous across the slab's bounds
/// (docs/quality.md, "True-depth layers").
#[inline(always)]
pub(super) fn slab_offset<T: Real>(s: T, disp: T, lo: T, hi: T) -> T {
    let o = s - disp;
    if o >= lo + lo && o <= hi + hi {
        o.max(lo).min(hi)
    } else {
        T::zero()
    }
}

/// The depth of a texel at disparity `d`: [`crate::mpi::planes::plane_depth`] in `T`, and
/// [`DEPTH_MAX`] where `d <= 0` (a texel's offset may take it to disparity 0 or beyond). Both
/// views' searches and reads call this one function (the four-lane loop its operations in lanes).
#[inline(always)]
pub(super) fn texel_depth<T: Real>(d: T) -> T {
    if d > T::zero() {
        cap(T::one() / d, DEPTH_MAX)
    } else {
        T::of(DEPTH_MAX)
    }
}

impl<T: Real> SurfaceRay<'_, T> {
    /// The source pixel where the ray of direction `v` (x and y; `inv_s` = 1 / v_z) meets
    /// disparity `d`: `(fx_s (C_x d + v_x g) + cx_s, fy_s (C_y d + v_y g) + cy_s)`, g = (1 + k d)
    /// / v_z.
    #[inline(always)]
    pub(super) fn at(&self, v: [T; 2], inv_s: T, d: T) -> (T, T) {
        let g = (T::one() + self.k * d) * inv_s;
        (
            self.fs[0] * (self.centre[0] * d + v[0] * g) + self.cs[0],
            self.fs[1] * (self.centre[1] * d + v[1] * g) + self.cs[1],
        )
    }

    /// The texel of plane `pl` that the ray meets, from the plane's point `q`: [`SURFACE_STEPS`]
    /// fixed-point steps, each reading the texels' offsets ([`slab_offset`], bilinear at the
    /// clamped point) where the last one landed and moving to the ray's point at that disparity
    /// (a mean of offsets within the slab stays within it). Returns the point, its disparity, its depth (capped) and g = (1 + k d) / v_z (<= 0:
    /// behind the target camera). The scalar loop and the lanes call this one function, so
    /// their bits agree.
    #[inline(always)]
    pub(super) fn search(&self, pl: &PlaneConst<T>, v: [T; 2], inv_s: T, q: (T, T)) -> ([T; 2], T, T, T) {
        let (mut qx, mut qy, mut d) = (q.0, q.1, pl.disp);
        for _ in 0..SURFACE_STEPS {
            let tap = Tap::new(qx.max(T::zero()).min(self.wm), qy.max(T::zero()).min(self.hm), self.w, self.h);
            d = pl.disp + tap.sample_map(self.surface, |s| slab_offset(s, pl.disp, pl.lo, pl.hi));
            (qx, qy) = self.at(v, inv_s, d);
        }
        ([qx, qy], d, texel_depth(d), (T::one() + self.k * d) * inv_s)
    }
}
