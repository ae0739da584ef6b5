//! The Rust client side: connecting with the raised message limit, and pulling a stream while
//! measuring what a trainer sees (samples/s, bytes/s, time to first sample, gaps between samples).

use std::time::{Duration, Instant};

use prost::Message;
use tonic::transport::{Channel, Endpoint};
use tonic::Status;

use super::config::MAX_MESSAGE_CAP;
use super::error::cursor_of;
use super::pb;
use super::pb::mpi_flow_client::MpiFlowClient;

/// `http://HOST:PORT` for `HOST:PORT` (an address with a scheme is kept).
pub fn endpoint_uri(addr: &str) -> String {
    if addr.contains("://") {
        addr.to_string()
    } else {
        format!("http://{addr}")
    }
}

/// Connects to a server; messages up to [`MAX_MESSAGE_CAP`] are accepted (the server states its
/// own limit in GetInfo, never above that).
pub async fn connect(addr: &str) -> Result<MpiFlowClient<Channel>, tonic::transport::Error> {
    let channel = Endpoint::from_shared(endpoint_uri(addr))?
        .tcp_nodelay(true)
        .connect_timeout(Duration::from_secs(10))
        .connect()
        .await?;
    Ok(client_for(channel))
}

/// The MpiFlow client of a channel with the raised limits.
pub fn client_for(channel: Channel) -> MpiFlowClient<Channel> {
    MpiFlowClient::new(channel)
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
    client: &mut MpiFlowClient<Channel>,
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
