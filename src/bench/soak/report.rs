//! What a soak run does (its configuration) and what it found (its report and summary).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

/// A soak run's failure to run at all (the server did not start, the runtime failed).
#[derive(Debug, thiserror::Error)]
#[error("soak: {0}")]
pub struct SoakError(pub String);

/// What a soak run does; see the documentation of `bench::soak`.
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
