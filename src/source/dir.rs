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
//!     by [`Source::baked_with`].
//!
//!   When several depth files exist for one name, `.npy` wins over `.pfm` over `.png`; a depth file
//!   wins over a disparity PNG (it gives exact geometry); `.png` masks win over `.json`.
//! - **Plain layout**, otherwise: one item per `DIR/*.(png|jpg|jpeg)`, sorted by file name, with
//!   nothing but the image.
//! - **Single file**: a path to one image is a one-item source.
//!
//! Ids are file stems (the whole file name where two images share a stem). Listing reads file
//! names and sizes only; [`Source::load`] decodes an item's files under [`ImageLimits`], and a
//! missing or corrupt file is a [`SourceError::File`] naming the file, the problem and its
//! [`FailureKind`] (too large, truncated, else the file's role: `decode` for the image, `depth`,
//! `mask`, `mpi` for companions), for that item only.
//!
//! # Sizes and camera
//!
//! Depth, disparity and masks whose size differs from the image's are resized to it (masks by
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
//! Listing a folder leaves out, each with its [`FailureKind`] in [`Source::skipped`] (so in
//! `GetInfo` and `mpiflow_skipped_sources`): names that are not UTF-8, unreadable entries,
//! dangling symbolic links (`dangling-link`), links that lead out of the source folder, which are
//! not followed (`outside-root`) unless [`SourceOptions::follow_links`], and entries with a source file's extension that are not regular
//! files (`not-a-file`: FIFOs, devices, a directory named `x.png`). Links inside the folder are
//! followed.
//!
//! # Fingerprint
//!
//! FNV-1a 64 ([`Fnv64`]) over the layout, each item's relative file paths (`/`-separated) and
//! sizes in bytes, and the options that change what is loaded (resize, intrinsics). It does not
//! depend on where the directory is (same files, same fingerprint on every machine), but a file
//! edited in place to the same size keeps it unless [`SourceOptions::hash_contents`] is set
//! (which reads every file once at open and hashes its bytes too). A baked folder's fingerprint
//! also covers its manifest's stage fingerprint (the models it was baked with).

use super::baked::BakeManifest;
pub use super::given::DepthFile;
pub use super::given::{
    depth_npy_from_bytes, disparity_png_from_bytes, read_depth, read_depth_npy, read_disparity_png, resize_rgb,
};
use super::given::{file_err, fit, io_err, over_limit};
use super::{Carried, FailureKind, Fnv64, GivenDepth, SkippedItem, Source, SourceError, SourceItem};
use crate::geometry::Intrinsics;
use crate::io::image::{load_rgb, ImageLimits, RgbImage};
use crate::mpi::{Mpi, MpiError};
use crate::raster::{cover, crop, resize_depth, InstanceMasks};
use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};

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
        }
    }
}

/// How a [`DirSource`] found its items.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// `DIR/*.png|jpg|jpeg`.
    Plain,
    /// `DIR/images/`, `depths/`, `disps/`, `masks/`, `mpis/`.
    Reference,
    /// One image file.
    File,
}

/// The kind of a mask file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaskFile {
    IndexPng,
    CocoJson,
}

#[derive(Clone, Debug)]
struct FileRef {
    /// Relative to the root, `/`-separated.
    rel: String,
    size: u64,
}

#[derive(Clone, Debug)]
struct Entry {
    id: String,
    image: FileRef,
    depth: Option<(DepthFile, FileRef)>,
    disparity: Option<FileRef>,
    masks: Option<(MaskFile, FileRef)>,
    mpi: Option<FileRef>,
}

/// The files of one item (absolute paths).
#[derive(Clone, Debug, PartialEq)]
pub struct ItemFiles {
    pub image: PathBuf,
    pub depth: Option<(DepthFile, PathBuf)>,
    pub disparity: Option<PathBuf>,
    pub masks: Option<(MaskFile, PathBuf)>,
    pub mpi: Option<PathBuf>,
}

