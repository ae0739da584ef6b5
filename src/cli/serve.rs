//! `mpiflow serve`: the gRPC sample service. Configuration from `--config FILE` (TOML), then
//! `MPIFLOW_*` variables, then these flags; prints `mpiflow serving on HOST:PORT` once the
//! listener is bound, drains on SIGTERM / SIGINT.

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;
use mpiflow::service::config::{parse_size, DatasetConfig, LogFormat};
use mpiflow::service::ServiceConfig;
use std::io::Write;

use super::CliError;

#[derive(Args, Debug)]
pub struct ServeArgs {
    /// TOML configuration file (see deploy/mpiflow.toml for every key and its default).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Listen address (port 0 = any free port). Default 127.0.0.1:50051.
    #[arg(long, value_name = "HOST:PORT")]
    addr: Option<String>,
    /// A dataset: a folder of photos (or the reference layout), or NAME=PATH. Repeatable; the
    /// first is the default. Default: the bundled scenes as dataset `builtin`.
    #[arg(long, value_name = "DIR")]
    source: Vec<String>,
    /// Serve Prometheus metrics on http://HOST:PORT/metrics.
    #[arg(long, value_name = "HOST:PORT")]
    metrics_addr: Option<String>,
    /// Generation threads (default: all cores).
    #[arg(long, value_name = "N")]
    workers: Option<usize>,
    /// Samples being made at once over all streams (default 2 x workers).
    #[arg(long, value_name = "N")]
    max_in_flight: Option<usize>,
    /// Concurrent streams (default 64).
    #[arg(long, value_name = "N")]
    max_streams: Option<usize>,
    /// MiB of samples made but not yet sent, over all streams (default: a quarter of the
    /// memory, 256 to 4096).
    #[arg(long, value_name = "MIB")]
    max_buffered_mb: Option<u64>,
    /// Samples made ahead per stream when a request says 0 (default 4).
    #[arg(long, value_name = "N")]
    prefetch: Option<u32>,
    /// Resize every source image to WxH (the bundled scenes are 640x480).
    #[arg(long, value_name = "WxH")]
    size: Option<String>,
    /// Follow symbolic links in folder sources that lead out of the source folder (true / false).
    #[arg(long, value_name = "BOOL")]
    follow_source_links: Option<bool>,
    /// Seconds a graceful shutdown may take (default 10).
    #[arg(long, value_name = "S")]
    drain_timeout_s: Option<f64>,
    /// Log format: text or json.
    #[arg(long, value_name = "FORMAT")]
    log_format: Option<LogFormat>,
    /// Log level: error, warn, info, debug or trace.
    #[arg(long, value_name = "LEVEL")]
    log_level: Option<String>,
    /// Scene cache budget in MiB.
    #[arg(long, value_name = "MIB")]
    cache_mb: Option<u64>,
    /// Build the scenes of each stream's next indices ahead on the scene pool (true / false).
    #[arg(long, value_name = "BOOL")]
    prefetch_scenes: Option<bool>,
    /// Depth model for sources without depth: a NAME (`mpiflow models list`; fetched and cached on
    /// first use) or an ONNX FILE (optional manifest FILE.toml beside it; docs/models.md).
    #[arg(long, value_name = "NAME|FILE")]
    depth_model: Option<PathBuf>,
    /// MPI network (ONNX) instead of the built-in layering.
    #[arg(long, value_name = "FILE.onnx")]
    mpi_model: Option<PathBuf>,
    /// Instance segmentation model for sources without masks: a NAME or an ONNX FILE.
    #[arg(long, value_name = "NAME|FILE")]
    segment_model: Option<PathBuf>,
    /// Planes of the built-in layering.
    #[arg(long, value_name = "N")]
    planes: Option<usize>,
    /// Default motion preset of the datasets: reference, paper-kitti, depthstillation, mixed or stereo.
    #[arg(long, value_name = "NAME")]
    preset: Option<mpiflow::sample::motion::MotionPreset>,
    /// Default objects moved per sample.
    #[arg(long, value_name = "K")]
    objects: Option<usize>,
    /// Default consecutive samples per source photo.
    #[arg(long, value_name = "M")]
    motions_per_image: Option<u64>,
    /// Default colour kernel of the target render: bilinear, bicubic, bspline3 or lanczos3.
    #[arg(long, value_name = "KERNEL")]
    resample: Option<mpiflow::render::Resample>,
    /// Also serve grpc.health.v1 alone, in plaintext, on this address (for probes that cannot
    /// do TLS).
    #[arg(long, value_name = "HOST:PORT")]
    health_addr: Option<String>,
    /// Serve TLS with this certificate chain (PEM; with --tls-key).
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    /// The private key (PEM) of --tls-cert.
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    tls_key: Option<PathBuf>,
    /// Require client certificates signed by this CA (PEM; needs --tls-cert).
    #[arg(long, value_name = "FILE")]
    tls_client_ca: Option<PathBuf>,
    /// Require the bearer token in this file on every call except health (or set
    /// MPIFLOW_AUTH_TOKEN; a token on the command line would show in the process list).
    #[arg(long, value_name = "FILE")]
    auth_token_file: Option<PathBuf>,
    /// Extra wait after the warm-up sample before health says SERVING.
    #[arg(long, value_name = "MS", hide = true)]
    warmup_delay_ms: Option<u64>,
}

