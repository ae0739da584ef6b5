//! The gRPC server and the command line, driven by real clients on loopback (service, auth,
//! configuration, overload and fairness, shards, uploads, model downloads), and the house's own
//! rules (the documented commands, the layering).
//! One test binary per group (each file beside this one is a module), so that the suite links a
//! handful of binaries.

mod cli_errors;
mod config_env;
mod docs_commands;
mod fairness;
mod hub_downloads;
mod layers;
mod overload;
mod random_access;
mod service;
mod service_auth;
mod service_config;
mod service_data;
mod shards;
mod soak;
mod uploads;
