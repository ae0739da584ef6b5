//! The transform of a sample's tensors by a drawn [`Plan`]: colour jitter and the eraser on the
//! images (PIL's ImageEnhance and HSV, as torchvision's ColorJitter applies them), then the
//! spatial map on every per-pixel field (images and dense flow bilinear, sparse flow scattered,
//! labels by nearest neighbour) and the camera.

#[allow(unused_imports)]
use super::*;
use crate::raster::grid::interleaved;
use crate::raster::Grid;

/// PIL's `L` of an RGB pixel.
pub(super) fn luma(p: &[u8]) -> u8 {
    ((u32::from(p[0]) * 19595 + u32::from(p[1]) * 38470 + u32::from(p[2]) * 7471 + 0x8000) >> 16) as u8
}

/// PIL's blend `a + f (b - a)` of u8 values, clipped and truncated.
pub(super) fn blend(a: f32, b: u8, f: f32) -> u8 {
    let t = a + f * (f32::from(b) - a);
    if t <= 0.0 {
        0
    } else if t >= 255.0 {
        255
    } else {
        t as u8
    }
}

pub(super) fn rgb_to_hsv(p: &[u8]) -> [u8; 3] {
    let (r, g, b) = (i32::from(p[0]), i32::from(p[1]), i32::from(p[2]));
    let (maxc, minc) = (r.max(g).max(b), r.min(g).min(b));
    if maxc == minc {
        return [0, 0, maxc as u8];
    }
    let cr = (maxc - minc) as f32;
    let s = cr / maxc as f32;
    let (rc, gc, bc) = ((maxc - r) as f32 / cr, (maxc - g) as f32 / cr, (maxc - b) as f32 / cr);
    let h = if r == maxc {
        bc - gc
    } else if g == maxc {
        2.0 + rc - bc
    } else {
        4.0 + gc - rc
    };
    // fmod(h / 6 + 1, 1): h / 6 + 1 lies in [5/6, 11/6)
    let h = h / 6.0 + 1.0;
    let h = if h >= 1.0 { h - 1.0 } else { h };
    // float to u8 casts saturate and truncate, as PIL's CLIP8((int) x) for x >= 0
    [(h * 255.0) as u8, (s * 255.0) as u8, maxc as u8]
}

