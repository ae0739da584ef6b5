//! The tonic service (`mpiflow.v1.MpiFlow`) and the server around it: start-up (datasets, models,
//! listener, health, reflection, metrics), warm-up, and graceful drain. Handlers stay thin:
//! validate, call the domain (dataset, pool), convert back. The sample streams' replies are
//! written by [`super::frames`] through `SampleRoutes`, in front of the generated service.

use std::convert::Infallible;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tokio_stream::{Stream, StreamExt};
use tonic::service::interceptor::InterceptedService;
use tonic::{Request, Response, Status, Streaming};
use tonic_health::server::HealthReporter;
use tonic_health::ServingStatus;

use super::config::ServiceConfig;
use super::dataset::{Dataset, Datasets};
use super::encode::{crop_sample, crop_window, to_proto, OutputSpec};
use super::error::ServiceError;
use super::metrics::{serve_metrics, Metrics};
use super::pb;
use super::pb::mpi_flow_server::{MpiFlow, MpiFlowServer};
use super::peer::PeerKey;
use super::pool::{Client, Produce, SampleStream, Scheduler, StreamSpec};
use super::reply::{ReplyHold, ReplyLayer};
use super::security::{server_tls, RequireToken};
use super::spec::{self, Spec};
use super::validate;
use crate::sample::pipeline::Generator;

/// The gRPC service name health reports on (besides "").
pub const SERVICE_NAME: &str = "mpiflow.v1.MpiFlow";

/// What the handlers share.
pub struct State {
    pub config: ServiceConfig,
    pub datasets: Arc<Datasets>,
    pub scheduler: Arc<Scheduler>,
    pub metrics: Arc<Metrics>,
    health: HealthReporter,
    serving: AtomicBool,
    draining: AtomicBool,
    active_streams: AtomicUsize,
    /// StreamSamples calls open now per peer (at most half of `max_streams`).
    streams_per_peer: std::sync::Mutex<std::collections::HashMap<PeerKey, usize>>,
    /// GetSample and GetSamples calls open now per peer (`max_random_access_calls`), replies not
    /// yet sent included.
    random_access_calls: std::sync::Mutex<std::collections::HashMap<PeerKey, usize>>,
}

impl std::fmt::Debug for State {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("State").field("scheduler", &self.scheduler).finish()
    }
}

impl State {
    pub fn is_serving(&self) -> bool {
        self.serving.load(Ordering::SeqCst)
    }

    pub fn active_streams(&self) -> usize {
        self.active_streams.load(Ordering::SeqCst)
    }

    async fn set_health(&self, status: ServingStatus) {
        self.health.set_service_status("", status).await;
        self.health.set_service_status(SERVICE_NAME, status).await;
    }

    /// The job of a stream: make the sample, crop it, encode it (on a worker).
    fn produce(&self, dataset: Arc<Dataset>, generator: Arc<Generator>, seed: u64, out: OutputSpec) -> Produce {
        let metrics = self.metrics.clone();
        let prepare: Option<super::pool::Prepare> = self.config.prefetch_scenes.then(|| {
            let g = generator.clone();
            Arc::new(move |index: u64, done: Box<dyn FnOnce() + Send>| g.prepare(index, done)) as super::pool::Prepare
        });
        let make: super::pool::Make = Arc::new(move |index| {
            let s = generator.sample(seed, index).map_err(|source| {
                metrics.observe_error(&source);
                tracing::warn!(dataset = %dataset.name, index, error = %source, "sample failed");
                ServiceError::Generation { index, source }
            })?;
            if s.skipped_sources > 0 {
                let opened = dataset.opened_skips();
                let mut counts = generator.skip_counts();
                for (k, n) in opened {
                    *counts.entry(k).or_default() += n;
                }
                if metrics.record_skips(&dataset.name, &counts) {
                    for (item, id, reason) in generator.skipped() {
                        tracing::warn!(dataset = %dataset.name, item, id = %id, reason = %reason, "bad source passed over");
                    }
                }
            }
            // the camera of the scene the sample was made from (before any crop)
            let mut k = s.intrinsics;
            let timings = s.timings;
            let mut record = String::new();
            let (corner, s) = match (&out.augment, &out.crop) {
                (Some(a), _) => {
                    // the augmentation makes its own crop (the frame resized to fit it)
                    let (s, r) = a.apply(s);
                    record = r.to_json();
                    k = s.intrinsics;
                    ((0, 0), s)
                }
                (None, Some(c)) => {
                    // a crop larger than the frame is the request's fault, never shrunk
                    let (x0, y0, cw, ch) = crop_window(c, s.width, s.height, s.address)
                        .map_err(|e| ServiceError::invalid("crop", e.to_string()))?;
                    if (cw, ch) == (s.width, s.height) {
                        ((0, 0), s)
                    } else {
                        ((x0, y0), crop_sample(&s, x0, y0, cw, ch))
                    }
                }
                (None, None) => ((0, 0), s),
            };
            let mut p = to_proto(s, &dataset.name, k, corner, &out);
            p.augment = record;
            metrics.observe_sample(&timings, p.timings.as_ref().map_or(0.0, |t| t.encode_ms));
            Ok(p)
        });
        Produce { make, prepare, bound: 0 }
    }

