//! The target view's plane loop for the sixteen pixels of a tile row at once on AVX-512
//! ([`rows16`]), reading the planes from their blocks ([`Bricks`]) in registers.
//!
//! The four-lane loop (`exact`, `TargetLanes::four`) does the geometry in vectors but reads
//! every texel lane by lane: a block look-up, four 4-channel loads and a bilinear step per lane,
//! and for the cubic B-spline a second look-up and twelve row loads; those per-lane reads were
//! most of the target view's instructions. Here the sixteen lanes share each read: the lanes
//! whose tap lies in one block form a group, each block row the group needs is loaded once
//! (four or five 512-bit loads), split into one vector per channel by permutes, and every lane's
//! texel of that row is picked out of it with one permute (`vpermt2ps`) per channel and tap
//! column. The bilinear tap then takes 4 channels x 4 pixels in sixteen lanes; the B-spline's
//! column sums run over the block rows in order, each lane adding only its own four rows.
//!
//! Every lane does the scalar loop's operations in its order (the ray set-up, the plane
//! intersection, the clamps, the tap, the gap, the exponential, the kernel's sums, the
//! compositing), so every pixel gets the scalar loop's bits on every path
//! (`tests/render/render_window.rs`, `tests/process/simd_paths.rs`); only the data movement differs.
//! The loop is taken for the packed planes (`render::store`) with the bilinear kernel or the
//! cubic B-spline and no minified planes; the four-lane loop takes the rest.

// the lane helpers serve the AVX-512 loop only
#![cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]

use super::plane::{cap, slab_offset, texel_depth, PlaneConst, SurfaceRay, SURFACE_STEPS};
use crate::mpi::bricks::Bricks;
use crate::mpi::planes::{DELTA_LAST, DEPTH_MAX};
use crate::render::real::Real;
use crate::render::types::{Prefilter, RenderStats};

/// Composite weights below this take the bilinear colour even with a higher-order kernel: the
/// difference is at most this fraction of full scale (below half an 8-bit step), and such
/// samples are common (the faint tails of soft layers), so the kernel's cost goes where it shows.
pub(crate) const KERNEL_MIN_WEIGHT: f32 = 1.0 / 1024.0;

/// The target view's per-render constants in `f32`, as the lane loops read them: R^T, the
/// window's columns and rows as u = K_t^-1 p, the planes' `1 + k disp`, depths and source
/// offsets, the source focal lengths, the bounds of the "leaves the source image" test and of
/// the edge clamp, the early-termination threshold and the planes' size.
pub(super) struct TargetLanes {
    pub(super) rt: [[f32; 3]; 3],
    pub(super) ux: Vec<f32>,
    pub(super) uy: Vec<f32>,
    pub(super) a: Vec<f32>,
    pub(super) depth: Vec<f32>,
    pub(super) ox: Vec<f32>,
    pub(super) oy: Vec<f32>,
    pub(super) fxs: f32,
    pub(super) fys: f32,
    pub(super) lo: f32,
    pub(super) hix: f32,
    pub(super) hiy: f32,
    pub(super) wm: f32,
    pub(super) hm: f32,
    pub(super) t_eps: f32,
    pub(super) w: usize,
    pub(super) h: usize,
}

/// Where [`rows16`] reads the planes: the packed (r, g, b, sigma) and, for a prefiltered cubic
/// (the cubic B-spline or OMOMS-3), its coefficients and which cubic (`None`: the bilinear
/// colour).
#[derive(Clone, Copy)]
pub(super) struct Blocks16<'a> {
    rgba: &'a Bricks,
    cubic: Option<(&'a Bricks, Prefilter)>,
}

impl<'a> Blocks16<'a> {
    /// The stores in the shapes the loop reads (the packed planes: 4 values, no apron before
    /// a block, one after; the coefficients: 3 values, one before, two after), else `None`.
    pub(super) fn new(rgba: &'a Bricks, cubic: Option<(&'a Bricks, Prefilter)>) -> Option<Self> {
        let fits = |b: &Bricks, stride: usize, lo: usize, side: usize| {
            b.stride() == stride && b.lo() == lo && b.side() == side
        };
        (fits(rgba, 4, 0, Bricks::SIZE + 1) && cubic.is_none_or(|(k, _)| fits(k, 3, 1, Bricks::SIZE + 3)))
            .then_some(Blocks16 { rgba, cubic })
    }
}

/// Sixteen lanes.
const L: usize = 16;
type F = [f32; L];
type I = [i32; L];
/// A set of lanes (bit k: lane k), an AVX-512 mask register.
type Lanes = u16;
const ALL: Lanes = Lanes::MAX;

#[inline(always)]
fn f16(f: impl Fn(usize) -> f32) -> F {
    let mut o = [0.0; L];
    for (k, v) in o.iter_mut().enumerate() {
        *v = f(k);
    }
    o
}

