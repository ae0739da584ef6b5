//! One stream's state and the rules of its next job: what it holds of the budget, what a job
//! reserves and costs, and when it may start one.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::Waker;
use std::time::Instant;

use super::meter::Rate;
use super::{lock, Item, Produce, StreamSpec};
use crate::service::conn::Activity;
use crate::service::peer::PeerKey;

pub(super) struct StreamState {
    /// Positions dispatched so far (the next job's k).
    pub(super) dispatched: u64,
    /// Bytes this stream holds against the budget (queued samples, the message in transport and
    /// the estimates of running jobs).
    pub(super) held: u64,
    /// The encoded size of the stream's latest sample (the estimate of the next); 0 = not known.
    pub(super) estimate: u64,
    /// The worker time of the stream's latest sample, nanoseconds (the cost of the next on the
    /// dispatch's virtual clock); 0 = not known.
    pub(super) work: u64,
    /// Bytes of the last message handed to the transport, held until the next poll.
    pub(super) in_transport: u64,
    /// When that message was handed over.
    pub(super) in_transport_since: Instant,
    /// Samples were dropped to bring the stream back to its share: it makes no more ahead until
    /// it sends a message (a stalled stream stays small instead of refilling and dropping again
    /// every time another stream comes and goes).
    pub(super) trimmed: bool,
    /// Positions handed to the transport so far.
    pub(super) delivered: u64,
    /// Jobs running now.
    pub(super) running: usize,
    pub(super) ready: BTreeMap<u64, Item>,
    /// Samples made for this stream (for tests and logs).
    pub(super) produced: u64,
    pub(super) waker: Option<Waker>,
    /// The consumer is gone or the stream ended.
    pub(super) closed: bool,
    pub(super) draining: bool,
}

/// The bytes held by all streams of one peer (client address), shared by them.
#[derive(Debug, Default)]
pub(super) struct PeerGroup {
    pub(super) held: AtomicU64,
    /// The peer's share of the budget (budget / peers with open streams).
    pub(super) share: AtomicU64,
    /// The cost of the jobs started for the peer, on the dispatch's virtual clock of worker
    /// nanoseconds (`Scheduler::next_eligible`): charged at dispatch by the estimate
    /// ([`StreamShared::cost`]), set right by what the job took once it is done.
    pub(super) used: AtomicU64,
    /// The worker time the peer's samples took, nanoseconds, and how many were made (for the
    /// stats: `SchedulerStats::per_peer`).
    pub(super) work_ns: AtomicU64,
    pub(super) made: AtomicU64,
    /// The peer has taken a message it was sent (see `Scheduler::reading`).
    pub(super) took: std::sync::atomic::AtomicBool,
}

/// One stream's shared state.
pub struct StreamShared {
    pub id: u64,
    pub spec: StreamSpec,
    /// The client's key: the fairness and the shares go by peer.
    pub(super) peer: PeerKey,
    /// The client's connection.
    pub(super) conn: Option<Arc<Activity>>,
    pub(super) group: Arc<PeerGroup>,
    /// This stream's share of the budget: its peer's share / the peer's open streams.
    pub(super) share: AtomicU64,
    /// An explicit index list (position k = `indices[k]`) instead of the spec's sequence.
    pub(super) indices: Option<Arc<[u64]>>,
    pub(super) len: u64,
    pub(super) produce: Produce,
    pub(super) state: Mutex<StreamState>,
}

impl StreamShared {
    /// The index of position `k` (`k < len`).
    pub(super) fn index(&self, k: u64) -> u64 {
        match &self.indices {
            Some(list) => list[k as usize],
            None => self.spec.index(k).unwrap_or(u64::MAX),
        }
    }

    /// The cursor after `k` positions: the spec's for a sequence; for an index list the
    /// position itself (as `(k, k)`), which has no meaning as a start_index.
    pub(super) fn cursor(&self, k: u64) -> (u64, u64) {
        if self.indices.is_some() {
            (k, k)
        } else {
            self.spec.cursor(k)
        }
    }

    /// What a job of the stream reserves in the budget while it runs: the job's bound until a
    /// sample's size is known, then that size and an eighth (never over the bound).
    pub(super) fn reserve(&self, s: &StreamState) -> u64 {
        // the small fields vary with the sample's objects and its record: an eighth covers them
        let known = s.estimate.saturating_add(s.estimate / 8);
        match (self.produce.bound, known) {
            (0, k) => k,
            (b, 0) => b,
            (b, k) => k.min(b),
        }
    }

    /// What a job of the stream costs the peer on the dispatch's virtual clock: the worker time
    /// of its sample, nanoseconds: what the stream's latest sample took, else the request's work
    /// units at the rate the samples made so far have set (`meter::Rate`).
    pub(super) fn cost(&self, s: &StreamState, rate: Rate) -> u64 {
        if s.work > 0 {
            s.work
        } else {
            rate.ns(self.produce.work)
        }
    }

    /// Whether the stream may start a job now, with `room` what the budget has left over all
    /// streams and `spare` what a job beyond its share may take of it (all of `room` for the
    /// client first in line, less a budget / `HEADROOM_DIVISOR` for the others: `Scheduler::spare`).
    pub(super) fn eligible(&self, s: &StreamState, room: u64, spare: u64) -> bool {
        if s.closed
            || s.draining
            || s.dispatched >= self.len
            || (s.dispatched - s.delivered) >= self.spec.prefetch as u64
        {
            return false;
        }
        let reserve = self.reserve(s);
        // what the job takes of the budget's room: its reservation and its sample's workspace
        // (the shares count only the reservation: they divide what clients are sent)
        let need = reserve.saturating_add(self.produce.workspace);
        let (share, peer_share) = (self.share.load(Ordering::Acquire), self.group.share.load(Ordering::Acquire));
        let peer_held = self.group.held.load(Ordering::Acquire);
        let holds_nothing = s.held == 0 && s.running == 0;
        // within its share a stream may start a job while the budget has room for it; the first
        // job once its size is known (a batch is filled within the share too: a stream at its
        // share sends the batch it has, cut short, see `SampleStream::poll_next`)
        let fits_share = if holds_nothing {
            peer_held.saturating_add(reserve) <= peer_share
        } else {
            !s.trimmed && s.estimate > 0 && s.held.saturating_add(reserve) <= share
        };
        if fits_share {
            return need <= room;
        }
        // beyond its share a stream may go on while the budget has spare room: the shares decide
        // who gets the room back when a client waits for it (`Scheduler::reclaim`), not who
        // idles; a stream holding nothing may start one job while its peer holds less than its
        // share (so a new client gets going even when its share is smaller than one sample)
        let may_exceed = if holds_nothing { peer_held < peer_share } else { !s.trimmed && s.estimate > 0 };
        may_exceed && need <= spare
    }

    /// (dispatched, delivered, produced, queued) for tests and diagnostics.
    pub fn counts(&self) -> (u64, u64, u64, usize) {
        let s = lock(&self.state);
        (s.dispatched, s.delivered, s.produced, s.ready.len())
    }
}
