//! The OpenCV variant (`modules/photo/src/inpaint.cpp`): the padded grid, the insertion-ordered
//! queue, the arrival times outside and inside, and each hole pixel's value with OpenCV's
//! weights and gradient correction.

use super::front::{band, key};
use crate::raster::morph::dilate;
use crate::raster::Grid;
use std::cmp::Reverse;
use std::collections::BinaryHeap;

const KNOWN: u8 = 0;
const BAND: u8 = 1;
const INSIDE: u8 = 2;
const CHANGE: u8 = 3;

/// Pixel storage of the OpenCV variant: how a computed value is written back.
pub(super) trait Sample: Copy {
    fn get(self) -> f32;
    fn put(v: f32) -> Self;
}

impl Sample for u8 {
    #[inline]
    fn get(self) -> f32 {
        f32::from(self)
    }
    /// OpenCV's `round_cast<uchar>`: `saturate_cast<uchar>(v + 0.5)`, i.e. round half to even
    /// of `v + 0.5`, clamped; NaN gives 0.
    #[inline]
    fn put(v: f32) -> u8 {
        (f64::from(v) + 0.5).round_ties_even().clamp(0.0, 255.0) as u8
    }
}

impl Sample for f32 {
    #[inline]
    fn get(self) -> f32 {
        self
    }
    #[inline]
    fn put(v: f32) -> f32 {
        v
    }
}

/// OpenCV's `FastMarching_solve` on the padded grid.
#[inline]
fn cv_solve(e1: usize, e2: usize, f: &[u8], t: &[f32]) -> f32 {
    let a11 = f64::from(t[e1]);
    let a22 = f64::from(t[e2]);
    let m12 = a11.min(a22);
    let sol = match (f[e1] != INSIDE, f[e2] != INSIDE) {
        (true, true) => {
            if (a11 - a22).abs() >= 1.0 {
                1.0 + m12
            } else {
                (a11 + a22 + (2.0 - (a11 - a22) * (a11 - a22)).sqrt()) * 0.5
            }
        }
        (true, false) => 1.0 + a11,
        (false, true) => 1.0 + a22,
        (false, false) => 1.0 + m12,
    };
    sol as f32
}

#[inline]
fn cv_min4(e: usize, ew: usize, f: &[u8], t: &[f32]) -> f32 {
    let (up, down, left, right) = (e - ew, e + ew, e - 1, e + 1);
    let a = cv_solve(up, left, f, t).min(cv_solve(down, left, f, t));
    let b = cv_solve(up, right, f, t).min(cv_solve(down, right, f, t));
    a.min(b)
}

/// A priority queue ordered by T, ties by insertion order (OpenCV's `CvPriorityQueueFloat`).
struct CvQueue {
    heap: BinaryHeap<Reverse<u64>>,
    next: u32,
    pos: Vec<u32>,
}

impl CvQueue {
    fn new() -> Self {
        CvQueue { heap: BinaryHeap::new(), next: 0, pos: Vec::new() }
    }
    fn push(&mut self, e: usize, t: f32) {
        self.heap.push(Reverse(key(t, self.next)));
        self.pos.push(e as u32);
        self.next += 1;
    }
    fn pop(&mut self) -> Option<usize> {
        self.heap.pop().map(|Reverse(k)| self.pos[(k & 0xffff_ffff) as usize] as usize)
    }
}

/// The padded grid: the image (`c` channels) inside a one-pixel frame, and the
/// neighbourhood's radius `r`. Padded row `i`, column `j` is the image's pixel
/// `(j - 1, i - 1)`.
#[derive(Clone, Copy)]
struct Padded {
    image: Grid,
    padded: Grid,
    c: usize,
    r: isize,
}

impl Padded {
    fn new(image: Grid, c: usize, r: isize) -> Self {
        Self { image, padded: Grid::new(image.w + 2, image.h + 2), c, r }
    }

    /// The padded index of the image's pixel `i`.
    fn ext(self, i: usize) -> usize {
        let (x, y) = self.image.xy(i);
        self.padded.index(x + 1, y + 1)
    }

    /// The padded index of row `i`, column `j`.
    fn at(self, i: isize, j: isize) -> usize {
        self.padded.index(j as usize, i as usize)
    }

