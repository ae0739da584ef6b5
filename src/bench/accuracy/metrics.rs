//! Error measures of the accuracy sweep: flow EPE, image error, differences, log-log slopes.

#[allow(clippy::wildcard_imports)]
use super::*;

// ---------------------------------------------------------------------------------------------
// Metrics

/// Mean end-point error of a rendered flow (H x W x 2) against the exact flow over `mask`
/// (NaN when the mask is empty).
pub fn flow_epe(flow: &[f32], exact: &ExactFlow, mask: &[bool]) -> f64 {
    let (mut sum, mut count) = (0.0f64, 0usize);
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
        let du = flow[2 * i] as f64 - exact.flow[2 * i];
        let dv = flow[2 * i + 1] as f64 - exact.flow[2 * i + 1];
        sum += (du * du + dv * dv).sqrt();
        count += 1;
    }
    if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    }
}

/// Mean absolute error and PSNR of an image against a reference over the pixels where the
/// reference coverage exceeds [`COVERAGE_MIN`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageErr {
    pub mae: f64,
    pub psnr: f64,
    pub pixels: usize,
}

pub const COVERAGE_MIN: f32 = 0.99;

pub fn image_error(image: &[f32], reference: &[f32], ref_coverage: &[f32]) -> ImageErr {
    let (mut abs, mut sq, mut count) = (0.0f64, 0.0f64, 0usize);
    for (i, _) in ref_coverage.iter().enumerate().filter(|(_, &c)| c > COVERAGE_MIN) {
        for c in 0..3 {
            let d = image[3 * i + c] as f64 - reference[3 * i + c] as f64;
            abs += d.abs();
            sq += d * d;
        }
        count += 1;
    }
    if count == 0 {
        return ImageErr { mae: f64::NAN, psnr: f64::NAN, pixels: 0 };
    }
    let m = (3 * count) as f64;
    let mse = sq / m;
    ImageErr { mae: abs / m, psnr: if mse > 0.0 { -10.0 * mse.log10() } else { f64::INFINITY }, pixels: count }
}

/// Largest and mean absolute difference of two equally long buffers.
pub fn abs_diff(a: &[f32], b: &[f32]) -> (f64, f64) {
    if a.is_empty() || a.len() != b.len() {
        return (f64::NAN, f64::NAN);
    }
    let (mut max, mut sum) = (0.0f64, 0.0f64);
    for (x, y) in a.iter().zip(b) {
        let d = (*x as f64 - *y as f64).abs();
        max = max.max(d);
        sum += d;
    }
    (max, sum / a.len() as f64)
}

/// Largest and mean end-point difference of two flows (H x W x 2).
pub fn flow_diff(a: &[f32], b: &[f32]) -> (f64, f64) {
    if a.is_empty() || a.len() != b.len() {
        return (f64::NAN, f64::NAN);
    }
    let (mut max, mut sum) = (0.0f64, 0.0f64);
    for (p, q) in a.chunks_exact(2).zip(b.chunks_exact(2)) {
        let d = ((p[0] as f64 - q[0] as f64).powi(2) + (p[1] as f64 - q[1] as f64).powi(2)).sqrt();
        max = max.max(d);
        sum += d;
    }
    (max, sum / (a.len() / 2) as f64)
}

/// Least-squares slope of ln(y) against ln(x) over the points with finite positive values
/// (NaN with fewer than two).
pub fn log_log_slope(points: &[(f64, f64)]) -> f64 {
    let pts: Vec<(f64, f64)> = points
        .iter()
        .filter(|(x, y)| x.is_finite() && y.is_finite() && *x > 0.0 && *y > 0.0)
        .map(|(x, y)| (x.ln(), y.ln()))
        .collect();
    if pts.len() < 2 {
        return f64::NAN;
    }
    let n = pts.len() as f64;
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    if sxx > 0.0 {
        sxy / sxx
    } else {
        f64::NAN
    }
}
