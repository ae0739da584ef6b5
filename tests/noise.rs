//! The noise estimate of the quality report (`bench::quality::noise_sigma`, Immerkaer 1996):
//! blind to smooth shading, close to the true level on Gaussian noise, empty regions refused.

use mpiflow::bench::quality::noise_sigma;

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