#[inline(always)]
fn i16(f: impl Fn(usize) -> i32) -> I {
    let mut o = [0; L];
    for (k, v) in o.iter_mut().enumerate() {
        *v = f(k);
    }
    o
}

/// The set bits of `m` (lanes, or a tile's rows), in order.
#[inline(always)]
fn each(mut m: u32) -> impl Iterator<Item = usize> {
    std::iter::from_fn(move || {
        (m != 0).then(|| {
            let k = m.trailing_zeros() as usize;
            m &= m - 1;
            k
        })
    })
}

// The lane operations on AVX-512 registers (`pulp`'s safe wrappers of the intrinsics): lane
// sets as mask registers, blends, compares and the permutes that pick each lane's texel.
#[cfg(target_arch = "x86_64")]
use core::arch::x86_64::{__m512, __m512i};
#[cfg(target_arch = "x86_64")]
use pulp::bytemuck::cast;
#[cfg(target_arch = "x86_64")]
use pulp::x86::V4;

#[cfg(target_arch = "x86_64")]
const LT: i32 = 0x11; // _CMP_LT_OQ
#[cfg(target_arch = "x86_64")]
const GE: i32 = 0x1D; // _CMP_GE_OQ
#[cfg(target_arch = "x86_64")]
const GT: i32 = 0x1E; // _CMP_GT_OQ
/// `!(a <= b)`: true where a NaN is involved, as the scalar loop's negated compares
#[cfg(target_arch = "x86_64")]
const NLE: i32 = 0x16; // _CMP_NLE_UQ
/// `!(a < b)`
#[cfg(target_arch = "x86_64")]
const NLT: i32 = 0x15; // _CMP_NLT_UQ

/// Lane k: `a[idx[k]]` for idx[k] in 0..16, `b[idx[k] - 16]` for 16..32 (`vpermt2ps`).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn two(v4: V4, a: &F, idx: &I, b: &F) -> F {
    let (a, idx, b): (__m512, __m512i, __m512) = (cast(*a), cast(*idx), cast(*b));
    cast(v4.avx512f._mm512_permutex2var_ps(a, idx, b))
}

/// `a` in the lanes of `m`, else `b`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn pick(v4: V4, m: Lanes, a: &F, b: &F) -> F {
    cast(v4.avx512f._mm512_mask_blend_ps(m, cast(*b), cast(*a)))
}

/// The lanes where `a P b` (`P` one of the predicates above).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn cmp<const P: i32>(v4: V4, a: &F, b: &F) -> Lanes {
    v4.avx512f._mm512_cmp_ps_mask::<P>(cast(*a), cast(*b))
}

/// The lanes where `a P s`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn cmp1<const P: i32>(v4: V4, a: &F, s: f32) -> Lanes {
    cmp::<P>(v4, a, &[s; L])
}

/// The lanes where `a == s`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn eq(v4: V4, a: &I, s: i32) -> Lanes {
    v4.avx512f._mm512_cmpeq_epi32_mask(cast(*a), cast([s; L]))
}

/// `a[k] as i32` for values inside i32's range (`vcvttps2dq`; Rust's saturating `as`
/// goes lane by lane).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn trunc(v4: V4, a: &F) -> I {
    cast(v4.avx512f._mm512_cvttps_epi32(cast(*a)))
}

/// `acc + a b` in the lanes of `m` (the product rounded, then the sum), `acc` elsewhere.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn add_mul(v4: V4, m: Lanes, acc: &F, a: &F, b: &F) -> F {
    let acc: __m512 = cast(*acc);
    let prod = v4.avx512f._mm512_mul_ps(cast(*a), cast(*b));
    cast(v4.avx512f._mm512_mask_add_ps(acc, m, acc, prod))
}

/// The least and the greatest of `a` over the lanes of `m` (not empty).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn min_max(v4: V4, m: Lanes, a: &I) -> (i32, i32) {
    let a: __m512i = cast(*a);
    (v4.avx512f._mm512_mask_reduce_min_epi32(m, a), v4.avx512f._mm512_mask_reduce_max_epi32(m, a))
}

/// The lanes where `0 <= a < n` (unsigned compare).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn below(v4: V4, a: &I, n: i32) -> Lanes {
    v4.avx512f._mm512_cmplt_epu32_mask(cast(*a), cast([n; L]))
}

/// One block row split by channel: `main[c][p]` the value of channel c at pixel p (0..16) of
/// the row, `rest[c][p - 16]` at pixels 16.. (the apron after the block).
struct RowChannels<const S: usize> {
    main: [F; S],
    rest: [F; S],
}

