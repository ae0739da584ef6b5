//! Object motion and merging on constructed scenes with known answers: a textured wall, a square
//! object in front of it and (in some tests) a pole nearer still; the merge rules on hand-made
//! renders; windowed renders against full-frame renders; the reference pre-blend.

use std::sync::Arc;

use mpiflow::geometry::{Intrinsics, Pose};
use mpiflow::io::image::RgbImage;
use mpiflow::mpi::layering::{build_mpi_for_camera, Layering, LayeringOptions};
use mpiflow::mpi::npz::load_npz;
use mpiflow::raster::{Instance, InstanceMasks};
use mpiflow::render::{render, Fields, Rect, RenderOutput, RenderParams, Skip, WindowRender};
use mpiflow::sample::config::{InpaintMethod, MotionSpec, SampleConfig};
use mpiflow::sample::holes::{inpaint_background, inpaint_holes};
use mpiflow::sample::merge::{merge, LabelRule, MergeRule, ObjectView, SceneView};
use mpiflow::sample::motion::{Axes, Component, MotionRanges, RigidLaw, RotationKind};
use mpiflow::sample::object::{object_window, scene_mask_window, support_rect, target_footprint, OBJECT_MARGIN};
use mpiflow::sample::preblend::{preblend, source_transmittance};
use mpiflow::sample::recipe::assemble;
use mpiflow::sample::{Sample, SampleAddress};
use mpiflow::scene::{Disparity, Scene};

const W: usize = 96;
const H: usize = 64;

fn wall_colour(x: usize, y: usize) -> [f32; 3] {
    [0.2 + 0.6 * x as f32 / W as f32, 0.3 + 0.4 * y as f32 / H as f32, 0.5]
}
const OBJECT: [f32; 3] = [0.9, 0.1, 0.1];
const POLE: [f32; 3] = [0.1, 0.1, 0.9];

/// A wall at depth 4, a square object `[x0, x1) x [y0, y1)` at depth 2, optionally a pole (full
/// height, columns `[p0, p1)`) at depth 1; hard layering on planes at exactly those depths.
fn wall_scene(square: (usize, usize, usize, usize), pole: Option<(usize, usize)>) -> Scene {
    let k = Intrinsics::reference_default(W, H);
    let mut rgb = vec![0.0f32; W * H * 3];
    let mut depth = vec![4.0f32; W * H];
    let mut mask = vec![0.0f32; W * H];
    for y in 0..H {
        for x in 0..W {
            let i = y * W + x;
            let mut c = wall_colour(x, y);
            if (square.0..square.1).contains(&x) && (square.2..square.3).contains(&y) {
                c = OBJECT;
                depth[i] = 2.0;
                mask[i] = 1.0;
            }
            if let Some((p0, p1)) = pole {
                if (p0..p1).contains(&x) {
                    c = POLE;
                    depth[i] = 1.0;
                    mask[i] = 0.0;
                }
            }
            rgb[3 * i..3 * i + 3].copy_from_slice(&c);
        }
    }
    let opts = LayeringOptions {
        planes: 4,
        layering: Layering::Hard,
        disparity_range: Some((1.0, 0.25)),
        backdrop: false,
        ..LayeringOptions::default()
    };
    let mpi = build_mpi_for_camera(&rgb, &depth, W, H, &opts, &k).unwrap();
    assert_eq!(mpi.disparity, vec![1.0, 0.75, 0.5, 0.25]);
    let masks = InstanceMasks { width: W, height: H, masks: vec![Instance::new(1, 0.9, mask)] };
    Scene {
        id: "wall".into(),
        image: RgbImage { width: W, height: H, data: rgb },
        disparity: Disparity { width: W, height: H, data: depth.iter().map(|d| 1.0 / d).collect() },
        mpi: Arc::new(mpi),
        masks,
        intrinsics: k,
        provenance: vec!["test: wall".into()],
    }
}

fn rigid(t: [f64; 3], r: [f64; 3]) -> RigidLaw {
    let c = Component::constant;
    RigidLaw {
        translation: Axes::new(c(t[0]), c(t[1]), c(t[2])),
        rotation_kind: RotationKind::AxisAngle,
        rotation: Axes::new(c(r[0]), c(r[1]), c(r[2])),
    }
}

