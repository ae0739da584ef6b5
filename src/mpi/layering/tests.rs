//! The unit tests of the built-in layering.

use super::*;

fn opts(planes: usize, layering: Layering) -> LayeringOptions {
    LayeringOptions { planes, layering, disparity_range: None, backdrop: false, ..LayeringOptions::default() }
}

proptest::proptest! {
    /// Content placement: the ends kept, strictly decreasing, no gap wider than
    /// `range / (λ (n - 1))`, and planes denser where the pixels are than uniform placement.
    #[test]
    fn content_planes_follow_the_pixels(
        n in 3usize..=256,
        near in 0.01f64..1.0,
        frac in 0.001f64..0.999,
        cluster in 0.0f64..1.0,
        seed in 0u64..1000,
    ) {
        let far = near * frac;
        let range = near - far;
        // a third of the pixels spread over the range, the rest in a cluster 1% wide
        let c = far + cluster * 0.99 * range;
        let disp: Vec<f64> = (0..3000u64)
            .map(|i| {
                let h = (i.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ seed) % 10_000;
                let u = h as f64 / 10_000.0;
                if i % 3 == 0 { far + u * range } else { c + u * 0.01 * range }
            })
            .collect();
        let p = content_planes(&disp, near, far, n);
        proptest::prop_assert_eq!(p.len(), n);
        proptest::prop_assert_eq!(p[0], near);
        proptest::prop_assert_eq!(p[n - 1], far);
        let widest = range / (CONTENT_UNIFORM_SHARE * (n - 1) as f64) * (1.0 + 1e-9);
        for w in p.windows(2) {
            proptest::prop_assert!(w[1] < w[0], "{:?}", w);
            proptest::prop_assert!(w[0] - w[1] <= widest, "gap {} > {widest}", w[0] - w[1]);
        }
        let inside = p.iter().filter(|&&d| d >= c && d <= c + 0.01 * range).count();
        // uniform placement puts about 1% of the planes in the cluster; content placement
        // about (1 - λ) * 2/3 of them
        proptest::prop_assert!(inside as f64 >= 0.4 * (n - 2) as f64 - 2.0, "{inside} of {n}");
    }
}

#[test]
fn disparities_are_uniform_and_strictly_decreasing() {
    let d = plane_disparities(1.0, 0.25, &opts(4, Layering::Soft)).unwrap();
    assert_eq!(d, vec![1.0, 0.75, 0.5, 0.25]);
    let one = plane_disparities(1.0, 0.5, &opts(1, Layering::Soft)).unwrap();
    assert_eq!(one, vec![0.75]);
    // zero range: widened towards the far side, nearest plane at the scene disparity
    let z = plane_disparities(0.5, 0.5, &opts(256, Layering::Soft)).unwrap();
    assert_eq!(z[0], 0.5);
    assert!(z.windows(2).all(|p| p[1] < p[0]));
    assert!((z[255] - 0.5 * (1.0 - MIN_RELATIVE_RANGE)).abs() < 1e-15);
    let mut o = opts(3, Layering::Hard);
    o.disparity_range = Some((2.0, 0.0));
    assert_eq!(plane_disparities(9.0, 1.0, &o).unwrap(), vec![2.0, 1.0, 0.0]);
    for bad in [(1.0, 1.0), (0.5, 1.0), (1.0, -0.1), (f64::NAN, 0.1), (f64::INFINITY, 0.0)] {
        o.disparity_range = Some(bad);
        assert!(plane_disparities(1.0, 0.5, &o).is_err(), "{bad:?}");
    }
    o.disparity_range = Some((1.0, 1.0 - 1e-15));
    o.planes = 256;
    assert!(plane_disparities(1.0, 0.5, &o).is_err());
}

#[test]
fn soft_split_is_linear_in_disparity() {
    let disp = [1.0, 0.5, 0.25];
    let s = assign(0.375, &disp, Layering::Soft);
    assert_eq!((s.near, s.far), (1, 2));
    let a = s.a_near as f64;
    assert!((a - 0.5).abs() < 1e-12);
    // composited weights: w_near = a, w_far = (1 - a) * 1; expected disparity = d
    let e = a * disp[1] + (1.0 - a) * disp[2];
    assert!((e - 0.375).abs() < 1e-12);
    let on = assign(0.5, &disp, Layering::Soft);
    assert_eq!((on.near, on.far, on.a_near), (1, 1, 1.0));
    assert_eq!(assign(2.0, &disp, Layering::Soft).far, 0);
    assert_eq!(assign(0.1, &disp, Layering::Soft).near, 2);
    assert_eq!(assign(0.76, &disp, Layering::Hard).near, 0);
    assert_eq!(assign(0.74, &disp, Layering::Hard).near, 1);
}

