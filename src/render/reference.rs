//! Reference-compatible rendering: the formulas of the public MPI-Flow implementation
//! (`render_novel_view_dynamic`), including its quirks, as documented in
//! `vectors/reference_render/README.md`: target samples at q = pi(H_i^-1 p) clamped to the image
//! border, sigma zeroed where the warped Z < 0, T_i = prod_{j<i}(exp(-sigma_j delta_j) + 1e-6),
//! last delta 1e3, depth = sum w Z / (sum w + 1e-5), flow = clip(sum w_src flow_i, -200, 200).
//! One addition keeps it finite where the reference is not: plane depths are capped at
//! [`DEPTH_MAX`](crate::mpi::planes::DEPTH_MAX), so a plane at disparity 0 sits very far away instead of at infinity.

/// Plane depth as the reference uses it, capped so that disparity 0 stays finite.
fn plane_depth(mpi: &Mpi, i: usize) -> f64 {
    planes::plane_depth(mpi.disparity[i])
}

use super::band::{for_each_band, mark_valid};
use super::real::Real;
use super::tap::Tap;
use super::types::{RenderOutput, RenderParams, RenderStats};
use super::window::Rect;
use crate::geometry::plane_homography;
use crate::mpi::planes;
use crate::mpi::planes::DELTA_LAST;
use crate::mpi::Mpi;

type M3<T> = [[T; 3]; 3];

fn to_t<T: Real>(m: &glam::DMat3) -> M3<T> {
    let r = |i: usize| [T::of(m.row(i).x), T::of(m.row(i).y), T::of(m.row(i).z)];
    [r(0), r(1), r(2)]
}

#[inline(always)]
fn mul<T: Real>(m: &M3<T>, x: T, y: T) -> [T; 3] {
    [m[0][0] * x + m[0][1] * y + m[0][2], m[1][0] * x + m[1][1] * y + m[1][2], m[2][0] * x + m[2][1] * y + m[2][2]]
}

pub(super) fn target_view<T: Real>(mpi: &Mpi, p: &RenderParams, out: &mut RenderOutput) -> RenderStats {
    let (w, h, n, c) = (mpi.width, mpi.height, mpi.planes(), mpi.extra_channels);
    // per plane: H_i^-1 (target pixel -> source pixel) and A_i = d_i R K_s^-1 (source pixel -> X_tgt - t)
    let planes: Vec<(M3<T>, M3<T>)> = (0..n)
        .map(|i| {
            let d = plane_depth(mpi, i);
            let hinv = plane_homography(&p.k_src, &p.k_tgt, &p.pose, d).inverse();
            let a = p.pose.rotation * p.k_src.inverse_matrix() * d;
            (to_t::<T>(&hinv), to_t::<T>(&a))
        })
        .collect();
    let t = [T::of(p.pose.translation.x), T::of(p.pose.translation.y), T::of(p.pose.translation.z)];
    let (wm, hm) = (T::of((w - 1) as f64), T::of((h - 1) as f64));
    let eps_t = T::of(1e-6);
    let (image, depth, coverage, extras) = (&mut out.image, &mut out.depth, &mut out.coverage, &mut out.extras);
    for_each_band(w, h, [image, depth, coverage, extras], [3, 1, 1, c], |y0, rows, b| {
        let mut stats = RenderStats::default();
        let mut acc_ex = vec![T::zero(); c];
        let mut prev_ex = vec![T::zero(); c];
        let mut cur_ex = vec![T::zero(); c];
        for ry in 0..rows {
            let y = T::of((y0 + ry) as f64);
            for x in 0..w {
                let xf = T::of(x as f64);
                let (mut tr, mut sum_w, mut sum_z) = (T::one(), T::zero(), T::zero());
                let mut rgb = [T::zero(); 3];
                acc_ex.iter_mut().for_each(|v| *v = T::zero());
                // previous plane: sigma, rgb, X_tgt
                let mut prev: Option<(T, [T; 3], [T; 3])> = None;
                for (i, (hinv, a)) in planes.iter().enumerate().take(n) {
                    let qh = mul(hinv, xf, y);
                    let qx = (qh[0] / qh[2]).max(T::zero()).min(wm);
                    let qy = (qh[1] / qh[2]).max(T::zero()).min(hm);
                    let tap = Tap::new(qx, qy, w, h);
                    let s = tap.sample4(mpi.plane_rgba(i));
                    tap.sample_c(mpi.plane_extras(i), c, &mut cur_ex);
                    stats.samples += 1;
                    let ax = mul(a, qx, qy);
                    let xt = [ax[0] + t[0], ax[1] + t[1], ax[2] + t[2]];
                    let sigma = if xt[2] < T::zero() { T::zero() } else { s[3] };
                    if let Some((ps, prgb, px)) = prev {
                        let d = ((xt[0] - px[0]).powi(2) + (xt[1] - px[1]).powi(2) + (xt[2] - px[2]).powi(2)).sqrt();
                        let e = T::exp_neg(ps * d);
                        let wgt = tr * (T::one() - e);
                        composite(wgt, prgb, px[2], &prev_ex, &mut rgb, &mut sum_w, &mut sum_z, &mut acc_ex);
                        tr *= e + eps_t;
                    }
                    prev = Some((sigma, [s[0], s[1], s[2]], xt));
                    std::mem::swap(&mut prev_ex, &mut cur_ex);
                }
                if let Some((ps, prgb, px)) = prev {
                    let e = T::exp_neg(ps * T::of(DELTA_LAST));
                    composite(
                        tr * (T::one() - e),
                        prgb,
                        px[2],
                        &prev_ex,
                        &mut rgb,
                        &mut sum_w,
                        &mut sum_z,
                        &mut acc_ex,
                    );
                }
                let o = ry * w + x;
                for k in 0..3 {
                    b[0][3 * o + k] = rgb[k].f32();
                }
                b[1][o] = (sum_z / (sum_w + T::of(1e-5))).f32();
                b[2][o] = sum_w.f32();
                for k in 0..c {
                    b[3][c * o + k] = acc_ex[k].f32();
                }
            }
        }
        stats
    })
}