/// The closed forms below hold pixel colours next to hard colour edges to the bilinear kernel's
/// one-pixel reach (the other kernels' laws are in tests/render/resample.rs).
fn config(camera: RigidLaw, object: RigidLaw, rule: MergeRule) -> SampleConfig {
    SampleConfig {
        motion: MotionSpec::Ranges(Box::new(MotionRanges {
            name: "test".into(),
            camera,
            object,
            stereo: false,
            reveal_budget: None,
        })),
        merge: rule,
        inpaint_radius: 3.0,
        resample: mpiflow::render::Resample::Bilinear,
        ..SampleConfig::default()
    }
}

const ADDR: SampleAddress = SampleAddress { dataset: 1, seed: 2, index: 3 };

fn px(img: &[u8], x: usize, y: usize) -> [u8; 3] {
    let i = 3 * (y * W + x);
    [img[i], img[i + 1], img[i + 2]]
}

fn close(a: [u8; 3], b: [f32; 3], tol: i32) -> bool {
    (0..3).all(|c| (a[c] as i32 - (b[c] * 255.0).round() as i32).abs() <= tol)
}

#[test]
fn translating_only_the_object_gives_the_closed_form_flow_and_fills_the_disocclusion() {
    let square = (40, 56, 24, 40);
    let scene = wall_scene(square, None);
    let tx = 0.1;
    for rule in [MergeRule::DepthAware, MergeRule::Reference] {
        let cfg = config(rigid([0.0; 3], [0.0; 3]), rigid([tx, 0.0, 0.0], [0.0; 3]), rule);
        let s = assemble(&scene, ADDR, &cfg).unwrap();
        let fx = scene.intrinsics.fx;
        let shift = (fx * tx / 2.0) as f32; // K t / depth: 2.784 px
        let mut object_px = 0;
        for y in 0..H {
            for x in 0..W {
                let i = y * W + x;
                let (u, v) = (s.flow[2 * i], s.flow[2 * i + 1]);
                assert!(u.is_finite() && v.is_finite());
                let inside = (square.0..square.1).contains(&x) && (square.2..square.3).contains(&y);
                if inside {
                    object_px += 1;
                    assert!((u - shift).abs() < 1e-4 && v.abs() < 1e-4, "{rule:?} object flow at ({x},{y}): {u},{v}");
                    assert_eq!(s.mask1[i], 1);
                } else {
                    assert!(
                        u.abs() < 1e-4 && v.abs() < 1e-4,
                        "{rule:?}: the wall does not move under an identity camera"
                    );
                    assert_eq!(s.mask1[i], 0);
                }
                assert_eq!(s.valid[i], 1, "{rule:?}: every point stays in view at ({x},{y})");
            }
        }
        assert_eq!(object_px, 256);
        // image2: the square moved right by 2.78 px
        for y in square.2 + 1..square.3 - 1 {
            for x in 44..56 {
                assert!(close(px(&s.image2, x, y), OBJECT, 1), "{rule:?}: object at ({x},{y})");
                assert_eq!(s.mask2[y * W + x], 1);
            }
            for x in 60..W {
                assert!(close(px(&s.image2, x, y), wall_colour(x, y), 1), "{rule:?}: wall at ({x},{y})");
                assert_eq!(s.mask2[y * W + x], 0);
            }
        }
        // the strip the object uncovered (x in [40, 42.78)) is a hole, inpainted from its
        // surroundings: the wall on its left, the moved object on its right; with the
        // depth-aware merge the object leaves the scene over its footprint (the square grown by
        // OBJECT_MARGIN), whose band the moved object does not cover is a hole too
        let band = match rule {
            MergeRule::DepthAware => (16 + 2 * OBJECT_MARGIN).pow(2) - 16 * 16,
            MergeRule::Reference => 0,
        };
        assert!(
            s.inpainted_pixels as usize >= band + 16 && s.inpainted_pixels as usize <= band + 3 * 16 + 8,
            "{rule:?}: {} holes",
            s.inpainted_pixels
        );
        for y in square.2 + 1..square.3 - 1 {
            for x in 40..42 {
                let got = px(&s.image2, x, y);
                let wall = wall_colour(x, y);
                for c in 0..3 {
                    let (lo, hi) = (wall[c].min(OBJECT[c]) * 255.0 - 12.0, wall[c].max(OBJECT[c]) * 255.0 + 12.0);
                    assert!((lo..=hi).contains(&(got[c] as f32)), "{rule:?}: disoccluded ({x},{y}) = {got:?}");
                }
                assert_eq!(s.mask2[y * W + x], 0);
            }
            // next to the wall, the fill looks like the wall
            let got = px(&s.image2, 40, y);
            let dist = |c: [f32; 3]| (0..3).map(|k| (got[k] as f32 - 255.0 * c[k]).abs()).sum::<f32>();
            assert!(dist(wall_colour(40, y)) < dist(OBJECT), "{rule:?}: ({}, {y}) = {got:?}", 40);
        }
        // wall points just right of the square are covered by the moved (nearer) object
        for y in square.2 + 1..square.3 - 1 {
            assert_eq!(s.occlusion[y * W + 56], 1, "{rule:?}: wall at (56,{y}) is hidden by the object");
            assert_eq!(s.occlusion[y * W + 70], 0);
            assert_eq!(s.occlusion[y * W + 48], 0, "{rule:?}: the object itself is visible");
        }
        assert_eq!(s.objects.len(), 1);
        assert_eq!(s.objects[0].motion.translation, [tx, 0.0, 0.0]);
    }
}

