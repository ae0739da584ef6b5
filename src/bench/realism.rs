//! The realism measures of `mpiflow bench quality`: a patch classifier that tries to tell
//! rendered patches from photo patches (its held-out AUC), the revealed region of image2 (what
//! no visible source pixel lands on) with its detail and noise against the rest of image2's
//! background, and the forward-backward residual of the flow.
//!
//! # The patch classifier
//!
//! A patch is a 16 x 16 block of the luminance on the grid `(16 i, 16 j)`. Its four features are
//! local detail statistics a flow network sees as well:
//!
//! 1. `ln(1 + var(L))`, the variance of the discrete Laplacian `4c - n - s - e - w` over the
//!    patch's interior (14 x 14);
//! 2. `ln(1 + mean |grad|^2)`, central differences over the interior;
//! 3. `ln(1 + sigma)`, Immerkaer's noise estimate (`|M * I|` with `M = [1 -2 1; -2 4 -2; 1 -2 1]`,
//!    mean absolute response times `sqrt(pi / 2) / 6`) over the interior;
//! 4. the high-frequency share `sum L^2 / (sum L^2 + 16 sum |grad|^2 + 1)`.
//!
//! Class 1 is the patches under test (image2's), class 0 the reference patches (image1's). Each
//! patch goes to the training or the held-out half by a fixed hash of its running number
//! (SplitMix64 of `n ^ SPLIT_SEED`, lowest bit), so the split is the same on every run. The
//! features are standardised with the training half's mean and deviation, and a logistic
//! regression (intercept and four weights, L2 penalty 1e-3, classes weighted to equal total
//! weight) is fitted by 400 steps of full-batch gradient descent with step 0.5 from zero. The
//! figure is the AUC on the held-out half (Mann-Whitney: the probability that a class-1 patch
//! scores above a class-0 patch, ties counting one half): 0.5 means the statistics cannot tell the
//! patches apart, 1.0 that they always can. With fewer than 8 held-out patches of either class
//! there is no figure (`None`).

use super::ghost::{object_colour, ObjectColour};
use super::measure::{ideal_warp, laplacian_variance, luminance};
use crate::raster::Grid;
use crate::rng::mix64;
use crate::sample::noise::noise_sigma;
use crate::sample::Sample;

/// Side of a classifier patch in pixels.
pub const PATCH: usize = 16;
/// Features per patch.
const FEATURES: usize = 4;
/// The fixed key of the train / held-out split.
const SPLIT_SEED: u64 = 0x6d70_6966_6c6f_7721;

/// The detail statistics of one patch (see the module documentation).
pub type Features = [f64; FEATURES];

/// The features of the patch of `img` (w x h x 3) whose top-left pixel is `(x0, y0)`.
pub fn patch_features(img: &[u8], w: usize, x0: usize, y0: usize) -> Features {
    let mut l = [[0.0f64; PATCH]; PATCH];
    for (dy, row) in l.iter_mut().enumerate() {
        for (dx, v) in row.iter_mut().enumerate() {
            *v = luminance(img, (y0 + dy) * w + x0 + dx);
        }
    }
    let (mut n, mut ls, mut lq, mut g2, mut noise) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for y in 1..PATCH - 1 {
        for x in 1..PATCH - 1 {
            let c = l[y][x];
            let lap = 4.0 * c - l[y - 1][x] - l[y + 1][x] - l[y][x - 1] - l[y][x + 1];
            let gx = 0.5 * (l[y][x + 1] - l[y][x - 1]);
            let gy = 0.5 * (l[y + 1][x] - l[y - 1][x]);
            let m = 4.0 * c - 2.0 * (l[y - 1][x] + l[y + 1][x] + l[y][x - 1] + l[y][x + 1])
                + l[y - 1][x - 1]
                + l[y - 1][x + 1]
                + l[y + 1][x - 1]
                + l[y + 1][x + 1];
            n += 1.0;
            ls += lap;
            lq += lap * lap;
            g2 += gx * gx + gy * gy;
            noise += m.abs();
        }
    }
    let var = (lq / n - (ls / n) * (ls / n)).max(0.0);
    let sigma = noise / n * (std::f64::consts::PI / 2.0).sqrt() / 6.0;
    [(1.0 + var).ln(), (1.0 + g2 / n).ln(), (1.0 + sigma).ln(), lq / (lq + 16.0 * g2 + 1.0)]
}

