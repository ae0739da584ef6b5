//! No stream waits behind another: while one client reads a stream as fast as it comes (every
//! worker busy), clients that open streams and GetSamples calls and drop them after 0 to 3
//! messages each get every message they wait for within a bounded number of the busy stream's
//! samples; and turns go by the worker time samples take, not by their bytes. Real server on
//! loopback, real clients; counted in samples and in the server's own accounting, not seconds.
//!
//! The case, from the soak: on one shared rayon pool a worker whose `join` waits (the renderer's
//! parallel loops) runs newer jobs nested on its stack, and the older job cannot finish before
//! them, so under a steady feed a stream's sample stays buried for as long as the feed lasts (a
//! client gets nothing for 20 s). The workers are one-thread pools fed from one queue.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use mpiflow::service::client::client_for;
use mpiflow::service::pb;
use mpiflow::service::{start, ServiceConfig};
use tonic::transport::Endpoint;

/// More busy-stream samples than this while a client waits for one message is a starved client:
/// its job is dispatched at the next free slot and runs after at most the in-flight jobs started
/// before it (4 here), each worth one busy sample, plus what the busy stream had made ahead.
const BOUND: u64 = 64;
/// The busy stream's length: a starved client gets its message when the feed ends (so the test
/// ends either way), far above what the busy stream receives in the clients' rounds.
const FEED: u64 = 20_000;

/// Opens and drops `rounds` streams and GetSamples calls; returns the most busy-stream samples
/// seen while it waited for one message, with the round.
async fn cancelling(addr: String, seed: u64, rounds: u64, busy: Arc<AtomicU64>) -> (u64, u64) {
    let mut c = client_for(Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap());
    let mut worst = (0, 0);
    let wait = |worst: &mut (u64, u64), before: u64, round: u64| {
        let waited = busy.load(Ordering::SeqCst) - before;
        if waited > worst.0 {
            *worst = (waited, round);
        }
    };
    for round in 1..=rounds {
        if round % 2 == 0 {
            let req = pb::SampleSpec { seed, ..Default::default() }.samples(vec![round, round + 7, round * 3]);
            let before = busy.load(Ordering::SeqCst);
            let mut s = c.get_samples(req).await.unwrap().into_inner();
            assert!(s.message().await.unwrap().is_some());
            wait(&mut worst, before, round);
        } else {
            let req = pb::StreamRequest {
                start_index: round * 100,
                ..pb::SampleSpec { seed, ..Default::default() }.stream()
            };
            let mut s = c.stream_samples(req).await.unwrap().into_inner();
            for _ in 0..round % 4 {
                let before = busy.load(Ordering::SeqCst);
                assert!(s.message().await.unwrap().is_some());
                wait(&mut worst, before, round);
            }
        }
        if worst.0 > BOUND {
            break;
        }
    }
    worst
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_that_open_and_drop_streams_are_not_starved_by_a_busy_stream() {
    let s = start(ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some("160x120".into()),
        workers: 2,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    })
    .await
    .expect("server starts");
    let addr = s.addr.to_string();
    let busy = Arc::new(AtomicU64::new(0));
    let b = busy.clone();
    let mut c = client_for(Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap());
    let mut stream = c
        .stream_samples(pb::StreamRequest { count: FEED, ..pb::SampleSpec { seed: 3, ..Default::default() }.stream() })
        .await
        .unwrap()
        .into_inner();
    let reader = tokio::spawn(async move {
        while let Ok(Some(m)) = stream.message().await {
            b.fetch_add(m.samples.len() as u64, Ordering::SeqCst);
        }
    });
    let rounds = 300;
    let a = tokio::spawn(cancelling(addr.clone(), 7, rounds, busy.clone()));
    let bb = tokio::spawn(cancelling(addr.clone(), 11, rounds, busy.clone()));
    let (wa, wb) = (a.await.unwrap(), bb.await.unwrap());
    let total = busy.load(Ordering::SeqCst);
    reader.abort();
    s.shutdown(Duration::from_secs(5)).await;
    assert!(total > 100 && total < FEED, "the busy stream kept the workers busy ({total} samples)");
    for (seed, (waited, round)) in [(7, wa), (11, wb)] {
        assert!(
            waited <= BOUND,
            "client {seed}, round {round}: waited for one message while the busy stream got {waited} samples"
        );
    }
}

