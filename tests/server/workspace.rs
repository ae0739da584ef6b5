//! Samples being made count in the byte budget: each running job reserves its sample's
//! workspace (its frames' render buffers and raw tensors) from dispatch until it is done, and a
//! budget that holds one such sample in making and not two still makes every sample asked for,
//! whoever else asks, and a stream holding nothing may start one job whatever its client holds.
//! Real server on loopback, real clients, samples of 64x48; and the scheduler alone.

use std::time::Duration;

use mpiflow::service::client::{client_for, connect_with, ClientOptions};
use mpiflow::service::pb;
use mpiflow::service::{start, RunningServer, ServiceConfig};
use tonic::transport::Endpoint;

const MIB: u64 = 1 << 20;

fn config(budget_mb: u64) -> ServiceConfig {
    ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some("64x48".into()),
        workers: 2,
        log_level: "warn".into(),
        max_buffered_mb: budget_mb,
        ..ServiceConfig::default()
    }
}

async fn server(c: ServiceConfig) -> RunningServer {
    start(c).await.expect("server starts")
}

/// Waits until `done()` holds, checking it every few milliseconds; the deadline only turns a
/// hang into a failure.
async fn until(what: &str, mut done: impl FnMut() -> bool) {
    let wait = async {
        while !done() {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    };
    tokio::time::timeout(Duration::from_secs(120), wait).await.unwrap_or_else(|_| panic!("never: {what}"));
}

/// An 8-frame clip of every field of a pair's law: at 64x48 about 0.54 MB sent and 2.1 MB of
/// workspace while it is made.
fn clip(seed: u64) -> pb::SampleSpec {
    pb::SampleSpec { seed, frames: 8, fields: (1..=13).collect(), ..Default::default() }
}

/// With a budget that holds one 8-frame clip of every field in making and not two (4 MiB), a
/// reader's stream of such clips on two workers never has two made at once, and what the server
/// holds (`buffered`, the workspace included) never goes over the budget; pairs, whose workspace
/// is small, are made two or more at a time under the same budget.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn samples_being_made_count_in_the_byte_budget() {
    let s = server(config(4)).await;
    until("the warm-up sample is made", || s.state.is_serving()).await;
    let mut c = client_for(Endpoint::from_shared(format!("http://{}", s.addr)).unwrap().connect().await.unwrap());
    let clips = pb::StreamRequest { count: 12, prefetch: 4, ..clip(3).stream() };
    let mut stream = c.stream_samples(clips).await.unwrap().into_inner();
    let (mut n, mut making) = (0, 0);
    while let Some(b) = stream.message().await.unwrap() {
        n += b.samples.len();
        making = making.max(s.state.scheduler.stats().making);
    }
    assert_eq!(n, 12);
    // the last job is counted done just after its sample is handed over
    until("the last job is done and the stream closed", || {
        let st = s.state.scheduler.stats();
        st.in_flight == 0 && st.streams == 0
    })
    .await;
    let st = s.state.scheduler.stats();
    assert_eq!(st.max_in_flight_seen, 1, "two clips of 2.1 MB workspace each were never made at once: {st:?}");
    assert!(st.max_buffered_seen <= 4 * MIB, "{st:?}");
    assert!(making <= 4 * MIB, "{making}");
    assert_eq!((st.buffered, st.making), (0, 0), "{st:?}");
    let pairs =
        pb::StreamRequest { count: 24, prefetch: 8, ..pb::SampleSpec { seed: 3, ..Default::default() }.stream() };
    let mut stream = c.stream_samples(pairs).await.unwrap().into_inner();
    while stream.message().await.unwrap().is_some() {}
    let st = s.state.scheduler.stats();
    assert!(st.max_in_flight_seen >= 2, "{st:?}");
    assert!(st.max_buffered_seen <= 4 * MIB, "{st:?}");
    s.shutdown(Duration::from_millis(500)).await;
}

