//! Training augmentation of finished samples (RAFT's `FlowAugmentor` and `SparseFlowAugmentor`),
//! deterministic by address: presets of RAFT's training stages, the JSON form of the parameters,
//! the draw of one sample's augmentation from its own random stream, and the transform of every
//! tensor of the sample (docs/augment.md).
//!
//! Order (RAFT's): colour jitter (both images as one stack, or each on its own with
//! `asymmetric_color_prob`), the eraser (boxes of image2 filled with its mean colour), then the
//! spatial part: a resize by `(sx, sy)`, flips, and the crop. The spatial part is one affine map
//! per axis from an output pixel to a source coordinate ([`Axis`]), evaluated only on the crop, so
//! its cost is that of the output, whatever the scale.
//!
//! Geometry (§3 of docs/design.md: pixel centres at integer coordinates). The resized frame is
//! `W' = round(w sx)` by `H' = round(h sy)`; output pixel `x` is resized pixel `r = x0 + x`
//! (mirrored to `W' - 1 - r` under a flip), which is source coordinate
//! `(r + 0.5) w / W' - 0.5` (OpenCV's INTER_LINEAR with its half-pixel centres). The map is affine
//! with slope `±W'/w`, so a correspondence `p -> p + f` of the sample becomes exactly
//! `x -> x + (±W'/w) f`: the flow is scaled by the frame's own ratio (and negated under a flip).
//! Images and the dense flow are interpolated bilinearly; `valid` stays 1 only where every
//! bilinear tap with a non-zero weight was valid (a flow interpolated from an invalid one is not
//! the flow of any point), and is cleared where the flow target leaves the output frame (the
//! crop's rule, [`clear_valid_outside`]). Under the sparse rule (`raft-kitti`), each valid vector is
//! moved to the output pixel nearest its mapped position (later source pixels in row-major order
//! win, as RAFT's scatter), scaled the same way; pixels nothing lands on are invalid. Every other
//! per-pixel field (occlusion, object masks, depths, any u8 label plane) follows the same map
//! with nearest neighbour. Colour jitter and the eraser touch only the images: never the flow.
//!
//! Determinism: every number comes from the sample's stream `Purpose::Other(AUGMENT_PURPOSE)`,
//! drawn in a fixed order and count whatever the parameters (see [`draw`]), so augmentation never
//! changes the draws of the unaugmented sample, and the same address with the same augmentation
//! gives the same bytes.

use serde::Serialize;

use super::{Sample, SampleAddress};
use crate::geometry::Intrinsics;
use crate::rng::{Purpose, SampleRng};

/// The random stream of a sample's augmentation: `Purpose::Other(AUGMENT_PURPOSE)`.
pub const AUGMENT_PURPOSE: u32 = 0x6175_676d; // "augm"

/// RAFT writes its hue ranges as `0.5 / 3.14` and `0.3 / 3.14`: that 3.14, not pi.
#[allow(clippy::approx_constant)]
const RAFT_PI: f64 = 3.14;

/// Most eraser boxes per sample.
pub const MAX_ERASER_BOXES: u32 = 16;

/// Largest crop side (the service checks its own, smaller, image-side limit).
pub const MAX_CROP_SIDE: u32 = 1 << 15;

/// A refused augmentation: `field` names what is wrong (`augment` for the whole text, or
/// `augment.<key>` for one key of the JSON form).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {reason}")]
pub struct AugmentError {
    pub field: &'static str,
    pub reason: String,
}

fn bad(field: &'static str, reason: impl Into<String>) -> AugmentError {
    AugmentError { field, reason: reason.into() }
}

/// Every parameter of an augmentation (RAFT's names; scales are log2, like RAFT's
/// `2 ** uniform(min_scale, max_scale)`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AugmentParams {
    /// Output `(width, height)`; `None` = the whole resized frame.
    pub crop: Option<(u32, u32)>,
    pub min_scale: f64,
    pub max_scale: f64,
    /// Probability of the resize (without it the frame keeps its size, unless it is smaller
    /// than the crop, when it is brought up to the crop as RAFT's scale clip would).
    pub spatial_prob: f64,
    /// Probability of an independent stretch of each axis by `2 ** uniform(-max_stretch,
    /// max_stretch)` (dense rule only; RAFT's sparse augmentor never stretches).
    pub stretch_prob: f64,
    pub max_stretch: f64,
    pub h_flip_prob: f64,
    pub v_flip_prob: f64,
    /// ColorJitter: factors drawn from `[max(0, 1 - b), 1 + b]` (brightness, contrast,
    /// saturation) and `[-hue, hue]` (hue, in turns), applied in a random order.
    pub brightness: f64,
    pub contrast: f64,
    pub saturation: f64,
    pub hue: f64,
    /// Probability that each image gets its own jitter (otherwise one jitter of both).
    pub asymmetric_color_prob: f64,
    /// Probability of the eraser: 1 to `eraser_boxes` boxes of sides in
    /// `[eraser_min, eraser_max)` on image2, filled with its mean colour.
    pub eraser_prob: f64,
    pub eraser_min: u32,
    pub eraser_max: u32,
    pub eraser_boxes: u32,
    /// RAFT's sparse rule (SparseFlowAugmentor): sparse flow resize, no stretch, no vertical
    /// flip, symmetric colour, the crop drawn with margins (50 px in x, 20 px in y).
    pub sparse: bool,
}

impl AugmentParams {
    /// Nothing: the identity (a base for the JSON form).
    pub const NONE: AugmentParams = AugmentParams {
        crop: None,
        min_scale: 0.0,
        max_scale: 0.0,
        spatial_prob: 0.0,
        stretch_prob: 0.0,
        max_stretch: 0.0,
        h_flip_prob: 0.0,
        v_flip_prob: 0.0,
        brightness: 0.0,
        contrast: 0.0,
        saturation: 0.0,
        hue: 0.0,
        asymmetric_color_prob: 0.0,
        eraser_prob: 0.0,
        eraser_min: 50,
        eraser_max: 100,
        eraser_boxes: 2,
        sparse: false,
    };

