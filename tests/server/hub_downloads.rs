//! Model downloads against a loopback HTTP mirror in the hub's URL layout (`scene::hub`), with
//! real files in a real cache folder: a silent or stalled mirror fails within the timeout, a
//! trickling one at its deadline or its least rate (`models fetch` and `serve` too, through the
//! real binary), each keeping nothing; a partial file a killed download left is resumed with a
//! `Range` request; a second fetch waiting for the lock fails at its deadline naming the holder;
//! a full disk stops the download with its partial file removed; an endless body or a huge
//! `Content-Length` stops at the pinned size; concurrent fetches of one file give one verified
//! file; a symbolic link planted in the cache is refused with nothing outside the cache changed;
//! registry paths with `..` are refused before anything is fetched or written. No ONNX Runtime
//! needed: the hub verifies bytes, whatever they are.

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
    /// Headers declaring the whole length, then one byte every 200 ms until the client goes away
    /// (or the file is sent).
    Trickle,
}

/// A loopback HTTP/1.1 mirror: `/{REPO}/resolve/main/{FILE}` answers 302 to `/blobs/model` with
/// `X-Repo-Commit`; the blob answers as `mode` says. Records the `Range` header of each blob
/// request (empty for none), and says on `asked` when a blob request has come.
struct Mirror {
    endpoint: String,
    ranges: Arc<Mutex<Vec<String>>>,
    /// Connections held open (Silent, Stall), closed when the mirror is dropped.
    held: Arc<Mutex<Vec<TcpStream>>>,
    asked: mpsc::Receiver<()>,
}

fn mirror(mode: Serve) -> Mirror {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let endpoint = format!("http://{}", listener.local_addr().unwrap());
    let ranges = Arc::new(Mutex::new(Vec::new()));
    let held = Arc::new(Mutex::new(Vec::new()));
    let (r, h) = (ranges.clone(), held.clone());
    let (tx, asked) = mpsc::channel();
    std::thread::spawn(move || {
        for conn in listener.incoming() {
            let Ok(conn) = conn else { continue };
            let (r, h, tx) = (r.clone(), h.clone(), tx.clone());
            std::thread::spawn(move || answer(conn, mode, &r, &h, &tx));
        }
    });
    Mirror { endpoint, ranges, held, asked }
}

