//! Sources: directory layouts (plain, reference, single file), given depth / disparity / masks /
//! MPI files, PFM, errors per item, fingerprints, resizing and intrinsics, the scene-scale
//! conversions, and the bundled procedural scenes.

use mpiflow::geometry::Intrinsics;
use mpiflow::io::image::{save_gray16_png, save_gray_png, save_rgb_png, ImageLimits, RgbImage};
use mpiflow::io::npy::write_f32;
use mpiflow::raster::InstanceMasks;
use mpiflow::scene::scale::{
    disparity_from_depth, disparity_from_given, disparity_from_unit, fill_nearest, normalise_relative, DISPARITY_FLOOR,
};
use mpiflow::source::builtin::{BuiltinOptions, BuiltinSource, Shape};
use mpiflow::source::dir::{DepthFile, Layout, MaskFile};
use mpiflow::source::pfm::{encode_pfm, parse_pfm, read_pfm, write_pfm};
use mpiflow::source::{
    fnv1a64, DirSource, FailureKind, GivenDepth, IntrinsicsSpec, Source, SourceError, SourceOptions,
};
use std::path::{Path, PathBuf};

/// A fresh, empty temporary folder for one test.
fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("mpiflow-sources-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A w x h test image whose pixel (x, y) is (x / w, y / h, seed / 10).
fn image(w: usize, h: usize, seed: usize) -> RgbImage {
    let mut data = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            data.extend_from_slice(&[x as f32 / w as f32, y as f32 / h as f32, (seed % 10) as f32 / 10.0]);
        }
    }
    RgbImage { width: w, height: h, data }
}

fn write_jpeg(path: &Path, img: &RgbImage) {
    let bytes: Vec<u8> = img.data.iter().map(|v| (v * 255.0).round() as u8).collect();
    image::RgbImage::from_raw(img.width as u32, img.height as u32, bytes).unwrap().save(path).unwrap();
}

fn mkdirs(root: &Path) {
    for d in ["images", "depths", "disps", "masks", "mpis"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
}

fn depth_of(item: &mpiflow::source::SourceItem) -> &[f32] {
    match item.depth.as_ref().expect("depth") {
        GivenDepth::Depth(d) => d,
        GivenDepth::Disparity(_) => panic!("expected metric depth"),
    }
}

fn disp_of(item: &mpiflow::source::SourceItem) -> &[f32] {
    match item.depth.as_ref().expect("disparity") {
        GivenDepth::Disparity(d) => d,
        GivenDepth::Depth(_) => panic!("expected disparity"),
    }
}

#[test]
fn plain_dir_lists_images_sorted_and_loads_lazily() {
    let root = tmp("plain");
    save_rgb_png(&root.join("b.png"), &image(8, 6, 1)).unwrap();
    write_jpeg(&root.join("a.JPG"), &image(10, 4, 2));
    save_rgb_png(&root.join("c.jpeg.png"), &image(3, 3, 3)).unwrap();
    std::fs::write(root.join("notes.txt"), "not an image").unwrap();
    std::fs::create_dir_all(root.join("sub.png")).unwrap(); // a folder is not an image
    let src = DirSource::open(&root, &SourceOptions::default()).unwrap();
    assert_eq!(src.layout(), Layout::Plain);
    assert_eq!(src.len(), 3);
    let ids: Vec<String> = (0..3).map(|i| src.id(i)).collect();
    assert_eq!(ids, ["a", "b", "c.jpeg"]);
    // three sizes: one frame, the largest photo's (8x6 has the most pixels), each photo covering it
    assert!(src.describe().contains("3 images, working size 8x6: each covers it, centred"), "{}", src.describe());
    let a = src.load(0).unwrap();
    assert_eq!((a.image.width, a.image.height), (8, 6));
    assert!(a.depth.is_none() && a.masks.is_none() && a.mpi.is_none() && a.intrinsics.is_none());
    let b = src.load(1).unwrap();
    assert_eq!(b.image, quantised(&image(8, 6, 1)));
    assert!(matches!(src.load(3), Err(SourceError::Invalid(_))));
}

/// The image as an 8-bit PNG round trip gives it back.
fn quantised(img: &RgbImage) -> RgbImage {
    RgbImage {
        width: img.width,
        height: img.height,
        data: img.data.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() / 255.0).collect(),
    }
}

#[test]
fn empty_or_missing_dirs_are_errors() {
    let root = tmp("empty");
    std::fs::write(root.join("readme.md"), "x").unwrap();
    let e = DirSource::open(&root, &SourceOptions::default()).unwrap_err();
    assert!(e.to_string().contains("no .png"), "{e}");
    let e = DirSource::open(&root.join("nope"), &SourceOptions::default()).unwrap_err();
    assert!(matches!(&e, SourceError::File { message, .. } if message == "not found"), "{e}");
    std::fs::create_dir_all(root.join("images")).unwrap();
    let e = DirSource::open(&root, &SourceOptions::default()).unwrap_err();
    assert!(e.to_string().contains("images/"), "{e}");
}

