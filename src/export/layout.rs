//! The flat file layouts (`flo` and `kitti`): every field of sample `I` is its own file
//! `OUT/I_name.ext` (FlyingChairs-style), the JSON record `OUT/I.json` written last.
//!
//! Each file is written under a hidden temporary name in the same directory and renamed into
//! place, so a crash never leaves a truncated file under a final name.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use super::fields::{EncodedSample, Field};
use super::ExportError;

/// Writes `bytes` to `path` through a temporary file in the same directory and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ExportError> {
    let tmp = temp_path(path);
    let io = |source, p: &Path| ExportError::Io { path: p.to_path_buf(), source };
    let result = (|| {
        let mut f = fs::File::create(&tmp).map_err(|e| io(e, &tmp))?;
        f.write_all(bytes).map_err(|e| io(e, &tmp))?;
        f.flush().map_err(|e| io(e, &tmp))?;
        drop(f);
        fs::rename(&tmp, path).map_err(|e| io(e, path))
    })();
    if result.is_err() {
        let _ = fs::remove_file(&tmp);
    }
    result
}

/// `DIR/.NAME.tmp` for `DIR/NAME`.
pub(crate) fn temp_path(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    path.with_file_name(format!(".{name}.tmp"))
}

/// Writes one encoded sample into `dir` as separate files, the JSON record last. Returns the
/// paths written.
pub fn write_files(dir: &Path, sample: &EncodedSample) -> Result<Vec<PathBuf>, ExportError> {
    write_fields(sample, |field| Ok(dir.join(field.file_name(&sample.key))))
}

/// Writes each field of `sample`, in order, atomically to the path `path_of` gives it (the one
/// loop of every file layout). Returns the paths written.
pub(crate) fn write_fields(
    sample: &EncodedSample,
    mut path_of: impl FnMut(&Field) -> Result<PathBuf, ExportError>,
) -> Result<Vec<PathBuf>, ExportError> {
    let mut written = Vec::with_capacity(sample.fields.len());
    for field in &sample.fields {
        let path = path_of(field)?;
        write_atomic(&path, &field.bytes)?;
        written.push(path);
    }
    Ok(written)
}

/// Writes one sample encoded by [`super::fields::encode_sintel`] into the Sintel training
/// layout under `dir`: field `KIND/frame_000N` to `dir/training/KIND/<key>/frame_000N.EXT`, the
/// record to `dir/training/<key>.json` (last). Returns the paths written.
pub fn write_sintel(dir: &Path, sample: &EncodedSample) -> Result<Vec<PathBuf>, ExportError> {
    let root = dir.join("training");
    write_fields(sample, |field| {
        Ok(match field.name.split_once('/') {
            Some((kind, frame)) => {
                let folder = root.join(kind).join(&sample.key);
                fs::create_dir_all(&folder).map_err(|source| ExportError::Io { path: folder.clone(), source })?;
                folder.join(format!("{frame}.{}", field.ext))
            }
            None => {
                fs::create_dir_all(&root).map_err(|source| ExportError::Io { path: root.clone(), source })?;
                root.join(field.file_name(&sample.key))
            }
        })
    })
}