#[test]
fn an_object_moved_behind_nearer_background_stays_hidden_only_under_depth_aware() {
    let square = (30, 46, 24, 40);
    let pole = (60, 66);
    let scene = wall_scene(square, Some(pole));
    // 0.6 * 55.68 / 2 = 16.7 px: the square ends up at [46.7, 62.7), partly behind the pole
    let cam = rigid([0.0; 3], [0.0; 3]);
    let obj = rigid([0.6, 0.0, 0.0], [0.0; 3]);
    let depth = assemble(&scene, ADDR, &config(cam, obj, MergeRule::DepthAware)).unwrap();
    let reference = assemble(&scene, ADDR, &config(cam, obj, MergeRule::Reference)).unwrap();
    let y = 32;
    for x in 60..62 {
        let i = y * W + x;
        assert!(close(px(&depth.image2, x, y), POLE, 1), "depth-aware: the pole stays in front at ({x},{y})");
        assert_eq!(depth.mask2[i], 0);
        assert!(close(px(&reference.image2, x, y), OBJECT, 1), "reference: the object is drawn on top");
        assert_eq!(reference.mask2[i], 1);
    }
    // in front of the pole the object is visible under both rules
    for s in [&depth, &reference] {
        assert!(close(px(&s.image2, 52, y), OBJECT, 1));
    }
    // the object's points that land behind the pole are occluded under depth-aware only
    let src_x = 45; // lands at 61.7
    assert_eq!(depth.occlusion[y * W + src_x], 1);
    assert_eq!(reference.occlusion[y * W + src_x], 0);
    // the pole's own points are never occluded
    assert_eq!(depth.occlusion[y * W + 62], 0);
}

