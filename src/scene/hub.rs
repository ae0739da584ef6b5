//! Fetching a registry model from the Hugging Face hub (or a mirror) into the hub's standard
//! cache, as `huggingface_hub` lays it out, verified by SHA-256; offline from that cache.
//!
//! - Endpoint: `HF_ENDPOINT` (default `https://huggingface.co`); a file's URL is
//!   `{endpoint}/{repo}/resolve/{revision}/{file}`.
//! - Cache: `HF_HUB_CACHE`, else `$HF_HOME/hub`, else `$XDG_CACHE_HOME/huggingface/hub`, else
//!   `~/.cache/huggingface/hub`. A file lives at `models--ORG--NAME/blobs/SHA256` with the link
//!   `models--ORG--NAME/snapshots/COMMIT/FILE` to it; a revision that is not a commit is recorded
//!   in `refs/REVISION` (the commit the server named in `X-Repo-Commit`, else the revision
//!   itself).
//! - `HF_HUB_OFFLINE=1` (or `true`, `yes`, `on`): the cache only; without the file there, the
//!   error names the URL and the path to put the file at.
//! - A download goes to `blobs/SHA256.incomplete` while it is hashed, and is renamed into place
//!   only when whole and of the pinned SHA-256: a mismatch or an interrupted download keeps
//!   nothing. A cached file is hashed again each time it is opened.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use super::registry::Entry;

/// The public hub.
pub const DEFAULT_ENDPOINT: &str = "https://huggingface.co";
/// Redirects followed per download (the hub sends files from a CDN).
const MAX_REDIRECTS: usize = 8;

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
    #[error("{url}: the download ended after {got} of {expected} bytes; nothing was kept (run it again)")]
    Interrupted { url: String, got: u64, expected: u64 },
    #[error("{what} has SHA-256 {actual}, but the registry pins {expected}: refused{kept}")]
    Checksum { what: String, expected: String, actual: String, kept: &'static str },
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
}

fn env_nonempty(key: &str) -> Option<String> {
    std::env::var(key).ok().filter(|v| !v.is_empty())
}

