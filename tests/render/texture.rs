//! The texture fill of image2's holes (`sample::holes`, "Texture"): a hole in a textured frame
//! gets the photo's texture back (detail and noise near the rest, where Telea's blend has next to
//! none), never an object's colour nor a pixel beside an object, however thin, never something
//! nearer than the background beside it; the result does not depend on the number of threads;
//! and on the real RGB-D photo the revealed regions of image2 are harder to tell from the photo
//! than with Telea.

use std::path::PathBuf;
use std::sync::Arc;

use mpiflow::bench::quality::quality_same_motions;
use mpiflow::sample::config::{InpaintMethod, SampleConfig};
use mpiflow::sample::holes::{fill_holes, inpaint_holes, texture_fill, TextureSource};
use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;

const W: usize = 96;
const H: usize = 72;

/// A grainy texture (a hash per pixel around a slow gradient), u8 RGB.
fn texture(w: usize, h: usize, key: u64) -> Vec<u8> {
    let mut out = Vec::with_capacity(3 * w * h);
    for p in 0..w * h {
        let r = mpiflow::rng::mix64(p as u64 ^ key);
        let base = 60.0 + 80.0 * (p % w) as f64 / w as f64;
        for c in 0..3 {
            let grain = ((r >> (8 * c)) & 0xff) as f64 / 255.0 - 0.5;
            out.push((base + 70.0 * grain + 10.0 * c as f64).round() as u8);
        }
    }
    out
}

/// Variance of the 4-neighbour Laplacian of the luminance over the pixels where `inside`.
fn laplacian_variance(img: &[u8], w: usize, h: usize, inside: impl Fn(usize) -> bool) -> f64 {
    let lum = |p: usize| (u32::from(img[3 * p]) + u32::from(img[3 * p + 1]) + u32::from(img[3 * p + 2])) as f64 / 3.0;
    let mut v = Vec::new();
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let p = y * w + x;
            if inside(p) {
                v.push(4.0 * lum(p) - lum(p - 1) - lum(p + 1) - lum(p - w) - lum(p + w));
            }
        }
    }
    let m = v.iter().sum::<f64>() / v.len() as f64;
    v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / v.len() as f64
}

/// A disc hole of radius 12 in the middle and a strip entering at the right edge.
fn holes() -> Vec<u8> {
    (0..W * H)
        .map(|p| {
            let (x, y) = ((p % W) as f64 - 48.0, (p / W) as f64 - 36.0);
            u8::from(x * x + y * y <= 144.0 || p % W >= W - 6)
        })
        .collect()
}

#[test]
fn a_hole_in_a_textured_frame_gets_texture_back_and_telea_does_not() {
    let photo = texture(W, H, 1);
    let hole = holes();
    let depth = vec![2.0f32; W * H];
    let frame_depth: Vec<f32> = hole.iter().map(|&o| if o != 0 { 0.0 } else { 2.0 }).collect();
    let (objects, labels) = (vec![false; W * H], vec![0u8; W * H]);
    let tex = TextureSource {
        image1: &photo,
        depth1: &depth,
        objects: &objects,
        depth: &frame_depth,
        mask: &labels,
        labels1: &labels,
        z_shift: 0.0,
    };
    let mut blank = photo.clone();
    for p in (0..W * H).filter(|&p| hole[p] != 0) {
        blank[3 * p..3 * p + 3].copy_from_slice(&[0, 0, 0]);
    }
    let mut textured = blank.clone();
    let left = texture_fill(&mut textured, W, H, &hole, &tex).left;
    assert!(!left.contains(&1), "every hole pixel found a source");
    let mut telea = blank.clone();
    inpaint_holes(&mut telea, W, H, &hole, InpaintMethod::TeleaKnownOnly, 3.0, true);
    let in_hole = |p: usize| hole[p] != 0 && (p % W) < W - 6;
    let rest = laplacian_variance(&photo, W, H, |p| hole[p] == 0);
    let tex_var = laplacian_variance(&textured, W, H, in_hole);
    let telea_var = laplacian_variance(&telea, W, H, in_hole);
    println!("Laplacian variance: photo {rest:.1}, texture fill {tex_var:.1}, Telea {telea_var:.1}");
    assert!(tex_var >= 0.8 * rest && tex_var <= 1.25 * rest, "texture {tex_var} against {rest}");
    assert!(telea_var < 0.3 * rest, "Telea {telea_var} against {rest}");
    // only hole pixels change
    for p in (0..W * H).filter(|&p| hole[p] == 0) {
        assert_eq!(&textured[3 * p..3 * p + 3], &blank[3 * p..3 * p + 3]);
    }
}

