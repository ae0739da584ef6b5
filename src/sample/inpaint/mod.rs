//! Telea's fast-marching inpainting (A. Telea, "An Image Inpainting Technique Based on the Fast
//! Marching Method", 2004) of holes in channel-interleaved f32 and u8 images: the paper's
//! first-order method ([`TeleaVariant::Paper`]) and an OpenCV-compatible variant
//! ([`TeleaVariant::OpenCv`], what `cv2.inpaint(..., cv2.INPAINT_TELEA)` computes), both through
//! one entry point, [`inpaint`], with [`TeleaOptions`]; `f32` and `u8` images alike
//! ([`InpaintPixel`]). The two variants share the front's machinery (the band, the arrival
//! times, the heap keys).
//!
//! Rooms: `types` (the options and the report), `front` (the shared set-up and the fast
//! marching), `paper` (the paper's method), `opencv` (the OpenCV variant); this front door holds
//! the entry point and the pixel types.
//!
//! # The method
//!
//! The hole is filled from its boundary inwards, in the order of the arrival time `T` of a front
//! that starts on the boundary and moves with unit speed (`|grad T| = 1`, solved with the standard
//! upwind quadratic on the 4-neighbourhood, fast marching with a binary heap and updates of
//! tentative times). The boundary ("band") is the set of known pixels 4-adjacent to a hole pixel,
//! `T = 0`. `T` is also computed outside the hole (negated: a signed distance) for the known
//! pixels near it, as in the paper and OpenCV, so the level-set weight below means something for
//! them.
//!
//! A hole pixel `p` becomes the weighted mean over the available pixels `q` (known, or filled
//! earlier) with `|p - q| <= radius` of the first-order extrapolation
//! `I(q) + grad I(q) . (p - q)`, with weight `dir * dst * lev`:
//! - `dir = |(p - q) / |p - q| . N(p)|`, `N = grad T / |grad T|` (isotropic where `grad T = 0`;
//!   floored at [`DIR_FLOOR`] so no available pixel gets weight zero),
//! - `dst = 1 / |p - q|^2`,
//! - `lev = 1 / (1 + |T(q) - T(p)|)`.
//!
//! `grad I(q)` of a known pixel is a finite difference of known pixels: along each axis the
//! minmod of the forward and backward differences where both neighbours are known (a slope
//! limiter: exact on linear data, zero at extrema, the gentler side across an edge), one-sided
//! where one is, 0 where none is. For a filled pixel it depends on [`GradientTerm`]:
//! - `Propagated` (the default): the weighted mean of the gradients its own value was
//!   extrapolated with. A linear image is reconstructed exactly (to rounding) at any depth, also
//!   at the border. The literal reading (finite differences of filled values) feeds errors back
//!   into the gradients and diverges on large holes: on `sin(x/9) + cos(y/11)` (amplitude 2)
//!   with a 20-pixel-radius hole its max error is 4.7, with propagation 1.0.
//! - `KnownOnly`: filled pixels contribute their value only (zero order).
//! - `Off`: no gradient term at all (a convex combination: never leaves the known range).
//!
//! Measured on the four photographs of `examples/photos` (u8, 10% of the pixels in random
//! discs, RMSE in grey levels, radius 5; `Propagated` / `KnownOnly` / `Off` / OpenCV variant):
//! small discs (radius 1-4): astronaut 14.6 / 14.3 / 18.0 / 18.4, chelsea 8.7 / 8.4 / 10.2 /
//! 10.7, coffee 15.2 / 14.6 / 15.7 / 15.9, rocket 12.4 / 11.8 / 11.5 / 11.6; large discs (radius
//! 5-20): astronaut 36.8 / 32.8 / 33.7 / 33.3, chelsea 27.1 / 20.1 / 20.9 / 20.8, coffee 33.2 /
//! 23.7 / 24.0 / 24.0, rocket 17.3 / 11.6 / 11.0 / 11.1. So on textured photographs with holes
//! deeper than the radius, extrapolating texture gradients far into the hole overshoots;
//! `KnownOnly` is the better choice there, `Propagated` for smooth fields (and what a
//! first-order method promises).
//!
//! Arrival times are computed first (inside and outside), then pixels are filled in order of
//! increasing `T`, ties broken by pixel index (row-major): the order in which the narrow band
//! freezes them. Everything is sequential and deterministic.
//!
//! # The OpenCV variant
//!
//! [`TeleaVariant::OpenCv`] re-implements OpenCV's
//! `modules/photo/src/inpaint.cpp` (4.x/5.x, with the insertion-ordered priority queue) with its
//! quirks, for compatibility with pipelines built on `cv2.inpaint`: the distance weight is
//! `1/|p-q|^3`; the central image gradient is multiplied by 2 instead of 0.5 (and taken on a
//! shifted row/column at the image border); the gradient enters only as the correction
//! `(Jx + Jy) / |J|` (at most sqrt(2), whatever the image's scale) added to the weighted mean of
//! `I(q)`; u8 results are `round_half_even(v + 0.5)`; a hole pixel's `T` is set once, when first
//! reached; the image border counts as known with `T = 1e6` in `grad T`; heap ties go by
//! insertion order; the radius is `round(radius)` clamped to `[1, 100]`. Because the correction is
//! scale-free, on f32 images in [0, 1] it is noise of amplitude ~1 (cv2 turns a constant 0.35
//! into values in [-1.2, 1.8]); on u8 images it is a level or two. On 1-pixel-wide or -high
//! images OpenCV reads outside the image; here those reads are clamped (results differ there).
//! Agreement with cv2 5.0.0: bit-identical on the stored cases of `tests/data/masks/`
//! (u8 grey and RGB, f32 grey).
//!
//! # Edge cases (all variants)
//!
//! - No hole and no non-finite value: nothing is touched or allocated.
//! - f32 pixels with a NaN or infinite value in any channel are treated as hole pixels (reported
//!   in [`InpaintStats::nonfinite`]), so the output never holds NaN or infinity.
//! - Every pixel a hole: there is nothing to propagate from; every value is set to 0 (OpenCV
//!   leaves such an image unchanged) and [`InpaintStats::all_hole`] is set.
//! - `radius` below 1 (or NaN) is treated as 1, above [`MAX_RADIUS`] as [`MAX_RADIUS`].
//! - 1 x N and N x 1 images and holes touching the border are handled (the front reaches every
//!   hole pixel, since the pixel grid is 4-connected and some pixel is known).
//!
//! Cost: a 640 x 480 RGB f32 image with a 10% hole takes about 25-55 ms on one core (radius 3-5).

