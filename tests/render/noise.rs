//! The noise estimate of the quality report (`bench::quality::noise_sigma`, Immerkaer 1996):
//! blind to smooth shading, close to the true level on Gaussian noise, empty regions refused;
//! and `restore_noise`: image2 of an RGB-D photo under lateral motion carries less
//! noise than image1, and with the option as much, deterministically by address, changing
//! nothing but the rendered frames' pixels.

use std::path::Path;
use std::sync::Arc;

use mpiflow::bench::quality::{noise_sigma, quality_same_motions};
use mpiflow::sample::config::{MotionSpec, SampleConfig};
use mpiflow::sample::motion::MotionPreset;
use mpiflow::sample::noise::channel_sigmas;
use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;

const REPO: &str = env!("CARGO_MANIFEST_DIR");

/// A deterministic standard normal stream (splitmix64 + Box-Muller).
fn normals(seed: u64) -> impl FnMut() -> f64 {
    let mut s = seed;
    let mut next = move || {
        s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = s;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    move || {
        let (u1, u2) = (next().max(1e-300), next());
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

fn grey(w: usize, h: usize, f: impl Fn(usize, usize) -> f64) -> Vec<u8> {
    let mut img = Vec::with_capacity(3 * w * h);
    for y in 0..h {
        for x in 0..w {
            let v = f(x, y).round().clamp(0.0, 255.0) as u8;
            img.extend([v, v, v]);
        }
    }
    img
}

#[test]
fn smooth_shading_reads_as_no_noise() {
    let (w, h) = (64, 48);
    // a linear ramp in whole levels: the mask cancels it exactly
    let ramp = grey(w, h, |x, y| (x + 2 * y) as f64);
    let s = noise_sigma(&ramp, w, h, |_| true).unwrap();
    assert!(s < 1e-9, "a ramp reads as noise {s}");
}

#[test]
fn gaussian_noise_is_estimated_within_a_tenth() {
    let (w, h) = (256, 192);
    for (sigma, seed) in [(2.0, 1u64), (5.0, 2), (12.0, 3)] {
        let mut n = normals(seed);
        let noisy: Vec<f64> = (0..w * h).map(|_| 128.0 + sigma * n()).collect();
        let img = grey(w, h, |x, y| noisy[y * w + x]);
        let est = noise_sigma(&img, w, h, |_| true).unwrap();
        // rounding to u8 adds uniform noise of variance 1/12
        let want = (sigma * sigma + 1.0 / 12.0_f64).sqrt();
        assert!((est - want).abs() < 0.1 * want, "sigma {sigma}: estimated {est}, want {want}");
    }
}

#[test]
fn only_the_region_is_read_and_an_empty_one_is_refused() {
    let (w, h) = (64, 64);
    let mut n = normals(7);
    let noisy: Vec<f64> = (0..w * h).map(|_| 128.0 + 8.0 * n()).collect();
    // noisy on the left half, flat on the right half
    let img = grey(w, h, |x, y| if x < w / 2 { noisy[y * w + x] } else { 100.0 });
    let right = noise_sigma(&img, w, h, |i| i % w >= w / 2).unwrap();
    let left = noise_sigma(&img, w, h, |i| i % w < w / 2).unwrap();
    assert_eq!(right, 0.0);
    assert!(left > 6.0, "left half {left}");
    assert!(noise_sigma(&img, w, h, |_| false).is_none());
    assert!(noise_sigma(&img[..3 * 2 * 2], 2, 2, |_| true).is_none());
}

/// The RGB-D photo of `examples/data` (the cat with its depth map) under a pure lateral camera
/// translation of up to 0.05 (flows up to ~10 px), no moving object.
fn lateral_photo(restore_noise: bool) -> (Pipeline, SampleConfig) {
    let ranges = MotionPreset::Reference.ranges().with_lateral_camera(0.05);
    let config = SampleConfig {
        motion: MotionSpec::Ranges(Box::new(ranges)),
        max_objects: 0,
        restore_noise,
        ..SampleConfig::default()
    };
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let spec = SourceSpec::Path(Path::new(REPO).join("examples/data"));
    let source = open_source(&spec, &OpenOptions::default()).unwrap();
    let p = Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 28)), config.clone()).unwrap();
    (p, config)
}