/// The features of every grid patch of `img` all of whose pixels satisfy `inside`.
pub fn patches(img: &[u8], w: usize, h: usize, inside: impl Fn(usize) -> bool) -> Vec<Features> {
    let mut out = Vec::new();
    for y0 in (0..h.saturating_sub(PATCH - 1)).step_by(PATCH) {
        for x0 in (0..w.saturating_sub(PATCH - 1)).step_by(PATCH) {
            let all = (0..PATCH).all(|dy| (0..PATCH).all(|dx| inside((y0 + dy) * w + x0 + dx)));
            if all {
                out.push(patch_features(img, w, x0, y0));
            }
        }
    }
    out
}

/// Patches of two classes for [`classifier_auc`].
#[derive(Clone, Debug, Default)]
pub struct PatchSet {
    /// Class 1: the patches under test.
    pub test: Vec<Features>,
    /// Class 0: the reference patches.
    pub reference: Vec<Features>,
}

/// The held-out AUC of the logistic regression of the module documentation on `set`.
pub fn classifier_auc(set: &PatchSet) -> Option<f64> {
    let mut train: Vec<(Features, bool)> = Vec::new();
    let mut held: Vec<(Features, bool)> = Vec::new();
    let all = set.test.iter().map(|f| (*f, true)).chain(set.reference.iter().map(|f| (*f, false)));
    for (n, item) in all.enumerate() {
        if mix64(n as u64 ^ SPLIT_SEED) & 1 == 0 {
            train.push(item);
        } else {
            held.push(item);
        }
    }
    let count = |v: &[(Features, bool)], c: bool| v.iter().filter(|x| x.1 == c).count();
    if count(&held, true) < 8 || count(&held, false) < 8 || count(&train, true) < 4 || count(&train, false) < 4 {
        return None;
    }
    // standardise with the training half
    let mut mean = [0.0; FEATURES];
    let mut dev = [0.0; FEATURES];
    for (f, _) in &train {
        for k in 0..FEATURES {
            mean[k] += f[k];
        }
    }
    mean.iter_mut().for_each(|m| *m /= train.len() as f64);
    for (f, _) in &train {
        for k in 0..FEATURES {
            dev[k] += (f[k] - mean[k]).powi(2);
        }
    }
    dev.iter_mut().for_each(|d| *d = (*d / train.len() as f64).sqrt().max(1e-9));
    let z = |f: &Features| -> Features { std::array::from_fn(|k| (f[k] - mean[k]) / dev[k]) };
    let xs: Vec<(Features, bool)> = train.iter().map(|(f, c)| (z(f), *c)).collect();
    let (n1, n0) = (count(&train, true) as f64, count(&train, false) as f64);
    let (w1, w0) = (0.5 / n1, 0.5 / n0);
    let mut beta = [0.0f64; FEATURES + 1];
    for _ in 0..400 {
        let mut grad = [0.0f64; FEATURES + 1];
        for (x, c) in &xs {
            let s = beta[0] + (0..FEATURES).map(|k| beta[k + 1] * x[k]).sum::<f64>();
            let p = 1.0 / (1.0 + (-s).exp());
            let (y, wt) = if *c { (1.0, w1) } else { (0.0, w0) };
            let e = wt * (p - y);
            grad[0] += e;
            for k in 0..FEATURES {
                grad[k + 1] += e * x[k];
            }
        }
        for k in 0..=FEATURES {
            let penalty = if k == 0 { 0.0 } else { 1e-3 * beta[k] };
            beta[k] -= 0.5 * (grad[k] + penalty);
        }
    }
    let score = |f: &Features| {
        let x = z(f);
        beta[0] + (0..FEATURES).map(|k| beta[k + 1] * x[k]).sum::<f64>()
    };
    let mut scored: Vec<(f64, bool)> = held.iter().map(|(f, c)| (score(f), *c)).collect();
    Some(auc(&mut scored))
}

/// Mann-Whitney AUC of scores with labels (true = class 1), ties counting one half.
pub fn auc(scored: &mut [(f64, bool)]) -> f64 {
    scored.sort_by(|a, b| a.0.total_cmp(&b.0));
    let n1 = scored.iter().filter(|s| s.1).count() as f64;
    let n0 = scored.len() as f64 - n1;
    if n1 == 0.0 || n0 == 0.0 {
        return 0.5;
    }
    // sum of the (average) ranks of class 1
    let mut rank_sum = 0.0;
    let mut i = 0;
    while i < scored.len() {
        let mut j = i;
        while j < scored.len() && scored[j].0 == scored[i].0 {
            j += 1;
        }
        let avg = (i + j + 1) as f64 / 2.0; // ranks i+1..=j
        rank_sum += avg * scored[i..j].iter().filter(|s| s.1).count() as f64;
        i = j;
    }
    (rank_sum - n1 * (n1 + 1.0) / 2.0) / (n1 * n0)
}

