//! Object instance masks of a source image: the [`InstanceMasks`] type, COCO run-length encodings
//! and polygons (bit-compatible with pycocotools' `maskApi.c`), instance-index PNGs, COCO
//! annotation JSON, the choice of the objects to move, and mask resizing.
//!
//! # Conventions
//!
//! Masks are row-major `H x W` (`mask[y * W + x]`). COCO RLE counts are runs over the
//! **column-major** (Fortran) order of the mask, the first run counting zeros (it may be 0).
//! The compressed string form is pycocotools' `rleToString`: each count (from the fourth on, as
//! the difference to the count two before) in 5-bit groups, least significant first, the 0x20 bit
//! marking "more", the last group sign-extended from its 0x10 bit, each group + 48 as an ASCII
//! character ('0'..='o').
//!
//! Decoding is stricter than pycocotools (which reads out of bounds or wraps on bad input): a
//! character outside '0'..='o', a string ending inside a count, a count needing more than 35
//! bits, a negative or over-`u32` count, or counts not summing to `h * w` are [`MaskError::Rle`]
//! errors, never panics. Valid input gives pycocotools' results exactly.
//!
//! Polygons (`[x0, y0, x1, y1, ...]` in pixels, pixel centres at integer coordinates) are
//! rasterised exactly as pycocotools' `rleFrPoly` (5x upsampled edge walk, boundary crossings
//! sampled at pixel centres); several polygons of one object are united (pycocotools'
//! `merge`). An odd number of coordinates or a non-finite one is an error (pycocotools drops the
//! last coordinate); coordinates beyond +-4e8 are refused (undefined in C).
//!
//! [`Instance::area`] is the number of pixels with mask value >= 0.5.

use crate::io::image::{decode_file, save_gray16_png, save_gray_png, ImageError, ImageLimits};
use crate::source::FailureKind;
use ::image::DynamicImage;
use serde_json::Value;
use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

/// The most instances one [`InstanceMasks`] may hold (each is a full-size f32 mask); more is an
/// error rather than gigabytes of masks.
pub const MAX_INSTANCES: usize = 1024;

/// The most boundary points one polygon may produce in the 5x upsampled edge walk (about 5 x its
/// perimeter in pixels), a guard against absurd coordinates.
pub const MAX_POLYGON_STEPS: u64 = 1 << 25;

/// Errors of mask decoding; `what` names the field or file, `reason` the problem.
#[derive(Debug, thiserror::Error)]
pub enum MaskError {
    /// A malformed run-length encoding.
    #[error("{what}: malformed RLE: {reason}")]
    Rle { what: String, reason: String },
    /// A malformed polygon.
    #[error("{what}: invalid polygon: {reason}")]
    Polygon { what: String, reason: String },
    /// A JSON value of the wrong shape.
    #[error("{what}: {reason}")]
    Json { what: String, reason: String },
    /// Sizes that do not fit together (mask vs image, too many instances, ids out of range).
    #[error("{what}: {reason}")]
    Size { what: String, reason: String },
    /// An instance-index PNG of a kind that cannot be read as instance ids.
    #[error("{}: {reason}", .path.display())]
    IndexPng { path: PathBuf, reason: String },
    /// Reading or writing an image file.
    #[error(transparent)]
    Image(#[from] ImageError),
}

impl MaskError {
    /// The kind of source failure: a mask image over the limits or cut short is
    /// [`FailureKind::TooLarge`] or [`FailureKind::Truncated`], anything else [`FailureKind::Mask`].
    pub fn failure_kind(&self) -> FailureKind {
        match self {
            MaskError::Image(e) => e.failure_kind().in_part(FailureKind::Mask),
            _ => FailureKind::Mask,
        }
    }

    /// The error with `what` replaced by `field` (the low-level functions do not know it).
    fn in_field(self, field: &str) -> Self {
        match self {
            MaskError::Rle { reason, .. } => MaskError::Rle { what: field.into(), reason },
            MaskError::Polygon { reason, .. } => MaskError::Polygon { what: field.into(), reason },
            MaskError::Json { reason, .. } => MaskError::Json { what: field.into(), reason },
            MaskError::Size { reason, .. } => MaskError::Size { what: field.into(), reason },
            other => other,
        }
    }

    /// The error with `prefix: ` in front of `what`.
    fn prefixed(self, prefix: &str) -> Self {
        let p = |what: String| format!("{prefix}: {what}");
        match self {
            MaskError::Rle { what, reason } => MaskError::Rle { what: p(what), reason },
            MaskError::Polygon { what, reason } => MaskError::Polygon { what: p(what), reason },
            MaskError::Json { what, reason } => MaskError::Json { what: p(what), reason },
            MaskError::Size { what, reason } => MaskError::Size { what: p(what), reason },
            other => other,
        }
    }
}

fn rle_err(reason: impl Into<String>) -> MaskError {
    MaskError::Rle { what: "RLE".into(), reason: reason.into() }
}

fn poly_err(reason: impl Into<String>) -> MaskError {
    MaskError::Polygon { what: "polygon".into(), reason: reason.into() }
}

fn json_err(what: &str, reason: impl Into<String>) -> MaskError {
    MaskError::Json { what: what.into(), reason: reason.into() }
}

fn size_err(what: &str, reason: impl Into<String>) -> MaskError {
    MaskError::Size { what: what.into(), reason: reason.into() }
}

/// `h * w` as the u32 range RLE counts live in.
fn pixel_count(h: usize, w: usize) -> Result<u32, MaskError> {
    h.checked_mul(w)
        .and_then(|n| u32::try_from(n).ok())
        .ok_or_else(|| size_err("mask", format!("{h} x {w} pixels do not fit in 32-bit RLE counts")))
}

// ---------------------------------------------------------------------------------------------
// COCO RLE

/// The counts of a COCO RLE, as they appear in annotation JSON.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RleCounts {
    /// pycocotools' compressed string (`rleToString`).
    Compressed(String),
    /// Plain run lengths (COCO "uncompressed RLE", e.g. crowd annotations).
    Uncompressed(Vec<u32>),
}