/// Pixels 0 .. 16 + `after` of a block row of `S` values per pixel from `data[at..]`, split by
/// channel (S <= 4, (16 + after) S <= 80: five registers, which [`Bricks::TAIL`] keeps inside
/// `data` from any row's start).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn split_row<const S: usize>(v4: pulp::x86::V4, data: &[f32], at: usize) -> RowChannels<S> {
    const N: usize = 5 * L;
    let row: &[f32; N] = data[at..at + N].try_into().expect("Bricks::TAIL values after every row");
    let t: [F; 5] = std::array::from_fn(|r| row[r * L..r * L + L].try_into().expect("16 values"));
    let [t0, t1, t2, t3, t4] = t;
    // pixels 16 + q: values 16 S + S q + c, from register S
    let tail = if S == 3 { t3 } else { t4 };
    let mut main = [[0.0; L]; S];
    let mut rest = [[0.0; L]; S];
    for c in 0..S {
        // pixel p's value c is value S p + c of the row: registers 0-1 below 32, 2-3 below 64
        let idx = i16(|p| (S * p + c) as i32);
        let lo = two(v4, &t0, &idx, &t1);
        let hi = two(v4, &t2, &idx, &t3);
        let high: Lanes = (0..L).filter(|&p| S * p + c >= 2 * L).fold(0, |m, p| m | 1 << p);
        main[c] = pick(v4, high, &hi, &lo);
        let idx = i16(|q| (S * q + c) as i32);
        rest[c] = two(v4, &tail, &idx, &tail);
    }
    RowChannels { main, rest }
}

/// The lanes' tap pixels: their blocks (one key per block) and their place in it.
struct TapPixels {
    block: I,
    bx: I,
    by: I,
    u: I,
    v: I,
}

impl TapPixels {
    /// The tap pixels (x0, y0) >= 0: a shift and a mask are the division and remainder by the
    /// block size (in registers: values written lane by lane and read back whole would stall
    /// the store forwarding).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn of(v4: pulp::x86::V4, x0: &I, y0: &I) -> Self {
        const SHIFT: u32 = Bricks::SIZE.trailing_zeros();
        let f = v4.avx512f;
        let (x0, y0): (__m512i, __m512i) = (cast(*x0), cast(*y0));
        let mask = f._mm512_set1_epi32(Bricks::SIZE as i32 - 1);
        let (bx, by) = (f._mm512_srai_epi32::<SHIFT>(x0), f._mm512_srai_epi32::<SHIFT>(y0));
        let block = f._mm512_or_si512(f._mm512_slli_epi32::<16>(by), bx);
        TapPixels {
            block: cast(block),
            bx: cast(bx),
            by: cast(by),
            u: cast(f._mm512_and_si512(x0, mask)),
            v: cast(f._mm512_and_si512(y0, mask)),
        }
    }

    /// The lanes of `todo` in the block of its first lane, and that block.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn group(&self, v4: pulp::x86::V4, todo: Lanes) -> (Lanes, usize, usize) {
        let k0 = todo.trailing_zeros() as usize;
        (todo & eq(v4, &self.block, self.block[k0]), self.bx[k0] as usize, self.by[k0] as usize)
    }

    /// The least and greatest `v` of the lanes of `g`.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    fn rows(&self, v4: pulp::x86::V4, g: Lanes) -> (i32, i32) {
        min_max(v4, g, &self.v)
    }
}

/// The bilinear (r, g, b, sigma) of plane `i` at the taps of the lanes of `take` (pixels `x0`,
/// `y0`, fractions `fx`, `fy`): `Tap::sample4_at`'s arithmetic per lane; 0 where the tap's
/// block is not stored, and in the other lanes.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn texels(v4: pulp::x86::V4, rgba: &Bricks, i: usize, px: &TapPixels, f: [&F; 2], take: Lanes) -> [F; 4] {
    // the four pixels (x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1), per channel
    let (mut p00, mut p10, mut p01, mut p11) = ([[0.0f32; L]; 4], [[0.0f32; L]; 4], [[0.0f32; L]; 4], [[0.0f32; L]; 4]);
    let row_len = rgba.row_len();
    let data = rgba.data();
    let u1 = i16(|k| px.u[k] + 1);
    let mut todo = take;
    while todo != 0 {
        let (g, bx, by) = px.group(v4, todo);
        todo &= !g;
        let Some(start) = rgba.block_start(i, bx, by) else { continue };
        let (vmin, vmax) = px.rows(v4, g);
        for r in vmin..=vmax + 1 {
            let (top, bottom) = if vmin == vmax {
                // the group's taps share their rows (the common case): the upper pixels in
                // row vmin, the lower ones in the next
                if r == vmin {
                    (g, 0)
                } else {
                    (0, g)
                }
            } else {
                (g & eq(v4, &px.v, r), g & eq(v4, &px.v, r - 1))
            };
            let row = split_row::<4>(v4, data, start + r as usize * row_len);
            // this row's pixels x0 and x0 + 1: the top pixels of the lanes of `top`, the
            // bottom ones of the lanes of `bottom`
            for c in 0..4 {
                let a = two(v4, &row.main[c], &px.u, &row.rest[c]);
                let b = two(v4, &row.main[c], &u1, &row.rest[c]);
                if top != 0 {
                    p00[c] = pick(v4, top, &a, &p00[c]);
                    p10[c] = pick(v4, top, &b, &p10[c]);
                }
                if bottom != 0 {
                    p01[c] = pick(v4, bottom, &a, &p01[c]);
                    p11[c] = pick(v4, bottom, &b, &p11[c]);
                }
            }
        }
    }
    let (wx, wy) = (f[0], f[1]);
    [
        lerp([&p00[0], &p10[0], &p01[0], &p11[0]], wx, wy),
        lerp([&p00[1], &p10[1], &p01[1], &p11[1]], wx, wy),
        lerp([&p00[2], &p10[2], &p01[2], &p11[2]], wx, wy),
        lerp([&p00[3], &p10[3], &p01[3], &p11[3]], wx, wy),
    ]
}