#[test]
fn single_file_source() {
    let root = tmp("single");
    let p = root.join("photo.png");
    save_rgb_png(&p, &image(5, 4, 0)).unwrap();
    let src = DirSource::open(&p, &SourceOptions::default()).unwrap();
    assert_eq!((src.layout(), src.len(), src.id(0)), (Layout::File, 1, "photo".to_string()));
    assert_eq!(src.load(0).unwrap().image.width, 5);
    std::fs::write(root.join("x.txt"), "x").unwrap();
    assert!(DirSource::open(&root.join("x.txt"), &SourceOptions::default()).is_err());
}

/// Builds the reference layout used by several tests: W x H = 6 x 4 images a..f.
fn reference_fixture(root: &Path) -> (usize, usize) {
    let (w, h) = (6usize, 4usize);
    mkdirs(root);
    for (k, n) in ["a", "b", "c", "d", "e", "f"].iter().enumerate() {
        save_rgb_png(&root.join(format!("images/{n}.png")), &image(w, h, k)).unwrap();
    }
    // a: npy depth with unknown pixels, and masks
    let mut depth: Vec<f32> = (0..w * h).map(|i| 2.0 + i as f32 * 0.25).collect();
    depth[3] = f32::NAN;
    depth[7] = 0.0;
    depth[8] = -1.0;
    write_f32(&root.join("depths/a.npy"), &[h as u64, w as u64], &depth).unwrap();
    let ids: Vec<u8> = (0..w * h)
        .map(|i| {
            if i % w < 2 {
                3
            } else if i / w == 3 {
                7
            } else {
                0
            }
        })
        .collect();
    save_gray_png(&root.join("masks/a.png"), w, h, &ids).unwrap();
    // b: 8-bit disparity
    let d8: Vec<u8> = (0..w * h).map(|i| (i * 10) as u8).collect();
    save_gray_png(&root.join("disps/b.png"), w, h, &d8).unwrap();
    // c: 16-bit disparity
    let d16: Vec<u16> = (0..w * h).map(|i| (i * 2000) as u16).collect();
    save_gray16_png(&root.join("disps/c.png"), w, h, &d16).unwrap();
    // d: PFM depth (little-endian) and an 8-bit disparity that the depth overrides
    let pfm: Vec<f32> = (0..w * h).map(|i| 1.0 + i as f32).collect();
    write_pfm(&root.join("depths/d.pfm"), w, h, 1, &pfm, true).unwrap();
    save_gray_png(&root.join("disps/d.png"), w, h, &d8).unwrap();
    // e: 16-bit PNG depth in millimetres (0 = unknown), [1, H, W] npy shape is tested on f
    let mm: Vec<u16> = (0..w * h).map(|i| if i == 0 { 0 } else { 1000 + i as u16 }).collect();
    save_gray16_png(&root.join("depths/e.png"), w, h, &mm).unwrap();
    // f: [1, H, W] float depth at half resolution (resized to the image by nearest neighbour)
    let half: Vec<f32> = (0..(w / 2) * (h / 2)).map(|i| 10.0 + i as f32).collect();
    write_f32(&root.join("depths/f.npy"), &[1, (h / 2) as u64, (w / 2) as u64], &half).unwrap();
    (w, h)
}

