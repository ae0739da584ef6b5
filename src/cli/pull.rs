//! `mpiflow pull`: a Rust client of the service. Pulls a stream, optionally saves the samples in
//! the export `flo` layout (`I_img1.png`, ... with `I` the global index) with preview sheets, and
//! prints samples/s, MB/s, the time to first sample and the gaps between samples.

use std::path::PathBuf;
use std::sync::mpsc::sync_channel;

use clap::Args;
use mpiflow::export::{ExportFormat, ExportOptions, Exporter, PreviewOptions};
use mpiflow::service::client::{connect_with, pull};
use mpiflow::service::encode::{from_proto, raw_view};
use mpiflow::service::error::cursor_of;
use mpiflow::service::pb;

use super::connect::ConnectArgs;
use super::CliError;

#[derive(Args, Debug)]
pub struct PullArgs {
    /// Server address (HOST:PORT; https://HOST:PORT or --tls-ca for TLS).
    #[arg(long, value_name = "HOST:PORT", default_value = mpiflow::service::config::DEFAULT_ADDR)]
    addr: String,
    #[command(flatten)]
    connect: ConnectArgs,
    /// Samples to pull.
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    count: u64,
    /// Save the samples here (in the --format layout, with previews); without it samples are
    /// received, their tensors checked (shape, size, lz4) and dropped (for benchmarks).
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// Layout of --out: flo, kitti, webdataset, sintel (clips) or stereo (rectified pairs; needs
    /// --preset stereo).
    #[arg(long, default_value = "flo", value_parser = |s: &str| s.parse::<ExportFormat>())]
    format: ExportFormat,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// This consumer's rank among --world-size consumers.
    #[arg(long, default_value_t = 0)]
    rank: u32,
    #[arg(long, default_value_t = 1)]
    world_size: u32,
    /// The resume cursor: the first index pulled is start_index + rank.
    #[arg(long, value_name = "I", default_value_t = 0)]
    start_index: u64,
    /// Dataset name (default: the server's default dataset).
    #[arg(long, default_value = "")]
    dataset: String,
    /// Expected dataset fingerprint (16 hex digits); the server refuses a different one.
    #[arg(long, value_name = "HEX")]
    fingerprint: Option<String>,
    /// Ask for lz4-compressed tensors.
    #[arg(long)]
    lz4: bool,
    /// Ask for f16 flow.
    #[arg(long)]
    f16: bool,
    /// Samples per message.
    #[arg(long, default_value_t = 1)]
    batch_size: u32,
    /// Samples the server makes ahead for this stream (0 = the server's default).
    #[arg(long, default_value_t = 0)]
    prefetch: u32,
    /// Motion preset: reference, paper-kitti, depthstillation, mixed or stereo (default: the
    /// dataset's).
    #[arg(long, default_value = "")]
    preset: String,
    /// Moving objects per sample (default: the dataset's).
    #[arg(long)]
    objects: Option<u32>,
    /// Motions drawn from each source photo while its scene is warm (default: the dataset's).
    #[arg(long)]
    motions_per_image: Option<u32>,
    /// Colour kernel of the target render (default: the dataset's).
    #[arg(long, value_name = "KERNEL", value_parser = super::kernels::resample_parser())]
    resample: Option<mpiflow::render::Resample>,
    /// Training augmentation: a preset (raft-chairs, raft-things, raft-sintel, raft-kitti, none)
    /// or its JSON form (docs/augment.md); with --crop, the crop replaces the preset's.
    #[arg(long, value_name = "NAME|JSON")]
    augment: Option<String>,
    /// Crop every sample to WxH (centre, or random with --random-crop).
    #[arg(long, value_name = "WxH")]
    crop: Option<String>,
    /// With --crop: a random window of each sample (deterministic by address) instead of the
    /// centre.
    #[arg(long)]
    random_crop: bool,
    /// A preview sheet at every multiple of N (with --out; 0 = none).
    #[arg(long, value_name = "N", default_value_t = 100)]
    preview_every: u64,
    /// Frames per sample: 2 = a pair, 3 to 8 = a clip (docs/outputs.md).
    #[arg(long, value_name = "K", default_value_t = 2, value_parser = clap::value_parser!(u32).range(2..=8))]
    frames: u32,
    /// Also ask for the backward flow and its valid and occlusion masks.
    #[arg(long)]
    backward: bool,
}

