//! The deterministic sample recipe: same address, same bytes (across runs, generators and rayon
//! pool sizes); different indices, different motions; motions within the preset ranges; no
//! objects when k = 0; finite flow; the source order; errors that name the source; failing
//! sources skipped deterministically.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

use mpiflow::geometry::Intrinsics;
use mpiflow::io::image::RgbImage;
use mpiflow::mpi::layering::{build_mpi_for_camera, Layering, LayeringOptions};
use mpiflow::raster::InstanceMasks;
use mpiflow::sample::config::{InpaintMethod, MotionSpec, SampleConfig};
use mpiflow::sample::error::SampleError;
use mpiflow::sample::holes::inpaint_background;
use mpiflow::sample::merge::MergeRule;
use mpiflow::sample::motion::{Component, Motion, MotionPreset, RigidLaw, RotationKind};
use mpiflow::sample::object::ObjectChoice;
use mpiflow::sample::pipeline::Generator;
use mpiflow::sample::recipe::{assemble, assemble_merged};
use mpiflow::sample::{Sample, StageTimings};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::{Disparity, Scene, SceneError, SceneLoader};
use mpiflow::source::{FailureKind, Fnv64};

const W: usize = 96;
const H: usize = 64;

/// Procedural RGB-D scenes: a ground plane receding upwards with a textured colour, and
/// `1 + item % 3` box-shaped objects standing on it (instance ids 1, 2, 3 in an index map), laid
/// out as an MPI by the built-in layering. Item `failing` (if any) fails to load.
struct Procedural {
    items: usize,
    planes: usize,
    failing: Option<usize>,
    loads: AtomicUsize,
}

impl Procedural {
    fn new(items: usize) -> Self {
        Self { items, planes: 8, failing: None, loads: AtomicUsize::new(0) }
    }
}

impl SceneLoader for Procedural {
    fn len(&self) -> usize {
        self.items
    }

    fn id(&self, i: usize) -> String {
        format!("procedural-{i}")
    }

    fn fingerprint(&self) -> u64 {
        let mut h = Fnv64::new();
        h.str("procedural").u64(self.items as u64).u64(self.planes as u64).u64(W as u64).u64(H as u64);
        h.finish()
    }

    fn load_scene(&self, i: usize) -> Result<Scene, SceneError> {
        self.loads.fetch_add(1, Ordering::SeqCst);
        if Some(i) == self.failing {
            return Err(SceneError::Given {
                path: format!("procedural/{i}.npy"),
                kind: FailureKind::Depth,
                message: "unreadable".into(),
            });
        }
        let k = Intrinsics::reference_default(W, H);
        let mut rgb = vec![0.0f32; W * H * 3];
        let mut depth = vec![0.0f32; W * H];
        let mut ids = vec![0u32; W * H];
        let boxes = [(10usize, 30usize, 30usize, 52usize, 2.0f32), (45, 60, 20, 50, 2.6), (68, 88, 34, 58, 1.7)];
        let n_obj = 1 + i % 3;
        for y in 0..H {
            for x in 0..W {
                let o = y * W + x;
                let (s, t) = (x as f32 / W as f32, y as f32 / H as f32);
                let mut d = 1.3 + 5.0 * (1.0 - t).powi(2);
                let ph = i as f32;
                let mut c =
                    [0.5 + 0.4 * (8.0 * s + ph).sin(), 0.5 + 0.4 * (6.0 * t - 2.0 * s).cos(), 0.3 + 0.4 * s * t];
                for (j, &(x0, x1, y0, y1, bd)) in boxes.iter().enumerate().take(n_obj) {
                    if (x0..x1).contains(&x) && (y0..y1).contains(&y) {
                        d = bd;
                        c = [0.8 - 0.2 * j as f32, 0.2 + 0.3 * j as f32, 0.3 + 0.2 * (5.0 * t).sin().abs()];
                        ids[o] = j as u32 + 1;
                    }
                }
                depth[o] = d;
                rgb[3 * o..3 * o + 3].copy_from_slice(&c);
            }
        }
        let opts = LayeringOptions {
            planes: self.planes,
            layering: Layering::Soft,
            disparity_range: None,
            backdrop: false,
            ..LayeringOptions::default()
        };
        let mpi = build_mpi_for_camera(&rgb, &depth, W, H, &opts, &k)?;
        let mut masks = InstanceMasks::from_index_map(&ids, W, H)?;
        // distinct scores so that the ranking is by score: id 2 first, then 1, then 3
        for m in &mut masks.masks {
            m.score = [0.0, 0.7, 0.9, 0.5][m.id as usize];
        }
        let near = depth.iter().copied().fold(f32::MAX, f32::min);
        Ok(Scene {
            id: self.id(i),
            image: RgbImage { width: W, height: H, data: rgb },
            disparity: Disparity { width: W, height: H, data: depth.iter().map(|d| near / d).collect() },
            mpi: Arc::new(mpi),
            masks,
            intrinsics: k,
            provenance: vec!["depth: procedural".into(), "mpi: builtin soft 8".into()],
        })
    }
}

