//! The Middlebury optical-flow colour wheel, drawn exactly as PyPI `flow-vis` (and RAFT's
//! `flow_viz.py`) draws it: the 55-colour palette, `flow_uv_to_colors` and `flow_to_color`.
//!
//! Numerics follow `flow-vis` 0.1 under NumPy 2 with a float32 flow: the magnitude, the
//! normalisation, `atan2` and the palette position are float32; the palette interpolation, the
//! saturation ramp and the final `floor(255 * col)` are float64. Against the pictures that
//! `flow-vis` draws this gives identical pixels except, rarely, one level on a pixel whose value
//! sits on an integer boundary (the tests state the exact difference).
//!
//! Unlike `flow-vis` (whose output is undefined for NaN), a pixel whose flow is not finite is
//! drawn black and is ignored when looking for the largest magnitude.

/// Number of hues per segment: red-yellow, yellow-green, green-cyan, cyan-blue, blue-magenta,
/// magenta-red.
const SEGMENTS: [usize; 6] = [15, 6, 4, 11, 13, 6];

/// Number of colours in the wheel.
pub const NCOLS: usize = 55;

/// The epsilon `flow-vis` adds to the largest magnitude before dividing by it.
pub const NORMALIZE_EPS: f32 = 1e-5;

/// `floor(255 * i / n)`; exact in integers (the float64 quotient in NumPy never rounds across an
/// integer, so this equals `np.floor(255 * np.arange(n) / n)`).
const fn ramp(i: usize, n: usize) -> u8 {
    (255 * i / n) as u8
}

const fn build_wheel() -> [[u8; 3]; NCOLS] {
    let mut w = [[0u8; 3]; NCOLS];
    let [ry, yg, gc, cb, bm, mr] = SEGMENTS;
    let mut col = 0;
    let mut i = 0;
    while i < ry {
        w[col + i] = [255, ramp(i, ry), 0];
        i += 1;
    }
    col += ry;
    i = 0;
    while i < yg {
        w[col + i] = [255 - ramp(i, yg), 255, 0];
        i += 1;
    }
    col += yg;
    i = 0;
    while i < gc {
        w[col + i] = [0, 255, ramp(i, gc)];
        i += 1;
    }
    col += gc;
    i = 0;
    while i < cb {
        w[col + i] = [0, 255 - ramp(i, cb), 255];
        i += 1;
    }
    col += cb;
    i = 0;
    while i < bm {
        w[col + i] = [ramp(i, bm), 0, 255];
        i += 1;
    }
    col += bm;
    i = 0;
    while i < mr {
        w[col + i] = [255, 0, 255 - ramp(i, mr)];
        i += 1;
    }
    w
}

/// The palette as integers 0..=255 (RGB), computed at compile time.
pub const COLORWHEEL: [[u8; 3]; NCOLS] = build_wheel();

/// The 55 x 3 palette as `flow-vis`'s `make_colorwheel()` returns it (RGB values 0..=255).
pub fn make_colorwheel() -> Vec<[f32; 3]> {
    COLORWHEEL.iter().map(|c| [f32::from(c[0]), f32::from(c[1]), f32::from(c[2])]).collect()
}

/// The colour of one flow vector `(u, v)` already normalised so that magnitude 1 is the rim of
/// the wheel. Magnitudes above 1 are drawn at 75 % brightness, as `flow-vis` does. Non-finite
/// input gives black.
#[inline]
pub fn uv_to_rgb(u: f32, v: f32) -> [u8; 3] {
    if !(u.is_finite() && v.is_finite()) {
        return [0, 0, 0];
    }
    // float32, as NumPy computes it for a float32 flow
    let rad = (u * u + v * v).sqrt();
    let a = (-v).atan2(-u) / std::f32::consts::PI;
    let fk = (a + 1.0) / 2.0 * (NCOLS - 1) as f32;
    let k0f = fk.floor();
    // fk lies in [0, 54]; the clamp only guards against rounding
    let k0 = (k0f as usize).min(NCOLS - 1);
    let k1 = if k0 + 1 == NCOLS { 0 } else { k0 + 1 };
    // float32 minus int32 promotes to float64 in NumPy; the difference is exact either way
    let f = f64::from(fk) - f64::from(k0f);
    let rad = f64::from(rad);
    let mut out = [0u8; 3];
    for (i, o) in out.iter_mut().enumerate() {
        let col0 = f64::from(COLORWHEEL[k0][i]) / 255.0;
        let col1 = f64::from(COLORWHEEL[k1][i]) / 255.0;
        let mut col = (1.0 - f) * col0 + f * col1;
        if rad <= 1.0 {
            col = 1.0 - rad * (1.0 - col);
        } else {
            col *= 0.75;
        }
        *o = (255.0 * col).floor().clamp(0.0, 255.0) as u8;
    }
    out
}

/// `flow_uv_to_colors(u, v)`: colours of the already normalised flow components `u` and `v`
/// (any layout, one value per pixel), as `n x 3` RGB bytes.
///
/// # Panics
/// If `u` and `v` differ in length.
pub fn flow_uv_to_colors(u: &[f32], v: &[f32]) -> Vec<u8> {
    assert_eq!(u.len(), v.len(), "u and v must have the same length");
    let mut out = Vec::with_capacity(u.len() * 3);
    for (&uu, &vv) in u.iter().zip(v) {
        out.extend_from_slice(&uv_to_rgb(uu, vv));
    }
    out
}

