//! The bilinear tap of a plane sample (a point's pixel and fractions) and its reads of dense
//! planes and blocks, and the truncating pixel index of the kernels.

use super::real::Real;

/// `(q as usize).min(n - 1)` for q >= 0 (truncation is floor there; NaN and negatives give 0,
/// as Rust's saturating `as` does), through `i32`: the same value for every q with n < 2^31, in
/// one x86-64 conversion where `f32 as usize` takes several (`resample::sample_rgb`: -2.3% of
/// the `bspline3` target pass's instructions; `Tap::new`'s scalar remainder gained nothing).
#[inline(always)]
pub(crate) fn floor_index(q: f32, n: usize) -> usize {
    ((q as i32).max(0) as usize).min(n - 1)
}

/// A bilinear tap at a point already clamped to [0, W-1] x [0, H-1].
#[derive(Clone, Copy, Debug)]
pub(crate) struct Tap<T> {
    /// the tap's pixel (the top-left of its four)
    pub(crate) x0: usize,
    pub(crate) y0: usize,
    /// the plane's width and height (the four pixels' indices are computed where a dense plane
    /// is read, [`Self::corners`]: a block store needs only the pixel)
    w: usize,
    h: usize,
    pub(crate) wx: T,
    pub(crate) wy: T,
}

impl<T: Real> Tap<T> {
    #[inline(always)]
    pub(crate) fn new(qx: T, qy: T, w: usize, h: usize) -> Self {
        // q >= 0 here, so truncation is floor (and avoids a libm call without SSE4.1)
        let x0 = (qx.f32() as usize).min(w - 1);
        let y0 = (qy.f32() as usize).min(h - 1);
        let (fx, fy) = (T::of(x0 as f64), T::of(y0 as f64));
        Self::from_parts(x0, y0, w, h, qx - fx, qy - fy)
    }

    /// The tap of [`Self::new`] from its parts: the pixel (x0, y0) (q truncated, at most the last
    /// pixel) and the fractions wx = qx - x0, wy = qy - y0 (the four-lane loop computes these in
    /// lanes with `new`'s operations).
    #[inline(always)]
    pub(crate) fn from_parts(x0: usize, y0: usize, w: usize, h: usize, wx: T, wy: T) -> Self {
        Self { x0, y0, w, h, wx, wy }
    }

    /// The indices in a dense plane of the tap's four pixels: (x0, y0), (x1, y0), (x0, y1),
    /// (x1, y1), with x1 = x0 + 1 and y1 = y0 + 1 clamped to the last column and row.
    #[inline(always)]
    fn corners(&self) -> [usize; 4] {
        let (w, x0, y0) = (self.w, self.x0, self.y0);
        let x1 = (x0 + 1).min(w - 1);
        let y1 = (y0 + 1).min(self.h - 1);
        [y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1]
    }

    /// [`Self::sample4`] of a block of 4-valued pixels ([`crate::mpi::bricks::Bricks`]) whose
    /// value at the tap's pixel starts at `s`, rows `row` values apart, the right and lower
    /// neighbours in the block's apron (the same arithmetic).
    #[inline(always)]
    pub(crate) fn sample4_at(&self, data: &[f32], s: usize, row: usize) -> [T; 4] {
        let d = &data[s..s + row + 8];
        T::lerp4(&d[..4], &d[4..8], &d[row..row + 4], &d[row + 4..], self.wx, self.wy)
    }

    /// Samples an interleaved 4-channel plane (per channel the arithmetic of [`Self::sample1`];
    /// `f32` takes the four channels at once, [`Real::lerp4`]).
    #[inline(always)]
    pub(crate) fn sample4(&self, plane: &[f32]) -> [T; 4] {
        let [i00, i10, i01, i11] = self.corners();
        let px = |i: usize| &plane[4 * i..4 * i + 4];
        T::lerp4(px(i00), px(i10), px(i01), px(i11), self.wx, self.wy)
    }

    /// Samples a single-channel plane (`sample_c` with `c = 1`, the same arithmetic).
    #[inline(always)]
    pub(crate) fn sample1(&self, plane: &[f32]) -> T {
        let [i00, i10, i01, i11] = self.corners();
        let at = |i: usize| T::of32(plane[i]);
        let top = at(i00) + self.wx * (at(i10) - at(i00));
        let bot = at(i01) + self.wx * (at(i11) - at(i01));
        top + self.wy * (bot - top)
    }

    /// Samples a single-channel plane counting only the pixels where `keep` holds (the others
    /// as 0), with the arithmetic of [`Self::sample1`].
    #[inline(always)]
    pub(crate) fn sample_where(&self, plane: &[f32], keep: impl Fn(usize) -> bool) -> T {
        let [i00, i10, i01, i11] = self.corners();
        let at = |i: usize| if keep(i) { T::of32(plane[i]) } else { T::zero() };
        let top = at(i00) + self.wx * (at(i10) - at(i00));
        let bot = at(i01) + self.wx * (at(i11) - at(i01));
        top + self.wy * (bot - top)
    }

    /// Samples a single-channel plane through `f` (each of the four pixels' values mapped by
    /// `f` before the arithmetic of [`Self::sample1`]).
    #[inline(always)]
    pub(crate) fn sample_map(&self, plane: &[f32], f: impl Fn(T) -> T) -> T {
        let [i00, i10, i01, i11] = self.corners();
        let at = |i: usize| f(T::of32(plane[i]));
        let top = at(i00) + self.wx * (at(i10) - at(i00));
        let bot = at(i01) + self.wx * (at(i11) - at(i01));
        top + self.wy * (bot - top)
    }

    /// Samples `c` interleaved channels into `out`.
    #[inline(always)]
    pub(crate) fn sample_c(&self, plane: &[f32], c: usize, out: &mut [T]) {
        let (wx, wy) = (self.wx, self.wy);
        let [i00, i10, i01, i11] = self.corners();
        for k in 0..c {
            let at = |i: usize| T::of32(plane[c * i + k]);
            let top = at(i00) + wx * (at(i10) - at(i00));
            let bot = at(i01) + wx * (at(i11) - at(i01));
            out[k] = top + wy * (bot - top);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::floor_index;

    /// `floor_index` is `(q as usize).min(n - 1)` for every q: a spread of values with their
    /// negatives, NaN, infinities and values past i32's range.
    #[test]
    fn floor_index_is_the_saturating_usize_conversion() {
        let mut qs: Vec<f32> =
            [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 3e9, -3e9, 2.1e9, 0.0, -0.0, 639.999].into_iter().collect();
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..4000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let unit = (x >> 40) as f32 / (1u64 << 24) as f32; // [0, 1)
            qs.extend([unit, -unit, unit * 700.0, -unit * 700.0, unit * 5000.0]);
        }
        for n in [1usize, 2, 640, 4096] {
            for &q in &qs {
                assert_eq!(floor_index(q, n), (q as usize).min(n - 1), "q = {q}, n = {n}");
            }
        }
    }
}
