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
use crate::mpi::npz::save_npz;
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

/// A bake of one source through one scene stage into one folder.
pub struct Baker {
    source: Arc<dyn Source>,
    stage: Arc<SceneStage>,
    out: PathBuf,
    manifest: BakeManifest,
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

/// Whether an id can name files in the output (no separators, not hidden, not empty).
fn usable_id(id: &str) -> bool {
    !id.is_empty() && !id.starts_with('.') && !id.contains(['/', '\\', '\0'])
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
    ) -> Result<Self, BakeError> {
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
            mpi_dtype: network_mpi.then(|| "f32".to_string()),
        };
        let subs: &[&str] =
            if network_mpi { &["images", "disps", "masks", "mpis"] } else { &["images", "disps", "masks"] };
        for sub in subs {
            std::fs::create_dir_all(out.join(sub)).map_err(|e| io_err(&out.join(sub), e))?;
        }
        match BakeManifest::read(out) {
            Ok(Some(old)) => {
                // the source's description names its path, which may differ between nodes
                let same = |m: &BakeManifest| (m.source_fingerprint.clone(), m.stage_fingerprint.clone(), m.resize);
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
        let baker = Baker { source, stage, out: out.to_path_buf(), manifest };
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

    /// Whether item `id` is baked: its image is there (written last) with its companions.
    pub fn is_done(&self, id: &str) -> bool {
        self.path("images", id, "png").is_file()
            && self.path("disps", id, "npy").is_file()
            && self.path("masks", id, "png").is_file()
            && (!self.manifest.has("mpis") || self.path("mpis", id, "npz").is_file())
    }

    /// Writes `write(tmp)` to a temporary file in the shard's partial folder, then renames it to
    /// `dest`.
    fn atomic<E: std::fmt::Display>(
        &self,
        shard: &Shard,
        dest: &Path,
        write: impl FnOnce(&Path) -> Result<(), E>,
    ) -> Result<(), BakeError> {
        let name = dest.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
        // the temporary keeps the extension (the PNG writer picks its format by it)
        let tmp = self.partial_dir(shard).join(format!("{}-{name}", std::process::id()));
        write(&tmp).map_err(|e| io_err(&tmp, e))?;
        std::fs::rename(&tmp, dest).map_err(|e| io_err(dest, e))
    }

    /// Writes the baked files of one scene (the image last).
    fn write_scene(&self, shard: &Shard, scene: &SceneParts) -> Result<(), BakeError> {
        let id = &scene.id;
        let d = &scene.disparity;
        self.atomic(shard, &self.path("disps", id, "npy"), |p| {
            crate::io::npy::write_f32(p, &[d.height as u64, d.width as u64], &d.data)
        })?;
        self.atomic(shard, &self.path("masks", id, "png"), |p| scene.masks.save_index_png(p))?;
        // an MPI is there only when it is stored: a network's (asked for below), or the item's own
        if let Some(mpi) = &scene.mpi {
            let dir = self.out.join("mpis");
            std::fs::create_dir_all(&dir).map_err(|e| io_err(&dir, e))?;
            let mut mpi = (**mpi).clone();
            mpi.intrinsics = Some(scene.intrinsics);
            self.atomic(shard, &self.path("mpis", id, "npz"), |p| -> std::io::Result<()> {
                let f = std::fs::File::create(p)?;
                let w = save_npz(&mpi, std::io::BufWriter::new(f))?;
                w.into_inner().map_err(std::io::IntoInnerError::into_error)?.sync_all()
            })?;
        }
        self.atomic(shard, &self.path("images", id, "png"), |p| save_rgb_png(p, &scene.image))
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
            if usable_id(&id) && self.is_done(&id) {
                already_done += 1;
                progress(p);
                continue;
            }
            let fail = |kind: &str, reason: String| BakeFailure { item: i, id: id.clone(), kind: kind.into(), reason };
            if !usable_id(&id) {
                failures.push(fail(FailureKind::Decode.as_str(), format!("the id `{id}` cannot name a file")));
                p.failed += 1;
                progress(p);
                continue;
            }
            let t = Instant::now();
            let loaded = self.source.load(i).map_err(SceneError::from).and_then(|mut item| {
                // the models see exactly the image that is stored (and served)
                quantize_to_u8(&mut item.image);
                // the built-in MPI is not stored, so it is not built
                self.stage.parts(item, self.manifest.has("mpis"))
            });
            let scene = match loaded {
                Ok(s) => s,
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
            self.write_scene(shard, &scene)?;
            write_ms += t.elapsed().as_secs_f64() * 1e3;
            p.baked += 1;
            progress(p);
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
