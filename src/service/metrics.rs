//! Prometheus metrics of the service (the `prometheus-client` crate, OpenMetrics text) and the
//! small HTTP endpoint that serves them on `GET /metrics`.

use std::collections::BTreeMap;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex};

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;
use tokio::net::TcpListener;

use crate::sample::error::SampleError;
use crate::sample::StageTimings;
use crate::scene::cache::SceneCache;
use crate::source::FailureKind;

use super::dataset::Datasets;

type Labels = Vec<(String, String)>;

fn label(k: &str, v: impl Into<String>) -> Labels {
    vec![(k.to_string(), v.into())]
}

fn stage_histogram() -> Histogram {
    // 0.25 ms to ~8 s
    Histogram::new(exponential_buckets(0.000_25, 2.0, 16))
}

/// Every metric of one server.
pub struct Metrics {
    registry: Registry,
    /// Samples made by the workers (for every stream and GetSample).
    pub samples_generated: Counter,
    /// Samples handed to the transport in StreamSamples batches.
    pub samples_sent: Counter,
    /// Encoded bytes of the batches handed to the transport.
    pub bytes_sent: Counter,
    /// Samples that could not be made, by reason.
    pub generation_errors: Family<Labels, Counter>,
    /// Bad source items found so far (each passed over deterministically), by dataset and reason.
    pub skipped_sources: Family<Labels, Gauge>,
    /// Seconds per stage of the recipe (from `Sample.timings`) and of the encoding.
    pub stage_seconds: Family<Labels, Histogram, fn() -> Histogram>,
    /// Finished samples waiting in each stream's queue.
    pub queue_depth: Family<Labels, Gauge>,
    pub active_streams: Gauge,
    /// Samples being made now.
    pub in_flight: Gauge,
    /// Bytes of samples made but not yet sent, over all streams, and their budget.
    pub buffered_bytes: Gauge,
    pub buffered_budget: Gauge,
    /// The most `buffered_bytes` has been since the server started.
    pub buffered_peak: Gauge,
    /// Finished samples dropped to bring a stream back to its share of the budget.
    pub samples_dropped: Counter,
    /// Connections closed because they held made samples they did not take while another client
    /// needed the room.
    pub holders_cut: Counter,
    /// The in-flight bound.
    pub capacity: Gauge,
    /// in_flight / capacity (0 to 1): the autoscaling signal.
    pub saturation: Gauge<f64, AtomicU64>,
    /// Worker seconds spent making samples (rate / workers = worker utilisation).
    pub busy_seconds: Counter<f64, AtomicU64>,
    pub workers: Gauge,
    /// Requests refused, by gRPC code.
    pub refused: Family<Labels, Counter>,
    /// Seconds per scene build (load, models, MPI) (`mpiflow_scene_seconds`).
    pub scene_seconds: Histogram,
    cache_hits: Counter,
    cache_misses: Counter,
    cache_evictions: Counter,
    cache_bytes: Gauge,
    cache_seen: Mutex<(u64, u64, u64)>,
    cache: Mutex<Option<Arc<SceneCache>>>,
    /// Scenes actually built, by dataset (`mpiflow_scene_builds_total`), read from the datasets'
    /// generators at every scrape.
    pub scene_builds: Family<Labels, Counter>,
    /// Inferences of the scene models, by role (`mpiflow_model_runs_total`), read from the
    /// models at every scrape (warm-up runs excluded): 0 while every scene comes baked.
    pub model_runs: Family<Labels, Counter>,
    model_runs_seen: Mutex<BTreeMap<&'static str, u64>>,
    datasets: Mutex<Option<Arc<Datasets>>>,
    /// Per dataset name: the generator counted (its address) and the builds counted so far.
    builds_seen: Mutex<BTreeMap<String, (usize, u64)>>,
    skipped_by_dataset: Mutex<BTreeMap<(String, String), u64>>,
}

