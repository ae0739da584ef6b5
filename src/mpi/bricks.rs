//! Block-sparse storage of per-pixel plane values ([`Bricks`]): each plane cut into
//! [`Bricks::SIZE`]-pixel square blocks, each block stored with an apron so that an N x N
//! neighbourhood whose anchor pixel lies in the block is one contiguous block of memory, and only
//! the blocks a reader can reach kept. The B-spline colour coefficients of a cached scene live
//! here (`render::resample`): the colour kernel only runs where a plane has density, and most
//! of a layered MPI's plane area has none (about 15% of the 16 x 16 blocks of a bundled scene's
//! planes hold any).

use rayon::prelude::*;

/// `u32::MAX` in the block table: the block is not stored.
const EMPTY: u32 = u32::MAX;

/// The shape of a [`Bricks`] store: planes of `width` x `height` pixels, `stride` values each,
/// cut into [`Bricks::SIZE`]-pixel blocks stored with an apron of `lo` pixels before and `hi`
/// after.
#[derive(Clone, Copy, Debug)]
pub struct BlockGrid {
    pub width: usize,
    pub height: usize,
    pub stride: usize,
    pub lo: usize,
    pub hi: usize,
}

impl BlockGrid {
    /// Blocks per row and per column.
    pub fn blocks(&self) -> (usize, usize) {
        (self.width.div_ceil(Bricks::SIZE), self.height.div_ceil(Bricks::SIZE))
    }

    /// Side of a stored block (its apron included).
    pub fn side(&self) -> usize {
        Bricks::SIZE + self.lo + self.hi
    }

    /// The values of the `kept` blocks (`bh x bw` flags, row-major) of one plane into `out`,
    /// block after block: `read(x, y, values)` writes the values of pixels x, x + 1, ...
    /// (`values.len() / stride` of them, inside the frame) of row y; `index` is the boundary rule
    /// of [`Bricks::build`]. A block whose columns lie inside the frame reads each of its rows
    /// at once.
    pub fn copy_blocks(
        &self,
        kept: &[bool],
        index: impl Fn(isize, usize) -> usize,
        read: impl Fn(usize, usize, &mut [f32]),
        out: &mut [f32],
    ) {
        let (w, h, s, lo) = (self.width, self.height, self.stride, self.lo as isize);
        let (bw, side) = (self.blocks().0, self.side());
        let row = side * s;
        let mut cols = vec![0usize; side];
        let mut blocks = out.chunks_exact_mut(side * row);
        for (b, _) in kept.iter().enumerate().filter(|&(_, &k)| k) {
            let (bx, by) = (b % bw, b / bw);
            let block = blocks.next().expect("copy_blocks: room for every kept block");
            let x0 = (bx * Bricks::SIZE) as isize - lo;
            let inside = x0 >= 0 && x0 as usize + side <= w;
            if !inside {
                for (u, c) in cols.iter_mut().enumerate() {
                    *c = index(x0 + u as isize, w);
                }
            }
            for (v, dst) in block.chunks_exact_mut(row).enumerate() {
                let sy = index((by * Bricks::SIZE + v) as isize - lo, h);
                if inside {
                    read(x0 as usize, sy, dst);
                } else {
                    for (d, &sx) in dst.chunks_exact_mut(s).zip(&cols) {
                        read(sx, sy, d);
                    }
                }
            }
        }
    }
}

/// Block-sparse planes of `stride` values per pixel; see the module documentation.
#[derive(Clone, Debug)]
pub struct Bricks {
    width: usize,
    height: usize,
    stride: usize,
    /// the apron before a block (columns and rows): the neighbourhood of anchor pixel x starts
    /// at x - lo
    lo: usize,
    /// side of a stored block: SIZE + lo + hi
    side: usize,
    /// values per stored block: side * side * stride
    block_len: usize,
    /// blocks per row and per column
    bw: usize,
    bh: usize,
    /// per plane, bh x bw entries: the index of the block's data, or [`EMPTY`]
    table: Vec<u32>,
    data: Vec<f32>,
}

impl Bricks {
    /// Pixels per block side.
    pub const SIZE: usize = 16;

    /// Zero values stored after the last block, so that a reader may load this many values
    /// from the start of any stored row (`render::exact::row16` loads a block row in five 512-bit
    /// registers) without a bounds branch.
    pub const TAIL: usize = 80;

