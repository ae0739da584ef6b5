//! Sensor noise: Immerkaer's estimate of an image's noise level, and the option that restores
//! image1's level in the rendered frames (`restore_noise`). Resampling the planes
//! low-passes image2, so it carries less of the photo's sensor noise than image1 ("frame 2 is the
//! clean one" is a cue a flow network can learn); with the option each later frame gets zero-mean
//! noise, per colour channel, of the standard deviation that brings the frame's estimate over its
//! rendered (not inpainted) pixels to image1's estimate over the whole frame.
//!
//! Determinism: the noise of pixel `i`, channel `c` of frame `f` is a function of the sample's
//! key word (one word of the stream `Purpose::Other(NOISE_PURPOSE)`), `f` and `3 i + c` only:
//! the sum of the four 16-bit quarters of `mix64(key ^ f K1 ^ (3 i + c + 1) K2)` (Irwin-Hall of
//! four uniforms: mean 0, unit variance after scaling, within ±3.47), times `sigma_add`, added in
//! f32 and rounded to the nearest level. Integer hashing, one IEEE multiply-add per value and
//! `sqrt` (correctly rounded): the same bytes on every machine and thread count.

use rayon::prelude::*;

use crate::rng::{mix64, Purpose, SampleRng};

use super::types::SampleAddress;

/// The purpose number of the noise stream (`Purpose::Other(NOISE_PURPOSE)`): "nois".
pub const NOISE_PURPOSE: u32 = 0x6e6f_6973;

/// Immerkaer's mask `[1 -2 1; -2 4 -2; 1 -2 1]`, row-major (the difference of two Laplacians:
/// zero on every polynomial of degree two).
const MASK: [f64; 9] = [1.0, -2.0, 1.0, -2.0, 4.0, -2.0, 1.0, -2.0, 1.0];

/// Rec. 601 luminance weights.
const LUMA: [f64; 3] = [0.299, 0.587, 0.114];

/// Immerkaer's fast noise estimate ("Fast Noise Variance Estimation", CVIU 1996): the standard
/// deviation, in 8-bit levels, of white Gaussian noise on a weighted sum of the channels
/// (`weights`) of an interleaved u8 RGB image, from `sqrt(pi / 2) / 6` times the mean absolute
/// response to the mask `[1 -2 1; -2 4 -2; 1 -2 1]` (the difference of two Laplacians, which
/// cancels every polynomial of degree two, so smooth shading adds nothing), over the interior
/// pixels whose 3x3 neighbourhood satisfies `inside`. Edges and fine texture add to it as the
/// estimator's known bias, the same on both images of a pair; `None` when fewer than 16 pixels
/// qualify. Rows are summed in parallel and added in row order (the same result on any thread
/// count).
pub fn noise_sigma_weighted(
    img: &[u8],
    w: usize,
    h: usize,
    weights: [f64; 3],
    inside: impl Fn(usize) -> bool + Sync,
) -> Option<f64> {
    if w < 3 || h < 3 || img.len() < 3 * w * h {
        return None;
    }
    let val = |i: usize| {
        weights[0] * f64::from(img[3 * i])
            + weights[1] * f64::from(img[3 * i + 1])
            + weights[2] * f64::from(img[3 * i + 2])
    };
    let rows: Vec<(u64, f64)> = (1..h - 1)
        .into_par_iter()
        .map(|y| {
            let (mut n, mut sum) = (0u64, 0.0f64);
            for x in 1..w - 1 {
                let at = |k: usize| (y + k / 3 - 1) * w + x + k % 3 - 1;
                if !(0..9).all(|k| inside(at(k))) {
                    continue;
                }
                let r: f64 = (0..9).map(|k| MASK[k] * val(at(k))).sum();
                n += 1;
                sum += r.abs();
            }
            (n, sum)
        })
        .collect();
    let (n, sum) = rows.iter().fold((0u64, 0.0f64), |(n, s), &(rn, rs)| (n + rn, s + rs));
    (n >= 16).then(|| std::f64::consts::FRAC_PI_2.sqrt() * sum / (6.0 * n as f64))
}