/// Bilinear interpolation per lane: top = a + wx (b - a), bot = c + wx (d - c),
/// top + wy (bot - top) (`Tap::sample1`'s arithmetic).
#[inline(always)]
fn lerp([a, b, c, d]: [&F; 4], wx: &F, wy: &F) -> F {
    let top = f16(|k| a[k] + wx[k] * (b[k] - a[k]));
    let bot = f16(|k| c[k] + wx[k] * (d[k] - c[k]));
    f16(|k| top[k] + wy[k] * (bot[k] - top[k]))
}

/// `q` clamped to [0, hi] (`q` not NaN): 0 below 0, `hi` above it.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn clamp_to(v4: pulp::x86::V4, q: &F, hi: f32) -> F {
    let q = pick(v4, cmp1::<GT>(v4, q, hi), &[hi; L], q);
    pick(v4, cmp1::<LT>(v4, &q, 0.0), &[0.0; L], &q)
}

/// The prefiltered cubic's colour of plane `i` from its coefficients at the taps of the lanes of
/// `want` (`sample_rgb_bricks_weighted`'s arithmetic per lane: the column sums over the four
/// rows in order, then the row sum, clamped to [0, 1]) and the lanes whose block is stored
/// (the others take the bilinear colour).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn cubic(
    v4: pulp::x86::V4,
    (coef, kind): (&Bricks, Prefilter),
    i: usize,
    px: &TapPixels,
    f: [&F; 2],
    want: Lanes,
) -> ([F; 3], Lanes) {
    let wx: [F; 4] = weights(kind, f[0]);
    let wy: [F; 4] = weights(kind, f[1]);
    let mut col = [[[0.0f32; L]; 3]; 4];
    let row_len = coef.row_len();
    let data = coef.data();
    let tap = |t: i32| i16(|k| px.u[k] + t);
    let idx: [I; 4] = [tap(0), tap(1), tap(2), tap(3)];
    let mut found = 0;
    let mut todo = want;
    while todo != 0 {
        let (g, bx, by) = px.group(v4, todo);
        todo &= !g;
        let Some(start) = coef.block_start(i, bx, by) else { continue };
        found |= g;
        let (vmin, vmax) = px.rows(v4, g);
        // row r of the block is row j = r - v of lane k's neighbourhood
        for r in vmin..=vmax + 3 {
            let (m, wr) = if vmin == vmax {
                // the group's taps share their rows (the common case): row j = r - vmin of
                // every lane's neighbourhood
                (g, wy[(r - vmin) as usize])
            } else {
                let j = i16(|k| r - px.v[k]);
                let m = g & below(v4, &j, 4);
                if m == 0 {
                    continue;
                }
                let wr = pick(v4, eq(v4, &j, 0), &wy[0], &wy[1]);
                let wr = pick(v4, eq(v4, &j, 2), &wy[2], &wr);
                (m, pick(v4, eq(v4, &j, 3), &wy[3], &wr))
            };
            let row = split_row::<3>(v4, data, start + r as usize * row_len);
            for (col_t, idx) in col.iter_mut().zip(&idx) {
                for (c, col_tc) in col_t.iter_mut().enumerate() {
                    let p = two(v4, &row.main[c], idx, &row.rest[c]);
                    *col_tc = add_mul(v4, m, col_tc, &wr, &p);
                }
            }
        }
    }
    let mut acc = [[0.0f32; L]; 3];
    for (t, col_t) in col.iter().enumerate() {
        for (a, col_tc) in acc.iter_mut().zip(col_t) {
            *a = f16(|k| a[k] + wx[t][k] * col_tc[k]);
        }
    }
    // max then min, as the scalar kernel: a NaN becomes 0 (`clamp` would keep it)
    #[allow(clippy::manual_clamp)]
    let clamp = |a: &F| f16(|k| a[k].max(0.0).min(1.0));
    ([clamp(&acc[0]), clamp(&acc[1]), clamp(&acc[2])], found)
}

