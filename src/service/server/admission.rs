//! A call's place under its limits: `max_streams` (over all clients and half of it per client)
//! and `max_random_access_calls`, the slot given back with the call's stream or reply; a slot of
//! `max_streams` taken back from a stream that makes no progress when another client needs one;
//! a call's client, and the refusal of a call (counted and logged).

use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio_stream::Stream;
use tonic::{Request, Status};

use super::state::State;
use crate::service::error::{Reason, ServiceError};
use crate::service::pb;
use crate::service::peer::PeerKey;
use crate::service::pool::{Client, SampleStream};
use crate::service::reply::conn_of;

impl State {
    /// Counts a new call against its limit: `max_streams` for StreamSamples over all clients
    /// and half of it per peer (so one client, one connection included, cannot keep every other
    /// out), `max_random_access_calls` for the GetSample and GetSamples calls of one peer (undone
    /// when the returned slot is dropped, with the call's reply).
    pub(super) fn admit(self: &Arc<Self>, kind: CallKind, peer: PeerKey) -> Result<Admitted, ServiceError> {
        match kind {
            CallKind::Stream => {
                let limit = self.config.max_streams;
                let per_peer = streams_per_peer(limit);
                let mut of_peer = self.streams_per_peer.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                let n = of_peer.entry(peer).or_insert(0);
                if *n >= per_peer {
                    return Err(ServiceError::LimitExceeded(
                        Reason::TooManyStreams,
                        format!(
                            "too many streams from this client: {per_peer} are open, half of max_streams ({limit}); \
                         retry when one has ended"
                        ),
                    ));
                }
                if self.active_streams.fetch_add(1, Ordering::SeqCst) >= limit {
                    self.active_streams.fetch_sub(1, Ordering::SeqCst);
                    return Err(ServiceError::TooManyStreams { limit });
                }
                *n += 1;
            }
            CallKind::RandomAccess => {
                let limit = self.config.max_random_access_calls;
                let mut calls = self.random_access_calls.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                let n = calls.entry(peer).or_insert(0);
                if *n >= limit {
                    return Err(ServiceError::LimitExceeded(
                        Reason::TooManyCalls,
                        format!(
                            "too many GetSample/GetSamples calls: {limit} of this client are open \
                         (max_random_access_calls); retry when one has been answered"
                        ),
                    ));
                }
                *n += 1;
            }
        }
        Ok(Admitted { state: self.clone(), kind, peer })
    }

    /// Takes a slot of `max_streams` back for `newcomer`, refused one because every slot is
    /// taken. Within [`SLOT_WAIT`] (and once more at its end) it looks for a stream of another
    /// client whose message has waited in the transport for `pool::UNREAD_GRACE` while its
    /// connection took no DATA as long (`Scheduler::stalled_holder`: a zero window, a socket
    /// never read), checking again whenever a slot comes back and every [`CHECK_EVERY`]; that
    /// stream's connection is closed (its streams end with their slots) and the newcomer waits
    /// up to [`SLOT_WAIT`] more for a slot. Whether a slot came back.
    pub(super) async fn reclaim_stream_slot(&self, newcomer: PeerKey) -> bool {
        let limit = self.config.max_streams;
        let until = tokio::time::Instant::now() + SLOT_WAIT;
        loop {
            let notified = self.slot_freed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            if self.active_streams() < limit {
                return true;
            }
            let holder = {
                let slots = self.slot_streams.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                self.scheduler.stalled_holder(newcomer, |id| slots.contains(&id))
            };
            if let Some(holder) = holder {
                tracing::info!(
                    peer = %holder.peer(),
                    for_peer = %newcomer,
                    "connection closed: its stream makes no progress, and another client needs a stream slot"
                );
                self.metrics.holders_cut.inc();
                holder.cut();
                return self.slot_back(limit).await;
            }
            if tokio::time::Instant::now() >= until {
                return false;
            }
            let tick = (tokio::time::Instant::now() + CHECK_EVERY).min(until);
            tokio::select! {
                () = notified => {}
                () = tokio::time::sleep_until(tick) => {}
            }
        }
    }