/// The revealed pixels of image2: in-frame target pixels that no valid, non-occluded source pixel
/// lands within one pixel of (its target `p + flow(p)` rounded, and the 8 neighbours of that
/// pixel). What image2 shows there was hidden or out of view in image1: the disocclusions of the
/// camera and of the moved objects, whatever filled them.
pub fn revealed(s: &Sample) -> Vec<bool> {
    let g = Grid::new(s.width, s.height);
    let mut reached = vec![false; g.len()];
    for i in 0..g.len() {
        if s.valid[i] == 0 || s.occlusion[i] != 0 {
            continue;
        }
        let (x, y) = g.xy(i);
        let tx = x as f32 + s.flow[2 * i];
        let ty = y as f32 + s.flow[2 * i + 1];
        if !(tx.is_finite() && ty.is_finite()) {
            continue;
        }
        let (cx, cy) = (tx.round() as i64, ty.round() as i64);
        for dy in -1..=1 {
            for dx in -1..=1 {
                if let Some(j) = g.at((cx + dx) as isize, (cy + dy) as isize) {
                    reached[j] = true;
                }
            }
        }
    }
    reached.into_iter().map(|r| !r).collect()
}

/// Per-sample realism figures (see [`RealismAccumulator`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RevealedDetail {
    /// Revealed pixels, as a fraction of the frame.
    pub share: f64,
    /// Laplacian variance of image2 over the revealed background pixels divided by that over the
    /// rest of image2's background (`mask2 = 0`, not revealed, not a hole).
    pub detail: Option<f64>,
    /// Noise estimates over the same two regions, divided.
    pub noise: Option<f64>,
}

/// The figures of [`RevealedDetail`] for one sample, `rev` from [`revealed`].
pub fn revealed_detail(s: &Sample, rev: &[bool]) -> RevealedDetail {
    let (w, h) = (s.width, s.height);
    let share = rev.iter().filter(|&&r| r).count() as f64 / (w * h) as f64;
    let in_rev = |i: usize| rev[i] && s.mask2[i] == 0;
    let other = |i: usize| !rev[i] && s.mask2[i] == 0 && s.holes[i] == 0;
    let lap = |f: &dyn Fn(usize) -> bool| laplacian_variance(&s.image2, w, h, f);
    let detail = match (lap(&in_rev), lap(&other)) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    };
    let noise = match (noise_sigma(&s.image2, w, h, in_rev), noise_sigma(&s.image2, w, h, other)) {
        (Some(a), Some(b)) if b > 0.0 => Some(a / b),
        _ => None,
    };
    RevealedDetail { share, detail, noise }
}

/// Spread (largest difference, either component) of the backward flow over a read's four
/// neighbours from which the read straddles a motion edge ([`forward_backward_residual`]).
pub const MOTION_EDGE_SPREAD: f32 = 1.0;

/// Sums of the forward-backward residual ([`forward_backward_residual`]), apart for the reads
/// that straddle a motion edge.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FbResidual {
    /// Sum and count over the reads whose four neighbours lie on one motion.
    pub sum: f64,
    pub n: u64,
    /// Sum and count over the reads that straddle a motion edge.
    pub edge_sum: f64,
    pub edge_n: u64,
}

impl FbResidual {
    fn add(&mut self, o: &FbResidual) {
        self.sum += o.sum;
        self.n += o.n;
        self.edge_sum += o.edge_sum;
        self.edge_n += o.edge_n;
    }
}