/// `f32::exp_neg` (`exp_neg_f32` of `real.rs`) in lanes, operation for operation: the same
/// clamps, argument reduction, polynomial and exponent bits, so the same bits.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn exp_neg16(v4: pulp::x86::V4, x: &F) -> F {
    use crate::render::simd::EXP2_TAYLOR as C;
    let x = f16(|k| if x[k] < 80.0 { x[k] } else { 80.0 });
    let x = f16(|k| if x[k] > 0.0 { x[k] } else { 0.0 });
    let t = f16(|k| -x[k] * std::f32::consts::LOG2_E);
    let n = f16(|k| (t[k] + 12_582_912.0) - 12_582_912.0);
    let f = f16(|k| t[k] - n[k]);
    let p = f16(|k| {
        let f = f[k];
        C[0] + f * (C[1] + f * (C[2] + f * (C[3] + f * (C[4] + f * (C[5] + f * C[6])))))
    });
    // n in [-116, 0]: inside i32, so truncation is Rust's `as`
    let n = trunc(v4, &n);
    let half = i16(|k| n[k] / 2);
    let a = f16(|k| f32::from_bits(((127 + half[k]) as u32) << 23));
    let b = f16(|k| f32::from_bits(((127 + n[k] - half[k]) as u32) << 23));
    f16(|k| p[k] * a[k] * b[k])
}

/// The cubic's weights of the lanes' fractions (`Bspline3::weights`' and `Omoms3::weights`'
/// operations in lanes, the same bits).
#[inline(always)]
fn weights(kind: Prefilter, t: &F) -> [F; 4] {
    let s = 1.0f32 / 6.0;
    let u = f16(|k| 1.0 - t[k]);
    let t2 = f16(|k| t[k] * t[k]);
    let t3 = f16(|k| t[k] * t[k] * t[k]);
    let b = [
        f16(|k| u[k] * u[k] * u[k] * s),
        f16(|k| (3.0 * t3[k] - 6.0 * t2[k] + 4.0) * s),
        f16(|k| (-3.0 * t3[k] + 3.0 * t2[k] + 3.0 * t[k] + 1.0) * s),
        f16(|k| t3[k] * s),
    ];
    if kind != Prefilter::Omoms3 {
        return b;
    }
    // the B-spline plus a 42nd of its second derivative
    let s = 1.0f32 / 42.0;
    [
        f16(|k| b[0][k] + u[k] * s),
        f16(|k| b[1][k] + (3.0 * t[k] - 2.0) * s),
        f16(|k| b[2][k] + (3.0 * u[k] - 2.0) * s),
        f16(|k| b[3][k] + t[k] * s),
    ]
}

/// One tile row's sixteen rays in the plane loop: their constants (1 / s, the source focal
/// lengths times the ray, |u|) and what they have gathered (transmittance, colour, weight,
/// weighted depth, the extra channel) and which of them have stopped.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Rays {
    inv_s: F,
    /// the rays' directions v = R^T u (x and y), for a true-depth texel's search
    v0: F,
    v1: F,
    fv0: F,
    fv1: F,
    norm_u: F,
    tr: F,
    rgb: [F; 3],
    sum_w: F,
    sum_z: F,
    acc1: F,
    done: Lanes,
}

impl Rays {
    const NONE: Rays = Rays {
        inv_s: [0.0; L],
        v0: [0.0; L],
        v1: [0.0; L],
        fv0: [0.0; L],
        fv1: [0.0; L],
        norm_u: [0.0; L],
        tr: [1.0; L],
        rgb: [[0.0; L]; 3],
        sum_w: [0.0; L],
        sum_z: [0.0; L],
        acc1: [0.0; L],
        done: 0,
    };

    /// The rays of the window's columns `at[0] .. at[0] + 16` of its row `at[1]`, and whether
    /// they look forward (s > 0); `None` unless all sixteen meet the planes in one order.
    #[inline(always)]
    fn new(c: &TargetLanes, at: [usize; 2]) -> Option<(Self, bool)> {
        let ux: &F = c.ux[at[0]..at[0] + L].try_into().expect("sixteen columns");
        let uy = c.uy[at[1]];
        let rt = &c.rt;
        let ray = |r: usize| f16(|k| rt[r][0] * ux[k] + rt[r][1] * uy + rt[r][2]);
        let (v0, v1, v2) = (ray(0), ray(1), ray(2));
        let forward = v2[0] > 0.0;
        if !v2.iter().all(|&s| s.abs() > 1e-12_f64 as f32 && (s > 0.0) == forward) {
            return None;
        }
        let rays = Rays {
            inv_s: f16(|k| 1.0 / v2[k]),
            v0,
            v1,
            fv0: f16(|k| c.fxs * v0[k]),
            fv1: f16(|k| c.fys * v1[k]),
            norm_u: f16(|k| (ux[k] * ux[k] + uy * uy + 1.0).sqrt()),
            ..Rays::NONE
        };
        Some((rays, forward))
    }
}

