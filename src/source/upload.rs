//! Uploaded sources: named in-memory datasets that clients fill with images (and optional depth
//! and instance masks) as streams of chunks, under byte and image limits. The gRPC layer calls
//! this plain API: [`UploadStore::session`], [`UploadSession::push`] per chunk,
//! [`UploadSession::finish`] at the end of the stream.
//!
//! # Files and chunks
//!
//! A chunk carries `(dataset, name, kind, data)` as the proto's `SourceChunk`: `dataset` is read
//! from the first chunk of the upload (later values are ignored); a chunk with a non-empty `name`
//! starts a new file (even with the current file's name: that is the same file sent twice), an
//! empty `name` continues the current one. `kind` is `image` (PNG, JPEG or WebP), `depth` (a `.npy` float depth in any linear unit,
//! or an 8/16-bit grey PNG disparity in [0, 1], told apart by their first bytes) or `mask` (an
//! instance-id PNG). Depth and mask attach to the image of the same name, sent in the same upload
//! or already in the dataset.
//!
//! Names are **stems only**: 1 to 128 (a dataset's: 64) of `A-Z a-z 0-9 - _ .`, not starting with `.`, without
//! `..` (so no paths, ever). A file with a bad name or kind, over the per-file limit
//! ([`ImageLimits::max_bytes`](crate::io::image::ImageLimits::max_bytes)), sent twice (the same
//! name and kind anywhere in one upload: the name is rejected whole), with bytes after the end of
//! a complete PNG, JPEG or `.npy` ([`crate::io::extent`]), or that does not decode (checked at [`finish`](UploadSession::finish) by decoding it fully under the
//! image limits) is **rejected** as `name: reason` and the upload goes on; an item with a
//! rejected part is rejected whole (an image without the depth that was meant for it would make
//! other samples). Over [`UploadLimits::max_upload_bytes`] (all chunks of one upload, checked as
//! they arrive), or, at the commit, [`UploadLimits::max_total_bytes`] (everything stored, items
//! replaced by the upload no longer counted) or the dataset and item counts, the upload fails
//! with [`SourceError::Limit`] and nothing of it is stored; a malformed stream
//! (no dataset, a file without a name) fails with [`SourceError::Upload`] naming the chunk field
//! at fault.
//!
//! # Datasets
//!
//! An accepted upload is committed atomically: its items are added to the dataset (an item of an
//! existing name is replaced; a lone depth or mask replaces that part of an existing item).
//! [`UploadStore::source`] returns a snapshot: an immutable `Arc<dyn Source>` whose items are
//! sorted by name (a deterministic order) and whose fingerprint is FNV-1a 64 over every item's
//! name and each part's kind, size and content hash (and the [`SourceOptions`] that change
//! loading), so it changes whenever the content does, and does not depend on the dataset's
//! name or the upload order. Items decode exactly as a directory's would (sizes fitted,
//! [`SourceOptions::resize`], intrinsics); errors name them `upload:DATASET/KIND/NAME`.

use super::dir::SourceOptions;
use super::encoded::{decode_item, sniff_depth, DepthEncoding, Encoded, EncodedItem};
use super::{fnv1a64, Fnv64, Source, SourceError, SourceItem};
use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

/// Byte and count limits of a [`UploadStore`] (per-file and image limits are the
/// [`SourceOptions::limits`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UploadLimits {
    /// All chunks of one upload together.
    pub max_upload_bytes: u64,
    /// Everything stored, all datasets together.
    pub max_total_bytes: u64,
    /// Most datasets.
    pub max_datasets: usize,
    /// Most items in one dataset.
    pub max_items: usize,
    /// Most uploads in progress at once (sessions not yet finished or dropped).
    pub max_concurrent: usize,
    /// Most bytes held by all uploads in progress together (received, not yet committed).
    pub max_buffer_bytes: u64,
}

impl Default for UploadLimits {
    /// 256 MiB per upload, 1 GiB stored, 64 datasets of at most 100 000 items; 4 uploads in
    /// progress holding at most 512 MiB together.
    fn default() -> Self {
        UploadLimits {
            max_upload_bytes: 256 << 20,
            max_total_bytes: 1 << 30,
            max_datasets: 64,
            max_items: 100_000,
            max_concurrent: 4,
            max_buffer_bytes: 512 << 20,
        }
    }
}

