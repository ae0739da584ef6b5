//! `mpiflow bake`: runs the scene models once per source item and writes what serving needs so
//! that it runs no model: the reference layout the directory source reads, plus a `bake.json`
//! manifest ([`crate::source::baked`]) and a report.
//!
//! # Output (`OUT/`)
//!
//! | member | what | exact? |
//! |---|---|---|
//! | `images/ID.png` | the image the models saw (8-bit RGB PNG; a resized or 16-bit image is rounded to 8 bits before the models run) | bit for bit |
//! | `disps/ID.npy` | the scene's disparity, float32 `[H, W]` in the scene scale | bit for bit: the served scene's disparity is the baked one |
//! | `masks/ID.png` | the scene's instances as an index PNG (0 = background; an empty scene gives an all-zero PNG, so no segmenter runs for it) | binary masks (the segmenter's at 0.5) exactly; soft masks and scores are not kept |
//! | `mpis/ID.npz` | the MPI, when an MPI network ran (or the item carried one), float32 in the reference npz layout | bit for bit (f16 is not offered: no accuracy report measures its cost yet) |
//! | `bake.json` | the manifest: models and their content hashes, stage fingerprint, source | written by the first shard, checked by the others |
//! | `bake-report.json` (`bake-report.I-of-N.json` for a shard) | counts, failures with reasons, model hashes and runs, timings | per run |
//!
//! # WebDataset output (`--format webdataset`)
//!
//! The same files as tar members, one sample per item with the item id as its key:
//! `ID.disp.npy`, `ID.mask.png`, `ID.mpi.npz` (with an MPI network) and `ID.png` (last), each
//! byte for byte the reference layout's file, in shards `OUT/bake-I-of-N-SSSSSS.tar` of at most
//! `items_per_shard` items (`SSSSSS` counts the shards this job has written), beside the same
//! `bake.json` (with `"layout": "webdataset"`). The shard source reads them back
//! ([`crate::source::shard`]: fields `png`, `disp.npy`, `mask.png`, `mpi.npz`) and serves them
//! as baked. Ids with a `.` cannot be WebDataset keys (the key ends at the first dot) and are
//! reported as failed items.
//!
//! An item's files are named by its id with every `/` made a `-` (the ids of a folder of shards
//! are `SHARD/KEY`); two ids that would share a name are both reported as failed, in every
//! shard.
//!
//! A shard is written in `OUT/.partial/I-of-N/`, flushed after every item, and renamed into
//! place when full or when the run ends. A restarted bake first recovers the shard a killed run
//! left there: its complete samples (every member there, the image last, all data inside the
//! file) are written to a finished shard, the rest is redone. Items already in a finished shard
//! are skipped, so nothing is lost or repeated.
//!
//! Without an MPI network the bake does not build the built-in MPI ([`SceneStage::parts`]): the
//! server's layering builds it from the baked disparity, so building it here was wasted (it was
//! most of an item's time).
//!
//! An item whose MPI came from a network is served from its `mpis/` file, so its served
//! disparity is the MPI's own composite (the rule for every given MPI, see
//! [`crate::scene::stage`]), not the depth model's map.
//!
//! # Sharding and resuming
//!
//! `--shard I/N` takes the items whose id hashes to `I` ([`shard_of`]: FNV-1a 64 of the id, mod
//! `N`), so N jobs cover every item exactly once whatever order or machine they run in, and an
//! item keeps its shard when others are added. Every file is written into
//! `OUT/.partial/I-of-N/` and renamed into place (atomic on one file system); the image goes
//! last, so an item is done exactly when its image exists (with its companions). A restarted
//! bake skips done items, clears its own leftover temporaries and redoes an item that was cut
//! in the middle: nothing is lost or repeated. A folder baked with other models (another
//! `bake.json`) is refused.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use serde::Serialize;

use crate::hash::Fnv64;
use crate::io::image::{quantize_to_u8, save_rgb_png};
use crate::mpi::npz::{save_npz_as, MpiDtype};
use crate::scene::stage::{SceneParts, SceneStage};
use crate::scene::SceneError;
use crate::source::baked::{BakeManifest, BakedModel, FORMAT, MANIFEST};
use crate::source::{FailureKind, Source};

