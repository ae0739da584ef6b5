//! The draw of one sample's augmentation from its own random stream: the colour jitter, the
//! eraser's boxes, and the spatial map ([`Axis`], one affine map per axis from an output pixel to
//! a source coordinate), in a fixed order and count whatever the parameters.

#[allow(unused_imports)]
use super::*;

/// One ColorJitter draw: the order of the four operations (0 brightness, 1 contrast,
/// 2 saturation, 3 hue) and their factors.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Jitter {
    pub order: [u8; 4],
    pub brightness: f64,
    pub contrast: f64,
    pub saturation: f64,
    pub hue: f64,
}

impl Jitter {
    pub(super) fn is_identity(&self) -> bool {
        self.brightness == 1.0 && self.contrast == 1.0 && self.saturation == 1.0 && self.hue == 0.0
    }
}

/// An eraser box on image2 (clipped to the frame when applied).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct EraserBox {
    pub x: u32,
    pub y: u32,
    pub w: u32,
    pub h: u32,
}

/// One axis of the spatial map: `src` pixels resized to `resized`, mirrored or not, cut to `out`
/// pixels from `offset`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct Axis {
    pub src: usize,
    pub resized: usize,
    pub flip: bool,
    pub offset: usize,
    pub out: usize,
}

impl Axis {
    /// The identity of an `n`-pixel axis.
    pub fn identity(n: usize) -> Self {
        Axis { src: n, resized: n, flip: false, offset: 0, out: n }
    }

    /// The resized frame's pixel of output pixel `i` (before the flip).
    fn resized_of(self, i: usize) -> usize {
        let r = self.offset + i;
        if self.flip {
            self.resized - 1 - r
        } else {
            r
        }
    }

    /// The source coordinate of output pixel `i`.
    pub fn source(self, i: usize) -> f64 {
        (self.resized_of(i) as f64 + 0.5) * self.src as f64 / self.resized as f64 - 0.5
    }

    /// The output coordinate of source coordinate `s` (the inverse of [`Axis::source`]).
    pub fn forward(self, s: f64) -> f64 {
        let r = (s + 0.5) * self.resized as f64 / self.src as f64 - 0.5;
        let r = if self.flip { (self.resized - 1) as f64 - r } else { r };
        r - self.offset as f64
    }

    /// d(output) / d(source): what a displacement along this axis is multiplied by.
    pub fn slope(self) -> f64 {
        let s = self.resized as f64 / self.src as f64;
        if self.flip {
            -s
        } else {
            s
        }
    }

    /// Bilinear taps `(i0, i1, weight of i1)` of every output pixel (edges clamped).
    pub(super) fn taps(self) -> Vec<(usize, usize, f32)> {
        let last = self.src - 1;
        (0..self.out)
            .map(|i| {
                let s = self.source(i).clamp(0.0, last as f64);
                let i0 = s.floor() as usize;
                (i0, (i0 + 1).min(last), (s - i0 as f64) as f32)
            })
            .collect()
    }

    /// The nearest source pixel of every output pixel (`floor((r + 0.5) src / resized)`).
    pub(super) fn nearest(self) -> Vec<usize> {
        (0..self.out)
            .map(|i| {
                let r = self.resized_of(i);
                (((r as f64 + 0.5) * self.src as f64 / self.resized as f64).floor() as usize).min(self.src - 1)
            })
            .collect()
    }

    /// The output pixel a source pixel lands on under the sparse rule (the nearest resized
    /// pixel, mirrored, cut), if inside.
    pub(super) fn scatter(self, p: usize) -> Option<usize> {
        let r = ((p as f64 + 0.5) * self.resized as f64 / self.src as f64 - 0.5).round_ties_even();
        if r < 0.0 || r >= self.resized as f64 {
            return None;
        }
        let r = r as usize;
        let r = if self.flip { self.resized - 1 - r } else { r };
        r.checked_sub(self.offset).filter(|&x| x < self.out)
    }
}

/// Everything drawn for one sample.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    pub asymmetric: bool,
    /// The jitter of both images (or of image1 when asymmetric), and of image2 when asymmetric.
    pub jitter: [Jitter; 2],
    /// Whether the colour jitter is applied at all (any factor range non-empty).
    pub color: bool,
    pub eraser: Vec<EraserBox>,
    /// Whether the resize was drawn (`spatial_prob`); the frame may still be resized to fit
    /// the crop.
    pub spatial: bool,
    pub x: Axis,
    pub y: Axis,
    pub sparse: bool,
}

pub(super) fn factor(rng: &mut SampleRng, spread: f64) -> f64 {
    let f = rng.uniform((1.0 - spread).max(0.0), 1.0 + spread);
    if spread == 0.0 {
        1.0
    } else {
        f
    }
}

