//! The gRPC service end to end on loopback: in-process servers (`mpiflow::service::start`, port 0)
//! and the real `mpiflow serve` binary, driven by the tonic client. Checks the promises of the
//! API (pure addressing across processes, rank partition, resume without loss or repeat, drain
//! with cursor, fingerprint refusal), back-pressure and the in-flight bound, each refusal's code
//! and field, health transitions, encodings and crops. Samples are 64x48 to stay fast.

use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use mpiflow::service::client::client_for;
use mpiflow::service::encode::{decode_f32, decode_tensor};
use mpiflow::service::error::cursor_of;
use mpiflow::service::pb;
use mpiflow::service::pb::mpi_flow_client::MpiFlowClient;
use mpiflow::service::{start, RunningServer, ServiceConfig};
use tonic::transport::{Channel, Endpoint};
use tonic::{Code, Status};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_health::pb::HealthCheckRequest;

const SIZE: &str = "64x48";

fn config() -> ServiceConfig {
    ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some(SIZE.into()),
        workers: 2,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    }
}

async fn server(c: ServiceConfig) -> RunningServer {
    start(c).await.expect("server starts")
}

async fn channel(addr: &str) -> Channel {
    Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.expect("connects")
}

async fn client(addr: impl ToString) -> MpiFlowClient<Channel> {
    client_for(channel(&addr.to_string()).await)
}

