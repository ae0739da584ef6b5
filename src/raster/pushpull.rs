//! The push-pull pyramid: values known at some pixels of a row-major `H x W` grid pulled into the
//! others, smoothly and from the known pixels only. One pyramid for every value it fills: the
//! disparity behind the objects (`mpi::backdrop`, `scene::matte`, f64) and the colour behind a
//! layer (`mpi::layering`, three f32 channels).
//!
//! # Method
//!
//! **Pull**: each level halves the one below (sizes rounded up), each cell the mean of its known
//! 2 x 2 children, known when any child is; down to 1 x 1. **Push**: from the coarsest level up,
//! each unknown cell of a level takes the bilinear sample of the (by then fully known) level
//! above at `((x - 0.5) / 2, (y - 0.5) / 2)`, clamped to that level's grid; at the full grid the
//! known pixels keep their value. The arithmetic is the value type's own ([`Cell`]), in the
//! order written there, so each caller's bytes are a function of its inputs only.

use super::grid::Grid;

/// A value the pyramid averages and interpolates.
pub trait Cell: Copy + Default {
    /// `self + v`, channel by channel.
    fn add(self, v: Self) -> Self;
    /// The mean of `m > 0` values whose sum is `sum`.
    fn mean(sum: Self, m: u32) -> Self;
    /// `a + w (b - a)`, channel by channel; `w` is 0, 1/4 or 3/4 (exact in any float type).
    fn lerp(a: Self, b: Self, w: f64) -> Self;
}

/// One disparity: sums and interpolation in f64, the mean a division.
impl Cell for f64 {
    #[inline(always)]
    fn add(self, v: f64) -> f64 {
        self + v
    }
    #[inline(always)]
    fn mean(sum: f64, m: u32) -> f64 {
        sum / f64::from(m)
    }
    #[inline(always)]
    fn lerp(a: f64, b: f64, w: f64) -> f64 {
        a + w * (b - a)
    }
}

/// An RGB colour: sums and interpolation in f32, the mean a product with `1 / m`.
impl Cell for [f32; 3] {
    #[inline(always)]
    fn add(self, v: [f32; 3]) -> [f32; 3] {
        [self[0] + v[0], self[1] + v[1], self[2] + v[2]]
    }
    #[inline(always)]
    fn mean(sum: [f32; 3], m: u32) -> [f32; 3] {
        let inv = 1.0 / m as f32;
        sum.map(|v| v * inv)
    }
    #[inline(always)]
    fn lerp(a: [f32; 3], b: [f32; 3], w: f64) -> [f32; 3] {
        let w = w as f32;
        [a[0] + w * (b[0] - a[0]), a[1] + w * (b[1] - a[1]), a[2] + w * (b[2] - a[2])]
    }
}

/// What a fill reads: pixel `p`'s value where it is known, `None` elsewhere. A type of its own
/// rather than a closure so that its one method is inlined into the pyramid's loops
/// (`#[inline(always)]` on the implementation): a closure called from two loops is not, and then
/// returns its value through memory for every pixel.
pub trait Known<T> {
    fn at(&self, p: usize) -> Option<T>;
}

/// Values known where a flag says so.
struct Flagged<'a, T> {
    v: &'a [T],
    known: &'a [bool],
}

impl<T: Copy> Known<T> for Flagged<'_, T> {
    #[inline(always)]
    fn at(&self, p: usize) -> Option<T> {
        self.known[p].then_some(self.v[p])
    }
}

/// One level of the pyramid: values and which of them are known.
#[derive(Default)]
struct Level<T> {
    grid: Grid,
    v: Vec<T>,
    known: Vec<bool>,
}

impl<T: Cell> Level<T> {
    fn reset(&mut self, grid: Grid) {
        self.grid = grid;
        self.v.clear();
        self.v.resize(grid.len(), T::default());
        self.known.clear();
        self.known.resize(grid.len(), false);
    }
}

