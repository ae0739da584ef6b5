//! Resizing masks: nearest (labels) and bilinear (probabilities); depth and disparity maps:
//! bilinear within a surface, nearest across its edges ([`resize_depth`]).

// ---------------------------------------------------------------------------------------------
// resizing

fn check_resize(len: usize, w: usize, h: usize) {
    assert_eq!(Some(len), w.checked_mul(h), "resize: mask holds {len} values, {w} x {h} needs more or fewer");
}

/// Nearest-neighbour resize of a row-major `w x h` mask to `new_w x new_h`, pixel centres
/// aligned (source pixel `floor((x + 0.5) * w / new_w)`, like PIL's NEAREST and PyTorch's
/// `nearest-exact`; OpenCV's INTER_NEAREST uses `floor(x * w / new_w)`). An empty source gives
/// zeros.
///
/// # Panics
/// If `mask.len() != w * h`.
pub fn resize_nearest(mask: &[f32], w: usize, h: usize, new_w: usize, new_h: usize) -> Vec<f32> {
    check_resize(mask.len(), w, h);
    if w == 0 || h == 0 {
        return vec![0.0; new_w * new_h];
    }
    let map = |dst: usize, src_len: usize, dst_len: usize| {
        ((((dst as f64 + 0.5) * src_len as f64 / dst_len as f64).floor()) as usize).min(src_len - 1)
    };
    let xs: Vec<usize> = (0..new_w).map(|x| map(x, w, new_w)).collect();
    let mut out = Vec::with_capacity(new_w * new_h);
    for y in 0..new_h {
        let row = &mask[map(y, h, new_h) * w..][..w];
        out.extend(xs.iter().map(|&x| row[x]));
    }
    out
}

/// The two source taps and the weight of the second for destination index `dst` of a bilinear
/// resize from `src_len` to `dst_len` (pixel centres aligned, edges clamped).
fn bilinear_taps(dst: usize, src_len: usize, dst_len: usize) -> (usize, usize, f32) {
    let s = ((dst as f64 + 0.5) * src_len as f64 / dst_len as f64 - 0.5).clamp(0.0, (src_len - 1) as f64);
    let i0 = s.floor() as usize;
    let i1 = (i0 + 1).min(src_len - 1);
    (i0, i1, (s - i0 as f64) as f32)
}

/// Bilinear interpolation of `[top-left, top-right, bottom-left, bottom-right]`.
fn lerp2(q: [f32; 4], fx: f32, fy: f32) -> f32 {
    let top = q[0] + (q[1] - q[0]) * fx;
    let bottom = q[2] + (q[3] - q[2]) * fx;
    top + (bottom - top) * fy
}

/// Largest ratio between the four source values a depth (or disparity) resize interpolates
/// between ([`resize_depth`]); a larger step is an edge between surfaces.
pub const DEPTH_RESIZE_SPREAD: f32 = 1.05;

