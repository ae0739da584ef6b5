//! Resampling kernels for the colour of the exact-mode target render ([`Resample`]) and the cubic
//! B-spline prefilters ([`bspline_coefficients`]).
//!
//! Every target ray samples each plane it meets at a sub-pixel point q. Bilinear interpolation
//! (the public reference's choice) is a low-pass filter: one bilinear resampling at a random
//! sub-pixel shift keeps well under half of a photo's Laplacian energy, so image2 came out much
//! blurrier than image1 (figures in docs/quality.md). The higher-order kernels here are
//! separable, evaluated over an N x N neighbourhood of q (N = 4 for the cubics, 6 for Lanczos-3):
//!
//! - [`Resample::Bilinear`]: 2 x 2 taps, the reference's formula (bit-identical to the renderer
//!   before this option existed).
//! - [`Resample::Bicubic`]: Keys' cubic convolution with a = -1/2 (Catmull-Rom), interpolating,
//!   reproduces quadratics, rings slightly (lobes of -1/16).
//! - [`Resample::Bspline3`]: cubic B-spline *interpolation*: the plane's colour is first turned
//!   into B-spline coefficients by the recursive prefilter of Unser (pole sqrt(3) - 2, mirror
//!   boundaries; [`bspline_coefficients`]) and then evaluated with the B-spline basis. Much
//!   closer to the ideal reconstruction than bicubic convolution; the prefilter is computed once
//!   per scene and kept with the MPI ([`crate::mpi::Mpi::bspline_rgb`], set by
//!   `sample::recipe::prepare_scene` through [`prefilter_arc`], so it lives in the scene cache;
//!   only the 16 x 16 blocks where the plane has density, [`bspline_bricks`]); a render of an MPI
//!   without it computes it for that render.
//! - [`Resample::Bspline5`]: quintic B-spline interpolation over 6 x 6 taps (prefilter poles
//!   -0.4306 and -0.0431), sharper still.
//! - [`Resample::Lanczos3`]: windowed sinc over 6 x 6 taps, weights normalised to sum 1.
//! - [`Resample::Omoms3`]: OMOMS-3 interpolation (Blu, Thevenaz and Unser, "MOMS: maximal-order
//!   interpolation of minimal support", 2001): the cubic B-spline plus 1/42 of its second
//!   derivative, prefiltered like the B-spline (pole (sqrt(105) - 13) / 8), over the same 4 x 4
//!   taps; of the cubics of that support the one closest to ideal reconstruction.
//!
//! Only colour uses the kernel. Density (and so alpha, coverage and depth) and the extra
//! (mask) channels stay bilinear, a kernel that cannot ring: they stay within their bounds, and
//! they are bit-identical to the bilinear render's, so the labels and flow do not depend on the
//! kernel. Each plane's colour sample is clamped to [0, 1] (the ringing of the higher-order
//! kernels at edges), so the composite stays within [0, coverage]. Indices outside the frame are
//! mirrored (whole-sample symmetric, the prefilter's boundary condition). The reference mode
//! ignores this option: it is bilinear formula for formula.

use rayon::prelude::*;

use super::real::Real;
use super::tap::floor_index;
use super::types::{Prefilter, Resample};
use crate::mpi::bricks::{BlockGrid, Bricks};
use crate::mpi::Mpi;

/// The weights of a separable kernel at fractional offset `t` in [0, 1) from the tap
/// `floor(q)`; tap `k` sits at `floor(q) + k - (N / 2 - 1)`.
pub(crate) trait Kernel<const N: usize>: Sync {
    /// The prefiltered cubic whose weights the sixteen-lane target loop evaluates itself
    /// (`render::exact::row16`: [`Bspline3`] and [`Omoms3`]); `None` for the others.
    const ROW16: Option<Prefilter> = None;

    fn weights<T: Real>(t: T) -> [T; N];

    /// [`Self::weights`] of four fractions at once (`f32`, the same bits): `[k][lane]`.
    #[inline(always)]
    fn weights4(t: wide::f32x4) -> [[f32; 4]; N] {
        let per_lane = t.to_array().map(Self::weights::<f32>);
        std::array::from_fn(|k| std::array::from_fn(|lane| per_lane[lane][k]))
    }
}

pub(crate) struct Keys;
pub(crate) struct Bspline3;
pub(crate) struct Omoms3;
pub(crate) struct Lanczos3;
pub(crate) struct Bspline5;

impl Kernel<6> for Bspline5 {
    #[inline(always)]
    fn weights<T: Real>(t: T) -> [T; 6] {
        // beta5 at the distances |t + 2 - k| of the taps k = 0..5
        let b = |x: T| -> T {
            let x = x.abs();
            let (x2, x4) = (x * x, x * x * x * x);
            if x < T::one() {
                T::of(11.0 / 20.0) - x2 * T::of(0.5) + x4 * T::of(0.25) - x4 * x / T::of(12.0)
            } else if x < T::of(2.0) {
                T::of(17.0 / 40.0) + x * T::of(5.0 / 8.0) - x2 * T::of(7.0 / 4.0) + x2 * x * T::of(5.0 / 4.0)
                    - x4 * T::of(3.0 / 8.0)
                    + x4 * x / T::of(24.0)
            } else if x < T::of(3.0) {
                let u = T::of(3.0) - x;
                u * u * u * u * u / T::of(120.0)
            } else {
                T::zero()
            }
        };
        std::array::from_fn(|k| b(t + T::of(2.0) - T::of(k as f64)))
    }
}

