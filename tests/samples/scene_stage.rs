//! The scene stage: which parts each item skips, errors, provenance, the built-in MPI builder,
//! `SourceScenes` fingerprints, and the bundled scenes through the whole stage.

use mpiflow::geometry::Intrinsics;
use mpiflow::io::image::RgbImage;
use mpiflow::mpi::layering::Layering;
use mpiflow::mpi::Mpi;
use mpiflow::raster::{Instance, InstanceMasks};
use mpiflow::scene::builtin::BuiltinMpi;
use mpiflow::scene::scale::{disparity_from_depth, DISPARITY_FLOOR};
use mpiflow::scene::stage::{composite_disparity, SceneStage, SourceScenes};
use mpiflow::scene::{DepthEstimator, Disparity, MpiBuilder, SceneError, SceneLoader, Segmenter};
use mpiflow::source::builtin::BuiltinSource;
use mpiflow::source::{DirSource, GivenDepth, Source, SourceError, SourceItem, SourceOptions};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

const W: usize = 16;
const H: usize = 12;

fn image() -> RgbImage {
    RgbImage { width: W, height: H, data: (0..W * H * 3).map(|i| (i % 7) as f32 / 7.0).collect() }
}

fn item(depth: Option<GivenDepth>, masks: Option<InstanceMasks>, mpi: Option<Mpi>) -> SourceItem {
    SourceItem { id: "x".into(), image: image(), depth, masks, mpi, intrinsics: None }
}

/// Disparity 0.5 on the left half, 0.25 on the right.
struct FakeDepth(AtomicUsize);

impl DepthEstimator for FakeDepth {
    fn name(&self) -> String {
        "fake-depth".into()
    }
    fn estimate(&self, image: &RgbImage) -> Result<Disparity, SceneError> {
        self.0.fetch_add(1, Ordering::SeqCst);
        let data = (0..image.width * image.height).map(|i| if i % image.width < image.width / 2 { 0.5 } else { 0.25 });
        Ok(Disparity { width: image.width, height: image.height, data: data.collect() })
    }
}

/// Returns a map with a NaN (a broken model).
struct NanDepth;

impl DepthEstimator for NanDepth {
    fn name(&self) -> String {
        "nan-depth".into()
    }
    fn estimate(&self, image: &RgbImage) -> Result<Disparity, SceneError> {
        let mut data = vec![0.5; image.width * image.height];
        data[3] = f32::NAN;
        Ok(Disparity { width: image.width, height: image.height, data })
    }
}

/// One instance: the top-left quarter.
struct FakeSeg(AtomicUsize);

impl Segmenter for FakeSeg {
    fn name(&self) -> String {
        "fake-seg".into()
    }
    fn segment(&self, image: &RgbImage) -> Result<InstanceMasks, SceneError> {
        self.0.fetch_add(1, Ordering::SeqCst);
        let (w, h) = (image.width, image.height);
        let mask = (0..w * h).map(|i| if i % w < w / 2 && i / w < h / 2 { 1.0 } else { 0.0 }).collect();
        Ok(InstanceMasks { width: w, height: h, masks: vec![Instance::new(9, 0.8, mask)] })
    }
}

/// Counts builds, delegating to the built-in layering.
struct CountingMpi(AtomicUsize, BuiltinMpi);

impl MpiBuilder for CountingMpi {
    fn name(&self) -> String {
        format!("counting {}", self.1.name())
    }
    fn build(&self, image: &RgbImage, disparity: &Disparity, k: &Intrinsics) -> Result<Mpi, SceneError> {
        self.0.fetch_add(1, Ordering::SeqCst);
        self.1.build(image, disparity, k)
    }
}

struct Models {
    depth: Arc<FakeDepth>,
    seg: Arc<FakeSeg>,
    mpi: Arc<CountingMpi>,
}