impl std::fmt::Debug for Metrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Metrics")
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let mut r = Registry::with_prefix("mpiflow");
        let m = Metrics {
            registry: Registry::default(),
            samples_generated: Counter::default(),
            samples_sent: Counter::default(),
            bytes_sent: Counter::default(),
            generation_errors: Family::default(),
            skipped_sources: Family::default(),
            stage_seconds: Family::new_with_constructor(stage_histogram as fn() -> Histogram),
            queue_depth: Family::default(),
            active_streams: Gauge::default(),
            in_flight: Gauge::default(),
            buffered_bytes: Gauge::default(),
            buffered_budget: Gauge::default(),
            buffered_peak: Gauge::default(),
            samples_dropped: Counter::default(),
            holders_cut: Counter::default(),
            capacity: Gauge::default(),
            saturation: Gauge::default(),
            busy_seconds: Counter::default(),
            workers: Gauge::default(),
            refused: Family::default(),
            // 1 ms to ~2 min: a scene with real models takes tens of seconds
            scene_seconds: Histogram::new(exponential_buckets(0.001, 2.0, 18)),
            cache_hits: Counter::default(),
            cache_misses: Counter::default(),
            cache_evictions: Counter::default(),
            cache_bytes: Gauge::default(),
            cache_seen: Mutex::new((0, 0, 0)),
            cache: Mutex::new(None),
            scene_builds: Family::default(),
            model_runs: Family::default(),
            model_runs_seen: Mutex::new(BTreeMap::new()),
            datasets: Mutex::new(None),
            builds_seen: Mutex::new(BTreeMap::new()),
            skipped_by_dataset: Mutex::new(BTreeMap::new()),
        };
        r.register("samples_generated", "Samples made by the workers", m.samples_generated.clone());
        r.register("samples_sent", "Samples handed to the transport in stream batches", m.samples_sent.clone());
        r.register("bytes_sent", "Encoded bytes of the stream batches handed to the transport", m.bytes_sent.clone());
        r.register("generation_errors", "Samples that could not be made, by reason", m.generation_errors.clone());
        r.register("skipped_sources", "Bad sources passed over, by reason", m.skipped_sources.clone());
        r.register(
            "stage_seconds",
            "Seconds per sample stage (scene, render, objects, merge, inpaint, encode, total)",
            m.stage_seconds.clone(),
        );
        r.register("stream_queue_depth", "Finished samples waiting in a stream's queue", m.queue_depth.clone());
        r.register("active_streams", "Open StreamSamples calls", m.active_streams.clone());
        r.register("in_flight_jobs", "Samples being made now", m.in_flight.clone());
        r.register(
            "buffered_bytes",
            "Bytes of samples being made and made but not yet sent, over all streams (reservations, queues, transport)",
            m.buffered_bytes.clone(),
        );
        r.register("buffered_budget_bytes", "Budget of buffered_bytes (max_buffered_mb)", m.buffered_budget.clone());
        r.register("buffered_peak_bytes", "The most buffered_bytes has been since the start", m.buffered_peak.clone());
        r.register(
            "samples_dropped",
            "Finished samples dropped to bring a stream back to its share of the budget (made again when read)",
            m.samples_dropped.clone(),
        );
        r.register(
            "holders_cut",
            "Connections closed for holding made samples they did not take while another client needed the room",
            m.holders_cut.clone(),
        );
        r.register("in_flight_capacity", "Bound on samples being made at once", m.capacity.clone());
        r.register("saturation", "in_flight_jobs / in_flight_capacity (0 to 1), for autoscaling", m.saturation.clone());
        r.register("worker_busy_seconds", "Worker seconds spent making samples", m.busy_seconds.clone());
        r.register("workers", "Generation threads", m.workers.clone());
        r.register("requests_refused", "Requests refused, by gRPC code", m.refused.clone());
        r.register(
            "scene_seconds",
            "Seconds per scene build (source load, scene models, MPI), on the scene pool",
            m.scene_seconds.clone(),
        );
        r.register("scene_cache_hits", "Scene cache lookups answered from the cache", m.cache_hits.clone());
        r.register("scene_cache_misses", "Scene cache lookups that loaded the scene", m.cache_misses.clone());
        r.register("scene_cache_evictions", "Scenes evicted from the cache", m.cache_evictions.clone());
        r.register("scene_cache_bytes", "Bytes held by the scene cache", m.cache_bytes.clone());
        r.register("scene_builds", "Scenes actually built (models run), by dataset", m.scene_builds.clone());
        r.register(
            "model_runs",
            "Inferences of the scene models (warm-up excluded), by role: depth, mpi, segment",
            m.model_runs.clone(),
        );
        Metrics { registry: r, ..m }
    }

    /// Reports this cache's statistics at every scrape.
    pub fn watch_cache(&self, cache: Arc<SceneCache>) {
        let h = self.scene_seconds.clone();
        cache.observe_loads(Box::new(move |s| h.observe(s)));
        *self.cache.lock().unwrap_or_else(std::sync::PoisonError::into_inner) = Some(cache);
    }

    /// Reports these datasets' scene builds at every scrape.
    pub fn watch_datasets(&self, datasets: Arc<Datasets>) {
        *self.datasets.lock().unwrap_or_else(std::sync::PoisonError::into_inner) = Some(datasets);
    }

    fn update_builds(&self) {
        let datasets = self.datasets.lock().unwrap_or_else(std::sync::PoisonError::into_inner).clone();
        let Some(datasets) = datasets else { return };
        {
            let mut seen = self.model_runs_seen.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            for (role, runs) in datasets.stage.model_runs() {
                let slot = seen.entry(role).or_insert(0);
                // created at 0 so that a scrape shows every configured model
                let c = self.model_runs.get_or_create(&label("role", role));
                if runs > *slot {
                    c.inc_by(runs - *slot);
                    *slot = runs;
                }
            }
        }
        let mut seen = self.builds_seen.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        for d in datasets.all() {
            let id = Arc::as_ptr(&d.generator) as usize;
            let total = d.scene_builds();
            let slot = seen.entry(d.name.clone()).or_insert((id, 0));
            if slot.0 != id {
                // an uploaded dataset was made anew: its generator counts from 0
                *slot = (id, 0);
            }
            if total > slot.1 {
                self.scene_builds.get_or_create(&label("dataset", d.name.clone())).inc_by(total - slot.1);
                slot.1 = total;
            }
        }
    }

    /// Records the stage timings of a made sample and its encoding time.
    pub fn observe_sample(&self, t: &StageTimings, encode_ms: f64) {
        self.samples_generated.inc();
        let stages = [
            ("scene", t.scene_ms),
            ("render", t.render_ms),
            ("objects", t.objects_ms),
            ("merge", t.merge_ms),
            ("inpaint", t.inpaint_ms),
            ("encode", encode_ms),
            ("total", t.total_ms + encode_ms),
        ];
        for (stage, ms) in stages {
            self.stage_seconds.get_or_create(&label("stage", stage)).observe(ms / 1e3);
        }
    }

    /// Counts a sample that could not be made.
    pub fn observe_error(&self, e: &SampleError) {
        let reason = match e {
            SampleError::Scene { .. } => "source",
            SampleError::NoGoodSource { .. } => "no-good-source",
            SampleError::InvalidScene { .. } => "invalid-scene",
            SampleError::Render { .. } => "render",
            SampleError::Preblend { .. } => "preblend",
            SampleError::EmptySource => "empty",
            SampleError::Crop(_) => "crop",
            SampleError::Config { .. } | SampleError::Motion(_) | SampleError::Unusable(_) => "config",
        };
        self.generation_errors.get_or_create(&label("reason", reason)).inc();
    }

    /// Records the bad source items of `dataset` known so far, by failure kind (a generator's
    /// [`skip_counts`](crate::sample::pipeline::Generator::skip_counts), or what a source left out
    /// when opened); the `reason` label is [`FailureKind::as_str`]. Counts only grow. True when a
    /// count grew (something new was skipped).
    pub fn record_skips(&self, dataset: &str, counts: &BTreeMap<FailureKind, u64>) -> bool {
        let mut grew = false;
        let mut m = self.skipped_by_dataset.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        for (&kind, &n) in counts {
            let reason = kind.as_str().to_string();
            let slot = m.entry((dataset.to_string(), reason.clone())).or_default();
            if n > *slot {
                *slot = n;
                grew = true;
                let labels = vec![("dataset".to_string(), dataset.to_string()), ("reason".to_string(), reason)];
                self.skipped_sources.get_or_create(&labels).set(n as i64);
            }
        }
        grew
    }

    /// Skipped sources of a dataset by reason (for GetInfo).
    pub fn skipped_of(&self, dataset: &str) -> std::collections::HashMap<String, u64> {
        let m = self.skipped_by_dataset.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        m.iter().filter(|((d, _), _)| d == dataset).map(|((_, r), n)| (r.clone(), *n)).collect()
    }

    /// Sets the in-flight gauges.
    pub fn set_in_flight(&self, in_flight: usize, capacity: usize) {
        self.in_flight.set(in_flight as i64);
        self.capacity.set(capacity as i64);
        self.saturation.set(if capacity == 0 { 0.0 } else { in_flight as f64 / capacity as f64 });
    }

    /// Sets the buffered-bytes gauges.
    pub fn set_buffered(&self, bytes: u64, budget: u64) {
        let bytes = i64::try_from(bytes).unwrap_or(i64::MAX);
        self.buffered_bytes.set(bytes);
        // the peak only grows (a reading that races another keeps the larger)
        let mut peak = self.buffered_peak.get();
        while bytes > peak {
            match self.buffered_peak.inner().compare_exchange(
                peak,
                bytes,
                std::sync::atomic::Ordering::AcqRel,
                std::sync::atomic::Ordering::Acquire,
            ) {
                Ok(_) => break,
                Err(now) => peak = now,
            }
        }
        self.buffered_budget.set(i64::try_from(budget).unwrap_or(i64::MAX));
    }

    pub fn set_queue_depth(&self, stream: u64, depth: usize) {
        self.queue_depth.get_or_create(&label("stream", stream.to_string())).set(depth as i64);
    }

    pub fn remove_stream(&self, stream: u64) {
        self.queue_depth.remove(&label("stream", stream.to_string()));
    }

    pub fn count_refused(&self, code: tonic::Code) {
        self.refused.get_or_create(&label("code", format!("{code:?}"))).inc();
    }

    fn update_cache(&self) {
        let cache = self.cache.lock().unwrap_or_else(std::sync::PoisonError::into_inner).clone();
        if let Some(c) = cache {
            let s = c.stats();
            let mut seen = self.cache_seen.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            self.cache_hits.inc_by(s.hits.saturating_sub(seen.0));
            self.cache_misses.inc_by(s.misses.saturating_sub(seen.1));
            self.cache_evictions.inc_by(s.evictions.saturating_sub(seen.2));
            *seen = (seen.0.max(s.hits), seen.1.max(s.misses), seen.2.max(s.evictions));
            self.cache_bytes.set(s.bytes as i64);
        }
    }

    /// The OpenMetrics text of every metric.
    pub fn render(&self) -> String {
        self.update_cache();
        self.update_builds();
        let mut out = String::new();
        // writing into a String cannot fail
        let _ = encode(&mut out, &self.registry);
        out
    }
}