#[test]
fn the_fill_never_copies_an_object_nor_what_is_nearer_than_the_background() {
    // left half: a near red object (an instance) and a near green surface (not an object, but
    // nearer than the background beside the hole); right half: the far grey background
    let mut photo = texture(W, H, 2);
    let mut depth = vec![4.0f32; W * H];
    let mut objects = vec![false; W * H];
    for p in 0..W * H {
        let (x, y) = (p % W, p / W);
        if x < 30 && y < H / 2 {
            photo[3 * p..3 * p + 3].copy_from_slice(&[230, 20, 20]);
            objects[p] = true;
            depth[p] = 1.0;
        } else if x < 30 {
            photo[3 * p..3 * p + 3].copy_from_slice(&[20, 230, 20]);
            depth[p] = 1.0;
        }
    }
    // the hole: the object's place moved a little to the right, in the far background
    let hole: Vec<u8> =
        (0..W * H).map(|p| u8::from((30..44).contains(&(p % W)) && (4..H - 10).contains(&(p / W)))).collect();
    let frame_depth: Vec<f32> = (0..W * H).map(|p| if hole[p] != 0 { 0.0 } else { depth[p] }).collect();
    // the frame is image1 with the hole: its object keeps its label
    let labels: Vec<u8> = objects.iter().map(|&o| u8::from(o)).collect();
    let tex = TextureSource {
        image1: &photo,
        depth1: &depth,
        objects: &objects,
        depth: &frame_depth,
        mask: &labels,
        labels1: &labels,
        z_shift: 0.0,
    };
    let mut img = photo.clone();
    let left = texture_fill(&mut img, W, H, &hole, &tex).left;
    let mut filled = 0;
    for p in (0..W * H).filter(|&p| hole[p] != 0 && left[p] == 0) {
        filled += 1;
        let c = &img[3 * p..3 * p + 3];
        assert!(!(c[0] > 200 && c[1] < 40), "object colour {c:?} at {p}");
        assert!(!(c[1] > 200 && c[0] < 40), "near surface {c:?} at {p}");
    }
    assert!(filled * 10 >= hole.iter().filter(|&&o| o != 0).count() * 9, "{filled} filled");
}