/// Rows a tile holds at most: a band's.
const ROWS: usize = crate::render::band::BAND_ROWS;

/// Where [`rows16`] writes and counts: the band's buffers (image, depth, coverage, the extra
/// channel, ...), the index in them of the tile's first pixel and the length of a band row.
pub(super) struct TileOut<'a, 'b> {
    pub(super) b: &'a mut [&'b mut [f32]; 10],
    pub(super) stats: &'a mut RenderStats,
    pub(super) o: usize,
    pub(super) row_len: usize,
}

/// The tile of the window's columns `at[0] .. at[0] + 16` and rows `at[1] .. at[1] + rows`
/// (`rows` at most a band's), the planes of `fwd` (or `rev` when the rays look back), plane by
/// plane: each plane's blocks are read by every row of the tile while they are in the cache.
/// Writes the tile's image, depth, coverage and, when `ex` is given, extra channel, and returns
/// the rows it rendered (bit r: row `at[1] + r`); a row whose sixteen rays do not meet the
/// planes in the tile's order is left to a narrower loop, with nothing written.
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(super) fn rows16<T: Real>(
    v4: pulp::x86::V4,
    c: &TargetLanes,
    (src, srf): (Blocks16<'_>, Surfaced16<'_, T>),
    ex: Option<&[&[f32]]>,
    at: [usize; 2],
    rows: usize,
    [fwd, rev]: [&[usize]; 2],
    out: TileOut<'_, '_>,
) -> u32 {
    let mut tile = [Rays::NONE; ROWS];
    let (mut members, mut forward) = (0u32, None);
    for (r, rays) in tile.iter_mut().enumerate().take(rows) {
        if let Some((new, f)) = Rays::new(c, [at[0], at[1] + r]) {
            if *forward.get_or_insert(f) == f {
                *rays = new;
                members |= 1 << r;
            }
        }
    }
    let Some(forward) = forward else { return 0 };
    let order = if forward { fwd } else { rev };
    let mut live = members;
    for (j, &i) in order.iter().enumerate() {
        if live == 0 {
            break;
        }
        let next = if forward { i + 1 } else { i.wrapping_sub(1) };
        let plane = Plane { i, next, left: order.len() - j };
        for r in each(live) {
            if !step(v4, c, (src, srf), ex, &plane, &mut tile[r], out.stats) {
                live &= !(1 << r);
            }
        }
    }
    for r in each(members) {
        let rays = &tile[r];
        write(out.b, out.o + r * out.row_len, &rays.rgb, [&rays.sum_w, &rays.sum_z], ex.map(|_| &rays.acc1));
    }
    members
}

/// A plane of the loop: its index, the next one along the rays (`c.a.get(next)` is `None`
/// past the last) and how many planes are left in the order with it.
struct Plane {
    i: usize,
    next: usize,
    left: usize,
}

