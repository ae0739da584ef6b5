//! The server's HTTP layer around every gRPC call: it counts the call on its connection (a
//! connection with no call open is idle and is closed after `idle_connection_timeout_s`, see
//! [`super::conn`]) and says when its request has arrived whole (from then on the call keeps its
//! connection from being closed for a newcomer); a request that has not arrived whole within the
//! request deadline (`idle_connection_timeout_s`: headers sent, the body trickled or withheld)
//! fails the call ([`RequestBody`]), so such calls hold no slot for long, and a client with as
//! many such calls as it may have (`conn::TooManyWaiting`) has its next call refused at once;
//! keeps what a handler attached to its reply (a [`ReplyHold`]: the budget a unary sample holds)
//! until the reply's last byte has left, hands the reply body to HTTP/2 in pieces of at most
//! [`PIECE_BYTES`] (so a reply the client does not read stays in this layer, counted, instead of
//! in the transport's buffers), and rewrites the status of the replies tonic makes before any
//! handler runs to the codes of the error table ([`super::error::transport_code`]).

use std::any::Any;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use bytes::Bytes;
use http::{HeaderValue, Request, Response};
use http_body::{Body, Frame, SizeHint};
use tonic::transport::server::TcpConnectInfo;

use super::conn::{Arrival, CallGuard, ConnInfo};
use super::error::{Reason, ServiceError};

/// The largest piece of a reply handed to HTTP/2 at once: the transport asks for the next piece
/// only when the client's window has room, so a reply keeps at most about one piece in the
/// transport, uncounted. Pieces start at [`FIRST_PIECE_BYTES`] and double with each piece the
/// transport takes, up to this: a reply nobody reads leaves 16 KiB there, one whose client stops
/// reading midway at most 256 KiB. Each piece is at least one HTTP/2 frame and one socket write,
/// and each frame wakes the client's reader: 16 KiB pieces cost a 640x480 sample ~290 frames and
/// the Rust client 3.7-3.9 ms of CPU, 256 KiB pieces ~20 frames and 1.7-1.9 ms
/// (docs/performance.md, "The wire"). A client that accepts only 16 KiB frames (HTTP/2's
/// default) still gets them: h2 cuts the piece.
pub const PIECE_BYTES: usize = 256 << 10;

/// The first piece of a reply (HTTP/2's default frame size).
pub const FIRST_PIECE_BYTES: usize = 16 << 10;

/// The health service's Watch call.
const HEALTH_WATCH_PATH: &str = "/grpc.health.v1.Health/Watch";

/// The calls whose request is a stream of any length (an upload's files, reflection's
/// questions): they count as arrived when they begin, and their request has no deadline (an
/// upload has its own limits).
const STREAMING_REQUEST_PATHS: [&str; 3] = [
    "/mpiflow.v1.MpiFlow/UploadSources",
    "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
    "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
];

/// Something a handler attaches to its reply (in the response's extensions) that must live until
/// the reply is sent or abandoned: a unary sample's place in the byte budget.
#[derive(Clone)]
pub struct ReplyHold(pub Arc<dyn Any + Send + Sync>);

impl std::fmt::Debug for ReplyHold {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ReplyHold")
    }
}

/// The layer ([`tower::Layer`]) of the server: `request_deadline` is how long a call's request
/// may take to arrive whole.
#[derive(Clone, Copy, Debug)]
pub struct ReplyLayer {
    pub request_deadline: Duration,
}

impl<S> tower::Layer<S> for ReplyLayer {
    type Service = Reply<S>;
    fn layer(&self, inner: S) -> Self::Service {
        Reply { inner, request_deadline: self.request_deadline }
    }
}

/// The service of [`ReplyLayer`].
#[derive(Clone, Debug)]
pub struct Reply<S> {
    inner: S,
    request_deadline: Duration,
}

/// The connection of a request (from its extensions): its [`ConnInfo`], on plaintext or under
/// TLS.
pub fn conn_of(e: &http::Extensions) -> Option<ConnInfo> {
    e.get::<ConnInfo>()
        .cloned()
        .or_else(|| e.get::<tonic::transport::server::TlsConnectInfo<ConnInfo>>().map(|t| t.get_ref().clone()))
}

