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

mod apply;
mod plan;
#[cfg(test)]
mod tests;

pub use apply::{apply_plan, clear_valid_outside};
pub use plan::{draw, Axis, EraserBox, Jitter, Plan};
