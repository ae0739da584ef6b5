//! A folder's listing: the layout, the regular files and what was left out, each item's image
//! and companion files, and the frame the items are brought to.

use super::options::{photo_limit_advice, working_size};
use crate::io::image::{is_heif, read_header, read_photo_header, ImageHeader, ImageLimits, HEIC_ADVICE};
use crate::raster::cover;
use crate::source::given::{check_shape, io_err, DepthFile};
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

/// Kept area below which a photo's crop to the frame is noted: a portrait in a landscape frame
/// keeps about 56% of its area.
const CROP_NOTED: f64 = 2.0 / 3.0;

/// What fitting the photos to `frame` does that a user should know, for the source's
/// description: the photos smaller than the frame, upscaled (with the factor), and those whose
/// aspect differs so much that the centred crop keeps less than two thirds of their area (with
/// the share kept), each counted with the first few ids; empty when none.
pub(super) fn fit_notes(entries: &[Entry], headers: &[Option<ImageHeader>], frame: (usize, usize)) -> String {
    const NAMES: usize = 3;
    let (fw, fh) = frame;
    let (mut upscaled, mut cropped) = (Vec::new(), Vec::new());
    for (e, h) in entries.iter().zip(headers).filter(|(e, _)| e.mpi.is_none()) {
        let Some(h) = h else { continue };
        let (w, hh) = (h.width as usize, h.height as usize);
        if w == 0 || hh == 0 || (w, hh) == frame {
            continue;
        }
        let (rw, rh, _, _) = cover(w, hh, fw, fh);
        let scale = rw as f64 / w as f64;
        if scale > 1.0 {
            upscaled.push(format!("{} {scale:.1}x", e.id));
        }
        let kept = (fw * fh) as f64 / (rw * rh) as f64;
        if kept < CROP_NOTED {
            cropped.push(format!("{} {:.0}%", e.id, kept * 100.0));
        }
    }
    let list = |v: &[String]| {
        let more = if v.len() > NAMES { format!(", {} more", v.len() - NAMES) } else { String::new() };
        format!("{}{more}", v.iter().take(NAMES).cloned().collect::<Vec<_>>().join(", "))
    };
    let mut notes = String::new();
    if !upscaled.is_empty() {
        notes.push_str(&format!("; {} smaller than the frame, upscaled ({})", upscaled.len(), list(&upscaled)));
    }
    if !cropped.is_empty() {
        notes.push_str(&format!(
            "; {} of another aspect, cropped to under two thirds of their area ({} kept)",
            cropped.len(),
            list(&cropped)
        ));
    }
    notes
}

/// Most photos checked at once when a folder is opened (each check reads one photo's file).
const CHECK_THREADS: usize = 4;

/// What the check of one entry at open found: its photo's header, whether a companion has
/// another resolution (resized when loaded), or why the entry cannot serve.
pub(super) type Checked = Result<(Option<ImageHeader>, bool), SkippedItem>;

/// Checks every entry when the folder is opened, at most [`CHECK_THREADS`] at once: the photo's
/// header (a known format, complete as far as its header tells, within the limits) and the shape
/// of its depth, disparity and index-PNG masks against the photo's displayed shape
/// ([`check_shape`]). Results in the entries' order.
pub(super) fn check_entries(root: &Path, entries: &[Entry], limits: &ImageLimits) -> Vec<Checked> {
    let next = std::sync::atomic::AtomicUsize::new(0);
    let threads =
        std::thread::available_parallelism().map_or(1, usize::from).clamp(1, CHECK_THREADS).min(entries.len());
    let mut found: Vec<(usize, Checked)> = std::thread::scope(|s| {
        let workers: Vec<_> = (0..threads)
            .map(|_| {
                s.spawn(|| {
                    let mut out = Vec::new();
                    loop {
                        let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        let Some(e) = entries.get(i) else { break };
                        out.push((i, check_entry(root, e, limits)));
                    }
                    out
                })
            })
            .collect();
        // a worker that panicked checked nothing more: its entries are checked again below
        workers.into_iter().flat_map(|w| w.join().unwrap_or_default()).collect()
    });
    found.sort_by_key(|(i, _)| *i);
    let mut out = Vec::with_capacity(entries.len());
    let mut it = found.into_iter().peekable();
    for (i, e) in entries.iter().enumerate() {
        match it.next_if(|(j, _)| *j == i) {
            Some((_, c)) => out.push(c),
            None => out.push(check_entry(root, e, limits)),
        }
    }
    out
}

