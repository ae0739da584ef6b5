//! `mpiflow generate`: an offline training set on disk (`flo`, `kitti` or `webdataset` layout,
//! see `docs/export.md`), made from a source folder or the bundled default scenes, with a
//! progress bar, preview sheets and a summary line.
//!
//! Samples are generated in parallel (rayon, chunks of a few samples per thread), encoded on the
//! workers and written in index order by one writer thread, so the output does not depend on the
//! thread count. A source item that fails to load is passed over (its samples come from the next
//! good item, see [`Generator::sample`]) with a one-line warning at the end; a sample that still
//! cannot be made is skipped with a one-line warning; the run goes on.

use std::path::PathBuf;
use std::sync::mpsc::{sync_channel, Receiver};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use clap::Args;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressState, ProgressStyle};
use mpiflow::export::{
    sample_key, EncodedSample, ExportFormat, ExportOptions, ExportSummary, Exporter, PreviewOptions,
};
use mpiflow::geometry::Intrinsics;
use mpiflow::mpi::layering::MAX_PLANES;
use mpiflow::sample::config::{SampleConfig, MAX_MOTIONS_PER_IMAGE, MAX_SCENE_WINDOW};
use mpiflow::sample::crop::CropSpec;
use mpiflow::sample::error::SampleError;
use mpiflow::sample::merge::{LabelRule, MergeRule};
use mpiflow::sample::motion::MotionPreset;
use mpiflow::sample::pipeline::{open_source, parse_size, Generator, OpenOptions, Pipeline, SourceSpec};
use mpiflow::sample::Sample;
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;
use mpiflow::scene::stage::SourceScenes;
use mpiflow::scene::SceneLoader;
use mpiflow::source::dir::IntrinsicsSpec;
use mpiflow::source::Source;
use rayon::prelude::*;

use super::{parse_floats, CliError};

