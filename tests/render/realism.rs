//! What motion reveals on a real RGB-D photo with a large object mask (Middlebury Cones,
//! `tests/data/rgbd`): with the completed background (`backdrop`) and the planes behind the
//! moved object as its fill, image2 leaves less to 2-D inpainting and the revealed regions keep
//! the photo's detail and noise; the labels stay honest and the samples a pure function of their
//! address; and the reveal budget keeps what a moved object uncovers near what a clip shows, also
//! for a mask of most of the frame. The figures come from `bench::quality` and `bench::realism`, as `mpiflow bench
//! quality --realism` prints them.

use std::path::PathBuf;
use std::sync::Arc;

use mpiflow::bench::quality::QualityReport;
use mpiflow::bench::quality::{quality, quality_on_motions, quality_same_motions};
use mpiflow::sample::background::Background;
use mpiflow::sample::config::{MotionSpec, SampleConfig};
use mpiflow::sample::motion::MotionPreset;
use mpiflow::sample::pipeline::{open_source, OpenOptions, Pipeline, SourceSpec};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::models::ModelConfig;

fn cones() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/rgbd/cones")
}

fn pipeline(backdrop: bool) -> Pipeline {
    pipeline_of(cones(), backdrop)
}

fn pipeline_of(dir: PathBuf, backdrop: bool) -> Pipeline {
    let models = ModelConfig { backdrop, ..ModelConfig::default() };
    let stage = Arc::new(models.build_stage().unwrap());
    let source = open_source(&SourceSpec::Path(dir), &OpenOptions::default()).unwrap();
    Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 28)), SampleConfig::default()).unwrap()
}

fn report(p: &Pipeline, background: Background) -> QualityReport {
    let c = SampleConfig { background, backward: true, ..SampleConfig::default() };
    quality(p.generator(), &c, 0, 6).unwrap()
}

/// The configuration `report` gives the plain pipeline.
fn plain_config() -> SampleConfig {
    SampleConfig { background: Background::Inpaint, backward: true, ..SampleConfig::default() }
}

#[test]
fn the_completed_background_fills_what_a_moved_object_reveals_with_the_photos_texture() {
    let plain = report(&pipeline(false), Background::Inpaint);
    // the completed background on the plain dataset's motions: a paired comparison
    let c = SampleConfig { background: Background::Planes, backward: true, ..SampleConfig::default() };
    let dataset = pipeline(false).generator().with_config(plain_config()).unwrap().fingerprint();
    let completed = quality_on_motions(pipeline(true).generator(), &c, dataset, 0, 6).unwrap();
    for (name, r) in [("inpaint", &plain), ("backdrop + planes", &completed)] {
        println!(
            "{name}: holes {:.4}, revealed {:.4}, detail {:?}, noise {:?}, AUC revealed {:?}, AUC pair {:?}, \
             photometric {:.4}, laws {:?}",
            r.hole_fraction,
            r.realism.revealed,
            r.realism.revealed_detail,
            r.realism.revealed_noise,
            r.realism.auc_revealed,
            r.realism.auc_pair,
            r.photometric,
            r.laws
        );
        assert_eq!(r.with_objects, 6, "{name}: every sample moves the cones");
        assert_eq!(r.laws.holes + r.laws.label + r.laws.depth, 0, "{name}: {:?}", r.laws);
    }
    // at most 3% of image2 left to 2-D inpainting, less than Telea alone is given
    assert!(completed.hole_fraction <= 0.03, "{}", completed.hole_fraction);
    assert!(completed.hole_fraction < plain.hole_fraction, "{} / {}", completed.hole_fraction, plain.hole_fraction);
    // the revealed background has the detail and noise of the rest of image2's background
    let detail = completed.realism.revealed_detail.unwrap();
    let noise = completed.realism.revealed_noise.unwrap();
    assert!(detail >= 0.8 && noise >= 0.8, "detail {detail}, noise {noise}");
    assert!(detail > plain.realism.revealed_detail.unwrap(), "{detail} / {:?}", plain.realism.revealed_detail);
    // and the photometric error does not grow
    assert!(completed.photometric <= plain.photometric * 1.05, "{} / {}", completed.photometric, plain.photometric);
}

#[test]
fn samples_with_the_completed_background_are_a_pure_function_of_their_address() {
    let c = SampleConfig { background: Background::Planes, ..SampleConfig::default() };
    let a = pipeline(true).generator().with_config(c.clone()).unwrap().sample(3, 1).unwrap();
    // a fresh pipeline (its own scene build) on two threads gives the same bytes
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    let b = pool.install(|| pipeline(true).generator().with_config(c).unwrap().sample(3, 1).unwrap());
    assert_eq!(a.image2, b.image2);
    assert_eq!(a.flow, b.flow);
    assert_eq!(a.mask1, b.mask1);
    assert_eq!(a.holes, b.holes);
}

/// A mask of most of the frame (the example photo's cat, `tests/data/rgbd/chelsea`, 83%): on the
/// same camera and object draws, the default law with the opt-in reveal budget moves the cat by
/// less than the default law (no budget), so image2 reveals less and leaves fewer holes to
/// inpainting; the labels stay honest either way.
#[test]
fn what_a_moved_object_uncovers_carries_no_more_of_its_colour_than_the_background_around_it() {
    // the cat of the example photo (its hand-drawn mask, whiskers and fur outside it), the
    // default configuration: the scene loses the cat over its footprint and Telea fills what it
    // uncovers from the background only
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/rgbd/chelsea");
    let r = quality(pipeline_of(dir, false).generator(), &plain_config(), 0, 6).unwrap();
    assert_eq!(r.with_objects, 6, "every sample moves the cat");
    assert_eq!(r.laws.holes + r.laws.label + r.laws.depth, 0, "{:?}", r.laws);
    let c = r.realism.object_colour.expect("revealed and ring pixels");
    let excess = c.excess().unwrap();
    println!("object colour: revealed {:?}, ring {:?}", c.revealed_share(), c.ring_share());
    assert!(excess <= 0.05, "{excess}: the revealed background carries the cat's colours");
}