impl Kernel<4> for Keys {
    #[inline(always)]
    fn weights<T: Real>(t: T) -> [T; 4] {
        let h = T::of(0.5);
        let (t2, t3) = (t * t, t * t * t);
        [
            -h * t3 + t2 - h * t,
            T::of(1.5) * t3 - T::of(2.5) * t2 + T::one(),
            T::of(-1.5) * t3 + T::of(2.0) * t2 + h * t,
            h * t3 - h * t2,
        ]
    }
}

impl Kernel<4> for Bspline3 {
    const ROW16: Option<Prefilter> = Some(Prefilter::Bspline3);

    #[inline(always)]
    fn weights<T: Real>(t: T) -> [T; 4] {
        let s = T::one() / T::of(6.0);
        let u = T::one() - t;
        let (t2, t3) = (t * t, t * t * t);
        [
            u * u * u * s,
            (T::of(3.0) * t3 - T::of(6.0) * t2 + T::of(4.0)) * s,
            (T::of(-3.0) * t3 + T::of(3.0) * t2 + T::of(3.0) * t + T::one()) * s,
            t3 * s,
        ]
    }

    /// [`Self::weights`]' operations in lanes.
    #[inline(always)]
    fn weights4(t: wide::f32x4) -> [[f32; 4]; 4] {
        use wide::f32x4;
        let c = f32x4::splat;
        let s = c(1.0f32 / 6.0);
        let u = c(1.0) - t;
        let (t2, t3) = (t * t, t * t * t);
        [
            u * u * u * s,
            (c(3.0) * t3 - c(6.0) * t2 + c(4.0)) * s,
            (c(-3.0) * t3 + c(3.0) * t2 + c(3.0) * t + c(1.0)) * s,
            t3 * s,
        ]
        .map(f32x4::to_array)
    }
}

impl Kernel<4> for Omoms3 {
    const ROW16: Option<Prefilter> = Some(Prefilter::Omoms3);

    #[inline(always)]
    fn weights<T: Real>(t: T) -> [T; 4] {
        // omega(x) = beta3(x) + beta3''(x) / 42 at the distances 1 + t, t, 1 - t and 2 - t
        let [b0, b1, b2, b3] = Bspline3::weights(t);
        let (s, u) = (T::one() / T::of(42.0), T::one() - t);
        let two = T::of(2.0);
        let three = T::of(3.0);
        [b0 + u * s, b1 + (three * t - two) * s, b2 + (three * u - two) * s, b3 + t * s]
    }

    /// [`Self::weights`]' operations in lanes.
    #[inline(always)]
    fn weights4(t: wide::f32x4) -> [[f32; 4]; 4] {
        use wide::f32x4;
        let c = f32x4::splat;
        let b = Bspline3::weights4(t).map(f32x4::from);
        let (s, u) = (c(1.0f32 / 42.0), c(1.0) - t);
        [b[0] + u * s, b[1] + (c(3.0) * t - c(2.0)) * s, b[2] + (c(3.0) * u - c(2.0)) * s, b[3] + t * s]
            .map(f32x4::to_array)
    }
}

impl Kernel<6> for Lanczos3 {
    #[inline(always)]
    fn weights<T: Real>(t: T) -> [T; 6] {
        // L(x) = sinc(x) sinc(x / 3) at x = t - k + 2, k = 0..5; with sin(pi (t + m)) =
        // (-1)^m sin(pi t) one sine of each argument family is enough
        let pi = T::of(std::f64::consts::PI);
        let mut w = [T::zero(); 6];
        if t < T::of(1e-6) {
            w[2] = T::one();
            return w;
        }
        let mut sum = T::zero();
        for (k, wk) in w.iter_mut().enumerate() {
            let x = t + T::of(2.0) - T::of(k as f64);
            let px = pi * x;
            let v = T::of(3.0) * (px).sin() * (px / T::of(3.0)).sin() / (px * px);
            *wk = v;
            sum += v;
        }
        for wk in &mut w {
            *wk = *wk / sum;
        }
        w
    }
}

/// Index `i` of the whole-sample symmetric extension of a line of `n` (period 2n - 2).
#[inline(always)]
fn mirror(i: isize, n: usize) -> usize {
    if n < 2 {
        return 0;
    }
    let last = n as isize - 1;
    let j = i.rem_euclid(2 * last);
    (if j > last { 2 * last - j } else { j }) as usize
}

