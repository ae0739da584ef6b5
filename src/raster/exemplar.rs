//! Exemplar synthesis: the one patch-copying completion both the scene's completed background
//! (`mpi::backdrop`, once per scene) and the texture fill of image2's holes (`sample::holes`,
//! per sample) use, with its onion-peel order.
//!
//! # The method
//!
//! Target pixels are completed one by one in a given order (onion peel: [`peel_order`]), each
//! taking the colour of one **source** pixel of a source image (the same image or another one):
//! the best of a fixed candidate list by the mean squared colour difference over the
//! `(2 half + 1)^2` neighbourhood (the target's known or already completed pixels against the
//! source's colours, source pixels in `masked` left out). The candidates, in order:
//! 1. **coherence**: the sources of the target's eight neighbours shifted by the step to the
//!    target, so whole patches of texture are copied (Ashikhmin 2001; PatchMatch's propagation,
//!    Barnes et al. 2009);
//! 2. the caller's **seeds** (random sources from an eligible set, or the target's own place);
//! 3. a **random search** around the best so far (or the target's place) at halving radii from
//!    `search_radius` down to 1.
//!
//! Only sources the caller's `eligible(target, source)` accepts are compared; a candidate seen
//! before for the same target is not compared again (its cost cannot beat the best twice). Random
//! numbers come from a counter-based hash of the target's index in the source frame and a salt
//! (no shared state), so the result is the same on every run, thread count and machine; and a
//! target that no candidate could be compared for takes the caller's `fallback`, or keeps its
//! value (counted as completed for the pixels after it, or not: `keep_unmatched`).

use super::grid::Grid;
use crate::rng::mix64;

/// Where the target grid lies in the source frame, and the synthesis' parameters.
#[derive(Clone, Copy, Debug)]
pub struct Layout {
    /// The source frame (the image copied from).
    pub source: Grid,
    /// The target grid (the image completed).
    pub target: Grid,
    /// Where the target grid's top-left pixel lies in the source frame (column, row).
    pub target_left: usize,
    pub target_top: usize,
    /// Half the side of the matching window.
    pub half: usize,
    /// Largest radius of the random search.
    pub search_radius: usize,
    /// Salt of the random draws.
    pub salt: u64,
    /// Weight of a target pixel known on entry in the patch distance (a completed one weighs 1):
    /// above 1, what the photo shows outweighs what the synthesis guessed.
    pub known_weight: u32,
    /// Whether a target no source was found for keeps its value as completed (it then takes part
    /// in the patch distance of the pixels after it) or stays unknown.
    pub keep_unmatched: bool,
}

impl Layout {
    /// The source-frame index of target pixel `t`.
    pub fn place(&self, t: usize) -> usize {
        let (x, y) = self.target.xy(t);
        self.source.index(self.target_left + x, self.target_top + y)
    }
}

/// A colour value the synthesis copies and compares: the squared differences of a pixel's three
/// channels are added to an accumulator in channel order (f32 in f64, exactly as written; u8 in
/// integers, exact).
pub trait Texel: Copy {
    type Acc: Copy + Default;
    /// Adds `weight` times the squared differences of the three channels of `a` and `b`.
    fn add_sq3(acc: &mut Self::Acc, a: &[Self], b: &[Self], weight: u32);
    fn total(acc: Self::Acc) -> f64;
}

impl Texel for f32 {
    type Acc = f64;
    #[inline]
    fn add_sq3(acc: &mut f64, a: &[f32], b: &[f32], weight: u32) {
        for c in 0..3 {
            let d = f64::from(a[c] - b[c]);
            // times 1.0 is exact: weight 1 is the plain sum
            *acc += d * d * f64::from(weight);
        }
    }
    fn total(acc: f64) -> f64 {
        acc
    }
}

impl Texel for u8 {
    type Acc = u32;
    #[inline]
    fn add_sq3(acc: &mut u32, a: &[u8], b: &[u8], weight: u32) {
        for c in 0..3 {
            let d = u32::from(a[c].abs_diff(b[c]));
            *acc += d * d * weight;
        }
    }
    fn total(acc: u32) -> f64 {
        f64::from(acc)
    }
}

/// The random draws of one target pixel.
pub struct Draw(u64);

impl Draw {
    /// A uniform integer in `0..n` (`n > 0`).
    pub fn below(&mut self, n: usize) -> usize {
        self.0 = mix64(self.0);
        ((u128::from(self.0) * n as u128) >> 64) as usize
    }
}

/// The source image and the rules of one synthesis.
pub struct Sources<'a, T, E, S, F> {
    /// Source colours, `source.w x source.h x 3`.
    pub rgb: &'a [T],
    /// Source pixels left out of the patch distance (`source.w x source.h`).
    pub masked: &'a [bool],
    /// Whether source pixel `s` may be copied into target pixel `t` (target-grid index).
    pub eligible: E,
    /// Pushes the seed candidates of target `t` (source-frame indices).
    pub seeds: S,
    /// The source of a target no candidate could be compared for.
    pub fallback: F,
}

