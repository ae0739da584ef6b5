//! The paper's first-order method: the arrival times inside and outside the hole, then each
//! hole pixel in the front's order as the weighted mean of its neighbours' extrapolations.

use super::front::{band, march};
use super::types::{GradientTerm, DIR_FLOOR};
use crate::raster::Grid;

pub(super) struct Offset {
    dx: isize,
    dy: isize,
    inv_d: f32,
    inv_d2: f32,
}

pub(super) fn disc(radius: f32) -> Vec<Offset> {
    let rb = radius.floor() as isize;
    let mut out = Vec::new();
    for dy in -rb..=rb {
        for dx in -rb..=rb {
            let d2 = (dx * dx + dy * dy) as f32;
            if d2 > 0.0 && d2 <= radius * radius {
                out.push(Offset { dx, dy, inv_d: 1.0 / d2.sqrt(), inv_d2: 1.0 / d2 });
            }
        }
    }
    out
}

/// The pixels to fill and those that are no context.
#[derive(Clone, Copy)]
pub(super) struct Pixels<'a> {
    pub(super) is_hole: &'a [bool],
    pub(super) excluded: Option<&'a [bool]>,
}

/// The paper's method on an image with at least one known and one hole pixel; returns the
/// largest arrival time. Pixels where `excluded` holds (outside the hole) are not context: never
/// read, never a seed of the front, left out of `grad T`; hole pixels the front cannot reach
/// without crossing them are filled afterwards by a second pass that reads them.
pub(super) fn paper(
    img: &mut [f32],
    w: usize,
    h: usize,
    c: usize,
    pixels: Pixels<'_>,
    radius: f32,
    mode: GradientTerm,
) -> f32 {
    let Pixels { is_hole, excluded } = pixels;
    let n = w * h;
    let known: Vec<bool> = match excluded {
        None => is_hole.iter().map(|&hole| !hole).collect(),
        Some(e) => is_hole.iter().zip(e).map(|(&hole, &x)| !hole && !x).collect(),
    };
    let (t, order, max_distance) = arrival_times(w, h, is_hole, &known, radius);
    let offsets = disc(radius);
    let mut avail = known.clone();
    let use_known_grad = mode != GradientTerm::Off;
    let propagate = mode == GradientTerm::Propagated;
    let grid = Grid::new(w, h);
    let front = Front { grid, c, t: &t, known: &known, excluded, offsets: &offsets, use_known_grad, propagate };
    // the gradient of a filled pixel (Propagated): the weighted mean of the gradients its value
    // was extrapolated with, per channel (x, y); indexed by fill rank
    let mut slot = vec![u32::MAX; if propagate { n } else { 0 }];
    for (rank, &p) in order.iter().enumerate().filter(|_| propagate) {
        slot[p as usize] = rank as u32;
    }
    let mut grads = crate::buf::zeros::<f32>(if propagate { order.len() * c * 2 } else { 0 });
    let mut acc = vec![0.0f64; c * 3];
    for (rank, &p) in order.iter().enumerate() {
        let p = p as usize;
        let wsum = front.accumulate(img, &avail, &grads, &slot, p, &mut acc);
        // wsum > 0: the neighbour p was reached from is available and within radius >= 1
        let inv = if wsum > 0.0 { 1.0 / wsum } else { 0.0 };
        for (ch, a) in acc.chunks_exact(3).enumerate() {
            img[p * c + ch] = (a[0] * inv) as f32;
        }
        if propagate {
            let g = &mut grads[rank * c * 2..][..c * 2];
            for (ch, a) in acc.chunks_exact(3).enumerate() {
                g[ch * 2] = (a[1] * inv) as f32;
                g[ch * 2 + 1] = (a[2] * inv) as f32;
            }
        }
        avail[p] = true;
    }
    if excluded.is_some() && order.len() < is_hole.iter().filter(|&&v| v).count() {
        // hole pixels enclosed by excluded ones: filled from everything around them
        let rest: Vec<bool> = is_hole.iter().zip(&avail).map(|(&hole, &a)| hole && !a).collect();
        return max_distance.max(paper(img, w, h, c, Pixels { is_hole: &rest, excluded: None }, radius, mode));
    }
    max_distance
}

/// The arrival times: inside the hole (and the fill order, with the largest time), then outside
/// for the known pixels near the hole, negated.
fn arrival_times(w: usize, h: usize, is_hole: &[bool], known: &[bool], radius: f32) -> (Vec<f32>, Vec<u32>, f32) {
    let n = w * h;
    let mut seeds = band(w, h, is_hole);
    seeds.retain(|&i| known[i as usize]);
    let mut t = vec![f32::INFINITY; n];
    // inside: the fill order
    let mut order = Vec::with_capacity(is_hole.iter().filter(|&&v| v).count());
    march(w, h, &mut t, |i| is_hole[i], &seeds, f32::INFINITY, Some(&mut order));
    let max_distance = order.last().map_or(0.0, |&i| t[i as usize]);
    // outside: distances of the known pixels near the hole, negated
    let limit = radius.ceil() * 1.5 + 2.0;
    march(w, h, &mut t, |i| known[i], &seeds, limit, None);
    for (ti, _) in t.iter_mut().zip(is_hole).filter(|(_, &hole)| !hole) {
        *ti = if ti.is_finite() { -*ti } else { -1.0e6 };
    }
    (t, order, max_distance)
}