/// A directory (or single image) source; see the module documentation.
#[derive(Clone, Debug)]
pub struct DirSource {
    root: PathBuf,
    layout: Layout,
    entries: Vec<Entry>,
    options: SourceOptions,
    fingerprint: u64,
    /// Folder entries left out when listed (not regular files, dangling links, links out of the
    /// folder), with their reasons.
    skipped: Vec<SkippedItem>,
    /// The `bake.json` of a baked reference-layout folder.
    baked: Option<BakeManifest>,
    /// The frame every item is brought to when no [`SourceOptions::resize`] is set and the
    /// folder's photos differ in size or are larger than the working size ([`frame_of`]);
    /// `None` when they are read as they are.
    frame: Option<(usize, usize)>,
}

const IMAGE_EXTS: [&str; 3] = ["png", "jpg", "jpeg"];

fn lower_ext(name: &str) -> Option<(String, String)> {
    let p = Path::new(name);
    let ext = p.extension()?.to_str()?.to_ascii_lowercase();
    let stem = p.file_stem()?.to_str()?.to_string();
    Some((stem, ext))
}

/// Extensions of the files a folder source reads (entries with them are reported when left out).
const SOURCE_EXTENSIONS: [&str; 8] = ["png", "jpg", "jpeg", "npy", "pfm", "npz", "json", "tar"];

/// A folder listing: regular files as (name, size), sorted by name, and what was left out.
struct Listing<'a> {
    /// The canonical source root: symbolic links that lead out of it are not followed, unless
    /// `follow_links`.
    root: &'a Path,
    /// Follow links out of `root` too.
    follow_links: bool,
    /// Entries left out, with their reason (in listing order, sorted at the end).
    skipped: Vec<SkippedItem>,
}

impl Listing<'_> {
    /// Regular files of `dir` (`rel` is its path below the root, `""` or `"images/"`, ...) as
    /// (name, size), sorted by name. Left out, with a reason: names that are not UTF-8 (they
    /// cannot be ids), dangling links, links out of the root, and entries with a source file's
    /// extension that are not regular files (FIFOs, devices, directories named `x.png`);
    /// unreadable entries. Directories without such an extension are subfolders, not reported.
    fn files(&mut self, dir: &Path, rel: &str) -> Result<Vec<(String, u64)>, SourceError> {
        let rd = std::fs::read_dir(dir).map_err(|e| io_err(dir, &e, FailureKind::Decode))?;
        let mut out = Vec::new();
        for ent in rd {
            let ent = ent.map_err(|e| io_err(dir, &e, FailureKind::Decode))?;
            let path = ent.path();
            let shown = format!("{rel}{}", ent.file_name().to_string_lossy());
            let mut skip = |kind: FailureKind, reason: &str| {
                self.skipped.push(SkippedItem { item: shown.clone(), kind, reason: reason.to_string() });
            };
            let Ok(name) = ent.file_name().into_string() else {
                skip(FailureKind::Decode, "the name is not UTF-8");
                continue;
            };
            let relevant = lower_ext(&name).is_some_and(|(_, e)| SOURCE_EXTENSIONS.contains(&e.as_str()));
            let Ok(link) = std::fs::symlink_metadata(&path) else {
                skip(FailureKind::Decode, "cannot be read");
                continue;
            };
            if link.file_type().is_symlink() {
                // a linked photo is a photo, as long as it stays inside the source folder
                match std::fs::canonicalize(&path) {
                    Err(_) => {
                        skip(FailureKind::DanglingLink, "a symbolic link to nothing");
                        continue;
                    }
                    Ok(target) if !self.follow_links && !target.starts_with(self.root) => {
                        skip(FailureKind::OutsideRoot, "a symbolic link out of the source folder (not followed)");
                        continue;
                    }
                    Ok(_) => {}
                }
            }
            let Ok(meta) = std::fs::metadata(&path) else {
                skip(FailureKind::Decode, "cannot be read");
                continue;
            };
            if meta.is_file() {
                out.push((name, meta.len()));
            } else if !meta.is_dir() || relevant {
                skip(FailureKind::NotAFile, "not a regular file");
            }
        }
        out.sort();
        Ok(out)
    }
}

