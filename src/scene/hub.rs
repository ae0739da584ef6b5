//! Fetching a registry model from the Hugging Face hub (or a mirror) into the hub's standard
//! cache, as `huggingface_hub` lays it out, verified by SHA-256; offline from that cache.
//!
//! - Endpoint: `HF_ENDPOINT` (default `https://huggingface.co`); a file's URL is
//!   `{endpoint}/{repo}/resolve/{revision}/{file}`.
//! - Cache: `HF_HUB_CACHE`, else `$HF_HOME/hub`, else `$XDG_CACHE_HOME/huggingface/hub`, else
//!   `~/.cache/huggingface/hub`. A file lives at `models--ORG--NAME/blobs/SHA256` with the link
//!   `models--ORG--NAME/snapshots/COMMIT/FILE` to it; a revision that is not a commit is recorded
//!   in `refs/REVISION` (the commit the server named in `X-Repo-Commit`, else the revision
//!   itself). A cached model is found by its pinned hash first (`blobs/SHA256`), then at its
//!   snapshot path (a file put there by hand); either is hashed again each time it is opened.
//! - `HF_HUB_OFFLINE=1` (or `true`, `yes`, `on`): the cache only; without the file there, the
//!   error names the URL and the path to put the file at.
//! - Bounds: name lookup, connecting and each read wait at most `HF_HUB_DOWNLOAD_TIMEOUT`
//!   seconds ([`DEFAULT_TIMEOUT_S`], as `huggingface_hub`); a file's whole fetch (the wait for
//!   its lock included) ends within `MPIFLOW_DOWNLOAD_DEADLINE_S` ([`DEFAULT_DEADLINE_S`]); each
//!   span of `HF_HUB_DOWNLOAD_TIMEOUT` seconds of the body brings at least
//!   `MPIFLOW_DOWNLOAD_MIN_RATE` bytes a second ([`DEFAULT_MIN_RATE`]; 0 = no least rate), so
//!   a mirror that trickles fails early; a file is at most the registry's `size` when it pins
//!   one, else [`MAX_MODEL_BYTES`]: a longer `Content-Length` is refused before any byte is read,
//!   a longer body stops at the bound.
//! - One download of a file at a time: it holds an exclusive lock on
//!   `.locks/models--ORG--NAME/SHA256.lock` (where `huggingface_hub` keeps its locks; the holder
//!   writes its process id and the time it took the lock there), writes
//!   `blobs/SHA256.incomplete`, and renames it into place only when whole and of the pinned
//!   SHA-256, then hashes the file in place again. A second fetch waits for the lock until the
//!   deadline, then fails naming the holder. A download that fails for any reason (the mirror,
//!   the deadline, a full disk) removes its partial file; one left by a process that was killed
//!   is resumed by the next download (an HTTP `Range` request).
//! - No symbolic link is followed inside the cache folder (the folder itself may be one):
//!   directories are checked before they are used and files opened with `O_NOFOLLOW`, a link
//!   there is refused; the snapshot links are the only links, made here.
//! - Registry paths (`repo`, `revision`, `file`) with `..`, `.`, empty or absolute components
//!   are refused ([`check_file`]).

use std::fs::{File, OpenOptions};
use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Component, Path, PathBuf};
use std::time::{Duration, Instant};

use sha2::{Digest, Sha256};

/// A pinned file in a hub repository: what [`Hub::fetch`] fetches (a registry entry names one).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct HubFile {
    /// The name errors give the file (the registry entry's name).
    pub name: String,
    /// The hub repository, `ORG/NAME`.
    pub repo: String,
    /// A commit (40 hex digits) or a branch or tag name.
    pub revision: String,
    /// The file in the repository.
    pub file: String,
    /// The SHA-256 of the file, lower-case hex.
    pub sha256: String,
    /// The file's size in bytes: a download stops there (without it, at [`MAX_MODEL_BYTES`]).
    pub size: Option<u64>,
}

/// The public hub.
pub const DEFAULT_ENDPOINT: &str = "https://huggingface.co";
/// Redirects followed per download (the hub sends files from a CDN).
const MAX_REDIRECTS: usize = 8;
/// The longest a name lookup, a connection or one read may take by default, in seconds
/// (`HF_HUB_DOWNLOAD_TIMEOUT` sets it).
pub const DEFAULT_TIMEOUT_S: f64 = 10.0;
/// The variable that sets the download timeout, in seconds (as `huggingface_hub` reads it).
pub const TIMEOUT_ENV: &str = "HF_HUB_DOWNLOAD_TIMEOUT";
/// The longest a file's whole fetch may take by default (the wait for its lock, the request and
/// the body), in seconds (`MPIFLOW_DOWNLOAD_DEADLINE_S` sets it): a 533 MB model at 150 KB/s.
pub const DEFAULT_DEADLINE_S: f64 = 3600.0;
/// The variable that sets the deadline of a file's fetch, in seconds.
pub const DEADLINE_ENV: &str = "MPIFLOW_DOWNLOAD_DEADLINE_S";
/// The least rate of a download by default, in bytes a second, over each span of the read
/// timeout (`MPIFLOW_DOWNLOAD_MIN_RATE` sets it; 0 = none).
pub const DEFAULT_MIN_RATE: u64 = 64 << 10;
/// The variable that sets the least rate of a download, in bytes a second.
pub const MIN_RATE_ENV: &str = "MPIFLOW_DOWNLOAD_MIN_RATE";
/// How often a fetch waiting for another's lock tries it again.
const LOCK_POLL: Duration = Duration::from_millis(100);

