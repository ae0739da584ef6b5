//! WebDataset tar shards as a source: one `.tar`, or a directory of `*.tar` files (sorted by
//! name), indexed once by their headers and read member by member on demand.
//!
//! # Samples and fields
//!
//! As WebDataset groups them: a member's **key** is its path up to the first `.` of the base
//! name and its **field** is the rest (`photos/0001.depth.npy`: key `photos/0001`, field
//! `depth.npy`); a sample is a run of adjacent members sharing a key. Fields read (matched
//! case-insensitively; any other field is ignored):
//!
//! | field | meaning |
//! |---|---|
//! | `jpg`, `jpeg`, `png`, `webp` | the photo (required; the first of them in the shard's order) |
//! | `depth.npy` | float depth `[H, W]` (or `[1, H, W]`, `[H, W, 1]`, `[1, 1, H, W]`), any linear unit; non-finite or `<= 0` = unknown |
//! | `disp.npy` | float disparity `[H, W]` in the scene scale (as `disps/NAME.npy`; what `mpiflow bake --format webdataset` writes) |
//! | `depth.png`, `disp.png` | disparity in [0, 1]: 8-bit grey / 255 or 16-bit / 65535 (as `disps/NAME.png` of a directory) |
//! | `mask.png` | instance ids, 0 = background (as `masks/NAME.png`) |
//! | `mpi.npz` | a whole MPI in the reference npz layout (as `mpis/NAME.npz`; at most [`SourceOptions::max_mpi_bytes`]); not resized, so it must match the image's size |
//! | `json` | optional intrinsics `{"fx", "fy", "cx", "cy"}` in pixels of the stored image; other keys ignored |
//!
//! `depth.npy` wins over `disp.npy` over `depth.png` over `disp.png`. Sizes, resizing and intrinsics follow
//! [`SourceOptions`] exactly as for a directory (the options' intrinsics win over a sample's
//! `json`; those are scaled with a resize).
//!
//! A directory of shards with a `bake.json` ([`super::baked`], written by `mpiflow bake --format
//! webdataset`) is a baked collection: its description and `GetInfo` say what it was baked with,
//! and its fingerprint covers the bake's stage fingerprint.
//!
//! # Index, limits and damage
//!
//! [`ShardSource::open`] reads every header once (member offsets and sizes; no data), and
//! [`Source::load`] reads an item's members by offset, each refused above
//! [`ImageLimits::max_bytes`](crate::io::image::ImageLimits::max_bytes) before it is read. Item
//! ids are the keys (prefixed by `SHARD_STEM/` when a directory of shards is opened). What cannot
//! be an item is left out of the index and listed by [`ShardSource::skipped`] with a reason,
//! never a panic:
//!
//! - a key without an image field (`no image`);
//! - a key whose members are not adjacent (a second run of the same key: `duplicate key`);
//! - a **truncated shard** (a member whose data runs past the end of the file, a header cut
//!   short or corrupt, or no end-of-archive block after the last member): the shard is indexed
//!   up to its last complete sample; the sample that was being read when the data ended is
//!   left out (it may be missing members), reported as `truncated`.
//!
//! A shard with no usable sample at all is not an error as long as another shard has one; a
//! source with no items is.
//!
//! # Fingerprint
//!
//! FNV-1a 64 over the shard file names (not their folder), each item's id and its members'
//! fields and sizes, and the options that change what is loaded (resize, intrinsics), plus every
//! member's bytes with [`SourceOptions::hash_contents`].

use super::baked::BakeManifest;
use super::dir::{mpi_message, SourceOptions};
use super::encoded::{decode_item, intrinsics_from_json, DepthEncoding, Encoded, EncodedItem};
use super::{Carried, FailureKind, Fnv64, SkippedItem, Source, SourceError, SourceItem};
use crate::failure::printable;
use std::collections::HashSet;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

/// One member of a shard: where its data is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Member {
    /// The field (the base name after its first `.`), as stored.
    pub field: String,
    /// Byte offset of the data in the shard.
    pub offset: u64,
    pub size: u64,
}

