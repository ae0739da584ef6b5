//! The service over real data sources: a directory with bad images among good ones (every index is
//! still served, deterministically from the next good source, and the skips are visible in
//! GetInfo, in the samples and in the metrics), WebDataset shards as a dataset, uploads (a new
//! dataset that streams, refusals by field and limit), and the depth fields.

use std::path::{Path, PathBuf};
use std::time::Duration;

use mpiflow::io::npy::write_f32_to;
use mpiflow::service::client::client_for;
use mpiflow::service::config::DatasetConfig;
use mpiflow::service::encode::decode_f32;
use mpiflow::service::pb;
use mpiflow::service::pb::mpi_flow_client::MpiFlowClient;
use mpiflow::service::{start, ServiceConfig};
use tonic::transport::{Channel, Endpoint};
use tonic::Code;

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("mpiflow-service-data-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn png(w: u32, h: u32, seed: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([((x * 7 + seed * 40) % 256) as u8, ((y * 9) % 256) as u8, ((x * y + seed) % 256) as u8])
    });
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// Depth 2 at the top to 1 at the bottom.
fn depth_npy(w: usize, h: usize) -> Vec<u8> {
    let d: Vec<f32> = (0..w * h).map(|i| 2.0 - (i / w) as f32 / h as f32).collect();
    let mut out = Vec::new();
    write_f32_to(&mut out, &[h as u64, w as u64], &d).unwrap();
    out
}

const W: u32 = 48;
const H: u32 = 32;

/// The reference layout with depths; `b` is a PNG with a corrupt header, `d` a truncated PNG.
fn photos(root: &Path) {
    std::fs::create_dir_all(root.join("images")).unwrap();
    std::fs::create_dir_all(root.join("depths")).unwrap();
    for (i, name) in ["a", "b", "c", "d", "e"].iter().enumerate() {
        let mut bytes = png(W, H, i as u32);
        match *name {
            "b" => bytes.iter_mut().skip(40).enumerate().for_each(|(k, v)| *v = (k * 13 % 251) as u8),
            "d" => bytes.truncate(bytes.len() / 2),
            _ => {}
        }
        std::fs::write(root.join(format!("images/{name}.png")), bytes).unwrap();
        std::fs::write(root.join(format!("depths/{name}.npy")), depth_npy(W as usize, H as usize)).unwrap();
    }
}

fn shard(path: &Path) {
    let mut b = tar::Builder::new(std::fs::File::create(path).unwrap());
    for i in 0..3u32 {
        for (field, data) in [("png", png(W, H, 10 + i)), ("depth.npy", depth_npy(W as usize, H as usize))] {
            let mut h = tar::Header::new_gnu();
            h.set_size(data.len() as u64);
            h.set_mode(0o644);
            h.set_cksum();
            b.append_data(&mut h, format!("s{i:03}.{field}"), data.as_slice()).unwrap();
        }
    }
    b.finish().unwrap();
}

fn config(datasets: Vec<DatasetConfig>) -> ServiceConfig {
    ServiceConfig {
        addr: "127.0.0.1:0".into(),
        metrics_addr: Some("127.0.0.1:0".into()),
        workers: 2,
        log_level: "warn".into(),
        datasets,
        ..ServiceConfig::default()
    }
}

async fn client(addr: impl ToString) -> MpiFlowClient<Channel> {
    let ch = Endpoint::from_shared(format!("http://{}", addr.to_string())).unwrap().connect().await.unwrap();
    client_for(ch)
}

async fn pull(c: &mut MpiFlowClient<Channel>, r: pb::StreamRequest) -> Vec<pb::Sample> {
    let mut s = c.stream_samples(r).await.expect("stream opens").into_inner();
    let mut out = vec![];
    while let Some(b) = s.message().await.expect("stream goes on") {
        out.extend(b.samples);
    }
    out
}

async fn http_get(addr: &str, path: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    s.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n").as_bytes()).await.unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).await.unwrap();
    out
}