impl<S, ReqBody, ResBody> tower::Service<Request<ReqBody>> for Reply<S>
where
    S: tower::Service<Request<RequestBody<ReqBody>>, Response = Response<ResBody>>,
    S::Future: Send + 'static,
    ReqBody: Body<Data = Bytes> + Unpin,
    ReqBody::Error: Into<BoxError>,
    ResBody: Body<Data = Bytes> + Unpin,
{
    type Response = Response<ReplyBody<ResBody>>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Self::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut req: Request<ReqBody>) -> Self::Future {
        let info = conn_of(req.extensions());
        // tonic's `Request::remote_addr` reads the plain TCP info
        if let Some(i) = &info {
            req.extensions_mut().insert::<TcpConnectInfo>(i.tcp.clone());
        }
        // a health watch keeps its connection from the idle timeout, not from a newcomer
        let path = req.uri().path();
        let watch = path == HEALTH_WATCH_PATH;
        let streaming = STREAMING_REQUEST_PATHS.contains(&path);
        let call = match info.map(|i| i.activity.begin(watch)).transpose() {
            Ok(call) => call,
            Err(too_many) => {
                tracing::debug!(error = %too_many, "call refused");
                let status =
                    tonic::Status::from(ServiceError::LimitExceeded(Reason::TooManyCalls, too_many.to_string()));
                return Box::pin(async move { Ok(status.into_http::<()>().map(|()| ReplyBody::empty())) });
            }
        };
        let arrival = call.as_ref().map(CallGuard::arrival);
        if streaming {
            if let Some(a) = &arrival {
                a.arrived();
            }
        }
        let deadline = (!streaming).then_some(self.request_deadline);
        let fut = self.inner.call(req.map(|body| RequestBody::new(body, arrival, deadline)));
        Box::pin(async move {
            let mut response = fut.await?;
            rewrite_status(&mut response);
            let hold = response.extensions_mut().remove::<ReplyHold>();
            Ok(response.map(|inner| ReplyBody {
                inner: Some(inner),
                piece: Bytes::new(),
                piece_size: FIRST_PIECE_BYTES,
                _call: call,
                _hold: hold,
            }))
        })
    }
}

/// A boxed error, as tonic's routes take a request body's errors.
pub type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// A call's request body: it says when the request has arrived whole (its first gRPC message
/// complete, or its end seen) and fails with [`ServiceError::RequestIncomplete`] (a status of
/// the error table) when that has not happened within its deadline.
pub struct RequestBody<B> {
    inner: B,
    arrival: Option<Arrival>,
    /// The deadline's timer (none once the request has arrived, or for a streaming request).
    timer: Option<Pin<Box<tokio::time::Sleep>>>,
    deadline: Duration,
    /// The first message's 5-byte gRPC prefix (flag, length) as far as it has come.
    prefix: [u8; 5],
    prefix_len: usize,
    /// The first message's bytes still to come, once its prefix is whole.
    left: u64,
    /// Whether the request has arrived.
    arrived: bool,
}

impl<B: Body> RequestBody<B> {
    fn new(inner: B, arrival: Option<Arrival>, deadline: Option<Duration>) -> Self {
        let timer = deadline.map(|d| Box::pin(tokio::time::sleep(d)));
        let mut body = Self {
            inner,
            arrival,
            timer,
            deadline: deadline.unwrap_or_default(),
            prefix: [0; 5],
            prefix_len: 0,
            left: 0,
            arrived: false,
        };
        if body.inner.is_end_stream() {
            body.arrive();
        }
        body
    }

    /// Counts `data` into the first message: whether that message is now whole.
    fn whole_message(&mut self, mut data: &[u8]) -> bool {
        while !data.is_empty() {
            if self.prefix_len < self.prefix.len() {
                let n = (self.prefix.len() - self.prefix_len).min(data.len());
                self.prefix[self.prefix_len..self.prefix_len + n].copy_from_slice(&data[..n]);
                self.prefix_len += n;
                data = &data[n..];
                if self.prefix_len == self.prefix.len() {
                    let [_, a, b, c, d] = self.prefix;
                    self.left = u64::from(u32::from_be_bytes([a, b, c, d]));
                    if self.left == 0 {
                        return true;
                    }
                }
            } else {
                let n = (data.len() as u64).min(self.left);
                self.left -= n;
                // n <= data.len()
                data = &data[n as usize..];
                if self.left == 0 {
                    return true;
                }
            }
        }
        false
    }