/// One of N disjoint parts of a collection.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    pub index: u64,
    pub count: u64,
}

impl Shard {
    /// The whole collection.
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// Whether the item with this id belongs to this shard.
    pub fn owns(&self, id: &str) -> bool {
        shard_of(id, self.count) == self.index
    }

    /// `I-of-N`, for file names.
    pub fn tag(&self) -> String {
        format!("{}-of-{}", self.index, self.count)
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

impl std::str::FromStr for Shard {
    type Err = String;

    /// `I/N` with `0 <= I < N`.
    fn from_str(s: &str) -> Result<Self, String> {
        let (i, n) = s.split_once('/').ok_or_else(|| format!("expected I/N (e.g. 0/4), got `{s}`"))?;
        let num = |v: &str| v.trim().parse::<u64>().map_err(|_| format!("`{v}` is not a whole number"));
        let (index, count) = (num(i)?, num(n)?);
        if count == 0 || index >= count {
            return Err(format!("shard {index}/{count}: expected 0 <= I < N"));
        }
        Ok(Shard { index, count })
    }
}

/// The shard (of `count`) that the item `id` belongs to: FNV-1a 64 of the id, mod `count`.
pub fn shard_of(id: &str, count: u64) -> u64 {
    Fnv64::new().str("mpiflow bake shard v1").str(id).finish() % count.max(1)
}

/// Errors that stop a bake (an item's own failure does not: it is reported and passed over).
#[derive(Debug, thiserror::Error)]
pub enum BakeError {
    #[error("{path}: {message}")]
    Io { path: String, message: String },
    /// The output folder was baked with other models or from another source.
    #[error("{0}")]
    Mismatch(String),
    /// ONNX Runtime itself failed: no item can be baked.
    #[error(transparent)]
    Runtime(SceneError),
}

fn io_err(path: &Path, e: impl std::fmt::Display) -> BakeError {
    BakeError::Io { path: path.display().to_string(), message: e.to_string() }
}

/// A source item that could not be baked.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct BakeFailure {
    pub item: usize,
    pub id: String,
    /// [`FailureKind::as_str`] of the item's failure, or `model` for a model's error on it.
    pub kind: String,
    pub reason: String,
}

/// Timings of one run.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct BakeTimings {
    /// Wall time of the run (listing to report).
    pub total_s: f64,
    /// Items baked per second of wall time.
    pub items_per_s: f64,
    /// Per baked item: scene (models) and writing, milliseconds (mean, median, max).
    pub scene_ms_mean: f64,
    pub scene_ms_median: f64,
    pub scene_ms_max: f64,
    pub write_ms_mean: f64,
}

/// `bake-report.json`: what one run of one shard did.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BakeReport {
    /// `mpiflow bake report v1`.
    pub format: String,
    pub shard: String,
    pub source: String,
    /// Items of the source, of this shard, and what became of this shard's items in this run.
    pub source_items: usize,
    pub shard_items: usize,
    pub baked: usize,
    pub already_done: usize,
    pub failed: usize,
    /// Items of the shard not reached (the run stopped at its `--limit`).
    pub remaining: usize,
    pub failures: Vec<BakeFailure>,
    /// The models with their content hashes (as in `bake.json`).
    pub models: Vec<BakedModel>,
    /// Inferences each model ran in this run, by role.
    pub model_runs: std::collections::BTreeMap<String, u64>,
    pub timings: BakeTimings,
    /// Peak resident memory of the process in MiB (`VmHWM`), where the platform tells it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub peak_rss_mib: Option<f64>,
}

/// Where a run stands, after each item (for a progress bar).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Progress {
    /// Items of the shard handled so far in this run (baked, failed or found done).
    pub handled: usize,
    pub total: usize,
    pub baked: usize,
    pub failed: usize,
}

/// How the baked items are laid out in the output folder.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BakeLayout {
    /// `images/`, `disps/`, `masks/`, `mpis/`: one file per member (the directory source reads it).
    Reference,
    /// WebDataset tar shards of at most `items_per_shard` items (the shard source reads them).
    WebDataset { items_per_shard: usize },
}

impl BakeLayout {
    /// The manifest's `layout` value.
    fn manifest_name(&self) -> Option<String> {
        match self {
            BakeLayout::Reference => None,
            BakeLayout::WebDataset { .. } => Some("webdataset".into()),
        }
    }
}

