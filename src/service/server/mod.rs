//! The tonic service (`mpiflow.v1.MpiFlow`) and the server around it: start-up (datasets, models,
//! listener, health, reflection, metrics), warm-up, and graceful drain. Handlers stay thin:
//! validate, call the domain (dataset, pool), convert back. The sample streams' replies are
//! written by [`super::frames`] through `SampleRoutes`, in front of the generated service.
//!
//! The rooms, from the ground up: `state` (what the handlers share), `admission` (the
//! per-call limits, a call's client and its refusal), `job` (a request's spec made ready, the
//! job that makes its samples), `calls` (the calls' work on the state), `routes` (the sample
//! streams' route), `handlers` (the generated service's handlers), `lifecycle` (start-up,
//! warm-up, drain).

mod admission;
mod calls;
mod handlers;
mod job;
mod lifecycle;
mod routes;
mod state;

pub use admission::{streams_per_peer, CountedStream};
pub use handlers::Service;
pub use lifecycle::{start, RunningServer};
pub use state::{State, SERVICE_NAME};