/// Halves a level of `grid` into `out`: each cell the mean of its known children (known if any is).
fn pull<T: Cell>(grid: Grid, src: &impl Known<T>, out: &mut Level<T>) {
    let coarse = Grid::new(grid.w.div_ceil(2), grid.h.div_ceil(2));
    out.reset(coarse);
    for (cx, cy) in coarse.pixels() {
        let (mut s, mut m) = (T::default(), 0u32);
        for y in 2 * cy..(2 * cy + 2).min(grid.h) {
            for x in 2 * cx..(2 * cx + 2).min(grid.w) {
                if let Some(v) = src.at(grid.index(x, y)) {
                    s = s.add(v);
                    m += 1;
                }
            }
        }
        if m > 0 {
            let c = coarse.index(cx, cy);
            out.v[c] = T::mean(s, m);
            out.known[c] = true;
        }
    }
}

/// Bilinear taps of a coarse level for each fine column or row (fine pixel x lies at coarse
/// coordinate (x - 0.5) / 2): the two coarse cells and the weight of the second.
fn taps(n: usize, cn: usize) -> Vec<(usize, usize, f64)> {
    (0..n)
        .map(|x| {
            let f = ((x as f64 - 0.5) * 0.5).clamp(0.0, (cn - 1) as f64);
            let x0 = f.floor() as usize;
            (x0, (x0 + 1).min(cn - 1), f - f.floor())
        })
        .collect()
}

#[inline(always)]
fn bilinear<T: Cell>(c: &Level<T>, (x0, x1, wx): (usize, usize, f64), (y0, y1, wy): (usize, usize, f64)) -> T {
    let at = |x: usize, y: usize| c.v[c.grid.index(x, y)];
    let top = T::lerp(at(x0, y0), at(x1, y0), wx);
    let bot = T::lerp(at(x0, y1), at(x1, y1), wx);
    T::lerp(top, bot, wy)
}

/// Fills the unknown cells of `fine` by bilinear up-sampling of the (fully known) `coarse`.
fn push<T: Cell>(fine: &mut Level<T>, coarse: &Level<T>) {
    let (xs, ys) = (taps(fine.grid.w, coarse.grid.w), taps(fine.grid.h, coarse.grid.h));
    for (y, &ty) in ys.iter().enumerate() {
        for (x, &tx) in xs.iter().enumerate() {
            let p = fine.grid.index(x, y);
            if !fine.known[p] {
                fine.v[p] = bilinear(coarse, tx, ty);
            }
        }
    }
}

/// The levels of one push-pull, kept between fills of the same size so that a caller filling
/// many grids (one per plane) allocates them once.
#[derive(Default)]
pub struct Pyramid<T> {
    levels: Vec<Level<T>>,
}

impl<T: Cell> Pyramid<T> {
    /// Fills a `w x h` grid whose pixel `p` is known as `src.at(p)` (`None`: unknown): calls
    /// `write(p, value)` for every pixel in row-major order, `src.at(p)` where known, else the fill.
    /// Where no pixel is known there is nothing to fill from: returns false without a call.
    pub fn fill(&mut self, w: usize, h: usize, src: &impl Known<T>, mut write: impl FnMut(usize, T)) -> bool {
        if w * h == 0 {
            return false;
        }
        // pull: means of known pixels, down to 1x1 (level 0 is the first halving)
        let levels = &mut self.levels;
        let mut depth = 0;
        let (mut lw, mut lh) = (w, h);
        while lw > 1 || lh > 1 {
            if levels.len() <= depth {
                levels.push(Level::default());
            }
            if depth == 0 {
                pull(Grid::new(w, h), src, &mut levels[0]);
            } else {
                let (prev, next) = levels.split_at_mut(depth);
                let l = &prev[depth - 1];
                pull(l.grid, &Flagged { v: &l.v, known: &l.known }, &mut next[0]);
            }
            (lw, lh) = (levels[depth].grid.w, levels[depth].grid.h);
            depth += 1;
        }
        if depth == 0 {
            // a 1 x 1 grid: known or nothing to fill from
            let own = src.at(0);
            if let Some(v) = own {
                write(0, v);
            }
            return own.is_some();
        }
        if !levels[depth - 1].known[0] {
            return false;
        }
        // push: fill each level's unknown cells from the level above
        for li in (0..depth - 1).rev() {
            let (fine, coarse) = levels.split_at_mut(li + 1);
            push(&mut fine[li], &coarse[0]);
        }
        let top = &levels[0];
        let grid = Grid::new(w, h);
        let (xs, ys) = (taps(w, top.grid.w), taps(h, top.grid.h));
        for (y, &ty) in ys.iter().enumerate() {
            for (x, &tx) in xs.iter().enumerate() {
                let p = grid.index(x, y);
                write(p, src.at(p).unwrap_or_else(|| bilinear(top, tx, ty)));
            }
        }
        true
    }
}

