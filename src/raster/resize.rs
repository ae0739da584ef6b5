//! Resizing masks: nearest (labels) and bilinear (probabilities).

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
    let taps = |dst: usize, src_len: usize, dst_len: usize| {
        let s = ((dst as f64 + 0.5) * src_len as f64 / dst_len as f64 - 0.5).clamp(0.0, (src_len - 1) as f64);
        let i0 = s.floor() as usize;
        let i1 = (i0 + 1).min(src_len - 1);
        (i0, i1, (s - i0 as f64) as f32)
    };
    let xs: Vec<(usize, usize, f32)> = (0..new_w).map(|x| taps(x, w, new_w)).collect();
    let mut out = Vec::with_capacity(new_w * new_h);
    for y in 0..new_h {
        let (y0, y1, fy) = taps(y, h, new_h);
        let (r0, r1) = (&mask[y0 * w..][..w], &mask[y1 * w..][..w]);
        out.extend(xs.iter().map(|&(x0, x1, fx)| {
            let top = r0[x0] + (r0[x1] - r0[x0]) * fx;
            let bottom = r1[x0] + (r1[x1] - r1[x0]) * fx;
            top + (bottom - top) * fy
        }));
    }
    out
}
