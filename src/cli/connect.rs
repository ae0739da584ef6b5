//! The client-side connection flags of `mpiflow pull` and `mpiflow health`: TLS and the bearer
//! token.

use std::path::PathBuf;

use clap::Args;
use mpiflow::service::client::ClientOptions;

use super::CliError;

#[derive(Args, Debug, Clone, Default)]
pub struct ConnectArgs {
    /// Bearer token sent as `authorization: Bearer TOKEN` (the server's auth_token).
    #[arg(long, value_name = "TOKEN", conflicts_with = "token_file")]
    token: Option<String>,
    /// Read the bearer token from a file (keeps it out of the process list).
    #[arg(long, value_name = "FILE")]
    token_file: Option<PathBuf>,
    /// Connect with TLS, trusting the server certificate's CA in this PEM file.
    #[arg(long, value_name = "FILE")]
    tls_ca: Option<PathBuf>,
    /// Client certificate (PEM) for servers that require one (with --tls-key).
    #[arg(long, value_name = "FILE", requires = "tls_key", requires = "tls_ca")]
    tls_cert: Option<PathBuf>,
    /// Private key (PEM) of --tls-cert.
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// The name the server certificate must carry (default: the host of --addr).
    #[arg(long, value_name = "NAME", requires = "tls_ca")]
    tls_domain: Option<String>,
}

impl ConnectArgs {
    pub fn options(&self) -> Result<ClientOptions, CliError> {
        let token = match (&self.token, &self.token_file) {
            (Some(t), _) => Some(t.trim().to_string()),
            (None, Some(p)) => Some(
                std::fs::read_to_string(p)
                    .map_err(|e| CliError(format!("--token-file {}: {e}", p.display())))?
                    .trim()
                    .to_string(),
            ),
            (None, None) => None,
        };
        Ok(ClientOptions {
            token: token.filter(|t| !t.is_empty()),
            tls_ca: self.tls_ca.clone(),
            tls_cert: self.tls_cert.clone(),
            tls_key: self.tls_key.clone(),
            tls_domain: self.tls_domain.clone(),
            local_address: None,
        })
    }
}