/// The forward-backward residual of a sample with backward fields: over valid, non-occluded
/// source pixels `p` (whose target `q = p + F(p)` has a valid backward flow at its bilinear
/// neighbours), `|F(p) + B(q)|` with `B` sampled bilinearly. A read whose four neighbours'
/// backward flows differ by more than [`MOTION_EDGE_SPREAD`] straddles a motion edge: a
/// neighbour shows another surface than `p`'s (the sampling of an edge, whatever the labels), so
/// those reads are summed apart. `None` without backward fields or when no pixel qualifies.
pub fn forward_backward_residual(s: &Sample) -> Option<FbResidual> {
    let (w, h) = (s.width, s.height);
    let b = &s.backward;
    if b.flow.len() != 2 * w * h || b.valid.len() != w * h || w < 2 || h < 2 {
        return None;
    }
    let mut out = FbResidual::default();
    for i in 0..w * h {
        if s.valid[i] == 0 || s.occlusion[i] != 0 {
            continue;
        }
        let (fx, fy) = (s.flow[2 * i], s.flow[2 * i + 1]);
        let (tx, ty) = ((i % w) as f32 + fx, (i / w) as f32 + fy);
        if !(tx >= 0.0 && ty >= 0.0 && tx <= (w - 1) as f32 && ty <= (h - 1) as f32) {
            continue;
        }
        let (x0, y0) = ((tx.floor() as usize).min(w - 2), (ty.floor() as usize).min(h - 2));
        let (ax, ay) = (tx - x0 as f32, ty - y0 as f32);
        let idx = [y0 * w + x0, y0 * w + x0 + 1, (y0 + 1) * w + x0, (y0 + 1) * w + x0 + 1];
        if idx.iter().any(|&j| b.valid[j] == 0) {
            continue;
        }
        let wts = [(1.0 - ax) * (1.0 - ay), ax * (1.0 - ay), (1.0 - ax) * ay, ax * ay];
        let (mut bx, mut by) = (0.0f32, 0.0f32);
        let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        for (j, wt) in idx.iter().zip(wts) {
            let f = [b.flow[2 * j], b.flow[2 * j + 1]];
            bx += wt * f[0];
            by += wt * f[1];
            for c in 0..2 {
                lo[c] = lo[c].min(f[c]);
                hi[c] = hi[c].max(f[c]);
            }
        }
        let r = f64::from((fx + bx).hypot(fy + by));
        if !r.is_finite() {
            continue;
        }
        if hi[0] - lo[0] > MOTION_EDGE_SPREAD || hi[1] - lo[1] > MOTION_EDGE_SPREAD {
            out.edge_sum += r;
            out.edge_n += 1;
        } else {
            out.sum += r;
            out.n += 1;
        }
    }
    (out.n + out.edge_n > 0).then_some(out)
}

/// Accumulates the realism figures over samples.
#[derive(Default)]
pub struct RealismAccumulator {
    /// image2 patches (not revealed, no hole, valid backward) against image1 patches (valid).
    pub pair: PatchSet,
    /// Revealed image2 background patches against image1 background patches.
    pub reveal: PatchSet,
    /// Patches of image1 warped ideally ([`ideal_warp`]) against image1 patches.
    pub ideal: PatchSet,
    shares: Vec<f64>,
    detail: Vec<f64>,
    noise: Vec<f64>,
    fb: FbResidual,
    colour: Option<ObjectColour>,
}

/// The realism figures over a set of samples.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RealismReport {
    /// AUC of the classifier telling image2 patches from image1 patches.
    pub auc_pair: Option<f64>,
    /// AUC of the classifier telling revealed image2 patches from image1 background patches.
    pub auc_revealed: Option<f64>,
    /// AUC of the classifier telling patches of image1 warped ideally by the sample's geometry
    /// ([`ideal_warp`]) from image1 patches: what an exact warp leaves for the
    /// classifier (magnification's loss of detail); `None` without the backward fields.
    pub auc_ideal: Option<f64>,
    /// Mean revealed share of image2.
    pub revealed: f64,
    /// Means of [`RevealedDetail::detail`] and [`RevealedDetail::noise`] over the samples that
    /// have them.
    pub revealed_detail: Option<f64>,
    pub revealed_noise: Option<f64>,
    /// Mean forward-backward residual in pixels ([`forward_backward_residual`]) over the reads
    /// that do not straddle a motion edge.
    pub fb_residual: Option<f64>,
    /// The reads that straddle a motion edge: their mean residual and their share of all reads.
    pub fb_edges: Option<FbEdges>,
    /// Object colour in the revealed background against the ring around the object
    /// ([`super::ghost`]), pooled over the samples with a moved object.
    pub object_colour: Option<ObjectColour>,
}

/// The forward-backward reads that straddle a motion edge ([`forward_backward_residual`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FbEdges {
    /// Mean residual in pixels.
    pub residual: f64,
    /// Share of all reads.
    pub share: f64,
}