    /// Builds the store of `planes` planes in the shape of `grid` (`width` x `height` pixels,
    /// `stride` values each, for neighbourhoods reaching `lo` pixels before and `hi` after their
    /// anchor).
    /// `plane(i)` gives plane `i` densely (row-major, interleaved, `width height stride` values;
    /// owned or borrowed);
    /// `keep(i)` which of its blocks to store (`bh x bw` flags, row-major; `None`: all);
    /// `index(c, n)` maps a column or row index `c` that may lie outside `0..n` to the one whose
    /// value the store holds there (the readers' boundary rule, e.g. a mirror; the identity
    /// inside `0..n`).
    ///
    /// # Panics
    /// If a plane has the wrong length, a flag list the wrong count, or the store would hold
    /// more than `u32::MAX` blocks.
    pub fn build<P: AsRef<[f32]>>(
        grid: BlockGrid,
        planes: usize,
        plane: impl Fn(usize) -> P + Sync,
        keep: impl Fn(usize) -> Option<Vec<bool>> + Sync,
        index: impl Fn(isize, usize) -> usize + Sync,
    ) -> Self {
        let BlockGrid { width, height, stride, .. } = grid;
        let fill = |_: &mut (), i: usize, kept: &[bool], out: &mut [f32]| {
            let dense = plane(i);
            let dense = dense.as_ref();
            assert_eq!(dense.len(), width * height * stride, "Bricks: plane {i} has the wrong length");
            let read = |x: usize, y: usize, values: &mut [f32]| {
                let at = (y * width + x) * stride;
                values.copy_from_slice(&dense[at..at + values.len()]);
            };
            grid.copy_blocks(kept, &index, read, out);
        };
        Self::build_with(grid, planes, keep, || (), fill)
    }

