//! `mpiflow bench quality`: the numbers a person checks before training on a new photo
//! collection, measured on finished samples: photometric error of the flow on valid,
//! non-occluded pixels, violations of the label laws, the fraction of image2 filled by 2-D
//! inpainting, thin-line runs in image2 against image1, the sharpness ratio of image2 to image1
//! (variance of the Laplacian), valid and occluded fractions and the flow magnitude percentiles. Every metric is a pure function of a sample (and, for the depth
//! law, the merge's target depth), written here independently of the merge's rule so that the
//! tests (`tests/samples/labels.rs`) can hold the merge to it.
//!
//! # The label laws
//!
//! For every source pixel `p` that is valid and not occluded, with target `q = p + flow(p)` and
//! `N` the four bilinear neighbours of `q` (clamped to the frame):
//!
//! - **holes**: no pixel of `N` is a hole (filled by 2-D inpainting);
//! - **label**: some pixel of `N` shows `p`'s object label (`mask2 = mask1(p)`);
//! - **depth**: some pixel of `N` with that label shows a depth `d` (`depth2`) that agrees with
//!   `p`'s expected target depth `z`: `z / d` in `[1 / (1 + tol), 1 + tol]`, `tol` =
//!   [`OCCLUSION_TOLERANCE`].
//!
//! Each law's violations are counted over the valid, non-occluded pixels (a pixel that breaks
//! the label law is not counted again under the depth law).

use super::measure::{ideal_warp, laplacian_variance};
use super::realism::{RealismAccumulator, RealismReport};
use crate::raster::Grid;
use crate::render::OCCLUSION_TOLERANCE;
use crate::sample::config::SampleConfig;
use crate::sample::error::SampleError;
use crate::sample::pipeline::Generator;
use crate::sample::recipe::assemble_with_target_depth;
use crate::sample::{Sample, SampleAddress};

/// Counts of the label laws over one or more samples (see the module documentation).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LawCounts {
    /// Valid, non-occluded pixels checked.
    pub checked: u64,
    /// Of those, pixels with a hole among the target's bilinear neighbours.
    pub holes: u64,
    /// Pixels whose label no neighbour shows.
    pub label: u64,
    /// Pixels whose label is shown but at no depth within the tolerance of theirs.
    pub depth: u64,
}

impl LawCounts {
    pub fn add(&mut self, o: &LawCounts) {
        self.checked += o.checked;
        self.holes += o.holes;
        self.label += o.label;
        self.depth += o.depth;
    }

    /// `count / checked` (0 when nothing was checked).
    pub fn rate(&self, count: u64) -> f64 {
        if self.checked == 0 {
            0.0
        } else {
            count as f64 / self.checked as f64
        }
    }
}