impl Models {
    fn new() -> Self {
        Models {
            depth: Arc::new(FakeDepth(AtomicUsize::new(0))),
            seg: Arc::new(FakeSeg(AtomicUsize::new(0))),
            mpi: Arc::new(CountingMpi(AtomicUsize::new(0), BuiltinMpi::new(8, Layering::Soft))),
        }
    }
    fn stage(&self) -> SceneStage {
        SceneStage::new(self.mpi.clone()).with_depth(self.depth.clone()).with_segmenter(self.seg.clone())
    }
    fn counts(&self) -> (usize, usize, usize) {
        (self.depth.0.load(Ordering::SeqCst), self.mpi.0.load(Ordering::SeqCst), self.seg.0.load(Ordering::SeqCst))
    }
}

fn given_masks() -> InstanceMasks {
    let ids: Vec<u32> = (0..W * H).map(|i| if i % W >= W - 4 { 4 } else { 0 }).collect();
    InstanceMasks::from_index_map(&ids, W, H).unwrap()
}

#[test]
fn nothing_given_runs_every_model() {
    let m = Models::new();
    let s = m.stage().scene(item(None, None, None)).unwrap();
    assert_eq!(m.counts(), (1, 1, 1));
    assert_eq!(s.disparity.data[0], 0.5);
    assert_eq!(s.disparity.data[W - 1], 0.25);
    assert_eq!(s.masks.masks[0].id, 9);
    assert_eq!(s.mpi.planes(), 8);
    assert_eq!(s.intrinsics, Intrinsics::reference_default(W, H));
    assert_eq!(
        s.provenance,
        vec!["depth: fake-depth", "mpi: counting builtin soft 8", "masks: fake-seg (1 instances)"]
    );
}

#[test]
fn given_depth_skips_the_depth_model_and_given_masks_the_segmenter() {
    let m = Models::new();
    let depth: Vec<f32> = (0..W * H).map(|i| 2.0 + (i % W) as f32).collect();
    let s = m.stage().scene(item(Some(GivenDepth::Depth(depth.clone())), Some(given_masks()), None)).unwrap();
    assert_eq!(m.counts(), (0, 1, 0));
    for (i, &v) in s.disparity.data.iter().enumerate() {
        assert!((v - 2.0 / depth[i]).abs() < 1e-7);
    }
    assert_eq!(s.masks, given_masks());
    assert_eq!(s.provenance[0], "depth: given metric depth, nearest 2 -> disparity 1");
    assert_eq!(s.provenance[2], "masks: given (1 instances)");

    let disp: Vec<f32> = (0..W * H).map(|i| (i % W) as f32 / W as f32).collect();
    let s = m.stage().scene(item(Some(GivenDepth::Disparity(disp.clone())), None, None)).unwrap();
    assert_eq!(m.counts(), (0, 2, 1));
    assert_eq!(s.disparity.data[0], DISPARITY_FLOOR);
    assert_eq!(s.disparity.data[5], disp[5]);
    assert_eq!(s.provenance[0], "depth: given disparity");
}

/// `parts(item, false)` (what `mpiflow bake` asks without an MPI network) runs the depth model
/// and the segmenter but not the MPI builder, and gives the disparity, masks, intrinsics and
/// image of the full scene bit for bit; an item's own MPI is still kept.
#[test]
fn parts_without_the_mpi_skip_the_builder_and_keep_everything_else() {
    let m = Models::new();
    let full = m.stage().scene(item(None, None, None)).unwrap();
    assert_eq!(m.counts(), (1, 1, 1));
    let p = m.stage().parts(item(None, None, None), false).unwrap();
    assert_eq!(m.counts(), (2, 1, 2), "the builder did not run");
    assert!(p.mpi.is_none());
    assert_eq!(p.disparity.data, full.disparity.data);
    assert_eq!(p.masks, full.masks);
    assert_eq!(p.intrinsics, full.intrinsics);
    assert_eq!(p.image.data, full.image.data);
    assert_eq!(p.provenance, vec!["depth: fake-depth", "masks: fake-seg (1 instances)"]);
    let p = m.stage().parts(item(None, None, Some(full.mpi.as_ref().clone())), false).unwrap();
    assert_eq!(p.mpi.map(|x| x.planes()), Some(8), "a given MPI is kept");
    assert_eq!(m.counts(), (2, 1, 3));
}

