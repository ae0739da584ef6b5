//! What both variants share: the arguments' checks, the pixels to fill, the radius rules, the
//! heap keys, the band and the fast marching of the arrival times.

use super::types::{InpaintStats, MAX_RADIUS};
use crate::raster::Grid;
use std::cmp::Reverse;
use std::collections::BinaryHeap;

pub(super) fn check_args(len: usize, width: usize, height: usize, channels: usize, hole_len: usize) -> usize {
    let n = width.checked_mul(height).expect("inpaint: width * height overflows usize");
    assert!(channels > 0 || n == 0, "inpaint: channels must be at least 1");
    assert!(
        n.checked_mul(channels) == Some(len),
        "inpaint: image holds {len} values, {width} x {height} x {channels} needs {}",
        n.saturating_mul(channels)
    );
    assert_eq!(hole_len, n, "inpaint: hole mask holds {hole_len} values, {width} x {height} needs {n}");
    assert!(n < u32::MAX as usize, "inpaint: images of u32::MAX pixels or more are not supported");
    n
}

/// The pixels to fill (hole or non-finite) and the counts; `None` when there is nothing to do.
pub(super) fn f32_hole(image: &[f32], n: usize, channels: usize, hole: &[u8]) -> Option<(Vec<bool>, InpaintStats)> {
    let any_hole = hole.iter().any(|&h| h != 0);
    if !any_hole && image.iter().all(|v| v.is_finite()) {
        return None;
    }
    let mut is_hole = vec![false; n];
    let (mut filled, mut nonfinite) = (0, 0);
    for (i, flag) in is_hole.iter_mut().enumerate() {
        let bad = image[i * channels..(i + 1) * channels].iter().any(|v| !v.is_finite());
        if hole[i] != 0 || bad {
            *flag = true;
            filled += 1;
            if hole[i] == 0 {
                nonfinite += 1;
            }
        }
    }
    Some((is_hole, InpaintStats { filled, nonfinite, all_hole: filled == n, max_distance: 0.0 }))
}

pub(super) fn u8_hole(n: usize, hole: &[u8]) -> Option<(Vec<bool>, InpaintStats)> {
    if !hole.iter().any(|&h| h != 0) {
        return None;
    }
    let is_hole: Vec<bool> = hole.iter().map(|&h| h != 0).collect();
    let filled = is_hole.iter().filter(|&&h| h).count();
    Some((is_hole, InpaintStats { filled, nonfinite: 0, all_hole: filled == n, max_distance: 0.0 }))
}

pub(super) fn paper_radius(radius: f32) -> f32 {
    if radius >= 1.0 {
        radius.min(MAX_RADIUS)
    } else {
        1.0 // also NaN
    }
}

/// OpenCV: `range = cvRound(radius)` clamped to [1, 100].
pub(super) fn opencv_range(radius: f32) -> usize {
    let r = f64::from(radius).round_ties_even();
    if r >= 1.0 {
        r.min(f64::from(MAX_RADIUS)) as usize
    } else {
        1
    }
}

/// A heap key: the f32 mapped to an order-preserving u32 (both signs; -0 equals +0) in the high
/// half, the tie-breaker in the low half.
#[inline]
pub(super) fn key(t: f32, tie: u32) -> u64 {
    let t = if t == 0.0 { 0.0 } else { t };
    let b = t.to_bits();
    let ord = if b >> 31 == 1 { !b } else { b | 0x8000_0000 };
    (u64::from(ord) << 32) | u64::from(tie)
}

#[inline]
pub(super) fn key_t(k: u64) -> f32 {
    let ord = (k >> 32) as u32;
    f32::from_bits(if ord >> 31 == 1 { ord & 0x7fff_ffff } else { !ord })
}

/// Known pixels 4-adjacent to a hole pixel, in row-major order.
pub(super) fn band(w: usize, h: usize, is_hole: &[bool]) -> Vec<u32> {
    let g = Grid::new(w, h);
    let mut out = Vec::new();
    for i in 0..g.len() {
        if !is_hole[i] && g.neighbours4(i).any(|q| is_hole[q]) {
            out.push(i as u32);
        }
    }
    out
}

/// The standard upwind solution of `|grad T| = 1` from the smallest frozen horizontal (`a`) and
/// vertical (`b`) neighbour times (infinite where there is none; at least one is finite).
#[inline]
pub(super) fn upwind(a: f32, b: f32) -> f32 {
    let (a, b) = if a <= b { (f64::from(a), f64::from(b)) } else { (f64::from(b), f64::from(a)) };
    if !b.is_finite() || b - a >= 1.0 {
        (1.0 + a) as f32
    } else {
        let d = b - a;
        ((a + b + (2.0 - d * d).sqrt()) * 0.5) as f32
    }
}

/// Fast marching from `seeds` (T = 0) into the pixels where `in_region` holds, with updates of
/// tentative times (a textbook narrow band; stale heap entries are skipped). Stops once the
/// smallest tentative time exceeds `limit`. Frozen region pixels are appended to `order` in the
/// order they freeze: increasing T, ties by pixel index.
pub(super) fn march(
    w: usize,
    h: usize,
    t: &mut [f32],
    in_region: impl Fn(usize) -> bool,
    seeds: &[u32],
    limit: f32,
    mut order: Option<&mut Vec<u32>>,
) {
    let mut frozen = vec![false; w * h];
    let mut heap = BinaryHeap::with_capacity(seeds.len() * 2);
    for &s in seeds {
        t[s as usize] = 0.0;
        heap.push(Reverse(key(0.0, s)));
    }
    while let Some(Reverse(k)) = heap.pop() {
        let i = (k & 0xffff_ffff) as usize;
        let tk = key_t(k);
        if frozen[i] || tk > t[i] {
            continue; // stale entry
        }
        if tk > limit {
            break;
        }
        frozen[i] = true;
        if let Some(o) = order.as_deref_mut() {
            if in_region(i) {
                o.push(i as u32);
            }
        }
        let (x, y) = (i % w, i / w);
        let mut relax = |j: usize| {
            if frozen[j] || !in_region(j) {
                return;
            }
            let (jx, jy) = (j % w, j / w);
            let mut a = f32::INFINITY;
            if jx > 0 && frozen[j - 1] {
                a = t[j - 1];
            }
            if jx + 1 < w && frozen[j + 1] {
                a = a.min(t[j + 1]);
            }
            let mut b = f32::INFINITY;
            if jy > 0 && frozen[j - w] {
                b = t[j - w];
            }
            if jy + 1 < h && frozen[j + w] {
                b = b.min(t[j + w]);
            }
            let tn = upwind(a, b);
            if tn < t[j] {
                t[j] = tn;
                heap.push(Reverse(key(tn, j as u32)));
            }
        };
        if y > 0 {
            relax(i - w);
        }
        if x > 0 {
            relax(i - 1);
        }
        if y + 1 < h {
            relax(i + w);
        }
        if x + 1 < w {
            relax(i + 1);
        }
    }
}
