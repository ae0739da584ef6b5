//! The Rust client side: connecting (TLS and the bearer token as [`ClientOptions`] say) with the
//! raised message limit, and pulling a stream while
//! measuring what a trainer sees (samples/s, bytes/s, time to first sample, gaps between samples).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use prost::Message;
use tonic::metadata::{Ascii, MetadataValue};
use tonic::service::interceptor::InterceptedService;
use tonic::service::Interceptor;
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint, Identity};
use tonic::{Request, Status};

use super::config::MAX_MESSAGE_CAP;
use super::error::cursor_of;
use super::pb;
use super::pb::mpi_flow_client::MpiFlowClient;

/// How to reach a server: TLS (on with `tls_ca` or an `https://` address) and the bearer token.
#[derive(Clone, Default)]
pub struct ClientOptions {
    /// Sent as `authorization: Bearer TOKEN` on every call.
    pub token: Option<String>,
    /// The CA that signed the server's certificate (PEM); turns TLS on.
    pub tls_ca: Option<PathBuf>,
    /// A client certificate (PEM) with its key, for servers that require one.
    pub tls_cert: Option<PathBuf>,
    pub tls_key: Option<PathBuf>,
    /// The name the server's certificate must carry (default: the address's host).
    pub tls_domain: Option<String>,
    /// The local address to connect from (default: the system's choice).
    pub local_address: Option<std::net::IpAddr>,
}

impl std::fmt::Debug for ClientOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClientOptions")
            .field("token", &self.token.as_ref().map(|_| "***"))
            .field("tls_ca", &self.tls_ca)
            .field("tls_cert", &self.tls_cert)
            .field("tls_key", &self.tls_key)
            .field("tls_domain", &self.tls_domain)
            .finish()
    }
}

impl ClientOptions {
    /// Whether the connection to `addr` uses TLS.
    pub fn tls(&self, addr: &str) -> bool {
        self.tls_ca.is_some() || addr.starts_with("https://")
    }
}

/// A connection failure: bad options or files, or the transport's.
#[derive(Debug, thiserror::Error)]
pub enum ConnectError {
    #[error("{0}")]
    Options(String),
    /// The transport's error with its causes (e.g. the TLS handshake's).
    #[error("{}", chain(.0))]
    Transport(tonic::transport::Error),
}

impl From<tonic::transport::Error> for ConnectError {
    fn from(e: tonic::transport::Error) -> Self {
        ConnectError::Transport(e)
    }
}

fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let c_text = c.to_string();
        if !s.contains(&c_text) {
            s.push_str(": ");
            s.push_str(&c_text);
        }
        cause = c.source();
    }
    s
}

/// Adds `authorization: Bearer TOKEN` to every call (nothing without a token).
#[derive(Clone, Debug, Default)]
pub struct BearerToken(Option<MetadataValue<Ascii>>);

impl BearerToken {
    pub fn new(token: Option<&str>) -> Result<Self, ConnectError> {
        token
            .map(|t| {
                format!("Bearer {}", t.trim())
                    .parse::<MetadataValue<Ascii>>()
                    .map_err(|_| ConnectError::Options("token: expected visible ASCII characters".into()))
            })
            .transpose()
            .map(Self)
    }
}

impl Interceptor for BearerToken {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        if let Some(v) = &self.0 {
            request.metadata_mut().insert(super::security::AUTHORIZATION, v.clone());
        }
        Ok(request)
    }
}

/// The MpiFlow client that [`connect`] gives: a channel that sends the token.
pub type Client = MpiFlowClient<InterceptedService<Channel, BearerToken>>;

/// `http://HOST:PORT` for `HOST:PORT` (an address with a scheme is kept).
pub fn endpoint_uri(addr: &str) -> String {
    if addr.contains("://") {
        addr.to_string()
    } else {
        format!("http://{addr}")
    }
}

fn read(what: &str, p: &PathBuf) -> Result<Vec<u8>, ConnectError> {
    std::fs::read(p).map_err(|e| ConnectError::Options(format!("{what} {}: {e}", p.display())))
}

/// The largest HTTP/2 frame this client accepts (`SETTINGS_MAX_FRAME_SIZE`; HTTP/2's default is
/// 16 KiB). A 640x480 sample is ~4.6 MB: in 16 KiB frames the client read it in ~560 socket reads
/// and woke its tasks as often, ~6 ms of CPU per sample on the cores the server shares; in 1 MiB
/// frames it takes a third of that (docs/performance.md, "The wire"). A frame is buffered whole
/// before it is passed on, so this also bounds the connection's read buffer (besides the
/// stream window, 2 MiB, of data received but not yet read).
pub const MAX_FRAME_BYTES: u32 = 1 << 20;

/// A channel to `addr` (`HOST:PORT`, `http://` or `https://`), with TLS as the options say.
pub async fn channel(addr: &str, options: &ClientOptions) -> Result<Channel, ConnectError> {
    let tls = options.tls(addr);
    let uri = match (tls, addr.split_once("://")) {
        (true, None) => format!("https://{addr}"),
        (true, Some(("http", _))) => {
            return Err(ConnectError::Options(format!("{addr}: TLS options with an http:// address")))
        }
        _ => endpoint_uri(addr),
    };
    let mut endpoint = Endpoint::from_shared(uri)?
        .tcp_nodelay(true)
        .connect_timeout(Duration::from_secs(10))
        .max_frame_size(MAX_FRAME_BYTES)
        .local_address(options.local_address);
    if tls {
        let Some(ca) = &options.tls_ca else {
            return Err(ConnectError::Options(format!("{addr}: TLS needs the server's CA (--tls-ca)")));
        };
        let mut t = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(read("tls_ca", ca)?));
        match (&options.tls_cert, &options.tls_key) {
            (Some(c), Some(k)) => t = t.identity(Identity::from_pem(read("tls_cert", c)?, read("tls_key", k)?)),
            (None, None) => {}
            _ => return Err(ConnectError::Options("a client certificate needs both tls_cert and tls_key".into())),
        }
        if let Some(d) = &options.tls_domain {
            t = t.domain_name(d.clone());
        }
        endpoint = endpoint.tls_config(t)?;
    } else if options.tls_cert.is_some() || options.tls_key.is_some() || options.tls_domain.is_some() {
        return Err(ConnectError::Options("client certificate options need TLS (tls_ca)".into()));
    }
    Ok(endpoint.connect().await?)
}