/// A sample of a shard as indexed: its key and members, in the shard's order.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ShardSample {
    pub key: String,
    pub members: Vec<Member>,
}

/// What [`index_shard`] found in one shard.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ShardIndex {
    /// Complete samples in the shard's order.
    pub samples: Vec<ShardSample>,
    /// Why the index stops early, if it does (the shard is truncated or corrupt).
    pub truncated: Option<String>,
    /// The key of the sample left out because the shard ended inside it (or right after it,
    /// without an end-of-archive block).
    pub incomplete_key: Option<String>,
    /// Keys whose members were not adjacent (later runs are left out).
    pub duplicate_keys: Vec<String>,
    /// Members whose base name has no key (empty before the first `.`) or no field.
    pub unnamed: Vec<String>,
}

/// Splits a member path into (key, field) by the WebDataset rule; `None` when either is empty.
pub fn split_key(path: &str) -> Option<(String, String)> {
    let (dir, base) = match path.rfind('/') {
        Some(p) => (&path[..p + 1], &path[p + 1..]),
        None => ("", path),
    };
    let dot = base.find('.')?;
    let (stem, field) = (&base[..dot], &base[dot + 1..]);
    if stem.is_empty() || field.is_empty() {
        return None;
    }
    Some((format!("{dir}{stem}"), field.to_string()))
}

fn io_msg(e: &std::io::Error) -> String {
    if e.kind() == std::io::ErrorKind::NotFound {
        "not found".into()
    } else {
        e.to_string()
    }
}

/// Indexes one shard by its headers (see the module documentation). Only an unreadable file is an
/// error; damage inside the shard is reported in the index.
pub fn index_shard(path: &Path) -> Result<ShardIndex, SourceError> {
    let file_err = |message: String| SourceError::file(path.display().to_string(), FailureKind::Decode, message);
    let file = File::open(path).map_err(|e| file_err(io_msg(&e)))?;
    let len = file.metadata().map_err(|e| file_err(io_msg(&e)))?.len();
    let mut archive = tar::Archive::new(BufReader::new(file));
    let entries = archive.entries_with_seek().map_err(|e| file_err(io_msg(&e)))?;

    let mut index = ShardIndex::default();
    // the run being read: (key, members)
    let mut current: Option<ShardSample> = None;
    let mut seen: HashSet<String> = HashSet::new();
    let mut skipping_duplicate: Option<String> = None;
    let mut end = 0u64; // end of the last member's data
    let mut truncated: Option<String> = None;
    let mut last_key: Option<String> = None;
    for entry in entries {
        let entry = match entry {
            Ok(e) => e,
            Err(e) => {
                truncated =
                    Some(format!("unreadable tar header after byte {end} ({})", printable(&e.to_string(), 200)));
                break;
            }
        };
        let (pos, size) = (entry.raw_file_position(), entry.size());
        let name = entry.path().ok().map(|p| p.to_string_lossy().replace('\\', "/"));
        let kind = entry.header().entry_type();
        let data_end = pos.checked_add(size);
        if data_end.is_none_or(|e| e > len) {
            let what = printable(name.as_deref().unwrap_or("a member"), 200);
            truncated = Some(format!("{what} needs {size} bytes at byte {pos}, the shard has {len} bytes"));
            if let Some((key, _)) = name.as_deref().and_then(split_key) {
                last_key = Some(key);
            }
            break;
        }
        end = data_end.unwrap_or(len);
        if !matches!(kind, tar::EntryType::Regular | tar::EntryType::Continuous) {
            continue;
        }
        let Some(name) = name else {
            index.unnamed.push(format!("(member at byte {pos}: path is not valid)"));
            continue;
        };
        let name = name.strip_prefix("./").unwrap_or(&name).to_string();
        let Some((key, field)) = split_key(&name) else {
            index.unnamed.push(name);
            continue;
        };
        last_key = Some(key.clone());
        match &mut current {
            Some(s) if s.key == key => {
                s.members.push(Member { field, offset: pos, size });
                continue;
            }
            _ => {}
        }
        if skipping_duplicate.as_deref() == Some(key.as_str()) {
            continue;
        }
        if let Some(done) = current.take() {
            index.samples.push(done);
        }
        skipping_duplicate = None;
        if !seen.insert(key.clone()) {
            index.duplicate_keys.push(key.clone());
            skipping_duplicate = Some(key);
            continue;
        }
        current = Some(ShardSample { key, members: vec![Member { field, offset: pos, size }] });
    }
    if truncated.is_none() {
        // a complete archive ends with zero blocks after its last member
        let at = end.div_ceil(512) * 512;
        let mut block = [0u8; 512];
        let ok = File::open(path)
            .and_then(|mut f| {
                f.seek(SeekFrom::Start(at))?;
                f.read_exact(&mut block)
            })
            .is_ok()
            && block.iter().all(|&b| b == 0);
        if !ok {
            truncated = Some(format!("no end-of-archive block after the last member (at byte {at} of {len})"));
        }
    }
    match truncated {
        None => index.samples.extend(current),
        Some(reason) => {
            // the sample being read when the data ended may be missing members: left out
            index.incomplete_key = last_key.clone();
            match current {
                Some(s) if Some(&s.key) != last_key.as_ref() => index.samples.push(s),
                _ => {}
            }
            index.truncated = Some(reason);
        }
    }
    Ok(index)
}