impl RleCounts {
    /// The run lengths.
    pub fn to_counts(&self) -> Result<Vec<u32>, MaskError> {
        match self {
            RleCounts::Compressed(s) => rle_from_string(s),
            RleCounts::Uncompressed(c) => Ok(c.clone()),
        }
    }
}

/// Decodes pycocotools' compressed RLE string (`rleFrString`) to run lengths.
pub fn rle_from_string(s: &str) -> Result<Vec<u32>, MaskError> {
    let bytes = s.as_bytes();
    let mut counts: Vec<u32> = Vec::with_capacity(bytes.len());
    let mut p = 0;
    while p < bytes.len() {
        let start = p;
        let mut x: i64 = 0;
        let mut k = 0;
        loop {
            let Some(&b) = bytes.get(p) else {
                return Err(rle_err(format!("the string ends inside the count that starts at byte {start}")));
            };
            if !(48..=111).contains(&b) {
                let shown =
                    s.get(p..).and_then(|r| r.chars().next()).map_or(format!("byte 0x{b:02x}"), |c| format!("{c:?}"));
                return Err(rle_err(format!("{shown} at byte {p} is not a compressed-RLE character ('0'..='o')")));
            }
            if k == 7 {
                return Err(rle_err(format!("the count at byte {start} has more than 7 groups (35 bits)")));
            }
            let c = i64::from(b - 48);
            x |= (c & 0x1f) << (5 * k);
            p += 1;
            k += 1;
            if c & 0x20 == 0 {
                if c & 0x10 != 0 {
                    x |= -1i64 << (5 * k);
                }
                break;
            }
        }
        let m = counts.len();
        if m > 2 {
            x += i64::from(counts[m - 2]);
        }
        let v = u32::try_from(x)
            .map_err(|_| rle_err(format!("count {} (at byte {start}) is {x}, outside 0..=4294967295", counts.len())))?;
        counts.push(v);
    }
    Ok(counts)
}

/// Encodes run lengths as pycocotools' compressed string (`rleToString`).
pub fn rle_to_string(counts: &[u32]) -> String {
    let mut s = String::with_capacity(counts.len() * 2);
    for (i, &c) in counts.iter().enumerate() {
        let mut x = i64::from(c);
        if i > 2 {
            x -= i64::from(counts[i - 2]);
        }
        loop {
            let mut c = (x & 0x1f) as u8;
            x >>= 5;
            let more = if c & 0x10 != 0 { x != -1 } else { x != 0 };
            if more {
                c |= 0x20;
            }
            s.push(char::from(c + 48));
            if !more {
                break;
            }
        }
    }
    s
}

/// Decodes an RLE to a row-major `h x w` mask of 0 and 1.
pub fn rle_decode(counts: &RleCounts, h: usize, w: usize) -> Result<Vec<u8>, MaskError> {
    rle_decode_counts(&counts.to_counts()?, h, w)
}

/// Decodes run lengths (column-major, zeros first) to a row-major `h x w` mask of 0 and 1; the
/// counts must sum to `h * w`.
pub fn rle_decode_counts(counts: &[u32], h: usize, w: usize) -> Result<Vec<u8>, MaskError> {
    let n = pixel_count(h, w)? as u64;
    let total: u64 = counts.iter().map(|&c| u64::from(c)).sum();
    if total != n {
        return Err(rle_err(format!("the counts sum to {total}, a {h} x {w} mask needs {n}")));
    }
    let mut mask = vec![0u8; n as usize];
    let mut k = 0usize;
    for (j, &c) in counts.iter().enumerate() {
        let c = c as usize;
        if j % 2 == 1 {
            for idx in k..k + c {
                mask[(idx % h) * w + idx / h] = 1;
            }
        }
        k += c;
    }
    Ok(mask)
}

/// Encodes a row-major `h x w` mask (non-zero = 1) as COCO run lengths (pycocotools'
/// `rleEncode`: column-major, zeros first; `[0]` for an empty mask).
///
/// # Panics
/// If `mask.len() != h * w` or `h * w` exceeds `u32::MAX`.
pub fn rle_encode(mask: &[u8], h: usize, w: usize) -> Vec<u32> {
    assert_eq!(
        Some(mask.len()),
        h.checked_mul(w),
        "rle_encode: mask holds {} values, {h} x {w} needs more",
        mask.len()
    );
    assert!(u32::try_from(mask.len()).is_ok(), "rle_encode: {h} x {w} does not fit in 32-bit counts");
    let mut counts = Vec::new();
    let (mut prev, mut run) = (false, 0u32);
    for x in 0..w {
        for y in 0..h {
            let v = mask[y * w + x] != 0;
            if v != prev {
                counts.push(run);
                run = 0;
                prev = v;
            }
            run += 1;
        }
    }
    counts.push(run);
    counts
}

