//! GetSamples, the batched random access, end to end on loopback: an in-process server (port 0)
//! driven by the tonic client. The samples of an index list (any order, duplicates) are those of
//! GetSample byte for byte, in request order; the list's bound, the stream limit and the crop
//! rule (a crop larger than the rendered frame is refused, never shrunk) hold. Samples are 64x48.

use std::time::Duration;

use mpiflow::service::client::client_for;
use mpiflow::service::pb;
use mpiflow::service::pb::mpi_flow_client::MpiFlowClient;
use mpiflow::service::validate::MAX_INDICES;
use mpiflow::service::{start, RunningServer, ServiceConfig};
use tonic::transport::{Channel, Endpoint};
use tonic::{Code, Status};

fn config() -> ServiceConfig {
    ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some("64x48".into()),
        workers: 2,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    }
}

async fn server(c: ServiceConfig) -> RunningServer {
    start(c).await.expect("server starts")
}

async fn client(s: &RunningServer) -> MpiFlowClient<Channel> {
    let ch = Endpoint::from_shared(format!("http://{}", s.addr)).unwrap().connect().await.expect("connects");
    client_for(ch)
}

/// The sample without its timings (measurements, not content).
fn content(mut s: pb::Sample) -> pb::Sample {
    s.timings = None;
    s
}

/// Every sample of a GetSamples call, and the status that ended it (None = OK).
async fn get_samples(c: &mut MpiFlowClient<Channel>, r: pb::SamplesRequest) -> Result<Vec<pb::Sample>, Status> {
    let mut s = c.get_samples(r).await?.into_inner();
    let mut out = Vec::new();
    while let Some(x) = s.message().await? {
        out.push(x);
    }
    Ok(out)
}

fn sample_request(r: &pb::SamplesRequest, index: u64) -> pb::SampleRequest {
    r.spec.clone().unwrap_or_default().sample(index)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn get_samples_of_an_unordered_list_equals_get_sample_per_index() {
    let s = server(config()).await;
    let mut c = client(&s).await;
    let indices = vec![9, 2, 17, 2, 0, 33, 9, 5];
    let r = pb::SampleSpec {
        seed: 11,
        fields: vec![1, 2, 3, 4, 5],
        compression: pb::Compression::Lz4 as i32,
        crop: Some(pb::OutputCrop { width: 40, height: 30, mode: pb::CropMode::Random as i32 }),
        ..Default::default()
    }
    .samples(indices.clone());
    let got = get_samples(&mut c, r.clone()).await.expect("GetSamples serves the list");
    assert_eq!(got.iter().map(|x| x.index).collect::<Vec<_>>(), indices, "request order, duplicates kept");
    for g in &got {
        let one = c.get_sample(sample_request(&r, g.index)).await.unwrap().into_inner();
        assert_eq!(content(g.clone()), content(one), "index {}", g.index);
        assert_eq!((g.width, g.height, g.seed), (40, 30, 11));
    }
    // the same index list from a stream's point of view: index 5 of a plain stream
    let mut st = c
        .stream_samples(pb::StreamRequest { start_index: 5, count: 1, ..r.spec.clone().unwrap().stream() })
        .await
        .unwrap()
        .into_inner();
    let b = st.message().await.unwrap().unwrap();
    assert_eq!(content(b.samples[0].clone()), content(got[7].clone()));
    drop(st);
    s.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_index_list_is_bounded_and_refusals_name_their_field() {
    let s = server(ServiceConfig { max_random_access_calls: 1, ..config() }).await;
    let mut c = client(&s).await;
    let info = c.get_info(pb::InfoRequest {}).await.unwrap().into_inner();
    assert_eq!(info.limits.unwrap().max_indices as usize, MAX_INDICES);
    assert_eq!(MAX_INDICES, 256, "the limit docs/api.md and the proto state");
    let inv = Code::InvalidArgument;
    let refused = |e: Status, code: Code, needle: &str| {
        assert_eq!(e.code(), code, "{e:?}");
        assert!(e.message().starts_with(needle), "{:?} does not name {needle:?}", e.message());
    };
    let list = |n: usize| pb::SamplesRequest { indices: (0..n as u64).collect(), ..Default::default() };
    refused(get_samples(&mut c, list(MAX_INDICES + 1)).await.unwrap_err(), inv, "indices");
    refused(get_samples(&mut c, list(0)).await.unwrap_err(), inv, "indices");
    let e = get_samples(&mut c, pb::SampleSpec { fields: vec![42], ..Default::default() }.samples(vec![0]))
        .await
        .unwrap_err();
    refused(e, inv, "fields");
    let e = get_samples(&mut c, pb::SampleSpec { fingerprint: 7, ..Default::default() }.samples(vec![0]))
        .await
        .unwrap_err();
    refused(e, Code::FailedPrecondition, "fingerprint");
    // exactly the limit is accepted (the first sample is enough to see it served)
    let mut full = c.get_samples(list(MAX_INDICES)).await.expect("256 indices are accepted").into_inner();
    assert_eq!(full.message().await.unwrap().unwrap().index, 0);
    // ... and it holds the one slot of max_random_access_calls = 1
    let e = get_samples(&mut c, list(1)).await.unwrap_err();
    refused(e, Code::ResourceExhausted, "too many GetSample/GetSamples calls");
    drop(full);
    s.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_crop_larger_than_the_frame_is_refused_with_both_sizes() {
    let s = server(config()).await;
    let mut c = client(&s).await;
    let crop = |w, h| Some(pb::OutputCrop { width: w, height: h, mode: pb::CropMode::Center as i32 });
    for (w, h, asked) in [(65, 48, "65x48"), (64, 49, "64x49"), (0, 60, "64x60")] {
        let e = c.get_sample(pb::SampleSpec { crop: crop(w, h), ..Default::default() }.sample(0)).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
        let m = e.message();
        assert!(m.starts_with("crop: ") && m.contains(asked) && m.contains("64x48"), "{m:?}");
        // a stream and GetSamples end with the same refusal
        let mut st =
            c.stream_samples(pb::SampleSpec { crop: crop(w, h), ..Default::default() }.stream()).await.unwrap();
        let e = st.get_mut().message().await.unwrap_err();
        assert_eq!((e.code(), e.message()), (Code::InvalidArgument, m));
        let r = pb::SampleSpec { crop: crop(w, h), ..Default::default() }.samples(vec![3]);
        let e = get_samples(&mut c, r).await.unwrap_err();
        assert_eq!((e.code(), e.message()), (Code::InvalidArgument, m));
    }
    // the frame's own size is no crop at all: the same bytes as without one
    let full = c.get_sample(pb::SampleRequest { index: 1, ..Default::default() }).await.unwrap().into_inner();
    let same = c.get_sample(pb::SampleSpec { crop: crop(64, 48), ..Default::default() }.sample(1)).await;
    assert_eq!(content(same.unwrap().into_inner()), content(full));
    s.shutdown(Duration::from_secs(5)).await;
}