fn generator(loader: Procedural, config: SampleConfig) -> Generator {
    Generator::new(Arc::new(loader), Arc::new(SceneCache::new(1 << 30)), config).unwrap()
}

/// Everything but the timings.
fn bytes(s: &Sample) -> Sample {
    Sample { timings: StageTimings::default(), ..s.clone() }
}

fn assert_same_bytes(a: &Sample, b: &Sample) {
    assert_eq!(bytes(a), bytes(b));
    // PartialEq treats -0.0 as 0.0: compare the flow's bits too
    assert!(a.flow.iter().zip(&b.flow).all(|(x, y)| x.to_bits() == y.to_bits()));
}

#[test]
fn the_same_address_gives_the_same_bytes_across_runs_generators_and_thread_counts() {
    let config = SampleConfig { max_objects: 2, ..SampleConfig::default() };
    let g = generator(Procedural::new(3), config.clone());
    let other = generator(Procedural::new(3), config);
    let pool = |n: usize| rayon::ThreadPoolBuilder::new().num_threads(n).build().unwrap();
    let (p1, p2) = (pool(1), pool(2));
    for index in [0u64, 1, 2, 5, 1000] {
        let a = g.sample(42, index).unwrap();
        let b = g.sample(42, index).unwrap();
        let c = other.sample(42, index).unwrap();
        let d = p1.install(|| g.sample(42, index)).unwrap();
        let e = p2.install(|| other.sample(42, index)).unwrap();
        for s in [&b, &c, &d, &e] {
            assert_same_bytes(&a, s);
        }
        assert_eq!(a.address.dataset, g.fingerprint());
        assert_eq!((a.address.seed, a.address.index), (42, index));
    }
}

#[test]
fn different_indices_and_seeds_give_different_motions() {
    let g = generator(Procedural::new(2), SampleConfig::default());
    let cams: Vec<Motion> = (0..8).map(|i| g.sample(7, i).unwrap().camera).collect();
    for i in 0..cams.len() {
        for j in i + 1..cams.len() {
            assert_ne!(cams[i].translation, cams[j].translation, "indices {i} and {j}");
        }
    }
    let a = g.sample(7, 3).unwrap();
    let b = g.sample(8, 3).unwrap();
    assert_ne!(a.camera.translation, b.camera.translation);
    assert_ne!(a.objects[0].motion.translation, b.objects[0].motion.translation);
    assert_ne!(a.image2, b.image2);
}

fn within(law: &RigidLaw, m: &Motion) {
    let comps = [
        (&law.translation.x, m.translation[0]),
        (&law.translation.y, m.translation[1]),
        (&law.translation.z, m.translation[2]),
        (&law.rotation.x, m.angles[0]),
        (&law.rotation.y, m.angles[1]),
        (&law.rotation.z, m.angles[2]),
    ];
    for (c, v) in comps {
        let (lo, hi) = c.bounds();
        assert!(v >= lo && v <= hi, "{v} outside [{lo}, {hi}] ({c:?})");
        match *c {
            Component::RandomSign { min, .. } | Component::LogUniform { min, .. } => {
                assert!(v.abs() >= min, "|{v}| < {min}");
            }
            Component::Forward { .. } => assert!(v <= 0.0, "forward motion has t_z <= 0"),
            Component::Uniform { .. } => {}
        }
    }
    assert_eq!(m.rotation_kind, law.rotation_kind);
}