#[test]
fn given_mpi_skips_depth_and_mpi() {
    let m = Models::new();
    // a two-plane MPI: an opaque near plane on the left half, the far plane opaque everywhere
    let mut mpi = Mpi::new(W, H, vec![0.8, 0.2], 0);
    for j in 0..W * H {
        if j % W < W / 2 {
            mpi.plane_rgba_mut(0)[4 * j + 3] = 1e6;
        }
        mpi.plane_rgba_mut(1)[4 * j + 3] = 1e6;
    }
    let depth = GivenDepth::Depth(vec![1.0; W * H]); // ignored: the MPI wins
    let s = m.stage().scene(item(Some(depth), Some(given_masks()), Some(mpi))).unwrap();
    assert_eq!(m.counts(), (0, 0, 0));
    assert!((s.disparity.data[0] - 0.8).abs() < 1e-6);
    assert!((s.disparity.data[W - 1] - 0.2).abs() < 1e-6);
    assert_eq!(s.provenance[0], "depth: composited from the given MPI");
    assert_eq!(s.provenance[1], "mpi: given (2 planes)");

    // an MPI whose nearest plane lies nearer than depth 1 is rescaled to the scene scale,
    // keeping each plane's opacity
    let mut near = Mpi::new(W, H, vec![4.0, 2.0], 0);
    for j in 0..W * H {
        near.plane_rgba_mut(0)[4 * j + 3] = 0.5;
        near.plane_rgba_mut(1)[4 * j + 3] = 1.0;
    }
    let s = m.stage().scene(item(None, None, Some(near))).unwrap();
    assert_eq!(s.mpi.disparity, vec![1.0, 0.5]);
    assert_eq!(s.mpi.plane_rgba(0)[3], 0.125);
    assert!(s.provenance[1].contains("scaled by 0.25"), "{:?}", s.provenance);
    // plane 0 is 0.25 deep before (opacity 1 - e^-0.125) and 1.0 after with sigma / 4: the same
    let alpha = 1.0 - (-0.125f64).exp();
    let expect = alpha * 1.0 + (1.0 - alpha) * 0.5;
    assert!((f64::from(s.disparity.data[0]) - expect).abs() < 1e-4, "{} vs {expect}", s.disparity.data[0]);
    assert_eq!(m.counts(), (0, 0, 1));

    // an MPI of another size is refused
    let bad = Mpi::new(W + 1, H, vec![0.5], 0);
    let e = m.stage().scene(item(None, None, Some(bad))).unwrap_err();
    assert!(e.to_string().contains("the given MPI is 17 x 12"), "{e}");
}

#[test]
fn no_depth_and_no_depth_model_is_a_clear_error() {
    let stage = SceneStage::builtin();
    let e = stage.scene(item(None, None, None)).unwrap_err();
    assert_eq!(e.to_string(), "source x has no depth and no depth model is configured");
}

#[test]
fn no_masks_and_no_segmenter_gives_no_instances() {
    let stage = SceneStage::builtin();
    let s = stage.scene(item(Some(GivenDepth::Depth(vec![3.0; W * H])), None, None)).unwrap();
    assert!(s.masks.masks.is_empty());
    assert_eq!((s.masks.width, s.masks.height), (W, H));
    assert_eq!(s.provenance[2], "masks: none (no masks given and no segmenter configured)");
    assert!(s.disparity.data.iter().all(|&v| v == 1.0));
    assert_eq!(s.mpi.planes(), 32);
}

