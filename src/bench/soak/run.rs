//! A soak run: the server started, the solo client, the mix with its readings, the tally.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::time::timeout_at;

use super::clients::{cancelling_client, fast_client, newcomer, slow_client, stalled_client, uploading_client};
use super::process::{metric_value, rss_mib, scrape, ServerProcess};
use super::report::{SoakConfig, SoakError, SoakPoint, SoakReport};
use crate::bench::clients::Shared;
use crate::bench::hostile;
use crate::service::client::connect;
use crate::service::pb;

/// Runs a soak (see the documentation of `bench::soak`), printing progress lines through `log`.
pub fn run_soak(cfg: &SoakConfig, log: &mut dyn FnMut(&str)) -> Result<SoakReport, SoakError> {
    if cfg.fast == 0 || cfg.duration.is_zero() {
        return Err(SoakError("a soak needs at least one fast client and a positive duration".into()));
    }
    let mut args: Vec<String> = [
        "--addr",
        "127.0.0.1:0",
        "--metrics-addr",
        "127.0.0.1:0",
        "--workers",
        &cfg.workers.to_string(),
        "--size",
        &cfg.size,
        "--log-level",
        "error",
    ]
    .iter()
    .map(|s| (*s).to_string())
    .collect();
    args.extend(cfg.server_args.iter().cloned());
    let server = ServerProcess::start(&cfg.exe, &args)?;
    let pid = server.pid();
    let addr = server.addr.clone();
    let metrics = server.metrics_addr.clone();
    log(&format!("server pid {pid} on {addr}, metrics {}", metrics.as_deref().unwrap_or("-")));
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| SoakError(format!("async runtime: {e}")))?;
    let report = rt.block_on(mix(cfg, &addr, pid, metrics.as_deref(), log));
    rt.shutdown_timeout(Duration::from_secs(5));
    log("clients done; draining the server (SIGTERM)");
    let status = server.terminate(Duration::from_secs(30));
    let mut report = report?;
    if !status.is_some_and(|s| s.success()) {
        report.unexpected += 1;
        report.unexpected_examples.push(format!("the server did not exit cleanly on SIGTERM: {status:?}"));
    }
    Ok(report)
}

/// Starts every client of the mix but the solo one; each stops at `until`.
fn spawn_clients(
    cfg: &SoakConfig,
    addr: &str,
    until: tokio::time::Instant,
    hold: Duration,
    sh: &Arc<Shared>,
) -> Vec<(&'static str, tokio::task::JoinHandle<()>)> {
    let mut tasks = Vec::new();
    for k in 0..cfg.fast {
        tasks.push((
            "fast",
            tokio::spawn(fast_client(addr.to_string(), 3, k as u32, cfg.fast as u32, until, sh.clone())),
        ));
    }
    for k in 0..cfg.stalled {
        tasks.push((
            "stalled",
            tokio::spawn(stalled_client(addr.to_string(), 1000 * (k as u64 + 1), 1, 0, hold, None, until, sh.clone())),
        ));
    }
    // the hostile clients, each from its attacker address
    let (n, frames) = (cfg.attacker_addresses, cfg.hostile_frames);
    let mut k = 0;
    let mut from = || {
        k += 1;
        hostile::attacker(k - 1, n)
    };
    for j in 0..cfg.batch_stall {
        let seed = 5000 * (j as u64 + 1);
        let f = Some(from().into());
        tasks.push((
            "batch-stall",
            tokio::spawn(stalled_client(addr.to_string(), seed, 64, frames, hold, f, until, sh.clone())),
        ));
    }
    for j in 0..cfg.unary {
        let client = hostile::unary_client(addr.to_string(), 300 + j as u64, frames, from(), until, sh.clone());
        tasks.push(("unary", tokio::spawn(client)));
    }
    for _ in 0..cfg.unread {
        let client = hostile::unread_client(addr.to_string(), cfg.unread_calls, frames, from(), until, sh.clone());
        tasks.push(("unread", tokio::spawn(client)));
    }
    for _ in 0..cfg.idle {
        tasks.push(("idle", tokio::spawn(hostile::idle_client(addr.to_string(), from(), until, sh.clone()))));
    }
    for _ in 0..cfg.watch {
        tasks.push(("watch", tokio::spawn(hostile::watch_client(addr.to_string(), from(), until, sh.clone()))));
    }
    if cfg.window_streams > 0 {
        let client = hostile::window_client(addr.to_string(), cfg.window_streams, frames, from(), until, sh.clone());
        tasks.push(("window", tokio::spawn(client)));
    }
    for k in 0..cfg.slow {
        tasks.push(("slow", tokio::spawn(slow_client(addr.to_string(), 100 + k as u64, until, sh.clone()))));
    }
    for k in 0..cfg.cancelling {
        tasks
            .push(("cancelling", tokio::spawn(cancelling_client(addr.to_string(), 200 + k as u64, until, sh.clone()))));
    }
    for k in 0..cfg.uploading {
        tasks.push(("uploading", tokio::spawn(uploading_client(addr.to_string(), k, until, sh.clone()))));
    }
    tasks
}

