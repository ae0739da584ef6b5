//! The server's configuration: a TOML file (`deploy/mpiflow.toml` documents every key and its
//! default), then `MPIFLOW_*` environment variables, then command-line flags, each overriding the
//! one before. Every key is declared once, here, as a field of `ServiceConfig` or of its
//! sections; the layers are merged above this module, from these declarations.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::io::image::ImageLimits;
use crate::sample::config::SampleConfig;
pub use crate::scene::models::ModelConfig;

use super::error::ServiceError;

/// Bytes per pixel of the largest sample a request can ask for: a clip of
/// [`MAX_FRAMES`](crate::sample::config::MAX_FRAMES) frames with every field and f32 flow
/// (`encode::bytes_per_pixel`).
pub fn bytes_per_pixel_largest() -> u64 {
    use super::encode::{bytes_per_pixel, ALL_FIELDS};
    bytes_per_pixel(&ALL_FIELDS, crate::sample::config::MAX_FRAMES, false).iter().map(|(_, b)| b).sum()
}

/// The encoded size bound of a sample of `pixels` pixels at `per_pixel` bytes each in `tensors`
/// tensors: lz4's worst case (1/255 more and 16 bytes per tensor), 64 bytes of name and shape
/// per tensor, and [`SAMPLE_METADATA_BYTES`] for the rest of the message.
pub fn sample_bytes_bound(pixels: u64, per_pixel: u64, tensors: u64) -> u64 {
    let raw = pixels.saturating_mul(per_pixel);
    raw.saturating_add(raw / 255).saturating_add(80 * tensors).saturating_add(SAMPLE_METADATA_BYTES)
}

/// The allowance for a sample's fields besides its tensors (camera, up to 255 objects with their
/// motions, provenance, the augmentation record, names).
pub const SAMPLE_METADATA_BYTES: u64 = 128 << 10;

/// The scene cache's default budget in MiB: the 8 bundled 640x480 scenes (about 45 MiB each,
/// 356 MiB together, since a prepared scene keeps its planes and B-spline coefficients only in
/// the blocks where they have density), or two windows of a photo folder at its working size
/// (2 x `scene_window` = 22 scenes of 640x480: the window served and the next one built ahead),
/// within a server's 2 GiB with the workers' buffers (docs/performance.md, "Photo folders").
pub const DEFAULT_CACHE_MB: u64 = 1024;

/// The largest gRPC message the server ever allows (well below protobuf's 2 GiB).
pub const MAX_MESSAGE_CAP: u64 = 1 << 30;

/// The largest configuration file read (bytes); a longer one is refused unread.
pub const MAX_CONFIG_FILE_BYTES: u64 = 1 << 20;

/// The largest token file read (bytes): a token is at most 4096 characters, with room for
/// surrounding whitespace.
pub const MAX_TOKEN_FILE_BYTES: u64 = 64 << 10;

/// The longest any timeout or delay key may be: one day (in seconds).
pub const MAX_SECONDS: f64 = 86_400.0;

/// The shortest `idle_connection_timeout_s` and `stall_timeout_s` may be: half a second, more
/// than a round trip across the world, so that a keepalive ping can be answered and a handshake
/// finished before the connection is closed for silence.
pub const MIN_TIMEOUT_SECONDS: f64 = 0.5;

/// The smallest side of a working frame (`size`): the bundled scenes place objects of at least
/// 8 pixels within 45% of the frame's width (so no sample of theirs can be made below 18
/// pixels), and a frame is rendered in 16x16 blocks; 32 keeps two blocks a side.
pub const MIN_FRAME_SIDE: usize = 32;

/// The most any count key (connections, streams, calls, uploads, samples in flight) may be.
pub const MAX_COUNT: u64 = 1_000_000;

/// The most any MiB key (`max_buffered_mb`, `cache_mb`, `max_upload_buffer_mb`) may be: 16 TiB.
pub const MAX_MIB: u64 = 1 << 24;

/// The most samples a stream may make ahead (`default_prefetch`, `max_prefetch`).
pub const MAX_PREFETCH: u32 = 65_536;

/// Log line format.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    #[default]
    Text,
    Json,
}

impl std::str::FromStr for LogFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "text" => Ok(LogFormat::Text),
            "json" => Ok(LogFormat::Json),
            _ => Err(format!("unknown log format {s:?} (expected text or json)")),
        }
    }
}

/// One dataset: a name and where its sources are.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetConfig {
    /// The name clients use (default: the path's file name, or `builtin`).
    #[serde(default)]
    pub name: Option<String>,
    /// A folder of photos (or the reference layout), one image, or `builtin` for the bundled scenes.
    pub path: String,
    /// This dataset's sample configuration (default: the server's `[sample]`).
    #[serde(default)]
    pub sample: Option<SampleConfig>,
}