/// Colour of one plane at `(qx, qy)` (clamped to [0, W-1] x [0, H-1]) with kernel `K`, from
/// `src` holding `S` values per pixel (colour in the first three), each channel clamped to
/// [0, 1]. Neighbourhoods inside the frame read contiguous rows; the others mirror their
/// indices (the same values).
#[inline(always)]
pub(crate) fn sample_rgb<T: Real, K: Kernel<N>, const N: usize, const S: usize>(
    src: &[f32],
    qx: T,
    qy: T,
    w: usize,
    h: usize,
) -> [T; 3] {
    // q >= 0 here, so truncation is floor
    let (x0, y0) = (floor_index(qx.f32(), w), floor_index(qy.f32(), h));
    sample_rgb_at::<T, K, N, S>(src, x0, y0, qx - T::of(x0 as f64), qy - T::of(y0 as f64), w, h)
}

/// [`sample_rgb`] at the pixel (x0, y0) that q truncates to and the fractions fx = qx - x0,
/// fy = qy - y0 (a bilinear tap's, `Tap`, which the render has at hand).
#[inline(always)]
pub(crate) fn sample_rgb_at<T: Real, K: Kernel<N>, const N: usize, const S: usize>(
    src: &[f32],
    x0: usize,
    y0: usize,
    fx: T,
    fy: T,
    w: usize,
    h: usize,
) -> [T; 3] {
    sample_rgb_weighted::<T, N, S>(src, x0, y0, &K::weights(fx), &K::weights(fy), w, h)
}

/// [`sample_rgb_at`] with the kernel's weights at the fractions given (`wx`, `wy`).
#[inline(always)]
pub(crate) fn sample_rgb_weighted<T: Real, const N: usize, const S: usize>(
    src: &[f32],
    x0: usize,
    y0: usize,
    wx: &[T; N],
    wy: &[T; N],
    w: usize,
    h: usize,
) -> [T; 3] {
    let off = N / 2 - 1;
    let acc = if x0 >= off && x0 + N - off <= w && y0 >= off && y0 + N - off <= h {
        kernel_rows::<T, N, S>(src, S * ((y0 - off) * w + x0 - off), S * w, wx, wy)
    } else {
        // the same sums in the same order over the mirrored pixels
        let xs: [usize; N] = std::array::from_fn(|k| S * mirror(x0 as isize + k as isize - off as isize, w));
        let mut col = [[T::zero(); 3]; N];
        for (j, &wyj) in wy.iter().enumerate() {
            let row = &src[S * w * mirror(y0 as isize + j as isize - off as isize, h)..];
            for (&xi, ck) in xs.iter().zip(&mut col) {
                for (c, v) in ck.iter_mut().enumerate() {
                    *v += wyj * T::of32(row[xi + c]);
                }
            }
        }
        let mut acc = [T::zero(); 3];
        for (ck, &wxk) in col.iter().zip(wx) {
            for (a, &v) in acc.iter_mut().zip(ck) {
                *a += wxk * v;
            }
        }
        acc
    };
    acc.map(|v| v.max(T::zero()).min(T::one()))
}

/// [`sample_rgb_weighted`] of plane `i` from block-sparse coefficients (3 values per pixel; the
/// blocks' aprons hold the mirrored values, so every neighbourhood reads one block): the same
/// bits as the dense coefficients'. `None` where the block is not stored.
#[inline(always)]
pub(crate) fn sample_rgb_bricks_weighted<T: Real, const N: usize>(
    b: &Bricks,
    i: usize,
    x0: usize,
    y0: usize,
    wx: &[T; N],
    wy: &[T; N],
) -> Option<[T; 3]> {
    let (data, start) = b.neighbourhood(i, x0, y0)?;
    let acc = kernel_rows::<T, N, 3>(data, start, b.row_len(), wx, wy);
    Some(acc.map(|v| v.max(T::zero()).min(T::one())))
}

/// A separable kernel over N rows of N pixels of `S` values (colour in the first three) from
/// `src[start]`, rows `row_len` apart: the column sums first (per pixel k and channel,
/// col = sum over the rows j of wy[j] px_jk, j = 0.., [`Real::kernel_cols`]), then per channel
/// acc = sum over k of wx[k] col_k (k = 0..). Every path of every kernel sums in this order.
#[inline(always)]
fn kernel_rows<T: Real, const N: usize, const S: usize>(
    src: &[f32],
    start: usize,
    row_len: usize,
    wx: &[T; N],
    wy: &[T; N],
) -> [T; 3] {
    let col = T::kernel_cols::<N, S>(src, start, row_len, wy);
    let mut acc = [T::zero(); 3];
    for (k, &wxk) in wx.iter().enumerate() {
        for (c, a) in acc.iter_mut().enumerate() {
            *a += wxk * col[S * k + c];
        }
    }
    acc
}

/// A still RGB image as a quintic B-spline that can be sampled anywhere: the high-order
/// reference warp of the quality report (image1 resampled "ideally" by a sample's geometry, to
/// separate what the colour kernel loses from what the geometry does; `bench::quality`). The
/// same prefilter and kernel as [`Resample::Bspline5`].
pub struct SplineImage {
    coefficients: Vec<f32>,
    width: usize,
    height: usize,
}

