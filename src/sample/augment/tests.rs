//! Laws and examples of the augmentation: the JSON form, the draw, and the transform.

use super::apply::*;
use super::plan::*;
use super::*;
use crate::raster::Grid;
use crate::sample::motion::{Motion, RotationKind};
use crate::sample::StageTimings;
use proptest::prelude::*;

#[test]
fn a_key_given_twice_is_refused_at_any_depth() {
    let e = Augment::parse(r#"{"preset":"raft-chairs","preset":"none"}"#).unwrap_err();
    assert_eq!(e.field, "augment");
    assert!(e.reason.contains("\"preset\" given twice"), "{}", e.reason);
    let e = Augment::parse(r#"{"crop":[8,8],"brightness":{"a":1,"a":2}}"#).unwrap_err();
    assert!(e.reason.contains("given twice"), "{}", e.reason);
    // the same key in two objects is fine, and so is a well-formed form
    assert!(Augment::parse(r#"{"preset":"raft-chairs","crop":[64,48]}"#).is_ok());
}

/// A `w` x `h` sample with textured images, the affine flow `f(p) = (a p.x + b, c p.y + d)`,
/// valid except a band, and label/depth planes that name their pixel.
fn sample(w: usize, h: usize, index: u64) -> Sample {
    let n = w * h;
    let mut flow = crate::buf::zeros::<f32>(2 * n);
    let mut valid = vec![1u8; n];
    let g = Grid::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let i = g.index(x, y);
            flow[2 * i] = 0.05 * x as f32 - 1.5;
            flow[2 * i + 1] = -0.03 * y as f32 + 0.75;
            valid[i] = u8::from(x % 7 != 3);
        }
    }
    Sample {
        address: SampleAddress { dataset: 11, seed: 5, index },
        source_id: "t".into(),
        width: w,
        height: h,
        image1: (0..n * 3).map(|i| ((i * 37) % 251) as u8).collect(),
        image2: (0..n * 3).map(|i| ((i * 53) % 241) as u8).collect(),
        flow,
        valid,
        occlusion: (0..n).map(|i| u8::from(i % 5 == 0)).collect(),
        mask1: (0..n).map(|i| (i % 251) as u8).collect(),
        mask2: (0..n).map(|i| (i % 13) as u8).collect(),
        holes: (0..n).map(|i| u8::from(i % 11 == 0)).collect(),
        camera: Motion::new("x", [0.0; 3], RotationKind::AxisAngle, [0.0; 3]),
        objects: vec![],
        depth1: (0..n).map(|i| i as f32).collect(),
        depth2: (0..n).map(|i| 2.0 * i as f32).collect(),
        inpainted_pixels: 0,
        backward: Default::default(),
        clip: Vec::new(),
        skipped_sources: 0,
        provenance: vec![],
        intrinsics: Intrinsics::reference_default(w, h),
        timings: StageTimings::default(),
    }
}

#[test]
fn presets_and_json_parse_and_errors_name_the_key() {
    for p in AugmentPreset::ALL {
        let a = Augment::parse(p.name()).unwrap();
        assert_eq!(a, Augment::preset(p));
        a.params.validate().unwrap();
    }
    let chairs = AugmentPreset::RaftChairs.params();
    assert_eq!(chairs.crop, Some((496, 368)));
    assert_eq!((chairs.min_scale, chairs.max_scale), (-0.1, 1.0));
    assert!(AugmentPreset::RaftKitti.params().sparse);
    let a = Augment::parse(r#"{"preset": "raft-things", "eraser_prob": 0, "crop": [320, 256]}"#).unwrap();
    assert_eq!(a.preset, AugmentPreset::RaftThings);
    assert!(a.custom);
    assert_eq!(a.params.crop, Some((320, 256)));
    assert_eq!(a.params.eraser_prob, 0.0);
    assert_eq!(a.params.min_scale, -0.4);
    let field = |t: &str| Augment::parse(t).unwrap_err().field;
    assert_eq!(field("raft-chair"), "augment");
    assert_eq!(field("{"), "augment");
    assert_eq!(field(r#"{"crop": [1]}"#), "augment.crop");
    assert_eq!(field(r#"{"crop": [0, 5]}"#), "augment.crop");
    assert_eq!(field(r#"{"hue": "x"}"#), "augment.hue");
    assert_eq!(field(r#"{"hue": 0.7}"#), "augment.hue");
    assert_eq!(field(r#"{"h_flip_prob": 2}"#), "augment.h_flip_prob");
    assert_eq!(field(r#"{"preset": "raft-chairs", "max_scale": -1}"#), "augment.min_scale");
    assert_eq!(field(r#"{"preset": "kitti"}"#), "augment.preset");
    assert_eq!(field(r#"{"eraser_boxes": 0}"#), "augment.eraser_boxes");
    assert_eq!(field(r#"{"sparse": 1}"#), "augment.sparse");
    let e = Augment::parse(r#"{"scale": 1}"#).unwrap_err();
    assert!(e.reason.contains("\"scale\""), "{e}");
}

#[test]
fn the_identity_changes_nothing() {
    let mut s = sample(23, 17, 4);
    // a rendered sample's valid already holds the target-inside rule
    clear_valid_outside(&s.flow, &mut s.valid, 23, 17);
    let (out, r) = Augment::preset(AugmentPreset::None).apply(s.clone());
    assert!(out == s, "the identity changed the sample");
    assert_eq!(r.flow_scale, [1.0, 1.0]);
    // a crop of the whole frame with nothing drawn is the identity too
    let (out, _) = Augment::preset(AugmentPreset::None).with_crop((23, 17)).apply(s.clone());
    assert!(out == s, "the whole-frame crop changed the sample");
}

#[test]
fn colour_and_eraser_never_change_the_flow_or_the_geometry() {
    let no_colour = AugmentParams {
        brightness: 0.0,
        contrast: 0.0,
        saturation: 0.0,
        hue: 0.0,
        eraser_prob: 0.0,
        ..AugmentPreset::RaftChairs.params()
    };
    let plain = Augment { preset: AugmentPreset::RaftChairs, custom: true, params: no_colour }.with_crop((40, 30));
    let full = Augment::preset(AugmentPreset::RaftChairs).with_crop((40, 30));
    let mut changed = 0;
    for index in 0..20 {
        let s = sample(64, 48, index);
        let (a, ra) = full.apply(s.clone());
        let (b, rb) = plain.apply(s);
        assert_eq!((ra.resized, ra.flip, ra.crop), (rb.resized, rb.flip, rb.crop));
        assert_eq!(a.flow, b.flow);
        assert_eq!(a.valid, b.valid);
        assert_eq!((a.occlusion, a.mask1, a.holes, a.depth1), (b.occlusion, b.mask1, b.holes, b.depth1));
        changed += usize::from(a.image1 != b.image1 || a.image2 != b.image2);
    }
    assert!(changed >= 15, "colour changed only {changed} of 20 samples");
}

#[test]
fn same_address_same_bytes_and_indices_differ() {
    let a = Augment::preset(AugmentPreset::RaftSintel).with_crop((50, 40));
    let (x, rx) = a.apply(sample(70, 52, 3));
    let (y, ry) = a.apply(sample(70, 52, 3));
    assert_eq!(x, y);
    assert_eq!(rx.to_json(), ry.to_json());
    let records: std::collections::BTreeSet<String> = (0..8).map(|i| a.apply(sample(70, 52, i)).1.to_json()).collect();
    assert!(records.len() >= 7, "{records:?}");
}

#[test]
fn the_frame_is_brought_up_to_a_crop_larger_than_it() {
    for p in AugmentPreset::ALL {
        let a = Augment::preset(p).with_crop((100, 80));
        for index in 0..10 {
            let (out, r) = a.apply(sample(40, 30, index));
            assert_eq!((out.width, out.height), (100, 80), "{p:?} {r:?}");
            assert_eq!(out.image1.len(), 100 * 80 * 3);
            assert_eq!(out.flow.len(), 100 * 80 * 2);
            assert!(out.flow.iter().all(|v| v.is_finite()));
            assert!(r.resized[0] > 100 && r.resized[1] > 80);
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn axis_forward_inverts_source(src in 1usize..300, resized in 1usize..600, flip: bool, off in 0usize..50, i in 0usize..50) {
        let out = resized.saturating_sub(off).max(1);
        let off = off.min(resized - 1);
        let a = Axis { src, resized, flip, offset: off, out };
        let i = i % out;
        prop_assert!((a.forward(a.source(i)) - i as f64).abs() < 1e-9);
        // the map is affine with the slope it reports
        prop_assert!((a.forward(a.source(i) + 1.0) - a.forward(a.source(i)) - a.slope()).abs() < 1e-9);
    }

    /// Dense rule: the output flow is the slope times the source flow at the source
    /// position (exact for an affine field, up to f32 rounding), and valid pixels come only
    /// from valid taps with the target inside the output.
    #[test]
    fn dense_flow_scales_and_flips_with_the_geometry(index in 0u64..1000, cw in 8u32..60, ch in 8u32..40) {
        let a = Augment::preset(AugmentPreset::RaftChairs).with_crop((cw, ch));
        let s = sample(48, 36, index);
        let plan = a.draw(s.address, s.width, s.height);
        let out = apply_plan(&plan, s.clone());
        let (ow, oh) = (out.width, out.height);
        prop_assert_eq!((ow, oh), (cw as usize, ch as usize));
        let (kx, ky) = (plan.x.slope(), plan.y.slope());
        let out_grid = Grid::new(ow, oh);
        for y in 0..oh {
            for x in 0..ow {
                let o = out_grid.index(x, y);
                let (sx, sy) = (plan.x.source(x).clamp(0.0, 47.0), plan.y.source(y).clamp(0.0, 35.0));
                let want = [(0.05 * sx - 1.5) * kx, (-0.03 * sy + 0.75) * ky];
                prop_assert!((f64::from(out.flow[2 * o]) - want[0]).abs() < 1e-3, "{} {}", out.flow[2 * o], want[0]);
                prop_assert!((f64::from(out.flow[2 * o + 1]) - want[1]).abs() < 1e-3);
                if out.valid[o] != 0 {
                    let tx = x as f64 + want[0];
                    let ty = y as f64 + want[1];
                    prop_assert!(tx >= -1e-3 && tx <= (ow - 1) as f64 + 1e-3 && ty >= -1e-3 && ty <= (oh - 1) as f64 + 1e-3);
                    // never next to the invalid column 3 (mod 7) of the source
                    let (x0, x1) = (sx.floor() as usize, sx.ceil() as usize);
                    prop_assert!(x0 % 7 != 3 && x1 % 7 != 3);
                }
                // labels follow with nearest neighbour
                let (nx, ny) = (plan.x.nearest()[x], plan.y.nearest()[y]);
                prop_assert_eq!(out.mask1[o], s.mask1[ny * 48 + nx]);
                prop_assert_eq!(out.depth2[o], s.depth2[ny * 48 + nx]);
            }
        }
    }

    /// Sparse rule: every valid output vector is a valid source vector times the slopes,
    /// put at the output pixel nearest the source pixel's mapped position.
    #[test]
    fn sparse_flow_moves_valid_vectors_to_the_nearest_pixel(index in 0u64..1000) {
        let a = Augment::preset(AugmentPreset::RaftKitti).with_crop((40, 20));
        let s = sample(60, 30, index);
        let plan = a.draw(s.address, s.width, s.height);
        let out = apply_plan(&plan, s.clone());
        let (kx, ky) = (plan.x.slope() as f32, plan.y.slope() as f32);
        let mut hits = 0;
        for y in 0..s.height {
            for x in 0..s.width {
                let (Some(ox), Some(oy)) = (plan.x.scatter(x), plan.y.scatter(y)) else { continue };
                prop_assert!((plan.x.forward(x as f64) - ox as f64).abs() <= 0.5 + 1e-9);
                let o = oy * 40 + ox;
                if out.valid[o] != 0 {
                    // the vector there is one of the source's, scaled
                    let u = out.flow[2 * o] / kx;
                    let v = out.flow[2 * o + 1] / ky;
                    let sxp = ((u + 1.5) / 0.05).round() as usize;
                    prop_assert!(sxp < s.width && s.valid[oy.min(s.height - 1) * s.width + sxp.min(s.width - 1)] <= 1);
                    prop_assert!((v - 0.75).abs() <= 0.03 * s.height as f32 + 1e-3);
                    hits += 1;
                }
            }
        }
        prop_assert!(out.valid.iter().filter(|&&v| v != 0).count() <= hits);
        prop_assert!(out.flow.iter().all(|v| v.is_finite()));
    }
}