    /// RAFT's `FlowAugmentor(crop, min_scale, max_scale, do_flip=True)`.
    const fn raft_dense(crop: (u32, u32), min_scale: f64, max_scale: f64) -> Self {
        AugmentParams {
            crop: Some(crop),
            min_scale,
            max_scale,
            spatial_prob: 0.8,
            stretch_prob: 0.8,
            max_stretch: 0.2,
            h_flip_prob: 0.5,
            v_flip_prob: 0.1,
            brightness: 0.4,
            contrast: 0.4,
            saturation: 0.4,
            hue: 0.5 / RAFT_PI,
            asymmetric_color_prob: 0.2,
            eraser_prob: 0.5,
            eraser_min: 50,
            eraser_max: 100,
            eraser_boxes: 2,
            sparse: false,
        }
    }

    /// Checks every value; errors name the JSON key.
    pub fn validate(&self) -> Result<(), AugmentError> {
        let probs: [(&'static str, f64); 7] = [
            ("augment.spatial_prob", self.spatial_prob),
            ("augment.stretch_prob", self.stretch_prob),
            ("augment.h_flip_prob", self.h_flip_prob),
            ("augment.v_flip_prob", self.v_flip_prob),
            ("augment.asymmetric_color_prob", self.asymmetric_color_prob),
            ("augment.eraser_prob", self.eraser_prob),
            ("augment.hue", self.hue * 2.0),
        ];
        for (field, p) in probs {
            if !(0.0..=1.0).contains(&p) {
                let what = if field == "augment.hue" { "expected 0 to 0.5 (turns)" } else { "expected 0 to 1" };
                let v = if field == "augment.hue" { p / 2.0 } else { p };
                return Err(bad(field, format!("{v} ({what})")));
            }
        }
        for (field, v) in [("augment.min_scale", self.min_scale), ("augment.max_scale", self.max_scale)] {
            if !(-4.0..=4.0).contains(&v) {
                return Err(bad(field, format!("{v} (expected a log2 scale in -4 to 4)")));
            }
        }
        if self.min_scale > self.max_scale {
            return Err(bad("augment.min_scale", format!("{} is above max_scale {}", self.min_scale, self.max_scale)));
        }
        if !(0.0..=2.0).contains(&self.max_stretch) {
            return Err(bad("augment.max_stretch", format!("{} (expected 0 to 2)", self.max_stretch)));
        }
        for (field, v) in [
            ("augment.brightness", self.brightness),
            ("augment.contrast", self.contrast),
            ("augment.saturation", self.saturation),
        ] {
            if !(0.0..=10.0).contains(&v) {
                return Err(bad(field, format!("{v} (expected 0 to 10)")));
            }
        }
        if self.eraser_min == 0 || self.eraser_min >= self.eraser_max || self.eraser_max > MAX_CROP_SIDE {
            return Err(bad(
                "augment.eraser_min",
                format!(
                    "box sides [{}, {}) (expected 1 <= eraser_min < eraser_max <= {MAX_CROP_SIDE})",
                    self.eraser_min, self.eraser_max
                ),
            ));
        }
        if !(1..=MAX_ERASER_BOXES).contains(&self.eraser_boxes) {
            return Err(bad(
                "augment.eraser_boxes",
                format!("{} (expected 1 to {MAX_ERASER_BOXES})", self.eraser_boxes),
            ));
        }
        if let Some((w, h)) = self.crop {
            if w == 0 || h == 0 || w > MAX_CROP_SIDE || h > MAX_CROP_SIDE {
                return Err(bad("augment.crop", format!("{w}x{h} (expected sides 1 to {MAX_CROP_SIDE})")));
            }
        }
        Ok(())
    }
}

/// The named augmentations: RAFT's training stages (train.py's `image_size` and
/// `fetch_dataloader`'s `aug_params`) and the identity.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AugmentPreset {
    None,
    RaftChairs,
    RaftThings,
    RaftSintel,
    RaftKitti,
}

impl AugmentPreset {
    pub const ALL: [AugmentPreset; 5] = [
        AugmentPreset::None,
        AugmentPreset::RaftChairs,
        AugmentPreset::RaftThings,
        AugmentPreset::RaftSintel,
        AugmentPreset::RaftKitti,
    ];

    pub fn name(self) -> &'static str {
        match self {
            AugmentPreset::None => "none",
            AugmentPreset::RaftChairs => "raft-chairs",
            AugmentPreset::RaftThings => "raft-things",
            AugmentPreset::RaftSintel => "raft-sintel",
            AugmentPreset::RaftKitti => "raft-kitti",
        }
    }

    pub fn params(self) -> AugmentParams {
        match self {
            AugmentPreset::None => AugmentParams::NONE,
            // chairs: image_size 368 496, min_scale -0.1, max_scale 1.0, do_flip
            AugmentPreset::RaftChairs => AugmentParams::raft_dense((496, 368), -0.1, 1.0),
            // things: image_size 400 720, -0.4 .. 0.8
            AugmentPreset::RaftThings => AugmentParams::raft_dense((720, 400), -0.4, 0.8),
            // sintel: image_size 368 768, -0.2 .. 0.6
            AugmentPreset::RaftSintel => AugmentParams::raft_dense((768, 368), -0.2, 0.6),
            // kitti: image_size 288 960, -0.2 .. 0.4, do_flip False, SparseFlowAugmentor
            AugmentPreset::RaftKitti => AugmentParams {
                crop: Some((960, 288)),
                min_scale: -0.2,
                max_scale: 0.4,
                spatial_prob: 0.8,
                stretch_prob: 0.0,
                max_stretch: 0.2,
                h_flip_prob: 0.0,
                v_flip_prob: 0.0,
                brightness: 0.3,
                contrast: 0.3,
                saturation: 0.3,
                hue: 0.3 / RAFT_PI,
                asymmetric_color_prob: 0.0,
                eraser_prob: 0.5,
                eraser_min: 50,
                eraser_max: 100,
                eraser_boxes: 2,
                sparse: true,
            },
        }
    }

    fn parse(name: &str) -> Option<Self> {
        AugmentPreset::ALL.into_iter().find(|p| p.name() == name)
    }

    fn names() -> String {
        AugmentPreset::ALL.iter().map(|p| p.name()).collect::<Vec<_>>().join(", ")
    }
}

/// Any JSON value whose objects name no key twice (deserialising it is the check).
struct NoRepeatedKeys;

impl<'de> serde::Deserialize<'de> for NoRepeatedKeys {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_any(NoRepeatedKeysVisitor)
    }
}

struct NoRepeatedKeysVisitor;