/// The reference layout's folder of each member, and its field in a WebDataset sample.
const MEMBERS: [(&str, &str, &str); 4] =
    [("disps", "npy", "disp.npy"), ("masks", "png", "mask.png"), ("mpis", "npz", "mpi.npz"), ("images", "png", "png")];

fn field_of(sub: &str) -> &'static str {
    MEMBERS.iter().find(|m| m.0 == sub).map_or("bin", |m| m.2)
}

fn ext_of(sub: &str) -> &'static str {
    MEMBERS.iter().find(|m| m.0 == sub).map_or("bin", |m| m.1)
}

/// A bake of one source through one scene stage into one folder.
pub struct Baker {
    source: Arc<dyn Source>,
    stage: Arc<SceneStage>,
    out: PathBuf,
    manifest: BakeManifest,
    layout: BakeLayout,
    /// The element type of stored MPIs' colours and densities.
    mpi_dtype: MpiDtype,
    /// [`baked_names`] of the source.
    names: Vec<Result<String, String>>,
}

/// The models of a stage as the manifest records them.
pub fn stage_models(stage: &SceneStage) -> Vec<BakedModel> {
    let hex = |h: Option<u64>| h.map(|h| format!("{h:016x}"));
    let mut out = Vec::with_capacity(3);
    if let Some(d) = &stage.depth {
        out.push(BakedModel {
            role: "depth".into(),
            name: d.name(),
            content_hash: hex(d.content_hash()),
            identity: d.identity(),
        });
    }
    let m = &stage.mpi;
    out.push(BakedModel {
        role: "mpi".into(),
        name: m.name(),
        content_hash: hex(m.content_hash()),
        identity: m.identity(),
    });
    if let Some(s) = &stage.segmenter {
        out.push(BakedModel {
            role: "segment".into(),
            name: s.name(),
            content_hash: hex(s.content_hash()),
            identity: s.identity(),
        });
    }
    out
}

/// The name of item `id`'s files (the reference layout) or its key (WebDataset): the id with
/// every path separator made a `-` (ids of a folder of shards are `SHARD/KEY`), or why it cannot
/// name one.
fn baked_name(id: &str, layout: BakeLayout) -> Result<String, String> {
    let name = id.replace(['/', '\\'], "-");
    if name.is_empty() || name.starts_with('.') || name.contains('\0') {
        return Err(format!("the id `{id}` cannot name a file"));
    }
    if matches!(layout, BakeLayout::WebDataset { .. }) && name.contains('.') {
        return Err(format!("the id `{id}` has a `.`, which would end its WebDataset key"));
    }
    Ok(name)
}

/// Every item's [`baked_name`], over the whole source (so that every shard agrees): two ids of
/// one name are both refused.
fn baked_names(source: &dyn Source, layout: BakeLayout) -> Vec<Result<String, String>> {
    let mut names: Vec<Result<String, String>> = (0..source.len()).map(|i| baked_name(&source.id(i), layout)).collect();
    let mut first: std::collections::HashMap<String, usize> = std::collections::HashMap::new();
    let mut clash: Vec<(usize, usize)> = Vec::new();
    for (i, n) in names.iter().enumerate() {
        if let Ok(n) = n {
            match first.get(n) {
                Some(&j) => clash.push((i, j)),
                None => {
                    first.insert(n.clone(), i);
                }
            }
        }
    }
    for (i, j) in clash {
        let name = names[i].clone().unwrap_or_default();
        for (a, b) in [(i, j), (j, i)] {
            names[a] = Err(format!("the ids `{}` and `{}` both name `{name}`", source.id(a), source.id(b)));
        }
    }
    names
}

/// A sample's members: (field, bytes), in order.
type Members = Vec<(String, Vec<u8>)>;

