//! WebDataset tar shards: sample `I` goes to `OUT/shard-NNNNNN.tar` with `NNNNNN = I /
//! shard_size` (6 digits), as the members `I.img1.png`, `I.img2.png`, `I.flow.npy`,
//! `I.valid.png`, `I.occ.png`, [`I.mask.png`], `I.json`, adjacent in the tar (WebDataset groups
//! a sample by the member name up to the first dot).
//!
//! A shard is written under a hidden temporary name (`OUT/.shard-NNNNNN.tar.tmp`), finished,
//! synced and only then renamed to its final name, so a crash never leaves a truncated shard
//! under a final name. Members carry fixed metadata (mode 0444, uid/gid 0, a fixed mtime), so
//! the same samples give the same shard bytes.

use std::fs::{self, File};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use super::fields::EncodedSample;
use super::layout::temp_path;
use super::ExportError;

/// The modification time written into every member header (2024-01-01T00:00:00Z), so shard
/// bytes do not depend on the wall clock.
pub const MEMBER_MTIME: u64 = 1_704_067_200;

/// `shard-NNNNNN.tar` (at least 6 digits).
pub fn shard_name(shard: u64) -> String {
    format!("shard-{shard:06}.tar")
}

struct OpenShard {
    number: u64,
    final_path: PathBuf,
    tmp_path: PathBuf,
    builder: Option<tar::Builder<BufWriter<File>>>,
    samples: usize,
}

impl OpenShard {
    fn create(dir: &Path, number: u64) -> Result<Self, ExportError> {
        let final_path = dir.join(shard_name(number));
        let tmp_path = temp_path(&final_path);
        let file = File::create(&tmp_path).map_err(|source| ExportError::Io { path: tmp_path.clone(), source })?;
        let mut builder = tar::Builder::new(BufWriter::with_capacity(1 << 20, file));
        builder.mode(tar::HeaderMode::Deterministic);
        Ok(Self { number, final_path, tmp_path, builder: Some(builder), samples: 0 })
    }

    fn append(&mut self, sample: &EncodedSample) -> Result<(), ExportError> {
        let builder = self.builder.as_mut().expect("an open shard has a builder");
        for field in &sample.fields {
            let name = field.member_name(&sample.key);
            let mut header = tar::Header::new_gnu();
            header.set_entry_type(tar::EntryType::Regular);
            header.set_size(field.bytes.len() as u64);
            header.set_mode(0o444);
            header.set_uid(0);
            header.set_gid(0);
            header.set_mtime(MEMBER_MTIME);
            builder
                .append_data(&mut header, &name, field.bytes.as_slice())
                .map_err(|source| ExportError::Io { path: self.tmp_path.clone(), source })?;
        }
        self.samples += 1;
        Ok(())
    }

    /// Ends the archive, syncs it and renames it to its final name.
    fn close(mut self) -> Result<ShardInfo, ExportError> {
        let io = |source, p: &Path| ExportError::Io { path: p.to_path_buf(), source };
        let builder = self.builder.take().expect("an open shard has a builder");
        let writer = builder.into_inner().map_err(|e| io(e, &self.tmp_path))?;
        let file = writer.into_inner().map_err(|e| io(e.into_error(), &self.tmp_path))?;
        file.sync_all().map_err(|e| io(e, &self.tmp_path))?;
        drop(file);
        fs::rename(&self.tmp_path, &self.final_path).map_err(|e| io(e, &self.final_path))?;
        Ok(ShardInfo { number: self.number, path: self.final_path.clone(), samples: self.samples })
    }
}

impl Drop for OpenShard {
    fn drop(&mut self) {
        // an unfinished shard (an error or a panic on the way): remove the partial file
        if let Some(b) = self.builder.take() {
            if let Ok(mut w) = b.into_inner() {
                let _ = w.flush();
            }
            let _ = fs::remove_file(&self.tmp_path);
        }
    }
}

/// A finished shard.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ShardInfo {
    pub number: u64,
    pub path: PathBuf,
    pub samples: usize,
}

/// Appends encoded samples to shards in `dir`, opening a new shard whenever the sample index
/// enters the next block of `shard_size` indices. Indices must not decrease.
pub struct ShardWriter {
    dir: PathBuf,
    shard_size: u64,
    current: Option<OpenShard>,
    last_index: Option<u64>,
    finished: Vec<ShardInfo>,
}

impl ShardWriter {
    /// `shard_size` >= 1 samples per shard.
    pub fn new(dir: &Path, shard_size: u64) -> Result<Self, ExportError> {
        if shard_size == 0 {
            return Err(ExportError::Invalid("the shard size must be at least 1".into()));
        }
        Ok(Self { dir: dir.to_path_buf(), shard_size, current: None, last_index: None, finished: Vec::new() })
    }

    /// The shard that sample `index` belongs to.
    pub fn shard_of(&self, index: u64) -> u64 {
        index / self.shard_size
    }

    pub fn append(&mut self, sample: &EncodedSample) -> Result<(), ExportError> {
        if let Some(last) = self.last_index {
            if sample.index <= last {
                return Err(ExportError::Invalid(format!(
                    "webdataset samples must come in increasing index order: {} after {last}",
                    sample.index
                )));
            }
        }
        let number = self.shard_of(sample.index);
        if self.current.as_ref().is_some_and(|s| s.number != number) {
            let done = self.current.take().expect("checked above").close()?;
            self.finished.push(done);
        }
        if self.current.is_none() {
            self.current = Some(OpenShard::create(&self.dir, number)?);
        }
        self.current.as_mut().expect("opened above").append(sample)?;
        self.last_index = Some(sample.index);
        Ok(())
    }

    /// Shards finished so far.
    pub fn finished(&self) -> &[ShardInfo] {
        &self.finished
    }

    /// Closes the open shard; returns every shard written.
    pub fn finish(mut self) -> Result<Vec<ShardInfo>, ExportError> {
        if let Some(open) = self.current.take() {
            let done = open.close()?;
            self.finished.push(done);
        }
        Ok(std::mem::take(&mut self.finished))
    }
}
