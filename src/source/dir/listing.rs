//! A folder's listing: the layout, the regular files and what was left out, each item's image
//! and companion files, and the frame the items are brought to.

use super::options::working_size;
use crate::io::image::{is_heif, read_header, ImageHeader, ImageLimits, HEIC_ADVICE};
use crate::source::given::{io_err, DepthFile};
use crate::source::{FailureKind, SkippedItem, SourceError};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// How a directory source found its items.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// `DIR/*.png|jpg|jpeg|webp`.
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
pub(super) struct FileRef {
    /// Relative to the root, `/`-separated.
    pub(super) rel: String,
    pub(super) size: u64,
}

#[derive(Clone, Debug)]
pub(super) struct Entry {
    pub(super) id: String,
    pub(super) image: FileRef,
    pub(super) depth: Option<(DepthFile, FileRef)>,
    pub(super) disparity: Option<FileRef>,
    pub(super) masks: Option<(MaskFile, FileRef)>,
    pub(super) mpi: Option<FileRef>,
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

pub(super) const IMAGE_EXTS: [&str; 4] = ["png", "jpg", "jpeg", "webp"];

pub(super) fn lower_ext(name: &str) -> Option<(String, String)> {
    let p = Path::new(name);
    let ext = p.extension()?.to_str()?.to_ascii_lowercase();
    let stem = p.file_stem()?.to_str()?.to_string();
    Some((stem, ext))
}

/// Extensions of the files a folder source reads (entries with them are reported when left out).
pub(super) const SOURCE_EXTENSIONS: [&str; 9] = ["png", "jpg", "jpeg", "webp", "npy", "pfm", "npz", "json", "tar"];

/// A folder listing: regular files as (name, size), sorted by name, and what was left out.
pub(super) struct Listing<'a> {
    /// The canonical source root: symbolic links that lead out of it are not followed, unless
    /// `follow_links`.
    pub(super) root: &'a Path,
    /// Follow links out of `root` too.
    pub(super) follow_links: bool,
    /// Entries left out, with their reason (in listing order, sorted at the end).
    pub(super) skipped: Vec<SkippedItem>,
}

impl Listing<'_> {
    /// Regular files of `dir` (`rel` is its path below the root, `""` or `"images/"`, ...) as
    /// (name, size), sorted by name. Left out, with a reason: names that are not UTF-8 (they
    /// cannot be ids), dangling links, links out of the root, and entries with a source file's
    /// extension that are not regular files (FIFOs, devices, directories named `x.png`);
    /// unreadable entries. Directories without such an extension are subfolders, not reported.
    pub(super) fn files(&mut self, dir: &Path, rel: &str) -> Result<Vec<(String, u64)>, SourceError> {
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

/// The files of a photo folder (a plain folder, or `images/`) that are not photos mpiflow reads,
/// each with its reason: HEIC/HEIF photos ([`HEIC_ADVICE`]), other files (`unsupported`).
pub(super) fn not_images(files: &[(String, u64)], prefix: &str) -> Vec<SkippedItem> {
    files
        .iter()
        .filter(|(name, _)| !lower_ext(name).is_some_and(|(_, e)| IMAGE_EXTS.contains(&e.as_str())))
        .map(|(name, _)| SkippedItem {
            item: format!("{prefix}{name}"),
            kind: FailureKind::Unsupported,
            reason: if is_heif(Path::new(name)) {
                HEIC_ADVICE.to_string()
            } else {
                "not a photo mpiflow reads (PNG, JPEG or WebP)".to_string()
            },
        })
        .collect()
}

/// Images of a listing as (stem, name, size), with ids made unique.
pub(super) fn image_entries(files: &[(String, u64)], prefix: &str) -> Vec<Entry> {
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
pub(super) type Companions = HashMap<String, Vec<(String, String, u64)>>;

pub(super) fn companions(listing: &mut Listing<'_>, root: &Path, sub: &str) -> Result<Companions, SourceError> {
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

pub(super) fn pick(map: &Companions, sub: &str, stem: &str, ext: &str) -> Option<FileRef> {
    map.get(stem)?
        .iter()
        .find(|(e, _, _)| e == ext)
        .map(|(_, name, size)| FileRef { rel: format!("{sub}/{name}"), size: *size })
}

pub(super) fn stem_of(entry: &Entry) -> String {
    let name = entry.image.rel.rsplit('/').next().unwrap_or(&entry.image.rel);
    lower_ext(name).map(|(s, _)| s).unwrap_or_else(|| name.to_string())
}

/// The frame every item of a folder is brought to ([`working_size`] of its largest photo as
/// displayed: most pixels; among equals the wider, then the first listed), from the image
/// headers (`headers[i]` of `entries[i]`, `None` where it cannot be read); items with a given MPI
/// are left out (they keep their size, as MPIs are never resized). `None` when every readable
/// photo has one size no larger than the working size (nothing is resized) or none is readable;
/// a photo whose header cannot be read, or that is over the limits, does not set the frame.
pub(super) fn frame_of(entries: &[Entry], headers: &[Option<ImageHeader>]) -> Option<(usize, usize)> {
    let mut sizes = entries
        .iter()
        .zip(headers)
        .filter(|(e, _)| e.mpi.is_none())
        .filter_map(|(_, h)| h.map(|h| (h.width as usize, h.height as usize)));
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

/// The header of each entry's photo (`None` where it cannot be read or is over the limits).
pub(super) fn headers_of(root: &Path, entries: &[Entry], limits: &ImageLimits) -> Vec<Option<ImageHeader>> {
    entries.iter().map(|e| read_header(&root.join(&e.image.rel), limits).ok()).collect()
}