mod front;
mod opencv;
mod paper;
#[cfg(test)]
mod tests;
mod types;

use front::{check_args, f32_hole, opencv_range, paper_radius, u8_hole};
use opencv::opencv;
use paper::{paper, Pixels};
pub use types::{GradientTerm, InpaintStats, TeleaOptions, TeleaVariant, DIR_FLOOR, MAX_RADIUS};

/// Fills the pixels where `hole` (H x W) is non-zero in `image` (H x W x `channels`, row-major,
/// `f32` or `u8`) with Telea's fast-marching method, the variant and its parameters as `options`
/// say (see the module documentation); known pixels are never changed (except non-finite `f32`
/// ones, which are filled), nor are the pixels of [`TeleaOptions::excluded`] outside the hole.
///
/// # Panics
/// If `channels` is 0 while the image is not empty, if `image.len() != width * height *
/// channels`, if `hole.len() != width * height`, if the image has `u32::MAX` pixels or more, or
/// if [`TeleaOptions::excluded`] is set with [`TeleaVariant::OpenCv`] or differs from `hole` in
/// length.
pub fn inpaint<P: InpaintPixel>(
    image: &mut [P],
    width: usize,
    height: usize,
    channels: usize,
    hole: &[u8],
    options: &TeleaOptions<'_>,
) -> InpaintStats {
    if let Some(excluded) = options.excluded {
        assert!(options.variant == TeleaVariant::Paper, "inpaint: the OpenCV variant reads every known pixel");
        assert_eq!(excluded.len(), hole.len(), "inpaint: the excluded mask and the hole mask differ in size");
    }
    let n = check_args(image.len(), width, height, channels, hole.len());
    let Some((is_hole, mut stats)) = P::holes(image, n, channels, hole) else {
        return InpaintStats::default();
    };
    if stats.all_hole {
        image.fill(P::ZERO);
        return stats;
    }
    stats.max_distance = P::fill(image, width, height, channels, &is_hole, options);
    stats
}