/// What every hole pixel's fill reads: the image's shape, the arrival times, the known pixels,
/// the disc of neighbours and the gradient rule.
struct Front<'a> {
    grid: Grid,
    c: usize,
    t: &'a [f32],
    known: &'a [bool],
    /// Pixels that are no context (see [`paper`]).
    excluded: Option<&'a [bool]>,
    offsets: &'a [Offset],
    use_known_grad: bool,
    propagate: bool,
}

impl Front<'_> {
    /// The weighted sums over the available neighbours of the hole pixel `p`, per channel in
    /// `acc` (the extrapolated value, the gradient's x and y); returns the sum of the weights.
    fn accumulate(&self, img: &[f32], avail: &[bool], grads: &[f32], slot: &[u32], p: usize, acc: &mut [f64]) -> f64 {
        let Front { grid, c, t, known, excluded, offsets, use_known_grad, propagate } = *self;
        let Grid { w, h } = grid;
        let (px, py) = grid.xy(p);
        let tp = t[p];
        // grad T at p: every in-image 4-neighbour of a hole pixel that is not excluded has a
        // finite T
        let ok = |q: usize| excluded.is_none_or(|e| !e[q]);
        let gx = central(px > 0 && ok(p - 1), px + 1 < w && ok(p + 1), || t[p - 1], || t[p + 1], tp);
        let gy = central(py > 0 && ok(p - w), py + 1 < h && ok(p + w), || t[p - w], || t[p + w], tp);
        let norm = (gx * gx + gy * gy).sqrt();
        let isotropic = norm <= 1.0e-6;
        let (nx, ny) = if isotropic { (0.0, 0.0) } else { (gx / norm, gy / norm) };

        acc.fill(0.0);
        let mut wsum = 0.0f64;
        for o in offsets {
            let Some(q) = grid.at(px as isize + o.dx, py as isize + o.dy) else { continue };
            if !avail[q] {
                continue;
            }
            // r = p - q
            let (rx, ry) = (-o.dx as f32, -o.dy as f32);
            let dir = if isotropic { 1.0 } else { ((rx * nx + ry * ny) * o.inv_d).abs().max(DIR_FLOOR) };
            let lev = 1.0 / (1.0 + (t[q] - tp).abs());
            let wd = f64::from(dir * o.inv_d2 * lev);
            wsum += wd;
            if known[q] && use_known_grad {
                let (qx, qy) = grid.xy(q);
                let xl = qx > 0 && known[q - 1];
                let xr = qx + 1 < w && known[q + 1];
                let yu = qy > 0 && known[q - w];
                let yd = qy + 1 < h && known[q + w];
                for (ch, a) in acc.chunks_exact_mut(3).enumerate() {
                    let v = img[q * c + ch];
                    let gix = limited(xl, xr, || img[(q - 1) * c + ch], || img[(q + 1) * c + ch], v);
                    let giy = limited(yu, yd, || img[(q - w) * c + ch], || img[(q + w) * c + ch], v);
                    a[0] += wd * f64::from(v + gix * rx + giy * ry);
                    a[1] += wd * f64::from(gix);
                    a[2] += wd * f64::from(giy);
                }
            } else if propagate {
                let g = &grads[slot[q] as usize * c * 2..][..c * 2];
                for (ch, a) in acc.chunks_exact_mut(3).enumerate() {
                    let v = img[q * c + ch];
                    let (gix, giy) = (g[ch * 2], g[ch * 2 + 1]);
                    a[0] += wd * f64::from(v + gix * rx + giy * ry);
                    a[1] += wd * f64::from(gix);
                    a[2] += wd * f64::from(giy);
                }
            } else {
                for (ch, a) in acc.chunks_exact_mut(3).enumerate() {
                    a[0] += wd * f64::from(img[q * c + ch]);
                }
            }
        }
        wsum
    }
}

/// A derivative along one axis from the values before and after the centre `v`: central where
/// both exist, one-sided where one does, 0 otherwise.
#[inline]
fn central(has_prev: bool, has_next: bool, prev: impl Fn() -> f32, next: impl Fn() -> f32, v: f32) -> f32 {
    match (has_prev, has_next) {
        (true, true) => (next() - prev()) * 0.5,
        (false, true) => next() - v,
        (true, false) => v - prev(),
        (false, false) => 0.0,
    }
}

/// An image derivative along one axis with a minmod slope limiter: where both neighbours exist,
/// the smaller of the forward and backward differences if they agree in sign, else 0 (exact on
/// linear data; no gradient at extrema; the gentle side across an edge); one-sided where one
/// exists, 0 otherwise.
#[inline]
fn limited(has_prev: bool, has_next: bool, prev: impl Fn() -> f32, next: impl Fn() -> f32, v: f32) -> f32 {
    match (has_prev, has_next) {
        (true, true) => {
            let (fwd, bwd) = (next() - v, v - prev());
            if fwd * bwd <= 0.0 {
                0.0
            } else if fwd.abs() < bwd.abs() {
                fwd
            } else {
                bwd
            }
        }
        (false, true) => next() - v,
        (true, false) => v - prev(),
        (false, false) => 0.0,
    }
}
