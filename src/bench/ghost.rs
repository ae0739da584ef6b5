//! Object colour in what a moved object uncovers: a colour classifier learnt on image1's moved
//! objects against a ring of background around them, applied to image2's revealed background,
//! so that ghosts of the object (contours, fringes, fills drawn from its colours) show up as a
//! number.
//!
//! # The classifier
//!
//! Per sample with a moved object: the **object** pixels are image1's `mask1 != 0`; the **ring**
//! is image1's background (`mask1 = 0`) within [`RING_OUTER`] pixels (Chebyshev) of the object
//! and farther than [`RING_INNER`] from it (the object's own fringe, where the mask is uncertain,
//! belongs to neither class). Colours are quantised to [`LEVELS`] levels per channel; each class
//! gets a histogram of the pixels of its training half (a fixed hash of the pixel's index,
//! lowest bit), and a colour is the object's when its smoothed frequency among the object's
//! pixels exceeds that among the ring's (equal priors, add-one smoothing; a colour neither class
//! shows in training is background).
//!
//! The figure is the share of image2's revealed background pixels (revealed as
//! the realism measures' `revealed`, `mask2 = 0`) classified as object, next to the share of the
//! ring's held-out half classified as object: what the classifier calls object in true
//! background of the same photo. Their difference is the object colour the revealed region
//! carries beyond what the background around the object already has. Counts are pooled over the
//! samples.

use crate::raster::morph::dilate;
use crate::rng::mix64;
use crate::sample::Sample;

/// Quantisation levels per colour channel.
pub const LEVELS: usize = 16;
/// The ring's inner distance from the object (pixels, exclusive): the fringe left out.
pub const RING_INNER: usize = 3;
/// The ring's outer distance from the object (pixels, inclusive).
pub const RING_OUTER: usize = 16;
/// The fixed key of the train / held-out split of the ring's pixels.
const SPLIT_SEED: u64 = 0x6768_6f73_7443_6f6c;

/// Pixels of two regions classified as object colour, pooled over samples.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ObjectColour {
    /// Revealed background pixels of image2 counted, and those classified as object.
    pub revealed: (u64, u64),
    /// Held-out ring pixels of image1 counted, and those classified as object.
    pub ring: (u64, u64),
}

impl ObjectColour {
    /// The share of revealed background pixels classified as object; `None` without any.
    pub fn revealed_share(&self) -> Option<f64> {
        share(self.revealed)
    }

    /// The share of held-out ring pixels classified as object; `None` without any.
    pub fn ring_share(&self) -> Option<f64> {
        share(self.ring)
    }

    /// [`Self::revealed_share`] minus [`Self::ring_share`]: the object colour revealed beyond
    /// what true background scores.
    pub fn excess(&self) -> Option<f64> {
        Some(self.revealed_share()? - self.ring_share()?)
    }

    /// Adds another count.
    pub fn add(&mut self, o: &ObjectColour) {
        self.revealed.0 += o.revealed.0;
        self.revealed.1 += o.revealed.1;
        self.ring.0 += o.ring.0;
        self.ring.1 += o.ring.1;
    }
}

fn share((n, k): (u64, u64)) -> Option<f64> {
    (n > 0).then(|| k as f64 / n as f64)
}

/// The histogram bin of pixel `i` of an interleaved u8 RGB image.
fn bin(img: &[u8], i: usize) -> usize {
    let q = |v: u8| usize::from(v) * LEVELS / 256;
    (q(img[3 * i]) * LEVELS + q(img[3 * i + 1])) * LEVELS + q(img[3 * i + 2])
}

/// Whether pixel `i` belongs to the training half.
fn training(i: usize) -> bool {
    mix64(i as u64 ^ SPLIT_SEED) & 1 == 0
}

/// The object-colour counts of one sample, `rev` the revealed pixels; `None`
/// without a moved object or without ring pixels.
pub fn object_colour(s: &Sample, rev: &[bool]) -> Option<ObjectColour> {
    let frames = Frames { width: s.width, height: s.height, image1: &s.image1, mask1: &s.mask1, image2: &s.image2 };
    classify(&frames, |i| rev[i] && s.mask2[i] == 0)
}

/// The two images of a sample that the classifier reads.
pub struct Frames<'a> {
    pub width: usize,
    pub height: usize,
    /// image1, interleaved RGB8.
    pub image1: &'a [u8],
    /// image1's labels of the moved objects (0 = background).
    pub mask1: &'a [u8],
    /// image2, interleaved RGB8.
    pub image2: &'a [u8],
}

