//! Connection hygiene of the listeners: at most `max_connections` connections open at once and
//! `max_connections_per_peer` from one address (more are closed as they arrive); a connection
//! must send its first bytes within `idle_connection_timeout_s`, and is closed once no call has
//! been open on it for as long (HTTP/2 pings answered or not: calls are counted by the server's
//! layer, `service::reply`, through the connection's [`Activity`]); a connection whose peer has
//! taken no data for `stall_timeout_s` while the server had bytes for it is closed
//! ([`super::stall`]), which ends its streams and frees their slots (each batch carries its
//! resume cursor). All of it holds on the plaintext and the TLS port alike (the TLS handshake
//! runs over these connections). HTTP/2 keepalive pings (`Server::http2_keepalive_*`) close
//! connections whose peer stops answering, and TCP keepalive (probes after
//! `idle_connection_timeout_s` of silence, every such interval, 3 tries) lets the kernel drop
//! connections whose peer vanished without a FIN (the cable, the node). A failed accept backs
//! off when the process is out of descriptors or memory ([`AcceptErrors`]).
//!
//! Peers are keyed by [`PeerKey`] (an IPv6 client by its /64). When all `max_connections` are
//! taken, a new connection closes one that has no call open whose request has arrived, but
//! health watches (one that has not sent its first bytes, is idle, only watches health, or whose
//! calls' requests never finish), from the peer with the most connections, the oldest first
//! ([`Registry::evict`]); a connection with a call whose request has arrived is never closed for
//! a newcomer. So connections that never authenticate, idle ones and health watches,
//! from any number of addresses, cannot keep a client out. The worker pool may also close a
//! connection ([`Activity::cut`]) that holds made samples it has not taken for a while when
//! another client needs the room (`service::pool`). What the peer took counts only as DATA on a
//! connection in the clear (`service::progress`: a PING ACK is not data taken). A peer may have at
//! most `max_calls_per_connection` calls whose request has not arrived whole over all its
//! connections ([`TooManyWaiting`]), so a few addresses cannot hold tens of thousands of them.

use std::collections::HashMap;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::task::{Context, Poll, Waker};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};
use tonic::transport::server::{Connected, TcpConnectInfo};

use super::peer::PeerKey;
use super::progress::FrameScan;
use super::stall::StallWatch;

fn locked<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// The calls open on one connection, since when it has had none, when its peer last took data,
/// and its cut.
#[derive(Debug)]
pub struct Activity {
    peer: PeerKey,
    /// The calls whose request has not arrived whole, per peer, over the listener's connections.
    waiting: Arc<WaitingCalls>,
    opened: Instant,
    calls: AtomicUsize,
    /// Health watches among the calls: they keep the connection from the idle timeout, not from
    /// being closed for a newcomer.
    watches: AtomicUsize,
    /// Calls whose request has arrived whole, health watches aside: only they keep the
    /// connection from being closed for a newcomer (a call whose request never ends holds
    /// nothing).
    arrived: AtomicUsize,
    /// When the last call ended (or the connection was accepted).
    quiet_since: Mutex<Instant>,
    /// When the peer last took DATA written to it (or the connection was accepted).
    taken_at: Mutex<Instant>,
    cut: AtomicBool,
    /// The connection's reader, woken by a cut.
    waker: Mutex<Option<Waker>>,
}

impl Activity {
    /// The activity of a new connection of `peer`, its calls counted in `waiting` until their
    /// requests arrive.
    fn new(peer: PeerKey, waiting: Arc<WaitingCalls>) -> Arc<Self> {
        let now = Instant::now();
        Arc::new(Self {
            peer,
            waiting,
            opened: now,
            calls: AtomicUsize::new(0),
            watches: AtomicUsize::new(0),
            arrived: AtomicUsize::new(0),
            quiet_since: Mutex::new(now),
            taken_at: Mutex::new(now),
            cut: AtomicBool::new(false),
            waker: Mutex::new(None),
        })
    }

    /// The peer of the connection.
    pub fn peer(&self) -> PeerKey {
        self.peer
    }

