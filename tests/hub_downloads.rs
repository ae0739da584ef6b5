//! Model downloads against a loopback HTTP mirror in the hub's URL layout (`scene::hub`), with
//! real files in a real cache folder: a silent or stalled mirror fails within the timeout (and a
//! stalled download resumes with a `Range` request), an endless body or a huge `Content-Length`
//! stops at the pinned size, concurrent fetches of one file give one verified file, a symbolic
//! link planted in the cache is refused with nothing outside the cache changed, and registry
//! paths with `..` are refused before anything is fetched or written. No ONNX Runtime needed:
//! the hub verifies bytes, whatever they are.

use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{mpsc, Arc, Barrier, Mutex};
use std::time::Duration;

use mpiflow::scene::hub::{Hub, HubError, HubFile};
use sha2::{Digest, Sha256};

const REPO: &str = "test-org/blob-hub";
const COMMIT: &str = "89abcdef0123456789abcdef0123456789abcdef";
const FILE: &str = "onnx/model.onnx";

/// The model's bytes: 300 KiB, deterministic.
fn model() -> Vec<u8> {
    (0..300u32 << 10).map(|i| (i.wrapping_mul(2_654_435_761) >> 11) as u8).collect()
}

fn sha256(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

fn entry(size: Option<u64>) -> HubFile {
    let body = model();
    HubFile {
        name: "blob-test".into(),
        repo: REPO.into(),
        revision: "main".into(),
        file: FILE.into(),
        sha256: sha256(&body),
        size,
    }
}

/// How the mirror answers the blob.
#[derive(Clone, Copy, PartialEq, Debug)]
enum Serve {
    /// The file (from the requested byte on, 206, for a `Range` request).
    Whole,
    /// Reads the request and never answers, the connection held open.
    Silent,
    /// Headers and the first half of the file, then nothing, the connection held open.
    Stall,
    /// Headers declaring the whole length and the first half, then the connection closed.
    Cut,
    /// No length, bytes without end.
    Endless,
    /// `Content-Length: 100 GB`, then bytes.
    HugeLength,
}

/// A loopback HTTP/1.1 mirror: `/{REPO}/resolve/main/{FILE}` answers 302 to `/blobs/model` with
/// `X-Repo-Commit`; the blob answers as `mode` says. Records the `Range` header of each blob
/// request (empty for none).
struct Mirror {
    endpoint: String,
    ranges: Arc<Mutex<Vec<String>>>,
    /// Connections held open (Silent, Stall), closed when the mirror is dropped.
    held: Arc<Mutex<Vec<TcpStream>>>,
}

fn mirror(mode: Serve) -> Mirror {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let endpoint = format!("http://{}", listener.local_addr().unwrap());
    let ranges = Arc::new(Mutex::new(Vec::new()));
    let held = Arc::new(Mutex::new(Vec::new()));
    let (r, h) = (ranges.clone(), held.clone());
    std::thread::spawn(move || {
        for conn in listener.incoming() {
            let Ok(conn) = conn else { continue };
            let (r, h) = (r.clone(), h.clone());
            std::thread::spawn(move || answer(conn, mode, &r, &h));
        }
    });
    Mirror { endpoint, ranges, held }
}

fn answer(mut conn: TcpStream, mode: Serve, ranges: &Mutex<Vec<String>>, held: &Mutex<Vec<TcpStream>>) {
    let body = model();
    let mut reader = BufReader::new(conn.try_clone().unwrap());
    let mut request_line = String::new();
    if reader.read_line(&mut request_line).is_err() {
        return;
    }
    let mut range = String::new();
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line).map_or(true, |n| n == 0) || line == "\r\n" {
            break;
        }
        if let Some(v) = line.to_ascii_lowercase().strip_prefix("range:") {
            range = v.trim().to_string();
        }
    }
    let path = request_line.split_whitespace().nth(1).unwrap_or_default().to_string();
    if path == format!("/{REPO}/resolve/main/{FILE}") {
        let _ = conn.write_all(
            format!(
                "HTTP/1.1 302 Found\r\nLocation: /blobs/model\r\nX-Repo-Commit: {COMMIT}\r\nContent-Length: 0\r\n\
                 Connection: close\r\n\r\n"
            )
            .as_bytes(),
        );
        return;
    }
    if path != "/blobs/model" {
        let _ = conn.write_all(b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n");
        return;
    }
    ranges.lock().unwrap().push(range.clone());
    let whole = |from: usize| {
        if from == 0 {
            format!("HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n", body.len())
        } else {
            format!(
                "HTTP/1.1 206 Partial Content\r\nContent-Range: bytes {from}-{}/{}\r\nContent-Length: {}\r\n\
                 Connection: close\r\n\r\n",
                body.len() - 1,
                body.len(),
                body.len() - from
            )
        }
    };
    let half = body.len() / 2;
    let _ = match mode {
        Serve::Whole => {
            let from = range.strip_prefix("bytes=").and_then(|r| r.strip_suffix('-')).map_or(0, |n| n.parse().unwrap());
            conn.write_all(whole(from).as_bytes()).and_then(|()| conn.write_all(&body[from..]))
        }
        Serve::Silent => {
            held.lock().unwrap().push(conn);
            return;
        }
        Serve::Stall | Serve::Cut => {
            let r = conn.write_all(whole(0).as_bytes()).and_then(|()| conn.write_all(&body[..half]));
            if mode == Serve::Stall {
                let _ = conn.flush();
                held.lock().unwrap().push(conn);
                return;
            }
            r
        }
        Serve::Endless | Serve::HugeLength => {
            let head = if mode == Serve::Endless {
                "HTTP/1.1 200 OK\r\nConnection: close\r\n\r\n".to_string()
            } else {
                "HTTP/1.1 200 OK\r\nContent-Length: 100000000000\r\nConnection: close\r\n\r\n".to_string()
            };
            // until the client goes away
            conn.write_all(head.as_bytes()).and_then(|()| loop {
                conn.write_all(&body)?;
            })
        }
    };
    let _ = conn.flush();
}