/// A 4 x 1 frame, hand-made renders: the rules of the merge, pixel by pixel.
#[test]
fn merge_rules_on_hand_made_renders() {
    let (w, h) = (4, 1);
    // scene: pixel 0 background, 1 background (near, depth 1), 2 the object's old place
    // (scene mask 0), 3 a hole (coverage 0)
    let image = [0.2f32; 12];
    let depth = [5.0, 1.0, 3.0, 0.0];
    let scene_mask = [1.0, 1.0, 0.0, 0.0];
    let flow = [0.0f32; 8];
    let valid = [1u8; 4];
    let sdepth = [5.0f32, 1.0, 3.0, 5.0];
    let scene = SceneView {
        width: w,
        height: h,
        image: &image,
        depth: depth.to_vec(),
        scene_mask: &scene_mask,
        scene_mask_patch: None,
        flow: flow.to_vec(),
        valid: valid.to_vec(),
        source_depth: sdepth.to_vec(),
    };
    let obj = |m: [f32; 4], d: [f32; 4], col: f32, fl: f32| WindowRender {
        win: Rect::full(w, h),
        out: RenderOutput {
            width: w,
            height: h,
            image: vec![col; 12],
            depth: d.to_vec(),
            coverage: m.to_vec(),
            extras: m.to_vec(),
            extra_channels: 1,
            flow: vec![fl, 0.0, fl, 0.0, fl, 0.0, fl, 0.0],
            source_depth_in_target: vec![2.0; 4],
            valid: vec![1; 4],
            ..Default::default()
        },
    };
    // object A (depth 2) visible on pixels 0..3, B (depth 4) on pixels 0 and 3
    let ra = obj([1.0, 1.0, 1.0, 0.5], [2.0; 4], 0.8, 1.0);
    let rb = obj([1.0, 0.0, 0.0, 1.0], [4.0; 4], 0.6, -1.0);
    let ma = [0.0, 0.0, 1.0, 0.0];
    let mb = [0.0, 0.0, 0.0, 0.995];
    let objects = [
        ObjectView { label: 1, source_mask: &ma, render: &ra },
        ObjectView { label: 2, source_mask: &mb, render: &rb },
    ];
    let v = |x: f32| (x * 255.0).round() as u8;

    let d = merge(scene.clone(), &objects, MergeRule::DepthAware, LabelRule::Honest, 0.99, true);
    // pixel 0: background at depth 5 behind both objects: the nearer object A is drawn
    // pixel 1: background at depth 1 in front of A: stays
    // pixel 2: the object's old place: A drawn; pixel 3: hole, B covers it (A's mask is 0.5)
    assert_eq!(d.mask2, vec![1, 0, 1, 2]);
    assert_eq!(
        d.image2,
        vec![v(0.8), v(0.8), v(0.8), v(0.2), v(0.2), v(0.2), v(0.8), v(0.8), v(0.8), v(0.6), v(0.6), v(0.6)]
    );
    assert_eq!(d.hole, vec![0, 0, 0, 0]);
    // flow: source pixel 2 from A (+1), pixel 3 from B (-1, M = 0.995 >= 0.99), others scene
    assert_eq!(d.flow, vec![0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0]);
    assert_eq!(d.mask1, vec![0, 0, 1, 2]);
    // honest labels: source 0 (background, z 5) lands on A (label 1): occluded; 1 lands on the
    // background it is (z 1): visible; 2 (A, +1) lands on B's pixel: occluded; 3 (B, z 2, -1)
    // lands between A and B where B shows depth 4: not B's point, occluded
    assert_eq!(d.occlusion, vec![1, 0, 1, 1]);
    assert_eq!(d.target_depth, vec![5.0, 1.0, 2.0, 2.0]);
    // the depth-only rule: occluded only when behind all four neighbours (source 0 only)
    let o = merge(scene.clone(), &objects, MergeRule::DepthAware, LabelRule::DepthOnly, 0.99, true);
    assert_eq!(o.occlusion, vec![1, 0, 0, 0]);
    assert_eq!((o.mask2, o.flow, o.image2), (d.mask2.clone(), d.flow.clone(), d.image2.clone()));

    let r = merge(scene.clone(), &objects, MergeRule::Reference, LabelRule::Honest, 0.99, true);
    // reference: no depth test; pixel 0 has two candidates with equal masks -> lower slot (A)
    assert_eq!(r.mask2, vec![1, 1, 1, 2]);
    assert_eq!(r.flow, d.flow);
    assert_eq!(r.hole, vec![0, 0, 0, 0]);

    // without objects: holes are exactly the pixels with scene mask < tau
    let n = merge(scene, &[], MergeRule::DepthAware, LabelRule::Honest, 0.99, true);
    assert_eq!(n.hole, vec![0, 0, 1, 1]);
    assert_eq!(n.holes, 2);
    assert_eq!(n.mask1, vec![0; 4]);
    assert_eq!(n.mask2, vec![0; 4]);
}

fn textured_scene(w: usize, h: usize, planes: usize) -> Scene {
    let k = Intrinsics::reference_default(w, h);
    let mut rgb = vec![0.0f32; w * h * 3];
    let mut depth = vec![0.0f32; w * h];
    let mut mask = vec![0.0f32; w * h];
    let (cx, cy, r) = (0.55 * w as f32, 0.5 * h as f32, 0.18 * h as f32);
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let (s, t) = (x as f32 / w as f32, y as f32 / h as f32);
            // a ground plane receding upwards, a disc object standing on it
            let mut d = 1.2 + 6.0 * (1.0 - t).powi(2);
            let mut c = [0.5 + 0.4 * (9.0 * s).sin(), 0.5 + 0.4 * (7.0 * t + 3.0 * s).cos(), 0.4 + 0.3 * s];
            let dist = ((x as f32 - cx).powi(2) + (y as f32 - cy).powi(2)).sqrt();
            // soft mask edge over ~1.5 px
            let m = ((r - dist) / 1.5 + 0.5).clamp(0.0, 1.0);
            if m > 0.0 {
                d = d.min(2.0);
                c = [0.9, 0.8 * (3.0 * t).sin().abs(), 0.2];
            }
            mask[i] = m;
            depth[i] = d;
            rgb[3 * i..3 * i + 3].copy_from_slice(&c);
        }
    }
    let opts = LayeringOptions {
        planes,
        layering: Layering::Soft,
        disparity_range: None,
        backdrop: false,
        ..LayeringOptions::default()
    };
    let mpi = build_mpi_for_camera(&rgb, &depth, w, h, &opts, &k).unwrap();
    let mut disp: Vec<f32> = depth.iter().map(|d| 1.0 / d).collect();
    let max = disp.iter().copied().fold(0.0, f32::max);
    disp.iter_mut().for_each(|v| *v /= max);
    Scene {
        id: "textured".into(),
        image: RgbImage { width: w, height: h, data: rgb },
        disparity: Disparity { width: w, height: h, data: disp },
        mpi: Arc::new(mpi),
        masks: InstanceMasks { width: w, height: h, masks: vec![Instance::new(4, 0.8, mask)] },
        intrinsics: k,
        provenance: vec!["test: textured".into()],
    }
}

