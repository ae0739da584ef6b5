//! Rasters of a source image (a leaf: it imports only `io`, `failure` and `rng`): object instance
//! masks ([`instances`]: the [`InstanceMasks`] type, instance-index PNGs, COCO annotation JSON,
//! the choice of the objects to move), COCO run-length encodings ([`rle`]) and polygons
//! ([`polygon`]), bit-compatible with pycocotools' `maskApi.c`, and resizing ([`resize`]); the
//! [`Grid`] that row-major rasters are indexed through ([`grid`]); and the fills the stages above
//! share: dilation ([`morph`]), the push-pull pyramid ([`pushpull`]) and exemplar synthesis
//! ([`exemplar`]).
//!
//! # Conventions
//!
//! Masks are row-major `H x W` (`mask[y * W + x]`, [`Grid::index`]). COCO RLE counts are runs
//! over the **column-major** (Fortran) order of the mask, the first run counting zeros (it may be 0).
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

use crate::failure::FailureKind;
use crate::io::image::{decode_file, save_gray16_png, save_gray_png, ImageError, ImageLimits};
use ::image::DynamicImage;
use serde_json::Value;
use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

pub mod exemplar;
pub mod grid;
pub mod instances;
pub mod morph;
pub mod polygon;
pub mod pushpull;
pub mod resize;
pub mod rle;

pub use grid::{Grid, Window};
pub use instances::*;
pub use polygon::*;
pub use resize::*;
pub use rle::*;

/// The most instances one [`InstanceMasks`] may hold (each is a full-size f32 mask); more is an
/// error rather than gigabytes of masks.
pub const MAX_INSTANCES: usize = 1024;

/// The most instance-mask values an index PNG may expand to, in frames of the pixel limit:
/// `instances x width x height <= MAX_MASK_FRAMES x ImageLimits::max_pixels` (16 f32 frames:
/// 2.5 GB at the default 40 MP limit, any number of instances up to [`MAX_INSTANCES`] for small
/// images), checked before the masks are allocated.
pub const MAX_MASK_FRAMES: usize = 16;

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
    /// More instance-mask values than the budget ([`MAX_MASK_FRAMES`] frames of the pixel limit).
    #[error("{}: {reason}", .path.display())]
    TooLarge { path: PathBuf, reason: String },
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
            MaskError::TooLarge { .. } => FailureKind::TooLarge,
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

    #[test]
    fn cover_keeps_the_aspect_and_centres_the_frame() {
        // one size: nothing to do
        assert_eq!(cover(64, 48, 64, 48), (64, 48, 0, 0));
        // 451x300 into 496x368: height decides (368 / 300), the width overflows and is centred
        let (rw, rh, x0, y0) = cover(451, 300, 496, 368);
        assert_eq!((rh, y0), (368, 0));
        assert_eq!(rw, (451.0f64 * 368.0 / 300.0).round() as usize);
        assert_eq!(x0, (rw - 496) / 2);
        // a portrait photo into a landscape frame: the width decides
        assert_eq!(cover(40, 80, 80, 60), (80, 160, 0, 50));
        // crop takes the window, channel-interleaved
        let v: Vec<f32> = (0..24).map(|i| i as f32).collect(); // 4 x 3, 2 channels
        assert_eq!(crop(&v, 4, 2, 1, 1, 2, 2), [10.0, 11.0, 12.0, 13.0, 18.0, 19.0, 20.0, 21.0]);
    }

    #[test]
    fn depth_resize_is_smooth_on_a_surface_and_sharp_at_its_edges() {
        // a slanted surface (1% per row) upsampled 1.5x: strictly increasing rows, no stair
        // steps (nearest repeats every third row), the values between the source's
        let (w, h) = (4, 20);
        let ramp: Vec<f32> = (0..w * h).map(|i| 3.0 * (1.0 + 0.01 * (i / w) as f32)).collect();
        let up = resize_depth(&ramp, w, h, 6, 30);
        let col: Vec<f32> = (0..30).map(|y| up[y * 6 + 2]).collect();
        assert!(col.windows(2).all(|p| p[1] > p[0]), "stair steps: {col:?}");
        assert!(resize_nearest(&ramp, w, h, 6, 30).chunks(6).collect::<Vec<_>>().windows(2).any(|p| p[0] == p[1]));
        assert!(col.iter().all(|&d| (3.0..=3.0 * 1.19).contains(&d)));
        // an edge (depth 2 beside depth 8) stays a step: every value is one of the two
        let edge: Vec<f32> = (0..16).map(|i| if i % 4 < 2 { 2.0 } else { 8.0 }).collect();
        let e = resize_depth(&edge, 4, 4, 7, 5);
        assert!(e.iter().all(|&d| d == 2.0 || d == 8.0), "{e:?}");
        // unknown depth (0, NaN, negative) is never blended into its neighbours
        let mut holes = vec![4.0f32; 16];
        holes[5] = 0.0;
        holes[10] = f32::NAN;
        let r = resize_depth(&holes, 4, 4, 9, 9);
        assert!(r.iter().all(|&d| d == 4.0 || d == 0.0 || d.is_nan()), "{r:?}");
        assert_eq!(
            r.iter().filter(|d| d.is_nan()).count(),
            resize_nearest(&holes, 4, 4, 9, 9).iter().filter(|d| d.is_nan()).count()
        );
        // the same size is the identity
        assert_eq!(resize_depth(&ramp, w, h, w, h), ramp);
    }
}
