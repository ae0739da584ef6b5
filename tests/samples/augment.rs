//! Server-side augmentation (docs/augment.md) on real samples: the photometric-consistency law
//! (image1(p) against image2(p + flow(p)) on valid, non-occluded pixels) holds after the spatial
//! augmentation as well as it held on the unaugmented sample, and breaks when the flow is not
//! transformed with the geometry; and on loopback (an in-process server, port 0): the same address
//! and augment give the same bytes on GetSample, GetSamples and a stream, a crop larger than the
//! rendered frame is accepted when the augmentation brings the frame up to it, and a bad augment is
//! INVALID_ARGUMENT naming the key.

use std::sync::Arc;
use std::time::Duration;

use mpiflow::sample::augment::{apply_plan, Augment, AugmentParams, AugmentPreset};
use mpiflow::sample::config::SampleConfig;
use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::sample::Sample;
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;
use mpiflow::service::client::client_for;
use mpiflow::service::pb;
use mpiflow::service::pb::mpi_flow_client::MpiFlowClient;
use mpiflow::service::{start, RunningServer, ServiceConfig};
use tonic::transport::{Channel, Endpoint};
use tonic::Code;

/// Bilinear sample of an RGB image at (x, y) (inside the frame).
fn at(img: &[u8], w: usize, h: usize, x: f32, y: f32) -> [f32; 3] {
    let (x, y) = (x.clamp(0.0, (w - 1) as f32), y.clamp(0.0, (h - 1) as f32));
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let px = |x: usize, y: usize, c: usize| f32::from(img[3 * (y * w + x) + c]);
    [0, 1, 2].map(|c| {
        let top = px(x0, y0, c) + (px(x1, y0, c) - px(x0, y0, c)) * fx;
        let bottom = px(x0, y1, c) + (px(x1, y1, c) - px(x0, y1, c)) * fx;
        top + (bottom - top) * fy
    })
}

/// Mean |image1(p) - image2(p + flow(p))| over valid, non-occluded pixels, and their count.
fn photometric_error(s: &Sample, flow: &[f32]) -> (f64, usize) {
    let (w, h) = (s.width, s.height);
    let (mut sum, mut n) = (0.0f64, 0usize);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if s.valid[i] == 0 || s.occlusion[i] != 0 {
                continue;
            }
            let q = at(&s.image2, w, h, x as f32 + flow[2 * i], y as f32 + flow[2 * i + 1]);
            for (c, v) in q.iter().enumerate() {
                sum += f64::from((f32::from(s.image1[3 * i + c]) - v).abs()) / 3.0;
            }
            n += 1;
        }
    }
    (sum / n.max(1) as f64, n)
}

fn pipeline(w: usize, h: usize) -> Pipeline {
    let open = OpenOptions { resize: Some((w, h)), ..OpenOptions::default() };
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let source = open_source(&SourceSpec::Builtin, &open).unwrap();
    Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 30)), SampleConfig::default()).unwrap()
}

#[test]
fn photometric_consistency_holds_after_spatial_augmentation() {
    let p = pipeline(160, 120);
    // RAFT's chairs stage without its photometric part (which changes the images on purpose)
    let spatial = AugmentParams {
        brightness: 0.0,
        contrast: 0.0,
        saturation: 0.0,
        hue: 0.0,
        eraser_prob: 0.0,
        ..AugmentPreset::RaftChairs.params()
    };
    let dense = Augment { preset: AugmentPreset::RaftChairs, custom: true, params: spatial }.with_crop((112, 84));
    let sparse = Augment {
        preset: AugmentPreset::RaftKitti,
        custom: true,
        params: AugmentParams {
            eraser_prob: 0.0,
            brightness: 0.0,
            contrast: 0.0,
            saturation: 0.0,
            hue: 0.0,
            ..AugmentPreset::RaftKitti.params()
        },
    }
    .with_crop((140, 60));
    let (mut resized, mut flipped, mut moved_cases, mut wrong_worse) = (0, 0, 0, 0);
    for index in 0..16 {
        let s = p.generator().sample(3, index).unwrap();
        let (base, n0) = photometric_error(&s, &s.flow);
        assert!(n0 > s.width * s.height / 4, "index {index}: {n0} valid pixels");
        for a in [&dense, &sparse] {
            let plan = a.draw(s.address, s.width, s.height);
            let out = apply_plan(&plan, s.clone());
            assert!(out.flow.iter().all(|v| v.is_finite()));
            let (err, n) = photometric_error(&out, &out.flow);
            let what = format!(
                "index {index} {:?} {:?} {:?}: base {base:.2} ({n0} px), augmented {err:.2} ({n} px)",
                a.preset, plan.x, plan.y
            );
            assert!(n > 0, "{what}");
            // (2 levels: the default B-spline image2 keeps more fine detail than bilinear did, and
            // the augmentation's resize of fine detail adds a little photometric error)
            assert!(err <= base * 1.3 + 2.0, "{what}");
            // the law has teeth: the flow left as it was (not scaled, not mirrored) breaks it
            let (kx, ky) = (plan.x.slope() as f32, plan.y.slope() as f32);
            let untransformed: Vec<f32> = out.flow.chunks_exact(2).flat_map(|f| [f[0] / kx, f[1] / ky]).collect();
            let (wrong, _) = photometric_error(&out, &untransformed);
            let moved = (kx.abs() - 1.0).abs() > 0.2 || kx < 0.0 || ky < 0.0;
            if moved {
                moved_cases += 1;
                wrong_worse += usize::from(wrong > err * 1.2 + 0.5);
            }
            resized += usize::from((plan.x.resized, plan.y.resized) != (s.width, s.height));
            flipped += usize::from(plan.x.flip || plan.y.flip);
        }
    }
    assert!(resized >= 8 && flipped >= 3, "the draws exercised resizes ({resized}) and flips ({flipped})");
    // every draw that moves pixels enough, and enough of them
    assert!(moved_cases >= 6, "only {moved_cases} draws moved pixels enough");
    assert_eq!(
        wrong_worse, moved_cases,
        "an untransformed flow broke the law only {wrong_worse} of {moved_cases} times"
    );
}