/// Plane `p.i` for the sixteen rays of `r` (the scalar loop's body in lanes): false when every
/// ray has stopped (nothing more to gather).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn step<T: Real>(
    v4: pulp::x86::V4,
    c: &TargetLanes,
    (src, srf): (Blocks16<'_>, Surfaced16<'_, T>),
    ex: Option<&[&[f32]]>,
    p: &Plane,
    r: &mut Rays,
    stats: &mut RenderStats,
) -> bool {
    let (depth_max, delta_last) = (DEPTH_MAX as f32, DELTA_LAST as f32);
    let cap = |v: f32, max: f32| if v > max { max } else { v };
    let (w, h) = (c.w as i32, c.h as i32);
    let i = p.i;
    let g = f16(|k| c.a[i] * r.inv_s[k]);
    let front = cmp1::<NLE>(v4, &g, 0.0);
    // a lane in front of the plane with its transmittance below t_eps stops here
    let stop = front & cmp1::<LT>(v4, &r.tr, c.t_eps) & !r.done;
    if stop != 0 {
        stats.skipped_early += u64::from(stop.count_ones()) * p.left as u64;
        r.done |= stop;
        if r.done == ALL {
            return false;
        }
    }
    let (ox, oy) = (c.ox[i], c.oy[i]);
    let qx = f16(|k| ox + r.fv0[k] * g[k]);
    let qy = f16(|k| oy + r.fv1[k] * g[k]);
    // a true-depth MPI: each lane's texel searched as the scalar loop searches it
    let (qx, qy, lambda_z, in_front) = match srf {
        None => (qx, qy, None, ALL),
        Some((sr, pls)) => {
            let (qx, qy, lz, f) = surface16(sr, &pls[i], r, [qx, qy], front & !r.done);
            (qx, qy, Some(lz), f)
        }
    };
    let inside =
        cmp1::<GE>(v4, &qx, c.lo) & cmp1::<LT>(v4, &qx, c.hix) & cmp1::<GE>(v4, &qy, c.lo) & cmp1::<LT>(v4, &qy, c.hiy);
    let take = front & inside & in_front & !r.done;
    if take == 0 {
        return true;
    }
    let (qx, qy) = (clamp_to(v4, &qx, c.wm), clamp_to(v4, &qy, c.hm));
    // `Tap::new` in lanes: q >= 0, so truncation is floor; at most the last pixel
    let (x0, y0) = (trunc(v4, &qx), trunc(v4, &qy));
    let x0 = i16(|k| x0[k].min(w - 1));
    let y0 = i16(|k| y0[k].min(h - 1));
    let fx = f16(|k| qx[k] - x0[k] as f32);
    let fy = f16(|k| qy[k] - y0[k] as f32);
    let px = TapPixels::of(v4, &x0, &y0);
    let texel = texels(v4, src.rgba, i, &px, [&fx, &fy], take);
    stats.samples += u64::from(take.count_ones());
    // the scalar loop goes on with this plane unless sigma <= 0
    let lit = take & cmp1::<NLE>(v4, &texel[3], 0.0);
    if lit == 0 {
        return true;
    }
    let sig = pick(v4, lit, &texel[3], &[0.0; L]);
    let lambda = f16(|k| cap(g[k] * c.depth[i], depth_max));
    let delta = match c.a.get(p.next) {
        Some(&an) => {
            let dn = c.depth[p.next];
            let an = f16(|k| an * r.inv_s[k]);
            let d = f16(|k| cap((cap(an[k] * dn, depth_max) - lambda[k]) * r.norm_u[k], delta_last));
            pick(v4, cmp1::<GT>(v4, &an, 0.0), &d, &[delta_last; L])
        }
        None => [delta_last; L],
    };
    let e = exp_neg16(v4, &f16(|k| sig[k] * delta[k]));
    let wgt = f16(|k| r.tr[k] * (1.0 - e[k]));
    r.tr = pick(v4, lit, &f16(|k| r.tr[k] * e[k]), &r.tr);
    let colour = colours(v4, src, i, &px, [&fx, &fy], &texel, lit & cmp1::<NLT>(v4, &wgt, KERNEL_MIN_WEIGHT));
    for (acc, col) in r.rgb.iter_mut().zip(&colour) {
        *acc = add_mul(v4, lit, acc, &wgt, col);
    }
    if let Some(ex) = ex {
        for k in each(lit.into()) {
            let tap = crate::render::tap::Tap::from_parts(x0[k] as usize, y0[k] as usize, c.w, c.h, fx[k], fy[k]);
            r.acc1[k] += wgt[k] * tap.sample1(ex[i]);
        }
    }
    r.sum_w = pick(v4, lit, &f16(|k| r.sum_w[k] + wgt[k]), &r.sum_w);
    r.sum_z = add_mul(v4, lit, &r.sum_z, &wgt, lambda_z.as_ref().unwrap_or(&lambda));
    true
}

/// A true-depth MPI's search and the planes' constants ([`rows16`]; `None`: texels on their
/// planes).
pub(super) type Surfaced16<'a, T> = Option<(&'a SurfaceRay<'a, T>, &'a [PlaneConst<T>])>;