fn neighbours(w: usize, h: usize, tx: f32, ty: f32) -> [usize; 4] {
    let tx = tx.clamp(0.0, (w - 1) as f32);
    let ty = ty.clamp(0.0, (h - 1) as f32);
    let (x0, y0) = (tx.floor() as usize, ty.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    [y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1]
}

/// The label laws of `s`, with `target_depth` the expected target depth of each source pixel
/// ([`crate::sample::recipe::assemble_with_target_depth`]).
///
/// # Panics
/// If a buffer's size disagrees with the sample's.
pub fn label_laws(s: &Sample, target_depth: &[f32]) -> LawCounts {
    let (w, h) = (s.width, s.height);
    let n = w * h;
    assert!(target_depth.len() == n && s.holes.len() == n && s.depth2.len() == n && s.mask2.len() == n);
    let tol = 1.0 + OCCLUSION_TOLERANCE;
    let mut c = LawCounts::default();
    for (i, &z) in target_depth.iter().enumerate() {
        if s.valid[i] == 0 || s.occlusion[i] != 0 {
            continue;
        }
        c.checked += 1;
        let (x, y) = (i % w, i / w);
        let nb = neighbours(w, h, x as f32 + s.flow[2 * i], y as f32 + s.flow[2 * i + 1]);
        if nb.iter().any(|&j| s.holes[j] != 0) {
            c.holes += 1;
        }
        let label = s.mask1[i];
        if !nb.iter().any(|&j| s.mask2[j] == label) {
            c.label += 1;
            continue;
        }
        let agrees = |j: usize| {
            let d = s.depth2[j];
            s.mask2[j] == label && d > 0.0 && z <= d * tol && d <= z * tol
        };
        if !nb.iter().any(|&j| agrees(j)) {
            c.depth += 1;
        }
    }
    c
}

/// Bilinear sample of channel `ch` of an interleaved u8 RGB image at `(x, y)` (inside the
/// frame), in 0..1.
fn bilinear(img: &[u8], w: usize, h: usize, x: f32, y: f32, ch: usize) -> f32 {
    let x = x.clamp(0.0, (w - 1) as f32);
    let y = y.clamp(0.0, (h - 1) as f32);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let g = Grid::new(w, h);
    let v = |xx: usize, yy: usize| f32::from(img[3 * g.index(xx, yy) + ch]) / 255.0;
    let top = v(x0, y0) * (1.0 - fx) + v(x1, y0) * fx;
    let bottom = v(x0, y1) * (1.0 - fx) + v(x1, y1) * fx;
    top * (1.0 - fy) + bottom * fy
}

/// Sum of `|img1(p) - img2(p + flow(p))|` (mean over the 3 channels, 0..1 units, image2 sampled
/// bilinearly) over the valid, non-occluded pixels (with `label`: only those whose `mask1` is
/// `label`), and their number.
pub fn photometric_error(s: &Sample, label: Option<u8>) -> (f64, u64) {
    let (w, h) = (s.width, s.height);
    let (mut sum, mut count) = (0.0f64, 0u64);
    for i in 0..w * h {
        if s.valid[i] == 0 || s.occlusion[i] != 0 || label.is_some_and(|l| s.mask1[i] != l) {
            continue;
        }
        let (tx, ty) = ((i % w) as f32 + s.flow[2 * i], (i / w) as f32 + s.flow[2 * i + 1]);
        let e: f32 = (0..3)
            .map(|c| (f32::from(s.image1[3 * i + c]) / 255.0 - bilinear(&s.image2, w, h, tx, ty, c)).abs())
            .sum::<f32>()
            / 3.0;
        sum += f64::from(e);
        count += 1;
    }
    (sum, count)
}

/// Smallest step (0..255 luminance) that makes a pixel a thin-line pixel.
pub const THIN_LINE_STEP: f32 = 24.0;
/// Shortest run that counts as a thin line, in pixels.
pub const THIN_LINE_MIN_RUN: usize = 6;

/// Horizontal thin-line runs in an interleaved u8 RGB image: runs of at least
/// [`THIN_LINE_MIN_RUN`] consecutive pixels of one row whose luminance differs from both the
/// row above and the row below by more than [`THIN_LINE_STEP`] in the same direction, while
/// those two rows agree within half that step (a one-pixel-high line across a surface).
pub fn thin_line_runs(img: &[u8], w: usize, h: usize) -> usize {
    let g = Grid::new(w, h);
    let lum = |x: usize, y: usize| {
        let o = 3 * g.index(x, y);
        0.299 * f32::from(img[o]) + 0.587 * f32::from(img[o + 1]) + 0.114 * f32::from(img[o + 2])
    };
    let mut runs = 0;
    for y in 1..h.saturating_sub(1) {
        let mut run = 0;
        for x in 0..=w {
            let line = x < w && {
                let (a, c, b) = (lum(x, y - 1), lum(x, y), lum(x, y + 1));
                let (da, db) = (c - a, c - b);
                da.abs() > THIN_LINE_STEP
                    && db.abs() > THIN_LINE_STEP
                    && da * db > 0.0
                    && (a - b).abs() < 0.5 * THIN_LINE_STEP
            };
            if line {
                run += 1;
            } else {
                if run >= THIN_LINE_MIN_RUN {
                    runs += 1;
                }
                run = 0;
            }
        }
    }
    runs
}

/// The sharpness ratio of a sample: [`laplacian_variance`] of image2 over the pixels that are not
/// holes (rendered, not 2-D inpainted) divided by that of image1 over its valid pixels (those
/// that stay in view). 1 for a reconstruction that keeps every detail; a low-pass kernel gives
/// less. `None` when either region is (nearly) empty or image1 is flat.
pub fn sharpness_ratio(s: &Sample) -> Option<f64> {
    let (w, h) = (s.width, s.height);
    let v1 = laplacian_variance(&s.image1, w, h, |i| s.valid[i] != 0)?;
    let v2 = laplacian_variance(&s.image2, w, h, |i| s.holes[i] == 0)?;
    (v1 > 0.0).then(|| v2 / v1)
}

pub use crate::sample::noise::noise_sigma;

/// The sharpness ratios, over the same pixels, of image1 warped *ideally* by the sample's geometry
/// and of image2 itself: `(ideal, image2)`, each the [`laplacian_variance`] over the image2 pixels
/// whose backward flow is valid, whose point image1 sees (backward occlusion 0) and that are not
/// holes, divided by image1's over its valid pixels (as [`sharpness_ratio`]). Where image1 does
/// not see the point (what the motion reveals), image1 warped by the geometry shows the occluder,
/// not the point, so there is no ideal to compare with: the revealed region's detail is
/// [`crate::bench::realism::RevealedDetail`]'s. The ideal warp samples image1's quintic B-spline
/// ([`crate::render::resample::SplineImage`]) at `q + backward_flow(q)`: what a high-order
/// reconstruction of the photo by the same geometry keeps, so the gap between the two is the
/// render's own loss (its kernel, the planes' blend) and `1 - ideal` is the geometry's
/// (magnification). Needs the backward fields (`None` without them or when a region is empty).
pub fn ideal_warp_sharpness(s: &Sample) -> Option<(f64, f64)> {
    let (w, h) = (s.width, s.height);
    let ideal = ideal_warp(s)?;
    let bw = &s.backward;
    let v1 = laplacian_variance(&s.image1, w, h, |i| s.valid[i] != 0)?;
    let seen = |i: usize| bw.occlusion.get(i).is_none_or(|&o| o == 0);
    let region = |i: usize| bw.valid[i] != 0 && seen(i) && s.holes[i] == 0;
    let vi = laplacian_variance(&ideal, w, h, region)?;
    let v2 = laplacian_variance(&s.image2, w, h, region)?;
    (v1 > 0.0).then(|| (vi / v1, v2 / v1))
}

/// The noise estimates ([`noise_sigma`]) of a sample's image1 over its valid pixels and image2
/// over its pixels that are not holes (the regions of [`sharpness_ratio`]).
pub fn noise_pair(s: &Sample) -> Option<(f64, f64)> {
    let (w, h) = (s.width, s.height);
    let n1 = noise_sigma(&s.image1, w, h, |i| s.valid[i] != 0)?;
    let n2 = noise_sigma(&s.image2, w, h, |i| s.holes[i] == 0)?;
    Some((n1, n2))
}

/// The `q` quantile (0..1, nearest rank) of sorted values; 0 when empty.
fn quantile(sorted: &[f32], q: f64) -> f32 {
    if sorted.is_empty() {
        return 0.0;
    }
    let k = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[k.min(sorted.len() - 1)]
}

/// The quality figures over a set of samples.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct QualityReport {
    pub samples: usize,
    /// Samples with at least one moved object.
    pub with_objects: usize,
    /// Mean photometric error over the valid, non-occluded pixels (0..1).
    pub photometric: f64,
    /// Mean photometric error over the valid, non-occluded background pixels (`mask1 = 0`).
    pub photometric_background: f64,
    pub laws: LawCounts,
    /// Fraction of image2 pixels filled by 2-D inpainting.
    pub hole_fraction: f64,
    /// Thin-line runs in image2 and in image1, summed over the samples.
    pub lines2: usize,
    pub lines1: usize,
    pub valid_fraction: f64,
    /// Valid and occluded pixels, as a fraction of all pixels.
    pub occluded_fraction: f64,
    /// Flow magnitude percentiles (p5, p50, p95, p99) and the largest magnitude over valid
    /// pixels, in pixels.
    pub flow_p5: f32,
    pub flow_p50: f32,
    pub flow_p95: f32,
    pub flow_p99: f32,
    pub flow_max: f32,
    /// Fraction of valid pixels moving less than 1 px.
    pub below_1px: f64,
    /// The sharpness ratio ([`sharpness_ratio`]): mean, smallest and largest over the samples
    /// (0 when no sample has one).
    pub sharpness: f64,
    pub sharpness_min: f64,
    pub sharpness_max: f64,
    /// Mean noise estimates ([`noise_pair`]) of image1 and image2, 8-bit levels (0 when no
    /// sample has one).
    pub noise1: f64,
    pub noise2: f64,
    /// Means over the samples with backward fields of [`ideal_warp_sharpness`]: image1 warped
    /// ideally, and image2 over the same pixels (0 when no sample has them).
    pub ideal_sharpness: f64,
    pub ideal_image2_sharpness: f64,
    /// The realism figures ([`crate::bench::realism`]): patch classifiers, revealed regions,
    /// forward-backward residual.
    pub realism: RealismReport,
}