/// What an upload did (the proto's `UploadSummary`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UploadSummary {
    pub dataset: String,
    /// Files accepted (images, depths and masks).
    pub accepted: u32,
    /// `name: reason` for each rejected file or item.
    pub rejected: Vec<String>,
    /// The dataset's fingerprint after the upload.
    pub fingerprint: u64,
    /// Items in the dataset after the upload.
    pub sources: u64,
}

/// A dataset in [`UploadStore::datasets`].
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UploadDatasetInfo {
    pub name: String,
    pub fingerprint: u64,
    pub sources: u64,
    /// Bytes of encoded files held.
    pub bytes: u64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Kind {
    Image,
    Depth,
    Mask,
}

impl Kind {
    fn parse(s: &str) -> Option<Self> {
        match s {
            "image" => Some(Kind::Image),
            "depth" => Some(Kind::Depth),
            "mask" => Some(Kind::Mask),
            _ => None,
        }
    }

    fn as_str(self) -> &'static str {
        match self {
            Kind::Image => "image",
            Kind::Depth => "depth",
            Kind::Mask => "mask",
        }
    }
}

/// One stored encoded file with its content hash.
#[derive(Debug)]
struct Part {
    bytes: Vec<u8>,
    hash: u64,
}

impl Part {
    fn new(bytes: Vec<u8>) -> Arc<Self> {
        let hash = fnv1a64(&bytes);
        Arc::new(Part { bytes, hash })
    }
}

/// A stored item: its encoded files.
#[derive(Clone, Debug)]
struct Item {
    image: Arc<Part>,
    depth: Option<(DepthEncoding, Arc<Part>)>,
    mask: Option<Arc<Part>>,
}

impl Item {
    fn bytes(&self) -> u64 {
        (self.image.bytes.len()
            + self.depth.as_ref().map_or(0, |(_, p)| p.bytes.len())
            + self.mask.as_ref().map_or(0, |p| p.bytes.len())) as u64
    }
}

/// Longest file name (stem) in an upload.
pub const MAX_FILE_NAME: usize = 128;
/// Longest dataset name (the names of configured datasets follow the same rule).
pub const MAX_DATASET_NAME: usize = 64;

/// Checks an upload's file name: 1 to [`MAX_FILE_NAME`] of `A-Z a-z 0-9 - _ .`, not starting
/// with `.`, no `..`.
pub fn validate_name(name: &str) -> Result<(), String> {
    validate_name_within(name, MAX_FILE_NAME)
}

/// Checks an upload's dataset name: as [`validate_name`], at most [`MAX_DATASET_NAME`] bytes.
pub fn validate_dataset_name(name: &str) -> Result<(), String> {
    validate_name_within(name, MAX_DATASET_NAME)
}

fn validate_name_within(name: &str, most: usize) -> Result<(), String> {
    if name.is_empty() {
        return Err("empty name".into());
    }
    if name.len() > most {
        return Err(format!("name of {} bytes (at most {most})", name.len()));
    }
    if let Some(c) = name.chars().find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))) {
        return Err(format!("invalid character {c:?} (names are stems: letters, digits, '-', '_', '.'; no paths)"));
    }
    if name.starts_with('.') || name.contains("..") {
        return Err("names may not start with '.' or contain '..'".into());
    }
    Ok(())
}

/// A snapshot of an upload dataset as a [`Source`] (items sorted by name).
#[derive(Clone, Debug)]
pub struct UploadSource {
    dataset: String,
    items: Vec<(String, Item)>,
    options: SourceOptions,
    fingerprint: u64,
}

impl UploadSource {
    fn new(dataset: &str, items: &BTreeMap<String, Item>, options: &SourceOptions) -> Self {
        let items: Vec<(String, Item)> = items.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        let mut h = Fnv64::new();
        h.str("mpiflow upload source v1");
        h.u64(items.len() as u64);
        for (name, item) in &items {
            h.str(name);
            h.str("image").u64(item.image.bytes.len() as u64).u64(item.image.hash);
            // only photos turned upright when decoded: other items keep the fingerprint they had
            let orientation = crate::io::image::orientation_of_prefix(&item.image.bytes);
            if orientation != 1 {
                h.str("orientation").u64(u64::from(orientation));
            }
            if let Some((enc, p)) = &item.depth {
                h.str(match enc {
                    DepthEncoding::Npy => "depth npy",
                    DepthEncoding::DisparityPng => "disparity png",
                    DepthEncoding::DisparityNpy => "disparity npy",
                });
                h.u64(p.bytes.len() as u64).u64(p.hash);
            }
            if let Some(p) = &item.mask {
                h.str("mask").u64(p.bytes.len() as u64).u64(p.hash);
            }
        }
        options.hash_into(&mut h);
        UploadSource { dataset: dataset.to_string(), items, options: *options, fingerprint: h.finish() }
    }

