//! The source view's lane loops ([`SourceLanes`]): four pixels at a time in `f32x4`, or the
//! path's 8 or 16 in plain arrays, each the scalar loop's operations in its order.

use super::plane::{slab_offset, texel_depth};
use crate::mpi::planes::DEPTH_MAX;
use crate::render::real::Real;
use crate::render::store::Rgba;

/// The source view's per-pixel loop for four adjacent pixels of a row at once (f32 only, the
/// scalar loop of `source_view` stays the reference): every lane does the scalar loop's
/// operations in its order on its own pixel, planes a lane does not take (density 0, or the
/// lane done because its transmittance fell below `t_eps`) are masked out instead of skipped,
/// and the plane loop ends when every lane is done. So each pixel gets the scalar loop's bits
/// (`tests/render/render_window.rs` compares the two: a window one pixel wide makes the scalar loop run).
pub(super) struct SourceLanes<'a> {
    pub(super) m: [[f32; 3]; 3],
    pub(super) b: [f32; 3],
    pub(super) disp: Vec<f32>,
    pub(super) depth: Vec<f32>,
    pub(super) gap: Vec<f32>,
    pub(super) t_eps: f32,
    pub(super) z_min: f32,
    pub(super) rgba: Rgba<'a>,
    /// the frame's columns as f32, and its columns and rows as u = K_s^-1 p (the scalar loop's
    /// values, computed once)
    pub(super) xs: Vec<f32>,
    pub(super) ux: Vec<f32>,
    pub(super) uy: Vec<f32>,
    pub(super) want_sd: bool,
    /// a true-depth MPI's surface ([`crate::mpi::Surface`], H x W) and the planes' slabs: each
    /// texel at its own disparity ([`texel_disparity`])
    pub(super) surface: Option<&'a [f32]>,
    pub(super) slab: Vec<(f32, f32)>,
    pub(super) w: usize,
}

/// The disparity and depth of plane `i`'s texel at a pixel of a true-depth MPI whose surface
/// value is `surface` (`d`: the plane's; `slab`: its offsets' bounds): `d` plus the texel's [`slab_offset`], and its depth,
/// capped at [`DEPTH_MAX`]. The scalar loop and the lanes call this one function, so their bits
/// agree.
#[inline(always)]
pub(super) fn texel_disparity<T: Real>(surface: f32, d: T, (lo, hi): (T, T)) -> (T, T) {
    let d = d + slab_offset(T::of32(surface), d, lo, hi);
    (d, texel_depth(d))
}

impl SourceLanes<'_> {
    /// Plane `i`'s disparity and depth at the `L` pixels `x .. x + L` of row `yy`: the plane's,
    /// or a true-depth MPI's texels' ([`texel_disparity`]).
    #[inline(always)]
    fn texels<const L: usize>(&self, i: usize, x: usize, yy: usize) -> ([f32; L], [f32; L]) {
        let (d, z) = (self.disp[i], self.depth[i]);
        match self.surface {
            None => ([d; L], [z; L]),
            Some(srf) => {
                // the row's L surface values in one load, then lane by lane
                let p = yy * self.w + x;
                let row: &[f32; L] = srf[p..p + L].try_into().expect("L columns");
                let at: [(f32, f32); L] = std::array::from_fn(|k| texel_disparity(row[k], d, self.slab[i]));
                (at.map(|t| t.0), at.map(|t| t.1))
            }
        }
    }
}

