//! `mpiflow serve`: the gRPC sample service. Configuration from `--config FILE` (TOML), then
//! `MPIFLOW_*` variables, then these flags; prints `mpiflow serving on HOST:PORT` once the
//! listener is bound, drains on SIGTERM / SIGINT.

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;
use mpiflow::service::config::{DatasetConfig, LogFormat};
use mpiflow::service::ServiceConfig;
use serde::Serialize;
use std::io::Write;

use super::CliError;

#[derive(Args, Debug)]
pub struct ServeArgs {
    /// TOML configuration file (see deploy/mpiflow.toml for every key and its default).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// A dataset: a folder of photos (or the reference layout), or NAME=PATH. Repeatable; the
    /// first is the default. Default: the bundled scenes as dataset `builtin`.
    #[arg(long, value_name = "DIR")]
    source: Vec<String>,
    /// Refuse to start when any file of a dataset's folder is left out (a photo that cannot
    /// serve, a format mpiflow does not read) instead of logging them and serving the others.
    #[arg(long)]
    strict: bool,
    #[command(flatten)]
    keys: KeyFlags,
}

/// The flags that set configuration keys: each field is named (in serde) after the key it sets,
/// the nested ones after the section's key, so the mapping is derived
/// ([`mpiflow::service::layers`]); a flag given overrides the file and the environment.
#[derive(Args, Debug, Serialize)]
struct KeyFlags {
    /// Listen address (port 0 = any free port). Default 127.0.0.1:50051.
    #[arg(long, value_name = "HOST:PORT")]
    addr: Option<String>,
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
    #[arg(long = "prefetch", value_name = "N")]
    default_prefetch: Option<u32>,
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
    #[command(flatten)]
    models: ModelFlags,
    #[command(flatten)]
    sample: SampleFlags,
}

/// Flags of `[models]` keys.
#[derive(Args, Debug, Serialize)]
struct ModelFlags {
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
}

/// Flags of `[sample]` keys (the datasets' default sample configuration).
#[derive(Args, Debug, Serialize)]
struct SampleFlags {
    /// Default motion preset of the datasets: reference, paper-kitti, depthstillation, mixed or stereo.
    #[arg(long = "preset", value_name = "NAME")]
    motion: Option<mpiflow::sample::motion::MotionPreset>,
    /// Default objects moved per sample.
    #[arg(long = "objects", value_name = "K")]
    max_objects: Option<usize>,
    /// Default motions drawn from each source photo while its scene is warm (default 8).
    #[arg(long, value_name = "M")]
    motions_per_image: Option<u64>,
    /// Source photos whose motions are interleaved, so that consecutive samples come from
    /// different photos (default 11; 1 = each photo's motions in a row).
    #[arg(long, value_name = "K")]
    scene_window: Option<u64>,
    /// Default colour kernel of the target render: bilinear, bicubic, bspline3, bspline5,
    /// lanczos3 or omoms3.
    #[arg(long, value_name = "KERNEL")]
    resample: Option<mpiflow::render::Resample>,
}

/// The configuration of `mpiflow serve`: defaults, then the file, then the environment, then
/// the flags.
pub fn build_config(a: &ServeArgs) -> Result<ServiceConfig, CliError> {
    build_config_with(a, std::env::vars())
}

