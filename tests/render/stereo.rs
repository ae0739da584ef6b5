//! Rectified stereo pairs: the `stereo` motion preset, the disparity field,
//! the `stereo` export layout and the request checks. The laws: the flow's v is exactly 0 and
//! u = -d with d >= 0; an opaque fronto-parallel plane at depth Z has d = fx B / Z (closed form);
//! the right view agrees photometrically with the left view through the disparity, as pairs do
//! through their flow.

use std::sync::Arc;

use mpiflow::bench::quality::photometric_error;
use mpiflow::export::{stereo, ExportFormat, ExportOptions, Exporter};
use mpiflow::geometry::{Intrinsics, Pose};
use mpiflow::io::image::ImageLimits;
use mpiflow::mpi::Mpi;
use mpiflow::render::{render, RenderParams};
use mpiflow::sample::config::{MotionSpec, SampleConfig};
use mpiflow::sample::motion::{Component, MotionPreset, MotionRanges};
use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::sample::Sample;
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;
use mpiflow::service::encode::decode_f32;
use mpiflow::service::pb;
use mpiflow::service::pb::mpi_flow_client::MpiFlowClient;
use mpiflow::service::{start, ServiceConfig};
use mpiflow::source::pfm::parse_pfm;
use tonic::Code;

fn pipeline(config: SampleConfig) -> Pipeline {
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let source =
        open_source(&SourceSpec::Builtin, &OpenOptions { resize: Some((160, 120)), ..OpenOptions::default() }).unwrap();
    Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 28)), config).unwrap()
}

fn stereo_samples(n: u64) -> Vec<Sample> {
    let p = pipeline(SampleConfig::with_preset(MotionPreset::Stereo));
    (0..n).map(|i| p.generator().sample(7, i).unwrap()).collect()
}

/// Every pixel's v is exactly 0, `disparity() = -u`, d >= 0 everywhere, the baseline lies in the
/// stated range, and nothing moved but the camera (the bundled scenes have objects to move).
#[test]
fn stereo_pairs_are_rectified_with_nonnegative_disparity() {
    let (lo, hi) = MotionRanges::STEREO_BASELINE;
    for s in stereo_samples(8) {
        assert!(s.objects.is_empty(), "a stereo pair moves no object");
        let t = s.camera.translation;
        assert!((-hi..=-lo).contains(&t[0]) && t[1] == 0.0 && t[2] == 0.0, "baseline {t:?}");
        assert!(s.camera.angles.iter().all(|&a| a == 0.0));
        assert!(stereo::not_rectified(&s).is_none());
        let d = s.disparity();
        for (i, uv) in s.flow.chunks_exact(2).enumerate() {
            assert_eq!(uv[1].to_bits(), 0.0f32.to_bits(), "pixel {i}: v = {}", uv[1]);
            assert_eq!(d[i], -uv[0]);
            assert!(d[i] >= 0.0 && d[i].is_finite(), "pixel {i}: d = {}", d[i]);
        }
        // disparity grows with nearness: the largest is fx B at the nearest content (depth ~1)
        let valid_max = d.iter().zip(&s.valid).filter(|(_, &v)| v != 0).map(|(&d, _)| d).fold(0.0f32, f32::max);
        let bound = s.intrinsics.fx * -t[0] / s.depth1.iter().copied().fold(f32::INFINITY, f32::min) as f64;
        assert!(f64::from(valid_max) <= bound * 1.001 + 1e-3, "largest disparity {valid_max} > fx B / Z_min {bound}");
        assert!(valid_max > 0.0);
    }
}