/// What the patch distance reads: the source's colours and masked pixels, and the weights of the
/// target's pixels.
struct Patch<'a, T> {
    lay: &'a Layout,
    rgb: &'a [T],
    masked: &'a [bool],
    /// The target pixels known on entry (empty when they weigh as much as completed ones).
    known: Vec<bool>,
}

impl<T: Texel> Patch<'_, T> {
    /// The mean squared colour difference between the window around target pixel `t` (its known
    /// or completed pixels) and the window around source pixel `s` (its pixels not masked), over
    /// the offsets inside both frames in row-major order; infinite where no pixel pairs up.
    fn cost(&self, t: usize, s: usize, target: &[T], filled: &[bool]) -> f64 {
        let (tg, sg) = (self.lay.target, self.lay.source);
        let half = self.lay.half;
        let ((tx, ty), (sx, sy)) = (tg.xy(t), sg.xy(s));
        // the window's reach left, right, up and down that stays inside both frames
        let (left, right) = (half.min(tx).min(sx), half.min(tg.w - 1 - tx).min(sg.w - 1 - sx));
        let (up, down) = (half.min(ty).min(sy), half.min(tg.h - 1 - ty).min(sg.h - 1 - sy));
        let (mut sum, mut m) = (T::Acc::default(), 0u32);
        for r in 0..=up + down {
            let a0 = tg.index(tx - left, ty - up + r);
            let b0 = sg.index(sx - left, sy - up + r);
            for k in 0..=left + right {
                let (a, b) = (a0 + k, b0 + k);
                if filled[a] && !self.masked[b] {
                    let weight = if !self.known.is_empty() && self.known[a] { self.lay.known_weight } else { 1 };
                    T::add_sq3(&mut sum, &target[3 * a..3 * a + 3], &self.rgb[3 * b..3 * b + 3], weight);
                    m += weight;
                }
            }
        }
        if m == 0 {
            f64::INFINITY
        } else {
            T::total(sum) / f64::from(m)
        }
    }
}

/// The candidates compared for one target and the best of them so far (lowest cost, the first
/// of equal ones).
#[derive(Default)]
struct Choice {
    seen: Vec<usize>,
    best: Option<(f64, usize)>,
}

impl Choice {
    fn reset(&mut self) {
        self.seen.clear();
        self.best = None;
    }

    /// Compares source `s` at `cost(s)`, unless it was compared before or is not `eligible(s)`.
    fn consider(&mut self, s: usize, eligible: impl FnOnce(usize) -> bool, cost: impl FnOnce(usize) -> f64) {
        if self.seen.contains(&s) || !eligible(s) {
            return;
        }
        self.seen.push(s);
        let c = cost(s);
        if self.best.is_none_or(|b| c < b.0) {
            self.best = Some((c, s));
        }
    }
}

/// Candidates 1 (coherence): the sources of target `t`'s eight neighbours shifted by the step to
/// `t`, where inside the source frame, into `out`.
fn coherent_candidates(lay: &Layout, src_of: &[u32], t: usize, out: &mut Vec<usize>) {
    let (tg, sg) = (lay.target, lay.source);
    let (tx, ty) = tg.xy(t);
    for (nx, ny) in tg.neighbours8(tx, ty) {
        let s = src_of[tg.index(nx, ny)];
        if s == u32::MAX {
            continue;
        }
        // the neighbour's source moved by the step from the neighbour to `t`
        let (sx, sy) = sg.xy(s as usize);
        let (x, y) = (sx as isize + tx as isize - nx as isize, sy as isize + ty as isize - ny as isize);
        out.extend(sg.at(x, y));
    }
}

/// Completes the target pixels of `order` (target-grid indices) in `target` (`lay.target` x 3,
/// known pixels where `filled`), see the module documentation. Returns, per target pixel, the
/// source it copied (`u32::MAX` where none).
pub fn synthesise<T, E, S, F>(
    lay: &Layout,
    src: &mut Sources<'_, T, E, S, F>,
    target: &mut [T],
    filled: &mut [bool],
    order: &[usize],
) -> Vec<u32>
where
    T: Texel,
    E: Fn(usize, usize) -> bool,
    S: FnMut(usize, &mut Draw, &mut Vec<usize>),
    F: Fn(usize) -> Option<usize>,
{
    let sg = lay.source;
    let known = if lay.known_weight == 1 { Vec::new() } else { filled.to_vec() };
    let patch = Patch { lay, rgb: src.rgb, masked: src.masked, known };
    let mut src_of: Vec<u32> = vec![u32::MAX; lay.target.len()];
    let mut choice = Choice::default();
    let mut candidates: Vec<usize> = Vec::new();
    for &t in order {
        let place = lay.place(t);
        let mut draw = Draw(mix64(place as u64 ^ lay.salt));
        // 1. coherence, 2. the caller's seeds
        candidates.clear();
        coherent_candidates(lay, &src_of, t, &mut candidates);
        (src.seeds)(t, &mut draw, &mut candidates);
        choice.reset();
        let (target_now, filled_now): (&[T], &[bool]) = (target, filled);
        let cost = |s: usize| patch.cost(t, s, target_now, filled_now);
        let eligible = |s: usize| (src.eligible)(t, s);
        for &s in &candidates {
            choice.consider(s, eligible, cost);
        }
        // 3. the random search around the best so far (or the target's place), halving radii
        let mut r = lay.search_radius;
        while r >= 1 {
            let (cx, cy) = sg.xy(choice.best.map_or(place, |b| b.1));
            let x = cx as isize + draw.below(2 * r + 1) as isize - r as isize;
            let y = cy as isize + draw.below(2 * r + 1) as isize - r as isize;
            if let Some(s) = sg.at(x, y) {
                choice.consider(s, eligible, cost);
            }
            r /= 2;
        }
        let chosen = choice.best.map(|b| b.1).or_else(|| (src.fallback)(t));
        if let Some(s) = chosen {
            target[3 * t..3 * t + 3].copy_from_slice(&src.rgb[3 * s..3 * s + 3]);
            src_of[t] = s as u32;
            filled[t] = true;
        } else if lay.keep_unmatched {
            filled[t] = true;
        }
    }
    src_of
}