/// The variable naming a TOML file of further registry entries (the same layout as the built-in
/// registry); an entry with a built-in name replaces it. Named here, where the hub's errors say
/// how to pin a file of one's own.
pub const REGISTRY_ENV: &str = "MPIFLOW_MODEL_REGISTRY";

/// The largest model file fetched when the registry pins no size: 2 GiB, protobuf's limit on one
/// message and so on an ONNX file without external data.
pub const MAX_MODEL_BYTES: u64 = 2 << 30;

#[derive(Debug, thiserror::Error)]
pub enum HubError {
    #[error(
        "HF_HUB_OFFLINE is set and the file is not in the cache: download {url} and put it at {} (or unset \
         HF_HUB_OFFLINE)",
        .path.display()
    )]
    Offline { url: String, path: PathBuf },
    #[error("{url}: {message}")]
    Http { url: String, message: String },
    #[error(
        "{url}: {message}: the hub cannot be reached; set HF_ENDPOINT to a mirror, or download the file \
         elsewhere and put it at {}",
        .path.display()
    )]
    Unreachable { url: String, path: PathBuf, message: String },
    #[error("{url}: no answer within {seconds} s ({TIMEOUT_ENV}); nothing was kept")]
    TimedOut { url: String, seconds: f64 },
    #[error(
        "{url}: the download did not finish within its deadline of {seconds} s ({DEADLINE_ENV}); nothing was kept"
    )]
    DeadlineExceeded { url: String, seconds: f64 },
    #[error(
        "{url}: {got} bytes in {window} s, below the least rate of {min_rate} bytes a second ({MIN_RATE_ENV}); \
         nothing was kept"
    )]
    TooSlow { url: String, got: u64, window: f64, min_rate: u64 },
    #[error(
        "{}: another download of this file holds the lock ({holder}) and did not end within the deadline of \
         {seconds} s ({DEADLINE_ENV}); try again when it is done",
        .path.display()
    )]
    Locked { path: PathBuf, holder: String, seconds: f64 },
    #[error("{url}: the download ended after {got} of {expected} bytes; nothing was kept, run it again")]
    Interrupted { url: String, got: u64, expected: u64 },
    #[error("{url}: the file is larger than the {limit} bytes {what}: refused; nothing was kept")]
    TooLarge { url: String, limit: u64, what: &'static str },
    #[error(
        "{what} has SHA-256 {actual}, but the registry pins {expected}: refused{kept}. To use this file \
         anyway, give it as a FILE (--depth-model FILE, --segment-model FILE) or pin it in your own \
         registry ({})",
        REGISTRY_ENV
    )]
    Checksum { what: String, expected: String, actual: String, kept: &'static str },
    #[error("{}: a symbolic link inside the hub cache: refused (nothing is written through it)", .path.display())]
    Link { path: PathBuf },
    #[error("model registry entry {name}: {message}")]
    BadEntry { name: String, message: String },
    #[error("{}: {message}", .path.display())]
    Io { path: PathBuf, message: String },
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> HubError + '_ {
    move |e| HubError::Io { path: path.to_path_buf(), message: e.to_string() }
}

/// Where models come from and where they are kept.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Hub {
    /// The hub's base URL, no trailing `/`.
    pub endpoint: String,
    /// The hub cache folder (the one holding `models--ORG--NAME`).
    pub cache: PathBuf,
    pub offline: bool,
    /// The longest a name lookup, a connection or one read may take; also the span over which
    /// the least rate is measured.
    pub timeout: Duration,
    /// The longest a file's whole fetch may take (the wait for its lock included).
    pub deadline: Duration,
    /// The least bytes a second of a body, over each span of `timeout` (0 = none).
    pub min_rate: u64,
}

fn env_nonempty(key: &str) -> Option<String> {
    std::env::var(key).ok().filter(|v| !v.is_empty())
}

/// `HF_HUB_DOWNLOAD_TIMEOUT` as seconds: a positive number of at most a day, else the default.
fn timeout_from(value: Option<&str>) -> Duration {
    seconds_from(value, DEFAULT_TIMEOUT_S)
}

/// A positive number of seconds of at most a day, else `default`.
fn seconds_from(value: Option<&str>, default: f64) -> Duration {
    value
        .and_then(|v| v.trim().parse::<f64>().ok())
        .filter(|s| s.is_finite() && *s > 0.0 && *s <= 86_400.0)
        .map_or(Duration::from_secs_f64(default), Duration::from_secs_f64)
}

/// `MPIFLOW_DOWNLOAD_MIN_RATE` as bytes a second (0 = none), else the default.
fn rate_from(value: Option<&str>) -> u64 {
    value.and_then(|v| v.trim().parse::<u64>().ok()).unwrap_or(DEFAULT_MIN_RATE)
}

