//! Backward flow and clips: laws on real samples of the bundled scenes.
//!
//! - forward-backward consistency: |flow(p) + flow_backward(p + flow(p))| (bilinear lookup) on
//!   valid, non-occluded pixels, per scene, without and with moving objects;
//! - asking for the backward fields changes no other byte of a sample, and a pair's address
//!   (fingerprint) is the one it had before clips existed;
//! - clips: the first pair of a clip is the pair; flows compose (1 -> 2 then 2 -> 3 equals the
//!   direct 1 -> 3 render on pixels visible in all three); every consecutive pair passes the
//!   photometric check as pairs do; same address, same clip on any thread count.

use std::sync::Arc;

use mpiflow::bench::quality::photometric_error;
use mpiflow::render::{render, RenderParams};
use mpiflow::sample::config::SampleConfig;
use mpiflow::sample::motion::MotionPreset;
use mpiflow::sample::pipeline::{dataset_fingerprint, open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::sample::recipe::{assemble, trajectory};
use mpiflow::sample::{Sample, SampleAddress};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;

const SIZE: (usize, usize) = (192, 144);

fn pipeline() -> Pipeline {
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let source =
        open_source(&SourceSpec::Builtin, &OpenOptions { resize: Some(SIZE), ..OpenOptions::default() }).unwrap();
    Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 28)), SampleConfig::default()).unwrap()
}