/// The server under test: its gRPC address, its process id, its metrics address.
#[derive(Clone, Copy)]
struct Target<'a> {
    addr: &'a str,
    pid: u32,
    metrics: Option<&'a str>,
}

async fn mix(
    cfg: &SoakConfig,
    addr: &str,
    pid: u32,
    metrics: Option<&str>,
    log: &mut dyn FnMut(&str),
) -> Result<SoakReport, SoakError> {
    let target = Target { addr, pid, metrics };
    let mut report = SoakReport::default();
    warm_up(addr).await?;
    report.idle_rss_mib = rss_mib(pid).unwrap_or(0.0);
    let solo = solo(cfg, addr, &mut report, log).await;

    // the mix
    let sh = Arc::new(Shared::default());
    let start = tokio::time::Instant::now();
    let until = start + cfg.duration;
    let hold = (cfg.duration / 3).min(Duration::from_secs(30));
    let tasks = spawn_clients(cfg, addr, until, hold, &sh);
    let peak = readings(cfg, target, &sh, (start, until), &mut report, log).await;
    report.mix_s = (tokio::time::Instant::now() - start).as_secs_f64();
    stop_clients(tasks, &sh).await;
    log("clients stopped");
    report.end_rss_mib = settled_rss(pid).await;
    report.peak_rss_mib = peak;
    tally(cfg, metrics, &solo, &sh, &mut report).await;
    Ok(report)
}

/// Warms the scene cache: one pull of eight samples.
async fn warm_up(addr: &str) -> Result<(), SoakError> {
    let mut client = connect(addr).await.map_err(|e| SoakError(format!("{addr}: {e}")))?;
    let warm = pb::StreamRequest { count: 8, ..pb::SampleSpec { seed: 1, ..Default::default() }.stream() };
    let w = crate::service::client::pull(&mut client, warm, |_| {}).await.map_err(|s| SoakError(s.to_string()))?;
    if let Some(e) = w.error {
        return Err(SoakError(format!("warm-up pull: {e}")));
    }
    drop(client);
    Ok(())
}

/// One fast client alone for `cfg.solo`: its samples/s go to the report; returns what it shared.
async fn solo(cfg: &SoakConfig, addr: &str, report: &mut SoakReport, log: &mut dyn FnMut(&str)) -> Arc<Shared> {
    let solo = Arc::new(Shared::default());
    let t = Instant::now();
    let until = tokio::time::Instant::now() + cfg.solo;
    fast_client(addr.to_string(), 2, 0, 1, until, solo.clone()).await;
    report.solo_per_s = solo.fast_samples.load(Ordering::Relaxed) as f64 / t.elapsed().as_secs_f64();
    log(&format!(
        "solo: {:.2} samples/s ({} samples in {:.0} s); idle RSS {:.0} MiB",
        report.solo_per_s,
        solo.fast_samples.load(Ordering::Relaxed),
        t.elapsed().as_secs_f64(),
        report.idle_rss_mib
    ));
    solo
}

/// The readings during the mix (`start` to `until`), every `cfg.report_every`: the server's
/// memory, its buffered bytes, a newcomer, the fast clients' rate; returns the peak memory.
async fn readings(
    cfg: &SoakConfig,
    target: Target<'_>,
    sh: &Shared,
    (start, until): (tokio::time::Instant, tokio::time::Instant),
    report: &mut SoakReport,
    log: &mut dyn FnMut(&str),
) -> f64 {
    let Target { addr, pid, metrics } = target;
    let every = cfg.report_every.max(Duration::from_millis(200));
    let (mut last_n, mut last_t) = (0u64, start);
    let mut peak = report.idle_rss_mib;
    loop {
        let now = tokio::time::Instant::now();
        if now >= until {
            break;
        }
        tokio::time::sleep_until((now + every).min(until)).await;
        let now = tokio::time::Instant::now();
        let n = sh.fast_samples.load(Ordering::Relaxed);
        let rss = rss_mib(pid).unwrap_or(0.0);
        peak = peak.max(rss);
        let buffered = match metrics {
            Some(m) => scrape(m).await.and_then(|t| metric_value(&t, "mpiflow_buffered_bytes")),
            None => None,
        };
        match newcomer(addr).await {
            Some(ms) => report.newcomer_max_ms = report.newcomer_max_ms.max(ms),
            None => report.newcomers_refused += 1,
        }
        let p = SoakPoint {
            t_s: (now - start).as_secs_f64(),
            rss_mib: rss,
            buffered_bytes: buffered,
            fast_per_s: (n - last_n) as f64 / (now - last_t).as_secs_f64().max(1e-9),
        };
        log(&format!(
            "t {:>6.0} s  RSS {:>6.0} MiB  buffered {}  fast {:>6.2} samples/s",
            p.t_s,
            p.rss_mib,
            p.buffered_bytes.map_or("-".to_string(), |b| format!("{:.1} MB", b / 1e6)),
            p.fast_per_s
        ));
        report.points.push(p);
        (last_n, last_t) = (n, now);
    }
    peak
}