/// An opaque fronto-parallel plane at depth Z seen from a camera moved by the baseline B:
/// d = fx B / Z at every pixel whose target stays in the frame, v = 0 exactly, for several depths,
/// baselines and focal lengths.
#[test]
fn an_opaque_plane_has_the_closed_form_disparity() {
    let (w, h) = (96, 64);
    for (z, b, fx) in [(1.0, 0.1, 55.0), (2.5, 0.2, 80.0), (7.0, 0.05, 120.0), (1.3, 0.02, 40.0)] {
        let mut mpi = Mpi::new(w, h, vec![1.0 / z], 0);
        for px in mpi.plane_rgba_mut(0).chunks_exact_mut(4) {
            px.copy_from_slice(&[0.5, 0.4, 0.3, 1e4]);
        }
        let k = Intrinsics::new(fx, fx, w as f64 / 2.0, h as f64 / 2.0);
        let pose = Pose::from_axis_angle([0.0; 3], [-b, 0.0, 0.0]);
        let out = render::<f32>(&mpi, &RenderParams::new(k, pose), None).unwrap();
        let want = fx * b / z;
        let mut checked = 0;
        for i in 0..w * h {
            if out.valid[i] == 0 {
                continue;
            }
            let (u, v) = (out.flow[2 * i], out.flow[2 * i + 1]);
            assert_eq!(v, 0.0, "z {z} b {b}: v at pixel {i}");
            assert!((f64::from(-u) - want).abs() <= want * 1e-5 + 1e-5, "z {z} b {b}: d = {} want {want}", -u);
            checked += 1;
        }
        // the pixels whose target x - d falls left of the frame are the invalid ones
        let invalid_cols = (want - 0.5).ceil().max(0.0) as usize;
        assert!(checked >= (w - invalid_cols - 1) * h, "z {z}: {checked} valid pixels");
    }
}

/// The right view agrees with the left view through the disparity on valid, non-occluded pixels
/// as well as pairs of the default motion law agree through their flow.
#[test]
fn stereo_pairs_pass_the_photometric_check() {
    let mean = |samples: &[Sample]| {
        let (mut sum, mut n) = (0.0, 0u64);
        for s in samples {
            let (a, b) = photometric_error(s, None);
            sum += a;
            n += b;
        }
        sum / n as f64
    };
    let stereo = mean(&stereo_samples(6));
    let p = pipeline(SampleConfig { max_objects: 0, ..SampleConfig::default() });
    let pairs: Vec<Sample> = (0..6).map(|i| p.generator().sample(7, i).unwrap()).collect();
    let reference = mean(&pairs);
    eprintln!("photometric error: stereo {stereo:.4}, reference pairs without objects {reference:.4}");
    assert!(stereo < 0.02, "stereo photometric error {stereo}");
    assert!(stereo <= reference * 1.25, "stereo {stereo} vs reference pairs {reference}");
}

/// Stereo laws are held to a rectified form; a custom baseline law is accepted.
#[test]
fn stereo_laws_refuse_anything_but_a_baseline() {
    let mut r = MotionPreset::Stereo.ranges();
    r.validate().unwrap();
    assert_eq!("stereo".parse::<MotionPreset>().unwrap(), MotionPreset::Stereo);
    r.camera.translation.x = Component::Uniform { lo: -0.5, hi: -0.3 };
    r.validate().unwrap();
    let json = serde_json::to_string(&r).unwrap();
    assert!(json.contains("\"stereo\":true"), "{json}");
    assert_eq!(serde_json::from_str::<MotionRanges>(&json).unwrap(), r);
    // other presets keep their JSON (and so their fingerprints): no `stereo` key
    assert!(!serde_json::to_string(&MotionPreset::Reference.ranges()).unwrap().contains("stereo"));
    type Change = fn(&mut MotionRanges);
    let cases: [(&str, Change); 4] = [
        ("camera.translation.x", |r| r.camera.translation.x = Component::Uniform { lo: -0.1, hi: 0.1 }),
        ("camera.translation.y", |r| r.camera.translation.y = Component::constant(0.01)),
        ("camera.translation.z", |r| r.camera.translation.z = Component::Forward { min: 0.1, max: 0.2 }),
        ("camera.rotation.y", |r| r.camera.rotation.y = Component::symmetric(0.01)),
    ];
    for (field, change) in cases {
        let mut bad = MotionPreset::Stereo.ranges();
        change(&mut bad);
        let e = bad.validate().unwrap_err().to_string();
        assert!(e.contains(field), "{field}: {e}");
    }
}

