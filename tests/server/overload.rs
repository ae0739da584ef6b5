//! No client can take the server: each way one client could hold the machine, tried on a real
//! server over loopback with real clients (tonic, and raw HTTP/2 through the `h2` crate where a
//! client must misbehave below gRPC: never read a reply, hold idle connections, send a malformed
//! message, stop reading its socket). Samples are 64x48 to stay fast.

use std::time::Duration;

use bytes::Bytes;
use mpiflow::service::client::client_for;
use mpiflow::service::pb;
use mpiflow::service::pb::mpi_flow_client::MpiFlowClient;
use mpiflow::service::{start, RunningServer, ServiceConfig};
use prost::Message;
use tonic::transport::{Channel, Endpoint};
use tonic::Code;

const SIZE: &str = "64x48";

fn config() -> ServiceConfig {
    ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some(SIZE.into()),
        workers: 2,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    }
}

async fn server(c: ServiceConfig) -> RunningServer {
    start(c).await.expect("server starts")
}

async fn client(addr: impl ToString) -> MpiFlowClient<Channel> {
    let ch = Endpoint::from_shared(format!("http://{}", addr.to_string())).unwrap().connect().await.expect("connects");
    client_for(ch)
}

/// An honest trainer's stream of 16 samples with every field in `fields` (seed 5): every sample
/// arrives, in order (each message within 60 s: the deadline only turns a hang into a failure).
async fn honest_stream_gets_every_sample(honest: &mut MpiFlowClient<Channel>, fields: &[i32]) {
    let req = pb::StreamRequest {
        count: 16,
        ..pb::SampleSpec { seed: 5, fields: fields.to_vec(), ..Default::default() }.stream()
    };
    let mut stream = honest.stream_samples(req).await.unwrap().into_inner();
    let mut got = Vec::new();
    while let Some(b) = tokio::time::timeout(Duration::from_secs(60), stream.message()).await.expect("served").unwrap()
    {
        got.extend(b.samples.iter().map(|x| x.index));
    }
    assert_eq!(got, (0..16).collect::<Vec<_>>());
}

/// Waits until `done()` holds (an observable state), checking it every few milliseconds; the
/// deadline only turns a hang into a failure.
async fn until(what: &str, mut done: impl FnMut() -> bool) {
    let wait = async {
        while !done() {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    };
    tokio::time::timeout(Duration::from_secs(120), wait).await.unwrap_or_else(|_| panic!("never: {what}"));
}

/// A raw HTTP/2 connection with `window` bytes of stream window: its replies are read only when
/// the test reads them.
async fn h2_connection(
    addr: std::net::SocketAddr,
    window: u32,
) -> (h2::client::SendRequest<Bytes>, tokio::task::JoinHandle<Result<(), h2::Error>>) {
    h2_connection_from([127, 0, 0, 1], addr, window).await
}

/// [`h2_connection`] from the loopback address `from` (127.x.y.z: a client of its own).
async fn h2_connection_from(
    from: [u8; 4],
    addr: std::net::SocketAddr,
    window: u32,
) -> (h2::client::SendRequest<Bytes>, tokio::task::JoinHandle<Result<(), h2::Error>>) {
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind((std::net::Ipv4Addr::from(from), 0).into()).expect("binds a loopback address");
    let tcp = socket.connect(addr).await.unwrap();
    let (send, conn) = h2::client::Builder::new().initial_window_size(window).handshake(tcp).await.expect("HTTP/2");
    (send, tokio::spawn(conn))
}

/// One gRPC message frame (uncompressed) around `body`.
fn grpc_frame(body: &[u8]) -> Bytes {
    let mut f = Vec::with_capacity(body.len() + 5);
    f.push(0);
    f.extend_from_slice(&(body.len() as u32).to_be_bytes());
    f.extend_from_slice(body);
    Bytes::from(f)
}

/// Sends one call of `method` with `body` as its message and waits for the reply's headers
/// (the body is left unread).
async fn raw_call(
    send: &mut h2::client::SendRequest<Bytes>,
    method: &str,
    body: &[u8],
) -> http::Response<h2::RecvStream> {
    raw_call_with(send, method, body, &[]).await
}

/// [`raw_call`] with more request headers.
async fn raw_call_with(
    send: &mut h2::client::SendRequest<Bytes>,
    method: &str,
    body: &[u8],
    headers: &[(&str, &str)],
) -> http::Response<h2::RecvStream> {
    raw_request(send, &format!("/mpiflow.v1.MpiFlow/{method}"), body, headers).await
}

/// One call to `path` (any service's) with `body` as its message and more request headers;
/// returns when the reply's headers come.
async fn raw_request(
    send: &mut h2::client::SendRequest<Bytes>,
    path: &str,
    body: &[u8],
    headers: &[(&str, &str)],
) -> http::Response<h2::RecvStream> {
    try_raw_request(send, path, body, headers).await.expect("reply headers")
}

/// [`raw_request`], or the error of a connection that failed first.
async fn try_raw_request(
    send: &mut h2::client::SendRequest<Bytes>,
    path: &str,
    body: &[u8],
    headers: &[(&str, &str)],
) -> Result<http::Response<h2::RecvStream>, h2::Error> {
    let mut req = http::Request::post(format!("http://localhost{path}"))
        .header("content-type", "application/grpc")
        .header("te", "trailers");
    for (k, v) in headers {
        req = req.header(*k, *v);
    }
    let req = req.body(()).unwrap();
    let mut ready = send.clone().ready().await?;
    let (response, mut stream) = ready.send_request(req, false)?;
    // a call refused on its headers alone (an unsupported encoding) may be answered and its
    // stream closed before the body goes out: the reply below is what the test reads, so a body
    // the server does not take is not an error here
    let _ = stream.send_data(grpc_frame(body), true);
    *send = ready;
    response.await
}

/// The grpc-status of a trailers-only reply.
fn header_status(r: &http::Response<h2::RecvStream>) -> Option<i32> {
    r.headers().get("grpc-status")?.to_str().ok()?.parse().ok()
}

/// A request whose largest sample cannot be sent or held is refused before any work, with
/// RESOURCE_EXHAUSTED naming what makes it large, on every sample RPC; an augmentation crop over
/// the pixel limit is refused by name; the server goes on serving.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn requests_whose_largest_sample_does_not_fit_are_refused_before_any_work() {
    let s = server(config()).await;
    let mut c = client(s.addr).await;
    let huge = r#"{"preset":"raft-chairs","crop":[8192,8192]}"#;
    let e = c
        .get_sample(pb::SampleSpec { augment: huge.into(), ..Default::default() }.sample(0))
        .await
        .map(|_| ())
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(e.message().starts_with("augment.crop: 8192x8192") && e.message().contains("max_image_pixels"), "{e:?}");
    s.shutdown(Duration::from_millis(500)).await;

    // 640x480 and 48 MiB of budget: a pair of the default fields (4.6 MB sent, 44 MB while it is
    // made) fits, a clip of eight frames with every field (54 MB) does not
    let s =
        server(ServiceConfig { size: Some("640x480".into()), max_buffered_mb: 48, max_sample_work: 64, ..config() })
            .await;
    let mut c = client(s.addr).await;
    let fields: Vec<i32> = (1..=13).collect();
    let check = |e: tonic::Status| {
        assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
        let m = e.message();
        assert!(m.starts_with("sample too large") && m.contains("max_buffered_mb") && m.contains("flows"), "{m}");
    };
    let r = pb::SampleSpec { fields: fields.clone(), frames: 8, ..Default::default() }.stream();
    check(c.stream_samples(r).await.map(|_| ()).unwrap_err());
    let r = pb::SampleSpec { fields: fields.clone(), frames: 8, ..Default::default() }.sample(0);
    check(c.get_sample(r).await.map(|_| ()).unwrap_err());
    let r = pb::SampleSpec { fields, frames: 8, ..Default::default() }.samples(vec![0]);
    check(c.get_samples(r).await.map(|_| ()).unwrap_err());
    // and with lanczos3 its work is over max_sample_work (88 million units; a pair of bspline3 is
    // 9.8 million)
    let valid = vec![pb::Field::Valid as i32];
    let lanczos = pb::SampleSpec { fields: valid, frames: 8, resample: "lanczos3".into(), ..Default::default() };
    let e = c.get_sample(lanczos.sample(0)).await.map(|_| ()).unwrap_err();
    assert!(e.code() == Code::ResourceExhausted && e.message().contains("max_sample_work = 64;"), "{e:?}");
    // nothing was started for them (the warm-up sample's stream aside, gone once it is made)
    until("the warm-up sample is made", || s.state.is_serving()).await;
    assert_eq!(s.state.scheduler.stats().streams, 0);
    let ok = c.get_sample(pb::SampleRequest { index: 3, ..Default::default() }).await.unwrap().into_inner();
    assert_eq!((ok.width, ok.height), (640, 480));
    s.shutdown(Duration::from_millis(500)).await;
}