fn bilinear2(f: &[f32], w: usize, h: usize, x: f32, y: f32) -> [f32; 2] {
    let x = x.clamp(0.0, (w - 1) as f32);
    let y = y.clamp(0.0, (h - 1) as f32);
    let (x0, y0) = (x as usize, y as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = |xx: usize, yy: usize, c: usize| f[2 * (yy * w + xx) + c];
    [0, 1].map(|c| {
        let top = at(x0, y0, c) * (1.0 - fx) + at(x1, y0, c) * fx;
        let bot = at(x0, y1, c) * (1.0 - fx) + at(x1, y1, c) * fx;
        top * (1.0 - fy) + bot * fy
    })
}

/// The nearest pixel of (x, y), if inside.
fn nearest(w: usize, h: usize, x: f32, y: f32) -> Option<usize> {
    let (xr, yr) = (x.round(), y.round());
    (xr >= 0.0 && yr >= 0.0 && (xr as usize) < w && (yr as usize) < h).then(|| yr as usize * w + xr as usize)
}

/// Mean and 99th percentile of |F(p) + B(p + F(p))| over the valid, non-occluded pixels of the
/// forward flow F whose target's nearest pixel has a valid, non-occluded backward flow B.
fn fb_errors(s: &Sample) -> (f64, f64, usize) {
    let (w, h) = (s.width, s.height);
    let (f, valid, occ) = (&s.flow, &s.valid, &s.occlusion);
    let (b, bvalid, bocc) = (&s.backward.flow, &s.backward.valid, &s.backward.occlusion);
    let mut e: Vec<f64> = Vec::new();
    for i in 0..w * h {
        if valid[i] == 0 || occ[i] != 0 {
            continue;
        }
        let (tx, ty) = ((i % w) as f32 + f[2 * i], (i / w) as f32 + f[2 * i + 1]);
        let Some(j) = nearest(w, h, tx, ty) else { continue };
        if bvalid[j] == 0 || bocc[j] != 0 {
            continue;
        }
        let bb = bilinear2(b, w, h, tx, ty);
        e.push(f64::from((f[2 * i] + bb[0]).hypot(f[2 * i + 1] + bb[1])));
    }
    assert!(!e.is_empty(), "no pixel to check");
    e.sort_by(f64::total_cmp);
    let mean = e.iter().sum::<f64>() / e.len() as f64;
    let p99 = e[(e.len() * 99 / 100).min(e.len() - 1)];
    (mean, p99, e.len())
}

fn backward_config(preset: MotionPreset, objects: usize) -> SampleConfig {
    SampleConfig { max_objects: objects, backward: true, ..SampleConfig::with_preset(preset) }
}

fn check_finite(s: &Sample) {
    assert!(s.backward.flow.iter().all(|v| v.is_finite()));
    for c in &s.clip {
        assert!(c.forward.flow.iter().chain(&c.backward.flow).all(|v| v.is_finite()));
    }
}

#[test]
fn forward_backward_consistency_per_scene() {
    let p = pipeline();
    let (w, h) = SIZE;
    let scenes = p.source().len() as u64;
    // (sum of errors, pixels) over every scene without objects
    let (mut sum_static, mut n_static) = (0.0f64, 0usize);
    for objects in [0usize, 1] {
        let g = p.generator().with_config(backward_config(MotionPreset::Reference, objects)).unwrap();
        for index in 0..scenes {
            let s = g.sample(3, index).unwrap();
            check_finite(&s);
            let b = &s.backward;
            assert_eq!((b.flow.len(), b.valid.len(), b.occlusion.len()), (2 * w * h, w * h, w * h));
            // holes are never valid backward; valid pixels land inside image1
            for i in 0..w * h {
                if s.holes[i] != 0 {
                    assert_eq!(b.valid[i], 0, "a hole is valid at {i}");
                }
                if b.valid[i] != 0 {
                    let (tx, ty) = ((i % w) as f32 + b.flow[2 * i], (i / w) as f32 + b.flow[2 * i + 1]);
                    assert!(tx >= 0.0 && ty >= 0.0 && tx <= (w - 1) as f32 && ty <= (h - 1) as f32);
                }
            }
            let (mean, p99, n) = fb_errors(&s);
            println!(
                "forward-backward {}, {} object(s) moved: mean {mean:.4} px, p99 {p99:.4} px over {n} pixels",
                s.source_id,
                s.objects.len()
            );
            // the soft depth edges of the layering are blended along different rays by the
            // forward (source rays) and the backward (target rays) flow: a scene with many such
            // edges errs more; every scene stays well under 0.1 px on average
            assert!(mean < 0.1, "{}: {} object(s), mean {mean} px", s.source_id, s.objects.len());
            if objects == 0 {
                sum_static += mean * n as f64;
                n_static += n;
            }
        }
    }
    let mean = sum_static / n_static as f64;
    println!("forward-backward without objects, all scenes: mean {mean:.4} px over {n_static} pixels");
    assert!(mean <= 0.05, "mean forward-backward error {mean} px without objects");
}

#[test]
fn backward_fields_change_nothing_else_and_pairs_keep_their_address() {
    let p = pipeline();
    let plain = p.generator().with_config(SampleConfig::default()).unwrap();
    let with_bw = p.generator().with_config(SampleConfig { backward: true, ..SampleConfig::default() }).unwrap();
    assert_eq!(plain.fingerprint(), with_bw.fingerprint());
    for index in 0..3 {
        let a = plain.sample(1, index).unwrap();
        let mut b = with_bw.sample(1, index).unwrap();
        assert!(a.backward.flow.is_empty() && a.clip.is_empty());
        assert!(!b.backward.flow.is_empty());
        b.backward = Default::default();
        b.timings = a.timings;
        assert_eq!(a, b, "index {index}");
    }
    // the default configuration's JSON (the fingerprint's input) has no clip or backward key:
    // pairs keep the fingerprint they had before clips; other frame counts change it
    let json = serde_json::to_string(&SampleConfig::default()).unwrap();
    assert!(!json.contains("frames") && !json.contains("backward"), "{json}");
    let fp = |c: &SampleConfig| dataset_fingerprint(42, c);
    let two = SampleConfig { frames: 2, ..SampleConfig::default() };
    assert_eq!(fp(&two), fp(&SampleConfig::default()));
    let three = SampleConfig { frames: 3, ..SampleConfig::default() };
    assert_ne!(fp(&three), fp(&SampleConfig::default()));
    for bad in [0usize, 1, 9] {
        let e = SampleConfig { frames: bad, ..SampleConfig::default() }.validate().unwrap_err();
        assert!(e.to_string().contains("frames"), "{e}");
    }
}

#[test]
fn a_clips_first_pair_is_the_pair() {
    let p = pipeline();
    let g = p.generator();
    let scene = g.scene(0).unwrap();
    let address = SampleAddress { dataset: g.fingerprint(), seed: 5, index: 0 };
    for objects in [0usize, 1] {
        let pair_cfg = SampleConfig { max_objects: objects, backward: true, ..SampleConfig::default() };
        let clip_cfg = SampleConfig { frames: 4, ..pair_cfg.clone() };
        let pair = assemble(&scene, address, &pair_cfg).unwrap();
        let mut clip = assemble(&scene, address, &clip_cfg).unwrap();
        assert_eq!(clip.clip.len(), 2);
        clip.clip.clear();
        clip.timings = pair.timings;
        assert_eq!(pair, clip, "{objects} object(s)");
    }
}

/// Frames 1 -> 2 -> 3 compose to the direct 1 -> 3 correspondence (rendered for this test from
/// the source view under pose^2) on pixels visible in all three; each consecutive pair passes
/// the photometric check about as well as the first pair.
#[test]
fn clip_flows_compose_and_pairs_are_photometrically_consistent() {
    let p = pipeline();
    let (w, h) = SIZE;
    let cfg = SampleConfig { frames: 4, max_objects: 0, backward: true, ..SampleConfig::default() };
    let g = p.generator().with_config(cfg).unwrap();
    for index in [0u64, 2, 4] {
        let s = g.sample(9, index).unwrap();
        assert_eq!(s.clip.len(), 2);
        check_finite(&s);
        let scene = g.scene(g.source_item(index).unwrap()).unwrap();
        let traj = trajectory(&s.camera.to_pose(), 4);
        let direct = render::<f32>(&scene.mpi, &RenderParams::new(scene.intrinsics, traj[2]), None).unwrap();
        let (f12, f23) = (&s.flow, &s.clip[0].forward);
        let mut e = Vec::new();
        for i in 0..w * h {
            if s.valid[i] == 0 || s.occlusion[i] != 0 || direct.valid[i] == 0 || direct.occlusion[i] != 0 {
                continue;
            }
            let (x2, y2) = ((i % w) as f32 + f12[2 * i], (i / w) as f32 + f12[2 * i + 1]);
            let Some(j) = nearest(w, h, x2, y2) else { continue };
            if f23.valid[j] == 0 || f23.occlusion[j] != 0 {
                continue;
            }
            let g23 = bilinear2(&f23.flow, w, h, x2, y2);
            let du = f12[2 * i] + g23[0] - direct.flow[2 * i];
            let dv = f12[2 * i + 1] + g23[1] - direct.flow[2 * i + 1];
            e.push(f64::from(du.hypot(dv)));
        }
        assert!(e.len() > w * h / 4, "too few pixels visible in all three frames: {}", e.len());
        e.sort_by(f64::total_cmp);
        let mean = e.iter().sum::<f64>() / e.len() as f64;
        let p99 = e[e.len() * 99 / 100];
        println!("composition {}: mean {mean:.4} px, p99 {p99:.4} px over {} pixels", s.source_id, e.len());
        assert!(mean < 0.05, "1->2->3 differs from 1->3 by {mean} px on average");

        // the photometric check of each consecutive pair, as bench quality does it for pairs
        let (e12, n12) = photometric_error(&s, None);
        let m12 = e12 / n12 as f64;
        let frames: Vec<&[u8]> = [s.image1.as_slice(), s.image2.as_slice()]
            .into_iter()
            .chain(s.clip.iter().map(|c| c.image.as_slice()))
            .collect();
        for (k, c) in s.clip.iter().enumerate() {
            let pair = Sample {
                image1: frames[k + 1].to_vec(),
                image2: frames[k + 2].to_vec(),
                flow: c.forward.flow.clone(),
                valid: c.forward.valid.clone(),
                occlusion: c.forward.occlusion.clone(),
                ..s.clone()
            };
            let (ek, nk) = photometric_error(&pair, None);
            assert!(nk as usize > w * h / 4, "pair {}: only {nk} valid pixels", k + 2);
            let mk = ek / nk as f64;
            println!("photometric {} pair {}->{}: {mk:.4} (pair 1->2: {m12:.4})", s.source_id, k + 2, k + 3);
            assert!(mk < 0.05 && mk < 2.0 * m12 + 0.01, "pair {}: {mk} vs {m12}", k + 2);
        }
    }
}

#[test]
fn clips_are_deterministic_on_any_thread_count() {
    let p = pipeline();
    let cfg = SampleConfig { frames: 3, backward: true, ..SampleConfig::default() };
    let g = p.generator().with_config(cfg).unwrap();
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let a = one.install(|| g.sample(2, 1).unwrap());
    let mut b = g.sample(2, 1).unwrap();
    b.timings = a.timings;
    assert_eq!(a, b);
    assert_eq!(a.clip.len(), 1);
}