/// The samples of a shard's tar file that are complete: every one of `fields` there with its data
/// inside the file, read up to the first damage (a killed writer leaves a shard without its end
/// block, maybe cut inside a member). Returns (key, [(field, bytes)]) in the shard's order.
fn complete_samples(path: &Path, fields: &[&str]) -> std::io::Result<Vec<(String, Members)>> {
    use std::io::Read;
    let len = std::fs::metadata(path)?.len();
    let mut archive = tar::Archive::new(std::io::BufReader::new(std::fs::File::open(path)?));
    let mut out: Vec<(String, Members)> = Vec::new();
    let entries = match archive.entries() {
        Ok(e) => e,
        Err(_) => return Ok(out),
    };
    for entry in entries {
        let Ok(mut entry) = entry else { break };
        if entry.raw_file_position().saturating_add(entry.size()) > len {
            break;
        }
        let Some((key, field)) = entry.path().ok().and_then(|p| crate::source::shard::split_key(&p.to_string_lossy()))
        else {
            continue;
        };
        let mut bytes = Vec::with_capacity(entry.size() as usize);
        if entry.read_to_end(&mut bytes).is_err() {
            break;
        }
        match out.last_mut() {
            Some((k, members)) if *k == key => members.push((field, bytes)),
            _ => out.push((key, vec![(field, bytes)])),
        }
    }
    out.retain(|(_, members)| fields.iter().all(|f| members.iter().any(|(m, _)| m == f)));
    Ok(out)
}

/// An open output shard of a WebDataset bake (in the partial folder until it is finished).
struct OpenTar {
    tmp: PathBuf,
    dest: PathBuf,
    builder: tar::Builder<std::io::BufWriter<std::fs::File>>,
    items: usize,
}

impl OpenTar {
    fn create(tmp: PathBuf, dest: PathBuf) -> Result<Self, BakeError> {
        let f = std::fs::File::create(&tmp).map_err(|e| io_err(&tmp, e))?;
        let mut builder = tar::Builder::new(std::io::BufWriter::with_capacity(1 << 20, f));
        builder.mode(tar::HeaderMode::Deterministic);
        Ok(Self { tmp, dest, builder, items: 0 })
    }

    /// Appends one sample's members and flushes them to the file.
    fn append(&mut self, key: &str, members: &[(String, Vec<u8>)]) -> Result<(), BakeError> {
        use std::io::Write;
        for (field, bytes) in members {
            let mut header = tar::Header::new_gnu();
            header.set_entry_type(tar::EntryType::Regular);
            header.set_size(bytes.len() as u64);
            header.set_mode(0o444);
            header.set_mtime(super::webdataset::MEMBER_MTIME);
            self.builder
                .append_data(&mut header, format!("{key}.{field}"), bytes.as_slice())
                .map_err(|e| io_err(&self.tmp, e))?;
        }
        self.builder.get_mut().flush().map_err(|e| io_err(&self.tmp, e))?;
        self.items += 1;
        Ok(())
    }

    /// Ends the archive, syncs it and renames it into place.
    fn finish(self) -> Result<(), BakeError> {
        let w = self.builder.into_inner().map_err(|e| io_err(&self.tmp, e))?;
        let f = w.into_inner().map_err(|e| io_err(&self.tmp, e.into_error()))?;
        f.sync_all().map_err(|e| io_err(&self.tmp, e))?;
        drop(f);
        std::fs::rename(&self.tmp, &self.dest).map_err(|e| io_err(&self.dest, e))
    }
}

/// The WebDataset output of one run: the keys in finished shards, the next shard number and
/// the open shard.
struct TarOut {
    done: std::collections::HashSet<String>,
    next: u64,
    open: Option<OpenTar>,
    items_per_shard: usize,
}

