//! Serving never stalls on a cache miss: the workers make samples of ready scenes only, a
//! scene that is not ready is built off the workers (the stream's prefetch window asks for the
//! scenes of its next indices), and the samples are the same bytes with or without it.
//!
//! The first test drives the real worker pool with a scene gate the test opens itself (events,
//! not sleeps); the second runs real gRPC servers on loopback over photos with a real ONNX depth
//! and segmentation model (needs `MPIFLOW_PYTHON` and `ORT_DYLIB_PATH`: `bash tools/test.sh`).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use mpiflow::scene::models::ModelConfig;
use mpiflow::service::client::client_for;
use mpiflow::service::config::DatasetConfig;
use mpiflow::service::metrics::Metrics;
use mpiflow::service::pb;
use mpiflow::service::pool::{Make, Prepare, Produce, Scheduler, StreamSpec};
use mpiflow::service::{start, ServiceConfig};
use tokio_stream::StreamExt;
use tonic::transport::Endpoint;

/// A scene build's completion callback, held back by the test.
type Done = Box<dyn FnOnce() + Send>;

fn spec(count: u64) -> StreamSpec {
    StreamSpec { start_index: 0, rank: 0, world_size: 1, count, batch_size: 1, prefetch: 4, max_message_bytes: 1 << 20 }
}

fn sample(index: u64) -> pb::Sample {
    pb::Sample { index, ..Default::default() }
}

/// A stream whose scenes are held back (their builds "run" until the test opens the gate) and a
/// stream whose scenes are ready, on ONE worker with ONE in-flight slot: the ready stream gets
/// every sample while the other's scenes are still being built, and no worker ever starts a
/// sample of a scene that is not ready.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_ready_scene_never_waits_for_one_being_built() {
    let sched = Scheduler::new(1, 1, 1 << 30, Arc::new(Metrics::new())).unwrap();
    let open = Arc::new(AtomicBool::new(false));
    let waiting: Arc<Mutex<Vec<Done>>> = Arc::default();
    let early = Arc::new(AtomicU64::new(0));
    let (o, e) = (open.clone(), early.clone());
    let slow_make: Make = Arc::new(move |i| {
        if !o.load(Ordering::SeqCst) {
            e.fetch_add(1, Ordering::SeqCst);
        }
        Ok(sample(i))
    });
    let (o, w) = (open.clone(), waiting.clone());
    let slow_prepare: Prepare = Arc::new(move |_i, done| {
        if o.load(Ordering::SeqCst) {
            return true;
        }
        w.lock().unwrap().push(done);
        false
    });
    let mut slow = sched
        .open(spec(6), Produce { make: slow_make, prepare: Some(slow_prepare), bound: 0, work: 0, workspace: 0 })
        .unwrap();
    let ready_prepare: Prepare = Arc::new(|_, _| true);
    let ready_make: Make = Arc::new(|i| Ok(sample(i)));
    let mut fast = sched
        .open(spec(20), Produce { make: ready_make, prepare: Some(ready_prepare), bound: 0, work: 0, workspace: 0 })
        .unwrap();

    let deadline = Duration::from_secs(60);
    let mut got = Vec::new();
    tokio::time::timeout(deadline, async {
        while let Some(b) = fast.next().await {
            got.extend(b.unwrap().samples.into_iter().map(|s| s.index));
        }
    })
    .await
    .expect("the ready stream was held up by the scenes of the other");
    assert_eq!(got, (0..20).collect::<Vec<_>>());
    // the held stream asked for the scenes of its whole prefetch window, and no worker ran it
    assert!(!waiting.lock().unwrap().is_empty());
    assert_eq!(early.load(Ordering::SeqCst), 0, "a worker made a sample of a scene not ready");

    // the builds finish: the held stream completes, in order
    open.store(true, Ordering::SeqCst);
    let dones: Vec<_> = std::mem::take(&mut *waiting.lock().unwrap());
    for d in dones {
        std::thread::spawn(d);
    }
    let mut got = Vec::new();
    tokio::time::timeout(deadline, async {
        while let Some(b) = slow.next().await {
            got.extend(b.unwrap().samples.into_iter().map(|s| s.index));
        }
    })
    .await
    .expect("the held stream never finished");
    assert_eq!(got, (0..6).collect::<Vec<_>>());
    assert_eq!(early.load(Ordering::SeqCst), 0);
}