/// The configuration of `mpiflow serve`: file, then environment, then flags.
pub fn build_config(a: &ServeArgs) -> Result<ServiceConfig, CliError> {
    let mut c = match &a.config {
        Some(p) => ServiceConfig::from_file(p)?,
        None => ServiceConfig::default(),
    };
    c.apply_env()?;
    macro_rules! set {
        ($flag:ident => $($field:tt)+) => {
            if let Some(v) = a.$flag.clone() {
                c.$($field)+ = v.into();
            }
        };
    }
    set!(addr => addr);
    set!(workers => workers);
    set!(max_in_flight => max_in_flight);
    set!(max_streams => max_streams);
    set!(prefetch => default_prefetch);
    set!(max_buffered_mb => max_buffered_mb);
    set!(drain_timeout_s => drain_timeout_s);
    set!(log_format => log_format);
    set!(log_level => log_level);
    set!(cache_mb => cache_mb);
    set!(follow_source_links => follow_source_links);
    set!(prefetch_scenes => prefetch_scenes);
    set!(planes => models.planes);
    set!(objects => sample.max_objects);
    set!(motions_per_image => sample.motions_per_image);
    set!(resample => sample.resample);
    set!(warmup_delay_ms => warmup_delay_ms);
    if let Some(m) = &a.metrics_addr {
        c.metrics_addr = Some(m.clone());
    }
    if let Some(h) = &a.health_addr {
        c.health_addr = Some(h.clone());
    }
    if let Some(s) = &a.size {
        parse_size(s).map_err(|e| CliError(format!("--size: {e}")))?;
        c.size = Some(s.clone());
    }
    for (flag, slot) in [
        (&a.depth_model, &mut c.models.depth_model),
        (&a.mpi_model, &mut c.models.mpi_model),
        (&a.segment_model, &mut c.models.segment_model),
        (&a.tls_cert, &mut c.tls_cert),
        (&a.tls_key, &mut c.tls_key),
        (&a.tls_client_ca, &mut c.tls_client_ca),
    ] {
        if let Some(p) = flag {
            *slot = Some(p.clone());
        }
    }
    if let Some(p) = &a.auth_token_file {
        c.auth_token = None;
        c.auth_token_file = Some(p.clone());
    }
    if let Some(p) = a.preset {
        c.sample.motion = mpiflow::sample::config::MotionSpec::Preset(p);
    }
    if !a.source.is_empty() {
        c.datasets = a
            .source
            .iter()
            .map(|s| DatasetConfig::parse(s).map_err(|e| CliError(format!("--source: {e}"))))
            .collect::<Result<_, _>>()?;
    }
    c.validate()?;
    Ok(c)
}

/// Logs to stderr as text or JSON lines; text is coloured only when stderr is a terminal (a log
/// redirected to a file or a pipe carries no ANSI codes).
pub fn init_tracing(format: LogFormat, level: &str) -> Result<(), CliError> {
    let level: tracing::Level = level
        .parse()
        .map_err(|_| CliError(format!("log level {level:?}: expected error, warn, info, debug or trace")))?;
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let builder =
        tracing_subscriber::fmt().with_writer(std::io::stderr).with_max_level(level).with_target(false).with_ansi(ansi);
    let result = match format {
        LogFormat::Json => builder.json().try_init(),
        LogFormat::Text => builder.try_init(),
    };
    result.map_err(|e| CliError(format!("logging: {e}")))
}

async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = tokio::signal::ctrl_c() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

pub fn run(a: ServeArgs) -> Result<(), CliError> {
    let config = build_config(&a)?;
    init_tracing(config.log_format, &config.log_level)?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("mpiflow-io")
        .build()
        .map_err(|e| CliError(format!("cannot start the async runtime: {e}")))?;
    rt.block_on(async move {
        let drain = Duration::from_secs_f64(config.drain_timeout_s);
        let server = mpiflow::service::start(config).await?;
        {
            let mut out = std::io::stdout().lock();
            writeln!(out, "mpiflow serving on {}", server.addr).map_err(|e| CliError(format!("stdout: {e}")))?;
            if let Some(m) = server.metrics_addr {
                writeln!(out, "mpiflow metrics on http://{m}/metrics").map_err(|e| CliError(format!("stdout: {e}")))?;
            }
            if let Some(h) = server.health_addr {
                writeln!(out, "mpiflow health on {h}").map_err(|e| CliError(format!("stdout: {e}")))?;
            }
            out.flush().map_err(|e| CliError(format!("stdout: {e}")))?;
        }
        shutdown_signal().await;
        server.shutdown(drain).await;
        Ok(())
    })
}