/// [`noise_sigma_weighted`] of the Rec. 601 luminance (the quality report's noise figure).
pub fn noise_sigma(img: &[u8], w: usize, h: usize, inside: impl Fn(usize) -> bool + Sync) -> Option<f64> {
    noise_sigma_weighted(img, w, h, LUMA, inside)
}

/// The noise level of each colour channel ([`noise_sigma_weighted`] with a unit weight).
pub fn channel_sigmas(
    img: &[u8],
    w: usize,
    h: usize,
    inside: impl Fn(usize) -> bool + Sync + Copy,
) -> Option<[f64; 3]> {
    let mut out = [0.0; 3];
    for (c, o) in out.iter_mut().enumerate() {
        let mut wt = [0.0; 3];
        wt[c] = 1.0;
        *o = noise_sigma_weighted(img, w, h, wt, inside)?;
    }
    Some(out)
}

/// 1 / the standard deviation of a sum of four independent uniform integers in 0..65536.
const IRWIN_HALL_SCALE: f32 = 1.0 / 37_837.23;
const FRAME_MIX: u64 = 0xd1b5_4a32_d192_ed03;
const VALUE_MIX: u64 = 0x9e37_79b9_7f4a_7c15;

/// Zero-mean, unit-variance noise of value `v` (pixel `i`, channel `c` at `v = 3 i + c`) of frame
/// `frame` under `key` (see the module documentation).
#[inline]
pub fn unit_noise(key: u64, frame: u64, v: u64) -> f32 {
    let z = mix64(key ^ frame.wrapping_mul(FRAME_MIX) ^ (v + 1).wrapping_mul(VALUE_MIX));
    let s = (z & 0xffff) + ((z >> 16) & 0xffff) + ((z >> 32) & 0xffff) + (z >> 48);
    (s as f32 - 131_070.0) * IRWIN_HALL_SCALE
}

/// The key word of a sample's noise (the first word of its noise stream).
pub fn noise_key(address: SampleAddress) -> u64 {
    SampleRng::new(address.dataset, address.seed, address.index, Purpose::Other(NOISE_PURPOSE)).next_word()
}

/// The share `rho` (0..1) of image1's noise that its three channels have in common, from its
/// channel levels `s` and luminance level `l` under the equicorrelation model
/// `n_c = s_c (sqrt(rho) g + sqrt(1 - rho) e_c)` (g shared, e_c per channel, all independent
/// and of unit variance): `l^2 = (1 - rho) sum w_c^2 s_c^2 + rho (sum w_c s_c)^2`, `w` the
/// luminance weights; clamped to [0, 1] (estimates are not exact).
pub fn shared_fraction(s: [f64; 3], l: f64) -> f64 {
    let a: f64 = (0..3).map(|c| LUMA[c] * LUMA[c] * s[c] * s[c]).sum();
    let b: f64 = (0..3).map(|c| LUMA[c] * s[c]).sum::<f64>().powi(2);
    if b - a <= f64::EPSILON * b.max(1.0) {
        return 0.0;
    }
    ((l * l - a) / (b - a)).clamp(0.0, 1.0)
}

/// Zero-mean, unit-variance noise for every value of an interleaved RGB frame of `pixels`
/// pixels: `sqrt(rho) g_i + sqrt(1 - rho) e_{3i+c}`, with `e_v` = [`unit_noise`]`(key, frame, v)`
/// and the shared `g_i` = [`unit_noise`]`(key, frame, 3 pixels + i)`.
pub fn noise_field(key: u64, frame: u64, pixels: usize, rho: f64) -> Vec<f32> {
    const CHUNK: usize = 4096;
    let (a, b) = (rho.clamp(0.0, 1.0).sqrt() as f32, (1.0 - rho.clamp(0.0, 1.0)).sqrt() as f32);
    let mut out = vec![0.0f32; 3 * pixels];
    out.par_chunks_mut(3 * CHUNK).enumerate().for_each(|(k, chunk)| {
        for (j, px) in chunk.chunks_exact_mut(3).enumerate() {
            let i = (k * CHUNK + j) as u64;
            let g = unit_noise(key, frame, 3 * pixels as u64 + i);
            for (c, o) in px.iter_mut().enumerate() {
                *o = a * g + b * unit_noise(key, frame, 3 * i + c as u64);
            }
        }
    });
    out
}