#[allow(clippy::needless_range_loop)]
fn compare_inside_object(a: &Sample, b: &Sample, mask: &[f32]) -> (f32, i32, usize, usize, usize) {
    let (mut flow, mut img, mut drawn_diff, mut drawn, mut img_diff_px) = (0.0f32, 0i32, 0usize, 0usize, 0usize);
    let n = a.width * a.height;
    for i in 0..n {
        if mask[i] >= 0.99 {
            flow = flow.max((a.flow[2 * i] - b.flow[2 * i]).abs()).max((a.flow[2 * i + 1] - b.flow[2 * i + 1]).abs());
        }
        if a.mask2[i] == 1 || b.mask2[i] == 1 {
            drawn += 1;
            if a.mask2[i] != b.mask2[i] {
                drawn_diff += 1;
            } else {
                let d = (0..3).map(|c| (a.image2[3 * i + c] as i32 - b.image2[3 * i + c] as i32).abs()).max().unwrap();
                img = img.max(d);
                img_diff_px += usize::from(d > 1);
            }
        }
    }
    (flow, img, drawn_diff, drawn, img_diff_px)
}

/// Windowed object and mask renders (no copy, only the footprints) against full-frame renders of
/// MPI copies with the mask channel (the reference's construction). Stated tolerances, which
/// hold in general (the scene mask's rounding can tip a threshold tie): inside the object
/// (source mask >= 0.99) the flow agrees within 1e-4 px; where both draw the object, image2
/// agrees within 1 level; the set of pixels where the object is drawn differs on at most 0.5% of
/// them; elsewhere image2 differs by more than 1 level on at most 0.1% of the pixels and the
/// flow agrees within 1e-4 px. In these scenes no tie tips, and the samples are identical.
#[test]
fn windowed_renders_match_full_frame_renders_inside_the_object() {
    let (w, h) = (128, 96);
    let scene = textured_scene(w, h, 16);
    let mask = scene.masks.masks[0].mask.clone();
    let presets = [
        (rigid([0.15, -0.1, -0.12], [0.01, -0.015, 0.008]), rigid([0.04, 0.03, 0.05], [0.01, 0.0, -0.01])),
        (rigid([-0.2, 0.05, 0.1], [-0.01, 0.01, 0.0]), rigid([-0.05, -0.02, -0.07], [0.0, 0.02, 0.01])),
    ];
    for (cam, obj) in presets {
        for rule in [MergeRule::DepthAware, MergeRule::Reference] {
            let mut cfg = config(cam, obj, rule);
            let windowed = assemble(&scene, ADDR, &cfg).unwrap();
            cfg.windowed = false;
            let full = assemble(&scene, ADDR, &cfg).unwrap();
            let (flow, img, drawn_diff, drawn, img_px) = compare_inside_object(&windowed, &full, &mask);
            println!(
                "{rule:?}: object flow {flow:.2e} px, image2 {img} levels ({img_px} px > 1), drawn differs on {drawn_diff} of {drawn}"
            );
            assert!(flow <= 1e-4, "object flow differs by {flow}");
            assert!(img <= 1, "object image differs by {img} levels");
            assert!(drawn > 500);
            assert!(drawn_diff as f64 <= 0.005 * drawn as f64, "{drawn_diff} of {drawn} object pixels differ");
            let mut differ = 0;
            for i in 0..w * h {
                if windowed.mask2[i] == 0 && full.mask2[i] == 0 {
                    let d = (0..3)
                        .map(|c| (windowed.image2[3 * i + c] as i32 - full.image2[3 * i + c] as i32).abs())
                        .max()
                        .unwrap();
                    differ += usize::from(d > 1);
                    assert!((windowed.flow[2 * i] - full.flow[2 * i]).abs() < 1e-4);
                }
            }
            println!("{rule:?}: {differ} background pixels differ by more than 1 level");
            assert!(differ as f64 <= 0.001 * (w * h) as f64, "{differ} background pixels differ");
            assert_eq!(windowed.inpainted_pixels, full.inpainted_pixels);
            // the object renders are the same renderer's values, bit for bit; the scene mask is
            // coverage - render(U) instead of render(1 - U), which differs by f32 rounding only
            // and flips no merge decision in this scene: the samples are identical
            assert_eq!(windowed.image2, full.image2, "{rule:?}: image2");
            assert_eq!(windowed.flow, full.flow, "{rule:?}: flow");
            assert_eq!(windowed.occlusion, full.occlusion, "{rule:?}: occlusion");
            assert_eq!(windowed.mask1, full.mask1, "{rule:?}: mask1");
            assert_eq!(windowed.mask2, full.mask2, "{rule:?}: mask2");
            assert_eq!(windowed.valid, full.valid, "{rule:?}: valid");
            assert_eq!(windowed.depth2, full.depth2, "{rule:?}: depth2");
            let mut windowed = windowed;
            windowed.timings = full.timings;
            assert_eq!(windowed, full, "{rule:?}: the whole sample");
        }
    }
}