/// 2^64 - 1 is the end of the index space, never a sample: GetSamples refuses it like GetSample.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_end_of_the_index_space_is_never_served() {
    let s = server(config()).await;
    let mut c = client(s.addr).await;
    let e = c
        .get_samples(pb::SamplesRequest { indices: vec![5, u64::MAX], ..Default::default() })
        .await
        .map(|_| ())
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    assert!(e.message().starts_with("indices: [1] = 2^64 - 1"), "{e:?}");
    let e = c.get_sample(pb::SampleRequest { index: u64::MAX, ..Default::default() }).await.map(|_| ()).unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
    s.shutdown(Duration::from_millis(500)).await;
}

/// A request message that is not valid protobuf is the client's fault: INVALID_ARGUMENT on every
/// RPC (tonic itself says INTERNAL, which the error table keeps for samples that fail).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_request_messages_are_invalid_argument() {
    let s = server(config()).await;
    let (mut send, _conn) = h2_connection(s.addr, 1 << 20).await;
    // field 1 says 5 bytes follow, and one does
    let truncated = [0x0A, 0x05, 0x41];
    for method in ["GetSample", "StreamSamples", "GetSamples", "GetInfo", "UploadSources"] {
        let r = raw_call(&mut send, method, &truncated).await;
        let code = match header_status(&r) {
            Some(c) => c,
            // a reply with a body (the upload reads its chunks in the handler): the trailers say it
            None => {
                let mut body = r.into_body();
                while let Some(d) = body.data().await {
                    let _ = d;
                }
                let t = body.trailers().await.unwrap().expect("trailers");
                t.get("grpc-status").unwrap().to_str().unwrap().parse().unwrap()
            }
        };
        assert_eq!(code, Code::InvalidArgument as i32, "{method}");
    }
    s.shutdown(Duration::from_millis(500)).await;
}