    /// The padded row and column of padded index `e`.
    fn row_col(self, e: usize) -> (usize, usize) {
        let (j, i) = self.padded.xy(e);
        (i, j)
    }
}

/// OpenCV's Telea inpainting on an image with at least one known and one hole pixel; returns
/// the largest arrival time.
pub(super) fn opencv<S: Sample>(img: &mut [S], w: usize, h: usize, c: usize, is_hole: &[bool], range: usize) -> f32 {
    let g = Padded::new(Grid::new(w, h), c, range as isize);
    let en = g.padded.len();
    // the hole (INSIDE) on the padded grid; the padding is KNOWN with T = 1e6
    let mut f = vec![KNOWN; en];
    for (i, _) in is_hole.iter().enumerate().filter(|(_, &v)| v) {
        f[g.ext(i)] = INSIDE;
    }
    let band_px = band(w, h, is_hole);
    let mut t = vec![1.0e6f32; en];
    let mut heap = CvQueue::new();
    for &b in &band_px {
        let e = g.ext(b as usize);
        t[e] = 0.0;
        heap.push(e, 0.0);
    }
    outside_times(g, is_hole, range, &band_px, &mut t);
    fill_inside(img, g, &mut f, &mut t, heap)
}

/// T outside: the known pixels within Chebyshev distance `range` of the hole, band excluded,
/// marched from the band and negated.
fn outside_times(g: Padded, is_hole: &[bool], range: usize, band_px: &[u32], t: &mut [f32]) {
    let ew = g.padded.w;
    let en = g.padded.len();
    let ring = dilate(g.image.w, g.image.h, is_hole, range);
    let mut fo = vec![KNOWN; en];
    for (i, _) in ring.iter().enumerate().filter(|(i, &r)| r && !is_hole[*i]) {
        fo[g.ext(i)] = INSIDE;
    }
    let mut out_q = CvQueue::new();
    for &b in band_px {
        let e = g.ext(b as usize);
        fo[e] = KNOWN;
        out_q.push(e, 0.0);
    }
    while let Some(e) = out_q.pop() {
        fo[e] = CHANGE;
        for nb in [e - ew, e - 1, e + ew, e + 1] {
            let (i, j) = g.row_col(nb);
            if i == 0 || j == 0 || fo[nb] != INSIDE {
                continue;
            }
            let dist = cv_min4(nb, ew, &fo, t);
            t[nb] = dist;
            fo[nb] = BAND;
            out_q.push(nb, dist);
        }
    }
    for (ti, _) in t.iter_mut().zip(&fo).filter(|(_, &s)| s == CHANGE) {
        *ti = -*ti;
    }
}

/// The weighted sums of one hole pixel, per channel: the values, the gradient's two terms, the
/// weights.
struct Sums {
    ia: Vec<f32>,
    jx: Vec<f32>,
    jy: Vec<f32>,
    s: Vec<f32>,
}

/// Inside: the front marches from the band into the hole; each pixel it reaches gets its time
/// and its value. Returns the largest arrival time.
fn fill_inside<S: Sample>(img: &mut [S], g: Padded, f: &mut [u8], t: &mut [f32], mut heap: CvQueue) -> f32 {
    let (c, ew) = (g.c, g.padded.w);
    let (ewi, ehi) = (g.padded.w as isize, g.padded.h as isize);
    let mut sums = Sums { ia: vec![0.0f32; c], jx: vec![0.0f32; c], jy: vec![0.0f32; c], s: vec![0.0f32; c] };
    let mut max_distance = 0.0f32;
    while let Some(e) = heap.pop() {
        f[e] = KNOWN;
        for nb in [e - ew, e - 1, e + ew, e + 1] {
            let (i, j) = g.row_col(nb);
            let (i, j) = (i as isize, j as isize);
            if i <= 0 || j <= 0 || i > ehi - 1 || j > ewi - 1 || f[nb] != INSIDE {
                continue;
            }
            let dist = cv_min4(nb, ew, f, t);
            t[nb] = dist;
            max_distance = max_distance.max(dist);
            fill_pixel(img, g, f, t, (i, j), &mut sums);
            f[nb] = BAND;
            heap.push(nb, dist);
        }
    }
    max_distance
}