/// The number of ones of an RLE (pycocotools' `area`).
pub fn rle_area(counts: &[u32]) -> u64 {
    counts.iter().skip(1).step_by(2).map(|&c| u64::from(c)).sum()
}

/// The bounding box `[x, y, width, height]` of an RLE, as pycocotools' `toBbox` (`rleToBbox`):
/// all zeros for an empty mask; a run of ones that wraps from one column into the next makes the
/// box span the full height, as in pycocotools.
pub fn rle_bbox(counts: &[u32], h: usize, w: usize) -> [f64; 4] {
    let m = counts.len() / 2 * 2;
    if m == 0 || h == 0 {
        return [0.0; 4];
    }
    let hh = h as u64;
    let (mut xs, mut ys, mut xe, mut ye) = (w as u64, hh, 0u64, 0u64);
    let (mut cc, mut xp) = (0u64, 0u64);
    for (j, &c) in counts[..m].iter().enumerate() {
        cc += u64::from(c);
        // pycocotools' uint arithmetic would wrap for an empty first ones-run; saturate instead
        let t = cc.saturating_sub((j % 2) as u64);
        let y = t % hh;
        let x = (t - y) / hh;
        if j % 2 == 0 {
            xp = x;
        } else if xp < x {
            ys = 0;
            ye = hh - 1;
        }
        xs = xs.min(x);
        xe = xe.max(x);
        ys = ys.min(y);
        ye = ye.max(y);
    }
    [xs as f64, ys as f64, (xe + 1).saturating_sub(xs) as f64, (ye + 1).saturating_sub(ys) as f64]
}

/// [`rle_bbox`] of a row-major mask.
///
/// # Panics
/// As [`rle_encode`].
pub fn mask_bbox(mask: &[u8], h: usize, w: usize) -> [f64; 4] {
    rle_bbox(&rle_encode(mask, h, w), h, w)
}

// ---------------------------------------------------------------------------------------------
// polygons

/// Rasterises one polygon `[x0, y0, x1, y1, ...]` to COCO run lengths exactly as pycocotools'
/// `frPyObjects` / `rleFrPoly` (see the module documentation). Fewer than one point gives an
/// empty mask.
pub fn polygon_to_rle(xy: &[f64], h: usize, w: usize) -> Result<Vec<u32>, MaskError> {
    if !xy.len().is_multiple_of(2) {
        return Err(poly_err(format!("{} coordinates: expected x, y pairs", xy.len())));
    }
    if let Some(i) = xy.iter().position(|v| !v.is_finite()) {
        return Err(poly_err(format!("coordinate {i} is {}", xy[i])));
    }
    let n = pixel_count(h, w)?;
    let k = xy.len() / 2;
    if k == 0 || n == 0 {
        return Ok(vec![n]);
    }
    const SCALE: f64 = 5.0;
    let limit = 4.0e8;
    if let Some(i) = xy.iter().position(|v| v.abs() > limit) {
        return Err(poly_err(format!("coordinate {i} is {}, beyond +-{limit:e}", xy[i])));
    }
    // C: (int)(scale * v + .5), truncating toward zero
    let px: Vec<i64> = (0..=k).map(|j| (SCALE * xy[(j % k) * 2] + 0.5) as i64).collect();
    let py: Vec<i64> = (0..=k).map(|j| (SCALE * xy[(j % k) * 2 + 1] + 0.5) as i64).collect();
    let steps: u64 =
        (0..k).map(|j| (px[j] - px[j + 1]).unsigned_abs().max((py[j] - py[j + 1]).unsigned_abs()) + 1).sum();
    if steps > MAX_POLYGON_STEPS {
        return Err(poly_err(format!(
            "its outline needs {steps} upsampled points, more than the limit of {MAX_POLYGON_STEPS}"
        )));
    }

    let (hf, wf) = (h as f64, w as f64);
    let mut a: Vec<u32> = Vec::new();
    let mut prev: Option<(i64, i64)> = None;
    let mut visit = |u: i64, v: i64| {
        if let Some((pu, pv)) = prev {
            if u != pu {
                let xd = (if u < pu { u } else { u - 1 }) as f64;
                let xd = (xd + 0.5) / SCALE - 0.5;
                if xd.floor() == xd && xd >= 0.0 && xd <= wf - 1.0 {
                    let yd = v.min(pv) as f64;
                    let yd = (yd + 0.5) / SCALE - 0.5;
                    let yd = if yd < 0.0 {
                        0.0
                    } else if yd > hf {
                        hf
                    } else {
                        yd
                    };
                    let yd = yd.ceil();
                    // x <= w - 1 and y <= h: fits in u32 since h * w does
                    a.push((xd as u64 * h as u64 + yd as u64) as u32);
                }
            }
        }
        prev = Some((u, v));
    };
    for j in 0..k {
        let (mut xs, mut xe, mut ys, mut ye) = (px[j], px[j + 1], py[j], py[j + 1]);
        let dx = (xe - xs).abs();
        let dy = (ys - ye).abs();
        let flip = (dx >= dy && xs > xe) || (dx < dy && ys > ye);
        if flip {
            std::mem::swap(&mut xs, &mut xe);
            std::mem::swap(&mut ys, &mut ye);
        }
        if dx == 0 && dy == 0 {
            // C divides 0 by 0 here; the point equals its neighbours, so only u matters
            visit(xs, ys);
            continue;
        }
        if dx >= dy {
            let s = (ye - ys) as f64 / dx as f64;
            for d in 0..=dx {
                let t = if flip { dx - d } else { d };
                visit(t + xs, (ys as f64 + s * t as f64 + 0.5) as i64);
            }
        } else {
            let s = (xe - xs) as f64 / dy as f64;
            for d in 0..=dy {
                let t = if flip { dy - d } else { d };
                visit((xs as f64 + s * t as f64 + 0.5) as i64, t + ys);
            }
        }
    }
    a.push(n);
    a.sort_unstable();
    let mut p = 0;
    for v in a.iter_mut() {
        let t = *v;
        *v -= p;
        p = t;
    }
    let mut b = Vec::with_capacity(a.len());
    b.push(a[0]);
    let mut j = 1;
    while j < a.len() {
        if a[j] > 0 {
            b.push(a[j]);
            j += 1;
        } else {
            j += 1;
            if j < a.len() {
                *b.last_mut().expect("b starts with one count") += a[j];
                j += 1;
            }
        }
    }
    Ok(b)
}