/// Waits until `done()` holds (an observable state of the server), checking it every few
/// milliseconds; the deadline only turns a hang into a failure.
async fn until(what: &str, mut done: impl FnMut() -> bool) {
    let wait = async {
        while !done() {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    };
    tokio::time::timeout(Duration::from_secs(120), wait).await.unwrap_or_else(|_| panic!("never: {what}"));
}

async fn wait_serving(addr: &str) {
    let mut h = HealthClient::new(channel(addr).await);
    let t = Instant::now();
    loop {
        let s = h.check(HealthCheckRequest { service: String::new() }).await.unwrap().into_inner().status;
        if s == ServingStatus::Serving as i32 {
            return;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "never SERVING");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Everything a stream delivered: samples, each batch's (next_index, resume_start_index), and the
/// status that ended it (None = OK).
struct Pulled {
    samples: Vec<pb::Sample>,
    cursors: Vec<(u64, u64)>,
    end: Option<Status>,
}

impl Pulled {
    fn indices(&self) -> Vec<u64> {
        self.samples.iter().map(|s| s.index).collect()
    }
}

async fn pull_all(c: &mut MpiFlowClient<Channel>, r: pb::StreamRequest) -> Pulled {
    let mut s = c.stream_samples(r).await.expect("stream opens").into_inner();
    let mut p = Pulled { samples: vec![], cursors: vec![], end: None };
    loop {
        match s.message().await {
            Ok(Some(b)) => {
                p.cursors.push((b.next_index, b.resume_start_index));
                p.samples.extend(b.samples);
            }
            Ok(None) => break,
            Err(e) => {
                p.end = Some(e);
                break;
            }
        }
    }
    p
}

/// The sample without its timings (measurements, not content).
fn content(mut s: pb::Sample) -> pb::Sample {
    s.timings = None;
    s
}

fn req(seed: u64, start_index: u64, count: u64) -> pb::StreamRequest {
    pb::StreamRequest { start_index, count, ..pb::SampleSpec { seed, ..Default::default() }.stream() }
}

/// A `mpiflow serve` child process.
struct Binary {
    child: Child,
    addr: String,
}

impl Binary {
    fn start(extra: &[&str]) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_mpiflow"))
            .args(["serve", "--addr", "127.0.0.1:0", "--size", SIZE, "--log-level", "warn"])
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("mpiflow serve starts");
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        let addr = line.trim().strip_prefix("mpiflow serving on ").unwrap_or_else(|| panic!("printed {line:?}"));
        Binary { addr: addr.to_string(), child }
    }

    fn sigterm(&self) {
        let ok = Command::new("kill").args(["-TERM", &self.child.id().to_string()]).status().unwrap();
        assert!(ok.success());
    }

    fn wait_exit(&mut self, within: Duration) -> std::process::ExitStatus {
        let t = Instant::now();
        loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                return s;
            }
            assert!(t.elapsed() < within, "the server did not exit within {within:?}");
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Binary {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_server_processes_give_byte_identical_samples() {
    let a = Binary::start(&["--workers", "1"]);
    let b = Binary::start(&["--workers", "2"]);
    let (mut ca, mut cb) = (client(&a.addr).await, client(&b.addr).await);
    let ia = ca.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    let ib = cb.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    assert_eq!(ia.datasets[0].fingerprint, ib.datasets[0].fingerprint);
    assert_ne!(ia.datasets[0].fingerprint, 0);
    let all = vec![1, 2, 3, 4, 5, 6, 7];
    let r =
        pb::StreamRequest { spec: Some(pb::SampleSpec { fields: all, seed: 7, ..Default::default() }), ..req(7, 3, 6) };
    let pa = pull_all(&mut ca, r.clone()).await;
    let pb_ = pull_all(&mut cb, r).await;
    assert!(pa.end.is_none() && pb_.end.is_none());
    assert_eq!(pa.indices(), (3..9).collect::<Vec<_>>());
    let sa: Vec<_> = pa.samples.into_iter().map(content).collect();
    let sb: Vec<_> = pb_.samples.into_iter().map(content).collect();
    assert_eq!(sa, sb, "same address, same bytes on two processes with different worker counts");
    assert!(sa.iter().all(|s| s.fingerprint == ia.datasets[0].fingerprint && s.seed == 7));
    // GetSample gives the same sample as the stream
    let one = cb
        .get_sample(pb::SampleSpec { seed: 7, fields: [1, 2, 3, 4, 5, 6, 7].to_vec(), ..Default::default() }.sample(5))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(content(one), sa[2]);
    // another seed gives other samples
    let other = pull_all(&mut ca, req(8, 3, 1)).await;
    let first = decode_tensor(&other.samples[0].tensors[1]).unwrap();
    assert_ne!(first, decode_tensor(&sa[0].tensors[1]).unwrap());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ranks_partition_the_indices() {
    let s = server(config()).await;
    let mut c = client(s.addr).await;
    let (start, world, count) = (5u64, 3u32, 4u64);
    let mut seen = BTreeSet::new();
    for rank in 0..world {
        let r = pb::StreamRequest { rank, world_size: world, batch_size: 3, ..req(1, start, count) };
        let p = pull_all(&mut c, r).await;
        assert!(p.end.is_none());
        let want: Vec<u64> = (0..count).map(|k| start + u64::from(rank) + k * u64::from(world)).collect();
        assert_eq!(p.indices(), want, "rank {rank}");
        // batches of 3 then 1; each carries the cursor after its last sample
        assert_eq!(p.cursors.len(), 2);
        let last_of_first = want[2];
        assert_eq!(p.cursors[0], (last_of_first + 3, last_of_first + 3 - u64::from(rank)));
        assert_eq!(p.cursors[1].0, want[3] + 3);
        for i in want {
            assert!(seen.insert(i), "index {i} twice");
        }
    }
    assert_eq!(seen, (start..start + count * u64::from(world)).collect());
    s.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_then_resume_loses_and_repeats_nothing() {
    let s = server(config()).await;
    let mut c = client(s.addr).await;
    let (rank, world) = (1u32, 2u32);
    let base = pb::StreamRequest { rank, world_size: world, batch_size: 2, ..req(3, 10, 0) };
    let reference = pull_all(&mut c, pb::StreamRequest { count: 10, ..base.clone() }).await;
    assert_eq!(reference.samples.len(), 10);
    // an endless stream, cancelled by the client after 3 batches
    let mut got = Vec::new();
    let mut cursor = None;
    {
        let mut st = c.stream_samples(base.clone()).await.unwrap().into_inner();
        for _ in 0..3 {
            let b = st.message().await.unwrap().unwrap();
            cursor = Some(b.resume_start_index);
            got.extend(b.samples);
        }
    }
    let resumed = pull_all(&mut c, pb::StreamRequest { start_index: cursor.unwrap(), count: 4, ..base.clone() }).await;
    got.extend(resumed.samples);
    let got: Vec<_> = got.into_iter().map(content).collect();
    let want: Vec<_> = reference.samples.into_iter().map(content).collect();
    assert_eq!(got, want);
    s.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_drains_with_a_cursor_that_resumes_exactly() {
    let mut a = Binary::start(&["--prefetch", "4"]);
    wait_serving(&a.addr).await;
    let mut c = client(&a.addr).await;
    let mut health = HealthClient::new(channel(&a.addr).await);
    let mut watch =
        health.watch(HealthCheckRequest { service: "mpiflow.v1.MpiFlow".into() }).await.unwrap().into_inner();
    assert_eq!(watch.message().await.unwrap().unwrap().status, ServingStatus::Serving as i32);
    let base = pb::StreamRequest { rank: 0, world_size: 2, ..req(11, 0, 0) };
    let mut st = c.stream_samples(base.clone()).await.unwrap().into_inner();
    let mut got = Vec::new();
    let mut last_cursor = None;
    for _ in 0..3 {
        let b = st.message().await.unwrap().unwrap();
        last_cursor = Some((b.next_index, b.resume_start_index));
        got.extend(b.samples);
    }
    a.sigterm();
    // health turns NOT_SERVING while draining
    let t = Instant::now();
    loop {
        let m = tokio::time::timeout(Duration::from_secs(10), watch.message()).await.expect("a health update");
        match m {
            Ok(Some(r)) if r.status == ServingStatus::NotServing as i32 => break,
            Ok(Some(_)) => {}
            other => panic!("health watch ended before NOT_SERVING: {other:?}"),
        }
        assert!(t.elapsed() < Duration::from_secs(10));
    }
    // the stream sends what was made, then ends with UNAVAILABLE and the cursor in the trailers
    let end = loop {
        match tokio::time::timeout(Duration::from_secs(15), st.message()).await.expect("the stream ends") {
            Ok(Some(b)) => {
                last_cursor = Some((b.next_index, b.resume_start_index));
                got.extend(b.samples);
            }
            Ok(None) => panic!("an endless stream ended without a status"),
            Err(e) => break e,
        }
    };
    assert_eq!(end.code(), Code::Unavailable, "{end:?}");
    let trailer = cursor_of(&end).expect("the trailers carry the cursor");
    assert_eq!(Some(trailer), last_cursor, "the trailer cursor is the one after the last sample received");
    assert!(a.wait_exit(Duration::from_secs(15)).success());
    assert!(got.len() >= 3);

    // a new server resumes from the cursor: nothing lost, nothing repeated
    let b = Binary::start(&[]);
    let mut cb = client(&b.addr).await;
    let n = got.len() as u64;
    let resumed = pull_all(&mut cb, pb::StreamRequest { start_index: trailer.1, count: 3, ..base.clone() }).await;
    assert_eq!(resumed.samples[0].index, trailer.0);
    got.extend(resumed.samples);
    let reference = pull_all(&mut cb, pb::StreamRequest { count: n + 3, ..base }).await;
    let got: Vec<_> = got.into_iter().map(content).collect();
    let want: Vec<_> = reference.samples.into_iter().map(content).collect();
    assert_eq!(got, want);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_is_not_serving_until_warm_and_while_draining() {
    let s = server(ServiceConfig { warmup_delay_ms: 1500, ..config() }).await;
    let addr = s.addr.to_string();
    let mut h = HealthClient::new(channel(&addr).await);
    for service in ["", "mpiflow.v1.MpiFlow"] {
        let r = h.check(HealthCheckRequest { service: service.into() }).await.unwrap().into_inner();
        assert_eq!(r.status, ServingStatus::NotServing as i32, "service {service:?} right after start");
    }
    let mut c = client(&addr).await;
    assert!(!c.get_info(pb::InfoRequest {}).await.unwrap().into_inner().serving);
    wait_serving(&addr).await;
    assert!(c.get_info(pb::InfoRequest {}).await.unwrap().into_inner().serving);
    let mut watch = h.watch(HealthCheckRequest { service: String::new() }).await.unwrap().into_inner();
    assert_eq!(watch.message().await.unwrap().unwrap().status, ServingStatus::Serving as i32);
    let drain = tokio::spawn(s.shutdown(Duration::from_secs(5)));
    let r = tokio::time::timeout(Duration::from_secs(5), watch.message()).await.unwrap().unwrap().unwrap();
    assert_eq!(r.status, ServingStatus::NotServing as i32);
    drain.await.unwrap();
}

async fn expect_refused(c: &mut MpiFlowClient<Channel>, r: pb::StreamRequest, code: Code, needle: &str) {
    let e = match c.stream_samples(r.clone()).await {
        Err(e) => e,
        Ok(_) => panic!("{r:?} was accepted"),
    };
    assert_eq!(e.code(), code, "{r:?}: {e:?}");
    assert!(e.message().contains(needle), "{:?} does not name {needle:?}", e.message());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn refusals_have_the_right_code_and_name_the_field() {
    let s = server(ServiceConfig { max_streams: 4, ..config() }).await;
    let mut c = client(s.addr).await;
    let d = pb::StreamRequest::default;
    let spec = pb::SampleSpec::default;
    let inv = Code::InvalidArgument;
    let crop = |w, h, mode| Some(pb::OutputCrop { width: w, height: h, mode });
    let cases: Vec<(pb::StreamRequest, Code, &str)> = vec![
        (pb::StreamRequest { world_size: (1 << 20) + 1, ..d() }, inv, "world_size"),
        (pb::StreamRequest { rank: 2, world_size: 2, ..d() }, inv, "rank"),
        (pb::StreamRequest { rank: 1, ..d() }, inv, "rank"),
        (pb::StreamRequest { batch_size: 65, ..d() }, inv, "batch_size"),
        (pb::SampleSpec { fields: vec![42], ..spec() }.stream(), inv, "fields"),
        (pb::SampleSpec { fields: vec![0], ..spec() }.stream(), inv, "fields"),
        (pb::SampleSpec { fields: vec![99], ..spec() }.stream(), inv, "fields"),
        (pb::SampleSpec { frames: 1, ..spec() }.stream(), inv, "frames"),
        (pb::SampleSpec { frames: 9, ..spec() }.stream(), inv, "frames"),
        (pb::SampleSpec { frames: 3, augment: "raft-chairs".into(), ..spec() }.stream(), inv, "augment"),
        (pb::SampleSpec { fields: vec![11], augment: "raft-chairs".into(), ..spec() }.stream(), inv, "augment"),
        (pb::SampleSpec { flow_dtype: 9, ..spec() }.stream(), inv, "flow_dtype"),
        (pb::SampleSpec { compression: 9, ..spec() }.stream(), inv, "compression"),
        (pb::SampleSpec { crop: crop(9000, 0, 0), ..spec() }.stream(), inv, "crop.width"),
        (pb::SampleSpec { crop: crop(0, 9000, 0), ..spec() }.stream(), inv, "crop.height"),
        (pb::SampleSpec { crop: crop(8, 8, 7), ..spec() }.stream(), inv, "crop.mode"),
        (pb::SampleSpec { motion_preset: "warp".into(), ..spec() }.stream(), inv, "motion_preset"),
        (pb::SampleSpec { motion_ranges_json: "{".into(), ..spec() }.stream(), inv, "motion_ranges_json"),
        (pb::SampleSpec { max_objects: Some(300), ..spec() }.stream(), inv, "max_objects"),
        (pb::SampleSpec { motions_per_image: Some(0), ..spec() }.stream(), inv, "motions_per_image"),
        (pb::SampleSpec { resample: "cubic".into(), ..spec() }.stream(), inv, "resample"),
        (pb::StreamRequest { start_index: u64::MAX, rank: 1, world_size: 2, ..d() }, inv, "start_index"),
        (pb::StreamRequest { count: 3, start_index: u64::MAX - 1, ..d() }, inv, "count"),
        // 2^64 - 1 is the end cursor, never a sample: the same rule for every count
        (pb::StreamRequest { count: 1, start_index: u64::MAX, ..d() }, inv, "count"),
        (pb::StreamRequest { count: 2, start_index: u64::MAX - 1, ..d() }, inv, "count"),
        (pb::SampleSpec { dataset: "nope".into(), ..spec() }.stream(), Code::NotFound, "nope"),
        // a huge name is echoed short: the client sees NOT_FOUND, not a metadata-size error
        (pb::SampleSpec { dataset: "n".repeat(15_000), ..spec() }.stream(), Code::NotFound, "(14800 more characters)"),
        (pb::SampleSpec { fingerprint: 0x1234, ..spec() }.stream(), Code::FailedPrecondition, "fingerprint"),
    ];
    for (r, code, needle) in cases {
        expect_refused(&mut c, r, code, needle).await;
    }
    // GetSample refuses alike
    let e = c.get_sample(pb::SampleRequest { index: u64::MAX, ..Default::default() }).await.unwrap_err();
    assert_eq!((e.code(), e.message().starts_with("index")), (inv, true), "{e:?}");
    let e = c.get_sample(pb::SampleSpec { crop: crop(9000, 0, 0), ..Default::default() }.sample(0)).await.unwrap_err();
    assert_eq!((e.code(), e.message().starts_with("crop.width")), (inv, true), "{e:?}");
    let e = c.get_sample(pb::SampleSpec { fingerprint: 7, ..Default::default() }.sample(0)).await.unwrap_err();
    assert_eq!(e.code(), Code::FailedPrecondition);
    // a valid motion_ranges_json is accepted (and changes the fingerprint)
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    // the instruction set the hot loops were dispatched to (the server runs in this process)
    assert_eq!(info.simd, mpiflow::isa::current().name());
    let ranges = serde_json::to_string(&mpiflow::sample::motion::MotionPreset::PaperKitti.ranges()).unwrap();
    let one = c
        .get_sample(pb::SampleSpec { motion_ranges_json: ranges.clone(), ..Default::default() }.sample(0))
        .await
        .unwrap()
        .into_inner();
    assert_ne!(one.fingerprint, info.datasets[0].fingerprint);
    // ... and a request naming that fingerprint with the same override is served
    let again =
        pb::SampleSpec { motion_ranges_json: ranges, fingerprint: one.fingerprint, ..Default::default() }.sample(0);
    assert!(c.get_sample(again).await.is_ok());
    let stale = pb::SampleSpec { fingerprint: one.fingerprint, ..Default::default() }.sample(0);
    assert_eq!(c.get_sample(stale).await.unwrap_err().code(), Code::FailedPrecondition);
    // a colour kernel other than the dataset's: another fingerprint (so other motions too)
    let fields = vec![pb::Field::Image2 as i32];
    let default =
        c.get_sample(pb::SampleSpec { fields: fields.clone(), ..Default::default() }.sample(0)).await.unwrap();
    let bilinear = pb::SampleSpec { resample: "bilinear".into(), fields, ..Default::default() }.sample(0);
    let bilinear = c.get_sample(bilinear).await.unwrap().into_inner();
    let default = default.into_inner();
    assert_ne!(bilinear.fingerprint, default.fingerprint);
    let image2 = |s: &pb::Sample| s.tensors.iter().find(|t| t.name == "image2").unwrap().data.clone();
    assert_ne!(image2(&bilinear), image2(&default));
    let e =
        c.get_sample(pb::SampleSpec { resample: "nearest".into(), ..Default::default() }.sample(0)).await.unwrap_err();
    assert_eq!((e.code(), e.message().starts_with("resample")), (inv, true), "{e:?}");
    // an upload without a dataset name (more upload cases in tests/server/service_data.rs)
    let chunks = tokio_stream::iter(vec![pb::SourceChunk::default()]);
    let e = c.upload_sources(chunks).await.unwrap_err();
    assert_eq!((e.code(), e.message().starts_with("dataset")), (inv, true), "{e:?}");
    // the stream limit: one client holds at most half of max_streams
    let s1 = c.stream_samples(d()).await.unwrap();
    let s2 = c.stream_samples(d()).await.unwrap();
    expect_refused(&mut c, d(), Code::ResourceExhausted, "half of max_streams").await;
    drop(s1);
    // the server sees the client's reset and closes the stream: its slot is free again
    until("the closed stream is dropped", || s.state.active_streams() == 1).await;
    let s3 = c.stream_samples(d()).await.expect("a closed stream frees its slot");
    drop((s2, s3));
    s.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_client_stops_its_production_and_in_flight_is_bounded() {
    let prefetch = 3u64;
    let s = server(ServiceConfig { max_in_flight: 2, default_prefetch: prefetch as u32, ..config() }).await;
    wait_serving(&s.addr.to_string()).await;
    // the stalled client: small HTTP/2 windows, never reads
    let small = Endpoint::from_shared(format!("http://{}", s.addr))
        .unwrap()
        .initial_stream_window_size(65_535)
        .initial_connection_window_size(65_535)
        .connect()
        .await
        .unwrap();
    let mut stalled_client = client_for(small);
    let _stalled = stalled_client.stream_samples(req(1, 0, 0)).await.unwrap();
    // two fast clients meanwhile
    let mut fast = Vec::new();
    for seed in [2, 3] {
        let addr = s.addr.to_string();
        fast.push(tokio::spawn(async move {
            let mut c = client(addr).await;
            pull_all(&mut c, req(seed, 0, 60)).await.samples.len()
        }));
    }
    for f in fast {
        assert_eq!(f.await.unwrap(), 60, "the fast streams are not held up by the stalled one");
    }
    // the fast streams end on the server once it has sent their last message
    let one_left = || s.state.scheduler.stats().per_stream.len() == 1;
    until("only the stalled stream is left", one_left).await;
    // the stalled stream settles: no job of it running and its prefetch window full, so the
    // dispatcher gives it nothing more until the transport takes a message
    let settled = || {
        let (_, dispatched, delivered, produced, _) = s.state.scheduler.stats().per_stream[0];
        produced == dispatched && dispatched - delivered == prefetch
    };
    until("the stalled stream fills its prefetch window", settled).await;
    let stats = s.state.scheduler.stats();
    assert_eq!(stats.capacity, 2);
    assert!(stats.max_in_flight_seen <= 2, "{stats:?}");
    assert_eq!(stats.max_in_flight_seen, 2, "three streams kept both slots busy");
    let stalled = stats.per_stream[0];
    let (_, dispatched, delivered, produced, _) = stalled;
    assert!(delivered <= 4, "a 64 KiB window takes at most a couple of ~46 KB messages: {stats:?}");
    // another 60 samples through the same workers (every job done re-runs the dispatch): the
    // stalled stream gets none of them, its production stopped at its window
    let mut c = client(s.addr.to_string()).await;
    assert_eq!(pull_all(&mut c, req(4, 0, 60)).await.samples.len(), 60);
    until("only the stalled stream is left", one_left).await;
    let later = s.state.scheduler.stats();
    assert_eq!(later.per_stream[0], stalled, "production stopped: {later:?}");
    assert_eq!((dispatched, produced), (delivered + prefetch, delivered + prefetch));
    s.shutdown(Duration::from_millis(500)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn lz4_f16_and_crops_round_trip() {
    let s = server(ServiceConfig { metrics_addr: Some("127.0.0.1:0".into()), ..config() }).await;
    let mut c = client(s.addr).await;
    let fields = vec![1, 2, 3, 4];
    let plain = c
        .get_sample(pb::SampleSpec { fields: fields.clone(), ..Default::default() }.sample(2))
        .await
        .unwrap()
        .into_inner();
    let packed = c
        .get_sample(
            pb::SampleSpec {
                fields: fields.clone(),
                compression: pb::Compression::Lz4 as i32,
                flow_dtype: pb::FlowDtype::F16 as i32,
                ..Default::default()
            }
            .sample(2),
        )
        .await
        .unwrap()
        .into_inner();
    let (w, h) = (plain.width as usize, plain.height as usize);
    assert_eq!((w, h), (64, 48));
    for i in [0, 1, 3] {
        assert_eq!(packed.tensors[i].compression, pb::Compression::Lz4 as i32);
        assert_eq!(decode_tensor(&packed.tensors[i]).unwrap(), decode_tensor(&plain.tensors[i]).unwrap());
    }
    assert_eq!(packed.tensors[2].dtype, pb::DType::DtypeF16 as i32);
    let (f32s, f16s) = (decode_f32(&plain.tensors[2]).unwrap(), decode_f32(&packed.tensors[2]).unwrap());
    assert_eq!(f32s.len(), w * h * 2);
    for (a, b) in f32s.iter().zip(&f16s) {
        assert!((a - b).abs() <= a.abs() / 1024.0 + 1e-4, "{a} vs {b}");
    }
    // centre crop: the middle of the full sample, intrinsics shifted
    let crop = |mode: pb::CropMode| Some(pb::OutputCrop { width: 32, height: 24, mode: mode as i32 });
    let center = c
        .get_sample(
            pb::SampleSpec { fields: fields.clone(), crop: crop(pb::CropMode::Center), ..Default::default() }.sample(2),
        )
        .await
        .unwrap()
        .into_inner();
    assert_eq!((center.width, center.height, center.crop_x, center.crop_y), (32, 24, 16, 12));
    let full1 = decode_tensor(&plain.tensors[0]).unwrap();
    let crop1 = decode_tensor(&center.tensors[0]).unwrap();
    for y in 0..24 {
        assert_eq!(&crop1[y * 32 * 3..(y + 1) * 32 * 3], &full1[((y + 12) * w + 16) * 3..((y + 12) * w + 48) * 3]);
    }
    let (ki, kc) = (plain.intrinsics.unwrap(), center.intrinsics.unwrap());
    assert_eq!((kc.cx, kc.cy, kc.fx), (ki.cx - 16.0, ki.cy - 12.0, ki.fx));
    // valid is cleared exactly where the flow target leaves the crop
    let (fullv, cropv) = (decode_tensor(&plain.tensors[3]).unwrap(), decode_tensor(&center.tensors[3]).unwrap());
    let cropf = decode_f32(&center.tensors[2]).unwrap();
    for y in 0..24 {
        for x in 0..32 {
            let (u, v) = (cropf[2 * (y * 32 + x)], cropf[2 * (y * 32 + x) + 1]);
            let (tx, ty) = (x as f32 + u, y as f32 + v);
            let inside = (0.0..=31.0).contains(&tx) && (0.0..=23.0).contains(&ty);
            let want = u8::from(fullv[(y + 12) * w + x + 16] != 0 && inside);
            assert_eq!(cropv[y * 32 + x], want, "pixel {x},{y}");
        }
    }
    // random crop: reproducible, inside the frame
    let r = pb::SampleSpec { fields, crop: crop(pb::CropMode::Random), ..Default::default() }.sample(2);
    let a = c.get_sample(r.clone()).await.unwrap().into_inner();
    let b = c.get_sample(r).await.unwrap().into_inner();
    assert_eq!(content(a.clone()), content(b));
    assert!(a.crop_x <= 32 && a.crop_y <= 24);
    // metrics saw these samples
    let m = s.metrics_addr.unwrap();
    let body = http_get(&m.to_string(), "/metrics").await;
    for name in [
        "mpiflow_samples_generated_total",
        "mpiflow_stage_seconds_bucket",
        "mpiflow_saturation",
        "mpiflow_scene_cache_hits_total",
    ] {
        assert!(body.contains(name), "{name} missing from /metrics");
    }
    s.shutdown(Duration::from_secs(5)).await;
}

async fn http_get(addr: &str, path: &str) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut sock = tokio::net::TcpStream::connect(addr).await.unwrap();
    sock.write_all(format!("GET {path} HTTP/1.1\r\nHost: x\r\n\r\n").as_bytes()).await.unwrap();
    let mut out = String::new();
    sock.read_to_string(&mut out).await.unwrap();
    assert!(out.starts_with("HTTP/1.1 200"), "{out}");
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sample_over_grpc_default_4_mib_limit_arrives() {
    // the bundled scenes at their full 640x480: with every field a sample is ~5.5 MB
    let s = server(ServiceConfig { size: None, ..config() }).await;
    let mut c = client(s.addr).await;
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    let limits = info.limits.unwrap();
    assert!(limits.max_message_bytes >= 26 * limits.max_image_pixels, "{limits:?}");
    let all = vec![1, 2, 3, 4, 5, 6, 7];
    let one = c.get_sample(pb::SampleSpec { fields: all, ..Default::default() }.sample(0)).await.unwrap().into_inner();
    assert_eq!((one.width, one.height), (640, 480));
    let bytes: usize = one.tensors.iter().map(|t| t.data.len()).sum();
    assert!(bytes > 4 << 20, "{bytes}");
    s.shutdown(Duration::from_secs(5)).await;
}

#[test]
fn pull_saves_the_flo_layout_and_health_exits_by_status() {
    let server = Binary::start(&[]);
    let dir = std::env::temp_dir().join(format!("mpiflow-pull-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let bin = env!("CARGO_BIN_EXE_mpiflow");
    let t = Instant::now();
    loop {
        let h = Command::new(bin).args(["health", "--addr", &server.addr]).output().unwrap();
        if h.status.success() {
            assert_eq!(String::from_utf8_lossy(&h.stdout).trim(), "SERVING");
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(20), "never healthy");
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = Command::new(bin)
        .args(["pull", "--addr", &server.addr, "--count", "3", "--rank", "1", "--world-size", "2"])
        .args(["--start-index", "4", "--lz4", "--f16", "--out"])
        .arg(&dir)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout} {}", String::from_utf8_lossy(&out.stderr));
    assert!(stdout.contains("samples/s") && stdout.contains("MB/s") && stdout.contains("first sample after"));
    for i in [5, 7, 9] {
        for f in ["img1.png", "img2.png", "flow.flo", "valid.png"] {
            assert!(dir.join(format!("{i:08}_{f}")).is_file(), "{i} {f}");
        }
    }
    assert!(!dir.join("00000004_img1.png").exists());
    assert!(dir.join("previews").is_dir());
    let _ = std::fs::remove_dir_all(&dir);
    // health fails (exit code != 0) when nothing answers
    drop(server);
    let h = Command::new(bin).args(["health", "--addr", "127.0.0.1:1", "--timeout-s", "2"]).output().unwrap();
    assert!(!h.status.success());
}

/// The end of the index space: an endless stream near 2^64 sends every index below 2^64 - 1
/// once and ends with the end cursor; resuming from that cursor repeats nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_at_the_end_of_the_index_space_ends_without_repeating() {
    let s = server(config()).await;
    let mut c = client(s.addr).await;
    let p = pull_all(&mut c, req(3, u64::MAX - 2, 0)).await;
    assert!(p.end.is_none(), "{:?}", p.end);
    assert_eq!(p.indices(), [u64::MAX - 2, u64::MAX - 1]);
    assert_eq!(*p.cursors.last().unwrap(), (u64::MAX, u64::MAX));
    let again = pull_all(&mut c, req(3, u64::MAX, 0)).await;
    assert!(again.end.is_none() && again.samples.is_empty(), "resuming at the end gives nothing");
    // two ranks: rank 1 of 2 from 2^64 - 4 gets 2^64 - 3 only, its cursor says the end
    let r = pb::StreamRequest { rank: 1, world_size: 2, ..req(3, u64::MAX - 3, 0) };
    let p = pull_all(&mut c, r).await;
    assert_eq!(p.indices(), [u64::MAX - 2]);
    assert_eq!(*p.cursors.last().unwrap(), (u64::MAX, u64::MAX - 1));
}

/// A start-up error never prints raw bytes: a `--source` that is a `.tar` of random bytes
/// (control characters, escape sequences) gives one printable line and exit code 2.
#[test]
fn a_binary_garbage_source_gives_one_printable_error_line() {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("garbage-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let tar = dir.join("noise.tar");
    // a deterministic byte soup with every byte value, escape sequences included
    let bytes: Vec<u8> = (0..20_000u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8).collect();
    std::fs::write(&tar, bytes).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_mpiflow"))
        .args(["serve", "--addr", "127.0.0.1:0", "--size", SIZE, "--log-level", "warn", "--source"])
        .arg(&tar)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8(out.stderr).expect("stderr is UTF-8, not raw bytes");
    assert_eq!(err.lines().count(), 1, "{err:?}");
    assert!(err.starts_with("error: ") && err.contains("noise.tar"), "{err:?}");
    assert!(!err.trim_end().chars().any(char::is_control), "{err:?}");
}

/// Reads from a raw connection until the server closes it (Ok(0)); the read timeout bounds the
/// wait, so a server that keeps the connection fails the test instead of hanging it.
fn closed_by_server(mut s: std::net::TcpStream) -> bool {
    use std::io::Read;
    s.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let mut buf = [0u8; 256];
    loop {
        match s.read(&mut buf) {
            Ok(0) => return true,
            Ok(_) => continue,
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => return true,
            Err(_) => return false,
        }
    }
}

/// Connection hygiene: a connection that sends nothing is closed after
/// `idle_connection_timeout_s`; with `max_connections` open, a newcomer takes the place of a
/// connection with no call open, and is closed as it arrives when every connection has a call
/// open (even one that speaks HTTP/2); when one closes, new clients get in again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_connections_are_closed_and_connections_are_bounded() {
    use std::io::Write;
    let idle = server(ServiceConfig { idle_connection_timeout_s: 0.5, ..config() }).await;
    let addr = idle.addr;
    let silent = tokio::task::spawn_blocking(move || closed_by_server(std::net::TcpStream::connect(addr).unwrap()));
    assert!(silent.await.unwrap(), "a silent connection is closed");

    let s = server(ServiceConfig { max_connections: 2, idle_connection_timeout_s: 600.0, ..config() }).await;
    let addr = s.addr;
    let preface = move || {
        let mut t = std::net::TcpStream::connect(addr).unwrap();
        // a real HTTP/2 preface: handled for the bound, not for silence (the timeout is 600 s)
        let _ = t.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n");
        t
    };
    // a client with a stream open, and a connection with no call
    let mut ca = client(s.addr).await;
    let mut sa = ca.stream_samples(pb::StreamRequest::default()).await.unwrap().into_inner();
    assert!(sa.message().await.unwrap().is_some());
    let quiet = tokio::task::spawn_blocking(preface).await.unwrap();
    // (the server accepts connections in the order they arrive: the quiet one is counted first)
    // a newcomer takes the quiet connection's place
    let mut cb = client(s.addr).await;
    let mut sb = cb.stream_samples(pb::StreamRequest::default()).await.unwrap().into_inner();
    assert!(sb.message().await.unwrap().is_some());
    assert!(tokio::task::spawn_blocking(move || closed_by_server(quiet)).await.unwrap(), "the quiet one is closed");
    // every connection has a call open: a third is closed as it arrives, the streams go on
    let third = tokio::task::spawn_blocking(move || closed_by_server(preface()));
    assert!(third.await.unwrap(), "a connection over max_connections is closed");
    assert!(sa.message().await.unwrap().is_some() && sb.message().await.unwrap().is_some());
    // one client leaves: a new one gets in (the server sees the close when it happens)
    drop((sa, ca));
    let t = Instant::now();
    loop {
        let ok = match Endpoint::from_shared(format!("http://{}", s.addr)).unwrap().connect().await {
            Ok(ch) => client_for(ch).get_info(pb::InfoRequest {}).await.is_ok(),
            Err(_) => false,
        };
        if ok {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "no slot came back");
        tokio::task::yield_now().await;
    }
    assert!(sb.message().await.unwrap().is_some(), "the stream that stayed is served");
}

/// A request over the message limit is RESOURCE_EXHAUSTED (gRPC's code for "too large"), not
/// tonic's OUT_OF_RANGE, for a unary call and a server stream alike; the server goes on serving.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_oversized_request_is_resource_exhausted() {
    let s = server(config()).await;
    let limit = s.state.config.max_request_bytes() as usize;
    let ch = channel(&s.addr.to_string()).await;
    let mut c = MpiFlowClient::new(ch).max_encoding_message_size(usize::MAX).max_decoding_message_size(usize::MAX);
    let huge = "d".repeat(limit + 1000);
    let e = c.get_sample(pb::SampleSpec { dataset: huge.clone(), ..Default::default() }.sample(0)).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    let e = c.stream_samples(pb::SampleSpec { dataset: huge, ..Default::default() }.stream()).await.unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{e:?}");
    assert!(c.get_info(pb::InfoRequest {}).await.is_ok());
}

/// A channel whose HTTP/2 windows are small: a client on it that never reads stalls its stream
/// after about one message.
async fn small_window_client(addr: &str) -> MpiFlowClient<Channel> {
    let small = Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .initial_stream_window_size(65_535)
        .initial_connection_window_size(65_535)
        .connect()
        .await
        .unwrap();
    client_for(small)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_streams_hold_at_most_their_share_of_the_buffered_budget() {
    const MIB: u64 = 1 << 20;
    let s = server(ServiceConfig {
        max_buffered_mb: 1,
        max_prefetch: 64,
        metrics_addr: Some("127.0.0.1:0".into()),
        ..config()
    })
    .await;
    let addr = s.addr.to_string();
    wait_serving(&addr).await;
    let all: Vec<i32> = (1..=9).collect();
    let stalled_req = |seed| pb::StreamRequest {
        prefetch: 64,
        ..pb::SampleSpec { seed, fields: all.clone(), ..Default::default() }.stream()
    };
    // the size of one such sample (its estimate on the server)
    let mut c = client(&addr).await;
    let one = pull_all(&mut c, pb::StreamRequest { count: 1, ..stalled_req(1) }).await;
    let sample = prost::Message::encoded_len(&one.samples[0]) as u64;
    assert!(sample > 60_000, "all nine fields at 64x48: {sample} bytes");
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    assert_eq!(info.limits.unwrap().max_buffered_bytes, MIB);

    // four stalled streams, each asking for 64 samples ahead (about 5 MB): the budget stops them
    let mut stalled = Vec::new();
    for seed in 1..=4u64 {
        let mut sc = small_window_client(&addr).await;
        stalled.push((sc.stream_samples(stalled_req(seed)).await.unwrap().into_inner(), sc));
    }
    let settled = |n: usize| {
        let st = s.state.scheduler.stats();
        st.in_flight == 0 && st.waiting_scene == 0 && st.eligible == 0 && st.per_stream.len() == n
    };
    until("the stalled streams settle", || settled(4)).await;
    let st = s.state.scheduler.stats();
    let share = MIB / 4;
    for (p, held) in st.per_stream.iter().zip(&st.held) {
        let (_, dispatched, delivered, _, _) = *p;
        assert!(dispatched - delivered < 64, "the budget, not the prefetch window, stopped it: {st:?}");
        assert!(*held <= share.max(sample), "a stream holds at most its share: {held} > {share}: {st:?}");
    }
    assert!(st.max_buffered_seen <= MIB + 4 * sample, "{st:?}");
    let metrics = http_get(&s.metrics_addr.unwrap().to_string(), "/metrics").await;
    assert!(metrics.contains(&format!("mpiflow_buffered_bytes {}", st.buffered)), "{metrics}");
    assert!(metrics.contains(&format!("mpiflow_buffered_budget_bytes {MIB}")), "{metrics}");

    // a fast client still gets its samples, in order
    let fast = pull_all(&mut c, pb::StreamRequest { count: 30, ..stalled_req(9) }).await;
    assert_eq!(fast.indices(), (0..30).collect::<Vec<_>>());

    // a fifth stalled stream shrinks the shares: the others drop their newest samples
    let mut sc = small_window_client(&addr).await;
    stalled.push((sc.stream_samples(stalled_req(5)).await.unwrap().into_inner(), sc));
    until("five stalled streams settle", || settled(5)).await;
    let st = s.state.scheduler.stats();
    assert!(st.dropped > 0, "{st:?}");
    let share = MIB / 5;
    assert!(st.held.iter().all(|&h| h <= share.max(sample)), "{st:?}");
    assert!(st.max_buffered_seen <= MIB + 5 * sample, "{st:?}");

    // a stalled stream that dropped samples reads on: it gets every index once, byte for byte
    // the samples a fresh stream makes
    let (mut first, _keep) = stalled.remove(0);
    let mut got = Vec::new();
    while got.len() < 40 {
        let b = first.message().await.unwrap().expect("the stream goes on");
        got.extend(b.samples.into_iter().map(content));
    }
    got.truncate(40);
    let fresh = pull_all(&mut c, pb::StreamRequest { count: 40, ..stalled_req(1) }).await;
    assert_eq!(got, fresh.samples.into_iter().map(content).collect::<Vec<_>>());

    // when the clients leave, nothing stays held
    drop((first, _keep));
    drop(stalled);
    until("every stream is closed", || s.state.scheduler.stats().streams == 0).await;
    assert_eq!(s.state.scheduler.stats().buffered, 0);
    s.shutdown(Duration::from_millis(500)).await;
}

/// The value of a metric without labels (or summed over them) in a /metrics text.
fn metric_sum(text: &str, name: &str) -> f64 {
    text.lines()
        .filter(|l| l.starts_with(name) && l[name.len()..].starts_with([' ', '{']))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

/// The server on the built-in default (640x480 bundled scenes, the default cache) keeps every
/// scene it builds: two samples of each of the 8 scenes build each once and evict nothing.
/// (With a cache of 2048 MiB the 8 scenes, then ~270 MiB each, did not fit and most samples rebuilt
/// their scene.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_default_cache_holds_every_bundled_scene() {
    let s = server(ServiceConfig { size: None, metrics_addr: Some("127.0.0.1:0".into()), ..config() }).await;
    let mut c = client(s.addr).await;
    let p = pull_all(&mut c, req(5, 0, 16)).await;
    assert!(p.end.is_none(), "{:?}", p.end);
    let ids: std::collections::BTreeSet<_> = p.samples.iter().map(|x| x.source_id.clone()).collect();
    assert_eq!((p.samples.len(), ids.len()), (16, 8), "two epochs of the 8 bundled scenes");
    assert!(p.samples.iter().all(|x| (x.width, x.height) == (640, 480)));
    let body = http_get(&s.metrics_addr.unwrap().to_string(), "/metrics").await;
    let builds = metric_sum(&body, "mpiflow_scene_builds_total");
    assert_eq!(builds, ids.len() as f64, "one build per scene used:\n{body}");
    assert_eq!(metric_sum(&body, "mpiflow_scene_cache_evictions_total"), 0.0, "{body}");
    let bytes = metric_sum(&body, "mpiflow_scene_cache_bytes");
    assert!(bytes > 0.0 && bytes <= (mpiflow::service::config::DEFAULT_CACHE_MB << 20) as f64, "{body}");
    // the memory goal: at most 80 MiB per cached 640x480, 32-plane scene (the planes and the
    // B-spline coefficients in blocks where there is density; about 45 MiB)
    assert!(bytes / 8.0 <= (80u64 << 20) as f64, "{} MiB per scene", bytes / 8.0 / (1u64 << 20) as f64);
    s.shutdown(Duration::from_secs(5)).await;
}

/// The occlusion mask is made only for the requests that ask for it (the other fields are the
/// same bytes either way, at the same fingerprint), and then it is the library's mask at that
/// address, byte for byte.
#[tokio::test]
async fn the_occlusion_mask_is_made_when_asked_for_and_is_the_librarys() {
    use mpiflow::service::dataset::{Datasets, Overrides};
    let c0 = config();
    // the library at the server's configuration, with the mask: an address where it has occluded pixels
    let datasets = Datasets::open(&c0).expect("datasets open");
    let ds = datasets.default_dataset();
    let g = ds.generator(&Overrides { occlusion: true, ..Overrides::default() }).expect("generator");
    assert_eq!(g.fingerprint(), ds.fingerprint(), "an output selection, not a dataset");
    let (index, want) = (0..16)
        .map(|i| (i, g.sample(3, i).expect("sample").occlusion))
        .find(|(_, o)| o.iter().any(|&v| v != 0))
        .expect("some sample of 16 has occluded pixels");
    // without the mask asked for, the dataset's own generator leaves it all 0
    let plain = ds.generator(&Overrides::default()).expect("generator").sample(3, index).expect("sample");
    assert!(plain.occlusion.iter().all(|&v| v == 0));

    let srv = server(c0).await;
    let mut c = client(&srv.addr).await;
    let get = |fields: Vec<pb::Field>| {
        pb::SampleSpec { seed: 3, fields: fields.into_iter().map(|f| f as i32).collect(), ..Default::default() }
            .sample(index)
    };
    let with = c.get_sample(get(vec![pb::Field::Image2, pb::Field::Flow, pb::Field::Occlusion])).await.unwrap();
    let without = c.get_sample(get(vec![pb::Field::Image2, pb::Field::Flow])).await.unwrap();
    let (with, without) = (with.into_inner(), without.into_inner());
    assert_eq!(with.fingerprint, without.fingerprint);
    let data = |s: &pb::Sample, n: &str| s.tensors.iter().find(|t| t.name == n).map(|t| t.data.to_vec());
    assert_eq!(data(&with, "image2"), data(&without, "image2"));
    assert_eq!(data(&with, "flow"), data(&without, "flow"));
    assert_eq!(data(&without, "occlusion"), None);
    assert_eq!(data(&with, "occlusion"), Some(want));
}

/// Every pair field a stream sends is the library's sample at that address in the plain wire
/// encoding, byte for byte: u8 buffers as they are, f32 values little-endian one after another,
/// and with lz4 the block of those bytes with its size prepended.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streamed_tensors_are_the_librarys_sample_in_the_plain_encoding() {
    use mpiflow::service::dataset::{Datasets, Overrides};
    let c0 = config();
    let datasets = Datasets::open(&c0).expect("datasets open");
    let g = datasets
        .default_dataset()
        .generator(&Overrides { occlusion: true, backward: true, ..Overrides::default() })
        .expect("generator");
    let srv = server(c0).await;
    let mut c = client(&srv.addr).await;
    let fields: Vec<i32> = (1..=13).collect();
    for lz4 in [false, true] {
        let compression = if lz4 { pb::Compression::Lz4 } else { pb::Compression::None } as i32;
        let spec = pb::SampleSpec { seed: 5, fields: fields.clone(), compression, ..Default::default() };
        let got = pull_all(&mut c, pb::StreamRequest { spec: Some(spec), ..req(0, 2, 2) }).await;
        assert!(got.end.is_none());
        assert_eq!(got.indices(), vec![2, 3]);
        for s in &got.samples {
            let want = g.sample(5, s.index).expect("sample");
            let f32s = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
            let plain: Vec<(&str, Vec<u8>)> = vec![
                ("image1", want.image1.clone()),
                ("image2", want.image2.clone()),
                ("flow", f32s(&want.flow)),
                ("valid", want.valid.clone()),
                ("occlusion", want.occlusion.clone()),
                ("mask1", want.mask1.clone()),
                ("mask2", want.mask2.clone()),
                ("depth1", f32s(&want.depth1)),
                ("depth2", f32s(&want.depth2)),
                ("holes", want.holes.clone()),
                ("flow_backward", f32s(&want.backward.flow)),
                ("valid_backward", want.backward.valid.clone()),
                ("occlusion_backward", want.backward.occlusion.clone()),
            ];
            assert_eq!(s.tensors.len(), plain.len());
            for (t, (name, bytes)) in s.tensors.iter().zip(&plain) {
                assert_eq!(t.name, *name);
                assert_eq!(t.raw_size, bytes.len() as u64, "{name}");
                let expected = if lz4 { lz4_flex::block::compress_prepend_size(bytes) } else { bytes.clone() };
                assert!(t.data[..] == expected[..], "{name} of sample {} (lz4 {lz4})", s.index);
            }
        }
    }
    srv.shutdown(Duration::from_secs(5)).await;
}