impl<'de> serde::de::Visitor<'de> for NoRepeatedKeysVisitor {
    type Value = NoRepeatedKeys;

    fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("a JSON value")
    }
    fn visit_bool<E>(self, _: bool) -> Result<NoRepeatedKeys, E> {
        Ok(NoRepeatedKeys)
    }
    fn visit_i64<E>(self, _: i64) -> Result<NoRepeatedKeys, E> {
        Ok(NoRepeatedKeys)
    }
    fn visit_u64<E>(self, _: u64) -> Result<NoRepeatedKeys, E> {
        Ok(NoRepeatedKeys)
    }
    fn visit_f64<E>(self, _: f64) -> Result<NoRepeatedKeys, E> {
        Ok(NoRepeatedKeys)
    }
    fn visit_str<E>(self, _: &str) -> Result<NoRepeatedKeys, E> {
        Ok(NoRepeatedKeys)
    }
    fn visit_unit<E>(self) -> Result<NoRepeatedKeys, E> {
        Ok(NoRepeatedKeys)
    }
    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut a: A) -> Result<NoRepeatedKeys, A::Error> {
        while a.next_element::<NoRepeatedKeys>()?.is_some() {}
        Ok(NoRepeatedKeys)
    }
    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut a: A) -> Result<NoRepeatedKeys, A::Error> {
        let mut seen = std::collections::HashSet::new();
        while let Some(key) = a.next_key::<String>()? {
            if !seen.insert(key.clone()) {
                let key = crate::failure::echo(&key);
                return Err(serde::de::Error::custom(format!("key {key} given twice")));
            }
            a.next_value::<NoRepeatedKeys>()?;
        }
        Ok(NoRepeatedKeys)
    }
}

/// An augmentation of a request: the preset it starts from and its parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct Augment {
    /// The preset (or the JSON form's `preset`, `none` when it names none).
    pub preset: AugmentPreset,
    /// Whether the JSON form changed anything of the preset.
    pub custom: bool,
    pub params: AugmentParams,
}

/// The keys of the JSON form, with the field names of their errors.
const KEYS: [(&str, &str); 19] = [
    ("preset", "augment.preset"),
    ("crop", "augment.crop"),
    ("min_scale", "augment.min_scale"),
    ("max_scale", "augment.max_scale"),
    ("spatial_prob", "augment.spatial_prob"),
    ("stretch_prob", "augment.stretch_prob"),
    ("max_stretch", "augment.max_stretch"),
    ("h_flip_prob", "augment.h_flip_prob"),
    ("v_flip_prob", "augment.v_flip_prob"),
    ("brightness", "augment.brightness"),
    ("contrast", "augment.contrast"),
    ("saturation", "augment.saturation"),
    ("hue", "augment.hue"),
    ("asymmetric_color_prob", "augment.asymmetric_color_prob"),
    ("eraser_prob", "augment.eraser_prob"),
    ("eraser_min", "augment.eraser_min"),
    ("eraser_max", "augment.eraser_max"),
    ("eraser_boxes", "augment.eraser_boxes"),
    ("sparse", "augment.sparse"),
];

fn num(field: &'static str, v: &serde_json::Value) -> Result<f64, AugmentError> {
    v.as_f64().filter(|x| x.is_finite()).ok_or_else(|| bad(field, format!("{v} (expected a number)")))
}

fn count(field: &'static str, v: &serde_json::Value) -> Result<u32, AugmentError> {
    v.as_u64()
        .and_then(|x| u32::try_from(x).ok())
        .ok_or_else(|| bad(field, format!("{v} (expected a non-negative integer)")))
}

impl Augment {
    pub fn preset(p: AugmentPreset) -> Self {
        Augment { preset: p, custom: false, params: p.params() }
    }

    /// A preset name (`raft-chairs`, `raft-things`, `raft-sintel`, `raft-kitti`, `none`) or a JSON
    /// object: `preset` (the base, default `none`) and any of the [`AugmentParams`] keys
    /// (`crop` as `[width, height]`) over it. Errors name the key.
    pub fn parse(text: &str) -> Result<Self, AugmentError> {
        let t = text.trim();
        if !t.starts_with('{') {
            return AugmentPreset::parse(t).map(Augment::preset).ok_or_else(|| {
                bad(
                    "augment",
                    format!("unknown preset {t:?} (expected one of {}, or a JSON object)", AugmentPreset::names()),
                )
            });
        }
        // serde_json keeps the last of a repeated key without a word: refused instead
        serde_json::from_str::<NoRepeatedKeys>(t).map_err(|e| bad("augment", format!("JSON: {e}")))?;
        let value: serde_json::Value = serde_json::from_str(t).map_err(|e| bad("augment", format!("JSON: {e}")))?;
        let obj = value.as_object().ok_or_else(|| bad("augment", "expected a JSON object"))?;
        let mut preset = AugmentPreset::None;
        if let Some(v) = obj.get("preset") {
            let name = v.as_str().ok_or_else(|| bad("augment.preset", format!("{v} (expected a preset name)")))?;
            preset = AugmentPreset::parse(name).ok_or_else(|| {
                bad("augment.preset", format!("unknown preset {name:?} (expected one of {})", AugmentPreset::names()))
            })?;
        }
        let mut p = preset.params();
        for (key, v) in obj {
            let Some(&(_, field)) = KEYS.iter().find(|(k, _)| k == key) else {
                let keys: Vec<&str> = KEYS.iter().map(|(k, _)| *k).collect();
                return Err(bad("augment", format!("unknown key {key:?} (expected one of {})", keys.join(", "))));
            };
            match key.as_str() {
                "preset" => {}
                "crop" => {
                    let pair = v
                        .as_array()
                        .filter(|a| a.len() == 2)
                        .ok_or_else(|| bad(field, format!("{v} (expected [width, height] or null)")));
                    p.crop = if v.is_null() {
                        None
                    } else {
                        let a = pair?;
                        Some((count(field, &a[0])?, count(field, &a[1])?))
                    };
                }
                "min_scale" => p.min_scale = num(field, v)?,
                "max_scale" => p.max_scale = num(field, v)?,
                "spatial_prob" => p.spatial_prob = num(field, v)?,
                "stretch_prob" => p.stretch_prob = num(field, v)?,
                "max_stretch" => p.max_stretch = num(field, v)?,
                "h_flip_prob" => p.h_flip_prob = num(field, v)?,
                "v_flip_prob" => p.v_flip_prob = num(field, v)?,
                "brightness" => p.brightness = num(field, v)?,
                "contrast" => p.contrast = num(field, v)?,
                "saturation" => p.saturation = num(field, v)?,
                "hue" => p.hue = num(field, v)?,
                "asymmetric_color_prob" => p.asymmetric_color_prob = num(field, v)?,
                "eraser_prob" => p.eraser_prob = num(field, v)?,
                "eraser_min" => p.eraser_min = count(field, v)?,
                "eraser_max" => p.eraser_max = count(field, v)?,
                "eraser_boxes" => p.eraser_boxes = count(field, v)?,
                _ => p.sparse = v.as_bool().ok_or_else(|| bad(field, format!("{v} (expected true or false)")))?,
            }
        }
        p.validate()?;
        Ok(Augment { preset, custom: p != preset.params(), params: p })
    }