impl SourceLanes<'_> {
    /// Pixels `x .. x + 4` of row `yy`, written at `o .. o + 4` of the band's buffers `b`
    /// (flow, expected target depth, front fraction, source depth).
    #[inline(always)]
    pub(super) fn four(
        &self,
        x: usize,
        yy: usize,
        active: &[usize],
        o: usize,
        b: &mut [&mut [f32]; 4],
        want: Option<&[bool; 4]>,
    ) {
        use crate::render::simd::exp_neg4;
        use wide::f32x4;
        let sp = f32x4::splat;
        let (zero, one) = (sp(0.0), sp(1.0));
        let four = |v: &[f32]| f32x4::from(*<&[f32; 4]>::try_from(&v[x..x + 4]).expect("four columns"));
        let (xf, ux) = (four(&self.xs), four(&self.ux));
        let y = yy as f64 as f32;
        let uy = sp(self.uy[yy]);
        let norm_u = (ux * ux + uy * uy + one).sqrt();
        let a: [f32x4; 3] = std::array::from_fn(|r| sp(self.m[r][0]) * xf + sp(self.m[r][1] * y) + sp(self.m[r][2]));
        let (mut tr, mut fu, mut fv, mut sw, mut sz, mut sall, mut sd) = (one, zero, zero, zero, zero, zero, zero);
        let (t_eps, z_lim) = (sp(self.t_eps), sp(self.z_min) * (a[2].abs() + one));
        let depth_max = sp(DEPTH_MAX as f32);
        for &i in active {
            // a lane is done once its transmittance is below t_eps (it only falls)
            let live = !tr.simd_lt(t_eps);
            if !live.any() {
                break;
            }
            let sigma = self.rgba.sigma4(i, x, yy);
            let take = live & !sigma.simd_le(zero);
            if !take.any() {
                continue;
            }
            let e = exp_neg4(sigma * sp(self.gap[i]) * norm_u);
            let wgt = tr * (one - e);
            tr = take.select(tr * e, tr);
            sall = take.select(sall + wgt, sall);
            let (dl, zl) = self.texels::<4>(i, x, yy);
            let (d, depth) = (f32x4::from(dl), f32x4::from(zl));
            if self.want_sd {
                sd = take.select(sd + wgt * depth, sd);
            }
            let hz = a[2] + sp(self.b[2]) * d;
            let front = take & hz.simd_gt(z_lim);
            if front.any() {
                let hx = a[0] + sp(self.b[0]) * d;
                let hy = a[1] + sp(self.b[1]) * d;
                fu = front.select(fu + wgt * (hx / hz - xf), fu);
                fv = front.select(fv + wgt * (hy / hz - sp(y)), fv);
                sw = front.select(sw + wgt, sw);
                let z = hz * depth;
                let z = z.simd_gt(depth_max).select(depth_max, z);
                sz = front.select(sz + wgt * z, sz);
            }
        }
        let [fu, fv, sw, sz, sall, sd] = [fu, fv, sw, sz, sall, sd].map(f32x4::to_array);
        self.write(o, [fu, fv, sw, sz, sall, sd], b, want);
    }
}