/// Connects to a plaintext server without a token ([`connect_with`]).
pub async fn connect(addr: &str) -> Result<Client, ConnectError> {
    connect_with(addr, &ClientOptions::default()).await
}

/// Connects to a server; messages up to [`MAX_MESSAGE_CAP`] are accepted (the server states its
/// own limit in GetInfo, never above that).
pub async fn connect_with(addr: &str, options: &ClientOptions) -> Result<Client, ConnectError> {
    let token = BearerToken::new(options.token.as_deref())?;
    Ok(client_with_token(channel(addr, options).await?, token))
}

/// The MpiFlow client of a channel with the raised limits.
pub fn client_for(channel: Channel) -> MpiFlowClient<Channel> {
    MpiFlowClient::new(channel)
        .max_decoding_message_size(MAX_MESSAGE_CAP as usize)
        .max_encoding_message_size(MAX_MESSAGE_CAP as usize)
}

/// The MpiFlow client of a channel with the raised limits, sending the token.
pub fn client_with_token(channel: Channel, token: BearerToken) -> Client {
    MpiFlowClient::with_interceptor(channel, token)
        .max_decoding_message_size(MAX_MESSAGE_CAP as usize)
        .max_encoding_message_size(MAX_MESSAGE_CAP as usize)
}

/// What one pull measured.
#[derive(Clone, Debug, Default)]
pub struct PullReport {
    pub samples: u64,
    /// Encoded message bytes received.
    pub bytes: u64,
    pub seconds: f64,
    /// From sending the request to the first sample.
    pub first_sample_ms: Option<f64>,
    /// Gaps between consecutive samples' arrivals (0 within a batch), milliseconds.
    pub gaps_ms: Vec<f64>,
    /// The cursor after the last batch received (or from the trailers of an interrupted stream).
    pub next_index: Option<u64>,
    pub resume_start_index: Option<u64>,
    /// The status that ended the stream, if not OK.
    pub error: Option<Status>,
}

impl PullReport {
    pub fn samples_per_s(&self) -> f64 {
        self.samples as f64 / self.seconds.max(1e-9)
    }

    pub fn mb_per_s(&self) -> f64 {
        self.bytes as f64 / 1e6 / self.seconds.max(1e-9)
    }

    /// The `q` quantile (0 to 1) of the gaps, nearest rank.
    pub fn gap_quantile_ms(&self, q: f64) -> Option<f64> {
        if self.gaps_ms.is_empty() {
            return None;
        }
        let mut g = self.gaps_ms.clone();
        g.sort_by(f64::total_cmp);
        let i = ((q * g.len() as f64).ceil() as usize).clamp(1, g.len()) - 1;
        Some(g[i])
    }

    /// One line: samples/s, MB/s, time to first sample, p50/p99 gap, cursor.
    pub fn summary(&self) -> String {
        let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.1} ms"));
        format!(
            "{} samples in {:.2} s: {:.2} samples/s, {:.2} MB/s ({:.1} MB); first sample after {}; gap p50 {}, p99 {}; \
             next index {}",
            self.samples,
            self.seconds,
            self.samples_per_s(),
            self.mb_per_s(),
            self.bytes as f64 / 1e6,
            f(self.first_sample_ms),
            f(self.gap_quantile_ms(0.5)),
            f(self.gap_quantile_ms(0.99)),
            self.next_index.map_or("-".to_string(), |n| n.to_string()),
        )
    }
}

/// Pulls one stream to its end, handing every sample to `on_sample` in order. A stream that ends
/// with an error status is reported in [`PullReport::error`] with its cursor, not as an `Err`.
pub async fn pull(
    client: &mut Client,
    request: pb::StreamRequest,
    mut on_sample: impl FnMut(pb::Sample),
) -> Result<PullReport, Status> {
    let started = Instant::now();
    let mut report = PullReport::default();
    let mut stream = client.stream_samples(request).await?.into_inner();
    let mut last: Option<Instant> = None;
    loop {
        match stream.message().await {
            Ok(Some(batch)) => {
                let now = Instant::now();
                report.bytes += batch.encoded_len() as u64;
                for (i, s) in batch.samples.into_iter().enumerate() {
                    if report.first_sample_ms.is_none() {
                        report.first_sample_ms = Some((now - started).as_secs_f64() * 1e3);
                    }
                    if let Some(l) = last {
                        report.gaps_ms.push(if i == 0 { (now - l).as_secs_f64() * 1e3 } else { 0.0 });
                    }
                    report.samples += 1;
                    on_sample(s);
                }
                last = Some(now);
                report.next_index = Some(batch.next_index);
                report.resume_start_index = Some(batch.resume_start_index);
            }
            Ok(None) => break,
            Err(status) => {
                if let Some((next, resume)) = cursor_of(&status) {
                    report.next_index = Some(next);
                    report.resume_start_index = Some(resume);
                }
                report.error = Some(status);
                break;
            }
        }
    }
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}
