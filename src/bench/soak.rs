//! `mpiflow bench soak`: a real `mpiflow serve` (a child process on a free loopback port) under a
//! mix of fast, stalled, slow, cancelling and uploading clients for a given time; the server's
//! memory over time (`VmRSS` from `/proc/PID/status`, and `mpiflow_buffered_bytes` from its
//! `/metrics` where the server has it), the fast clients' samples/s against one client alone,
//! errors by client and gRPC code, and whether any fast client lost or repeated an index.
//!
//! # The clients (each bounded in count; all stop at the deadline)
//!
//! - **fast** `k` of `F`: one endless stream of rank `k`, world size `F`, read as fast as it
//!   comes; every index must be the next of its rank (`k, k + F, ...`); an interrupted stream is
//!   resumed from its cursor. Any error is unexpected.
//! - **stalled**: opens a stream with prefetch 64 and every field, reads one batch, then stops
//!   reading for a while (a third of the run, at most 30 s), drops it and starts again.
//! - **slow**: reads one batch every 250 ms.
//! - **cancelling**: opens a stream, reads 0 to 3 batches and drops it; every other time a
//!   GetSamples of three indices read once.
//! - **uploading**: uploads two small photos with depth to its own dataset, checks that both are
//!   accepted and pulls two samples of it; once a second.
//!
//! The hostile clients ([`super::hostile`]), each from an attacker address (127.0.0.2 and up,
//! round-robin over `attacker_addresses`), asking for `hostile_frames`-frame samples:
//! - **unary**: GetSample calls one after another, read whole (a flood when there are many).
//! - **unread**: a raw HTTP/2 connection with a one-byte window that keeps `unread_calls`
//!   GetSample calls of every field open and never reads them; reconnects when the server closes
//!   it.
//! - **idle**: a raw HTTP/2 connection that answers pings and opens no call; reconnects when the
//!   server closes it.
//! - **batch-stall**: like stalled, with batch 64.
//! - **watch**: a raw HTTP/2 connection holding a health Watch open.
//! - **window**: one raw connection granting no HTTP/2 window with `window_streams` StreamSamples
//!   calls of every field open.
//!
//! Every reading also times a newcomer: a new connection from 127.0.0.1 and a GetInfo call.
//!
//! RESOURCE_EXHAUSTED (a budget said no) is expected for all but the fast clients; every other
//! error is unexpected. [`SoakReport::passed`] is false on a lost or repeated index, an
//! unexpected error, or fast clients that got nothing.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::time::timeout_at;

use super::clients::{all_fields, Shared};
use super::hostile;
use crate::service::client::{connect, Client};
use crate::service::pb;

/// A soak run's failure to run at all (the server did not start, the runtime failed).
#[derive(Debug, thiserror::Error)]
#[error("soak: {0}")]
pub struct SoakError(pub String);

/// What a soak run does; see the module documentation.
#[derive(Clone, Debug)]
pub struct SoakConfig {
    /// The `mpiflow` binary to start as `mpiflow serve`.
    pub exe: PathBuf,
    /// How long the mix of clients runs.
    pub duration: Duration,
    /// How long the one fast client runs alone first (its rate is the reference).
    pub solo: Duration,
    /// `--size` of the server (e.g. `160x120`).
    pub size: String,
    /// `--workers` of the server.
    pub workers: usize,
    pub fast: usize,
    pub stalled: usize,
    pub slow: usize,
    pub cancelling: usize,
    pub uploading: usize,
    pub unary: usize,
    pub unread: usize,
    pub idle: usize,
    pub batch_stall: usize,
    /// Raw connections each holding a health Watch open.
    pub watch: usize,
    /// StreamSamples calls on one connection that grants no HTTP/2 window.
    pub window_streams: usize,
    /// GetSample calls each unread client keeps open.
    pub unread_calls: usize,
    /// Frames of the samples the unary, unread, batch-stall and window clients ask for (2 = pairs).
    pub hostile_frames: u32,
    /// Loopback addresses the hostile clients spread over (127.0.0.2 and up, round-robin).
    pub attacker_addresses: usize,
    /// How often the server's memory is read and printed.
    pub report_every: Duration,
    /// More `mpiflow serve` flags (e.g. `--max-buffered-mb 512`).
    pub server_args: Vec<String>,
}

