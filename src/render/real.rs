//! The scalar type of the per-pixel loops: f32 for production, f64 for accuracy references.

use std::ops::{AddAssign, MulAssign};

use super::simd::{EXP2_TAYLOR, KERNEL_COLS};

pub trait Real: num_traits::Float + AddAssign + MulAssign + Send + Sync + Default + 'static {
    fn of(x: f64) -> Self;
    fn of32(x: f32) -> Self;
    fn f32(self) -> f32;
    fn f64(self) -> f64;

    /// exp(-x) for x >= 0, with the argument capped at 80: exp(-80) ~ 1.8e-35 is 0 for every
    /// use here (1 - it rounds to 1 in f32 and f64), and the cap keeps libm off its slow
    /// underflow path, which opaque planes (sigma * delta in the thousands) would hit.
    fn exp_neg(x: Self) -> Self;

    /// Whether the loops may take four pixels at once in `f32x4` lanes (`f32`; the lanes do the
    /// scalar formulas' operations, so the bits are the same); `f64` runs the scalar loops.
    const LANES: bool = false;

    /// Bilinear interpolation of four channels: per channel, top = a + wx (b - a),
    /// bot = c + wx (d - c), top + wy (bot - top) (`Tap::sample1`'s arithmetic); `a`..`d`
    /// are the four pixels' channels (at least 4 values each). `f32` does the four at once
    /// ([`super::simd::lerp4`], the same bits).
    #[inline(always)]
    fn lerp4(a: &[f32], b: &[f32], c: &[f32], d: &[f32], wx: Self, wy: Self) -> [Self; 4] {
        std::array::from_fn(|k| {
            let top = Self::of32(a[k]) + wx * (Self::of32(b[k]) - Self::of32(a[k]));
            let bot = Self::of32(c[k]) + wx * (Self::of32(d[k]) - Self::of32(c[k]));
            top + wy * (bot - top)
        })
    }

    /// The column sums of a separable kernel over `N` rows of `N` pixels of `S` values each,
    /// rows `row_len` apart from `src[start]`: value `m` (< N S) of the result is the sum over the
    /// rows j = 0, 1, .. (in order, from 0) of wy[j] times value `m` of row j; the rest is 0.
    /// `f32` takes four values at once ([`super::simd::kernel_cols`], the same bits).
    #[inline(always)]
    fn kernel_cols<const N: usize, const S: usize>(
        src: &[f32],
        start: usize,
        row_len: usize,
        wy: &[Self; N],
    ) -> [Self; KERNEL_COLS] {
        let mut col = [Self::zero(); KERNEL_COLS];
        for (j, &wyj) in wy.iter().enumerate() {
            let at = start + j * row_len;
            for (c, &v) in col[..N * S].iter_mut().zip(&src[at..at + N * S]) {
                *c += wyj * Self::of32(v);
            }
        }
        col
    }
}

/// exp(-x) in f32 for x in [0, 80], inlined: 2^(-x log2 e) split into an integer power (set in
/// the exponent bits) and a degree-6 polynomial for 2^f, f in [-0.5, 0.5]. Absolute error below
/// 2e-7 over the whole range (what matters for alpha = 1 - exp(-sigma delta)); the relative error
/// grows to about 5e-6 near x = 80 from the f32 argument reduction, on values below 1e-34.
#[inline(always)]
fn exp_neg_f32(x: f32) -> f32 {
    let x = if x < 80.0 { x } else { 80.0 }; // NaN becomes 80
    let x = if x > 0.0 { x } else { 0.0 };
    let t = -x * std::f32::consts::LOG2_E;
    // round to nearest with the 1.5 * 2^23 trick (no libm call without SSE4.1)
    let n = (t + 12_582_912.0) - 12_582_912.0;
    // f in [-0.5, 0.5]
    let f = t - n;
    const C: [f32; 7] = EXP2_TAYLOR;
    let p = C[0] + f * (C[1] + f * (C[2] + f * (C[3] + f * (C[4] + f * (C[5] + f * C[6])))));
    // n in [-116, 0]; 2^n as f32 bits, split in two factors to stay in the normal range
    let n = n as i32;
    let half = n / 2;
    let a = f32::from_bits(((127 + half) as u32) << 23);
    let b = f32::from_bits(((127 + n - half) as u32) << 23);
    p * a * b
}

impl Real for f32 {
    const LANES: bool = true;
    #[inline(always)]
    fn of(x: f64) -> Self {
        x as f32
    }
    #[inline(always)]
    fn of32(x: f32) -> Self {
        x
    }
    #[inline(always)]
    fn f32(self) -> f32 {
        self
    }
    #[inline(always)]
    fn f64(self) -> f64 {
        self as f64
    }
    #[inline(always)]
    fn exp_neg(x: Self) -> Self {
        exp_neg_f32(x)
    }
    #[inline(always)]
    fn lerp4(a: &[f32], b: &[f32], c: &[f32], d: &[f32], wx: Self, wy: Self) -> [Self; 4] {
        super::simd::lerp4(a, b, c, d, wx, wy)
    }
    #[inline(always)]
    fn kernel_cols<const N: usize, const S: usize>(
        src: &[f32],
        start: usize,
        row_len: usize,
        wy: &[Self; N],
    ) -> [Self; KERNEL_COLS] {
        super::simd::kernel_cols::<N, S>(src, start, row_len, wy)
    }
}