#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn composite<T: Real>(
    wgt: T,
    rgb: [T; 3],
    z: T,
    ex: &[T],
    acc: &mut [T; 3],
    sum_w: &mut T,
    sum_z: &mut T,
    acc_ex: &mut [T],
) {
    for k in 0..3 {
        acc[k] += wgt * rgb[k];
    }
    *sum_w += wgt;
    *sum_z += wgt * z;
    for (a, e) in acc_ex.iter_mut().zip(ex) {
        *a += wgt * *e;
    }
}

pub(super) fn source_view<T: Real>(mpi: &Mpi, p: &RenderParams, out: &mut RenderOutput) {
    let (w, h, n) = (mpi.width, mpi.height, mpi.planes());
    let hs: Vec<M3<T>> =
        (0..n).map(|i| to_t::<T>(&plane_homography(&p.k_src, &p.k_tgt, &p.pose, plane_depth(mpi, i)))).collect();
    let depths: Vec<T> = (0..n).map(|i| T::of(plane_depth(mpi, i))).collect();
    let ks = p.k_src;
    let clip = T::of(200.0);
    let eps_t = T::of(1e-6);
    let mut flow = std::mem::take(&mut out.flow);
    let mut zexp = std::mem::take(&mut out.source_depth_in_target);
    let mut front = vec![0.0f32; w * h];
    for_each_band(w, h, [&mut flow, &mut zexp, &mut front], [2, 1, 1], |y0, rows, b| {
        for ry in 0..rows {
            let yy = y0 + ry;
            let y = T::of(yy as f64);
            let uy = T::of((yy as f64 - ks.cy) / ks.fy);
            for x in 0..w {
                let xf = T::of(x as f64);
                let ux = T::of((x as f64 - ks.cx) / ks.fx);
                let norm_u = (ux * ux + uy * uy + T::one()).sqrt();
                let (mut tr, mut fu, mut fv, mut sw, mut sz, mut sfront) =
                    (T::one(), T::zero(), T::zero(), T::zero(), T::zero(), T::zero());
                let pix = yy * w + x;
                for i in 0..n {
                    let sigma = T::of32(mpi.plane_rgba(i)[4 * pix + 3]);
                    let delta = if i + 1 < n { (depths[i + 1] - depths[i]) * norm_u } else { T::of(DELTA_LAST) };
                    let e = T::exp_neg(sigma * delta);
                    let wgt = tr * (T::one() - e);
                    tr *= e + eps_t;
                    let hp = mul(&hs[i], xf, y);
                    fu += wgt * (hp[0] / hp[2] - xf);
                    fv += wgt * (hp[1] / hp[2] - y);
                    sw += wgt;
                    sz += wgt * hp[2] * depths[i];
                    if hp[2] > T::zero() {
                        sfront += wgt;
                    }
                }
                let o = ry * w + x;
                b[0][2 * o] = fu.max(-clip).min(clip).f32();
                b[0][2 * o + 1] = fv.max(-clip).min(clip).f32();
                b[1][o] = if sw > T::zero() { (sz / sw).f32() } else { 0.0 };
                b[2][o] = if sw > T::zero() { (sfront / sw).f32() } else { 0.0 };
            }
        }
        RenderStats::default()
    });
    out.valid = mark_valid(&Rect::full(w, h), w, h, &flow, &front);
    out.flow = flow;
    out.source_depth_in_target = zexp;
}