fn without_timings(mut s: pb::Sample) -> pb::Sample {
    s.timings = None;
    s
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_sources_are_passed_over_deterministically_and_reported() {
    let root = tmp("photos");
    photos(&root);
    let ds = vec![DatasetConfig::parse(&format!("photos={}", root.display())).unwrap()];
    let s = start(config(ds.clone())).await.unwrap();
    let mut c = client(s.addr).await;
    let fields =
        vec![pb::Field::Image1 as i32, pb::Field::Flow as i32, pb::Field::Depth1 as i32, pb::Field::Depth2 as i32];
    let r = pb::StreamRequest {
        count: 10,
        ..pb::SampleSpec { seed: 3, fields: fields.clone(), ..Default::default() }.stream()
    };
    let got = pull(&mut c, r.clone()).await;
    assert_eq!(got.iter().map(|s| s.index).collect::<Vec<_>>(), (0..10).collect::<Vec<_>>());
    // b's header is corrupt: left out when the folder is opened (items a, c, d, e); d's data
    // ends early, which only decoding finds: its indices come from the next good item
    let ids: Vec<&str> = got.iter().map(|s| s.source_id.as_str()).collect();
    assert_eq!(&ids[..5], &["a", "c", "e", "e", "a"], "{ids:?}");
    assert_eq!(got[2].skipped_sources, 1);
    assert_eq!((got[0].skipped_sources, got[1].skipped_sources), (0, 0));
    // the depth fields: H x W f32, finite; depth1 is the given depth in the scene scale (nearest 1)
    for smp in &got {
        let d1 = smp.tensors.iter().find(|t| t.name == "depth1").expect("depth1");
        let d2 = smp.tensors.iter().find(|t| t.name == "depth2").expect("depth2");
        assert_eq!(d1.shape, vec![H, W]);
        let d1 = decode_f32(d1).unwrap();
        let d2 = decode_f32(d2).unwrap();
        assert!(d1.iter().chain(&d2).all(|v| v.is_finite() && *v >= 0.0));
        let min = d1.iter().copied().fold(f32::INFINITY, f32::min);
        assert!((min - 1.0).abs() < 0.05, "nearest depth {min}");
        assert!(d2.iter().any(|v| *v > 0.5));
    }
    // skips are visible: GetInfo by reason, metrics
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    let mut skipped: Vec<(&str, u64)> = info.datasets[0].skipped.iter().map(|(k, &n)| (k.as_str(), n)).collect();
    skipped.sort();
    assert_eq!(skipped, [("decode", 1), ("truncated", 1)], "b is corrupt, d truncated");
    let m = http_get(&s.metrics_addr.unwrap().to_string(), "/metrics").await;
    for reason in ["decode", "truncated"] {
        let line = format!("mpiflow_skipped_sources{{dataset=\"photos\",reason=\"{reason}\"}} 1");
        assert!(m.lines().any(|l| l == line), "{line} in {m}");
    }
    // a second server process gives the same bytes (skips included)
    let s2 = start(config(ds)).await.unwrap();
    let mut c2 = client(s2.addr).await;
    let again = pull(&mut c2, r).await;
    assert_eq!(
        got.into_iter().map(without_timings).collect::<Vec<_>>(),
        again.into_iter().map(without_timings).collect::<Vec<_>>()
    );
    s.shutdown(Duration::from_secs(5)).await;
    s2.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shards_serve_and_uploads_make_datasets() {
    let root = tmp("shards");
    shard(&root.join("train-000000.tar"));
    let ds = vec![DatasetConfig::parse(&format!("shards={}", root.display())).unwrap()];
    let s = start(ServiceConfig { max_upload_bytes: 200_000, ..config(ds) }).await.unwrap();
    let mut c = client(s.addr).await;
    let got = pull(&mut c, pb::StreamRequest { count: 4, ..Default::default() }).await;
    let ids: Vec<String> = got.iter().map(|s| s.source_id.clone()).collect();
    assert_eq!(got.len(), 4);
    assert!(ids.iter().all(|id| id.contains("s00")), "{ids:?}");

    // an upload makes a new dataset that streams
    let chunk = |dataset: &str, name: &str, kind: &str, data: Vec<u8>| pb::SourceChunk {
        dataset: dataset.into(),
        name: name.into(),
        kind: kind.into(),
        data,
    };
    let img = png(W, H, 5);
    let (first, rest) = img.split_at(100);
    let chunks = vec![
        chunk("mine", "p1", "image", first.to_vec()),
        chunk("", "", "", rest.to_vec()), // continues p1
        chunk("", "p1", "depth", depth_npy(W as usize, H as usize)),
        chunk("", "p2", "image", png(W, H, 6)),
        chunk("", "p2", "depth", depth_npy(W as usize, H as usize)),
        chunk("", "bad", "image", b"not an image".to_vec()),
    ];
    let summary = c.upload_sources(tokio_stream::iter(chunks)).await.unwrap().into_inner();
    assert_eq!((summary.dataset.as_str(), summary.sources), ("mine", 2), "{summary:?}");
    assert_eq!(summary.rejected.len(), 1, "{summary:?}");
    assert!(summary.rejected[0].starts_with("bad:"), "{summary:?}");
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    let mine = info.datasets.iter().find(|d| d.name == "mine").expect("listed");
    assert_eq!((mine.sources, mine.fingerprint), (2, summary.fingerprint));
    let got = pull(
        &mut c,
        pb::StreamRequest { count: 3, ..pb::SampleSpec { dataset: "mine".into(), ..Default::default() }.stream() },
    )
    .await;
    let ids: Vec<&str> = got.iter().map(|s| s.source_id.as_str()).collect();
    assert_eq!(ids, ["p1", "p2", "p1"]);
    let one = c
        .get_sample(pb::SampleSpec { dataset: "mine".into(), ..Default::default() }.sample(1))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(without_timings(one), without_timings(got[1].clone()));

    // refusals: a configured dataset's name, a bad name, over the byte limit (nothing kept)
    let up = |chunks: Vec<pb::SourceChunk>| {
        let mut c = c.clone();
        async move { c.upload_sources(tokio_stream::iter(chunks)).await.unwrap_err() }
    };
    let e = up(vec![chunk("shards", "x", "image", png(W, H, 1))]).await;
    assert_eq!((e.code(), e.message().starts_with("dataset")), (Code::InvalidArgument, true), "{e:?}");
    let e = up(vec![chunk("../etc", "x", "image", png(W, H, 1))]).await;
    assert_eq!((e.code(), e.message().starts_with("dataset")), (Code::InvalidArgument, true), "{e:?}");
    let e = up(vec![chunk("big", "x", "image", vec![0; 150_000]), chunk("", "y", "image", vec![0; 150_000])]).await;
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    assert!(info.datasets.iter().all(|d| d.name != "big"));
    s.shutdown(Duration::from_secs(5)).await;
}

/// Uploads are checked at the door against what the server can make of them: on a server
/// without a depth model an image without depth, and depth that is all NaN, zero or negative,
/// are rejected with their reason when uploaded (before, they were accepted and every stream on
/// the dataset then failed); the good item is stored and streams.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_that_could_never_make_a_scene_are_rejected_at_the_door() {
    let s = start(config(vec![])).await.unwrap();
    let mut c = client(s.addr).await;
    let (w, h) = (W as usize, H as usize);
    let npy = |v: f32| {
        let mut out = Vec::new();
        write_f32_to(&mut out, &[h as u64, w as u64], &vec![v; w * h]).unwrap();
        out
    };
    let chunk = |dataset: &str, name: &str, kind: &str, data: Vec<u8>| pb::SourceChunk {
        dataset: dataset.into(),
        name: name.into(),
        kind: kind.into(),
        data,
    };
    let chunks = vec![
        chunk("door", "nodepth", "image", png(W, H, 1)),
        chunk("", "nan", "image", png(W, H, 2)),
        chunk("", "nan", "depth", npy(f32::NAN)),
        chunk("", "zero", "image", png(W, H, 3)),
        chunk("", "zero", "depth", npy(0.0)),
        chunk("", "negative", "image", png(W, H, 4)),
        chunk("", "negative", "depth", npy(-2.0)),
        chunk("", "good", "image", png(W, H, 5)),
        chunk("", "good", "depth", depth_npy(w, h)),
    ];
    let summary = c.upload_sources(tokio_stream::iter(chunks)).await.unwrap().into_inner();
    assert_eq!(summary.sources, 1, "{summary:?}");
    for (name, needle) in [
        ("nodepth", "no depth model"),
        ("nan", "no known pixel"),
        ("zero", "no known pixel"),
        ("negative", "no known pixel"),
    ] {
        assert!(
            summary.rejected.iter().any(|r| r.starts_with(&format!("{name}:")) && r.contains(needle)),
            "{name}: {:?}",
            summary.rejected
        );
    }
    let got = pull(
        &mut c,
        pb::StreamRequest { count: 2, ..pb::SampleSpec { dataset: "door".into(), ..Default::default() }.stream() },
    )
    .await;
    assert!(got.iter().all(|s| s.source_id == "good"), "the stored item streams");
    s.shutdown(Duration::from_secs(5)).await;
}

/// An upload that starts and never finishes holds one of `max_concurrent_uploads` slots (and
/// its bytes); a further upload is RESOURCE_EXHAUSTED with nothing kept; when the stalled client
/// goes away its slot comes back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_in_progress_are_bounded() {
    let s = start(ServiceConfig { max_concurrent_uploads: 1, ..config(vec![]) }).await.unwrap();
    let mut c = client(s.addr).await;
    let chunk = |dataset: &str, name: &str, data: Vec<u8>| pb::SourceChunk {
        dataset: dataset.into(),
        name: name.into(),
        kind: "image".into(),
        data,
    };
    // a stalled upload: one chunk sent, the stream kept open
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(chunk("stalled", "a", png(W, H, 1))).await.unwrap();
    let depth = pb::SourceChunk {
        name: "a".into(),
        kind: "depth".into(),
        data: depth_npy(W as usize, H as usize),
        ..Default::default()
    };
    let held = (png(W, H, 1).len() + depth.data.len()) as u64;
    tx.send(depth).await.unwrap();
    let mut c2 = c.clone();
    let stalled = tokio::spawn(async move { c2.upload_sources(tokio_stream::wrappers::ReceiverStream::new(rx)).await });
    let uploads = s.state.datasets.uploads.clone();
    let t = std::time::Instant::now();
    while uploads.in_progress() != (1, held) {
        assert!(t.elapsed() < Duration::from_secs(30), "the stalled upload never arrived: {:?}", uploads.in_progress());
        tokio::task::yield_now().await;
    }
    let one = vec![chunk("second", "b", png(W, H, 2))];
    let e = c.upload_sources(tokio_stream::iter(one.clone())).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(e.message().contains("max_concurrent_uploads"), "{e:?}");
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    assert!(info.datasets.iter().all(|d| d.name != "second"), "nothing of the refused upload is kept");
    // the stalled client finishes (closes its stream): its upload commits and the slot is free
    drop(tx);
    assert_eq!(stalled.await.unwrap().unwrap().into_inner().sources, 1);
    assert_eq!(uploads.in_progress(), (0, 0));
    let depth_b = pb::SourceChunk {
        name: "b".into(),
        kind: "depth".into(),
        data: depth_npy(W as usize, H as usize),
        ..Default::default()
    };
    let again = one.into_iter().chain([depth_b]);
    assert_eq!(c.upload_sources(tokio_stream::iter(again)).await.unwrap().into_inner().sources, 1);
    s.shutdown(Duration::from_secs(5)).await;
}