    pub fn dataset(&self) -> &str {
        &self.dataset
    }
}

fn part_name(dataset: &str, kind: Kind, name: &str) -> String {
    format!("upload:{dataset}/{}/{name}", kind.as_str())
}

fn decode(dataset: &str, name: &str, item: &Item, options: &SourceOptions) -> Result<SourceItem, SourceError> {
    decode_item(
        EncodedItem {
            id: name.to_string(),
            image: Encoded { name: part_name(dataset, Kind::Image, name), bytes: &item.image.bytes },
            depth: item
                .depth
                .as_ref()
                .map(|(enc, p)| (*enc, Encoded { name: part_name(dataset, Kind::Depth, name), bytes: &p.bytes })),
            masks: item.mask.as_ref().map(|p| Encoded { name: part_name(dataset, Kind::Mask, name), bytes: &p.bytes }),
            intrinsics: None,
        },
        options,
    )
}

impl Source for UploadSource {
    fn len(&self) -> usize {
        self.items.len()
    }

    fn id(&self, i: usize) -> String {
        self.items.get(i).map(|(n, _)| n.clone()).unwrap_or_default()
    }

    fn load(&self, i: usize) -> Result<SourceItem, SourceError> {
        let (name, item) = self.items.get(i).ok_or_else(|| {
            SourceError::Invalid(format!("item {i} is out of range ({} has {} items)", self.describe(), self.len()))
        })?;
        decode(&self.dataset, name, item, &self.options)
    }

    fn fingerprint(&self) -> u64 {
        self.fingerprint
    }

    fn describe(&self) -> String {
        format!("upload:{} ({} images)", self.dataset, self.items.len())
    }
}

struct Dataset {
    items: BTreeMap<String, Item>,
    snapshot: Arc<UploadSource>,
}

#[derive(Default)]
struct Inner {
    datasets: BTreeMap<String, Dataset>,
    bytes: u64,
}

/// A check of a decoded item against what the server can make of it (the server passes its
/// scene stage's `check_item`): `Err(reason)` rejects the item at the door.
pub type ItemCheck = dyn Fn(&SourceItem) -> Result<(), String> + Send + Sync;

/// Named upload datasets held in memory; see the module documentation.
pub struct UploadStore {
    options: SourceOptions,
    limits: UploadLimits,
    /// Run on every decoded item before it is accepted (none = decoding is the only check).
    check: Option<Arc<ItemCheck>>,
    /// Uploads in progress, and the bytes they hold together (the in-progress budgets).
    active: AtomicUsize,
    buffered: AtomicU64,
    inner: Mutex<Inner>,
}

impl std::fmt::Debug for UploadStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UploadStore").field("limits", &self.limits).field("datasets", &self.datasets()).finish()
    }
}

impl UploadStore {
    /// An empty store; `options` decode the items (image limits, resize, intrinsics).
    pub fn new(options: SourceOptions, limits: UploadLimits) -> Arc<Self> {
        Self::make(options, limits, None)
    }

    /// A store that also runs `check` on every decoded item and rejects, with its reason, an
    /// item that would decode but never make a sample (the server passes its scene stage's
    /// check: no depth and no depth model, unusable depth).
    pub fn with_check(options: SourceOptions, limits: UploadLimits, check: Arc<ItemCheck>) -> Arc<Self> {
        Self::make(options, limits, Some(check))
    }

    fn make(options: SourceOptions, limits: UploadLimits, check: Option<Arc<ItemCheck>>) -> Arc<Self> {
        Arc::new(UploadStore {
            options,
            limits,
            check,
            active: AtomicUsize::new(0),
            buffered: AtomicU64::new(0),
            inner: Mutex::new(Inner::default()),
        })
    }

    /// Uploads in progress now, and the bytes they hold together.
    pub fn in_progress(&self) -> (usize, u64) {
        (self.active.load(Ordering::SeqCst), self.buffered.load(Ordering::SeqCst))
    }

    fn lock(&self) -> MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    pub fn limits(&self) -> &UploadLimits {
        &self.limits
    }

    pub fn options(&self) -> &SourceOptions {
        &self.options
    }

