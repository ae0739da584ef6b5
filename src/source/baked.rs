//! Baked collections: the `bake.json` manifest that `mpiflow bake` writes beside the reference
//! layout or the WebDataset shards it produces, read back by the directory and the shard
//! sources so that a served dataset says what
//! its scenes were baked with (`GetInfo` `baked_with`, the dataset description) and whether any
//! scene model still has to run.
//!
//! The manifest records the models' content hashes (FNV-1a 64 of each file, [`crate::hash`]),
//! the scene stage's configuration fingerprint, the source it was baked from and which members
//! every item carries. It holds nothing that differs between the shards of one bake (no shard
//! number, no timings: those go to the bake report), so every shard writes the same bytes and a
//! shard that finds a manifest of other models refuses to mix them into the folder.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{FailureKind, SourceError};

/// The file name of the manifest in a baked folder.
pub const MANIFEST: &str = "bake.json";

/// The manifest format this build writes and reads.
pub const FORMAT: &str = "mpiflow bake v1";

/// One scene model (or built-in rule) a bake used.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BakedModel {
    /// `depth`, `mpi` or `segment`.
    pub role: String,
    /// The model's short name (`onnx:depth.onnx`, `builtin soft 32`).
    pub name: String,
    /// FNV-1a 64 of the model file's bytes as 16 hex digits; absent for a built-in rule.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub content_hash: Option<String>,
    /// Everything that makes the model's output what it is (content hash and contract).
    pub identity: String,
}

/// The `bake.json` of a baked folder (see the module documentation).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BakeManifest {
    /// [`FORMAT`].
    pub format: String,
    /// The source baked, as it described itself (`dir:/photos (120 images)`).
    pub source: String,
    /// The source's fingerprint (16 hex digits).
    pub source_fingerprint: String,
    /// The size every item was resized to before the models ran (`[W, H]`), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resize: Option<[usize; 2]>,
    /// The scene stage's configuration fingerprint (16 hex digits): changes with any model.
    pub stage_fingerprint: String,
    /// The models of the stage, in the order depth, mpi, segment (only those configured).
    pub models: Vec<BakedModel>,
    /// The members every baked item has: `images`, `disps`, `masks`, and `mpis` when an MPI
    /// network ran.
    pub members: Vec<String>,
    /// The element type of the baked MPIs' colours and densities (`f32` or `f16`), when there
    /// are any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mpi_dtype: Option<String>,
    /// `webdataset` when the items are in tar shards beside the manifest (members `KEY.png`,
    /// `KEY.disp.npy`, `KEY.mask.png`, `KEY.mpi.npz`); absent for the reference layout.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layout: Option<String>,
}

impl BakeManifest {
    /// The manifest of `dir`, `None` when it has none; an unreadable or malformed manifest (or one
    /// of another format) is an error naming the file.
    pub fn read(dir: &Path) -> Result<Option<Self>, SourceError> {
        let p = dir.join(MANIFEST);
        let bytes = match std::fs::read(&p) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(SourceError::file(p.display().to_string(), FailureKind::Decode, e.to_string())),
        };
        let bad = |m: String| SourceError::file(p.display().to_string(), FailureKind::Decode, m);
        if bytes.len() > 1 << 20 {
            return Err(bad(format!("{} bytes is too large for a bake manifest", bytes.len())));
        }
        let m: BakeManifest = serde_json::from_slice(&bytes).map_err(|e| bad(format!("not a bake manifest: {e}")))?;
        if m.format != FORMAT {
            return Err(bad(format!("format `{}`, this build reads `{FORMAT}`", m.format)));
        }
        Ok(Some(m))
    }

    /// The manifest as the bytes written to `bake.json` (pretty JSON and a newline).
    pub fn to_bytes(&self) -> Vec<u8> {
        // a struct of strings cannot fail to serialise
        let mut b = serde_json::to_vec_pretty(self).unwrap_or_default();
        b.push(b'\n');
        b
    }

    /// Whether every item carries `member` (`disps`, `masks`, `mpis`).
    pub fn has(&self, member: &str) -> bool {
        self.members.iter().any(|m| m == member)
    }

    /// One line for `GetInfo` and the dataset description: `mpiflow bake v1 of SOURCE with
    /// depth onnx:depth.onnx (content 0123456789abcdef), mpi builtin soft 32, ...`.
    pub fn describe(&self) -> String {
        let models: Vec<String> = self
            .models
            .iter()
            .map(|m| match &m.content_hash {
                Some(h) => format!("{} {} (content {h})", m.role, m.name),
                None => format!("{} {}", m.role, m.name),
            })
            .collect();
        let dtype = match self.mpi_dtype.as_deref() {
            Some(d) if d != "f32" => format!("; MPIs stored as {d}"),
            _ => String::new(),
        };
        format!(
            "{} of {} (fingerprint {}) with {}; stage {}{dtype}",
            self.format,
            self.source,
            self.source_fingerprint,
            if models.is_empty() { "no models".to_string() } else { models.join(", ") },
            self.stage_fingerprint
        )
    }
}