/// The pixels of `todo` by chessboard distance from the pixels not in it (breadth-first, ties in
/// row-major order of discovery).
pub fn peel_order(todo: &[bool], w: usize, h: usize) -> Vec<usize> {
    let g = Grid::new(w, h);
    let n = g.len();
    let mut seen: Vec<bool> = todo.iter().map(|&t| !t).collect();
    let mut frontier: Vec<usize> = (0..n)
        .filter(|&p| {
            todo[p] && {
                let (x, y) = g.xy(p);
                g.window(x, y, 1).pixels().any(|(xx, yy)| !todo[g.index(xx, yy)])
            }
        })
        .collect();
    let mut order = Vec::with_capacity(todo.iter().filter(|&&t| t).count());
    frontier.iter().for_each(|&p| seen[p] = true);
    if frontier.is_empty() {
        // everything is to do: start at the first pixel
        if let Some(p) = (0..n).find(|&p| todo[p]) {
            seen[p] = true;
            frontier.push(p);
        }
    }
    while !frontier.is_empty() {
        order.extend_from_slice(&frontier);
        let mut next = Vec::new();
        for &p in &frontier {
            let (x, y) = g.xy(p);
            for (xx, yy) in g.window(x, y, 1).pixels() {
                let q = g.index(xx, yy);
                if !seen[q] {
                    seen[q] = true;
                    next.push(q);
                }
            }
        }
        next.sort_unstable();
        frontier = next;
    }
    order
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn peel_order_visits_every_todo_pixel_once_by_distance() {
        let (w, h) = (9, 7);
        let todo: Vec<bool> = (0..w * h).map(|p| (2..7).contains(&(p % w)) && (1..6).contains(&(p / w))).collect();
        let order = peel_order(&todo, w, h);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        let want: Vec<usize> = (0..w * h).filter(|&p| todo[p]).collect();
        assert_eq!(sorted, want);
        // the centre of the 5 x 5 block comes last (distance 3 from the outside)
        assert_eq!(*order.last().unwrap(), 3 * w + 4);
    }

    #[test]
    fn a_periodic_texture_is_continued_exactly() {
        // a 6-periodic texture with a hole in the middle: coherent copies continue it
        let (w, h) = (40, 30);
        let value = |x: usize, y: usize| ((x % 6) * 40 + (y % 6) * 7) as u8;
        let full: Vec<u8> = (0..w * h).flat_map(|p| [value(p % w, p / w); 3]).collect();
        let todo: Vec<bool> = (0..w * h).map(|p| (15..25).contains(&(p % w)) && (10..20).contains(&(p / w))).collect();
        let mut target = full.clone();
        for p in 0..w * h {
            if todo[p] {
                target[3 * p..3 * p + 3].copy_from_slice(&[0, 0, 0]);
            }
        }
        let mut filled: Vec<bool> = todo.iter().map(|&t| !t).collect();
        let masked = todo.clone();
        let order = peel_order(&todo, w, h);
        let lay = Layout {
            source: Grid::new(w, h),
            target: Grid::new(w, h),
            target_left: 0,
            target_top: 0,
            half: 2,
            search_radius: 16,
            salt: 7,
            known_weight: 1,
            keep_unmatched: false,
        };
        let mut src = Sources {
            rgb: &full,
            masked: &masked,
            eligible: |_t: usize, s: usize| !todo[s],
            // the target's place two periods to the left
            seeds: |t: usize, _d: &mut Draw, out: &mut Vec<usize>| out.push(t - 12),
            fallback: |_t: usize| None,
        };
        synthesise(&lay, &mut src, &mut target, &mut filled, &order);
        assert!(filled.iter().all(|&f| f));
        assert_eq!(target, full);
    }
}