/// Images of a listing as (stem, name, size), with ids made unique.
fn image_entries(files: &[(String, u64)], prefix: &str) -> Vec<Entry> {
    let images: Vec<(String, String, u64)> = files
        .iter()
        .filter_map(|(name, size)| {
            let (stem, ext) = lower_ext(name)?;
            IMAGE_EXTS.contains(&ext.as_str()).then(|| (stem, name.clone(), *size))
        })
        .collect();
    let mut stem_count: HashMap<&str, usize> = HashMap::new();
    for (stem, _, _) in &images {
        *stem_count.entry(stem.as_str()).or_insert(0) += 1;
    }
    images
        .iter()
        .map(|(stem, name, size)| Entry {
            id: if stem_count[stem.as_str()] > 1 { name.clone() } else { stem.clone() },
            image: FileRef { rel: format!("{prefix}{name}"), size: *size },
            depth: None,
            disparity: None,
            masks: None,
            mpi: None,
        })
        .collect()
}

/// Companion files of a reference-layout subfolder by stem: (lower-case extension, name, size).
type Companions = HashMap<String, Vec<(String, String, u64)>>;

fn companions(listing: &mut Listing<'_>, root: &Path, sub: &str) -> Result<Companions, SourceError> {
    let dir = root.join(sub);
    let mut map: Companions = HashMap::new();
    if !dir.is_dir() {
        return Ok(map);
    }
    for (name, size) in listing.files(&dir, &format!("{sub}/"))? {
        if let Some((stem, ext)) = lower_ext(&name) {
            map.entry(stem).or_default().push((ext, name, size));
        }
    }
    Ok(map)
}

fn pick(map: &Companions, sub: &str, stem: &str, ext: &str) -> Option<FileRef> {
    map.get(stem)?
        .iter()
        .find(|(e, _, _)| e == ext)
        .map(|(_, name, size)| FileRef { rel: format!("{sub}/{name}"), size: *size })
}

fn stem_of(entry: &Entry) -> String {
    let name = entry.image.rel.rsplit('/').next().unwrap_or(&entry.image.rel);
    lower_ext(name).map(|(s, _)| s).unwrap_or_else(|| name.to_string())
}

