//! Bad sources are skipped deterministically: a directory with a corrupt PNG, a truncated JPEG, a
//! truncated PNG, an image over the limits and an unreadable depth file among good photos gives a
//! sample for every index, byte-identical across fresh generators, request orders and thread
//! counts, with each bad item skipped once and counted by reason; and each kind of bad file (corrupt,
//! truncated, over the limits, bad depth, disparity, mask or MPI) is counted as its kind.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use mpiflow::io::image::{jpeg_truncation, ImageLimits};
use mpiflow::sample::config::SampleConfig;
use mpiflow::sample::error::SampleError;
use mpiflow::sample::pipeline::Generator;
use mpiflow::sample::{Sample, StageTimings};
use mpiflow::scene::cache::SceneCache;
use mpiflow::scene::stage::{SceneStage, SourceScenes};
use mpiflow::source::{open_source, FailureKind, SourceOptions};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("mpiflow-bad-sources-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A textured w x h photo, different per seed.
fn photo(w: u32, h: u32, seed: u32) -> image::RgbImage {
    image::RgbImage::from_fn(w, h, |x, y| {
        let v = (x * 7 + y * 13 + seed * 31) % 256;
        image::Rgb([v as u8, ((x * 3 + seed * 50) % 256) as u8, ((y * 5 + x * y / 7) % 256) as u8])
    })
}

fn encode(img: &image::RgbImage, format: image::ImageFormat) -> Vec<u8> {
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, format).unwrap();
    out.into_inner()
}

/// An 8-bit disparity map: a ramp from far (top) to near (bottom).
fn disparity(w: u32, h: u32) -> Vec<u8> {
    let img = image::GrayImage::from_fn(w, h, |_, y| image::Luma([(60 + 190 * y / h.max(1)) as u8]));
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).unwrap();
    out.into_inner()
}

