//! The reference generator's pre-blend of network MPIs: every plane's colour is pulled towards
//! the source photo where that plane is visible from the source camera,
//! `rgb_i <- T_src_i * source + (1 - T_src_i) * rgb_i`, so the source view reproduces the photo
//! wherever the network's colours would blur it.
//!
//! `T_src_i` is the source-view transmittance in front of plane `i`, exactly as the public
//! reference computes it (its `blend_weights`): `T_0 = 1`,
//! `T_i = prod_{j<i} (exp(-sigma_j delta_j) + 1e-6)`, with the ray distance between planes
//! `delta_j = (d_{j+1} - d_j) |K^-1 p|` for the source pixel `p` (`d = 1 / disparity`, capped at
//! [`DEPTH_MAX`](planes::DEPTH_MAX); a gap is capped at [`DELTA_LAST`](planes::DELTA_LAST)) and
//! `delta_{N-1} = 1e3` (`DELTA_LAST`): the shared plane-spacing rule of [`crate::mpi::planes`].
//! The `+1e-6` is the reference's (it keeps a plane behind an opaque one from being fully
//! replaced by its own colour: `T` never reaches 0).
//!
//! Meant for MPIs from a network (AdaMPI-style colours are soft); the built-in layering already
//! puts the photo's colour on every plane where it is visible, so there the source view stays
//! the same (to 1e-7, tested) and novel views change only where bilinear sampling at a layer's
//! edge mixes in the colour of an empty plane pixel. It is applied once per scene, when the
//! scene is prepared for the cache (`SampleConfig::preblend`); the
//! cache key carries the option. Cost: one pass over the planes, in parallel over row bands.
//! The `+1e-6` and the in-place colour update make this a pass of its own rather than a call of
//! the renderer (whose source view has neither); only the gap rule is shared.

use rayon::prelude::*;

use crate::geometry::Intrinsics;
use crate::mpi::planes;
use crate::mpi::Mpi;
use crate::raster::Grid;

/// The reference's `+1e-6` in every transmittance factor.
pub const TRANSMITTANCE_EPS: f32 = 1e-6;

/// Rows per parallel task.
const BAND_ROWS: usize = 16;

#[derive(Debug, thiserror::Error)]
pub enum PreblendError {
    #[error("pre-blend: the source image is {got} values, the MPI needs {need} ({w} x {h} x 3)")]
    Size { got: usize, need: usize, w: usize, h: usize },
    #[error("pre-blend: invalid intrinsics {0:?}")]
    Intrinsics(Intrinsics),
}

/// The per-pixel source-view gap to the next plane before the `|K^-1 p|` factor, in f32 (the
/// shared rule of [`crate::mpi::planes`], set up in f64).
fn plane_gaps(mpi: &Mpi) -> Vec<f32> {
    planes::plane_gaps(&mpi.disparity).iter().map(|&g| g as f32).collect()
}

/// Pre-blends `mpi` with the source photo `image` (H x W x 3, the MPI's size) seen through
/// intrinsics `k` (see the module documentation). Extra channels are left alone. Returns an
/// error when the sizes disagree or `k` is unusable; the MPI is then unchanged.
pub fn preblend(mpi: &mut Mpi, image: &[f32], k: &Intrinsics) -> Result<(), PreblendError> {
    let (w, h) = (mpi.width, mpi.height);
    if image.len() != w * h * 3 {
        return Err(PreblendError::Size { got: image.len(), need: w * h * 3, w, h });
    }
    if !k.is_valid() {
        return Err(PreblendError::Intrinsics(*k));
    }
    let n = mpi.planes();
    if n == 0 || w == 0 || h == 0 {
        return Ok(());
    }
    let last = n - 1;
    let gaps: Vec<f32> = plane_gaps(mpi);
    // |K^-1 p| per pixel, separable: sqrt(ux^2 + uy^2 + 1)
    let ux: Vec<f64> = (0..w).map(|x| (x as f64 - k.cx) / k.fx).collect();
    let uy: Vec<f64> = (0..h).map(|y| (y as f64 - k.cy) / k.fy).collect();
    let band_len = BAND_ROWS * w;
    let nbands = h.div_ceil(BAND_ROWS);
    // bands[b][i] = plane i's rows of band b
    let mut bands: Vec<Vec<&mut [f32]>> = (0..nbands).map(|_| Vec::with_capacity(n)).collect();
    for plane in mpi.rgba.chunks_mut(w * h * 4) {
        for (b, chunk) in plane.chunks_mut(band_len * 4).enumerate() {
            bands[b].push(chunk);
        }
    }
    bands.par_iter_mut().enumerate().for_each(|(b, planes)| {
        let y0 = b * BAND_ROWS;
        let rows = BAND_ROWS.min(h - y0);
        let mut t = vec![1.0f32; rows * w];
        let norm: Vec<f32> = (0..rows * w)
            .map(|o| {
                let (x, y) = (o % w, y0 + o / w);
                (ux[x] * ux[x] + uy[y] * uy[y] + 1.0).sqrt() as f32
            })
            .collect();
        for (i, plane) in planes.iter_mut().enumerate() {
            for (o, px) in plane.chunks_exact_mut(4).enumerate() {
                let tr = t[o];
                let src = &image[3 * (y0 * w + o)..3 * (y0 * w + o) + 3];
                for c in 0..3 {
                    px[c] = tr * src[c] + (1.0 - tr) * px[c];
                }
                let delta = if i < last { gaps[i] * norm[o] } else { gaps[i] };
                t[o] = tr * ((-px[3] * delta).exp() + TRANSMITTANCE_EPS);
            }
        }
    });
    Ok(())
}

/// The source-view transmittance `T_src` in front of every plane (N x H x W, plane-major), as
/// [`preblend`] uses it (for tests and diagnostics).
pub fn source_transmittance(mpi: &Mpi, k: &Intrinsics) -> Vec<f32> {
    let (g, n) = (Grid::new(mpi.width, mpi.height), mpi.planes());
    let gaps: Vec<f32> = plane_gaps(mpi);
    let mut out = vec![0.0f32; n * g.len()];
    for (x, y) in g.pixels() {
        let p = g.index(x, y);
        let u = k.unproject(x as f64, y as f64).length() as f32;
        let mut t = 1.0f32;
        for (i, plane) in out.chunks_exact_mut(g.len().max(1)).enumerate() {
            plane[p] = t;
            let delta = if i + 1 < n { gaps[i] * u } else { gaps[i] };
            let sigma = mpi.plane_rgba(i)[4 * p + 3];
            t *= (-sigma * delta).exp() + TRANSMITTANCE_EPS;
        }
    }
    out
}