impl DatasetConfig {
    /// `NAME=PATH` or `PATH` (named after the path's file name).
    pub fn parse(spec: &str) -> Result<Self, String> {
        let spec = spec.trim();
        if spec.is_empty() {
            return Err("empty source".into());
        }
        let (name, path) = match spec.split_once('=') {
            Some((n, p)) if !n.is_empty() && !n.contains('/') => (Some(n.to_string()), p.to_string()),
            _ => (None, spec.to_string()),
        };
        if path.is_empty() {
            return Err(format!("source {spec:?}: empty path"));
        }
        Ok(Self { name, path, sample: None })
    }

    /// The dataset's name: the given one, else `builtin` for the bundled scenes, else the path's
    /// file name.
    pub fn name(&self) -> String {
        if let Some(n) = &self.name {
            return n.clone();
        }
        if self.is_builtin() {
            return "builtin".into();
        }
        Path::new(&self.path)
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .filter(|n| !n.is_empty())
            .unwrap_or_else(|| self.path.clone())
    }

    pub fn is_builtin(&self) -> bool {
        self.path == "builtin"
    }

    /// Where the dataset's items come from.
    pub fn source_spec(&self) -> crate::sample::pipeline::SourceSpec {
        use crate::sample::pipeline::SourceSpec;
        if self.is_builtin() {
            SourceSpec::Builtin
        } else {
            SourceSpec::Path(PathBuf::from(&self.path))
        }
    }
}

/// The server's default listen address, and the address the clients (`pull`, `health`) ask
/// by default.
pub const DEFAULT_ADDR: &str = "127.0.0.1:50051";

