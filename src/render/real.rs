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
    #[inline(always)]
    fn exp_neg(x: Self) -> Self {
        let cap = Self::of(80.0);
        (-(if x < cap { x } else { cap })).exp()
    }
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
}
