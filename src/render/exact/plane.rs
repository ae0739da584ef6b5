//! What both views' loops share: the tile width of plane skipping, the per-plane constants of
//! the target view's rays, and the cap on depths and gaps.

use crate::render::real::Real;

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