/// Everything the server reads at start-up.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServiceConfig {
    /// gRPC listen address. Default `127.0.0.1:50051` (port 0 = any free port).
    pub addr: String,
    /// Prometheus metrics address (HTTP `/metrics`); none = no metrics endpoint.
    pub metrics_addr: Option<String>,
    /// Generation threads (one sample each at a time). 0 = all cores.
    pub workers: usize,
    /// Samples being made at once over all streams. 0 = 2 x workers.
    pub max_in_flight: usize,
    /// Concurrent StreamSamples calls; more are refused with RESOURCE_EXHAUSTED.
    pub max_streams: usize,
    /// Samples made ahead per stream when the request says 0.
    pub default_prefetch: u32,
    /// Cap of a request's `prefetch`.
    pub max_prefetch: u32,
    /// MiB of samples made but not yet sent, over all streams (queues, messages handed to the
    /// transport); each stream may hold its fair share. 0 = sized for the machine: a quarter of
    /// the memory the process may use (cgroup limit, else physical memory), 256 to 4096 MiB.
    pub max_buffered_mb: u64,
    /// Largest `batch_size` a request may ask for.
    pub max_batch_size: u32,
    /// Largest source image side in pixels (checked in the file header before decoding).
    pub max_image_side: u32,
    /// Largest source image read as it is (and so sample) in pixels; sets the message limit.
    pub max_image_pixels: u64,
    /// Largest photo of a folder source in pixels (checked in the header before decoding): a
    /// folder's photos are fitted to its working size (or `size`) before use, so a phone's
    /// 12-megapixel photo is read by default while samples stay within `max_image_pixels`.
    pub max_photo_pixels: u64,
    /// Largest encoded source image file in bytes.
    pub max_image_bytes: u64,
    /// Largest upload (all files of one UploadSources call) in bytes.
    pub max_upload_bytes: u64,
    /// Most connections open at once on each listener (more are closed as they arrive).
    pub max_connections: usize,
    /// Most connections open at once from one peer address (more are closed as they arrive).
    pub max_connections_per_peer: usize,
    /// Most calls open at once on one connection (HTTP/2 `SETTINGS_MAX_CONCURRENT_STREAMS`).
    pub max_calls_per_connection: u32,
    /// Seconds a new connection may stay silent, and a connection may stay open with no call,
    /// before it is closed; also the HTTP/2 keepalive ping interval, a ping unanswered for this
    /// long closes the connection.
    pub idle_connection_timeout_s: f64,
    /// Seconds a client may take no data while the server has bytes waiting for it (its writes
    /// are blocked: it stopped reading) before its connection is closed, ending its streams and
    /// freeing their slots; a stall ends when the client takes data again (`service::stall`).
    pub stall_timeout_s: f64,
    /// Concurrent GetSample and GetSamples calls from one client address (unsent replies
    /// included); more are refused with RESOURCE_EXHAUSTED.
    pub max_random_access_calls: usize,
    /// The most work one sample of a request may take, in millions of work units (its pixels x
    /// frames x the taps of its resampling kernel: `service::work`); a request whose largest
    /// sample would take more is refused with RESOURCE_EXHAUSTED before any work, naming it.
    pub max_sample_work: u64,
    /// Most uploads in progress at once; more are RESOURCE_EXHAUSTED with nothing kept.
    pub max_concurrent_uploads: usize,
    /// Most MiB held by all uploads in progress together (received, not yet committed); over it
    /// an upload is RESOURCE_EXHAUSTED with nothing kept.
    pub max_upload_buffer_mb: u64,
    /// Resize every source image to `WxH` (e.g. `"640x480"`); none = keep sizes (the bundled
    /// scenes are 640x480).
    pub size: Option<String>,
    /// Follow symbolic links in folder sources that lead out of the source folder (default
    /// false: they are left out as `outside-root`; links that stay inside are always followed).
    pub follow_source_links: bool,
    /// Scene cache budget in MiB ([`DEFAULT_CACHE_MB`]; a 640x480 scene with 32 planes takes
    /// about 45 MiB: ~22 of planes and ~18 of B-spline colour coefficients, both in the blocks
    /// with density, the photo and masks).
    pub cache_mb: u64,
    /// Build the scenes of each stream's next indices (its prefetch window) on the scene pool
    /// ahead of the samples, so that the workers only make samples of ready scenes; false =
    /// a worker builds a missing scene itself (and waits for it). Default false: jobs waiting
    /// for a scene are outside the in-flight bound, and with them the buffered bytes were seen
    /// to exceed the budget's stated slack (budget + in-flight samples) in the stalled-streams
    /// test, so the scene prefetch stays opt-in until the budget accounts for them.
    pub prefetch_scenes: bool,
    /// How long a graceful shutdown may take before open streams are cut.
    pub drain_timeout_s: f64,
    /// Extra wait after the warm-up sample before health reports SERVING.
    pub warmup_delay_ms: u64,
    pub log_format: LogFormat,
    /// `error`, `warn`, `info`, `debug` or `trace`.
    pub log_level: String,
    pub models: ModelConfig,
    /// The default sample configuration of every dataset (the recipe's JSON schema; see
    /// `docs/api.md`).
    pub sample: SampleConfig,
    /// The datasets; the first is the default. None = the bundled scenes as `builtin`.
    pub datasets: Vec<DatasetConfig>,
    /// A second, plaintext listener serving only `grpc.health.v1`, for probes that cannot do TLS
    /// (the kubelet's gRPC probe); none = health only on `addr`.
    pub health_addr: Option<String>,
    /// TLS: the server's certificate chain (PEM). With `tls_key`; none = plaintext.
    pub tls_cert: Option<PathBuf>,
    /// TLS: the server's private key (PEM).
    pub tls_key: Option<PathBuf>,
    /// TLS: require client certificates signed by this CA (PEM); none = no client certificates.
    pub tls_client_ca: Option<PathBuf>,
    /// The bearer token every `mpiflow.v1.MpiFlow` call (and reflection) must send as
    /// `authorization: Bearer TOKEN`; health stays open. None = no token check.
    pub auth_token: Option<String>,
    /// The token read from a file (surrounding whitespace dropped), e.g. a mounted Secret.
    pub auth_token_file: Option<PathBuf>,
}

impl Default for ServiceConfig {
    fn default() -> Self {
        Self {
            addr: DEFAULT_ADDR.into(),
            metrics_addr: None,
            workers: 0,
            max_in_flight: 0,
            max_streams: 64,
            default_prefetch: 4,
            max_prefetch: 64,
            max_buffered_mb: 0,
            max_batch_size: 64,
            max_image_side: 8192,
            max_image_pixels: 4 << 20,
            max_photo_pixels: 32 << 20,
            max_image_bytes: 64 << 20,
            max_upload_bytes: 256 << 20,
            max_connections: 512,
            max_connections_per_peer: 128,
            max_calls_per_connection: 128,
            idle_connection_timeout_s: 20.0,
            stall_timeout_s: 120.0,
            max_random_access_calls: 32,
            max_sample_work: 1024,
            max_concurrent_uploads: 4,
            max_upload_buffer_mb: 512,
            size: None,
            follow_source_links: false,
            cache_mb: DEFAULT_CACHE_MB,
            prefetch_scenes: false,
            drain_timeout_s: 10.0,
            warmup_delay_ms: 0,
            log_format: LogFormat::Text,
            log_level: "info".into(),
            models: ModelConfig::default(),
            sample: SampleConfig::default(),
            datasets: Vec::new(),
            health_addr: None,
            tls_cert: None,
            tls_key: None,
            tls_client_ca: None,
            auth_token: None,
            auth_token_file: None,
        }
    }
}