#[derive(Clone, Debug)]
struct ShardFile {
    path: PathBuf,
    /// File name, as in the fingerprint and the error messages.
    name: String,
}

#[derive(Clone, Debug)]
struct Entry {
    id: String,
    shard: usize,
    key: String,
    image: Member,
    depth: Option<(DepthEncoding, Member)>,
    masks: Option<Member>,
    mpi: Option<Member>,
    json: Option<Member>,
}

/// A source over WebDataset shards; see the module documentation.
#[derive(Clone, Debug)]
pub struct ShardSource {
    root: PathBuf,
    /// Opened as a directory of shards (ids are prefixed by the shard's stem).
    from_dir: bool,
    shards: Vec<ShardFile>,
    entries: Vec<Entry>,
    skipped: Vec<SkippedItem>,
    options: SourceOptions,
    fingerprint: u64,
    /// The `bake.json` of a baked directory of shards.
    baked: Option<BakeManifest>,
}

fn field_is(m: &Member, name: &str) -> bool {
    m.field.eq_ignore_ascii_case(name)
}

/// The `.tar` shards of directory `dir` (regular files with UTF-8 names), sorted by name; none is
/// an error.
fn shard_paths(dir: &Path) -> Result<Vec<PathBuf>, SourceError> {
    let file_err = |message: String| SourceError::file(dir.display().to_string(), FailureKind::Decode, message);
    let mut v = Vec::new();
    for ent in std::fs::read_dir(dir).map_err(|e| file_err(io_msg(&e)))? {
        let ent = ent.map_err(|e| file_err(io_msg(&e)))?;
        let p = ent.path();
        let is_tar = p.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("tar"));
        if is_tar
            && std::fs::metadata(&p).is_ok_and(|m| m.is_file())
            && p.file_name().and_then(|n| n.to_str()).is_some()
        {
            v.push(p);
        }
    }
    v.sort();
    if v.is_empty() {
        return Err(file_err("no .tar shards in this directory".into()));
    }
    Ok(v)
}