/// A request compressed with an encoding the server does not take gets the same trailers-only
/// reply on every RPC (UNIMPLEMENTED, naming the encoding, `grpc-accept-encoding: identity`): the
/// sample streams, answered by the service's own route, as the calls of tonic's generated service.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn compressed_requests_are_refused_alike_on_every_rpc() {
    let s = server(config()).await;
    let (mut send, _conn) = h2_connection(s.addr, 1 << 20).await;
    let mut replies = Vec::new();
    for method in ["GetSample", "StreamSamples", "GetSamples", "GetInfo", "UploadSources"] {
        let r = raw_call_with(&mut send, method, &[], &[("grpc-encoding", "gzip")]).await;
        assert_eq!(header_status(&r), Some(Code::Unimplemented as i32), "{method}");
        let h = |k: &str| r.headers().get(k).map(|v| v.to_str().unwrap().to_owned());
        let message = h("grpc-message").unwrap_or_default();
        assert!(message.contains("gzip"), "{method}: {message}");
        replies.push((method, message, h("grpc-accept-encoding")));
    }
    for (method, message, accept) in &replies[1..] {
        assert_eq!((message, accept), (&replies[0].1, &replies[0].2), "{method} against GetSample");
    }
    s.shutdown(Duration::from_millis(500)).await;
}

/// GetSample and GetSamples calls are bounded (`max_random_access_calls`, unsent replies
/// included): over it a call is RESOURCE_EXHAUSTED at once, a stream keeps getting samples, and a
/// slot comes back when a held reply goes away.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn random_access_calls_over_the_limit_are_refused() {
    let s = server(ServiceConfig { max_random_access_calls: 2, ..config() }).await;
    // two replies nobody reads (a one-byte window): each holds its slot
    let (mut send, conn) = h2_connection(s.addr, 1).await;
    let req = pb::SampleSpec { fields: (1..=9).collect(), ..Default::default() }.sample(1).encode_to_vec();
    let held = vec![raw_call(&mut send, "GetSample", &req).await, raw_call(&mut send, "GetSample", &req).await];
    assert!(held.iter().all(|r| header_status(r).is_none()), "both answered with a sample");
    let mut c = client(s.addr).await;
    let e = c.get_sample(pb::SampleRequest::default()).await.map(|_| ()).unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("max_random_access_calls"), "{e:?}");
    let e = c.get_samples(pb::SamplesRequest { indices: vec![0], ..Default::default() }).await.map(|_| ()).unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    // streams are not affected
    let mut st = c.stream_samples(pb::StreamRequest { count: 5, ..Default::default() }).await.unwrap().into_inner();
    let mut n = 0;
    while let Some(b) = st.message().await.unwrap() {
        n += b.samples.len();
    }
    assert_eq!(n, 5);
    // the unread replies go: their slots come back
    drop((held, send));
    conn.abort();
    let mut got = None;
    until("a slot comes back", || s.state.scheduler.stats().streams == 0).await;
    for _ in 0..100 {
        match c.get_sample(pb::SampleRequest::default()).await {
            Ok(r) => {
                got = Some(r.into_inner());
                break;
            }
            Err(e) => assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}"),
        }
        tokio::task::yield_now().await;
    }
    assert!(got.is_some(), "a GetSample is served again");
    s.shutdown(Duration::from_millis(500)).await;
}

/// A unary reply the client does not read stays counted in the byte budget until it goes, not
/// only until it is handed to the transport (where it would sit uncounted).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unread_unary_replies_count_in_the_byte_budget() {
    let s = server(config()).await;
    let all: Vec<i32> = (1..=9).collect();
    let mut c = client(s.addr).await;
    let one = c.get_sample(pb::SampleSpec { fields: all.clone(), ..Default::default() }.sample(0)).await.unwrap();
    let sample = one.into_inner().encoded_len() as u64;
    until("the read reply is released", || s.state.scheduler.stats().buffered == 0).await;
    let (mut send, conn) = h2_connection(s.addr, 1).await;
    let mut held = Vec::new();
    for index in 0..3 {
        let req = pb::SampleSpec { fields: all.clone(), ..Default::default() }.sample(index).encode_to_vec();
        held.push(raw_call(&mut send, "GetSample", &req).await);
    }
    let st = s.state.scheduler.stats();
    assert!(st.buffered >= 3 * sample - 3 * 64, "three unread replies of ~{sample} bytes are held: {st:?}");
    assert_eq!(st.streams, 3, "{st:?}");
    drop((held, send));
    conn.abort();
    until("nothing is held once the client is gone", || {
        let st = s.state.scheduler.stats();
        st.buffered == 0 && st.streams == 0
    })
    .await;
    s.shutdown(Duration::from_millis(500)).await;
}

/// Stalled streams with large batches hold their share of the budget plus one message, not a
/// batch in the transport and another being filled: a batch is cut short at the share.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_batched_streams_stay_within_their_share() {
    const MIB: u64 = 1 << 20;
    let s = server(ServiceConfig { max_buffered_mb: 1, max_prefetch: 64, ..config() }).await;
    let all: Vec<i32> = (1..=9).collect();
    let mut c = client(s.addr).await;
    let one = c.get_sample(pb::SampleSpec { fields: all.clone(), ..Default::default() }.sample(0)).await.unwrap();
    let sample = one.into_inner().encoded_len() as u64;
    assert!(64 * sample > 4 * MIB, "a batch of 64 is several budgets: {sample}");
    let mut stalled = Vec::new();
    for seed in 1..=4u64 {
        let (mut send, conn) = h2_connection(s.addr, 1).await;
        let req = pb::StreamRequest {
            batch_size: 64,
            prefetch: 64,
            ..pb::SampleSpec { seed, fields: all.clone(), ..Default::default() }.stream()
        };
        let r = raw_call(&mut send, "StreamSamples", &req.encode_to_vec()).await;
        stalled.push((r, send, conn));
    }
    until("the stalled streams settle", || {
        let st = s.state.scheduler.stats();
        st.in_flight == 0 && st.eligible == 0 && st.per_stream.len() == 4
    })
    .await;
    let st = s.state.scheduler.stats();
    // no stream holds a batch of 64 (5 MB): what a stream sent was cut at its share then, and
    // in all the budget holds, samples being made included
    for held in &st.held {
        assert!(*held <= MIB, "a stream holds at most the budget: {st:?}");
    }
    assert!(st.max_buffered_seen <= MIB, "{st:?}");
    for (_, _, conn) in &stalled {
        conn.abort();
    }
    drop(stalled);
    until("every stream is closed", || s.state.scheduler.stats().streams == 0).await;
    assert_eq!(s.state.scheduler.stats().buffered, 0);
    s.shutdown(Duration::from_millis(500)).await;
}