    /// Counts a call on the connection until the guard is dropped; a health watch counts as a
    /// watch too. Refused when the peer already has as many calls whose request has not arrived
    /// whole as its bound (over all its connections: `WaitingCalls`).
    pub fn begin(self: &Arc<Self>, watch: bool) -> Result<CallGuard, TooManyWaiting> {
        self.waiting.enter(self.peer)?;
        self.calls.fetch_add(1, Ordering::SeqCst);
        if watch {
            self.watches.fetch_add(1, Ordering::SeqCst);
        }
        Ok(CallGuard { activity: self.clone(), watch, state: Arc::new(AtomicU8::new(WAITING)) })
    }

    /// Whether a newcomer may close the connection: no call open whose request has arrived, but
    /// health watches.
    fn evictable(&self) -> bool {
        self.arrived.load(Ordering::SeqCst) == 0
    }

    /// How long the peer has taken no DATA written to it (PING ACKs and other control frames
    /// do not count on a connection in the clear).
    pub fn not_taken_for(&self) -> Duration {
        locked(&self.taken_at).elapsed()
    }

    fn took(&self) {
        *locked(&self.taken_at) = Instant::now();
    }

    /// Closes the connection: its reads and writes fail from now on, which ends the HTTP/2
    /// connection and every call on it (their samples and slots are given back as they drop).
    pub fn cut(&self) {
        self.cut.store(true, Ordering::SeqCst);
        if let Some(w) = locked(&self.waker).take() {
            w.wake();
        }
    }

    pub fn is_cut(&self) -> bool {
        self.cut.load(Ordering::SeqCst)
    }

    /// Ready once the connection is cut (the waker of `cx` is woken then).
    fn poll_cut(&self, cx: &mut Context<'_>) -> Poll<()> {
        if self.is_cut() {
            return Poll::Ready(());
        }
        *locked(&self.waker) = Some(cx.waker().clone());
        if self.is_cut() {
            Poll::Ready(())
        } else {
            Poll::Pending
        }
    }

    /// When the connection is idle for `idle` (None while a call is open).
    fn idle_deadline(&self, idle: Duration) -> Option<Instant> {
        if self.calls.load(Ordering::SeqCst) > 0 {
            return None;
        }
        Some(*self.quiet_since.lock().unwrap_or_else(std::sync::PoisonError::into_inner) + idle)
    }
}

/// A call's request has not arrived whole yet.
const WAITING: u8 = 0;
/// A call's request has arrived (counted in [`Activity::arrived`] unless it is a watch).
const ARRIVED: u8 = 1;
/// A call has ended.
const ENDED: u8 = 2;

/// A call counted on its connection ([`Activity::begin`]).
#[derive(Debug)]
pub struct CallGuard {
    activity: Arc<Activity>,
    watch: bool,
    /// [`WAITING`], [`ARRIVED`] or [`ENDED`], shared with its [`Arrival`].
    state: Arc<AtomicU8>,
}

impl CallGuard {
    /// What says that the call's request has arrived whole.
    pub fn arrival(&self) -> Arrival {
        Arrival { activity: self.activity.clone(), watch: self.watch, state: self.state.clone() }
    }
}

impl Drop for CallGuard {
    fn drop(&mut self) {
        *locked(&self.activity.quiet_since) = Instant::now();
        match self.state.swap(ENDED, Ordering::SeqCst) {
            ARRIVED if !self.watch => {
                self.activity.arrived.fetch_sub(1, Ordering::SeqCst);
            }
            WAITING => self.activity.waiting.leave(self.activity.peer),
            _ => {}
        }
        if self.watch {
            self.activity.watches.fetch_sub(1, Ordering::SeqCst);
        }
        self.activity.calls.fetch_sub(1, Ordering::SeqCst);
    }
}

/// Says that a call's request has arrived whole ([`CallGuard::arrival`]): from then on the call
/// keeps its connection from being closed for a newcomer.
#[derive(Debug)]
pub struct Arrival {
    activity: Arc<Activity>,
    watch: bool,
    state: Arc<AtomicU8>,
}