/// Rasterises the polygons of one object (united) to a row-major `h x w` mask of 0 and 1, as
/// pycocotools' `annToMask` does for polygon segmentations.
pub fn polygon_to_mask(polys: &[Vec<f64>], h: usize, w: usize) -> Result<Vec<u8>, MaskError> {
    let mut mask = vec![0u8; pixel_count(h, w)? as usize];
    for (i, poly) in polys.iter().enumerate() {
        let rle = polygon_to_rle(poly, h, w).map_err(|e| e.in_field(&format!("polygon {i}")))?;
        let m = rle_decode_counts(&rle, h, w)?;
        mask.iter_mut().zip(&m).for_each(|(a, &b)| *a |= b);
    }
    Ok(mask)
}

// ---------------------------------------------------------------------------------------------
// instances

/// One object instance.
#[derive(Clone, Debug, PartialEq)]
pub struct Instance {
    /// The instance id (the value in an index PNG, the annotation id in COCO JSON).
    pub id: u32,
    /// Detection confidence (1.0 for given masks).
    pub score: f32,
    /// `H x W` values in [0, 1], row-major.
    pub mask: Vec<f32>,
    /// Pixels with mask value >= 0.5.
    pub area: f64,
    /// The COCO `category_id`, where known.
    pub category: Option<u32>,
}

impl Instance {
    /// An instance with its area computed from `mask`.
    pub fn new(id: u32, score: f32, mask: Vec<f32>) -> Self {
        let area = binary_area(&mask);
        Instance { id, score, mask, area, category: None }
    }
}

/// The number of values >= 0.5.
pub fn binary_area(mask: &[f32]) -> f64 {
    mask.iter().filter(|&&v| v >= 0.5).count() as f64
}

/// The object instances of one image.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct InstanceMasks {
    pub width: usize,
    pub height: usize,
    pub masks: Vec<Instance>,
}

/// The PNG file signature.
const PNG_SIGNATURE: [u8; 8] = [0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];

impl InstanceMasks {
    /// No instances.
    pub fn new(width: usize, height: usize) -> Self {
        InstanceMasks { width, height, masks: Vec::new() }
    }

    /// One instance per distinct non-zero id of a row-major `width x height` index map (0 =
    /// background), in increasing id order, with score 1.0 and area = its pixel count.
    pub fn from_index_map(ids: &[u32], width: usize, height: usize) -> Result<Self, MaskError> {
        if Some(ids.len()) != width.checked_mul(height) {
            return Err(size_err("index map", format!("{} values for {width} x {height} pixels", ids.len())));
        }
        let mut counts: BTreeMap<u32, usize> = BTreeMap::new();
        for &id in ids.iter().filter(|&&id| id != 0) {
            *counts.entry(id).or_insert(0) += 1;
            if counts.len() > MAX_INSTANCES {
                return Err(size_err(
                    "index map",
                    format!("more than {MAX_INSTANCES} distinct instance ids (MAX_INSTANCES)"),
                ));
            }
        }
        let mut slot: BTreeMap<u32, usize> = BTreeMap::new();
        let mut masks: Vec<Instance> = Vec::with_capacity(counts.len());
        for (k, (&id, &count)) in counts.iter().enumerate() {
            slot.insert(id, k);
            masks.push(Instance { id, score: 1.0, mask: vec![0.0; ids.len()], area: count as f64, category: None });
        }
        let mut last: Option<(u32, usize)> = None;
        for (i, &id) in ids.iter().enumerate().filter(|(_, &id)| id != 0) {
            let k = match last {
                Some((lid, k)) if lid == id => k,
                _ => slot[&id],
            };
            last = Some((id, k));
            masks[k].mask[i] = 1.0;
        }
        Ok(InstanceMasks { width, height, masks })
    }

    /// Reads an instance-index PNG (the reference's `masks/NAME.png`) with the default limits;
    /// see [`from_index_png_with_limits`](Self::from_index_png_with_limits).
    pub fn from_index_png(path: &Path) -> Result<Self, MaskError> {
        Self::from_index_png_with_limits(path, &ImageLimits::default())
    }