impl Real for f64 {
    #[inline(always)]
    fn of(x: f64) -> Self {
        x
    }
    #[inline(always)]
    fn of32(x: f32) -> Self {
        x as f64
    }
    #[inline(always)]
    fn f32(self) -> f32 {
        self as f32
    }
    #[inline(always)]
    fn f64(self) -> f64 {
        self
    }
    #[inline(always)]
    fn exp_neg(x: Self) -> Self {
        (-x.clamp(0.0, 80.0)).exp()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_exp_is_accurate() {
        let (mut worst_abs, mut worst_rel) = (0.0f64, 0.0f64);
        let mut x = 0.0f32;
        while x <= 80.0 {
            let got = f32::exp_neg(x) as f64;
            let want = (-(x as f64)).exp();
            worst_abs = worst_abs.max((got - want).abs());
            worst_rel = worst_rel.max((got - want).abs() / want);
            x += 0.000_37;
        }
        assert!(worst_abs < 2e-7, "absolute error {worst_abs}");
        assert!(worst_rel < 1e-5, "relative error {worst_rel}");
        assert_eq!(f32::exp_neg(0.0), 1.0);
        assert!(f32::exp_neg(1e30) < 1e-34 && f32::exp_neg(f32::INFINITY) < 1e-34);
        assert!((0.0..=1.0).contains(&f32::exp_neg(f32::NAN)), "NaN maps into [0, 1]");
        assert!((f64::exp_neg(1.0) - (-1.0f64).exp()).abs() < 1e-16);
    }

    /// A deterministic spread of test values: magnitudes over many binades, both signs, zeros.
    fn values(n: usize, seed: u64) -> Vec<f32> {
        let mut x = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..n)
            .map(|i| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                let unit = (x >> 40) as f32 / (1u64 << 24) as f32; // [0, 1)
                match i % 7 {
                    0 => 0.0,
                    1 => -unit,
                    2 => unit * 1e3,
                    3 => unit * 1e-3,
                    _ => unit * 1.5 - 0.25,
                }
            })
            .collect()
    }

    /// The four-lane exponential gives `exp_neg_f32`'s bits: over the random spread, every
    /// binade of [0, 80] and the special values (zeros, negatives, the cap, NaN, infinities).
    #[test]
    fn vector_exp_matches_the_scalar_one_bit_for_bit() {
        let mut xs: Vec<f32> = [0.0, -0.0, 1e-45, 1e-38, 0.5, 1.0, 79.999, 80.0, 80.001, 1e30, f32::MAX]
            .into_iter()
            .chain([f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -1.0, -1e30])
            .collect();
        xs.extend((0..2000).flat_map(|s| values(8, s)).map(|v| v * 80.0));
        let mut x = 1e-30f32;
        while x < 100.0 {
            xs.push(x);
            x *= 1.37;
        }
        for c in xs.chunks(4) {
            let mut v = [0.0f32; 4];
            v[..c.len()].copy_from_slice(c);
            let got = super::super::simd::exp_neg4(wide::f32x4::from(v)).to_array();
            for (k, &x) in v.iter().enumerate() {
                assert_eq!(got[k].to_bits(), exp_neg_f32(x).to_bits(), "exp(-{x})");
            }
        }
    }

    /// The four-lane tap gives the scalar formula's bits: the vector path is tested against the
    /// scalar reference it replaces (also end to end: the renders' bytes did not change).
    #[test]
    fn vector_taps_match_the_scalar_formulas_bit_for_bit() {
        // `Tap::sample1`'s formula, channel by channel
        let scalar = |a: &[f32], b: &[f32], c: &[f32], d: &[f32], wx: f32, wy: f32| -> [f32; 4] {
            std::array::from_fn(|k| {
                let top = a[k] + wx * (b[k] - a[k]);
                let bot = c[k] + wx * (d[k] - c[k]);
                top + wy * (bot - top)
            })
        };
        for seed in 0..2000u64 {
            let v = values(18, seed);
            let (px, w) = v.split_at(16);
            let (wx, wy) = (w[0].abs().fract(), w[1].abs().fract());
            let got = f32::lerp4(&px[0..4], &px[4..8], &px[8..12], &px[12..16], wx, wy);
            let want = scalar(&px[0..4], &px[4..8], &px[8..12], &px[12..16], wx, wy);
            assert_eq!(got.map(f32::to_bits), want.map(f32::to_bits), "lerp4, seed {seed}");
        }
    }

    /// The four-value column sums of the colour kernels give the scalar formula's bits, for
    /// every shape the kernels use (4 and 6 taps of 3 and 4 values; 18 values leave a tail of 2).
    #[test]
    fn vector_column_sums_match_the_scalar_formula_bit_for_bit() {
        fn check<const N: usize, const S: usize>(seed: u64) {
            let row_len = N * S + 5;
            let src = values(N * row_len + 3, seed);
            let wy: [f32; N] = std::array::from_fn(|j| values(1, seed * 31 + j as u64)[0].abs().fract());
            let got = f32::kernel_cols::<N, S>(&src, 3, row_len, &wy);
            let mut want = [0.0f32; KERNEL_COLS];
            for (j, &w) in wy.iter().enumerate() {
                for m in 0..N * S {
                    want[m] += w * src[3 + j * row_len + m];
                }
            }
            assert_eq!(got.map(f32::to_bits), want.map(f32::to_bits), "N {N}, S {S}, seed {seed}");
        }
        for seed in 0..500u64 {
            check::<4, 3>(seed);
            check::<4, 4>(seed);
            check::<6, 3>(seed);
            check::<6, 4>(seed);
        }
    }
}