#[derive(Args, Debug)]
pub struct GenerateArgs {
    /// Source photos: a folder of images, a folder in the reference layout (images/ with
    /// optional depths/, disps/, masks/, mpis/), one image, a WebDataset .tar shard or a folder
    /// of shards. Default: the bundled scenes.
    #[arg(long, value_name = "DIR")]
    source: Option<PathBuf>,
    /// Number of samples (indices --start .. --start + N).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..))]
    count: u64,
    /// Output folder (created if missing).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Refuse to run when any file of the source is left out (a photo that cannot serve, a
    /// format mpiflow does not read) instead of warning and going on with the others.
    #[arg(long)]
    strict: bool,
    /// Layout: flo (FlyingChairs-style, .flo flow), kitti (16-bit flow PNG), webdataset (tar
    /// shards), sintel (the MPI Sintel training layout, for clips) or stereo (left/ right/
    /// disparity/ folders of rectified pairs; needs --preset stereo).
    #[arg(long, default_value = "flo", value_parser = parse_format)]
    format: ExportFormat,
    /// Motions drawn from each source item while its scene is warm (its scene is computed once
    /// for them).
    #[arg(long, value_name = "M", default_value_t = SampleConfig::default().motions_per_image, value_parser = clap::value_parser!(u64).range(1..=MAX_MOTIONS_PER_IMAGE))]
    motions_per_image: u64,
    /// Source items whose motions are interleaved, so that consecutive samples come from
    /// different items (1 = each item's motions in a row; docs/export.md).
    #[arg(long, value_name = "K", default_value_t = SampleConfig::default().scene_window, value_parser = clap::value_parser!(u64).range(1..=MAX_SCENE_WINDOW))]
    scene_window: u64,
    /// Seed of the samples: same source, seed and index, same sample.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// First sample index.
    #[arg(long, value_name = "I", default_value_t = 0)]
    start: u64,
    /// Motion law: reference, paper-kitti, depthstillation, mixed or stereo (rectified pairs).
    #[arg(long, value_name = "NAME", default_value = "reference")]
    preset: MotionPreset,
    /// Most objects moved independently per sample (0 = camera motion only).
    #[arg(long, value_name = "K", default_value_t = 1, value_parser = clap::value_parser!(u8))]
    objects: u8,
    /// How object and scene renders are merged: reference or depth-aware.
    #[arg(long, value_name = "RULE", default_value = "depth-aware")]
    merge: MergeRule,
    /// Which valid pixels are marked occluded: honest (visible only where image2 shows the
    /// pixel's surface, no hole next to its target) or depth-only (occluded only where hidden
    /// behind by depth; holes never occlude).
    #[arg(long, value_name = "RULE", default_value = "honest")]
    label_rule: LabelRule,
    /// What fills image2's holes before 2-D inpainting with the depth-aware merge: inpaint (the
    /// default: Telea alone, the paper's rule) or planes (what the MPI holds behind a moved
    /// object's place, the completed background).
    #[arg(long, value_name = "FILL", default_value_t = SampleConfig::default().background)]
    background: mpiflow::sample::background::Background,
    /// Colour kernel of the target render.
    #[arg(long, value_name = "KERNEL", default_value_t = mpiflow::render::Resample::default(),
          value_parser = super::kernels::resample_parser())]
    resample: mpiflow::render::Resample,
    /// Restore image1's sensor-noise level in image2 and the later frames (per channel, the
    /// variance the render lost; deterministic by address; part of the fingerprint).
    #[arg(long)]
    restore_noise: bool,
    /// Alias-free minification: planes the view shrinks are sampled from prefiltered levels
    /// (part of the fingerprint).
    #[arg(long)]
    minify: bool,
    /// What fills image2's holes: exemplar (texture from image1's background at the hole's
    /// depth) or a Telea variant (telea, telea-known-only, telea-zero-order, telea-opencv).
    #[arg(long, value_name = "METHOD", default_value_t = mpiflow::sample::config::InpaintMethod::default())]
    inpaint: mpiflow::sample::config::InpaintMethod,
    /// Camera intrinsics fx,fy,cx,cy in pixels for every source image (default 0.58 W, 0.58 H,
    /// centre). Only with --source.
    #[arg(long, value_name = "FX,FY,CX,CY", value_parser = parse_floats::<4>, allow_hyphen_values = true)]
    intrinsics: Option<[f64; 4]>,
    /// Resize every source image to WxH (default: keep sizes; the bundled scenes are 640x480).
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    size: Option<(usize, usize)>,
    /// Crop every sample to WxH (centre, or random with --random-crop), made over the crop only:
    /// the bytes `mpiflow pull --crop WxH` receives.
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    crop: Option<(usize, usize)>,
    /// With --crop: a random window of each sample (deterministic by address) instead of the
    /// centre.
    #[arg(long, requires = "crop")]
    random_crop: bool,
    #[command(flatten)]
    scene: super::scene_flags::SceneFlags,
    /// Worker threads (default: all cores).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1..=1024))]
    threads: Option<u64>,
    /// Samples per WebDataset shard (sample I goes to shard I / S).
    #[arg(long, value_name = "S", default_value_t = 1000, value_parser = clap::value_parser!(u64).range(1..))]
    shard_size: u64,
    /// A preview contact sheet at every index that is a multiple of N, and at the first sample (0 = none).
    #[arg(long, value_name = "N", default_value_t = 100)]
    preview_every: u64,
    /// Rows (samples) per preview sheet.
    #[arg(long, value_name = "R", default_value_t = 4, value_parser = clap::value_parser!(u64).range(1..=256))]
    preview_rows: u64,
    /// Width of one preview panel in pixels.
    #[arg(long, value_name = "PX", default_value_t = 160, value_parser = clap::value_parser!(u64).range(8..=4096))]
    preview_width: u64,
    /// Scene cache budget in MiB (a 640x480 scene with 32 planes takes about 45 MiB).
    #[arg(long, value_name = "MIB", default_value_t = mpiflow::service::config::DEFAULT_CACHE_MB, value_parser = clap::value_parser!(u64).range(1..))]
    cache_mb: u64,
    /// Frames per sample: 2 = a pair, 3 to 8 = a clip along the constant-velocity trajectory
    /// (docs/outputs.md; part of the fingerprint).
    #[arg(long, value_name = "K", default_value_t = 2, value_parser = clap::value_parser!(u64).range(2..=8))]
    frames: u64,
    /// Also write the backward flow (image2 -> image1) and its valid and occlusion masks.
    #[arg(long)]
    backward: bool,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