    /// Reads an instance-index PNG: each distinct non-zero value is one instance (0 =
    /// background), as [`from_index_map`](Self::from_index_map).
    ///
    /// - 8- or 16-bit grey: the value is the id.
    /// - Grey with alpha: the value where alpha > 0, else background.
    /// - 8-bit RGB(A) (also palette PNGs, which the decoder expands to RGB): if every pixel has
    ///   R = G = B (grey saved as colour) the value R is the id; otherwise each colour is one
    ///   instance with id `R << 16 | G << 8 | B` (black = background); pixels with alpha 0 are
    ///   background.
    /// - 16-bit RGB(A) that is not grey, and anything that is not a PNG: refused.
    pub fn from_index_png_with_limits(path: &Path, limits: &ImageLimits) -> Result<Self, MaskError> {
        let mut sig = [0u8; 8];
        let is_png = std::fs::File::open(path).and_then(|mut f| f.read_exact(&mut sig)).map(|_| sig == PNG_SIGNATURE);
        if let Ok(false) = is_png {
            return Err(MaskError::IndexPng {
                path: path.to_path_buf(),
                reason: "not a PNG file (instance masks must be lossless PNGs)".into(),
            });
        }
        // other failures (missing file, short file) are reported by the decoder
        let img = decode_file(path, limits)?;
        let (w, h) = (img.width() as usize, img.height() as usize);
        let ids = index_ids(&img).map_err(|reason| MaskError::IndexPng { path: path.to_path_buf(), reason })?;
        Self::from_index_map(&ids, w, h).map_err(|e| e.prefixed(&path.display().to_string()))
    }

    /// [`from_index_png_with_limits`](Self::from_index_png_with_limits) for a PNG held in memory
    /// (a shard member, an upload), named `name` in errors.
    pub fn from_index_png_bytes(bytes: &[u8], name: &str, limits: &ImageLimits) -> Result<Self, MaskError> {
        let path = Path::new(name);
        if !bytes.starts_with(&PNG_SIGNATURE) {
            return Err(MaskError::IndexPng {
                path: path.to_path_buf(),
                reason: "not a PNG file (instance masks must be lossless PNGs)".into(),
            });
        }
        let img = crate::io::image::decode_bytes(bytes, path, limits)?;
        let (w, h) = (img.width() as usize, img.height() as usize);
        let ids = index_ids(&img).map_err(|reason| MaskError::IndexPng { path: path.to_path_buf(), reason })?;
        Self::from_index_map(&ids, w, h).map_err(|e| e.prefixed(name))
    }

    /// The index map of the instances: each pixel gets the id of the instance with the largest
    /// mask value `>= threshold` there (ties: the earlier instance), 0 where none reaches it.
    pub fn to_index_map(&self, threshold: f32) -> Vec<u32> {
        let n = self.width * self.height;
        let mut ids = vec![0u32; n];
        let mut best = vec![f32::NEG_INFINITY; n];
        for inst in &self.masks {
            for (i, &v) in inst.mask.iter().enumerate().take(n) {
                if v >= threshold && v > best[i] {
                    best[i] = v;
                    ids[i] = inst.id;
                }
            }
        }
        ids
    }

    /// Writes [`to_index_map`](Self::to_index_map)`(0.5)` as a grey PNG: 8-bit when every id is
    /// at most 255, 16-bit when at most 65535; larger ids, an id 0, or an empty image are errors.
    pub fn save_index_png(&self, path: &Path) -> Result<(), MaskError> {
        let what = path.display().to_string();
        if self.masks.iter().any(|m| m.id == 0) {
            return Err(size_err(&what, "instance id 0 cannot be told from the background"));
        }
        let max_id = self.masks.iter().map(|m| m.id).max().unwrap_or(0);
        let ids = self.to_index_map(0.5);
        if max_id <= 255 {
            let bytes: Vec<u8> = ids.iter().map(|&v| v as u8).collect();
            save_gray_png(path, self.width, self.height, &bytes)?;
        } else if max_id <= 65535 {
            let words: Vec<u16> = ids.iter().map(|&v| v as u16).collect();
            save_gray16_png(path, self.width, self.height, &words)?;
        } else {
            return Err(size_err(&what, format!("instance id {max_id} does not fit in a 16-bit PNG")));
        }
        Ok(())
    }

    /// Instances from COCO annotations: a JSON list of annotation objects, or an object with
    /// such a list under `"annotations"`. Each annotation needs `"segmentation"`: an RLE object
    /// `{"counts": string | [int], "size": [h, w]}` (the size must equal `h, w`), or a list of
    /// polygons `[[x0, y0, ...], ...]` (a flat `[x0, y0, ...]` is one polygon; polygons of fewer
    /// than 3 points are skipped, where pycocotools would read a 4-number one as a box).
    /// Optional: `"score"` (default 1.0), `"id"` (default: position + 1), `"category_id"`.
    /// Errors name the field, e.g. `annotations[3].segmentation.counts`.
    pub fn from_coco_json(value: &Value, h: usize, w: usize) -> Result<Self, MaskError> {
        pixel_count(h, w)?;
        let list = match value {
            Value::Array(a) => a,
            Value::Object(o) => match o.get("annotations") {
                Some(Value::Array(a)) => a,
                _ => return Err(json_err("annotations", "expected a list of annotations or {\"annotations\": [...]}")),
            },
            _ => return Err(json_err("annotations", "expected a list of annotations or {\"annotations\": [...]}")),
        };
        if list.len() > MAX_INSTANCES {
            return Err(size_err("annotations", format!("{} annotations, more than {MAX_INSTANCES}", list.len())));
        }
        let mut masks = Vec::with_capacity(list.len());
        for (i, ann) in list.iter().enumerate() {
            let field = format!("annotations[{i}]");
            masks.push(annotation(ann, &field, i, h, w)?);
        }
        Ok(InstanceMasks { width: w, height: h, masks })
    }