#[test]
fn motions_stay_within_each_presets_ranges() {
    for preset in MotionPreset::ALL {
        let ranges = preset.ranges();
        // the presets carry no reveal budget: the objects' records are the drawn motions
        let config = SampleConfig { max_objects: 3, ..SampleConfig::with_preset(preset) };
        let g = generator(Procedural::new(3), config);
        for index in 0..12 {
            let s = g.sample(1, index).unwrap();
            within(&ranges.camera, &s.camera);
            assert_eq!(s.camera.law, preset.name());
            for o in &s.objects {
                within(&ranges.object, &o.motion);
            }
            if preset == MotionPreset::PaperKitti {
                assert_eq!(s.camera.rotation_kind, RotationKind::EulerZyx);
            }
        }
    }
}

#[test]
fn k_zero_gives_no_objects_and_empty_masks() {
    let g = generator(Procedural::new(3), SampleConfig { max_objects: 0, ..SampleConfig::default() });
    for index in 0..3 {
        let s = g.sample(3, index).unwrap();
        assert!(s.objects.is_empty());
        assert!(s.mask1.iter().all(|&v| v == 0));
        assert!(s.mask2.iter().all(|&v| v == 0));
    }
}

#[test]
fn outputs_are_finite_binary_and_sized() {
    for preset in MotionPreset::ALL {
        for merge in [MergeRule::DepthAware, MergeRule::Reference] {
            let config = SampleConfig { max_objects: 3, merge, ..SampleConfig::with_preset(preset) };
            let g = generator(Procedural::new(3), config);
            for index in 0..6 {
                let s = g.sample(11, index).unwrap();
                let n = W * H;
                assert_eq!((s.width, s.height), (W, H));
                assert_eq!(s.image1.len(), 3 * n);
                assert_eq!(s.image2.len(), 3 * n);
                assert_eq!(s.flow.len(), 2 * n);
                assert!(s.flow.iter().all(|v| v.is_finite()), "{preset} {merge:?} {index}: non-finite flow");
                for m in [&s.valid, &s.occlusion] {
                    assert_eq!(m.len(), n);
                    assert!(m.iter().all(|&v| v <= 1));
                }
                let labels = s.objects.len() as u8;
                assert!(s.mask1.iter().chain(&s.mask2).all(|&v| v <= labels));
                for (j, o) in s.objects.iter().enumerate() {
                    assert_eq!(o.label as usize, j + 1);
                    assert!(s.mask1.contains(&o.label), "object {} is in mask1", o.label);
                }
                // occluded points are valid points
                assert!(s.occlusion.iter().zip(&s.valid).all(|(&o, &v)| o == 0 || v == 1));
                let t = s.timings;
                assert!(t.total_ms >= t.render_ms + t.objects_ms + t.merge_ms + t.inpaint_ms - 1e-9);
            }
        }
    }
}

#[test]
fn source_items_follow_motions_per_image() {
    let config = SampleConfig { motions_per_image: 3, scene_window: 1, ..SampleConfig::default() };
    let loader = Procedural::new(3);
    let g = generator(loader, config);
    let ids: Vec<String> = (0..10).map(|i| g.sample(0, i).unwrap().source_id).collect();
    let expect: Vec<String> = [0, 0, 0, 1, 1, 1, 2, 2, 2, 0].iter().map(|i| format!("procedural-{i}")).collect();
    assert_eq!(ids, expect);
    // each scene was loaded once and then served from the cache
    let stats = g.cache().stats();
    assert_eq!(stats.misses, 3);
    assert_eq!(stats.hits, 7);
    assert_eq!(g.source_item(10), Some(0));
}