impl Hub {
    /// From `HF_ENDPOINT`, `HF_HUB_CACHE` / `HF_HOME` / `XDG_CACHE_HOME` / `HOME`,
    /// `HF_HUB_OFFLINE` and `HF_HUB_DOWNLOAD_TIMEOUT`, as `huggingface_hub` reads them.
    pub fn from_env() -> Self {
        let endpoint = env_nonempty("HF_ENDPOINT").unwrap_or_else(|| DEFAULT_ENDPOINT.into());
        let cache = match env_nonempty("HF_HUB_CACHE") {
            Some(c) => PathBuf::from(c),
            None => {
                let home = match env_nonempty("HF_HOME") {
                    Some(h) => PathBuf::from(h),
                    None => match env_nonempty("XDG_CACHE_HOME") {
                        Some(x) => Path::new(&x).join("huggingface"),
                        None => Path::new(&env_nonempty("HOME").unwrap_or_else(|| ".".into()))
                            .join(".cache")
                            .join("huggingface"),
                    },
                };
                home.join("hub")
            }
        };
        let offline = env_nonempty("HF_HUB_OFFLINE")
            .is_some_and(|v| matches!(v.to_ascii_lowercase().as_str(), "1" | "true" | "yes" | "on"));
        let timeout = timeout_from(env_nonempty(TIMEOUT_ENV).as_deref());
        let deadline = seconds_from(env_nonempty(DEADLINE_ENV).as_deref(), DEFAULT_DEADLINE_S);
        let min_rate = rate_from(env_nonempty(MIN_RATE_ENV).as_deref());
        Hub { endpoint: endpoint.trim_end_matches('/').to_string(), cache, offline, timeout, deadline, min_rate }
    }

    /// `{endpoint}/{repo}/resolve/{revision}/{file}`.
    pub fn url(&self, e: &HubFile) -> String {
        format!("{}/{}/resolve/{}/{}", self.endpoint, e.repo, e.revision, e.file)
    }

    /// `models--ORG--NAME`, the repository's folder name in the cache.
    fn repo_name(e: &HubFile) -> String {
        format!("models--{}", e.repo.replace('/', "--"))
    }

    /// `models--ORG--NAME` in the cache.
    pub fn repo_dir(&self, e: &HubFile) -> PathBuf {
        self.cache.join(Self::repo_name(e))
    }

    /// The commit a revision stands for in the cache: the revision itself when it is a commit,
    /// else the commit `refs/REVISION` records (read without following a link), else the
    /// revision.
    fn commit(&self, e: &HubFile) -> String {
        if is_commit(&e.revision) {
            return e.revision.clone();
        }
        let refs = self.repo_dir(e).join("refs").join(&e.revision);
        open_nofollow(&refs, OpenOptions::new().read(true))
            .ok()
            .and_then(|f| {
                let mut s = String::new();
                f.take(64).read_to_string(&mut s).ok().map(|_| s.trim().to_string())
            })
            .filter(|s| is_commit(s))
            .unwrap_or_else(|| e.revision.clone())
    }

    /// Where the file is (or would be) in the cache: `snapshots/COMMIT/FILE`.
    pub fn cached_path(&self, e: &HubFile) -> PathBuf {
        self.repo_dir(e).join("snapshots").join(self.commit(e)).join(&e.file)
    }

    /// `blobs/SHA256` of the file.
    fn blob_path(&self, e: &HubFile) -> PathBuf {
        self.repo_dir(e).join("blobs").join(&e.sha256)
    }

    /// The model file of `e`: the cached copy (its SHA-256 checked), else downloaded into the
    /// cache (unless offline). `progress` draws a progress bar on stderr.
    pub fn fetch(&self, e: &HubFile, progress: bool) -> Result<PathBuf, HubError> {
        check_file(e).map_err(|message| HubError::BadEntry { name: e.name.clone(), message })?;
        if let Some(p) = self.cached(e)? {
            return Ok(p);
        }
        if self.offline {
            return Err(HubError::Offline { url: self.url(e), path: self.cached_path(e) });
        }
        self.download(e, progress)
    }

    /// The cached file of `e`, checked: the blob of its hash first (then its snapshot path, made
    /// when missing and the cache is writable), else a file put at the snapshot path by hand.
    fn cached(&self, e: &HubFile) -> Result<Option<PathBuf>, HubError> {
        let blob = self.blob_path(e);
        if self.inside_dirs_exist(e, &["blobs"])? && is_regular(&blob)? {
            self.verify(&blob, e, " (the cached file is left as it is: delete it to download it again)")?;
            let link = self.cached_path(e);
            return Ok(Some(if self.is_our_link(&link, e) { link } else { blob }));
        }
        let snapshot = self.cached_path(e);
        let commit = self.commit(e);
        let file_dirs: Vec<&str> = e.file.split('/').collect();
        let dirs: Vec<&str> = std::iter::once("snapshots")
            .chain(commit.split('/'))
            .chain(file_dirs[..file_dirs.len() - 1].iter().copied())
            .collect();
        if !self.inside_dirs_exist(e, &dirs)? {
            return Ok(None);
        }
        // a link there is a snapshot link whose blob is missing: downloaded again, the link
        // replaced; only a regular file put there is used
        match std::fs::symlink_metadata(&snapshot) {
            Ok(m) if m.is_file() => {
                self.verify(&snapshot, e, " (the cached file is left as it is: delete it to download it again)")?;
                Ok(Some(snapshot))
            }
            _ => Ok(None),
        }
    }