    /// Starts an upload, or [`SourceError::Limit`] when [`UploadLimits::max_concurrent`]
    /// uploads are in progress already. The session counts until it is finished or dropped.
    pub fn session(self: &Arc<Self>) -> Result<UploadSession, SourceError> {
        let max = self.limits.max_concurrent;
        if self.active.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| (n < max).then_some(n + 1)).is_err() {
            return Err(SourceError::Limit(format!(
                "upload: {max} uploads are in progress already (max_concurrent_uploads); try again later"
            )));
        }
        Ok(UploadSession {
            store: self.clone(),
            dataset: None,
            current: None,
            files: Vec::new(),
            rejected: Vec::new(),
            rejected_names: BTreeSet::new(),
            bytes: 0,
            held: 0,
        })
    }

    /// The dataset's current snapshot (`None` if there is no such dataset).
    pub fn source(&self, dataset: &str) -> Option<Arc<UploadSource>> {
        self.lock().datasets.get(dataset).map(|d| d.snapshot.clone())
    }

    /// [`source`](Self::source) as a trait object.
    pub fn dyn_source(&self, dataset: &str) -> Option<Arc<dyn Source>> {
        self.source(dataset).map(|s| s as Arc<dyn Source>)
    }

    /// The datasets, sorted by name.
    pub fn datasets(&self) -> Vec<UploadDatasetInfo> {
        self.lock()
            .datasets
            .iter()
            .map(|(name, d)| UploadDatasetInfo {
                name: name.clone(),
                fingerprint: d.snapshot.fingerprint,
                sources: d.items.len() as u64,
                bytes: d.items.values().map(Item::bytes).sum(),
            })
            .collect()
    }

    /// Removes a dataset (snapshots already handed out stay valid); whether it existed.
    pub fn remove(&self, dataset: &str) -> bool {
        let mut inner = self.lock();
        match inner.datasets.remove(dataset) {
            Some(d) => {
                inner.bytes -= d.items.values().map(Item::bytes).sum::<u64>();
                true
            }
            None => false,
        }
    }

    /// Bytes of encoded files held, all datasets together.
    pub fn total_bytes(&self) -> u64 {
        self.lock().bytes
    }
}

/// The file being received.
struct Current {
    name: String,
    kind: Option<Kind>,
    data: Vec<u8>,
    /// Rejected already (bad name, kind, size, duplicate): further chunks are dropped.
    rejected: bool,
}

/// One upload in progress; see the module documentation.
pub struct UploadSession {
    store: Arc<UploadStore>,
    dataset: Option<String>,
    current: Option<Current>,
    /// Files received whole and not rejected: (name, kind, bytes).
    files: Vec<(String, Kind, Vec<u8>)>,
    rejected: Vec<String>,
    /// Names with a part rejected while receiving.
    rejected_names: BTreeSet<String>,
    bytes: u64,
    /// Bytes of this session counted in the store's in-progress budget.
    held: u64,
}

impl Drop for UploadSession {
    /// Gives the session's slot and bytes back to the store's in-progress budgets.
    fn drop(&mut self) {
        self.store.buffered.fetch_sub(self.held, Ordering::SeqCst);
        self.store.active.fetch_sub(1, Ordering::SeqCst);
    }
}

impl std::fmt::Debug for UploadSession {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("UploadSession")
            .field("dataset", &self.dataset)
            .field("files", &self.files.len())
            .field("bytes", &self.bytes)
            .finish()
    }
}

impl UploadSession {
    /// Whether any file of this upload so far (the one being received included) is a depth map.
    pub fn has_depth(&self) -> bool {
        self.files.iter().any(|(_, k, _)| *k == Kind::Depth)
            || self.current.as_ref().is_some_and(|c| c.kind == Some(Kind::Depth) && !c.rejected)
    }

