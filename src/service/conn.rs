//! Connection hygiene of the listeners: at most `max_connections` connections open at once and
//! `max_connections_per_peer` from one address (more are closed as they arrive); a connection
//! must send its first bytes within `idle_connection_timeout_s`, and is closed once no call has
//! been open on it for as long (HTTP/2 pings answered or not: calls are counted by the server's
//! layer, `service::reply`, through the connection's [`Activity`]); a connection whose peer takes
//! less than [`STALL_PROGRESS_BYTES`] over `stall_timeout_s` while the server has bytes for it is
//! closed, which ends its streams and frees their slots (each batch carries its resume cursor).
//! All of it holds on the plaintext and the TLS port alike (the TLS handshake runs over these
//! connections). HTTP/2 keepalive pings (`Server::http2_keepalive_*`) close connections whose
//! peer stops answering, and TCP keepalive (probes after `idle_connection_timeout_s` of silence,
//! every such interval, 3 tries) lets the kernel drop connections whose peer vanished without a
//! FIN (the cable, the node).

use std::collections::HashMap;
use std::future::Future;
use std::io;
use std::net::IpAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};
use tonic::transport::server::{Connected, TcpConnectInfo};

/// The calls open on one connection and since when it has had none.
#[derive(Debug)]
pub struct Activity {
    calls: AtomicUsize,
    /// When the last call ended (or the connection was accepted).
    quiet_since: Mutex<Instant>,
}

impl Activity {
    fn new() -> Arc<Self> {
        Arc::new(Self { calls: AtomicUsize::new(0), quiet_since: Mutex::new(Instant::now()) })
    }

    /// Counts a call on the connection until the guard is dropped.
    pub fn begin(self: &Arc<Self>) -> CallGuard {
        self.calls.fetch_add(1, Ordering::SeqCst);
        CallGuard(self.clone())
    }

    /// When the connection is idle for `idle` (None while a call is open).
    fn idle_deadline(&self, idle: Duration) -> Option<Instant> {
        if self.calls.load(Ordering::SeqCst) > 0 {
            return None;
        }
        Some(*self.quiet_since.lock().unwrap_or_else(std::sync::PoisonError::into_inner) + idle)
    }
}

/// A call counted on its connection ([`Activity::begin`]).
#[derive(Debug)]
pub struct CallGuard(Arc<Activity>);

impl Drop for CallGuard {
    fn drop(&mut self) {
        *self.0.quiet_since.lock().unwrap_or_else(std::sync::PoisonError::into_inner) = Instant::now();
        self.0.calls.fetch_sub(1, Ordering::SeqCst);
    }
}

/// What a request knows of its connection (in its extensions): the TCP addresses and the
/// connection's [`Activity`], which the server's layer (`service::reply`) counts calls on.
#[derive(Clone, Debug)]
pub struct ConnInfo {
    pub tcp: TcpConnectInfo,
    pub activity: Arc<Activity>,
}

/// The connections open per peer address (for `max_connections_per_peer`).
#[derive(Debug, Default)]
struct Peers(Mutex<HashMap<IpAddr, usize>>);

impl Peers {
    /// Takes a slot of `ip` when it has fewer than `max` connections.
    fn take(self: &Arc<Self>, ip: IpAddr, max: usize) -> Option<PeerSlot> {
        let mut m = self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let n = m.entry(ip).or_insert(0);
        if *n >= max {
            return None;
        }
        *n += 1;
        Some(PeerSlot { peers: self.clone(), ip })
    }
}

/// A connection's place in its peer's count.
#[derive(Debug)]
struct PeerSlot {
    peers: Arc<Peers>,
    ip: IpAddr,
}

impl Drop for PeerSlot {
    fn drop(&mut self) {
        let mut m = self.peers.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        if let Some(n) = m.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                m.remove(&self.ip);
            }
        }
    }
}

/// Bytes a stalled connection must take within `stall_timeout` to count as reading again.
pub const STALL_PROGRESS_BYTES: u64 = 1 << 20;

/// An accepted connection holding its slots of the connection bounds until it is dropped. It
/// ends itself (end of input to the HTTP/2 server, which then closes it) when no call has been
/// open on it for the idle timeout, and fails its writes when the peer has taken less than
/// [`STALL_PROGRESS_BYTES`] over the stall timeout while the server had bytes for it.
#[derive(Debug)]
pub struct Guarded {
    inner: TcpStream,
    info: ConnInfo,
    limits: ConnLimits,
    idle_timer: Pin<Box<Sleep>>,
    /// Since when writes have been waiting for the peer, and the bytes written since then.
    stalled: Option<(Instant, u64)>,
    stall_timer: Pin<Box<Sleep>>,
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

    /// Notes a write that could not go on; true when the connection has stalled for too long.
    fn write_stalled(&mut self, cx: &mut Context<'_>) -> bool {
        let now = Instant::now();
        let since = match self.stalled {
            Some((t, _)) => t,
            None => {
                self.stalled = Some((now, 0));
                self.stall_timer.as_mut().reset(now + self.limits.stall_timeout);
                now
            }
        };
        if now >= since + self.limits.stall_timeout {
            return true;
        }
        // wake the connection when the timeout passes, even if the peer never reads again
        let _ = self.stall_timer.as_mut().poll(cx);
        false
    }