/// Accumulates [`QualityReport`] over samples.
#[derive(Default)]
pub struct QualityAccumulator {
    report: QualityReport,
    photo: (f64, u64),
    photo_bg: (f64, u64),
    pixels: u64,
    valid: u64,
    occluded: u64,
    holes: u64,
    magnitudes: Vec<f32>,
    sharpness: Vec<f64>,
    noise: Vec<(f64, f64)>,
    ideal: Vec<(f64, f64)>,
    realism: RealismAccumulator,
}

impl QualityAccumulator {
    /// Adds a sample and its target depth ([`crate::sample::recipe::assemble_with_target_depth`]).
    pub fn add(&mut self, s: &Sample, target_depth: &[f32]) {
        let r = &mut self.report;
        r.samples += 1;
        r.with_objects += usize::from(!s.objects.is_empty());
        r.laws.add(&label_laws(s, target_depth));
        let (sum, n) = photometric_error(s, None);
        self.photo.0 += sum;
        self.photo.1 += n;
        let (sum, n) = photometric_error(s, Some(0));
        self.photo_bg.0 += sum;
        self.photo_bg.1 += n;
        r.lines2 += thin_line_runs(&s.image2, s.width, s.height);
        r.lines1 += thin_line_runs(&s.image1, s.width, s.height);
        self.sharpness.extend(sharpness_ratio(s));
        self.noise.extend(noise_pair(s));
        self.ideal.extend(ideal_warp_sharpness(s));
        self.realism.add(s);
        let n = (s.width * s.height) as u64;
        self.pixels += n;
        self.holes += s.holes.iter().filter(|&&v| v != 0).count() as u64;
        for i in 0..s.width * s.height {
            if s.valid[i] != 0 {
                self.valid += 1;
                self.occluded += u64::from(s.occlusion[i] != 0);
                self.magnitudes.push(s.flow[2 * i].hypot(s.flow[2 * i + 1]));
            }
        }
    }