#[test]
fn no_source_lies_within_three_pixels_of_an_object_however_thin() {
    // image1: grey far background with vertical objects one pixel wide every 12 columns, and the
    // two columns either side of each object pink (a mask edge rarely sits exactly on the
    // object); the frame around the hole is pink, so a pink source would match best
    const PINK: [u8; 3] = [200, 50, 200];
    let line = |x: usize| x % 12 == 6;
    let beside = |x: usize| (1..=2).any(|d| (x >= d && line(x - d)) || line(x + d));
    let mut photo = vec![120u8; 3 * W * H];
    let objects: Vec<bool> = (0..W * H).map(|p| line(p % W)).collect();
    for p in 0..W * H {
        if objects[p] || beside(p % W) {
            photo[3 * p..3 * p + 3].copy_from_slice(&PINK);
        }
    }
    let depth = vec![4.0f32; W * H];
    let hole: Vec<u8> =
        (0..W * H).map(|p| u8::from((40..52).contains(&(p % W)) && (30..42).contains(&(p / W)))).collect();
    let frame_depth: Vec<f32> = (0..W * H).map(|p| if hole[p] != 0 { 0.0 } else { 4.0 }).collect();
    let none = vec![0u8; W * H];
    let tex = TextureSource {
        image1: &photo,
        depth1: &depth,
        objects: &objects,
        depth: &frame_depth,
        mask: &none,
        labels1: &none,
        z_shift: 0.0,
    };
    let mut img: Vec<u8> = (0..W * H).flat_map(|p| if hole[p] != 0 { [0, 0, 0] } else { PINK }).collect();
    let left = texture_fill(&mut img, W, H, &hole, &tex).left;
    let mut filled = 0;
    for p in (0..W * H).filter(|&p| hole[p] != 0 && left[p] == 0) {
        filled += 1;
        assert_eq!(&img[3 * p..3 * p + 3], &[120, 120, 120], "a source beside a thin object at {p}");
    }
    assert!(filled * 10 >= hole.iter().filter(|&&o| o != 0).count() * 9, "{filled} filled");
}

#[test]
fn what_enters_beside_a_moved_object_that_reaches_the_border_is_more_of_that_object() {
    // image1: a red-textured object over the left 40 columns (reaching the frame's left border),
    // grey-textured background elsewhere; the object moves 8 pixels to the right, so a strip of 8
    // columns enters at the left edge beside it, and the background's strip enters at the right
    let grain = texture(W, H, 5);
    let mut photo = texture(W, H, 4);
    let mut labels1 = vec![0u8; W * H];
    for p in (0..W * H).filter(|&p| p % W < 40) {
        let g = &grain[3 * p..3 * p + 3];
        photo[3 * p..3 * p + 3].copy_from_slice(&[g[0].saturating_add(80), g[1] / 3, g[2] / 3]);
        labels1[p] = 1;
    }
    let objects: Vec<bool> = labels1.iter().map(|&l| l != 0).collect();
    let depth: Vec<f32> = labels1.iter().map(|&l| if l != 0 { 1.0 } else { 3.0 }).collect();
    let shift = 8;
    let mut frame = photo.clone();
    let mut mask2 = vec![0u8; W * H];
    let mut hole = vec![0u8; W * H];
    for p in 0..W * H {
        let x = p % W;
        if x < shift || x >= W - 4 {
            hole[p] = 1;
        } else if x < 40 + shift {
            let q = p - shift;
            frame[3 * p..3 * p + 3].copy_from_slice(&photo[3 * q..3 * q + 3]);
            mask2[p] = 1;
        }
    }
    let frame_depth: Vec<f32> = (0..W * H)
        .map(|p| {
            if hole[p] != 0 {
                0.0
            } else if mask2[p] != 0 {
                1.0
            } else {
                3.0
            }
        })
        .collect();
    let tex = TextureSource {
        image1: &photo,
        depth1: &depth,
        objects: &objects,
        depth: &frame_depth,
        mask: &mask2,
        labels1: &labels1,
        z_shift: 0.0,
    };
    let mut img = frame.clone();
    let fill = texture_fill(&mut img, W, H, &hole, &tex);
    assert!(!fill.left.contains(&1), "every hole pixel found a source");
    // the strip drawn as the object carries its label (for the frame's mask), the other none
    for (p, (&got, &o)) in fill.continued.iter().zip(&hole).enumerate() {
        let want = u8::from(o != 0 && p % W < shift);
        assert_eq!(got, want, "label at ({}, {})", p % W, p / W);
    }
    let reddish = |p: usize| img[3 * p] > img[3 * p + 1].saturating_add(60);
    let (entering_left, entering_right): (Vec<usize>, Vec<usize>) =
        (0..W * H).filter(|&p| hole[p] != 0).partition(|&p| p % W < shift);
    let red_left = entering_left.iter().filter(|&&p| reddish(p)).count();
    let red_right = entering_right.iter().filter(|&&p| reddish(p)).count();
    println!(
        "object colour: {red_left} of {} beside the object, {red_right} of {} beside the background",
        entering_left.len(),
        entering_right.len()
    );
    assert_eq!(red_left, entering_left.len(), "the object continues where it enters");
    assert_eq!(red_right, 0, "the background continues where it enters");
    let in_strip = |p: usize| hole[p] != 0 && (1..shift).contains(&(p % W));
    let object_rows = |p: usize| labels1[p] != 0 && p % W > 3 && p % W < 36;
    let (strip, object) = (laplacian_variance(&img, W, H, in_strip), laplacian_variance(&photo, W, H, object_rows));
    println!("Laplacian variance: strip {strip:.1}, the object in image1 {object:.1}");
    assert!(strip >= 0.7 * object && strip <= 1.4 * object, "strip {strip} against {object}");
}

