//! The scalar type of the per-pixel loops: f32 for production, f64 for accuracy references.

use std::ops::{AddAssign, MulAssign};

pub trait Real: num_traits::Float + AddAssign + MulAssign + Send + Sync + Default + 'static {
    fn of(x: f64) -> Self;
    fn of32(x: f32) -> Self;
    fn f32(self) -> f32;
    fn f64(self) -> f64;

    /// exp(-x) for x >= 0, with the argument capped at 80: exp(-80) ~ 1.8e-35 is 0 for every
    /// use here (1 - it rounds to 1 in f32 and f64), and the cap keeps libm off its slow
    /// underflow path, which opaque planes (sigma * delta in the thousands) would hit.
    fn exp_neg(x: Self) -> Self;
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
    let f = t - n; // [-0.5, 0.5]
                   // 2^f = e^(f ln2), Taylor coefficients of e^y with y = f ln 2
    const C: [f32; 7] =
        [1.0, std::f32::consts::LN_2, 0.240_226_5, 0.055_504_11, 0.009_618_129, 0.001_333_355_8, 0.000_154_035_3];
    let p = C[0] + f * (C[1] + f * (C[2] + f * (C[3] + f * (C[4] + f * (C[5] + f * C[6])))));
    // n in [-116, 0]; 2^n as f32 bits, split in two factors to stay in the normal range
    let n = n as i32;
    let half = n / 2;
    let a = f32::from_bits(((127 + half) as u32) << 23);
    let b = f32::from_bits(((127 + n - half) as u32) << 23);
    p * a * b
}

impl Real for f32 {
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
}