    /// Takes one chunk (see the module documentation). An error ends the upload (nothing of it is
    /// stored); rejected files are reported by [`finish`](Self::finish).
    pub fn push(&mut self, dataset: &str, name: &str, kind: &str, data: &[u8]) -> Result<(), SourceError> {
        if self.dataset.is_none() {
            validate_dataset_name(dataset).map_err(|message| SourceError::Upload { field: "dataset", message })?;
            self.dataset = Some(dataset.to_string());
        }
        let limits = self.store.limits;
        // the budget of all uploads in progress, reserved before the bytes are kept
        let n = data.len() as u64;
        let cap = limits.max_buffer_bytes;
        if self
            .store
            .buffered
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |b| (b + n <= cap).then_some(b + n))
            .is_err()
        {
            return Err(SourceError::Limit(format!(
                "upload: uploads in progress hold {cap} bytes together already (max_upload_buffer_mb); try again later"
            )));
        }
        self.held += n;
        self.bytes += data.len() as u64;
        if self.bytes > limits.max_upload_bytes {
            return Err(SourceError::Limit(format!(
                "upload: more than {} bytes (the per-upload limit)",
                limits.max_upload_bytes
            )));
        }
        let kind_parsed = if kind.is_empty() { None } else { Some(Kind::parse(kind)) };
        // a named chunk always starts a file (the proto: the first chunk of each file names it,
        // the following ones do not), so the same name and kind twice is a second file: rejected
        let starts_new = !name.is_empty();
        if starts_new {
            self.close_current();
            let mut c =
                Current { name: name.to_string(), kind: kind_parsed.flatten(), data: Vec::new(), rejected: false };
            let reason = if let Err(m) = validate_name(name) {
                Some(m)
            } else if kind.is_empty() {
                Some("no kind (expected image, depth or mask)".to_string())
            } else if c.kind.is_none() {
                Some(format!("unknown kind {kind:?} (expected image, depth or mask)"))
            } else if self.files.iter().any(|(n, k, _)| n == name && Some(*k) == c.kind) {
                Some(format!("sent twice as {kind} in one upload"))
            } else {
                None
            };
            if let Some(r) = reason {
                self.rejected.push(format!("{}: {r}", printable(name)));
                self.rejected_names.insert(name.to_string());
                c.rejected = true;
            }
            self.current = Some(c);
        }
        let Some(c) = self.current.as_mut() else {
            return Err(SourceError::Upload {
                field: "name",
                message: "the first chunk of a file must name it".into(),
            });
        };
        if c.rejected {
            return Ok(());
        }
        let max = self.store.options.limits.max_bytes;
        if (c.data.len() + data.len()) as u64 > max {
            self.rejected.push(format!("{}: more than {max} bytes (the per-file limit)", c.name));
            self.rejected_names.insert(c.name.clone());
            c.rejected = true;
            c.data = Vec::new();
            return Ok(());
        }
        c.data.extend_from_slice(data);
        Ok(())
    }

    fn close_current(&mut self) {
        if let Some(c) = self.current.take() {
            if c.rejected {
                return;
            }
            // bytes after a complete PNG, JPEG or .npy are refused, never silently dropped
            if let Some(extra) = crate::io::extent::trailing_bytes(&c.data).filter(|&n| n > 0) {
                self.rejected.push(format!("{}: {extra} bytes after the end of the file", c.name));
                self.rejected_names.insert(c.name);
                return;
            }
            if let Some(k) = c.kind {
                self.files.push((c.name, k, c.data));
            }
        }
    }

    /// Ends the upload: checks every file by decoding it, commits what is accepted to the
    /// dataset atomically, and reports. Errors (nothing stored): no chunk at all
    /// ([`SourceError::Upload`]), a limit of the store ([`SourceError::Limit`]).
    pub fn finish(mut self) -> Result<UploadSummary, SourceError> {
        self.close_current();
        let dataset = self
            .dataset
            .clone()
            .ok_or_else(|| SourceError::Upload { field: "dataset", message: "no chunks received".into() })?;
        let store = self.store.clone();
        let options = store.options;
        let mut rejected = std::mem::take(&mut self.rejected);

        // the parts of each name sent in this upload
        let mut by_name: BTreeMap<String, BTreeMap<Kind, Vec<u8>>> = BTreeMap::new();
        for (name, kind, data) in self.files.drain(..) {
            by_name.entry(name).or_default().insert(kind, data);
        }
        // names rejected while receiving take their other parts with them
        let rejected_names = std::mem::take(&mut self.rejected_names);

        let existing: BTreeMap<String, Item> =
            store.lock().datasets.get(&dataset).map(|d| d.items.clone()).unwrap_or_default();
        let mut accepted_items: BTreeMap<String, Item> = BTreeMap::new();
        let mut accepted_files = 0u32;
        for (name, parts) in by_name {
            if rejected_names.contains(&name) {
                let kinds: Vec<&str> = parts.keys().map(|k| k.as_str()).collect();
                rejected.push(format!("{name}: not stored ({} dropped with the rejected part)", kinds.join(", ")));
                continue;
            }
            let count = parts.len() as u32;
            match checked_item(&store, &dataset, &name, parts, &existing) {
                Ok(item) => {
                    accepted_files += count;
                    accepted_items.insert(name, item);
                }
                Err(reason) => rejected.push(reason),
            }
        }

        // commit atomically under the limits
        let limits = store.limits;
        let mut inner = store.lock();
        let is_new = !inner.datasets.contains_key(&dataset);
        if is_new && inner.datasets.len() >= limits.max_datasets && !accepted_items.is_empty() {
            return Err(SourceError::Limit(format!(
                "dataset: the store holds {} datasets already",
                limits.max_datasets
            )));
        }
        let mut items = inner.datasets.get(&dataset).map(|d| d.items.clone()).unwrap_or_default();
        let old_bytes: u64 = items.values().map(Item::bytes).sum();
        for (name, item) in accepted_items {
            items.insert(name, item);
        }
        if items.len() > limits.max_items {
            return Err(SourceError::Limit(format!(
                "dataset: {} items would exceed the limit of {} per dataset",
                items.len(),
                limits.max_items
            )));
        }
        let new_bytes: u64 = items.values().map(Item::bytes).sum();
        let total = inner.bytes - old_bytes + new_bytes;
        if total > limits.max_total_bytes {
            return Err(SourceError::Limit(format!(
                "upload: the store would hold {total} bytes, over its limit of {} bytes",
                limits.max_total_bytes
            )));
        }
        let (fingerprint, sources) = if items.is_empty() {
            (UploadSource::new(&dataset, &items, &options).fingerprint, 0)
        } else {
            let snapshot = Arc::new(UploadSource::new(&dataset, &items, &options));
            let out = (snapshot.fingerprint, items.len() as u64);
            inner.bytes = total;
            inner.datasets.insert(dataset.clone(), Dataset { items, snapshot });
            out
        };
        Ok(UploadSummary { dataset, accepted: accepted_files, rejected, fingerprint, sources })
    }
}