pub use crate::sample::pipeline::parse_size;

impl ServiceConfig {
    /// Reads a TOML file (every key optional; at most [`MAX_CONFIG_FILE_BYTES`]).
    pub fn from_file(path: &Path) -> Result<Self, ServiceError> {
        let text = crate::io::bounded::read_to_string(path, MAX_CONFIG_FILE_BYTES)
            .map_err(|e| ServiceError::Config(format!("{}: {e}", path.display())))?;
        Self::from_toml(&text).map_err(|e| ServiceError::Config(format!("{}: {e}", path.display())))
    }

    pub fn from_toml(text: &str) -> Result<Self, String> {
        toml::from_str(text).map_err(|e| e.to_string().trim().replace('\n', " "))
    }

    /// Checks every value; the error names the key.
    pub fn validate(&self) -> Result<(), ServiceError> {
        let bad = |m: String| Err(ServiceError::Config(m));
        self.validate_ranges()?;
        if self.max_streams == 0 {
            return bad("max_streams = 0 (expected at least 1)".into());
        }
        if self.max_connections == 0 {
            return bad("max_connections = 0 (expected at least 1)".into());
        }
        if self.max_connections_per_peer == 0 || self.max_calls_per_connection == 0 {
            return bad("max_connections_per_peer and max_calls_per_connection must be at least 1".into());
        }
        if self.max_random_access_calls == 0 {
            return bad("max_random_access_calls = 0 (expected at least 1)".into());
        }
        if self.max_sample_work == 0 {
            return bad("max_sample_work = 0 (expected at least 1)".into());
        }
        if self.max_concurrent_uploads == 0 || self.max_upload_buffer_mb == 0 {
            return bad("max_concurrent_uploads and max_upload_buffer_mb must be at least 1".into());
        }
        if self.default_prefetch == 0 || self.max_prefetch == 0 {
            return bad("default_prefetch and max_prefetch must be at least 1".into());
        }
        if self.max_batch_size == 0 || self.max_batch_size > 4096 {
            return bad(format!("max_batch_size = {} (expected 1 to 4096)", self.max_batch_size));
        }
        if self.max_image_side < 16 || self.max_image_pixels < 256 {
            return bad("max_image_side must be at least 16 and max_image_pixels at least 256".into());
        }
        if self.workers > 1024 {
            return bad(format!("workers = {} (expected at most 1024)", self.workers));
        }
        if let Some((w, h)) = self.resize()? {
            if (w * h) as u64 > self.max_image_pixels {
                return bad(format!("size = {w}x{h} is larger than max_image_pixels = {}", self.max_image_pixels));
            }
            if w.min(h) < MIN_FRAME_SIDE {
                return bad(format!(
                    "size = {w}x{h} is smaller than the smallest working frame ({MIN_FRAME_SIDE} pixels a side)"
                ));
            }
        }
        self.sample.validate().map_err(|e| ServiceError::Config(format!("[sample]: {e}")))?;
        self.check_radius("[sample] inpaint_radius", &self.sample)?;
        let paths = [
            ("auth_token_file", &self.auth_token_file),
            ("tls_cert", &self.tls_cert),
            ("tls_key", &self.tls_key),
            ("tls_client_ca", &self.tls_client_ca),
        ];
        for (key, path) in paths {
            if path.as_ref().is_some_and(|p| p.as_os_str().to_string_lossy().trim().is_empty()) {
                return bad(format!("{key} is empty: give the path of the file, or leave the key out"));
            }
        }
        if self.tls_cert.is_some() != self.tls_key.is_some() {
            return bad("tls_cert and tls_key go together (both PEM files)".into());
        }
        if self.tls_client_ca.is_some() && self.tls_cert.is_none() {
            return bad("tls_client_ca needs TLS (tls_cert and tls_key)".into());
        }
        if self.auth_token.is_some() && self.auth_token_file.is_some() {
            return bad("auth_token and auth_token_file: give one of them".into());
        }
        if let Some(t) = &self.auth_token {
            if t.trim().is_empty() {
                return bad("auth_token is empty: give the token, or leave the key out for no token check".into());
            }
            check_token(t).map_err(|e| ServiceError::Config(format!("auth_token: {e}")))?;
        }
        let mut names = std::collections::HashSet::new();
        for d in &self.datasets {
            let name = d.name();
            if !valid_name(&name) {
                return bad(format!("dataset name {name:?}: use letters, digits, '-', '_' and '.'"));
            }
            if !names.insert(name.clone()) {
                return bad(format!("dataset name {name:?} is used twice"));
            }
            if let Some(s) = &d.sample {
                s.validate().map_err(|e| ServiceError::Config(format!("dataset {name}: {e}")))?;
                self.check_radius(&format!("dataset {name}: inpaint_radius"), s)?;
            }
        }
        Ok(())
    }

