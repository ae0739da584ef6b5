//! Offline export of samples to disk, in layouts RAFT-style trainers read: flat files
//! (`flo`: FlyingChairs-style with Middlebury `.flo`; `kitti`: the same with a KITTI 16-bit flow
//! PNG), WebDataset tar shards, or the stereo folders of rectified pairs (`stereo`, see
//! [`stereo`]), plus preview contact sheets. See `docs/export.md`.
//!
//! With `I` the sample index as 8 digits (`00000042`):
//!
//! | field | `flo` / `kitti` file | `webdataset` member | content |
//! |---|---|---|---|
//! | image 1 | `I_img1.png` | `I.img1.png` | 8-bit RGB, the source photo |
//! | image 2 | `I_img2.png` | `I.img2.png` | 8-bit RGB, the novel view |
//! | flow | `I_flow.flo` / `I_flow.png` | `I.flow.npy` | forward flow on image 1's pixels |
//! | valid | `I_valid.png` | `I.valid.png` | 8-bit gray, 255 = flow valid |
//! | occlusion | `I_occ.png` | `I.occ.png` | 8-bit gray, 255 = hidden in image 2 |
//! | holes | `I_holes.png` | `I.holes.png` | 8-bit gray, 255 = image 2 filled by 2-D inpainting |
//! | objects | `I_mask.png` | `I.mask.png` | object labels (1, 2, ...) in image 1, when objects moved |
//! | backward flow | `I_flow_bw.flo` / `.png` | `I.flow_bw.npy` | image 2 -> image 1 on image 2's pixels (with the backward fields) |
//! | backward valid | `I_valid_bw.png` | `I.valid_bw.png` | 255 = backward flow valid |
//! | backward occlusion | `I_occ_bw.png` | `I.occ_bw.png` | 255 = the image 2 pixel is not visible in image 1 |
//! | clip frames | `I_img3.png` ... | `I.img3.png` ... | frames 3..K of a clip; pairs `flow23`, `valid23`, `occ23`, `flow_bw32`, ... |
//! | record | `I.json` | `I.json` | source id, address, motions, objects, stats, provenance, timings |
//!
//! The `sintel` format writes the MPI Sintel training layout instead ([`fields::encode_sintel`]):
//! `OUT/training/clean/I/frame_000k.png` (k = 1..K), `OUT/training/flow/I/frame_000k.flo`
//! (k = 1..K-1, frame k -> k+1), `OUT/training/occlusions/I/frame_000k.png` and
//! `OUT/training/invalid/I/frame_000k.png` (255 = occluded / invalid, as Sintel), and the record
//! `OUT/training/I.json`: RAFT's `MpiSintel(root=OUT, dstype='clean')` reads it as it is.
//!
//! Encoding ([`fields::encode_sample`]) is pure and runs on any thread; an [`Exporter`] writes
//! encoded samples in the order it is given them.

pub mod bake;
pub mod fields;
pub mod layout;
pub mod preview;
pub mod stereo;
pub mod webdataset;

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use crate::sample::Sample;
pub use fields::{encode_sample, sample_key, EncodedSample, FlowEncoding};
pub use preview::PreviewOptions;

/// Errors of the export layer; each names the file or the sample.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    #[error("{}: {source}", .path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("sample {index}: {reason}")]
    InvalidSample { index: u64, reason: String },
    #[error("encoding failed: {0}")]
    Encode(String),
    #[error("{0}")]
    Invalid(String),
}

/// The on-disk layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ExportFormat {
    /// Flat files, flow as Middlebury `.flo`.
    Flo,
    /// Flat files, flow as a KITTI 16-bit PNG.
    Kitti,
    /// WebDataset tar shards, flow as `.npy`.
    WebDataset,
    /// The MPI Sintel training layout (clips), flow as `.flo`.
    Sintel,
    /// Rectified stereo pairs in SceneFlow-style folders, disparity as PFM ([`stereo`]).
    Stereo,
}

impl ExportFormat {
    pub const ALL: [ExportFormat; 5] =
        [ExportFormat::Flo, ExportFormat::Kitti, ExportFormat::WebDataset, ExportFormat::Sintel, ExportFormat::Stereo];

    pub fn name(self) -> &'static str {
        match self {
            ExportFormat::Flo => "flo",
            ExportFormat::Kitti => "kitti",
            ExportFormat::WebDataset => "webdataset",
            ExportFormat::Sintel => "sintel",
            ExportFormat::Stereo => "stereo",
        }
    }

    /// How this layout stores the flow.
    pub fn flow_encoding(self) -> FlowEncoding {
        match self {
            ExportFormat::Flo | ExportFormat::Sintel => FlowEncoding::Flo,
            ExportFormat::Kitti => FlowEncoding::KittiPng,
            ExportFormat::WebDataset => FlowEncoding::Npy,
            ExportFormat::Stereo => FlowEncoding::DisparityPfm,
        }
    }
}