impl DirSource {
    /// Lists a directory (reference or plain layout) or a single image file. Reads names and
    /// sizes only (and contents with [`SourceOptions::hash_contents`]). A path that does not
    /// exist, or a directory without images, is an error.
    pub fn open(path: &Path, options: &SourceOptions) -> Result<Self, SourceError> {
        let mut fitted = *options;
        if let Some(l) = options.photo_limits {
            fitted.limits = l;
        }
        let options = &fitted;
        let meta = std::fs::metadata(path).map_err(|e| io_err(path, &e, FailureKind::Decode))?;
        let canonical = std::fs::canonicalize(path).map_err(|e| io_err(path, &e, FailureKind::Decode))?;
        let mut listing = Listing { root: &canonical, follow_links: options.follow_links, skipped: Vec::new() };
        let (root, layout, entries) = if meta.is_file() {
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_string();
            let entries = image_entries(&[(name.clone(), meta.len())], "");
            if entries.is_empty() {
                return Err(SourceError::file(
                    path.display().to_string(),
                    FailureKind::Decode,
                    "not a .png, .jpg or .jpeg image",
                ));
            }
            let root = path.parent().map(Path::to_path_buf).unwrap_or_default();
            (root, Layout::File, entries)
        } else if path.join("images").is_dir() {
            let mut entries = image_entries(&listing.files(&path.join("images"), "images/")?, "images/");
            let depths = companions(&mut listing, path, "depths")?;
            let disps = companions(&mut listing, path, "disps")?;
            let masks = companions(&mut listing, path, "masks")?;
            let mpis = companions(&mut listing, path, "mpis")?;
            for e in &mut entries {
                let stem = stem_of(e);
                e.depth = pick(&depths, "depths", &stem, "npy")
                    .map(|f| (DepthFile::Npy, f))
                    .or_else(|| pick(&depths, "depths", &stem, "pfm").map(|f| (DepthFile::Pfm, f)))
                    .or_else(|| pick(&depths, "depths", &stem, "png").map(|f| (DepthFile::Png16, f)));
                e.disparity = pick(&disps, "disps", &stem, "npy").or_else(|| pick(&disps, "disps", &stem, "png"));
                e.masks = pick(&masks, "masks", &stem, "png")
                    .map(|f| (MaskFile::IndexPng, f))
                    .or_else(|| pick(&masks, "masks", &stem, "json").map(|f| (MaskFile::CocoJson, f)));
                e.mpi = pick(&mpis, "mpis", &stem, "npz");
            }
            (path.to_path_buf(), Layout::Reference, entries)
        } else {
            (path.to_path_buf(), Layout::Plain, image_entries(&listing.files(path, "")?, ""))
        };
        if entries.is_empty() {
            let message = if layout == Layout::Reference {
                "no .png, .jpg or .jpeg images in images/"
            } else {
                "no .png, .jpg or .jpeg images (and no images/ folder)"
            };
            return Err(SourceError::file(path.display().to_string(), FailureKind::Decode, message));
        }
        let mut skipped = listing.skipped;
        skipped.sort_by(|a, b| a.item.cmp(&b.item));
        let baked = if layout == Layout::Reference { BakeManifest::read(path)? } else { None };
        let frame = if options.resize.is_none() { frame_of(&root, &entries, &options.limits) } else { None };
        let mut src = DirSource { root, layout, entries, options: *options, fingerprint: 0, skipped, baked, frame };
        src.fingerprint = src.compute_fingerprint()?;
        Ok(src)
    }

    /// The folder the items' relative paths start from.
    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn layout(&self) -> Layout {
        self.layout
    }

    pub fn options(&self) -> &SourceOptions {
        &self.options
    }

    /// The files item `i` is read from (`None` when out of range).
    pub fn files(&self, i: usize) -> Option<ItemFiles> {
        let e = self.entries.get(i)?;
        let abs = |f: &FileRef| self.root.join(&f.rel);
        Some(ItemFiles {
            image: abs(&e.image),
            depth: e.depth.as_ref().map(|(k, f)| (*k, abs(f))),
            disparity: e.disparity.as_ref().map(abs),
            masks: e.masks.as_ref().map(|(k, f)| (*k, abs(f))),
            mpi: e.mpi.as_ref().map(abs),
        })
    }

    fn compute_fingerprint(&self) -> Result<u64, SourceError> {
        let mut h = Fnv64::new();
        h.str("mpiflow dir source v1");
        h.str(match self.layout {
            Layout::Plain => "plain",
            Layout::Reference => "reference",
            Layout::File => "file",
        });
        h.u64(self.entries.len() as u64);
        let file = |h: &mut Fnv64, role: &str, f: &FileRef| -> Result<(), SourceError> {
            h.str(role).str(&f.rel).u64(f.size);
            if self.options.hash_contents {
                h.u64(hash_file(&self.root.join(&f.rel))?);
            }
            Ok(())
        };
        for e in &self.entries {
            h.str(&e.id);
            file(&mut h, "image", &e.image)?;
            if let Some((_, f)) = &e.depth {
                file(&mut h, "depth", f)?;
            }
            if let Some(f) = &e.disparity {
                file(&mut h, "disparity", f)?;
            }
            if let Some((_, f)) = &e.masks {
                file(&mut h, "masks", f)?;
            }
            if let Some(f) = &e.mpi {
                file(&mut h, "mpi", f)?;
            }
        }
        self.options.hash_into(&mut h);
        // only folders of mixed sizes: a folder of one size keeps the fingerprint it had
        if let Some((fw, fh)) = self.frame {
            h.str("frame: cover, centre crop").u64(fw as u64).u64(fh as u64);
        }
        if let Some(m) = &self.baked {
            h.str("baked").str(&m.stage_fingerprint);
            // f32 bakes keep the fingerprint they had before f16 was offered
            if let Some(d) = m.mpi_dtype.as_deref().filter(|d| *d != "f32") {
                h.str("mpi dtype").str(d);
            }
        }
        Ok(h.finish())
    }

