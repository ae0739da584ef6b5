//! Source items from encoded files held in memory (WebDataset shard members, uploads): decoding
//! under the same limits, and with the same sizing and camera rules, as [`super::DirSource`].

use super::dir::{depth_npy_from_bytes, disparity_png_from_bytes, resize_rgb, SourceOptions};
use super::{FailureKind, GivenDepth, SourceError, SourceItem};
use crate::geometry::Intrinsics;
use crate::io::image::load_rgb_from_bytes_named;
use crate::raster::{resize_depth, InstanceMasks};

/// How an encoded depth companion is read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DepthEncoding {
    /// A `.npy` float depth (any linear unit; non-finite or <= 0 = unknown).
    Npy,
    /// A grey PNG disparity in [0, 1]: 8-bit / 255, 16-bit / 65535 (as `disps/NAME.png`).
    DisparityPng,
    /// A `.npy` float disparity in the scene scale (as `disps/NAME.npy`; what `mpiflow bake`
    /// writes).
    DisparityNpy,
}

/// Sniffs a depth file's encoding from its first bytes (`.npy` magic or PNG signature).
pub fn sniff_depth(bytes: &[u8]) -> Option<DepthEncoding> {
    if bytes.starts_with(b"\x93NUMPY") {
        Some(DepthEncoding::Npy)
    } else if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        Some(DepthEncoding::DisparityPng)
    } else {
        None
    }
}

/// One encoded file and the name its errors carry (`shard.tar:key.depth.npy`, ...).
pub struct Encoded<'a> {
    pub name: String,
    pub bytes: &'a [u8],
}

/// The encoded parts of one item.
pub struct EncodedItem<'a> {
    pub id: String,
    pub image: Encoded<'a>,
    pub depth: Option<(DepthEncoding, Encoded<'a>)>,
    pub masks: Option<Encoded<'a>>,
    /// Intrinsics given with the item in pixels of its image as stored (before any resize).
    pub intrinsics: Option<Intrinsics>,
}

fn err(name: &str, kind: FailureKind, message: impl std::fmt::Display) -> SourceError {
    let m = message.to_string();
    let message = m.strip_prefix(&format!("{name}: ")).map(str::to_string).unwrap_or(m);
    SourceError::file(name, kind, message)
}

/// Decodes an item: image, depth or disparity and masks resized to the image (nearest
/// neighbour) when their size differs with the aspect kept (another aspect is an error naming
/// both shapes), then [`SourceOptions::resize`] and the intrinsics
/// ([`SourceOptions::intrinsics`] wins over the item's own, which are scaled with a resize).
pub fn decode_item(item: EncodedItem<'_>, options: &SourceOptions) -> Result<SourceItem, SourceError> {
    let limits = &options.limits;
    let mut image = load_rgb_from_bytes_named(item.image.bytes, &item.image.name, limits)
        .map_err(|e| err(&item.image.name, e.failure_kind(), e))?;
    let (w0, h0) = (image.width, image.height);
    let fit = |what: &str, name: &str, d: Vec<f32>, w: usize, h: usize| {
        super::given::fit(what, d, w, h, w0, h0).map_err(|m| err(name, FailureKind::Depth, m))
    };
    let mut depth = match &item.depth {
        Some((DepthEncoding::Npy, f)) => {
            let (w, h, d) = depth_npy_from_bytes(f.bytes, limits).map_err(|(kind, m)| err(&f.name, kind, m))?;
            Some(GivenDepth::Depth(fit("depth", &f.name, d, w, h)?))
        }
        Some((DepthEncoding::DisparityNpy, f)) => {
            let (w, h, d) = depth_npy_from_bytes(f.bytes, limits).map_err(|(kind, m)| err(&f.name, kind, m))?;
            Some(GivenDepth::Disparity(fit("disparity", &f.name, d, w, h)?))
        }
        Some((DepthEncoding::DisparityPng, f)) => {
            let (w, h, d) = disparity_png_from_bytes(f.bytes, &f.name, limits)?;
            Some(GivenDepth::Disparity(fit("disparity", &f.name, d, w, h)?))
        }
        None => None,
    };
    let mut masks = match &item.masks {
        Some(f) => {
            let m = InstanceMasks::from_index_png_bytes(f.bytes, &f.name, limits)
                .map_err(|e| err(&f.name, e.failure_kind(), e))?;
            if (m.width, m.height) != (w0, h0) {
                super::given::check_shape("masks", m.width, m.height, w0, h0)
                    .map_err(|msg| err(&f.name, FailureKind::Mask, msg))?;
                Some(m.resize_nearest(w0, h0))
            } else {
                Some(m)
            }
        }
        None => None,
    };
    let mut own_k = item.intrinsics;
    if let Some((rw, rh)) = options.resize {
        if (rw, rh) != (w0, h0) {
            if rw == 0 || rh == 0 {
                return Err(SourceError::Invalid(format!("cannot resize to {rw} x {rh}")));
            }
            image = resize_rgb(image, rw, rh);
            depth = depth.map(|d| match d {
                GivenDepth::Depth(v) => GivenDepth::Depth(resize_depth(&v, w0, h0, rw, rh)),
                GivenDepth::Disparity(v) => GivenDepth::Disparity(resize_depth(&v, w0, h0, rw, rh)),
            });
            masks = masks.map(|m| m.resize_nearest(rw, rh));
            let (sx, sy) = (rw as f64 / w0 as f64, rh as f64 / h0 as f64);
            own_k = own_k.map(|k| Intrinsics::new(k.fx * sx, k.fy * sy, k.cx * sx, k.cy * sy));
        }
    }
    let intrinsics = options.intrinsics.map(|s| s.for_size(image.width, image.height)).or(own_k);
    Ok(SourceItem { id: item.id, image, depth, masks, mpi: None, intrinsics })
}

/// Intrinsics from a JSON object's `fx`, `fy`, `cx`, `cy` (pixels); `None` when none of the four
/// is present (other keys are ignored); an error when only some are, or one is not a positive
/// finite number (`cx`, `cy`: finite).
pub fn intrinsics_from_json(v: &serde_json::Value) -> Result<Option<Intrinsics>, String> {
    let keys = ["fx", "fy", "cx", "cy"];
    let Some(obj) = v.as_object() else { return Ok(None) };
    let present: Vec<&str> = keys.iter().copied().filter(|k| obj.contains_key(*k)).collect();
    if present.is_empty() {
        return Ok(None);
    }
    if present.len() < 4 {
        return Err(format!("intrinsics need all of fx, fy, cx, cy; found only {}", present.join(", ")));
    }
    let mut vals = [0.0f64; 4];
    for (slot, k) in vals.iter_mut().zip(keys) {
        let x = obj[k].as_f64().filter(|x| x.is_finite()).ok_or_else(|| format!("`{k}` is not a finite number"))?;
        *slot = x;
    }
    if vals[0] <= 0.0 || vals[1] <= 0.0 {
        return Err(format!("focal lengths must be positive (fx = {}, fy = {})", vals[0], vals[1]));
    }
    Ok(Some(Intrinsics::new(vals[0], vals[1], vals[2], vals[3])))
}
