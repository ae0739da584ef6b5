//! Per-plane block occupancy of an MPI: which 8x8 source blocks hold any density above a
//! threshold, as 2-D prefix counts, so the renderer can ask in O(1) whether a plane is empty over
//! the footprint of a target tile and skip it there.

use super::store::Rgba;
use super::types::{Mode, RenderParams};
use crate::mpi::Mpi;

pub const BLOCK: usize = 8;

#[derive(Clone, Debug)]
pub struct Occupancy {
    bw: usize,
    bh: usize,
    width: usize,
    height: usize,
    /// Threshold used: a block is occupied when some sigma > `sigma_eps`.
    pub sigma_eps: f32,
    /// Per plane, (bh + 1) x (bw + 1) prefix counts of occupied blocks.
    prefix: Vec<Vec<u32>>,
    /// Per plane, whether any block is occupied.
    pub plane_any: Vec<bool>,
}

impl Occupancy {
    pub fn build(mpi: &Mpi, sigma_eps: f32) -> Self {
        let (w, h) = (mpi.width, mpi.height);
        let bw = w.div_ceil(BLOCK);
        let bh = h.div_ceil(BLOCK);
        let mut prefix = Vec::with_capacity(mpi.planes());
        let mut plane_any = Vec::with_capacity(mpi.planes());
        let rgba = Rgba::of(mpi);
        for i in 0..mpi.planes() {
            let mut occ = vec![false; bw * bh];
            for y in 0..h {
                let brow = &mut occ[(y / BLOCK) * bw..(y / BLOCK + 1) * bw];
                for x in 0..w {
                    if rgba.sigma(i, x, y) > sigma_eps {
                        brow[x / BLOCK] = true;
                    }
                }
            }
            let mut p = vec![0u32; (bw + 1) * (bh + 1)];
            for by in 0..bh {
                let mut run = 0u32;
                for bx in 0..bw {
                    run += occ[by * bw + bx] as u32;
                    p[(by + 1) * (bw + 1) + bx + 1] = p[by * (bw + 1) + bx + 1] + run;
                }
            }
            plane_any.push(p[(bh + 1) * (bw + 1) - 1] > 0);
            prefix.push(p);
        }
        Self { bw, bh, width: w, height: h, sigma_eps, prefix, plane_any }
    }

    /// Whether plane `i` has any occupied block overlapping the pixel box [x0, x1] x [y0, y1]
    /// (inclusive, clamped to the image; a box fully outside is empty).
    pub fn any_in(&self, i: usize, x0: f64, y0: f64, x1: f64, y1: f64) -> bool {
        let (wm, hm) = ((self.width - 1) as f64, (self.height - 1) as f64);
        if x1 < 0.0 || y1 < 0.0 || x0 > wm || y0 > hm {
            return false;
        }
        let bx0 = (x0.max(0.0) as usize) / BLOCK;
        let by0 = (y0.max(0.0) as usize) / BLOCK;
        let bx1 = ((x1.min(wm) as usize) / BLOCK).min(self.bw - 1);
        let by1 = ((y1.min(hm) as usize) / BLOCK).min(self.bh - 1);
        let p = &self.prefix[i];
        let s = self.bw + 1;
        let count = p[(by1 + 1) * s + bx1 + 1] + p[by0 * s + bx0] - p[by0 * s + bx1 + 1] - p[(by1 + 1) * s + bx0];
        count > 0
    }
}

/// The tile occupancy an exact render with tile skipping uses: `given` when it was built with
/// the render's threshold, else one built into `built`; none in reference mode or without tiles.
pub(crate) fn tile_occupancy<'a>(
    mpi: &Mpi,
    params: &RenderParams,
    given: Option<&'a Occupancy>,
    built: &'a mut Option<Occupancy>,
) -> Option<&'a Occupancy> {
    if params.mode != Mode::Exact || !params.skip.tiles {
        return None;
    }
    match given {
        Some(o) if o.sigma_eps == params.skip.tile_sigma_eps => Some(o),
        _ => Some(built.insert(Occupancy::build(mpi, params.skip.tile_sigma_eps))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_single_occupied_block() {
        let mut m = Mpi::new(40, 30, vec![0.5], 0);
        let (x, y) = (21, 17);
        m.rgba[(y * 40 + x) * 4 + 3] = 1.0;
        let o = Occupancy::build(&m, 0.0);
        assert!(o.plane_any[0]);
        assert!(o.any_in(0, 0.0, 0.0, 39.0, 29.0));
        assert!(o.any_in(0, 16.0, 16.0, 23.0, 23.0));
        assert!(!o.any_in(0, 0.0, 0.0, 15.0, 29.0));
        assert!(!o.any_in(0, 24.0, 0.0, 39.0, 29.0));
        assert!(!o.any_in(0, -10.0, -10.0, -1.0, -1.0));
        assert!(!o.any_in(0, 50.0, 0.0, 60.0, 10.0));
    }
}