    fn load_entry(&self, e: &Entry) -> Result<SourceItem, SourceError> {
        let limits = &self.options.limits;
        let ipath = self.root.join(&e.image.rel);
        let mut image = load_rgb(&ipath, limits).map_err(|err| file_err(&ipath, err.failure_kind(), err))?;
        let (w0, h0) = (image.width, image.height);

        let mut depth = match &e.depth {
            Some((kind, f)) => {
                let p = self.root.join(&f.rel);
                let (w, h, d) = read_depth(&p, *kind, limits)?;
                Some(GivenDepth::Depth(fit(d, w, h, w0, h0)))
            }
            None => match &e.disparity {
                Some(f) => {
                    let p = self.root.join(&f.rel);
                    let (w, h, d) = if f.rel.ends_with(".npy") {
                        read_depth_npy(&p, limits)?
                    } else {
                        read_disparity_png(&p, limits)?
                    };
                    Some(GivenDepth::Disparity(fit(d, w, h, w0, h0)))
                }
                None => None,
            },
        };

        let mut masks = match &e.masks {
            Some((kind, f)) => {
                let p = self.root.join(&f.rel);
                let m = match kind {
                    MaskFile::IndexPng => InstanceMasks::from_index_png_with_limits(&p, limits),
                    MaskFile::CocoJson => {
                        let size = std::fs::metadata(&p).map_err(|err| io_err(&p, &err, FailureKind::Mask))?.len();
                        if size > limits.max_bytes {
                            return Err(file_err(&p, FailureKind::TooLarge, over_limit(size, limits)));
                        }
                        InstanceMasks::from_coco_json_file(&p, h0, w0)
                    }
                }
                .map_err(|err| file_err(&p, err.failure_kind(), err))?;
                Some(if (m.width, m.height) != (w0, h0) { m.resize_nearest(w0, h0) } else { m })
            }
            None => None,
        };

        let mpi = match &e.mpi {
            Some(f) => Some(self.read_mpi(&self.root.join(&f.rel))?),
            None => None,
        };

        if let Some((rw, rh)) = self.options.resize {
            if (rw, rh) != (w0, h0) {
                if rw == 0 || rh == 0 {
                    return Err(SourceError::Invalid(format!("cannot resize to {rw} x {rh}")));
                }
                image = resize_rgb(&image, rw, rh);
                depth = depth.map(|d| match d {
                    GivenDepth::Depth(v) => GivenDepth::Depth(resize_depth(&v, w0, h0, rw, rh)),
                    GivenDepth::Disparity(v) => GivenDepth::Disparity(resize_depth(&v, w0, h0, rw, rh)),
                });
                masks = masks.map(|m| m.resize_nearest(rw, rh));
            }
        }
        // an item with its MPI keeps its size: an MPI is never resized
        if let Some((fw, fh)) = self.frame.filter(|f| *f != (image.width, image.height) && e.mpi.is_none()) {
            // cover the frame with the aspect kept, then its centre
            let (w0, h0) = (image.width, image.height);
            let (rw, rh, x0, y0) = cover(w0, h0, fw, fh);
            let resized = resize_rgb(&image, rw, rh);
            image = RgbImage { width: fw, height: fh, data: crop(&resized.data, rw, 3, x0, y0, fw, fh) };
            let fit_depth = |v: Vec<f32>| crop(&resize_depth(&v, w0, h0, rw, rh), rw, 1, x0, y0, fw, fh);
            depth = depth.map(|d| match d {
                GivenDepth::Depth(v) => GivenDepth::Depth(fit_depth(v)),
                GivenDepth::Disparity(v) => GivenDepth::Disparity(fit_depth(v)),
            });
            masks = masks.map(|m| m.resize_nearest(rw, rh).cropped(x0, y0, fw, fh));
        }
        if let (Some(m), Some(f)) = (&mpi, &e.mpi) {
            if (m.width, m.height) != (image.width, image.height) {
                return Err(file_err(
                    &self.root.join(&f.rel),
                    FailureKind::Mpi,
                    format!(
                        "the MPI is {} x {} but its image is {} x {}{}; MPIs are not resized",
                        m.width,
                        m.height,
                        image.width,
                        image.height,
                        if self.options.resize.is_some() { " after resizing" } else { "" }
                    ),
                ));
            }
        }
        let intrinsics = self.options.intrinsics.map(|s| s.for_size(image.width, image.height));
        Ok(SourceItem { id: e.id.clone(), image, depth, masks, mpi, intrinsics })
    }