/// One peer holds at most `max_connections_per_peer` connections, and a slot comes back when one
/// closes; a connection with no call open is closed after the idle timeout even though it
/// answers every ping, while one with a call open (a health watch) stays and serves more calls.
/// The bound is tried with connections that are never idle, so no timer races the test.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_connections_are_closed_and_each_peer_is_bounded() {
    let s = server(ServiceConfig { idle_connection_timeout_s: 1.0, max_connections_per_peer: 3, ..config() }).await;
    // three connections, each with a health watch open: never idle
    let mut watches = Vec::new();
    for _ in 0..3 {
        let (mut send, conn) = h2_connection(s.addr, 1 << 20).await;
        let watch = raw_request(&mut send, "/grpc.health.v1.Health/Watch", &[], &[]).await;
        assert_eq!(header_status(&watch), None, "the watch is answered with a stream");
        watches.push((send, conn, watch));
    }
    // the peer has 3 connections: a fourth is closed as it arrives
    assert!(refused_connection(s.addr).await, "a connection over max_connections_per_peer is closed");
    // one goes: its slot comes back (each refused probe is closed at once)
    let (send, conn, watch) = watches.pop().unwrap();
    drop((send, watch));
    conn.abort();
    let back = async { while refused_connection(s.addr).await {} };
    tokio::time::timeout(Duration::from_secs(120), back).await.expect("a slot comes back");
    // a connection that opens no call is closed by the server (its connection task ends)
    let (_idle, idle_conn) = h2_connection(s.addr, 1 << 20).await;
    let closed = tokio::time::timeout(Duration::from_secs(120), idle_conn).await;
    assert!(closed.is_ok(), "an idle connection is closed");
    // the watches, older than the idle one, are still open: their connections take a call
    for (send, conn, _watch) in &mut watches {
        assert!(!conn.is_finished(), "a connection with a watch open stays");
        let info = raw_call(send, "GetInfo", &[]).await;
        assert_eq!(header_status(&info), None, "GetInfo is answered on the watch's connection");
        let mut body = info.into_body();
        let first = body.data().await.expect("a GetInfo reply").expect("read");
        assert!(first.len() > 5, "a GetInfo message");
    }
    // a new client is served
    let mut c = client(s.addr).await;
    assert!(c.get_info(pb::InfoRequest {}).await.is_ok());
    s.shutdown(Duration::from_millis(500)).await;
}

/// Connects and makes a GetInfo call over raw HTTP/2; true when the server closed the connection
/// instead of answering.
async fn refused_connection(addr: std::net::SocketAddr) -> bool {
    let tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    let Ok((send, conn)) = h2::client::handshake(tcp).await else { return true };
    let conn = tokio::spawn(conn);
    let call = async {
        let mut ready = send.ready().await?;
        let req = http::Request::post("http://localhost/mpiflow.v1.MpiFlow/GetInfo")
            .header("content-type", "application/grpc")
            .header("te", "trailers")
            .body(())
            .unwrap();
        let (response, mut stream) = ready.send_request(req, false)?;
        stream.send_data(grpc_frame(&[]), true)?;
        response.await
    };
    let r = tokio::time::timeout(Duration::from_secs(30), call).await.expect("an answer or a close");
    conn.abort();
    r.is_err()
}

/// A client that stops reading its socket loses its connection after `stall_timeout_s`: its
/// stream ends and the stream slot comes back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_is_cut_after_the_stall_timeout() {
    let s = server(ServiceConfig { stall_timeout_s: 1.0, max_streams: 1, ..config() }).await;
    let tcp = Frozen::new(tokio::net::TcpStream::connect(s.addr).await.unwrap());
    let freeze = tcp.switch.clone();
    let (send, conn) = h2::client::Builder::new()
        .initial_window_size(i32::MAX as u32)
        .initial_connection_window_size(i32::MAX as u32)
        .handshake(tcp)
        .await
        .unwrap();
    let conn = tokio::spawn(conn);
    let mut send = send;
    let all: Vec<i32> = (1..=9).collect();
    let req = pb::SampleSpec { fields: all, ..Default::default() }.stream().encode_to_vec();
    let r = raw_call(&mut send, "StreamSamples", &req).await;
    assert!(header_status(&r).is_none(), "the stream opened");
    // the client stops reading: the server fills the socket, then waits
    freeze.store(true, std::sync::atomic::Ordering::SeqCst);
    until("the stalled stream is ended", || s.state.active_streams() == 0).await;
    // its slot (max_streams = 1) serves another client
    let mut c = client(s.addr).await;
    let mut st = c.stream_samples(pb::StreamRequest { count: 2, ..Default::default() }).await.unwrap().into_inner();
    assert_eq!(st.message().await.unwrap().unwrap().samples.len(), 1);
    conn.abort();
    s.shutdown(Duration::from_millis(500)).await;
}