/// One reading of the server during the mix.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SoakPoint {
    /// Seconds since the mix started.
    pub t_s: f64,
    pub rss_mib: f64,
    /// `mpiflow_buffered_bytes` from `/metrics`, when the server reports it.
    pub buffered_bytes: Option<f64>,
    /// Fast clients' samples/s since the previous reading.
    pub fast_per_s: f64,
}

/// What a soak run measured.
#[derive(Clone, Debug, Default)]
pub struct SoakReport {
    /// One fast client alone, samples/s.
    pub solo_per_s: f64,
    /// All fast clients together during the mix, samples/s.
    pub fast_per_s: f64,
    pub fast_samples: u64,
    /// Indices a fast client never got (a gap in its rank's sequence).
    pub lost: u64,
    /// Indices a fast client got twice or out of order.
    pub repeated: u64,
    /// Server RSS after warm-up, before any client of the mix.
    pub idle_rss_mib: f64,
    pub peak_rss_mib: f64,
    /// Server RSS after every client left.
    pub end_rss_mib: f64,
    pub points: Vec<SoakPoint>,
    /// Errors seen, by `client kind: CODE`.
    pub errors: BTreeMap<String, u64>,
    /// How many of them were unexpected, and the first few with their messages.
    pub unexpected: u64,
    pub unexpected_examples: Vec<String>,
    pub slow_samples: u64,
    pub stalled_streams: u64,
    pub cancelled_streams: u64,
    pub uploads: u64,
    /// GetSample calls answered to unary clients; calls left unread; idle connections the server
    /// closed.
    pub unary_samples: u64,
    pub unread_calls: u64,
    pub idle_closed: u64,
    /// Health watches opened; window-withholding streams opened.
    pub watches: u64,
    pub window_streams: u64,
    /// The most `mpiflow_buffered_bytes` read during the mix, and the budget.
    pub max_buffered_bytes: f64,
    pub budget_bytes: f64,
    /// The fast clients' longest wait for a message during the mix, ms.
    pub fast_max_gap_ms: f64,
    /// The longest a newcomer waited for its first answer (connect + GetInfo), ms; and how many
    /// newcomers were turned away.
    pub newcomer_max_ms: f64,
    pub newcomers_refused: u64,
    /// The mix's length as it ran, seconds.
    pub mix_s: f64,
    /// Kinds of client that were in the mix and got nothing done (a starved client).
    pub idle_kinds: Vec<&'static str>,
}

impl SoakReport {
    /// No index lost or repeated, no unexpected error, the fast clients got samples and every
    /// other kind of client in the mix got something done.
    pub fn passed(&self) -> bool {
        self.lost == 0
            && self.repeated == 0
            && self.unexpected == 0
            && self.fast_samples > 0
            && self.idle_kinds.is_empty()
    }

    /// The closing summary, one fact a line.
    pub fn summary(&self) -> Vec<String> {
        let ratio = if self.solo_per_s > 0.0 { 100.0 * self.fast_per_s / self.solo_per_s } else { 0.0 };
        let errors = if self.errors.is_empty() {
            "none".to_string()
        } else {
            self.errors.iter().map(|(k, n)| format!("{k} x{n}")).collect::<Vec<_>>().join(", ")
        };
        let mut out = vec![
            format!(
                "fast clients: {:.2} samples/s together over {:.0} s ({} samples) = {ratio:.0}% of one client alone ({:.2} samples/s)",
                self.fast_per_s, self.mix_s, self.fast_samples, self.solo_per_s
            ),
            format!("fast-client indices: {} lost, {} repeated", self.lost, self.repeated),
            format!(
                "server RSS: {:.0} MiB idle, peak {:.0} MiB, {:.0} MiB after the clients left",
                self.idle_rss_mib, self.peak_rss_mib, self.end_rss_mib
            ),
            format!(
                "other clients: {} stalled streams, {} slow samples, {} cancelled streams, {} uploads, {} unary samples, \
                 {} unread calls, {} health watches, {} window-withholding streams, {} idle or watching connections \
                 closed by the server",
                self.stalled_streams,
                self.slow_samples,
                self.cancelled_streams,
                self.uploads,
                self.unary_samples,
                self.unread_calls,
                self.watches,
                self.window_streams,
                self.idle_closed
            ),
            format!(
                "buffered: at most {:.1} MB of a {:.1} MB budget",
                self.max_buffered_bytes / 1e6,
                self.budget_bytes / 1e6
            ),
            format!(
                "fast clients' longest wait for a message: {:.0} ms; newcomers: longest wait {:.0} ms, {} turned away",
                self.fast_max_gap_ms, self.newcomer_max_ms, self.newcomers_refused
            ),
            format!("errors by code: {errors}; unexpected: {}", self.unexpected),
        ];
        if !self.idle_kinds.is_empty() {
            out.push(format!("clients that got nothing done: {}", self.idle_kinds.join(", ")));
        }
        out.extend(self.unexpected_examples.iter().map(|e| format!("  unexpected: {e}")));
        out.push(if self.passed() { "soak: PASS".into() } else { "soak: FAIL".into() });
        out
    }
}

