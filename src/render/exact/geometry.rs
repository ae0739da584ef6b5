//! The target view's per-render constants ([`TargetGeometry`]): what every ray of the view
//! shares, computed once before the band loop.

use super::plane::{PlaneConst, SurfaceRay};
use crate::mpi::planes::{plane_depth, DELTA_LAST};
use crate::mpi::Mpi;
use crate::render::real::Real;
use crate::render::types::RenderParams;
use crate::render::window::Rect;

/// The per-render constants of the target view: the target intrinsics, the planes' constants,
/// R^T, the source focal lengths, the bounds of the "leaves the source image" test and of the
/// edge clamp, the early-termination threshold, the last gap, and the window's columns and rows
/// as u = K_t^-1 p.
pub(super) struct TargetGeometry<T> {
    pub(super) kt: crate::geometry::Intrinsics,
    pub(super) planes: Vec<PlaneConst<T>>,
    pub(super) rt_t: [[T; 3]; 3],
    pub(super) fxs: T,
    pub(super) fys: T,
    pub(super) lo: T,
    pub(super) hix: T,
    pub(super) hiy: T,
    pub(super) wm: T,
    pub(super) hm: T,
    pub(super) t_eps: T,
    pub(super) delta_last: T,
    pub(super) ux: Vec<T>,
    pub(super) uy: Vec<T>,
    /// The target centre in source coordinates (x, y), k = -C_z and the source principal
    /// point: a true-depth texel's search ([`Self::surface_ray`]).
    pub(super) centre: [T; 2],
    pub(super) k: T,
    pub(super) cs: [T; 2],
}

impl<T: Real> TargetGeometry<T> {
    pub(super) fn new(mpi: &Mpi, p: &RenderParams, win: &Rect) -> Self {
        let (w, h) = (mpi.width, mpi.height);
        let (ks, kt) = (p.k_src, p.k_tgt);
        let rt = p.pose.rotation.transpose();
        let centre = p.pose.target_centre_in_source();
        let k = -centre.z;
        let planes: Vec<PlaneConst<T>> = mpi
            .disparity
            .iter()
            .enumerate()
            .map(|(i, &disp)| (crate::mpi::Surface::slab(&mpi.disparity, i), disp))
            .map(|((lo, hi), disp)| PlaneConst {
                a: T::of(1.0 + k * disp),
                depth: T::of(plane_depth(disp)),
                disp: T::of(disp),
                ox: T::of(ks.fx * centre.x * disp + ks.cx),
                oy: T::of(ks.fy * centre.y * disp + ks.cy),
                lo: T::of(lo),
                hi: T::of(hi),
            })
            .collect();
        let r = |i: usize| [T::of(rt.row(i).x), T::of(rt.row(i).y), T::of(rt.row(i).z)];
        Self {
            kt,
            planes,
            rt_t: [r(0), r(1), r(2)],
            fxs: T::of(ks.fx),
            fys: T::of(ks.fy),
            lo: T::of(-0.5),
            hix: T::of(w as f64 - 0.5),
            hiy: T::of(h as f64 - 0.5),
            wm: T::of((w - 1) as f64),
            hm: T::of((h - 1) as f64),
            t_eps: T::of32(p.skip.transmittance_eps),
            delta_last: T::of(DELTA_LAST),
            ux: (win.x0..win.x1).map(|x| T::of((x as f64 - kt.cx) / kt.fx)).collect(),
            uy: (win.y0..win.y1).map(|y| T::of((y as f64 - kt.cy) / kt.fy)).collect(),
            centre: [T::of(centre.x), T::of(centre.y)],
            k: T::of(k),
            cs: [T::of(ks.cx), T::of(ks.cy)],
        }
    }

    /// The search of a true-depth texel over `surface` ([`SurfaceRay`]).
    pub(super) fn surface_ray<'a>(&self, surface: &'a [f32], w: usize, h: usize) -> SurfaceRay<'a, T> {
        SurfaceRay {
            surface,
            fs: [self.fxs, self.fys],
            cs: self.cs,
            centre: self.centre,
            k: self.k,
            wm: self.wm,
            hm: self.hm,
            w,
            h,
        }
    }
}
