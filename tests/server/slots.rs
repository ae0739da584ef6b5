//! Stream slots come back: when every slot of `max_streams` is held and none of the holders is
//! stalled, the client holding more than an even share gives one back to a newcomer. Real
//! server on loopback, real clients from their own loopback addresses; samples are 64x48.

use std::time::Duration;

use mpiflow::service::client::{client_for, connect_with, ClientOptions};
use mpiflow::service::pb;
use mpiflow::service::pool::SLOT_TAKEN_BACK;
use mpiflow::service::{start, ServiceConfig};
use tonic::transport::Endpoint;
use tonic::Code;

/// Two clients (127.0.0.12 and 127.0.0.13) read three endless streams each as fast as they come,
/// holding every slot of `max_streams` = 6; a newcomer's StreamSamples is served, and the slot
/// it takes is one of theirs: one of their streams ends with RESOURCE_EXHAUSTED saying its slot
/// was taken back, with its cursor, after every sample it made was sent in order.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn prompt_readers_holding_every_slot_give_one_back_to_a_newcomer() {
    let s = start(ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some("64x48".into()),
        workers: 2,
        log_level: "warn".into(),
        max_streams: 6,
        ..ServiceConfig::default()
    })
    .await
    .expect("server starts");
    let addr = s.addr.to_string();
    let (tx, mut ended) = tokio::sync::mpsc::unbounded_channel();
    let mut readers = Vec::new();
    for a in [12u8, 13] {
        let options = ClientOptions { local_address: Some([127, 0, 0, a].into()), ..Default::default() };
        let client = connect_with(&addr, &options).await.unwrap();
        for k in 0..3u64 {
            let mut client = client.clone();
            let tx = tx.clone();
            let req = pb::StreamRequest { start_index: k << 32, ..pb::SampleSpec::default().stream() };
            let mut stream = client.stream_samples(req).await.expect("a slot").into_inner();
            readers.push(tokio::spawn(async move {
                let mut next = k << 32;
                loop {
                    match stream.message().await {
                        Ok(Some(b)) => {
                            for x in &b.samples {
                                if x.index != next {
                                    let _ =
                                        tx.send((tonic::Status::internal(format!("{} after {next}", x.index)), next));
                                    return;
                                }
                                next += 1;
                            }
                        }
                        Ok(None) => {
                            let _ = tx.send((tonic::Status::internal("an endless stream ended"), next));
                            return;
                        }
                        Err(status) => {
                            let _ = tx.send((status, next));
                            return;
                        }
                    }
                }
            }));
        }
    }
    assert_eq!(s.state.active_streams(), 6, "every slot is held");
    let mut newcomer = client_for(Endpoint::from_shared(format!("http://{addr}")).unwrap().connect().await.unwrap());
    let req = pb::StreamRequest { count: 2, ..Default::default() };
    let mut stream = newcomer.stream_samples(req).await.expect("the newcomer's stream is opened").into_inner();
    let mut got = 0;
    while let Some(b) = stream.message().await.expect("served") {
        got += b.samples.len();
    }
    assert_eq!(got, 2);
    let (status, next) = tokio::time::timeout(Duration::from_secs(60), ended.recv()).await.expect("one ended").unwrap();
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert_eq!(status.message(), SLOT_TAKEN_BACK, "{status:?}");
    let cursor = mpiflow::service::error::cursor_of(&status).expect("a cursor");
    assert_eq!(cursor.0, next, "the cursor is the next index it did not get: {status:?}");
    // the five other streams go on
    assert!(ended.try_recv().is_err());
    for r in readers {
        r.abort();
    }
    s.shutdown(Duration::from_millis(500)).await;
}