    fn arrive(&mut self) {
        self.arrived = true;
        self.timer = None;
        if let Some(a) = self.arrival.take() {
            a.arrived();
        }
    }
}

impl<B> Body for RequestBody<B>
where
    B: Body<Data = Bytes> + Unpin,
    B::Error: Into<BoxError>,
{
    type Data = Bytes;
    type Error = BoxError;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, BoxError>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(None) => {
                this.arrive();
                Poll::Ready(None)
            }
            Poll::Ready(Some(Ok(frame))) => {
                let whole = !this.arrived && frame.data_ref().is_some_and(|d| this.whole_message(d));
                if whole || frame.is_trailers() || this.inner.is_end_stream() {
                    this.arrive();
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Ready(Some(Err(e))) => Poll::Ready(Some(Err(e.into()))),
            Poll::Pending => match this.timer.as_mut().map(|t| t.as_mut().poll(cx)) {
                Some(Poll::Ready(())) => {
                    this.timer = None;
                    let e = ServiceError::RequestIncomplete { seconds: this.deadline.as_secs_f64() };
                    Poll::Ready(Some(Err(Box::new(tonic::Status::from(e)))))
                }
                _ => Poll::Pending,
            },
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// Rewrites the status of a trailers-only reply that tonic made itself (it carries no
/// `mpiflow-reason`: a request over the decoding limit, a malformed message) to the code and
/// reason of the error table, by its code alone.
fn rewrite_status<B>(response: &mut Response<B>) {
    use super::error::REASON_TRAILER;
    let h = response.headers();
    if h.contains_key(REASON_TRAILER) {
        return;
    }
    let Some(code) = h.get("grpc-status").and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<i32>().ok()) else {
        return;
    };
    if let Some((new, reason)) = super::error::transport_code(tonic::Code::from_i32(code)) {
        let headers = response.headers_mut();
        headers.insert("grpc-status", HeaderValue::from(new as i32));
        headers.insert(REASON_TRAILER, HeaderValue::from_static(reason.as_str()));
    }
}

/// A reply body handed on in pieces growing from [`FIRST_PIECE_BYTES`] to [`PIECE_BYTES`]; it
/// keeps its call counted on the connection and its [`ReplyHold`] until it is dropped (sent, or
/// abandoned with the call).
pub struct ReplyBody<B> {
    /// None for a call refused before it reached a service (its status in the headers).
    inner: Option<B>,
    /// The rest of the current data frame.
    piece: Bytes,
    /// The size of the next piece.
    piece_size: usize,
    _call: Option<CallGuard>,
    _hold: Option<ReplyHold>,
}

impl<B> ReplyBody<B> {
    /// The body of a trailers-only reply: nothing.
    fn empty() -> Self {
        ReplyBody { inner: None, piece: Bytes::new(), piece_size: FIRST_PIECE_BYTES, _call: None, _hold: None }
    }

    fn next_piece(&mut self) -> Frame<Bytes> {
        let n = self.piece.len().min(self.piece_size);
        self.piece_size = (self.piece_size * 2).min(PIECE_BYTES);
        Frame::data(self.piece.split_to(n))
    }
}

impl<B: Body<Data = Bytes> + Unpin> Body for ReplyBody<B> {
    type Data = Bytes;
    type Error = B::Error;

    fn poll_frame(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, B::Error>>> {
        if !self.piece.is_empty() {
            return Poll::Ready(Some(Ok(self.next_piece())));
        }
        let Some(inner) = self.inner.as_mut() else { return Poll::Ready(None) };
        match Pin::new(inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => match frame.into_data() {
                Ok(data) => {
                    self.piece = data;
                    Poll::Ready(Some(Ok(self.next_piece())))
                }
                Err(frame) => Poll::Ready(Some(Ok(frame))),
            },
            other => other,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.piece.is_empty() && self.inner.as_ref().is_none_or(Body::is_end_stream)
    }

    fn size_hint(&self) -> SizeHint {
        let inner = self.inner.as_ref().map_or_else(|| SizeHint::with_exact(0), Body::size_hint);
        let extra = self.piece.len() as u64;
        let mut h = SizeHint::new();
        h.set_lower(inner.lower() + extra);
        if let Some(u) = inner.upper() {
            h.set_upper(u + extra);
        }
        h
    }
}