/// Push-pull of `v` (`w x h`) from the pixels where `known` into the others: a new grid with the
/// known values unchanged and the others filled ([`Pyramid::fill`]); `v` itself where nothing is
/// known.
pub fn push_pull<T: Cell>(v: &[T], known: &[bool], w: usize, h: usize) -> Vec<T> {
    let mut out = v.to_vec();
    Pyramid::default().fill(w, h, &Flagged { v, known }, |p, c| out[p] = c);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Known pixels come back unchanged, the fill is finite and lies within the known values'
        /// range (means and convex blends of them), and a constant field stays constant.
        #[test]
        fn known_pixels_stay_and_the_fill_is_a_blend_of_them(
            w in 1usize..24,
            h in 1usize..24,
            values in proptest::collection::vec(-1e3f64..1e3, 24 * 24),
            known_bits in proptest::collection::vec(any::<bool>(), 24 * 24),
            constant in -1e3f64..1e3,
        ) {
            let n = w * h;
            let (v, known) = (&values[..n], &known_bits[..n]);
            let out = push_pull(v, known, w, h);
            prop_assert_eq!(out.len(), n);
            let kv: Vec<f64> = (0..n).filter(|&p| known[p]).map(|p| v[p]).collect();
            if kv.is_empty() {
                prop_assert_eq!(&out[..], v);
            } else {
                let (lo, hi) = kv.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(x), b.max(x)));
                for p in 0..n {
                    prop_assert!(out[p].is_finite());
                    if known[p] {
                        prop_assert_eq!(out[p].to_bits(), v[p].to_bits());
                    } else {
                        prop_assert!(out[p] >= lo - 1e-9 && out[p] <= hi + 1e-9, "{} outside [{lo}, {hi}]", out[p]);
                    }
                }
                let flat = push_pull(&vec![constant; n], known, w, h);
                prop_assert!(flat.iter().all(|&x| (x - constant).abs() <= 1e-12 * constant.abs().max(1.0)));
                // the colour pyramid: the same laws channel by channel
                let rgb: Vec<[f32; 3]> = v.iter().map(|&x| [x as f32, -x as f32, 0.5]).collect();
                let c = push_pull(&rgb, known, w, h);
                for p in 0..n {
                    prop_assert!(c[p].iter().all(|x| x.is_finite()));
                    prop_assert_eq!(c[p][2], 0.5);
                    if known[p] {
                        prop_assert_eq!(c[p], rgb[p]);
                    }
                }
            }
        }
    }

    #[test]
    fn a_reused_pyramid_gives_the_same_fill() {
        let (w, h) = (13, 9);
        let v: Vec<f64> = (0..w * h).map(|p| (p * 7 % 11) as f64).collect();
        let known: Vec<bool> = (0..w * h).map(|p| p % 5 == 0).collect();
        let once = push_pull(&v, &known, w, h);
        let mut pyramid = Pyramid::default();
        let mut big = vec![0.0; 64 * 64];
        let (ones, thirds): (Vec<f64>, Vec<bool>) = (0..64 * 64).map(|p| (1.0, p % 3 == 0)).unzip();
        pyramid.fill(64, 64, &Flagged { v: &ones, known: &thirds }, |p, c| big[p] = c);
        let mut again = vec![f64::NAN; w * h];
        assert!(pyramid.fill(w, h, &Flagged { v: &v, known: &known }, |p, c| again[p] = c));
        assert_eq!(once, again);
        // one known pixel fills the whole grid with its value
        let v: Vec<f64> = (0..35).map(|p| if p == 17 { 3.0 } else { 0.0 }).collect();
        let one = push_pull(&v, &(0..35).map(|p| p == 17).collect::<Vec<_>>(), 7, 5);
        assert!(one.iter().all(|&x| x == 3.0), "{one:?}");
        assert!(push_pull(&[1.0; 0], &[], 0, 4).is_empty());
    }
}