impl Arrival {
    /// The request has arrived (once; nothing after the call has ended).
    pub fn arrived(&self) {
        let first = self.state.compare_exchange(WAITING, ARRIVED, Ordering::SeqCst, Ordering::SeqCst).is_ok();
        if first {
            self.activity.waiting.leave(self.activity.peer);
        }
        if first && !self.watch {
            self.activity.arrived.fetch_add(1, Ordering::SeqCst);
        }
    }
}

/// The calls whose request has not arrived whole (headers sent, the body still to come), per
/// peer over all the listener's connections: at most `max` at once, so a few addresses cannot
/// hold tens of thousands of unfinished calls (each a few KiB of the server's memory until the
/// request deadline) however many connections and calls per connection they may open.
#[derive(Debug)]
struct WaitingCalls {
    per_peer: Mutex<HashMap<PeerKey, usize>>,
    max: usize,
}

/// A call refused because its peer has as many calls whose request has not arrived as it may.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error(
    "too many calls whose request has not arrived whole: {0} of this client are waiting for their \
     request (max_calls_per_connection); retry when they have arrived or failed"
)]
pub struct TooManyWaiting(pub usize);

impl WaitingCalls {
    fn enter(&self, peer: PeerKey) -> Result<(), TooManyWaiting> {
        let mut m = locked(&self.per_peer);
        let n = m.entry(peer).or_insert(0);
        if *n >= self.max {
            return Err(TooManyWaiting(self.max));
        }
        *n += 1;
        Ok(())
    }

    fn leave(&self, peer: PeerKey) {
        let mut m = locked(&self.per_peer);
        if let Some(n) = m.get_mut(&peer) {
            *n -= 1;
            if *n == 0 {
                m.remove(&peer);
            }
        }
    }
}

/// What a request knows of its connection (in its extensions): the TCP addresses and the
/// connection's [`Activity`], which the server's layer (`service::reply`) counts calls on.
#[derive(Clone, Debug)]
pub struct ConnInfo {
    pub tcp: TcpConnectInfo,
    pub activity: Arc<Activity>,
}

/// The open connections of a listener: their number per peer (for `max_connections_per_peer`)
/// and their activities (for [`Registry::evict`]).
#[derive(Debug, Default)]
struct Registry(Mutex<Conns>);

#[derive(Debug, Default)]
struct Conns {
    per_peer: HashMap<PeerKey, usize>,
    open: Vec<Weak<Activity>>,
}

impl Registry {
    /// Takes a place for a connection of `activity`'s peer when it has fewer than `max`.
    fn take(self: &Arc<Self>, activity: &Arc<Activity>, max: usize) -> Option<PeerSlot> {
        let mut m = locked(&self.0);
        let n = m.per_peer.entry(activity.peer).or_insert(0);
        if *n >= max {
            return None;
        }
        *n += 1;
        m.open.retain(|w| w.strong_count() > 0);
        m.open.push(Arc::downgrade(activity));
        Some(PeerSlot { registry: self.clone(), peer: activity.peer })
    }

    /// Closes one connection for a newcomer: among those with no call open whose request has
    /// arrived, but health watches (and not cut already), one of the peer with the most
    /// connections, the oldest first. Never `newcomer` itself. Whether there was one.
    fn evict(&self, newcomer: &Arc<Activity>) -> bool {
        let m = locked(&self.0);
        let victim = m
            .open
            .iter()
            .filter_map(Weak::upgrade)
            .filter(|a| a.evictable() && !a.is_cut() && !Arc::ptr_eq(a, newcomer))
            .max_by_key(|a| (m.per_peer.get(&a.peer).copied().unwrap_or(0), std::cmp::Reverse(a.opened)));
        drop(m);
        match victim {
            Some(a) => {
                tracing::debug!(peer = %a.peer, "connection closed for a newcomer: no call open whose request has arrived");
                a.cut();
                true
            }
            None => false,
        }
    }
}