impl SplineImage {
    /// `rgb`: interleaved RGB in [0, 1], `width` x `height` (both at least 1).
    ///
    /// # Panics
    /// If `rgb` is not `3 width height` values long.
    pub fn new(rgb: &[f32], width: usize, height: usize) -> Self {
        assert_eq!(rgb.len(), 3 * width * height, "SplineImage: buffer size");
        let mut mpi = Mpi::new(width, height, vec![1.0], 0);
        for (d, s) in mpi.plane_rgba_mut(0).chunks_exact_mut(4).zip(rgb.chunks_exact(3)) {
            d[..3].copy_from_slice(s);
        }
        Self { coefficients: bspline_coefficients(&mpi, Prefilter::Bspline5), width, height }
    }

    /// The colour at `(x, y)` (clamped to the frame), each channel clamped to [0, 1].
    pub fn sample(&self, x: f32, y: f32) -> [f32; 3] {
        let x = x.clamp(0.0, (self.width - 1) as f32);
        let y = y.clamp(0.0, (self.height - 1) as f32);
        sample_rgb::<f32, Bspline5, 6, 3>(&self.coefficients, x, y, self.width, self.height)
    }
}

/// Computes the B-spline coefficients `resample` needs (if any, and if `mpi` does not hold them
/// already) and keeps them in [`Mpi::bspline_rgb`]: the blocks the colour kernel can reach
/// ([`bspline_bricks`] with `sparse`), the same colours as all of them.
pub fn prefilter(mpi: &mut Mpi, resample: Resample) {
    if let Some(prefilter) = resample.prefilter() {
        if mpi.bspline_rgb.as_ref().is_none_or(|c| c.prefilter != prefilter) {
            let coefficients = std::sync::Arc::new(bspline_bricks(mpi, prefilter, true));
            mpi.bspline_rgb = Some(crate::mpi::BsplineRgb { prefilter, coefficients });
        }
    }
}

/// [`prefilter`] of a shared MPI (copied first only when it needs the coefficients and others
/// hold it).
pub fn prefilter_arc(mpi: &mut std::sync::Arc<Mpi>, resample: Resample) {
    if let Some(prefilter) = resample.prefilter() {
        if mpi.bspline_rgb.as_ref().is_none_or(|c| c.prefilter != prefilter) {
            let coefficients = std::sync::Arc::new(bspline_bricks(mpi, prefilter, true));
            std::sync::Arc::make_mut(mpi).bspline_rgb = Some(crate::mpi::BsplineRgb { prefilter, coefficients });
        }
    }
}

/// The poles of an interpolation prefilter.
fn poles(prefilter: Prefilter) -> &'static [f64] {
    match prefilter {
        Prefilter::Bspline3 => &[-0.267_949_192_431_122_7],
        Prefilter::Bspline5 => &[-0.430_575_347_099_973_8, -0.043_096_288_203_264_65],
        // (sqrt(105) - 13) / 8: the root inside the unit circle of 4 z^2 + 13 z + 4, the
        // sampled kernel (4 z + 13 + 4 / z) / 21
        Prefilter::Omoms3 => &[-0.344_131_154_255_050_3],
    }
}

/// B-spline interpolation coefficients (degree 3 or 5) of the rgb channels of every plane of
/// `mpi` (N x H x W x 3, plane-major, row-major, interleaved): the exact inverse of sampling the
/// B-spline at the pixel centres, with mirror boundaries (Unser, "Fast B-spline transforms for
/// continuous image representation and interpolation", 1991). Computed in f64 per line.
pub fn bspline_coefficients(mpi: &Mpi, prefilter: Prefilter) -> Vec<f32> {
    let mpi = &*mpi.unpacked();
    let (w, h) = (mpi.width, mpi.height);
    let z = poles(prefilter);
    let every = vec![true; w];
    let planes: Vec<Vec<f32>> = (0..mpi.planes())
        .into_par_iter()
        .map_init(Vec::new, |buf, i| {
            let strips = plane_coefficients(mpi.plane_rgba(i), w, h, z, &every, buf);
            let mut out = vec![0.0f32; 3 * w * h];
            for (y, row) in out.chunks_exact_mut(3 * w).enumerate() {
                strips.read(buf, 0, y, row);
            }
            out
        })
        .collect();
    planes.concat()
}

/// Rows of a plane prefiltered at once ([`plane_coefficients`]): their lines side by side, so
/// each step of the recursion runs over `3 ROWS_AT_ONCE` adjacent values.
const ROWS_AT_ONCE: usize = 8;

/// Where [`plane_coefficients`] keeps a plane's values (3 per pixel, f64): in strips of
/// [`Bricks::SIZE`] columns, each strip's rows one after the other, so that a column pass runs
/// down a strip through contiguous memory.
#[derive(Clone, Copy)]
struct Strips {
    width: usize,
    height: usize,
}

impl Strips {
    const WIDTH: usize = Bricks::SIZE;

    /// Strip `s`'s first value and its row length in values.
    fn strip(&self, s: usize) -> (usize, usize) {
        let x0 = s * Self::WIDTH;
        (3 * x0 * self.height, 3 * Self::WIDTH.min(self.width - x0))
    }

    /// The first value of pixel (x, y).
    fn at(&self, x: usize, y: usize) -> usize {
        let (start, row) = self.strip(x / Self::WIDTH);
        start + y * row + 3 * (x % Self::WIDTH)
    }