/// A window of K items interleaves their M motions: consecutive samples change item, each item's
/// scene is built once per window, and the windows walk through the collection.
#[test]
fn a_scene_window_interleaves_its_items_motions() {
    let config = SampleConfig { motions_per_image: 2, scene_window: 3, ..SampleConfig::default() };
    let g = generator(Procedural::new(7), config);
    let items: Vec<usize> = (0..24).map(|i| g.source_item(i).unwrap()).collect();
    #[rustfmt::skip]
    let expect = [0, 1, 2, 0, 1, 2, 3, 4, 5, 3, 4, 5, 6, 0, 1, 6, 0, 1, 2, 3, 4, 2, 3, 4];
    assert_eq!(items, expect);
    let ids: Vec<String> = (0..6).map(|i| g.sample(0, i).unwrap().source_id).collect();
    assert_eq!(ids, [0, 1, 2, 0, 1, 2].map(|i| format!("procedural-{i}")));
    let stats = g.cache().stats();
    assert_eq!((stats.misses, stats.hits), (3, 3), "each scene of the window built once");
    // a window wider than the collection is the collection
    let small = SampleConfig { motions_per_image: 2, scene_window: 11, ..SampleConfig::default() };
    let items: Vec<usize> = (0..8).map(|i| small.source_item(i, 3).unwrap()).collect();
    assert_eq!(items, [0, 1, 2, 0, 1, 2, 0, 1]);
}

proptest::proptest! {
    /// The default window (11, prime) gives every rank of a world size that is not a multiple of 11
    /// different items in any 11 consecutive samples, when the collection holds the windows those
    /// samples span; every window uses each of its items exactly M times (a partition of the
    /// window's indices).
    #[test]
    fn ranks_see_different_items_in_consecutive_samples(
        world in 1u64..=64,
        rank_seed in 0u64..1_000,
        motions in 1u64..=16,
        start in 0u64..1_000_000,
        extra in 0usize..40,
    ) {
        proptest::prop_assume!(world % 11 != 0);
        let c = SampleConfig { motions_per_image: motions, ..SampleConfig::default() };
        let k = c.scene_window;
        let rank = rank_seed % world;
        let first = (start / world) * world + rank;
        let indices: Vec<u64> = (0..k).map(|j| first + j * world).collect();
        let windows = indices.last().unwrap() / (k * motions) - indices[0] / (k * motions) + 1;
        let len = (windows * k) as usize + extra;
        let items: std::collections::BTreeSet<usize> = indices.iter().map(|&i| c.source_item(i, len).unwrap()).collect();
        proptest::prop_assert_eq!(items.len(), k as usize, "rank {} of {}: {:?}", rank, world, indices);
        // a window's K M indices: each of its K items M times
        let w0 = (start / (k * motions)) * k * motions;
        let mut counts = std::collections::BTreeMap::new();
        for i in w0..w0 + k * motions {
            *counts.entry(c.source_item(i, len).unwrap()).or_insert(0u64) += 1;
        }
        proptest::prop_assert_eq!(counts.len(), k as usize);
        proptest::prop_assert!(counts.values().all(|&n| n == motions));
    }
}

#[test]
fn object_choice_is_keyed_and_top_picks_the_best_score() {
    // item 2 has three objects; ids by score: 2 (0.9), 1 (0.7), 3 (0.5)
    let top =
        generator(Procedural::new(3), SampleConfig { object_choice: ObjectChoice::Top, ..SampleConfig::default() });
    for index in [2u64, 5, 8] {
        let s = top.sample(0, index).unwrap();
        assert_eq!(s.objects.iter().map(|o| o.instance).collect::<Vec<_>>(), vec![2]);
    }
    let random = generator(Procedural::new(3), SampleConfig::default());
    let mut seen = std::collections::BTreeSet::new();
    // 24 draws: a uniform choice misses one of three objects in 3 (2/3)^24 < 2e-4 of datasets
    // (12 draws missed object 2 under one dataset word)
    for r in 0..24u64 {
        let s = random.sample(0, 2 + 3 * r).unwrap();
        assert_eq!(s.objects.len(), 1);
        seen.insert(s.objects[0].instance);
    }
    assert_eq!(seen.len(), 3, "a uniform choice reaches every object: {seen:?}");
    // two of three, in rank order
    let two = generator(Procedural::new(3), SampleConfig { max_objects: 2, ..SampleConfig::default() });
    for r in 0..6u64 {
        let s = two.sample(0, 2 + 3 * r).unwrap();
        let score: Vec<f32> = s.objects.iter().map(|o| o.score).collect();
        assert_eq!(score.len(), 2);
        assert!(score[0] >= score[1]);
    }
}

