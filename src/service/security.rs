//! Transport security and the bearer token: the server's TLS configuration (rustls through
//! tonic, optional client certificates) and the interceptor that checks `authorization: Bearer
//! TOKEN` on the calls it guards (`mpiflow.v1.MpiFlow` and reflection; never `grpc.health.v1`,
//! which the probes call). Both are off unless configured.

use std::sync::Arc;

use subtle::ConstantTimeEq;
use tonic::service::Interceptor;
use tonic::transport::{Certificate, Identity, ServerTlsConfig};
use tonic::{Code, Request, Status};

use super::config::ServiceConfig;
use super::error::ServiceError;
use super::metrics::Metrics;

/// The header the token travels in.
pub const AUTHORIZATION: &str = "authorization";

fn read_pem(what: &str, path: &std::path::Path) -> Result<Vec<u8>, ServiceError> {
    let bytes = std::fs::read(path).map_err(|e| ServiceError::Config(format!("{what} {}: {e}", path.display())))?;
    if !bytes.windows(11).any(|w| w == b"-----BEGIN ") {
        return Err(ServiceError::Config(format!("{what} {}: not a PEM file", path.display())));
    }
    Ok(bytes)
}

/// The server's TLS configuration (`tls_cert`, `tls_key`, `tls_client_ca`); none = plaintext.
/// Files are read here, so a missing or unreadable file fails the start-up, naming the key.
pub fn server_tls(config: &ServiceConfig) -> Result<Option<ServerTlsConfig>, ServiceError> {
    let (Some(cert), Some(key)) = (&config.tls_cert, &config.tls_key) else {
        return Ok(None);
    };
    let identity = Identity::from_pem(read_pem("tls_cert", cert)?, read_pem("tls_key", key)?);
    let mut tls = ServerTlsConfig::new().identity(identity).timeout(std::time::Duration::from_secs(10));
    if let Some(ca) = &config.tls_client_ca {
        tls = tls.client_ca_root(Certificate::from_pem(read_pem("tls_client_ca", ca)?)).client_auth_optional(false);
    }
    Ok(Some(tls))
}

/// The server's token check: with a token configured, a call without `authorization: Bearer
/// TOKEN`, or with another token, is refused with UNAUTHENTICATED before its handler runs. The
/// comparison takes the same time wherever the tokens differ.
#[derive(Clone)]
pub struct RequireToken {
    token: Option<Arc<[u8]>>,
    metrics: Arc<Metrics>,
}

impl std::fmt::Debug for RequireToken {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RequireToken").field("enabled", &self.token.is_some()).finish()
    }
}

impl RequireToken {
    pub fn new(token: Option<String>, metrics: Arc<Metrics>) -> Self {
        Self { token: token.map(|t| Arc::from(t.into_bytes())), metrics }
    }

    pub fn enabled(&self) -> bool {
        self.token.is_some()
    }

    fn check<T>(&self, request: &Request<T>) -> Result<(), Status> {
        let Some(want) = &self.token else { return Ok(()) };
        let refuse = |message: &str| {
            self.metrics.count_refused(Code::Unauthenticated);
            tracing::info!(error = message, "request refused");
            Err(Status::unauthenticated(message))
        };
        let Some(value) = request.metadata().get(AUTHORIZATION) else {
            return refuse("missing bearer token: send the header `authorization: Bearer TOKEN`");
        };
        let value = value.as_bytes();
        let Some(token) = bearer(value) else {
            return refuse("malformed authorization header: expected `Bearer TOKEN`");
        };
        if bool::from(token.ct_eq(want)) {
            Ok(())
        } else {
            refuse("invalid bearer token")
        }
    }
}

/// The token of `Bearer TOKEN` (the scheme in any case).
fn bearer(value: &[u8]) -> Option<&[u8]> {
    let (scheme, rest) = value.split_at_checked(7)?;
    if !scheme.eq_ignore_ascii_case(b"bearer ") {
        return None;
    }
    let token = rest.trim_ascii();
    (!token.is_empty()).then_some(token)
}

impl Interceptor for RequireToken {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        self.check(&request)?;
        Ok(request)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn req(header: Option<&str>) -> Request<()> {
        let mut r = Request::new(());
        if let Some(h) = header {
            r.metadata_mut().insert(AUTHORIZATION, h.parse().unwrap());
        }
        r
    }

    #[test]
    fn bearer_token_check() {
        let m = Arc::new(Metrics::new());
        let off = RequireToken::new(None, m.clone());
        assert!(off.check(&req(None)).is_ok());
        let on = RequireToken::new(Some("s3cret".into()), m);
        assert!(on.check(&req(Some("Bearer s3cret"))).is_ok());
        assert!(on.check(&req(Some("bearer s3cret"))).is_ok());
        for (h, msg) in [
            (None, "missing"),
            (Some("Bearer s3cre"), "invalid"),
            (Some("Bearer s3cret2"), "invalid"),
            (Some("Bearer "), "malformed"),
            (Some("Basic s3cret"), "malformed"),
            (Some("s3cret"), "malformed"),
        ] {
            let e = on.check(&req(h)).unwrap_err();
            assert_eq!(e.code(), Code::Unauthenticated, "{h:?}");
            assert!(e.message().contains(msg), "{h:?}: {}", e.message());
        }
    }
}
