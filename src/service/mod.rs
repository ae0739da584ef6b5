//! The gRPC sample service (`mpiflow.v1.MpiFlow`): a thin tonic layer over the sample generator.
//!
//! A request's sample options ([`spec`]: one message for all three calls) are validated once
//! ([`validate`]), resolved to a dataset and a generator ([`dataset`]), and served through the
//! worker pool ([`pool`]: rayon workers, a bounded queue per stream, a global in-flight bound,
//! round-robin between streams); samples are made (a request's crop over its window only:
//! [`crate::sample::crop`]) and encoded on the workers ([`encode`], a
//! tensor's bytes made from the sample's buffers without copies: [`tensor`]); [`codec`] puts the
//! messages on the wire, and [`frames`] the sample streams', their tensors uncopied.
//! Errors map to gRPC codes in one place ([`error`]). The server ([`server`]) adds health,
//! reflection, Prometheus [`metrics`] and graceful drain; [`config`] holds the keys, read from
//! the TOML file, the `MPIFLOW_*` variables and the flags, layered ([`layers`]); [`security`]
//! the optional TLS and bearer-token check; [`conn`] the listeners' connection bounds and timeouts,
//! [`stall`] the cut of a client that stops taking data, [`progress`] what counts as taken (DATA,
//! never a PING ACK); [`client`] is the Rust client side used by
//! `mpiflow pull` and the tests. The API and its guarantees: `docs/api.md`.

/// The generated protobuf messages and the tonic server and client of `mpiflow.v1`.
#[allow(clippy::all, missing_docs)]
pub mod pb {
    tonic::include_proto!("mpiflow.v1");

    /// The encoded file descriptor set of the API (for gRPC reflection).
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("mpiflow_descriptor");
}

pub mod client;
pub mod codec;
pub mod config;
pub mod conn;
pub mod dataset;
pub mod encode;
pub mod error;
pub mod frames;
pub mod layers;
pub mod metrics;
pub mod peer;
pub mod pool;
pub mod progress;
pub mod reply;
pub mod security;
pub mod server;
pub mod spec;
pub mod stall;
pub mod tensor;
pub mod validate;
pub mod work;

pub use config::ServiceConfig;
pub use error::ServiceError;
pub use server::{start, RunningServer};