fn config() -> ServiceConfig {
    ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some("64x48".into()),
        workers: 2,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    }
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn same_address_and_augment_give_the_same_bytes_on_every_path() {
    let s = start(config()).await.expect("server starts");
    let mut c = client(&s).await;
    let fields = vec![1, 2, 3, 4, 5, 6, 8];
    let one = |index: u64, augment: &str| {
        pb::SampleSpec { seed: 7, fields: fields.clone(), augment: augment.into(), ..Default::default() }.sample(index)
    };
    // RAFT's chairs stage: 496x368 crops of a 64x48 render (the frame is brought up to the crop)
    let a = c.get_sample(one(4, "raft-chairs")).await.expect("raft-chairs is served").into_inner();
    let b = c.get_sample(one(4, " raft-chairs ")).await.unwrap().into_inner();
    assert_eq!((a.width, a.height), (496, 368));
    assert_eq!(content(a.clone()), content(b), "same address + augment, same bytes");
    let record: serde_json::Value = serde_json::from_str(&a.augment).expect("the record is JSON");
    assert_eq!(record["preset"], "raft-chairs");
    assert_eq!(record["frame"], serde_json::json!([64, 48]));
    let plain = c.get_sample(one(4, "")).await.unwrap().into_inner();
    assert!(plain.augment.is_empty());
    assert_eq!(plain.fingerprint, a.fingerprint, "augment is not part of the dataset fingerprint");
    assert_eq!(plain.camera, a.camera, "augmentation never changes the sample's own draws");
    // GetSamples and a stream give the same bytes as GetSample
    let json = r#"{"preset": "raft-things", "crop": [96, 72]}"#;
    let mut list = c
        .get_samples(
            pb::SampleSpec { seed: 7, fields: fields.clone(), augment: json.into(), ..Default::default() }
                .samples(vec![5, 2]),
        )
        .await
        .unwrap()
        .into_inner();
    let mut got = vec![];
    while let Some(x) = list.message().await.unwrap() {
        got.push(x);
    }
    let mut st = c
        .stream_samples(pb::StreamRequest {
            start_index: 2,
            count: 4,
            ..pb::SampleSpec { seed: 7, fields: fields.clone(), augment: json.into(), ..Default::default() }.stream()
        })
        .await
        .unwrap()
        .into_inner();
    let mut streamed = vec![];
    while let Some(batch) = st.message().await.unwrap() {
        streamed.extend(batch.samples);
    }
    assert_eq!(streamed.len(), 4);
    for g in &got {
        let direct = c.get_sample(one(g.index, json)).await.unwrap().into_inner();
        assert_eq!((g.width, g.height), (96, 72));
        assert_eq!(content(g.clone()), content(direct.clone()), "GetSamples index {}", g.index);
        let from_stream = streamed.iter().find(|x| x.index == g.index).unwrap();
        assert_eq!(content(from_stream.clone()), content(direct), "stream index {}", g.index);
    }
    assert_ne!(content(got[0].clone()).tensors, content(got[1].clone()).tensors, "indices differ");
    // a request crop of both sides replaces the preset's
    let mut r = one(3, "raft-sintel");
    r.spec.as_mut().unwrap().crop = Some(pb::OutputCrop { width: 80, height: 50, mode: 0 });
    let x = c.get_sample(r).await.unwrap().into_inner();
    assert_eq!((x.width, x.height), (80, 50));
    s.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_augments_and_crops_are_refused_naming_the_field() {
    let s = start(config()).await.expect("server starts");
    let mut c = client(&s).await;
    let req = |augment: &str, crop: Option<(u32, u32)>| {
        pb::SampleSpec {
            seed: 1,
            augment: augment.into(),
            crop: crop.map(|(width, height)| pb::OutputCrop { width, height, mode: 0 }),
            ..Default::default()
        }
        .sample(0)
    };
    for (augment, crop, field) in [
        ("raft-chair", None, "augment"),
        ("{\"crop\": [1]}", None, "augment.crop"),
        ("{\"preset\": \"raft-kitti\", \"hue\": \"x\"}", None, "augment.hue"),
        ("{\"spatial_prob\": 1.5}", None, "augment.spatial_prob"),
        ("{\"zoom\": 2}", None, "augment"),
        ("{not json", None, "augment"),
        ("raft-chairs", Some((100, 0)), "crop"),
        ("{\"crop\": [9000, 10]}", None, "augment.crop"),
        // without augmentation a crop larger than the frame is refused, naming both sizes
        ("", Some((96, 72)), "crop"),
    ] {
        let e = c.get_sample(req(augment, crop)).await.unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{augment} {crop:?}: {e:?}");
        assert!(e.message().starts_with(field), "{augment}: {:?} does not name {field}", e.message());
    }
    let e = c.get_sample(req("", Some((96, 72)))).await.unwrap_err();
    assert!(e.message().contains("96x72") && e.message().contains("64x48"), "{}", e.message());
    // the same crop with an augmentation that brings the frame up to it is served
    let ok = c.get_sample(req("none", Some((96, 72)))).await.expect("augment brings the frame up").into_inner();
    assert_eq!((ok.width, ok.height), (96, 72));
    s.shutdown(Duration::from_secs(5)).await;
}