    /// The same augmentation with its crop replaced (a request's crop of both sides).
    #[must_use]
    pub fn with_crop(mut self, crop: (u32, u32)) -> Self {
        if self.params.crop != Some(crop) {
            self.params.crop = Some(crop);
            self.custom = self.params != self.preset.params();
        }
        self
    }

    /// Draws the augmentation of the sample at `address` for a `w` x `h` frame.
    pub fn draw(&self, address: SampleAddress, w: usize, h: usize) -> Plan {
        draw(&self.params, address, w, h)
    }

    /// Augments `s`: see the module documentation. Returns the augmented sample (its intrinsics
    /// scaled, mirrored under a flip and shifted to the crop) and what was applied.
    pub fn apply(&self, s: Sample) -> (Sample, AugmentRecord) {
        let plan = self.draw(s.address, s.width, s.height);
        let out = apply_plan(&plan, s);
        let record = AugmentRecord::new(self, &plan);
        (out, record)
    }
}

// ---------------------------------------------------------------------------------------------
// the draw

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
    fn is_identity(&self) -> bool {
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
    fn taps(self) -> Vec<(usize, usize, f32)> {
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
    fn nearest(self) -> Vec<usize> {
        (0..self.out)
            .map(|i| {
                let r = self.resized_of(i);
                (((r as f64 + 0.5) * self.src as f64 / self.resized as f64).floor() as usize).min(self.src - 1)
            })
            .collect()
    }

    /// The output pixel a source pixel lands on under the sparse rule (the nearest resized
    /// pixel, mirrored, cut), if inside.
    fn scatter(self, p: usize) -> Option<usize> {
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

fn factor(rng: &mut SampleRng, spread: f64) -> f64 {
    let f = rng.uniform((1.0 - spread).max(0.0), 1.0 + spread);
    if spread == 0.0 {
        1.0
    } else {
        f
    }
}

fn jitter(rng: &mut SampleRng, p: &AugmentParams) -> Jitter {
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

// ---------------------------------------------------------------------------------------------
// colour (PIL's ImageEnhance and HSV, as torchvision's ColorJitter applies them to PIL images)

/// PIL's `L` of an RGB pixel.
fn luma(p: &[u8]) -> u8 {
    ((u32::from(p[0]) * 19595 + u32::from(p[1]) * 38470 + u32::from(p[2]) * 7471 + 0x8000) >> 16) as u8
}

/// PIL's blend `a + f (b - a)` of u8 values, clipped and truncated.
fn blend(a: f32, b: u8, f: f32) -> u8 {
    let t = a + f * (f32::from(b) - a);
    if t <= 0.0 {
        0
    } else if t >= 255.0 {
        255
    } else {
        t as u8
    }
}

fn rgb_to_hsv(p: &[u8]) -> [u8; 3] {
    let (r, g, b) = (i32::from(p[0]), i32::from(p[1]), i32::from(p[2]));
    let (maxc, minc) = (r.max(g).max(b), r.min(g).min(b));
    if maxc == minc {
        return [0, 0, maxc as u8];
    }
    let cr = (maxc - minc) as f32;
    let s = cr / maxc as f32;
    let (rc, gc, bc) = ((maxc - r) as f32 / cr, (maxc - g) as f32 / cr, (maxc - b) as f32 / cr);
    let h = if r == maxc {
        bc - gc
    } else if g == maxc {
        2.0 + rc - bc
    } else {
        4.0 + gc - rc
    };
    // fmod(h / 6 + 1, 1): h / 6 + 1 lies in [5/6, 11/6)
    let h = h / 6.0 + 1.0;
    let h = if h >= 1.0 { h - 1.0 } else { h };
    // float to u8 casts saturate and truncate, as PIL's CLIP8((int) x) for x >= 0
    [(h * 255.0) as u8, (s * 255.0) as u8, maxc as u8]
}

fn hsv_to_rgb(hsv: [u8; 3]) -> [u8; 3] {
    let h = f32::from(hsv[0]) * 6.0 / 255.0;
    let s = f32::from(hsv[1]) / 255.0;
    let v = f32::from(hsv[2]);
    // h >= 0: the cast is the floor; x >= 0: x + 0.5 truncated is x rounded (half away from 0)
    let i = h as u32;
    let f = h - i as f32;
    let c = |x: f32| (x + 0.5) as u8;
    let (p, q, t) = (c(v * (1.0 - s)), c(v * (1.0 - s * f)), c(v * (1.0 - s * (1.0 - f))));
    let v = c(v);
    match i % 6 {
        0 => [v, t, p],
        1 => [q, v, p],
        2 => [p, v, t],
        3 => [p, q, v],
        4 => [t, p, v],
        _ => [v, p, q],
    }
}

/// ColorJitter on one image or a stack of images (the contrast mean is that of the stack).
fn apply_jitter(images: &mut [&mut Vec<u8>], j: &Jitter) {
    if j.is_identity() {
        return;
    }
    for &op in &j.order {
        match op {
            0 if j.brightness != 1.0 => {
                let f = j.brightness as f32;
                for img in images.iter_mut() {
                    img.iter_mut().for_each(|v| *v = blend(0.0, *v, f));
                }
            }
            1 if j.contrast != 1.0 => {
                let (sum, n) = images.iter().fold((0u64, 0u64), |(s, n), img| {
                    (s + img.chunks_exact(3).map(|p| u64::from(luma(p))).sum::<u64>(), n + img.len() as u64 / 3)
                });
                let mean = (sum as f64 / n.max(1) as f64 + 0.5).floor() as f32;
                let f = j.contrast as f32;
                for img in images.iter_mut() {
                    img.iter_mut().for_each(|v| *v = blend(mean, *v, f));
                }
            }
            2 if j.saturation != 1.0 => {
                let f = j.saturation as f32;
                for img in images.iter_mut() {
                    for p in img.chunks_exact_mut(3) {
                        let l = f32::from(luma(p));
                        p.iter_mut().for_each(|v| *v = blend(l, *v, f));
                    }
                }
            }
            3 if j.hue != 0.0 => {
                // torchvision: h (u8) += uint8(hue * 255), wrapping
                let shift = (j.hue * 255.0) as i32;
                for img in images.iter_mut() {
                    for p in img.chunks_exact_mut(3) {
                        let mut hsv = rgb_to_hsv(p);
                        hsv[0] = (i32::from(hsv[0]) + shift).rem_euclid(256) as u8;
                        p.copy_from_slice(&hsv_to_rgb(hsv));
                    }
                }
            }
            _ => {}
        }
    }
}

/// RAFT's eraser: each box of image2 (clipped to the frame) filled with image2's mean colour
/// (truncated to u8), measured once before the first box.
fn apply_eraser(img: &mut [u8], w: usize, h: usize, boxes: &[EraserBox]) {
    if boxes.is_empty() || img.is_empty() {
        return;
    }
    let n = (w * h).max(1) as f64;
    let mut mean = [0u8; 3];
    for (c, m) in mean.iter_mut().enumerate() {
        *m = (img.iter().skip(c).step_by(3).map(|&v| f64::from(v)).sum::<f64>() / n) as u8;
    }
    for b in boxes {
        let (x0, y0) = (b.x as usize, b.y as usize);
        let (x1, y1) = ((x0 + b.w as usize).min(w), (y0 + b.h as usize).min(h));
        for y in y0..y1 {
            for x in x0..x1 {
                img[3 * (y * w + x)..3 * (y * w + x) + 3].copy_from_slice(&mean);
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// the spatial map

/// Bilinear resampling of an interleaved u8 image (rounded to nearest).
fn bilinear_u8(
    src: &[u8],
    w: usize,
    channels: usize,
    xt: &[(usize, usize, f32)],
    yt: &[(usize, usize, f32)],
) -> Vec<u8> {
    if src.is_empty() {
        return Vec::new();
    }
    let mut out = Vec::with_capacity(xt.len() * yt.len() * channels);
    for &(y0, y1, fy) in yt {
        let (r0, r1) = (&src[y0 * w * channels..][..w * channels], &src[y1 * w * channels..][..w * channels]);
        for &(x0, x1, fx) in xt {
            let (a, b) = (&r0[x0 * channels..][..channels], &r0[x1 * channels..][..channels]);
            let (d, e) = (&r1[x0 * channels..][..channels], &r1[x1 * channels..][..channels]);
            for c in 0..channels {
                let top = f32::from(a[c]) + (f32::from(b[c]) - f32::from(a[c])) * fx;
                let bottom = f32::from(d[c]) + (f32::from(e[c]) - f32::from(d[c])) * fx;
                // in [0, 255.5): the saturating cast of v + 0.5 is v rounded
                out.push((top + (bottom - top) * fy + 0.5) as u8);
            }
        }
    }
    out
}

/// Nearest-neighbour resampling of a plane of any element type.
fn nearest<T: Copy>(src: &[T], w: usize, xn: &[usize], yn: &[usize]) -> Vec<T> {
    if src.is_empty() {
        return Vec::new();
    }
    let mut out = Vec::with_capacity(xn.len() * yn.len());
    for &y in yn {
        let row = &src[y * w..][..w];
        out.extend(xn.iter().map(|&x| row[x]));
    }
    out
}

/// The dense flow under the map (bilinear, scaled by the slopes) and its `valid` (1 where every
/// tap with a non-zero weight was valid).
fn dense_flow(s: &Sample, plan: &Plan, xt: &[(usize, usize, f32)], yt: &[(usize, usize, f32)]) -> (Vec<f32>, Vec<u8>) {
    let w = s.width;
    let (kx, ky) = (plan.x.slope() as f32, plan.y.slope() as f32);
    let n = xt.len() * yt.len();
    let mut flow = Vec::with_capacity(2 * n);
    let mut valid = Vec::with_capacity(n);
    for &(y0, y1, fy) in yt {
        let (f0, f1) = (&s.flow[2 * y0 * w..][..2 * w], &s.flow[2 * y1 * w..][..2 * w]);
        let (v0, v1) = (&s.valid[y0 * w..][..w], &s.valid[y1 * w..][..w]);
        // the second row counts only with a non-zero weight
        let row1 = fy > 0.0;
        for &(x0, x1, fx) in xt {
            let col1 = fx > 0.0;
            let ok = v0[x0] != 0 && (!col1 || v0[x1] != 0) && (!row1 || (v1[x0] != 0 && (!col1 || v1[x1] != 0)));
            for (c, k) in [(0, kx), (1, ky)] {
                let top = f0[2 * x0 + c] + (f0[2 * x1 + c] - f0[2 * x0 + c]) * fx;
                let bottom = f1[2 * x0 + c] + (f1[2 * x1 + c] - f1[2 * x0 + c]) * fx;
                flow.push((top + (bottom - top) * fy) * k);
            }
            valid.push(u8::from(ok));
        }
    }
    (flow, valid)
}

/// RAFT's sparse rule: each valid vector moved to the output pixel nearest its mapped position
/// (later source pixels win), scaled by the slopes; nothing else is valid.
fn sparse_flow(s: &Sample, plan: &Plan) -> (Vec<f32>, Vec<u8>) {
    let (ow, oh) = (plan.x.out, plan.y.out);
    let (kx, ky) = (plan.x.slope() as f32, plan.y.slope() as f32);
    let mut flow = crate::buf::zeros::<f32>(2 * ow * oh);
    let mut valid = crate::buf::zeros::<u8>(ow * oh);
    let xs: Vec<Option<usize>> = (0..s.width).map(|x| plan.x.scatter(x)).collect();
    for y in 0..s.height {
        let Some(oy) = plan.y.scatter(y) else { continue };
        for (x, ox) in xs.iter().enumerate() {
            let i = y * s.width + x;
            if let (Some(ox), true) = (ox, s.valid[i] != 0) {
                let o = oy * ow + ox;
                flow[2 * o] = s.flow[2 * i] * kx;
                flow[2 * o + 1] = s.flow[2 * i + 1] * ky;
                valid[o] = 1;
            }
        }
    }
    (flow, valid)
}

/// Clears `valid` where the flow target leaves the `w` x `h` frame (target inside
/// `[0, w - 1] x [0, h - 1]`, the renderer's rule) or the flow is not finite.
pub fn clear_valid_outside(flow: &[f32], valid: &mut [u8], w: usize, h: usize) {
    let (maxx, maxy) = (w.saturating_sub(1) as f32, h.saturating_sub(1) as f32);
    for (i, v) in valid.iter_mut().enumerate() {
        if *v != 0 {
            let tx = (i % w) as f32 + flow[2 * i];
            let ty = (i / w) as f32 + flow[2 * i + 1];
            if !(tx >= 0.0 && tx <= maxx && ty >= 0.0 && ty <= maxy) {
                *v = 0;
            }
        }
    }
}

/// The u8 label planes of a sample (one byte per pixel, resampled with nearest neighbour).
fn label_planes(s: &mut Sample) -> [&mut Vec<u8>; 4] {
    [&mut s.occlusion, &mut s.mask1, &mut s.mask2, &mut s.holes]
}

/// The intrinsics of the output frame: scaled with the frame, the principal point mirrored
/// under a flip and shifted to the crop (the focal lengths stay positive; the flip is recorded).
fn intrinsics(k: Intrinsics, x: Axis, y: Axis) -> Intrinsics {
    let axis = |f: f64, c: f64, a: Axis| {
        let s = a.resized as f64 / a.src as f64;
        let r = (c + 0.5) * s - 0.5;
        let r = if a.flip { (a.resized - 1) as f64 - r } else { r };
        (f * s, r - a.offset as f64)
    };
    let (fx, cx) = axis(k.fx, k.cx, x);
    let (fy, cy) = axis(k.fy, k.cy, y);
    Intrinsics::new(fx, fy, cx, cy)
}

/// Applies a drawn plan to a sample (all its per-pixel fields). Augmentation is made for pairs:
/// a sample's backward fields and clip frames are dropped (the service refuses to ask for both).
pub fn apply_plan(plan: &Plan, mut s: Sample) -> Sample {
    s.backward = crate::sample::LinkFields::default();
    s.clip.clear();
    let (w, h) = (s.width, s.height);
    if w == 0 || h == 0 {
        return s;
    }
    // colour, then the eraser, on the rendered frame (RAFT's order)
    if plan.color {
        if plan.asymmetric {
            apply_jitter(&mut [&mut s.image1], &plan.jitter[0]);
            apply_jitter(&mut [&mut s.image2], &plan.jitter[1]);
        } else {
            apply_jitter(&mut [&mut s.image1, &mut s.image2], &plan.jitter[0]);
        }
    }
    apply_eraser(&mut s.image2, w, h, &plan.eraser);
    if plan.x == Axis::identity(w) && plan.y == Axis::identity(h) {
        // no resize, flip or crop: the flow, `valid` and the labels stay as they are
        return s;
    }
    // the spatial map
    let (xt, yt) = (plan.x.taps(), plan.y.taps());
    let (xn, yn) = (plan.x.nearest(), plan.y.nearest());
    let (ow, oh) = (plan.x.out, plan.y.out);
    let (flow, valid) = if s.flow.len() != 2 * w * h || s.valid.len() != w * h {
        (Vec::new(), Vec::new())
    } else {
        let (flow, mut valid) = if plan.sparse { sparse_flow(&s, plan) } else { dense_flow(&s, plan, &xt, &yt) };
        clear_valid_outside(&flow, &mut valid, ow, oh);
        (flow, valid)
    };
    s.image1 = bilinear_u8(&s.image1, w, 3, &xt, &yt);
    s.image2 = bilinear_u8(&s.image2, w, 3, &xt, &yt);
    s.flow = flow;
    s.valid = valid;
    for plane in label_planes(&mut s) {
        *plane = nearest(plane, w, &xn, &yn);
    }
    s.depth1 = nearest(&s.depth1, w, &xn, &yn);
    s.depth2 = nearest(&s.depth2, w, &xn, &yn);
    s.intrinsics = intrinsics(s.intrinsics, plan.x, plan.y);
    s.width = ow;
    s.height = oh;
    s
}

// ---------------------------------------------------------------------------------------------
// the record

/// What was applied to a sample, as the `augment` field of the sample on the wire (JSON).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AugmentRecord {
    /// The preset name, with `+json` when the JSON form changed it.
    pub preset: String,
    /// The rendered frame `[width, height]`.
    pub frame: [usize; 2],
    /// The resized frame `[width, height]` (the rendered one when not resized).
    pub resized: [usize; 2],
    /// The flow's multipliers `[x, y]` (negative under a flip).
    pub flow_scale: [f64; 2],
    /// `[horizontal, vertical]` flips.
    pub flip: [bool; 2],
    /// The crop `[x, y, width, height]` in the resized, flipped frame.
    pub crop: [usize; 4],
    /// The colour jitters (one for both images, or one per image when asymmetric; none when
    /// colour is off).
    pub color: Vec<Jitter>,
    /// The eraser boxes on image2, in the rendered frame.
    pub eraser: Vec<EraserBox>,
    pub sparse: bool,
}

impl AugmentRecord {
    pub fn new(a: &Augment, plan: &Plan) -> Self {
        let color = match (plan.color, plan.asymmetric) {
            (false, _) => vec![],
            (true, false) => vec![plan.jitter[0]],
            (true, true) => plan.jitter.to_vec(),
        };
        AugmentRecord {
            preset: format!("{}{}", a.preset.name(), if a.custom { "+json" } else { "" }),
            frame: [plan.x.src, plan.y.src],
            resized: [plan.x.resized, plan.y.resized],
            flow_scale: [plan.x.slope(), plan.y.slope()],
            flip: [plan.x.flip, plan.y.flip],
            crop: [plan.x.offset, plan.y.offset, plan.x.out, plan.y.out],
            color,
            eraser: plan.eraser.clone(),
            sparse: plan.sparse,
        }
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string(self).unwrap_or_default()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::motion::{Motion, RotationKind};
    use crate::sample::StageTimings;
    use proptest::prelude::*;

    #[test]
    fn a_key_given_twice_is_refused_at_any_depth() {
        let e = Augment::parse(r#"{"preset":"raft-chairs","preset":"none"}"#).unwrap_err();
        assert_eq!(e.field, "augment");
        assert!(e.reason.contains("\"preset\" given twice"), "{}", e.reason);
        let e = Augment::parse(r#"{"crop":[8,8],"brightness":{"a":1,"a":2}}"#).unwrap_err();
        assert!(e.reason.contains("given twice"), "{}", e.reason);
        // the same key in two objects is fine, and so is a well-formed form
        assert!(Augment::parse(r#"{"preset":"raft-chairs","crop":[64,48]}"#).is_ok());
    }

    /// A `w` x `h` sample with textured images, the affine flow `f(p) = (a p.x + b, c p.y + d)`,
    /// valid except a band, and label/depth planes that name their pixel.
    fn sample(w: usize, h: usize, index: u64) -> Sample {
        let n = w * h;
        let mut flow = crate::buf::zeros::<f32>(2 * n);
        let mut valid = vec![1u8; n];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                flow[2 * i] = 0.05 * x as f32 - 1.5;
                flow[2 * i + 1] = -0.03 * y as f32 + 0.75;
                valid[i] = u8::from(x % 7 != 3);
            }
        }
        Sample {
            address: SampleAddress { dataset: 11, seed: 5, index },
            source_id: "t".into(),
            width: w,
            height: h,
            image1: (0..n * 3).map(|i| ((i * 37) % 251) as u8).collect(),
            image2: (0..n * 3).map(|i| ((i * 53) % 241) as u8).collect(),
            flow,
            valid,
            occlusion: (0..n).map(|i| u8::from(i % 5 == 0)).collect(),
            mask1: (0..n).map(|i| (i % 251) as u8).collect(),
            mask2: (0..n).map(|i| (i % 13) as u8).collect(),
            holes: (0..n).map(|i| u8::from(i % 11 == 0)).collect(),
            camera: Motion::new("x", [0.0; 3], RotationKind::AxisAngle, [0.0; 3]),
            objects: vec![],
            depth1: (0..n).map(|i| i as f32).collect(),
            depth2: (0..n).map(|i| 2.0 * i as f32).collect(),
            inpainted_pixels: 0,
            backward: Default::default(),
            clip: Vec::new(),
            skipped_sources: 0,
            provenance: vec![],
            intrinsics: Intrinsics::reference_default(w, h),
            timings: StageTimings::default(),
        }
    }

    #[test]
    fn presets_and_json_parse_and_errors_name_the_key() {
        for p in AugmentPreset::ALL {
            let a = Augment::parse(p.name()).unwrap();
            assert_eq!(a, Augment::preset(p));
            a.params.validate().unwrap();
        }
        let chairs = AugmentPreset::RaftChairs.params();
        assert_eq!(chairs.crop, Some((496, 368)));
        assert_eq!((chairs.min_scale, chairs.max_scale), (-0.1, 1.0));
        assert!(AugmentPreset::RaftKitti.params().sparse);
        let a = Augment::parse(r#"{"preset": "raft-things", "eraser_prob": 0, "crop": [320, 256]}"#).unwrap();
        assert_eq!(a.preset, AugmentPreset::RaftThings);
        assert!(a.custom);
        assert_eq!(a.params.crop, Some((320, 256)));
        assert_eq!(a.params.eraser_prob, 0.0);
        assert_eq!(a.params.min_scale, -0.4);
        let field = |t: &str| Augment::parse(t).unwrap_err().field;
        assert_eq!(field("raft-chair"), "augment");
        assert_eq!(field("{"), "augment");
        assert_eq!(field(r#"{"crop": [1]}"#), "augment.crop");
        assert_eq!(field(r#"{"crop": [0, 5]}"#), "augment.crop");
        assert_eq!(field(r#"{"hue": "x"}"#), "augment.hue");
        assert_eq!(field(r#"{"hue": 0.7}"#), "augment.hue");
        assert_eq!(field(r#"{"h_flip_prob": 2}"#), "augment.h_flip_prob");
        assert_eq!(field(r#"{"preset": "raft-chairs", "max_scale": -1}"#), "augment.min_scale");
        assert_eq!(field(r#"{"preset": "kitti"}"#), "augment.preset");
        assert_eq!(field(r#"{"eraser_boxes": 0}"#), "augment.eraser_boxes");
        assert_eq!(field(r#"{"sparse": 1}"#), "augment.sparse");
        let e = Augment::parse(r#"{"scale": 1}"#).unwrap_err();
        assert!(e.reason.contains("\"scale\""), "{e}");
    }

    #[test]
    fn the_identity_changes_nothing() {
        let mut s = sample(23, 17, 4);
        // a rendered sample's valid already holds the target-inside rule
        clear_valid_outside(&s.flow, &mut s.valid, 23, 17);
        let (out, r) = Augment::preset(AugmentPreset::None).apply(s.clone());
        assert!(out == s, "the identity changed the sample");
        assert_eq!(r.flow_scale, [1.0, 1.0]);
        // a crop of the whole frame with nothing drawn is the identity too
        let (out, _) = Augment::preset(AugmentPreset::None).with_crop((23, 17)).apply(s.clone());
        assert!(out == s, "the whole-frame crop changed the sample");
    }

    #[test]
    fn colour_and_eraser_never_change_the_flow_or_the_geometry() {
        let no_colour = AugmentParams {
            brightness: 0.0,
            contrast: 0.0,
            saturation: 0.0,
            hue: 0.0,
            eraser_prob: 0.0,
            ..AugmentPreset::RaftChairs.params()
        };
        let plain = Augment { preset: AugmentPreset::RaftChairs, custom: true, params: no_colour }.with_crop((40, 30));
        let full = Augment::preset(AugmentPreset::RaftChairs).with_crop((40, 30));
        let mut changed = 0;
        for index in 0..20 {
            let s = sample(64, 48, index);
            let (a, ra) = full.apply(s.clone());
            let (b, rb) = plain.apply(s);
            assert_eq!((ra.resized, ra.flip, ra.crop), (rb.resized, rb.flip, rb.crop));
            assert_eq!(a.flow, b.flow);
            assert_eq!(a.valid, b.valid);
            assert_eq!((a.occlusion, a.mask1, a.holes, a.depth1), (b.occlusion, b.mask1, b.holes, b.depth1));
            changed += usize::from(a.image1 != b.image1 || a.image2 != b.image2);
        }
        assert!(changed >= 15, "colour changed only {changed} of 20 samples");
    }

    #[test]
    fn same_address_same_bytes_and_indices_differ() {
        let a = Augment::preset(AugmentPreset::RaftSintel).with_crop((50, 40));
        let (x, rx) = a.apply(sample(70, 52, 3));
        let (y, ry) = a.apply(sample(70, 52, 3));
        assert_eq!(x, y);
        assert_eq!(rx.to_json(), ry.to_json());
        let records: std::collections::BTreeSet<String> =
            (0..8).map(|i| a.apply(sample(70, 52, i)).1.to_json()).collect();
        assert!(records.len() >= 7, "{records:?}");
    }

    #[test]
    fn the_frame_is_brought_up_to_a_crop_larger_than_it() {
        for p in AugmentPreset::ALL {
            let a = Augment::preset(p).with_crop((100, 80));
            for index in 0..10 {
                let (out, r) = a.apply(sample(40, 30, index));
                assert_eq!((out.width, out.height), (100, 80), "{p:?} {r:?}");
                assert_eq!(out.image1.len(), 100 * 80 * 3);
                assert_eq!(out.flow.len(), 100 * 80 * 2);
                assert!(out.flow.iter().all(|v| v.is_finite()));
                assert!(r.resized[0] > 100 && r.resized[1] > 80);
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]

        #[test]
        fn axis_forward_inverts_source(src in 1usize..300, resized in 1usize..600, flip: bool, off in 0usize..50, i in 0usize..50) {
            let out = resized.saturating_sub(off).max(1);
            let off = off.min(resized - 1);
            let a = Axis { src, resized, flip, offset: off, out };
            let i = i % out;
            prop_assert!((a.forward(a.source(i)) - i as f64).abs() < 1e-9);
            // the map is affine with the slope it reports
            prop_assert!((a.forward(a.source(i) + 1.0) - a.forward(a.source(i)) - a.slope()).abs() < 1e-9);
        }

        /// Dense rule: the output flow is the slope times the source flow at the source
        /// position (exact for an affine field, up to f32 rounding), and valid pixels come only
        /// from valid taps with the target inside the output.
        #[test]
        fn dense_flow_scales_and_flips_with_the_geometry(index in 0u64..1000, cw in 8u32..60, ch in 8u32..40) {
            let a = Augment::preset(AugmentPreset::RaftChairs).with_crop((cw, ch));
            let s = sample(48, 36, index);
            let plan = a.draw(s.address, s.width, s.height);
            let out = apply_plan(&plan, s.clone());
            let (ow, oh) = (out.width, out.height);
            prop_assert_eq!((ow, oh), (cw as usize, ch as usize));
            let (kx, ky) = (plan.x.slope(), plan.y.slope());
            for y in 0..oh {
                for x in 0..ow {
                    let o = y * ow + x;
                    let (sx, sy) = (plan.x.source(x).clamp(0.0, 47.0), plan.y.source(y).clamp(0.0, 35.0));
                    let want = [(0.05 * sx - 1.5) * kx, (-0.03 * sy + 0.75) * ky];
                    prop_assert!((f64::from(out.flow[2 * o]) - want[0]).abs() < 1e-3, "{} {}", out.flow[2 * o], want[0]);
                    prop_assert!((f64::from(out.flow[2 * o + 1]) - want[1]).abs() < 1e-3);
                    if out.valid[o] != 0 {
                        let tx = x as f64 + want[0];
                        let ty = y as f64 + want[1];
                        prop_assert!(tx >= -1e-3 && tx <= (ow - 1) as f64 + 1e-3 && ty >= -1e-3 && ty <= (oh - 1) as f64 + 1e-3);
                        // never next to the invalid column 3 (mod 7) of the source
                        let (x0, x1) = (sx.floor() as usize, sx.ceil() as usize);
                        prop_assert!(x0 % 7 != 3 && x1 % 7 != 3);
                    }
                    // labels follow with nearest neighbour
                    let (nx, ny) = (plan.x.nearest()[x], plan.y.nearest()[y]);
                    prop_assert_eq!(out.mask1[o], s.mask1[ny * 48 + nx]);
                    prop_assert_eq!(out.depth2[o], s.depth2[ny * 48 + nx]);
                }
            }
        }

        /// Sparse rule: every valid output vector is a valid source vector times the slopes,
        /// put at the output pixel nearest the source pixel's mapped position.
        #[test]
        fn sparse_flow_moves_valid_vectors_to_the_nearest_pixel(index in 0u64..1000) {
            let a = Augment::preset(AugmentPreset::RaftKitti).with_crop((40, 20));
            let s = sample(60, 30, index);
            let plan = a.draw(s.address, s.width, s.height);
            let out = apply_plan(&plan, s.clone());
            let (kx, ky) = (plan.x.slope() as f32, plan.y.slope() as f32);
            let mut hits = 0;
            for y in 0..s.height {
                for x in 0..s.width {
                    let (Some(ox), Some(oy)) = (plan.x.scatter(x), plan.y.scatter(y)) else { continue };
                    prop_assert!((plan.x.forward(x as f64) - ox as f64).abs() <= 0.5 + 1e-9);
                    let o = oy * 40 + ox;
                    if out.valid[o] != 0 {
                        // the vector there is one of the source's, scaled
                        let u = out.flow[2 * o] / kx;
                        let v = out.flow[2 * o + 1] / ky;
                        let sxp = ((u + 1.5) / 0.05).round() as usize;
                        prop_assert!(sxp < s.width && s.valid[oy.min(s.height - 1) * s.width + sxp.min(s.width - 1)] <= 1);
                        prop_assert!((v - 0.75).abs() <= 0.03 * s.height as f32 + 1e-3);
                        hits += 1;
                    }
                }
            }
            prop_assert!(out.valid.iter().filter(|&&v| v != 0).count() <= hits);
            prop_assert!(out.flow.iter().all(|v| v.is_finite()));
        }
    }
}
