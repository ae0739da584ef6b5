//! One pipeline, one fingerprint: `mpiflow generate` and `mpiflow serve` + `mpiflow pull` (the
//! real binaries) write byte-identical sample files for the same address, on the bundled default
//! scenes and on a `--source` folder, with the same fingerprint in `I.json`, in the stream and in
//! the start-up lines; options that change samples change the fingerprint; and the scenes of a
//! served dataset are built once under concurrent first requests
//! (`mpiflow_scene_builds_total`).

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};

use mpiflow::sample::config::SampleConfig;
use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;
use mpiflow::service::pb;
use mpiflow::service::{start, ServiceConfig};
use std::sync::Arc;

const SIZE: &str = "64x48";
/// The sample files both commands write (per index `I`; `mask.png` only when objects moved).
const FILES: [&str; 7] = ["img1.png", "img2.png", "flow.flo", "valid.png", "occ.png", "holes.png", "mask.png"];

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mpiflow"))
}

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("pipeline-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn ok(out: Output, what: &str) -> String {
    assert!(
        out.status.success(),
        "{what} failed ({}):\n{}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr))
}

/// A `mpiflow serve` child.
struct Server {
    child: Child,
    addr: String,
}

impl Server {
    fn start(args: &[&str]) -> Self {
        let mut child = bin()
            .args(["serve", "--addr", "127.0.0.1:0", "--size", SIZE, "--log-level", "warn", "--workers", "2"])
            .args(args)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("mpiflow serve starts");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        let addr = line.trim().strip_prefix("mpiflow serving on ").unwrap_or_else(|| panic!("printed {line:?}"));
        Server { addr: addr.to_string(), child }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The `dataset_hex` of `dir/I.json`.
fn fingerprint_in_json(dir: &Path, index: u64) -> String {
    let text = std::fs::read_to_string(dir.join(format!("{index:08}.json"))).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["address"]["dataset_hex"].as_str().unwrap_or_else(|| panic!("no dataset_hex in {text}")).to_string()
}

/// Generates `count` samples with `generate`, serves the same source and pulls them, and checks
/// every sample file byte for byte and the fingerprints.
/// Returns the fingerprint and how many object masks were compared.
fn generate_equals_pull(source: &[&str], extra_generate: &[&str], extra_pull: &[&str], count: u64) -> (String, usize) {
    let name = if source.is_empty() { "builtin".to_string() } else { format!("src{}", extra_generate.len()) };
    let (a, b) = (tmp(&format!("{name}-generate")), tmp(&format!("{name}-pull")));
    let n = count.to_string();
    let gen = ok(
        bin()
            .args(["generate", "--count", &n, "--size", SIZE, "--quiet", "--preview-every", "0", "--out"])
            .arg(&a)
            .args(source)
            .args(extra_generate)
            .output()
            .unwrap(),
        "generate",
    );
    let server = Server::start(source);
    ok(
        bin()
            .args(["pull", "--addr", &server.addr, "--count", &n, "--preview-every", "0", "--out"])
            .arg(&b)
            .args(extra_pull)
            .output()
            .unwrap(),
        "pull",
    );
    let fp = fingerprint_in_json(&a, 0);
    let mut masks = 0;
    for i in 0..count {
        for f in FILES {
            let (pa, pb_) = (a.join(format!("{i:08}_{f}")), b.join(format!("{i:08}_{f}")));
            if f == "mask.png" && !pa.exists() {
                // written only when objects moved
                assert!(!pb_.exists(), "{} without {}", pb_.display(), pa.display());
                continue;
            }
            let (ba, bb) = (std::fs::read(&pa).unwrap(), std::fs::read(&pb_).unwrap());
            assert!(!ba.is_empty());
            assert!(ba == bb, "{} and {} differ", pa.display(), pb_.display());
            masks += usize::from(f == "mask.png");
        }
        assert_eq!(fingerprint_in_json(&a, i), fp);
        assert_eq!(fingerprint_in_json(&b, i), fp, "the stream's fingerprint is generate's");
    }
    assert!(gen.contains(&format!("dataset fingerprint {fp}")), "generate prints the fingerprint: {gen}");
    (fp, masks)
}

#[test]
fn generate_and_pull_write_the_same_bytes_for_the_bundled_scenes() {
    let (fp, masks) = generate_equals_pull(&[], &[], &[], 3);
    assert!(masks > 0, "the bundled scenes move objects");
    // an option that changes samples changes the fingerprint (and a pull with it matches again)
    let (fp2, masks) = generate_equals_pull(&[], &["--objects", "0"], &["--objects", "0"], 2);
    assert_eq!(masks, 0);
    assert_ne!(fp, fp2, "--objects is part of the fingerprint");
}

/// A textured photo and a depth ramp in the reference layout (`images/`, `depths/NAME.npy`).
fn reference_layout(dir: &Path) {
    std::fs::create_dir_all(dir.join("images")).unwrap();
    std::fs::create_dir_all(dir.join("depths")).unwrap();
    for (k, name) in ["a", "b"].iter().enumerate() {
        let img = image::RgbImage::from_fn(80, 60, |x, y| {
            image::Rgb([(x * 3 + k as u32 * 40) as u8, (y * 4) as u8, ((x * y) % 251) as u8])
        });
        img.save(dir.join(format!("images/{name}.png"))).unwrap();
        let depth: Vec<f32> = (0..60 * 80).map(|i| 1.0 + (i / 80) as f32 * 0.05 + (i % 80) as f32 * 0.01).collect();
        mpiflow::io::npy::write_f32(&dir.join(format!("depths/{name}.npy")), &[60, 80], &depth).unwrap();
    }
}

#[test]
fn generate_and_pull_write_the_same_bytes_for_a_source_folder() {
    let src = tmp("reference-layout");
    reference_layout(&src);
    let s = src.to_str().unwrap();
    let (fp, _) = generate_equals_pull(&["--source", s], &[], &[], 3);
    let (fp2, _) =
        generate_equals_pull(&["--source", s], &["--preset", "paper-kitti"], &["--preset", "paper-kitti"], 1);
    assert_ne!(fp, fp2, "--preset is part of the fingerprint");
}

#[test]
fn the_library_pipeline_has_the_fingerprint_of_the_served_dataset() {
    // what generate builds, built here through the same functions, against GetInfo
    let open = OpenOptions { resize: Some((64, 48)), ..OpenOptions::default() };
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let source = open_source(&SourceSpec::Builtin, &open).unwrap();
    let p = Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 30)), SampleConfig::default()).unwrap();
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    rt.block_on(async {
        let config = ServiceConfig { addr: "127.0.0.1:0".into(), size: Some(SIZE.into()), ..ServiceConfig::default() };
        let server = start(config).await.unwrap();
        let mut c = mpiflow::service::client::client_for(
            tonic::transport::Endpoint::from_shared(format!("http://{}", server.addr))
                .unwrap()
                .connect()
                .await
                .unwrap(),
        );
        let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
        assert_eq!(info.datasets[0].fingerprint, p.fingerprint());
    });
}