#[test]
fn bad_model_output_names_the_model() {
    let stage = SceneStage::builtin().with_depth(Arc::new(NanDepth));
    let e = stage.scene(item(None, None, None)).unwrap_err();
    match &e {
        SceneError::Model { kind, model, message } => {
            assert_eq!((*kind, model.as_str()), ("depth", "nan-depth"));
            assert!(message.contains("NaN"), "{message}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn item_intrinsics_are_used() {
    let k = Intrinsics::new(20.0, 20.0, 8.0, 6.0);
    let mut it = item(Some(GivenDepth::Depth(vec![1.0; W * H])), None, None);
    it.intrinsics = Some(k);
    assert_eq!(SceneStage::builtin().scene(it).unwrap().intrinsics, k);
}

#[test]
fn builtin_mpi_names_and_reproduces_disparity() {
    assert_eq!(BuiltinMpi::default().name(), "builtin soft 32");
    assert_eq!(BuiltinMpi { backdrop: true, ..BuiltinMpi::default() }.name(), "builtin soft 32 backdrop");
    assert_eq!(BuiltinMpi::new(16, Layering::Hard).name(), "builtin hard 16");
    let ranged = BuiltinMpi { disparity_range: Some((1.0, 0.001)), ..BuiltinMpi::default() };
    assert_eq!(ranged.name(), "builtin soft 32 range 1-0.001");
    assert!(BuiltinMpi::new(0, Layering::Soft).validate().is_err());
    assert!(BuiltinMpi { disparity_range: Some((0.1, 0.5)), ..BuiltinMpi::default() }.validate().is_err());
    // soft layering: the composite disparity of the built MPI is the input disparity (at the
    // principal point, where the ray length is 1)
    let disp: Vec<f32> = (0..W * H).map(|i| 0.2 + 0.8 * (i % W) as f32 / (W - 1) as f32).collect();
    let d = Disparity { width: W, height: H, data: disp.clone() };
    let k = Intrinsics::new(1e6, 1e6, W as f64 / 2.0, H as f64 / 2.0);
    let mpi = BuiltinMpi::new(8, Layering::Soft).build(&image(), &d, &k).unwrap();
    let back = composite_disparity(&mpi);
    for (a, b) in back.data.iter().zip(&disp) {
        assert!((a - b).abs() < 1e-3, "{a} vs {b}");
    }
    let wrong = Disparity { width: W - 1, height: H, data: vec![0.5; (W - 1) * H] };
    assert!(BuiltinMpi::default().build(&image(), &wrong, &k).is_err());
}

/// A source of two items; the second has neither depth nor an MPI.
struct TwoItems;

impl Source for TwoItems {
    fn len(&self) -> usize {
        2
    }
    fn id(&self, i: usize) -> String {
        format!("item{i}")
    }
    fn load(&self, i: usize) -> Result<SourceItem, SourceError> {
        let depth = (i == 0).then(|| GivenDepth::Depth(vec![2.0; W * H]));
        Ok(SourceItem { id: self.id(i), image: image(), depth, masks: None, mpi: None, intrinsics: None })
    }
    fn fingerprint(&self) -> u64 {
        42
    }
    fn describe(&self) -> String {
        "two items".into()
    }
}

#[test]
fn source_scenes_loads_and_fingerprints_the_configuration() {
    let a = SourceScenes::new(Arc::new(TwoItems), Arc::new(SceneStage::builtin()));
    assert_eq!((a.len(), a.id(1)), (2, "item1".to_string()));
    assert!(a.load_scene(0).is_ok());
    let e = a.load_scene(1).unwrap_err();
    assert!(e.to_string().contains("item1 has no depth"), "{e}");
    assert_eq!(a.describe(), "two items; depth: none, mpi: builtin soft 32, masks: none");
    let same = SourceScenes::new(Arc::new(TwoItems), Arc::new(SceneStage::builtin()));
    assert_eq!(a.fingerprint(), same.fingerprint());
    let fewer_planes =
        SourceScenes::new(Arc::new(TwoItems), Arc::new(SceneStage::new(Arc::new(BuiltinMpi::new(16, Layering::Soft)))));
    assert_ne!(a.fingerprint(), fewer_planes.fingerprint());
    let hard =
        SourceScenes::new(Arc::new(TwoItems), Arc::new(SceneStage::new(Arc::new(BuiltinMpi::new(32, Layering::Hard)))));
    assert_ne!(a.fingerprint(), hard.fingerprint());
    let true_depth = SourceScenes::new(
        Arc::new(TwoItems),
        Arc::new(SceneStage::new(Arc::new(BuiltinMpi::new(32, Layering::TrueDepth)))),
    );
    assert_ne!(a.fingerprint(), true_depth.fingerprint());
    let backdrop = SourceScenes::new(
        Arc::new(TwoItems),
        Arc::new(SceneStage::new(Arc::new(BuiltinMpi { backdrop: true, ..BuiltinMpi::default() }))),
    );
    assert_ne!(a.fingerprint(), backdrop.fingerprint());
    let with_depth = SourceScenes::new(
        Arc::new(TwoItems),
        Arc::new(SceneStage::builtin().with_depth(Arc::new(FakeDepth(AtomicUsize::new(0))))),
    );
    assert_ne!(a.fingerprint(), with_depth.fingerprint());
    assert!(with_depth.load_scene(1).is_ok());
    // a source error becomes a scene error naming the file
    let dir = std::env::temp_dir().join(format!("mpiflow-stage-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("broken.png"), b"not a png").unwrap();
    // (not checked when the folder is opened, which would leave the broken photo out: the
    // error is the scene's here)
    let src = DirSource::open(&dir, &SourceOptions { check_at_open: false, ..SourceOptions::default() }).unwrap();
    let scenes = SourceScenes::new(Arc::new(src), Arc::new(SceneStage::builtin()));
    match scenes.load_scene(0) {
        Err(SceneError::Given { path, .. }) => assert!(path.ends_with("broken.png")),
        other => panic!("{other:?}"),
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn builtin_scenes_through_the_stage() {
    let src = Arc::new(BuiltinSource::open_default().unwrap());
    let scenes =
        SourceScenes::new(src.clone(), Arc::new(SceneStage::new(Arc::new(BuiltinMpi::new(16, Layering::Soft)))));
    for i in [0, 5] {
        let c = src.compose(i).unwrap();
        let s = scenes.load_scene(i).unwrap();
        let (w, h) = (640, 480);
        assert_eq!((s.image.width, s.image.height, s.mpi.width, s.mpi.height), (w, h, w, h));
        s.mpi.validate().unwrap();
        assert_eq!(s.mpi.planes(), 16);
        // the scene disparity is exactly the composition's depth brought to the scene scale
        let d_min = c.depth.iter().copied().fold(f32::INFINITY, f32::min);
        let (expect, _) = disparity_from_depth(&c.depth, w, h).unwrap();
        assert_eq!(s.disparity, expect);
        for (j, &v) in s.disparity.data.iter().enumerate().step_by(97) {
            assert!((v - d_min / c.depth[j]).abs() <= 1e-6);
        }
        assert_eq!(s.disparity.data.iter().copied().fold(0.0, f32::max), 1.0);
        assert!(s.disparity.data.iter().all(|v| (DISPARITY_FLOOR..=1.0).contains(v)));
        // masks: one instance per visible object
        let visible = c.objects.iter().filter(|o| o.visible_pixels > 0).count();
        assert_eq!(s.masks.masks.len(), visible);
        assert!(visible >= 2);
        assert_eq!(s.intrinsics, Intrinsics::reference_default(w, h));
        assert!(s.provenance[0].starts_with("depth: given metric depth"), "{:?}", s.provenance);
        assert_eq!(s.provenance[1], "mpi: builtin soft 16");
        assert!(s.provenance[2].starts_with("masks: given"));
        assert!(s.byte_size() > 0);
    }
}