    /// [`from_coco_json`](Self::from_coco_json) of a JSON file; errors name the file.
    pub fn from_coco_json_file(path: &Path, h: usize, w: usize) -> Result<Self, MaskError> {
        let name = path.display().to_string();
        let text = std::fs::read(path).map_err(|e| {
            MaskError::Image(if e.kind() == std::io::ErrorKind::NotFound {
                ImageError::NotFound { path: path.to_path_buf() }
            } else {
                ImageError::Io { path: path.to_path_buf(), source: e }
            })
        })?;
        let value: Value = serde_json::from_slice(&text).map_err(|e| json_err(&name, format!("invalid JSON: {e}")))?;
        Self::from_coco_json(&value, h, w).map_err(|e| e.prefixed(&name))
    }

    /// Up to `k` instances to move: those with an area of at least `min_area_fraction` of the
    /// image (and not empty), by decreasing score (NaN last), then decreasing area, then
    /// increasing id, then position. Returns indices into [`masks`](Self::masks).
    pub fn select_objects(&self, k: usize, min_area_fraction: f64) -> Vec<usize> {
        let min_area = min_area_fraction * (self.width * self.height) as f64;
        let mut idx: Vec<usize> =
            (0..self.masks.len()).filter(|&i| self.masks[i].area > 0.0 && self.masks[i].area >= min_area).collect();
        let score = |i: usize| {
            let s = self.masks[i].score;
            if s.is_nan() {
                f32::NEG_INFINITY
            } else {
                s
            }
        };
        idx.sort_by(|&a, &b| {
            score(b)
                .total_cmp(&score(a))
                .then(self.masks[b].area.total_cmp(&self.masks[a].area))
                .then(self.masks[a].id.cmp(&self.masks[b].id))
                .then(a.cmp(&b))
        });
        idx.truncate(k);
        idx
    }

    /// Every mask resized with [`resize_nearest`], areas recomputed.
    pub fn resize_nearest(&self, new_width: usize, new_height: usize) -> Self {
        self.resized(new_width, new_height, resize_nearest)
    }

    /// Every mask resized with [`resize_bilinear`], areas recomputed.
    pub fn resize_bilinear(&self, new_width: usize, new_height: usize) -> Self {
        self.resized(new_width, new_height, resize_bilinear)
    }

    fn resized(&self, nw: usize, nh: usize, f: fn(&[f32], usize, usize, usize, usize) -> Vec<f32>) -> Self {
        let masks = self
            .masks
            .iter()
            .map(|m| {
                let mask = f(&m.mask, self.width, self.height, nw, nh);
                Instance { area: binary_area(&mask), mask, ..m.clone() }
            })
            .collect();
        InstanceMasks { width: nw, height: nh, masks }
    }
}

/// Instance ids of the pixels of a decoded index PNG (see `from_index_png_with_limits`).
fn index_ids(img: &DynamicImage) -> Result<Vec<u32>, String> {
    fn colour<T: Copy + Into<u32>>(raw: &[T], ch: usize, wide: bool) -> Result<Vec<u32>, String> {
        let px = || raw.chunks_exact(ch).map(|p| (p[0].into(), p[1].into(), p[2].into(), ch == 4 && p[3].into() == 0));
        let grey = px().all(|(r, g, b, transparent)| transparent || (r == g && g == b));
        if grey {
            return Ok(px().map(|(r, _, _, transparent)| if transparent { 0 } else { r }).collect());
        }
        if wide {
            return Err("a 16-bit colour PNG cannot be read as instance ids (use 8- or 16-bit grey)".into());
        }
        Ok(px().map(|(r, g, b, transparent)| if transparent { 0 } else { (r << 16) | (g << 8) | b }).collect())
    }
    fn grey_alpha<T: Copy + Into<u32>>(raw: &[T]) -> Vec<u32> {
        raw.chunks_exact(2).map(|p| if p[1].into() == 0 { 0 } else { p[0].into() }).collect()
    }
    match img {
        DynamicImage::ImageLuma8(b) => Ok(b.as_raw().iter().map(|&v| u32::from(v)).collect()),
        DynamicImage::ImageLuma16(b) => Ok(b.as_raw().iter().map(|&v| u32::from(v)).collect()),
        DynamicImage::ImageLumaA8(b) => Ok(grey_alpha(b.as_raw())),
        DynamicImage::ImageLumaA16(b) => Ok(grey_alpha(b.as_raw())),
        DynamicImage::ImageRgb8(b) => colour(b.as_raw(), 3, false),
        DynamicImage::ImageRgba8(b) => colour(b.as_raw(), 4, false),
        DynamicImage::ImageRgb16(b) => colour(b.as_raw(), 3, true),
        DynamicImage::ImageRgba16(b) => colour(b.as_raw(), 4, true),
        other => Err(format!("a {:?} image cannot be read as instance ids (use 8- or 16-bit grey)", other.color())),
    }
}

