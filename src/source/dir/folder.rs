//! The directory source: opening a folder (or one image), its fingerprint, and loading an item
//! with its companions.

use super::listing::{
    check_entries, companions, fit_notes, frame_of, image_entries, not_images, pick, stem_of, Entry, FileRef,
    ItemFiles, Layout, Listing, MaskFile,
};
use super::options::{photo_limit_advice, SourceOptions};
use crate::io::image::{is_heif, load_photo, photo_scale, read_photo_header, RgbImage, HEIC_ADVICE};
use crate::mpi::{Mpi, MpiError};
use crate::raster::{cover, crop, resize_depth, InstanceMasks};
use crate::source::baked::BakeManifest;
use crate::source::given::DepthFile;
use crate::source::given::{check_shape, file_err, fit, io_err, over_limit};
use crate::source::given::{read_depth, read_depth_npy, read_disparity_png, resize_rgb};
use crate::source::{Carried, FailureKind, Fnv64, GivenDepth, SkippedItem, Source, SourceError, SourceItem};
use std::io::Read;
use std::path::{Path, PathBuf};

/// A directory (or single image) source; see the documentation of `source::dir`.
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
    /// The EXIF orientation of each item's photo (1 where it carries none or cannot be read):
    /// the photos that carry another are turned upright when loaded.
    oriented: Vec<u8>,
    /// Items whose depth, disparity or masks have another resolution than the photo (the same
    /// aspect): resized when loaded.
    resized: usize,
    /// The scale, in eighths, each item's photo is decoded at ([`photo_scale`]): below 8 for a
    /// baseline JPEG at least twice the size it is brought to.
    scales: Vec<u32>,
    /// The photos upscaled or cropped hard to fit the frame, for the description ([`fit_notes`]).
    fit_notes: String,
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
                let message = if is_heif(path) { HEIC_ADVICE } else { "not a .png, .jpg, .jpeg or .webp image" };
                return Err(SourceError::file(path.display().to_string(), FailureKind::Unsupported, message));
            }
            let root = path.parent().map(Path::to_path_buf).unwrap_or_default();
            (root, Layout::File, entries)
        } else if path.join("images").is_dir() {
            let files = listing.files(&path.join("images"), "images/")?;
            listing.skipped.extend(not_images(&files, "images/"));
            let mut entries = image_entries(&files, "images/");
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
            let files = listing.files(path, "")?;
            listing.skipped.extend(not_images(&files, ""));
            (path.to_path_buf(), Layout::Plain, image_entries(&files, ""))
        };
        if entries.is_empty() {
            let mut message = if layout == Layout::Reference {
                "no .png, .jpg, .jpeg or .webp images in images/".to_string()
            } else {
                "no .png, .jpg, .jpeg or .webp images (and no images/ folder)".to_string()
            };
            let heic = listing.skipped.iter().filter(|s| s.reason == HEIC_ADVICE).count();
            if heic > 0 {
                message.push_str(&format!("; {heic} HEIC/HEIF photos: not supported, convert them to JPEG"));
            }
            return Err(SourceError::file(path.display().to_string(), FailureKind::Decode, message));
        }
        let mut skipped = listing.skipped;
        // every photo checked now, so that the index holds only photos that can serve: each
        // served photo has equal weight and the scene window keeps its interleaving
        let mut kept = Vec::with_capacity(entries.len());
        let mut headers = Vec::with_capacity(entries.len());
        let mut resized = 0;
        let checks = if options.check_at_open {
            check_entries(&root, &entries, &options.limits)
        } else {
            // headers only (for the working size and the orientation); a bad photo fails when loaded
            entries
                .iter()
                .map(|e| {
                    let h = read_photo_header(&root.join(&e.image.rel), &options.limits).ok();
                    Ok((h, false))
                })
                .collect()
        };
        for (e, c) in entries.into_iter().zip(checks) {
            match c {
                Ok((h, r)) => {
                    kept.push(e);
                    headers.push(h);
                    resized += usize::from(r);
                }
                Err(s) => skipped.push(s),
            }
        }
        let entries = kept;
        skipped.sort_by(|a, b| a.item.cmp(&b.item));
        if entries.is_empty() {
            return Err(SourceError::file(
                path.display().to_string(),
                skipped.first().map_or(FailureKind::Decode, |s| s.kind),
                match skipped.iter().find(|s| s.kind != FailureKind::Unsupported).or(skipped.first()) {
                    Some(s) => format!("no photo can serve; {}; {}: {}", left_out_summary(&skipped), s.item, s.reason),
                    None => "no photo can serve".to_string(),
                },
            ));
        }
        let baked = if layout == Layout::Reference { BakeManifest::read(path)? } else { None };
        let frame = if options.resize.is_none() { frame_of(&entries, &headers) } else { None };
        let oriented = headers.iter().map(|h| h.map_or(1, |h| h.orientation)).collect();
        let scales = entries
            .iter()
            .zip(&headers)
            .map(|(e, h)| h.map_or(8, |h| photo_scale(&h, need_of(options, frame, e))))
            .collect();
        let notes = frame.map_or(String::new(), |f| fit_notes(&entries, &headers, f));
        let mut src = DirSource {
            root,
            layout,
            entries,
            options: *options,
            fingerprint: 0,
            skipped,
            baked,
            frame,
            oriented,
            resized,
            scales,
            fit_notes: notes,
        };
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
        for ((e, &o), &eighths) in self.entries.iter().zip(&self.oriented).zip(&self.scales) {
            h.str(&e.id);
            // only photos turned upright when loaded: a folder without them keeps its fingerprint
            if o != 1 {
                h.str("orientation").u64(u64::from(o));
            }
            // only photos decoded at reduced scale, likewise
            if eighths != 8 {
                h.str("decoded at eighths").u64(u64::from(eighths));
            }
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
        let (mut image, header) = load_photo(&ipath, limits, need_of(&self.options, self.frame, e))
            .map_err(|err| file_err(&ipath, err.failure_kind(), photo_limit_advice(&err)))?;
        // the photo's size as decoded (a baseline JPEG may be decoded at reduced scale) and as
        // displayed at full size (COCO annotations are in its pixels)
        let (w0, h0) = (image.width, image.height);
        let (full_w, full_h) = (header.width as usize, header.height as usize);

        let mut depth = match &e.depth {
            Some((kind, f)) => {
                let p = self.root.join(&f.rel);
                let (w, h, d) = read_depth(&p, *kind, limits)?;
                Some(GivenDepth::Depth(fit("depth", d, w, h, w0, h0).map_err(|m| file_err(&p, FailureKind::Depth, m))?))
            }
            None => match &e.disparity {
                Some(f) => {
                    let p = self.root.join(&f.rel);
                    let (w, h, d) = if f.rel.ends_with(".npy") {
                        read_depth_npy(&p, limits)?
                    } else {
                        read_disparity_png(&p, limits)?
                    };
                    let d = fit("disparity", d, w, h, w0, h0).map_err(|m| file_err(&p, FailureKind::Depth, m))?;
                    Some(GivenDepth::Disparity(d))
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
                        InstanceMasks::from_coco_json_file(&p, full_h, full_w)
                    }
                }
                .map_err(|err| file_err(&p, err.failure_kind(), err))?;
                if (m.width, m.height) != (w0, h0) {
                    check_shape("masks", m.width, m.height, w0, h0)
                        .map_err(|msg| file_err(&p, FailureKind::Mask, msg))?;
                    Some(m.resize_nearest(w0, h0))
                } else {
                    Some(m)
                }
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
                image = resize_rgb(image, rw, rh);
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
            let resized = resize_rgb(image, rw, rh);
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

/// The size an entry's photo is brought to, which its decoding must cover: the resize, else the
/// folder's frame (not for an item with its MPI, which keeps its size); `None`: kept as it is.
fn need_of(options: &SourceOptions, frame: Option<(usize, usize)>, e: &Entry) -> Option<(usize, usize)> {
    options.resize.or(frame.filter(|_| e.mpi.is_none()))
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
        let mut described = self.describe_items();
        described.push_str(&self.fit_notes);
        if self.resized > 0 {
            described.push_str(&format!("; {} with depth or masks at another resolution, resized", self.resized));
        }
        if !self.skipped.is_empty() {
            described.push_str(&format!("; {}", left_out_summary(&self.skipped)));
        }
        described
    }
}

/// `N files left out: 2 HEIC (not supported, convert to JPEG), 1 unsupported (notes.txt), ...`:
/// the entries a listing left out, counted by reason with the first few names.
pub fn left_out_summary(skipped: &[SkippedItem]) -> String {
    const NAMES: usize = 3;
    let mut by_reason: std::collections::BTreeMap<(&str, &str), Vec<&str>> = std::collections::BTreeMap::new();
    for s in skipped {
        let label = if s.reason == HEIC_ADVICE { "HEIC: not supported, convert to JPEG" } else { s.kind.as_str() };
        by_reason.entry((label, s.kind.as_str())).or_default().push(&s.item);
    }
    let parts: Vec<String> = by_reason
        .iter()
        .map(|((label, _), names)| {
            let more = if names.len() > NAMES { format!(", {} more", names.len() - NAMES) } else { String::new() };
            let shown: Vec<&str> = names.iter().take(NAMES).copied().collect();
            format!("{} {label} ({}{more})", names.len(), shown.join(", "))
        })
        .collect();
    format!("{} left out: {}", skipped.len(), parts.join(", "))
}

impl DirSource {
    /// The source as [`Source::describe`] shows it, before the entries left out.
    fn describe_items(&self) -> String {
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