impl ShardSource {
    /// Opens one `.tar` shard or a directory of them (its `*.tar` files, sorted by name; not
    /// recursive). Reads the headers only (and every member with
    /// [`SourceOptions::hash_contents`]). No shard, or no usable sample in any, is an error.
    pub fn open(path: &Path, options: &SourceOptions) -> Result<Self, SourceError> {
        let file_err = |message: String| SourceError::file(path.display().to_string(), FailureKind::Decode, message);
        let meta = std::fs::metadata(path).map_err(|e| file_err(io_msg(&e)))?;
        let (paths, prefixed) =
            if meta.is_dir() { (shard_paths(path)?, true) } else { (vec![path.to_path_buf()], false) };
        let root =
            if meta.is_dir() { path.to_path_buf() } else { path.parent().map(Path::to_path_buf).unwrap_or_default() };
        let mut shards: Vec<ShardFile> = Vec::new();
        let mut entries: Vec<Entry> = Vec::new();
        let mut skipped: Vec<SkippedItem> = Vec::new();
        for p in paths {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or_default().to_string();
            let stem = name.strip_suffix(".tar").or_else(|| name.strip_suffix(".TAR")).unwrap_or(&name).to_string();
            let shard = shards.len();
            let index = index_shard(&p)?;
            let id_of = |key: &str| if prefixed { format!("{stem}/{key}") } else { key.to_string() };
            // names come from the tar headers: reported as printable lines
            let mut skip = |item: String, kind: FailureKind, reason: String| {
                skipped.push(SkippedItem { item: printable(&item, 300), kind, reason: printable(&reason, 300) });
            };
            if let Some(reason) = &index.truncated {
                let item = match &index.incomplete_key {
                    Some(k) => format!("{name}:{k}"),
                    None => name.clone(),
                };
                skip(item, FailureKind::Truncated, format!("truncated shard: {reason}"));
            }
            for k in &index.duplicate_keys {
                skip(
                    format!("{name}:{k}"),
                    FailureKind::Duplicate,
                    "duplicate key: its members are not adjacent (the later run is left out)".into(),
                );
            }
            for m in &index.unnamed {
                skip(
                    format!("{name}:{m}"),
                    FailureKind::Unnamed,
                    "member without a key or field (KEY.FIELD expected)".into(),
                );
            }
            for s in index.samples {
                let find = |f: &str| s.members.iter().find(|m| field_is(m, f)).cloned();
                let image =
                    s.members.iter().find(|m| ["jpg", "jpeg", "png", "webp"].iter().any(|f| field_is(m, f))).cloned();
                let Some(image) = image else {
                    let fields: Vec<&str> = s.members.iter().map(|m| m.field.as_str()).collect();
                    skip(
                        format!("{name}:{}", s.key),
                        FailureKind::NoImage,
                        format!("no image (jpg, jpeg, png or webp field); fields: {}", fields.join(", ")),
                    );
                    continue;
                };
                let depth = find("depth.npy")
                    .map(|m| (DepthEncoding::Npy, m))
                    .or_else(|| find("disp.npy").map(|m| (DepthEncoding::DisparityNpy, m)))
                    .or_else(|| find("depth.png").map(|m| (DepthEncoding::DisparityPng, m)))
                    .or_else(|| find("disp.png").map(|m| (DepthEncoding::DisparityPng, m)));
                entries.push(Entry {
                    id: id_of(&s.key),
                    shard,
                    key: s.key.clone(),
                    image,
                    depth,
                    masks: find("mask.png"),
                    mpi: find("mpi.npz"),
                    json: find("json"),
                });
            }
            shards.push(ShardFile { path: p, name });
        }
        if entries.is_empty() {
            let why: Vec<String> = skipped.iter().take(5).map(|s| format!("{}: {}", s.item, s.reason)).collect();
            return Err(file_err(format!(
                "no usable samples in {} shard(s){}",
                shards.len(),
                if why.is_empty() { String::new() } else { format!(" ({})", why.join("; ")) }
            )));
        }
        let baked = if meta.is_dir() { BakeManifest::read(path)? } else { None };
        let mut src = ShardSource {
            root,
            from_dir: prefixed,
            shards,
            entries,
            skipped,
            options: *options,
            fingerprint: 0,
            baked,
        };
        src.fingerprint = src.compute_fingerprint()?;
        Ok(src)
    }

    /// Items left out of the index, with reasons (see the module documentation).
    pub fn skipped(&self) -> &[SkippedItem] {
        &self.skipped
    }

    pub fn options(&self) -> &SourceOptions {
        &self.options
    }

    /// The key (within its shard) of item `i`.
    pub fn key(&self, i: usize) -> Option<&str> {
        self.entries.get(i).map(|e| e.key.as_str())
    }

    /// The member's name in errors (printable: keys and fields come from the tar headers).
    fn member_name(&self, e: &Entry, m: &Member) -> String {
        printable(&format!("{}:{}.{}", self.shards[e.shard].name, e.key, m.field), 300)
    }