/// A batch larger than a stream's share of the byte budget is sent in parts cut at the share:
/// every sample arrives, in order, and no message holds more than the share allows (the budget
/// is never exceeded).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_batch_larger_than_the_share_of_the_budget_is_sent_in_parts() {
    use mpiflow::service::metrics::Metrics;
    use mpiflow::service::pool::{Make, Produce, Scheduler, StreamSpec};
    use tokio_stream::StreamExt;
    // ~1 kB samples, a 2.5 kB budget, batches of 4
    let sched = Scheduler::new(2, 4, 2_500, Arc::new(Metrics::new())).unwrap();
    let make: Make = Arc::new(|i| Ok(pb::Sample { index: i, source_id: "x".repeat(1_000), ..Default::default() }));
    let spec = StreamSpec {
        start_index: 0,
        rank: 0,
        world_size: 1,
        count: 12,
        batch_size: 4,
        prefetch: 8,
        max_message_bytes: 1 << 20,
    };
    let mut st = sched.open(spec, Produce::new(make)).unwrap();
    let mut got = Vec::new();
    let mut batches = 0;
    while let Some(b) = tokio::time::timeout(Duration::from_secs(60), st.next()).await.expect("the stream stalled") {
        let b = b.unwrap();
        // ~1 kB each: the 2.5 kB share holds two (a stream holding nothing starts one more)
        assert!((1..=2).contains(&b.samples.len()), "a batch of {} samples", b.samples.len());
        got.extend(b.samples.into_iter().map(|s| s.index));
        batches += 1;
    }
    assert_eq!(got, (0..12).collect::<Vec<_>>());
    assert!(batches >= 6, "{batches} batches");
    let seen = sched.stats().max_buffered_seen;
    assert!(seen <= 2_500, "{seen} bytes held against a budget of 2500");
}

/// Turns go to clients by the worker time of their samples, not one per call and not by their
/// bytes: with the worker the bottleneck and two clients always ready, one whose samples take
/// eight times the other's work (and are an eighth of its bytes: cheap to send, dear to make)
/// gets about one sample for the other's eight (round-robin by turns would give one each, turns
/// by bytes sixty-four).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn turns_go_to_clients_by_the_worker_time_of_their_samples() {
    use mpiflow::service::metrics::Metrics;
    use mpiflow::service::peer::PeerKey;
    use mpiflow::service::pool::{Client, Make, Produce, Scheduler, StreamSpec};
    use tokio_stream::StreamExt;
    let sched = Scheduler::new(1, 1, 1 << 30, Arc::new(Metrics::new())).unwrap();
    let make = |n: usize, rounds: u64| -> Make {
        Arc::new(move |i| {
            // the work of making a sample
            let w = (0..rounds).fold(i, |a, r| work(a ^ r));
            Ok(pb::Sample { index: i, seed: w, source_id: "x".repeat(n), ..Default::default() })
        })
    };
    let spec = StreamSpec {
        start_index: 0,
        rank: 0,
        world_size: 1,
        count: 0,
        batch_size: 1,
        prefetch: 16,
        max_message_bytes: 1 << 20,
    };
    let client = |k: u32| Client { peer: PeerKey::V4(k), conn: None };
    let mut dear = sched.open_for(client(1), spec, Produce::new(make(1_000, 8))).unwrap();
    let mut cheap = sched.open_for(client(2), spec, Produce::new(make(8_000, 1))).unwrap();
    let dear_got = Arc::new(AtomicU64::new(0));
    let counter = dear_got.clone();
    let reader = tokio::spawn(async move {
        while let Some(b) = dear.next().await {
            b.unwrap();
            counter.fetch_add(1, Ordering::SeqCst);
        }
    });
    for _ in 0..200 {
        cheap.next().await.unwrap().unwrap();
    }
    let dear_got = dear_got.load(Ordering::SeqCst);
    let used = sched.stats().per_peer;
    reader.abort();
    assert!((200 / 16..=200 / 4).contains(&dear_got), "the dear client got {dear_got} samples for the cheap one's 200");
    // the scheduler's own accounting: the two took about the same worker time
    let (d, c) = (used[0].work_ns as f64, used[1].work_ns as f64);
    assert!(d < 2.0 * c && c < 2.0 * d, "worker time: dear {d} ns, cheap {c} ns");
}

/// Work of a few milliseconds that the compiler cannot skip.
fn work(seed: u64) -> u64 {
    (0..2_000_000u64).fold(seed, |a, i| std::hint::black_box(a.wrapping_mul(6364136223846793005).wrapping_add(i)))
}

