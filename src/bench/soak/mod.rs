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
//!
//! Rooms: `report` (the configuration and the report), `process` (the server's process and what
//! is read from it), `clients` (the soak's own clients), `run` (the run: the server, the mix, the
//! readings, the tally).

mod clients;
mod process;
mod report;
mod run;
#[cfg(test)]
mod tests;

pub use process::{cpu_s, metric_value, rss_mib, scrape, ServerProcess};
pub use report::{SoakConfig, SoakError, SoakPoint, SoakReport};
pub use run::run_soak;