#[test]
fn every_inpainting_method_fills_the_holes_as_the_whole_frame_call_does() {
    for method in
        [InpaintMethod::Telea, InpaintMethod::TeleaKnownOnly, InpaintMethod::TeleaZeroOrder, InpaintMethod::TeleaOpencv]
    {
        // (every hole to Telea: with `background = "planes"` the MPI's planes would fill the
        // holes this motion opens next to the moved object)
        let config = SampleConfig {
            inpaint_method: method,
            inpaint_radius: 5.0,
            background: mpiflow::sample::background::Background::Inpaint,
            ..SampleConfig::default()
        };
        let g = generator(Procedural::new(2), config.clone());
        let s = g.sample(0, 1).unwrap();
        // the same address up to the merge: image2 before inpainting, and its holes
        let scene = g.scene(g.source_item(1).unwrap()).unwrap();
        let (merged, hole) = assemble_merged(&scene, s.address, &config, None).unwrap();
        let (w, h) = (s.width, s.height);
        let holes: Vec<usize> = (0..w * h).filter(|&i| hole[i] != 0).collect();
        assert!(!holes.is_empty(), "{method:?}: the camera motion opens holes");
        assert_eq!((s.inpainted_pixels, merged.inpainted_pixels), (holes.len() as u64, holes.len() as u64));
        // inpainting changes image2 in the holes only...
        assert_eq!(bytes(&Sample { image2: s.image2.clone(), ..merged.clone() }), bytes(&s), "{method:?}");
        let px = |img: &[u8], i: usize| [img[3 * i], img[3 * i + 1], img[3 * i + 2]];
        for i in (0..w * h).filter(|&i| hole[i] == 0) {
            assert_eq!(px(&s.image2, i), px(&merged.image2, i), "{method:?}: pixel {i} is not a hole");
        }
        // ... where it changed the merge's pixels ...
        let changed = holes.iter().filter(|&&i| px(&s.image2, i) != px(&merged.image2, i)).count();
        assert!(changed * 2 > holes.len(), "{method:?}: only {changed} of {} hole pixels changed", holes.len());
        // ... to what the inpainting function gives on the merged image over the whole frame,
        // from its background only (the moved object's pixels are no context)
        let mut direct = merged.image2.clone();
        inpaint_background(&mut direct, w, h, &hole, &merged.mask2, method, config.inpaint_radius, false);
        assert!(direct == s.image2, "{method:?}: the sample's holes differ from the whole-frame inpainting");
    }
    // the same address under objects_follow_camera (the option is part of the fingerprint, so
    // the address is given explicitly)
    let plain = SampleConfig::default();
    let g = generator(Procedural::new(2), plain.clone());
    let b = g.sample(0, 1).unwrap();
    let scene = g.scene(g.source_item(1).unwrap()).unwrap();
    let follow = SampleConfig { objects_follow_camera: true, ..plain };
    let a = assemble(&scene, b.address, &follow).unwrap();
    assert_eq!(a.camera, b.camera);
    assert_eq!(a.objects[0].motion, b.objects[0].motion, "the drawn motion is recorded, not the composed one");
    assert_ne!(a.flow, b.flow, "objects that follow the camera move differently");
    let pre = generator(Procedural::new(2), SampleConfig { preblend: true, ..SampleConfig::default() });
    assert!(pre.sample(0, 1).unwrap().provenance.iter().any(|p| p.starts_with("preblend")));
}