/// A GET of the metrics endpoint (HTTP/1.0, the whole body).
fn scrape(addr: &str) -> String {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.write_all(b"GET /metrics HTTP/1.0\r\nHost: x\r\n\r\n").unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    out
}

/// The value of `mpiflow_scene_builds_total{dataset="NAME"}` (0 when absent).
fn builds(metrics: &str, dataset: &str) -> u64 {
    let key = format!("mpiflow_scene_builds_total{{dataset=\"{dataset}\"}} ");
    metrics.lines().find_map(|l| l.strip_prefix(&key)).map_or(0, |v| v.trim().parse().unwrap())
}

#[test]
fn concurrent_first_requests_for_one_scene_build_it_once() {
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    rt.block_on(async {
        let config = ServiceConfig {
            addr: "127.0.0.1:0".into(),
            metrics_addr: Some("127.0.0.1:0".into()),
            size: Some(SIZE.into()),
            workers: 2,
            // more in flight than workers: every request is a job on the worker pool at once
            max_in_flight: 8,
            log_level: "warn".into(),
            ..ServiceConfig::default()
        };
        let server = start(config).await.unwrap();
        let metrics_addr = server.metrics_addr.unwrap().to_string();
        let endpoint = tonic::transport::Endpoint::from_shared(format!("http://{}", server.addr)).unwrap();
        let channel = endpoint.connect().await.unwrap();
        // health SERVING means the warm-up sample (index 0's scene) is made
        let mut health = tonic_health::pb::health_client::HealthClient::new(channel.clone());
        loop {
            let s = health
                .check(tonic_health::pb::HealthCheckRequest { service: String::new() })
                .await
                .unwrap()
                .into_inner()
                .status;
            if s == tonic_health::pb::health_check_response::ServingStatus::Serving as i32 {
                break;
            }
            tokio::task::yield_now().await;
        }
        let m = tokio::task::spawn_blocking({
            let a = metrics_addr.clone();
            move || scrape(&a)
        })
        .await
        .unwrap();
        let before = builds(&m, "builtin");
        assert!(before >= 1, "the warm-up built a scene: {m}");
        // index 5 uses bundled scene 5, not built yet; 8 concurrent GetSample calls
        let calls: Vec<_> = (0..8)
            .map(|_| {
                let mut c = mpiflow::service::client::client_for(channel.clone());
                tokio::spawn(async move {
                    c.get_sample(pb::SampleRequest { index: 5, ..Default::default() })
                        .await
                        .map(tonic::Response::into_inner)
                })
            })
            .collect();
        let mut samples = Vec::new();
        for c in calls {
            samples.push(c.await.unwrap().expect("GetSample"));
        }
        for s in &samples {
            assert_eq!(s.tensors, samples[0].tensors, "the same address gives the same sample");
        }
        let m = tokio::task::spawn_blocking(move || scrape(&metrics_addr)).await.unwrap();
        assert_eq!(builds(&m, "builtin"), before + 1, "one build for 8 concurrent first requests:\n{m}");
    });
}
