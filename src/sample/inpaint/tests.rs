//! The unit tests of the inpainting: the heap keys, the marching, the radius rules, the rounding.

use super::front::{key, key_t, march, opencv_range, paper_radius, upwind};
use super::opencv::Sample;
use super::paper::disc;
use super::*;
use crate::raster::morph::dilate;
use crate::raster::Grid;

#[test]
fn key_orders_by_time_then_tie() {
    let ks = [key(-3.5, 0), key(0.0, 0), key(-0.0, 1), key(0.0, 2), key(1.0, 0), key(1.0e6, 0)];
    assert!(ks.windows(2).all(|p| p[0] < p[1]), "{ks:x?}");
    for t in [-2.0f32, 0.0, 0.5, 1.0, 7.25, 1.0e6] {
        assert_eq!(key_t(key(t, 9)), t);
    }
}

#[test]
fn upwind_matches_the_quadratic() {
    assert_eq!(upwind(0.0, f32::INFINITY), 1.0);
    assert_eq!(upwind(f32::INFINITY, 2.0), 3.0);
    assert_eq!(upwind(0.0, 1.0), 1.0);
    let v = upwind(0.0, 0.0);
    assert!((v - std::f32::consts::FRAC_1_SQRT_2).abs() < 1e-6, "{v}");
    // (T - a)^2 + (T - b)^2 = 1
    let (a, b) = (0.3f32, 0.8f32);
    let s = upwind(a, b);
    assert!(((s - a).powi(2) + (s - b).powi(2) - 1.0).abs() < 1e-5);
}

#[test]
fn marching_gives_distances_from_a_line() {
    // band = column 0, region = the rest: T = x exactly
    let (w, h) = (7, 3);
    let mut t = vec![f32::INFINITY; w * h];
    let seeds: Vec<u32> = (0..h).map(|y| (y * w) as u32).collect();
    let mut order = Vec::new();
    march(w, h, &mut t, |i| i % w != 0, &seeds, f32::INFINITY, Some(&mut order));
    for (i, &ti) in t.iter().enumerate() {
        assert_eq!(ti, (i % w) as f32, "pixel {i}");
    }
    // increasing T, ties by index
    assert_eq!(order, vec![1, 8, 15, 2, 9, 16, 3, 10, 17, 4, 11, 18, 5, 12, 19, 6, 13, 20]);
}

#[test]
fn march_stops_at_the_limit() {
    let (w, h) = (10, 1);
    let mut t = vec![f32::INFINITY; w];
    march(w, h, &mut t, |_| true, &[0], 3.0, None);
    assert_eq!(&t[..4], &[0.0, 1.0, 2.0, 3.0]);
    assert!(t[5..].iter().all(|v| v.is_infinite()));
}

#[test]
fn dilation_is_chebyshev() {
    let g = Grid::new(7, 6);
    let mut set = vec![false; g.len()];
    set[g.index(3, 2)] = true;
    let d = dilate(g.w, g.h, &set, 2);
    for (x, y) in g.pixels() {
        let inside = (x as isize - 3).abs() <= 2 && (y as isize - 2).abs() <= 2;
        assert_eq!(d[g.index(x, y)], inside, "({x},{y})");
    }
}

#[test]
fn radius_rules() {
    assert_eq!(paper_radius(0.2), 1.0);
    assert_eq!(paper_radius(f32::NAN), 1.0);
    assert_eq!(paper_radius(3.5), 3.5);
    assert_eq!(paper_radius(1.0e9), MAX_RADIUS);
    assert_eq!(opencv_range(2.5), 2);
    assert_eq!(opencv_range(3.5), 4);
    assert_eq!(opencv_range(0.4), 1);
    assert_eq!(opencv_range(f32::NAN), 1);
    assert_eq!(opencv_range(500.0), 100);
    assert_eq!(disc(1.0).len(), 4);
    assert_eq!(disc(1.5).len(), 8);
}

#[test]
fn u8_put_rounds_like_opencv() {
    assert_eq!(<u8 as Sample>::put(1.0), 2); // 1.5 -> 2 (half to even)
    assert_eq!(<u8 as Sample>::put(2.0), 2); // 2.5 -> 2
    assert_eq!(<u8 as Sample>::put(2.2), 3);
    assert_eq!(<u8 as Sample>::put(-9.0), 0);
    assert_eq!(<u8 as Sample>::put(300.0), 255);
    assert_eq!(<u8 as Sample>::put(f32::NAN), 0);
}

