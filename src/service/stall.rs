//! Stall detection on a connection's writes, measuring the client: a stall starts when a write
//! cannot go on (the socket's send buffer is full because the peer stopped taking data) and ends
//! as soon as the peer takes data again (any write goes through). A stall that lasts
//! `stall_timeout` fails the writes, which closes the connection. Time in which the server has
//! nothing to send is never counted: a client that pauses briefly now and then is never cut.

use std::future::Future;
use std::io;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::time::{Instant, Sleep};

/// Why a stalled connection's writes fail (the source of their `TimedOut` error).
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("the peer took no data for {:?} while the server had bytes for it (stall_timeout_s)", .0)]
pub struct Stalled(pub Duration);

/// An IO object whose writes fail once they have been blocked for `timeout` without the peer
/// taking any data in between.
#[derive(Debug)]
pub struct StallWatch<T> {
    inner: T,
    timeout: Duration,
    /// Since when writes have been blocked (None: the last write went through).
    blocked_since: Option<Instant>,
    /// Wakes the writer when the timeout passes, even if the peer never reads again.
    timer: Pin<Box<Sleep>>,
    cut: bool,
}

impl<T> StallWatch<T> {
    pub fn new(inner: T, timeout: Duration) -> Self {
        let timer = Box::pin(tokio::time::sleep(timeout));
        Self { inner, timeout, blocked_since: None, timer, cut: false }
    }

    pub fn get_ref(&self) -> &T {
        &self.inner
    }

    /// Whether the writes failed for a stall (the connection is being closed).
    pub fn is_cut(&self) -> bool {
        self.cut
    }

    /// Notes a blocked write; the error once the stall has lasted the timeout.
    fn blocked(&mut self, cx: &mut Context<'_>) -> Option<io::Error> {
        let now = Instant::now();
        let since = *self.blocked_since.get_or_insert_with(|| {
            self.timer.as_mut().reset(now + self.timeout);
            now
        });
        if now.duration_since(since) >= self.timeout {
            self.cut = true;
            return Some(self.error());
        }
        // registers the waker: the writer is polled again when the timeout passes
        let _ = self.timer.as_mut().poll(cx);
        None
    }

    fn error(&self) -> io::Error {
        io::Error::new(io::ErrorKind::TimedOut, Stalled(self.timeout))
    }

    /// What a write returned, with the stall noted: bytes taken end a stall, a blocked write
    /// starts one (or fails it, once it has lasted the timeout).
    fn note(&mut self, cx: &mut Context<'_>, r: Poll<io::Result<usize>>) -> Poll<io::Result<usize>> {
        match r {
            Poll::Ready(Ok(n)) => {
                if n > 0 {
                    self.blocked_since = None;
                }
                Poll::Ready(Ok(n))
            }
            Poll::Pending => match self.blocked(cx) {
                Some(e) => Poll::Ready(Err(e)),
                None => Poll::Pending,
            },
            err => err,
        }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for StallWatch<T> {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for StallWatch<T> {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        if self.cut {
            return Poll::Ready(Err(self.error()));
        }
        let r = Pin::new(&mut self.inner).poll_write(cx, buf);
        self.note(cx, r)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        if self.cut {
            return Poll::Ready(Err(self.error()));
        }
        let r = Pin::new(&mut self.inner).poll_write_vectored(cx, bufs);
        self.note(cx, r)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    /// A flush that cannot go on is a blocked write too; one that completes is no sign that the
    /// peer took anything (a socket's flush always completes), so it leaves a stall as it is.
    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        if self.cut {
            return Poll::Ready(Err(self.error()));
        }
        match Pin::new(&mut self.inner).poll_flush(cx) {
            Poll::Pending => match self.blocked(cx) {
                Some(e) => Poll::Ready(Err(e)),
                None => Poll::Pending,
            },
            other => other,
        }
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

#[cfg(test)]
mod tests {
    //! Driven on tokio's paused clock with an in-memory pipe of 64 KiB (`tokio::io::duplex`) as
    //! the socket: the test is the client, reading the far end or not.

    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream};

    const TIMEOUT: Duration = Duration::from_secs(120);
    const PIPE: usize = 64 << 10;

    fn pipe() -> (StallWatch<DuplexStream>, DuplexStream) {
        let (server, client) = tokio::io::duplex(PIPE);
        (StallWatch::new(server, TIMEOUT), client)
    }

    /// Writes until a write is blocked (the pipe is full): the server has more bytes than the
    /// client has taken. Panics if the watch fails a write.
    async fn fill(w: &mut StallWatch<DuplexStream>) {
        let chunk = [7u8; 4096];
        loop {
            let r = std::future::poll_fn(|cx| Poll::Ready(Pin::new(&mut *w).poll_write(cx, &chunk))).await;
            match r {
                Poll::Ready(Ok(n)) => assert!(n > 0),
                Poll::Ready(Err(e)) => panic!("a write failed: {e}"),
                Poll::Pending => return,
            }
        }
    }

    /// The client takes `n` bytes.
    async fn take(client: &mut DuplexStream, n: usize) {
        let mut buf = vec![0u8; n];
        client.read_exact(&mut buf).await.unwrap();
    }

    /// A client that pauses for less than the timeout twice, far apart (the server runs out of
    /// data in between), is never cut: each pause is a stall of its own.
    #[tokio::test(start_paused = true)]
    async fn a_client_that_pauses_briefly_twice_far_apart_is_not_cut() {
        let (mut w, mut client) = pipe();
        fill(&mut w).await;
        tokio::time::sleep(TIMEOUT * 3 / 4).await; // the client's first pause
        take(&mut client, PIPE).await;
        fill(&mut w).await; // it took data: the stall is over, the pipe fills again
        take(&mut client, PIPE).await;
        // the server has nothing to send for a long time, then a burst the client reads slowly
        tokio::time::sleep(TIMEOUT * 10).await;
        fill(&mut w).await;
        tokio::time::sleep(TIMEOUT * 3 / 4).await; // the second pause
        take(&mut client, 1).await; // a single byte taken counts
        let more = tokio::time::timeout(TIMEOUT / 2, w.write_all(&[1u8; 4096]));
        let blocked = more.await;
        assert!(blocked.is_err(), "the pipe is full again: the write waits, not failed");
        assert!(!w.is_cut());
        take(&mut client, 8192).await;
        w.write_all(&[1u8; 4096]).await.expect("the client reads again: the write goes through");
        assert!(!w.is_cut());
    }

    /// A client that stops reading is cut once the timeout has passed since its last byte was
    /// taken, and not before: the blocked write fails with `TimedOut`, later writes fail too.
    #[tokio::test(start_paused = true)]
    async fn a_client_that_stops_reading_is_cut_after_the_timeout() {
        let (mut w, client) = pipe();
        fill(&mut w).await;
        let blocked_at = Instant::now();
        let before = tokio::time::timeout(TIMEOUT - Duration::from_millis(1), w.write_all(&[1u8; 4096])).await;
        assert!(before.is_err(), "still waiting just before the timeout");
        assert!(!w.is_cut());
        let e = w.write_all(&[1u8; 4096]).await.unwrap_err();
        assert_eq!(e.kind(), io::ErrorKind::TimedOut);
        assert_eq!(e.get_ref().and_then(|s| s.downcast_ref::<Stalled>()), Some(&Stalled(TIMEOUT)));
        assert!(blocked_at.elapsed() >= TIMEOUT);
        assert!(w.is_cut());
        assert_eq!(w.write(&[1]).await.unwrap_err().kind(), io::ErrorKind::TimedOut);
        drop(client);
    }
}