    /// The one path of a request's spec (all three calls): validated into a [`Spec`], resolved
    /// to the dataset and the generator of its overrides, the fingerprint checked, the outputs
    /// checked against the motion law, and admitted by size; then the job that makes its samples.
    fn prepare(&self, spec: Option<&pb::SampleSpec>) -> Result<Prepared, ServiceError> {
        let spec = Spec::try_from((&*spec::of(spec), &self.config))?;
        let ds = self.datasets.get(&spec.dataset)?;
        let generator = ds.generator(&spec.overrides)?;
        if spec.fingerprint != 0 && spec.fingerprint != generator.fingerprint() {
            return Err(ServiceError::FingerprintMismatch {
                dataset: ds.name.clone(),
                requested: spec.fingerprint,
                actual: generator.fingerprint(),
            });
        }
        validate::outputs_fit_motion(&spec.out, generator.config())?;
        let bound = validate::admit_size(&spec.out, spec.frames(), &self.config, self.scheduler.budget())?;
        let (dataset, fingerprint, seed) = (ds.name.clone(), generator.fingerprint(), spec.seed);
        let mut produce = self.produce(ds, generator, seed, spec.out);
        produce.bound = bound;
        Ok(Prepared { dataset, fingerprint, seed, produce })
    }

    fn open_stream(self: &Arc<Self>, r: &pb::StreamRequest, client: Client) -> Result<CountedStream, ServiceError> {
        if self.draining.load(Ordering::SeqCst) {
            return Err(ServiceError::Draining);
        }
        let (rank, world, batch, prefetch) = validate::stream_shape(r, &self.config)?;
        let p = self.prepare(r.spec.as_ref())?;
        // the stream limit
        let admitted = self.admit(CallKind::Stream, client.peer)?;
        let spec = StreamSpec {
            start_index: r.start_index,
            rank: u64::from(rank),
            world_size: u64::from(world),
            count: r.count,
            batch_size: batch as usize,
            prefetch: prefetch as usize,
            max_message_bytes: self.config.max_message_bytes() as usize,
        };
        let peer = client.peer;
        let inner = self.scheduler.open_for(client, spec, p.produce)?;
        self.metrics.active_streams.inc();
        tracing::info!(
            %peer,
            stream = inner.id(),
            dataset = %p.dataset,
            fingerprint = format!("{:016x}", p.fingerprint),
            seed = p.seed,
            rank,
            world_size = world,
            start_index = r.start_index,
            count = r.count,
            batch,
            prefetch,
            "stream opened"
        );
        Ok(CountedStream { inner, _admitted: admitted })
    }

