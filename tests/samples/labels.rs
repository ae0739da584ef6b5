//! Honest labels with moving objects: on RGB-D photos with large object masks that
//! span many depths and on the bundled scenes, under several motion laws, seeds and both merge
//! rules, every valid, non-occluded pixel's flow lands on the surface it names (the label laws
//! of `mpiflow::bench::quality`): no hole next to the target, the object label shown there, the
//! depth shown there within the occlusion tolerance. The earlier rule (`label_rule =
//! "depth-only"`) breaks them on the same samples, so the laws see what the rule fixes.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use mpiflow::bench::quality::{label_laws, quality, thin_line_runs, LawCounts, QualityReport};
use mpiflow::io::npy;
use mpiflow::raster::InstanceMasks;
use mpiflow::sample::background::Background;
use mpiflow::sample::config::{MotionSpec, SampleConfig};
use mpiflow::sample::merge::{LabelRule, MergeRule};
use mpiflow::sample::motion::{Axes, Component, MotionPreset, MotionRanges, RigidLaw, RotationKind};
use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;

const REPO: &str = env!("CARGO_MANIFEST_DIR");

fn tmpdir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("mpiflow-labels-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A large mask: the rectangle `[x0, x1) x [y0, y1)` (fractions of the frame) as instance 1.
fn rect_mask(path: &Path, w: usize, h: usize, r: [f64; 4]) {
    let mut ids = vec![0u32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (s, t) = (x as f64 / w as f64, y as f64 / h as f64);
            if s >= r[0] && s < r[1] && t >= r[2] && t < r[3] {
                ids[y * w + x] = 1;
            }
        }
    }
    InstanceMasks::from_index_map(&ids, w, h).unwrap().save_index_png(path).unwrap();
}

/// RGB-D photos in the reference layout, each with one mask covering about a third of the frame
/// and spanning many depths: the cat photo with its slanted-background depth (the mask takes
/// the cat and much of the background around it), and the coffee photo on a receding floor
/// (depth 1.2 at the bottom row to 7 at the top, the mask a block standing on and including the
/// floor).
fn photos(name: &str) -> PathBuf {
    let root = tmpdir(name);
    for d in ["images", "depths", "masks"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    let data = Path::new(REPO).join("examples/data");
    std::fs::copy(data.join("images/chelsea.png"), root.join("images/chelsea.png")).unwrap();
    std::fs::copy(data.join("depths/chelsea.npy"), root.join("depths/chelsea.npy")).unwrap();
    rect_mask(&root.join("masks/chelsea.png"), 451, 300, [0.2, 0.78, 0.3, 0.92]);
    let coffee = Path::new(REPO).join("examples/photos/coffee.png");
    let img = image::open(&coffee).unwrap();
    let (w, h) = (img.width() as usize, img.height() as usize);
    std::fs::copy(&coffee, root.join("images/coffee.png")).unwrap();
    let depth: Vec<f32> = (0..w * h)
        .map(|i| {
            let t = (i / w) as f32 / h as f32;
            1.2 + 5.8 * (1.0 - t).powi(2)
        })
        .collect();
    npy::write_f32(&root.join("depths/coffee.npy"), &[h as u64, w as u64], &depth).unwrap();
    rect_mask(&root.join("masks/coffee.png"), w, h, [0.22, 0.78, 0.38, 1.0]);
    root
}

fn pipeline(spec: SourceSpec, size: (usize, usize)) -> Pipeline {
    let stage = Arc::new(ModelConfig::default().build_stage().unwrap());
    let source = open_source(&spec, &OpenOptions { resize: Some(size), ..OpenOptions::default() }).unwrap();
    Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 28)), SampleConfig::default()).unwrap()
}

fn config(preset: MotionPreset, merge: MergeRule, label_rule: LabelRule) -> SampleConfig {
    SampleConfig { motion: MotionSpec::Preset(preset), merge, label_rule, ..SampleConfig::default() }
}

/// The laws over `count` samples of every (preset, seed) under `merge` and `rule`.
fn laws(p: &Pipeline, merge: MergeRule, rule: LabelRule, count: u64) -> (LawCounts, usize) {
    let mut total = LawCounts::default();
    let mut with_objects = 0;
    for preset in MotionPreset::ALL {
        let g = p.generator().with_config(config(preset, merge, rule)).unwrap();
        for seed in [0u64, 7] {
            for index in 0..count {
                let (s, z) = g.sample_with_target_depth(seed, index).unwrap();
                with_objects += usize::from(!s.objects.is_empty());
                total.add(&label_laws(&s, &z));
            }
        }
    }
    (total, with_objects)
}

fn rates(c: &LawCounts) -> String {
    format!(
        "checked {} holes {:.4}% label {:.4}% depth {:.4}%",
        c.checked,
        100.0 * c.rate(c.holes),
        100.0 * c.rate(c.label),
        100.0 * c.rate(c.depth)
    )
}

