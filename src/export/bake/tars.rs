//! The shards of a WebDataset bake: an open shard written sample by sample, the run's output
//! state, and the complete samples a killed run left in a shard.

use std::path::{Path, PathBuf};

use super::types::{io_err, BakeError};

/// A sample's members: (field, bytes), in order.
pub(super) type Members = Vec<(String, Vec<u8>)>;

/// The samples of a shard's tar file that are complete: every one of `fields` there with its data
/// inside the file, read up to the first damage (a killed writer leaves a shard without its end
/// block, maybe cut inside a member). Returns (key, [(field, bytes)]) in the shard's order.
pub(super) fn complete_samples(path: &Path, fields: &[&str]) -> std::io::Result<Vec<(String, Members)>> {
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
pub(super) struct OpenTar {
    pub(super) tmp: PathBuf,
    pub(super) dest: PathBuf,
    pub(super) builder: tar::Builder<std::io::BufWriter<std::fs::File>>,
    pub(super) items: usize,
}

impl OpenTar {
    pub(super) fn create(tmp: PathBuf, dest: PathBuf) -> Result<Self, BakeError> {
        let f = std::fs::File::create(&tmp).map_err(|e| io_err(&tmp, e))?;
        let mut builder = tar::Builder::new(std::io::BufWriter::with_capacity(1 << 20, f));
        builder.mode(tar::HeaderMode::Deterministic);
        Ok(Self { tmp, dest, builder, items: 0 })
    }

    /// Appends one sample's members and flushes them to the file.
    pub(super) fn append(&mut self, key: &str, members: &[(String, Vec<u8>)]) -> Result<(), BakeError> {
        use std::io::Write;
        for (field, bytes) in members {
            let mut header = tar::Header::new_gnu();
            header.set_entry_type(tar::EntryType::Regular);
            header.set_size(bytes.len() as u64);
            header.set_mode(0o444);
            header.set_mtime(crate::export::webdataset::MEMBER_MTIME);
            self.builder
                .append_data(&mut header, format!("{key}.{field}"), bytes.as_slice())
                .map_err(|e| io_err(&self.tmp, e))?;
        }
        self.builder.get_mut().flush().map_err(|e| io_err(&self.tmp, e))?;
        self.items += 1;
        Ok(())
    }

    /// Ends the archive, syncs it and renames it into place.
    pub(super) fn finish(self) -> Result<(), BakeError> {
        let w = self.builder.into_inner().map_err(|e| io_err(&self.tmp, e))?;
        let f = w.into_inner().map_err(|e| io_err(&self.tmp, e.into_error()))?;
        f.sync_all().map_err(|e| io_err(&self.tmp, e))?;
        drop(f);
        std::fs::rename(&self.tmp, &self.dest).map_err(|e| io_err(&self.dest, e))
    }
}

/// The WebDataset output of one run: the keys in finished shards, the next shard number and
/// the open shard.
pub(super) struct TarOut {
    pub(super) done: std::collections::HashSet<String>,
    pub(super) next: u64,
    pub(super) open: Option<OpenTar>,
    pub(super) items_per_shard: usize,
}