/// Serves `GET /metrics` (and `GET /healthz`, always 200) on `listener` until the task is
/// dropped, over hyper's HTTP/1.1: one request per connection, [`METRICS_CONNECTIONS`] at once.
pub async fn serve_metrics(listener: TcpListener, metrics: Arc<Metrics>) {
    let slots = Arc::new(tokio::sync::Semaphore::new(METRICS_CONNECTIONS));
    loop {
        let Ok((sock, _)) = listener.accept().await else { continue };
        // a bounded number of scrapes at once; more are closed as they arrive
        let Ok(slot) = slots.clone().try_acquire_owned() else { continue };
        let metrics = metrics.clone();
        tokio::spawn(async move {
            let service = hyper::service::service_fn(move |req: http::Request<hyper::body::Incoming>| {
                let response = respond(&metrics, req.method(), req.uri().path());
                async move { Ok::<_, std::convert::Infallible>(response) }
            });
            // one request per connection, its head within 5 s, the whole exchange within 30 s
            let conn = hyper::server::conn::http1::Builder::new()
                .timer(hyper_util::rt::TokioTimer::new())
                .header_read_timeout(std::time::Duration::from_secs(5))
                .keep_alive(false)
                .serve_connection(hyper_util::rt::TokioIo::new(sock), service);
            let _ = tokio::time::timeout(std::time::Duration::from_secs(30), conn).await;
            drop(slot);
        });
    }
}

/// Scrapes served at once by the metrics endpoint.
const METRICS_CONNECTIONS: usize = 16;

/// The answer of the metrics endpoint: `GET /metrics` (OpenMetrics text), `GET /healthz`, else 404.
fn respond(metrics: &Metrics, method: &http::Method, path: &str) -> http::Response<http_body_util::Full<bytes::Bytes>> {
    let (status, ctype, body) = match (method == http::Method::GET, path) {
        (true, "/metrics") => {
            (http::StatusCode::OK, "application/openmetrics-text; version=1.0.0; charset=utf-8", metrics.render())
        }
        (true, "/healthz") => (http::StatusCode::OK, "text/plain", "ok\n".to_string()),
        _ => (http::StatusCode::NOT_FOUND, "text/plain", "not found: try /metrics\n".to_string()),
    };
    let mut r = http::Response::new(http_body_util::Full::new(bytes::Bytes::from(body)));
    *r.status_mut() = status;
    r.headers_mut().insert(http::header::CONTENT_TYPE, http::HeaderValue::from_static(ctype));
    r
}