/// A socket whose reads stop (stay pending) once its switch is set: a client that stops reading.
struct Frozen {
    inner: tokio::net::TcpStream,
    switch: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl Frozen {
    fn new(inner: tokio::net::TcpStream) -> Self {
        Self { inner, switch: Default::default() }
    }
}

impl tokio::io::AsyncRead for Frozen {
    fn poll_read(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &mut tokio::io::ReadBuf<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        if self.switch.load(std::sync::atomic::Ordering::SeqCst) {
            return std::task::Poll::Pending;
        }
        std::pin::Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl tokio::io::AsyncWrite for Frozen {
    fn poll_write(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
        buf: &[u8],
    ) -> std::task::Poll<std::io::Result<usize>> {
        std::pin::Pin::new(&mut self.inner).poll_write(cx, buf)
    }
    fn poll_flush(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.inner).poll_flush(cx)
    }
    fn poll_shutdown(
        mut self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<std::io::Result<()>> {
        std::pin::Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// Unread GetSample replies from many addresses (a client each, as behind a NAT pool) hold at
/// most the byte budget, samples being made included, however many addresses there are; an
/// honest stream that needs the room gets it (the connections that hold replies they do not
/// read are closed once their replies have waited `UNREAD_GRACE`) and receives every sample in
/// order; newcomers are served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unread_replies_from_many_addresses_stay_within_the_budget() {
    const MIB: u64 = 1 << 20;
    let s = server(ServiceConfig { max_buffered_mb: 1, ..config() }).await;
    let all: Vec<i32> = (1..=9).collect();
    let mut honest = client(s.addr).await;
    let one = honest.get_sample(pb::SampleSpec { fields: all.clone(), ..Default::default() }.sample(0)).await.unwrap();
    let sample = one.into_inner().encoded_len() as u64;
    assert!(32 * sample > 2 * MIB, "the attackers ask for twice the budget: {sample}");
    // 16 addresses, 2 unread calls each (every call waits for its reply's headers, which come
    // once the sample is made: the calls beyond the budget are admitted and wait for room)
    let (attackers, pending) = unread_attackers(s.addr, 1, 0, &all).await;
    // a call that waits for room while its peer holds less than its share has the holders of
    // unread replies closed: the attackers close each other's connections
    let cut = |m: String| {
        m.lines().find_map(|l| l.strip_prefix("mpiflow_holders_cut_total ")).and_then(|v| v.trim().parse::<f64>().ok())
    };
    until("the attackers fill the budget", || cut(s.state.metrics.render()).unwrap_or(0.0) >= 1.0).await;
    // the honest stream gets every sample, in order
    honest_stream_gets_every_sample(&mut honest, &all).await;
    let st = s.state.scheduler.stats();
    assert!(st.max_buffered_seen <= MIB, "the budget held: {st:?}");
    // a newcomer is served
    let mut c = client(s.addr).await;
    assert!(c.get_info(pb::InfoRequest {}).await.is_ok());
    for (_, conn) in &attackers {
        conn.abort();
    }
    drop(attackers);
    for p in pending {
        p.abort();
    }
    until("every stream is closed", || s.state.scheduler.stats().streams == 0).await;
    s.shutdown(Duration::from_millis(500)).await;
}

/// Health watches and connections with no call open cannot keep a newcomer out: with
/// `max_connections` taken by them, a new client takes the place of one (from the peer with the
/// most connections), and is served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watches_and_quiet_connections_make_room_for_newcomers() {
    let s = server(ServiceConfig { max_connections: 4, idle_connection_timeout_s: 600.0, ..config() }).await;
    let mut watches = Vec::new();
    for a in 0..4u8 {
        let (mut send, conn) = h2_connection_from([127, 0, 2, 2 + a], s.addr, 1 << 20).await;
        let watch = raw_request(&mut send, "/grpc.health.v1.Health/Watch", &[], &[]).await;
        assert_eq!(header_status(&watch), None, "the watch is answered with a stream");
        watches.push((send, conn, watch));
    }
    for round in 0..3 {
        let mut c = client(s.addr).await;
        assert!(c.get_info(pb::InfoRequest {}).await.is_ok(), "newcomer {round} is served");
    }
    until("a watch made room", || watches.iter().any(|(_, conn, _)| conn.is_finished())).await;
    s.shutdown(Duration::from_millis(500)).await;
}

/// A Health/Check request's headers, its body to follow.
fn health_check_headers() -> http::Request<()> {
    http::Request::post("http://localhost/grpc.health.v1.Health/Check")
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(())
        .unwrap()
}

/// Opens a Health/Check call on `send` whose request never arrives whole: its headers, then
/// `prefix` (the start of the body) and nothing more.
async fn unfinished_check(
    send: &h2::client::SendRequest<Bytes>,
    prefix: &'static [u8],
) -> (h2::client::ResponseFuture, h2::SendStream<Bytes>) {
    let mut ready = send.clone().ready().await.expect("room for a call");
    let (response, mut stream) = ready.send_request(health_check_headers(), false).expect("the call opens");
    if !prefix.is_empty() {
        stream.send_data(Bytes::from_static(prefix), false).expect("the prefix goes out");
    }
    (response, stream)
}

/// Health/Check calls whose request never arrives whole (headers, then the gRPC prefix of a
/// 10-byte message and nothing more; or headers alone) fail at the request deadline
/// (`idle_connection_timeout_s`) with INVALID_ARGUMENT `malformed-request` naming it, instead of
/// holding their call for as long as the client likes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn calls_whose_request_never_arrives_fail_at_the_request_deadline() {
    let s = server(ServiceConfig { idle_connection_timeout_s: 1.0, ..config() }).await;
    let (send, _conn) = h2_connection_from([127, 0, 6, 2], s.addr, 1 << 20).await;
    for prefix in [&[0u8, 0, 0, 0, 10][..], &[][..]] {
        let (response, _stream) = unfinished_check(&send, prefix).await;
        // the guard only turns a call held for ever into a failure
        let response = tokio::time::timeout(Duration::from_secs(60), response)
            .await
            .expect("the call is answered, not held")
            .expect("reply headers");
        assert_eq!(header_status(&response), Some(Code::InvalidArgument as i32), "{prefix:?}: {response:?}");
        let status = tonic::Status::from_header_map(response.headers()).expect("a status");
        assert!(status.message().contains("did not arrive whole within 1 s"), "{prefix:?}: {status:?}");
        let reason = response.headers().get("mpiflow-reason").map(|v| v.to_str().unwrap().to_string());
        assert_eq!(reason.as_deref(), Some("malformed-request"), "{prefix:?}");
    }
    s.shutdown(Duration::from_millis(500)).await;
}

/// 512 Health/Check calls whose request never arrives whole (128 on each of 4 connections from 4
/// addresses, all of `max_connections`) do not keep newcomers out: such a call does not count as
/// open, so a newcomer takes the place of one of their connections and is served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unfinished_requests_do_not_keep_a_newcomer_out() {
    let s = server(ServiceConfig {
        max_connections: 4,
        max_calls_per_connection: 129,
        idle_connection_timeout_s: 600.0,
        ..config()
    })
    .await;
    let mut held = Vec::new();
    for a in 0..4u8 {
        let (mut send, conn) = h2_connection_from([127, 0, 7, 2 + a], s.addr, 1 << 20).await;
        let mut calls = Vec::new();
        for _ in 0..128 {
            calls.push(unfinished_check(&send, &[0, 0, 0, 0, 10]).await);
        }
        // a whole call after them on the same connection, answered: the server has taken the
        // unfinished calls' headers (HTTP/2 frames arrive in order) and dispatched them first
        let done = raw_request(&mut send, "/grpc.health.v1.Health/Check", &[], &[]).await;
        assert_eq!(header_status(&done), None, "the whole call is answered with a message");
        held.push((send, conn, calls));
    }
    for round in 0..3 {
        let mut c = client(s.addr).await;
        assert!(c.get_info(pb::InfoRequest {}).await.is_ok(), "newcomer {round} is served");
    }
    until("an unfinished call's connection made room", || held.iter().any(|(_, conn, _)| conn.is_finished())).await;
    s.shutdown(Duration::from_millis(500)).await;
}

/// A client that reads, however slowly, is never closed for room: while unread replies from many
/// addresses keep the budget short, a client that takes a few KiB of its reply every 100 ms
/// (well within `UNREAD_GRACE` each time) reads its whole reply and its OK status.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_reader_is_not_closed_for_room() {
    let s = server(ServiceConfig { max_buffered_mb: 1, ..config() }).await;
    let all: Vec<i32> = (1..=9).collect();
    // the slow reader's reply is made first
    let (mut send, slow_conn) = h2_connection_from([127, 0, 3, 1], s.addr, 4096).await;
    let req = pb::SampleSpec { fields: all.clone(), ..Default::default() }.sample(0).encode_to_vec();
    let reply = raw_call(&mut send, "GetSample", &req).await;
    // then unread calls from 16 addresses press for room
    let (attackers, pending) = unread_attackers(s.addr, 4, 1, &all).await;
    // read the reply a window at a time, a pause after each
    let mut body = reply.into_body();
    let mut bytes = 0usize;
    while let Some(chunk) = body.data().await {
        let chunk = chunk.expect("the slow reader's connection stays open");
        bytes += chunk.len();
        let _ = body.flow_control().release_capacity(chunk.len());
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let trailers = body.trailers().await.expect("trailers").expect("a status");
    assert_eq!(trailers.get("grpc-status").map(|v| v.to_str().unwrap()), Some("0"), "{trailers:?}");
    assert!(bytes > 16 * 4096, "a reply of {bytes} bytes was read in many pauses");
    assert!(!slow_conn.is_finished());
    for (_, conn) in &attackers {
        conn.abort();
    }
    for p in pending {
        p.abort();
    }
    s.shutdown(Duration::from_millis(500)).await;
}

/// 16 clients from 127.0.`net`.2 .. 127.0.`net`.17, each a raw connection with a one-byte window
/// and 2 GetSample calls of `fields` (indices from `first`) whose replies it keeps unread until
/// its task is aborted; the connections and the calls' tasks.
async fn unread_attackers(
    addr: std::net::SocketAddr,
    net: u8,
    first: u64,
    fields: &[i32],
) -> (
    Vec<(h2::client::SendRequest<Bytes>, tokio::task::JoinHandle<Result<(), h2::Error>>)>,
    Vec<tokio::task::JoinHandle<()>>,
) {
    let mut attackers = Vec::new();
    let mut pending = Vec::new();
    for a in 0..16u8 {
        let (send, conn) = h2_connection_from([127, 0, net, 2 + a], addr, 1).await;
        for index in 0..2u64 {
            let req = pb::SampleSpec { fields: fields.to_vec(), ..Default::default() }
                .sample(first + u64::from(a) * 2 + index);
            let mut send = send.clone();
            pending.push(tokio::spawn(async move {
                let path = "/mpiflow.v1.MpiFlow/GetSample";
                // a call whose connection is closed before its reply comes has nothing to keep
                let _reply = try_raw_request(&mut send, path, &req.encode_to_vec(), &[]).await;
                std::future::pending::<()>().await;
            }));
        }
        attackers.push((send, conn));
    }
    (attackers, pending)
}

/// With a token required, 512 connections that never authenticate (silent ones from 8 addresses,
/// and ones whose call was refused as UNAUTHENTICATED, kept open) fill `max_connections`; a
/// client holding the token is still served, each time on a new connection, and refused callers
/// make room for it like any connection with no call open.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unauthenticated_connections_do_not_keep_a_token_holder_out() {
    const TOKEN: &str = "t0ken-for-the-overload-test";
    let s = server(ServiceConfig {
        max_connections: 512,
        idle_connection_timeout_s: 600.0,
        auth_token: Some(TOKEN.into()),
        ..config()
    })
    .await;
    let info = pb::InfoRequest {}.encode_to_vec();
    let mut silent = Vec::new();
    let mut refused = Vec::new();
    for a in 0..8u8 {
        for k in 0..64 {
            let from = std::net::Ipv4Addr::new(127, 0, 5, 2 + a);
            if k < 8 {
                let (mut send, conn) = h2_connection_from(from.octets(), s.addr, 1 << 16).await;
                let reply = raw_request(&mut send, "/mpiflow.v1.MpiFlow/GetInfo", &info, &[]).await;
                assert_eq!(header_status(&reply), Some(16), "a call without the token is UNAUTHENTICATED");
                refused.push((send, conn));
            } else {
                let socket = tokio::net::TcpSocket::new_v4().unwrap();
                socket.bind((from, 0).into()).expect("binds a loopback address");
                // a plain socket, asked without waiting whether the server closed it
                let tcp = socket.connect(s.addr).await.expect("connects").into_std().unwrap();
                tcp.set_nonblocking(true).unwrap();
                silent.push(tcp);
            }
        }
    }
    let bearer = format!("Bearer {TOKEN}");
    // the token holder's connections stay open: each takes the place of one that never authenticated
    let mut holder = Vec::new();
    for round in 0..4u8 {
        let (mut send, conn) = h2_connection_from([127, 0, 0, 1], s.addr, 1 << 20).await;
        holder.push((send.clone(), conn));
        let reply = raw_request(&mut send, "/mpiflow.v1.MpiFlow/GetInfo", &info, &[("authorization", &bearer)]).await;
        assert_eq!(header_status(&reply), None, "round {round}: the token holder's call is answered");
        let mut body = reply.into_body();
        while let Some(chunk) = body.data().await {
            let chunk = chunk.expect("the token holder's reply arrives whole");
            let _ = body.flow_control().release_capacity(chunk.len());
        }
        let trailers = body.trailers().await.expect("trailers").expect("a status");
        assert_eq!(trailers.get("grpc-status").map(|v| v.to_str().unwrap()), Some("0"), "round {round}: {trailers:?}");
    }
    // the room was made by closing connections that never authenticated
    until("4 unauthenticated connections were closed for the token holder", || {
        let silent_closed = silent
            .iter()
            .filter(|t| {
                let mut r: &std::net::TcpStream = t;
                loop {
                    match std::io::Read::read(&mut r, &mut [0u8; 256]) {
                        Ok(0) => return true, // closed by the server
                        Ok(_) => continue,    // what the server sent before
                        Err(e) => return e.kind() != std::io::ErrorKind::WouldBlock,
                    }
                }
            })
            .count();
        silent_closed + refused.iter().filter(|(_, conn)| conn.is_finished()).count() >= 4
    })
    .await;
    drop(silent);
    drop(refused);
    s.shutdown(Duration::from_millis(500)).await;
}