/// `--format stereo` writes the SceneFlow-style folders; the disparity PFM reads back (bottom-up
/// rows, little-endian) as the sample's disparity; a pair that is not rectified is refused.
#[test]
fn the_stereo_layout_round_trips_and_refuses_other_pairs() {
    let dir = std::env::temp_dir().join(format!("mpiflow-stereo-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let samples = stereo_samples(2);
    let mut ex = Exporter::create(ExportOptions::new(ExportFormat::Stereo, &dir)).unwrap();
    for (i, s) in samples.iter().enumerate() {
        ex.write(i as u64, s).unwrap();
    }
    assert_eq!(ex.finish().unwrap().samples, 2);
    for (i, s) in samples.iter().enumerate() {
        let key = format!("{i:08}");
        let pfm = parse_pfm(&std::fs::read(dir.join(format!("disparity/{key}.pfm"))).unwrap(), &ImageLimits::default())
            .unwrap();
        assert_eq!((pfm.width, pfm.height, pfm.channels), (s.width, s.height, 1));
        assert_eq!(pfm.data, s.disparity());
        let left = image::open(dir.join(format!("left/{key}.png"))).unwrap().to_rgb8();
        let right = image::open(dir.join(format!("right/{key}.png"))).unwrap().to_rgb8();
        assert_eq!(left.as_raw(), &s.image1);
        assert_eq!(right.as_raw(), &s.image2);
        let valid = image::open(dir.join(format!("valid/{key}.png"))).unwrap().to_luma8();
        let want: Vec<u8> = s.valid.iter().map(|&v| if v != 0 { 255 } else { 0 }).collect();
        assert_eq!(valid.as_raw(), &want);
        for f in ["occlusion", "holes"] {
            assert!(dir.join(format!("{f}/{key}.png")).is_file(), "{f}");
        }
        let record: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join(format!("records/{key}.json"))).unwrap()).unwrap();
        assert_eq!(record["flow_encoding"], "pfm-disparity");
    }
    // a pair of the reference law is not rectified
    let p = pipeline(SampleConfig::default());
    let pair = p.generator().sample(7, 0).unwrap();
    let mut ex = Exporter::create(ExportOptions::new(ExportFormat::Stereo, &dir)).unwrap();
    let e = ex.write(5, &pair).unwrap_err().to_string();
    assert!(e.contains("not a rectified stereo pair"), "{e}");
    assert!(!dir.join("left/00000005.png").exists());
    std::fs::remove_dir_all(dir).unwrap();
}

/// Over gRPC: `motion_preset = "stereo"` with FIELD_DISPARITY gives a disparity tensor equal to
/// -u of the flow tensor; the disparity of a non-stereo law and a stereo pair with a horizontal
/// flip are refused, naming the field; a custom stereo law goes through `motion_ranges_json`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stereo_over_grpc() {
    let config = ServiceConfig {
        addr: "127.0.0.1:0".into(),
        size: Some("64x48".into()),
        workers: 2,
        log_level: "warn".into(),
        ..ServiceConfig::default()
    };
    let server = start(config).await.expect("server starts");
    let mut c = MpiFlowClient::connect(format!("http://{}", server.addr)).await.unwrap();
    let fields = vec![pb::Field::Flow as i32, pb::Field::Valid as i32, pb::Field::Disparity as i32];
    let spec =
        |preset: &str| pb::SampleSpec { fields: fields.clone(), motion_preset: preset.into(), ..Default::default() };
    let req = |preset: &str| spec(preset).sample(3);
    let s = c.get_sample(req("stereo")).await.unwrap().into_inner();
    let names: Vec<&str> = s.tensors.iter().map(|t| t.name.as_str()).collect();
    assert_eq!(names, ["flow", "valid", "disparity"]);
    assert_eq!(s.tensors[2].shape, [48, 64]);
    let (flow, disp) = (decode_f32(&s.tensors[0]).unwrap(), decode_f32(&s.tensors[2]).unwrap());
    for (uv, d) in flow.chunks_exact(2).zip(&disp) {
        assert_eq!((uv[1], *d), (0.0, -uv[0]));
    }
    assert!(s.objects.is_empty());
    assert_eq!(s.camera.as_ref().unwrap().law, "stereo");

    let e = c.get_sample(req("reference")).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().starts_with("fields") && e.message().contains("stereo"), "{}", e.message());
    let flipped = pb::SampleSpec { augment: "raft-chairs".into(), ..spec("stereo") }.sample(3);
    let e = c.get_sample(flipped).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().starts_with("augment.h_flip_prob"), "{}", e.message());

    let mut wide = MotionPreset::Stereo.ranges();
    wide.name = "wide-baseline".into();
    wide.camera.translation.x = Component::constant(-0.4);
    let custom = pb::SampleSpec { motion_ranges_json: serde_json::to_string(&wide).unwrap(), ..spec("") }.sample(3);
    let s = c.get_sample(custom).await.unwrap().into_inner();
    assert_eq!(s.camera.as_ref().unwrap().translation, [-0.4, 0.0, 0.0]);
    let not_stereo = MotionSpec::Ranges(Box::new(MotionPreset::Reference.ranges()));
    assert!(!not_stereo.ranges().stereo);
    server.shutdown(std::time::Duration::from_secs(5)).await;
}