/// Waits for every client task: each stops at the deadline; one that has not within 15 s more
/// is a finding.
async fn stop_clients(tasks: Vec<(&'static str, tokio::task::JoinHandle<()>)>, sh: &Shared) {
    let grace = tokio::time::Instant::now() + Duration::from_secs(15);
    for (kind, mut t) in tasks {
        match timeout_at(grace, &mut t).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => sh.error(kind, "task failed", &e.to_string(), false),
            Err(_) => {
                t.abort();
                sh.error(kind, "did not stop", "still running 15 s after the deadline", false);
            }
        }
    }
}

/// The server's memory once every client has left (the streams are dropped): the last of ten
/// readings 300 ms apart.
async fn settled_rss(pid: u32) -> f64 {
    let mut end = rss_mib(pid).unwrap_or(0.0);
    for _ in 0..10 {
        tokio::time::sleep(Duration::from_millis(300)).await;
        end = rss_mib(pid).unwrap_or(end);
    }
    end
}

/// The counts of the mix's clients (and the solo one's losses and errors), the server's
/// buffered peak and budget, and the kinds of client that got nothing done.
async fn tally(cfg: &SoakConfig, metrics: Option<&str>, solo: &Shared, sh: &Shared, report: &mut SoakReport) {
    report.fast_samples = sh.fast_samples.load(Ordering::Relaxed);
    report.fast_per_s = report.fast_samples as f64 / report.mix_s.max(1e-9);
    report.lost = sh.lost.load(Ordering::Relaxed) + solo.lost.load(Ordering::Relaxed);
    report.repeated = sh.repeated.load(Ordering::Relaxed) + solo.repeated.load(Ordering::Relaxed);
    report.slow_samples = sh.slow_samples.load(Ordering::Relaxed);
    report.stalled_streams = sh.stalled_streams.load(Ordering::Relaxed);
    report.cancelled_streams = sh.cancelled_streams.load(Ordering::Relaxed);
    report.uploads = sh.uploads.load(Ordering::Relaxed);
    report.unary_samples = sh.unary_samples.load(Ordering::Relaxed);
    report.unread_calls = sh.unread_calls.load(Ordering::Relaxed);
    report.idle_closed = sh.idle_closed.load(Ordering::Relaxed);
    report.watches = sh.watches.load(Ordering::Relaxed);
    report.window_streams = sh.window_streams.load(Ordering::Relaxed);
    if let Some(text) = match metrics {
        Some(m) => scrape(m).await,
        None => None,
    } {
        report.max_buffered_bytes = metric_value(&text, "mpiflow_buffered_peak_bytes").unwrap_or(0.0);
        report.budget_bytes = metric_value(&text, "mpiflow_buffered_budget_bytes").unwrap_or(0.0);
    }
    report.fast_max_gap_ms = sh.fast_max_gap_us.load(Ordering::Relaxed) as f64 / 1e3;
    // each stalled client opens a stream at least once; the others get something every round
    for (kind, clients, done) in [
        ("stalled", cfg.stalled, report.stalled_streams / cfg.stalled.max(1) as u64),
        ("slow", cfg.slow, report.slow_samples),
        ("cancelling", cfg.cancelling, report.cancelled_streams),
        ("uploading", cfg.uploading, report.uploads),
        ("batch-stall", cfg.batch_stall, 1),
        ("unary", cfg.unary, report.unary_samples),
        ("unread", cfg.unread, report.unread_calls),
        ("idle", cfg.idle, 1),
        ("watch", cfg.watch, report.watches),
        ("window", usize::from(cfg.window_streams > 0), report.window_streams),
    ] {
        if clients > 0 && done == 0 {
            report.idle_kinds.push(kind);
        }
    }
    for s in [solo, sh] {
        let e = s.errors.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        for (k, n) in &e.0 {
            *report.errors.entry(k.clone()).or_insert(0) += n;
        }
        report.unexpected += e.1;
        report.unexpected_examples.extend(e.2.iter().cloned());
    }
}
