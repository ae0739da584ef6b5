//! `mpiflow bake`: the scene models run once per source item; the output folder (reference
//! layout + `bake.json`) is served with no model (see [`mpiflow::export::bake`] and
//! docs/deploy.md). Progress with ETA on stderr, `bake-report.json` at the end; exit status 2
//! when any item failed, naming them.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::Args;
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressState, ProgressStyle};
use mpiflow::export::bake::{BakeLayout, Baker, Progress, Shard};
use mpiflow::mpi::npz::MpiDtype;
use mpiflow::sample::pipeline::{open_source, parse_size, OpenOptions, SourceSpec};

use super::CliError;

#[derive(Args, Debug)]
pub struct BakeArgs {
    /// Source photos: a folder of images, a folder in the reference layout, one image, a
    /// WebDataset .tar shard or a folder of shards.
    #[arg(long, value_name = "DIR|SHARDS")]
    source: PathBuf,
    /// Output folder (images/, disps/, masks/, mpis/ or tar shards, and bake.json); shared by all
    /// shards of one bake.
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// The scene models (with --mpi-model its MPIs are baked into mpis/; without it the server's
    /// built-in layering lifts the baked disparity, which needs no model; the layering flags are
    /// recorded and used to check items).
    #[command(flatten)]
    scene: super::scene_flags::SceneFlags,
    /// This job's part of the items: I of N (items whose id hashes to I mod N).
    #[arg(long, value_name = "I/N", default_value = "0/1")]
    shard: Shard,
    /// Output layout: `reference` (images/, disps/, masks/, mpis/) or `webdataset` (tar shards
    /// bake-I-of-N-SSSSSS.tar with the members ID.png, ID.disp.npy, ID.mask.png, ID.mpi.npz).
    #[arg(long, value_name = "FORMAT", default_value = "reference", value_parser = ["reference", "webdataset"])]
    format: String,
    /// Items per tar shard with `--format webdataset` (a killed run redoes at most the items of
    /// the shard it was writing that were not complete).
    #[arg(long, value_name = "N", default_value_t = 100, value_parser = clap::value_parser!(u64).range(1..=1_000_000))]
    items_per_shard: u64,
    /// Element type of the stored MPIs' colours and densities (with --mpi-model): `f32`
    /// (lossless) or `f16` (half the bytes; its render error: docs/accuracy.md "MPI stored as f16").
    #[arg(long, value_name = "DTYPE", default_value = "f32", value_parser = ["f32", "f16"])]
    mpi_dtype: String,
    /// Resize every image to WxH before the models run (serve the result without --size).
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    size: Option<(usize, usize)>,
    /// Bake at most N items in this run, then stop (a planned interruption; run again to go on).
    #[arg(long, value_name = "N")]
    limit: Option<usize>,
    /// No progress bar.
    #[arg(long)]
    quiet: bool,
}

fn progress_bar(total: usize, quiet: bool) -> ProgressBar {
    if quiet || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::with_draw_target(Some(total as u64), ProgressDrawTarget::stderr());
    let style = ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} items, {rate}, ETA {eta} {msg}",
    )
    .unwrap_or_else(|_| ProgressStyle::default_bar())
    .with_key("rate", |state: &ProgressState, w: &mut dyn std::fmt::Write| {
        let _ = write!(w, "{:.2} items/s", state.per_sec());
    });
    pb.set_style(style);
    pb.enable_steady_tick(Duration::from_millis(250));
    pb
}

pub fn run(a: BakeArgs) -> Result<(), CliError> {
    let options = OpenOptions { resize: a.size, ..OpenOptions::default() };
    let source =
        open_source(&SourceSpec::Path(a.source.clone()), &options).map_err(|e| CliError(format!("--source: {e}")))?;
    for s in source.skipped() {
        eprintln!("bake: left out {} ({}): {}", s.item, s.kind.as_str(), s.reason);
    }
    let models = a.scene.models();
    let stage = Arc::new(models.build_stage().map_err(CliError)?);
    mpiflow::scene::stage::SourceScenes::new(source.clone(), stage.clone())
        .check_can_make_scenes()
        .map_err(|e| CliError(format!("--source {}: {e}", a.source.display())))?;
    let layout = match a.format.as_str() {
        "webdataset" => BakeLayout::WebDataset { items_per_shard: a.items_per_shard as usize },
        _ => BakeLayout::Reference,
    };
    let mpi_dtype = if a.mpi_dtype == "f16" { MpiDtype::F16 } else { MpiDtype::F32 };
    let baker = Baker::new(source.clone(), stage.clone(), a.size, &a.out, layout, mpi_dtype)?;
    let total = baker.items(&a.shard).len();
    eprintln!(
        "bake: shard {} = {total} of {} items of {} into {} ({})",
        a.shard,
        source.len(),
        source.describe(),
        a.out.display(),
        stage.describe()
    );
    let pb = progress_bar(total, a.quiet);
    // without a terminal: one plain line every few seconds (logs of a batch job)
    let plain = !a.quiet && !std::io::stderr().is_terminal();
    let start = Instant::now();
    let mut last_line = Instant::now();
    let report = baker.run(&a.shard, a.limit, |p: Progress| {
        pb.set_position(p.handled as u64);
        pb.set_message(format!("({} failed)", p.failed));
        if plain && (last_line.elapsed() >= Duration::from_secs(5) || p.handled == p.total) {
            last_line = Instant::now();
            let secs = start.elapsed().as_secs_f64();
            let rate = p.handled as f64 / secs.max(1e-9);
            let eta = (p.total - p.handled) as f64 / rate.max(1e-9);
            eprintln!(
                "bake: {}/{} items ({} baked, {} failed), {rate:.2} items/s, ETA {eta:.0} s",
                p.handled, p.total, p.baked, p.failed
            );
        }
    })?;
    pb.finish_and_clear();
    let path = baker.write_report(&a.shard, &report)?;
    for f in &report.failures {
        eprintln!("bake: failed {} ({}): {}", f.id, f.kind, f.reason);
    }
    eprintln!(
        "bake: shard {}: {} baked, {} already done, {} failed, {} not reached, {:.2} items/s, peak {:.0} MiB; report {}",
        a.shard,
        report.baked,
        report.already_done,
        report.failed,
        report.remaining,
        report.timings.items_per_s,
        report.peak_rss_mib.unwrap_or(0.0),
        path.display()
    );
    if report.failures.is_empty() {
        return Ok(());
    }
    // a batch job (a CI step, a Kubernetes Indexed Job) must see that items are missing
    const NAMED: usize = 10;
    let mut names: Vec<&str> = report.failures.iter().take(NAMED).map(|f| f.id.as_str()).collect();
    let more = report.failures.len().saturating_sub(NAMED);
    let and_more = if more > 0 { format!(" and {more} more") } else { String::new() };
    names.sort_unstable();
    Err(CliError(format!(
        "{} of {} items failed ({}{and_more}; each with its reason above and in {}); fix or remove them and run \
         the bake again: what is baked is kept",
        report.failures.len(),
        report.shard_items,
        names.join(", "),
        path.display()
    )))
}
