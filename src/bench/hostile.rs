//! The hostile clients of `mpiflow bench soak`: each misbehaves as an
//! attacker would, from a loopback address of its own ([`attacker`]: 127.0.0.2 and up, so that
//! many addresses can be tried on one machine), mostly below gRPC on raw HTTP/2 (the `h2` crate).

use std::net::Ipv4Addr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::Duration;

use prost::Message;
use tokio::time::timeout_at;

use super::clients::{all_fields, Shared};
use crate::service::pb;

/// The most attacker addresses: 127.0.0.2 .. 127.0.0.251.
pub const MAX_ATTACKER_ADDRESSES: usize = 250;

/// The loopback address of hostile client `k` when the attackers spread over `n` addresses
/// (127.0.0.2 .. 127.0.0.(1 + n), round-robin): a peer of its own, as a different machine would
/// be.
pub fn attacker(k: usize, n: usize) -> Ipv4Addr {
    let n = n.clamp(1, MAX_ATTACKER_ADDRESSES);
    Ipv4Addr::new(127, 0, 0, 2 + (k % n) as u8)
}

/// One gRPC message frame (uncompressed) around `body`.
fn grpc_frame(body: &[u8]) -> bytes::Bytes {
    let mut frame = Vec::with_capacity(body.len() + 5);
    frame.push(0);
    frame.extend_from_slice(&(body.len() as u32).to_be_bytes());
    frame.extend_from_slice(body);
    bytes::Bytes::from(frame)
}

/// One call of `path` with the message `frame` on a raw connection; returns when the reply's
/// headers come (its body is never read).
async fn raw_call(
    send: &h2::client::SendRequest<bytes::Bytes>,
    path: &str,
    frame: bytes::Bytes,
) -> Result<http::Response<h2::RecvStream>, h2::Error> {
    let mut ready = send.clone().ready().await?;
    let req = http::Request::post(format!("http://localhost{path}"))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(())
        .expect("a valid request");
    let (response, mut stream) = ready.send_request(req, false)?;
    stream.send_data(frame, true)?;
    response.await
}