#[test]
fn errors_name_the_source() {
    let empty = generator(Procedural::new(0), SampleConfig::default());
    assert!(matches!(empty.sample(0, 0), Err(SampleError::EmptySource)));

    // a failing item is skipped: its index is served by the next item, the failure is recorded
    // with the item's id and file, remembered (not loaded again) and never cached as a scene
    let mut loader = Procedural::new(3);
    loader.failing = Some(1);
    let g = generator(loader, SampleConfig::default());
    assert_eq!(g.sample(0, 0).unwrap().skipped_sources, 0);
    let s = g.sample(0, 1).unwrap();
    assert_eq!((s.source_id.as_str(), s.skipped_sources), ("procedural-2", 1));
    let skipped = g.skipped();
    assert_eq!(skipped.len(), 1);
    let (item, id, reason) = &skipped[0];
    assert_eq!((*item, id.as_str()), (1, "procedural-1"));
    assert!(reason.contains("procedural-1") && reason.contains("procedural/1.npy"), "{reason}");
    assert_eq!(g.skip_counts().into_iter().collect::<Vec<_>>(), [(FailureKind::Depth, 1)], "the kind the loader gave");
    assert_eq!(bytes(&g.sample(0, 1).unwrap()), bytes(&s));
    assert_eq!(g.cache().stats().load_errors, 1, "a known-bad item is not loaded again");
    assert_eq!(g.cache().stats().entries, 2);

    // nothing loads: an error naming the first failure
    let mut loader = Procedural::new(1);
    loader.failing = Some(0);
    let g = generator(loader, SampleConfig::default());
    for _ in 0..2 {
        let err = g.sample(0, 0).unwrap_err();
        assert!(matches!(err, SampleError::NoGoodSource { items: 1, .. }), "{err}");
        assert!(err.to_string().contains("procedural/0.npy"), "{err}");
    }
    assert_eq!(g.cache().stats().load_errors, 1);

    let bad = SampleConfig { mask_threshold: 0.0, ..SampleConfig::default() };
    let e = Generator::new(Arc::new(Procedural::new(1)), Arc::new(SceneCache::new(1 << 20)), bad).unwrap_err();
    assert!(e.to_string().contains("mask_threshold"), "{e}");
    let mut ranges = MotionPreset::Reference.ranges();
    ranges.camera.translation.x = Component::Uniform { lo: 1.0, hi: -1.0 };
    let bad = SampleConfig { motion: MotionSpec::Ranges(Box::new(ranges)), ..SampleConfig::default() };
    let e = Generator::new(Arc::new(Procedural::new(1)), Arc::new(SceneCache::new(1 << 20)), bad).unwrap_err();
    assert!(e.to_string().contains("camera.translation.x"), "{e}");
}