    /// Reads a member's bytes; `part` is the kind of a read failure of the member's role
    /// ([`FailureKind::Decode`] for the image and JSON, `Depth`, `Mask`).
    fn read_member(&self, file: &mut File, e: &Entry, m: &Member, part: FailureKind) -> Result<Vec<u8>, SourceError> {
        let name = self.member_name(e, m);
        let max = if part == FailureKind::Mpi { self.options.max_mpi_bytes } else { self.options.limits.max_bytes };
        if m.size > max {
            let message = format!("{} bytes is larger than the limit of {max} bytes", m.size);
            return Err(SourceError::file(name, FailureKind::TooLarge, message));
        }
        let mut buf = vec![0u8; m.size as usize];
        file.seek(SeekFrom::Start(m.offset)).and_then(|_| file.read_exact(&mut buf)).map_err(|err| {
            if err.kind() == std::io::ErrorKind::UnexpectedEof {
                let message =
                    "truncated member: the shard ends inside its data (the shard changed after it was indexed?)";
                SourceError::file(name, FailureKind::Truncated, message)
            } else {
                SourceError::file(name, part, io_msg(&err))
            }
        })?;
        Ok(buf)
    }

    /// The EXIF orientation of an item's image, from its member's first bytes
    /// ([`orientation_of_prefix`](crate::io::image::orientation_of_prefix)); `open` keeps the
    /// shard file last opened.
    fn image_orientation(&self, open: &mut Option<(usize, File)>, e: &Entry) -> Result<u8, SourceError> {
        let p = &self.shards[e.shard].path;
        let io_fail =
            |err: std::io::Error| SourceError::file(p.display().to_string(), FailureKind::Decode, io_msg(&err));
        let f = match open {
            Some((i, f)) if *i == e.shard => f,
            _ => &mut open.insert((e.shard, File::open(p).map_err(io_fail)?)).1,
        };
        let n = e.image.size.min(crate::io::image::ORIENTATION_PREFIX as u64);
        let mut buf = Vec::with_capacity(n as usize);
        f.seek(SeekFrom::Start(e.image.offset)).map_err(io_fail)?;
        f.take(n).read_to_end(&mut buf).map_err(io_fail)?;
        Ok(crate::io::image::orientation_of_prefix(&buf))
    }

    fn compute_fingerprint(&self) -> Result<u64, SourceError> {
        let mut h = Fnv64::new();
        h.str("mpiflow shard source v1");
        h.u64(self.shards.len() as u64);
        for s in &self.shards {
            h.str(&s.name);
        }
        h.u64(self.entries.len() as u64);
        let mut open: Option<(usize, File)> = None;
        for e in &self.entries {
            h.str(&e.id).u64(e.shard as u64);
            let members =
                [Some(&e.image), e.depth.as_ref().map(|(_, m)| m), e.masks.as_ref(), e.mpi.as_ref(), e.json.as_ref()];
            for m in members.into_iter().flatten() {
                h.str(&m.field).u64(m.size);
                if self.options.hash_contents {
                    if open.as_ref().map(|(i, _)| *i) != Some(e.shard) {
                        let p = &self.shards[e.shard].path;
                        let f = File::open(p).map_err(|err| {
                            SourceError::file(p.display().to_string(), FailureKind::Decode, io_msg(&err))
                        })?;
                        open = Some((e.shard, f));
                    }
                    let (_, f) = open.as_mut().expect("opened above");
                    let bytes = self.read_member(f, e, m, FailureKind::Decode)?;
                    h.bytes(&bytes);
                }
            }
            // only photos turned upright when decoded: other items keep the fingerprint they had
            let orientation = self.image_orientation(&mut open, e)?;
            if orientation != 1 {
                h.str("orientation").u64(u64::from(orientation));
            }
        }
        self.options.hash_into(&mut h);
        if let Some(m) = &self.baked {
            h.str("baked").str(&m.stage_fingerprint);
            // f32 bakes keep the fingerprint they had before f16 was offered
            if let Some(d) = m.mpi_dtype.as_deref().filter(|d| *d != "f32") {
                h.str("mpi dtype").str(d);
            }
        }
        Ok(h.finish())
    }
}