/// GetSample calls of `frames`-frame samples one after another from `from`, each read whole.
pub(super) async fn unary_client(
    addr: String,
    seed: u64,
    frames: u32,
    from: Ipv4Addr,
    until: tokio::time::Instant,
    sh: Arc<Shared>,
) {
    let Some(mut client) = sh.connect("unary", &addr, Some(from.into()), until).await else { return };
    let mut index = 0u64;
    while tokio::time::Instant::now() < until {
        index += 1;
        match timeout_at(until, client.get_sample(pb::SampleSpec { seed, frames, ..Default::default() }.sample(index)))
            .await
        {
            Ok(Ok(_)) => {
                sh.unary_samples.fetch_add(1, Ordering::Relaxed);
            }
            Ok(Err(status)) => {
                // refused (its peer's call bound), or its connection refused (its peer's
                // connection bound): the flood's own doing, expected; a pause before the next try
                sh.error("unary", &format!("{:?}", status.code()), status.message(), true);
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(_) => return,
        }
    }
}

/// A raw HTTP/2 connection from `from` with a `window`-byte stream window.
async fn raw_h2(
    addr: &str,
    from: Ipv4Addr,
    window: u32,
) -> Result<(h2::client::SendRequest<bytes::Bytes>, tokio::task::JoinHandle<Result<(), h2::Error>>), String> {
    let to: std::net::SocketAddr = addr.parse().map_err(|e| format!("{addr}: {e}"))?;
    let sock = tokio::net::TcpSocket::new_v4().map_err(|e| e.to_string())?;
    sock.bind((from, 0).into()).map_err(|e| e.to_string())?;
    let tcp = sock.connect(to).await.map_err(|e| e.to_string())?;
    let (send, conn) =
        h2::client::Builder::new().initial_window_size(window).handshake(tcp).await.map_err(|e| e.to_string())?;
    Ok((send, tokio::spawn(conn)))
}

/// [`raw_h2`] until it connects (a refusal counted as `kind`'s expected error, then tried again
/// 200 ms later); None once `until` has passed.
async fn raw_h2_until(
    kind: &str,
    addr: &str,
    from: Ipv4Addr,
    window: u32,
    until: tokio::time::Instant,
    sh: &Shared,
) -> Option<(h2::client::SendRequest<bytes::Bytes>, tokio::task::JoinHandle<Result<(), h2::Error>>)> {
    loop {
        match timeout_at(until, raw_h2(addr, from, window)).await {
            Ok(Ok(c)) => return Some(c),
            Ok(Err(e)) => {
                sh.error(kind, "connect", &e, true);
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(_) => return None,
        }
    }
}

/// Keeps `calls` GetSample calls of `frames`-frame samples with every field open on a raw
/// connection from `from` with a one-byte window, never reading them; reconnects when the server
/// closes the connection.
pub(super) async fn unread_client(
    addr: String,
    calls: usize,
    frames: u32,
    from: Ipv4Addr,
    until: tokio::time::Instant,
    sh: Arc<Shared>,
) {
    let body = pb::SampleSpec { fields: all_fields(), frames, ..Default::default() }.sample(0).encode_to_vec();
    let frame = grpc_frame(&body);
    while tokio::time::Instant::now() < until {
        let Some((send, conn)) = raw_h2_until("unread", &addr, from, 1, until, &sh).await else { return };
        let mut held = Vec::new();
        for _ in 0..calls {
            let call = raw_call(&send, "/mpiflow.v1.MpiFlow/GetSample", frame.clone());
            match timeout_at(until, call).await {
                Ok(Ok(r)) => {
                    sh.unread_calls.fetch_add(1, Ordering::Relaxed);
                    held.push(r);
                }
                Ok(Err(_)) | Err(_) => break,
            }
        }
        // hold them unread until the server closes the connection (or the run ends)
        let _ = timeout_at(until, conn).await;
        drop(held);
    }
}

/// A raw HTTP/2 connection from `from` that opens no call; counts the server's closes and
/// reconnects.
pub(super) async fn idle_client(addr: String, from: Ipv4Addr, until: tokio::time::Instant, sh: Arc<Shared>) {
    while tokio::time::Instant::now() < until {
        match timeout_at(until, raw_h2(&addr, from, 1 << 16)).await {
            Ok(Ok((_send, conn))) => {
                let opened = tokio::time::Instant::now();
                if timeout_at(until, conn).await.is_ok() {
                    // closed at once: refused by the peer's connection bound; later: idle
                    if opened.elapsed() > Duration::from_millis(500) {
                        sh.idle_closed.fetch_add(1, Ordering::Relaxed);
                    }
                    tokio::time::sleep(Duration::from_secs(1)).await;
                }
            }
            // refused (the peer's connection bound): try again a second later
            Ok(Err(_)) => tokio::time::sleep(Duration::from_secs(1)).await,
            Err(_) => return,
        }
    }
}

/// A raw HTTP/2 connection from `from` holding a health Watch open (no token needed); reconnects
/// when the server closes it, counting the closes.
pub(super) async fn watch_client(addr: String, from: Ipv4Addr, until: tokio::time::Instant, sh: Arc<Shared>) {
    while tokio::time::Instant::now() < until {
        let (send, conn) = match timeout_at(until, raw_h2(&addr, from, 1 << 16)).await {
            Ok(Ok(c)) => c,
            Ok(Err(_)) => {
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
            Err(_) => return,
        };
        let watch = timeout_at(until, raw_call(&send, "/grpc.health.v1.Health/Watch", grpc_frame(&[]))).await;
        if let Ok(Ok(_reply)) = watch {
            sh.watches.fetch_add(1, Ordering::Relaxed);
            if timeout_at(until, conn).await.is_ok() {
                sh.idle_closed.fetch_add(1, Ordering::Relaxed);
            }
        }
        tokio::time::sleep_until((tokio::time::Instant::now() + Duration::from_secs(1)).min(until)).await;
    }
}

/// `streams` StreamSamples calls of `frames`-frame samples with every field on one raw
/// connection from `from` that grants no HTTP/2 window (the server can send it nothing, and its
/// socket never blocks); reopens them when the server closes the connection.
pub(super) async fn window_client(
    addr: String,
    streams: usize,
    frames: u32,
    from: Ipv4Addr,
    until: tokio::time::Instant,
    sh: Arc<Shared>,
) {
    let body = pb::StreamRequest {
        prefetch: 64,
        ..pb::SampleSpec { fields: all_fields(), frames, ..Default::default() }.stream()
    }
    .encode_to_vec();
    let frame = grpc_frame(&body);
    while tokio::time::Instant::now() < until {
        let Some((send, conn)) = raw_h2_until("window", &addr, from, 0, until, &sh).await else { return };
        let mut held = Vec::new();
        for _ in 0..streams {
            match timeout_at(until, raw_call(&send, "/mpiflow.v1.MpiFlow/StreamSamples", frame.clone())).await {
                Ok(Ok(r)) => {
                    // a trailers-only reply is a refusal (the client's share of the stream slots)
                    if r.headers().contains_key("grpc-status") {
                        sh.error("window", "ResourceExhausted", "refused", true);
                    } else {
                        sh.window_streams.fetch_add(1, Ordering::Relaxed);
                    }
                    held.push(r);
                }
                Ok(Err(_)) | Err(_) => break,
            }
        }
        let _ = timeout_at(until, conn).await;
        drop(held);
        tokio::time::sleep_until((tokio::time::Instant::now() + Duration::from_millis(200)).min(until)).await;
    }
}