#[test]
fn config_round_trips_through_json() {
    let c: SampleConfig = serde_json::from_str(
        r#"{"motion": "paper-kitti", "max_objects": 2, "merge": "reference", "inpaint_method": "telea-opencv",
            "mode": "exact", "skip": {"transmittance_eps": 0.001, "tiles": true, "tile_sigma_eps": 0.0}}"#,
    )
    .unwrap();
    assert_eq!(c.motion, MotionSpec::Preset(MotionPreset::PaperKitti));
    assert_eq!((c.max_objects, c.merge, c.inpaint_method), (2, MergeRule::Reference, InpaintMethod::TeleaOpencv));
    assert_eq!(c.skip.transmittance_eps, 0.001);
    assert_eq!(c.inpaint_radius, 3.0, "left-out fields take their defaults");
    for config in [
        c,
        SampleConfig::default(),
        SampleConfig {
            motion: MotionSpec::Ranges(Box::new(MotionPreset::Depthstillation.ranges())),
            ..SampleConfig::default()
        },
    ] {
        let json = serde_json::to_string(&config).unwrap();
        let back: SampleConfig = serde_json::from_str(&json).unwrap();
        assert_eq!(back, config, "{json}");
    }
    assert!(serde_json::from_str::<SampleConfig>(r#"{"max_object": 2}"#).is_err(), "unknown fields are refused");
    let d = SampleConfig::default();
    assert_eq!((d.max_objects, d.merge, d.inpaint_radius), (1, MergeRule::DepthAware, 3.0));
    assert_eq!((d.motions_per_image, d.scene_window), (8, 11));
}

#[test]
fn depth1_is_the_scenes_depth_and_depth2_what_image2_shows() {
    let g = generator(Procedural::new(3), SampleConfig { max_objects: 2, ..SampleConfig::default() });
    for index in [0u64, 1, 2, 7] {
        let s = g.sample(3, index).unwrap();
        let item = g.source_item(index).unwrap();
        let scene = g.scene(item).unwrap();
        let n = W * H;
        assert_eq!((s.depth1.len(), s.depth2.len()), (n, n));
        // depth1 = 1 / disparity (the procedural depth divided by its nearest value)
        assert_eq!(s.depth1, mpiflow::scene::scale::depth_from_disparity(&scene.disparity));
        assert!(s.depth1.iter().all(|&d| (1.0..1000.0).contains(&d)));
        // depth2: positive where image2 shows something, 0 exactly in the inpainted holes
        assert!(s.depth2.iter().all(|d| d.is_finite() && *d >= 0.0));
        let zeros = s.depth2.iter().filter(|&&d| d == 0.0).count() as u64;
        assert_eq!(zeros, s.inpainted_pixels, "index {index}");
        // where a moved object is drawn, its depth is that of one of the boxes (moved a little)
        for (i, &label) in s.mask2.iter().enumerate() {
            if label != 0 {
                assert!(s.depth2[i] > 0.5 && s.depth2[i] < 3.0, "object depth {} at {i}", s.depth2[i]);
            }
        }
    }

    // without any motion, image2's depth is the source's, up to the MPI's layering
    let still = RigidLaw {
        translation: mpiflow::sample::motion::Axes {
            x: Component::symmetric(0.0),
            y: Component::symmetric(0.0),
            z: Component::symmetric(0.0),
        },
        rotation_kind: RotationKind::AxisAngle,
        rotation: mpiflow::sample::motion::Axes {
            x: Component::symmetric(0.0),
            y: Component::symmetric(0.0),
            z: Component::symmetric(0.0),
        },
    };
    let mut ranges = MotionPreset::Reference.ranges();
    ranges.camera = still;
    ranges.object = still;
    let config = SampleConfig { motion: MotionSpec::Ranges(Box::new(ranges)), ..SampleConfig::default() };
    // a scene made by the scene stage (whose MPI lives in the scene scale) from a given depth
    let proc_scene = Procedural::new(1).load_scene(0).unwrap();
    let depth: Vec<f32> = proc_scene.disparity.data.iter().map(|d| 3.0 / d).collect();
    let item = mpiflow::source::SourceItem {
        id: "given".into(),
        image: proc_scene.image.clone(),
        depth: Some(mpiflow::source::GivenDepth::Depth(depth)),
        masks: None,
        mpi: None,
        intrinsics: None,
    };
    let scene = mpiflow::scene::stage::SceneStage::builtin().scene(item).unwrap();
    let address = mpiflow::sample::SampleAddress { dataset: 1, seed: 0, index: 0 };
    let s = mpiflow::sample::recipe::assemble(&scene, address, &config).unwrap();
    assert_eq!(s.camera.translation, [0.0; 3]);
    let mut rel: Vec<f32> =
        s.depth1.iter().zip(&s.depth2).map(|(&a, &b)| if b > 0.0 { (b - a).abs() / a } else { 1.0 }).collect();
    rel.sort_by(f32::total_cmp);
    let (median, p95) = (rel[rel.len() / 2], rel[rel.len() * 95 / 100]);
    assert!(median < 0.05 && p95 < 0.25, "relative depth error median {median}, p95 {p95}");
}