#[test]
fn reference_layout_reads_every_companion() {
    let root = tmp("reference");
    let (w, h) = reference_fixture(&root);
    let src = DirSource::open(&root, &SourceOptions::default()).unwrap();
    assert_eq!(src.layout(), Layout::Reference);
    assert_eq!(src.len(), 6);
    assert!(
        src.describe().contains("reference layout: 4 depths, 3 disparities, 1 masks, 0 MPIs"),
        "{}",
        src.describe()
    );
    let files = src.files(0).unwrap();
    assert_eq!(files.depth.as_ref().unwrap().0, DepthFile::Npy);
    assert_eq!(files.masks.as_ref().unwrap().0, MaskFile::IndexPng);
    assert_eq!(src.files(3).unwrap().depth.unwrap().0, DepthFile::Pfm);
    assert_eq!(src.files(4).unwrap().depth.unwrap().0, DepthFile::Png16);

    // a: npy depth kept as read (unknown values included), masks by id
    let a = src.load(0).unwrap();
    let d = depth_of(&a);
    assert_eq!(d.len(), w * h);
    assert_eq!(d[0], 2.0);
    assert!(d[3].is_nan() && d[7] == 0.0 && d[8] == -1.0);
    let m = a.masks.as_ref().unwrap();
    assert_eq!(m.masks.iter().map(|i| i.id).collect::<Vec<_>>(), vec![3, 7]);
    assert_eq!(m.masks[0].area, 8.0);
    assert_eq!(m.masks[1].area, 4.0);

    // b: 8-bit disparity / 255
    let b = src.load(1).unwrap();
    let db = disp_of(&b);
    for (i, &v) in db.iter().enumerate() {
        assert_eq!(v, (i * 10) as f32 / 255.0);
    }
    // c: 16-bit disparity / 65535
    let c = src.load(2).unwrap();
    for (i, &v) in disp_of(&c).iter().enumerate() {
        assert_eq!(v, (i * 2000) as f32 / 65535.0);
    }
    // d: the PFM depth wins over the disparity PNG; rows top to bottom
    let dd = src.load(3).unwrap();
    assert_eq!(depth_of(&dd), (0..w * h).map(|i| 1.0 + i as f32).collect::<Vec<_>>().as_slice());
    // e: 16-bit depth PNG raw values
    let e = src.load(4).unwrap();
    assert_eq!(depth_of(&e)[0], 0.0);
    assert_eq!(depth_of(&e)[5], 1005.0);
    // f: [1, H/2, W/2] resized to H x W by nearest neighbour
    let f = src.load(5).unwrap();
    let df = depth_of(&f);
    assert_eq!(df.len(), w * h);
    assert_eq!((df[0], df[1], df[2], df[w], df[2 * w + 5]), (10.0, 10.0, 11.0, 10.0, 15.0));
}

