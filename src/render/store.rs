//! How the renderer reads a plane's (r, g, b, sigma): the MPI's dense planes, or the blocks of a
//! packed MPI ([`pack`]: a prepared scene keeps only the 16 x 16 blocks a render can read, those
//! where the plane has density, in [`crate::mpi::Mpi::rgba_blocks`]). [`Rgba`] gives both the
//! same bits: a render reads colour only where the bilinear density is > 0, and a block left
//! out has no density anywhere its reads reach.

use super::real::Real;
use super::tap::Tap;
use super::types::{Mode, Resample};
use crate::mpi::bricks::{BlockGrid, Bricks};
use crate::mpi::Mpi;
use std::sync::Arc;

/// A render's view of the planes' rgba (see the module documentation).
#[derive(Clone)]
pub(crate) enum Rgba<'a> {
    Dense { planes: Vec<&'a [f32]>, w: usize },
    Blocks(&'a Bricks),
}

impl<'a> Rgba<'a> {
    pub(crate) fn of(mpi: &'a Mpi) -> Self {
        match &mpi.rgba_blocks {
            Some(b) => Rgba::Blocks(b),
            None => Rgba::Dense { planes: (0..mpi.planes()).map(|i| mpi.plane_rgba(i)).collect(), w: mpi.width },
        }
    }

    /// The bilinear (r, g, b, sigma) of plane `i` at `tap` ([`Tap::sample4`]); 0 in a block
    /// not stored.
    #[inline(always)]
    pub(crate) fn texel<T: Real>(&self, tap: &Tap<T>, i: usize) -> [T; 4] {
        match self {
            Rgba::Dense { planes, .. } => tap.sample4(planes[i]),
            Rgba::Blocks(b) => match b.offset(i, tap.x0, tap.y0) {
                Some(s) => tap.sample4_at(b.data(), s, b.row_len()),
                None => [T::zero(); 4],
            },
        }
    }

    /// The density of plane `i` at pixel (x, y).
    #[inline(always)]
    pub(crate) fn sigma(&self, i: usize, x: usize, y: usize) -> f32 {
        match self {
            Rgba::Dense { planes, w } => planes[i][4 * (y * w + x) + 3],
            Rgba::Blocks(b) => b.offset(i, x, y).map_or(0.0, |s| b.data()[s + 3]),
        }
    }

    /// The densities of plane `i` at pixels x .. x + L of row y (within the frame).
    #[inline(always)]
    pub(crate) fn sigma_n<const L: usize>(&self, i: usize, x: usize, y: usize) -> [f32; L] {
        match self {
            Rgba::Dense { planes, w } => {
                let s = &planes[i][4 * (y * w + x) + 3..];
                std::array::from_fn(|k| s[4 * k])
            }
            Rgba::Blocks(b) if x % Bricks::SIZE + L <= Bricks::SIZE => match b.offset(i, x, y) {
                Some(s) => {
                    let d = &b.data()[s + 3..s + 4 * L];
                    std::array::from_fn(|k| d[4 * k])
                }
                None => [0.0; L],
            },
            Rgba::Blocks(_) => std::array::from_fn(|k| self.sigma(i, x + k, y)),
        }
    }

    /// The densities of plane `i` at pixels x .. x + 4 of row y, in lanes.
    #[inline(always)]
    pub(crate) fn sigma4(&self, i: usize, x: usize, y: usize) -> wide::f32x4 {
        match self {
            Rgba::Dense { planes, w } => super::simd::gather(planes[i], 4 * (y * w + x) + 3, 4),
            Rgba::Blocks(b) if x % Bricks::SIZE + 3 < Bricks::SIZE => match b.offset(i, x, y) {
                Some(s) => super::simd::gather(&b.data()[s + 3..s + 16], 0, 4),
                None => wide::f32x4::splat(0.0),
            },
            Rgba::Blocks(_) => wide::f32x4::from(std::array::from_fn::<f32, 4, _>(|k| self.sigma(i, x + k, y))),
        }
    }
}

/// The blocks ([`Bricks::SIZE`] square) of plane `i` that hold an anchor pixel (x, y) with
/// density > 0 at (x, y), (x + 1, y), (x, y + 1) or (x + 1, y + 1): those a bilinear tap at
/// any point whose pixel lies in the block can find density in. A pixel with density marks its
/// own block and, on a block's first column or row, the blocks before it.
pub fn reachable_blocks(mpi: &Mpi, i: usize) -> Vec<bool> {
    let (w, h) = (mpi.width, mpi.height);
    let b = Bricks::SIZE;
    let (bw, bh) = (w.div_ceil(b), h.div_ceil(b));
    let mut keep = vec![false; bw * bh];
    let dense = |px: &[f32]| px[3] > 0.0;
    for (y, row) in mpi.plane_rgba(i).chunks_exact(4 * w).enumerate() {
        let by = y / b;
        // a block's first row also reaches the block above
        let up = (y % b == 0 && y > 0).then(|| by - 1);
        for (bx, cols) in row.chunks(4 * b).enumerate() {
            // any pixel of this row in the block marks it; its first pixel also the block before
            let mut mark = |bx: usize| {
                keep[by * bw + bx] = true;
                if let Some(u) = up {
                    keep[u * bw + bx] = true;
                }
            };
            if cols.chunks_exact(4).any(dense) {
                mark(bx);
                if bx > 0 && dense(&cols[..4]) {
                    mark(bx - 1);
                }
            }
        }
    }
    keep
}

/// Whether a prepared scene's MPI is packed ([`pack`]) for renders with these settings: in the
/// exact mode, with a kernel that reads colour only where there is density (bilinear and the
/// prefiltered kernels, whose coefficients are computed before), and without minification (its levels
/// read colour around the density).
pub fn packs(mode: Mode, resample: Resample, minify: bool) -> bool {
    use Resample as R;
    mode == Mode::Exact && !minify && (resample == R::Bilinear || resample.prefilter().is_some())
}

/// Packs the planes into blocks ([`crate::mpi::Mpi::rgba_blocks`]): the blocks of
/// [`reachable_blocks`], each with a one-pixel apron after it (the edge pixel repeated past the
/// frame, as [`Tap`] clamps), and drops the dense planes. Everything computed from the dense
/// planes (B-spline coefficients, minification levels, occupancy) must be computed before.
pub fn pack(mpi: &mut Mpi) {
    if mpi.is_packed() {
        return;
    }
    let (w, h, n) = (mpi.width, mpi.height, mpi.planes());
    let clamp = |c: isize, n: usize| c.clamp(0, n as isize - 1) as usize;
    let m: &Mpi = mpi;
    let grid = BlockGrid { width: w, height: h, stride: 4, lo: 0, hi: 1 };
    // the B-spline coefficients, where the scene has them, store exactly these blocks (the
    // colour prefilter keeps the reachable ones): their table saves a scan of the dense planes
    let keep =
        |i: usize| Some(m.bspline_rgb.as_ref().map_or_else(|| reachable_blocks(m, i), |c| c.coefficients.kept(i)));
    let blocks = Bricks::build(grid, n, |i| m.plane_rgba(i), keep, clamp);
    mpi.rgba_blocks = Some(Arc::new(blocks));
    crate::buf::give_back(std::mem::take(&mut mpi.rgba));
}

/// [`pack`] of a shared MPI (copied first only when others hold it).
pub fn pack_arc(mpi: &mut Arc<Mpi>) {
    if !mpi.is_packed() {
        pack(Arc::make_mut(mpi));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// The definition, pixel by pixel: a pixel with density marks its block and, on a block's
    /// first column or row, the blocks before it.
    fn reachable_by_pixel(mpi: &Mpi, i: usize) -> Vec<bool> {
        let (w, h, b) = (mpi.width, mpi.height, Bricks::SIZE);
        let bw = w.div_ceil(b);
        let mut keep = vec![false; bw * h.div_ceil(b)];
        for y in 0..h {
            for x in 0..w {
                if mpi.plane_rgba(i)[4 * (y * w + x) + 3] > 0.0 {
                    let bxs = [x / b, if x % b == 0 && x > 0 { x / b - 1 } else { x / b }];
                    let bys = [y / b, if y % b == 0 && y > 0 { y / b - 1 } else { y / b }];
                    for by in bys {
                        for bx in bxs {
                            keep[by * bw + bx] = true;
                        }
                    }
                }
            }
        }
        keep
    }

    proptest! {
        /// The block-wise scan marks exactly the blocks of the pixel-wise definition, for any
        /// size (partial blocks at the right and bottom) and any pixels with density (block
        /// edges, frame edges, NaN and negative densities, which hold none).
        #[test]
        fn reachable_blocks_follow_the_pixel_definition(
            w in 1usize..70,
            h in 1usize..50,
            dense in proptest::collection::vec((0usize..70 * 50, prop_oneof![Just(1.0f32), Just(-1.0), Just(f32::NAN), Just(1e-30)]), 0..12),
            edges in proptest::collection::vec((0usize..5, 0usize..4), 0..6),
        ) {
            let mut mpi = Mpi::new(w, h, vec![0.5], 0);
            let plane = mpi.plane_rgba_mut(0);
            for (p, sigma) in dense {
                plane[4 * (p % (w * h)) + 3] = sigma;
            }
            // pixels on block edges (x or y a multiple of 16)
            for (bx, by) in edges {
                let (x, y) = ((16 * bx).min(w - 1), (16 * by).min(h - 1));
                plane[4 * (y * w + x) + 3] = 2.0;
            }
            prop_assert_eq!(reachable_blocks(&mpi, 0), reachable_by_pixel(&mpi, 0));
        }
    }
}