    /// Whether the folders `dirs` below the repository's folder all exist (none a link).
    fn inside_dirs_exist(&self, e: &HubFile, dirs: &[&str]) -> Result<bool, HubError> {
        let mut p = self.cache.clone();
        for d in std::iter::once(Self::repo_name(e).as_str()).chain(dirs.iter().copied()) {
            p.push(d);
            match std::fs::symlink_metadata(&p) {
                Ok(m) if m.file_type().is_symlink() => return Err(HubError::Link { path: p }),
                Ok(m) if m.is_dir() => {}
                Ok(_) => return Ok(false),
                Err(err) if err.kind() == std::io::ErrorKind::NotFound => return Ok(false),
                Err(err) => return Err(io(&p)(err)),
            }
        }
        Ok(true)
    }

    /// Checks the SHA-256 of the file at `path` (opened without following a link).
    fn verify(&self, path: &Path, e: &HubFile, kept: &'static str) -> Result<(), HubError> {
        let actual = sha256_nofollow(path)?;
        if actual != e.sha256 {
            return Err(HubError::Checksum {
                what: path.display().to_string(),
                expected: e.sha256.clone(),
                actual,
                kept,
            });
        }
        Ok(())
    }

    /// Whether `link` is the relative link to the file's blob that [`place`] makes.
    fn is_our_link(&self, link: &Path, e: &HubFile) -> bool {
        std::fs::read_link(link).is_ok_and(|t| t == link_target(e))
    }

    /// The folders below the cache folder, made where missing; a link among them is refused.
    fn make_dirs(&self, parts: &[&str]) -> Result<PathBuf, HubError> {
        let mut p = self.cache.clone();
        std::fs::create_dir_all(&p).map_err(io(&p))?;
        for part in parts {
            p.push(part);
            match std::fs::symlink_metadata(&p) {
                Ok(m) if m.file_type().is_symlink() => return Err(HubError::Link { path: p }),
                Ok(m) if m.is_dir() => continue,
                Ok(_) => return Err(io(&p)(std::io::Error::other("not a folder"))),
                Err(err) if err.kind() == std::io::ErrorKind::NotFound => {}
                Err(err) => return Err(io(&p)(err)),
            }
            match std::fs::create_dir(&p) {
                Ok(()) => {}
                // made by another download meanwhile: checked again
                Err(err) if err.kind() == std::io::ErrorKind::AlreadyExists => {
                    if std::fs::symlink_metadata(&p).map_err(io(&p))?.file_type().is_symlink() {
                        return Err(HubError::Link { path: p });
                    }
                }
                Err(err) => return Err(io(&p)(err)),
            }
        }
        Ok(p)
    }

    fn download(&self, e: &HubFile, progress: bool) -> Result<PathBuf, HubError> {
        let deadline = Instant::now() + self.deadline;
        let url = self.url(e);
        let repo_name = Self::repo_name(e);
        let locks = self.make_dirs(&[".locks", &repo_name])?;
        let lock_path = locks.join(format!("{}.lock", e.sha256));
        let lock = self.take_lock(&lock_path, deadline)?;
        // another download may have finished while this one waited for the lock
        if let Some(p) = self.cached(e)? {
            return Ok(p);
        }
        let blobs = self.make_dirs(&[&repo_name, "blobs"])?;
        let blob = blobs.join(&e.sha256);
        let partial_path = blobs.join(format!("{}.incomplete", e.sha256));
        tracing::info!(
            model = %e.name,
            %url,
            to = %blob.display(),
            deadline_s = self.deadline.as_secs_f64(),
            min_rate = self.min_rate,
            "downloading a model"
        );
        let (actual, commit) = match self.receive(&url, e, &partial_path, progress, deadline) {
            Ok(r) => r,
            Err(err) => {
                // whatever went wrong, the partial file goes (a link planted there is left alone)
                if !matches!(err, HubError::Link { .. }) && is_regular(&partial_path).unwrap_or(false) {
                    let _ = std::fs::remove_file(&partial_path);
                }
                return Err(err);
            }
        };
        if actual != e.sha256 {
            let _ = std::fs::remove_file(&partial_path);
            return Err(HubError::Checksum {
                what: url,
                expected: e.sha256.clone(),
                actual,
                kept: "; nothing was kept",
            });
        }
        // rename replaces whatever is at `blob` (a link too) without following it
        std::fs::rename(&partial_path, &blob).map_err(io(&blob))?;
        if let Err(err) = self.verify(&blob, e, "; it was removed") {
            let _ = std::fs::remove_file(&blob);
            return Err(err);
        }
        let link = self.link_snapshot(e, &repo_name, &blob, commit)?;
        drop(lock);
        Ok(link)
    }