/// Holders that answer nothing but pings keep nothing: 16 clients from 16 addresses, each a raw
/// connection with a 16 KiB window and 2 GetSample calls of every field (twice the budget in
/// all), never grant window and send a PING every 100 ms, answered each time. PING ACKs are not
/// data taken, so when an honest stream needs the room their connections are closed (once a
/// reply has waited `UNREAD_GRACE` with no DATA taken), and the stream gets every sample.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pings_alone_do_not_keep_a_holder_from_being_cut() {
    const MIB: u64 = 1 << 20;
    let s = server(ServiceConfig { max_buffered_mb: 1, ..config() }).await;
    let all: Vec<i32> = (1..=9).collect();
    let pongs = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let mut holders = Vec::new();
    let mut pending = Vec::new();
    for a in 0..16u8 {
        let socket = tokio::net::TcpSocket::new_v4().unwrap();
        socket.bind((std::net::Ipv4Addr::new(127, 0, 8, 2 + a), 0).into()).expect("binds a loopback address");
        let tcp = socket.connect(s.addr).await.unwrap();
        let (send, mut conn) = h2::client::Builder::new().initial_window_size(16 << 10).handshake(tcp).await.unwrap();
        let mut ping_pong = conn.ping_pong().expect("the connection's pings");
        let conn = tokio::spawn(conn);
        let counted = pongs.clone();
        pending.push(tokio::spawn(async move {
            let mut every = tokio::time::interval(Duration::from_millis(100));
            loop {
                every.tick().await;
                if ping_pong.ping(h2::Ping::opaque()).await.is_err() {
                    return; // the connection is closed
                }
                counted.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            }
        }));
        for index in 0..2u64 {
            let req = pb::SampleSpec { fields: all.clone(), ..Default::default() }.sample(u64::from(a) * 2 + index);
            let mut send = send.clone();
            pending.push(tokio::spawn(async move {
                let path = "/mpiflow.v1.MpiFlow/GetSample";
                let _reply = try_raw_request(&mut send, path, &req.encode_to_vec(), &[]).await;
                std::future::pending::<()>().await;
            }));
        }
        holders.push((send, conn));
    }
    // the holders' pings are answered while they hold their replies
    until("every holder's pings are answered", || pongs.load(std::sync::atomic::Ordering::SeqCst) >= 64).await;
    let mut honest = client(s.addr).await;
    honest_stream_gets_every_sample(&mut honest, &all).await;
    // the room came from pinging holders' connections, closed by the server
    until("a pinging holder's connection is closed", || holders.iter().any(|(_, conn)| conn.is_finished())).await;
    let cut = s
        .state
        .metrics
        .render()
        .lines()
        .find_map(|l| l.strip_prefix("mpiflow_holders_cut_total ").and_then(|v| v.trim().parse::<f64>().ok()));
    assert!(cut.unwrap_or(0.0) >= 1.0, "holders were cut: {cut:?}");
    assert!(s.state.scheduler.stats().max_buffered_seen <= MIB, "the budget held");
    for (_, conn) in &holders {
        conn.abort();
    }
    for p in pending {
        p.abort();
    }
    s.shutdown(Duration::from_millis(500)).await;
}

