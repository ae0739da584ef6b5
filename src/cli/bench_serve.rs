//! `mpiflow bench serve`: delivered samples/s of `mpiflow serve` over loopback (a child server
//! process, pulled by the Rust client) against the in-process generator rate on the same number
//! of workers; time to first sample, p99 gap; where the CPU went (the workers' busy time from
//! the server's `/metrics`, the server's and the client's CPU time per sample against the
//! in-process run's); server memory with stalled and fast clients.

use std::time::{Duration, Instant};

use clap::Args;
use mpiflow::bench::soak::{cpu_s, metric_value, rss_mib, scrape, ServerProcess};
use mpiflow::service::client::{connect, pull};
use mpiflow::service::config::DatasetConfig;
use mpiflow::service::dataset::Datasets;
use mpiflow::service::pb;
use mpiflow::service::ServiceConfig;
use rayon::prelude::*;

use super::CliError;

#[derive(Args, Debug)]
pub struct ServeBench {
    /// Generation threads, in process and in the server (default: all cores).
    #[arg(long)]
    workers: Option<usize>,
    /// Timed samples per run.
    #[arg(long, default_value_t = 48)]
    count: u64,
    /// Source image size.
    #[arg(long, value_name = "WxH", default_value = "640x480")]
    size: String,
    /// A folder of photos (default: the bundled scenes).
    #[arg(long, value_name = "DIR")]
    source: Option<String>,
    #[arg(long, default_value_t = 1)]
    batch_size: u32,
    #[arg(long)]
    lz4: bool,
    /// Also measure the server's memory with this many stalled, then this many fast, clients (0 = skip).
    #[arg(long, default_value_t = 8)]
    clients: usize,
    /// Seconds each memory phase lasts.
    #[arg(long, default_value_t = 6.0)]
    memory_s: f64,
}

fn request(b: &ServeBench, seed: u64, count: u64) -> pb::StreamRequest {
    pb::StreamRequest {
        count,
        batch_size: b.batch_size,
        ..pb::SampleSpec {
            seed,
            compression: if b.lz4 { pb::Compression::Lz4 } else { pb::Compression::None } as i32,
            ..Default::default()
        }
        .stream()
    }
}

pub fn run(b: ServeBench) -> Result<(), CliError> {
    let workers = b.workers.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, std::num::NonZero::get));
    let mut config = ServiceConfig { workers, size: Some(b.size.clone()), ..ServiceConfig::default() };
    if let Some(s) = &b.source {
        config.datasets = vec![DatasetConfig::parse(s).map_err(CliError)?];
    }
    config.validate()?;
    let local = run_in_process(&b, &config, workers)?;

    // ---- served: a child server process, pulled over loopback
    let args = server_args(&b, workers);
    let exe = std::env::current_exe().map_err(|e| CliError(format!("cannot find the mpiflow binary: {e}")))?;
    let server = ServerProcess::start(&exe, &args).map_err(|e| CliError(e.0))?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| CliError(format!("async runtime: {e}")))?;
    let result = rt.block_on(served(&b, &server, &local, workers));
    server.terminate(Duration::from_secs(30));
    result
}

/// The in-process run's figures, the served run's yardstick.
struct InProcess {
    /// The samples of the warm-up (one per source).
    warm: u64,
    /// Samples per second.
    rate: f64,
    /// The CPU seconds of this process over the run, where the platform tells them.
    cpu_s: Option<f64>,
}

/// In process: the generator on `workers` threads, warmed on every source, then `b.count` samples
/// timed; prints its line.
fn run_in_process(b: &ServeBench, config: &ServiceConfig, workers: usize) -> Result<InProcess, CliError> {
    let datasets = Datasets::open(config)?;
    let ds = datasets.default_dataset().clone();
    let generator = ds.generator.clone();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(workers).build()?;
    let warm = ds.sources() as u64;
    pool.install(|| (0..warm).into_par_iter().try_for_each(|i| generator.sample(0, i).map(drop)))?;
    let me = std::process::id();
    let (t, cpu0) = (Instant::now(), cpu_s(me));
    pool.install(|| (0..b.count).into_par_iter().try_for_each(|i| generator.sample(1, i).map(drop)))?;
    let rate = b.count as f64 / t.elapsed().as_secs_f64();
    let cpu = cpu0.zip(cpu_s(me)).map(|(a, z)| z - a);
    drop(datasets);
    println!(
        "in process: {rate:.2} samples/s ({} samples of {}, {workers} workers, dataset {} with {} sources)",
        b.count,
        b.size,
        ds.name,
        ds.sources()
    );
    Ok(InProcess { warm, rate, cpu_s: cpu })
}

/// The flags of the child server: loopback, `workers` workers, the bench's size and source, its
/// metrics on.
fn server_args(b: &ServeBench, workers: usize) -> Vec<String> {
    let mut args: Vec<String> = vec![
        "--addr".into(),
        "127.0.0.1:0".into(),
        "--workers".into(),
        workers.to_string(),
        "--size".into(),
        b.size.clone(),
        "--log-level".into(),
        "warn".into(),
        "--metrics-addr".into(),
        "127.0.0.1:0".into(),
    ];
    if let Some(s) = &b.source {
        args.extend(["--source".into(), s.clone()]);
    }
    args
}