/// A small budget still makes progress: at 3 MiB, where one 8-frame clip of every field takes
/// 2.65 MB of it while it is made (more than a client's share and more than the room a client
/// not first in line may take), a trainer streaming pairs from 127.0.0.1 and a second client
/// (127.0.0.7) asking for such clips, by GetSample and by a stream, each get every sample they
/// asked for, in order, and the budget holds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_small_budget_still_makes_progress_with_large_workspaces() {
    let s = server(config(3)).await;
    until("the warm-up sample is made", || s.state.is_serving()).await;
    let addr = s.addr.to_string();
    let mut trainer = client_for(Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap());
    let pairs = pb::StreamRequest { count: 64, ..pb::SampleSpec { seed: 5, ..Default::default() }.stream() };
    let mut pairs = trainer.stream_samples(pairs).await.unwrap().into_inner();
    let options = ClientOptions { local_address: Some("127.0.0.7".parse().unwrap()), ..Default::default() };
    let mut other = connect_with(&addr, &options).await.unwrap();
    let clips = tokio::spawn(async move {
        let mut got = Vec::new();
        for i in 0..3 {
            let one = other.get_sample(clip(9).sample(i)).await.expect("a clip by GetSample").into_inner();
            got.push(one.index);
        }
        let req = pb::StreamRequest { count: 4, start_index: 10, ..clip(9).stream() };
        let mut stream = other.stream_samples(req).await.expect("a stream of clips").into_inner();
        while let Some(b) = stream.message().await.expect("the clips' stream goes on") {
            got.extend(b.samples.iter().map(|x| x.index));
        }
        got
    });
    let mut got = Vec::new();
    while let Some(b) =
        tokio::time::timeout(Duration::from_secs(60), pairs.message()).await.expect("pairs keep coming").unwrap()
    {
        got.extend(b.samples.iter().map(|x| x.index));
    }
    assert_eq!(got, (0..64).collect::<Vec<_>>());
    let clips = tokio::time::timeout(Duration::from_secs(120), clips).await.expect("the clips are made").unwrap();
    assert_eq!(clips, vec![0, 1, 2, 10, 11, 12, 13]);
    let st = s.state.scheduler.stats();
    assert!(st.max_buffered_seen <= 3 * MIB, "{st:?}");
    until("every stream is closed and every job done", || {
        let st = s.state.scheduler.stats();
        st.streams == 0 && st.in_flight == 0
    })
    .await;
    assert_eq!(s.state.scheduler.stats().making, 0);
    s.shutdown(Duration::from_millis(500)).await;
}

/// The next batch of a stream; a stream that gets nothing within a minute fails the test.
async fn next_batch(st: &mut mpiflow::service::pool::SampleStream) -> pb::SampleBatch {
    use tokio_stream::StreamExt;
    tokio::time::timeout(Duration::from_secs(60), st.next())
        .await
        .expect("the stream gets its sample")
        .expect("the stream goes on")
        .expect("a batch")
}

/// A stream holding nothing may start one job whatever its client holds: streams of one client
/// that took one message each and then stopped reading hold samples made ahead, and the room they
/// leave is less than a sample's bound and workspace (~10 kB samples that take 40 kB while they
/// are made, a budget of 100 kB); each new stream of the same client still gets its samples (the
/// stalled streams drop what they have not sent once their message has waited `UNREAD_GRACE`
/// untaken), a stream that reads gets every sample in order, and the budget holds.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_holding_nothing_may_start_one_job_whatever_its_client_holds() {
    use mpiflow::service::metrics::Metrics;
    use mpiflow::service::peer::PeerKey;
    use mpiflow::service::pool::{Client, Make, Produce, Scheduler, StreamSpec};
    use std::sync::Arc;
    const BUDGET: u64 = 100_000;
    let sched = Scheduler::new(2, 4, BUDGET, Arc::new(Metrics::new())).unwrap();
    let make: Make = Arc::new(|i| Ok(pb::Sample { index: i, source_id: "x".repeat(10_000), ..Default::default() }));
    let produce = Produce { bound: 12_000, workspace: 40_000, ..Produce::new(make) };
    let spec = |count| StreamSpec {
        start_index: 0,
        rank: 0,
        world_size: 1,
        count,
        batch_size: 1,
        prefetch: 64,
        max_message_bytes: 1 << 20,
    };
    let client = Client { peer: PeerKey::V4(0x7f00_0001), conn: None };
    let mut stalled = Vec::new();
    for _ in 0..4 {
        let mut st = sched.open_for(client.clone(), spec(0), produce.clone()).unwrap();
        assert_eq!(next_batch(&mut st).await.samples[0].index, 0);
        stalled.push(st);
    }
    let mut reader = sched.open_for(client.clone(), spec(12), produce.clone()).unwrap();
    let mut got = Vec::new();
    while got.len() < 12 {
        got.extend(next_batch(&mut reader).await.samples.into_iter().map(|x| x.index));
    }
    assert_eq!(got, (0..12).collect::<Vec<_>>());
    let st = sched.stats();
    assert!(st.max_buffered_seen <= BUDGET, "{st:?}");
    assert!(st.dropped > 0, "the stalled streams dropped what they had not sent: {st:?}");
    drop((stalled, reader));
}
