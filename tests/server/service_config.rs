//! Configuration values that make no sense are refused at start-up naming their key: through the
//! real loading path (a TOML file read by `ServiceConfig::from_file`, then checked) and through
//! `mpiflow serve --config FILE` (exit status 2, one line, never listening). The bounds
//! themselves are accepted, and a frame of the smallest working size serves samples.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use mpiflow::service::config::{MIN_FRAME_SIDE, MIN_TIMEOUT_SECONDS};
use mpiflow::service::pb;
use mpiflow::service::{start, ServiceConfig};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

fn tmp(name: &str) -> PathBuf {
    let d = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("config-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A configuration file of `body` under the listening address of a test.
fn file(dir: &Path, i: usize, body: &str) -> PathBuf {
    let p = dir.join(format!("{i}.toml"));
    std::fs::write(&p, format!("addr = \"127.0.0.1:0\"\nworkers = 1\nlog_level = \"warn\"\n{body}")).unwrap();
    p
}

/// (the file's lines, what the error starts with after `configuration: `)
const REFUSED: [(&str, &str); 8] = [
    ("idle_connection_timeout_s = 1e-12", "idle_connection_timeout_s = 1e-12 (expected seconds, at least 0.5"),
    ("stall_timeout_s = 0.25", "stall_timeout_s = 0.25 (expected seconds, at least 0.5"),
    ("size = \"16x16\"", "size = 16x16 is smaller than the smallest working frame (32 pixels a side)"),
    ("size = \"640x16\"", "size = 640x16 is smaller than the smallest working frame"),
    ("size = \"64x48\"\n[sample]\ninpaint_radius = 1e30", "[sample] inpaint_radius = 1e30 is beyond the frame"),
    ("size = \"64x48\"\n[sample]\ninpaint_radius = 64.5", "[sample] inpaint_radius = 64.5 is beyond the frame"),
    ("max_image_side = 100\n[sample]\ninpaint_radius = 101.0", "[sample] inpaint_radius = 101.0 is beyond the frame"),
    (
        "size = \"64x48\"\n[[datasets]]\npath = \"builtin\"\n[datasets.sample]\ninpaint_radius = 1e30",
        "dataset builtin: inpaint_radius = 1e30 is beyond the frame",
    ),
];

#[test]
fn values_that_make_no_sense_are_refused_naming_the_key() {
    let dir = tmp("refused");
    for (i, (body, says)) in REFUSED.iter().enumerate() {
        let e = ServiceConfig::from_file(&file(&dir, i, body)).unwrap().validate().unwrap_err().to_string();
        assert!(e.starts_with(&format!("configuration: {says}")), "{body}: {e}");
    }
    // the bounds themselves are accepted
    let edges = [
        format!("idle_connection_timeout_s = {MIN_TIMEOUT_SECONDS:?}\nstall_timeout_s = {MIN_TIMEOUT_SECONDS:?}"),
        format!("size = \"{MIN_FRAME_SIDE}x{MIN_FRAME_SIDE}\"\n[sample]\ninpaint_radius = {MIN_FRAME_SIDE}.0"),
        "max_image_side = 100\n[sample]\ninpaint_radius = 100.0".to_string(),
    ];
    for (i, body) in edges.iter().enumerate() {
        ServiceConfig::from_file(&file(&dir, 100 + i, body))
            .unwrap()
            .validate()
            .unwrap_or_else(|e| panic!("{body}: {e}"));
    }
}

/// `mpiflow serve --config FILE` with each refused value: exit status 2 and one line naming the
/// key, and no listening line.
#[test]
fn serve_exits_with_the_key_named() {
    let dir = tmp("serve");
    for (i, (body, says)) in REFUSED.iter().enumerate() {
        let config = file(&dir, i, body);
        let mut child = Command::new(env!("CARGO_BIN_EXE_mpiflow"))
            .args(["serve", "--config"])
            .arg(&config)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        if !line.is_empty() {
            child.kill().unwrap();
            child.wait().unwrap();
            panic!("{body}: the server started: {line}");
        }
        let out = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{body}: {err}");
        assert!(err.starts_with(&format!("error: configuration: {says}")), "{body}: {err}");
        assert_eq!(err.lines().count(), 1, "{body}: one line: {err}");
    }
}

/// A server at the smallest working frame becomes SERVING (its warm-up sample made) and serves
/// a clip with every field of the bundled scenes, objects included.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_smallest_working_frame_serves_samples() {
    let side = MIN_FRAME_SIDE;
    let c = ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some(format!("{side}x{side}")),
        workers: 1,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    };
    let s = start(c).await.expect("starts");
    let channel =
        tonic::transport::Endpoint::from_shared(format!("http://{}", s.addr)).unwrap().connect().await.unwrap();
    // the health Watch says when the warm-up sample is made
    let mut watch = HealthClient::new(channel.clone())
        .watch(HealthCheckRequest { service: String::new() })
        .await
        .unwrap()
        .into_inner();
    let serving = tokio::time::timeout(Duration::from_secs(120), async {
        while let Some(r) = watch.message().await.unwrap() {
            if r.status == ServingStatus::Serving as i32 {
                return true;
            }
        }
        false
    });
    assert!(serving.await.expect("SERVING or the end of the watch"), "the watch ended before SERVING");
    let mut client = mpiflow::service::client::client_for(channel);
    let all: Vec<i32> = (1..=13).collect(); // every field but the stereo disparity
    for index in 0..3 {
        let spec = pb::SampleSpec { seed: 7, frames: 3, fields: all.clone(), ..Default::default() };
        let sample = client.get_sample(spec.sample(index)).await.expect("a sample").into_inner();
        // a clip's images stacked over its 3 frames
        let images = sample.tensors.iter().find(|t| t.name == "images").expect("images");
        assert_eq!(images.shape, [3, side as u32, side as u32, 3], "{index}");
        assert_eq!(images.data.len(), 3 * side * side * 3, "{index}");
    }
    s.shutdown(Duration::from_secs(5)).await;
}