    /// The download lock at `lock_path`, waited for until `deadline`; the holder's process id
    /// and the time it took the lock are written into it. Waiting past the deadline is
    /// [`HubError::Locked`], naming the holder.
    fn take_lock(&self, lock_path: &Path, deadline: Instant) -> Result<File, HubError> {
        let mut lock = open_nofollow(lock_path, OpenOptions::new().read(true).write(true).create(true))?;
        let mut logged = false;
        loop {
            match lock.try_lock() {
                Ok(()) => break,
                Err(std::fs::TryLockError::WouldBlock) => {}
                Err(std::fs::TryLockError::Error(err)) => return Err(io(lock_path)(err)),
            }
            let holder = lock_holder(lock_path);
            let now = Instant::now();
            if now >= deadline {
                return Err(HubError::Locked {
                    path: lock_path.to_path_buf(),
                    holder,
                    seconds: self.deadline.as_secs_f64(),
                });
            }
            if !logged {
                tracing::info!(lock = %lock_path.display(), %holder, "waiting for another download of the model");
                logged = true;
            }
            std::thread::sleep(LOCK_POLL.min(deadline - now));
        }
        let unix = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |d| d.as_secs());
        let record = format!("process {} since unix time {unix}\n", std::process::id());
        let written = lock
            .set_len(0)
            .and_then(|()| lock.seek(SeekFrom::Start(0)))
            .and_then(|_| lock.write_all(record.as_bytes()));
        written.map_err(io(lock_path))?;
        Ok(lock)
    }

    /// Receives `e` from `url` into `partial_path`, resuming what a killed download left there:
    /// the SHA-256 of the whole file (hex) and the commit the hub named. It ends by `deadline`,
    /// and each span of `timeout` brings at least `min_rate` bytes a second.
    fn receive(
        &self,
        url: &str,
        e: &HubFile,
        partial_path: &Path,
        progress: bool,
        deadline: Instant,
    ) -> Result<(String, Option<String>), HubError> {
        let limit = e.size.unwrap_or(MAX_MODEL_BYTES);
        // the bytes an interrupted download kept, resumed unless over the bound
        let kept = if is_regular(partial_path)? {
            std::fs::symlink_metadata(partial_path).map_err(io(partial_path))?.len()
        } else {
            0
        };
        let (response, commit, resumed) = self.request(url, e, if kept > limit { 0 } else { kept }, deadline)?;
        let mut got = if resumed { kept } else { 0 };
        let mut partial =
            open_nofollow(partial_path, OpenOptions::new().read(true).write(true).create(true).truncate(false))?;
        partial.set_len(got).map_err(io(partial_path))?;
        // the bytes kept from before go into the hash first
        let mut hasher = Sha256::new();
        partial.seek(SeekFrom::Start(0)).map_err(io(partial_path))?;
        let copied =
            std::io::copy(&mut (&mut partial).take(got), &mut HashWriter(&mut hasher)).map_err(io(partial_path))?;
        if copied != got {
            return Err(io(partial_path)(std::io::Error::other("the partial file changed while it was read")));
        }
        let remaining =
            response.headers().get("content-length").and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<u64>().ok());
        let what = if e.size.is_some() { "the registry pins" } else { "a model file may have" };
        let too_large = HubError::TooLarge { url: url.to_string(), limit, what };
        if remaining.is_some_and(|r| got.saturating_add(r) > limit) {
            drop(partial);
            let _ = std::fs::remove_file(partial_path);
            return Err(too_large);
        }
        let expected = remaining.map(|r| got + r).or(e.size);
        let bar = progress.then(|| progress_bar(expected, &e.name, got));
        let mut reader = response.into_body().into_reader();
        let pace = Pace { deadline, window: self.timeout, min_rate: self.min_rate };
        let read =
            read_body(&mut reader, &mut partial, partial_path, &mut hasher, &mut got, limit, bar.as_ref(), &pace);
        let read = read.map_err(|stop| match stop {
            Stop::Io(err) => err,
            Stop::Deadline => HubError::DeadlineExceeded { url: url.to_string(), seconds: self.deadline.as_secs_f64() },
            Stop::Slow { got, window } => {
                HubError::TooSlow { url: url.to_string(), got, window, min_rate: self.min_rate }
            }
        })?;
        let Some(read_result) = read else {
            drop(partial);
            let _ = std::fs::remove_file(partial_path);
            return Err(too_large);
        };
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        partial.sync_all().map_err(io(partial_path))?;
        drop(partial);
        let url = url.to_string();
        if let Err(err) = read_result {
            return Err(match timeout_of(&err) {
                Some(ureq::Timeout::Global) => HubError::DeadlineExceeded { url, seconds: self.deadline.as_secs_f64() },
                Some(_) => HubError::TimedOut { url, seconds: self.timeout.as_secs_f64() },
                None if is_timeout(&err) => HubError::TimedOut { url, seconds: self.timeout.as_secs_f64() },
                None => match expected {
                    Some(expected) => HubError::Interrupted { url, got, expected },
                    None => HubError::Http { url, message: format!("reading the body: {err}") },
                },
            });
        }
        if let Some(expected) = expected.filter(|&x| x != got) {
            return Err(HubError::Interrupted { url, got, expected });
        }
        Ok((hex(&hasher.finalize()), commit))
    }

    /// The snapshot link of `e` to its `blob` (under the commit the hub named, or the entry's
    /// revision when that is a commit), and the ref of a revision that is not a commit.
    fn link_snapshot(
        &self,
        e: &HubFile,
        repo_name: &str,
        blob: &Path,
        commit: Option<String>,
    ) -> Result<PathBuf, HubError> {
        let commit = match commit {
            Some(c) if is_commit(&c) => c,
            _ => e.revision.clone(),
        };
        if !is_commit(&e.revision) {
            let rev: Vec<&str> = e.revision.split('/').collect();
            let mut dirs = vec![repo_name, "refs"];
            dirs.extend(&rev[..rev.len() - 1]);
            let refs = self.make_dirs(&dirs)?;
            let r = refs.join(rev[rev.len() - 1]);
            let mut f = open_nofollow(&r, OpenOptions::new().write(true).create(true).truncate(true))?;
            f.write_all(commit.as_bytes()).map_err(io(&r))?;
        }
        let parts: Vec<&str> = e.file.split('/').collect();
        let mut dirs = vec![repo_name, "snapshots", commit.as_str()];
        dirs.extend(&parts[..parts.len() - 1]);
        let dir = self.make_dirs(&dirs)?;
        let link = dir.join(parts[parts.len() - 1]);
        let _ = std::fs::remove_file(&link);
        place(blob, &link, e)?;
        Ok(link)
    }

    /// GETs `url` from byte `from` on (a `Range` request when `from` > 0), following redirects by
    /// hand (the first answer names the commit, `X-Repo-Commit`): the response, the commit and
    /// whether the server resumed at `from` (206), rather than sending the whole file (200).
    fn request(
        &self,
        url: &str,
        e: &HubFile,
        from: u64,
        deadline: Instant,
    ) -> Result<(ureq::http::Response<ureq::Body>, Option<String>, bool), HubError> {
        let http = |message: String| HubError::Http { url: url.to_string(), message };
        let t = Some(self.timeout);
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(HubError::DeadlineExceeded { url: url.to_string(), seconds: self.deadline.as_secs_f64() });
        }
        let agent: ureq::Agent = ureq::Agent::config_builder()
            .max_redirects(0)
            .timeout_global(Some(left))
            .http_status_as_error(false)
            .timeout_resolve(t)
            .timeout_connect(t)
            .timeout_send_request(t)
            .timeout_recv_response(t)
            .timeout_per_read(t)
            .build()
            .into();
        let mut next = url.to_string();
        let mut commit = None;
        for _ in 0..=MAX_REDIRECTS {
            let mut req = agent.get(&next);
            if from > 0 {
                req = req.header("range", format!("bytes={from}-"));
            }
            let r = req.call().map_err(|err| match err {
                ureq::Error::Timeout(ureq::Timeout::Global) => {
                    HubError::DeadlineExceeded { url: next.clone(), seconds: self.deadline.as_secs_f64() }
                }
                ureq::Error::Timeout(_) => {
                    HubError::TimedOut { url: next.clone(), seconds: self.timeout.as_secs_f64() }
                }
                err => HubError::Unreachable { url: next.clone(), path: self.cached_path(e), message: err.to_string() },
            })?;
            if commit.is_none() {
                commit = r.headers().get("x-repo-commit").and_then(|v| v.to_str().ok()).map(str::to_string);
            }
            let status = r.status();
            if status.is_redirection() {
                let location = r
                    .headers()
                    .get("location")
                    .and_then(|v| v.to_str().ok())
                    .ok_or_else(|| http(format!("HTTP {status} without a location")))?;
                next = join_location(&next, location);
                continue;
            }
            if from > 0 && status.as_u16() == 206 {
                let start = r
                    .headers()
                    .get("content-range")
                    .and_then(|v| v.to_str().ok())
                    .and_then(|v| v.strip_prefix("bytes "))
                    .and_then(|v| v.split('-').next())
                    .and_then(|v| v.parse::<u64>().ok());
                if start == Some(from) {
                    return Ok((r, commit, true));
                }
                return Err(http(format!("HTTP 206 that does not start at byte {from}")));
            }
            if from > 0 && status.as_u16() == 416 {
                // the partial file is not a prefix the server knows: start again
                return self.request(url, e, 0, deadline);
            }
            if !status.is_success() {
                let hint = match status.as_u16() {
                    401 | 403 => " (a gated or private repository: not supported)",
                    404 => " (no such repository, revision or file)",
                    _ => "",
                };
                return Err(http(format!("HTTP {status}{hint}")));
            }
            return Ok((r, commit, false));
        }
        Err(http(format!("more than {MAX_REDIRECTS} redirects")))
    }
}