fn check_entry(root: &Path, e: &Entry, limits: &ImageLimits) -> Checked {
    let left_out = |rel: &str, kind: FailureKind, message: String| {
        let shown = root.join(rel).display().to_string();
        let reason = message.strip_prefix(&format!("{shown}: ")).map(str::to_string).unwrap_or(message);
        SkippedItem { item: rel.to_string(), kind, reason }
    };
    let header = read_photo_header(&root.join(&e.image.rel), limits)
        .map_err(|err| left_out(&e.image.rel, err.failure_kind(), photo_limit_advice(&err)))?;
    let (w0, h0) = (header.width as usize, header.height as usize);
    let mut resized = false;
    let mut companions: Vec<(&FileRef, FailureKind, &str)> = Vec::new();
    if let Some((kind, f)) = &e.depth {
        if *kind != DepthFile::Pfm {
            companions.push((f, FailureKind::Depth, "depth"));
        }
    } else if let Some(f) = &e.disparity {
        companions.push((f, FailureKind::Depth, "disparity"));
    }
    if let Some((MaskFile::IndexPng, f)) = &e.masks {
        companions.push((f, FailureKind::Mask, "masks"));
    }
    for (f, part, what) in companions {
        let p = root.join(&f.rel);
        let shape = if f.rel.to_ascii_lowercase().ends_with(".npy") {
            npy_shape(&p, limits)
        } else {
            read_header(&p, limits).map(|h| (h.width as usize, h.height as usize)).map_err(|err| {
                let kind = err.failure_kind().in_part(part);
                (kind, err.to_string())
            })
        };
        let (w, h) = shape.map_err(|(kind, m)| left_out(&f.rel, kind, m))?;
        if (w, h) != (w0, h0) {
            check_shape(what, w, h, w0, h0).map_err(|m| left_out(&f.rel, part, m))?;
            resized = true;
        }
    }
    Ok((Some(header), resized))
}

/// The (width, height) of a depth `.npy` from its header alone.
fn npy_shape(p: &Path, limits: &ImageLimits) -> Result<(usize, usize), (FailureKind, String)> {
    let fail = |m: String| (FailureKind::Depth, m);
    let size = std::fs::metadata(p).map_err(|e| fail(e.to_string()))?.len();
    if size > limits.max_bytes {
        return Err((
            FailureKind::TooLarge,
            format!("{size} bytes is larger than the limit of {} bytes", limits.max_bytes),
        ));
    }
    let mut f = std::fs::File::open(p).map_err(|e| fail(e.to_string()))?;
    crate::io::npy::check_header(&mut f, size).map_err(|e| fail(format!("not a valid .npy depth: {e}")))?;
    std::io::Seek::rewind(&mut f).map_err(|e| fail(e.to_string()))?;
    let npy =
        npyz::NpyFile::new(std::io::BufReader::new(f)).map_err(|e| fail(format!("not a valid .npy depth: {e}")))?;
    match npy.shape() {
        [h, w] | [1, h, w] | [h, w, 1] | [1, 1, h, w] => Ok((*w as usize, *h as usize)),
        s => Err(fail(format!("depth array has shape {s:?}, expected [H, W] (or [1, H, W], [H, W, 1], [1, 1, H, W])"))),
    }
}