/// [`build_config`] with the environment `vars`.
fn build_config_with(
    a: &ServeArgs,
    vars: impl IntoIterator<Item = (String, String)>,
) -> Result<ServiceConfig, CliError> {
    let mut c = match &a.config {
        Some(p) => ServiceConfig::from_file(p)?,
        None => ServiceConfig::default(),
    };
    c.apply_env_vars(vars).map_err(CliError)?;
    c.apply_flags(&a.keys).map_err(CliError)?;
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

/// `--strict`: every dataset's source opened as the server opens it; any file left out is an
/// error naming them by reason.
fn check_strict(config: &ServiceConfig) -> Result<(), CliError> {
    use mpiflow::sample::pipeline::{open_source, OpenOptions};
    let open = OpenOptions {
        resize: config.resize()?,
        limits: config.image_limits(),
        photo_limits: Some(config.photo_limits()),
        follow_links: config.follow_source_links,
        ..OpenOptions::default()
    };
    for spec in &config.datasets {
        let name = spec.name();
        let source =
            open_source(&spec.source_spec(), &open).map_err(|e| CliError(format!("dataset \"{name}\": {e}")))?;
        let skipped = source.skipped();
        if !skipped.is_empty() {
            return Err(CliError(format!(
                "--strict: dataset \"{name}\": {}; remove or fix them, or start without --strict",
                mpiflow::source::dir::left_out_summary(&skipped)
            )));
        }
    }
    Ok(())
}

pub fn run(a: ServeArgs) -> Result<(), CliError> {
    let config = build_config(&a)?;
    init_tracing(config.log_format, &config.log_level)?;
    if a.strict {
        check_strict(&config)?;
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;
    use mpiflow::sample::config::MotionSpec;
    use mpiflow::sample::motion::MotionPreset;

    #[derive(Parser)]
    struct Serve {
        #[command(flatten)]
        args: ServeArgs,
    }

    fn config(file: &str, env: &[(&str, &str)], flags: &[&str]) -> Result<ServiceConfig, CliError> {
        let dir = std::env::temp_dir().join(format!("mpiflow-serve-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        static FILES: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let path = dir.join(format!("{}.toml", FILES.fetch_add(1, std::sync::atomic::Ordering::Relaxed)));
        std::fs::write(&path, file).unwrap();
        let mut argv = vec!["serve".to_string(), "--config".into(), path.display().to_string()];
        argv.extend(flags.iter().map(|f| (*f).to_string()));
        let a = Serve::try_parse_from(argv).map_err(|e| CliError(e.to_string()))?.args;
        build_config_with(&a, env.iter().map(|(k, v)| ((*k).to_string(), (*v).to_string())))
    }

    /// Each layer overrides the ones below it, key by key: defaults < file < environment < flags,
    /// in sections too, and a flag sets the key it is named after.
    #[test]
    fn defaults_then_file_then_environment_then_flags() {
        let file = "workers = 3\nmax_streams = 5\ncache_mb = 100\n[sample]\nmax_objects = 2\nmotions_per_image = 4\n";
        let env = [("MPIFLOW_MAX_STREAMS", "6"), ("MPIFLOW_CACHE_MB", "200"), ("MPIFLOW_MAX_OBJECTS", "1")];
        let flags = ["--cache-mb", "300", "--objects", "0", "--prefetch", "7", "--preset", "paper-kitti"];
        let c = config(file, &env, &flags).unwrap();
        let d = ServiceConfig::default();
        assert_eq!((c.max_prefetch, c.addr.as_str()), (d.max_prefetch, d.addr.as_str()), "defaults");
        assert_eq!((c.workers, c.sample.motions_per_image), (3, 4), "the file over the defaults");
        assert_eq!(c.max_streams, 6, "the environment over the file");
        assert_eq!((c.cache_mb, c.sample.max_objects), (300, 0), "the flags over the environment");
        assert_eq!(c.default_prefetch, 7);
        assert_eq!(c.sample.motion, MotionSpec::Preset(MotionPreset::PaperKitti));
        // the same environment without the flags
        let c = config(file, &env, &[]).unwrap();
        assert_eq!((c.cache_mb, c.sample.max_objects, c.sample.motions_per_image), (200, 1, 4));
    }

    #[test]
    fn a_bad_value_names_its_variable_or_key_and_what_it_expects() {
        let e = config("", &[("MPIFLOW_MAX_STREAMS", "lots")], &[]).unwrap_err().0;
        assert!(e.starts_with("MPIFLOW_MAX_STREAMS=\"lots\": ") && e.contains("usize"), "{e}");
        let e = config("", &[("MPIFLOW_LOG_FORMAT", "xml")], &[]).unwrap_err().0;
        assert!(e.starts_with("MPIFLOW_LOG_FORMAT=\"xml\": ") && e.contains("text") && e.contains("json"), "{e}");
        let e = config("max_stream = 3\n", &[], &[]).unwrap_err().0;
        assert!(e.contains("max_stream") && e.contains("max_streams"), "{e}");
        let e = config("", &[("MPIFLOW_MAX_STREAMS", "0")], &[]).unwrap_err().0;
        assert!(e.contains("max_streams = 0"), "{e}");
    }
}