fn parse_format(s: &str) -> Result<ExportFormat, String> {
    s.parse()
}

/// The scene models of the flags (the same [`ModelConfig`] the server reads).
fn model_config(a: &GenerateArgs) -> ModelConfig {
    a.scene.models()
}

/// The source of the flags, opened as the server opens a dataset's.
fn source(a: &GenerateArgs) -> Result<Arc<dyn Source>, CliError> {
    let intrinsics = match a.intrinsics {
        Some(v) => {
            let k = Intrinsics::new(v[0], v[1], v[2], v[3]);
            if !k.is_valid() {
                return Err(CliError("--intrinsics: focal lengths must be non-zero".into()));
            }
            Some(IntrinsicsSpec::Pixels(k))
        }
        None => None,
    };
    let spec = match &a.source {
        Some(path) => SourceSpec::Path(path.clone()),
        None if intrinsics.is_some() => {
            return Err(CliError(
                "--intrinsics needs --source (the bundled scenes are composed for their own camera)".into(),
            ))
        }
        None => SourceSpec::Builtin,
    };
    let options = OpenOptions { resize: a.size, intrinsics, ..OpenOptions::default() };
    let what = if a.source.is_some() { "--source" } else { "bundled scenes" };
    let source = open_source(&spec, &options).map_err(|e| CliError(format!("{what}: {e}")))?;
    let skipped = source.skipped();
    if !a.strict {
        // said at once: a refusal below (no photo with depth left) names what was left out
        for s in &skipped {
            eprintln!("warning: {} left out of the source: {}", s.item, s.reason);
        }
    }
    if a.strict && !skipped.is_empty() {
        return Err(CliError(format!(
            "--strict: {what}: {}; remove or fix them, or run without --strict",
            mpiflow::source::dir::left_out_summary(&skipped)
        )));
    }
    Ok(source)
}

/// What a worker hands to the writer for one index.
enum Outcome {
    Done(Box<(Sample, EncodedSample)>),
    /// The sample could not be made (or encoded): the warning text.
    Skipped(String),
}

fn progress_bar(count: u64, quiet: bool) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::with_draw_target(Some(count), ProgressDrawTarget::stderr());
    let style = ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} samples, {rate}, ETA {eta} {msg}",
    )
    .unwrap_or_else(|_| ProgressStyle::default_bar())
    .with_key("rate", |state: &ProgressState, w: &mut dyn std::fmt::Write| {
        let _ = write!(w, "{:.2} samples/s", state.per_sec());
    });
    pb.set_style(style);
    pb.enable_steady_tick(Duration::from_millis(250));
    pb
}

