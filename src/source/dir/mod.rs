//! Sources from the file system: a directory of plain photos, a directory in the public
//! reference generator's input layout (images with optional depth, disparity, instance masks and
//! precomputed MPIs), or a single image file.
//!
//! # Layouts
//!
//! - **Reference layout**, chosen when `DIR/images/` is a folder: one item per
//!   `images/NAME.(png|jpg|jpeg)` (sorted by file name), each with optional companions sharing
//!   the image's stem `NAME`:
//!   - `depths/NAME.npy`: float depth `[H, W]` (also `[1, H, W]`, `[H, W, 1]`, `[1, 1, H, W]`; any
//!     numeric dtype), any linear unit; non-finite or `<= 0` = unknown;
//!   - `depths/NAME.pfm`: the same as a one-channel PFM (`Pf`);
//!   - `depths/NAME.png`: the same as a 16-bit grey PNG (e.g. millimetres; 0 = unknown);
//!   - `disps/NAME.png`: disparity in `[0, 1]`: an 8-bit grey PNG read as value / 255 (as the
//!     reference reads it) or a 16-bit one read as value / 65535;
//!   - `disps/NAME.npy`: disparity in `[0, 1]` as float (the shapes of `depths/NAME.npy`): what
//!     `mpiflow bake` writes, the scene's disparity bit for bit (wins over a disparity PNG);
//!   - `masks/NAME.png`: instance ids (0 = background; see
//!     [`InstanceMasks::from_index_png`](crate::raster::InstanceMasks::from_index_png)),
//!     or `masks/NAME.json`: COCO annotations (RLE or polygons);
//!   - `mpis/NAME.npz`: a whole MPI in the reference's npz layout (see [`crate::mpi::npz`]).
//!
//!   - `bake.json` (one for the folder): the manifest of `mpiflow bake` ([`super::baked`]), shown
//!     by [`Source::baked_with`](super::Source::baked_with).
//!
//!   When several depth files exist for one name, `.npy` wins over `.pfm` over `.png`; a depth file
//!   wins over a disparity PNG (it gives exact geometry); `.png` masks win over `.json`.
//! - **Plain layout**, otherwise: one item per `DIR/*.(png|jpg|jpeg)`, sorted by file name, with
//!   nothing but the image.
//! - **Single file**: a path to one image is a one-item source.
//!
//! Ids are file stems (the whole file name where two images share a stem). Listing reads file
//! names and sizes only; [`Source::load`](super::Source::load) decodes an item's files under [`ImageLimits`](crate::io::image::ImageLimits), and a
//! missing or corrupt file is a [`SourceError::File`](super::SourceError::File) naming the file, the problem and its
//! [`FailureKind`](super::FailureKind) (too large, truncated, else the file's role: `decode` for the image, `depth`,
//! `mask`, `mpi` for companions), for that item only.
//!
//! # Sizes and camera
//!
//! Photos are decoded as displayed (their EXIF orientation applied, see
//! [`crate::io::image::load_photo`]), a baseline JPEG brought to a smaller size at the smallest
//! DCT scale that still covers it ([`crate::io::scaled`]; the limits apply to the size decoded
//! at, and size errors name the settings: [`PHOTO_LIMIT_SETTINGS`]); given depth, disparity
//! and masks are taken in the orientation of the photo as displayed. Depth, disparity and masks whose aspect differs from the photo's by
//! more than a pixel of rounding fail the item, naming both shapes and the likely cause
//! ([`super::given::same_aspect`]). Those whose size differs with the aspect kept are resized to
//! the image's (masks by
//! nearest neighbour, so ids stay ids; depth and disparity bilinearly on a surface and by
//! nearest neighbour across its edges and next to unknown values, so unknown depth stays unknown
//! and no depth is invented between surfaces: [`crate::raster::resize_depth`]), as the reference
//! resizes all its inputs to one size. With [`SourceOptions::resize`] every item is resized to
//! that size: the image with an antialiasing triangle filter, depth and disparity the same way
//! as above, masks by nearest neighbour (the aspect is not kept).
//!
//! **The working size.** Without [`SourceOptions::resize`] a folder (or a single photo) is not
//! rendered at its photos' own resolution but at a working size that suits flow training
//! ([`working_size`]): the frame has the aspect of the folder's largest photo (most pixels; among
//! equals the wider, then the first listed; read from the image headers at open) and about
//! [`WORKING_PIXELS`] pixels (640 x 480 for a 4:3 photo), widened where needed so that both sides
//! cover [`WORKING_MIN`] (RAFT's largest common crop, 496 x 368, with a margin), each side a
//! multiple of 8 and never larger than the photo. Every photo of another size is resized to cover
//! that frame with its aspect kept (the image with the triangle filter, depth and masks as above)
//! and cropped to its centre ([`crate::raster::cover`]): every sample of the folder has one size,
//! so a crop that fits one sample fits every sample. A folder whose photos all have one size no
//! larger than the working size is read as it is, and so is an item with a given MPI. A given
//! MPI must have the size of the (resized) image; it is never resized. Intrinsics are the
//! reference's default (`0.58 W, 0.58 H`, centre; left to the scene stage) unless
//! [`SourceOptions::intrinsics`] sets them for the run.
//!
//! # Entries left out
//!
//! Listing a folder leaves out, each with its [`FailureKind`](super::FailureKind) in [`Source::skipped`](super::Source::skipped) (so in
//! `GetInfo` and `mpiflow_skipped_sources`): names that are not UTF-8, unreadable entries,
//! dangling symbolic links (`dangling-link`), links that lead out of the source folder, which are
//! not followed (`outside-root`) unless [`SourceOptions::follow_links`], and entries with a source file's extension that are not regular
//! files (`not-a-file`: FIFOs, devices, a directory named `x.png`). Links inside the folder are
//! followed.
//!
//! # Fingerprint
//!
//! FNV-1a 64 ([`Fnv64`](super::Fnv64)) over the layout, each item's relative file paths (`/`-separated) and
//! sizes in bytes, the EXIF orientation of each photo that carries one other than 1 (read from
//! the headers at open), and the options that change what is loaded (resize, intrinsics). It does not
//! depend on where the directory is (same files, same fingerprint on every machine), but a file
//! edited in place to the same size keeps it unless [`SourceOptions::hash_contents`] is set
//! (which reads every file once at open and hashes its bytes too). A baked folder's fingerprint
//! also covers its manifest's stage fingerprint (the models it was baked with).
//!
//! Rooms: `options` (what a run asks of every item: resize, intrinsics, the working size),
//! `listing` (the folder's listing and each item's files), `folder` (the source: opening, the
//! fingerprint, loading an item).

mod folder;
mod listing;
mod options;

pub use super::given::DepthFile;
pub use super::given::{
    depth_npy_from_bytes, disparity_png_from_bytes, read_depth, read_depth_npy, read_disparity_png, resize_rgb,
};
pub(crate) use folder::mpi_message;
pub use folder::{left_out_summary, DirSource};
pub use listing::{ItemFiles, Layout, MaskFile};
pub use options::{
    photo_limit_advice, working_size, IntrinsicsSpec, SourceOptions, PHOTO_LIMIT_SETTINGS, WORKING_MIN, WORKING_PIXELS,
};