/// Three clients whose connections grant no HTTP/2 window at all hold every stream slot
/// (`max_streams` 6, 2 streams each); once their first messages have waited `UNREAD_GRACE` in
/// the transport with no DATA taken, a newcomer's StreamSamples takes the slot of one of them
/// (its connection is closed) and is served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn zero_window_clients_do_not_hold_every_stream_slot() {
    let s = server(ServiceConfig { max_streams: 6, ..config() }).await;
    let mut holders = Vec::new();
    let mut replies = Vec::new();
    for a in 0..3u8 {
        let (mut send, conn) = h2_connection_from([127, 0, 9, 2 + a], s.addr, 0).await;
        for seed in 0..2u64 {
            let req = pb::SampleSpec { seed, ..Default::default() }.stream().encode_to_vec();
            let r = raw_call(&mut send, "StreamSamples", &req).await;
            assert_eq!(header_status(&r), None, "the holder's stream opened");
            replies.push(r);
        }
        holders.push((send, conn));
    }
    assert_eq!(s.state.active_streams(), 6, "every slot is held");
    // each holder's first message is made and handed to the transport, where it stays
    until("every holder's first message waits in the transport", || {
        let st = s.state.scheduler.stats();
        st.per_stream.len() == 6 && st.per_stream.iter().all(|&(_, _, delivered, ..)| delivered >= 1)
    })
    .await;
    let mut newcomer = client(s.addr).await;
    let mut stream = newcomer
        .stream_samples(pb::StreamRequest { count: 2, ..Default::default() })
        .await
        .expect("the newcomer's stream is opened")
        .into_inner();
    let mut got = 0;
    while let Some(b) = stream.message().await.expect("served") {
        got += b.samples.len();
    }
    assert_eq!(got, 2);
    until("a holder's connection is closed", || holders.iter().any(|(_, conn)| conn.is_finished())).await;
    for (_, conn) in &holders {
        conn.abort();
    }
    drop(replies);
    s.shutdown(Duration::from_millis(500)).await;
}