pub fn run(a: GenerateArgs) -> Result<(), CliError> {
    let end = a
        .start
        .checked_add(a.count)
        .ok_or_else(|| CliError(format!("--start {} + --count {} overflows", a.start, a.count)))?;
    if a.out.exists() && !a.out.is_dir() {
        return Err(CliError(format!("--out {}: exists and is not a directory", a.out.display())));
    }
    let source = source(&a)?;
    if source.is_empty() {
        return Err(CliError(format!("{}: no images to make samples from", source.describe())));
    }
    let planes = a.scene.models().planes;
    if !(1..=MAX_PLANES).contains(&planes) {
        return Err(CliError(format!("--planes {planes}: expected 1 to {MAX_PLANES}")));
    }
    let stage = Arc::new(model_config(&a).build_stage().map_err(CliError)?);
    let cache = Arc::new(SceneCache::new(usize::try_from(a.cache_mb.saturating_mul(1 << 20)).unwrap_or(usize::MAX)));
    let pipeline = Pipeline::new(source.clone(), stage, cache, sample_config(&a))?;
    let generator = pipeline.generator().clone();
    let loader = pipeline.loader().clone();
    let (threads, pool) = worker_pool(&a)?;
    let exporter = exporter(&a)?;

    eprintln!(
        "generate: {} samples (indices {}..{end}) from {} into {} ({}), {threads} threads, dataset fingerprint {:016x}",
        a.count,
        a.start,
        loader.describe(),
        a.out.display(),
        a.format,
        pipeline.fingerprint()
    );
    let started = Instant::now();
    let pb = progress_bar(a.count, a.quiet);
    let (tx, rx) = sync_channel::<Vec<(u64, Outcome)>>(2);
    let writer = spawn_writer(exporter, rx, pb.clone())?;
    let crop = a.crop.map(|(w, h)| CropSpec { width: w as u32, height: h as u32, random: a.random_crop });
    let make = |index: u64| make_one(&generator, &loader, (a.seed, crop.as_ref()), a.format, index);
    let chunk = (threads * 2).max(2) as u64;
    let mut next = a.start;
    pool.install(|| {
        while next < end {
            let stop = end.min(next + chunk);
            let outcomes: Vec<(u64, Outcome)> = (next..stop).into_par_iter().map(|i| (i, make(i))).collect();
            if tx.send(outcomes).is_err() {
                break; // the writer stopped on an error; it is reported below
            }
            next = stop;
        }
    });
    drop(tx);
    let joined = writer.join();
    pb.finish_and_clear();
    let (summary, skipped) = match joined {
        Ok(r) => r?,
        Err(_) => return Err(CliError("the writer thread panicked".into())),
    };
    let secs = started.elapsed().as_secs_f64();
    let bad = warn_bad_sources(&generator);
    report(&summary, skipped, bad, secs, &a)
}

/// The sample options of the flags, over the preset's.
fn sample_config(a: &GenerateArgs) -> SampleConfig {
    SampleConfig {
        max_objects: usize::from(a.objects),
        merge: a.merge,
        label_rule: a.label_rule,
        background: a.background,
        restore_noise: a.restore_noise,
        minify: a.minify,
        motions_per_image: a.motions_per_image,
        scene_window: a.scene_window,
        frames: a.frames as usize,
        backward: a.backward,
        resample: a.resample,
        inpaint_method: a.inpaint,
        ..SampleConfig::with_preset(a.preset)
    }
}

/// The worker threads (`--threads`, or one per core) and their pool.
fn worker_pool(a: &GenerateArgs) -> Result<(usize, rayon::ThreadPool), CliError> {
    let threads = match a.threads {
        Some(n) => n as usize,
        None => std::thread::available_parallelism().map(std::num::NonZero::get).unwrap_or(1),
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("mpiflow-generate-{i}"))
        .build()
        .map_err(|e| CliError(format!("cannot start {threads} worker threads: {e}")))?;
    Ok((threads, pool))
}

/// The exporter of `--out` in `--format`, with its shard size and preview sheets.
fn exporter(a: &GenerateArgs) -> Result<Exporter, CliError> {
    let mut options = ExportOptions::new(a.format, &a.out);
    options.shard_size = a.shard_size;
    options.preview =
        PreviewOptions { every: a.preview_every, rows: a.preview_rows as usize, panel_width: a.preview_width as usize };
    Ok(Exporter::create(options)?)
}

/// What the writer thread gives back: the export's summary and the samples skipped.
type Written = Result<(ExportSummary, u64), mpiflow::export::ExportError>;