/// Served: the child `server` pulled over loopback (its scene cache warmed like the in-process
/// run), its rate against `local`'s and where the CPU went; then the memory phase.
async fn served(b: &ServeBench, server: &ServerProcess, local: &InProcess, workers: usize) -> Result<(), CliError> {
    let (me, pid, addr) = (std::process::id(), server.pid(), server.addr.clone());
    let mut client = connect(&addr).await.map_err(|e| CliError(format!("{addr}: {e}")))?;
    // warm the server's scene cache like the in-process run
    let w = pull(&mut client, request(b, 0, local.warm), |_| {}).await.map_err(|s| CliError(s.to_string()))?;
    if let Some(e) = w.error {
        return Err(CliError(format!("warm-up pull: {e}")));
    }
    let usage = || async {
        let busy = match &server.metrics_addr {
            Some(m) => scrape(m).await.map(|t| {
                ["total", "encode"]
                    .iter()
                    .filter_map(|k| metric_value(&t, &format!("mpiflow_stage_seconds_sum{{stage=\"{k}\"}}")))
                    .sum::<f64>()
            }),
            None => None,
        };
        (busy, cpu_s(pid), cpu_s(me))
    };
    let before = usage().await;
    let r = pull(&mut client, request(b, 1, b.count), |_| {}).await.map_err(|s| CliError(s.to_string()))?;
    let after = usage().await;
    if let Some(e) = &r.error {
        return Err(CliError(format!("pull: {e}")));
    }
    println!("served:     {}", r.summary());
    println!(
        "served / in process = {:.1}% (time to first sample {:.1} ms, p99 gap {:.1} ms, batch {}, lz4 {})",
        100.0 * r.samples_per_s() / local.rate,
        r.first_sample_ms.unwrap_or(0.0),
        r.gap_quantile_ms(0.99).unwrap_or(0.0),
        b.batch_size,
        b.lz4
    );
    let per = |a: Option<f64>, z: Option<f64>| a.zip(z).map(|(a, z)| 1e3 * (z - a) / b.count as f64);
    let ms = |v: Option<f64>| v.map_or_else(|| "?".into(), |v| format!("{v:.1} ms"));
    let run_s = r.seconds;
    println!(
        "where the CPU went (per sample): in process {}; served: server {}, client {}; the workers were busy {} of the run",
        ms(local.cpu_s.map(|c| 1e3 * c / b.count as f64)),
        ms(per(before.1, after.1)),
        ms(per(before.2, after.2)),
        before.0.zip(after.0).map_or_else(
            || "?".into(),
            |(a, z)| format!("{:.1}%", 100.0 * (z - a) / (run_s * workers as f64))
        )
    );
    if b.clients == 0 {
        return Ok(());
    }
    memory_phase(b, &addr, pid).await
}

/// The memory phase: the server's RSS idle, with `b.clients` streams opened and never read, and
/// at its peak with as many read as fast as they come.
async fn memory_phase(b: &ServeBench, addr: &str, pid: u32) -> Result<(), CliError> {
    let phase = Duration::from_secs_f64(b.memory_s);
    let idle = rss_mib(pid).unwrap_or(0.0);
    // stalled: streams opened and never read
    let mut stalled = Vec::new();
    for _ in 0..b.clients {
        let mut c = connect(addr).await.map_err(|e| CliError(e.to_string()))?;
        let s = c.stream_samples(request(b, 2, 0)).await.map_err(|s| CliError(s.to_string()))?;
        stalled.push((c, s));
    }
    tokio::time::sleep(phase).await;
    let stalled_rss = rss_mib(pid).unwrap_or(0.0);
    drop(stalled);
    tokio::time::sleep(Duration::from_millis(500)).await;
    // fast: streams read as fast as they come
    let mut tasks = Vec::new();
    for i in 0..b.clients {
        let addr = addr.to_string();
        let req = request(b, 3 + i as u64, 0);
        tasks.push(tokio::spawn(async move {
            let mut c = connect(&addr).await.ok()?;
            let mut s = c.stream_samples(req).await.ok()?.into_inner();
            let stop = Instant::now() + phase;
            let mut n = 0u64;
            while Instant::now() < stop {
                match s.message().await {
                    Ok(Some(batch)) => n += batch.samples.len() as u64,
                    _ => break,
                }
            }
            Some(n)
        }));
    }
    let mut peak = 0.0f64;
    let start = Instant::now();
    while start.elapsed() < phase {
        tokio::time::sleep(Duration::from_millis(200)).await;
        peak = peak.max(rss_mib(pid).unwrap_or(0.0));
    }
    let mut fast_samples = 0;
    for t in tasks {
        fast_samples += t.await.ok().flatten().unwrap_or(0);
    }
    println!(
        "server memory (RSS): {idle:.0} MiB idle after the runs; {stalled_rss:.0} MiB with {n} stalled clients \
         after {s:.0} s; peak {peak:.0} MiB with {n} fast clients ({fast_samples} samples in {s:.0} s)",
        n = b.clients,
        s = b.memory_s
    );
    Ok(())
}