/// A client's calls whose request has not arrived whole are bounded over all its connections
/// (`max_calls_per_connection` of them, here 16): with 10 unfinished Health/Check calls on one
/// connection and 6 on another from the same address, its next call is refused at once with
/// RESOURCE_EXHAUSTED `too-many-calls` naming the bound, while another client's Check is answered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unfinished_calls_of_one_client_are_bounded() {
    let s = server(ServiceConfig { max_calls_per_connection: 16, idle_connection_timeout_s: 600.0, ..config() }).await;
    let mut held = Vec::new();
    let (first, _first_conn) = h2_connection_from([127, 0, 10, 2], s.addr, 1 << 20).await;
    for _ in 0..10 {
        held.push(unfinished_check(&first, &[0, 0, 0, 0, 10]).await);
    }
    let (mut second, _second_conn) = h2_connection_from([127, 0, 10, 2], s.addr, 1 << 20).await;
    for _ in 0..6 {
        held.push(unfinished_check(&second, &[0, 0, 0, 0, 10]).await);
    }
    // each call is dispatched on a task of its own, in no set order: a whole call may be answered
    // until the server has counted all 16 unfinished ones, and is refused from then on
    let ask = async {
        loop {
            let r = raw_request(&mut second, "/grpc.health.v1.Health/Check", &[], &[]).await;
            if header_status(&r).is_some() {
                return r;
            }
            // an answered call is read whole: a reply dropped unread would be a stream reset by
            // this client's own library, which closes the connection after enough of them
            let mut body = r.into_body();
            while let Some(Ok(chunk)) = body.data().await {
                let _ = body.flow_control().release_capacity(chunk.len());
            }
            let _ = body.trailers().await;
        }
    };
    let refused = tokio::time::timeout(Duration::from_secs(60), ask).await.expect("a call over the bound is refused");
    assert_eq!(header_status(&refused), Some(Code::ResourceExhausted as i32), "{refused:?}");
    let status = tonic::Status::from_header_map(refused.headers()).expect("a status");
    assert!(status.message().contains("16 of this client are waiting for their request"), "{status:?}");
    let reason = refused.headers().get("mpiflow-reason").map(|v| v.to_str().unwrap().to_string());
    assert_eq!(reason.as_deref(), Some("too-many-calls"));
    // another client is served
    let (mut other, _other_conn) = h2_connection_from([127, 0, 10, 3], s.addr, 1 << 20).await;
    let answered = raw_request(&mut other, "/grpc.health.v1.Health/Check", &[], &[]).await;
    assert_eq!(header_status(&answered), None, "another client's call is answered");
    drop(held);
    s.shutdown(Duration::from_millis(500)).await;
}