    /// Waits up to [`SLOT_WAIT`] for fewer than `limit` streams to be open; whether they are.
    async fn slot_back(&self, limit: usize) -> bool {
        let freed = async {
            loop {
                let notified = self.slot_freed.notified();
                tokio::pin!(notified);
                notified.as_mut().enable();
                if self.active_streams() < limit {
                    return;
                }
                notified.await;
            }
        };
        tokio::time::timeout(SLOT_WAIT, freed).await.is_ok()
    }

    /// Gives a call's slot back.
    pub(super) fn release(&self, kind: CallKind, peer: PeerKey) {
        match kind {
            CallKind::Stream => {
                self.active_streams.fetch_sub(1, Ordering::SeqCst);
                self.slot_freed.notify_waiters();
                let mut of_peer = self.streams_per_peer.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                if let Some(n) = of_peer.get_mut(&peer) {
                    *n -= 1;
                    if *n == 0 {
                        of_peer.remove(&peer);
                    }
                }
            }
            CallKind::RandomAccess => {
                let mut calls = self.random_access_calls.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                if let Some(n) = calls.get_mut(&peer) {
                    *n -= 1;
                    if *n == 0 {
                        calls.remove(&peer);
                    }
                }
            }
        }
    }
}

/// How long a client refused a stream slot waits for a slot holder to have made no progress for
/// `pool::UNREAD_GRACE`, and then for the slot of the connection closed for it
/// ([`State::reclaim_stream_slot`]).
pub const SLOT_WAIT: Duration = Duration::from_secs(1);

/// How often a client waiting for a stream slot looks again for a holder that makes no progress.
const CHECK_EVERY: Duration = Duration::from_millis(100);

/// Which limit a call counts against.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum CallKind {
    /// StreamSamples: `max_streams`.
    Stream,
    /// GetSample and GetSamples: `max_random_access_calls`.
    RandomAccess,
}

/// A call's place under its limit, given back when dropped.
pub(super) struct Admitted {
    state: Arc<State>,
    kind: CallKind,
    peer: PeerKey,
}

impl Drop for Admitted {
    fn drop(&mut self) {
        self.state.release(self.kind, self.peer);
    }
}

/// A call's client: its key for the fairness and the per-client limits, and its connection.
pub(super) fn client_of<T>(request: &Request<T>) -> Client {
    Client { peer: PeerKey::of_addr(request.remote_addr()), conn: conn_of(request.extensions()).map(|c| c.activity) }
}

/// The StreamSamples calls one client may hold: half of `max_streams` (at least 1).
pub fn streams_per_peer(max_streams: usize) -> usize {
    (max_streams / 2).max(1)
}

/// A stream counted against its limit while it lives.
pub struct CountedStream {
    pub(super) inner: SampleStream,
    pub(super) _admitted: Admitted,
}

impl Stream for CountedStream {
    type Item = Result<pb::SampleBatch, Status>;
    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        Pin::new(&mut self.inner).poll_next(cx)
    }
}

impl Drop for CountedStream {
    fn drop(&mut self) {
        let state = &self._admitted.state;
        state.slot_streams.lock().unwrap_or_else(std::sync::PoisonError::into_inner).remove(&self.inner.id());
        state.metrics.active_streams.dec();
        if self._admitted.kind == CallKind::RandomAccess {
            tracing::debug!(stream = self.inner.id(), "samples closed");
        } else {
            tracing::info!(stream = self.inner.id(), "stream closed");
        }
    }
}

/// A call refused: counted by its code, logged, and answered with its status.
pub(super) fn refused<T>(state: &State, r: Result<T, ServiceError>) -> Result<T, Status> {
    r.map_err(|e| {
        state.metrics.count_refused(e.code());
        tracing::info!(error = %e, "request refused");
        e.into()
    })
}