#[test]
fn windows_hold_the_footprints() {
    let (w, h) = (128, 96);
    let scene = textured_scene(w, h, 8);
    let k = scene.intrinsics;
    let mpi = &scene.mpi;
    let support = support_rect(&scene.masks.masks[0].mask, w, h).unwrap();
    let pose = Pose::from_axis_angle([0.01, -0.02, 0.01], [0.15, -0.1, -0.2]);
    let (near, far) = (mpi.disparity[0], mpi.disparity[mpi.planes() - 1]);
    let t = target_footprint(&support, &k, &pose, near, far, w, h).unwrap();
    // every support pixel lands inside the footprint on every plane (or leaves the image)
    for i in 0..mpi.planes() {
        let hom = mpiflow::geometry::plane_homography(&k, &k, &pose, mpi.depth(i));
        for y in support.y0..support.y1 {
            for x in support.x0..support.x1 {
                let (u, v, _) = mpiflow::geometry::apply_homography(&hom, x as f64, y as f64);
                if u >= 0.0 && v >= 0.0 && u <= (w - 1) as f64 && v <= (h - 1) as f64 {
                    assert!(t.contains(u as usize, v as usize), "plane {i}: ({x},{y}) -> ({u},{v}) outside {t:?}");
                }
            }
        }
    }
    let win = scene_mask_window(mpi, &k, &pose, &support);
    assert!(win.union(&t) == win);
    assert!(win.area() < w * h / 2, "the window should be much smaller than the frame here: {win:?}");
    let ow = object_window(mpi, &k, &pose, &support);
    assert!(ow.union(&support) == ow && ow.union(&t) == ow);
}

#[test]
fn without_objects_the_sample_is_the_scene_render() {
    let (w, h) = (128, 96);
    let mut scene = textured_scene(w, h, 16);
    let cam = rigid([0.1, -0.05, -0.1], [0.01, 0.0, -0.01]);
    let obj = rigid([0.05, 0.0, 0.0], [0.0; 3]);
    let mut cfg = config(cam, obj, MergeRule::DepthAware);
    cfg.max_objects = 0;
    let none = assemble(&scene, ADDR, &cfg).unwrap();
    assert!(none.objects.is_empty());
    assert!(none.mask1.iter().chain(&none.mask2).all(|&v| v == 0));
    // the same as a scene that has no instances at all
    let mut bare = scene.clone();
    bare.masks = InstanceMasks::new(w, h);
    cfg.max_objects = 3;
    let mut bare_sample = assemble(&bare, ADDR, &cfg).unwrap();
    bare_sample.timings = none.timings;
    assert_eq!(bare_sample, none);
    // and the flow / valid are the renderer's own
    let mut p = RenderParams::new(scene.intrinsics, cam_pose(&cam));
    p.skip = Skip::DEFAULT;
    p.fields = Fields { target: true, flow: true, occlusion: false };
    let out = render::<f32>(&scene.mpi, &p, None).unwrap();
    assert_eq!(none.flow, out.flow);
    assert_eq!(none.valid, out.valid);
    let holes = out.coverage.iter().filter(|&&c| c < 0.99).count() as u64;
    assert_eq!(none.inpainted_pixels, holes);
    // an object too small for min_object_area_fraction does not move either
    cfg.min_object_area_fraction = 0.5;
    scene.id = "small".into();
    let small = assemble(&scene, ADDR, &cfg).unwrap();
    assert!(small.objects.is_empty());
}

