//! The real-view check of `mpiflow bench quality --right-view`: a sample rendered to the camera
//! of a real second photo of the scene (a rectified stereo pair with measured disparity) and
//! compared with what that camera saw: image error, sharpness and flow error.
//!
//! The pair is rectified: a left pixel at column `x` with disparity `d` appears in the right view
//! at `x - d`, and `d = fb / depth` for the depth file's `depth` (`fb`: focal length times
//! baseline in the depth file's units). The scene puts its nearest known depth `d_min` at depth 1
//! (`scene::scale`), so with the source camera's focal length `fx` the right camera is the pure
//! translation `t = (-fb / (fx d_min), 0, 0)` in scene units, and the exact flow is `(-d, 0)`.

use crate::geometry::Intrinsics;
use crate::raster::grid::pixel_values;
use crate::raster::Grid;
use crate::sample::motion::{Component, MotionPreset, MotionRanges};
use crate::sample::Sample;

use super::measure::laplacian_variance;

/// Columns at the right view's right border left out of the image comparison: what the left
/// photo never saw enters there (at most the largest disparity).
pub const DEFAULT_BORDER: usize = 60;

/// A real right view and the measured disparity of the left photo.
#[derive(Clone, Debug)]
pub struct RealView {
    pub width: usize,
    pub height: usize,
    /// The right photo, interleaved RGB8.
    pub right: Vec<u8>,
    /// The left photo's disparity in pixels (`fb / depth`), NaN where the depth is unknown.
    pub disparity: Vec<f32>,
    /// Columns at the right border left out of the image comparison.
    pub border: usize,
}

/// The figures of one comparison.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RealViewReport {
    /// Mean absolute difference of image2 and the right photo (0..255, mean of the channels) over
    /// the columns left of the border.
    pub mae: f64,
    /// Laplacian variance of image2 over its rendered pixels (no hole) left of the border divided
    /// by the right photo's over the same pixels; 1 = as sharp as the photo.
    pub sharpness: f64,
    /// Mean end-point error of the forward flow against `(-d, 0)` over the valid pixels with a
    /// measured disparity, in pixels.
    pub epe: f64,
    /// The pair's own photometric floor: the mean absolute difference between each left pixel
    /// with a measured disparity and the right photo at `x - d` (nearest column), occluded pixels
    /// included.
    pub floor: f64,
}

impl RealView {
    /// A view from its parts; the depth file's `depth` (non-finite or `<= 0`: unknown) becomes
    /// disparity `fb / depth`. None when the sizes disagree or no depth is known.
    pub fn new(width: usize, height: usize, right: Vec<u8>, depth: &[f64], fb: f64) -> Option<Self> {
        if right.len() != width * height * 3 || depth.len() != width * height || !(fb.is_finite() && fb > 0.0) {
            return None;
        }
        let disparity: Vec<f32> =
            depth.iter().map(|&z| if z.is_finite() && z > 0.0 { (fb / z) as f32 } else { f32::NAN }).collect();
        disparity.iter().any(|d| d.is_finite()).then_some(Self {
            width,
            height,
            right,
            disparity,
            border: DEFAULT_BORDER,
        })
    }

    /// The smallest known depth in the depth file's units (`fb / max d`).
    fn nearest_depth(&self, fb: f64) -> f64 {
        let max = self.disparity.iter().copied().filter(|d| d.is_finite()).fold(0.0f32, f32::max);
        fb / f64::from(max)
    }

    /// The motion law whose only draw is the right camera (see the module documentation), for
    /// a source camera of focal length `fx` in pixels.
    pub fn law(&self, fx: f64, fb: f64) -> MotionRanges {
        let mut law = MotionPreset::Stereo.ranges();
        law.name = "right-view".into();
        law.camera.translation.x = Component::constant(-fb / (fx * self.nearest_depth(fb)));
        law
    }

    /// The focal length the pipeline gives a source without intrinsics.
    pub fn default_fx(&self) -> f64 {
        Intrinsics::reference_default(self.width, self.height).fx
    }

    /// Compares a sample of the left photo rendered to the right camera with the right photo.
    /// None when the sizes differ.
    pub fn compare(&self, s: &Sample) -> Option<RealViewReport> {
        let (w, h) = (self.width, self.height);
        if s.width != w || s.height != h {
            return None;
        }
        let g = Grid::new(w, h);
        let keep = w.saturating_sub(self.border);
        let (mut err, mut n) = (0.0f64, 0u64);
        for y in 0..h {
            for x in 0..keep {
                let i = pixel_values(g.index(x, y), 3);
                err += s.image2[i.clone()]
                    .iter()
                    .zip(&self.right[i])
                    .map(|(&a, &b)| f64::from(a.abs_diff(b)))
                    .sum::<f64>();
                n += 3;
            }
        }
        let mae = if n == 0 { 0.0 } else { err / n as f64 };
        let region = |i: usize| i % w < keep && s.holes[i] == 0;
        let sharp2 = laplacian_variance(&s.image2, w, h, region).unwrap_or(0.0);
        let sharp_r = laplacian_variance(&self.right, w, h, region).unwrap_or(0.0);
        let sharpness = if sharp_r > 0.0 { sharp2 / sharp_r } else { 0.0 };
        let (mut epe, mut m) = (0.0f64, 0u64);
        let (mut floor, mut k) = (0.0f64, 0u64);
        for y in 0..h {
            for x in 0..w {
                let i = g.index(x, y);
                let d = self.disparity[i];
                if !d.is_finite() {
                    continue;
                }
                if s.valid[i] != 0 {
                    epe += f64::from((s.flow[2 * i] + d).hypot(s.flow[2 * i + 1]));
                    m += 1;
                }
                let xr = (x as f64 - f64::from(d)).round();
                if xr >= 0.0 && (xr as usize) < w {
                    let j = 3 * g.index(xr as usize, y);
                    floor += (0..3).map(|c| f64::from(s.image1[3 * i + c].abs_diff(self.right[j + c]))).sum::<f64>();
                    k += 3;
                }
            }
        }
        Some(RealViewReport {
            mae,
            sharpness,
            epe: if m == 0 { 0.0 } else { epe / m as f64 },
            floor: if k == 0 { 0.0 } else { floor / k as f64 },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn law_moves_the_nearest_content_by_the_largest_disparity() {
        // depth 2 and 4 with fb = 100: disparities 50 and 25; the nearest content (depth 2) sits
        // at scene depth 1, so fx * |t| must be 50
        let v = RealView::new(2, 1, vec![0; 6], &[2.0, 4.0], 100.0).unwrap();
        let law = v.law(10.0, 100.0);
        let (lo, hi) = law.camera.translation.x.bounds();
        assert_eq!(lo, hi);
        assert!((10.0 * -lo - 50.0).abs() < 1e-12, "{lo}");
        assert!(law.validate().is_ok());
    }

    #[test]
    fn unknown_depth_and_bad_sizes_are_refused() {
        assert!(RealView::new(2, 1, vec![0; 6], &[f64::NAN, -1.0], 100.0).is_none());
        assert!(RealView::new(2, 1, vec![0; 5], &[1.0, 1.0], 100.0).is_none());
        assert!(RealView::new(2, 1, vec![0; 6], &[1.0, 1.0], 0.0).is_none());
    }
}