#[test]
fn corrupt_or_missing_file_fails_only_its_item() {
    let root = tmp("corrupt");
    reference_fixture(&root);
    std::fs::write(root.join("depths/a.npy"), b"\x93NUMPY garbage").unwrap();
    std::fs::write(root.join("disps/b.png"), b"\x89PNG\r\n\x1a\n truncated").unwrap();
    std::fs::write(root.join("depths/d.pfm"), b"Pf\n6 4\n-1\n\0\0\0\0").unwrap();
    std::fs::write(root.join("images/e.png"), b"").unwrap();
    // without the check at open: each bad file fails its item when loaded (as shards' do)
    let src = DirSource::open(&root, &SourceOptions { check_at_open: false, ..SourceOptions::default() }).unwrap();
    let expect = |i: usize, file: &str, what: &str, want: FailureKind| match src.load(i) {
        Err(SourceError::File { path, kind, message }) => {
            assert_eq!(kind, want, "item {i}: {message}");
            assert!(path.ends_with(file), "item {i}: path {path}");
            assert!(message.contains(what), "item {i}: {message}");
            assert!(!message.contains(&path), "item {i}: the path is repeated in {message}");
        }
        other => panic!("item {i}: expected a file error, got {other:?}"),
    };
    expect(0, "depths/a.npy", "npy", FailureKind::Depth);
    expect(1, "disps/b.png", "corrupt", FailureKind::Depth);
    expect(3, "depths/d.pfm", "truncated", FailureKind::Truncated);
    expect(4, "images/e.png", "", FailureKind::Decode);
    assert!(src.load(2).is_ok());
    assert!(src.load(5).is_ok());
    // a file removed after listing
    std::fs::remove_file(root.join("images/c.png")).unwrap();
    match src.load(2) {
        Err(SourceError::File { path, kind, message }) => {
            assert_eq!(kind, FailureKind::Decode);
            assert!(path.ends_with("images/c.png"));
            assert!(message.contains("not found"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    // a depth file of the wrong shape
    write_f32(&root.join("depths/f.npy"), &[2, 3, 4], &[1.0; 24]).unwrap();
    let e = src.load(5).unwrap_err();
    assert!(e.to_string().contains("shape [2, 3, 4]"), "{e}");
}

#[test]
fn limits_refuse_large_companions() {
    let root = tmp("limits");
    reference_fixture(&root);
    let opts = SourceOptions {
        limits: ImageLimits { max_width: 5, ..ImageLimits::default() },
        check_at_open: false,
        ..SourceOptions::default()
    };
    let src = DirSource::open(&root, &opts).unwrap();
    // the 6-pixel-wide image itself is refused, naming the image
    let e = src.load(0).unwrap_err();
    assert!(e.to_string().contains("images/a.png") && e.to_string().contains("too large"), "{e}");
    assert_eq!(e.failure_kind(), Some(FailureKind::TooLarge));
    // a depth larger than the limits is refused before it is used, naming the depth file
    write_f32(&root.join("depths/a.npy"), &[40, 60], &[1.0; 2400]).unwrap();
    let opts =
        SourceOptions { limits: ImageLimits { max_width: 50, ..ImageLimits::default() }, ..SourceOptions::default() };
    let src = DirSource::open(&root, &opts).unwrap();
    let e = src.load(0).unwrap_err();
    assert!(e.to_string().contains("depths/a.npy") && e.to_string().contains("too large"), "{e}");
    assert_eq!(e.failure_kind(), Some(FailureKind::TooLarge));
    assert!(src.load(1).is_ok());
}

#[test]
fn given_mpi_is_loaded_and_must_match_the_image() {
    let root = tmp("mpi");
    mkdirs(&root);
    let npz = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/case_tx.npz");
    std::fs::copy(&npz, root.join("mpis/scene.npz")).unwrap();
    save_rgb_png(&root.join("images/scene.png"), &image(64, 48, 0)).unwrap();
    save_rgb_png(&root.join("images/wrong.png"), &image(32, 48, 0)).unwrap();
    std::fs::copy(&npz, root.join("mpis/wrong.npz")).unwrap();
    let src = DirSource::open(&root, &SourceOptions::default()).unwrap();
    let item = src.load(0).unwrap();
    let mpi = item.mpi.unwrap();
    assert_eq!((mpi.width, mpi.height, mpi.planes()), (64, 48, 8));
    assert!(mpi.intrinsics.is_some());
    let e = src.load(1).unwrap_err();
    assert!(e.to_string().contains("mpis/wrong.npz") && e.to_string().contains("not resized"), "{e}");
    // a size limit for MPIs
    let small = SourceOptions { max_mpi_bytes: 1000, ..SourceOptions::default() };
    let e = DirSource::open(&root, &small).unwrap().load(0).unwrap_err();
    assert!(e.to_string().contains("MPI limit"), "{e}");
    // a broken archive
    std::fs::write(root.join("mpis/scene.npz"), b"PK not really").unwrap();
    let e = src.load(0).unwrap_err();
    assert!(e.to_string().contains("npz"), "{e}");
}

#[test]
fn coco_json_masks() {
    let root = tmp("coco");
    mkdirs(&root);
    save_rgb_png(&root.join("images/x.png"), &image(4, 3, 0)).unwrap();
    let json = r#"[{"id": 5, "score": 0.9, "segmentation": {"counts": [1, 2, 9], "size": [3, 4]}}]"#;
    std::fs::write(root.join("masks/x.json"), json).unwrap();
    let src = DirSource::open(&root, &SourceOptions::default()).unwrap();
    let m = src.load(0).unwrap().masks.unwrap();
    assert_eq!(m.masks.len(), 1);
    assert_eq!((m.masks[0].id, m.masks[0].area), (5, 2.0));
    // column-major runs: pixels (x=0, y=1) and (x=0, y=2)
    assert_eq!(m.masks[0].mask[4], 1.0);
    assert_eq!(m.masks[0].mask[8], 1.0);
}

#[test]
fn resize_and_intrinsics_options() {
    let root = tmp("resize");
    let (w, h) = reference_fixture(&root);
    let opts = SourceOptions {
        resize: Some((12, 8)),
        intrinsics: Some(IntrinsicsSpec::Relative(Intrinsics::new(0.58, 0.58, 0.5, 0.5))),
        ..SourceOptions::default()
    };
    let src = DirSource::open(&root, &opts).unwrap();
    let a = src.load(0).unwrap();
    assert_eq!((a.image.width, a.image.height), (12, 8));
    assert_eq!(a.image.data.len(), 12 * 8 * 3);
    let d = depth_of(&a);
    assert_eq!(d.len(), 96);
    // nearest neighbour: each source pixel becomes a 2 x 2 block
    assert_eq!((d[0], d[1], d[12], d[2]), (2.0, 2.0, 2.0, 2.25));
    let m = a.masks.as_ref().unwrap();
    assert_eq!((m.width, m.height), (12, 8));
    assert_eq!(m.masks[0].area, 32.0);
    assert_eq!(a.intrinsics, Some(Intrinsics::new(0.58 * 12.0, 0.58 * 8.0, 6.0, 4.0)));
    // pixel intrinsics are passed through
    let k = Intrinsics::new(100.0, 90.0, 3.0, 2.0);
    let src2 = DirSource::open(
        &root,
        &SourceOptions { intrinsics: Some(IntrinsicsSpec::Pixels(k)), ..SourceOptions::default() },
    )
    .unwrap();
    let b = src2.load(1).unwrap();
    assert_eq!((b.image.width, b.image.height), (w, h));
    assert_eq!(b.intrinsics, Some(k));
    // options that change what is loaded change the fingerprint
    let plain = DirSource::open(&root, &SourceOptions::default()).unwrap();
    assert_ne!(plain.fingerprint(), src.fingerprint());
    assert_ne!(plain.fingerprint(), src2.fingerprint());
}

#[test]
fn fingerprint_is_location_independent_and_tracks_files() {
    let r1 = tmp("fp1");
    let r2 = tmp("fp2");
    reference_fixture(&r1);
    reference_fixture(&r2);
    let o = SourceOptions::default();
    let f1 = DirSource::open(&r1, &o).unwrap().fingerprint();
    assert_eq!(f1, DirSource::open(&r2, &o).unwrap().fingerprint(), "same files, other folder");
    assert_eq!(f1, DirSource::open(&r1, &o).unwrap().fingerprint(), "stable across opens");
    // a file that changes size
    write_f32(&r2.join("depths/a.npy"), &[4, 7], &[1.0; 28]).unwrap();
    let f2 = DirSource::open(&r2, &o).unwrap().fingerprint();
    assert_ne!(f1, f2);
    // a new companion
    save_gray_png(&r2.join("masks/b.png"), 6, 4, &[0; 24]).unwrap();
    assert_ne!(f2, DirSource::open(&r2, &o).unwrap().fingerprint());
    // a same-size edit is only seen with hash_contents
    let r3 = tmp("fp3");
    reference_fixture(&r3);
    let hashed = SourceOptions { hash_contents: true, ..o };
    let h1 = DirSource::open(&r3, &hashed).unwrap().fingerprint();
    let p = r3.join("depths/d.pfm");
    let mut bytes = std::fs::read(&p).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&p, &bytes).unwrap();
    assert_eq!(f1, DirSource::open(&r3, &o).unwrap().fingerprint());
    assert_ne!(h1, DirSource::open(&r3, &hashed).unwrap().fingerprint());
    // FNV-1a 64 test vectors (the fixed algorithm)
    assert_eq!(fnv1a64(b""), 0xcbf2_9ce4_8422_2325);
    assert_eq!(fnv1a64(b"a"), 0xaf63_dc4c_8601_ec8c);
    assert_eq!(fnv1a64(b"foobar"), 0x8594_4171_f739_67e8);
}

#[test]
fn pfm_reader_handles_both_byte_orders_and_row_order() {
    let root = tmp("pfm");
    let data: Vec<f32> = vec![1.0, 2.0, 3.0, 4.0, 5.0, f32::INFINITY];
    for little in [true, false] {
        let p = root.join(format!("x{little}.pfm"));
        write_pfm(&p, 2, 3, 1, &data, little).unwrap();
        let pfm = read_pfm(&p, &ImageLimits::default()).unwrap();
        assert_eq!((pfm.width, pfm.height, pfm.channels), (2, 3, 1));
        assert_eq!(pfm.data, data);
    }
    // a hand-made little-endian file: bottom row stored first
    let mut bytes = b"Pf\n2 2\n-1.000000\n".to_vec();
    for v in [30.0f32, 40.0, 10.0, 20.0] {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    let pfm = parse_pfm(&bytes, &ImageLimits::default()).unwrap();
    assert_eq!(pfm.data, vec![10.0, 20.0, 30.0, 40.0]);
    let mut expect = b"Pf\n2 2\n-1.0\n".to_vec();
    expect.extend_from_slice(&bytes[b"Pf\n2 2\n-1.000000\n".len()..]);
    assert_eq!(encode_pfm(2, 2, 1, &pfm.data, true), expect);
    // a colour PFM is refused as depth
    let rootd = tmp("pfm-colour");
    mkdirs(&rootd);
    save_rgb_png(&rootd.join("images/x.png"), &image(2, 2, 0)).unwrap();
    write_pfm(&rootd.join("depths/x.pfm"), 2, 2, 3, &[1.0; 12], true).unwrap();
    let e = DirSource::open(&rootd, &SourceOptions::default()).unwrap().load(0).unwrap_err();
    assert!(e.to_string().contains("Pf"), "{e}");
    assert!(read_pfm(&root.join("missing.pfm"), &ImageLimits::default()).unwrap_err().message.contains("not found"));
}

// ---------------------------------------------------------------------------------------------
// scene scale

#[test]
fn metric_depth_scaled_by_any_factor_gives_the_same_disparity() {
    let (w, h) = (7, 5);
    let depth: Vec<f32> = (0..w * h).map(|i| 1.5 + ((i * 37) % 11) as f32 * 0.7).collect();
    let (base, d_min) = disparity_from_depth(&depth, w, h).unwrap();
    assert_eq!(d_min, 1.5);
    assert_eq!(base.data.iter().copied().fold(0.0, f32::max), 1.0);
    for (i, &v) in base.data.iter().enumerate() {
        assert!((v - 1.5 / depth[i]).abs() <= 1e-7, "pixel {i}");
    }
    for s in [0.001f32, 0.25, 2.0, 3.7, 1000.0, 123456.0] {
        let scaled: Vec<f32> = depth.iter().map(|d| d * s).collect();
        let d = disparity_from_given(&GivenDepth::Depth(scaled), w, h).unwrap();
        for (a, b) in d.data.iter().zip(&base.data) {
            if s.log2().fract() == 0.0 {
                assert_eq!(a, b, "factor {s}");
            } else {
                assert!((a - b).abs() <= 2e-7, "factor {s}: {a} vs {b}");
            }
        }
    }
}

#[test]
fn unknown_depth_is_filled_and_far_depth_floored() {
    let (w, h) = (4, 3);
    let mut depth = vec![2.0f32; w * h];
    depth[5] = f32::NAN;
    depth[6] = 0.0;
    depth[11] = f32::INFINITY;
    depth[0] = 1.0;
    depth[3] = 1e6; // far beyond 1000 x nearest
    let (d, _) = disparity_from_depth(&depth, w, h).unwrap();
    assert!(d.data.iter().all(|v| v.is_finite() && (DISPARITY_FLOOR..=1.0).contains(v)));
    assert_eq!(d.data[0], 1.0);
    assert_eq!(d.data[3], DISPARITY_FLOOR);
    // unknown pixels copy their nearest known neighbour, ties to the first in row-major order:
    // (1, 1) from (0, 0) (depth 1), (2, 1) from (1, 0) and (3, 2) from (3, 1) (depth 2)
    assert_eq!((d.data[5], d.data[6], d.data[11]), (1.0, 0.5, 0.5));
    assert!(disparity_from_depth(&[f32::NAN, 0.0, -1.0, f32::INFINITY], 2, 2).is_err());
    assert!(disparity_from_depth(&[1.0; 3], 2, 2).is_err());
}

#[test]
fn given_disparity_is_kept_and_relative_depth_min_max_normalised() {
    let disp = vec![0.0, 0.25, f32::NAN, 1.0, 0.5, 1.2];
    let d = disparity_from_unit(&disp, 3, 2).unwrap();
    assert_eq!(d.data, vec![DISPARITY_FLOOR, 0.25, 0.25, 1.0, 0.5, 1.0]);
    // relative inverse depth: invariant under positive affine maps
    let rel: Vec<f32> = vec![3.0, 5.0, 7.0, 11.0, f32::NAN, 4.0];
    let a = normalise_relative(&rel, 3, 2).unwrap();
    assert_eq!(a.data[3], 1.0);
    assert_eq!(a.data[0], DISPARITY_FLOOR);
    assert_eq!(a.data[1], 0.25);
    let mapped: Vec<f32> = rel.iter().map(|v| 4.0 * v + 100.0).collect();
    let b = normalise_relative(&mapped, 3, 2).unwrap();
    for (x, y) in a.data.iter().zip(&b.data) {
        assert!((x - y).abs() < 1e-6);
    }
    // the NaN at (1, 1) copies its nearest known neighbour, the first in row-major order: (0, 0)
    assert_eq!(a.data[4], a.data[0]);
}

#[test]
fn nearest_fill_is_deterministic() {
    let (w, h) = (5, 5);
    let mut v = vec![0.0f32; 25];
    let mut known = vec![false; 25];
    v[0] = 1.0;
    known[0] = true;
    v[24] = 2.0;
    known[24] = true;
    fill_nearest(&mut v, &known, w, h);
    // chessboard distance: the anti-diagonal ties go to (0, 0), found first
    for y in 0..h {
        for x in 0..w {
            let expect = if x.max(y) <= (4 - x).max(4 - y) { 1.0 } else { 2.0 };
            assert_eq!(v[y * w + x], expect, "({x}, {y})");
        }
    }
}

// ---------------------------------------------------------------------------------------------
// the bundled procedural scenes

#[test]
fn builtin_scenes_are_valid_deterministic_and_exact() {
    let src = BuiltinSource::open_default().unwrap();
    assert_eq!(src.len(), 8);
    assert_eq!(src.photos().len(), 4);
    let again = BuiltinSource::open_default().unwrap();
    assert_eq!(src.fingerprint(), again.fingerprint());
    assert!(src.describe().starts_with("builtin:8 procedural scenes of 640 x 480"), "{}", src.describe());
    let mut shapes = std::collections::HashSet::new();
    for i in 0..src.len() {
        let c = src.compose(i).unwrap();
        let (w, h) = (640usize, 480usize);
        assert_eq!((c.image.width, c.image.height), (w, h));
        assert_eq!(c.id, src.id(i));
        assert!(c.image.data.iter().all(|v| (0.0..=1.0).contains(v)));
        assert!(c.depth.iter().all(|d| d.is_finite() && *d > 0.0));
        assert!((2..=3).contains(&c.objects.len()));
        // each pixel's depth is the composition's exact depth: its object's, else the background's
        for (j, (&d, &id)) in c.depth.iter().zip(&c.ids).enumerate() {
            let expect = if id == 0 {
                c.background.depth(&c.intrinsics, (j % w) as f64, (j / w) as f64)
            } else {
                c.objects.iter().find(|o| o.id == id).unwrap().depth
            };
            assert_eq!(d, expect as f32, "scene {i} pixel {j}");
        }
        // objects stand on the ground in front of the wall, and are visible
        for o in &c.objects {
            shapes.insert(o.shape);
            let z_bottom = c.background.camera_height * c.intrinsics.fy / (h as f64 - 1.0 - c.intrinsics.cy);
            assert!(o.depth > z_bottom && o.depth < c.background.wall_depth, "{o:?}");
            assert!(o.visible_pixels > 100, "scene {i}: {o:?}");
            assert_ne!(o.photo, c.background_photo);
        }
        // the masks of the item are the composition's ids
        let item = src.load(i).unwrap();
        let masks = item.masks.as_ref().unwrap();
        let expect = InstanceMasks::from_index_map(&c.ids, w, h).unwrap();
        assert_eq!(masks, &expect);
        assert!(!masks.masks.is_empty());
        assert_eq!(depth_of(&item), c.depth.as_slice());
        assert_eq!(item.intrinsics, Some(Intrinsics::reference_default(w, h)));
        // deterministic: a second source composes the same bytes
        let c2 = again.compose(i).unwrap();
        assert_eq!(c2.image, c.image);
        assert_eq!(c2.depth, c.depth);
        assert_eq!(c2.ids, c.ids);
    }
    assert_eq!(shapes.len(), 2, "both cut-out shapes occur");
    assert!(src.load(8).is_err());
    // the scenes differ from one another and with the seed
    assert_ne!(src.compose(0).unwrap().image, src.compose(4).unwrap().image);
    let other = BuiltinSource::open(&BuiltinOptions { seed: 1, ..BuiltinOptions::default() }).unwrap();
    assert_ne!(other.fingerprint(), src.fingerprint());
    assert_ne!(other.compose(0).unwrap().depth, src.compose(0).unwrap().depth);
}

#[test]
fn builtin_source_options_and_errors() {
    let small = BuiltinOptions { count: 3, width: 96, height: 64, ..BuiltinOptions::default() };
    let src = BuiltinSource::open(&small).unwrap();
    assert_eq!(src.len(), 3);
    let item = src.load(2).unwrap();
    assert_eq!((item.image.width, item.image.height), (96, 64));
    let e =
        BuiltinSource::open(&BuiltinOptions { photos_dir: tmp("no-photos"), ..BuiltinOptions::default() }).unwrap_err();
    assert!(e.to_string().contains("no .png or .jpg photos"), "{e}");
    assert!(BuiltinSource::open(&BuiltinOptions { count: 0, ..BuiltinOptions::default() }).is_err());
    // a corrupt photo fails the scenes that use it, with its path
    let dir = tmp("bad-photo");
    save_rgb_png(&dir.join("a.png"), &image(64, 48, 1)).unwrap();
    std::fs::write(dir.join("b.png"), b"\x89PNG\r\n\x1a\n broken").unwrap();
    let src = BuiltinSource::open(&BuiltinOptions { photos_dir: dir, count: 2, ..BuiltinOptions::default() }).unwrap();
    let e = src.load(1).unwrap_err();
    assert!(e.to_string().contains("b.png"), "{e}");
    assert_eq!(Shape::Ellipse, Shape::Ellipse);
}

/// Writes each built-in scene's image, depth (as disparity, 8-bit) and ids to
/// `$MPIFLOW_DUMP_DIR` (default: a temp folder; set it to keep the files for a look) and checks
/// that the written files read back: full size, disparity spanning up to the nearest surface,
/// one id per visible object plus the background.
#[test]
fn dump_builtin_scenes() {
    let out = std::env::var_os("MPIFLOW_DUMP_DIR").map(PathBuf::from).unwrap_or_else(|| tmp("dump"));
    std::fs::create_dir_all(&out).unwrap();
    let src = BuiltinSource::open_default().unwrap();
    for i in 0..src.len() {
        let c = src.compose(i).unwrap();
        let (w, h) = (c.image.width, c.image.height);
        save_rgb_png(&out.join(format!("{}_image.png", c.id)), &c.image).unwrap();
        let (d, _) = disparity_from_depth(&c.depth, w, h).unwrap();
        let bytes: Vec<u8> = d.data.iter().map(|v| (v * 255.0).round() as u8).collect();
        save_gray_png(&out.join(format!("{}_disp.png", c.id)), w, h, &bytes).unwrap();
        let ids: Vec<u8> = c.ids.iter().map(|&v| (v * 80) as u8).collect();
        save_gray_png(&out.join(format!("{}_ids.png", c.id)), w, h, &ids).unwrap();

        let image = image::open(out.join(format!("{}_image.png", c.id))).unwrap();
        assert_eq!((image.width() as usize, image.height() as usize), (w, h));
        let disp = image::open(out.join(format!("{}_disp.png", c.id))).unwrap().to_luma8();
        assert_eq!(disp.as_raw(), &bytes, "{}: the disparity PNG reads back", c.id);
        assert_eq!(bytes.iter().max(), Some(&255), "{}: the nearest surface has disparity 1", c.id);
        let back = image::open(out.join(format!("{}_ids.png", c.id))).unwrap().to_luma8();
        let distinct: std::collections::BTreeSet<u8> = back.as_raw().iter().copied().collect();
        let visible = c.objects.iter().filter(|o| o.visible_pixels > 0).count();
        assert_eq!(distinct.len(), visible + 1, "{}: background + visible objects", c.id);
    }
}

/// A folder's entries that are not photos it can read are left out with a reason, never
/// silently: a FIFO, a dangling symbolic link, a directory named `x.png` and links out of the
/// source folder (to `/dev/zero`, to a photo elsewhere: not followed). A link to a photo inside
/// the folder is a photo. With `follow_links` the link to the photo elsewhere is followed.
#[cfg(unix)]
#[test]
fn folder_entries_left_out_are_reported_and_links_stay_inside() {
    let root = std::env::temp_dir().join(format!("mpiflow-sources-{}-entries", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let dir = root.join("photos");
    std::fs::create_dir_all(&dir).unwrap();
    let photo = |p: &Path| {
        image::RgbImage::from_fn(20, 10, |x, y| image::Rgb([(x * 9) as u8, (y * 20) as u8, 3])).save(p).unwrap();
    };
    photo(&dir.join("a.png"));
    photo(&dir.join("b.png"));
    photo(&root.join("outside.png"));
    std::os::unix::fs::symlink(dir.join("a.png"), dir.join("c.png")).unwrap();
    std::os::unix::fs::symlink(root.join("outside.png"), dir.join("d.png")).unwrap();
    std::os::unix::fs::symlink("/dev/zero", dir.join("e.png")).unwrap();
    std::os::unix::fs::symlink(dir.join("missing.png"), dir.join("f.png")).unwrap();
    std::fs::create_dir_all(dir.join("g.png")).unwrap();
    std::fs::create_dir_all(dir.join("subfolder")).unwrap();
    assert!(std::process::Command::new("mkfifo").arg(dir.join("h.png")).status().unwrap().success());
    let src = DirSource::open(&dir, &SourceOptions::default()).unwrap();
    let ids: Vec<String> = (0..src.len()).map(|i| src.id(i)).collect();
    assert_eq!(ids, ["a", "b", "c"], "the link inside the folder is a photo");
    let skipped: Vec<(String, FailureKind)> = src.skipped().into_iter().map(|s| (s.item, s.kind)).collect();
    assert_eq!(
        skipped,
        [
            ("d.png".to_string(), FailureKind::OutsideRoot),
            ("e.png".to_string(), FailureKind::OutsideRoot),
            ("f.png".to_string(), FailureKind::DanglingLink),
            ("g.png".to_string(), FailureKind::NotAFile),
            ("h.png".to_string(), FailureKind::NotAFile),
        ]
    );

    // `follow_source_links`: the link to a photo outside is followed and read; a link to a
    // device is still not a file, a dangling link still nothing
    let follow = SourceOptions { follow_links: true, ..SourceOptions::default() };
    let src = DirSource::open(&dir, &follow).unwrap();
    let ids: Vec<String> = (0..src.len()).map(|i| src.id(i)).collect();
    assert_eq!(ids, ["a", "b", "c", "d"], "the link out of the folder is followed");
    let d = src.load(3).unwrap();
    assert_eq!((d.image.width, d.image.height), (20, 10), "the photo outside the folder is read");
    let skipped: Vec<(String, FailureKind)> = src.skipped().into_iter().map(|s| (s.item, s.kind)).collect();
    assert_eq!(
        skipped,
        [
            ("e.png".to_string(), FailureKind::NotAFile),
            ("f.png".to_string(), FailureKind::DanglingLink),
            ("g.png".to_string(), FailureKind::NotAFile),
            ("h.png".to_string(), FailureKind::NotAFile),
        ]
    );
    std::fs::remove_dir_all(&root).unwrap();
}

#[test]
fn the_bundled_example_data_is_a_reference_layout_source() {
    // `mpiflow serve --source examples/data` (README): the photo with its depth
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("examples/data");
    let src = DirSource::open(&root, &SourceOptions::default()).unwrap();
    assert_eq!(src.layout(), Layout::Reference);
    assert_eq!((src.len(), src.id(0)), (1, "chelsea".to_string()));
    let item = src.load(0).unwrap();
    assert_eq!((item.image.width, item.image.height), (451, 300));
    let depth = depth_of(&item);
    assert_eq!(depth.len(), 451 * 300);
    assert!(depth.iter().all(|d| d.is_finite() && *d > 0.0));
}