/// A connection's place in its peer's count.
#[derive(Debug)]
struct PeerSlot {
    registry: Arc<Registry>,
    peer: PeerKey,
}

impl Drop for PeerSlot {
    fn drop(&mut self) {
        let mut m = locked(&self.registry.0);
        if let Some(n) = m.per_peer.get_mut(&self.peer) {
            *n -= 1;
            if *n == 0 {
                m.per_peer.remove(&self.peer);
            }
        }
    }
}

/// An accepted connection holding its slots of the connection bounds until it is dropped. It
/// ends itself (end of input to the HTTP/2 server, which then closes it) when no call has been
/// open on it for the idle timeout, and fails its writes when the peer has taken no data for the
/// stall timeout while the server had bytes for it ([`StallWatch`]).
#[derive(Debug)]
pub struct Guarded {
    inner: StallWatch<TcpStream>,
    info: ConnInfo,
    /// The HTTP/2 frames written, on a connection in the clear (none under TLS).
    scan: Option<FrameScan>,
    limits: ConnLimits,
    idle_timer: Pin<Box<Sleep>>,
    ended: bool,
    _slot: OwnedSemaphorePermit,
    _peer: PeerSlot,
}

impl Guarded {
    /// Whether the idle timeout has passed with no call open (re-arming the timer otherwise).
    fn idle_expired(&mut self, cx: &mut Context<'_>) -> bool {
        loop {
            if self.idle_timer.as_mut().poll(cx).is_pending() {
                return false;
            }
            let now = Instant::now();
            match self.info.activity.idle_deadline(self.limits.first_bytes_timeout) {
                Some(deadline) if deadline <= now => return true,
                Some(deadline) => self.idle_timer.as_mut().reset(deadline),
                None => self.idle_timer.as_mut().reset(now + self.limits.first_bytes_timeout),
            }
        }
    }

    /// A write's result: the peer's taking noted when the bytes written carry DATA payload
    /// (`data`: how many of the `n` written do; in the clear a PING ACK or any other control
    /// frame is no sign that the client took anything), the connection ended (and logged once)
    /// when the stall watch cut it.
    fn noted(
        &mut self,
        r: Poll<io::Result<usize>>,
        data: impl FnOnce(&mut Self, usize) -> usize,
    ) -> Poll<io::Result<usize>> {
        if let Poll::Ready(Ok(n)) = r {
            if n > 0 && data(self, n) > 0 {
                self.info.activity.took();
            }
        }
        self.stalled(r)
    }

    /// How many of the first `n` bytes of `buf` just written are DATA payload; under TLS the
    /// frames cannot be seen, and every byte counts.
    fn data_in(&mut self, buf: &[u8], n: usize) -> usize {
        match &mut self.scan {
            Some(scan) => scan.feed(&buf[..n]),
            None => n,
        }
    }

    fn stalled<T>(&mut self, r: Poll<io::Result<T>>) -> Poll<io::Result<T>> {
        if matches!(r, Poll::Ready(Err(_))) && self.inner.is_cut() && !self.ended {
            tracing::info!(peer = ?self.info.tcp.remote_addr(), stall_timeout_s = self.limits.stall_timeout.as_secs_f64(), "connection closed: the peer stopped reading");
            self.ended = true;
        }
        r
    }
}

impl AsyncRead for Guarded {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        if self.info.activity.poll_cut(cx).is_ready() {
            return Poll::Ready(Err(cut_error()));
        }
        if self.ended {
            return Poll::Ready(Ok(()));
        }
        match Pin::new(&mut self.inner).poll_read(cx, buf) {
            Poll::Pending => {
                if self.idle_expired(cx) {
                    tracing::debug!(peer = ?self.info.tcp.remote_addr(), "connection closed: no call open for the idle timeout");
                    self.ended = true;
                    return Poll::Ready(Ok(())); // the end of input: the HTTP/2 server closes it
                }
                Poll::Pending
            }
            ready => ready,
        }
    }
}

