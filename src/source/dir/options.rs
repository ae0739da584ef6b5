//! What a run asks of every item of a folder: the resize, the intrinsics, the hashing of the
//! contents, following links; and the working size a folder's photos are brought to.

use crate::geometry::Intrinsics;
use crate::io::image::{ImageError, ImageLimits};
use crate::source::Fnv64;

/// Camera intrinsics set for a whole run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum IntrinsicsSpec {
    /// fx, fy, cx, cy in pixels of the image as loaded (after any resize).
    Pixels(Intrinsics),
    /// fx, cy as fractions of the width and fy, cy of the height (the reference's default is
    /// `Relative(Intrinsics::new(0.58, 0.58, 0.5, 0.5))`).
    Relative(Intrinsics),
}

impl IntrinsicsSpec {
    /// The intrinsics of a `width x height` image.
    pub fn for_size(&self, width: usize, height: usize) -> Intrinsics {
        match *self {
            IntrinsicsSpec::Pixels(k) => k,
            IntrinsicsSpec::Relative(r) => {
                let (w, h) = (width as f64, height as f64);
                Intrinsics::new(r.fx * w, r.fy * h, r.cx * w, r.cy * h)
            }
        }
    }
}

/// How a file-system source is read.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SourceOptions {
    /// Resize every item to (width, height) (the reference uses 1280 x 384); `None` keeps sizes.
    pub resize: Option<(usize, usize)>,
    /// Limits for images, depth and mask files (file size and dimensions, checked before
    /// decoding).
    pub limits: ImageLimits,
    /// Largest accepted `.npz` MPI file in bytes (MPIs are much larger than images); its arrays
    /// may hold at most `max_mpi_bytes / 4` values together (as f32), checked from their headers
    /// before they are decompressed.
    pub max_mpi_bytes: u64,
    /// Intrinsics for every item; `None` = the reference default (or the MPI's own `K`).
    pub intrinsics: Option<IntrinsicsSpec>,
    /// Also hash every file's bytes into the fingerprint (reads all files once at open).
    pub hash_contents: bool,
    /// Follow symbolic links that lead out of a folder source's root (default false: they are
    /// left out as `outside-root`). Links inside the root are followed either way; dangling links
    /// and links to what is not a regular file are left out either way.
    pub follow_links: bool,
    /// Limits of a folder's (or a single file's) photos, which are fitted to the working size or
    /// [`resize`](Self::resize) before use and so may be larger than `limits` allows (a phone's
    /// 12-megapixel photos); `None` = `limits`. Sources read as they are keep `limits`.
    pub photo_limits: Option<ImageLimits>,
    /// Check every photo of a folder when it is opened (its header, its depth's and masks'
    /// shapes) and leave those that cannot serve out of the index (default): every served photo
    /// then has equal weight. Without it, a bad photo fails when loaded and its samples use the
    /// next good photo (as shards and uploads do).
    pub check_at_open: bool,
}

impl SourceOptions {
    /// Feeds what of the options changes the items (resize, intrinsics) into a fingerprint.
    pub fn hash_into(&self, h: &mut Fnv64) {
        match self.resize {
            None => h.str("size as is"),
            Some((w, hh)) => h.str("resize").u64(w as u64).u64(hh as u64),
        };
        // depth maps of another size are resized bilinearly on surfaces (not nearest-only)
        h.str("depth resize: surface-bilinear");
        match self.intrinsics {
            None => h.str("intrinsics default"),
            Some(IntrinsicsSpec::Pixels(k)) => h.str("intrinsics px").f64(k.fx).f64(k.fy).f64(k.cx).f64(k.cy),
            Some(IntrinsicsSpec::Relative(k)) => h.str("intrinsics rel").f64(k.fx).f64(k.fy).f64(k.cx).f64(k.cy),
        };
    }
}

impl Default for SourceOptions {
    /// Sizes kept, default image limits, MPIs up to 4 GiB, reference intrinsics, fingerprint
    /// from names and sizes.
    fn default() -> Self {
        SourceOptions {
            resize: None,
            limits: ImageLimits::default(),
            max_mpi_bytes: 4 << 30,
            intrinsics: None,
            hash_contents: false,
            follow_links: false,
            photo_limits: None,
            check_at_open: true,
        }
    }
}