    /// The values of pixels x, x + 1, ... of row y (`out.len() / 3` of them) as f32.
    fn read(&self, buf: &[f64], x: usize, y: usize, out: &mut [f32]) {
        for (k, o) in out.chunks_exact_mut(3).enumerate() {
            let at = self.at(x + k, y);
            for (o, &v) in o.iter_mut().zip(&buf[at..at + 3]) {
                *o = v as f32;
            }
        }
    }
}

/// [`bspline_coefficients`] of one plane (`rgba`, W x H x 4) into `buf` (resized to fit), laid
/// out as the returned [`Strips`]: every row's three channel lines, then the column lines of the
/// strips that hold a column flagged in `columns` (W flags); the other strips hold their row
/// pass only. Rows go through the recursion [`ROWS_AT_ONCE`] at a time (turned so that their
/// values at one column lie side by side), columns a strip at a time: every line gets the
/// operations of a line alone ([`recurse_lines`]; the [`gain`] is applied as the values are
/// copied in), so the same bits as one line after the other.
fn plane_coefficients(rgba: &[f32], w: usize, h: usize, z: &[f64], columns: &[bool], buf: &mut Vec<f64>) -> Strips {
    assert_eq!(rgba.len(), 4 * w * h, "plane_coefficients: a W x H x 4 plane");
    assert_eq!(columns.len(), w, "plane_coefficients: a flag per column");
    let strips = Strips { width: w, height: h };
    buf.resize(3 * w * h, 0.0);
    let (row_gain, column_gain) = (gain(z, w), gain(z, h));
    let mut turned = vec![0.0f64; 3 * w * ROWS_AT_ONCE];
    for (c, rows) in rgba.chunks(4 * w * ROWS_AT_ONCE).enumerate() {
        let r = rows.len() / (4 * w);
        let m = 3 * r;
        // value x of channel k of row j at turned[x m + 3 j + k]
        for (x, t) in turned.chunks_exact_mut(m).take(w).enumerate() {
            for (j, t) in t.chunks_exact_mut(3).enumerate() {
                let px = &rows[4 * (j * w + x)..4 * (j * w + x) + 3];
                for (t, &v) in t.iter_mut().zip(px) {
                    *t = f64::from(v) * row_gain;
                }
            }
        }
        recurse_lines(&mut turned[..w * m], w, m, m, z);
        for (x, t) in turned.chunks_exact(m).take(w).enumerate() {
            for (j, t) in t.chunks_exact(3).enumerate() {
                let at = strips.at(x, c * ROWS_AT_ONCE + j);
                for (o, &v) in buf[at..at + 3].iter_mut().zip(t) {
                    *o = v * column_gain;
                }
            }
        }
    }
    for (s, held) in columns.chunks(Strips::WIDTH).enumerate() {
        if held.iter().any(|&c| c) {
            let (start, row) = strips.strip(s);
            recurse_lines(&mut buf[start..start + row * h], h, row, row, z);
        }
    }
    strips
}

/// [`bspline_coefficients`] in block-sparse form ([`Bricks`]) with the mirror boundary in each
/// block's apron, so that the kernel's N x N neighbourhood of any anchor pixel in a block is in
/// that block. `sparse`: only the blocks the colour kernel can reach, those of anchor pixels
/// whose bilinear density taps (the pixel and its right, lower and lower-right neighbours) hold
/// any density > 0: the target render asks for a plane's colour only where its bilinear density
/// is > 0 ([`prefilter`]'s blocks); otherwise every block. A plane's column pass runs only over
/// the columns its stored blocks hold.
pub fn bspline_bricks(mpi: &Mpi, prefilter: Prefilter, sparse: bool) -> Bricks {
    let mpi = &*mpi.unpacked();
    let (w, h) = (mpi.width, mpi.height);
    let z = poles(prefilter);
    let n = prefilter.taps();
    let lo = n / 2 - 1;
    let grid = BlockGrid { width: w, height: h, stride: 3, lo, hi: n - 1 - lo };
    let keep = |i: usize| sparse.then(|| super::store::reachable_blocks(mpi, i));
    let fill = |buf: &mut Vec<f64>, i: usize, kept: &[bool], out: &mut [f32]| {
        let columns = held_columns(&grid, kept);
        let strips = plane_coefficients(mpi.plane_rgba(i), w, h, z, &columns, buf);
        grid.copy_blocks(kept, mirror, |x, y, values| strips.read(buf, x, y, values), out);
    };
    Bricks::build_with(grid, mpi.planes(), keep, Vec::new, fill)
}

/// The columns (W flags) whose values the `kept` blocks of `grid` hold, their aprons included,
/// under the mirror boundary.
fn held_columns(grid: &BlockGrid, kept: &[bool]) -> Vec<bool> {
    let (bw, side) = (grid.blocks().0, grid.side());
    let mut columns = vec![false; grid.width];
    for bx in 0..bw {
        if kept.iter().skip(bx).step_by(bw).any(|&k| k) {
            let x0 = (bx * Bricks::SIZE) as isize - grid.lo as isize;
            for u in 0..side {
                columns[mirror(x0 + u as isize, grid.width)] = true;
            }
        }
    }
    columns
}