impl SourceLanes<'_> {
    /// Writes the `L` pixels `o .. o + L` of the band from their sums `[fu, fv, sw, sz, sall,
    /// sd]`: flow and depth normalised by the weight in front, `valid` the share in front, the
    /// expected depth (the scalar loop's divisions, pixel by pixel); with `want`, only the
    /// pixels asked for.
    #[inline(always)]
    fn write<const L: usize>(
        &self,
        o: usize,
        [fu, fv, sw, sz, sall, sd]: [[f32; L]; 6],
        b: &mut [&mut [f32]; 4],
        want: Option<&[bool; L]>,
    ) {
        // the scalar loop's T::of(1e-6)
        const EPS: f32 = 1e-6_f64 as f32;
        for k in 0..L {
            if want.is_some_and(|m| !m[k]) {
                continue;
            }
            let o = o + k;
            if sw[k] > EPS {
                b[0][2 * o] = fu[k] / sw[k];
                b[0][2 * o + 1] = fv[k] / sw[k];
                b[1][o] = sz[k] / sw[k];
            }
            b[2][o] = if sall[k] > 0.0 { sw[k] / sall[k] } else { 0.0 };
            if self.want_sd && sall[k] > EPS {
                b[3][o] = sd[k] / sall[k];
            }
        }
    }

    /// [`Self::four`] for the `L` pixels `x .. x + L` (the paths whose registers hold 8 or 16
    /// values, [`crate::isa`]) in plain arrays: lane by lane the same operations in the same
    /// order, which LLVM turns into the path's vector instructions, so the same bits (the
    /// negated compares are the scalar loop's: NaN densities are taken, as there).
    #[allow(clippy::neg_cmp_op_on_partial_ord)]
    #[inline(always)]
    pub(super) fn wide<const L: usize>(
        &self,
        x: usize,
        yy: usize,
        active: &[usize],
        o: usize,
        b: &mut [&mut [f32]; 4],
        want: Option<&[bool; L]>,
    ) {
        use std::array::from_fn;
        let ld = |v: &[f32]| -> [f32; L] { v[x..x + L].try_into().expect("L columns") };
        let (xf, ux) = (ld(&self.xs), ld(&self.ux));
        let y = yy as f64 as f32;
        let uy = self.uy[yy];
        let norm_u: [f32; L] = from_fn(|k| (ux[k] * ux[k] + uy * uy + 1.0).sqrt());
        let m = &self.m;
        let a: [[f32; L]; 3] = from_fn(|r| from_fn(|k| m[r][0] * xf[k] + m[r][1] * y + m[r][2]));
        let z_lim: [f32; L] = from_fn(|k| self.z_min * (a[2][k].abs() + 1.0));
        let mut tr = [1.0f32; L];
        let (mut fu, mut fv, mut sw, mut sz, mut sall, mut sd) =
            ([0.0f32; L], [0.0; L], [0.0; L], [0.0; L], [0.0; L], [0.0; L]);
        let depth_max = DEPTH_MAX as f32;
        let sel = |m: bool, a: f32, b: f32| if m { a } else { b };
        for &i in active {
            // a lane is done once its transmittance is below t_eps (it only falls)
            if tr.iter().all(|&t| t < self.t_eps) {
                break;
            }
            let sigma = self.rgba.sigma_n::<L>(i, x, yy);
            let take: [bool; L] = from_fn(|k| !(tr[k] < self.t_eps) & !(sigma[k] <= 0.0));
            if !take.iter().any(|&t| t) {
                continue;
            }
            let gap = self.gap[i];
            let (d, depth) = self.texels::<L>(i, x, yy);
            let e: [f32; L] = from_fn(|k| f32::exp_neg(sigma[k] * gap * norm_u[k]));
            let wgt: [f32; L] = from_fn(|k| tr[k] * (1.0 - e[k]));
            tr = from_fn(|k| sel(take[k], tr[k] * e[k], tr[k]));
            sall = from_fn(|k| sel(take[k], sall[k] + wgt[k], sall[k]));
            if self.want_sd {
                sd = from_fn(|k| sel(take[k], sd[k] + wgt[k] * depth[k], sd[k]));
            }
            let hz: [f32; L] = from_fn(|k| a[2][k] + self.b[2] * d[k]);
            let front: [bool; L] = from_fn(|k| take[k] & (hz[k] > z_lim[k]));
            if front.iter().any(|&f| f) {
                let (bx, by): ([f32; L], [f32; L]) = (from_fn(|k| self.b[0] * d[k]), from_fn(|k| self.b[1] * d[k]));
                fu = from_fn(|k| sel(front[k], fu[k] + wgt[k] * ((a[0][k] + bx[k]) / hz[k] - xf[k]), fu[k]));
                fv = from_fn(|k| sel(front[k], fv[k] + wgt[k] * ((a[1][k] + by[k]) / hz[k] - y), fv[k]));
                sw = from_fn(|k| sel(front[k], sw[k] + wgt[k], sw[k]));
                sz = from_fn(|k| {
                    let z = hz[k] * depth[k];
                    let z = if z > depth_max { depth_max } else { z };
                    sel(front[k], sz[k] + wgt[k] * z, sz[k])
                });
            }
        }
        self.write(o, [fu, fv, sw, sz, sall, sd], b, want);
    }
}