/// The ureq timeout that failed a body read, if one did.
fn timeout_of(err: &std::io::Error) -> Option<ureq::Timeout> {
    match err.get_ref().and_then(|e| e.downcast_ref::<ureq::Error>()) {
        Some(ureq::Error::Timeout(t)) => Some(*t),
        _ => None,
    }
}

/// The pace a body must keep: done by `deadline`, and at least `min_rate` bytes a second over
/// each span of `window` (0 = no least rate).
struct Pace {
    deadline: Instant,
    window: Duration,
    min_rate: u64,
}

/// Why [`read_body`] stopped a download.
enum Stop {
    Io(HubError),
    Deadline,
    /// `got` bytes in the last `window` seconds, below the least rate.
    Slow {
        got: u64,
        window: f64,
    },
}

/// Whether a body read failed for want of data within the timeout.
fn is_timeout(err: &std::io::Error) -> bool {
    let ureq_timeout = err
        .get_ref()
        .and_then(|e| e.downcast_ref::<ureq::Error>())
        .is_some_and(|e| matches!(e, ureq::Error::Timeout(_)));
    ureq_timeout || matches!(err.kind(), std::io::ErrorKind::TimedOut | std::io::ErrorKind::WouldBlock)
}

/// Reads the body from `reader` into `partial` (at `partial_path`) and `hasher`, `got` counting
/// the file's bytes and `bar` showing them: the read's own result (an error cuts the download
/// short), or `None` when the file would grow over `limit`; a body that misses its `pace` (its
/// deadline, or its least rate over a span) stops it.
#[allow(clippy::too_many_arguments)]
fn read_body(
    reader: &mut impl Read,
    partial: &mut File,
    partial_path: &Path,
    hasher: &mut Sha256,
    got: &mut u64,
    limit: u64,
    bar: Option<&indicatif::ProgressBar>,
    pace: &Pace,
) -> Result<Option<std::io::Result<()>>, Stop> {
    let mut buf = vec![0u8; 1 << 16];
    let (mut span_start, mut span_bytes) = (Instant::now(), 0u64);
    loop {
        let n = match reader.read(&mut buf) {
            Ok(0) => return Ok(Some(Ok(()))),
            Ok(n) => n,
            Err(err) if err.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(err) => return Ok(Some(Err(err))),
        };
        if *got + n as u64 > limit {
            return Ok(None);
        }
        hasher.update(&buf[..n]);
        partial.write_all(&buf[..n]).map_err(|e| Stop::Io(io(partial_path)(e)))?;
        *got += n as u64;
        if let Some(b) = bar {
            b.set_position(*got);
        }
        let now = Instant::now();
        if now >= pace.deadline {
            return Err(Stop::Deadline);
        }
        span_bytes += n as u64;
        let span = now - span_start;
        if span >= pace.window {
            if (span_bytes as f64) < pace.min_rate as f64 * span.as_secs_f64() {
                return Err(Stop::Slow { got: span_bytes, window: span.as_secs_f64() });
            }
            (span_start, span_bytes) = (now, 0);
        }
    }
}