    /// Counts a new call against its limit: `max_streams` for StreamSamples over all clients
    /// and half of it per peer (so one client, one connection included, cannot keep every other
    /// out), `max_random_access_calls` for the GetSample and GetSamples calls of one peer (undone
    /// when the returned slot is dropped, with the call's reply).
    fn admit(self: &Arc<Self>, kind: CallKind, peer: PeerKey) -> Result<Admitted, ServiceError> {
        match kind {
            CallKind::Stream => {
                let limit = self.config.max_streams;
                let per_peer = streams_per_peer(limit);
                let mut of_peer = self.streams_per_peer.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                let n = of_peer.entry(peer).or_insert(0);
                if *n >= per_peer {
                    return Err(ServiceError::LimitExceeded(
                        super::error::Reason::TooManyStreams,
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
                        super::error::Reason::TooManyCalls,
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
    fn release(&self, kind: CallKind, peer: PeerKey) {
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

    /// The samples of an explicit index list, in its order (GetSamples): a stream of the pool
    /// with the list as its positions, counted against `max_streams`, one sample per message.
    fn open_samples(self: &Arc<Self>, r: &pb::SamplesRequest, client: Client) -> Result<CountedStream, ServiceError> {
        if self.draining.load(Ordering::SeqCst) {
            return Err(ServiceError::Draining);
        }
        let indices = validate::indices(&r.indices)?;
        let p = self.prepare(r.spec.as_ref())?;
        let admitted = self.admit(CallKind::RandomAccess, client.peer)?;
        // as many made ahead as keep every worker busy (within max_prefetch)
        let prefetch = (self.config.default_prefetch as usize)
            .max(self.scheduler.workers())
            .min(self.config.max_prefetch as usize)
            .min(indices.len());
        let n = indices.len();
        let max_bytes = self.config.max_message_bytes() as usize;
        let inner = self.scheduler.open_indices(client, indices, 1, prefetch, max_bytes, p.produce)?;
        self.metrics.active_streams.inc();
        tracing::debug!(
            stream = inner.id(),
            dataset = %p.dataset,
            fingerprint = format!("{:016x}", p.fingerprint),
            seed = p.seed,
            indices = n,
            prefetch,
            "samples opened"
        );
        Ok(CountedStream { inner, _admitted: admitted })
    }

    /// One sample through the worker pool (GetSample and the warm-up), with its place in the
    /// byte budget: the sample's bytes stay counted until the returned stream is dropped (with
    /// the reply, once sent: [`ReplyHold`]).
    pub async fn one_sample(
        self: &Arc<Self>,
        r: &pb::SampleRequest,
        client: Client,
    ) -> Result<(pb::Sample, SampleStream), Status> {
        if r.index == super::pool::END_INDEX {
            return Err(ServiceError::invalid("index", "2^64 - 1 is the end of the index space, not a sample").into());
        }
        let p = self.prepare(r.spec.as_ref())?;
        let spec = StreamSpec {
            start_index: r.index,
            rank: 0,
            world_size: 1,
            count: 1,
            batch_size: 1,
            prefetch: 1,
            max_message_bytes: self.config.max_message_bytes() as usize,
        };
        let mut stream = self.scheduler.open_for(client, spec, p.produce)?;
        match stream.next().await {
            Some(Ok(mut b)) if !b.samples.is_empty() => Ok((b.samples.swap_remove(0), stream)),
            // the status without the stream's cursor, with its reason
            Some(Err(status)) => {
                let mut s = Status::new(status.code(), status.message().to_string());
                if let Some(r) = super::error::Reason::of(&status) {
                    r.set(&mut s);
                }
                Err(s)
            }
            _ => Err(ServiceError::Internal("no sample came back".into()).into()),
        }
    }

    /// Receives an upload's chunks into a session of the upload store, commits it, and (re)makes
    /// the uploaded dataset. Nothing of a failed upload is kept.
    async fn upload(&self, mut chunks: Streaming<pb::SourceChunk>) -> Result<pb::UploadSummary, ServiceError> {
        if self.draining.load(Ordering::SeqCst) {
            return Err(ServiceError::Draining);
        }
        // the in-progress budgets: a slot now, bytes as they arrive (RESOURCE_EXHAUSTED over them)
        let mut session = self.datasets.uploads.session()?;
        let mut dataset = String::new();
        while let Some(chunk) = chunks.message().await.map_err(super::error::from_request_stream)? {
            if dataset.is_empty() {
                dataset = chunk.dataset.clone();
                if self.datasets.is_configured(&dataset) {
                    return Err(ServiceError::invalid(
                        "dataset",
                        format!("{dataset} is a configured dataset; upload to another name"),
                    ));
                }
            }
            session.push(&dataset, &chunk.name, &chunk.kind, &chunk.data)?;
        }
        // a new dataset of photos alone, with no depth model: nothing of it could make a scene
        let fresh = !dataset.is_empty() && self.datasets.get(&dataset).is_err();
        if fresh && self.datasets.stage.depth.is_none() && !session.has_depth() {
            return Err(ServiceError::Unusable { dataset, source: crate::scene::SceneError::NoDepthModel });
        }
        let datasets = self.datasets.clone();
        let summary = tokio::task::spawn_blocking(move || -> Result<_, ServiceError> {
            let summary = session.finish()?;
            if summary.sources > 0 {
                datasets.refresh_upload(&summary)?;
            }
            Ok(summary)
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("upload: {e}")))??;
        tracing::info!(dataset = %summary.dataset, accepted = summary.accepted, rejected = summary.rejected.len(), sources = summary.sources, "upload");
        let fingerprint = self.datasets.get(&summary.dataset).map(|d| d.fingerprint()).unwrap_or(summary.fingerprint);
        Ok(pb::UploadSummary {
            dataset: summary.dataset,
            accepted: summary.accepted,
            rejected: summary.rejected,
            fingerprint,
            sources: summary.sources,
        })
    }

    fn info(&self) -> pb::InfoResponse {
        let stage = &self.datasets.stage;
        let mut models = vec![pb::ModelInfo { role: "mpi".into(), name: stage.mpi.name() }];
        if let Some(d) = &stage.depth {
            models.push(pb::ModelInfo { role: "depth".into(), name: d.name() });
        }
        if let Some(s) = &stage.segmenter {
            models.push(pb::ModelInfo { role: "segment".into(), name: s.name() });
        }
        let c = &self.config;
        pb::InfoResponse {
            version: env!("CARGO_PKG_VERSION").into(),
            datasets: self
                .datasets
                .all()
                .iter()
                .enumerate()
                .map(|(i, d)| pb::DatasetInfo {
                    name: d.name.clone(),
                    fingerprint: d.fingerprint(),
                    sources: d.sources() as u64,
                    description: d.description.clone(),
                    is_default: i == 0,
                    skipped: self.metrics.skipped_of(&d.name),
                    needs_models: d.loader.needs_models(),
                    baked_with: d.source.baked_with().unwrap_or_default(),
                })
                .collect(),
            models,
            limits: Some(pb::Limits {
                max_message_bytes: c.max_message_bytes(),
                max_streams: c.max_streams as u32,
                max_batch_size: c.max_batch_size,
                max_prefetch: c.max_prefetch,
                max_image_side: c.max_image_side,
                max_image_pixels: c.max_image_pixels,
                max_upload_bytes: c.max_upload_bytes,
                max_indices: validate::MAX_INDICES as u32,
                max_buffered_bytes: self.scheduler.budget(),
                max_request_bytes: c.max_request_bytes(),
                max_random_access_calls: c.max_random_access_calls as u32,
                max_connections: c.max_connections as u32,
                max_connections_per_peer: c.max_connections_per_peer as u32,
                max_calls_per_connection: c.max_calls_per_connection,
                idle_connection_timeout_s: c.idle_connection_timeout_s,
                stall_timeout_s: c.stall_timeout_s,
            }),
            workers: self.scheduler.workers() as u32,
            serving: self.is_serving(),
            simd: crate::isa::current().name().into(),
        }
    }
}

/// A request's spec made ready: the job that makes its samples, and what the log says of it.
struct Prepared {
    dataset: String,
    fingerprint: u64,
    seed: u64,
    produce: Produce,
}

/// Which limit a call counts against.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum CallKind {
    /// StreamSamples: `max_streams`.
    Stream,
    /// GetSample and GetSamples: `max_random_access_calls`.
    RandomAccess,
}

/// A call's place under its limit, given back when dropped.
struct Admitted {
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
fn client_of<T>(request: &Request<T>) -> Client {
    Client {
        peer: PeerKey::of_addr(request.remote_addr()),
        conn: super::reply::conn_of(request.extensions()).map(|c| c.activity),
    }
}

/// The StreamSamples calls one client may hold: half of `max_streams` (at least 1).
pub fn streams_per_peer(max_streams: usize) -> usize {
    (max_streams / 2).max(1)
}

/// A stream counted against its limit while it lives.
pub struct CountedStream {
    inner: SampleStream,
    _admitted: Admitted,
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

/// The tonic service.
#[derive(Clone, Debug)]
pub struct Service {
    state: Arc<State>,
}

fn refused<T>(state: &State, r: Result<T, ServiceError>) -> Result<T, Status> {
    r.map_err(|e| {
        state.metrics.count_refused(e.code());
        tracing::info!(error = %e, "request refused");
        e.into()
    })
}

#[tonic::async_trait]
impl MpiFlow for Service {
    // StreamSamples and GetSamples are answered by `SampleRoutes`, which takes their paths before
    // this service sees a request; the generated trait still requires a handler for each, so
    // both are one refusal that names the route serving them.
    type StreamSamplesStream = tokio_stream::Empty<Result<pb::SampleBatch, Status>>;
    type GetSamplesStream = tokio_stream::Empty<Result<pb::Sample, Status>>;

    async fn stream_samples(
        &self,
        _request: Request<pb::StreamRequest>,
    ) -> Result<Response<Self::StreamSamplesStream>, Status> {
        Err(served_by_sample_routes(STREAM_SAMPLES_PATH))
    }

    async fn get_sample(&self, request: Request<pb::SampleRequest>) -> Result<Response<pb::Sample>, Status> {
        if self.state.draining.load(Ordering::SeqCst) {
            return Err(refused::<()>(&self.state, Err(ServiceError::Draining)).unwrap_err());
        }
        let client = client_of(&request);
        let admitted = refused(&self.state, self.state.admit(CallKind::RandomAccess, client.peer))?;
        let r = self.state.one_sample(request.get_ref(), client).await;
        let (sample, stream) = r.inspect_err(|s| self.state.metrics.count_refused(s.code()))?;
        let mut response = Response::new(sample);
        // the sample's bytes and the call's slot are held until the reply has been sent
        response.extensions_mut().insert(ReplyHold(Arc::new(std::sync::Mutex::new((stream, admitted)))));
        Ok(response)
    }

    async fn get_samples(
        &self,
        _request: Request<pb::SamplesRequest>,
    ) -> Result<Response<Self::GetSamplesStream>, Status> {
        Err(served_by_sample_routes(GET_SAMPLES_PATH))
    }

    async fn upload_sources(
        &self,
        request: Request<Streaming<pb::SourceChunk>>,
    ) -> Result<Response<pb::UploadSummary>, Status> {
        let r = self.state.upload(request.into_inner()).await;
        refused(&self.state, r).map(Response::new)
    }

    async fn get_info(&self, _request: Request<pb::InfoRequest>) -> Result<Response<pb::InfoResponse>, Status> {
        Ok(Response::new(self.state.info()))
    }
}

/// The answer of the generated handlers of the calls [`SampleRoutes`] serves: a request for
/// `path` reaches `SampleRoutes` first and never the generated service, so this is an internal
/// error if it is ever sent.
fn served_by_sample_routes(path: &str) -> Status {
    Status::internal(format!("{path} is served by the sample routes, not the generated service"))
}

/// The calls answered by [`SampleRoutes`]: the sample streams.
const STREAM_SAMPLES_PATH: &str = "/mpiflow.v1.MpiFlow/StreamSamples";
const GET_SAMPLES_PATH: &str = "/mpiflow.v1.MpiFlow/GetSamples";

/// The `mpiflow.v1.MpiFlow` service as served: the sample streams (StreamSamples, GetSamples)
/// answered here with the reply body of [`super::frames`] (the tensors handed to HTTP/2 without a
/// copy), every other call by tonic's generated service. The request is decoded by tonic's own
/// decoder, with the same size limit and errors, and opened by the same [`State`] methods as the
/// generated service's handlers; the token check, the reply layer and the connection limits wrap
/// both alike.
#[derive(Clone)]
struct SampleRoutes<S> {
    inner: S,
    state: Arc<State>,
    /// `max_request_bytes` and `max_message_bytes`
    max_request: usize,
    max_message: usize,
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
                Box::pin(reply(req, max_request, max_message, move |r: Request<pb::StreamRequest>| {
                    refused(&state, state.open_stream(r.get_ref(), client_of(&r)))
                }))
            }
            GET_SAMPLES_PATH => {
                Box::pin(reply(req, max_request, max_message, move |r: Request<pb::SamplesRequest>| {
                    refused(&state, state.open_samples(r.get_ref(), client_of(&r))).map(samples_of)
                }))
            }
            _ => Box::pin(self.inner.call(req)),
        }
    }
}

/// A sample stream's reply: the request decoded (tonic's decoder, at most `max_request` bytes; no
/// request compression, as the generated service), the stream opened by `open`, its messages
/// sent by [`super::frames::FrameBody`]; a refusal as tonic's trailers-only reply.
async fn reply<Q, S, M>(
    req: http::Request<tonic::body::Body>,
    max_request: usize,
    max_message: usize,
    open: impl FnOnce(Request<Q>) -> Result<S, Status>,
) -> Result<http::Response<tonic::body::Body>, Infallible>
where
    Q: prost::Message + Default + Send + 'static,
    S: Stream<Item = Result<M, Status>> + Send + Unpin + 'static,
    M: super::frames::Framed + Send + 'static,
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
        open(Request::from_http(http::Request::from_parts(parts, message)))
    };
    Ok(match opened.await {
        Ok(stream) => {
            let mut response =
                http::Response::new(tonic::body::Body::new(super::frames::FrameBody::new(stream, max_message)));
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

/// A started server.
pub struct RunningServer {
    /// The bound gRPC address (the real port when the config said 0).
    pub addr: SocketAddr,
    /// The bound metrics address, when metrics are on.
    pub metrics_addr: Option<SocketAddr>,
    /// The bound plaintext health-only address, when `health_addr` is set.
    pub health_addr: Option<SocketAddr>,
    pub state: Arc<State>,
    shutdown: Option<oneshot::Sender<()>>,
    server: JoinHandle<Result<(), tonic::transport::Error>>,
    metrics_task: Option<JoinHandle<()>>,
    health_task: Option<JoinHandle<Result<(), tonic::transport::Error>>>,
    warmup: JoinHandle<()>,
}

impl std::fmt::Debug for RunningServer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RunningServer").field("addr", &self.addr).finish()
    }
}

async fn bind(addr: &str, what: &str) -> Result<tokio::net::TcpListener, ServiceError> {
    tokio::net::TcpListener::bind(addr).await.map_err(|e| ServiceError::Config(format!("{what} {addr}: {e}")))
}

/// Opens the datasets (loading the models), binds the listeners and starts serving; health says
/// NOT_SERVING until a warm-up sample of the default dataset is made, then SERVING.
pub async fn start(config: ServiceConfig) -> Result<RunningServer, ServiceError> {
    config.validate()?;
    // the hot loops' instruction set, chosen once (a wrong MPIFLOW_SIMD is a start-up error)
    let simd = crate::isa::init().map_err(|e| ServiceError::Config(e.to_string()))?;
    let metrics = Arc::new(Metrics::new());
    // the token guards the API and reflection; health stays open for the probes
    let auth = RequireToken::new(config.resolved_auth_token()?, metrics.clone());
    let tls = server_tls(&config)?;
    let cfg = config.clone();
    let datasets = tokio::task::spawn_blocking(move || Datasets::open(&cfg))
        .await
        .map_err(|e| ServiceError::Internal(format!("dataset start-up: {e}")))??;
    let datasets = Arc::new(datasets);
    metrics.watch_cache(datasets.cache.clone());
    metrics.watch_datasets(datasets.clone());
    for d in datasets.all() {
        metrics.record_skips(&d.name, &d.opened_skips());
    }
    let scheduler = Scheduler::new(
        config.worker_count(),
        config.in_flight_capacity(),
        config.buffered_budget_bytes(),
        metrics.clone(),
    )?;
    let (health, health_service) = tonic_health::server::health_reporter();
    let state = Arc::new(State {
        config: config.clone(),
        datasets,
        scheduler,
        metrics: metrics.clone(),
        health,
        serving: AtomicBool::new(false),
        draining: AtomicBool::new(false),
        active_streams: AtomicUsize::new(0),
        streams_per_peer: std::sync::Mutex::new(std::collections::HashMap::new()),
        random_access_calls: std::sync::Mutex::new(std::collections::HashMap::new()),
    });
    state.set_health(ServingStatus::NotServing).await;

    let listener = bind(&config.addr, "addr").await?;
    // connection hygiene, the same on every listener (see service::conn)
    let idle = Duration::from_secs_f64(config.idle_connection_timeout_s);
    let conn_limits = super::conn::ConnLimits {
        max_connections: config.max_connections,
        max_per_peer: config.max_connections_per_peer,
        first_bytes_timeout: idle,
        stall_timeout: Duration::from_secs_f64(config.stall_timeout_s),
    };
    let addr = listener.local_addr().map_err(|e| ServiceError::Config(format!("addr: {e}")))?;
    let (metrics_addr, metrics_task) = match &config.metrics_addr {
        Some(a) => {
            let l = bind(a, "metrics_addr").await?;
            let bound = l.local_addr().map_err(|e| ServiceError::Config(format!("metrics_addr: {e}")))?;
            (Some(bound), Some(tokio::spawn(serve_metrics(l, metrics.clone()))))
        }
        None => (None, None),
    };
    // plaintext, health only: for probes that cannot do TLS (it reports until the drain ends)
    let (health_addr, health_task) = match &config.health_addr {
        Some(a) => {
            let l = bind(a, "health_addr").await?;
            let bound = l.local_addr().map_err(|e| ServiceError::Config(format!("health_addr: {e}")))?;
            let incoming = super::conn::incoming(l, conn_limits);
            let health = tonic::transport::Server::builder()
                .http2_keepalive_interval(Some(idle))
                .http2_keepalive_timeout(Some(idle))
                .layer(ReplyLayer)
                .add_service(health_service.clone());
            (Some(bound), Some(tokio::spawn(health.serve_with_incoming(incoming))))
        }
        None => (None, None),
    };

    let reflection = || {
        tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
    };
    let refl_err = |e: tonic_reflection::server::Error| ServiceError::Internal(format!("reflection: {e}"));
    let reflection_v1 = reflection().build_v1().map_err(refl_err)?;
    let reflection_v1alpha = reflection().build_v1alpha().map_err(refl_err)?;
    let limit = config.max_message_bytes() as usize;
    let max_request = config.max_request_bytes() as usize;
    let service = SampleRoutes {
        inner: MpiFlowServer::new(Service { state: state.clone() })
            .max_decoding_message_size(max_request)
            .max_encoding_message_size(limit),
        state: state.clone(),
        max_request,
        max_message: limit,
    };
    let mut builder = tonic::transport::Server::builder()
        .http2_keepalive_interval(Some(idle))
        .http2_keepalive_timeout(Some(idle))
        .max_concurrent_streams(config.max_calls_per_connection);
    if let Some(tls) = tls.clone() {
        builder = builder.tls_config(tls).map_err(|e| ServiceError::Config(format!("tls_cert / tls_key: {e}")))?;
    }
    let (tx, rx) = oneshot::channel::<()>();
    let incoming = super::conn::incoming(listener, conn_limits);
    let server = tokio::spawn(
        builder
            .layer(ReplyLayer)
            .add_service(health_service)
            .add_service(InterceptedService::new(reflection_v1, auth.clone()))
            .add_service(InterceptedService::new(reflection_v1alpha, auth.clone()))
            .add_service(InterceptedService::new(service, auth.clone()))
            .serve_with_incoming_shutdown(incoming, async {
                let _ = rx.await;
            }),
    );
    tracing::info!(
        %addr,
        metrics = ?metrics_addr,
        health = ?health_addr,
        workers = state.scheduler.workers(),
        simd = simd.name(),
        in_flight = state.scheduler.capacity(),
        max_message_bytes = limit,
        tls = tls.is_some(),
        client_certificates = config.tls_client_ca.is_some(),
        token = auth.enabled(),
        datasets = ?state.datasets.list.iter().map(|d| format!("{} ({:016x}, {} sources)", d.name, d.fingerprint(), d.sources())).collect::<Vec<_>>(),
        "listening"
    );

    let warmup = spawn_warmup(state.clone());

    Ok(RunningServer {
        addr,
        metrics_addr,
        health_addr,
        state,
        shutdown: Some(tx),
        server,
        metrics_task,
        health_task,
        warmup,
    })
}

/// The warm-up: one sample of the default dataset, then (after `warmup_delay_ms`) health
/// SERVING; on failure the server keeps running NOT_SERVING so that the failure can be seen.
fn spawn_warmup(warm: Arc<State>) -> JoinHandle<()> {
    tokio::spawn(async move {
        let t = Instant::now();
        let r = warm.one_sample(&pb::SampleRequest::default(), Client::default()).await;
        match r {
            Ok((s, _stream)) => tracing::info!(
                ms = t.elapsed().as_secs_f64() * 1e3,
                source = %s.source_id,
                "warm-up sample made"
            ),
            Err(e) => {
                tracing::error!(error = %e.message(), "warm-up sample failed: staying NOT_SERVING");
                return;
            }
        }
        tokio::time::sleep(Duration::from_millis(warm.config.warmup_delay_ms)).await;
        if !warm.draining.load(Ordering::SeqCst) {
            warm.serving.store(true, Ordering::SeqCst);
            warm.set_health(ServingStatus::Serving).await;
            tracing::info!("serving");
        }
    })
}

impl RunningServer {
    /// Graceful shutdown: health NOT_SERVING, no new connections or streams, no new samples
    /// started; every open stream sends its finished samples and ends with UNAVAILABLE and its
    /// resume cursor. Connections still open after `deadline` (a client that stopped reading) are
    /// cut.
    pub async fn shutdown(mut self, deadline: Duration) {
        let started = Instant::now();
        let state = self.state.clone();
        state.draining.store(true, Ordering::SeqCst);
        state.serving.store(false, Ordering::SeqCst);
        self.warmup.abort();
        state.set_health(ServingStatus::NotServing).await;
        tracing::info!(streams = state.active_streams(), deadline_s = deadline.as_secs_f64(), "draining");
        state.scheduler.begin_drain();
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        // the streams end by themselves once their finished samples are sent
        while state.active_streams() > 0 && started.elapsed() < deadline {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let left = state.active_streams();
        // a moment for the last frames and trailers; connections kept open by others (e.g. a
        // health Watch) are not waited for past it
        let grace = deadline.saturating_sub(started.elapsed()).min(Duration::from_secs(1));
        if tokio::time::timeout(grace, &mut self.server).await.is_err() {
            self.server.abort();
        }
        if let Some(t) = self.metrics_task.take() {
            t.abort();
        }
        if let Some(t) = self.health_task.take() {
            t.abort();
        }
        if left > 0 {
            tracing::warn!(streams = left, "drain deadline passed: open streams were cut");
        } else {
            tracing::info!(ms = started.elapsed().as_secs_f64() * 1e3, "drained");
        }
    }
}