fn as_u32(v: &Value, what: &str) -> Result<u32, MaskError> {
    v.as_u64()
        .and_then(|x| u32::try_from(x).ok())
        .ok_or_else(|| json_err(what, format!("expected an integer in 0..=4294967295, found {v}")))
}

fn as_coords(v: &Value, what: &str) -> Result<Vec<f64>, MaskError> {
    let Value::Array(a) = v else {
        return Err(json_err(what, format!("expected a list of coordinates, found {}", kind(v))));
    };
    a.iter()
        .enumerate()
        .map(|(j, c)| {
            c.as_f64().ok_or_else(|| json_err(&format!("{what}[{j}]"), format!("expected a number, found {c}")))
        })
        .collect()
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "a list",
        Value::Object(_) => "an object",
    }
}

/// One COCO annotation object.
fn annotation(ann: &Value, field: &str, i: usize, h: usize, w: usize) -> Result<Instance, MaskError> {
    let Value::Object(o) = ann else {
        return Err(json_err(field, format!("expected an annotation object, found {}", kind(ann))));
    };
    let seg_field = format!("{field}.segmentation");
    let seg = o.get("segmentation").ok_or_else(|| json_err(field, "no \"segmentation\""))?;
    let mask: Vec<u8> = match seg {
        Value::Object(r) => {
            let size_field = format!("{seg_field}.size");
            let size = match r.get("size") {
                Some(Value::Array(s)) if s.len() == 2 => [as_u32(&s[0], &size_field)?, as_u32(&s[1], &size_field)?],
                _ => return Err(json_err(&size_field, "expected [height, width]")),
            };
            if (size[0] as usize, size[1] as usize) != (h, w) {
                return Err(size_err(
                    &size_field,
                    format!("RLE of {} x {} for an image of {h} x {w}", size[0], size[1]),
                ));
            }
            let counts_field = format!("{seg_field}.counts");
            let counts = match r.get("counts") {
                Some(Value::String(s)) => RleCounts::Compressed(s.clone()),
                Some(Value::Array(a)) => RleCounts::Uncompressed(
                    a.iter()
                        .enumerate()
                        .map(|(j, c)| as_u32(c, &format!("{counts_field}[{j}]")))
                        .collect::<Result<_, _>>()?,
                ),
                _ => return Err(json_err(&counts_field, "expected a compressed RLE string or a list of counts")),
            };
            rle_decode(&counts, h, w).map_err(|e| e.in_field(&counts_field))?
        }
        Value::Array(a) => {
            let polys: Vec<Vec<f64>> = if a.first().is_some_and(Value::is_number) {
                vec![as_coords(seg, &seg_field)?]
            } else {
                a.iter()
                    .enumerate()
                    .map(|(j, p)| as_coords(p, &format!("{seg_field}[{j}]")))
                    .collect::<Result<_, _>>()?
            };
            let mut mask = vec![0u8; h * w];
            for (j, p) in polys.iter().enumerate().filter(|(_, p)| p.len() >= 6 || p.len() % 2 != 0) {
                let pf = format!("{seg_field}[{j}]");
                let rle = polygon_to_rle(p, h, w).map_err(|e| e.in_field(&pf))?;
                let m = rle_decode_counts(&rle, h, w).map_err(|e| e.in_field(&pf))?;
                mask.iter_mut().zip(&m).for_each(|(a, &b)| *a |= b);
            }
            mask
        }
        other => {
            return Err(json_err(
                &seg_field,
                format!("expected an RLE object or a list of polygons, found {}", kind(other)),
            ))
        }
    };
    let score = match o.get("score") {
        None | Some(Value::Null) => 1.0,
        Some(v) => {
            v.as_f64().ok_or_else(|| json_err(&format!("{field}.score"), format!("expected a number, found {v}")))?
                as f32
        }
    };
    let id = match o.get("id") {
        None | Some(Value::Null) => u32::try_from(i + 1).unwrap_or(u32::MAX),
        Some(v) => as_u32(v, &format!("{field}.id"))?,
    };
    let category = match o.get("category_id") {
        None | Some(Value::Null) => None,
        Some(v) => Some(as_u32(v, &format!("{field}.category_id"))?),
    };
    let area = mask.iter().filter(|&&v| v != 0).count() as f64;
    Ok(Instance { id, score, mask: mask.into_iter().map(f32::from).collect(), area, category })
}

// ---------------------------------------------------------------------------------------------
// resizing

fn check_resize(len: usize, w: usize, h: usize) {
    assert_eq!(Some(len), w.checked_mul(h), "resize: mask holds {len} values, {w} x {h} needs more or fewer");
}

