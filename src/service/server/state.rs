//! What the handlers share ([`State`]): the configuration, the datasets, the worker pool, the
//! metrics, the health reporter, and the counters of the calls open now.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;

use tonic_health::server::HealthReporter;
use tonic_health::ServingStatus;

use crate::service::config::ServiceConfig;
use crate::service::dataset::Datasets;
use crate::service::metrics::Metrics;
use crate::service::peer::PeerKey;
use crate::service::pool::Scheduler;

/// The gRPC service name health reports on (besides "").
pub const SERVICE_NAME: &str = "mpiflow.v1.MpiFlow";

/// What the handlers share.
pub struct State {
    pub config: ServiceConfig,
    pub datasets: Arc<Datasets>,
    pub scheduler: Arc<Scheduler>,
    pub metrics: Arc<Metrics>,
    pub(super) health: HealthReporter,
    pub(super) serving: AtomicBool,
    pub(super) draining: AtomicBool,
    pub(super) active_streams: AtomicUsize,
    /// StreamSamples calls open now per peer (at most half of `max_streams`).
    pub(super) streams_per_peer: std::sync::Mutex<std::collections::HashMap<PeerKey, usize>>,
    /// The pool's ids of the streams that hold a slot of `max_streams` (StreamSamples calls).
    pub(super) slot_streams: std::sync::Mutex<std::collections::HashSet<u64>>,
    /// Woken when a slot of `max_streams` is given back.
    pub(super) slot_freed: tokio::sync::Notify,
    /// GetSample and GetSamples calls open now per peer (`max_random_access_calls`), replies not
    /// yet sent included.
    pub(super) random_access_calls: std::sync::Mutex<std::collections::HashMap<PeerKey, usize>>,
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

    pub(super) async fn set_health(&self, status: ServingStatus) {
        self.health.set_service_status("", status).await;
        self.health.set_service_status(SERVICE_NAME, status).await;
    }
}
