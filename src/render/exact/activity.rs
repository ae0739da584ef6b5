//! Tile skipping in the target view: which planes can contribute inside a tile
//! ([`tile_activity`]), from the tile occupancy of the source planes.

use super::plane::{PlaneConst, SurfaceRay};
use crate::render::occupancy::Occupancy;
use crate::render::real::Real;

/// Marks which planes can contribute inside the target tile [x0, x1] x [y0, y1]: a plane is
/// skipped when its source footprint over the tile (the bounding box of the four corner
/// samples, grown by one pixel for the bilinear support) holds no occupied block. The footprint
/// is exact only when the plane is in front of the camera over the whole tile, so a tile where
/// some corner sees the plane from behind keeps the plane active. With `along` (a true-depth
/// MPI's search, [`SurfaceRay`]) the footprint also holds
/// the corners' points at both ends of the plane's slab: a texel's point moves along its ray's
/// source segment between them (affine in disparity), and a point behind the camera is not drawn.
pub(super) fn tile_activity<T: Real>(
    occ: &Occupancy,
    planes: &[PlaneConst<T>],
    ray: &impl Fn(f64, f64) -> ([T; 3], T),
    source_px: &impl Fn(&PlaneConst<T>, &[T; 3], T) -> (T, T),
    along: Option<&SurfaceRay<'_, T>>,
    [x0, y0, x1, y1]: [usize; 4],
    active: &mut [bool],
) {
    let corners = [(x0, y0), (x1, y0), (x0, y1), (x1, y1)].map(|(x, y)| ray(x as f64, y as f64).0);
    for (i, pl) in planes.iter().enumerate() {
        if !occ.plane_any[i] {
            active[i] = false;
            continue;
        }
        let (mut bx0, mut by0, mut bx1, mut by1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        let mut exact = true;
        for v in &corners {
            if v[2] <= T::zero() {
                exact = false;
                break;
            }
            let g = pl.a / v[2];
            if g <= T::zero() {
                exact = false;
                break;
            }
            let mut pts = [source_px(pl, v, g); 3];
            if let Some(sr) = along {
                let inv_s = T::one() / v[2];
                pts[1] = sr.at([v[0], v[1]], inv_s, pl.disp + pl.lo);
                pts[2] = sr.at([v[0], v[1]], inv_s, pl.disp + pl.hi);
            }
            for (qx, qy) in pts {
                let (qx, qy) = (qx.f64(), qy.f64());
                bx0 = bx0.min(qx);
                by0 = by0.min(qy);
                bx1 = bx1.max(qx);
                by1 = by1.max(qy);
            }
        }
        active[i] = !exact
            || ![bx0, bx1, by0, by1].iter().all(|v| v.is_finite())
            || occ.any_in(i, bx0 - 1.0, by0 - 1.0, bx1 + 1.0, by1 + 1.0);
    }
}