/// Who holds the download lock at `path`, as its holder wrote it (a process id and since when),
/// or that it did not say.
fn lock_holder(path: &Path) -> String {
    let said = open_nofollow(path, OpenOptions::new().read(true)).ok().and_then(|f| {
        let mut s = String::new();
        f.take(256).read_to_string(&mut s).ok().map(|_| s.trim().to_string())
    });
    match said.filter(|s| !s.is_empty()) {
        Some(s) => printable_line(&s),
        None => "a holder that did not say who it is".to_string(),
    }
}

/// `s` with control characters dropped (it comes from a file anyone may write).
fn printable_line(s: &str) -> String {
    s.chars().filter(|c| !c.is_control()).collect()
}

/// Feeds what is written into a SHA-256.
struct HashWriter<'a>(&'a mut Sha256);

impl Write for HashWriter<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.update(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// Checks the file's paths before any of them reaches a URL or the cache: `repo` is `ORG/NAME`
/// and `revision` and `file` relative paths, each component non-empty, not `.` or `..`, without
/// `\` or control characters; `sha256` is 64 lower-case hex digits.
pub fn check_file(e: &HubFile) -> Result<(), String> {
    let component_ok =
        |c: &str| !c.is_empty() && c != "." && c != ".." && !c.chars().any(|ch| ch == '\\' || ch.is_control());
    let relative = |what: &str, p: &str| -> Result<(), String> {
        let normal = Path::new(p).components().all(|c| matches!(c, Component::Normal(_)));
        if p.is_empty() || p.starts_with('/') || !normal || !p.split('/').all(component_ok) {
            return Err(format!("{what} {p:?} must be a relative path without `.`, `..` or empty parts"));
        }
        Ok(())
    };
    let repo: Vec<&str> = e.repo.split('/').collect();
    let repo_ok = repo.len() == 2
        && repo.iter().all(|c| component_ok(c) && c.chars().all(|ch| ch.is_ascii_alphanumeric() || "-_.".contains(ch)));
    if !repo_ok {
        return Err(format!("repo {:?} must be ORG/NAME (letters, digits, '-', '_', '.')", e.repo));
    }
    relative("revision", &e.revision)?;
    relative("file", &e.file)?;
    if !(e.sha256.len() == 64 && e.sha256.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))) {
        return Err("sha256 must be 64 lower-case hex digits".into());
    }
    Ok(())
}