impl Baker {
    /// Prepares `out` for a bake of `source` through `stage` (`resize`: the size the source was
    /// opened with, recorded): creates the folders and writes `bake.json`, or checks that the
    /// one there is the same (same models, same source).
    pub fn new(
        source: Arc<dyn Source>,
        stage: Arc<SceneStage>,
        resize: Option<(usize, usize)>,
        out: &Path,
        layout: BakeLayout,
        mpi_dtype: MpiDtype,
    ) -> Result<Self, BakeError> {
        if layout == (BakeLayout::WebDataset { items_per_shard: 0 }) {
            return Err(BakeError::Mismatch("a WebDataset bake needs at least 1 item per shard".into()));
        }
        let network_mpi = stage.mpi.inference_runs().is_some();
        let mut members = vec!["images".to_string(), "disps".to_string(), "masks".to_string()];
        if network_mpi {
            members.push("mpis".into());
        }
        let manifest = BakeManifest {
            format: FORMAT.into(),
            source: source.describe(),
            source_fingerprint: format!("{:016x}", source.fingerprint()),
            resize: resize.map(|(w, h)| [w, h]),
            stage_fingerprint: format!("{:016x}", stage.config_fingerprint()),
            models: stage_models(&stage),
            members,
            mpi_dtype: network_mpi.then(|| mpi_dtype.as_str().to_string()),
            layout: layout.manifest_name(),
        };
        let subs: &[&str] = match layout {
            BakeLayout::WebDataset { .. } => &[],
            BakeLayout::Reference if network_mpi => &["images", "disps", "masks", "mpis"],
            BakeLayout::Reference => &["images", "disps", "masks"],
        };
        std::fs::create_dir_all(out).map_err(|e| io_err(out, e))?;
        match BakeManifest::read(out) {
            Ok(Some(old)) => {
                // the source's description names its path, which may differ between nodes
                let same = |m: &BakeManifest| {
                    let d = m.mpi_dtype.clone();
                    (m.source_fingerprint.clone(), m.stage_fingerprint.clone(), m.resize, m.layout.clone(), d)
                };
                if old.layout != manifest.layout {
                    let name = |l: &Option<String>| l.clone().unwrap_or_else(|| "reference".into());
                    return Err(BakeError::Mismatch(format!(
                        "{} is a {} bake; bake {} output into a new folder",
                        out.join(MANIFEST).display(),
                        name(&old.layout),
                        name(&manifest.layout)
                    )));
                }
                if old.mpi_dtype.is_some() && old.mpi_dtype != manifest.mpi_dtype {
                    return Err(BakeError::Mismatch(format!(
                        "{} stores MPIs as {}; bake with --mpi-dtype {} into a new folder",
                        out.join(MANIFEST).display(),
                        old.mpi_dtype.clone().unwrap_or_default(),
                        manifest.mpi_dtype.clone().unwrap_or_default()
                    )));
                }
                if same(&old) != same(&manifest) {
                    return Err(BakeError::Mismatch(format!(
                        "{} was baked from another source or with other models ({}); bake into a new folder",
                        out.join(MANIFEST).display(),
                        old.describe()
                    )));
                }
            }
            Ok(None) => {}
            Err(e) => return Err(BakeError::Mismatch(e.to_string())),
        }
        // only now: a refused folder is left as it was
        for sub in subs {
            std::fs::create_dir_all(out.join(sub)).map_err(|e| io_err(&out.join(sub), e))?;
        }
        let names = baked_names(source.as_ref(), layout);
        let baker = Baker { source, stage, out: out.to_path_buf(), manifest, layout, mpi_dtype, names };
        if !out.join(MANIFEST).is_file() {
            let tmp = baker.partial_dir(&Shard::ALL).join(format!("{MANIFEST}.{}", std::process::id()));
            std::fs::create_dir_all(tmp.parent().unwrap_or(out)).map_err(|e| io_err(&tmp, e))?;
            std::fs::write(&tmp, baker.manifest.to_bytes()).map_err(|e| io_err(&tmp, e))?;
            std::fs::rename(&tmp, out.join(MANIFEST)).map_err(|e| io_err(&out.join(MANIFEST), e))?;
        }
        Ok(baker)
    }

    pub fn manifest(&self) -> &BakeManifest {
        &self.manifest
    }

    /// The items of `shard`, in source order.
    pub fn items(&self, shard: &Shard) -> Vec<usize> {
        (0..self.source.len()).filter(|&i| shard.owns(&self.source.id(i))).collect()
    }

    fn partial_dir(&self, shard: &Shard) -> PathBuf {
        self.out.join(".partial").join(shard.tag())
    }

    fn path(&self, sub: &str, id: &str, ext: &str) -> PathBuf {
        self.out.join(sub).join(format!("{id}.{ext}"))
    }

    /// Whether item `id` is baked in the reference layout: its image is there (written last) with
    /// its companions.
    pub fn is_done(&self, id: &str) -> bool {
        self.path("images", id, "png").is_file()
            && self.path("disps", id, "npy").is_file()
            && self.path("masks", id, "png").is_file()
            && (!self.manifest.has("mpis") || self.path("mpis", id, "npz").is_file())
    }

