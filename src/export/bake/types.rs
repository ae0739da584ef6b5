//! What a bake is about: the shards of a collection, the errors, the report and its timings, the
//! output layouts and their members.

use std::path::Path;

use serde::Serialize;

use crate::hash::Fnv64;
use crate::scene::SceneError;
use crate::source::baked::BakedModel;

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

pub(super) fn io_err(path: &Path, e: impl std::fmt::Display) -> BakeError {
    BakeError::Io { path: path.display().to_string(), message: e.to_string() }
}

/// A source item that could not be baked.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct BakeFailure {
    pub item: usize,
    pub id: String,
    /// [`FailureKind::as_str`](crate::source::FailureKind::as_str) of the item's failure, or `model` for a model's error on it.
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
    pub(super) fn manifest_name(&self) -> Option<String> {
        match self {
            BakeLayout::Reference => None,
            BakeLayout::WebDataset { .. } => Some("webdataset".into()),
        }
    }
}

/// The reference layout's folder of each member, and its field in a WebDataset sample.
pub(super) const MEMBERS: [(&str, &str, &str); 4] =
    [("disps", "npy", "disp.npy"), ("masks", "png", "mask.png"), ("mpis", "npz", "mpi.npz"), ("images", "png", "png")];

pub(super) fn field_of(sub: &str) -> &'static str {
    MEMBERS.iter().find(|m| m.0 == sub).map_or("bin", |m| m.2)
}

pub(super) fn ext_of(sub: &str) -> &'static str {
    MEMBERS.iter().find(|m| m.0 == sub).map_or("bin", |m| m.1)
}

/// Peak resident memory of this process in MiB (`VmHWM` of `/proc/self/status`; Linux only).
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    Some(line.split_whitespace().nth(1)?.parse::<f64>().ok()? / 1024.0)
}