impl AsyncWrite for Guarded {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        if self.info.activity.is_cut() {
            return Poll::Ready(Err(cut_error()));
        }
        let r = Pin::new(&mut self.inner).poll_write(cx, buf);
        self.noted(r, |me, n| me.data_in(buf, n))
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let r = Pin::new(&mut self.inner).poll_flush(cx);
        self.stalled(r)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        if self.info.activity.is_cut() {
            return Poll::Ready(Err(cut_error()));
        }
        let r = Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        self.noted(r, |me, n| match &mut me.scan {
            Some(scan) => scan.feed_vectored(bufs, n),
            None => n,
        })
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

/// The error of a cut connection's reads and writes.
fn cut_error() -> io::Error {
    io::Error::new(io::ErrorKind::ConnectionAborted, "the connection was closed by the server (room for other clients)")
}

impl Connected for Guarded {
    type ConnectInfo = ConnInfo;

    fn connect_info(&self) -> Self::ConnectInfo {
        self.info.clone()
    }
}

/// The connection limits of one listener.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConnLimits {
    /// Most connections open at once (waiting for their first bytes included).
    pub max_connections: usize,
    /// Most connections open at once from one peer address.
    pub max_per_peer: usize,
    /// How long a new connection may stay silent before it is closed, and how long a connection
    /// may stay open with no call; also the TCP keepalive idle time and probe interval.
    pub first_bytes_timeout: Duration,
    /// How long the peer may take no data while the server has bytes for it before the
    /// connection is closed.
    pub stall_timeout: Duration,
    /// Most calls of one peer whose request has not arrived whole, over all its connections.
    pub max_waiting_per_peer: usize,
    /// Whether the connections carry HTTP/2 in the clear: then only DATA payload written counts
    /// as the client taking data ([`FrameScan`]); under TLS any byte written counts.
    pub frames_in_clear: bool,
}

/// Probes a silent peer gets before the kernel drops the connection.
const KEEPALIVE_RETRIES: u32 = 3;

/// Turns TCP keepalive on for `stream`: the first probe after `every` of silence, then one
/// every `every`, [`KEEPALIVE_RETRIES`] of them.
fn set_keepalive(stream: &TcpStream, every: Duration) -> io::Result<()> {
    let every = every.max(Duration::from_secs(1));
    let ka = socket2::TcpKeepalive::new().with_time(every).with_interval(every).with_retries(KEEPALIVE_RETRIES);
    socket2::SockRef::from(stream).set_tcp_keepalive(&ka)
}

/// How long the accept loop pauses after an accept that failed for want of a resource (file
/// descriptors, socket buffers, memory): the connections waiting are not accepted any sooner by
/// trying again at once, and trying again at once spins a core and floods the log.
pub const ACCEPT_BACKOFF: Duration = Duration::from_millis(100);

/// At most one log line per this interval for failed accepts; it counts the failures since the
/// line before.
pub const ACCEPT_LOG_EVERY: Duration = Duration::from_secs(10);

/// How long a newcomer waits for the slot of the connection closed for it.
const EVICTION_WAIT: Duration = Duration::from_secs(1);

/// The failed accepts of one listener: what to do after each, and their rate-limited log.
#[derive(Debug, Default)]
struct AcceptErrors {
    /// When the last line was logged.
    logged_at: Option<Instant>,
    /// Failures since then that were not logged.
    unlogged: u64,
}

impl AcceptErrors {
    /// Notes a failed accept at `now`: the pause before the next accept ([`ACCEPT_BACKOFF`]),
    /// or none for an error of the one connection being accepted (it reset or aborted before it
    /// was taken, or its network went away), which the next accept does not meet again.
    fn failed(&mut self, e: &io::Error, now: Instant) -> Option<Duration> {
        use io::ErrorKind as K;
        let own = matches!(
            e.kind(),
            K::ConnectionAborted
                | K::ConnectionReset
                | K::ConnectionRefused
                | K::Interrupted
                | K::WouldBlock
                | K::NetworkDown
                | K::NetworkUnreachable
                | K::HostUnreachable
        );
        if own {
            tracing::debug!(error = %e, "accept failed for one connection");
            return None;
        }
        match self.logged_at {
            Some(t) if now.duration_since(t) < ACCEPT_LOG_EVERY => self.unlogged += 1,
            _ => {
                tracing::warn!(
                    error = %e,
                    failed_since_last_line = self.unlogged,
                    backoff_ms = ACCEPT_BACKOFF.as_millis() as u64,
                    "accept failed (out of file descriptors or memory?): pausing the accept loop"
                );
                self.logged_at = Some(now);
                self.unlogged = 0;
            }
        }
        Some(ACCEPT_BACKOFF)
    }