fn answer(
    mut conn: TcpStream,
    mode: Serve,
    ranges: &Mutex<Vec<String>>,
    held: &Mutex<Vec<TcpStream>>,
    asked: &mpsc::Sender<()>,
) {
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
    let _ = asked.send(());
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
        Serve::Trickle => conn.write_all(whole(0).as_bytes()).and_then(|()| {
            // the mirror's own pace (not the test's synchronisation): a byte, then a pause
            for b in &body {
                conn.write_all(std::slice::from_ref(b))?;
                conn.flush()?;
                std::thread::sleep(Duration::from_millis(200));
            }
            Ok(())
        }),
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
    Hub {
        endpoint: endpoint.into(),
        cache: dir.join("hub"),
        offline: false,
        timeout,
        deadline: Duration::from_secs(3600),
        min_rate: 0,
    }
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
/// timeout), not a hang, and keeps nothing.
#[test]
fn a_black_holed_or_stalled_mirror_fails_within_the_timeout_and_keeps_nothing() {
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
    assert!(err.to_string().contains("nothing was kept"), "{err}");
    assert!(files_under(&repo_cache(&dir)).is_empty(), "{:?}", files_under(&repo_cache(&dir)));
}

/// A download cut halfway keeps nothing; a partial file left behind by a download that was
/// killed (no error path ran) is resumed: the next fetch asks for the rest only.
#[test]
fn a_cut_download_keeps_nothing_and_a_killed_one_resumes_with_a_range_request() {
    let dir = tmp("resume");
    let e = entry(Some(model().len() as u64));
    let cut = mirror(Serve::Cut);
    let err = hub(&dir, &cut.endpoint, Duration::from_secs(10)).fetch(&e, false).unwrap_err();
    assert!(matches!(err, HubError::Interrupted { .. }), "{err}");
    assert!(err.to_string().contains("nothing was kept"), "{err}");
    assert!(files_under(&repo_cache(&dir)).is_empty(), "{:?}", files_under(&repo_cache(&dir)));
    // what a killed download leaves: the first half in the partial file
    let half = model().len() as u64 / 2;
    let blobs = repo_cache(&dir).join("blobs");
    std::fs::create_dir_all(&blobs).unwrap();
    std::fs::write(blobs.join(format!("{}.incomplete", e.sha256)), &model()[..half as usize]).unwrap();
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

/// A mirror that sends one byte every 200 ms: with a deadline of 2 s (and no least rate) the
/// fetch fails with the deadline error, and with a least rate of 1 KiB/s over spans of 1 s it
/// fails with the rate error; neither keeps a byte.
#[test]
fn a_trickling_mirror_fails_at_the_deadline_or_the_least_rate_and_keeps_nothing() {
    let e = entry(Some(model().len() as u64));
    let dir = tmp("trickle-deadline");
    let m = mirror(Serve::Trickle);
    let h = Hub { deadline: Duration::from_secs(2), ..hub(&dir, &m.endpoint, Duration::from_secs(10)) };
    let err = fetch_guarded(&h, &e, Duration::from_secs(120)).unwrap_err();
    assert!(matches!(err, HubError::DeadlineExceeded { .. }), "{err}");
    let said = err.to_string();
    assert!(said.contains("deadline of 2 s") && said.contains("MPIFLOW_DOWNLOAD_DEADLINE_S"), "{said}");
    assert!(said.contains("nothing was kept"), "{said}");
    assert!(files_under(&repo_cache(&dir)).is_empty(), "{:?}", files_under(&repo_cache(&dir)));

    let dir = tmp("trickle-rate");
    let h = Hub { min_rate: 1024, ..hub(&dir, &m.endpoint, Duration::from_secs(1)) };
    let err = fetch_guarded(&h, &e, Duration::from_secs(120)).unwrap_err();
    let HubError::TooSlow { got, min_rate, .. } = &err else { panic!("{err}") };
    assert!(*got < 1024 && *min_rate == 1024, "{err}");
    assert!(err.to_string().contains("MPIFLOW_DOWNLOAD_MIN_RATE"), "{err}");
    assert!(files_under(&repo_cache(&dir)).is_empty(), "{:?}", files_under(&repo_cache(&dir)));
}

/// While one fetch holds the file's lock (its mirror silent), a second fetch of the same file
/// waits until its deadline and fails naming the holder (this process); the first ends when its
/// mirror goes away.
#[test]
fn a_fetch_waiting_for_the_lock_fails_at_its_deadline_naming_the_holder() {
    let dir = tmp("lock");
    let e = entry(Some(model().len() as u64));
    let m = mirror(Serve::Silent);
    let first_hub = hub(&dir, &m.endpoint, Duration::from_secs(60));
    let first = {
        let e = e.clone();
        std::thread::spawn(move || first_hub.fetch(&e, false))
    };
    // the first fetch has the lock once it has asked the mirror for the blob
    m.asked.recv_timeout(Duration::from_secs(60)).expect("the first fetch asks for the blob");
    let second = Hub { deadline: Duration::from_secs(1), ..hub(&dir, &m.endpoint, Duration::from_secs(60)) };
    let err = fetch_guarded(&second, &e, Duration::from_secs(60)).unwrap_err();
    let HubError::Locked { holder, path, .. } = &err else { panic!("{err}") };
    assert!(holder.starts_with(&format!("process {} since", std::process::id())), "{err}");
    assert_eq!(*path, dir.join(format!("hub/.locks/models--test-org--blob-hub/{}.lock", e.sha256)));
    assert!(err.to_string().contains("MPIFLOW_DOWNLOAD_DEADLINE_S"), "{err}");
    drop(m);
    assert!(first.join().unwrap().is_err(), "the first fetch ends when its mirror closes");
    assert!(files_under(&repo_cache(&dir)).is_empty(), "{:?}", files_under(&repo_cache(&dir)));
}

/// A cache on a 128 KiB filesystem (a tmpfs mounted here; the test says so and stops where it
/// cannot mount one, as a user without the right to) and a file of 300 KiB: the download stops
/// at the write error (no space left) and removes its partial file, so the disk is not left full.
#[cfg(target_os = "linux")]
#[test]
fn a_full_disk_stops_the_download_and_removes_the_partial_file() {
    use std::process::Command;
    let dir = tmp("enospc");
    let small = dir.join("small");
    std::fs::create_dir_all(&small).unwrap();
    let mounted = Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=128k", "tmpfs"])
        .arg(&small)
        .output()
        .is_ok_and(|o| o.status.success());
    if !mounted {
        eprintln!("a_full_disk_stops_the_download_and_removes_the_partial_file: no tmpfs can be mounted here");
        return;
    }
    struct Unmount(PathBuf);
    impl Drop for Unmount {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount").arg(&self.0).status();
        }
    }
    let _unmount = Unmount(small.clone());
    let m = mirror(Serve::Whole);
    let e = entry(Some(model().len() as u64));
    let err =
        fetch_guarded(&hub(&small, &m.endpoint, Duration::from_secs(10)), &e, Duration::from_secs(60)).unwrap_err();
    let HubError::Io { path, message } = &err else { panic!("{err}") };
    assert_eq!(*path, repo_cache(&small).join(format!("blobs/{}.incomplete", e.sha256)), "{err}");
    assert!(message.contains("No space left"), "{err}");
    assert!(files_under(&repo_cache(&small)).is_empty(), "{:?}", files_under(&repo_cache(&small)));
}

/// A registry naming `depth-anything-v2-small` at the mirror's repository (the pinned hash is
/// the test model's; the contract is never used, the file never arrives).
fn test_registry(dir: &Path) -> PathBuf {
    let e = entry(Some(model().len() as u64));
    let text = format!(
        "[[model]]\nname = \"depth-anything-v2-small\"\nrole = \"depth\"\nrepo = \"{REPO}\"\nrevision = \"main\"\n\
         file = \"{FILE}\"\nsha256 = \"{}\"\nsize = {}\nlicence = \"test\"\n",
        e.sha256,
        model().len()
    );
    let path = dir.join("registry.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// `mpiflow ARGS` with the hub environment (cache under `dir/hf`, the test registry, the mirror)
/// and a download deadline of 2 s without a least rate; its output, the child killed (and the
/// test failed) if it has not ended after `guard`.
fn mpiflow_with_deadline(dir: &Path, endpoint: &str, args: &[&str], guard: Duration) -> std::process::Output {
    use std::process::{Command, Stdio};
    let child = Command::new(env!("CARGO_BIN_EXE_mpiflow"))
        .args(args)
        .env("HF_HOME", dir.join("hf"))
        .env_remove("HF_HUB_CACHE")
        .env_remove("HF_HUB_OFFLINE")
        .env("HF_ENDPOINT", endpoint)
        .env("MPIFLOW_MODEL_REGISTRY", test_registry(dir))
        .env("MPIFLOW_DOWNLOAD_DEADLINE_S", "2")
        .env("MPIFLOW_DOWNLOAD_MIN_RATE", "0")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(child.wait_with_output());
    });
    match rx.recv_timeout(guard) {
        Ok(out) => out.unwrap(),
        Err(_) => {
            let _ = std::process::Command::new("kill").arg("-9").arg(pid.to_string()).status();
            panic!("mpiflow {args:?} neither finished nor failed: it hangs");
        }
    }
}

/// `mpiflow models fetch` from a trickling mirror fails at its deadline with the reason and
/// keeps no partial file; `mpiflow serve` with the model as its depth model logs what it is
/// downloading and exits (status 2) with the same reason, never serving.
#[test]
fn models_fetch_and_serve_fail_at_the_deadline_of_a_trickling_mirror() {
    let m = mirror(Serve::Trickle);
    let dir = tmp("cli-fetch");
    let out = mpiflow_with_deadline(
        &dir,
        &m.endpoint,
        &["models", "fetch", "depth-anything-v2-small"],
        Duration::from_secs(120),
    );
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("did not finish within its deadline of 2 s") && err.contains("nothing was kept"), "{err}");
    assert!(files_under(&dir.join("hf/hub/models--test-org--blob-hub")).is_empty());

    let dir = tmp("cli-serve");
    let photos = dir.join("photos");
    std::fs::create_dir_all(&photos).unwrap();
    image::RgbImage::from_fn(64, 48, |x, y| image::Rgb([(x * 3) as u8, (y * 5) as u8, 90]))
        .save(photos.join("p.png"))
        .unwrap();
    let src = photos.display().to_string();
    let args = ["serve", "--addr", "127.0.0.1:0", "--source", &src, "--depth-model", "depth-anything-v2-small"];
    let out = mpiflow_with_deadline(&dir, &m.endpoint, &args, Duration::from_secs(120));
    let (stdout, err) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert_eq!(out.status.code(), Some(2), "{stdout} {err}");
    assert!(!stdout.contains("serving on"), "{stdout}");
    assert!(err.contains("downloading a model") && err.contains("depth-anything-v2-small"), "{err}");
    assert!(err.contains("did not finish within its deadline of 2 s"), "{err}");
    assert!(files_under(&dir.join("hf/hub/models--test-org--blob-hub")).is_empty());
}