pub(super) fn jitter(rng: &mut SampleRng, p: &AugmentParams) -> Jitter {
    let mut order = [0u8, 1, 2, 3];
    for i in (1..4).rev() {
        let j = rng.below(i as u64 + 1) as usize;
        order.swap(i, j);
    }
    let brightness = factor(rng, p.brightness);
    let contrast = factor(rng, p.contrast);
    let saturation = factor(rng, p.saturation);
    let hue = rng.uniform(-p.hue, p.hue);
    Jitter { order, brightness, contrast, saturation, hue: if p.hue == 0.0 { 0.0 } else { hue } }
}

/// The draws of one sample, in a fixed order and count: the asymmetry word, two jitters (3 words
/// of order, 4 factors each), the eraser word, its box count and `MAX_ERASER_BOXES` boxes of 4
/// words, the scale, the stretch word and two stretches, the resize word, two flip words and two
/// crop words.
pub fn draw(p: &AugmentParams, address: SampleAddress, w: usize, h: usize) -> Plan {
    let mut rng = SampleRng::new(address.dataset, address.seed, address.index, Purpose::Other(AUGMENT_PURPOSE));
    let (w, h) = (w.max(1), h.max(1));
    // colour
    let asymmetric = rng.unit() < p.asymmetric_color_prob && !p.sparse;
    let jitter = [jitter(&mut rng, p), jitter(&mut rng, p)];
    let color = p.brightness > 0.0 || p.contrast > 0.0 || p.saturation > 0.0 || p.hue > 0.0;
    // eraser
    let erase = rng.unit() < p.eraser_prob;
    let n = 1 + rng.below(u64::from(p.eraser_boxes)) as usize;
    let mut eraser = Vec::new();
    for k in 0..MAX_ERASER_BOXES as usize {
        let x = rng.below(w as u64) as u32;
        let y = rng.below(h as u64) as u32;
        let span = u64::from(p.eraser_max - p.eraser_min);
        let bw = p.eraser_min + rng.below(span) as u32;
        let bh = p.eraser_min + rng.below(span) as u32;
        if erase && k < n {
            eraser.push(EraserBox { x, y, w: bw, h: bh });
        }
    }
    // spatial
    let scale = rng.uniform(p.min_scale, p.max_scale).exp2();
    let stretched = rng.unit() < p.stretch_prob && !p.sparse;
    let (ax, ay) = (rng.uniform(-p.max_stretch, p.max_stretch), rng.uniform(-p.max_stretch, p.max_stretch));
    let spatial = rng.unit() < p.spatial_prob;
    let hflip = rng.unit() < p.h_flip_prob;
    let vflip = rng.unit() < p.v_flip_prob && !p.sparse;
    let (cx_word, cy_word) = (rng.next_word(), rng.next_word());
    // RAFT: the scale is clipped so that the frame exceeds the crop by 8 px (1 px, sparse)
    let margin = if p.sparse { 1.0 } else { 8.0 };
    let fit =
        p.crop.map_or(0.0, |(cw, ch)| ((f64::from(ch) + margin) / h as f64).max((f64::from(cw) + margin) / w as f64));
    let (mut sx, mut sy) = (scale, scale);
    if stretched {
        sx *= ax.exp2();
        sy *= ay.exp2();
    }
    let (sx, sy) = if spatial {
        (sx.max(fit), sy.max(fit))
    } else if p.crop.is_some_and(|(cw, ch)| cw as usize > w || ch as usize > h) {
        // not resized by RAFT (which would then fail): brought up to the crop
        (fit, fit)
    } else {
        (1.0, 1.0)
    };
    let size = |n: usize, s: f64| ((n as f64 * s).round() as usize).max(1);
    let (rw, rh) = (size(w, sx), size(h, sy));
    let (cw, ch) = p.crop.map_or((rw, rh), |(cw, ch)| (cw as usize, ch as usize));
    let (cw, ch) = (cw.min(rw), ch.min(rh));
    // RAFT's crop: randint(0, W' - cw) (dense); with margins clipped back into the frame (sparse)
    let below = |word: u64, n: usize| -> usize { ((u128::from(word) * n as u128) >> 64) as usize };
    let (x0, y0) = if p.sparse {
        let x = below(cx_word, rw - cw + 100) as i64 - 50;
        let y = below(cy_word, rh - ch + 20) as i64;
        (x.clamp(0, (rw - cw) as i64) as usize, y.clamp(0, (rh - ch) as i64) as usize)
    } else {
        (below(cx_word, (rw - cw).max(1)), below(cy_word, (rh - ch).max(1)))
    };
    Plan {
        asymmetric,
        jitter,
        color,
        eraser,
        spatial,
        x: Axis { src: w, resized: rw, flip: hflip, offset: x0, out: cw },
        y: Axis { src: h, resized: rh, flip: vflip, offset: y0, out: ch },
        sparse: p.sparse,
    }
}