/// The mask responses ([`noise_sigma_weighted`]'s mask) of channel `c` of `img` and of the same
/// channel of `noise` (both interleaved RGB), at the interior pixels with even `x` and `y` whose
/// 3x3 neighbourhood satisfies `inside` (a quarter of the pixels: enough for the level), in
/// row order.
fn paired_responses(
    img: &[u8],
    noise: &[f32],
    w: usize,
    h: usize,
    c: usize,
    inside: impl Fn(usize) -> bool + Sync,
) -> (Vec<f32>, Vec<f32>) {
    let m = MASK.map(|v| v as f32);
    let rows: Vec<(Vec<f32>, Vec<f32>)> = (1..h.saturating_sub(1))
        .into_par_iter()
        .filter(|y| y % 2 == 0)
        .map(|y| {
            let (mut r, mut n) = (Vec::new(), Vec::new());
            for x in (2..w.saturating_sub(1)).step_by(2) {
                let at = |k: usize| (y + k / 3 - 1) * w + x + k % 3 - 1;
                if !(0..9).all(|k| inside(at(k))) {
                    continue;
                }
                r.push((0..9).map(|k| m[k] * f32::from(img[3 * at(k) + c])).sum());
                n.push((0..9).map(|k| m[k] * noise[3 * at(k) + c]).sum());
            }
            (r, n)
        })
        .collect();
    let mut r = Vec::new();
    let mut n = Vec::new();
    for (a, b) in rows {
        r.extend(a);
        n.extend(b);
    }
    (r, n)
}

/// The standard deviation `s >= 0` of the noise to add so that the frame's estimate
/// ([`noise_sigma_weighted`]: `sqrt(pi / 2) / 6` times the mean absolute response) reads `want`,
/// 0 when it already reads `want` or more. `mean |r + s n|` is convex in `s`, so Newton's method
/// from a point above the root descends to it monotonically (a few steps). Solved on the
/// estimator itself, not in quadrature, because its texture bias does not add in quadrature (the
/// render also blurs texture that the estimator reads).
fn solve_sigma(r: &[f32], n: &[f32], want: f64) -> f64 {
    if r.is_empty() {
        return 0.0;
    }
    let k = std::f64::consts::FRAC_PI_2.sqrt() / 6.0;
    let len = r.len() as f64;
    // the estimate at s and its derivative in s
    let read = |s: f64| {
        let sf = s as f32;
        let (mut v, mut d) = (0.0f64, 0.0f64);
        for (&a, &b) in r.iter().zip(n) {
            let x = a + sf * b;
            v += f64::from(x.abs());
            d += f64::from(if x < 0.0 { -b } else { b });
        }
        (k * v / len, k * d / len)
    };
    let (at0, _) = read(0.0);
    if at0 >= want {
        return 0.0;
    }
    // above the root: the estimate of noise alone at s is about s
    let mut s = (want * want - at0 * at0).sqrt().max(want * 0.25).max(1e-3) * 1.5;
    for _ in 0..12 {
        if read(s).0 >= want {
            break;
        }
        s *= 2.0;
    }
    for _ in 0..8 {
        let (v, d) = read(s);
        if d <= 0.0 || v - want <= 1e-4 * want {
            break;
        }
        s = (s - (v - want) / d).max(0.0);
    }
    s
}