fn request(a: &PullArgs) -> Result<pb::StreamRequest, CliError> {
    let fingerprint = match &a.fingerprint {
        Some(h) => u64::from_str_radix(h.trim_start_matches("0x"), 16)
            .map_err(|_| CliError(format!("--fingerprint {h}: expected hex digits")))?,
        None => 0,
    };
    let crop = match &a.crop {
        Some(s) => {
            let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| CliError(format!("--crop {s}: expected WxH")))?;
            let p = |v: &str| v.trim().parse::<u32>().map_err(|_| CliError(format!("--crop {s}: expected WxH")));
            Some(pb::OutputCrop {
                width: p(w)?,
                height: p(h)?,
                mode: if a.random_crop { pb::CropMode::Random } else { pb::CropMode::Center } as i32,
            })
        }
        None => None,
    };
    let mut fields = vec![pb::Field::Image1, pb::Field::Image2, pb::Field::Flow, pb::Field::Valid];
    if a.out.is_some() {
        fields.extend([pb::Field::Occlusion, pb::Field::Holes, pb::Field::Mask1]);
    }
    if a.backward {
        fields.extend([pb::Field::FlowBackward, pb::Field::ValidBackward, pb::Field::OcclusionBackward]);
    }
    let spec = pb::SampleSpec {
        dataset: a.dataset.clone(),
        fingerprint,
        seed: a.seed,
        fields: fields.into_iter().map(|f| f as i32).collect(),
        flow_dtype: if a.f16 { pb::FlowDtype::F16 } else { pb::FlowDtype::F32 } as i32,
        compression: if a.lz4 { pb::Compression::Lz4 } else { pb::Compression::None } as i32,
        crop,
        motion_preset: a.preset.clone(),
        motion_ranges_json: String::new(),
        max_objects: a.objects,
        motions_per_image: a.motions_per_image,
        augment: a.augment.clone().unwrap_or_default(),
        frames: a.frames,
        resample: a.resample.map_or_else(String::new, |r| r.name().to_owned()),
    };
    Ok(pb::StreamRequest {
        spec: Some(spec),
        rank: a.rank,
        world_size: a.world_size,
        start_index: a.start_index,
        count: a.count,
        batch_size: a.batch_size,
        prefetch: a.prefetch,
    })
}

/// The run of consecutive samples whose photos `pull` counts (a trainer's batch).
const BATCH: usize = 8;

pub fn run(a: PullArgs) -> Result<(), CliError> {
    let req = request(&a)?;
    let options = a.connect.options()?;
    // the writer: decodes and writes in arrival (= index) order on its own thread
    let (tx, rx) = sync_channel::<pb::Sample>(64);
    let writer = match &a.out {
        Some(dir) => {
            let mut options = ExportOptions::new(a.format, dir);
            options.preview = PreviewOptions { every: a.preview_every, ..PreviewOptions::default() };
            let mut exporter = Exporter::create(options)?;
            std::thread::spawn(move || -> Result<u64, String> {
                for s in rx {
                    let sample = from_proto(&s).map_err(|e| format!("sample {}: {e}", s.index))?;
                    exporter.write(s.index, &sample).map_err(|e| e.to_string())?;
                }
                exporter.finish().map(|summary| summary.samples).map_err(|e| e.to_string())
            })
        }
        None => std::thread::spawn(move || -> Result<u64, String> {
            let mut n = 0;
            for s in rx {
                for t in &s.tensors {
                    // checked and decompressed as a trainer's client would, not copied
                    raw_view(t).map_err(|e| format!("sample {}: {e}", s.index))?;
                }
                n += 1;
            }
            Ok(n)
        }),
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .map_err(|e| CliError(format!("cannot start the async runtime: {e}")))?;
    let report = rt.block_on(async {
        let mut client = connect_with(&a.addr, &options).await.map_err(|e| CliError(format!("{}: {e}", a.addr)))?;
        // a progress line on a terminal (stderr; nothing when it is not a terminal)
        let bar = indicatif::ProgressBar::with_draw_target(Some(a.count), indicatif::ProgressDrawTarget::stderr());
        bar.set_style(
            indicatif::ProgressStyle::with_template("{pos}/{len} samples, {per_sec}, {elapsed} (eta {eta})")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        // how many different photos every 8 consecutive samples hold (a trainer's batch)
        let mut last: std::collections::VecDeque<String> = std::collections::VecDeque::with_capacity(BATCH);
        let mut fewest: Option<usize> = None;
        let pulled = pull(&mut client, req, |s| {
            if last.len() == BATCH {
                last.pop_front();
            }
            last.push_back(s.source_id.clone());
            if last.len() == BATCH {
                let distinct = last.iter().collect::<std::collections::BTreeSet<_>>().len();
                fewest = Some(fewest.map_or(distinct, |f| f.min(distinct)));
            }
            let _ = tx.send(s);
            bar.inc(1);
        })
        .await;
        bar.finish_and_clear();
        if let Some(f) = fewest {
            println!("pull: every {BATCH} consecutive samples came from at least {f} different photos");
        }
        pulled.map_err(|s| CliError(format!("{:?}: {}", s.code(), s.message())))
    });
    drop(tx);
    let written = writer.join().map_err(|_| CliError("the writer thread panicked".into()))?;
    let report = report?;
    let written = written.map_err(CliError)?;
    // a stream that failed before its first sample is its error alone (below)
    if report.samples > 0 || report.error.is_none() {
        println!("pull: {}", report.summary());
        if let Some(dir) = &a.out {
            println!("pull: wrote {written} samples to {} ({} layout, previews in previews/)", dir.display(), a.format);
        }
    }
    if let Some(status) = &report.error {
        // a request the server refuses as invalid fails again when resumed: no resume hint
        let resumable = status.code() != tonic::Code::InvalidArgument;
        let cursor = cursor_of(status)
            .filter(|_| resumable)
            .map(|(n, r)| format!("; next index {n}, resume with --start-index {r}"))
            .or_else(|| {
                report.resume_start_index.filter(|_| resumable).map(|r| format!("; resume with --start-index {r}"))
            })
            .unwrap_or_default();
        return Err(CliError(format!("the stream ended with {:?}: {}{cursor}", status.code(), status.message())));
    }
    Ok(())
}