    fn read_mpi(&self, p: &Path) -> Result<Mpi, SourceError> {
        let size = std::fs::metadata(p).map_err(|e| io_err(p, &e, FailureKind::Mpi))?.len();
        if size > self.options.max_mpi_bytes {
            return Err(file_err(
                p,
                FailureKind::TooLarge,
                format!("{size} bytes is larger than the MPI limit of {} bytes", self.options.max_mpi_bytes),
            ));
        }
        let mpi = crate::mpi::npz::load_npz_limited(p, self.options.max_mpi_bytes / 4)
            .map_err(|e| file_err(p, FailureKind::Mpi, mpi_message(e)))?;
        mpi.validate().map_err(|e| file_err(p, FailureKind::Mpi, mpi_message(e)))?;
        Ok(mpi)
    }
}

/// The pixel count of the working size ([`working_size`]): that of 640 x 480.
pub const WORKING_PIXELS: usize = 640 * 480;

/// The smallest working size (width, height): RAFT's largest common training crop (496 x 368,
/// FlyingChairs) with a margin of 64 x 48 for random crop positions.
pub const WORKING_MIN: (usize, usize) = (560, 416);

/// The working size of a folder whose largest photo is `w x h` (see the module documentation):
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

/// The frame every item of a folder is brought to ([`working_size`] of its largest photo: most
/// pixels; among equals the wider, then the first listed), read from the image headers; items
/// with a given MPI are left out (they keep their size, as MPIs are never resized). `None` when
/// every readable photo has one size no larger than the working size (nothing is resized) or
/// none is readable; a photo whose header cannot be read is left out here and fails when loaded.
fn frame_of(root: &Path, entries: &[Entry], limits: &ImageLimits) -> Option<(usize, usize)> {
    let mut sizes = entries.iter().filter(|e| e.mpi.is_none()).filter_map(|e| {
        let p = root.join(&e.image.rel);
        if e.image.size > limits.max_bytes {
            return None;
        }
        let (w, h) = ::image::ImageReader::open(&p).ok()?.with_guessed_format().ok()?.into_dimensions().ok()?;
        // a photo over the limits fails when loaded: it does not set the frame
        let within =
            w <= limits.max_width && h <= limits.max_height && u64::from(w) * u64::from(h) <= limits.max_pixels;
        within.then_some((w as usize, h as usize))
    });
    let first = sizes.next()?;
    let mut mixed = false;
    let mut best = first;
    for s in sizes {
        mixed |= s != first;
        if (s.0 * s.1, s.0) > (best.0 * best.1, best.0) {
            best = s;
        }
    }
    let frame = working_size(best.0, best.1);
    (mixed || frame != best).then_some(frame)
}

