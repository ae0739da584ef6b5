//! The sample streams' route ([`SampleRoutes`]): StreamSamples and GetSamples answered in front of
//! the generated service, their replies written by the frames' body.

use std::convert::Infallible;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Status, Streaming};

use super::admission::{client_of, refused, CountedStream};
use super::state::{State, SERVICE_NAME};
use crate::service::error::ServiceError;
use crate::service::frames::{FrameBody, Framed};
use crate::service::pb;

/// The calls answered by [`SampleRoutes`]: the sample streams.
pub(super) const STREAM_SAMPLES_PATH: &str = "/mpiflow.v1.MpiFlow/StreamSamples";
pub(super) const GET_SAMPLES_PATH: &str = "/mpiflow.v1.MpiFlow/GetSamples";

/// The `mpiflow.v1.MpiFlow` service as served: the sample streams (StreamSamples, GetSamples)
/// answered here with the reply body of [`crate::service::frames`] (the tensors handed to HTTP/2
/// without a copy), every other call by tonic's generated service. The request is decoded by
/// tonic's own decoder, with the same size limit and errors, and opened by the same [`State`]
/// methods as the generated service's handlers; the token check, the reply layer and the
/// connection limits wrap both alike.
#[derive(Clone)]
pub(super) struct SampleRoutes<S> {
    pub(super) inner: S,
    pub(super) state: Arc<State>,
    /// `max_request_bytes` and `max_message_bytes`
    pub(super) max_request: usize,
    pub(super) max_message: usize,
}

impl<S> tonic::server::NamedService for SampleRoutes<S> {
    const NAME: &'static str = SERVICE_NAME;
}

type RouteFuture =
    Pin<Box<dyn std::future::Future<Output = Result<http::Response<tonic::body::Body>, Infallible>> + Send>>;

impl<S> tower::Service<http::Request<tonic::body::Body>> for SampleRoutes<S>
where
    S: tower::Service<
        http::Request<tonic::body::Body>,
        Response = http::Response<tonic::body::Body>,
        Error = Infallible,
    >,
    S::Future: Send + 'static,
{
    type Response = http::Response<tonic::body::Body>;
    type Error = Infallible;
    type Future = RouteFuture;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, req: http::Request<tonic::body::Body>) -> Self::Future {
        let (state, max_request, max_message) = (self.state.clone(), self.max_request, self.max_message);
        match req.uri().path() {
            STREAM_SAMPLES_PATH => {
                Box::pin(reply(req, max_request, max_message, move |r: Request<pb::StreamRequest>| async move {
                    refused(&state, state.open_stream_making_room(r.get_ref(), client_of(&r)).await)
                }))
            }
            GET_SAMPLES_PATH => {
                Box::pin(reply(req, max_request, max_message, move |r: Request<pb::SamplesRequest>| {
                    std::future::ready(refused(&state, state.open_samples(r.get_ref(), client_of(&r))).map(samples_of))
                }))
            }
            _ => Box::pin(self.inner.call(req)),
        }
    }
}

/// A sample stream's reply: the request decoded (tonic's decoder, at most `max_request` bytes; no
/// request compression, as the generated service), the stream opened by `open`, its messages
/// sent by [`FrameBody`]; a refusal as tonic's trailers-only reply.
async fn reply<Q, S, M, F>(
    req: http::Request<tonic::body::Body>,
    max_request: usize,
    max_message: usize,
    open: impl FnOnce(Request<Q>) -> F,
) -> Result<http::Response<tonic::body::Body>, Infallible>
where
    F: std::future::Future<Output = Result<S, Status>>,
    Q: prost::Message + Default + Send + 'static,
    S: Stream<Item = Result<M, Status>> + Send + Unpin + 'static,
    M: Framed + Send + 'static,
{
    let opened = async {
        if let Some(enc) = req.headers().get("grpc-encoding").filter(|v| v.as_bytes() != b"identity") {
            let mut status = Status::unimplemented(format!(
                "Content is compressed with `{}` which isn't supported",
                String::from_utf8_lossy(enc.as_bytes())
            ));
            status
                .metadata_mut()
                .insert("grpc-accept-encoding", tonic::metadata::MetadataValue::from_static("identity"));
            return Err(status);
        }
        let (parts, body) = req.into_parts();
        let decoder = tonic_prost::ProstDecoder::<Q>::new(tonic::codec::BufferSettings::default());
        let mut messages = Streaming::new_request(decoder, body, None, Some(max_request));
        let message = messages.message().await?.ok_or_else(|| Status::internal("Missing request message."))?;
        open(Request::from_http(http::Request::from_parts(parts, message))).await
    };
    Ok(match opened.await {
        Ok(stream) => {
            let mut response = http::Response::new(tonic::body::Body::new(FrameBody::new(stream, max_message)));
            response
                .headers_mut()
                .insert(http::header::CONTENT_TYPE, http::HeaderValue::from_static("application/grpc"));
            response
        }
        Err(status) => status.into_http(),
    })
}

/// GetSamples' messages: the stream's batches hold one sample each (batch_size 1), sent alone.
fn samples_of(stream: CountedStream) -> impl Stream<Item = Result<pb::Sample, Status>> + Send + Unpin {
    stream.map(|b| {
        b.and_then(|b| {
            b.samples.into_iter().next().ok_or_else(|| ServiceError::Internal("an empty batch".into()).into())
        })
    })
}