#[test]
fn restored_noise_brings_image2_to_image1s_level() {
    let (p, plain) = lateral_photo(false);
    let restored = SampleConfig { restore_noise: true, ..plain.clone() };
    // the same motions for both (the addresses of the plain configuration)
    let a = quality_same_motions(p.generator(), &plain, 0, 4).unwrap();
    let b = quality_same_motions(p.generator(), &restored, 0, 4).unwrap();
    println!("noise img1 / img2: plain {:.3} / {:.3}, restored {:.3} / {:.3}", a.noise1, a.noise2, b.noise1, b.noise2);
    println!("sharpness: plain {:.3}, restored {:.3}", a.sharpness, b.sharpness);
    assert_eq!(a.noise1, b.noise1, "image1 is untouched");
    assert!(a.noise2 < 0.9 * a.noise1, "the render removes noise: {} of {}", a.noise2, a.noise1);
    assert!((b.noise2 / b.noise1 - 1.0).abs() < 0.08, "restored: {} against {}", b.noise2, b.noise1);
    // the labels do not change, nor does the photometric consistency by more than the noise
    assert_eq!(a.valid_fraction, b.valid_fraction);
    assert_eq!(a.occluded_fraction, b.occluded_fraction);
    assert!(b.photometric < a.photometric + 0.01, "{} -> {}", a.photometric, b.photometric);
}

#[test]
fn restored_noise_is_per_channel_deterministic_and_only_in_the_rendered_frames() {
    let (p, plain) = lateral_photo(false);
    let restored = SampleConfig { restore_noise: true, frames: 3, ..plain.clone() };
    let plain3 = SampleConfig { frames: 3, ..plain.clone() };
    let g = p.generator().with_config(restored.clone()).unwrap();
    let g0 = p.generator().with_config(plain3.clone()).unwrap();
    // the option is part of the fingerprint, and only when set
    assert_ne!(g.fingerprint(), g0.fingerprint());
    let json = serde_json::to_string(&plain).unwrap();
    assert!(!json.contains("restore_noise") && !json.contains("minify"), "{json}");
    // so is the minification option
    let minify = p.generator().with_config(SampleConfig { minify: true, ..plain3.clone() }).unwrap();
    assert_ne!(minify.fingerprint(), g0.fingerprint());
    let s = g.sample(0, 1).unwrap();
    let again = g.sample(0, 1).unwrap();
    assert_eq!(s.image2, again.image2, "the same address gives the same bytes");
    assert_eq!(s.clip[0].image, again.clip[0].image);
    assert_ne!(s.image2, g.sample(0, 2).unwrap().image2);
    // against the plain render of the same motion: only image2 and the later frames' pixels move
    let scene = g.scene(g.source_item(1).unwrap()).unwrap();
    let plain_s = mpiflow::sample::recipe::assemble(&scene, s.address, &plain3).unwrap();
    assert_eq!(s.image1, plain_s.image1);
    assert_eq!(s.flow, plain_s.flow);
    assert_eq!(s.valid, plain_s.valid);
    assert_eq!(s.occlusion, plain_s.occlusion);
    assert_eq!(s.holes, plain_s.holes);
    assert_eq!(s.camera, plain_s.camera);
    let (w, h) = (s.width, s.height);
    let frames = [(&s.image2, &plain_s.image2, &s.holes), (&s.clip[0].image, &plain_s.clip[0].image, &s.clip[0].holes)];
    let want = channel_sigmas(&s.image1, w, h, |_| true).unwrap();
    for (k, (noisy, clean, holes)) in frames.into_iter().enumerate() {
        assert_ne!(noisy, clean, "frame {k} got noise");
        let mean_diff: f64 = noisy.iter().zip(clean.iter()).map(|(&a, &b)| f64::from(a) - f64::from(b)).sum::<f64>()
            / noisy.len() as f64;
        assert!(mean_diff.abs() < 0.05, "frame {k}: zero-mean noise, mean shift {mean_diff}");
        let got = channel_sigmas(noisy, w, h, |i| holes[i] == 0).unwrap();
        let before = channel_sigmas(clean, w, h, |i| holes[i] == 0).unwrap();
        for c in 0..3 {
            assert!(before[c] < want[c], "frame {k} channel {c}: {} >= {}", before[c], want[c]);
            assert!((got[c] / want[c] - 1.0).abs() < 0.08, "frame {k} channel {c}: {} against {}", got[c], want[c]);
        }
    }
}