    /// The longest side a frame can have: that of `size` when set, else `max_image_side`.
    pub fn max_frame_side(&self) -> usize {
        match self.resize() {
            Ok(Some((w, h))) => w.max(h),
            _ => self.max_image_side as usize,
        }
    }

    /// Refuses an inpainting radius beyond the frame (longer than its longest side,
    /// [`max_frame_side`](Self::max_frame_side)): every pixel of the frame is within a radius of
    /// that length, so a longer one only costs time.
    fn check_radius(&self, key: &str, sample: &SampleConfig) -> Result<(), ServiceError> {
        let side = self.max_frame_side();
        if f64::from(sample.inpaint_radius) > side as f64 {
            let of = if self.size.is_some() { "size" } else { "max_image_side" };
            return Err(ServiceError::Config(format!(
                "{key} = {:?} is beyond the frame (expected at most its longest side, {side} pixels: {of})",
                sample.inpaint_radius
            )));
        }
        Ok(())
    }

    /// The bearer token to require: `auth_token`, or the contents of `auth_token_file`
    /// (surrounding whitespace dropped; at most [`MAX_TOKEN_FILE_BYTES`] read); none = no token
    /// check. A token file that cannot be read, is too long or holds no token is an error.
    pub fn resolved_auth_token(&self) -> Result<Option<String>, ServiceError> {
        if let Some(t) = &self.auth_token {
            return Ok(Some(t.clone()));
        }
        let Some(p) = &self.auth_token_file else { return Ok(None) };
        let failed = |e: String| ServiceError::Config(format!("auth_token_file {}: {e}", p.display()));
        let text = crate::io::bounded::read_to_string(p, MAX_TOKEN_FILE_BYTES).map_err(|e| failed(e.to_string()))?;
        let t = text.trim().to_string();
        if t.is_empty() {
            return Err(failed("the file holds no token (it is empty or blank)".into()));
        }
        check_token(&t).map_err(failed)?;
        Ok(Some(t))
    }

    /// Checks that no duration, count or size key is out of the range the server can hold
    /// ([`MAX_SECONDS`], [`MAX_COUNT`], [`MAX_MIB`], [`MAX_PREFETCH`]); the error names the key.
    fn validate_ranges(&self) -> Result<(), ServiceError> {
        let seconds = [
            ("idle_connection_timeout_s", self.idle_connection_timeout_s, MIN_TIMEOUT_SECONDS),
            ("stall_timeout_s", self.stall_timeout_s, MIN_TIMEOUT_SECONDS),
            ("drain_timeout_s", self.drain_timeout_s, 0.0),
        ];
        for (key, v, least) in seconds {
            if !(v.is_finite() && v >= least && v <= MAX_SECONDS) {
                return Err(ServiceError::Config(format!(
                    "{key} = {v:?} (expected seconds, at least {least:?} and at most {MAX_SECONDS:?})"
                )));
            }
        }
        let max_ms = (MAX_SECONDS * 1e3) as u64;
        let counts = [
            ("warmup_delay_ms", self.warmup_delay_ms, max_ms),
            ("max_streams", self.max_streams as u64, MAX_COUNT),
            ("max_in_flight", self.max_in_flight as u64, MAX_COUNT),
            ("max_connections", self.max_connections as u64, MAX_COUNT),
            ("max_connections_per_peer", self.max_connections_per_peer as u64, MAX_COUNT),
            ("max_calls_per_connection", u64::from(self.max_calls_per_connection), MAX_COUNT),
            ("max_random_access_calls", self.max_random_access_calls as u64, MAX_COUNT),
            ("max_sample_work", self.max_sample_work, MAX_COUNT),
            ("max_concurrent_uploads", self.max_concurrent_uploads as u64, MAX_COUNT),
            ("default_prefetch", u64::from(self.default_prefetch), u64::from(MAX_PREFETCH)),
            ("max_prefetch", u64::from(self.max_prefetch), u64::from(MAX_PREFETCH)),
            ("max_buffered_mb", self.max_buffered_mb, MAX_MIB),
            ("cache_mb", self.cache_mb, MAX_MIB),
            ("max_upload_buffer_mb", self.max_upload_buffer_mb, MAX_MIB),
        ];
        for (key, v, most) in counts {
            if v > most {
                return Err(ServiceError::Config(format!("{key} = {v} (expected at most {most})")));
            }
        }
        Ok(())
    }