#[test]
fn the_reveal_budget_moves_a_large_mask_by_less() {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/rgbd/chelsea");
    let p = pipeline_of(dir, false);
    let free = SampleConfig { backward: true, ..SampleConfig::default() };
    let budgeted = SampleConfig {
        motion: MotionSpec::Ranges(Box::new(MotionPreset::Reference.ranges().with_reveal_budget())),
        ..free.clone()
    };
    // the addresses of the default configuration: the same draws, the budget the only difference
    let with = quality_same_motions(p.generator(), &budgeted, 0, 8).unwrap();
    let without = quality_same_motions(p.generator(), &free, 0, 8).unwrap();
    for (name, r) in [("budget", &with), ("no budget", &without)] {
        println!(
            "{name}: holes {:.4}, revealed {:.4}, photometric {:.4}, laws {:?}",
            r.hole_fraction, r.realism.revealed, r.photometric, r.laws
        );
        assert_eq!(r.with_objects, 8, "{name}: every sample moves the cat");
        assert_eq!(r.laws.holes + r.laws.label + r.laws.depth, 0, "{name}: {:?}", r.laws);
    }
    assert!(with.hole_fraction < without.hole_fraction, "{} / {}", with.hole_fraction, without.hole_fraction);
    assert!(
        with.realism.revealed < 0.8 * without.realism.revealed,
        "revealed {} / {}",
        with.realism.revealed,
        without.realism.revealed
    );
}

/// The default law moves objects by its draw, unscaled: on Cones (the front cones, a sixth of
/// the frame) every recorded object motion lies within the reference object law, and the
/// object's translation relative to the camera's is about a fifth of the camera's (the law's
/// median is 0.2; a reveal budget scales it to about 0.01 on this mask).
#[test]
fn objects_move_by_the_laws_draw_unscaled() {
    let p = pipeline(true);
    let law = MotionPreset::Reference.ranges().object;
    let bound = |c: &mpiflow::sample::motion::Component| c.bounds().0.abs().max(c.bounds().1.abs()) + 1e-12;
    let mut ratios = Vec::new();
    for index in 0..16 {
        let s = p.generator().sample(0, index).unwrap();
        for o in &s.objects {
            let m = &o.motion;
            let t = law.translation;
            for (v, c) in m.translation.iter().zip([&t.x, &t.y, &t.z]) {
                assert!(v.abs() <= bound(c), "sample {index}: translation {:?} outside the law", m.translation);
            }
            let r = law.rotation;
            for (v, c) in m.axis_angle.iter().zip([&r.x, &r.y, &r.z]) {
                assert!(v.abs() <= bound(c), "sample {index}: rotation {:?} outside the law", m.axis_angle);
            }
            let rel: f64 = (0..3).map(|k| (m.translation[k] - s.camera.translation[k]).powi(2)).sum::<f64>().sqrt();
            let cam: f64 = s.camera.translation.iter().map(|v| v * v).sum::<f64>().sqrt();
            ratios.push(rel / cam);
        }
    }
    assert!(ratios.len() >= 12, "{} of 16 samples moved an object", ratios.len());
    ratios.sort_by(f64::total_cmp);
    let median = ratios[ratios.len() / 2];
    println!("|t_obj - t_cam| / |t_cam|: median {median:.3} over {} objects", ratios.len());
    assert!(median >= 0.1, "median {median}: object motion scaled down");
}

/// True-depth layers keep image1's detail where image1 sees what image2 shows (the ideal warp's
/// region, `bench::quality::ideal_warp_sharpness`) and their flows agree forward and backward
/// off motion edges (`bench::realism::forward_backward_residual`); soft layering, whose pixels
/// part by the parallax of the plane spacing, loses both (docs/quality.md, "True-depth layers").
#[test]
fn true_depth_layers_keep_the_ideal_warps_detail_and_agree_forward_and_backward() {
    use mpiflow::mpi::layering::Layering;
    let run = |layering: Layering| {
        let models = ModelConfig { layering, ..ModelConfig::default() };
        let stage = Arc::new(models.build_stage().unwrap());
        let source = open_source(&SourceSpec::Path(cones()), &OpenOptions::default()).unwrap();
        let p = Pipeline::new(source, stage, Arc::new(SceneCache::new(1 << 28)), SampleConfig::default()).unwrap();
        let c = SampleConfig { max_objects: 0, backward: true, ..SampleConfig::default() };
        let r = quality(p.generator(), &c, 0, 4).unwrap();
        let detail = r.ideal_image2_sharpness / r.ideal_sharpness;
        let edges = r.realism.fb_edges.unwrap();
        println!(
            "{layering:?}: detail {detail:.3}, fb {:?} (edges {:.3} px, {:.3} of reads)",
            r.realism.fb_residual, edges.residual, edges.share
        );
        (detail, r.realism.fb_residual.unwrap(), edges)
    };
    let (soft, soft_fb, _) = run(Layering::Soft);
    let (true_depth, fb, edges) = run(Layering::TrueDepth);
    assert!(true_depth > 0.85 && true_depth > soft + 0.15, "detail: true-depth {true_depth}, soft {soft}");
    assert!(fb < 0.05 && soft_fb > fb, "fb residual: true-depth {fb}, soft {soft_fb}");
    // the reads across motion edges are few, and their residual is the edge's, not a label error
    assert!(edges.share < 0.08 && edges.residual > 0.5, "{edges:?}");
}