impl Drop for Mirror {
    fn drop(&mut self) {
        for c in self.held.lock().unwrap().drain(..) {
            let _ = c.shutdown(std::net::Shutdown::Both);
        }
    }
}

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("hub-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn hub(dir: &Path, endpoint: &str, timeout: Duration) -> Hub {
    Hub { endpoint: endpoint.into(), cache: dir.join("hub"), offline: false, timeout }
}

fn repo_cache(dir: &Path) -> PathBuf {
    dir.join("hub/models--test-org--blob-hub")
}

/// Every file under `dir` with its size (relative paths; links as `-> TARGET`).
fn files_under(dir: &Path) -> Vec<(String, u64)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(rd) = std::fs::read_dir(&d) else { continue };
        for e in rd.flatten() {
            let p = e.path();
            let t = e.file_type().unwrap();
            let name = p.strip_prefix(dir).unwrap().display().to_string();
            if t.is_dir() {
                stack.push(p);
            } else if t.is_symlink() {
                out.push((format!("{name} -> {}", std::fs::read_link(&p).unwrap().display()), 0));
            } else {
                out.push((name, e.metadata().unwrap().len()));
            }
        }
    }
    out.sort();
    out
}

/// `hub.fetch(e)` on a thread of its own, the test waiting at most `guard` for it (so that a
/// download that hangs fails the test instead of hanging it).
fn fetch_guarded(hub: &Hub, e: &HubFile, guard: Duration) -> Result<PathBuf, HubError> {
    let (tx, rx) = mpsc::channel();
    let (hub, e) = (hub.clone(), e.clone());
    std::thread::spawn(move || {
        let _ = tx.send(hub.fetch(&e, false));
    });
    rx.recv_timeout(guard).expect("the fetch neither finished nor failed: it hangs")
}