/// The value of the hole pixel at padded row `i`, column `j`: the weighted mean of its known
/// neighbours within the radius plus OpenCV's gradient correction.
fn fill_pixel<S: Sample>(img: &mut [S], g: Padded, f: &[u8], t: &[f32], (i, j): (isize, isize), sums: &mut Sums) {
    let Padded { image, c, r, .. } = g;
    let (ewi, ehi) = (g.padded.w as isize, g.padded.h as isize);
    let clamp_row = |v: isize| v.clamp(0, image.h as isize - 1) as usize;
    let clamp_col = |v: isize| v.clamp(0, image.w as isize - 1) as usize;
    let Sums { ia, jx, jy, s } = sums;
    let known = |ii: isize, jj: isize| f[g.at(ii, jj)] != INSIDE;
    let tt = |ii: isize, jj: isize| t[g.at(ii, jj)];
    let gtx = match (known(i, j + 1), known(i, j - 1)) {
        (true, true) => (tt(i, j + 1) - tt(i, j - 1)) * 0.5,
        (true, false) => tt(i, j + 1) - tt(i, j),
        (false, true) => tt(i, j) - tt(i, j - 1),
        (false, false) => 0.0,
    };
    let gty = match (known(i + 1, j), known(i - 1, j)) {
        (true, true) => (tt(i + 1, j) - tt(i - 1, j)) * 0.5,
        (true, false) => tt(i + 1, j) - tt(i, j),
        (false, true) => tt(i, j) - tt(i - 1, j),
        (false, false) => 0.0,
    };
    ia.fill(0.0);
    jx.fill(0.0);
    jy.fill(0.0);
    s.fill(1.0e-20);
    let tij = tt(i, j);
    for k in i - r..=i + r {
        let km = k - 1 + isize::from(k == 1);
        let kp = k - 1 - isize::from(k == ehi - 2);
        for l in j - r..=j + r {
            if !(k > 0 && l > 0 && k < ehi - 1 && l < ewi - 1) {
                continue;
            }
            if !known(k, l) || (l - j) * (l - j) + (k - i) * (k - i) > r * r {
                continue;
            }
            let lm = l - 1 + isize::from(l == 1);
            let lp = l - 1 - isize::from(l == ewi - 2);
            let ry = (i - k) as f32;
            let rx = (j - l) as f32;
            let len2 = f64::from(rx * rx + ry * ry);
            let dst = (1.0 / (len2 * len2.sqrt())) as f32;
            let lev = (1.0 / (1.0 + f64::from((tt(k, l) - tij).abs()))) as f32;
            let mut dir = rx * gtx + ry * gty;
            if dir.abs() <= 0.01 {
                dir = 1.0e-6;
            }
            let wgt = (dst * lev * dir).abs();
            let (kl_r, kl_c) = (known(k, l + 1), known(k, l - 1));
            let (kd, ku) = (known(k + 1, l), known(k - 1, l));
            let px =
                |row: isize, col: isize, ch: usize| img[image.index(clamp_col(col), clamp_row(row)) * c + ch].get();
            for ch in 0..c {
                let gix = match (kl_r, kl_c) {
                    (true, true) => (px(km, lp + 1, ch) - px(km, lm - 1, ch)) * 2.0,
                    (true, false) => px(km, lp + 1, ch) - px(km, lm, ch),
                    (false, true) => px(km, lp, ch) - px(km, lm - 1, ch),
                    (false, false) => 0.0,
                };
                let giy = match (kd, ku) {
                    (true, true) => (px(kp + 1, lm, ch) - px(km - 1, lm, ch)) * 2.0,
                    (true, false) => px(kp + 1, lm, ch) - px(km, lm, ch),
                    (false, true) => px(kp, lm, ch) - px(km - 1, lm, ch),
                    (false, false) => 0.0,
                };
                ia[ch] += wgt * px(k - 1, l - 1, ch);
                jx[ch] -= wgt * (gix * rx);
                jy[ch] -= wgt * (giy * ry);
                s[ch] += wgt;
            }
        }
    }
    let o = image.index((j - 1) as usize, (i - 1) as usize) * c;
    for ch in 0..c {
        let corr = (jx[ch] + jy[ch]) / ((jx[ch] * jx[ch] + jy[ch] * jy[ch]).sqrt() + 1.0e-20);
        img[o + ch] = S::put(ia[ch] / s[ch] + corr);
    }
}