    /// The parsed `size`.
    pub fn resize(&self) -> Result<Option<(usize, usize)>, ServiceError> {
        self.size.as_deref().map(parse_size).transpose().map_err(|e| ServiceError::Config(format!("size: {e}")))
    }

    /// The worker count (0 resolved to the number of cores).
    pub fn worker_count(&self) -> usize {
        match self.workers {
            0 => std::thread::available_parallelism().map(std::num::NonZero::get).unwrap_or(1),
            n => n,
        }
    }

    /// The byte budget of made-but-unsent samples (`max_buffered_mb`, 0 resolved for the
    /// machine: a quarter of [`memory_limit_bytes`], 256 to 4096 MiB; 1024 MiB when unknown).
    pub fn buffered_budget_bytes(&self) -> u64 {
        const MIB: u64 = 1 << 20;
        match self.max_buffered_mb {
            0 => memory_limit_bytes().map_or(1024 * MIB, |m| (m / 4).clamp(256 * MIB, 4096 * MIB)),
            n => n.saturating_mul(MIB),
        }
    }

    /// The in-flight bound (0 resolved to 2 x workers).
    pub fn in_flight_capacity(&self) -> usize {
        match self.max_in_flight {
            0 => 2 * self.worker_count(),
            n => n,
        }
    }

    /// Limits for decoding source images.
    pub fn image_limits(&self) -> ImageLimits {
        ImageLimits {
            max_width: self.max_image_side,
            max_height: self.max_image_side,
            max_pixels: self.max_image_pixels,
            max_bytes: self.max_image_bytes,
        }
    }

    /// Limits for decoding a folder's photos ([`image_limits`](Self::image_limits) with
    /// `max_photo_pixels`).
    pub fn photo_limits(&self) -> ImageLimits {
        ImageLimits { max_pixels: self.max_photo_pixels.max(self.max_image_pixels), ..self.image_limits() }
    }

    /// The largest sample in pixels: the resize size, else `max_image_pixels`.
    pub fn max_sample_pixels(&self) -> u64 {
        match self.resize() {
            Ok(Some((w, h))) => (w * h) as u64,
            _ => self.max_image_pixels,
        }
    }

    /// The limit of a reply message: the largest sample the configuration admits (a clip of the
    /// most frames with every field at the largest frame, [`sample_bytes_bound`]), at least
    /// 64 MiB, at most [`MAX_MESSAGE_CAP`]. A request whose largest sample is over it is refused
    /// before any work (`validate::admit_size`); a batch is cut short rather than exceed it.
    pub fn max_message_bytes(&self) -> u64 {
        sample_bytes_bound(self.max_sample_pixels(), bytes_per_pixel_largest(), 14).clamp(64 << 20, MAX_MESSAGE_CAP)
    }

    /// The limit of a request message: an upload chunk may carry a whole source file
    /// (`max_image_bytes`) plus 1 MiB; at least 64 MiB, at most [`MAX_MESSAGE_CAP`].
    pub fn max_request_bytes(&self) -> u64 {
        self.max_image_bytes.saturating_add(1 << 20).clamp(64 << 20, MAX_MESSAGE_CAP)
    }
}

/// A bearer token: 1 to 4096 visible ASCII characters (it travels in an HTTP/2 header).
fn check_token(t: &str) -> Result<(), String> {
    if t.is_empty() || t.len() > 4096 || !t.bytes().all(|b| b.is_ascii_graphic()) {
        return Err("expected 1 to 4096 visible ASCII characters (no spaces)".into());
    }
    Ok(())
}

/// Dataset and upload names: 1 to 64 of letters, digits, `-`, `_`, `.`, not starting with `.`.
pub fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= crate::source::upload::MAX_DATASET_NAME
        && !name.starts_with('.')
        && name.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
}