/// A pixel value type [`inpaint`] fills: `f32` (NaN and infinite values are filled too, and
/// counted in [`InpaintStats::nonfinite`]) or `u8` (computed in f32; the paper's method rounds a
/// filled value to the nearest integer and clamps it to `[0, 255]`, the OpenCV variant rounds as
/// OpenCV does). Sealed: these two only.
pub trait InpaintPixel: sealed::Pixel {}

impl InpaintPixel for f32 {}
impl InpaintPixel for u8 {}

mod sealed {
    use super::{InpaintStats, TeleaOptions};

    /// How a pixel type finds its hole pixels and is filled.
    pub trait Pixel: Copy {
        /// The value of every pixel of an image that is all hole.
        const ZERO: Self;
        /// The pixels to fill and the report so far; `None` when there is none.
        fn holes(image: &[Self], n: usize, channels: usize, hole: &[u8]) -> Option<(Vec<bool>, InpaintStats)>;
        /// Fills the pixels of `is_hole` (at least one pixel is known); the largest arrival time.
        fn fill(
            image: &mut [Self],
            width: usize,
            height: usize,
            channels: usize,
            is_hole: &[bool],
            options: &TeleaOptions<'_>,
        ) -> f32;
    }
}

impl sealed::Pixel for f32 {
    const ZERO: f32 = 0.0;

    fn holes(image: &[f32], n: usize, channels: usize, hole: &[u8]) -> Option<(Vec<bool>, InpaintStats)> {
        f32_hole(image, n, channels, hole)
    }

    fn fill(
        image: &mut [f32],
        width: usize,
        height: usize,
        channels: usize,
        is_hole: &[bool],
        options: &TeleaOptions<'_>,
    ) -> f32 {
        match options.variant {
            TeleaVariant::Paper => {
                let pixels = Pixels { is_hole, excluded: options.excluded };
                paper(image, width, height, channels, pixels, paper_radius(options.radius), options.gradient)
            }
            TeleaVariant::OpenCv => opencv(image, width, height, channels, is_hole, opencv_range(options.radius)),
        }
    }
}

impl sealed::Pixel for u8 {
    const ZERO: u8 = 0;

    fn holes(_image: &[u8], n: usize, _channels: usize, hole: &[u8]) -> Option<(Vec<bool>, InpaintStats)> {
        u8_hole(n, hole)
    }

    /// The paper's method computed in f32, filled values rounded to the nearest integer and
    /// clamped (known pixels are left bit-identical); the OpenCV variant with OpenCV's rounding.
    fn fill(
        image: &mut [u8],
        width: usize,
        height: usize,
        channels: usize,
        is_hole: &[bool],
        options: &TeleaOptions<'_>,
    ) -> f32 {
        if options.variant == TeleaVariant::OpenCv {
            return opencv(image, width, height, channels, is_hole, opencv_range(options.radius));
        }
        let mut work: Vec<f32> = image.iter().map(|&v| f32::from(v)).collect();
        let pixels = Pixels { is_hole, excluded: options.excluded };
        let max_distance =
            paper(&mut work, width, height, channels, pixels, paper_radius(options.radius), options.gradient);
        for (i, _) in is_hole.iter().enumerate().filter(|(_, &h)| h) {
            for ch in 0..channels {
                let k = i * channels + ch;
                // `as` saturates; the value is finite here
                image[k] = work[k].round().clamp(0.0, 255.0) as u8;
            }
        }
        max_distance
    }
}