/// Nearest-neighbour resize of a row-major `w x h` mask to `new_w x new_h`, pixel centres
/// aligned (source pixel `floor((x + 0.5) * w / new_w)`, like PIL's NEAREST and PyTorch's
/// `nearest-exact`; OpenCV's INTER_NEAREST uses `floor(x * w / new_w)`). An empty source gives
/// zeros.
///
/// # Panics
/// If `mask.len() != w * h`.
pub fn resize_nearest(mask: &[f32], w: usize, h: usize, new_w: usize, new_h: usize) -> Vec<f32> {
    check_resize(mask.len(), w, h);
    if w == 0 || h == 0 {
        return vec![0.0; new_w * new_h];
    }
    let map = |dst: usize, src_len: usize, dst_len: usize| {
        ((((dst as f64 + 0.5) * src_len as f64 / dst_len as f64).floor()) as usize).min(src_len - 1)
    };
    let xs: Vec<usize> = (0..new_w).map(|x| map(x, w, new_w)).collect();
    let mut out = Vec::with_capacity(new_w * new_h);
    for y in 0..new_h {
        let row = &mask[map(y, h, new_h) * w..][..w];
        out.extend(xs.iter().map(|&x| row[x]));
    }
    out
}

/// Bilinear resize of a row-major `w x h` mask to `new_w x new_h`, pixel centres aligned
/// (`align_corners = false`, edges clamped; like OpenCV's INTER_LINEAR and PyTorch's bilinear
/// without antialiasing, so strong downscaling aliases). An empty source gives zeros.
///
/// # Panics
/// If `mask.len() != w * h`.
pub fn resize_bilinear(mask: &[f32], w: usize, h: usize, new_w: usize, new_h: usize) -> Vec<f32> {
    check_resize(mask.len(), w, h);
    if w == 0 || h == 0 {
        return vec![0.0; new_w * new_h];
    }
    let taps = |dst: usize, src_len: usize, dst_len: usize| {
        let s = ((dst as f64 + 0.5) * src_len as f64 / dst_len as f64 - 0.5).clamp(0.0, (src_len - 1) as f64);
        let i0 = s.floor() as usize;
        let i1 = (i0 + 1).min(src_len - 1);
        (i0, i1, (s - i0 as f64) as f32)
    };
    let xs: Vec<(usize, usize, f32)> = (0..new_w).map(|x| taps(x, w, new_w)).collect();
    let mut out = Vec::with_capacity(new_w * new_h);
    for y in 0..new_h {
        let (y0, y1, fy) = taps(y, h, new_h);
        let (r0, r1) = (&mask[y0 * w..][..w], &mask[y1 * w..][..w]);
        out.extend(xs.iter().map(|&(x0, x1, fx)| {
            let top = r0[x0] + (r0[x1] - r0[x0]) * fx;
            let bottom = r1[x0] + (r1[x1] - r1[x0]) * fx;
            top + (bottom - top) * fy
        }));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn string_codec_round_trips_the_readme_example() {
        assert_eq!(rle_from_string("7330:N").unwrap(), vec![7, 3, 3, 3, 13, 1]);
        assert_eq!(rle_to_string(&[7, 3, 3, 3, 13, 1]), "7330:N");
        assert_eq!(rle_from_string("").unwrap(), Vec::<u32>::new());
        for counts in [vec![0u32, 5, 100000, 3, 2, 4_000_000_000, 0, 1], vec![u32::MAX, 0, u32::MAX, 0, 1]] {
            assert_eq!(rle_from_string(&rle_to_string(&counts)).unwrap(), counts);
        }
    }

    #[test]
    fn string_errors() {
        for bad in ["7 3", "p", "\u{e9}", "7330:o", "_", "ooooooo0", "00N"] {
            let e = rle_from_string(bad).unwrap_err();
            assert!(matches!(e, MaskError::Rle { .. }), "{bad:?}: {e}");
        }
        // "00N": the third count is absolute and 'N' decodes to -2
        assert!(rle_from_string("00N").unwrap_err().to_string().contains("-2"));
        // from the fourth on, counts are deltas: 5, 5, 5, then 5 + (-2)
        assert_eq!(rle_from_string("555N").unwrap(), vec![5, 5, 5, 3]);
    }

    #[test]
    fn encode_decode_small() {
        let (h, w) = (3, 2);
        let mask = [0, 1, 1, 1, 0, 0];
        let c = rle_encode(&mask, h, w);
        // column-major: x=0: 0,1,0 ; x=1: 1,1,0
        assert_eq!(c, vec![1, 1, 1, 2, 1]);
        assert_eq!(rle_decode_counts(&c, h, w).unwrap(), mask);
        assert_eq!(rle_area(&c), 3);
        assert_eq!(rle_encode(&[], 0, 4), vec![0]);
        assert_eq!(rle_encode(&[0; 6], 2, 3), vec![6]);
        assert!(rle_decode_counts(&[1, 2], 2, 2).is_err());
    }

    #[test]
    fn resize_identity_and_upsample() {
        let m: Vec<f32> = (0..12).map(|v| v as f32).collect();
        assert_eq!(resize_nearest(&m, 4, 3, 4, 3), m);
        assert_eq!(resize_bilinear(&m, 4, 3, 4, 3), m);
        let up = resize_nearest(&[1.0, 0.0], 2, 1, 4, 2);
        assert_eq!(up, vec![1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0]);
        let b = resize_bilinear(&[0.0, 1.0], 2, 1, 4, 1);
        assert_eq!(b, vec![0.0, 0.25, 0.75, 1.0]);
        assert_eq!(resize_nearest(&[], 0, 0, 2, 2), vec![0.0; 4]);
    }
}