fn cam_pose(law: &RigidLaw) -> Pose {
    let b = |c: &Component| c.bounds().0;
    Pose::from_axis_angle(
        [b(&law.rotation.x), b(&law.rotation.y), b(&law.rotation.z)],
        [b(&law.translation.x), b(&law.translation.y), b(&law.translation.z)],
    )
}

/// `T_src` of the shared reference vectors (`case_tx`; `case_cam` has the same MPI) at
/// (plane, y, x), from the reference implementation in float64.
const T_SRC_GOLDEN: [(usize, usize, usize, f64); 16] = [
    (3, 24, 48, 0.19821888954683123),
    (7, 1, 9, 0.0044116747631713065),
    (6, 45, 15, 0.008413567030743176),
    (2, 41, 27, 0.9805971625487988),
    (2, 39, 16, 0.9965980188087656),
    (3, 30, 35, 0.013906280806448146),
    (0, 1, 55, 1.0),
    (6, 40, 34, 0.008973083036224226),
    (6, 15, 28, 0.013476699052263313),
    (6, 5, 19, 0.0754639185009562),
    (4, 14, 29, 0.7424842699525324),
    (3, 14, 46, 0.9274296920035929),
    (2, 36, 50, 0.9237911321950077),
    (7, 20, 0, 0.6868005438028532),
    (4, 38, 21, 0.5134924460117856),
    (4, 16, 59, 0.40346532537706437),
];

/// The pre-blend's transmittance is the reference's `T_src` (its `blend_weights`), and
/// pre-blending a black MPI with a white photo gives exactly `T_src` on every plane.
#[test]
fn preblend_uses_the_reference_source_transmittance() {
    let path = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/case_tx.npz");
    let mpi = load_npz(&path).unwrap();
    let k = mpi.intrinsics.unwrap();
    let (w, h) = (mpi.width, mpi.height);
    let t = source_transmittance(&mpi, &k);
    assert_eq!(t.len(), mpi.planes() * w * h);
    for (i, y, x, want) in T_SRC_GOLDEN {
        let got = t[i * w * h + y * w + x] as f64;
        assert!((got - want).abs() < 2e-6, "T_src[{i}, {y}, {x}] = {got}, reference {want}");
    }

    let mut black = mpi.clone();
    black.rgba.chunks_exact_mut(4).for_each(|p| p[..3].fill(0.0));
    let white = vec![1.0f32; w * h * 3];
    preblend(&mut black, &white, &k).unwrap();
    for (i, p) in black.rgba.chunks_exact(4).enumerate() {
        assert!(
            (p[0] - t[i]).abs() < 1e-6 && p[0] == p[1] && p[1] == p[2],
            "plane {} pixel {}",
            i / (w * h),
            i % (w * h)
        );
        assert_eq!(p[3], mpi.rgba[4 * i + 3], "densities are untouched");
    }
    // the blend itself: T * photo + (1 - T) * rgb
    let photo: Vec<f32> = (0..w * h * 3).map(|i| (i % 7) as f32 / 7.0).collect();
    let mut m = mpi.clone();
    preblend(&mut m, &photo, &k).unwrap();
    for (i, y, x, _) in T_SRC_GOLDEN {
        let o = i * w * h + y * w + x;
        for c in 0..3 {
            let want = t[o] * photo[3 * (y * w + x) + c] + (1.0 - t[o]) * mpi.rgba[4 * o + c];
            assert!((m.rgba[4 * o + c] - want).abs() < 1e-6);
        }
    }
}

#[test]
fn preblend_leaves_the_source_view_of_a_layered_mpi_unchanged() {
    let scene = textured_scene(96, 64, 8);
    let mut mpi = (*scene.mpi).clone();
    preblend(&mut mpi, &scene.image.data, &scene.intrinsics).unwrap();
    let p = RenderParams::new(scene.intrinsics, Pose::identity());
    let before = render::<f32>(&scene.mpi, &p, None).unwrap();
    let after = render::<f32>(&mpi, &p, None).unwrap();
    let worst = before.image.iter().zip(&after.image).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
    println!("identity render changed by at most {worst:.2e}");
    assert!(worst < 1e-3);
    // and the size is checked
    assert!(preblend(&mut mpi, &[0.0; 3], &scene.intrinsics).is_err());
}