#[test]
fn the_fill_is_the_same_on_any_number_of_threads_and_fill_holes_uses_it() {
    let photo = texture(W, H, 3);
    let hole = holes();
    let depth = vec![2.0f32; W * H];
    let frame_depth: Vec<f32> = hole.iter().map(|&o| if o != 0 { 0.0 } else { 2.5 }).collect();
    let (objects, labels) = (vec![false; W * H], vec![0u8; W * H]);
    let tex = TextureSource {
        image1: &photo,
        depth1: &depth,
        objects: &objects,
        depth: &frame_depth,
        mask: &labels,
        labels1: &labels,
        z_shift: 0.4,
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        let mut img = photo.clone();
        let continued = pool.install(|| fill_holes(&mut img, W, H, &hole, InpaintMethod::Exemplar, 3.0, &tex));
        assert!(continued.is_empty(), "no object continues");
        img
    };
    let one = run(1);
    assert_eq!(one, run(2));
    assert_eq!(one, run(3));
    let mut direct = photo.clone();
    texture_fill(&mut direct, W, H, &hole, &tex);
    assert_eq!(one, direct);
}

#[test]
fn on_the_real_rgbd_photo_the_revealed_regions_keep_the_photos_detail() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/rgbd/cones");
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let source = open_source(&SourceSpec::Path(dir), &OpenOptions::default()).unwrap();
    let p = Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 28)), SampleConfig::default()).unwrap();
    let run = |inpaint_method| {
        let c = SampleConfig { inpaint_method, backward: true, ..SampleConfig::default() };
        quality_same_motions(p.generator(), &c, 0, 8).unwrap()
    };
    let telea = run(InpaintMethod::TeleaKnownOnly);
    let texture = run(InpaintMethod::Exemplar);
    for (name, r) in [("telea", &telea), ("exemplar", &texture)] {
        println!(
            "{name}: holes {:.4}, detail {:?}, noise {:?}, AUC revealed {:?}, photometric {:.4}, laws {:?}",
            r.hole_fraction,
            r.realism.revealed_detail,
            r.realism.revealed_noise,
            r.realism.auc_revealed,
            r.photometric,
            r.laws
        );
        assert_eq!(r.laws.holes + r.laws.label + r.laws.depth, 0, "{name}: {:?}", r.laws);
    }
    // the same motions: the same holes and labels, only their colour differs
    assert_eq!(telea.hole_fraction, texture.hole_fraction);
    assert_eq!(telea.photometric, texture.photometric);
    let detail = texture.realism.revealed_detail.unwrap();
    let noise = texture.realism.revealed_noise.unwrap();
    assert!(detail >= 0.8 && noise >= 0.8, "detail {detail}, noise {noise}");
    assert!(telea.realism.revealed_detail.unwrap() < 0.8, "Telea's blend loses detail");
    let (a, b) = (texture.realism.auc_revealed.unwrap(), telea.realism.auc_revealed.unwrap());
    assert!(a + 0.05 <= b, "AUC revealed: texture {a}, Telea {b}");
}