/// The memory this process may use: the cgroup v2 limit (`memory.max`) when one is set, else
/// the machine's physical memory (`MemTotal`); None where neither can be read.
pub fn memory_limit_bytes() -> Option<u64> {
    let total = std::fs::read_to_string("/proc/meminfo").ok().and_then(|t| {
        let line = t.lines().find(|l| l.starts_with("MemTotal:"))?;
        let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some(kib * 1024)
    });
    let cgroup = std::fs::read_to_string("/sys/fs/cgroup/memory.max").ok().and_then(|t| t.trim().parse::<u64>().ok());
    match (cgroup, total) {
        (Some(c), Some(t)) => Some(c.min(t)),
        (c, t) => c.or(t),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn toml_env_and_defaults() {
        let mut c = ServiceConfig::from_toml(
            "addr = \"0.0.0.0:1\"\nworkers = 3\n[sample]\nmax_objects = 2\n[[datasets]]\npath = \"/data/photos\"\n",
        )
        .unwrap();
        assert_eq!(c.addr, "0.0.0.0:1");
        assert_eq!(c.workers, 3);
        assert_eq!(c.sample.max_objects, 2);
        assert_eq!(c.datasets[0].name(), "photos");
        assert_eq!(c.max_streams, 64);
        c.apply_env_vars([
            ("MPIFLOW_WORKERS".to_string(), "5".to_string()),
            ("MPIFLOW_SOURCES".to_string(), "a=/x,/y/z".to_string()),
            ("MPIFLOW_PHOTOS".to_string(), "/ignored".to_string()),
            ("HOME".to_string(), "/root".to_string()),
        ])
        .unwrap();
        assert_eq!(c.workers, 5);
        assert_eq!(c.datasets.iter().map(super::DatasetConfig::name).collect::<Vec<_>>(), ["a", "z"]);
        c.validate().unwrap();
        let e = c.apply_env_vars([("MPIFLOW_WORKERS".to_string(), "many".to_string())]).unwrap_err();
        assert!(e.contains("MPIFLOW_WORKERS"), "{e}");
        assert!(ServiceConfig::from_toml("wrokers = 1").unwrap_err().contains("wrokers"));
    }

    #[test]
    fn security_keys_from_toml_and_env() {
        let mut c = ServiceConfig::from_toml(
            "tls_cert = \"/tls/tls.crt\"\ntls_key = \"/tls/tls.key\"\nauth_token_file = \"/secret/token\"\n",
        )
        .unwrap();
        assert_eq!(c.tls_cert.as_deref(), Some(Path::new("/tls/tls.crt")));
        c.validate().unwrap();
        // a token from the environment replaces the file's token file
        c.apply_env_vars([
            ("MPIFLOW_AUTH_TOKEN".to_string(), " abc \n".to_string()),
            ("MPIFLOW_TLS_CLIENT_CA".to_string(), "/tls/ca.crt".to_string()),
        ])
        .unwrap();
        assert_eq!((c.auth_token.as_deref(), c.auth_token_file.as_ref()), (Some("abc"), None));
        assert_eq!(c.tls_client_ca.as_deref(), Some(Path::new("/tls/ca.crt")));
        c.validate().unwrap();
        assert_eq!(c.resolved_auth_token().unwrap().as_deref(), Some("abc"));
        // both from the environment: refused
        c.apply_env_vars([
            ("MPIFLOW_AUTH_TOKEN".to_string(), "abc".to_string()),
            ("MPIFLOW_AUTH_TOKEN_FILE".to_string(), "/t".to_string()),
        ])
        .unwrap();
        assert!(c.validate().unwrap_err().to_string().contains("auth_token"));
        let client_ca_alone = ServiceConfig { tls_client_ca: Some("/ca".into()), ..ServiceConfig::default() };
        assert!(client_ca_alone.validate().unwrap_err().to_string().contains("tls_client_ca"));
    }

    /// An empty security setting in any layer stops the start-up: the environment (which would
    /// otherwise unset the key, and with `auth_token` the file's `auth_token_file` too), the file
    /// and a token file that is empty or blank.
    #[test]
    fn an_empty_security_setting_is_an_error_in_every_layer() {
        let file = ServiceConfig::from_toml("auth_token_file = \"/secret/token\"\n").unwrap();
        for var in ["AUTH_TOKEN", "AUTH_TOKEN_FILE", "TLS_CERT", "TLS_KEY", "TLS_CLIENT_CA"] {
            for empty in ["", "  "] {
                let mut c = file.clone();
                let e = c.apply_env_vars([(format!("MPIFLOW_{var}"), empty.to_string())]).unwrap_err();
                assert!(e.starts_with(&format!("MPIFLOW_{var} is set but empty")), "{e}");
                assert_eq!(c, file, "nothing changed");
            }
        }
        // other keys: empty is still the default
        let mut c = file.clone();
        c.apply_env_vars([("MPIFLOW_METRICS_ADDR".to_string(), String::new())]).unwrap();
        assert_eq!(c.auth_token_file.as_deref(), Some(Path::new("/secret/token")));
        for text in ["auth_token = \"\"", "auth_token = \"  \""] {
            let e = ServiceConfig::from_toml(text).unwrap().validate().unwrap_err().to_string();
            assert!(e.contains("auth_token is empty"), "{e}");
        }
        for key in ["auth_token_file", "tls_cert", "tls_key", "tls_client_ca"] {
            let e = ServiceConfig::from_toml(&format!("{key} = \"\"")).unwrap().validate().unwrap_err().to_string();
            assert!(e.contains(&format!("{key} is empty")), "{e}");
        }
        let dir = std::env::temp_dir().join(format!("mpiflow-empty-token-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for (name, contents) in [("empty", "".to_string()), ("blank", " \n\t\n".to_string())] {
            let p = dir.join(name);
            std::fs::write(&p, contents).unwrap();
            let c = ServiceConfig { auth_token_file: Some(p), ..ServiceConfig::default() };
            c.validate().unwrap();
            let e = c.resolved_auth_token().unwrap_err().to_string();
            assert!(e.contains("auth_token_file") && e.contains("holds no token"), "{e}");
        }
        let missing = ServiceConfig { auth_token_file: Some(dir.join("missing")), ..ServiceConfig::default() };
        assert!(missing.resolved_auth_token().unwrap_err().to_string().contains("missing"));
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Files are read with a bound: a token file or a configuration file that is `/dev/zero` is
    /// refused at the bound, not read without end.
    #[cfg(unix)]
    #[test]
    fn endless_token_and_configuration_files_are_refused() {
        let zero = PathBuf::from("/dev/zero");
        let c = ServiceConfig { auth_token_file: Some(zero.clone()), ..ServiceConfig::default() };
        let e = c.resolved_auth_token().unwrap_err().to_string();
        assert!(
            e.contains("auth_token_file /dev/zero") && e.contains(&format!("larger than {MAX_TOKEN_FILE_BYTES}")),
            "{e}"
        );
        let e = ServiceConfig::from_file(&zero).unwrap_err().to_string();
        assert!(e.contains("/dev/zero") && e.contains(&format!("larger than {MAX_CONFIG_FILE_BYTES}")), "{e}");
    }

    /// Durations and counts the server cannot hold (a timeout of 1e300 s, NaN, 2^63 - 1
    /// connections) are configuration errors naming the key, never a panic later.
    #[test]
    fn out_of_range_values_are_refused_naming_the_key() {
        let cases = [
            "idle_connection_timeout_s = 1e300",
            "idle_connection_timeout_s = nan",
            "stall_timeout_s = inf",
            "stall_timeout_s = 86400.5",
            "stall_timeout_s = 0.0",
            "drain_timeout_s = 1e300",
            "drain_timeout_s = -1.0",
            "warmup_delay_ms = 9223372036854775807",
            "max_connections = 9223372036854775807",
            "max_connections_per_peer = 9223372036854775807",
            "max_streams = 9223372036854775807",
            "max_in_flight = 9223372036854775807",
            "max_random_access_calls = 9223372036854775807",
            "max_concurrent_uploads = 9223372036854775807",
            "max_calls_per_connection = 4294967295",
            "default_prefetch = 4294967295",
            "max_prefetch = 4294967295",
            "max_buffered_mb = 9223372036854775807",
            "cache_mb = 9223372036854775807",
            "max_upload_buffer_mb = 9223372036854775807",
        ];
        for text in cases {
            let key = text.split(' ').next().unwrap();
            let e = ServiceConfig::from_toml(text).unwrap().validate().unwrap_err().to_string();
            assert!(e.contains(&format!("{key} = ")) && e.contains("expected"), "{text}: {e}");
        }
        // the bounds themselves are accepted
        let edge = format!(
            "stall_timeout_s = {MAX_SECONDS}\nmax_connections = {MAX_COUNT}\nmax_prefetch = {MAX_PREFETCH}\n\
             cache_mb = {MAX_MIB}\ndrain_timeout_s = 0.0"
        );
        ServiceConfig::from_toml(&edge).unwrap().validate().unwrap();
    }

    #[test]
    fn the_shipped_example_is_the_default() {
        let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/deploy/mpiflow.toml")).unwrap();
        let c = ServiceConfig::from_toml(&text).unwrap();
        assert_eq!(c, ServiceConfig::default());
    }

    #[test]
    fn message_limit_fits_the_largest_sample() {
        let c = ServiceConfig::default();
        // a clip of 8 frames with all 14 fields: 8 x 3 + 7 x (8 + 1 + 1) x 2 + 3 + 3 x 4 bytes
        assert_eq!(bytes_per_pixel_largest(), 24 + 140 + 3 + 12);
        assert!(c.max_message_bytes() >= bytes_per_pixel_largest() * c.max_image_pixels);
        assert!(c.max_message_bytes() <= MAX_MESSAGE_CAP);
        let small = ServiceConfig { size: Some("64x48".into()), ..ServiceConfig::default() };
        assert_eq!(small.max_message_bytes(), 64 << 20);
    }
}