    /// [`Self::build`] with each plane's stored blocks written by `fill(scratch, i, kept, out)`:
    /// `out` holds the kept blocks of plane `i` one after the other (row-major order of the
    /// blocks, [`BlockGrid::copy_blocks`]'s layout), `scratch` is the worker's own (`init`), for
    /// buffers reused from plane to plane. Planes are filled in parallel.
    ///
    /// # Panics
    /// If a flag list has the wrong count or the store would hold more than `u32::MAX` blocks.
    pub fn build_with<S>(
        grid: BlockGrid,
        planes: usize,
        keep: impl Fn(usize) -> Option<Vec<bool>> + Sync,
        init: impl Fn() -> S + Sync + Send,
        fill: impl Fn(&mut S, usize, &[bool], &mut [f32]) + Sync + Send,
    ) -> Self {
        let BlockGrid { width, height, stride, lo, .. } = grid;
        let (bw, bh) = grid.blocks();
        let side = grid.side();
        let block_len = side * side * stride;
        let kept: Vec<Vec<bool>> = (0..planes)
            .into_par_iter()
            .map(|i| {
                let kept = keep(i).unwrap_or_else(|| vec![true; bw * bh]);
                assert_eq!(kept.len(), bw * bh, "Bricks: plane {i}'s block flags");
                kept
            })
            .collect();
        let counts: Vec<usize> = kept.iter().map(|k| k.iter().filter(|&&k| k).count()).collect();
        let stored: usize = counts.iter().sum();
        assert!(stored < EMPTY as usize, "Bricks: too many blocks");
        let mut table = Vec::with_capacity(planes * bw * bh);
        let mut next = 0u32;
        for k in kept.iter().flatten() {
            table.push(if *k {
                next += 1;
                next - 1
            } else {
                EMPTY
            });
        }
        let mut data: Vec<f32> = crate::buf::zeros(stored * block_len + Self::TAIL);
        let mut parts: Vec<(usize, &mut [f32])> = Vec::with_capacity(planes);
        let mut rest: &mut [f32] = &mut data;
        for (i, &c) in counts.iter().enumerate() {
            let (part, after) = rest.split_at_mut(c * block_len);
            parts.push((i, part));
            rest = after;
        }
        parts.into_par_iter().for_each_init(&init, |scratch, (i, out)| fill(scratch, i, &kept[i], out));
        Self { width, height, stride, lo, side, block_len, bw, bh, table, data }
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// Values per pixel.
    pub fn stride(&self) -> usize {
        self.stride
    }

    pub fn planes(&self) -> usize {
        self.table.len() / (self.bw * self.bh).max(1)
    }

    /// Plane `i` spread out densely (row-major, interleaved): every pixel some stored block holds
    /// (in its own area or its apron) gets that value, the others 0.
    pub fn plane_dense(&self, i: usize) -> Vec<f32> {
        let (s, side, w, h) = (self.stride, self.side, self.width, self.height);
        let mut out = vec![0.0; w * h * s];
        for by in 0..self.bh {
            for bx in 0..self.bw {
                let b = self.table[(i * self.bh + by) * self.bw + bx];
                if b == EMPTY {
                    continue;
                }
                let data = &self.data[b as usize * self.block_len..(b as usize + 1) * self.block_len];
                for v in 0..side {
                    let Some(y) = (by * Self::SIZE + v).checked_sub(self.lo).filter(|&y| y < h) else { continue };
                    for u in 0..side {
                        let Some(x) = (bx * Self::SIZE + u).checked_sub(self.lo).filter(|&x| x < w) else { continue };
                        let at = (v * side + u) * s;
                        out[(y * w + x) * s..(y * w + x + 1) * s].copy_from_slice(&data[at..at + s]);
                    }
                }
            }
        }
        out
    }

    /// Which blocks of plane `i` are stored (row-major over the blocks).
    pub fn kept(&self, i: usize) -> Vec<bool> {
        let n = self.bw * self.bh;
        self.table[i * n..(i + 1) * n].iter().map(|&b| b != EMPTY).collect()
    }

    /// Distance in values between two rows of a neighbourhood ([`Self::neighbourhood`]).
    #[inline(always)]
    pub fn row_len(&self) -> usize {
        self.side * self.stride
    }

    /// The neighbourhood of anchor pixel (x, y) (inside the plane) of plane `i`: the data of
    /// its block and the index in it of the value at (x - lo, y - lo), the neighbourhood's first;
    /// rows follow [`Self::row_len`] apart. `None` where the block is not stored.
    #[inline(always)]
    pub fn neighbourhood(&self, i: usize, x: usize, y: usize) -> Option<(&[f32], usize)> {
        let at = self.offset(i, x, y)?;
        let (u, v) = (x % Self::SIZE, y % Self::SIZE);
        let start = (v * self.side + u) * self.stride;
        let block = at - start;
        Some((&self.data[block..block + self.block_len], start))
    }

    /// Where the neighbourhood of anchor pixel (x, y) of plane `i` starts in [`Self::data`]
    /// (its block's values follow to the block's end); `None` where the block is not stored.
    #[inline(always)]
    pub fn offset(&self, i: usize, x: usize, y: usize) -> Option<usize> {
        let (bx, by) = (x / Self::SIZE, y / Self::SIZE);
        let b = self.table[(i * self.bh + by) * self.bw + bx];
        if b == EMPTY {
            return None;
        }
        let (u, v) = (x % Self::SIZE, y % Self::SIZE);
        Some(b as usize * self.block_len + (v * self.side + u) * self.stride)
    }

    /// Where block (bx, by) of plane `i` starts in [`Self::data`] (its [`Self::side`] rows of
    /// [`Self::row_len`] values follow, the apron included); `None` where it is not stored.
    #[inline(always)]
    pub fn block_start(&self, i: usize, bx: usize, by: usize) -> Option<usize> {
        let b = self.table[(i * self.bh + by) * self.bw + bx];
        (b != EMPTY).then(|| b as usize * self.block_len)
    }

    /// Side of a stored block in pixels (its apron included).
    #[inline(always)]
    pub fn side(&self) -> usize {
        self.side
    }

    /// The apron before a block (columns and rows).
    #[inline(always)]
    pub fn lo(&self) -> usize {
        self.lo
    }

    /// All stored values, block after block ([`Self::offset`]).
    #[inline(always)]
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// The value the store holds for channel `k` at pixel (x, y) of plane `i` read through the
    /// block of anchor pixel (ax, ay) (x - ax and y - ay in -lo..=hi); `None` where that block is
    /// not stored.
    pub fn get(&self, i: usize, ax: usize, ay: usize, x: isize, y: isize, k: usize) -> Option<f32> {
        let (data, start) = self.neighbourhood(i, ax, ay)?;
        let du = (x - ax as isize + self.lo as isize) as usize;
        let dv = (y - ay as isize + self.lo as isize) as usize;
        Some(data[start + dv * self.row_len() + du * self.stride + k])
    }

    /// Blocks stored, of all the planes' blocks.
    pub fn stored(&self) -> (usize, usize) {
        (self.table.iter().filter(|&&b| b != EMPTY).count(), self.table.len())
    }

    /// Bytes held (values and the block table).
    pub fn byte_size(&self) -> usize {
        self.data.len() * 4 + self.table.len() * 4
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn clamp(c: isize, n: usize) -> usize {
        c.clamp(0, n as isize - 1) as usize
    }

    fn dense(w: usize, h: usize, s: usize, i: usize) -> Vec<f32> {
        (0..w * h * s).map(|k| (k * 7 + i * 1000) as f32).collect()
    }

    /// Every value of every stored neighbourhood is the dense plane's value at the boundary
    /// rule's index; dropped blocks read `None`; sizes add up.
    #[test]
    fn neighbourhoods_read_the_dense_values() {
        let (w, h, s, n) = (37, 21, 3, 2);
        let keep = |i: usize| (i == 1).then(|| (0..3 * 2).map(|b| b % 2 == 0).collect::<Vec<_>>());
        let b = Bricks::build(
            BlockGrid { width: w, height: h, stride: s, lo: 1, hi: 2 },
            n,
            |i| dense(w, h, s, i),
            keep,
            clamp,
        );
        assert_eq!(b.stored(), (6 + 3, 12));
        assert_eq!(b.byte_size(), (9 * 19 * 19 * 3 + Bricks::TAIL) * 4 + 12 * 4);
        for i in 0..n {
            let d = dense(w, h, s, i);
            for ay in 0..h {
                for ax in 0..w {
                    let block = (ay / 16) * 3 + ax / 16;
                    let present = i == 0 || block % 2 == 0;
                    assert_eq!(b.neighbourhood(i, ax, ay).is_some(), present, "plane {i} ({ax}, {ay})");
                    if !present {
                        continue;
                    }
                    for y in ay as isize - 1..=ay as isize + 2 {
                        for x in ax as isize - 1..=ax as isize + 2 {
                            for k in 0..s {
                                let want = d[(clamp(y, h) * w + clamp(x, w)) * s + k];
                                assert_eq!(b.get(i, ax, ay, x, y, k), Some(want), "({x}, {y}) from ({ax}, {ay})");
                            }
                        }
                    }
                }
            }
        }
    }

    /// Spread out again, a store gives every pixel a kept block holds (its own area or its
    /// apron) and 0 elsewhere; with every block kept, the dense plane.
    #[test]
    fn plane_dense_gives_back_what_the_blocks_hold() {
        let (w, h, s) = (37, 21, 4);
        let all = Bricks::build(
            BlockGrid { width: w, height: h, stride: s, lo: 0, hi: 1 },
            1,
            |i| dense(w, h, s, i),
            |_| None,
            clamp,
        );
        assert_eq!(all.plane_dense(0), dense(w, h, s, 0));
        // only block (1, 0): pixels 16..=32 x 0..=16 (its area and its apron's column and row)
        let keep = |_| Some(vec![false, true, false, false, false, false]);
        let one = Bricks::build(
            BlockGrid { width: w, height: h, stride: s, lo: 0, hi: 1 },
            1,
            |i| dense(w, h, s, i),
            keep,
            clamp,
        );
        let (d, got) = (dense(w, h, s, 0), one.plane_dense(0));
        for y in 0..h {
            for x in 0..w {
                let held = (16..=32).contains(&x) && y <= 16;
                for k in 0..s {
                    let want = if held { d[(y * w + x) * s + k] } else { 0.0 };
                    assert_eq!(got[(y * w + x) * s + k], want, "({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn a_plane_smaller_than_a_block_is_one_block() {
        let b = Bricks::build(
            BlockGrid { width: 1, height: 1, stride: 3, lo: 2, hi: 3 },
            1,
            |_| vec![0.25, 0.5, 0.75],
            |_| None,
            clamp,
        );
        assert_eq!(b.stored(), (1, 1));
        assert_eq!(b.get(0, 0, 0, -2, 3, 1), Some(0.5));
    }
}