/// The settings that bound a folder's photos, named in every size error of a photo
/// ([`photo_limit_advice`]).
pub const PHOTO_LIMIT_SETTINGS: &str = "the limits of a folder's photos are `mpiflow serve`'s keys max_photo_pixels \
     and max_image_side (max_image_bytes for the file; TOML, or MPIFLOW_MAX_PHOTO_PIXELS and the like; `generate`, \
     `bake` and `bench` read up to 8192 pixels a side and 40000000 pixels): raise them, or shrink the photo; a \
     baseline JPEG is held to them at the reduced scale it is decoded at, a progressive JPEG, PNG or WebP at its \
     full size";

/// A photo's decoding error as a message; a size error names the settings that bound it
/// ([`PHOTO_LIMIT_SETTINGS`]).
pub fn photo_limit_advice(err: &ImageError) -> String {
    match err {
        ImageError::TooLarge { .. } | ImageError::ScaledTooLarge { .. } | ImageError::FileTooLarge { .. } => {
            format!("{err}; {PHOTO_LIMIT_SETTINGS}")
        }
        other => other.to_string(),
    }
}

/// The pixel count of the working size ([`working_size`]): that of 640 x 480.
pub const WORKING_PIXELS: usize = 640 * 480;

/// The smallest working size (width, height): RAFT's largest common training crop (496 x 368,
/// FlyingChairs) with a margin of 64 x 48 for random crop positions.
pub const WORKING_MIN: (usize, usize) = (560, 416);

/// The working size of a folder whose largest photo is `w x h` (see the documentation of `source::dir`):
/// the photo's aspect at about [`WORKING_PIXELS`] pixels, widened so that both sides cover
/// [`WORKING_MIN`], each side rounded to a multiple of 8; a photo no larger than that keeps its
/// size, and no side is ever larger than the photo's.
pub fn working_size(w: usize, h: usize) -> (usize, usize) {
    if w == 0 || h == 0 || w * h <= WORKING_PIXELS {
        return (w, h);
    }
    let (wf, hf) = (w as f64, h as f64);
    let s = (WORKING_PIXELS as f64 / (wf * hf)).sqrt().max(WORKING_MIN.0 as f64 / wf).max(WORKING_MIN.1 as f64 / hf);
    if s >= 1.0 {
        return (w, h);
    }
    // a multiple of 8, at most the photo's side rounded down to one
    let side = |v: f64, max: usize| (((v * s / 8.0).round() as usize) * 8).clamp(8, (max / 8 * 8).max(8));
    (side(wf, w), side(hf, h))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn the_working_size_of_common_photos() {
        assert_eq!(working_size(4032, 3024), (640, 480), "a phone photo");
        assert_eq!(working_size(1024, 768), (640, 480));
        assert_eq!(working_size(1920, 1080), (736, 416), "16:9 is widened to cover 416 rows");
        assert_eq!(working_size(3024, 4032), (560, 744), "a portrait photo covers 560 columns");
        assert_eq!(working_size(640, 480), (640, 480), "no larger than the working size: as it is");
        assert_eq!(working_size(1280, 384), (1280, 384), "a KITTI frame cannot cover 416 rows: as it is");
        assert_eq!(working_size(320, 240), (320, 240));
    }

    proptest! {
        /// The working size never enlarges a photo, keeps its aspect within the rounding to 8
        /// pixels, has about WORKING_PIXELS pixels unless WORKING_MIN asks for more, and covers
        /// WORKING_MIN wherever the photo does.
        #[test]
        fn the_working_size_shrinks_to_the_working_pixels_and_covers_the_crop(w in 16usize..9000, h in 16usize..9000) {
            let (ww, wh) = working_size(w, h);
            prop_assert!(ww <= w && wh <= h);
            if (ww, wh) == (w, h) {
                return Ok(());
            }
            prop_assert!(ww % 8 == 0 && wh % 8 == 0);
            let aspect = |a: usize, b: usize| a as f64 / b as f64;
            prop_assert!((aspect(ww, wh) / aspect(w, h) - 1.0).abs() < 8.0 / ww.min(wh) as f64 + 1e-9);
            for (side, min, full) in [(ww, WORKING_MIN.0, w), (wh, WORKING_MIN.1, h)] {
                prop_assert!(side + 4 >= min.min(full), "{}x{} -> {}x{}", w, h, ww, wh);
            }
            let widened = ww + 4 >= WORKING_MIN.0 && ww <= WORKING_MIN.0 + 4 || wh + 4 >= WORKING_MIN.1 && wh <= WORKING_MIN.1 + 4;
            let pixels = (ww * wh) as f64 / WORKING_PIXELS as f64;
            prop_assert!(widened || (0.95..1.05).contains(&pixels), "{}x{} -> {}x{}", w, h, ww, wh);
        }
    }
}