impl fmt::Display for ExportFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for ExportFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "flo" => Ok(ExportFormat::Flo),
            "kitti" => Ok(ExportFormat::Kitti),
            "webdataset" | "wds" => Ok(ExportFormat::WebDataset),
            "sintel" => Ok(ExportFormat::Sintel),
            "stereo" => Ok(ExportFormat::Stereo),
            _ => Err(format!("unknown export format {s:?} (expected flo, kitti, webdataset, sintel or stereo)")),
        }
    }
}

/// Encodes a sample for `format` (pure; call it from any thread).
pub fn encode_for(format: ExportFormat, index: u64, sample: &Sample) -> Result<EncodedSample, ExportError> {
    match format {
        ExportFormat::Sintel => fields::encode_sintel(index, sample),
        ExportFormat::Stereo => stereo::encode_stereo(index, sample),
        f => encode_sample(index, sample, f.flow_encoding()),
    }
}

/// Where and how an [`Exporter`] writes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ExportOptions {
    pub format: ExportFormat,
    /// Output directory (created if missing).
    pub out_dir: PathBuf,
    /// Samples per WebDataset shard (sample `I` goes to shard `I / shard_size`).
    pub shard_size: u64,
    pub preview: PreviewOptions,
}

impl ExportOptions {
    pub fn new(format: ExportFormat, out_dir: impl Into<PathBuf>) -> Self {
        Self { format, out_dir: out_dir.into(), shard_size: 1000, preview: PreviewOptions::default() }
    }
}

/// What an export wrote.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ExportSummary {
    pub samples: u64,
    pub bytes: u64,
    /// WebDataset shards written.
    pub shards: Vec<PathBuf>,
    pub previews: Vec<PathBuf>,
}

enum Sink {
    Files,
    Sintel,
    Shards(webdataset::ShardWriter),
    Stereo,
}

/// Writes samples in one format, with previews. Give it samples in increasing index order.
pub struct Exporter {
    options: ExportOptions,
    sink: Sink,
    previews: preview::PreviewCollector,
    samples: u64,
    bytes: u64,
}

impl Exporter {
    /// Creates the output directory and checks the options.
    pub fn create(options: ExportOptions) -> Result<Self, ExportError> {
        let dir = &options.out_dir;
        std::fs::create_dir_all(dir).map_err(|source| ExportError::Io { path: dir.clone(), source })?;
        let sink = match options.format {
            ExportFormat::WebDataset => Sink::Shards(webdataset::ShardWriter::new(dir, options.shard_size)?),
            ExportFormat::Flo | ExportFormat::Kitti => Sink::Files,
            ExportFormat::Stereo => {
                for f in stereo::FOLDERS {
                    let d = dir.join(f);
                    std::fs::create_dir_all(&d).map_err(|source| ExportError::Io { path: d, source })?;
                }
                Sink::Stereo
            }
            ExportFormat::Sintel => Sink::Sintel,
        };
        let previews = preview::PreviewCollector::new(&dir.join("previews"), options.preview)?;
        Ok(Self { options, sink, previews, samples: 0, bytes: 0 })
    }

    pub fn options(&self) -> &ExportOptions {
        &self.options
    }

    /// The output directory.
    pub fn out_dir(&self) -> &Path {
        &self.options.out_dir
    }

    /// Encodes a sample for this exporter's format (pure; call it from any thread).
    pub fn encode(&self, index: u64, sample: &Sample) -> Result<EncodedSample, ExportError> {
        encode_for(self.options.format, index, sample)
    }

    /// Writes a sample encoded by [`Exporter::encode`]; `sample` (the same one) feeds the
    /// preview sheets.
    pub fn write_encoded(&mut self, encoded: &EncodedSample, sample: &Sample) -> Result<(), ExportError> {
        match &mut self.sink {
            Sink::Files => {
                layout::write_files(&self.options.out_dir, encoded)?;
            }
            Sink::Sintel => {
                layout::write_sintel(&self.options.out_dir, encoded)?;
            }
            Sink::Shards(w) => w.append(encoded)?,
            Sink::Stereo => {
                stereo::write_stereo(&self.options.out_dir, encoded)?;
            }
        }
        self.previews.add(encoded.index, sample)?;
        self.samples += 1;
        self.bytes += encoded.byte_len() as u64;
        Ok(())
    }

    /// Encodes and writes one sample.
    pub fn write(&mut self, index: u64, sample: &Sample) -> Result<(), ExportError> {
        let encoded = self.encode(index, sample)?;
        self.write_encoded(&encoded, sample)
    }

    /// Finishes the open shard and the preview sheet in progress.
    pub fn finish(self) -> Result<ExportSummary, ExportError> {
        let shards = match self.sink {
            Sink::Shards(w) => w.finish()?.into_iter().map(|s| s.path).collect(),
            Sink::Files | Sink::Sintel | Sink::Stereo => Vec::new(),
        };
        let previews = self.previews.finish()?;
        Ok(ExportSummary { samples: self.samples, bytes: self.bytes, shards, previews })
    }
}