/// The resident memory (`VmRSS`) of a process in MiB.
pub fn rss_mib(pid: u32) -> Option<f64> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = s.lines().find(|l| l.starts_with("VmRSS:"))?;
    Some(line.split_whitespace().nth(1)?.parse::<f64>().ok()? / 1024.0)
}

/// CPU seconds (user + system, all threads) process `pid` has used so far, from
/// `/proc/PID/stat` (Linux; its unit, `USER_HZ`, is 100 per second in the kernel's ABI). None
/// where there is no `/proc`.
pub fn cpu_s(pid: u32) -> Option<f64> {
    stat_cpu_s(&std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?)
}

/// [`cpu_s`] of one `/proc/PID/stat` line.
fn stat_cpu_s(s: &str) -> Option<f64> {
    // the fields after the command name, which is in parentheses and may hold spaces
    let rest = &s[s.rfind(')')? + 1..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the line, 12 and 13 after the name
    let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0)
}

/// A `mpiflow serve` child process on loopback; SIGTERM and wait on drop.
pub struct ServerProcess {
    child: Child,
    /// `HOST:PORT` of the gRPC listener.
    pub addr: String,
    /// `HOST:PORT` of `/metrics`, when the server printed one.
    pub metrics_addr: Option<String>,
}

impl ServerProcess {
    /// Starts `exe serve ARGS` and reads the addresses it prints (`mpiflow serving on ...`, then
    /// `mpiflow metrics on http://.../metrics` when `--metrics-addr` is among the arguments).
    pub fn start(exe: &std::path::Path, args: &[String]) -> Result<Self, SoakError> {
        let mut child = Command::new(exe)
            .arg("serve")
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(|e| SoakError(format!("cannot start {} serve: {e}", exe.display())))?;
        let stdout = child.stdout.take().ok_or_else(|| SoakError("no stdout from mpiflow serve".into()))?;
        let mut lines = BufReader::new(stdout).lines();
        let mut next = || lines.next().and_then(Result::ok).unwrap_or_default();
        let first = next();
        let Some(addr) = first.trim().strip_prefix("mpiflow serving on ").map(str::to_string) else {
            let _ = child.kill();
            let _ = child.wait();
            return Err(SoakError(format!("mpiflow serve printed {:?}", crate::failure::printable(&first, 200))));
        };
        let metrics_addr = if args.iter().any(|a| a == "--metrics-addr") {
            let m = next();
            m.trim()
                .strip_prefix("mpiflow metrics on http://")
                .and_then(|m| m.strip_suffix("/metrics"))
                .map(str::to_string)
        } else {
            None
        };
        // keep reading the server's stdout to its end: a closed pipe would fail its later writes
        std::thread::spawn(move || lines.for_each(drop));
        Ok(Self { child, addr, metrics_addr })
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// SIGTERM (a graceful drain), then waits up to `grace`; the exit status (`None` when it had
    /// to be killed).
    pub fn terminate(mut self, grace: Duration) -> Option<std::process::ExitStatus> {
        let _ = Command::new("kill").arg("-TERM").arg(self.child.id().to_string()).status();
        let end = Instant::now() + grace;
        while Instant::now() < end {
            match self.child.try_wait() {
                Ok(Some(status)) => return Some(status),
                Ok(None) => std::thread::sleep(Duration::from_millis(50)),
                Err(_) => break,
            }
        }
        None // Drop kills it
    }
}

impl Drop for ServerProcess {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// The sum of a metric's samples in a Prometheus text exposition (`None` when absent).
pub fn metric_value(text: &str, name: &str) -> Option<f64> {
    let mut found = None;
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let Some(rest) = line.strip_prefix(name) else { continue };
        if !(rest.starts_with(' ') || rest.starts_with('{')) {
            continue;
        }
        if let Some(v) = rest.rsplit(' ').next().and_then(|v| v.parse::<f64>().ok()) {
            *found.get_or_insert(0.0) += v;
        }
    }
    found
}

/// `GET /metrics` over plain HTTP/1.0.
pub async fn scrape(addr: &str) -> Option<String> {
    let mut s = tokio::net::TcpStream::connect(addr).await.ok()?;
    s.write_all(format!("GET /metrics HTTP/1.0\r\nHost: {addr}\r\n\r\n").as_bytes()).await.ok()?;
    let mut body = Vec::new();
    s.read_to_end(&mut body).await.ok()?;
    Some(String::from_utf8_lossy(&body).into_owned())
}

/// Every field there is (`pb::Field` values but `FIELD_UNSPECIFIED`).
/// A fast client: rank `rank` of `world`, read as fast as it comes until `until`; checks that
/// every index is the next of its rank, resumes an interrupted stream from its cursor.
async fn fast_client(addr: String, seed: u64, rank: u32, world: u32, until: tokio::time::Instant, sh: Arc<Shared>) {
    let mut client = match timeout_at(until, connect(&addr)).await {
        Ok(Ok(c)) => c,
        Ok(Err(e)) => return sh.error("fast", "connect", &e.to_string(), false),
        Err(_) => return,
    };
    let step = u64::from(world);
    let mut expected = u64::from(rank);
    let mut start = 0u64;
    while tokio::time::Instant::now() < until {
        let req = pb::StreamRequest {
            rank,
            world_size: world,
            start_index: start,
            ..pb::SampleSpec { seed, ..Default::default() }.stream()
        };
        let mut stream = match timeout_at(until, client.stream_samples(req)).await {
            Ok(Ok(s)) => s.into_inner(),
            Ok(Err(s)) => {
                sh.status("fast", &s, true);
                continue;
            }
            Err(_) => return,
        };
        // a timeout polls its future first: a stream that is always ready never times out
        let mut last = tokio::time::Instant::now();
        while tokio::time::Instant::now() < until {
            match timeout_at(until, stream.message()).await {
                Err(_) => return,
                Ok(Ok(Some(batch))) => {
                    let now = tokio::time::Instant::now();
                    sh.fast_max_gap_us.fetch_max((now - last).as_micros() as u64, Ordering::Relaxed);
                    last = now;
                    for s in &batch.samples {
                        if s.index == expected {
                            expected += step;
                        } else if s.index < expected {
                            sh.repeated.fetch_add(1, Ordering::Relaxed);
                        } else {
                            let gap = (s.index - expected) / step;
                            sh.lost.fetch_add(gap.max(1), Ordering::Relaxed);
                            expected = s.index + step;
                        }
                        sh.fast_samples.fetch_add(1, Ordering::Relaxed);
                    }
                    start = batch.resume_start_index;
                }
                Ok(Ok(None)) => {
                    sh.error("fast", "stream ended", "an endless stream ended", false);
                    break;
                }
                Ok(Err(s)) => {
                    sh.status("fast", &s, true);
                    if let Some((_, resume)) = crate::service::error::cursor_of(&s) {
                        start = resume;
                    }
                    break;
                }
            }
        }
    }
}

async fn connected(kind: &str, addr: &str, until: tokio::time::Instant, sh: &Shared) -> Option<Client> {
    match timeout_at(until, connect(addr)).await {
        Ok(Ok(c)) => Some(c),
        Ok(Err(e)) => {
            sh.error(kind, "connect", &e.to_string(), false);
            None
        }
        Err(_) => None,
    }
}

/// Opens a stream with prefetch 64, every field and `batch` samples per message, reads one
/// batch, stops reading for `hold`.
#[allow(clippy::too_many_arguments)] // the client's shape: its stream, its pause, its address
async fn stalled_client(
    addr: String,
    seed: u64,
    batch: u32,
    frames: u32,
    hold: Duration,
    from: Option<std::net::IpAddr>,
    until: tokio::time::Instant,
    sh: Arc<Shared>,
) {
    let Some(mut client) = sh.connect("stalled", &addr, from, until).await else { return };
    let mut round = 0u64;
    while tokio::time::Instant::now() < until {
        let req = pb::StreamRequest {
            prefetch: 64,
            batch_size: batch,
            ..pb::SampleSpec { seed: seed + round, fields: all_fields(), frames, ..Default::default() }.stream()
        };
        round += 1;
        match timeout_at(until, client.stream_samples(req)).await {
            Ok(Ok(s)) => {
                let mut s = s.into_inner();
                sh.stalled_streams.fetch_add(1, Ordering::Relaxed);
                match timeout_at(until, s.message()).await {
                    Ok(Err(status)) => sh.status("stalled", &status, false),
                    Ok(Ok(_)) => {
                        // stop reading: the server holds what it made for this stream
                        let wake = (tokio::time::Instant::now() + hold).min(until);
                        tokio::time::sleep_until(wake).await;
                    }
                    Err(_) => return,
                }
            }
            Ok(Err(status)) => {
                sh.status("stalled", &status, false);
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(_) => return,
        }
    }
}

/// A newcomer: a new connection and a GetInfo call; its wait in ms, or None when turned away.
async fn newcomer(addr: &str) -> Option<f64> {
    let t = Instant::now();
    let mut c = tokio::time::timeout(Duration::from_secs(60), connect(addr)).await.ok()?.ok()?;
    tokio::time::timeout(Duration::from_secs(60), c.get_info(pb::InfoRequest {})).await.ok()?.ok()?;
    Some(t.elapsed().as_secs_f64() * 1e3)
}

/// Reads one batch every 250 ms.
async fn slow_client(addr: String, seed: u64, until: tokio::time::Instant, sh: Arc<Shared>) {
    let Some(mut client) = connected("slow", &addr, until, &sh).await else { return };
    while tokio::time::Instant::now() < until {
        let req = pb::SampleSpec { seed, ..Default::default() }.stream();
        let mut s = match timeout_at(until, client.stream_samples(req)).await {
            Ok(Ok(s)) => s.into_inner(),
            Ok(Err(status)) => {
                sh.status("slow", &status, false);
                tokio::time::sleep(Duration::from_millis(200)).await;
                continue;
            }
            Err(_) => return,
        };
        while tokio::time::Instant::now() < until {
            match timeout_at(until, s.message()).await {
                Ok(Ok(Some(b))) => {
                    sh.slow_samples.fetch_add(b.samples.len() as u64, Ordering::Relaxed);
                }
                Ok(Ok(None)) => break,
                Ok(Err(status)) => {
                    sh.status("slow", &status, false);
                    break;
                }
                Err(_) => return,
            }
            // the client's pace, not a wait for the server
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    }
}

/// Opens streams and drops them after 0 to 3 batches; every other time a GetSamples read once.
async fn cancelling_client(addr: String, seed: u64, until: tokio::time::Instant, sh: Arc<Shared>) {
    let Some(mut client) = connected("cancelling", &addr, until, &sh).await else { return };
    let mut round = 0u64;
    while tokio::time::Instant::now() < until {
        round += 1;
        let reads = round % 4;
        let opened = if round.is_multiple_of(2) {
            let req = pb::SampleSpec { seed, ..Default::default() }.samples(vec![round, round + 7, round * 3]);
            match timeout_at(until, client.get_samples(req)).await {
                Ok(Ok(s)) => {
                    let mut s = s.into_inner();
                    if let Ok(Err(status)) = timeout_at(until, s.message()).await {
                        sh.status("cancelling", &status, false);
                    }
                    Ok(())
                }
                Ok(Err(status)) => Err(status),
                Err(_) => return,
            }
        } else {
            let req = pb::StreamRequest {
                start_index: round * 100,
                ..pb::SampleSpec { seed, ..Default::default() }.stream()
            };
            match timeout_at(until, client.stream_samples(req)).await {
                Ok(Ok(s)) => {
                    let mut s = s.into_inner();
                    for _ in 0..reads {
                        match timeout_at(until, s.message()).await {
                            Ok(Ok(Some(_))) => {}
                            Ok(Ok(None)) => break,
                            Ok(Err(status)) => {
                                sh.status("cancelling", &status, false);
                                break;
                            }
                            Err(_) => return,
                        }
                    }
                    Ok(())
                }
                Ok(Err(status)) => Err(status),
                Err(_) => return,
            }
        };
        match opened {
            Ok(()) => {
                sh.cancelled_streams.fetch_add(1, Ordering::Relaxed);
            }
            Err(status) => {
                sh.status("cancelling", &status, false);
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    }
}

/// The chunks of an upload of two small photos with depth (`.npy`) to `dataset`.
fn upload_chunks(dataset: &str, round: u64) -> Vec<pb::SourceChunk> {
    let (w, h) = (80u32, 60u32);
    let mut chunks = Vec::new();
    for k in 0..2u32 {
        let r = (round % 200) as u32;
        let img = ::image::RgbImage::from_fn(w, h, |x, y| {
            ::image::Rgb([(x * 3 + r) as u8, (y * 4 + k * 60) as u8, ((x ^ y) + r) as u8])
        });
        let mut png = std::io::Cursor::new(Vec::new());
        if img.write_to(&mut png, ::image::ImageFormat::Png).is_err() {
            continue;
        }
        let depth: Vec<f32> = (0..w * h).map(|i| 2.0 + (i % w) as f32 / w as f32).collect();
        let mut npy = Vec::new();
        if crate::io::npy::write_f32_to(&mut npy, &[u64::from(h), u64::from(w)], &depth).is_err() {
            continue;
        }
        let name = format!("photo{k}");
        let png = png.into_inner();
        // the image in two chunks, as a client streaming a file does
        let half = png.len() / 2;
        chunks.push(pb::SourceChunk {
            dataset: dataset.into(),
            name: name.clone(),
            kind: "image".into(),
            data: png[..half].to_vec(),
        });
        chunks.push(pb::SourceChunk { data: png[half..].to_vec(), ..Default::default() });
        chunks.push(pb::SourceChunk { name, kind: "depth".into(), data: npy, ..Default::default() });
    }
    chunks
}

/// Uploads two photos with depth to its dataset once a second, checks both are accepted, pulls
/// two samples of it.
async fn uploading_client(addr: String, k: usize, until: tokio::time::Instant, sh: Arc<Shared>) {
    let Some(mut client) = connected("uploading", &addr, until, &sh).await else { return };
    let dataset = format!("soak-upload-{k}");
    let mut round = 0u64;
    while tokio::time::Instant::now() < until {
        round += 1;
        let chunks = upload_chunks(&dataset, round);
        match timeout_at(until, client.upload_sources(tokio_stream::iter(chunks))).await {
            Ok(Ok(r)) => {
                let sum = r.into_inner();
                if sum.accepted != 4 || !sum.rejected.is_empty() {
                    let m = format!("accepted {} of 4, rejected {:?}", sum.accepted, sum.rejected);
                    sh.error("uploading", "not accepted", &m, false);
                } else {
                    sh.uploads.fetch_add(1, Ordering::Relaxed);
                    let req = pb::StreamRequest {
                        count: 2,
                        ..pb::SampleSpec { dataset: dataset.clone(), seed: round, ..Default::default() }.stream()
                    };
                    match timeout_at(until, crate::service::client::pull(&mut client, req, |_| {})).await {
                        Ok(Ok(p)) => {
                            if let Some(s) = p.error {
                                sh.status("uploading", &s, false);
                            } else if p.samples != 2 {
                                sh.error("uploading", "short pull", &format!("{} of 2 samples", p.samples), false);
                            }
                        }
                        Ok(Err(s)) => sh.status("uploading", &s, false),
                        Err(_) => return,
                    }
                }
            }
            Ok(Err(status)) => sh.status("uploading", &status, false),
            Err(_) => return,
        }
        // the client's pace: one upload a second
        tokio::time::sleep_until((tokio::time::Instant::now() + Duration::from_secs(1)).min(until)).await;
    }
}

/// Runs a soak (see the module documentation), printing progress lines through `log`.
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

async fn mix(
    cfg: &SoakConfig,
    addr: &str,
    pid: u32,
    metrics: Option<&str>,
    log: &mut dyn FnMut(&str),
) -> Result<SoakReport, SoakError> {
    let mut report = SoakReport::default();
    // warm the scene cache
    let mut client = connect(addr).await.map_err(|e| SoakError(format!("{addr}: {e}")))?;
    let warm = pb::StreamRequest { count: 8, ..pb::SampleSpec { seed: 1, ..Default::default() }.stream() };
    let w = crate::service::client::pull(&mut client, warm, |_| {}).await.map_err(|s| SoakError(s.to_string()))?;
    if let Some(e) = w.error {
        return Err(SoakError(format!("warm-up pull: {e}")));
    }
    drop(client);
    report.idle_rss_mib = rss_mib(pid).unwrap_or(0.0);

    // one fast client alone
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

    // the mix
    let sh = Arc::new(Shared::default());
    let start = tokio::time::Instant::now();
    let until = start + cfg.duration;
    let hold = (cfg.duration / 3).min(Duration::from_secs(30));
    let tasks = spawn_clients(cfg, addr, until, hold, &sh);
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
    report.mix_s = (tokio::time::Instant::now() - start).as_secs_f64();
    // every client stops at the deadline; one that has not within 15 s more is a finding
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
    log("clients stopped");
    // the server's memory once every client has left (the streams are dropped)
    let mut end = rss_mib(pid).unwrap_or(0.0);
    for _ in 0..10 {
        tokio::time::sleep(Duration::from_millis(300)).await;
        end = rss_mib(pid).unwrap_or(end);
    }
    report.end_rss_mib = end;
    report.peak_rss_mib = peak;
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
    for s in [&solo, &sh] {
        let e = s.errors.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        for (k, n) in &e.0 {
            *report.errors.entry(k.clone()).or_insert(0) += n;
        }
        report.unexpected += e.1;
        report.unexpected_examples.extend(e.2.iter().cloned());
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_kind_of_client_that_got_nothing_done_fails_the_soak() {
        let mut r = SoakReport { fast_samples: 10, ..SoakReport::default() };
        assert!(r.passed());
        r.idle_kinds.push("slow");
        assert!(!r.passed());
        assert!(r.summary().iter().any(|l| l == "clients that got nothing done: slow"), "{:?}", r.summary());
        assert_eq!(r.summary().last().map(String::as_str), Some("soak: FAIL"));
    }

    #[test]
    fn cpu_time_is_user_plus_system_after_a_command_name_with_spaces_and_parentheses() {
        // pid (comm) state ppid pgrp session tty tpgid flags minflt cminflt majflt cmajflt utime stime ...
        let line = "4242 (mpi (flow) x) S 1 4242 4242 0 -1 4194560 100 0 0 0 250 75 0 0 20 0 3 0";
        assert_eq!(stat_cpu_s(line), Some(3.25));
        assert_eq!(stat_cpu_s("4242 (truncated) S 1 2"), None);
        let me = cpu_s(std::process::id()).expect("this process's /proc/PID/stat");
        assert!(me >= 0.0 && me.is_finite());
    }

    #[test]
    fn metric_values_are_summed_over_labels_and_absent_ones_are_none() {
        let text = "# HELP mpiflow_buffered_bytes x\n# TYPE mpiflow_buffered_bytes gauge\n\
                    mpiflow_buffered_bytes 1024\nmpiflow_buffered_bytes_limit 5\n\
                    mpiflow_streams{dataset=\"a\"} 2\nmpiflow_streams{dataset=\"b\"} 3\n";
        assert_eq!(metric_value(text, "mpiflow_buffered_bytes"), Some(1024.0));
        assert_eq!(metric_value(text, "mpiflow_streams"), Some(5.0));
        assert_eq!(metric_value(text, "mpiflow_missing"), None);
    }
}