#[test]
fn single_pixel_hole_in_constant_image() {
    let (w, h) = (5, 4);
    let mut img = vec![0.25f32; w * h * 2];
    let mut hole = vec![0u8; w * h];
    hole[w + 2] = 1;
    img[(w + 2) * 2] = 9.0;
    let st = inpaint(&mut img, w, h, 2, &hole, &TeleaOptions { radius: 3.0, ..TeleaOptions::default() });
    assert_eq!(st.filled, 1);
    assert!(img.iter().all(|&v| (v - 0.25).abs() < 1e-6), "{img:?}");
}

#[test]
fn excluded_pixels_are_never_context_and_enclosed_holes_are_still_filled() {
    // columns 0-5 known grey 100, 6-9 a hole, 10-13 excluded white, 14-19 known grey 100
    let (w, h) = (20, 8);
    let g = Grid::new(w, h);
    let mut img = vec![100u8; 3 * w * h];
    let mut hole = vec![0u8; w * h];
    let mut excluded = vec![false; w * h];
    for (x, y) in g.pixels() {
        let i = g.index(x, y);
        if (6..10).contains(&x) {
            hole[i] = 1;
            img[3 * i..3 * i + 3].fill(0);
        } else if (10..14).contains(&x) {
            excluded[i] = true;
            img[3 * i..3 * i + 3].fill(255);
        }
    }
    let options = TeleaOptions { radius: 5.0, gradient: GradientTerm::KnownOnly, ..TeleaOptions::default() };
    let apart_options = TeleaOptions { excluded: Some(&excluded), ..options };
    let (mut apart, mut plain) = (img.clone(), img.clone());
    inpaint(&mut apart, w, h, 3, &hole, &apart_options);
    inpaint(&mut plain, w, h, 3, &hole, &options);
    for i in (0..w * h).filter(|&i| hole[i] != 0) {
        assert_eq!(&apart[3 * i..3 * i + 3], &[100, 100, 100], "pixel {i}: read an excluded pixel");
    }
    assert!((0..w * h).any(|i| hole[i] != 0 && plain[3 * i] > 100), "without exclusion the white is read");
    for i in (0..w * h).filter(|&i| excluded[i]) {
        assert_eq!(&apart[3 * i..3 * i + 3], &[255, 255, 255], "excluded pixels are not changed");
    }
    // without any excluded pixel, the same bits as the plain fill
    let mut none = img.clone();
    let nothing = vec![false; w * h];
    inpaint(&mut none, w, h, 3, &hole, &TeleaOptions { excluded: Some(&nothing), ..options });
    let mut again = img.clone();
    inpaint(&mut again, w, h, 3, &hole, &options);
    assert_eq!(none, again);
    // a hole enclosed by excluded pixels (and the border) is filled from them
    let mut enclosed = vec![255u8; 3 * w * h];
    let mut small = vec![0u8; w * h];
    small[g.index(0, 0)] = 1;
    enclosed[..3].fill(0);
    let ring: Vec<bool> = (0..w * h).map(|i| i != 0).collect();
    inpaint(&mut enclosed, w, h, 3, &small, &TeleaOptions { excluded: Some(&ring), ..options });
    assert_eq!(&enclosed[..3], &[255, 255, 255]);
    // f32 images: the same rule
    let mut apart_f32: Vec<f32> = img.iter().map(|&v| f32::from(v)).collect();
    inpaint(&mut apart_f32, w, h, 3, &hole, &apart_options);
    for i in (0..w * h).filter(|&i| hole[i] != 0) {
        let got = &apart_f32[3 * i..3 * i + 3];
        assert!(got.iter().all(|&v| (v - 100.0).abs() < 1e-3), "pixel {i}: {got:?}");
    }
}

#[test]
#[should_panic(expected = "the OpenCV variant reads every known pixel")]
fn the_opencv_variant_refuses_excluded_pixels() {
    let (w, h) = (4, 3);
    let mut hole = vec![0u8; w * h];
    hole[5] = 1;
    let excluded = vec![false; w * h];
    let options = TeleaOptions { variant: TeleaVariant::OpenCv, excluded: Some(&excluded), ..TeleaOptions::default() };
    inpaint(&mut vec![0u8; w * h], w, h, 1, &hole, &options);
}