/// The noise levels ([`noise_sigma_weighted`], every pixel inside) of the three channels and the
/// luminance of an interleaved RGB image, read at the interior pixels with even `x` and `y` (the
/// grid [`restore_noise`] solves on), in one pass.
fn grid_levels(img: &[u8], w: usize, h: usize) -> Option<([f64; 3], f64)> {
    let rows: Vec<(u64, [f64; 4])> = (1..h.saturating_sub(1))
        .into_par_iter()
        .filter(|y| y % 2 == 0)
        .map(|y| {
            let (mut n, mut sum) = (0u64, [0.0f64; 4]);
            for x in (2..w.saturating_sub(1)).step_by(2) {
                let mut r = [0.0f64; 3];
                for (k, m) in MASK.iter().enumerate() {
                    let o = 3 * ((y + k / 3 - 1) * w + x + k % 3 - 1);
                    for c in 0..3 {
                        r[c] += m * f64::from(img[o + c]);
                    }
                }
                n += 1;
                for c in 0..3 {
                    sum[c] += r[c].abs();
                }
                sum[3] += (LUMA[0] * r[0] + LUMA[1] * r[1] + LUMA[2] * r[2]).abs();
            }
            (n, sum)
        })
        .collect();
    let (mut n, mut sum) = (0u64, [0.0f64; 4]);
    for (rn, rs) in rows {
        n += rn;
        for c in 0..4 {
            sum[c] += rs[c];
        }
    }
    let k = std::f64::consts::FRAC_PI_2.sqrt() / (6.0 * n as f64);
    (n >= 16).then(|| ([sum[0] * k, sum[1] * k, sum[2] * k], sum[3] * k))
}

/// What the later frames of a sample are brought to: image1's noise level per channel (every
/// pixel, read on the quarter grid) and the share of it its channels have in common
/// ([`shared_fraction`]). The same for every frame of a sample, so computed once.
#[derive(Clone, Copy, Debug)]
pub struct NoiseTarget {
    want: [f64; 3],
    rho: f64,
}

impl NoiseTarget {
    /// The target of `image1` (`w` x `h`, interleaved RGB); `None` when it cannot be read.
    pub fn of(image1: &[u8], w: usize, h: usize) -> Option<Self> {
        if image1.len() != 3 * w * h {
            return None;
        }
        let (want, luma) = grid_levels(image1, w, h)?;
        Some(Self { want, rho: shared_fraction(want, luma) })
    }
}

/// Restores image1's noise level in a later frame (`frame`: 1 = image2): per channel, the
/// estimate of `image1` (every pixel, read on the quarter grid) is the level wanted, and the
/// share of it the channels have in common ([`shared_fraction`]) shapes the noise; the noise of the frame's key is added
/// to `image` at the standard deviation that makes the frame's own estimate over its pixels that
/// are not `holes` read that level ([`solve_sigma`]), rounded to the nearest level and clamped.
/// Returns the added standard deviations (zeros when an estimate is unavailable or the frame is
/// not less noisy).
pub fn restore_noise(
    image1: &[u8],
    image: &mut [u8],
    holes: &[u8],
    w: usize,
    h: usize,
    key: u64,
    frame: u64,
) -> [f64; 3] {
    match NoiseTarget::of(image1, w, h) {
        Some(target) => restore_noise_to(&target, image, holes, w, h, key, frame),
        None => [0.0; 3],
    }
}