pub(crate) fn mpi_message(e: MpiError) -> String {
    match e {
        MpiError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => "not found".into(),
        MpiError::Io { source, .. } => source.to_string(),
        MpiError::BadArchive { reason, .. } => format!("not a valid .npz archive: {reason}"),
        MpiError::MissingKey { key, .. } => format!("missing array `{key}`"),
        MpiError::BadShape { key, shape, expected, .. } => {
            format!("array `{key}` has shape {shape:?}, expected {expected}")
        }
        MpiError::Invalid(m) => m,
    }
}

fn hash_file(p: &Path) -> Result<u64, SourceError> {
    let f = std::fs::File::open(p).map_err(|e| io_err(p, &e, FailureKind::Decode))?;
    let mut r = std::io::BufReader::with_capacity(1 << 16, f);
    let mut h = Fnv64::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = r.read(&mut buf).map_err(|e| io_err(p, &e, FailureKind::Decode))?;
        if n == 0 {
            break;
        }
        h.bytes(&buf[..n]);
    }
    Ok(h.finish())
}

impl Source for DirSource {
    fn len(&self) -> usize {
        self.entries.len()
    }

    fn id(&self, i: usize) -> String {
        self.entries.get(i).map(|e| e.id.clone()).unwrap_or_default()
    }

    fn load(&self, i: usize) -> Result<SourceItem, SourceError> {
        let e = self.entries.get(i).ok_or_else(|| {
            SourceError::Invalid(format!("item {i} is out of range ({} has {} items)", self.describe(), self.len()))
        })?;
        self.load_entry(e)
    }

    fn fingerprint(&self) -> u64 {
        self.fingerprint
    }

    fn skipped(&self) -> Vec<SkippedItem> {
        self.skipped.clone()
    }

    fn carried(&self) -> Carried {
        let all = |f: fn(&Entry) -> bool| self.entries.iter().all(f);
        Carried {
            depth: all(|e| e.depth.is_some() || e.disparity.is_some()),
            masks: all(|e| e.masks.is_some()),
            mpi: all(|e| e.mpi.is_some()),
        }
    }

    fn baked_with(&self) -> Option<String> {
        self.baked.as_ref().map(BakeManifest::describe)
    }

    fn items_without_depth(&self) -> Option<usize> {
        Some(self.entries.iter().filter(|e| e.depth.is_none() && e.disparity.is_none() && e.mpi.is_none()).count())
    }

    fn describe(&self) -> String {
        let n = self.entries.len();
        let root = self.root.display();
        match self.layout {
            Layout::Plain => match self.frame {
                Some((w, h)) => format!("dir:{root} ({n} images, working size {w}x{h}: each covers it, centred)"),
                None => format!("dir:{root} ({n} images)"),
            },
            Layout::File => format!(
                "file:{}{}",
                self.root.join(&self.entries[0].image.rel).display(),
                self.frame.map_or(String::new(), |(w, h)| format!(" (working size {w}x{h})"))
            ),
            Layout::Reference => {
                let count = |f: fn(&Entry) -> bool| self.entries.iter().filter(|e| f(e)).count();
                format!(
                    "dir:{root} ({n} images, reference layout: {} depths, {} disparities, {} masks, {} MPIs{})",
                    count(|e| e.depth.is_some()),
                    count(|e| e.disparity.is_some()),
                    count(|e| e.masks.is_some()),
                    count(|e| e.mpi.is_some()),
                    self.frame
                        .map_or(String::new(), |(w, h)| format!("; working size {w}x{h}: each covers it, centred"))
                )
            }
        }
    }
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