/// In-place B-spline prefilter (mirror boundaries) of `m` lines of `n` values at once, laid out
/// as in [`recurse_lines`]: the [`gain`], then the recursions.
#[cfg(test)]
fn prefilter_lines(c: &mut [f64], n: usize, m: usize, stride: usize, poles: &[f64]) {
    let g = gain(poles, n);
    for k in 0..n {
        for v in &mut c[k * stride..k * stride + m] {
            *v *= g;
        }
    }
    recurse_lines(c, n, m, stride, poles);
}

/// The prefilter's gain for lines of `n` values: the product over the poles of
/// `(1 - z) (1 - 1 / z)`; 1 for lines of fewer than two values, which the prefilter leaves as
/// they are.
fn gain(poles: &[f64], n: usize) -> f64 {
    if n < 2 {
        return 1.0;
    }
    poles.iter().map(|&z| (1.0 - z) * (1.0 - 1.0 / z)).product()
}

/// The recursions of the B-spline prefilter (mirror boundaries; each pole's causal and
/// anti-causal pass) of `m` lines of `n` values at once, already multiplied by the [`gain`]:
/// `c` holds value k of line j at `c[k stride + j]` (`stride >= m`; so each step runs over `m`
/// adjacent values). Every line gets the operations of a line alone, in the same order, so the
/// same bits.
fn recurse_lines(c: &mut [f64], n: usize, m: usize, stride: usize, poles: &[f64]) {
    assert!(stride >= m, "recurse_lines: lines side by side");
    if n < 2 || m == 0 {
        return;
    }
    assert!(c.len() >= (n - 1) * stride + m, "recurse_lines: n x m values");
    let mut init = vec![0.0f64; m];
    for &z in poles {
        causal_init(c, n, m, stride, z, &mut init);
        c[..m].copy_from_slice(&init);
        for k in 1..n {
            let (before, from_k) = c.split_at_mut(k * stride);
            for (v, &p) in from_k[..m].iter_mut().zip(&before[(k - 1) * stride..]) {
                *v += z * p;
            }
        }
        let a = z / (z * z - 1.0);
        let (before, last) = c.split_at_mut((n - 1) * stride);
        for (v, &p) in last[..m].iter_mut().zip(&before[(n - 2) * stride..]) {
            *v = a * (*v + z * p);
        }
        for k in (0..n - 1).rev() {
            let (upto, after) = c.split_at_mut((k + 1) * stride);
            for (v, &q) in upto[k * stride..k * stride + m].iter_mut().zip(&after[..m]) {
                *v = z * (q - *v);
            }
        }
    }
}