/// The writer: takes chunks in index order, writes them, reports skips.
fn spawn_writer(
    exporter: Exporter,
    rx: Receiver<Vec<(u64, Outcome)>>,
    writer_pb: ProgressBar,
) -> Result<JoinHandle<Written>, CliError> {
    std::thread::Builder::new()
        .name("mpiflow-generate-writer".into())
        .spawn(move || {
            let mut exporter = exporter;
            let mut skipped = 0u64;
            for chunk in rx {
                for (index, outcome) in chunk {
                    match outcome {
                        Outcome::Done(b) => {
                            let (sample, encoded) = *b;
                            exporter.write_encoded(&encoded, &sample)?;
                        }
                        Outcome::Skipped(why) => {
                            skipped += 1;
                            writer_pb.suspend(|| eprintln!("warning: sample {} skipped: {why}", sample_key(index)));
                        }
                    }
                    writer_pb.inc(1);
                }
            }
            let summary = exporter.finish()?;
            Ok::<_, mpiflow::export::ExportError>((summary, skipped))
        })
        .map_err(|e| CliError(format!("cannot start the writer thread: {e}")))
}

/// Sample `index` made and encoded (on a worker), or the warning that skips it.
fn make_one(
    generator: &Generator,
    loader: &SourceScenes,
    (seed, crop): (u64, Option<&CropSpec>),
    format: ExportFormat,
    index: u64,
) -> Outcome {
    let describe_source = || match generator.source_item(index) {
        Some(item) => format!("source item {item} ({})", loader.id(item)),
        None => "no source".into(),
    };
    let made = match crop {
        Some(c) => generator.sample_cropped(seed, index, c).map(|(s, _)| s),
        None => generator.sample(seed, index),
    };
    match made {
        Ok(sample) => match mpiflow::export::encode_for(format, index, &sample) {
            Ok(encoded) => Outcome::Done(Box::new((sample, encoded))),
            Err(e) => Outcome::Skipped(format!("{}: cannot encode: {e}", describe_source())),
        },
        // a scene error already names the source item
        Err(e @ SampleError::Scene { .. }) => Outcome::Skipped(e.to_string()),
        // the frame is the photos' working size (or --size): say which setting makes it larger
        Err(SampleError::Crop(c)) => Outcome::Skipped(format!(
            "{}: --crop {c}; pass --size WxH with both sides at least {}x{} to render a larger frame, or a smaller \
             --crop",
            describe_source(),
            c.want_w,
            c.want_h
        )),
        Err(e) => Outcome::Skipped(format!("{}: {e}", describe_source())),
    }
}

/// Bad sources passed over (their samples came from the next good source), once each; the number
/// of source items the generator skipped.
fn warn_bad_sources(generator: &Generator) -> usize {
    let bad = generator.skipped();
    for (item, id, reason) in &bad {
        eprintln!("warning: source item {item} ({id}) skipped, its samples use the next good source: {reason}");
    }
    bad.len()
}

/// The closing line of a run (what was written, how fast), and the error when nothing was.
fn report(summary: &ExportSummary, skipped: u64, bad: usize, secs: f64, a: &GenerateArgs) -> Result<(), CliError> {
    let format = a.format;
    let mut extra = format!("{} preview sheet(s)", summary.previews.len());
    if bad > 0 {
        extra.push_str(&format!(", {bad} bad source(s) passed over"));
    }
    if format == ExportFormat::WebDataset {
        extra.push_str(&format!(", {} shard(s)", summary.shards.len()));
    }
    println!(
        "generate: wrote {} samples ({skipped} skipped) to {} in {secs:.1} s ({:.2} samples/s, {:.1} MB, {extra}), format {format}",
        summary.samples,
        a.out.display(),
        summary.samples as f64 / secs.max(1e-9),
        summary.bytes as f64 / 1e6,
    );
    if summary.samples == 0 {
        return Err(CliError(format!("no sample written: all {} samples failed (see the warnings above)", a.count)));
    }
    Ok(())
}
