//! The server's life: start-up (datasets, models, listeners, health, reflection, metrics),
//! warm-up, and graceful drain ([`RunningServer`]).

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::ServerTlsConfig;
use tonic_health::pb::health_server::{Health, HealthServer};
use tonic_health::ServingStatus;

use super::handlers::Service;
use super::routes::SampleRoutes;
use super::state::State;
use crate::service::config::ServiceConfig;
use crate::service::conn::{self, ConnLimits};
use crate::service::dataset::Datasets;
use crate::service::error::ServiceError;
use crate::service::metrics::{serve_metrics, Metrics};
use crate::service::pb;
use crate::service::pb::mpi_flow_server::MpiFlowServer;
use crate::service::pool::{Client, Scheduler};
use crate::service::reply::ReplyLayer;
use crate::service::security::{server_tls, RequireToken};

/// The task of a tonic server.
type ServerTask = JoinHandle<Result<(), tonic::transport::Error>>;

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
    server: ServerTask,
    metrics_task: Option<JoinHandle<()>>,
    health_task: Option<ServerTask>,
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
    let datasets = open_datasets(&config, &metrics).await?;
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
        slot_streams: std::sync::Mutex::new(std::collections::HashSet::new()),
        slot_freed: tokio::sync::Notify::new(),
    });
    state.set_health(ServingStatus::NotServing).await;

    let listener = bind(&config.addr, "addr").await?;
    let addr = listener.local_addr().map_err(|e| ServiceError::Config(format!("addr: {e}")))?;
    let (metrics_addr, metrics_task) = spawn_metrics(&config, &metrics).await?;
    let (health_addr, health_task) = spawn_health(&config, health_service.clone()).await?;
    let (tx, server) = spawn_api(&config, &state, &auth, tls.clone(), listener, health_service)?;
    tracing::info!(
        %addr,
        metrics = ?metrics_addr,
        health = ?health_addr,
        workers = state.scheduler.workers(),
        simd = simd.name(),
        in_flight = state.scheduler.capacity(),
        max_message_bytes = config.max_message_bytes() as usize,
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

/// The datasets of the config, opened off the tokio threads (the models loaded), and watched by
/// the metrics: the cache, the datasets, and the sources each passed over when it opened.
async fn open_datasets(config: &ServiceConfig, metrics: &Arc<Metrics>) -> Result<Arc<Datasets>, ServiceError> {
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
    Ok(datasets)
}

/// The HTTP/2 keepalive interval and timeout of every listener, and its idle timeout.
fn idle_timeout(config: &ServiceConfig) -> Duration {
    Duration::from_secs_f64(config.idle_connection_timeout_s)
}

/// Connection hygiene, the same on every listener (see service::conn); `tls`: whether the
/// listener's connections carry TLS (their HTTP/2 frames cannot be told apart below it).
fn conn_limits(config: &ServiceConfig, tls: bool) -> ConnLimits {
    ConnLimits {
        max_connections: config.max_connections,
        max_per_peer: config.max_connections_per_peer,
        first_bytes_timeout: idle_timeout(config),
        stall_timeout: Duration::from_secs_f64(config.stall_timeout_s),
        max_waiting_per_peer: config.max_calls_per_connection as usize,
        frames_in_clear: !tls,
    }
}

/// The metrics listener, when `metrics_addr` is set: its bound address and its task.
async fn spawn_metrics(
    config: &ServiceConfig,
    metrics: &Arc<Metrics>,
) -> Result<(Option<SocketAddr>, Option<JoinHandle<()>>), ServiceError> {
    Ok(match &config.metrics_addr {
        Some(a) => {
            let l = bind(a, "metrics_addr").await?;
            let bound = l.local_addr().map_err(|e| ServiceError::Config(format!("metrics_addr: {e}")))?;
            (Some(bound), Some(tokio::spawn(serve_metrics(l, metrics.clone()))))
        }
        None => (None, None),
    })
}

/// The plaintext, health-only listener, when `health_addr` is set: for probes that cannot do TLS
/// (it reports until the drain ends). Its bound address and its task.
async fn spawn_health<H: Health>(
    config: &ServiceConfig,
    health_service: HealthServer<H>,
) -> Result<(Option<SocketAddr>, Option<ServerTask>), ServiceError> {
    Ok(match &config.health_addr {
        Some(a) => {
            let l = bind(a, "health_addr").await?;
            let bound = l.local_addr().map_err(|e| ServiceError::Config(format!("health_addr: {e}")))?;
            let incoming = conn::incoming(l, conn_limits(config, false));
            let idle = idle_timeout(config);
            let health = tonic::transport::Server::builder()
                .http2_keepalive_interval(Some(idle))
                .http2_keepalive_timeout(Some(idle))
                .layer(ReplyLayer { request_deadline: idle })
                .add_service(health_service);
            (Some(bound), Some(tokio::spawn(health.serve_with_incoming(incoming))))
        }
        None => (None, None),
    })
}

/// The API on `listener`: health, reflection (v1 and v1alpha) and `mpiflow.v1.MpiFlow` (its sample
/// streams by [`SampleRoutes`]), the token checked on all but health, TLS when configured. The
/// sender that starts its graceful shutdown, and its task.
fn spawn_api<H: Health>(
    config: &ServiceConfig,
    state: &Arc<State>,
    auth: &RequireToken,
    tls: Option<ServerTlsConfig>,
    listener: tokio::net::TcpListener,
    health_service: HealthServer<H>,
) -> Result<(oneshot::Sender<()>, ServerTask), ServiceError> {
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
    let idle = idle_timeout(config);
    let mut builder = tonic::transport::Server::builder()
        .http2_keepalive_interval(Some(idle))
        .http2_keepalive_timeout(Some(idle))
        .max_concurrent_streams(config.max_calls_per_connection);
    let limits = conn_limits(config, tls.is_some());
    if let Some(tls) = tls {
        builder = builder.tls_config(tls).map_err(|e| ServiceError::Config(format!("tls_cert / tls_key: {e}")))?;
    }
    let (tx, rx) = oneshot::channel::<()>();
    let incoming = conn::incoming(listener, limits);
    let server = tokio::spawn(
        builder
            .layer(ReplyLayer { request_deadline: idle })
            .add_service(health_service)
            .add_service(InterceptedService::new(reflection_v1, auth.clone()))
            .add_service(InterceptedService::new(reflection_v1alpha, auth.clone()))
            .add_service(InterceptedService::new(service, auth.clone()))
            .serve_with_incoming_shutdown(incoming, async {
                let _ = rx.await;
            }),
    );
    Ok((tx, server))
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