/// A mirror that accepts the request and never answers, and one that stops sending halfway
/// with the connection open: each fetch fails with the timeout error (no answer within the
/// timeout), not a hang. What the stalled one received is kept, and the next fetch resumes it
/// from there with a `Range` request; the file in place has the pinned hash.
#[test]
fn a_black_holed_mirror_fails_within_the_timeout_and_a_stalled_download_resumes() {
    let dir = tmp("timeout");
    let e = entry(None);
    let timeout = Duration::from_secs(1);
    let silent = mirror(Serve::Silent);
    let err = fetch_guarded(&hub(&dir, &silent.endpoint, timeout), &e, Duration::from_secs(60)).unwrap_err();
    assert!(matches!(err, HubError::TimedOut { .. }), "{err}");
    assert!(err.to_string().contains("HF_HUB_DOWNLOAD_TIMEOUT"), "{err}");
    assert!(files_under(&repo_cache(&dir)).is_empty(), "nothing received, nothing kept");

    let stall = mirror(Serve::Stall);
    let err = fetch_guarded(&hub(&dir, &stall.endpoint, timeout), &e, Duration::from_secs(60)).unwrap_err();
    assert!(matches!(err, HubError::TimedOut { .. }), "{err}");
    let half = model().len() as u64 / 2;
    assert_eq!(files_under(&repo_cache(&dir)), [(format!("blobs/{}.incomplete", e.sha256), half)]);

    let whole = mirror(Serve::Whole);
    let path = fetch_guarded(&hub(&dir, &whole.endpoint, timeout), &e, Duration::from_secs(60)).unwrap();
    assert_eq!(*whole.ranges.lock().unwrap(), [format!("bytes={half}-")], "resumed where it stopped");
    assert_eq!(sha256(&std::fs::read(&path).unwrap()), e.sha256);
    assert_eq!(path, repo_cache(&dir).join(format!("snapshots/{COMMIT}/{FILE}")));
}

/// A download cut halfway keeps its half; the next one asks for the rest only.
#[test]
fn an_interrupted_download_resumes_with_a_range_request() {
    let dir = tmp("resume");
    let e = entry(Some(model().len() as u64));
    let cut = mirror(Serve::Cut);
    let err = hub(&dir, &cut.endpoint, Duration::from_secs(10)).fetch(&e, false).unwrap_err();
    assert!(matches!(err, HubError::Interrupted { .. }), "{err}");
    assert!(err.to_string().contains("resume"), "{err}");
    let half = model().len() as u64 / 2;
    assert_eq!(files_under(&repo_cache(&dir)), [(format!("blobs/{}.incomplete", e.sha256), half)]);
    let whole = mirror(Serve::Whole);
    let path = hub(&dir, &whole.endpoint, Duration::from_secs(10)).fetch(&e, false).unwrap();
    assert_eq!(*whole.ranges.lock().unwrap(), [format!("bytes={half}-")]);
    assert_eq!(std::fs::read(&path).unwrap(), model());
    let listed: Vec<String> = files_under(&repo_cache(&dir)).into_iter().map(|(n, _)| n).collect();
    assert_eq!(
        listed,
        [
            format!("blobs/{}", e.sha256),
            "refs/main".to_string(),
            format!("snapshots/{COMMIT}/{FILE} -> ../../../blobs/{}", e.sha256)
        ]
    );
}

/// A body without end, or one declaring 100 GB, stops at the pinned size (or, with no size
/// pinned, is refused from its `Content-Length` before a byte is read); nothing is kept and no
/// file in the cache ever grows past the bound.
#[test]
fn an_endless_or_oversized_body_stops_at_the_pinned_size() {
    let size = model().len() as u64;
    for (mode, pinned) in [(Serve::Endless, Some(size)), (Serve::HugeLength, Some(size)), (Serve::HugeLength, None)] {
        let dir = tmp(&format!("large-{mode:?}-{}", pinned.is_some()));
        let m = mirror(mode);
        let err =
            fetch_guarded(&hub(&dir, &m.endpoint, Duration::from_secs(10)), &entry(pinned), Duration::from_secs(60))
                .unwrap_err();
        let HubError::TooLarge { limit, .. } = err else { panic!("{mode:?}: {err}") };
        assert_eq!(limit, pinned.unwrap_or(mpiflow::scene::hub::MAX_MODEL_BYTES), "{mode:?}");
        assert!(err.to_string().contains("nothing was kept"), "{err}");
        assert!(files_under(&repo_cache(&dir)).is_empty(), "{mode:?}: {:?}", files_under(&repo_cache(&dir)));
    }
}