/// Per line j of [`recurse_lines`]' layout, `sum_k c[k] z^k` over the mirrored signal into
/// `out[j]`: truncated where `|z|^k < 1e-12`, exact for short lines.
fn causal_init(c: &[f64], n: usize, m: usize, stride: usize, z: f64, out: &mut [f64]) {
    let at = |k: usize| &c[k * stride..k * stride + m];
    let horizon = ((1e-12f64).ln() / z.abs().ln()).ceil() as usize;
    if horizon < n {
        out.fill(0.0);
        let mut zk = 1.0;
        for k in 0..horizon {
            for (o, &v) in out.iter_mut().zip(at(k)) {
                *o += zk * v;
            }
            zk *= z;
        }
        return;
    }
    // the mirrored signal has period 2n - 2
    let iz = 1.0 / z;
    let mut zk = z;
    let mut z2n = z.powi(n as i32 - 1);
    for ((o, &first), &last) in out.iter_mut().zip(at(0)).zip(at(n - 1)) {
        *o = first + z2n * last;
    }
    z2n = z2n * z2n * iz;
    for k in 1..n - 1 {
        for (o, &v) in out.iter_mut().zip(at(k)) {
            *o += (zk + z2n) * v;
        }
        zk *= z;
        z2n *= iz;
    }
    let d = 1.0 - zk * zk;
    for o in out.iter_mut() {
        *o /= d;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    proptest::proptest! {
        /// The coefficients store exactly the blocks a bilinear density tap can reach, and
        /// `pack` (which reads their table) the same blocks of the planes.
        #[test]
        fn coefficients_and_packed_planes_keep_the_reachable_blocks(
            w in 1usize..70,
            h in 1usize..50,
            dense in proptest::collection::vec(0usize..70 * 50, 0..12),
            resample in proptest::prop_oneof![
                proptest::strategy::Just(Resample::Bspline3),
                proptest::strategy::Just(Resample::Bspline5),
                proptest::strategy::Just(Resample::Omoms3),
            ],
        ) {
            let mut mpi = Mpi::new(w, h, vec![0.5, 0.25], 0);
            for (k, p) in dense.into_iter().enumerate() {
                mpi.plane_rgba_mut(k % 2)[4 * (p % (w * h)) + 3] = 1.0;
            }
            let reach: Vec<Vec<bool>> = (0..2).map(|i| crate::render::store::reachable_blocks(&mpi, i)).collect();
            prefilter(&mut mpi, resample);
            crate::render::store::pack(&mut mpi);
            for (i, r) in reach.iter().enumerate() {
                let coefficients = &mpi.bspline_rgb.as_ref().expect("a B-spline kernel").coefficients;
                proptest::prop_assert_eq!(&coefficients.kept(i), r);
                proptest::prop_assert_eq!(&mpi.rgba_blocks.as_ref().expect("packed").kept(i), r);
            }
        }
    }

    fn eval_line(c: &[f64], x: f64, prefilter: Prefilter) -> f64 {
        let x0 = x.floor();
        let at = |k: isize| c[mirror(x0 as isize + k, c.len())];
        let sum = |w: &[f64], lo: isize| -> f64 { w.iter().enumerate().map(|(k, v)| v * at(k as isize - lo)).sum() };
        match prefilter {
            Prefilter::Bspline3 => sum(&Bspline3::weights(x - x0), 1),
            Prefilter::Omoms3 => sum(&Omoms3::weights(x - x0), 1),
            Prefilter::Bspline5 => sum(&Bspline5::weights(x - x0), 2),
        }
    }

    const PREFILTERS: [Prefilter; 3] = [Prefilter::Bspline3, Prefilter::Bspline5, Prefilter::Omoms3];

    /// The prefilter of one line alone.
    fn prefilter_line(c: &mut [f64], poles: &[f64]) {
        let n = c.len();
        prefilter_lines(c, n, 1, 1, poles);
    }

    /// Lines prefiltered together (as the column pass does) get each line's bits alone, for
    /// short lines (the exact mirrored start) and long ones (the truncated start).
    #[test]
    fn lines_at_once_are_each_line_alone() {
        for degree in PREFILTERS {
            for n in [2usize, 3, 7, 30, 64, 200] {
                for m in [1usize, 2, 3, 7] {
                    let all: Vec<f64> = (0..n * m).map(|i| ((i * 7919 + 17) % 101) as f64 / 101.0 - 0.3).collect();
                    let mut together = all.clone();
                    prefilter_lines(&mut together, n, m, m, poles(degree));
                    for j in 0..m {
                        let mut alone: Vec<f64> = (0..n).map(|k| all[k * m + j]).collect();
                        prefilter_line(&mut alone, poles(degree));
                        for k in 0..n {
                            assert_eq!(
                                together[k * m + j].to_bits(),
                                alone[k].to_bits(),
                                "{degree:?} n {n} m {m} line {j}"
                            );
                        }
                    }
                }
            }
        }
    }

    /// A plane's coefficients (rows turned and filtered together, columns in strips, the gain
    /// applied on the way in) are the bits of every row line alone and then every column line
    /// alone, for any size (one pixel, one row or column, partial strips and row groups); with
    /// some columns flagged, the strips that hold them.
    #[test]
    fn plane_coefficients_are_each_line_alone() {
        for degree in PREFILTERS {
            let z = poles(degree);
            for (w, h) in [(1usize, 1usize), (1, 6), (7, 1), (2, 2), (17, 9), (37, 23), (40, 33)] {
                let rgba: Vec<f32> = (0..4 * w * h).map(|i| ((i * 7919 + 13) % 97) as f32 / 97.0 - 0.2).collect();
                let mut want: Vec<f64> =
                    rgba.chunks_exact(4).flat_map(|p| p[..3].iter().map(|&v| f64::from(v))).collect();
                for y in 0..h {
                    for k in 0..3 {
                        let mut line: Vec<f64> = (0..w).map(|x| want[3 * (y * w + x) + k]).collect();
                        prefilter_line(&mut line, z);
                        for (x, v) in line.into_iter().enumerate() {
                            want[3 * (y * w + x) + k] = v;
                        }
                    }
                }
                for x in 0..w {
                    for k in 0..3 {
                        let mut line: Vec<f64> = (0..h).map(|y| want[3 * (y * w + x) + k]).collect();
                        prefilter_line(&mut line, z);
                        for (y, v) in line.into_iter().enumerate() {
                            want[3 * (y * w + x) + k] = v;
                        }
                    }
                }
                let some: Vec<bool> = (0..w).map(|x| x == w - 1 || x == 16).collect();
                for columns in [vec![true; w], some] {
                    let mut buf = Vec::new();
                    let strips = plane_coefficients(&rgba, w, h, z, &columns, &mut buf);
                    for y in 0..h {
                        for x in (0..w).filter(|&x| columns[x - x % 16..(x - x % 16 + 16).min(w)].contains(&true)) {
                            let at = strips.at(x, y);
                            for k in 0..3 {
                                let (got, want) = (buf[at + k], want[3 * (y * w + x) + k]);
                                assert_eq!(got.to_bits(), want.to_bits(), "{degree:?}, {w} x {h}, ({x}, {y}) {k}");
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn prefilter_interpolates_at_the_samples() {
        for degree in PREFILTERS {
            for n in [2usize, 3, 4, 5, 17, 40, 100] {
                let s: Vec<f64> = (0..n).map(|i| ((i * 7919) % 13) as f64 / 13.0).collect();
                let mut c = s.clone();
                prefilter_line(&mut c, poles(degree));
                for (i, &v) in s.iter().enumerate() {
                    let got = eval_line(&c, i as f64, degree);
                    assert!((got - v).abs() < 1e-9, "{degree:?} n {n} i {i}: {got} vs {v}");
                }
            }
        }
    }

    /// The colour from the blocks (every block kept) is the dense coefficients' colour, bit for
    /// bit, everywhere in the frame: inside, on the mirrored borders, at integer positions and
    /// at the last pixel; in f32 and f64, for both degrees.
    #[test]
    fn blocks_give_the_dense_kernels_bits() {
        let (w, h) = (37, 23);
        let mut m = Mpi::new(w, h, vec![0.8, 0.2], 0);
        for (k, v) in m.rgba.iter_mut().enumerate() {
            *v = ((k * 7919 + k / 5) % 101) as f32 / 100.0;
        }
        let mut qs: Vec<(f64, f64)> = vec![(0.0, 0.0), ((w - 1) as f64, (h - 1) as f64), (0.0, (h - 1) as f64)];
        for j in 0..=4 * (h - 1) {
            for i in 0..=4 * (w - 1) {
                qs.push((i as f64 * 0.25 + 0.013 * (j % 3) as f64, j as f64 * 0.25));
            }
        }
        qs.retain(|&(x, y)| x <= (w - 1) as f64 && y <= (h - 1) as f64);
        fn check<K: Kernel<N>, const N: usize>(m: &Mpi, degree: Prefilter, qs: &[(f64, f64)]) {
            let (w, h) = (m.width, m.height);
            let dense = bspline_coefficients(m, degree);
            let blocks = bspline_bricks(m, degree, false);
            for i in 0..m.planes() {
                let plane = &dense[i * w * h * 3..(i + 1) * w * h * 3];
                for &(x, y) in qs {
                    let a = sample_rgb::<f32, K, N, 3>(plane, x as f32, y as f32, w, h);
                    let at = |q: f64, n: usize| (q as f32 as usize).min(n - 1);
                    let (x0, y0) = (at(x, w), at(y, h));
                    let (fx, fy) = (x as f32 - x0 as f32, y as f32 - y0 as f32);
                    let b = sample_rgb_bricks_weighted::<f32, N>(&blocks, i, x0, y0, &K::weights(fx), &K::weights(fy))
                        .expect("every block");
                    assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "{degree:?}, plane {i}, ({x}, {y})");
                    let a = sample_rgb::<f64, K, N, 3>(plane, x, y, w, h);
                    let (x0, y0) = (at(x, w), at(y, h));
                    let (wx, wy) = (K::weights(x - x0 as f64), K::weights(y - y0 as f64));
                    let b = sample_rgb_bricks_weighted::<f64, N>(&blocks, i, x0, y0, &wx, &wy).expect("every block");
                    assert_eq!(a.map(f64::to_bits), b.map(f64::to_bits), "f64, {degree:?}, ({x}, {y})");
                }
            }
        }
        check::<Bspline3, 4>(&m, Prefilter::Bspline3, &qs);
        check::<Bspline5, 6>(&m, Prefilter::Bspline5, &qs);
        check::<Omoms3, 4>(&m, Prefilter::Omoms3, &qs);
    }

    #[test]
    fn weights_sum_to_one() {
        for i in 0..100 {
            let t = i as f64 / 100.0;
            assert!((Keys::weights(t).iter().sum::<f64>() - 1.0).abs() < 1e-12);
            assert!((Bspline3::weights(t).iter().sum::<f64>() - 1.0).abs() < 1e-12);
            assert!((Lanczos3::weights(t).iter().sum::<f64>() - 1.0).abs() < 1e-12);
            assert!((Bspline5::weights(t).iter().sum::<f64>() - 1.0).abs() < 1e-12);
            assert!((Omoms3::weights(t).iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
    }

    /// The kernels' weights of four fractions in lanes are their scalar weights' bits, lane by
    /// lane (the cubic B-spline's own vector formula and the others' per-lane default).
    #[test]
    fn lane_weights_are_the_scalar_weights() {
        fn check<K: Kernel<N>, const N: usize>(t: [f32; 4]) {
            let got = K::weights4(wide::f32x4::from(t));
            for (lane, &tl) in t.iter().enumerate() {
                let want = K::weights::<f32>(tl);
                for k in 0..N {
                    assert_eq!(got[k][lane].to_bits(), want[k].to_bits(), "t = {tl}, tap {k}");
                }
            }
        }
        let mut x = 0x2545_f491_4f6c_dd1du64;
        for i in 0..20_000u32 {
            let t: [f32; 4] = std::array::from_fn(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 40) as f32 / (1u64 << 24) as f32
            });
            // exact quarters and the ends too
            let t = if i < 4 { [0.0, 0.25, 0.5, 1.0 - f32::EPSILON] } else { t };
            check::<Bspline3, 4>(t);
            check::<Bspline5, 6>(t);
            check::<Keys, 4>(t);
            check::<Omoms3, 4>(t);
        }
    }

    #[test]
    fn names_round_trip() {
        for r in Resample::ALL {
            assert_eq!(r.name().parse::<Resample>(), Ok(r));
        }
        assert!("cubic".parse::<Resample>().is_err());
    }
}