/// While a client that reads has a stream open, the clients that do not read (new ones, whose
/// samples nobody takes) run on one worker at a time: 8 such clients from 8 addresses never read
/// their streams (64 samples made ahead each) while one client reads 300 samples on 2 workers.
/// Before the reader's 20th sample they have made fewer than 100 (while the reader is new, it
/// takes its turns with them; once it reads, they get one worker at most); from then on, while
/// the reader has samples left to make, at most one of their jobs is seen running at once; the reader gets all 300 in order; and they are not
/// shut out (samples of theirs are made meanwhile).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_that_do_not_read_take_one_worker_at_most_while_a_client_reads() {
    use mpiflow::service::metrics::Metrics;
    use mpiflow::service::peer::PeerKey;
    use mpiflow::service::pool::{Client, Make, Produce, Scheduler, StreamSpec};
    use std::sync::atomic::AtomicBool;
    use tokio_stream::StreamExt;

    let spec = |count| StreamSpec {
        start_index: 0,
        rank: 0,
        world_size: 1,
        count,
        batch_size: 1,
        prefetch: 64,
        max_message_bytes: 1 << 20,
    };
    let sample = |index: u64, w: u64| pb::Sample { index, seed: w, ..Default::default() };
    let sched = Scheduler::new(2, 4, 1 << 30, Arc::new(Metrics::new())).unwrap();
    let (running, most, made) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let watching = Arc::new(AtomicBool::new(false));
    let make_others: Make = {
        let (running, most, made, watching) = (running.clone(), most.clone(), made.clone(), watching.clone());
        Arc::new(move |i| {
            let now = running.fetch_add(1, Ordering::SeqCst) + 1;
            if watching.load(Ordering::SeqCst) {
                most.fetch_max(now, Ordering::SeqCst);
            }
            let w = work(i);
            running.fetch_sub(1, Ordering::SeqCst);
            made.fetch_add(1, Ordering::SeqCst);
            Ok(sample(i, w))
        })
    };
    let make_reader: Make = Arc::new(move |i| Ok(sample(i, work(i))));
    let client = |ip: std::net::Ipv4Addr| Client { peer: PeerKey::of(ip.into()), conn: None };
    let mut reader = sched.open_for(client([127, 0, 0, 1].into()), spec(300), Produce::new(make_reader)).unwrap();
    let others: Vec<_> = (0..8u8)
        .map(|a| {
            let who = client(std::net::Ipv4Addr::new(127, 0, 9, 2 + a));
            sched.open_for(who, spec(1000), Produce::new(make_others.clone())).unwrap()
        })
        .collect();
    let mut got = Vec::new();
    let mut made_before_20 = None;
    while let Some(batch) = reader.next().await {
        got.extend(batch.expect("the reader's samples").samples.iter().map(|s| s.index));
        if got.len() == 20 {
            made_before_20 = Some(made.load(Ordering::SeqCst));
            watching.store(true, Ordering::SeqCst);
        }
        // near its end the reader has nothing left to make: the others may take every worker
        if got.len() >= 280 {
            watching.store(false, Ordering::SeqCst);
        }
    }
    let made_before_20 = made_before_20.expect("the reader's 20th sample came");
    assert!(made_before_20 < 100, "{made_before_20} samples of clients that do not read before the reader's 20th");
    assert_eq!(got, (0..300).collect::<Vec<u64>>(), "the reader gets every sample in order");
    assert!(
        most.load(Ordering::SeqCst) <= 1,
        "{} jobs of clients that do not read ran at once",
        most.load(Ordering::SeqCst)
    );
    assert!(made.load(Ordering::SeqCst) > made_before_20, "the clients that do not read are not shut out");
    drop(others);
}