const HOW: &str = "run the tests with `bash tools/test.sh` (or `eval \"$(bash tools/setup_python.sh)\"` first)";

fn models() -> PathBuf {
    let python = std::env::var_os("MPIFLOW_PYTHON")
        .filter(|v| !v.is_empty())
        .unwrap_or_else(|| panic!("MPIFLOW_PYTHON is not set: {HOW}"));
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("prefetch_models_{}", std::process::id()));
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/make_test_models.py");
    let out = Command::new(&python).arg(&script).arg(&dir).output().expect("runs the model script");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    dir
}

fn metric(text: &str, name: &str) -> Option<f64> {
    text.lines().find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
}

async fn http_get(addr: &str, path: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut sock = tokio::net::TcpStream::connect(addr).await.unwrap();
    sock.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes()).await.unwrap();
    let mut out = String::new();
    sock.read_to_string(&mut out).await.unwrap();
    out
}

/// Over photos with real models and a cache smaller than the dataset, two streams with scene
/// prefetching give the same bytes as without it, and `/metrics` has the scene histogram and
/// the cache counters.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn prefetched_scenes_give_the_same_samples_and_are_measured() {
    let m = models();
    let photos = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/photos");
    let config = |prefetch_scenes: bool| ServiceConfig {
        addr: "127.0.0.1:0".into(),
        metrics_addr: Some("127.0.0.1:0".into()),
        size: Some("64x48".into()),
        workers: 2,
        log_level: "warn".into(),
        // two 64x48 scenes of 32 planes (1.6 MB each): fewer than the four photos
        cache_mb: 4,
        prefetch_scenes,
        models: ModelConfig {
            depth_model: Some(m.join("depth.onnx")),
            segment_model: Some(m.join("seg.onnx")),
            ..ModelConfig::default()
        },
        datasets: vec![DatasetConfig { name: Some("photos".into()), path: photos.display().to_string(), sample: None }],
        ..ServiceConfig::default()
    };
    let mut pulled = Vec::new();
    for prefetch in [true, false] {
        let s = start(config(prefetch)).await.expect("server starts");
        let ch = Endpoint::from_shared(format!("http://{}", s.addr)).unwrap().connect().await.unwrap();
        let mut c = client_for(ch);
        let mut samples = Vec::new();
        for rank in 0..2 {
            let r = pb::StreamRequest {
                count: 8,
                rank,
                world_size: 2,
                prefetch: 4,
                ..pb::SampleSpec { seed: 9, ..Default::default() }.stream()
            };
            let mut st = c.stream_samples(r).await.unwrap().into_inner();
            while let Some(b) = st.message().await.unwrap() {
                samples.extend(b.samples.into_iter().map(|mut x| {
                    x.timings = None;
                    x
                }));
            }
        }
        samples.sort_by_key(|x| x.index);
        assert_eq!(samples.len(), 16);
        let text = http_get(&s.metrics_addr.unwrap().to_string(), "/metrics").await;
        let builds = metric(&text, "mpiflow_scene_seconds_count").unwrap_or_else(|| panic!("{text}"));
        assert!(builds >= 4.0, "{text}");
        assert!(metric(&text, "mpiflow_scene_cache_misses_total").unwrap() >= 4.0, "{text}");
        assert!(metric(&text, "mpiflow_scene_cache_evictions_total").unwrap() >= 1.0, "{text}");
        pulled.push(samples);
        s.shutdown(Duration::from_secs(5)).await;
    }
    assert!(pulled[0] == pulled[1], "prefetching scenes changed the samples");
}