/// The reference layout: images/NAME.* with disps/NAME.png, and the bad items.
fn dataset(root: &Path) {
    for d in ["images", "disps", "depths"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    let (w, h) = (48, 32);
    let write = |name: &str, bytes: &[u8]| std::fs::write(root.join(name), bytes).unwrap();
    let png = |seed| encode(&photo(w, h, seed), image::ImageFormat::Png);
    let jpg = |seed| encode(&photo(w, h, seed), image::ImageFormat::Jpeg);
    // a: good
    write("images/a.png", &png(1));
    // b: corrupt PNG (a valid signature, then garbage)
    let mut b = png(2);
    for (i, v) in b.iter_mut().enumerate().skip(40) {
        *v = (i * 17 % 251) as u8;
    }
    write("images/b.png", &b);
    // c: truncated JPEG
    let c = jpg(3);
    assert!(jpeg_truncation(&c).is_none());
    write("images/c.jpg", &c[..c.len() * 2 / 3]);
    // d: good JPEG
    write("images/d.jpg", &jpg(4));
    // e: over the limits (the test's max width is 64)
    write("images/e.png", &encode(&photo(80, 20, 5), image::ImageFormat::Png));
    // f: good image, unreadable depth
    write("images/f.png", &png(6));
    write("depths/f.npy", b"\x93NUMPY garbage");
    // g: good
    write("images/g.png", &png(7));
    // h: truncated PNG
    let hb = png(8);
    write("images/h.png", &hb[..hb.len() / 2]);
    for name in ["a", "b", "c", "d", "e", "g", "h"] {
        write(&format!("disps/{name}.png"), &disparity(w, h));
    }
}

/// The test's limits, with the check at open off: bad photos stay in the index and fail when
/// loaded, as a shard's or an upload's do (the default check leaves them out, see below).
fn options() -> SourceOptions {
    SourceOptions {
        limits: ImageLimits { max_width: 64, ..ImageLimits::default() },
        check_at_open: false,
        ..SourceOptions::default()
    }
}

fn generator(root: &Path) -> Generator {
    let source = open_source(root, &options()).unwrap();
    let loader = SourceScenes::new(source, Arc::new(SceneStage::builtin()));
    Generator::new(Arc::new(loader), Arc::new(SceneCache::new(1 << 30)), SampleConfig::default()).unwrap()
}

fn bytes(s: &Sample) -> Sample {
    Sample { timings: StageTimings::default(), ..s.clone() }
}

#[test]
fn every_index_gets_a_sample_from_the_next_good_source_deterministically() {
    let root = tmp("dir");
    dataset(&root);
    let g = generator(&root);
    let n = 8u64;
    let samples: Vec<Sample> = (0..2 * n).map(|i| g.sample(5, i).unwrap()).collect();
    let good = |i: u64| ["a", "d", "d", "d", "g", "g", "g", "a"][(i % n) as usize];
    let passed = |i: u64| [0u32, 2, 1, 0, 2, 1, 0, 1][(i % n) as usize];
    for (i, s) in samples.iter().enumerate() {
        let i = i as u64;
        assert_eq!((s.source_id.as_str(), s.skipped_sources), (good(i), passed(i)), "index {i}");
        assert_eq!(s.address.index, i);
        // the record says whose slot a stand-in fills
        let stand_in = s.provenance.iter().find(|p| p.starts_with("source: "));
        match passed(i) {
            0 => assert!(stand_in.is_none(), "index {i}: {stand_in:?}"),
            _ => {
                let line = stand_in.expect("a stand-in is recorded");
                let own = format!("stands in for item {} (", i % n);
                assert!(line.starts_with(&format!("source: {} ", good(i))) && line.contains(&own), "{line}");
            }
        }
    }
    // the address keeps its own motions: indices served by the same source differ
    assert_ne!(samples[1].camera, samples[3].camera);
    assert_ne!(samples[1].image2, samples[3].image2);

    // each bad item recorded once, with its failure kind
    let skipped = g.skipped();
    let ids: Vec<(usize, &str)> = skipped.iter().map(|(i, id, _)| (*i, id.as_str())).collect();
    assert_eq!(ids, [(1, "b"), (2, "c"), (4, "e"), (5, "f"), (7, "h")]);
    for (_, id, reason) in &skipped {
        assert!(reason.contains(&format!("({id})")), "{reason}");
    }
    let counts: Vec<(&str, u64)> = g.skip_counts().into_iter().map(|(k, n)| (k.as_str(), n)).collect();
    assert_eq!(counts, [("decode", 1u64), ("truncated", 2), ("too-large", 1), ("depth", 1)], "{skipped:#?}");
    // a bad item is loaded once: 5 failures in the cache's counters, however many samples
    assert_eq!(g.cache().stats().load_errors, 5);

    // fresh generators, other request orders and thread counts give the same bytes
    let pool = |t: usize| rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
    let fresh = generator(&root);
    for i in (0..2 * n).rev() {
        assert_eq!(bytes(&fresh.sample(5, i).unwrap()), bytes(&samples[i as usize]), "index {i} (reverse order)");
    }
    for threads in [1, 2] {
        let p = pool(threads);
        for i in [1u64, 4, 7, 9] {
            let one = generator(&root); // nothing known: finds the bad items itself
            let s = p.install(|| one.sample(5, i)).unwrap();
            assert_eq!(bytes(&s), bytes(&samples[i as usize]), "index {i}, {threads} threads");
        }
    }
}

#[test]
fn all_bad_sources_is_an_error_not_a_loop() {
    let root = tmp("all-bad");
    std::fs::write(root.join("x.png"), b"\x89PNG\r\n\x1a\nnot really").unwrap();
    std::fs::write(root.join("y.jpg"), b"\xff\xd8\xff\xe0 cut").unwrap();
    let g = generator(&root);
    for i in 0..3 {
        match g.sample(0, i) {
            Err(SampleError::NoGoodSource { items: 2, first }) => assert!(first.contains("x.png"), "{first}"),
            other => panic!("expected NoGoodSource, got {other:?}"),
        }
    }
    assert_eq!(g.skipped().len(), 2);
    assert_eq!(g.cache().stats().load_errors, 2);
}

#[test]
fn plain_images_without_depth_or_model_are_depth_skips() {
    // plain images without depth and no depth model: every item says so, as a depth problem
    let root = tmp("no-depth");
    std::fs::write(root.join("p.png"), encode(&photo(16, 16, 1), image::ImageFormat::Png)).unwrap();
    let g = generator(&root);
    let e = g.sample(0, 0).unwrap_err();
    assert!(e.to_string().contains("no depth"), "{e}");
    assert_eq!(g.skip_counts().into_iter().collect::<Vec<_>>(), [(FailureKind::Depth, 1)]);
}

/// One kind of bad file: what to write next to a good image (`images/a.png` with its disparity)
/// for the bad item `b`, and the kind its failure must be counted as.
struct BadCase {
    what: &'static str,
    files: Vec<(&'static str, Vec<u8>)>,
    kind: FailureKind,
}

fn bad_cases() -> Vec<BadCase> {
    let (w, h) = (48, 32);
    let png = encode(&photo(w, h, 2), image::ImageFormat::Png);
    let jpg = encode(&photo(w, h, 3), image::ImageFormat::Jpeg);
    let mut corrupt = png.clone();
    for (i, v) in corrupt.iter_mut().enumerate().skip(40) {
        *v = (i * 17 % 251) as u8;
    }
    let with_disp = |image: (&'static str, Vec<u8>)| vec![image, ("disps/b.png", disparity(w, h))];
    let good_b = || ("images/b.png", png.clone());
    let case = |what, files, kind| BadCase { what, files, kind };
    vec![
        case("corrupt PNG", with_disp(("images/b.png", corrupt.clone())), FailureKind::Decode),
        case("truncated JPEG", with_disp(("images/b.jpg", jpg[..jpg.len() * 2 / 3].to_vec())), FailureKind::Truncated),
        case("truncated PNG", with_disp(("images/b.png", png[..png.len() / 2].to_vec())), FailureKind::Truncated),
        case(
            "image over the limits",
            with_disp(("images/b.png", encode(&photo(80, 20, 5), image::ImageFormat::Png))),
            FailureKind::TooLarge,
        ),
        case("unreadable depth", vec![good_b(), ("depths/b.npy", b"\x93NUMPY garbage".to_vec())], FailureKind::Depth),
        case(
            "truncated PFM depth",
            vec![good_b(), ("depths/b.pfm", b"Pf\n48 32\n-1\n\0\0\0\0".to_vec())],
            FailureKind::Truncated,
        ),
        case("no depth at all", vec![good_b()], FailureKind::Depth),
        case("corrupt disparity PNG", vec![good_b(), ("disps/b.png", corrupt.clone())], FailureKind::Depth),
        case(
            "corrupt mask",
            vec![good_b(), ("disps/b.png", disparity(w, h)), ("masks/b.png", corrupt.clone())],
            FailureKind::Mask,
        ),
        case(
            "broken MPI archive",
            vec![good_b(), ("disps/b.png", disparity(w, h)), ("mpis/b.npz", b"PK not really".to_vec())],
            FailureKind::Mpi,
        ),
    ]
}

#[test]
fn each_kind_of_bad_file_is_counted_as_its_kind() {
    for (n, case) in bad_cases().into_iter().enumerate() {
        let root = tmp(&format!("kind-{n}"));
        for d in ["images", "disps", "depths", "masks", "mpis"] {
            std::fs::create_dir_all(root.join(d)).unwrap();
        }
        std::fs::write(root.join("images/a.png"), encode(&photo(48, 32, 1), image::ImageFormat::Png)).unwrap();
        std::fs::write(root.join("disps/a.png"), disparity(48, 32)).unwrap();
        for (name, bytes) in &case.files {
            std::fs::write(root.join(name), bytes).unwrap();
        }
        let what = case.what;
        // the source says so where it fails (the no-depth case fails later, in the scene stage)
        let src = open_source(&root, &options()).unwrap();
        assert_eq!(src.len(), 2, "{what}");
        let loaded = src.load(1);
        match &loaded {
            Err(e) => assert_eq!(e.failure_kind(), Some(case.kind), "{what}: {e}"),
            Ok(_) => assert_eq!(what, "no depth at all", "{what}: the bad item loaded"),
        }
        // and the generator passes the item over and counts it as that kind, and only it
        let g = generator(&root);
        let s = g.sample(3, 1).unwrap();
        assert_eq!((s.source_id.as_str(), s.skipped_sources), ("a", 1), "{what}");
        assert_eq!(g.skip_counts().into_iter().collect::<Vec<_>>(), [(case.kind, 1)], "{what}: {:?}", g.skipped());
        let (item, id, reason) = &g.skipped()[0];
        assert_eq!((*item, id.as_str()), (1, "b"), "{what}");
        assert!(reason.contains("(b)"), "{what}: {reason}");
        assert_eq!(g.sample(3, 0).unwrap().skipped_sources, 0, "{what}: the good item is its own");
    }
}

#[test]
fn jpeg_truncation_finds_cuts_anywhere_and_accepts_trailers() {
    let full = encode(&photo(40, 24, 9), image::ImageFormat::Jpeg);
    assert_eq!(jpeg_truncation(&full), None);
    let mut trailer = full.clone();
    trailer.extend_from_slice(b"camera trailer \xff\xd9 junk");
    assert_eq!(jpeg_truncation(&trailer), None);
    for cut in [3, 10, 100, full.len() / 2, full.len() - 2, full.len() - 1] {
        let r = jpeg_truncation(&full[..cut]);
        assert!(r.as_deref().is_some_and(|m| m.contains("truncated JPEG")), "cut at {cut}: {r:?}");
    }
    // not a JPEG: not this check's business
    assert_eq!(jpeg_truncation(b"\x89PNG\r\n\x1a\n"), None);
    // and the decoder path reports it (the lenient decoder alone would fill in grey)
    let e = mpiflow::io::image::load_rgb_from_bytes(&full[..full.len() / 2], &ImageLimits::default()).unwrap_err();
    assert!(e.to_string().contains("truncated JPEG"), "{e}");
    let src_dir = tmp("jpeg");
    std::fs::write(src_dir.join("t.jpg"), &full[..full.len() - 1]).unwrap();
    let src = open_source(&src_dir, &options()).unwrap();
    assert!(src.load(0).unwrap_err().to_string().contains("truncated JPEG"));
    // checked when the folder is opened (the default), the photo is left out: none can serve
    let Err(e) = open_source(&src_dir, &SourceOptions::default()) else { panic!("the folder opened") };
    assert!(e.to_string().contains("no photo can serve") && e.to_string().contains("truncated JPEG"), "{e}");
}

#[test]
fn checked_at_open_the_photos_whose_header_fails_are_left_out_by_kind() {
    let root = tmp("at-open");
    dataset(&root);
    let checked = SourceOptions { check_at_open: true, ..options() };
    let src = open_source(&root, &checked).unwrap();
    let ids: Vec<String> = (0..src.len()).map(|i| src.id(i)).collect();
    // the corrupt PNG's header, the truncated JPEG, the photo over the limits and the unreadable
    // depth are seen at open; the truncated PNG's header is whole (it fails when loaded)
    assert_eq!(ids, ["a", "d", "g", "h"]);
    let left: Vec<(String, FailureKind)> = src.skipped().into_iter().map(|s| (s.item, s.kind)).collect();
    assert_eq!(
        left,
        [
            ("depths/f.npy".to_string(), FailureKind::Depth),
            ("images/b.png".to_string(), FailureKind::Decode),
            ("images/c.jpg".to_string(), FailureKind::Truncated),
            ("images/e.png".to_string(), FailureKind::TooLarge),
        ]
    );
}