#[test]
fn density_round_trips_and_stays_finite() {
    for a in [1e-9, 0.1, 0.5, 0.9, 1.0] {
        let s = density(a, 0.3) as f64;
        let back = 1.0 - (-s * 0.3).exp();
        assert!((back - a.min(ALPHA_MAX)).abs() < 1e-6, "{a} -> {back}");
    }
    assert_eq!(density(1.0, 0.0), SIGMA_MAX);
    assert!(density(1.0, 1e-300).is_finite());
}

#[test]
fn nearest_fill_copies_known_values() {
    let mut v = vec![1.0, 0.0, 0.0, 0.0, 0.0, 2.0];
    let known = vec![true, false, false, false, false, true];
    fill_nearest(&mut v, &known, 3, 2);
    // pixel (1, 1) is at distance 1 from both sources: the first in scan order wins
    assert_eq!(v, vec![1.0, 1.0, 2.0, 1.0, 1.0, 2.0]);
}

#[test]
fn plane_fill_keeps_sources_and_fills_from_sources_only() {
    let (w, h) = (9, 7);
    let mut rgb = vec![0.0f32; w * h * 3];
    let mut lim = vec![0u8; w * h];
    for p in 0..w * h {
        if p % w >= 5 {
            lim[p] = 3;
            rgb[3 * p..3 * p + 3].copy_from_slice(&[0.2, 0.4, 0.6]);
        } else {
            rgb[3 * p..3 * p + 3].copy_from_slice(&[1.0, 0.0, 0.0]);
        }
    }
    let ctx = PlaneCtx { rgb: &rgb, w, h, lim: &lim, hidden: &[], back: &[] };
    let mut out = vec![0.0f32; w * h * 4];
    fill_plane(&ctx, 2, &mut Pyramid::default(), &mut out);
    for px in out.chunks_exact(4) {
        for (a, b) in px[..3].iter().zip([0.2, 0.4, 0.6]) {
            assert!((a - b).abs() < 1e-6);
        }
    }
    fill_plane(&ctx, 0, &mut Pyramid::default(), &mut out);
    for (o, c) in out.chunks_exact(4).zip(rgb.chunks_exact(3)) {
        assert_eq!(&o[..3], c);
    }
}

#[test]
fn a_plane_with_no_colour_source_is_black_whatever_its_buffer_held() {
    let (w, h) = (6, 5);
    let rgb = vec![0.5f32; w * h * 3];
    let lim = vec![0u8; w * h];
    let ctx = PlaneCtx { rgb: &rgb, w, h, lim: &lim, hidden: &[], back: &[] };
    let mut out = vec![f32::NAN; w * h * 4];
    fill_plane(&ctx, 2, &mut Pyramid::default(), &mut out);
    assert!(out.chunks_exact(4).all(|px| px[..3] == [0.0, 0.0, 0.0]));
}

/// The layering writes every value of its planes: a reused buffer full of NaN (handed back for
/// the next build of this size) gives the planes of a fresh one, bit for bit.
#[test]
fn the_layering_writes_every_value_of_a_reused_buffer() {
    let (w, h) = (23, 17);
    let rgb: Vec<f32> = (0..w * h * 3).map(|k| (k % 7) as f32 / 7.0).collect();
    let depth: Vec<f32> = (0..w * h).map(|p| if p % w < 9 { 1.5 } else { 4.0 + (p / w) as f32 * 0.1 }).collect();
    for layering in [Layering::Soft, Layering::Hard] {
        let o = opts(8, layering);
        let fresh = build_mpi(&rgb, &depth, w, h, &o).unwrap();
        crate::buf::give_back(vec![f32::NAN; fresh.rgba.len()]);
        let again = build_mpi(&rgb, &depth, w, h, &o).unwrap();
        assert!(again.rgba.iter().all(|v| v.is_finite()), "{layering:?}: a value was not written");
        let bits = |m: &Mpi| m.rgba.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&fresh), bits(&again), "{layering:?}");
    }
}