impl Source for ShardSource {
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
        let shard = &self.shards[e.shard];
        let mut file = File::open(&shard.path)
            .map_err(|err| SourceError::file(shard.path.display().to_string(), FailureKind::Decode, io_msg(&err)))?;
        let image = self.read_member(&mut file, e, &e.image, FailureKind::Decode)?;
        let depth = match &e.depth {
            Some((enc, m)) => {
                Some((*enc, self.member_name(e, m), self.read_member(&mut file, e, m, FailureKind::Depth)?))
            }
            None => None,
        };
        let masks = match &e.masks {
            Some(m) => Some((self.member_name(e, m), self.read_member(&mut file, e, m, FailureKind::Mask)?)),
            None => None,
        };
        let intrinsics = match &e.json {
            Some(m) => {
                let bytes = self.read_member(&mut file, e, m, FailureKind::Decode)?;
                let bad = |message: String| SourceError::file(self.member_name(e, m), FailureKind::Decode, message);
                let v: serde_json::Value =
                    serde_json::from_slice(&bytes).map_err(|err| bad(format!("not valid JSON: {err}")))?;
                intrinsics_from_json(&v).map_err(bad)?
            }
            None => None,
        };
        let mpi = match &e.mpi {
            Some(m) => {
                let bytes = self.read_member(&mut file, e, m, FailureKind::Mpi)?;
                let name = self.member_name(e, m);
                let bad =
                    |err: crate::mpi::MpiError| SourceError::file(name.clone(), FailureKind::Mpi, mpi_message(err));
                let mpi = crate::mpi::npz::load_npz_bytes_limited(&bytes, &name, self.options.max_mpi_bytes / 4)
                    .map_err(bad)?;
                Some(mpi)
            }
            None => None,
        };
        let mut item = decode_item(
            EncodedItem {
                id: e.id.clone(),
                image: Encoded { name: self.member_name(e, &e.image), bytes: &image },
                depth: depth.as_ref().map(|(enc, name, b)| (*enc, Encoded { name: name.clone(), bytes: b })),
                masks: masks.as_ref().map(|(name, b)| Encoded { name: name.clone(), bytes: b }),
                intrinsics,
            },
            &self.options,
        )?;
        if let Some(m) = mpi {
            if (m.width, m.height) != (item.image.width, item.image.height) {
                let name = self.member_name(e, e.mpi.as_ref().expect("read above"));
                let message = format!(
                    "the MPI is {} x {} but its image is {} x {}{}; MPIs are not resized",
                    m.width,
                    m.height,
                    item.image.width,
                    item.image.height,
                    if self.options.resize.is_some() { " after resizing" } else { "" }
                );
                return Err(SourceError::file(name, FailureKind::Mpi, message));
            }
            item.mpi = Some(m);
        }
        Ok(item)
    }

    fn fingerprint(&self) -> u64 {
        self.fingerprint
    }

    fn describe(&self) -> String {
        let skipped = if self.skipped.is_empty() { String::new() } else { format!(", {} skipped", self.skipped.len()) };
        if !self.from_dir {
            format!("shard:{} ({} samples{skipped})", self.shards[0].path.display(), self.entries.len())
        } else {
            format!(
                "shards:{} ({} shards, {} samples{skipped})",
                self.root.display(),
                self.shards.len(),
                self.entries.len()
            )
        }
    }

    fn skipped(&self) -> Vec<SkippedItem> {
        self.skipped.clone()
    }

    fn baked_with(&self) -> Option<String> {
        self.baked.as_ref().map(BakeManifest::describe)
    }

    fn carried(&self) -> Carried {
        let all = |f: fn(&Entry) -> bool| self.entries.iter().all(f);
        Carried { depth: all(|e| e.depth.is_some()), masks: all(|e| e.masks.is_some()), mpi: all(|e| e.mpi.is_some()) }
    }

    fn items_without_depth(&self) -> Option<usize> {
        Some(self.entries.iter().filter(|e| e.depth.is_none() && e.mpi.is_none()).count())
    }
}