/// The item one name's `parts` of an upload make (over the stored one in `existing` when no image
/// is sent), decoded once as a sample would and checked that it can make a scene; `Err`: the
/// report line of its rejection.
fn checked_item(
    store: &UploadStore,
    dataset: &str,
    name: &str,
    mut parts: BTreeMap<Kind, Vec<u8>>,
    existing: &BTreeMap<String, Item>,
) -> Result<Item, String> {
    let base = match parts.remove(&Kind::Image) {
        Some(bytes) => Item { image: Part::new(bytes), depth: None, mask: None },
        None => match existing.get(name) {
            Some(item) => item.clone(),
            None => return Err(format!("{name}: depth or mask without an image (send the image too)")),
        },
    };
    let mut item = base;
    if let Some(bytes) = parts.remove(&Kind::Depth) {
        match sniff_depth(&bytes) {
            Some(enc) => item.depth = Some((enc, Part::new(bytes))),
            None => return Err(format!("{name}: depth is neither a .npy array nor a PNG")),
        }
    }
    if let Some(bytes) = parts.remove(&Kind::Mask) {
        item.mask = Some(Part::new(bytes));
    }
    // decode everything once, as a sample would, and check it can make a scene
    match decode(dataset, name, &item, &store.options) {
        Err(e) => return Err(format!("{name}: {e}")),
        Ok(decoded) => {
            if let Some(Err(reason)) = store.check.as_ref().map(|c| c(&decoded)) {
                return Err(format!("{name}: {reason}"));
            }
        }
    }
    Ok(item)
}

/// A name as it may be shown in a report (control characters escaped, at most 64 characters).
fn printable(name: &str) -> String {
    let s: String = name.chars().take(64).flat_map(char::escape_debug).collect();
    if name.chars().count() > 64 {
        format!("{s}...")
    } else {
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dataset_names_stop_at_64_bytes_and_file_names_at_128() {
        let at = |n: usize| "a".repeat(n);
        assert!(validate_dataset_name(&at(MAX_DATASET_NAME)).is_ok());
        let e = validate_dataset_name(&at(MAX_DATASET_NAME + 1)).unwrap_err();
        assert_eq!(e, format!("name of {} bytes (at most 64)", MAX_DATASET_NAME + 1));
        assert!(validate_name(&at(MAX_FILE_NAME)).is_ok());
        assert!(validate_name(&at(MAX_FILE_NAME + 1)).unwrap_err().ends_with("(at most 128)"));
    }
}