pub(super) fn hsv_to_rgb(hsv: [u8; 3]) -> [u8; 3] {
    let h = f32::from(hsv[0]) * 6.0 / 255.0;
    let s = f32::from(hsv[1]) / 255.0;
    let v = f32::from(hsv[2]);
    // h >= 0: the cast is the floor; x >= 0: x + 0.5 truncated is x rounded (half away from 0)
    let i = h as u32;
    let f = h - i as f32;
    let c = |x: f32| (x + 0.5) as u8;
    let (p, q, t) = (c(v * (1.0 - s)), c(v * (1.0 - s * f)), c(v * (1.0 - s * (1.0 - f))));
    let v = c(v);
    match i % 6 {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

/// ColorJitter on one image or a stack of images (the contrast mean is that of the stack).
pub(super) fn apply_jitter(images: &mut [&mut Vec<u8>], j: &Jitter) {
    if j.is_identity() {
        return;
    }
    for &op in &j.order {
        match op {
            0 if j.brightness != 1.0 => {
                let f = j.brightness as f32;
                for img in images.iter_mut() {
                    img.iter_mut().for_each(|v| *v = blend(0.0, *v, f));
                }
            }
            1 if j.contrast != 1.0 => {
                let (sum, n) = images.iter().fold((0u64, 0u64), |(s, n), img| {
                    (s + img.chunks_exact(3).map(|p| u64::from(luma(p))).sum::<u64>(), n + img.len() as u64 / 3)
                });
                let mean = (sum as f64 / n.max(1) as f64 + 0.5).floor() as f32;
                let f = j.contrast as f32;
                for img in images.iter_mut() {
                    img.iter_mut().for_each(|v| *v = blend(mean, *v, f));
                }
            }
            2 if j.saturation != 1.0 => {
                let f = j.saturation as f32;
                for img in images.iter_mut() {
                    for p in img.chunks_exact_mut(3) {
                        let l = f32::from(luma(p));
                        p.iter_mut().for_each(|v| *v = blend(l, *v, f));
                    }
                }
            }
            3 if j.hue != 0.0 => {
                // torchvision: h (u8) += uint8(hue * 255), wrapping
                let shift = (j.hue * 255.0) as i32;
                for img in images.iter_mut() {
                    for p in img.chunks_exact_mut(3) {
                        let mut hsv = rgb_to_hsv(p);
                        hsv[0] = (i32::from(hsv[0]) + shift).rem_euclid(256) as u8;
                        p.copy_from_slice(&hsv_to_rgb(hsv));
                    }
                }
            }
            _ => {}
        }
    }
}

/// RAFT's eraser: each box of image2 (clipped to the frame) filled with image2's mean colour
/// (truncated to u8), measured once before the first box.
pub(super) fn apply_eraser(img: &mut [u8], w: usize, h: usize, boxes: &[EraserBox]) {
    if boxes.is_empty() || img.is_empty() {
        return;
    }
    let n = (w * h).max(1) as f64;
    let mut mean = [0u8; 3];
    for (c, m) in mean.iter_mut().enumerate() {
        *m = (img.iter().skip(c).step_by(3).map(|&v| f64::from(v)).sum::<f64>() / n) as u8;
    }
    for b in boxes {
        let (x0, y0) = (b.x as usize, b.y as usize);
        let (x1, y1) = ((x0 + b.w as usize).min(w), (y0 + b.h as usize).min(h));
        let g = Grid::new(w, h);
        for y in (y0..y1).filter(|_| x0 < x1) {
            img[interleaved(g.span(y, x0..x1), 3)].chunks_exact_mut(3).for_each(|px| px.copy_from_slice(&mean));
        }
    }
}

/// Bilinear resampling of an interleaved u8 image (rounded to nearest).
pub(super) fn bilinear_u8(
    src: &[u8],
    w: usize,
    channels: usize,
    xt: &[(usize, usize, f32)],
    yt: &[(usize, usize, f32)],
) -> Vec<u8> {
    if src.is_empty() {
        return Vec::new();
    }
    let mut out = Vec::with_capacity(xt.len() * yt.len() * channels);
    for &(y0, y1, fy) in yt {
        let (r0, r1) = (&src[y0 * w * channels..][..w * channels], &src[y1 * w * channels..][..w * channels]);
        for &(x0, x1, fx) in xt {
            let (a, b) = (&r0[x0 * channels..][..channels], &r0[x1 * channels..][..channels]);
            let (d, e) = (&r1[x0 * channels..][..channels], &r1[x1 * channels..][..channels]);
            for c in 0..channels {
                let top = f32::from(a[c]) + (f32::from(b[c]) - f32::from(a[c])) * fx;
                let bottom = f32::from(d[c]) + (f32::from(e[c]) - f32::from(d[c])) * fx;
                // in [0, 255.5): the saturating cast of v + 0.5 is v rounded
                out.push((top + (bottom - top) * fy + 0.5) as u8);
            }
        }
    }
    out
}

/// Nearest-neighbour resampling of a plane of any element type.
pub(super) fn nearest<T: Copy>(src: &[T], w: usize, xn: &[usize], yn: &[usize]) -> Vec<T> {
    if src.is_empty() {
        return Vec::new();
    }
    let mut out = Vec::with_capacity(xn.len() * yn.len());
    for &y in yn {
        let row = &src[y * w..][..w];
        out.extend(xn.iter().map(|&x| row[x]));
    }
    out
}

/// The dense flow under the map (bilinear, scaled by the slopes) and its `valid` (1 where every
/// tap with a non-zero weight was valid).
pub(super) fn dense_flow(
    s: &Sample,
    plan: &Plan,
    xt: &[(usize, usize, f32)],
    yt: &[(usize, usize, f32)],
) -> (Vec<f32>, Vec<u8>) {
    let w = s.width;
    let (kx, ky) = (plan.x.slope() as f32, plan.y.slope() as f32);
    let n = xt.len() * yt.len();
    let mut flow = Vec::with_capacity(2 * n);
    let mut valid = Vec::with_capacity(n);
    for &(y0, y1, fy) in yt {
        let (f0, f1) = (&s.flow[2 * y0 * w..][..2 * w], &s.flow[2 * y1 * w..][..2 * w]);
        let (v0, v1) = (&s.valid[y0 * w..][..w], &s.valid[y1 * w..][..w]);
        // the second row counts only with a non-zero weight
        let row1 = fy > 0.0;
        for &(x0, x1, fx) in xt {
            let col1 = fx > 0.0;
            let ok = v0[x0] != 0 && (!col1 || v0[x1] != 0) && (!row1 || (v1[x0] != 0 && (!col1 || v1[x1] != 0)));
            for (c, k) in [(0, kx), (1, ky)] {
                let top = f0[2 * x0 + c] + (f0[2 * x1 + c] - f0[2 * x0 + c]) * fx;
                let bottom = f1[2 * x0 + c] + (f1[2 * x1 + c] - f1[2 * x0 + c]) * fx;
                flow.push((top + (bottom - top) * fy) * k);
            }
            valid.push(u8::from(ok));
        }
    }
    (flow, valid)
}

/// RAFT's sparse rule: each valid vector moved to the output pixel nearest its mapped position
/// (later source pixels win), scaled by the slopes; nothing else is valid.
pub(super) fn sparse_flow(s: &Sample, plan: &Plan) -> (Vec<f32>, Vec<u8>) {
    let (ow, oh) = (plan.x.out, plan.y.out);
    let (kx, ky) = (plan.x.slope() as f32, plan.y.slope() as f32);
    let mut flow = crate::buf::zeros::<f32>(2 * ow * oh);
    let mut valid = crate::buf::zeros::<u8>(ow * oh);
    let (src, out) = (Grid::new(s.width, s.height), Grid::new(ow, oh));
    let xs: Vec<Option<usize>> = (0..s.width).map(|x| plan.x.scatter(x)).collect();
    for y in 0..s.height {
        let Some(oy) = plan.y.scatter(y) else { continue };
        for (x, ox) in xs.iter().enumerate() {
            let i = src.index(x, y);
            if let (Some(ox), true) = (ox, s.valid[i] != 0) {
                let o = out.index(*ox, oy);
                flow[2 * o] = s.flow[2 * i] * kx;
                flow[2 * o + 1] = s.flow[2 * i + 1] * ky;
                valid[o] = 1;
            }
        }
    }
    (flow, valid)
}

/// Clears `valid` where the flow target leaves the `w` x `h` frame (target inside
/// `[0, w - 1] x [0, h - 1]`, the renderer's rule) or the flow is not finite.
pub fn clear_valid_outside(flow: &[f32], valid: &mut [u8], w: usize, h: usize) {
    let (maxx, maxy) = (w.saturating_sub(1) as f32, h.saturating_sub(1) as f32);
    for (i, v) in valid.iter_mut().enumerate() {
        if *v != 0 {
            let tx = (i % w) as f32 + flow[2 * i];
            let ty = (i / w) as f32 + flow[2 * i + 1];
            if !(tx >= 0.0 && tx <= maxx && ty >= 0.0 && ty <= maxy) {
                *v = 0;
            }
        }
    }
}

/// The u8 label planes of a sample (one byte per pixel, resampled with nearest neighbour).
pub(super) fn label_planes(s: &mut Sample) -> [&mut Vec<u8>; 4] {
    [&mut s.occlusion, &mut s.mask1, &mut s.mask2, &mut s.holes]
}

/// The intrinsics of the output frame: scaled with the frame, the principal point mirrored
/// under a flip and shifted to the crop (the focal lengths stay positive; the flip is recorded).
pub(super) fn intrinsics(k: Intrinsics, x: Axis, y: Axis) -> Intrinsics {
    let axis = |f: f64, c: f64, a: Axis| {
        let s = a.resized as f64 / a.src as f64;
        let r = (c + 0.5) * s - 0.5;
        let r = if a.flip { (a.resized - 1) as f64 - r } else { r };
        (f * s, r - a.offset as f64)
    };
    let (fx, cx) = axis(k.fx, k.cx, x);
    let (fy, cy) = axis(k.fy, k.cy, y);
    Intrinsics::new(fx, fy, cx, cy)
}

/// Applies a drawn plan to a sample (all its per-pixel fields). Augmentation is made for pairs:
/// a sample's backward fields and clip frames are dropped (the service refuses to ask for both).
pub fn apply_plan(plan: &Plan, mut s: Sample) -> Sample {
    s.backward = crate::sample::LinkFields::default();
    s.clip.clear();
    let (w, h) = (s.width, s.height);
    if w == 0 || h == 0 {
        return s;
    }
    // colour, then the eraser, on the rendered frame (RAFT's order)
    if plan.color {
        if plan.asymmetric {
            apply_jitter(&mut [&mut s.image1], &plan.jitter[0]);
            apply_jitter(&mut [&mut s.image2], &plan.jitter[1]);
        } else {
            apply_jitter(&mut [&mut s.image1, &mut s.image2], &plan.jitter[0]);
        }
    }
    apply_eraser(&mut s.image2, w, h, &plan.eraser);
    if plan.x == Axis::identity(w) && plan.y == Axis::identity(h) {
        // no resize, flip or crop: the flow, `valid` and the labels stay as they are
        return s;
    }
    // the spatial map
    let (xt, yt) = (plan.x.taps(), plan.y.taps());
    let (xn, yn) = (plan.x.nearest(), plan.y.nearest());
    let (ow, oh) = (plan.x.out, plan.y.out);
    let (flow, valid) = if s.flow.len() != 2 * w * h || s.valid.len() != w * h {
        (Vec::new(), Vec::new())
    } else {
        let (flow, mut valid) = if plan.sparse { sparse_flow(&s, plan) } else { dense_flow(&s, plan, &xt, &yt) };
        clear_valid_outside(&flow, &mut valid, ow, oh);
        (flow, valid)
    };
    s.image1 = bilinear_u8(&s.image1, w, 3, &xt, &yt);
    s.image2 = bilinear_u8(&s.image2, w, 3, &xt, &yt);
    s.flow = flow;
    s.valid = valid;
    for plane in label_planes(&mut s) {
        *plane = nearest(plane, w, &xn, &yn);
    }
    s.depth1 = nearest(&s.depth1, w, &xn, &yn);
    s.depth2 = nearest(&s.depth2, w, &xn, &yn);
    s.intrinsics = intrinsics(s.intrinsics, plan.x, plan.y);
    s.width = ow;
    s.height = oh;
    s
}
