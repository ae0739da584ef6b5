//! `mpiflow health`: a `grpc.health.v1` check (for container health checks): exit code 0 only
//! when the service answers SERVING.

use std::time::Duration;

use clap::Args;
use mpiflow::service::client::BearerToken;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

use super::connect::ConnectArgs;
use super::CliError;

#[derive(Args, Debug)]
pub struct HealthArgs {
    /// Server address (HOST:PORT; https://HOST:PORT or --tls-ca for TLS).
    #[arg(long, value_name = "HOST:PORT", default_value = mpiflow::service::config::DEFAULT_ADDR)]
    addr: String,
    /// TLS options (health needs no token; one given is sent anyway).
    #[command(flatten)]
    connect: ConnectArgs,
    /// The service to ask about ("" = the whole server, or mpiflow.v1.MpiFlow).
    #[arg(long, value_name = "NAME", default_value = "")]
    service: String,
    /// Give up after this many seconds.
    #[arg(long, value_name = "T", default_value_t = 5.0)]
    timeout_s: f64,
}

pub fn run(a: HealthArgs) -> Result<(), CliError> {
    if !(a.timeout_s.is_finite() && a.timeout_s > 0.0) {
        return Err(CliError(format!("--timeout-s {}: expected a positive number of seconds", a.timeout_s)));
    }
    let timeout = Duration::from_secs_f64(a.timeout_s);
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| CliError(format!("cannot start the async runtime: {e}")))?;
    let status = rt.block_on(async {
        let check = async {
            let options = a.connect.options()?;
            let channel = mpiflow::service::client::channel(&a.addr, &options)
                .await
                .map_err(|e| CliError(format!("{}: {e}", a.addr)))?;
            let token = BearerToken::new(options.token.as_deref()).map_err(|e| CliError(e.to_string()))?;
            let r = HealthClient::with_interceptor(channel, token)
                .check(HealthCheckRequest { service: a.service.clone() })
                .await
                .map_err(|s| CliError(format!("{}: {:?}: {}", a.addr, s.code(), s.message())))?;
            Ok::<_, CliError>(r.into_inner().status)
        };
        tokio::time::timeout(timeout, check)
            .await
            .map_err(|_| CliError(format!("{}: no answer within {} s", a.addr, a.timeout_s)))?
    })?;
    let status = ServingStatus::try_from(status).unwrap_or(ServingStatus::Unknown);
    println!("{}", status.as_str_name());
    if status == ServingStatus::Serving {
        Ok(())
    } else {
        Err(CliError(format!("{} is {}", a.addr, status.as_str_name())))
    }
}
