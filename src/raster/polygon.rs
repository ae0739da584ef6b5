//! COCO polygons rasterised exactly as pycocotools' `rleFrPoly`.

#[allow(clippy::wildcard_imports)]
use super::*;

// ---------------------------------------------------------------------------------------------
// polygons

/// Rasterises one polygon `[x0, y0, x1, y1, ...]` to COCO run lengths exactly as pycocotools'
/// `frPyObjects` / `rleFrPoly` (see the module documentation). Fewer than one point gives an
/// empty mask.
pub fn polygon_to_rle(xy: &[f64], h: usize, w: usize) -> Result<Vec<u32>, MaskError> {
    if !xy.len().is_multiple_of(2) {
        return Err(poly_err(format!("{} coordinates: expected x, y pairs", xy.len())));
    }
    if let Some(i) = xy.iter().position(|v| !v.is_finite()) {
        return Err(poly_err(format!("coordinate {i} is {}", xy[i])));
    }
    let n = pixel_count(h, w)?;
    let k = xy.len() / 2;
    if k == 0 || n == 0 {
        return Ok(vec![n]);
    }
    const SCALE: f64 = 5.0;
    let limit = 4.0e8;
    if let Some(i) = xy.iter().position(|v| v.abs() > limit) {
        return Err(poly_err(format!("coordinate {i} is {}, beyond +-{limit:e}", xy[i])));
    }
    // C: (int)(scale * v + .5), truncating toward zero
    let px: Vec<i64> = (0..=k).map(|j| (SCALE * xy[(j % k) * 2] + 0.5) as i64).collect();
    let py: Vec<i64> = (0..=k).map(|j| (SCALE * xy[(j % k) * 2 + 1] + 0.5) as i64).collect();
    let steps: u64 =
        (0..k).map(|j| (px[j] - px[j + 1]).unsigned_abs().max((py[j] - py[j + 1]).unsigned_abs()) + 1).sum();
    if steps > MAX_POLYGON_STEPS {
        return Err(poly_err(format!(
            "its outline needs {steps} upsampled points, more than the limit of {MAX_POLYGON_STEPS}"
        )));
    }

    let (hf, wf) = (h as f64, w as f64);
    let mut a: Vec<u32> = Vec::new();
    let mut prev: Option<(i64, i64)> = None;
    let mut visit = |u: i64, v: i64| {
        if let Some((pu, pv)) = prev {
            if u != pu {
                let xd = (if u < pu { u } else { u - 1 }) as f64;
                let xd = (xd + 0.5) / SCALE - 0.5;
                if xd.floor() == xd && xd >= 0.0 && xd <= wf - 1.0 {
                    let yd = v.min(pv) as f64;
                    let yd = (yd + 0.5) / SCALE - 0.5;
                    let yd = if yd < 0.0 {
                        0.0
                    } else if yd > hf {
                        hf
                    } else {
                        yd
                    };
                    let yd = yd.ceil();
                    // x <= w - 1 and y <= h: fits in u32 since h * w does
                    a.push((xd as u64 * h as u64 + yd as u64) as u32);
                }
            }
        }
        prev = Some((u, v));
    };
    for j in 0..k {
        let (mut xs, mut xe, mut ys, mut ye) = (px[j], px[j + 1], py[j], py[j + 1]);
        let dx = (xe - xs).abs();
        let dy = (ys - ye).abs();
        let flip = (dx >= dy && xs > xe) || (dx < dy && ys > ye);
        if flip {
            std::mem::swap(&mut xs, &mut xe);
            std::mem::swap(&mut ys, &mut ye);
        }
        if dx == 0 && dy == 0 {
            // C divides 0 by 0 here; the point equals its neighbours, so only u matters
            visit(xs, ys);
            continue;
        }
        if dx >= dy {
            let s = (ye - ys) as f64 / dx as f64;
            for d in 0..=dx {
                let t = if flip { dx - d } else { d };
                visit(t + xs, (ys as f64 + s * t as f64 + 0.5) as i64);
            }
        } else {
            let s = (xe - xs) as f64 / dy as f64;
            for d in 0..=dy {
                let t = if flip { dy - d } else { d };
                visit((xs as f64 + s * t as f64 + 0.5) as i64, t + ys);
            }
        }
    }
    Ok(crossings_to_runs(a, n))
}

/// The column-major crossing positions of an outline (the last, `n`, appended here) as COCO run
/// lengths, as `rleFrPoly` turns them into counts: sorted, differenced, and zero-length runs
/// merged with the run after them.
fn crossings_to_runs(mut a: Vec<u32>, n: u32) -> Vec<u32> {
    a.push(n);
    a.sort_unstable();
    let mut p = 0;
    for v in a.iter_mut() {
        let t = *v;
        *v -= p;
        p = t;
    }
    let mut b = Vec::with_capacity(a.len());
    b.push(a[0]);
    let mut j = 1;
    while j < a.len() {
        if a[j] > 0 {
            b.push(a[j]);
            j += 1;
        } else {
            j += 1;
            if j < a.len() {
                *b.last_mut().expect("b starts with one count") += a[j];
                j += 1;
            }
        }
    }
    b
}

/// Rasterises the polygons of one object (united) to a row-major `h x w` mask of 0 and 1, as
/// pycocotools' `annToMask` does for polygon segmentations.
pub fn polygon_to_mask(polys: &[Vec<f64>], h: usize, w: usize) -> Result<Vec<u8>, MaskError> {
    let mut mask = vec![0u8; pixel_count(h, w)? as usize];
    for (i, poly) in polys.iter().enumerate() {
        let rle = polygon_to_rle(poly, h, w).map_err(|e| e.in_field(&format!("polygon {i}")))?;
        let m = rle_decode_counts(&rle, h, w)?;
        mask.iter_mut().zip(&m).for_each(|(a, &b)| *a |= b);
    }
    Ok(mask)
}