/// [`object_colour`] on the pixels of image2 where `revealed` holds.
pub fn classify(f: &Frames<'_>, revealed: impl Fn(usize) -> bool) -> Option<ObjectColour> {
    let (w, h) = (f.width, f.height);
    let object: Vec<bool> = f.mask1.iter().map(|&m| m != 0).collect();
    if !object.iter().any(|&o| o) {
        return None;
    }
    let inner = dilate(w, h, &object, RING_INNER);
    let outer = dilate(w, h, &object, RING_OUTER);
    let ring = |i: usize| outer[i] && !inner[i];
    let bins = LEVELS * LEVELS * LEVELS;
    let (mut obj, mut bg) = (vec![0u32; bins], vec![0u32; bins]);
    let (mut n_obj, mut n_bg) = (0u64, 0u64);
    for i in (0..w * h).filter(|&i| training(i)) {
        if object[i] {
            obj[bin(f.image1, i)] += 1;
            n_obj += 1;
        } else if ring(i) {
            bg[bin(f.image1, i)] += 1;
            n_bg += 1;
        }
    }
    if n_obj == 0 || n_bg == 0 {
        return None;
    }
    // add-one smoothing over the bins; compared as (a + 1) / (N_a + B) > (b + 1) / (N_b + B)
    let (za, zb) = ((n_obj + bins as u64) as f64, (n_bg + bins as u64) as f64);
    let is_object = |b: usize| {
        let (a, c) = (obj[b], bg[b]);
        (a > 0 || c > 0) && f64::from(a + 1) / za > f64::from(c + 1) / zb
    };
    let mut out = ObjectColour::default();
    for i in 0..w * h {
        if revealed(i) {
            out.revealed.0 += 1;
            out.revealed.1 += u64::from(is_object(bin(f.image2, i)));
        }
        if ring(i) && !training(i) {
            out.ring.0 += 1;
            out.ring.1 += u64::from(is_object(bin(f.image1, i)));
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantised_bins_cover_the_cube() {
        let img = [0u8, 0, 0, 255, 255, 255, 16, 0, 0];
        assert_eq!(bin(&img, 0), 0);
        assert_eq!(bin(&img, 1), LEVELS * LEVELS * LEVELS - 1);
        assert_eq!(bin(&img, 2), LEVELS * LEVELS);
    }

    /// A red square on green with some grey noise; image2 paints `ghost` of the revealed
    /// column band red.
    fn scene(ghost: usize) -> (Vec<u8>, Vec<u8>, Vec<u8>) {
        let (w, h) = (64, 48);
        let mut img1 = vec![0u8; 3 * w * h];
        let mut mask1 = vec![0u8; w * h];
        for i in 0..w * h {
            let (x, y) = (i % w, i / w);
            let n = (mix64(i as u64) % 24) as u8;
            let obj = (20..40).contains(&x) && (12..36).contains(&y);
            mask1[i] = u8::from(obj);
            let c = if obj { [200 + n, 20 + n, 20] } else { [30, 150 + n, 40 + n] };
            img1[3 * i..3 * i + 3].copy_from_slice(&c);
        }
        let mut img2 = img1.clone();
        for i in 0..w * h {
            let x = i % w;
            if (20..24).contains(&x) {
                let c = if (i / w) % 4 < ghost { [210, 30, 20] } else { [30, 160, 50] };
                img2[3 * i..3 * i + 3].copy_from_slice(&c);
            }
        }
        (img1, mask1, img2)
    }

    #[test]
    fn object_colour_in_the_revealed_band_is_counted_and_true_background_is_not() {
        let (w, h) = (64, 48);
        for (ghost, want) in [(0usize, 0.0f64), (2, 0.5), (4, 1.0)] {
            let (image1, mask1, image2) = scene(ghost);
            let f = Frames { width: w, height: h, image1: &image1, mask1: &mask1, image2: &image2 };
            let c = classify(&f, |i| (20..24).contains(&(i % w))).unwrap();
            assert_eq!(c.ring_share(), Some(0.0));
            assert!((c.excess().unwrap() - want).abs() < 1e-9, "{ghost}: {c:?}");
        }
        let none = vec![0u8; w * h];
        let (image1, _, image2) = scene(0);
        let f = Frames { width: w, height: h, image1: &image1, mask1: &none, image2: &image2 };
        assert_eq!(classify(&f, |_| true), None);
    }

    #[test]
    fn shares_and_excess() {
        let c = ObjectColour { revealed: (10, 4), ring: (20, 2) };
        assert_eq!(c.revealed_share(), Some(0.4));
        assert!((c.excess().unwrap() - 0.3).abs() < 1e-12);
        assert_eq!(ObjectColour::default().excess(), None);
    }
}
