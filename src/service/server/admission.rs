//! A call's place under its limits: `max_streams` (over all clients and half of it per client)
//! and `max_random_access_calls`, the slot given back with the call's stream or reply; a call's
//! client, and the refusal of a call (counted and logged).

use std::pin::Pin;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::task::{Context, Poll};

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

    /// Gives a call's slot back.
    pub(super) fn release(&self, kind: CallKind, peer: PeerKey) {
        match kind {
            CallKind::Stream => {
                self.active_streams.fetch_sub(1, Ordering::SeqCst);
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
        self._admitted.state.metrics.active_streams.dec();
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