/// Waits until `done()` holds (an observable state), checking it every few milliseconds; the
/// deadline only turns a hang into a failure.
async fn until(what: &str, mut done: impl FnMut() -> bool) {
    let wait = async {
        while !done() {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    };
    tokio::time::timeout(Duration::from_secs(120), wait).await.unwrap_or_else(|_| panic!("never: {what}"));
}

/// A StreamSamples call of `req` (one gRPC message) on a raw HTTP/2 connection; its reply.
async fn stream_call(send: &mut h2::client::SendRequest<bytes::Bytes>, req: Vec<u8>) -> http::Response<h2::RecvStream> {
    let head = http::Request::post("http://localhost/mpiflow.v1.MpiFlow/StreamSamples")
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(())
        .unwrap();
    let mut ready = send.clone().ready().await.unwrap();
    let (response, mut body) = ready.send_request(head, false).unwrap();
    let mut frame = vec![0u8];
    frame.extend_from_slice(&(req.len() as u32).to_be_bytes());
    frame.extend_from_slice(&req);
    body.send_data(bytes::Bytes::from(frame), true).unwrap();
    *send = ready;
    response.await.expect("reply headers")
}

/// A prompt reader of cheap-to-send expensive samples gets no more than its share of the workers'
/// time: one address keeps 16 streams of 8-frame clips asking only `valid` with LZ4 (a few hundred
/// bytes each, several pairs' worker time) and takes every message at once; an honest trainer
/// beside it takes 48 pairs of the default fields (a hundred times the clips' bytes). By the
/// server's own accounting, while the trainer's stream runs the attacker's samples take about the
/// worker time the trainer's take, not more (turns by bytes would give the clips nearly every
/// turn), and the trainer gets every sample in order.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_prompt_reader_of_cheap_to_send_expensive_samples_gets_no_more_than_its_share() {
    use mpiflow::service::peer::PeerKey;
    let s = start(ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some("64x48".into()),
        workers: 2,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    })
    .await
    .expect("server starts");
    until("the warm-up sample is made", || s.state.is_serving()).await;
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind((std::net::Ipv4Addr::new(127, 0, 5, 2), 0).into()).expect("binds a loopback address");
    let tcp = socket.connect(s.addr).await.unwrap();
    let (send, conn) = h2::client::Builder::new().initial_window_size(1 << 20).handshake(tcp).await.expect("HTTP/2");
    let _conn = tokio::spawn(conn);
    let clip = pb::SampleSpec {
        seed: 9,
        frames: 8,
        fields: vec![pb::Field::Valid as i32],
        compression: pb::Compression::Lz4 as i32,
        ..Default::default()
    };
    let mut readers = Vec::new();
    for k in 0..16u64 {
        let req = prost::Message::encode_to_vec(&pb::StreamRequest { start_index: k << 32, ..clip.clone().stream() });
        let mut send = send.clone();
        readers.push(tokio::spawn(async move {
            let mut body = stream_call(&mut send, req).await.into_body();
            while let Some(Ok(chunk)) = body.data().await {
                let _ = body.flow_control().release_capacity(chunk.len());
            }
        }));
    }
    let key = |ip: [u8; 4]| PeerKey::of(std::net::Ipv4Addr::from(ip).into());
    let (attacker, trainer) = (key([127, 0, 5, 2]), key([127, 0, 0, 1]));
    let use_of = |peer| {
        let stats = s.state.scheduler.stats().per_peer;
        stats.iter().find(|u| u.peer == peer).copied().unwrap_or(mpiflow::service::pool::PeerUse {
            peer,
            work_ns: 0,
            samples: 0,
        })
    };
    until("the attack's clips are made and read", || use_of(attacker).samples >= 32).await;
    let clips_before = use_of(attacker);

    // the trainer's stream is endless: its use is read while it is open, after 48 samples
    let mut honest = client_for(Endpoint::from_shared(format!("http://{}", s.addr)).unwrap().connect().await.unwrap());
    let req = pb::SampleSpec { seed: 5, ..Default::default() }.stream();
    let mut stream = honest.stream_samples(req).await.unwrap().into_inner();
    let mut got = Vec::new();
    while got.len() < 48 {
        let b = tokio::time::timeout(Duration::from_secs(60), stream.message()).await.expect("served").unwrap();
        got.extend(b.expect("an endless stream").samples.iter().map(|x| x.index));
    }
    let (clips, pairs) = (use_of(attacker), use_of(trainer));
    drop(stream);
    assert!(pairs.samples >= 40, "{pairs:?}");
    assert_eq!(got[..48], (0..48).collect::<Vec<_>>());
    let clip_ns = clips_before.work_ns / clips_before.samples.max(1);
    let pair_ns = pairs.work_ns / pairs.samples.max(1);
    let (attack_ns, honest_ns) = (clips.work_ns - clips_before.work_ns, pairs.work_ns);
    assert!(clip_ns > 2 * pair_ns, "a clip takes {clip_ns} ns of a worker, a pair {pair_ns} ns");
    // fair queueing by worker time: the two share the workers; the slack is the clips already
    // running when the trainer came and those running when it left (at most max_in_flight each)
    let slack = 2 * s.state.scheduler.capacity() as u64 * clip_ns;
    assert!(
        attack_ns <= 2 * honest_ns + slack,
        "while the trainer's 48 pairs took {honest_ns} ns of the workers, the attacker's {} clips took {attack_ns} ns",
        clips.samples - clips_before.samples
    );
    for r in readers {
        r.abort();
    }
    s.shutdown(Duration::from_millis(500)).await;
}
