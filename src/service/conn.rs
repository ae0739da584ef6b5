//! Connection hygiene of the listeners: at most `max_connections` connections open at once
//! (more are closed as they arrive), and a connection must send its first bytes within
//! `idle_connection_timeout_s` or it is closed. Both hold on the plaintext and the TLS port
//! alike (the TLS handshake runs over these connections); HTTP/2 keepalive pings
//! (`Server::http2_keepalive_*`) then close connections whose peer stops answering, and TCP
//! keepalive (probes after `idle_connection_timeout_s` of silence, every such interval, 3 tries)
//! lets the kernel drop connections whose peer vanished without a FIN (the cable, the node).

use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};
use tonic::transport::server::{Connected, TcpConnectInfo};

/// An accepted connection holding its slot of the connection bound until it is dropped.
#[derive(Debug)]
pub struct Guarded {
    inner: TcpStream,
    _slot: OwnedSemaphorePermit,
}

impl AsyncRead for Guarded {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl AsyncWrite for Guarded {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }
}

impl Connected for Guarded {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> Self::ConnectInfo {
        self.inner.connect_info()
    }
}

/// The connection limits of one listener.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConnLimits {
    /// Most connections open at once (waiting for their first bytes included).
    pub max_connections: usize,
    /// How long a new connection may stay silent before it is closed; also the TCP keepalive
    /// idle time and probe interval.
    pub first_bytes_timeout: Duration,
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
    tokio::spawn(async move {
        loop {
            let accepted = tokio::select! {
                a = listener.accept() => a,
                () = tx.closed() => return,
            };
            let stream = match accepted {
                Ok((s, _)) => s,
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
                        let _ = tx.send(Ok(Guarded { inner: stream, _slot: slot })).await;
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
        let limits = ConnLimits { max_connections: 4, first_bytes_timeout: Duration::from_secs(7) };
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