/// The largest finite flow magnitude (float32, as NumPy computes it); 0 for an empty flow or one
/// without finite vectors.
pub fn max_magnitude(flow: &[f32]) -> f32 {
    flow.chunks_exact(2)
        .filter(|p| p[0].is_finite() && p[1].is_finite())
        .map(|p| (p[0] * p[0] + p[1] * p[1]).sqrt())
        .fold(0.0f32, f32::max)
}

/// `flow_to_color(flow_uv)`: an H x W x 2 flow (u, v interleaved, row-major) drawn as H x W x 3
/// RGB bytes.
///
/// `normalize_by`:
/// - `None`: divide by the largest finite magnitude plus [`NORMALIZE_EPS`], exactly as
///   `flow_to_color(flow_uv, clip_flow=None)` does, so the largest vector reaches the rim.
/// - `Some(s)` with a finite `s > 0`: divide by `s` (a fixed scale, so pictures of several flows
///   are comparable); vectors longer than `s` are drawn darkened. This is *not* `flow-vis`'s
///   `clip_flow`, which clamps u and v to `[0, clip_flow]` (dropping negative components) and
///   still normalises by the maximum. Any other `s` (0, negative, NaN, infinite) falls back to
///   `None`.
///
/// # Panics
/// If `flow.len() != width * height * 2`.
pub fn flow_to_color(flow: &[f32], width: usize, height: usize, normalize_by: Option<f32>) -> Vec<u8> {
    assert_eq!(
        Some(flow.len()),
        width.checked_mul(height).and_then(|n| n.checked_mul(2)),
        "flow must hold width * height * 2 values"
    );
    let scale = match normalize_by {
        Some(s) if s.is_finite() && s > 0.0 => s,
        _ => max_magnitude(flow) + NORMALIZE_EPS,
    };
    let mut out = Vec::with_capacity(width * height * 3);
    for p in flow.chunks_exact(2) {
        out.extend_from_slice(&uv_to_rgb(p[0] / scale, p[1] / scale));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn palette_segments() {
        let w = make_colorwheel();
        assert_eq!(w.len(), NCOLS);
        assert_eq!(SEGMENTS.iter().sum::<usize>(), NCOLS);
        assert_eq!(w[0], [255.0, 0.0, 0.0]);
        assert_eq!(w[1], [255.0, 17.0, 0.0]);
        assert_eq!(w[15], [255.0, 255.0, 0.0]);
        assert_eq!(w[21], [0.0, 255.0, 0.0]);
        assert_eq!(w[25], [0.0, 255.0, 255.0]);
        assert_eq!(w[36], [0.0, 0.0, 255.0]);
        assert_eq!(w[49], [255.0, 0.0, 255.0]);
        assert_eq!(w[54], [255.0, 0.0, 43.0]);
    }

    #[test]
    fn zero_flow_is_white_and_nan_is_black() {
        assert_eq!(uv_to_rgb(0.0, 0.0), [255, 255, 255]);
        assert_eq!(uv_to_rgb(f32::NAN, 0.0), [0, 0, 0]);
        assert_eq!(uv_to_rgb(0.0, f32::INFINITY), [0, 0, 0]);
        // an all-zero flow normalises by eps only and stays white
        assert_eq!(flow_to_color(&[0.0; 8], 2, 2, None), vec![255; 12]);
    }

    #[test]
    fn rim_colours() {
        // u = -1, v = 0: atan2(-0, 1) = 0 -> fk = 27 (palette index 27, cyan-blue segment)
        assert_eq!(uv_to_rgb(-1.0, 0.0), [0, 209, 255]);
        // u = 1, v = 0: atan2(-0, -1) = -pi -> index 0, pure red
        assert_eq!(uv_to_rgb(1.0, 0.0), [255, 0, 0]);
        // beyond the rim: 75 % of the rim colour
        assert_eq!(uv_to_rgb(2.0, 0.0), [191, 0, 0]);
    }

    #[test]
    fn normalisation() {
        let flow = [3.0, 4.0, 0.0, 0.0, f32::NAN, 1.0];
        assert_eq!(max_magnitude(&flow), 5.0);
        let auto = flow_to_color(&flow, 3, 1, None);
        let fixed = flow_to_color(&flow, 3, 1, Some(5.0 + NORMALIZE_EPS));
        assert_eq!(auto, fixed);
        assert_eq!(&auto[6..], &[0, 0, 0]);
        // invalid scales fall back to the automatic one
        assert_eq!(flow_to_color(&flow, 3, 1, Some(0.0)), auto);
        assert_eq!(flow_to_color(&flow, 3, 1, Some(f32::NAN)), auto);
        // a larger fixed scale draws the same vector paler
        let pale = flow_to_color(&flow, 3, 1, Some(50.0));
        assert!(pale[..3].iter().zip(&auto[..3]).all(|(p, a)| p >= a));
    }
}
