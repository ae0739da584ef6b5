//! `mpiflow bench soak`: a real `mpiflow serve` under a mix of fast, stalled, slow, cancelling
//! and uploading clients for M minutes ([`mpiflow::bench::soak`]); a non-zero exit code when a
//! fast client lost or repeated an index or an unexpected error came back.

use std::time::Duration;

use clap::Args;
use mpiflow::bench::soak::{run_soak, SoakConfig};

use super::CliError;

#[derive(Args, Debug)]
pub struct SoakBench {
    /// Minutes the mix of clients runs.
    #[arg(long, conflicts_with = "seconds")]
    minutes: Option<f64>,
    /// Seconds the mix of clients runs (for short runs; default 60).
    #[arg(long)]
    seconds: Option<f64>,
    /// Seconds one fast client runs alone first (the reference rate).
    #[arg(long, default_value_t = 10.0)]
    solo_s: f64,
    /// Source image size of the server.
    #[arg(long, value_name = "WxH", default_value = "320x240")]
    size: String,
    /// Generation threads of the server (default: all cores).
    #[arg(long)]
    workers: Option<usize>,
    #[arg(long, default_value_t = 4)]
    fast: usize,
    #[arg(long, default_value_t = 8)]
    stalled: usize,
    #[arg(long, default_value_t = 2)]
    slow: usize,
    #[arg(long, default_value_t = 2)]
    cancelling: usize,
    #[arg(long, default_value_t = 1)]
    uploading: usize,
    /// Clients making GetSample calls one after another (a flood when many).
    #[arg(long, default_value_t = 0)]
    unary: usize,
    /// Raw HTTP/2 clients keeping `--unread-calls` GetSample calls open, never reading them.
    #[arg(long, default_value_t = 0)]
    unread: usize,
    /// GetSample calls each unread client keeps open.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..=64))]
    unread_calls: u64,
    /// Raw HTTP/2 connections that answer pings and open no call.
    #[arg(long, default_value_t = 0)]
    idle: usize,
    /// Stalled clients with batch 64.
    #[arg(long, default_value_t = 0)]
    batch_stall: usize,
    /// Raw HTTP/2 connections each holding a health Watch open.
    #[arg(long, default_value_t = 0)]
    watch: usize,
    /// StreamSamples calls on one raw connection that grants no HTTP/2 window.
    #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u64).range(0..=1000))]
    window_streams: u64,
    /// Frames of the samples the hostile clients (unary, unread, batch-stall, window) ask for.
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u32).range(2..=8))]
    hostile_frames: u32,
    /// Loopback addresses the hostile clients spread over, round-robin: 127.0.0.2 and up.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=250))]
    attacker_addresses: u64,
    /// Seconds between readings of the server's memory.
    #[arg(long, default_value_t = 10.0)]
    report_every_s: f64,
    /// More `mpiflow serve` flags, after `--` (e.g. `-- --max-buffered-mb 512`).
    #[arg(last = true, value_name = "SERVE FLAGS")]
    server_args: Vec<String>,
}

fn seconds(what: &str, s: f64, max: f64) -> Result<Duration, CliError> {
    if !(s.is_finite() && s > 0.0 && s <= max) {
        return Err(CliError(format!("bench soak: {what} must be above 0 and at most {max}")));
    }
    Ok(Duration::from_secs_f64(s))
}

pub fn run(b: SoakBench) -> Result<(), CliError> {
    let duration = match (b.minutes, b.seconds) {
        (Some(m), _) => seconds("--minutes", m * 60.0, 7.0 * 24.0 * 3600.0)?,
        (None, s) => seconds("--seconds", s.unwrap_or(60.0), 7.0 * 24.0 * 3600.0)?,
    };
    let all = b.fast
        + b.stalled
        + b.slow
        + b.cancelling
        + b.uploading
        + b.unary
        + b.unread
        + b.idle
        + b.batch_stall
        + b.watch;
    if b.fast == 0 || all > 2000 {
        return Err(CliError("bench soak: at least 1 fast client and at most 2000 clients in all".into()));
    }
    let exe = std::env::current_exe().map_err(|e| CliError(format!("cannot find the mpiflow binary: {e}")))?;
    let cfg = SoakConfig {
        exe,
        duration,
        solo: seconds("--solo-s", b.solo_s, 3600.0)?,
        size: b.size,
        workers: b.workers.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, std::num::NonZero::get)),
        fast: b.fast,
        stalled: b.stalled,
        slow: b.slow,
        cancelling: b.cancelling,
        uploading: b.uploading,
        unary: b.unary,
        unread: b.unread,
        idle: b.idle,
        batch_stall: b.batch_stall,
        watch: b.watch,
        window_streams: b.window_streams as usize,
        unread_calls: b.unread_calls as usize,
        hostile_frames: b.hostile_frames,
        attacker_addresses: b.attacker_addresses as usize,
        report_every: seconds("--report-every-s", b.report_every_s, 3600.0)?,
        server_args: b.server_args,
    };
    println!(
        "soak: {:.0} s of {} fast, {} stalled, {} slow, {} cancelling, {} uploading, {} unary, {} unread, {} idle, {} \
         batch-stall, {} watch clients, {} window-withholding streams; hostile clients from {} addresses asking for \
         {}-frame samples; server --size {} --workers {} {}",
        duration.as_secs_f64(),
        cfg.fast,
        cfg.stalled,
        cfg.slow,
        cfg.cancelling,
        cfg.uploading,
        cfg.unary,
        cfg.unread,
        cfg.idle,
        cfg.batch_stall,
        cfg.watch,
        cfg.window_streams,
        cfg.attacker_addresses,
        cfg.hostile_frames,
        cfg.size,
        cfg.workers,
        cfg.server_args.join(" ")
    );
    let report = run_soak(&cfg, &mut |line: &str| println!("{line}"))?;
    for line in report.summary() {
        println!("{line}");
    }
    if report.passed() {
        Ok(())
    } else {
        Err(CliError(format!(
            "soak failed: {} indices lost, {} repeated, {} unexpected errors, {} fast samples",
            report.lost, report.repeated, report.unexpected, report.fast_samples
        )))
    }
}