/// The texels of a true-depth MPI's plane `pl` that the lanes of `lanes` meet, from the plane's
/// points `q`: [`SurfaceRay::search`] in sixteen lanes, each step over all of them as the
/// four-lane loop's `surface4` takes its four (the clamp, the tap's pixel and fractions, the four surface reads,
/// [`slab_offset`] and the bilinear blend, the ray's point at that disparity, all
/// in `f32` in the scalar loop's order): the points (`q` in the other lanes), their depths along
/// the rays (0 in lanes not taken) and the lanes whose texel is in front of the camera.
#[inline(always)]
fn surface16<T: Real>(
    sr: &SurfaceRay<'_, T>,
    pl: &PlaneConst<T>,
    r: &Rays,
    q: [F; 2],
    lanes: Lanes,
) -> (F, F, F, Lanes) {
    let (disp, lo, hi) = (pl.disp.f32(), pl.lo.f32(), pl.hi.f32());
    let (wm, hm, kk) = (sr.wm.f32(), sr.hm.f32(), sr.k.f32());
    let [fx, fy] = sr.fs.map(Real::f32);
    let [cx, cy] = sr.cs.map(Real::f32);
    let [ox, oy] = sr.centre.map(Real::f32);
    let (w, h) = (sr.w as i32, sr.h as i32);
    let surface = sr.surface;
    let (mut qx, mut qy, mut d) = (q[0], q[1], [disp; L]);
    // the surface's texel offsets at four pixels of each lane
    let offsets = |i: &I| f16(|k| slab_offset(surface[i[k] as usize], disp, lo, hi));
    for _ in 0..SURFACE_STEPS {
        // `Tap::new` at the clamped point (q >= 0 there, so truncation is floor), each
        // operation over the sixteen lanes at once
        let px = f16(|k| qx[k].max(0.0).min(wm));
        let py = f16(|k| qy[k].max(0.0).min(hm));
        let x0 = i16(|k| (px[k] as i32).max(0).min(w - 1));
        let y0 = i16(|k| (py[k] as i32).max(0).min(h - 1));
        let wx = f16(|k| px[k] - x0[k] as f32);
        let wy = f16(|k| py[k] - y0[k] as f32);
        let x1 = i16(|k| (x0[k] + 1).min(w - 1));
        let r0 = i16(|k| y0[k] * w);
        let r1 = i16(|k| (y0[k] + 1).min(h - 1) * w);
        let a00 = offsets(&i16(|k| r0[k] + x0[k]));
        let a10 = offsets(&i16(|k| r0[k] + x1[k]));
        let a01 = offsets(&i16(|k| r1[k] + x0[k]));
        let a11 = offsets(&i16(|k| r1[k] + x1[k]));
        let top = f16(|k| a00[k] + wx[k] * (a10[k] - a00[k]));
        let bot = f16(|k| a01[k] + wx[k] * (a11[k] - a01[k]));
        d = f16(|k| disp + (top[k] + wy[k] * (bot[k] - top[k])));
        // `SurfaceRay::at`
        let g = f16(|k| (1.0 + kk * d[k]) * r.inv_s[k]);
        qx = f16(|k| fx * (ox * d[k] + r.v0[k] * g[k]) + cx);
        qy = f16(|k| fy * (oy * d[k] + r.v1[k] * g[k]) + cy);
    }
    let depth = f16(|k| texel_depth(d[k]));
    let g = f16(|k| (1.0 + kk * d[k]) * r.inv_s[k]);
    let in_front = (0..L).filter(|&k| g[k] > 0.0).fold(0, |m, k| m | 1 << k) & lanes;
    let on = |m: Lanes, k: usize| m >> k & 1 == 1;
    let lambda = f16(|k| if on(in_front, k) { cap(g[k] * depth[k], DEPTH_MAX) } else { 0.0 });
    (
        f16(|k| if on(lanes, k) { qx[k] } else { q[0][k] }),
        f16(|k| if on(lanes, k) { qy[k] } else { q[1][k] }),
        lambda,
        in_front,
    )
}

/// The colour of the lanes' samples of plane `i`: the bilinear colour of `texel`, or in the
/// lanes of `want` the cubic B-spline's where the sampler has its coefficients and they are
/// stored (`HighOrder::colour4`'s choice per lane).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn colours(v4: V4, src: Blocks16<'_>, i: usize, px: &TapPixels, f: [&F; 2], texel: &[F; 4], want: Lanes) -> [F; 3] {
    let mut colour = [texel[0], texel[1], texel[2]];
    if let Some(c) = src.cubic.filter(|_| want != 0) {
        let (kc, found) = cubic(v4, c, i, px, f, want);
        for (col, kc) in colour.iter_mut().zip(&kc) {
            *col = pick(v4, found, kc, col);
        }
    }
    colour
}

/// Pixels `o .. o + 16` of the band's image, depth (the weight-normalised `sum_z`, 0 where the
/// weight `sum_w` is at most the scalar loop's 1e-6), coverage and, when given, extra channel.
#[inline(always)]
fn write(b: &mut [&mut [f32]; 10], o: usize, rgb: &[F; 3], [sum_w, sum_z]: [&F; 2], extra: Option<&F>) {
    // the scalar loop's T::of(1e-6)
    const EPS: f32 = 1e-6_f64 as f32;
    for k in 0..L {
        let o = o + k;
        b[0][3 * o..3 * o + 3].copy_from_slice(&[rgb[0][k], rgb[1][k], rgb[2][k]]);
        b[1][o] = if sum_w[k] > EPS { sum_z[k] / sum_w[k] } else { 0.0 };
        b[2][o] = sum_w[k];
        if let Some(e) = extra {
            b[3][o] = e[k];
        }
    }
}
