//! Image measures of finished pictures that the benchmarks share: luminance, the variance of the
//! Laplacian (the focus measure of the sharpness figures) and image1 warped ideally by a
//! sample's geometry.

use crate::raster::Grid;
use crate::sample::Sample;

/// Rec. 601 luminance (0..255) of pixel `i` of an interleaved u8 RGB image.
pub(crate) fn luminance(img: &[u8], i: usize) -> f64 {
    0.299 * f64::from(img[3 * i]) + 0.587 * f64::from(img[3 * i + 1]) + 0.114 * f64::from(img[3 * i + 2])
}

/// Variance of the discrete Laplacian (`4 c - n - s - e - w` of the luminance, 0..255 units) of
/// an interleaved u8 RGB image over the interior pixels where `inside` holds for the pixel and
/// its four neighbours; `None` when fewer than 16 pixels qualify. The usual focus measure: it
/// weighs the highest frequencies, which a resampling kernel loses first.
pub fn laplacian_variance(img: &[u8], w: usize, h: usize, inside: impl Fn(usize) -> bool) -> Option<f64> {
    let lum = |i: usize| luminance(img, i);
    let g = Grid::new(w, h);
    let (mut n, mut sum, mut sq) = (0u64, 0.0f64, 0.0f64);
    for y in 1..h.saturating_sub(1) {
        for x in 1..w - 1 {
            let i = g.index(x, y);
            if ![i, i - 1, i + 1, i - w, i + w].into_iter().all(&inside) {
                continue;
            }
            let l = 4.0 * lum(i) - lum(i - 1) - lum(i + 1) - lum(i - w) - lum(i + w);
            n += 1;
            sum += l;
            sq += l * l;
        }
    }
    (n >= 16).then(|| {
        let m = sum / n as f64;
        (sq / n as f64 - m * m).max(0.0)
    })
}

/// Image1 warped ideally by the sample's geometry (RGB8, W x H x 3): image1's quintic B-spline
/// ([`crate::render::resample::SplineImage`]) sampled at `q + backward_flow(q)` where the
/// backward flow is valid, 0 elsewhere. `None` without the backward fields.
pub fn ideal_warp(s: &Sample) -> Option<Vec<u8>> {
    let (w, h) = (s.width, s.height);
    let bw = &s.backward;
    if bw.flow.len() != 2 * w * h || bw.valid.len() != w * h {
        return None;
    }
    let rgb: Vec<f32> = s.image1.iter().map(|&v| f32::from(v) / 255.0).collect();
    let spline = crate::render::resample::SplineImage::new(&rgb, w, h);
    let mut ideal = vec![0u8; 3 * w * h];
    for i in 0..w * h {
        if bw.valid[i] == 0 {
            continue;
        }
        let (x, y) = ((i % w) as f32 + bw.flow[2 * i], (i / w) as f32 + bw.flow[2 * i + 1]);
        let c = spline.sample(x, y);
        for k in 0..3 {
            ideal[3 * i + k] = (c[k] * 255.0 + 0.5).clamp(0.0, 255.0) as u8;
        }
    }
    Some(ideal)
}
