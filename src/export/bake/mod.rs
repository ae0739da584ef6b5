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
//! Without an MPI network the bake does not build the built-in MPI
//! ([`SceneStage::parts`](crate::scene::stage::SceneStage::parts)): the server's layering builds
//! it from the baked disparity, so building it here was wasted (it was most of an item's time).
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
//!
//! Rooms: `types` (shards, errors, the report, the layouts), `tars` (a WebDataset bake's shards:
//! writing, recovering), `baker` (the bake's folder, its manifest and one item's files), `run`
//! (a run over a shard's items and its report).

mod baker;
mod run;
mod tars;
mod types;

pub use baker::{stage_models, Baker};
pub use types::{peak_rss_mib, shard_of, BakeError, BakeFailure, BakeLayout, BakeReport, BakeTimings, Progress, Shard};