/// Inpainting on crops around the hole groups gives the whole-frame result bit for bit.
#[test]
fn cropped_inpainting_equals_whole_frame_inpainting() {
    let (w, h) = (160, 120);
    let img: Vec<u8> = (0..w * h * 3)
        .map(|i| {
            let (p, c) = (i / 3, i % 3);
            let (x, y) = ((p % w) as f32, (p / w) as f32);
            (128.0 + 60.0 * (x / 7.0 + c as f32).sin() + 50.0 * (y / 5.0).cos() + ((p * 7919) % 23) as f32) as u8
        })
        .collect();
    let mut hole = vec![0u8; w * h];
    let mut put = |x: usize, y: usize| hole[y * w + x] = 1;
    // a disc, a border strip, a one-pixel line, scattered pixels, two holes close together
    for y in 0..h {
        for x in 0..w {
            let (dx, dy) = (x as f32 - 60.0, y as f32 - 50.0);
            if dx * dx + dy * dy < 300.0
                || x < 6
                || (y == 100 && (20..140).contains(&x))
                || (x * 31 + y * 17) % 211 == 0
            {
                put(x, y);
            }
            if (120..126).contains(&x) && (10..20).contains(&y) || (128..131).contains(&x) && (12..30).contains(&y) {
                put(x, y);
            }
        }
    }
    for method in
        [InpaintMethod::Telea, InpaintMethod::TeleaKnownOnly, InpaintMethod::TeleaZeroOrder, InpaintMethod::TeleaOpencv]
    {
        for radius in [1.0f32, 3.0, 5.0, 7.5] {
            let mut a = img.clone();
            let mut b = img.clone();
            inpaint_holes(&mut a, w, h, &hole, method, radius, true);
            inpaint_holes(&mut b, w, h, &hole, method, radius, false);
            assert!(a == b, "{method:?} radius {radius}: cropped and whole-frame inpainting differ");
            assert!(a.iter().zip(&img).zip(hole.iter().flat_map(|&v| [v; 3])).all(|((x, y), m)| m != 0 || x == y));
            // from the background only: an object beside the disc and inside the two close holes
            let labels: Vec<u8> = (0..w * h)
                .map(|i| u8::from(hole[i] == 0 && ((76..84).contains(&(i % w)) || (126..128).contains(&(i % w)))))
                .collect();
            let mut a = img.clone();
            let mut b = img.clone();
            inpaint_background(&mut a, w, h, &hole, &labels, method, radius, true);
            inpaint_background(&mut b, w, h, &hole, &labels, method, radius, false);
            assert!(a == b, "{method:?} radius {radius}: cropped and whole-frame background fills differ");
        }
    }
}

/// Degenerate sizes and the reference mode: defined, finite results.
#[test]
fn tiny_scenes_and_the_reference_mode_give_finite_samples() {
    for (w, h) in [(1usize, 1usize), (2, 1), (1, 3), (5, 4)] {
        let k = Intrinsics::reference_default(w, h);
        let rgb: Vec<f32> = (0..w * h * 3).map(|i| (i % 5) as f32 / 5.0).collect();
        let depth: Vec<f32> = (0..w * h).map(|i| 1.0 + (i % 3) as f32).collect();
        let opts = LayeringOptions {
            planes: 4,
            layering: Layering::Soft,
            disparity_range: None,
            backdrop: false,
            ..LayeringOptions::default()
        };
        let mpi = build_mpi_for_camera(&rgb, &depth, w, h, &opts, &k).unwrap();
        let mut mask = vec![0.0f32; w * h];
        mask[0] = 1.0;
        let scene = Scene {
            id: format!("tiny-{w}x{h}"),
            image: RgbImage { width: w, height: h, data: rgb },
            disparity: Disparity { width: w, height: h, data: depth.iter().map(|d| 1.0 / d).collect() },
            mpi: Arc::new(mpi),
            masks: InstanceMasks { width: w, height: h, masks: vec![Instance::new(1, 1.0, mask)] },
            intrinsics: k,
            provenance: vec![],
        };
        for mode in [mpiflow::render::Mode::Exact, mpiflow::render::Mode::Reference] {
            for merge_rule in [MergeRule::DepthAware, MergeRule::Reference] {
                let cfg =
                    SampleConfig { mode, merge: merge_rule, min_object_area_fraction: 0.0, ..SampleConfig::default() };
                let s = assemble(&scene, ADDR, &cfg).unwrap();
                assert_eq!(s.objects.len(), 1, "{w}x{h} {mode:?}");
                assert_eq!((s.image2.len(), s.flow.len()), (3 * w * h, 2 * w * h));
                assert!(s.flow.iter().all(|v| v.is_finite()));
                assert_eq!(s.mask1[0], 1);
            }
        }
    }
}