    /// Whether the next failure at `now` would be logged (for the tests).
    #[cfg(test)]
    fn would_log(&self, now: Instant) -> bool {
        self.logged_at.is_none_or(|t| now.duration_since(t) >= ACCEPT_LOG_EVERY)
    }
}

/// The accepted connections of `listener` under `limits`, as a stream for tonic's
/// `serve_with_incoming`. The accept loop ends when the stream is dropped.
pub fn incoming(
    listener: TcpListener,
    limits: ConnLimits,
) -> tokio_stream::wrappers::ReceiverStream<io::Result<Guarded>> {
    let (tx, rx) = mpsc::channel::<io::Result<Guarded>>(64);
    let slots = Arc::new(Semaphore::new(limits.max_connections.max(1)));
    let registry = Arc::new(Registry::default());
    let waiting = Arc::new(WaitingCalls { per_peer: Mutex::default(), max: limits.max_waiting_per_peer.max(1) });
    tokio::spawn(async move {
        let mut accept_errors = AcceptErrors::default();
        loop {
            let accepted = tokio::select! {
                a = listener.accept() => a,
                () = tx.closed() => return,
            };
            let (stream, peer) = match accepted {
                Ok((s, a)) => (s, a),
                // a failed accept is not the end of the listener
                Err(e) => {
                    if let Some(pause) = accept_errors.failed(&e, Instant::now()) {
                        tokio::select! {
                            () = tokio::time::sleep(pause) => {}
                            () = tx.closed() => return,
                        }
                    }
                    continue;
                }
            };
            let activity = Activity::new(PeerKey::of(peer.ip()), waiting.clone());
            let Some(peer_slot) = registry.take(&activity, limits.max_per_peer.max(1)) else {
                tracing::debug!(%peer, max_connections_per_peer = limits.max_per_peer, "connection refused: max_connections_per_peer");
                drop(stream);
                continue;
            };
            // all slots taken: one connection with no call open makes room, or the newcomer goes
            let slot = match slots.clone().try_acquire_owned() {
                Ok(slot) => Some(slot),
                Err(_) if registry.evict(&activity) => None,
                Err(_) => {
                    tracing::debug!(
                        max_connections = limits.max_connections,
                        "connection refused: max_connections, every connection has a call open"
                    );
                    drop(stream);
                    continue;
                }
            };
            let _ = stream.set_nodelay(true);
            if let Err(e) = set_keepalive(&stream, limits.first_bytes_timeout) {
                tracing::debug!(error = %e, "TCP keepalive not set");
            }
            let tx = tx.clone();
            let slots = slots.clone();
            tokio::spawn(async move {
                // the slot of the connection closed for this one, once it has closed
                let slot = match slot {
                    Some(slot) => slot,
                    None => match tokio::time::timeout(EVICTION_WAIT, slots.acquire_owned()).await {
                        Ok(Ok(slot)) => slot,
                        _ => {
                            tracing::debug!("connection refused: max_connections, no slot freed in time");
                            return;
                        }
                    },
                };
                // the first bytes within the deadline, or the connection is closed (also when a
                // newcomer needs its slot first)
                let mut probe = [0u8; 1];
                let first = tokio::select! {
                    r = tokio::time::timeout(limits.first_bytes_timeout, stream.peek(&mut probe)) => r.ok(),
                    () = std::future::poll_fn(|cx| activity.poll_cut(cx)) => None,
                };
                match first {
                    Some(Ok(n)) if n > 0 => {
                        let info = ConnInfo { tcp: stream.connect_info(), activity };
                        let g = Guarded {
                            inner: StallWatch::new(stream, limits.stall_timeout),
                            info,
                            scan: limits.frames_in_clear.then(FrameScan::default),
                            limits,
                            idle_timer: Box::pin(tokio::time::sleep(limits.first_bytes_timeout)),
                            ended: false,
                            _slot: slot,
                            _peer: peer_slot,
                        };
                        let _ = tx.send(Ok(g)).await;
                    }
                    _ => tracing::debug!("connection closed: nothing received in time"),
                }
            });
        }
    });
    tokio_stream::wrappers::ReceiverStream::new(rx)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::AsyncWriteExt;
    use tokio_stream::StreamExt;

    /// An accepted connection carries TCP keepalive with the configured idle time and interval.
    #[tokio::test]
    async fn accepted_connections_have_tcp_keepalive() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let limits = ConnLimits {
            max_connections: 4,
            max_per_peer: 4,
            first_bytes_timeout: Duration::from_secs(7),
            stall_timeout: Duration::from_secs(60),
            max_waiting_per_peer: 4,
            frames_in_clear: true,
        };
        let mut conns = incoming(listener, limits);
        let mut client = TcpStream::connect(addr).await.unwrap();
        client.write_all(b"x").await.unwrap();
        let accepted = conns.next().await.unwrap().unwrap();
        let sock = socket2::SockRef::from(accepted.inner.get_ref());
        assert!(sock.keepalive().unwrap());
        assert_eq!(sock.tcp_keepalive_time().unwrap(), Duration::from_secs(7));
        assert_eq!(sock.tcp_keepalive_interval().unwrap(), Duration::from_secs(7));
        assert_eq!(sock.tcp_keepalive_retries().unwrap(), KEEPALIVE_RETRIES);
        // the client's own socket is untouched: the option is the server's doing
        assert!(!socket2::SockRef::from(&client).keepalive().unwrap());
    }

    /// Out of descriptors (EMFILE, ENFILE), buffers (ENOBUFS) or memory (ENOMEM), the accept
    /// loop pauses; an error of the one connection being accepted is skipped at once. Failures
    /// are logged at most once per [`ACCEPT_LOG_EVERY`], the line counting those in between.
    #[cfg(target_os = "linux")]
    #[test]
    fn accept_errors_back_off_on_exhaustion_and_skip_one_connections_own() {
        const EMFILE: i32 = 24;
        const ENFILE: i32 = 23;
        const ENOBUFS: i32 = 105;
        const ENOMEM: i32 = 12;
        const ECONNABORTED: i32 = 103;
        let mut errors = AcceptErrors::default();
        let t0 = Instant::now();
        for (i, code) in [EMFILE, ENFILE, ENOBUFS, ENOMEM].into_iter().enumerate() {
            let now = t0 + Duration::from_millis(i as u64);
            let e = io::Error::from_raw_os_error(code);
            assert_eq!(errors.failed(&e, now), Some(ACCEPT_BACKOFF), "{e}");
        }
        assert_eq!(errors.unlogged, 3, "one line for the first, the next three counted");
        for own in [io::Error::from_raw_os_error(ECONNABORTED), io::ErrorKind::ConnectionReset.into()] {
            assert_eq!(errors.failed(&own, t0), None, "{own}");
        }
        assert_eq!(errors.unlogged, 3, "a connection's own error is not an exhaustion");
        assert!(!errors.would_log(t0 + ACCEPT_LOG_EVERY - Duration::from_millis(1)));
        assert!(errors.would_log(t0 + ACCEPT_LOG_EVERY));
        let later = t0 + ACCEPT_LOG_EVERY;
        assert_eq!(errors.failed(&io::Error::from_raw_os_error(EMFILE), later), Some(ACCEPT_BACKOFF));
        assert_eq!((errors.logged_at, errors.unlogged), (Some(later), 0));
    }
}
