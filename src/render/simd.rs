//! Four-lane f32 arithmetic for the render's taps (`wide::f32x4`: SSE2 on x86-64, NEON on
//! aarch64, scalar elsewhere). Each function does, lane for lane, exactly the operations of its
//! scalar twin (no fused multiply-add, the same order), so the results are bit-identical to the
//! scalar formulas of the `Real` trait (`real.rs`, which tests them against each other).

use wide::bytemuck::cast;
use wide::{f32x4, i32x4};

/// The most values of a kernel row (`Real::kernel_cols`, [`kernel_cols`]): 6 taps of 4 values.
pub(crate) const KERNEL_COLS: usize = 24;

/// 2^f = e^(f ln 2) for f in [-0.5, 0.5]: the Taylor coefficients of e^y at y = f ln 2 (the
/// polynomial of [`exp_neg4`] and of its scalar twin, `exp_neg_f32` in `real.rs`).
pub(crate) const EXP2_TAYLOR: [f32; 7] =
    [1.0, std::f32::consts::LN_2, 0.240_226_5, 0.055_504_11, 0.009_618_129, 0.001_333_355_8, 0.000_154_035_3];

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

/// exp(-x) of four values: `exp_neg_f32` of `real.rs`, operation for operation in every
/// lane (the same clamps, argument reduction, polynomial and exponent bits), so the same bits.
#[inline(always)]
pub(crate) fn exp_neg4(x: f32x4) -> f32x4 {
    let (zero, cap) = (f32x4::splat(0.0), f32x4::splat(80.0));
    let x = x.simd_lt(cap).select(x, cap); // NaN becomes 80
    let x = x.simd_gt(zero).select(x, zero);
    let t = -x * f32x4::splat(std::f32::consts::LOG2_E);
    let magic = f32x4::splat(12_582_912.0);
    let n = (t + magic) - magic;
    let f = t - n;
    let c = |k: usize| f32x4::splat(EXP2_TAYLOR[k]);
    let p = c(0) + f * (c(1) + f * (c(2) + f * (c(3) + f * (c(4) + f * (c(5) + f * c(6))))));
    let n = n.trunc_int();
    // n / 2 rounded toward zero, as Rust's integer division: one more before the shift when n < 0
    let half = (n - n.simd_lt(i32x4::splat(0))) >> 1;
    let pow2 = |k: i32x4| cast::<i32x4, f32x4>((i32x4::splat(127) + k) << 23);
    p * pow2(half) * pow2(n - half)
}

/// Four values `stride` apart from `s[at]` (a gather, one load per lane).
#[inline(always)]
pub(crate) fn gather(s: &[f32], at: usize, stride: usize) -> f32x4 {
    f32x4::from([s[at], s[at + stride], s[at + 2 * stride], s[at + 3 * stride]])
}

/// `Real::kernel_cols` for `f32`: the column sums four values at a time (the
/// vectors of a row, then the row's last `N S mod 4` values one by one), each value's sum in
/// the scalar order, so the same bits.
#[inline(always)]
pub(crate) fn kernel_cols<const N: usize, const S: usize>(
    src: &[f32],
    start: usize,
    row_len: usize,
    wy: &[f32; N],
) -> [f32; KERNEL_COLS] {
    let (nv, len) = ((N * S) / 4, N * S);
    let mut vec = [f32x4::splat(0.0); KERNEL_COLS / 4];
    let mut tail = [0.0f32; 4];
    for (j, &wyj) in wy.iter().enumerate() {
        let row = &src[start + j * row_len..start + j * row_len + len];
        let w = f32x4::splat(wyj);
        for (v, acc) in vec[..nv].iter_mut().enumerate() {
            *acc += w * load(&row[4 * v..]);
        }
        for (t, &x) in tail.iter_mut().zip(&row[4 * nv..]) {
            *t += wyj * x;
        }
    }
    let mut col = [0.0f32; KERNEL_COLS];
    for (v, acc) in vec[..nv].iter().enumerate() {
        col[4 * v..4 * v + 4].copy_from_slice(&acc.to_array());
    }
    col[4 * nv..len].copy_from_slice(&tail[..len - 4 * nv]);
    col
}