fn check_laws(name: &str, p: &Pipeline, count: u64) {
    for merge in [MergeRule::DepthAware, MergeRule::Reference] {
        let (after, objects) = laws(p, merge, LabelRule::Honest, count);
        let (before, _) = laws(p, merge, LabelRule::DepthOnly, count);
        println!("{name} {merge:?}: before (depth-only) {}", rates(&before));
        println!("{name} {merge:?}: after  (honest)     {}", rates(&after));
        assert!(objects > 0, "{name}: some samples move an object");
        assert!(after.checked * 2 > before.checked, "{name} {merge:?}: most pixels stay usable");
        for (law, n) in [("holes", after.holes), ("label", after.label), ("depth", after.depth)] {
            assert!(after.rate(n) <= 1e-3, "{name} {merge:?}: law {law} broken on {n} of {} pixels", after.checked);
        }
        // the laws see what the earlier rule let through
        assert!(before.holes + before.label + before.depth > 0, "{name} {merge:?}: {}", rates(&before));
    }
}

#[test]
fn labels_are_honest_on_rgbd_photos_with_large_masks() {
    let root = photos("laws");
    let p = pipeline(SourceSpec::Path(root.clone()), (150, 100));
    check_laws("photos", &p, 4);
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn labels_are_honest_on_the_bundled_scenes() {
    let p = pipeline(SourceSpec::Builtin, (128, 96));
    check_laws("builtin", &p, 3);
}

fn show(name: &str, r: &QualityReport) {
    println!(
        "{name}: photometric {:.4} (background {:.4}), holes {:.4}, lines {} vs {}, valid {:.3} occluded {:.3}, \
         flow p5/p50/p95 {:.2}/{:.2}/{:.2}, laws {}",
        r.photometric,
        r.photometric_background,
        r.hole_fraction,
        r.lines2,
        r.lines1,
        r.valid_fraction,
        r.occluded_fraction,
        r.flow_p5,
        r.flow_p50,
        r.flow_p95,
        rates(&r.laws)
    );
}

/// With one moving object the photometric error of the honest labels stays near the error
/// without objects, on photos with masks that span many depths; printed for both rules.
#[test]
fn photometric_error_with_objects_is_near_the_error_without() {
    let root = photos("photometric");
    let p = pipeline(SourceSpec::Path(root.clone()), (150, 100));
    let rules = [
        (MergeRule::DepthAware, Background::Inpaint),
        (MergeRule::DepthAware, Background::Planes),
        (MergeRule::Reference, Background::Inpaint),
    ];
    for (merge, background) in rules {
        let base = SampleConfig { background, ..config(MotionPreset::Reference, merge, LabelRule::Honest) };
        let none = quality(p.generator(), &SampleConfig { max_objects: 0, ..base.clone() }, 0, 8).unwrap();
        let one = quality(p.generator(), &base, 0, 8).unwrap();
        let old =
            quality(p.generator(), &SampleConfig { label_rule: LabelRule::DepthOnly, ..base.clone() }, 0, 8).unwrap();
        show(&format!("{merge:?} {background} no objects"), &none);
        show(&format!("{merge:?} {background} one object, honest"), &one);
        show(&format!("{merge:?} {background} one object, depth-only"), &old);
        assert_eq!(one.with_objects, 8);
        assert!(one.photometric < old.photometric, "{merge:?} {background}: honest labels agree better with image2");
        // the goal: within 1.3 times the error without objects; the laws hold
        assert!(
            one.photometric <= 1.3 * none.photometric,
            "{merge:?} {background}: {} with an object, {} without",
            one.photometric,
            none.photometric
        );
        for (law, n) in [("holes", one.laws.holes), ("label", one.laws.label), ("depth", one.laws.depth)] {
            assert!(one.laws.rate(n) <= 1e-3, "{merge:?} {background}: law {law} broken on {n} pixels");
        }
    }
    std::fs::remove_dir_all(root).unwrap();
}

/// The reference camera law with an object law of fixed direction: `forward` moves the object
/// towards the camera by 0.05 to 0.1, else sideways by 0.05 to 0.1 (random sign), no rotation.
fn object_law(forward: bool) -> MotionRanges {
    let mut r = MotionPreset::Reference.ranges();
    let zero = Component::constant(0.0);
    let amount = Component::RandomSign { min: 0.05, max: 0.1 };
    r.object = RigidLaw {
        translation: if forward {
            Axes::new(zero, zero, Component::Forward { min: 0.05, max: 0.1 })
        } else {
            Axes::new(amount, zero, zero)
        },
        rotation_kind: RotationKind::AxisAngle,
        rotation: Axes::splat(zero),
    };
    r.name = if forward { "object-forward" } else { "object-lateral" }.into();
    r
}

/// Thin one-pixel lines: with a mask spanning many depths (the photos above at 740 x 493) under
/// the default law and under forward and lateral object motion, image2 has no more thin-line
/// runs than image1 (seed 0), and over five seeds the depth-aware merge draws few one-row label
/// slivers (a row of object between rows of scene, or the reverse): at most one run per two
/// samples. (Measured for comparison: with the paper's exact depth comparison in the
/// depth-aware merge, image2 has 13 runs against image1's 6 under the default law, 7 against 6
/// under lateral motion; with the depth maps upsampled by nearest neighbour and the occlusion
/// test on single pixels, seeds 0-4 give 31, 4 and 37 sliver runs in 30 samples under the
/// default, forward and lateral laws, where this merge gives 4, 0 and 5.)
#[test]
fn no_thin_lines_with_masks_spanning_many_depths() {
    let root = photos("lines");
    let p = pipeline(SourceSpec::Path(root.clone()), (740, 493));
    let laws = [
        ("default", MotionSpec::default()),
        ("forward", MotionSpec::Ranges(Box::new(object_law(true)))),
        ("lateral", MotionSpec::Ranges(Box::new(object_law(false)))),
    ];
    for merge in [MergeRule::DepthAware, MergeRule::Reference] {
        for (law, motion) in &laws {
            let c = SampleConfig { motion: motion.clone(), merge, ..SampleConfig::default() };
            let g = p.generator().with_config(c).unwrap();
            let (mut lines1, mut lines2, mut slivers, mut samples) = (0, 0, 0, 0);
            // the reference rule draws the object on top (no slivers): one seed is its check
            let seeds = if merge == MergeRule::Reference { 1 } else { 5 };
            for (seed, index) in (0..seeds).flat_map(|s| (0..6).map(move |i| (s, i))) {
                let s = g.sample(seed, index).unwrap();
                let (w, h) = (s.width, s.height);
                slivers += sliver_runs(&s.mask2, &s.holes, w, h);
                samples += 1;
                if seed > 0 {
                    continue;
                }
                let (l1, l2) = (thin_line_runs(&s.image1, w, h), thin_line_runs(&s.image2, w, h));
                lines1 += l1;
                lines2 += l2;
                if l2 > l1 {
                    diagnose(&s);
                }
            }
            println!(
                "{merge:?} {law} object motion: thin-line runs image2 {lines2}, image1 {lines1} (seed 0); \
                 one-row label slivers {slivers} in {samples} samples"
            );
            assert!(lines2 <= lines1, "{merge:?} {law}: {lines2} runs in image2, {lines1} in image1");
            assert!(2 * slivers <= samples, "{merge:?} {law}: {slivers} one-row label slivers in {samples} samples");
        }
    }
    std::fs::remove_dir_all(root).unwrap();
}

/// Runs of at least `THIN_LINE_MIN_RUN` pixels of one row whose label differs from the rows
/// above and below while those two agree: a one-row sliver of an object (or of the scene) that
/// the merge drew, whatever the photo shows there. A hole is not drawn: a one-row hole (where
/// some of a moved object's planes leave the source frame, near its border) is left to
/// inpainting and marked in `holes`, and the label laws check the flow that lands next to it.
fn sliver_runs(mask: &[u8], holes: &[u8], w: usize, h: usize) -> usize {
    let mut runs = 0;
    for y in 1..h.saturating_sub(1) {
        let mut len = 0;
        for x in 0..=w {
            let sliver = x < w && {
                let (a, c, b) = (mask[(y - 1) * w + x], mask[y * w + x], mask[(y + 1) * w + x]);
                a == b && c != a && holes[y * w + x] == 0
            };
            if sliver {
                len += 1;
            } else {
                runs += usize::from(len >= mpiflow::bench::quality::THIN_LINE_MIN_RUN);
                len = 0;
            }
        }
    }
    runs
}

/// Prints where image2's thin-line pixels are: label, hole, depth above / at / below.
fn diagnose(s: &mpiflow::sample::Sample) {
    let (w, h) = (s.width, s.height);
    let lum = |x: usize, y: usize| {
        let o = 3 * (y * w + x);
        0.299 * f32::from(s.image2[o]) + 0.587 * f32::from(s.image2[o + 1]) + 0.114 * f32::from(s.image2[o + 2])
    };
    let mut shown = 0;
    for y in 1..h - 1 {
        for x in 0..w {
            let (a, c, b) = (lum(x, y - 1), lum(x, y), lum(x, y + 1));
            if (c - a).abs() > 24.0
                && (c - b).abs() > 24.0
                && (c - a) * (c - b) > 0.0
                && (a - b).abs() < 12.0
                && shown < 12
            {
                shown += 1;
                let i = y * w + x;
                println!(
                    "  {} line px ({x},{y}): mask2 {}/{}/{} holes {}/{}/{} depth2 {:.3}/{:.3}/{:.3} lum {a:.0}/{c:.0}/{b:.0}",
                    s.source_id,
                    s.mask2[i - w],
                    s.mask2[i],
                    s.mask2[i + w],
                    s.holes[i - w],
                    s.holes[i],
                    s.holes[i + w],
                    s.depth2[i - w],
                    s.depth2[i],
                    s.depth2[i + w]
                );
            }
        }
    }
}