    /// Writes the baked files of one scene (the image last): into the reference layout, or as
    /// one sample of the open shard of `tars`.
    fn write_scene(&self, shard: &Shard, scene: &SceneParts, tars: Option<&mut TarOut>) -> Result<(), BakeError> {
        let id = &scene.id;
        let d = &scene.disparity;
        let mut staged: Vec<(&str, PathBuf)> = Vec::with_capacity(4);
        let mut stage = |sub: &'static str, ext: &str, write: &dyn Fn(&Path) -> Result<(), String>| {
            let tmp = self.partial_dir(shard).join(format!("{}-{id}.{sub}.{ext}", std::process::id()));
            write(&tmp).map_err(|e| io_err(&tmp, e))?;
            staged.push((sub, tmp));
            Ok::<(), BakeError>(())
        };
        stage("disps", "npy", &|p| {
            crate::io::npy::write_f32(p, &[d.height as u64, d.width as u64], &d.data).map_err(|e| e.to_string())
        })?;
        stage("masks", "png", &|p| scene.masks.save_index_png(p).map_err(|e| e.to_string()))?;
        // an MPI is there only when it is stored: a network's (asked for below), or the item's own
        if let Some(mpi) = &scene.mpi {
            let mut mpi = (**mpi).clone();
            mpi.intrinsics = Some(scene.intrinsics);
            stage("mpis", "npz", &|p| {
                let write = || -> std::io::Result<()> {
                    let f = std::fs::File::create(p)?;
                    let w = save_npz_as(&mpi, std::io::BufWriter::new(f), self.mpi_dtype)?;
                    w.into_inner().map_err(std::io::IntoInnerError::into_error)?.sync_all()
                };
                write().map_err(|e| e.to_string())
            })?;
        }
        stage("images", "png", &|p| save_rgb_png(p, &scene.image).map_err(|e| e.to_string()))?;
        match tars {
            None => {
                for (sub, tmp) in staged {
                    if sub == "mpis" {
                        let dir = self.out.join("mpis");
                        std::fs::create_dir_all(&dir).map_err(|e| io_err(&dir, e))?;
                    }
                    let dest = self.path(sub, id, ext_of(sub));
                    std::fs::rename(&tmp, &dest).map_err(|e| io_err(&dest, e))?;
                }
                Ok(())
            }
            Some(t) => {
                let mut members = Vec::with_capacity(staged.len());
                for (sub, tmp) in staged {
                    let bytes = std::fs::read(&tmp).map_err(|e| io_err(&tmp, e))?;
                    std::fs::remove_file(&tmp).map_err(|e| io_err(&tmp, e))?;
                    members.push((field_of(sub).to_string(), bytes));
                }
                self.append_sample(shard, t, id, &members)
            }
        }
    }

    /// The fields every sample of a WebDataset bake has (the image last).
    fn fields(&self) -> Vec<&'static str> {
        MEMBERS.iter().filter(|m| m.0 != "mpis" || self.manifest.has("mpis")).map(|m| m.2).collect()
    }

    /// `bake-I-of-N-SSSSSS.tar`.
    fn tar_name(shard: &Shard, number: u64) -> String {
        format!("bake-{}-{number:06}.tar", shard.tag())
    }

    /// Appends a sample to the open shard (opening one first), finishing the shard when full.
    fn append_sample(
        &self,
        shard: &Shard,
        t: &mut TarOut,
        key: &str,
        members: &[(String, Vec<u8>)],
    ) -> Result<(), BakeError> {
        if t.open.is_none() {
            let name = Self::tar_name(shard, t.next);
            t.next += 1;
            t.open = Some(OpenTar::create(self.partial_dir(shard).join(&name), self.out.join(&name))?);
        }
        let open = t.open.as_mut().expect("opened above");
        open.append(key, members)?;
        t.done.insert(key.to_string());
        if open.items >= t.items_per_shard {
            t.open.take().expect("open").finish()?;
        }
        Ok(())
    }

    /// The WebDataset state at the start of a run of `shard`: the keys of every finished shard in
    /// the folder, this job's next shard number, and the complete samples of a shard a killed run
    /// of this job left in its partial folder, written out as a finished shard.
    fn open_tars(&self, shard: &Shard, items_per_shard: usize) -> Result<TarOut, BakeError> {
        let mut t = TarOut { done: Default::default(), next: 0, open: None, items_per_shard };
        let prefix = format!("bake-{}-", shard.tag());
        let rd = std::fs::read_dir(&self.out).map_err(|e| io_err(&self.out, e))?;
        for ent in rd {
            let p = ent.map_err(|e| io_err(&self.out, e))?.path();
            let Some(name) = p.file_name().and_then(|n| n.to_str()).map(str::to_string) else { continue };
            if !name.ends_with(".tar") || !p.is_file() {
                continue;
            }
            if let Some(n) = name.strip_prefix(&prefix).and_then(|r| r.strip_suffix(".tar")) {
                if let Ok(n) = n.parse::<u64>() {
                    t.next = t.next.max(n + 1);
                }
            }
            let index = crate::source::shard::index_shard(&p).map_err(|e| io_err(&p, e))?;
            t.done.extend(index.samples.into_iter().map(|s| s.key));
        }
        let partial = self.partial_dir(shard);
        let mut leftovers: Vec<PathBuf> = match std::fs::read_dir(&partial) {
            Ok(rd) => rd
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|e| e == "tar"))
                .collect(),
            Err(_) => Vec::new(),
        };
        leftovers.sort();
        let fields = self.fields();
        let mut recovered = Vec::new();
        for p in &leftovers {
            let samples = complete_samples(p, &fields).map_err(|e| io_err(p, e))?;
            recovered.extend(samples.into_iter().filter(|(k, _)| !t.done.contains(k)));
        }
        if !recovered.is_empty() {
            let name = Self::tar_name(shard, t.next);
            t.next += 1;
            let tmp = self.out.join(".partial").join(format!("recovered-{}-{name}", std::process::id()));
            let mut open = OpenTar::create(tmp, self.out.join(&name))?;
            for (key, members) in &recovered {
                open.append(key, members)?;
                t.done.insert(key.clone());
            }
            open.finish()?;
        }
        Ok(t)
    }

    /// Bakes the not yet baked items of `shard`, at most `limit` of them (then stops, as an
    /// interrupted run would), calling `progress` after each item. Items that fail are passed
    /// over and reported; an error of ONNX Runtime itself or of the output folder stops the run.
    pub fn run(
        &self,
        shard: &Shard,
        limit: Option<usize>,
        mut progress: impl FnMut(Progress),
    ) -> Result<BakeReport, BakeError> {
        let start = Instant::now();
        let partial = self.partial_dir(shard);
        std::fs::create_dir_all(self.out.join(".partial")).map_err(|e| io_err(&partial, e))?;
        // a WebDataset bake first keeps what a killed run of this shard finished
        let mut tars = match self.layout {
            BakeLayout::WebDataset { items_per_shard } => Some(self.open_tars(shard, items_per_shard)?),
            BakeLayout::Reference => None,
        };
        // leftovers of a killed run of this shard (never another shard's)
        if partial.exists() {
            std::fs::remove_dir_all(&partial).map_err(|e| io_err(&partial, e))?;
        }
        std::fs::create_dir_all(&partial).map_err(|e| io_err(&partial, e))?;
        let runs_before: Vec<(&str, u64)> = self.stage.model_runs();
        let items = self.items(shard);
        let mut p = Progress { handled: 0, total: items.len(), baked: 0, failed: 0 };
        let (mut already_done, mut failures) = (0usize, Vec::new());
        let (mut scene_ms, mut write_ms) = (Vec::new(), 0.0f64);
        for &i in &items {
            if limit.is_some_and(|l| p.baked + p.failed >= l) {
                break;
            }
            let id = self.source.id(i);
            p.handled += 1;
            let name = self.names[i].clone();
            let done = match (&tars, &name) {
                (_, Err(_)) => false,
                (Some(t), Ok(n)) => t.done.contains(n),
                (None, Ok(n)) => self.is_done(n),
            };
            if done {
                already_done += 1;
                progress(p);
                continue;
            }
            let fail = |kind: &str, reason: String| BakeFailure { item: i, id: id.clone(), kind: kind.into(), reason };
            let name = match name {
                Ok(n) => n,
                Err(reason) => {
                    failures.push(fail(FailureKind::Decode.as_str(), reason));
                    p.failed += 1;
                    progress(p);
                    continue;
                }
            };
            let t = Instant::now();
            let loaded = self.source.load(i).map_err(SceneError::from).and_then(|mut item| {
                // the models see exactly the image that is stored (and served)
                quantize_to_u8(&mut item.image);
                // the built-in MPI is not stored, so it is not built
                self.stage.parts(item, self.manifest.has("mpis"))
            });
            let scene = match loaded {
                Ok(mut s) => {
                    s.id = name;
                    s
                }
                Err(e @ SceneError::Runtime(_)) => return Err(BakeError::Runtime(e)),
                Err(e) => {
                    let kind = e.failure_kind().map_or("model", FailureKind::as_str);
                    failures.push(fail(kind, crate::failure::printable(&e.to_string(), 1000)));
                    p.failed += 1;
                    progress(p);
                    continue;
                }
            };
            scene_ms.push(t.elapsed().as_secs_f64() * 1e3);
            let t = Instant::now();
            // the output folder failing (full, read-only) stops the run: no item could be written
            self.write_scene(shard, &scene, tars.as_mut())?;
            write_ms += t.elapsed().as_secs_f64() * 1e3;
            p.baked += 1;
            progress(p);
        }
        if let Some(open) = tars.and_then(|t| t.open) {
            open.finish()?;
        }
        std::fs::remove_dir_all(&partial).ok();
        let total_s = start.elapsed().as_secs_f64();
        let mut sorted = scene_ms.clone();
        sorted.sort_by(f64::total_cmp);
        let n = scene_ms.len().max(1) as f64;
        let timings = BakeTimings {
            total_s,
            items_per_s: if total_s > 0.0 { p.baked as f64 / total_s } else { 0.0 },
            scene_ms_mean: scene_ms.iter().sum::<f64>() / n,
            scene_ms_median: sorted.get(sorted.len() / 2).copied().unwrap_or(0.0),
            scene_ms_max: sorted.last().copied().unwrap_or(0.0),
            write_ms_mean: write_ms / n,
        };
        let model_runs = self
            .stage
            .model_runs()
            .into_iter()
            .map(|(role, runs)| {
                let before = runs_before.iter().find(|(r, _)| *r == role).map_or(0, |(_, n)| *n);
                (role.to_string(), runs - before)
            })
            .collect();
        Ok(BakeReport {
            format: "mpiflow bake report v1".into(),
            shard: shard.to_string(),
            source: self.source.describe(),
            source_items: self.source.len(),
            shard_items: items.len(),
            baked: p.baked,
            already_done,
            failed: p.failed,
            remaining: items.len() - p.handled,
            failures,
            models: self.manifest.models.clone(),
            model_runs,
            timings,
            peak_rss_mib: peak_rss_mib(),
        })
    }

    /// Where the report of `shard` goes: `bake-report.json` for the whole collection,
    /// `bake-report.I-of-N.json` for a shard.
    pub fn report_path(&self, shard: &Shard) -> PathBuf {
        if *shard == Shard::ALL {
            self.out.join("bake-report.json")
        } else {
            self.out.join(format!("bake-report.{}.json", shard.tag()))
        }
    }

    /// Writes the report (atomically).
    pub fn write_report(&self, shard: &Shard, report: &BakeReport) -> Result<PathBuf, BakeError> {
        let dest = self.report_path(shard);
        let tmp = self.out.join(".partial").join(format!("report-{}-{}", shard.tag(), std::process::id()));
        std::fs::create_dir_all(self.out.join(".partial")).map_err(|e| io_err(&tmp, e))?;
        let mut bytes = serde_json::to_vec_pretty(report).map_err(|e| io_err(&dest, e))?;
        bytes.push(b'\n');
        std::fs::write(&tmp, bytes).map_err(|e| io_err(&tmp, e))?;
        std::fs::rename(&tmp, &dest).map_err(|e| io_err(&dest, e))?;
        Ok(dest)
    }
}

/// Peak resident memory of this process in MiB (`VmHWM` of `/proc/self/status`; Linux only).
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    Some(line.split_whitespace().nth(1)?.parse::<f64>().ok()? / 1024.0)
}