    /// Notes `n` bytes written: enough of them end a stall.
    fn wrote(&mut self, n: usize) {
        if let Some((t, w)) = self.stalled {
            let w = w + n as u64;
            self.stalled = (w < STALL_PROGRESS_BYTES).then_some((t, w));
        }
    }
}

impl AsyncRead for Guarded {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
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

impl Guarded {
    fn stall_error(&mut self) -> io::Error {
        tracing::info!(peer = ?self.info.tcp.remote_addr(), stall_timeout_s = self.limits.stall_timeout.as_secs_f64(), "connection closed: the peer stopped reading");
        self.ended = true;
        io::Error::new(io::ErrorKind::TimedOut, "the peer stopped reading (stall_timeout_s)")
    }
}

impl AsyncWrite for Guarded {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        match Pin::new(&mut self.inner).poll_write(cx, buf) {
            Poll::Ready(Ok(n)) => {
                self.wrote(n);
                Poll::Ready(Ok(n))
            }
            Poll::Pending if self.write_stalled(cx) => Poll::Ready(Err(self.stall_error())),
            other => other,
        }
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match Pin::new(&mut self.inner).poll_flush(cx) {
            Poll::Pending if self.write_stalled(cx) => Poll::Ready(Err(self.stall_error())),
            other => other,
        }
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        match Pin::new(&mut self.inner).poll_write_vectored(cx, bufs) {
            Poll::Ready(Ok(n)) => {
                self.wrote(n);
                Poll::Ready(Ok(n))
            }
            Poll::Pending if self.write_stalled(cx) => Poll::Ready(Err(self.stall_error())),
            other => other,
        }
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
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
    /// How long the peer may take less than [`STALL_PROGRESS_BYTES`] while the server has bytes
    /// for it before the connection is closed.
    pub stall_timeout: Duration,
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

/// The accepted connections of `listener` under `limits`, as a stream for tonic's
/// `serve_with_incoming`. The accept loop ends when the stream is dropped.
pub fn incoming(
    listener: TcpListener,
    limits: ConnLimits,
) -> tokio_stream::wrappers::ReceiverStream<io::Result<Guarded>> {
    let (tx, rx) = mpsc::channel::<io::Result<Guarded>>(64);
    let slots = Arc::new(Semaphore::new(limits.max_connections.max(1)));
    let peers = Arc::new(Peers::default());
    tokio::spawn(async move {
        loop {
            let accepted = tokio::select! {
                a = listener.accept() => a,
                () = tx.closed() => return,
            };
            let (stream, peer) = match accepted {
                Ok((s, a)) => (s, a),
                // a failed accept (e.g. out of file descriptors) is not the end of the listener
                Err(e) => {
                    tracing::warn!(error = %e, "accept failed");
                    tokio::task::yield_now().await;
                    continue;
                }
            };
            let Ok(slot) = slots.clone().try_acquire_owned() else {
                tracing::debug!(max_connections = limits.max_connections, "connection refused: max_connections");
                drop(stream);
                continue;
            };
            let Some(peer_slot) = peers.take(peer.ip(), limits.max_per_peer.max(1)) else {
                tracing::debug!(%peer, max_connections_per_peer = limits.max_per_peer, "connection refused: max_connections_per_peer");
                drop(stream);
                continue;
            };
            let _ = stream.set_nodelay(true);
            if let Err(e) = set_keepalive(&stream, limits.first_bytes_timeout) {
                tracing::debug!(error = %e, "TCP keepalive not set");
            }
            let tx = tx.clone();
            tokio::spawn(async move {
                // the first bytes within the deadline, or the connection is closed
                let mut probe = [0u8; 1];
                match tokio::time::timeout(limits.first_bytes_timeout, stream.peek(&mut probe)).await {
                    Ok(Ok(n)) if n > 0 => {
                        let info = ConnInfo { tcp: stream.connect_info(), activity: Activity::new() };
                        let now = Instant::now();
                        let g = Guarded {
                            inner: stream,
                            info,
                            limits,
                            idle_timer: Box::pin(tokio::time::sleep_until(now + limits.first_bytes_timeout)),
                            stalled: None,
                            stall_timer: Box::pin(tokio::time::sleep_until(now + limits.stall_timeout)),
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
        };
        let mut conns = incoming(listener, limits);
        let mut client = TcpStream::connect(addr).await.unwrap();
        client.write_all(b"x").await.unwrap();
        let accepted = conns.next().await.unwrap().unwrap();
        let sock = socket2::SockRef::from(&accepted.inner);
        assert!(sock.keepalive().unwrap());
        assert_eq!(sock.tcp_keepalive_time().unwrap(), Duration::from_secs(7));
        assert_eq!(sock.tcp_keepalive_interval().unwrap(), Duration::from_secs(7));
        assert_eq!(sock.tcp_keepalive_retries().unwrap(), KEEPALIVE_RETRIES);
        // the client's own socket is untouched: the option is the server's doing
        assert!(!socket2::SockRef::from(&client).keepalive().unwrap());
    }
}
