//! Four-lane f32 arithmetic for the render's taps (`wide::f32x4`: SSE2 on x86-64, NEON on
//! aarch64, scalar elsewhere). Each function does, lane for lane, exactly the operations of its
//! scalar twin (no fused multiply-add, the same order), so the results are bit-identical to the
//! scalar formulas of [`super::real::Real`] (tested in `render::real`).

use wide::f32x4;

#[inline(always)]
fn load(s: &[f32]) -> f32x4 {
    let a: &[f32; 4] = s[..4].try_into().expect("four values");
    f32x4::from(*a)
}

/// Bilinear interpolation of four channels: per channel, top = a + wx (b - a),
/// bot = c + wx (d - c), top + wy (bot - top) (`Tap::sample1`'s arithmetic); `a`..`d` are
/// the four pixels' channels (at least 4 values each).
#[inline(always)]
pub(crate) fn lerp4(a: &[f32], b: &[f32], c: &[f32], d: &[f32], wx: f32, wy: f32) -> [f32; 4] {
    let (a, b, c, d) = (load(a), load(b), load(c), load(d));
    let (wx, wy) = (f32x4::splat(wx), f32x4::splat(wy));
    let top = a + wx * (b - a);
    let bot = c + wx * (d - c);
    (top + wy * (bot - top)).to_array()
}