impl Hub {
    /// From `HF_ENDPOINT`, `HF_HUB_CACHE` / `HF_HOME` / `XDG_CACHE_HOME` / `HOME` and
    /// `HF_HUB_OFFLINE`, as `huggingface_hub` reads them.
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
        Hub { endpoint: endpoint.trim_end_matches('/').to_string(), cache, offline }
    }

    /// `{endpoint}/{repo}/resolve/{revision}/{file}`.
    pub fn url(&self, e: &Entry) -> String {
        format!("{}/{}/resolve/{}/{}", self.endpoint, e.repo, e.revision, e.file)
    }

    /// `models--ORG--NAME` in the cache.
    pub fn repo_dir(&self, e: &Entry) -> PathBuf {
        self.cache.join(format!("models--{}", e.repo.replace('/', "--")))
    }

    /// The commit a revision stands for in the cache: the revision itself when it is a commit,
    /// else what `refs/REVISION` records, else the revision.
    fn commit(&self, e: &Entry) -> String {
        if is_commit(&e.revision) {
            return e.revision.clone();
        }
        std::fs::read_to_string(self.repo_dir(e).join("refs").join(&e.revision))
            .ok()
            .map(|s| s.trim().to_string())
            .filter(|s| !s.is_empty())
            .unwrap_or_else(|| e.revision.clone())
    }

    /// Where the file is (or would be) in the cache: `snapshots/COMMIT/FILE`.
    pub fn cached_path(&self, e: &Entry) -> PathBuf {
        self.repo_dir(e).join("snapshots").join(self.commit(e)).join(&e.file)
    }

    /// The model file of `e`: the cached copy (its SHA-256 checked), else downloaded into the
    /// cache (unless offline). `progress` draws a progress bar on stderr.
    pub fn fetch(&self, e: &Entry, progress: bool) -> Result<PathBuf, HubError> {
        let cached = self.cached_path(e);
        if cached.is_file() {
            let actual = sha256_file(&cached)?;
            if actual != e.sha256 {
                return Err(HubError::Checksum {
                    what: cached.display().to_string(),
                    expected: e.sha256.clone(),
                    actual,
                    kept: " (the cached file is left as it is: delete it to download it again)",
                });
            }
            return Ok(cached);
        }
        if self.offline {
            return Err(HubError::Offline { url: self.url(e), path: cached });
        }
        self.download(e, progress)
    }

    fn download(&self, e: &Entry, progress: bool) -> Result<PathBuf, HubError> {
        let url = self.url(e);
        let http = |message: String| HubError::Http { url: url.clone(), message };
        let agent: ureq::Agent =
            ureq::Agent::config_builder().max_redirects(0).http_status_as_error(false).build().into();
        // follow redirects by hand: the first answer names the commit (X-Repo-Commit)
        let mut next = url.clone();
        let mut commit = None;
        let mut response = None;
        for _ in 0..=MAX_REDIRECTS {
            let r = agent.get(&next).call().map_err(|err| HubError::Unreachable {
                url: next.clone(),
                path: self.cached_path(e),
                message: err.to_string(),
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
            if !status.is_success() {
                let hint = match status.as_u16() {
                    401 | 403 => " (a gated or private repository: not supported)",
                    404 => " (no such repository, revision or file)",
                    _ => "",
                };
                return Err(http(format!("HTTP {status}{hint}")));
            }
            response = Some(r);
            break;
        }
        let response = response.ok_or_else(|| http(format!("more than {MAX_REDIRECTS} redirects")))?;
        let expected_len =
            response.headers().get("content-length").and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<u64>().ok());

        let blobs = self.repo_dir(e).join("blobs");
        std::fs::create_dir_all(&blobs).map_err(io(&blobs))?;
        let blob = blobs.join(&e.sha256);
        let partial = blobs.join(format!("{}.incomplete", e.sha256));
        let result = (|| -> Result<(), HubError> {
            let mut out = std::fs::File::create(&partial).map_err(io(&partial))?;
            let bar = progress.then(|| progress_bar(expected_len, &e.name));
            let mut reader = response.into_body().into_reader();
            let mut hasher = Sha256::new();
            let mut got = 0u64;
            let mut buf = vec![0u8; 1 << 16];
            loop {
                let n = match reader.read(&mut buf) {
                    Ok(0) => break,
                    Ok(n) => n,
                    Err(err) if err.kind() == std::io::ErrorKind::Interrupted => continue,
                    Err(err) => {
                        return Err(match expected_len {
                            Some(expected) => HubError::Interrupted { url: url.clone(), got, expected },
                            None => http(format!("reading the body: {err}")),
                        })
                    }
                };
                hasher.update(&buf[..n]);
                out.write_all(&buf[..n]).map_err(io(&partial))?;
                got += n as u64;
                if let Some(b) = &bar {
                    b.set_position(got);
                }
            }
            if let Some(b) = bar {
                b.finish_and_clear();
            }
            if let Some(expected) = expected_len.filter(|&x| x != got) {
                return Err(HubError::Interrupted { url: url.clone(), got, expected });
            }
            let actual = hex(&hasher.finalize());
            if actual != e.sha256 {
                return Err(HubError::Checksum {
                    what: url.clone(),
                    expected: e.sha256.clone(),
                    actual,
                    kept: "; nothing was kept",
                });
            }
            out.sync_all().map_err(io(&partial))?;
            Ok(())
        })();
        if let Err(err) = result {
            let _ = std::fs::remove_file(&partial);
            return Err(err);
        }
        std::fs::rename(&partial, &blob).map_err(io(&blob))?;

        // the snapshot link, and the ref of a revision that is not a commit
        let commit = match commit {
            Some(c) if is_commit(&c) => c,
            _ => e.revision.clone(),
        };
        if !is_commit(&e.revision) {
            let refs = self.repo_dir(e).join("refs");
            std::fs::create_dir_all(&refs).map_err(io(&refs))?;
            let r = refs.join(&e.revision);
            std::fs::write(&r, &commit).map_err(io(&r))?;
        }
        let link = self.repo_dir(e).join("snapshots").join(&commit).join(&e.file);
        let dir = link.parent().unwrap_or(&link).to_path_buf();
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        let _ = std::fs::remove_file(&link);
        place(&blob, &link, e.file.split('/').count())?;
        Ok(link)
    }
}

/// Puts the snapshot entry at `link` for `blob`: a relative symbolic link
/// (`../../[../]blobs/SHA256`, as `huggingface_hub` makes it) where links exist, else a copy.
fn place(blob: &Path, link: &Path, file_depth: usize) -> Result<(), HubError> {
    #[cfg(unix)]
    {
        let up = "../".repeat(file_depth + 1);
        let name = blob.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        let target = PathBuf::from(format!("{up}blobs/{name}"));
        std::os::unix::fs::symlink(&target, link).map_err(io(link))
    }
    #[cfg(not(unix))]
    {
        let _ = file_depth;
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

fn progress_bar(len: Option<u64>, name: &str) -> indicatif::ProgressBar {
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
    bar
}

/// Whether `s` is a full commit hash (40 hex digits).
pub fn is_commit(s: &str) -> bool {
    s.len() == 40 && s.bytes().all(|b| b.is_ascii_hexdigit())
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The SHA-256 of a file, lower-case hex.
pub fn sha256_file(path: &Path) -> Result<String, HubError> {
    let mut f = std::fs::File::open(path).map_err(io(path))?;
    let mut h = Sha256::new();
    let mut buf = vec![0u8; 1 << 16];
    loop {
        let n = f.read(&mut buf).map_err(io(path))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(hex(&h.finalize()))
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
}