/// Resize of a depth or disparity map (`w x h` to `new_w x new_h`, pixel centres aligned):
/// bilinear, as [`resize_bilinear`], where the four source values around the point are all
/// known (finite and > 0) and lie within [`DEPTH_RESIZE_SPREAD`] of each other, i.e. on one
/// smooth surface; elsewhere (an edge between surfaces, or unknown depth next to the point)
/// nearest, as [`resize_nearest`], so no depth is invented between two surfaces and unknown
/// stays unknown. Nearest alone turns an upsampled slanted surface into stair steps (rows of
/// equal depth), which the object merge saw as depth ripples and drew as thin lines
/// (`tests/samples/labels.rs`).
///
/// # Panics
/// If `v.len() != w * h`.
pub fn resize_depth(v: &[f32], w: usize, h: usize, new_w: usize, new_h: usize) -> Vec<f32> {
    let nearest = resize_nearest(v, w, h, new_w, new_h);
    if w == 0 || h == 0 {
        return nearest;
    }
    let xs: Vec<(usize, usize, f32)> = (0..new_w).map(|x| bilinear_taps(x, w, new_w)).collect();
    let known = |d: f32| d.is_finite() && d > 0.0;
    let mut out = nearest;
    for (y, row) in out.chunks_exact_mut(new_w.max(1)).enumerate().take(new_h) {
        let (y0, y1, fy) = bilinear_taps(y, h, new_h);
        let (r0, r1) = (&v[y0 * w..][..w], &v[y1 * w..][..w]);
        for (o, &(x0, x1, fx)) in row.iter_mut().zip(&xs) {
            let q = [r0[x0], r0[x1], r1[x0], r1[x1]];
            if !q.iter().all(|&d| known(d)) {
                continue;
            }
            let (lo, hi) = q.iter().fold((f32::MAX, 0.0f32), |(lo, hi), &d| (lo.min(d), hi.max(d)));
            if hi > lo * DEPTH_RESIZE_SPREAD {
                continue;
            }
            *o = lerp2(q, fx, fy);
        }
    }
    out
}

/// Bilinear resize of a row-major `w x h` mask to `new_w x new_h`, pixel centres aligned
/// (`align_corners = false`, edges clamped; like OpenCV's INTER_LINEAR and PyTorch's bilinear
/// without antialiasing, so strong downscaling aliases). An empty source gives zeros.
///
/// # Panics
/// If `mask.len() != w * h`.
pub fn resize_bilinear(mask: &[f32], w: usize, h: usize, new_w: usize, new_h: usize) -> Vec<f32> {
    check_resize(mask.len(), w, h);
    if w == 0 || h == 0 {
        return vec![0.0; new_w * new_h];
    }
    let xs: Vec<(usize, usize, f32)> = (0..new_w).map(|x| bilinear_taps(x, w, new_w)).collect();
    let mut out = Vec::with_capacity(new_w * new_h);
    for y in 0..new_h {
        let (y0, y1, fy) = bilinear_taps(y, h, new_h);
        let (r0, r1) = (&mask[y0 * w..][..w], &mask[y1 * w..][..w]);
        out.extend(xs.iter().map(|&(x0, x1, fx)| lerp2([r0[x0], r0[x1], r1[x0], r1[x1]], fx, fy)));
    }
    out
}

// ---------------------------------------------------------------------------------------------
// cover and crop

/// The size a `w x h` image is resized to so that it covers a `frame_w x frame_h` frame with its
/// aspect kept, and the corner of the centred frame in it: `(rw, rh, x0, y0)`. The scale is
/// `max(frame_w / w, frame_h / h)`; each resized side is rounded to the nearest pixel and at least
/// the frame's; the frame is centred (`x0 = (rw - frame_w) / 2`, rounded down).
pub fn cover(w: usize, h: usize, frame_w: usize, frame_h: usize) -> (usize, usize, usize, usize) {
    let s = (frame_w as f64 / w.max(1) as f64).max(frame_h as f64 / h.max(1) as f64);
    let rw = ((w as f64 * s).round() as usize).max(frame_w);
    let rh = ((h as f64 * s).round() as usize).max(frame_h);
    (rw, rh, (rw - frame_w) / 2, (rh - frame_h) / 2)
}

/// The `cw x ch` window at `(x0, y0)` of a row-major `w`-wide buffer of `channels` values per
/// pixel.
///
/// # Panics
/// If the window does not fit in the buffer.
pub fn crop(v: &[f32], w: usize, channels: usize, x0: usize, y0: usize, cw: usize, ch: usize) -> Vec<f32> {
    assert!(x0 + cw <= w && (y0 + ch) * w * channels <= v.len(), "crop: the window is outside the buffer");
    let mut out = Vec::with_capacity(cw * ch * channels);
    for y in y0..y0 + ch {
        let row = (y * w + x0) * channels;
        out.extend_from_slice(&v[row..row + cw * channels]);
    }
    out
}