/// [`restore_noise`] with image1's [`NoiseTarget`] computed beforehand.
pub fn restore_noise_to(
    target: &NoiseTarget,
    image: &mut [u8],
    holes: &[u8],
    w: usize,
    h: usize,
    key: u64,
    frame: u64,
) -> [f64; 3] {
    if image.len() != 3 * w * h || holes.len() != w * h {
        return [0.0; 3];
    }
    let want = target.want;
    let noise = noise_field(key, frame, w * h, target.rho);
    let mut add = [0.0f64; 3];
    for (c, a) in add.iter_mut().enumerate() {
        let (r, n) = paired_responses(image, &noise, w, h, c, |i| holes[i] == 0);
        if r.len() >= 16 {
            *a = solve_sigma(&r, &n, want[c]);
        }
    }
    if add.iter().all(|&a| a <= 0.0) {
        return add;
    }
    let s = add.map(|v| v as f32);
    image.par_chunks_mut(3 * 4096).zip(noise.par_chunks(3 * 4096)).for_each(|(px, nz)| {
        for (j, (p, &z)) in px.iter_mut().zip(nz).enumerate() {
            // round half up: + 0.5, clamp, truncate (no libm call)
            *p = (f32::from(*p) + s[j % 3] * z + 0.5).clamp(0.0, 255.0) as u8;
        }
    });
    add
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unit_noise_has_zero_mean_and_unit_variance() {
        let n = 200_000u64;
        let (mut s, mut sq) = (0.0f64, 0.0f64);
        for v in 0..n {
            let x = f64::from(unit_noise(7, 1, v));
            assert!(x.abs() < 3.5);
            s += x;
            sq += x * x;
        }
        let mean = s / n as f64;
        let var = sq / n as f64 - mean * mean;
        assert!(mean.abs() < 0.01, "{mean}");
        assert!((var - 1.0).abs() < 0.01, "{var}");
    }

    #[test]
    fn frames_and_keys_draw_different_noise() {
        let a: Vec<f32> = (0..64).map(|v| unit_noise(1, 1, v)).collect();
        let b: Vec<f32> = (0..64).map(|v| unit_noise(1, 2, v)).collect();
        let c: Vec<f32> = (0..64).map(|v| unit_noise(2, 1, v)).collect();
        assert_ne!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn a_flat_frame_gets_image1s_level() {
        let (w, h) = (96, 80);
        // image1: grey 128 with noise of about 4 levels per channel (another key)
        let field = noise_field(99, 1, w * h, 0.0);
        let image1: Vec<u8> = field.iter().map(|&z| (128.0 + 4.0 * z).round() as u8).collect();
        let want = channel_sigmas(&image1, w, h, |_| true).unwrap();
        let mut flat = vec![100u8; 3 * w * h];
        let holes = vec![0u8; w * h];
        let added = restore_noise(&image1, &mut flat, &holes, w, h, 5, 1);
        let got = channel_sigmas(&flat, w, h, |_| true).unwrap();
        for c in 0..3 {
            assert!((got[c] / want[c] - 1.0).abs() < 0.05, "channel {c}: {} against {}", got[c], want[c]);
            assert!((added[c] - want[c]).abs() < 0.15 * want[c], "added {} for {}", added[c], want[c]);
        }
        // a frame as noisy as image1 gets little (the solve reads a quarter of the pixels)
        let mut same = image1.clone();
        let more = restore_noise(&image1, &mut same, &holes, w, h, 5, 1);
        assert!(more.iter().all(|&m| m < 0.25 * want[0]), "{more:?}");
    }

    #[test]
    fn the_shared_fraction_inverts_the_luminance_law() {
        let s = [3.0, 2.0, 5.0];
        for rho in [0.0, 0.3, 0.8, 1.0] {
            let a: f64 = (0..3).map(|c| LUMA[c] * LUMA[c] * s[c] * s[c]).sum();
            let b: f64 = (0..3).map(|c| LUMA[c] * s[c]).sum::<f64>().powi(2);
            let l = ((1.0 - rho) * a + rho * b).sqrt();
            assert!((shared_fraction(s, l) - rho).abs() < 1e-12);
        }
        // a shared field has the law's correlation
        let f = noise_field(3, 1, 50_000, 0.64);
        let n = f.len() / 3;
        let cov: f64 = (0..n).map(|i| f64::from(f[3 * i]) * f64::from(f[3 * i + 1])).sum::<f64>() / n as f64;
        let var: f64 = (0..n).map(|i| f64::from(f[3 * i]).powi(2)).sum::<f64>() / n as f64;
        assert!((cov - 0.64).abs() < 0.02 && (var - 1.0).abs() < 0.02, "cov {cov} var {var}");
    }
}