    pub fn finish(mut self) -> QualityReport {
        let frac = |a: u64, b: u64| if b == 0 { 0.0 } else { a as f64 / b as f64 };
        let r = &mut self.report;
        let mean = |(sum, n): (f64, u64)| if n == 0 { 0.0 } else { sum / n as f64 };
        r.photometric = mean(self.photo);
        r.photometric_background = mean(self.photo_bg);
        r.hole_fraction = frac(self.holes, self.pixels);
        r.valid_fraction = frac(self.valid, self.pixels);
        r.occluded_fraction = frac(self.occluded, self.pixels);
        self.magnitudes.sort_by(f32::total_cmp);
        r.flow_p5 = quantile(&self.magnitudes, 0.05);
        r.flow_p50 = quantile(&self.magnitudes, 0.5);
        r.flow_p95 = quantile(&self.magnitudes, 0.95);
        r.flow_p99 = quantile(&self.magnitudes, 0.99);
        r.flow_max = self.magnitudes.last().copied().unwrap_or(0.0);
        let below = self.magnitudes.partition_point(|&m| m < 1.0);
        r.below_1px = frac(below as u64, self.magnitudes.len() as u64);
        if !self.sharpness.is_empty() {
            r.sharpness = self.sharpness.iter().sum::<f64>() / self.sharpness.len() as f64;
            r.sharpness_min = self.sharpness.iter().copied().fold(f64::INFINITY, f64::min);
            r.sharpness_max = self.sharpness.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        }
        if !self.ideal.is_empty() {
            let k = self.ideal.len() as f64;
            r.ideal_sharpness = self.ideal.iter().map(|v| v.0).sum::<f64>() / k;
            r.ideal_image2_sharpness = self.ideal.iter().map(|v| v.1).sum::<f64>() / k;
        }
        if !self.noise.is_empty() {
            let k = self.noise.len() as f64;
            r.noise1 = self.noise.iter().map(|n| n.0).sum::<f64>() / k;
            r.noise2 = self.noise.iter().map(|n| n.1).sum::<f64>() / k;
        }
        r.realism = self.realism.finish();
        self.report
    }
}