/// The patches of a region covering at least half of each patch.
fn majority_patches(img: &[u8], w: usize, h: usize, region: impl Fn(usize) -> bool) -> Vec<Features> {
    let mut out = Vec::new();
    for y0 in (0..h.saturating_sub(PATCH - 1)).step_by(PATCH) {
        for x0 in (0..w.saturating_sub(PATCH - 1)).step_by(PATCH) {
            let n = (0..PATCH * PATCH).filter(|k| region((y0 + k / PATCH) * w + x0 + k % PATCH)).count();
            if 2 * n >= PATCH * PATCH {
                out.push(patch_features(img, w, x0, y0));
            }
        }
    }
    out
}

impl RealismAccumulator {
    pub fn add(&mut self, s: &Sample) {
        let (w, h) = (s.width, s.height);
        let rev = revealed(s);
        let has_backward = s.backward.valid.len() == w * h;
        self.pair.test.extend(patches(&s.image2, w, h, |i| {
            !rev[i] && s.holes[i] == 0 && (!has_backward || s.backward.valid[i] != 0)
        }));
        self.pair.reference.extend(patches(&s.image1, w, h, |i| s.valid[i] != 0));
        self.reveal.test.extend(majority_patches(&s.image2, w, h, |i| rev[i] && s.mask2[i] == 0));
        self.reveal.reference.extend(patches(&s.image1, w, h, |i| s.mask1[i] == 0));
        if let Some(ideal) = ideal_warp(s) {
            self.ideal.test.extend(patches(&ideal, w, h, |i| !rev[i] && s.holes[i] == 0 && s.backward.valid[i] != 0));
            self.ideal.reference.extend(patches(&s.image1, w, h, |i| s.valid[i] != 0));
        }
        if let Some(c) = object_colour(s, &rev) {
            self.colour.get_or_insert_with(ObjectColour::default).add(&c);
        }
        let d = revealed_detail(s, &rev);
        self.shares.push(d.share);
        self.detail.extend(d.detail);
        self.noise.extend(d.noise);
        if let Some(fb) = forward_backward_residual(s) {
            self.fb.add(&fb);
        }
    }

    pub fn finish(&self) -> RealismReport {
        let mean = |v: &[f64]| (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64);
        RealismReport {
            auc_pair: classifier_auc(&self.pair),
            auc_revealed: classifier_auc(&self.reveal),
            auc_ideal: classifier_auc(&self.ideal),
            revealed: mean(&self.shares).unwrap_or(0.0),
            revealed_detail: mean(&self.detail),
            revealed_noise: mean(&self.noise),
            fb_residual: (self.fb.n > 0).then(|| self.fb.sum / self.fb.n as f64),
            fb_edges: (self.fb.edge_n > 0).then(|| FbEdges {
                residual: self.fb.edge_sum / self.fb.edge_n as f64,
                share: self.fb.edge_n as f64 / (self.fb.n + self.fb.edge_n) as f64,
            }),
            object_colour: self.colour,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noise_image(w: usize, h: usize, amp: f64, key: u64) -> Vec<u8> {
        (0..3 * w * h)
            .map(|i| {
                let r = (mix64(i as u64 ^ key) >> 11) as f64 / (1u64 << 53) as f64;
                (128.0 + amp * (r - 0.5)).round().clamp(0.0, 255.0) as u8
            })
            .collect()
    }

    #[test]
    fn auc_is_the_rank_statistic() {
        let mut s = vec![(0.1, false), (0.3, true), (0.35, false), (0.8, true)];
        assert!((auc(&mut s) - 0.75).abs() < 1e-12);
        let mut all_above = vec![(0.0, false), (1.0, true)];
        assert_eq!(auc(&mut all_above), 1.0);
        let mut ties = vec![(1.0, false), (1.0, true)];
        assert_eq!(auc(&mut ties), 0.5);
    }

    #[test]
    fn the_classifier_separates_blur_from_noise_and_not_a_set_from_itself() {
        let (w, h) = (256, 256);
        let sharp = noise_image(w, h, 120.0, 1);
        let flat = noise_image(w, h, 8.0, 2);
        let a = patches(&sharp, w, h, |_| true);
        let b = patches(&flat, w, h, |_| true);
        assert_eq!(a.len(), 256);
        let apart = classifier_auc(&PatchSet { test: b.clone(), reference: a.clone() }).unwrap();
        assert!(apart > 0.95, "{apart}");
        let other = patches(&noise_image(w, h, 120.0, 3), w, h, |_| true);
        let same = classifier_auc(&PatchSet { test: other, reference: a }).unwrap();
        assert!((same - 0.5).abs() < 0.15, "{same}");
        assert_eq!(classifier_auc(&PatchSet { test: b[..3].to_vec(), reference: b.clone() }), None);
    }
}