/// Eight fetches of one file at once: each returns the one verified file, and the mirror sends
/// the blob once (the others wait for the download's lock and then find the file in place).
#[test]
fn concurrent_fetches_give_one_verified_file() {
    let dir = tmp("concurrent");
    let e = entry(Some(model().len() as u64));
    let m = mirror(Serve::Whole);
    let h = hub(&dir, &m.endpoint, Duration::from_secs(10));
    let start = Arc::new(Barrier::new(8));
    let done = Arc::new(AtomicUsize::new(0));
    let threads: Vec<_> = (0..8)
        .map(|_| {
            let (h, e, start, done) = (h.clone(), e.clone(), start.clone(), done.clone());
            std::thread::spawn(move || {
                start.wait();
                let r = h.fetch(&e, false);
                done.fetch_add(1, Ordering::SeqCst);
                r
            })
        })
        .collect();
    let paths: Vec<PathBuf> = threads.into_iter().map(|t| t.join().unwrap().expect("every fetch succeeds")).collect();
    assert!(paths.iter().all(|p| *p == paths[0]), "{paths:?}");
    assert_eq!(std::fs::read(&paths[0]).unwrap(), model());
    assert_eq!(m.ranges.lock().unwrap().len(), 1, "one download");
    let listed: Vec<String> = files_under(&repo_cache(&dir)).into_iter().map(|(n, _)| n).collect();
    assert!(listed.iter().all(|n| !n.contains(".incomplete")), "{listed:?}");
}

/// Links planted in the cache are refused, never written through: the repository folder,
/// `blobs/`, the partial file, the blob itself and `refs/main` each a link to a place outside the
/// cache; the places outside stay as they were.
#[cfg(unix)]
#[test]
fn a_symlink_in_the_cache_is_refused_and_nothing_outside_changes() {
    let e = entry(Some(model().len() as u64));
    let m = mirror(Serve::Whole);
    let cases: [(&str, bool); 5] = [
        ("", true),
        ("blobs", true),
        (&format!("blobs/{}.incomplete", e.sha256), false),
        (&format!("blobs/{}", e.sha256), false),
        ("refs/main", false),
    ];
    for (i, (planted, is_dir)) in cases.iter().enumerate() {
        let dir = tmp(&format!("link-{i}"));
        let outside = dir.join("outside");
        std::fs::create_dir_all(&outside).unwrap();
        let victim = outside.join("victim");
        std::fs::write(&victim, b"precious").unwrap();
        let at = if planted.is_empty() { repo_cache(&dir) } else { repo_cache(&dir).join(planted) };
        std::fs::create_dir_all(at.parent().unwrap()).unwrap();
        let target = if *is_dir { outside.clone() } else { victim.clone() };
        std::os::unix::fs::symlink(&target, &at).unwrap();
        let err = hub(&dir, &m.endpoint, Duration::from_secs(10)).fetch(&e, false).unwrap_err();
        let HubError::Link { path } = &err else { panic!("{planted}: {err}") };
        assert_eq!(*path, at, "{planted}");
        assert_eq!(files_under(&outside), [("victim".to_string(), 8)], "{planted}: the outside is untouched");
        assert_eq!(std::fs::read(&victim).unwrap(), b"precious", "{planted}");
    }
}

/// `..` (or an absolute part) in a registry path is refused before anything is fetched or
/// written: no request, no folder made.
#[test]
fn dot_dot_in_a_registry_path_is_refused() {
    let m = mirror(Serve::Whole);
    let bad = [
        HubFile { file: "../../outside.onnx".into(), ..entry(None) },
        HubFile { file: "/etc/passwd".into(), ..entry(None) },
        HubFile { revision: "../../../x".into(), ..entry(None) },
        HubFile { repo: "../escape".into(), ..entry(None) },
    ];
    for (i, e) in bad.iter().enumerate() {
        let dir = tmp(&format!("dotdot-{i}"));
        let err = hub(&dir, &m.endpoint, Duration::from_secs(10)).fetch(e, false).unwrap_err();
        assert!(matches!(err, HubError::BadEntry { .. }), "{err}");
        assert!(!dir.join("hub").exists(), "nothing made for {e:?}");
    }
    assert!(m.ranges.lock().unwrap().is_empty(), "nothing requested");
}