/// Opens `path` with `options`, never through a symbolic link (`O_NOFOLLOW`): a link there is
/// [`HubError::Link`].
fn open_nofollow(path: &Path, options: &mut OpenOptions) -> Result<File, HubError> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NOFOLLOW);
    }
    match options.open(path) {
        Ok(f) => Ok(f),
        Err(err) => match std::fs::symlink_metadata(path) {
            Ok(m) if m.file_type().is_symlink() => Err(HubError::Link { path: path.to_path_buf() }),
            _ => Err(io(path)(err)),
        },
    }
}

/// Whether a regular file is at `path` (false when nothing is); a link there is refused.
fn is_regular(path: &Path) -> Result<bool, HubError> {
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_symlink() => Err(HubError::Link { path: path.to_path_buf() }),
        Ok(m) => Ok(m.is_file()),
        Err(err) if err.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(err) => Err(io(path)(err)),
    }
}

/// The relative link from `snapshots/COMMIT/FILE` to `blobs/SHA256`
/// (`../../[../]blobs/SHA256`, as `huggingface_hub` makes it).
fn link_target(e: &HubFile) -> PathBuf {
    PathBuf::from(format!("{}blobs/{}", "../".repeat(e.file.split('/').count() + 1), e.sha256))
}

/// Puts the snapshot entry at `link` for `blob`: a relative symbolic link where links exist, else
/// a copy.
fn place(blob: &Path, link: &Path, e: &HubFile) -> Result<(), HubError> {
    #[cfg(unix)]
    {
        let _ = blob;
        std::os::unix::fs::symlink(link_target(e), link).map_err(io(link))
    }
    #[cfg(not(unix))]
    {
        let _ = e;
        std::fs::copy(blob, link).map(|_| ()).map_err(io(link))
    }
}

/// A `Location` header against the URL it came from (absolute, or a path on the same origin).
fn join_location(from: &str, location: &str) -> String {
    if location.contains("://") {
        return location.to_string();
    }
    let origin_end = from.find("://").map_or(0, |i| i + 3);
    let origin = match from[origin_end..].find('/') {
        Some(i) => &from[..origin_end + i],
        None => from,
    };
    if location.starts_with('/') {
        format!("{origin}{location}")
    } else {
        let base = from.rsplit_once('/').map_or(from, |(b, _)| b);
        format!("{base}/{location}")
    }
}

fn progress_bar(len: Option<u64>, name: &str, at: u64) -> indicatif::ProgressBar {
    let bar = match len {
        Some(n) => indicatif::ProgressBar::new(n),
        None => indicatif::ProgressBar::no_length(),
    };
    bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
    let style =
        indicatif::ProgressStyle::with_template("{msg} [{bar:30}] {bytes}/{total_bytes} {bytes_per_sec} eta {eta}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> ");
    bar.set_style(style);
    bar.set_message(format!("downloading {name}"));
    bar.set_position(at);
    bar
}

/// Whether `s` is a full commit hash (40 hex digits).
pub fn is_commit(s: &str) -> bool {
    s.len() == 40 && s.bytes().all(|b| b.is_ascii_hexdigit())
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn sha256_of(mut f: File, path: &Path) -> Result<String, HubError> {
    let mut h = Sha256::new();
    std::io::copy(&mut f, &mut HashWriter(&mut h)).map_err(io(path))?;
    Ok(hex(&h.finalize()))
}

/// The SHA-256 of a file, lower-case hex.
pub fn sha256_file(path: &Path) -> Result<String, HubError> {
    sha256_of(File::open(path).map_err(io(path))?, path)
}

/// The SHA-256 of a file opened without following a link.
fn sha256_nofollow(path: &Path) -> Result<String, HubError> {
    sha256_of(open_nofollow(path, OpenOptions::new().read(true))?, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locations_join_like_a_browser() {
        assert_eq!(join_location("http://h:1/a/resolve/m/f.onnx", "https://cdn/x"), "https://cdn/x");
        assert_eq!(join_location("http://h:1/a/resolve/m/f.onnx", "/api/x"), "http://h:1/api/x");
        assert_eq!(join_location("http://h:1/a/resolve/m/f.onnx", "g.onnx"), "http://h:1/a/resolve/m/g.onnx");
    }

    #[test]
    fn commits_are_forty_hex_digits() {
        assert!(is_commit("4472b7362082ad9968fee890ca0f1e5aca36b93d"));
        assert!(!is_commit("main"));
    }

    #[test]
    fn the_timeout_variable_is_read_as_positive_seconds() {
        assert_eq!(timeout_from(None), Duration::from_secs(10));
        assert_eq!(timeout_from(Some("2.5")), Duration::from_millis(2500));
        for bad in ["0", "-1", "nan", "inf", "1e300", "soon"] {
            assert_eq!(timeout_from(Some(bad)), Duration::from_secs(10), "{bad}");
        }
    }
}