/// The quality report of samples `0..count` (seed `seed`) of `generator`'s items under
/// `config` (the generator's scenes and cache, another configuration).
pub fn quality(
    generator: &Generator,
    config: &SampleConfig,
    seed: u64,
    count: u64,
) -> Result<QualityReport, SampleError> {
    let g = generator.with_config(config.clone())?;
    let mut acc = QualityAccumulator::default();
    for index in 0..count {
        let (s, z) = g.sample_with_target_depth(seed, index)?;
        acc.add(&s, &z);
    }
    Ok(acc.finish())
}

/// [`quality`] at the addresses of `generator`'s own fingerprint instead of `config`'s: every
/// configuration that differs from the generator's only in how it renders (the colour kernel,
/// skipping, the merge) then draws the same motions, so a table of kernels compares them on the
/// same samples, not on different draws. (Not a dataset of its own: these addresses belong to
/// the generator's configuration.)
pub fn quality_same_motions(
    generator: &Generator,
    config: &SampleConfig,
    seed: u64,
    count: u64,
) -> Result<QualityReport, SampleError> {
    quality_on_motions(generator, config, generator.fingerprint(), seed, count)
}

/// [`quality_same_motions`] on the motions of the addresses `(dataset, seed, 0..count)`: two
/// collections of the same photos (scenes built with other models) compared on the same draws.
pub fn quality_on_motions(
    generator: &Generator,
    config: &SampleConfig,
    dataset: u64,
    seed: u64,
    count: u64,
) -> Result<QualityReport, SampleError> {
    let g = generator.with_config(config.clone())?;
    let mut acc = QualityAccumulator::default();
    for index in 0..count {
        let item = g.source_item(index).ok_or(SampleError::EmptySource)?;
        let scene = g.scene(item)?;
        let address = SampleAddress { dataset, seed, index };
        let (s, z) = assemble_with_target_depth(&scene, address, config, None)?;
        acc.add(&s, &z);
    }
    Ok(acc.finish())
}
